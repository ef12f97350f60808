"""The layered tissue: skin, fat and muscle between four nested SH boundary surfaces.

Boundaries, outermost first: 0 skin surface, 1 skin/fat, 2 fat/muscle, 3 muscle/bone. Each is a radial
surface r_k(theta, phi) about one common centre, fitted by least squares (eq. 4) from points sampled on
it. Layer k (0 skin, 1 fat, 2 muscle) lies between boundaries k and k+1; "layer" 3 is bone, -1 outside.

The default body is limb-like: an ellipsoid elongated along x with a smooth asymmetric bulge whose value
and gradient vanish at the +z pole. Inner boundaries sit the cumulative layer thicknesses radially below
the skin. The scene puts the acupoint, the +z pole of the fitted skin surface, at the origin, so the
outward normal there is +z and a needle moving along -z from z = +5 mm enters perpendicularly.

Everything here is SI (metres).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numba as nb
import numpy as np

from . import shf
from ..base.config import TissueConfig
from ..base.errors import UserError
from .layers import BONE, FAT, MUSCLE, OUTSIDE, SKIN  # noqa: F401 (the place codes, re-exported)

BOUNDARIES = ("skin surface", "skin/fat", "fat/muscle", "muscle/bone")


def limb_radius(theta, phi, semi_axes_m, bulge):
    """Radius of the default skin surface about the ellipsoid's centre (metres)."""
    u = shf.unit_vectors(theta, phi)
    a, b, c = semi_axes_m
    r = 1.0 / np.sqrt((u[..., 0] / a) ** 2 + (u[..., 1] / b) ** 2 + (u[..., 2] / c) ** 2)
    # ux * (1 - uz^2): zero value and zero gradient at the +z pole, so the acupoint normal stays +z.
    return r * (1.0 + bulge * u[..., 0] * (1.0 - u[..., 2] ** 2))


def sample_directions(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n well-spread directions (a Fibonacci sphere with a seeded azimuth offset)."""
    i = np.arange(n) + 0.5
    theta = np.arccos(1.0 - 2.0 * i / n)
    phi = (np.pi * (1.0 + 5.0 ** 0.5) * i + np.random.default_rng(seed).uniform(0, 2 * np.pi)) % (2 * np.pi)
    return theta, phi


@nb.njit(cache=True, nogil=True)
def boundary_radii(coeffs, lmax, centre, p, out):
    """Radii of all boundaries toward point ``p`` into ``out[4]``; returns |p - centre|."""
    theta, phi, rho = shf.direction_of(p[0], p[1], p[2], centre[0], centre[1], centre[2])
    shf.eval_point_many(coeffs, lmax, theta, phi, out)
    return rho


@nb.njit(cache=True, nogil=True, _nrt=False)
def boundary_radii_grad(coeffs, lmax, centre, p, out, k, grad):
    """:func:`boundary_radii` (the same radii, bit for bit) and, for 0 <= ``k`` < 4, boundary k's
    surface gradient on the unit sphere at the direction of ``p`` into ``grad[3]`` (a tangent vector,
    m per radian: dr/dtheta e_theta + (dr/dphi) / sin(theta) e_phi), from the same evaluation
    (:func:`shf.eval_point4_grad`). Returns |p - centre|."""
    theta, phi, rho = shf.direction_of(p[0], p[1], p[2], centre[0], centre[1], centre[2])
    if k < 0 or k >= coeffs.shape[0] or coeffs.shape[0] != 4:
        shf.eval_point_many(coeffs, lmax, theta, phi, out)
        return rho
    shf.eval_point4_grad(coeffs, lmax, theta, phi, out, k, grad)  # grad[:2]: the (theta, phi) parts
    gt = grad[0]
    gp = grad[1]
    ct = math.cos(theta)
    st = math.sin(theta)
    cp = math.cos(phi)
    sp = math.sin(phi)
    grad[0] = gt * ct * cp - gp * sp
    grad[1] = gt * ct * sp + gp * cp
    grad[2] = -gt * st
    return rho


@nb.njit(cache=True, nogil=True)
def locate_kernel(coeffs, lmax, centre, p, radii):
    """(layer, depth below that layer's top surface) for point ``p``; fills ``radii[4]``.

    Layer -1 is outside the skin (depth then negative: the height above the skin), 3 is bone.
    Allocates nothing. (The servo step reads the same radii through ``boundary_radii``, in
    ``needle.tip_radii``, and places the tip itself in ``needle.locate``.)
    """
    rho = boundary_radii(coeffs, lmax, centre, p, radii)
    nb_ = coeffs.shape[0]
    if rho > radii[0]:
        return -1, radii[0] - rho
    for k in range(nb_ - 1):
        if rho > radii[k + 1]:
            return k, radii[k] - rho
    return nb_ - 1, radii[nb_ - 1] - rho


FIT_VERSION = 1  # bump when the fitted body's content changes in a way the key below does not see
_FITS: dict[str, tuple] = {}


def fit_key(cfg: TissueConfig) -> str:
    """The cache key of ``cfg``'s fitted body: everything the fit reads."""
    import hashlib

    body = cfg.body
    h = hashlib.sha256(repr((FIT_VERSION, tuple(body.semi_axes_mm), float(body.bulge), int(body.lmax),
                             int(body.fit_samples), [float(layer.thickness_mm) for layer in cfg.layers],
                             np.__version__)).encode())
    for f in (Path(__file__), Path(shf.__file__)):  # the fitting code itself
        h.update(f.read_bytes())
    if body.skin_coefficients:
        try:
            h.update(Path(body.skin_coefficients).read_bytes())
        except OSError:
            h.update(b"unreadable")  # the fit reports it (load_coefficients)
    return h.hexdigest()[:24]


def _fit_path(key: str):
    from .netresponse import cache_dir

    d = cache_dir()
    return d / f"body-{key}.npz" if d is not None else None


def _load_fit(key: str):
    from .netresponse import cached_file

    path = cached_file(f"body-{key}.npz")
    if path is None:
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            return (np.ascontiguousarray(z["coeffs"]), z["centre"].copy(), z["thick"].copy(), z["rms"].copy(),
                    z["mx"].copy(), int(z["lmax"]))
    except (OSError, ValueError, KeyError):
        return None  # unreadable: fit again


def _save_fit(key: str, fit: tuple) -> None:
    """Write atomically; a cache that cannot be written is not an error."""
    import os
    import tempfile

    path = _fit_path(key)
    if path is None:
        return
    coeffs, centre, thick, rms, mx, lmax = fit
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            np.savez(f, coeffs=coeffs, centre=centre, thick=thick, rms=rms, mx=mx, lmax=lmax)
        os.replace(tmp, path)
    except OSError:
        pass


@dataclass
class Tissue:
    """Four nested SH boundaries about ``centre`` (m); ``coeffs[k]`` is boundary k's expansion (m)."""

    coeffs: np.ndarray  # (4, (lmax+1)^2), metres
    centre: np.ndarray  # (3,), metres
    lmax: int
    thickness_m: np.ndarray  # (3,) nominal layer thicknesses from the config
    fit_rms_m: np.ndarray  # (4,) RMS fit residual of each boundary
    fit_max_m: np.ndarray  # (4,) max fit residual of each boundary

    @classmethod
    def from_config(cls, cfg: TissueConfig) -> "Tissue":
        """The body of ``cfg``: fitted once per body (its keys, the layers' thicknesses, the skin
        coefficients file's bytes, the fitting code and numpy's version), then read from this
        process's memo or the cache directory (``HAPTIC_ACU_CACHE``, as the net tables) in
        milliseconds; a fit that cannot be cached is simply kept in memory."""
        key = fit_key(cfg)
        hit = _FITS.get(key)
        if hit is None:
            hit = _load_fit(key)
        if hit is None:
            hit = cls._fit(cfg)
            _save_fit(key, hit)
        _FITS[key] = hit
        coeffs, centre, thick, rms, mx, lmax = hit
        return cls(coeffs.copy(), centre.copy(), lmax, thick.copy(), rms.copy(), mx.copy())

    @staticmethod
    def _fit(cfg: TissueConfig) -> tuple:
        """(coeffs, centre, thicknesses, fit rms, fit max, lmax) of the least-squares fit (eq. 4)."""
        body = cfg.body
        lmax = body.lmax
        thick = np.array([layer.thickness_mm for layer in cfg.layers]) * 1e-3
        offsets = np.concatenate([[0.0], np.cumsum(thick)])
        theta, phi = sample_directions(body.fit_samples)
        if body.skin_coefficients:
            skin_c, skin_centre = load_coefficients(body.skin_coefficients)
            skin_r = shf.evaluate(skin_c, theta, phi)
            lmax_file = shf.lmax_of(skin_c.size)
            if lmax_file != lmax:
                raise UserError(f"{cfg.path}: key 'body.lmax': {lmax} but {body.skin_coefficients} has lmax {lmax_file}")
        else:
            skin_r = limb_radius(theta, phi, np.array(body.semi_axes_mm) * 1e-3, body.bulge)
        u = shf.unit_vectors(theta, phi)
        coeffs = np.empty((4, shf.n_coeffs(lmax)))
        rms = np.empty(4)
        mx = np.empty(4)
        for k in range(4):
            # Sample points on boundary k (radially below the skin by the cumulative thickness), then
            # fit them as a radial surface about the centre: the same path a scanned surface takes.
            r_k = skin_r - offsets[k]
            if np.any(r_k <= 0):
                raise UserError(f"{cfg.path}: key 'body': layers thicker than the body at some direction")
            pts = u * r_k[:, None]
            th, ph, rr = _to_spherical(pts)
            coeffs[k] = shf.fit(th, ph, rr, lmax)
            resid = shf.evaluate(coeffs[k], th, ph) - rr
            rms[k] = np.sqrt(np.mean(resid ** 2))
            mx[k] = np.abs(resid).max()
        # The acupoint is the +z pole of the fitted skin surface: put it at the origin.
        r_pole = shf.evaluate(coeffs[0], np.array([0.0]), np.array([0.0]))[0]
        centre = np.array([0.0, 0.0, -r_pole])
        return np.ascontiguousarray(coeffs), centre, thick, rms, mx, lmax

    # -- queries -------------------------------------------------------------------------------
    def locate(self, p_m) -> tuple[int, float]:
        """Layer index (-1 outside, 0 skin, 1 fat, 2 muscle, 3 bone) and depth below its top (m)."""
        radii = np.empty(self.coeffs.shape[0])
        layer, depth = locate_kernel(self.coeffs, self.lmax, self.centre, np.asarray(p_m, dtype=np.float64), radii)
        return int(layer), float(depth)

    def radii_toward(self, p_m) -> np.ndarray:
        radii = np.empty(self.coeffs.shape[0])
        boundary_radii(self.coeffs, self.lmax, self.centre, np.asarray(p_m, dtype=np.float64), radii)
        return radii

    def radius(self, k: int, theta, phi) -> np.ndarray:
        return shf.evaluate(self.coeffs[k], theta, phi)

    def surface_point(self, k: int, direction) -> np.ndarray:
        """The point of boundary k in the (unit or not) direction from the centre."""
        d = np.asarray(direction, dtype=np.float64)
        d = d / np.linalg.norm(d)
        th = np.arccos(np.clip(d[2], -1, 1))
        ph = np.arctan2(d[1], d[0])
        return self.centre + d * shf.evaluate(self.coeffs[k], np.array([th]), np.array([ph]))[0]

    def normal(self, k: int, p_m, h: float = 1e-4) -> np.ndarray:
        """Outward unit normal of boundary k at the surface point toward ``p_m`` (central differences)."""
        p = np.asarray(p_m, dtype=np.float64)
        d = p - self.centre
        d = d / np.linalg.norm(d)
        # Two tangents of the unit sphere at d; the surface point moved along each gives surface tangents.
        a = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        t1 = np.cross(d, a)
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(d, t1)
        s1 = self.surface_point(k, d + h * t1) - self.surface_point(k, d - h * t1)
        s2 = self.surface_point(k, d + h * t2) - self.surface_point(k, d - h * t2)
        n = np.cross(s1, s2)
        n /= np.linalg.norm(n)
        return n if np.dot(n, d) > 0 else -n

    def project_to_surface(self, k: int, p_m) -> np.ndarray:
        """The point of boundary k radially above/below ``p_m``."""
        return self.surface_point(k, np.asarray(p_m, dtype=np.float64) - self.centre)

    def depths_at_acupoint(self) -> np.ndarray:
        """Depth of each boundary below the acupoint along -z (m): [0, h_s, h_s + h_f, ...]."""
        radii = self.radii_toward(np.array([0.0, 0.0, 0.0]))
        return radii[0] - radii

    def mesh(self, k: int, n_theta: int = 48, n_phi: int = 96, radius_offset=None):
        """Vertices (N, 3) and triangles (M, 3) of boundary k on a theta/phi grid (for rendering).

        ``radius_offset`` (n_theta, n_phi), if given, is subtracted from the radius (the net's dent).
        """
        th, ph = shf.grid(n_theta, n_phi)
        r = self.radius(k, th, ph)
        if radius_offset is not None:
            r = r - radius_offset
        verts = self.centre + shf.unit_vectors(th, ph) * r[..., None]
        return verts.reshape(-1, 3), grid_triangles(n_theta, n_phi)


def grid_triangles(n_theta: int, n_phi: int) -> np.ndarray:
    """Triangles of a (n_theta, n_phi) theta/phi grid, wrapping in phi."""
    i, j = np.meshgrid(np.arange(n_theta - 1), np.arange(n_phi), indexing="ij")
    a = i * n_phi + j
    b = i * n_phi + (j + 1) % n_phi
    c = (i + 1) * n_phi + j
    d = (i + 1) * n_phi + (j + 1) % n_phi
    return np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)]).astype(np.uint32)


def _to_spherical(pts: np.ndarray):
    rr = np.linalg.norm(pts, axis=1)
    th = np.arccos(np.clip(pts[:, 2] / rr, -1.0, 1.0))
    ph = np.arctan2(pts[:, 1], pts[:, 0])
    return th, ph, rr


def save_coefficients(path, coeffs_m: np.ndarray, centre_m: np.ndarray, source: str = "") -> None:
    """Write a radial surface's coefficients (stored in mm) for ``body.skin_coefficients``."""
    np.savez(path, coeffs_mm=np.asarray(coeffs_m) * 1e3, centre_mm=np.asarray(centre_m) * 1e3,
             lmax=shf.lmax_of(np.asarray(coeffs_m).size), source=source)


def load_coefficients(path) -> tuple[np.ndarray, np.ndarray]:
    """(coeffs in m, centre in m) from a file written by :func:`save_coefficients`."""
    import zipfile

    from ..base.csvin import check_source

    check_source(path, "coefficients file")  # a device or a pipe: refused unread
    try:
        with np.load(path, allow_pickle=False) as z:
            c = np.asarray(z["coeffs_mm"], dtype=np.float64) * 1e-3
            centre = np.asarray(z["centre_mm"], dtype=np.float64) * 1e-3
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile) as e:  # TypeError: a .npy
        raise UserError(f"{path}: not a coefficients file written by 'haptic-acu fit' ({e})") from None
    if c.ndim != 1 or not np.all(np.isfinite(c)) or centre.shape != (3,):
        raise UserError(f"{path}: malformed coefficients (need finite coeffs_mm (K,) and centre_mm (3,))")
    try:
        shf.lmax_of(c.size)
    except ValueError as e:
        raise UserError(f"{path}: {e}") from None
    return c, centre

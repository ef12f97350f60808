"""The section through the needle's axis: the geometry the trainee's view draws.

The section is the vertical plane that holds the needle's axis (for a needle along the vertical,
the scene's x-z plane through the needle). Its coordinates are millimetres: ``u`` across (the
plane's horizontal direction, the acupoint's column at u = 0) and ``w`` up (the scene's +z; the
acupoint's rest skin at w = 0). The viewer draws them as the 3D points (u, 0, w).

Everything here is numpy on a :class:`haptic_acu.tissue.body.Tissue`-like object (``centre`` and
``radius(k, theta, phi)``); nothing is logged.

* :meth:`Section.boundary` - boundary k's curve in the plane, at rest or dented (the dent of the
  live force nets, sampled on the engine's patch grid, interpolated with :func:`patch_dent`);
* :meth:`Section.depths_along` - where the needle's line crosses each rest boundary, as depths
  below its entry into the skin along the needle (the depth gauge's marks);
* :func:`structure_outline` - a danger structure (a membrane, a vessel or nerve as a tube, a bone
  wall) cut by the plane, as a polyline.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_Z = np.array([0.0, 0.0, 1.0])
VERTICAL_TOL = np.sin(np.radians(2.0))  # an axis within 2 deg of the vertical keeps the x-z plane


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _angles(d: np.ndarray):
    """(theta, phi) of direction vectors d (..., 3), not necessarily unit."""
    rho = np.linalg.norm(d, axis=-1)
    theta = np.arccos(np.clip(d[..., 2] / np.where(rho > 0.0, rho, 1.0), -1.0, 1.0))
    return theta, np.arctan2(d[..., 1], d[..., 0])


def patch_dent(dent: np.ndarray, theta_axis: np.ndarray, phi_axis: np.ndarray, theta, phi) -> np.ndarray:
    """Bilinear interpolation of a dent sampled on the patch grid (rows ``theta_axis``, ascending;
    columns ``phi_axis``, uniform over a full turn) at directions (theta, phi). Zero past the
    patch's last row; inside its first row, that row's mean (the pole, as the 3D patch draws it)."""
    theta = np.asarray(theta, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64)
    if dent.ndim == 3:  # a stack of dents (m, n_theta, n_phi), each at its own row of (theta, phi) (m, ...)
        return _patch_dents(dent, theta_axis, phi_axis, theta, phi)
    return _patch_dents(dent[None], theta_axis, phi_axis, theta[None], phi[None])[0]


def _patch_dents(dent, theta_axis, phi_axis, theta, phi) -> np.ndarray:
    """:func:`patch_dent` of a stack of dents (m, n_theta, n_phi), each at its own directions
    (theta, phi: (m, ...))."""
    m, n_th, n_ph = dent.shape
    sel = np.arange(m).reshape((m,) + (1,) * (theta.ndim - 1))
    dphi = 2.0 * np.pi / n_ph
    fj = np.mod(phi - phi_axis[0], 2.0 * np.pi) / dphi
    j0 = np.floor(fj).astype(np.int64) % n_ph
    j1 = (j0 + 1) % n_ph
    b = fj - np.floor(fj)
    fi = np.interp(theta, theta_axis, np.arange(n_th, dtype=np.float64))
    i0 = np.clip(np.floor(fi).astype(np.int64), 0, n_th - 1)
    i1 = np.minimum(i0 + 1, n_th - 1)
    a = fi - i0
    row = lambda i: dent[sel, i, j0] * (1.0 - b) + dent[sel, i, j1] * b  # noqa: E731
    out = row(i0) * (1.0 - a) + row(i1) * a
    pole = theta < theta_axis[0]
    if np.any(pole):
        mean = dent[:, 0, :].mean(axis=-1).reshape(sel.shape)
        t = theta / theta_axis[0]
        out = np.where(pole, mean * (1.0 - t) + out * t, out)
    return np.where(theta > theta_axis[-1], 0.0, out)


@dataclass(frozen=True)
class Section:
    """The vertical plane through the needle's line (``axis``, unit handle to tip, through the point
    ``through``, both in the scene frame, m)."""

    tissue: object
    origin: np.ndarray  # (3,) m: the acupoint (scene origin) projected onto the plane
    e_u: np.ndarray  # (3,) the plane's horizontal unit direction (u grows along it)
    normal: np.ndarray  # (3,) the plane's unit normal

    @classmethod
    def through(cls, tissue, axis, through) -> "Section":
        a = _unit(axis)
        n = np.cross(a, _Z)
        if np.linalg.norm(n) < VERTICAL_TOL:
            n = np.array([0.0, 1.0, 0.0])  # the x-z plane
        n = _unit(n)
        e_u = _unit(np.cross(n, _Z))
        if e_u[0] < -1e-9 or abs(e_u[0]) <= 1e-9 and e_u[1] < 0.0:  # u grows toward +x (else +y)
            n, e_u = -n, -e_u
        origin = float(np.dot(np.asarray(through, dtype=np.float64), n)) * n
        return cls(tissue, origin, e_u, n)

    def same_plane(self, other: "Section", tol_m: float = 0.2e-3, tol_cos: float = np.cos(np.radians(1.0))) -> bool:
        return (abs(float(np.dot(self.normal, other.normal))) >= tol_cos
                and float(np.linalg.norm(self.origin - other.origin)) <= tol_m)

    # -- coordinates ----------------------------------------------------------------------------
    def to_uw(self, p) -> np.ndarray:
        """Scene points (..., 3) in m -> section coordinates (..., 2) in mm (off-plane part dropped)."""
        d = np.asarray(p, dtype=np.float64) - self.origin
        return np.stack([d @ self.e_u, d[..., 2]], axis=-1) * 1e3

    def to_scene(self, u_mm, w_mm) -> np.ndarray:
        """Section coordinates (mm) -> scene points (..., 3) in m."""
        u = np.asarray(u_mm, dtype=np.float64)[..., None] * 1e-3
        w = np.asarray(w_mm, dtype=np.float64)[..., None] * 1e-3
        return self.origin + u * self.e_u + w * _Z

    def direction_uw(self, v) -> np.ndarray:
        """A scene vector (..., 3) projected into the plane, as (du, dw) (same units as v)."""
        v = np.asarray(v, dtype=np.float64)
        return np.stack([v @ self.e_u, v[..., 2]], axis=-1)

    # -- surfaces -------------------------------------------------------------------------------
    def boundary(self, k: int, u_mm, dent=None, start=None, iters: int = 3) -> np.ndarray:
        """w (mm) of boundary k above each u (mm) in the plane (its upper crossing of the vertical
        line at u; NaN where the line misses it). At rest: bisection (50 steps, to 1e-10 m).
        ``dent``, a callable (theta, phi) -> radial dent (m) subtracted from the rest radius, moves
        the rest curve (``start``, w mm, or computed) by ``iters`` fixed-point steps along the
        vertical; the dent is small against the radius, so a few steps converge. ``start`` (m, n)
        moves m curves at once (``dent`` then takes and gives (m, n))."""
        t = self.tissue
        q = self.to_scene(u_mm, np.zeros_like(np.asarray(u_mm, dtype=np.float64))) - t.centre
        if dent is None or start is None:
            start = self._rest_boundary(k, q)
        if dent is None:
            return start
        h2 = q[..., 0] ** 2 + q[..., 1] ** 2
        w = np.asarray(start, dtype=np.float64) * 1e-3  # metres above z = 0 (or (m, n): m curves at once)
        for _ in range(iters):
            d = np.empty(w.shape + (3,))
            d[:] = q
            d[..., 2] += w
            th, ph = _angles(d)
            r = t.radius(k, th, ph) - dent(th, ph)
            # the radial move of the surface point, taken along the vertical line
            rho = np.sqrt(h2 + d[..., 2] ** 2)
            cos_v = np.where(rho > 0.0, d[..., 2] / np.where(rho > 0.0, rho, 1.0), 1.0)
            w = w + (r - rho) / np.maximum(cos_v, 0.2)
        return w * 1e3

    def _rest_boundary(self, k: int, q: np.ndarray) -> np.ndarray:
        t = self.tissue
        lo = np.zeros(q.shape[:-1]) - q[..., 2]  # the centre's height: inside, if the line meets it
        hi = lo + 1.0  # a metre above: outside
        def outside(w):
            d = q.copy()
            d[..., 2] += w
            th, ph = _angles(d)
            return np.linalg.norm(d, axis=-1) > t.radius(k, th, ph)
        miss = outside(lo)
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            o = outside(mid)
            hi = np.where(o, mid, hi)
            lo = np.where(o, lo, mid)
        w = 0.5 * (lo + hi) * 1e3
        return np.where(miss, np.nan, w)

    def depths_along(self, entry, axis, n_boundaries: int = 4, reach_mm: float = 90.0) -> np.ndarray:
        """Depths (mm) along the needle's line (from ``entry``, unit ``axis``) at which it crosses
        each rest boundary 0..n-1 going in, relative to its crossing of the skin (boundary 0 -> 0).
        NaN for a boundary the line does not reach within ``reach_mm``."""
        t = self.tissue
        a = _unit(axis)
        s = np.linspace(-20.0, reach_mm, int(4 * (reach_mm + 20.0)) + 1) * 1e-3  # 0.25 mm steps
        p = np.asarray(entry, dtype=np.float64) + s[:, None] * a - t.centre
        th, ph = _angles(p)
        rho = np.linalg.norm(p, axis=1)
        out = np.full(n_boundaries, np.nan)
        for k in range(n_boundaries):
            f = rho - t.radius(k, th, ph)  # > 0 outside boundary k
            idx = np.nonzero((f[:-1] > 0.0) & (f[1:] <= 0.0))[0]
            if idx.size:
                i = idx[0]
                out[k] = (s[i] + (s[i + 1] - s[i]) * f[i] / (f[i] - f[i + 1])) * 1e3
        return out - out[0]


def skin_entry(tissue, tip, axis) -> np.ndarray:
    """Where the needle's line (through ``tip``, unit ``axis`` handle to tip) enters the rest skin
    (m): the last crossing of boundary 0 before the tip, going in; the tip itself if none."""
    a = _unit(axis)
    s = np.linspace(-90.0, 5.0, 381) * 1e-3
    p = np.asarray(tip, dtype=np.float64) + s[:, None] * a - tissue.centre
    th, ph = _angles(p)
    f = np.linalg.norm(p, axis=1) - tissue.radius(0, th, ph)
    idx = np.nonzero((f[:-1] > 0.0) & (f[1:] <= 0.0))[0]
    if not idx.size:
        return np.asarray(tip, dtype=np.float64)
    i = idx[-1]
    si = s[i] + (s[i + 1] - s[i]) * f[i] / (f[i] - f[i + 1])
    return np.asarray(tip, dtype=np.float64) + si * a


@dataclass(frozen=True)
class Structure:
    """A danger structure near a point, in the scene frame (m). ``kind``: "membrane" (a plane
    across ``normal`` through ``centre``), "vessel"/"nerve"/"artery" (a tube of ``radius_m`` along
    ``along`` through ``centre``; a ball where ``along`` is None) or "bone" (a wall like a membrane)."""

    name: str
    kind: str
    centre: np.ndarray
    radius_m: float = 0.0
    normal: np.ndarray | None = None
    along: np.ndarray | None = None


def structure_outline(s: Structure, section: Section, half_width_mm: float = 40.0, n: int = 48) -> np.ndarray | None:
    """Structure ``s`` cut by the section plane, as a polyline (k, 2) in section mm; None if the
    plane misses it. A membrane or wall: its line across the plane; a tube: the outline of its cut
    (an ellipse; a circle when it crosses the plane square); a ball: its circle."""
    c = np.asarray(s.centre, dtype=np.float64)
    nrm = section.normal
    if s.kind in ("membrane", "bone") or s.normal is not None and s.along is None and s.radius_m == 0.0:
        m = _unit(s.normal if s.normal is not None else [0.0, 0.0, 1.0])
        t = np.cross(m, nrm)  # the membrane's line in the plane
        if np.linalg.norm(t) < 1e-9:
            return None  # the membrane lies in the plane
        t = _unit(t)
        # a point of the plane on the membrane: from the centre's projection, along the plane's
        # direction perpendicular to t within the plane
        c_in = c - float(np.dot(c - section.origin, nrm)) * nrm
        q = _unit(np.cross(nrm, t))
        denom = float(np.dot(q, m))
        if abs(denom) < 1e-12:
            return None
        p0 = c_in + q * float(np.dot(c - c_in, m)) / denom
        u = np.linspace(-half_width_mm, half_width_mm, 2) * 1e-3
        return section.to_uw(p0 + u[:, None] * t)
    r = float(s.radius_m)
    dist = float(np.dot(c - section.origin, nrm))
    if s.along is None:
        if abs(dist) >= r:
            return None
        rr = np.sqrt(r * r - dist * dist)
        ang = np.linspace(0.0, 2.0 * np.pi, n + 1)
        uw0 = section.to_uw(c)
        return uw0 + 1e3 * rr * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    a = _unit(s.along)
    cos_t = float(np.dot(a, nrm))
    if abs(cos_t) < 1e-6:  # the tube runs in the plane's direction: a band where it is close enough
        if abs(dist) >= r:
            return None
        half = np.sqrt(r * r - dist * dist)
        t_in = _unit(a - cos_t * nrm)
        side = np.cross(nrm, t_in)
        L = half_width_mm * 1e-3
        c_in = c - dist * nrm
        pts = [c_in - L * t_in - half * side, c_in + L * t_in - half * side,
               c_in + L * t_in + half * side, c_in - L * t_in + half * side, c_in - L * t_in - half * side]
        return section.to_uw(np.array(pts))
    # the tube's axis meets the plane at x0; its cut is an ellipse around x0
    x0 = c - a * dist / cos_t
    b1 = np.cross(a, nrm)  # across the tube, in the plane
    b1 = _unit(b1) if np.linalg.norm(b1) > 1e-9 else section.e_u
    b2 = np.cross(a, b1)  # across the tube, out of the plane
    ang = np.linspace(0.0, 2.0 * np.pi, n + 1)
    ring = x0 + r * (np.cos(ang)[:, None] * b1 + np.sin(ang)[:, None] * b2)
    # slide each ring point along the tube onto the plane
    off = (ring - section.origin) @ nrm
    pts = ring - a * (off / cos_t)[:, None]
    return section.to_uw(pts)


def structures_from_danger(rows, names=None) -> list[Structure]:
    """:class:`Structure` s from the servo's danger rows (a record array with ``kind``, ``p``, ``n``,
    ``depth``, ``radius``; scene frame, SI; kind 0 rows skipped): a membrane or bone wall is the
    plane ``depth`` from the acupoint along ``n`` (its normal), a nerve or artery the cylinder of
    ``radius`` about ``p`` along ``n``. ``names``: one per structure (default: the kind)."""
    from ..servo.danger import KIND_CODES

    kinds = {code: name for name, code in KIND_CODES.items()}
    out = []
    if rows is None:
        return out
    for i, r in enumerate(rows):
        kind = kinds.get(int(r["kind"]))
        if kind is None:
            continue
        name = names[i] if names is not None and i < len(names) else kind
        n = np.asarray(r["n"], dtype=np.float64)
        if kind in ("membrane", "bone"):
            out.append(Structure(name, kind, float(r["depth"]) * n, normal=n))
        else:
            out.append(Structure(name, kind, np.asarray(r["p"], dtype=np.float64), radius_m=float(r["radius"]), along=n))
    return out


def structures_from_anatomy(anatomy) -> list[Structure]:
    """:class:`Structure` s of a ``--point`` session's realised point (its ``structures``, each with
    ``name``, ``kind``, ``depth_mm`` and either ``toward``, a plane's normal into the body, or
    ``centre_mm``, ``axis`` and ``radius_mm``, a cylinder; the point's frame is the scene's)."""
    out = []
    for st in getattr(anatomy, "structures", ()) or ():
        if st.toward is not None:
            n = np.asarray(st.toward, dtype=np.float64)
            out.append(Structure(st.name, st.kind, n * st.depth_mm * 1e-3, normal=n))
        else:
            out.append(Structure(st.name, st.kind, np.asarray(st.centre_mm, dtype=np.float64) * 1e-3,
                                 radius_m=float(st.radius_mm) * 1e-3, along=np.asarray(st.axis, dtype=np.float64)))
    return out

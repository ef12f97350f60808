"""The four baseline tissue models of the paper's comparison (MSM, FEM, BEM, SHF): what each layer's
surface does before it breaks, precomputed once per parameter set (docs/model.md section 12).

Each baseline answers the question the force net answers in the servo (``servo.step.press``): with
the tip at depth ``d`` below the pressed layer's rest surface (radially, the same depth the force net
reads), how hard does the surface push back along ``grad(-d)``, and has the layer broken. Every
baseline here is linear elastic and its contact is centred under the tip (as the force net is
re-centred under a sliding tip), so its answer is ``F = k d`` with a stiffness ``k`` per layer, and
it breaks at a depth ``d_c`` per layer; they differ in where ``k`` and ``d_c`` come from:

* **SHF** (the SH surface alone, Fang & Wu 2011's family): a penalty ``k`` along the normal below
  the SH surface, per layer, from the config; breaks at a force (``d_c = F_c / k``).
* **MSM** (a volumetric mass-spring lattice, [38]'s family): a cubic lattice of spacing ``h`` of the
  layers from the pressed one down (edge and face-diagonal springs, ``k_spring = 2 E h / 5`` summed
  over the cubes a spring borders: the isotropic central-force cubic lattice, E exact, nu = 1/4),
  the bottom fixed, the node under the tip pushed in; ``k`` is the reaction per unit push (the
  lattice at equilibrium, its inertia left out, as the FEM and BEM are elastostatic); breaks when a
  spring at that node reaches a strain.
* **FEM** (linear elastostatics on tetrahedra, DiMaio & Salcudean 2005; Bro-Nielsen 1998;
  :mod:`haptic_acu.tissue.fem`): a structured tetrahedral mesh between the body's SH boundaries from
  the pressed layer down, around the acupoint, P1 elements assembled with scikit-fem, the stiffness
  condensed (Schur complement) onto the surface nodes near the tip, then onto the contact set (a
  flat tip of the needle's radius); ``k`` is the condensed matrix's sum. Breaks by the energy
  criterion (:func:`rupture_depth`).
* **BEM** (boundary elements, James & Pai 1999; Zhu & Gu 2012's family;
  :mod:`haptic_acu.tissue.bem`): the contact disc in boundary elements with Boussinesq's Green's
  function of a half-space of the pressed layer's material; ``k`` is the sum of the capacitance
  matrix (the compliance matrix's inverse). Breaks by the energy criterion (:func:`rupture_depth`).

Precomputation is cached like the force nets' tables (``netresponse.cache_dir``), keyed by every
parameter that enters.
"""
from __future__ import annotations

import hashlib
import itertools
import math
import os
import tempfile
import time
from dataclasses import dataclass

import numba as nb
import numpy as np

from ..base.config import MODEL_KINDS
from . import bem, fem
from .body import Tissue, fit_key
from .mechanics import puncture_threshold
from .netresponse import cache_dir

VERSION = 3  # bump when a precomputation changes (invalidates the cache)
KIND_CODES = {name: i for i, name in enumerate(MODEL_KINDS)}  # PARAMS.kind (0: the force net)
FORCENET, MSM, FEM, BEM, SHF = (KIND_CODES[n] for n in MODEL_KINDS)

MSM_HALF_CELLS = 6  # the lattice spans +-6 cells around the tip
MSM_DEPTH_M = 6e-3  # and at most this deep (fixed below)


# ---- the servo's side (compiled; one small function, not inlined into the step) -------------------

@nb.njit(cache=True, nogil=True)
def baseline_response(inp, m, s, k, idx, dep, ax):
    """A baseline's pressed layer ``k`` with the tip ``dep`` below its rest surface: (the force along
    grad(-d), N; broken?). ``F = bl_k dep``; the layer breaks past ``bl_crit`` scaled by the approach
    speed as the force net's threshold is (``mechanics.puncture_threshold``). Keeps the tip in
    ``servo.slot_q`` for the drawn net (the force net's shape at that depth)."""
    for c in range(3):
        s.servo[0].slot_q[idx, c] = s.work[0].q[c]
    lay = m.layer[k]
    fn = lay.bl_k * dep
    broke = dep > puncture_threshold(lay.bl_crit, inp.v, ax, m.params[0])
    return fn, broke


@nb.njit(cache=True, nogil=True)
def baseline_slope(m, s, k):
    """A baseline's stiffness along grad(-d) at the tip for the rendering layer: ``bl_k |grad d|^2``."""
    g = s.work[0].gd
    return m.layer[k].bl_k * (g[0] * g[0] + g[1] * g[1] + g[2] * g[2])


# ---- MSM ----------------------------------------------------------------------------------------

_EDGE = ((1, 0, 0), (0, 1, 0), (0, 0, 1))
_DIAG = ((1, 1, 0), (1, -1, 0), (1, 0, 1), (1, 0, -1), (0, 1, 1), (0, 1, -1))


def msm_springs(nx, ny, nz, h, cube_E):
    """The lattice's springs: (i, j, stiffness, unit direction) for nodes on an (nx, ny, nz) grid of
    spacing h; ``cube_E[cx, cy, cz]`` is each cube's Young's modulus. A spring's stiffness is the sum
    over the cubes it borders of 0.1 E h (an edge, up to four cubes) or 0.2 E h (a face diagonal, up
    to two): inside a homogeneous lattice every spring is 2 E h / 5."""
    idx = np.arange(nx * ny * nz).reshape(nx, ny, nz)
    rows = []
    for off, share in [(o, 0.1) for o in _EDGE] + [(o, 0.2) for o in _DIAG]:
        dx, dy, dz = off
        ax = np.arange(nx - abs(dx)) + (max(0, -dx))
        ay = np.arange(ny - abs(dy)) + (max(0, -dy))
        az = np.arange(nz - abs(dz)) + (max(0, -dz))
        I, J, L = np.meshgrid(ax, ay, az, indexing="ij")
        i0 = idx[I, J, L].ravel()
        i1 = idx[I + dx, J + dy, L + dz].ravel()
        # the cubes bordering this spring: cube (cx, cy, cz) spans nodes cx..cx+1 etc.
        kk = np.zeros(i0.size)
        lo = np.stack([np.minimum(I, I + dx), np.minimum(J, J + dy), np.minimum(L, L + dz)], -1).reshape(-1, 3)
        # the cubes bordering the spring start at lo, or one cell back along each axis it lies across
        choices = [(0, -1) if dv == 0 else (0,) for dv in off]
        shape = cube_E.shape
        for m in itertools.product(*choices):
            cx, cy, cz = lo[:, 0] + m[0], lo[:, 1] + m[1], lo[:, 2] + m[2]
            ok = (cx >= 0) & (cy >= 0) & (cz >= 0) & (cx < shape[0]) & (cy < shape[1]) & (cz < shape[2])
            kk[ok] += share * cube_E[cx[ok], cy[ok], cz[ok]] * h
        n = np.array(off, float) / np.linalg.norm(off)
        good = kk > 0
        rows.append((i0[good], i1[good], kk[good], np.tile(n, (int(good.sum()), 1))))
    i = np.concatenate([r[0] for r in rows])
    j = np.concatenate([r[1] for r in rows])
    k = np.concatenate([r[2] for r in rows])
    n = np.concatenate([r[3] for r in rows])
    return i, j, k, n


def msm_stiffness_matrix(nnodes, i, j, k, n):
    """The linearised lattice's stiffness matrix (3 nnodes square, sparse CSR)."""
    import scipy.sparse as sp

    blocks = k[:, None, None] * n[:, :, None] * n[:, None, :]  # (m, 3, 3)
    r, c, v = [], [], []
    for a_, b_, sgn in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
        for p in range(3):
            for q in range(3):
                r.append(3 * a_ + p)
                c.append(3 * b_ + q)
                v.append(sgn * blocks[:, p, q])
    return sp.csr_matrix((np.concatenate(v), (np.concatenate(r), np.concatenate(c))), shape=(3 * nnodes, 3 * nnodes))


def _solve_fixed(K, fixed_dofs, fixed_vals):
    import scipy.sparse.linalg as spla

    n = K.shape[0]
    u = np.zeros(n)
    u[fixed_dofs] = fixed_vals
    free = np.setdiff1d(np.arange(n), fixed_dofs)
    rhs = -(K[free][:, fixed_dofs] @ u[fixed_dofs])
    u[free] = spla.spsolve(K[free][:, free].tocsc(), rhs)
    return u


def msm_compression_modulus(E, h, cells=6) -> float:
    """A homogeneous lattice cube of ``cells`` cells a side, compressed 0.1% between a rolling bottom
    and a rolling top (sides free): its effective Young's modulus, stress over strain (Pa)."""
    n = cells + 1
    i, j, k, nv = msm_springs(n, n, n, h, np.full((cells, cells, cells), float(E)))
    K = msm_stiffness_matrix(n ** 3, i, j, k, nv)
    idx = np.arange(n ** 3).reshape(n, n, n)
    bottom, top = idx[:, :, 0].ravel(), idx[:, :, -1].ravel()
    strain = 1e-3
    dz = strain * cells * h
    fixed = np.concatenate([3 * bottom + 2, 3 * top + 2, [3 * idx[0, 0, 0], 3 * idx[0, 0, 0] + 1,
                                                          3 * idx[-1, 0, 0] + 1]])
    vals = np.concatenate([np.zeros(bottom.size), np.full(top.size, -dz), [0.0, 0.0, 0.0]])
    u = _solve_fixed(K, fixed, vals)
    force = -(K @ u)[3 * top + 2].sum()
    return force / (cells * h) ** 2 / strain


def msm_press(E, thick, h, half_cells=MSM_HALF_CELLS, depth=MSM_DEPTH_M):
    """The lattice of the layers (moduli ``E`` Pa, thicknesses ``thick`` m from the top, the last one
    continuing to ``depth``), bottom fixed, its centre surface node pushed down: (stiffness N/m, the
    largest strain of a spring at that node per metre of push)."""
    nz = max(2, int(round(min(depth, float(np.sum(thick))) / h)) + 1)
    n = 2 * half_cells + 1
    zc = (np.arange(nz - 1) + 0.5) * h  # cube centre depths, node layer 0 = surface
    bounds = np.concatenate([[0.0], np.cumsum(thick)[:-1], [np.inf]])
    layer = np.searchsorted(bounds, zc, side="right") - 1
    cube_E = np.broadcast_to(np.asarray(E, float)[layer][None, None, ::-1], (n - 1, n - 1, nz - 1)).copy()
    i, j, k, nv = msm_springs(n, n, nz, h, cube_E)  # node z index 0 = bottom, nz-1 = surface
    K = msm_stiffness_matrix(n * n * nz, i, j, k, nv)
    idx = np.arange(n * n * nz).reshape(n, n, nz)
    bottom = idx[:, :, 0].ravel()
    tip = idx[half_cells, half_cells, nz - 1]
    fixed = np.concatenate([3 * bottom, 3 * bottom + 1, 3 * bottom + 2, [3 * tip + 2]])
    vals = np.zeros(fixed.size)
    vals[-1] = -1.0  # a unit push (linear)
    u = _solve_fixed(K, fixed, vals)
    stiff = -(K @ u)[3 * tip + 2]
    at = (i == tip) | (j == tip)
    du = u.reshape(-1, 3)[j[at]] - u.reshape(-1, 3)[i[at]]
    L = np.where(np.abs(nv[at]).sum(axis=1) > 1.5, math.sqrt(2.0) * h, h)
    strain = np.abs((du * nv[at]).sum(axis=1)) / L
    return float(stiff), float(strain.max())


# ---- per layer, per config ----------------------------------------------------------------------

@dataclass
class Contact:
    """One model's per-layer contact, as the servo reads it (:data:`haptic_acu.servo.state.LAYER`'s
    ``bl_k``, ``bl_crit``)."""

    kind: str
    stiffness: np.ndarray  # N/m along grad(-d), per layer
    crit_depth: np.ndarray  # m: the depth at which each layer breaks (at the reference speed)
    build_s: float = 0.0  # seconds the precomputation took (0: from the cache)
    table_bytes: int = 0  # memory of what was precomputed and kept


def _layers(cfg, k):
    m = cfg.model
    E = [m.young_modulus_kpa[j] * 1e3 for j in range(k, len(cfg.layers))]
    nu = [m.poisson_ratio[j] for j in range(k, len(cfg.layers))]
    thick = [cfg.layers[j].thickness_mm * 1e-3 for j in range(k, len(cfg.layers))]
    return E, nu, thick


def rupture_depth(k: float, toughness: float, a: float) -> float:
    """The energy criterion (Mahvash & Dupont 2010's rupture: the energy the press stored pays for
    the crack): a linear contact of stiffness ``k`` (N/m) breaks when ``k d^2 / 2`` reaches
    ``toughness`` (J/m^2) times the crack's area, taken as the tip's cross-section ``pi a^2``
    (ours): ``d_c = sqrt(2 J pi a^2 / k)`` (m)."""
    return math.sqrt(2.0 * toughness * math.pi * a * a / k)


def contact_key(cfg) -> str:
    m = cfg.model
    text = repr((VERSION, m.kind, m.young_modulus_kpa, m.poisson_ratio, m.fracture_toughness_j_per_m2, m.shf_stiffness_n_per_mm,
                 m.shf_puncture_force_n, m.msm_spacing_mm, m.msm_puncture_strain,
                 tuple(layer.thickness_mm for layer in cfg.layers), cfg.needle.diameter_mm, fem.N_IN, fem.RATIO,
                 fem.HALF_WIDTH_M, fem.DEPTH_M, fem.PATCH_M, bem.N_IN, MSM_HALF_CELLS, MSM_DEPTH_M,
                 fit_key(cfg) if m.kind == "fem" else None))
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def build_contact(cfg) -> Contact:
    """Precompute ``cfg.model.kind``'s per-layer contact (no cache)."""
    m = cfg.model
    n = len(cfg.layers)
    a = 0.5 * cfg.needle.diameter_mm * 1e-3
    t0 = time.perf_counter()
    k = np.zeros(n)
    crit = np.zeros(n)
    nbytes = 0
    tissue = Tissue.from_config(cfg) if m.kind == "fem" else None
    for j in range(n):
        E, nu, thick = _layers(cfg, j)
        if m.kind == "shf":
            k[j] = m.shf_stiffness_n_per_mm[j] * 1e3
            crit[j] = m.shf_puncture_force_n[j] / k[j]
        elif m.kind == "fem":
            res = fem.tissue_press(tissue, j, E, nu, a)
            k[j] = res.stiffness
            crit[j] = rupture_depth(k[j], m.fracture_toughness_j_per_m2[j], a)
            nbytes += res.schur.nbytes + res.patch_xy.nbytes
        elif m.kind == "bem":
            k[j] = bem.flat_punch(E[0], nu[0], a)
            crit[j] = rupture_depth(k[j], m.fracture_toughness_j_per_m2[j], a)
            nbytes += bem.element_count() ** 2 * 8  # the compliance matrix
        elif m.kind == "msm":
            stiff, strain_per_m = msm_press(E, thick, m.msm_spacing_mm * 1e-3)
            k[j] = stiff
            crit[j] = m.msm_puncture_strain[j] / strain_per_m
    return Contact(m.kind, k, crit, time.perf_counter() - t0, int(nbytes) + k.nbytes + crit.nbytes)


_MEMO: dict[str, Contact] = {}


def contact_for(cfg) -> Contact | None:
    """``cfg.model.kind``'s per-layer contact (None for the force net): from this process's memo, the
    cache directory, or built (and cached)."""
    if cfg.model.kind == "forcenet":
        return None
    key = contact_key(cfg)
    if key in _MEMO:
        return _MEMO[key]
    d = cache_dir()
    path = d / f"contact-{key}.npz" if d is not None else None
    out = None
    if path is not None and path.is_file():
        try:
            with np.load(path) as z:
                out = Contact(cfg.model.kind, z["k"].copy(), z["crit"].copy(), 0.0, int(z["nbytes"]))
        except (OSError, ValueError, KeyError):
            out = None
    if out is None:
        out = build_contact(cfg)
        if path is not None:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
                with os.fdopen(fd, "wb") as f:
                    np.savez(f, k=out.stiffness, crit=out.crit_depth, nbytes=out.table_bytes)
                os.replace(tmp, path)
            except OSError:
                pass
    _MEMO[key] = out
    return out

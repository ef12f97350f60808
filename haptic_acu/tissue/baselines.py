"""The four baseline tissue models of the paper's comparison (MSM, FEM, BEM, SHF): what each layer's
surface does before it breaks, precomputed once per parameter set (docs/model.md section 12).

Each baseline answers the question the force net answers in the servo (``servo.step.press``): with
the tip at depth ``d`` below the pressed layer's rest surface (radially, the same depth the force net
reads), how hard does the surface push back along ``grad(-d)``, and has the layer broken. Every
baseline here is linear elastic and its contact is centred under the tip (as the force net is
re-centred under a sliding tip); the static ones answer ``F = k d`` with a stiffness ``k`` per
layer, and break at a depth ``d_c`` per layer; they differ in where ``k`` and ``d_c`` come from:

* **SHF** (the SH surface alone, Fang & Wu 2011's family): a penalty ``k`` along the normal below
  the SH surface, per layer, from the config; breaks at a force (``d_c = F_c / k``).
* **MSM** (a volumetric mass-spring lattice, [38]'s family; ``tissue/msm.py``): a cubic lattice of
  the layers from the pressed one down with springs and a volume energy that give it the layers' E
  and nu, lumped masses, integrated at the servo's rate by backward Euler in its symmetric modes
  (:func:`msm_response`, its state in ``State.msm_qv``); breaks when a spring at the tip's node
  reaches a strain. Its ``k`` and ``d_c`` here are its statics, for reports.
* **FEM** (linear elastostatics on tetrahedra, DiMaio & Salcudean 2005; Bro-Nielsen 1998): a
  structured tetrahedral mesh of the layers from the pressed one down (quarter-symmetric block,
  graded toward the tip, layer interfaces on element faces), P1 elements assembled with
  scikit-fem, the stiffness condensed (Schur complement) onto the surface nodes within
  :data:`FEM_PATCH_M` of the tip, then onto the contact set (a flat tip of the needle's radius);
  ``k`` is the condensed matrix's sum. Breaks at an indentation depth.
* **BEM** (boundary elements, James & Pai 1999; Zhu & Gu 2012's family): the contact disc (the
  needle's radius) in square boundary elements, their Green's functions Boussinesq's point-load
  solution of a half-space of the pressed layer's material (each element's own, its uniformly
  loaded equal-area disc's centre deflection); ``k`` is the sum of the capacitance matrix (the
  compliance matrix's inverse). Breaks at an indentation depth.

Precomputation is cached like the force nets' tables (``netresponse.cache_dir``), keyed by every
parameter that enters.
"""
from __future__ import annotations

import hashlib
import math
import os
import tempfile
import time
from dataclasses import dataclass, field

import numba as nb
import numpy as np

from ..base.config import MODEL_KINDS
from .mechanics import puncture_threshold
from . import msm
from .msm import msm_tick
from .netresponse import cache_dir

VERSION = 3  # bump when a precomputation changes (invalidates the cache)
KIND_CODES = {name: i for i, name in enumerate(MODEL_KINDS)}  # PARAMS.kind (0: the force net)
FORCENET, MSM, FEM, BEM, SHF = (KIND_CODES[n] for n in MODEL_KINDS)

# FEM mesh (ours): N_IN elements across the tip's radius, then cells growing by RATIO; the block is
# HALF_WIDTH wide (a quarter, by symmetry) and at most DEPTH deep (the rest of the body below is
# taken as fixed: at 100 tip radii it moves the tip's stiffness by under 1%).
FEM_N_IN = 2
FEM_RATIO = 1.45
FEM_HALF_WIDTH_M = 12e-3
FEM_DEPTH_M = 12e-3
FEM_PATCH_M = 1e-3  # surface nodes kept by the condensation (within this of the tip)
BEM_N_IN = 8  # boundary elements across the tip's radius


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
    """A baseline's stiffness along grad(-d) at the tip for the rendering layer: ``bl_k |grad d|^2``
    (the MSM's: its contact's stiffness within a step, ``1 / msm_g``, at least its static one)."""
    g = s.work[0].gd
    k_along = m.layer[k].bl_k
    if m.params[0].kind == MSM and m.layer[k].msm_g > 0.0:
        k_along = 1.0 / m.layer[k].msm_g
    return k_along * (g[0] * g[0] + g[1] * g[1] + g[2] * g[2])


# ---- FEM ----------------------------------------------------------------------------------------

def graded_grid(a: float, n_in: int, ratio: float, length: float) -> np.ndarray:
    """0 .. length: n_in equal cells across ``a``, then cells growing by ``ratio``."""
    h = a / n_in
    pts = list(np.linspace(0.0, a, n_in + 1))
    while pts[-1] + 1.5 * h * ratio < length:
        h *= ratio
        pts.append(pts[-1] + h)
    pts.append(length)
    return np.array(pts)


def depth_grid(a: float, n_in: int, ratio: float, interfaces, depth: float) -> np.ndarray:
    """Depths 0 .. depth graded from the surface, with every layer interface a grid plane."""
    z = graded_grid(a, n_in, ratio, depth)
    keep = [v for v in z if all(abs(v - s) > 0.3 * _local_h(z, v) for s in interfaces)]
    return np.unique(np.concatenate([keep, [s for s in interfaces if 0.0 < s < depth]]))


def _local_h(z, v):
    i = min(int(np.searchsorted(z, v)), len(z) - 1)
    return z[i] - z[i - 1] if i > 0 else z[1] - z[0]


@dataclass
class FemResult:
    stiffness: float  # N/m: flat-tip force per metre of indentation
    patch_xy: np.ndarray  # (n, 2) the condensed surface nodes (quarter), m
    schur: np.ndarray  # (n, n) the stiffness condensed onto their normal displacements, N/m (quarter)
    profile_r: np.ndarray  # surface nodes along x (m)
    profile_u: np.ndarray  # their downward displacement per metre of indentation
    nodes: int


def fem_flat_punch(E, nu, thick, a, n_in=FEM_N_IN, ratio=FEM_RATIO, half_width=FEM_HALF_WIDTH_M,
                   depth=FEM_DEPTH_M, patch=FEM_PATCH_M) -> FemResult:
    """A flat rigid tip of radius ``a`` pressed (frictionless) into a layered block: layers of
    Young's moduli ``E`` (Pa), Poisson ratios ``nu`` and thicknesses ``thick`` (m) from the top,
    the last one continuing to ``depth``; bottom fixed, sides free. Returns the condensed patch
    and the stiffness (:class:`FemResult`)."""
    import scipy.sparse.linalg as spla
    from skfem import Basis, ElementTetP1, ElementVector, MeshTet, asm
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    interfaces = list(np.cumsum(thick)[:-1])
    depth = min(depth, max(float(np.sum(thick)), depth))
    x = graded_grid(a, n_in, ratio, half_width)
    z = -depth_grid(a, n_in, ratio, interfaces, depth)[::-1]
    mesh = MeshTet.init_tensor(x, x, z)
    e = ElementVector(ElementTetP1())
    zc = -mesh.p[2, mesh.t].mean(axis=0)  # each element's centroid depth
    bounds = np.concatenate([[0.0], np.cumsum(thick)[:-1], [np.inf]])
    K = None
    for j in range(len(E)):
        sel = np.nonzero((zc >= bounds[j]) & (zc < bounds[j + 1]))[0]
        if sel.size == 0:
            continue
        # skfem's lame_parameters(E, nu) returns (lambda, mu), linear_elasticity takes (Lambda, Mu)
        Kj = asm(linear_elasticity(*lame_parameters(E[j], nu[j])), Basis(mesh, e, elements=sel))
        K = Kj if K is None else K + Kj
    K = K.tocsr()
    p = mesh.p
    dofs = Basis(mesh, e).nodal_dofs  # (3, nodes)
    fixed = np.concatenate([dofs[:, np.isclose(p[2], -depth)].ravel(), dofs[0, np.isclose(p[0], 0.0)],
                            dofs[1, np.isclose(p[1], 0.0)]])
    top = np.isclose(p[2], 0.0)
    r = np.hypot(p[0], p[1])
    pnodes = np.nonzero(top & (r <= patch * (1 + 1e-9)))[0]
    b = dofs[2, pnodes]
    fixed = np.setdiff1d(np.unique(fixed), b)
    inner = np.setdiff1d(np.arange(K.shape[0]), np.concatenate([fixed, b]))
    Kii = K[inner][:, inner].tocsc()
    Kib = K[inner][:, b].toarray()
    lu = spla.splu(Kii)
    X = lu.solve(Kib)  # K_ii^-1 K_ib
    S = K[b][:, b].toarray() - Kib.T @ X  # the Schur complement onto the patch's normal displacements
    S = 0.5 * (S + S.T)
    # the contact set (a flat tip of radius a) and the rest of the patch, free
    inside = r[pnodes] <= a * (1 + 1e-9)
    c = np.nonzero(inside)[0]
    o = np.nonzero(~inside)[0]
    Soo_inv_Soc = np.linalg.solve(S[np.ix_(o, o)], S[np.ix_(o, c)])
    Sc = S[np.ix_(c, c)] - S[np.ix_(c, o)] @ Soo_inv_Soc
    k = 4.0 * float(Sc.sum())  # four quarters
    # unit indentation: the patch's displacement, then the interior's, for the surface profile
    ub = np.zeros(len(b))
    ub[c] = 1.0
    ub[o] = -Soo_inv_Soc @ np.ones(len(c))
    u = np.zeros(K.shape[0])
    u[b] = ub
    u[inner] = -X @ ub
    along = np.nonzero(top & np.isclose(p[1], 0.0))[0]
    along = along[np.argsort(p[0, along])]
    return FemResult(k, p[:2, pnodes].T.copy(), S, p[0, along].copy(), u[dofs[2, along]].copy(), p.shape[1])


# ---- BEM ----------------------------------------------------------------------------------------

def _bem_grid(a, n_in):
    s = a / n_in
    g = (np.arange(-n_in, n_in) + 0.5) * s
    X, Y = np.meshgrid(g, g)
    keep = np.hypot(X, Y) <= a
    return s, np.stack([X[keep], Y[keep]], axis=1)


def bem_elements(n_in=BEM_N_IN) -> int:
    """The number of boundary elements on the tip's disc."""
    return len(_bem_grid(1.0, n_in)[1])


def bem_flat_punch(E, nu, a, n_in=BEM_N_IN) -> float:
    """Stiffness (N/m) of a flat tip of radius ``a`` on a half-space (E Pa, nu) by boundary elements:
    the disc in squares of side a / n_in; the displacement at element i of a unit load on element j
    is Boussinesq's (1 - nu^2) / (pi E r_ij), on itself that of its equal-area disc under uniform
    pressure at the centre, 2 (1 - nu^2) / (pi E R) with pi R^2 the element's area; the forces for
    a unit indentation are the compliance matrix's inverse (the capacitance matrix) times ones."""
    s, xy = _bem_grid(a, n_in)
    c = (1.0 - nu * nu) / (math.pi * E)
    r = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    R = s / math.sqrt(math.pi)
    np.fill_diagonal(r, 1.0)
    C = c / r
    np.fill_diagonal(C, 2.0 * c / R)
    return float(np.linalg.solve(C, np.ones(len(xy))).sum())


# ---- MSM (tissue/msm.py) -----------------------------------------------------------------------

@nb.njit(cache=True, nogil=True)
def msm_response(inp, m, s, k, idx, dep, ax):
    """The MSM's pressed layer ``k`` with the tip ``dep`` below its rest surface: one backward-Euler
    step of its lattice (``msm.msm_tick``; the lattice's state in ``State.msm_qv``, started from rest
    whenever the pressed layer changes), (the contact force along grad(-d), N; broken?). The layer
    breaks when a spring at the tip's node reaches ``msm_eps`` scaled by the approach speed as the
    force net's threshold is."""
    sv = s.servo[0]
    for c in range(3):
        sv.slot_q[idx, c] = s.work[0].q[c]
    lay = m.layer[k]
    qv = s.msm_qv
    if sv.msm_layer != k + 1:
        qv[:, :] = 0.0
        sv.msm_layer = k + 1
    fn, strain = msm_tick(m.msm, k, lay.msm_n, lay.msm_g, qv[0], qv[1], dep, m.params[0].dt)
    broke = strain > puncture_threshold(lay.msm_eps, inp.v, ax, m.params[0])
    return fn, broke


@nb.njit(cache=True, nogil=True)
def msm_release(m, s, k):
    """The tip off layer ``k``'s surface: its lattice moves on freely (one step, no contact)."""
    sv = s.servo[0]
    if sv.msm_layer != k + 1:
        return
    msm_tick(m.msm, k, m.layer[k].msm_n, m.layer[k].msm_g, s.msm_qv[0], s.msm_qv[1], -1.0, m.params[0].dt)


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
    # the MSM's lattices (msm.pack): the modes' table, per layer their count and the contact's
    # backward-Euler compliance (m/N); empty for the other models
    msm_tab: np.ndarray = field(default_factory=lambda: np.zeros((1, 1)))
    msm_count: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    msm_g: np.ndarray = field(default_factory=lambda: np.zeros(0))


def _layers(cfg, k):
    m = cfg.model
    E = [m.young_modulus_kpa[j] * 1e3 for j in range(k, len(cfg.layers))]
    nu = [m.poisson_ratio[j] for j in range(k, len(cfg.layers))]
    thick = [cfg.layers[j].thickness_mm * 1e-3 for j in range(k, len(cfg.layers))]
    return E, nu, thick


def contact_key(cfg) -> str:
    m = cfg.model
    text = repr((VERSION, m.kind, m.young_modulus_kpa, m.poisson_ratio, m.puncture_depth_mm, m.shf_stiffness_n_per_mm,
                 m.shf_puncture_force_n, m.msm_spacing_mm, m.msm_puncture_strain,
                 tuple(layer.thickness_mm for layer in cfg.layers), cfg.needle.diameter_mm, FEM_N_IN, FEM_RATIO,
                 FEM_HALF_WIDTH_M, FEM_DEPTH_M, FEM_PATCH_M, BEM_N_IN, msm.HALF_CELLS, msm.DEPTH_M,
                 msm.DAMPING_RATIO, msm.DENSITY_KG_M3, msm.DT))
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
    layer_modes = []
    for j in range(n):
        E, nu, thick = _layers(cfg, j)
        if m.kind == "shf":
            k[j] = m.shf_stiffness_n_per_mm[j] * 1e3
            crit[j] = m.shf_puncture_force_n[j] / k[j]
        elif m.kind == "fem":
            res = fem_flat_punch(E, nu, thick, a)
            k[j] = res.stiffness
            crit[j] = m.puncture_depth_mm[j] * 1e-3
            nbytes += res.schur.nbytes + res.patch_xy.nbytes
        elif m.kind == "bem":
            k[j] = bem_flat_punch(E[0], nu[0], a)
            crit[j] = m.puncture_depth_mm[j] * 1e-3
            nbytes += bem_elements(BEM_N_IN) ** 2 * 8  # the compliance matrix
        elif m.kind == "msm":
            md = msm.modes(E, nu, msm.DENSITY_KG_M3[j:], thick, m.msm_spacing_mm * 1e-3)
            layer_modes.append(md)
            k[j] = md.stiffness
            crit[j] = m.msm_puncture_strain[j] / md.strain_per_m
    out = Contact(m.kind, k, crit)
    if m.kind == "msm":
        out.msm_tab, out.msm_count, out.msm_g = msm.pack(layer_modes, n)
        nbytes += out.msm_tab.nbytes
    out.build_s = time.perf_counter() - t0
    out.table_bytes = int(nbytes) + k.nbytes + crit.nbytes
    return out


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
                out = Contact(cfg.model.kind, z["k"].copy(), z["crit"].copy(), 0.0, int(z["nbytes"]),
                              z["msm_tab"].copy(), z["msm_count"].copy(), z["msm_g"].copy())
        except (OSError, ValueError, KeyError):
            out = None
    if out is None:
        out = build_contact(cfg)
        if path is not None:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
                with os.fdopen(fd, "wb") as f:
                    np.savez(f, k=out.stiffness, crit=out.crit_depth, nbytes=out.table_bytes, msm_tab=out.msm_tab,
                             msm_count=out.msm_count, msm_g=out.msm_g)
                os.replace(tmp, path)
            except OSError:
                pass
    _MEMO[key] = out
    return out

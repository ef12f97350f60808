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
  (:func:`msm_response`, its state in ``State.msm_qv``); breaks when the tissue's mean strain over
  a gauge below the tip reaches a threshold. Its ``k`` and ``d_c`` here are its statics, for reports.
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
import math
import os
import tempfile
import time
from dataclasses import dataclass, field

import numba as nb
import numpy as np

from ..base.config import MODEL_KINDS
from . import bem, contact, fem, msm
from .body import Tissue, fit_key
from .mechanics import puncture_threshold
from .contact import Disc, Scratch, contact_solve
from .msm import msm_tick
from .netresponse import cache_dir

VERSION = 7  # bump when a precomputation changes (invalidates the cache)
KIND_CODES = {name: i for i, name in enumerate(MODEL_KINDS)}  # PARAMS.kind (0: the force net)
FORCENET, MSM, FEM, BEM, SHF = (KIND_CODES[n] for n in MODEL_KINDS)



# ---- the servo's side (compiled; one small function, not inlined into the step) -------------------

@nb.njit(cache=True, nogil=True, _nrt=False)
def baseline_response(inp, m, s, k, idx, dep, ax):
    """A baseline's pressed layer ``k`` with the tip ``dep`` below its rest surface: (the force along
    grad(-d), N; broken?). ``F = bl_k dep``; the layer breaks past ``bl_crit`` scaled by the approach
    speed as the force net's threshold is (``mechanics.puncture_threshold``). Keeps the tip in
    ``servo.slot_q`` for the drawn net (the force net's shape at that depth)."""
    for c in range(3):
        s.servo[0].slot_q[idx, c] = s.work[0].q[c]
    lay = m.layer[k]
    fn = lay.bl_k * dep
    broke = dep > puncture_threshold(lay.bl_crit, s.work[0].tip_v, ax, m.params[0])
    return fn, broke


@nb.njit(cache=True, nogil=True, _nrt=False)
def baseline_slope(m, s, k):
    """A baseline's stiffness along grad(-d) at the tip for the rendering layer: ``bl_k |grad d|^2``
    (the MSM's: its contact's stiffness within a step, ``1 / msm_g``, at least its static one)."""
    g = s.work[0].gd
    k_along = m.layer[k].bl_k
    if m.params[0].kind == MSM and m.layer[k].msm_g > 0.0:
        k_along = 1.0 / m.layer[k].msm_g
    return k_along * (g[0] * g[0] + g[1] * g[1] + g[2] * g[2])


# ---- FEM, BEM: the contact set (tissue/contact.py) -------------------------------------------------

@nb.njit(cache=True, nogil=True, _nrt=False)
def contact_response(inp, m, s, k, idx, dep, ax):
    """The FEM's or BEM's pressed layer ``k`` with the tip's apex ``dep`` below its rest surface:
    Signorini's contact on the layer's disc (``contact.contact_solve``; the set and its capacitance
    matrix kept in ``State.ct_*`` from tick to tick, emptied when the pressed layer changes), (the
    force along grad(-d), N; broken?). The layer breaks past ``bl_crit`` scaled by the approach speed
    as the force net's threshold is."""
    sv = s.servo[0]
    for c in range(3):
        sv.slot_q[idx, c] = s.work[0].q[c]
    lay = m.layer[k]
    if sv.ct_layer != k + 1:
        sv.ct_n = 0
        sv.ct_layer = k + 1
    n, fn, changes = contact_solve(Disc(m.ct_c, m.ct_ref, m.ct_h), k, lay.ct_row, lay.ct_n, dep,
                                   Scratch(s.ct_p, s.ct_f, s.ct_i), sv.ct_n)
    sv.ct_n = n
    broke = dep > puncture_threshold(lay.bl_crit, s.work[0].tip_v, ax, m.params[0])
    return fn, broke


@nb.njit(cache=True, nogil=True, _nrt=False)
def contact_release(s):
    """The tip off the surface: the contact set empties."""
    s.servo[0].ct_n = 0


# ---- MSM (tissue/msm.py) -----------------------------------------------------------------------

@nb.njit(cache=True, nogil=True, _nrt=False)
def msm_response(inp, m, s, k, idx, dep, ax):
    """The MSM's pressed layer ``k`` with the tip ``dep`` below its rest surface: one backward-Euler
    step of its lattice (``msm.msm_tick``; the lattice's state in ``State.msm_qv``, started from rest
    whenever the pressed layer changes), (the contact force along grad(-d), N; broken?). The layer
    breaks when the tissue's mean strain over the gauge below the tip (``msm.GAUGE_M``) reaches
    ``msm_eps`` scaled by the approach speed as the
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
    broke = strain > puncture_threshold(lay.msm_eps, s.work[0].tip_v, ax, m.params[0])
    return fn, broke


@nb.njit(cache=True, nogil=True, _nrt=False)
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
    # the FEM's / BEM's contact discs (contact.pack): compliances, whole-disc capacitances, the tip's
    # heights over the nodes, per layer the node count; (1, 1) and empty for the other models
    ct_c: np.ndarray = field(default_factory=lambda: np.zeros((1, 1)))
    ct_ref: np.ndarray = field(default_factory=lambda: np.zeros((1, 1)))
    ct_h: np.ndarray = field(default_factory=lambda: np.zeros((1, 1)))
    ct_n: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


def _layers(cfg, k):
    m = cfg.model
    E = [m.young_modulus_kpa[j] * 1e3 for j in range(k, len(cfg.layers))]
    nu = [m.poisson_ratio[j] for j in range(k, len(cfg.layers))]
    thick = [cfg.layers[j].thickness_mm * 1e-3 for j in range(k, len(cfg.layers))]
    return E, nu, thick


def rupture_depth(k: float, toughness: float, a: float) -> float:
    """The energy criterion (docs/model.md section 12.5: the energy the press stored pays for the
    first crack): a linear contact of stiffness ``k`` (N/m) breaks when ``k d^2 / 2`` reaches
    ``toughness`` (J/m^2) times the crack's area, taken as the tip's cross-section ``pi a^2``
    (ours): ``d_c = sqrt(2 J pi a^2 / k)`` (m)."""
    return math.sqrt(2.0 * toughness * math.pi * a * a / k)


def rupture_depth_curve(depth, force, toughness: float, a: float) -> float:
    """The same criterion for any quasi-static force curve ``force(depth)`` (N at m, from 0, rising):
    the depth at which the stored energy, its integral (trapezoids), reaches ``toughness`` times
    ``pi a^2``; linear within the last interval. ``inf`` if the curve ends first."""
    d = np.asarray(depth, float)
    f = np.asarray(force, float)
    w = np.concatenate([[0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(d))])
    need = toughness * math.pi * a * a
    i = int(np.searchsorted(w, need))
    if i >= len(w):
        return math.inf
    if i == 0:
        return float(d[0])
    # within [d[i-1], d[i]] the force is linear: solve the quadratic for the energy left
    f0, f1, h = f[i - 1], f[i], d[i] - d[i - 1]
    slope = (f1 - f0) / h
    left = need - w[i - 1]
    if abs(slope) < 1e-300:
        return float(d[i - 1] + left / f0)
    x = (-f0 + math.sqrt(max(f0 * f0 + 2.0 * slope * left, 0.0))) / slope
    return float(d[i - 1] + x)


def _tip_rupture_depth(k: float, disc, toughness: float, a: float, shape: str) -> float:
    """The FEM's or BEM's break depth by the energy criterion for the tip's shape: the flat tip's
    closed form (its force is ``k d``), else the energy stored along the disc's quasi-static contact
    curve (``contact.press_curve``, the servo's own solve) reaching ``toughness`` times ``pi a^2``."""
    flat = rupture_depth(k, toughness, a)
    if shape == "flat":
        return flat
    C, rho = disc
    h = contact.tip_heights(rho, a, shape)
    reach = flat + float(h.max())  # the curve lies above the flat tip's moved by the tip's height
    depths = np.linspace(0.0, 1.5 * reach, 3001)
    force, _, _ = contact.press_curve(C, h, depths)
    return rupture_depth_curve(depths, force, toughness, a)


def contact_key(cfg) -> str:
    m = cfg.model
    text = repr((VERSION, m.kind, m.young_modulus_kpa, m.poisson_ratio, m.fracture_toughness_j_per_m2, m.shf_stiffness_n_per_mm,
                 m.shf_puncture_force_n, m.msm_spacing_mm, m.msm_gauge_strain, msm.GAUGE_M,
                 tuple(layer.thickness_mm for layer in cfg.layers), cfg.needle.diameter_mm, m.tip_shape, fem.N_IN, fem.RATIO,
                 fem.HALF_WIDTH_M, fem.DEPTH_M, fem.PATCH_M, bem.N_IN, msm.HALF_CELLS, msm.DEPTH_M,
                 msm.DAMPING_RATIO, msm.DENSITY_KG_M3, msm.DT, fit_key(cfg) if m.kind == "fem" else None))
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def build_contact(cfg, fem_mesh: dict | None = None) -> Contact:
    """Precompute ``cfg.model.kind``'s per-layer contact (no cache). ``fem_mesh``: keywords of
    :func:`fem.press` for the FEM's mesh (e.g. ``{"ratio": 2.5}``, coarser than the default; never
    cached, see :func:`contact_key`), for a bench that times the build on a smaller mesh."""
    m = cfg.model
    n = len(cfg.layers)
    a = 0.5 * cfg.needle.diameter_mm * 1e-3
    t0 = time.perf_counter()
    k = np.zeros(n)
    crit = np.zeros(n)
    nbytes = 0
    layer_modes = []
    discs = []  # FEM, BEM: per layer (compliance, lateral distances of its nodes)
    tissue = Tissue.from_config(cfg) if m.kind == "fem" else None
    for j in range(n):
        E, nu, thick = _layers(cfg, j)
        if m.kind == "shf":
            k[j] = m.shf_stiffness_n_per_mm[j] * 1e3
            crit[j] = m.shf_puncture_force_n[j] / k[j]
        elif m.kind == "fem":
            res = fem.tissue_press(tissue, j, E, nu, a, **(fem_mesh or {}))
            discs.append(fem.disc_compliance(res, a))
            k[j] = res.stiffness
            crit[j] = _tip_rupture_depth(k[j], discs[-1], m.fracture_toughness_j_per_m2[j], a, m.tip_shape)
        elif m.kind == "bem":
            s_, xy = bem.disc_elements(a)
            discs.append((bem.compliance(E[0], nu[0], a), np.hypot(xy[:, 0], xy[:, 1])))
            k[j] = bem.flat_punch(E[0], nu[0], a)
            crit[j] = _tip_rupture_depth(k[j], discs[-1], m.fracture_toughness_j_per_m2[j], a, m.tip_shape)
        elif m.kind == "msm":
            md = msm.modes(E, nu, msm.DENSITY_KG_M3[j:], thick, m.msm_spacing_mm * 1e-3)
            layer_modes.append(md)
            k[j] = md.stiffness
            crit[j] = m.msm_gauge_strain[j] / md.strain_per_m
    out = Contact(m.kind, k, crit)
    if m.kind == "msm":
        out.msm_tab, out.msm_count, out.msm_g = msm.pack(layer_modes, n)
        nbytes += out.msm_tab.nbytes
    if discs:
        out.ct_c, out.ct_ref, out.ct_h, out.ct_n = contact.pack(discs, n, a, m.tip_shape)
        nbytes += out.ct_c.nbytes + out.ct_ref.nbytes + out.ct_h.nbytes
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
                              z["msm_tab"].copy(), z["msm_count"].copy(), z["msm_g"].copy(), z["ct_c"].copy(),
                              z["ct_ref"].copy(), z["ct_h"].copy(), z["ct_n"].copy())
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
                             msm_count=out.msm_count, msm_g=out.msm_g, ct_c=out.ct_c, ct_ref=out.ct_ref,
                             ct_h=out.ct_h, ct_n=out.ct_n)
                os.replace(tmp, path)
            except OSError:
                pass
    _MEMO[key] = out
    return out

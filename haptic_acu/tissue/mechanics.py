"""Post-puncture needle mechanics: cutting at the tip, shaft friction, track memory, Table 1 mode.

Standalone kernels (numba, ``nogil``, ``cache``, no ``fastmath``) that the servo step calls in its
post-puncture phase (docs/model.md, "Post-puncture mechanics"). Everything is SI and one-dimensional
along the needle's axis: ``s`` is the arc length from the skin entry point into the tissue (m), ``v``
its rate (m/s, positive advancing), forces are signed along +s (negative resists advancing).

Parts (Okamura, Simone and O'Leary 2004 split the force the same way):

* **Cutting** at the tip, ``cut[k]`` (N, at this needle's diameter), only while the tip advances into
  tissue of layer k that no earlier pass has cut. Track memory says what is cut: for each track (an
  insertion line: entry point, axis) and layer, the arc-length range already opened. A point near a
  track is cut in proportion to the overlap of the needle's cross-section with the track's
  (:func:`overlap_damage`, zero beyond two radii), so damage decays over the needle's radius instead of
  an all-or-nothing hole radius. A re-insertion along a track meets friction only.
* **Shaft friction**, per layer proportional to the needle length in it: breakaway (stiction)
  ``fs[k]``, Coulomb ``fc[k]`` (N per metre of needle) and viscous ``b[k]`` (N*s/m per metre).
  Karnopp's model (1985) is force-input: it needs the applied force to decide stick. The servo is
  position-input, so the stick phase is rendered by a stick point (an anchor on the shaft joined to
  the needle by a spring ``k_stick``) that slips when the spring's force passes the breakaway force
  and then trails at the Coulomb force (an elasto-plastic, Dahl-like element; Hayward and Armstrong
  2000 render friction for haptics the same way). The anchor only ever moves toward the needle, so the
  element stores at most ``f^2 / 2k`` and dissipates the rest: it is passive over any closed path.
  The cutting force joins the forward (advancing) slip threshold only. ``decay`` (from the config's
  ``friction_relaxation_s``) lets the held force relax exponentially (tissue stress relaxation), so
  a needle held still ends with no force.
* **Table 1 mode** (the paper's preset): ``F = -(sum_k d_k h_k) v`` with ``h_k`` the needle length in
  layer k (the physical depth below that layer's rest surface, clipped to its thickness).

Cost: every call between compiled functions that passes arrays (or tuples of them) pays numba's
reference counting (atomic increments and decrements), and every ``tuple.field`` access of an array
is one more; kernels therefore bind each array to a local once and take plain arrays and scalars
below :func:`post_puncture_force` (the tick's cost is measured by ``bench/``: docs/performance.md).

The needle's diameter scales cutting and friction linearly (config keys are per mm of diameter:
docs/model.md cites the measurements); :func:`mech_params` does that conversion.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from .layers import MAX_TRACKS, N_LAYERS

STUCK, SLIP_FWD, SLIP_BACK = 0, 1, -1
V_BAND = 1e-4  # m/s, ours: Karnopp's stick band: slower than this a sliding needle sticks again
UNCUT = 1e9  # m: a layer's cut range [lo, hi] is empty while lo = UNCUT, hi = -UNCUT (finite, so the
# state stays finite everywhere: the servo's checks treat a non-finite value as a fault)


class MechParams(NamedTuple):
    """Post-puncture parameters at this needle's diameter (SI)."""

    cut: np.ndarray  # (3,) N: cutting force at the tip per layer
    fs: np.ndarray  # (3,) N/m: breakaway (stiction) friction per metre of needle in the layer
    fc: np.ndarray  # (3,) N/m: Coulomb friction per metre of needle in the layer
    b: np.ndarray  # (3,) N*s/m per metre: viscous friction per metre of needle in the layer
    k_stick: float  # N/m: stick-point spring
    decay: float  # per tick: held force multiplied by exp(-dt / relax_s) (1.0: no relaxation)
    radius: float  # m: needle radius (track damage)
    length: float  # m: needle shaft length (no more than this is in tissue)


class FrictionState(NamedTuple):
    """The stick point. ``anchor[0]``: its arc length (m); ``mode[0]``: STUCK / SLIP_FWD / SLIP_BACK;
    ``engaged[0]``: 0 until the first call after :func:`friction_reset` places the anchor at the tip."""

    anchor: np.ndarray  # (1,) float64
    mode: np.ndarray  # (1,) int64
    engaged: np.ndarray  # (1,) int64


class Tracks(NamedTuple):
    """Track memory: every insertion line and, per layer, the arc-length range already cut."""

    entry: np.ndarray  # (MAX_TRACKS, 3) m: skin entry point
    axis: np.ndarray  # (MAX_TRACKS, 3): unit vector into the tissue
    cut_lo: np.ndarray  # (MAX_TRACKS, 3) m: cut range start per layer (UNCUT: none)
    cut_hi: np.ndarray  # (MAX_TRACKS, 3) m: cut range end per layer (-UNCUT: none)
    count: np.ndarray  # (1,) int64: tracks ever begun (the ring buffer holds the last MAX_TRACKS)


class Tip(NamedTuple):
    """The needle this tick, as the post-puncture phase needs it (all along the insertion line)."""

    s: float  # m: tip arc length from the skin entry point along the axis (physical: rest surfaces)
    v: float  # m/s: axial velocity, positive advancing
    p: np.ndarray  # (3,) m: tip position, scene frame
    axis: np.ndarray  # (3,): unit insertion axis into the tissue
    bounds: np.ndarray  # (4,) m: arc lengths where the line crosses the four rest boundaries
    lengths: np.ndarray  # (3,) m: needle length per layer (lengths_in_layers)
    punctured: int  # layers whose surface this insertion has broken (0..3), from the skin down


def new_friction_state() -> FrictionState:
    return FrictionState(np.zeros(1), np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64))


def new_tracks() -> Tracks:
    return Tracks(np.zeros((MAX_TRACKS, 3)), np.tile([0.0, 0.0, -1.0], (MAX_TRACKS, 1)),
                  np.full((MAX_TRACKS, N_LAYERS), UNCUT), np.full((MAX_TRACKS, N_LAYERS), -UNCUT),
                  np.zeros(1, dtype=np.int64))


def mech_params(layers, needle, dt: float = 1e-3) -> MechParams:
    """Kernel parameters from the config: ``layers`` (skin, fat, muscle LayerParams) and ``needle``
    (NeedleParams). Per-mm-of-diameter keys times the needle's diameter in mm."""
    dmm = needle.diameter_mm
    cut = np.array([layer.cutting_n_per_mm_diameter * dmm for layer in layers])
    fc = np.array([layer.coulomb_n_per_mm2 * dmm * 1e3 for layer in layers])
    fs = fc * np.array([layer.stiction_ratio for layer in layers])
    b = np.array([layer.viscous_n_s_per_m_per_mm2 * dmm * 1e3 for layer in layers])
    relax = needle.friction_relaxation_s
    decay = math.exp(-dt / relax) if relax > 0 else 1.0
    return MechParams(cut, fs, fc, b, needle.stick_stiffness_n_per_mm * 1e3, decay, 0.5e-3 * dmm,
                      needle.length_mm * 1e-3)


# ---- geometry ---------------------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True, _nrt=False)
def overlap_damage(r, radius):
    """Fraction of a needle's cross-section (radius ``radius``) at lateral distance ``r`` from a track
    of the same needle that the track has already opened: the two discs' lens area over the disc's
    area. 1 on the track, 0 from two radii on, continuous and decreasing in between."""
    if radius <= 0.0:
        return 0.0
    r = abs(r)
    if r >= 2.0 * radius:
        return 0.0
    x = r / (2.0 * radius)  # lens area / disc area = (2 acos x - 2 x sqrt(1 - x^2)) / pi
    return (2.0 * math.acos(x) - 2.0 * x * math.sqrt(1.0 - x * x)) / math.pi


@nb.njit(cache=True, nogil=True, _nrt=False)
def lengths_in_layers(s_tip, bounds, length, out):
    """Needle length in each layer (m) for a tip at arc length ``s_tip`` on a line whose rest
    boundaries lie at arc lengths ``bounds[0..3]`` (skin surface, skin/fat, fat/muscle, muscle/bone;
    ``bounds[0]`` is normally 0). No more than ``length`` of shaft (behind the tip) counts. Returns
    the total."""
    back = s_tip - length
    total = 0.0
    for k in range(N_LAYERS):
        lo = max(bounds[k], back)
        hi = min(bounds[k + 1], s_tip)
        d = hi - lo
        if d < 0.0:
            d = 0.0
        out[k] = d
        total += d
    return total


@nb.njit(cache=True, nogil=True, _nrt=False)
def layer_at(s, bounds):
    """Layer at arc length ``s`` along a line with boundaries ``bounds``: -1 above the skin, 0-2 the
    tissue layers, 3 beyond the muscle/bone boundary."""
    if s < bounds[0]:
        return -1
    for k in range(N_LAYERS):
        if s < bounds[k + 1]:
            return k
    return N_LAYERS


# ---- track memory -----------------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True, _nrt=False)
def begin_track(tracks, entry, axis, radius):
    """The track an insertion at ``entry`` along unit ``axis`` extends: an existing one whose line
    passes within ``radius`` of the entry with an axis within ~1 degree, else a new one (the oldest is
    overwritten past MAX_TRACKS). Returns its slot."""
    te, ta, lo, hi, count = tracks.entry, tracks.axis, tracks.cut_lo, tracks.cut_hi, tracks.count
    n = min(count[0], MAX_TRACKS)
    for j in range(n):
        c = ta[j, 0] * axis[0] + ta[j, 1] * axis[1] + ta[j, 2] * axis[2]
        if c < 0.99985:
            continue
        dx = entry[0] - te[j, 0]
        dy = entry[1] - te[j, 1]
        dz = entry[2] - te[j, 2]
        t = dx * ta[j, 0] + dy * ta[j, 1] + dz * ta[j, 2]
        r2 = (dx - t * ta[j, 0]) ** 2 + (dy - t * ta[j, 1]) ** 2 + (dz - t * ta[j, 2]) ** 2
        if r2 <= radius * radius:
            return j
    j = count[0] % MAX_TRACKS
    for c in range(3):
        te[j, c] = entry[c]
        ta[j, c] = axis[c]
    for k in range(N_LAYERS):
        lo[j, k] = UNCUT
        hi[j, k] = -UNCUT
    count[0] += 1
    return j


@nb.njit(cache=True, nogil=True, _nrt=False)
def record_cut(cut_lo, cut_hi, j, layer, lo, hi):
    """Track ``j``'s layer ``layer`` is cut over arc lengths [lo, hi]: extends its range in the
    tracks' ``cut_lo`` / ``cut_hi`` arrays."""
    if layer < 0 or layer >= N_LAYERS or hi < lo:
        return
    if lo < cut_lo[j, layer]:
        cut_lo[j, layer] = lo
    if hi > cut_hi[j, layer]:
        cut_hi[j, layer] = hi


@nb.njit(cache=True, nogil=True, _nrt=False)
def record_passage(tracks, j, bounds, s_tip, punctured):
    """The tip at ``s_tip`` has opened every punctured layer (k < ``punctured``) of track ``j`` from
    its rest surface down to the tip (a straight needle cuts contiguously)."""
    cut_lo, cut_hi = tracks.cut_lo, tracks.cut_hi
    for k in range(min(punctured, N_LAYERS)):
        record_cut(cut_lo, cut_hi, j, k, bounds[k], min(s_tip, bounds[k + 1]))


@nb.njit(cache=True, nogil=True, _nrt=False)
def track_damage(tracks, px, py, pz, layer, radius):
    """How much of layer ``layer``'s tissue at point (px, py, pz) (scene frame, m) earlier passes have
    opened (0 intact .. 1 cut): the largest :func:`overlap_damage` over the tracks whose cut range in
    that layer contains the point's projection."""
    te, ta, clo, chi = tracks.entry, tracks.axis, tracks.cut_lo, tracks.cut_hi
    n = min(tracks.count[0], MAX_TRACKS)
    best = 0.0
    if layer < 0 or layer >= N_LAYERS:
        return best
    for j in range(n):
        lo = clo[j, layer]
        hi = chi[j, layer]
        if hi < lo:
            continue
        dx = px - te[j, 0]
        dy = py - te[j, 1]
        dz = pz - te[j, 2]
        s = dx * ta[j, 0] + dy * ta[j, 1] + dz * ta[j, 2]
        if s < lo or s > hi:
            continue
        r2 = (dx - s * ta[j, 0]) ** 2 + (dy - s * ta[j, 1]) ** 2 + (dz - s * ta[j, 2]) ** 2
        d = overlap_damage(math.sqrt(r2), radius)
        if d > best:
            best = d
    return best


# ---- friction ---------------------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def karnopp_force(v, f_applied, fs, fc, b, v_band):
    """Karnopp's (1985) friction force for velocity ``v`` and net applied force ``f_applied``
    (force-input form): inside the stick band |v| <= ``v_band`` it cancels the applied force up to
    the breakaway ``fs``; outside, ``-(fc sign v + b v)``."""
    if abs(v) <= v_band:
        if f_applied > fs:
            return -fs
        if f_applied < -fs:
            return fs
        return -f_applied
    return -(fc * (1.0 if v > 0.0 else -1.0) + b * v)


@nb.njit(cache=True, nogil=True)
def friction_reset(st):
    """Forget the stick point (a new insertion): the next :func:`stick_slip` places it at the tip."""
    engaged, mode, anchor = st.engaged, st.mode, st.anchor
    engaged[0] = 0
    mode[0] = STUCK
    anchor[0] = 0.0


@nb.njit(cache=True, nogil=True, _nrt=False)
def stick_point(anchor, mode, k, decay, s, v, thr):
    """One tick of the stick point on plain scalars: the anchor's arc length ``anchor`` (m) and its
    ``mode`` (STUCK / SLIP_FWD / SLIP_BACK) for a needle at ``s`` moving at ``v``; spring ``k`` (N/m),
    held force times ``decay`` per tick; ``thr`` as for :func:`stick_slip`. Returns (new anchor, new
    mode, force on the needle along +s)."""
    u = (anchor - s) * decay  # anchor - needle, relaxed toward the needle
    f = k * u
    fwd = thr[0] if mode != SLIP_FWD else thr[2]  # pushing forward: the spring pulls back (f < 0)
    back = thr[1] if mode != SLIP_BACK else thr[3]
    new_mode = mode
    if f < -fwd:
        u = -fwd / k
        new_mode = SLIP_FWD
    elif f > back:
        u = back / k
        new_mode = SLIP_BACK
    elif not ((mode == SLIP_FWD and v > V_BAND) or (mode == SLIP_BACK and v < -V_BAND)):
        new_mode = STUCK
    return s + u, new_mode, k * u


@nb.njit(cache=True, nogil=True)
def stick_slip(st, k, decay, s, v, thr):
    """One tick of the stick point (spring ``k`` N/m, held force times ``decay`` per tick) for a
    needle at arc length ``s`` moving at ``v`` (m/s). ``thr``: slip thresholds in N, a 4-tuple
    (stuck forward, stuck backward, sliding forward, sliding backward), all >= 0, the forward ones
    including any cutting (:func:`shaft_thresholds`). Returns the force on the needle along +s. A
    sliding needle stays sliding (Coulomb threshold) while it keeps moving the same way faster than
    V_BAND, even if a threshold rose (fresh tissue ahead): it sticks (breakaway threshold) only when
    it stops or turns. Passive: the anchor only moves toward the needle (relaxation and slip
    both shrink the spring). The state lives in ``st`` (:class:`FrictionState`); the arithmetic is
    :func:`stick_point`'s."""
    anchor, mode_a, engaged = st.anchor, st.mode, st.engaged
    if engaged[0] == 0:
        anchor[0] = s
        engaged[0] = 1
        mode_a[0] = STUCK
    a, mo, f = stick_point(anchor[0], mode_a[0], k, decay, s, v, thr)
    anchor[0] = a
    mode_a[0] = mo
    return f


@nb.njit(cache=True, nogil=True)
def shaft_thresholds(fs, fc, lengths, cut_now):
    """Slip thresholds (N) for :func:`stick_slip`, a 4-tuple (stuck forward, stuck backward, sliding
    forward, sliding backward): friction of the needle lengths per layer plus the cutting force
    ``cut_now`` (N) on the forward ones. ``fs``, ``fc``: MechParams' breakaway and Coulomb (N/m)."""
    s_st = 0.0
    s_c = 0.0
    for k in range(N_LAYERS):
        s_st += fs[k] * lengths[k]
        s_c += fc[k] * lengths[k]
    return (s_st + cut_now, s_st, s_c + cut_now, s_c)


@nb.njit(cache=True, nogil=True)
def viscous_force(b, lengths, v):
    """Viscous shaft friction along +s: ``-(sum_k b_k L_k) v`` (``b``: MechParams.b)."""
    c = 0.0
    for k in range(N_LAYERS):
        c += b[k] * lengths[k]
    return -c * v


@nb.njit(cache=True, nogil=True, _nrt=False)
def cutting_layer(s, bounds, punctured):
    """The layer a tip at arc length ``s`` cuts into: the one it is in, if this insertion has broken
    its surface (``punctured`` layers from the skin down); -1 while it presses a surface, is above the
    skin or is in bone."""
    k = layer_at(s, bounds)
    if 0 <= k < min(punctured, N_LAYERS):
        return k
    return -1


@nb.njit(cache=True, nogil=True)
def post_puncture_force(prm, st, tracks, j, tip):
    """The post-puncture axial force (N along +s) for one tick of an insertion on track ``j``:
    stick-slip shaft friction with the cutting force on its forward threshold, plus viscous
    friction; then records on the track what an advancing tip has opened (:func:`record_passage`).
    The cutting force is the tip's layer's times the uncut fraction one needle radius ahead of the
    tip (:func:`track_damage`), 0 where :func:`cutting_layer` is -1. Each NamedTuple field is read
    once: numba reference-counts every array field access and every array passed to a call."""
    s, v, bounds, lengths, ax, p = tip.s, tip.v, tip.bounds, tip.lengths, tip.axis, tip.p
    r = prm.radius
    k = cutting_layer(s, bounds, tip.punctured)
    cut = 0.0
    if k >= 0:
        dmg = track_damage(tracks, p[0] + r * ax[0], p[1] + r * ax[1], p[2] + r * ax[2], k, r)
        cut = prm.cut[k] * (1.0 - dmg)
    f = stick_slip(st, prm.k_stick, prm.decay, s, v, shaft_thresholds(prm.fs, prm.fc, lengths, cut))
    if v > 0.0:  # only an advancing tip opens tissue
        record_passage(tracks, j, bounds, s, tip.punctured)
    return f + viscous_force(prm.b, lengths, v)


@nb.njit(cache=True, nogil=True)
def table1_force(d, lengths, v, out):
    """The paper's Table 1 after and between punctures: ``-(sum_k d_k h_k) v`` with ``d`` (3,) in
    N*s/m per metre of needle and ``h_k = lengths[k]`` the needle length in layer k (physical depth
    below that layer's rest surface, clipped to its thickness). ``out`` (3,): each layer's share.
    Returns the total along +s."""
    total = 0.0
    for k in range(N_LAYERS):
        out[k] = -d[k] * lengths[k] * v
        total += out[k]
    return total


# ---- rupture speed dependence ---------------------------------------------------------------------
def rupture_fields(rp) -> tuple:
    """``(PARAMS field, value)`` pairs (SI) for the servo's Model from the config's ``[rupture]``
    section (:class:`haptic_acu.base.config.RuptureParams`)."""
    return (("rupture_ratio", float(rp.high_speed_ratio)), ("rupture_vc", rp.speed_scale_mm_s * 1e-3),
            ("rupture_vref", rp.reference_speed_mm_s * 1e-3))


@nb.njit(cache=True, nogil=True, _nrt=False)
def rupture_speed_factor(u, ratio, vc, vref):
    """Factor on a surface's puncture threshold at approach speed ``u`` (m/s, along the axis into
    the tissue; a receding or still tip counts as 0): the threshold falls from its quasi-static value
    toward ``ratio`` times it as the speed rises, halfway at ``vc``, normalised to 1 at ``vref``::

        g(u) = (ratio + (1 - ratio) vc / (vc + u)) / (ratio + (1 - ratio) vc / (vc + vref))

    (Mahvash and Dupont 2009/2010: the rupture force and the deflection before it fall as the needle
    moves faster and approach lower bounds; docs/model.md section 2.2.) ``ratio >= 1``: exactly 1
    at every speed (no speed dependence)."""
    if ratio >= 1.0:
        return 1.0
    if not u > 0.0:  # receding, still, or not a number: the quasi-static threshold
        u = 0.0
    num = ratio + (1.0 - ratio) * vc / (vc + u)
    den = ratio + (1.0 - ratio) * vc / (vc + vref)
    return num / den


@nb.njit(cache=True, nogil=True, inline="always")
def puncture_threshold(threshold, v, ax, pr):
    """A pressed layer's ring-w puncture threshold (``threshold``, m) for a tip moving at ``v`` (3,)
    m/s on a net whose axis ``ax`` (3,) points out of the tissue: times :func:`rupture_speed_factor`
    of the approach speed ``-(v . ax)``, with the PARAMS record ``pr``'s ``rupture_ratio``,
    ``rupture_vc`` and ``rupture_vref``."""
    u = -(v[0] * ax[0] + v[1] * ax[1] + v[2] * ax[2])
    return threshold * rupture_speed_factor(u, pr.rupture_ratio, pr.rupture_vc, pr.rupture_vref)

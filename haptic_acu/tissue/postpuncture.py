"""The needle inside the tissue, as the servo step sees it: its axis and entry, the geometry along
that axis, track memory at the surfaces, and the post-puncture forces (mechanics.py's kernels).

Phases of :func:`haptic_acu.servo.step.step_kernel` (each takes the NamedTuples of
:mod:`haptic_acu.servo.state`):

* :func:`begin_insertion` when the skin breaks (or the tip enters through an earlier track): the
  needle's axis (the device's, ``TickIn.axis``, where it knows it; else the direction of travel from
  where the tip first crossed the rest skin surface, ``servo.touch``), the entry point (where that
  line crosses the rest skin surface), the arc lengths at which the line crosses the four rest
  boundaries (``servo.bounds``), the track it extends, and a fresh stick point.
* :func:`find_track`: a layer touched where an earlier pass opened it (half or more of the needle's
  cross-section over a track's cut range, ``mechanics.overlap_damage``) is entered without a surface
  to break (replaces the all-or-nothing hole radius).
* :func:`shaft_forces` each tick while inserted: the needle length in each punctured layer
  (``servo.lengths``, physical: measured from the rest boundaries along the axis), then either the
  paper's Table 1 (``-sum d_k h_k v``) or cutting at the tip into uncut tissue plus the stick-point
  Karnopp shaft friction (stiction and Coulomb levels times ``servo.grasp[k]``) plus viscous friction.

Everything is along the axis: ``s`` the tip's arc length from the entry (``work.s_p``), ``v`` its
rate, a force along +s is ``f * axis`` (negative resists advancing).
"""
from __future__ import annotations

import math

import numba as nb

from . import shf
from .mechanics import (STUCK, SLIP_FWD, Tracks, begin_track, cutting_layer, lengths_in_layers,
                        overlap_damage, record_passage, stick_point, track_damage)
from .layers import MAX_TRACKS, N_LAYERS, TABLE1

NO_CROSSING = 1.0  # m: a boundary the axis never reaches (beyond any needle)


@nb.njit(cache=True, nogil=True, inline="always")
def tracks_of(s):
    """The state's track memory as mechanics.Tracks (views, no copies)."""
    return Tracks(s.tr_entry, s.tr_axis, s.tr_lo, s.tr_hi, s.tr_count)


@nb.njit(cache=True, nogil=True)
def gap_on_line(m, k, p, a, t):
    """How far the point ``p + t a`` lies outside rest boundary ``k`` (m, radially; < 0 inside)."""
    c = m.centre
    th, ph, rho = shf.direction_of(p[0] + t * a[0], p[1] + t * a[1], p[2] + t * a[2], c[0], c[1], c[2])
    return rho - shf.eval_point(m.coeffs[k], m.params[0].lmax, th, ph)


@nb.njit(cache=True, nogil=True)
def line_crossing(m, k, p, a, t0, t1):
    """The parameter t where the line ``p + t a`` crosses rest boundary ``k``, by the secant method
    from the guesses ``t0``, ``t1``; NaN if it does not converge (the line misses the boundary)."""
    g0 = gap_on_line(m, k, p, a, t0)
    g1 = gap_on_line(m, k, p, a, t1)
    for _ in range(40):
        if abs(g1) < 1e-10:
            return t1
        den = g1 - g0
        if den == 0.0:
            break
        step = -g1 * (t1 - t0) / den
        if step > 0.02:  # no jumps past 20 mm: a grazing line converges to its nearer crossing
            step = 0.02
        elif step < -0.02:
            step = -0.02
        t0, g0 = t1, g1
        t1 = t1 + step
        g1 = gap_on_line(m, k, p, a, t1)
    if abs(g1) < 1e-8:
        return t1
    return math.nan


@nb.njit(cache=True, nogil=True)
def axis_bounds(m, s):
    """``servo.bounds``: arc lengths from the entry along the axis where the line crosses the rest
    boundaries (0 for the skin; NO_CROSSING where it never does), non-decreasing."""
    sv = s.servo[0]
    e = sv.entry
    a = sv.axis
    c = m.centre
    rx, ry, rz = e[0] - c[0], e[1] - c[1], e[2] - c[2]
    rr = math.sqrt(rx * rx + ry * ry + rz * rz)
    cosang = -(a[0] * rx + a[1] * ry + a[2] * rz) / rr if rr > 0.0 else 1.0
    if cosang < 0.1:
        cosang = 0.1
    b = sv.bounds
    b[0] = 0.0
    for k in range(1, N_LAYERS + 1):
        prev = b[k - 1]
        if prev >= NO_CROSSING:
            b[k] = NO_CROSSING
            continue
        thick = m.layer[k - 1].thickness
        g = prev + thick / cosang
        t = line_crossing(m, k, e, a, g, g + 1e-4)
        if not (t >= prev) or not math.isfinite(t):
            t = NO_CROSSING
        b[k] = t


@nb.njit(cache=True, nogil=True)
def set_axis(inp, s, fx, fy, fz):
    """``servo.axis``: the device's (``inp.axis``, if finite and non-zero), else the direction of
    travel from ``servo.touch`` to the tip, else (fx, fy, fz) (unit)."""
    sv = s.servo[0]
    ia = inp.axis
    n = math.sqrt(ia[0] * ia[0] + ia[1] * ia[1] + ia[2] * ia[2])
    if math.isfinite(n) and n > 0.5:
        for c in range(3):
            sv.axis[c] = ia[c] / n
        return
    p = s.work[0].tip
    dx = p[0] - sv.touch[0]
    dy = p[1] - sv.touch[1]
    dz = p[2] - sv.touch[2]
    d = math.sqrt(dx * dx + dy * dy + dz * dz)
    if d > 2e-5:
        sv.axis[0] = dx / d
        sv.axis[1] = dy / d
        sv.axis[2] = dz / d
    else:
        sv.axis[0] = fx
        sv.axis[1] = fy
        sv.axis[2] = fz


@nb.njit(cache=True, nogil=True)
def begin_insertion(inp, m, s, j):
    """The skin is broken (``j`` = -1) or entered through track ``j``: axis (:func:`set_axis`; a
    track's own where the device does not say), entry point (where the axis through the tip crosses
    the rest skin surface; a track's entry), boundaries along it, the track this insertion extends,
    and a fresh stick point. ``servo.axis`` holds the fallback direction on entry."""
    sv = s.servo[0]
    tr = tracks_of(s)
    if j >= 0:
        set_axis(inp, s, s.tr_axis[j, 0], s.tr_axis[j, 1], s.tr_axis[j, 2])
        if not math.isfinite(inp.axis[0]):
            for c in range(3):
                sv.axis[c] = s.tr_axis[j, c]
        for c in range(3):
            sv.entry[c] = s.tr_entry[j, c]
    else:
        set_axis(inp, s, sv.axis[0], sv.axis[1], sv.axis[2])
        a = sv.axis
        p = s.work[0].tip
        back = ((p[0] - sv.touch[0]) * a[0] + (p[1] - sv.touch[1]) * a[1] + (p[2] - sv.touch[2]) * a[2])
        t = line_crossing(m, 0, p, a, -back, -back - 1e-4)
        if not math.isfinite(t):
            t = -back
        for c in range(3):
            sv.entry[c] = p[c] + t * a[c]
    sv.inserted = 1
    e = sv.entry
    a = sv.axis
    p = s.work[0].tip
    s.work[0].s_p = (p[0] - e[0]) * a[0] + (p[1] - e[1]) * a[1] + (p[2] - e[2]) * a[2]
    sv.deepest = s.work[0].s_p
    axis_bounds(m, s)
    sv.track = begin_track(tr, sv.entry, sv.axis, m.params[0].needle_radius)
    sv.engaged = 0


@nb.njit(cache=True, nogil=True)
def find_track(m, s, k):
    """A track whose layer-``k`` cut range holds the contact point ``work.cpt`` (from one needle
    radius above the rest surface) with half or more of the needle's cross-section over it; or -1."""
    cpt = s.work[0].cpt
    r = m.params[0].needle_radius
    best = 0.5
    jbest = -1
    for j in range(min(s.tr_count[0], MAX_TRACKS)):
        lo = s.tr_lo[j, k]
        hi = s.tr_hi[j, k]
        if hi < lo:
            continue
        dx = cpt[0] - s.tr_entry[j, 0]
        dy = cpt[1] - s.tr_entry[j, 1]
        dz = cpt[2] - s.tr_entry[j, 2]
        ax = s.tr_axis[j]
        t = dx * ax[0] + dy * ax[1] + dz * ax[2]
        if t < lo - r or t > hi:
            continue
        lat = math.sqrt(max((dx - t * ax[0]) ** 2 + (dy - t * ax[1]) ** 2 + (dz - t * ax[2]) ** 2, 0.0))
        dmg = overlap_damage(lat, r)
        if dmg >= best:
            best = dmg
            jbest = j
    return jbest


@nb.njit(cache=True, nogil=True, inline="always")
def held_lengths(m, s):
    """``servo.lengths``: needle length in each punctured layer (physical, from the rest boundaries
    along the axis; a layer still pressed holds none). Returns their sum."""
    sv = s.servo[0]
    wk = s.work[0]
    lengths_in_layers(wk.s_p, sv.bounds, m.params[0].needle_length, sv.lengths)
    total = 0.0
    for k in range(N_LAYERS):
        if k >= wk.front:
            sv.lengths[k] = 0.0
        total += sv.lengths[k]
    return total


@nb.njit(cache=True, nogil=True, inline="always")
def table1_axial(m, s, d, v):
    """The paper's Table 1 along the axis: ``-(sum_k d_k h_k) v``, h_k the needle length in layer k."""
    lengths = s.servo[0].lengths
    cd = 0.0
    for k in range(N_LAYERS):
        ck = m.layer[k].damping * lengths[k]
        cd += ck
        d.f_layer[k] += -ck * v
    d.axial_damping = cd
    d.f_viscous = -cd * v
    return -cd * v


@nb.njit(cache=True, nogil=True)
def rich_axial(inp, m, s, d, v):
    """Cutting + stick-point shaft friction + viscous friction along the axis (N along +s)."""
    sv = s.servo[0]
    wk = s.work[0]
    prm = m.params[0]
    lengths = sv.lengths
    s_tip = wk.s_p
    a = sv.axis
    r = prm.needle_radius
    kc = cutting_layer(s_tip, sv.bounds, wk.front)
    cut = 0.0
    if s_tip > sv.deepest:
        sv.deepest = s_tip
    if kc >= 0 and m.layer[kc].cut > 0.0:
        # The crack front: the deepest this insertion has been. The tissue one radius ahead of it
        # (within the layer), as far as no pass has opened it, resists; a tip drawn back from the
        # front loses it over twice the travel that unloads the stick spring by the cutting force
        # (so the friction never slips forward while the needle is withdrawn).
        behind = sv.deepest - s_tip
        reach = 1.0 - 0.5 * behind * prm.k_stick / m.layer[kc].cut
        if reach > 0.0:
            ahead = behind + r
            room = sv.bounds[kc + 1] - 1e-9 - s_tip
            if ahead > room:
                ahead = room
            p = wk.tip
            dmg = track_damage(tracks_of(s), p[0] + ahead * a[0], p[1] + ahead * a[1], p[2] + ahead * a[2], kc, r)
            cut = m.layer[kc].cut * (1.0 - dmg) * reach
    st = 0.0
    co = 0.0
    b = 0.0
    for k in range(N_LAYERS):
        g = sv.grasp[k]
        st += g * m.layer[k].fs * lengths[k]
        co += g * m.layer[k].fc * lengths[k]
        b += m.layer[k].visc * lengths[k]
    if sv.engaged == 0:
        sv.anchor = s_tip
        sv.fmode = STUCK
        sv.engaged = 1
    anchor, mode, f = stick_point(sv.anchor, sv.fmode, prm.k_stick, prm.decay, s_tip, v,
                                  (st + cut, st, co + cut, co))
    sv.anchor = anchor
    sv.fmode = mode
    thr = co + cut if mode == SLIP_FWD else st + cut
    f_cut = f * cut / thr if (f < 0.0 and thr > 0.0) else 0.0
    fv = -b * v
    for k in range(N_LAYERS):
        share = m.layer[k].visc * lengths[k] * -v
        if st > 0.0:
            share += (f - f_cut) * sv.grasp[k] * m.layer[k].fs * lengths[k] / st
        d.f_layer[k] += share
    if kc >= 0:
        d.f_layer[kc] += f_cut
    d.f_cut = f_cut
    d.f_friction = f - f_cut
    d.f_viscous = fv
    d.axial_damping = b
    d.breakaway = st
    return f + fv


@nb.njit(cache=True, nogil=True, inline="always")
def shaft_forces(inp, m, s, d):
    """The post-puncture force along the axis (Table 1 or cutting + friction), into ``work.f`` and
    ``d.f_damp`` (N along +axis; its parts in ``f_cut``, ``f_friction``, ``f_viscous``); records on
    the track what an advancing tip opens."""
    sv = s.servo[0]
    a = sv.axis
    tv = s.work[0].tip_v  # the needle's (held by the handle: not along the axis)
    v = tv[0] * a[0] + tv[1] * a[1] + tv[2] * a[2]
    held_lengths(m, s)
    if m.params[0].mechanics == TABLE1:
        fa = table1_axial(m, s, d, v)
    else:
        fa = rich_axial(inp, m, s, d, v)
    wk = s.work[0]
    if v > 0.0:  # an advancing tip opens the layers it has broken down to where it is
        record_passage(tracks_of(s), sv.track, sv.bounds, wk.s_p, wk.front)
    for c in range(3):
        wk.f[c] += fa * a[c]
    d.f_damp = fa

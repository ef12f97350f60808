"""The needle in layered tissue: per-layer state machine, Table 1 forces, holes, safety.

One servo tick is one call of :func:`step_kernel` (numba, ``nogil``, allocation-free), a short
sequence of named phases, each a small kernel of its own:

    check_input -> track_entry [hold_at_handle: no more than the needle's length goes in] ->
    (tip radii) -> touch / press [recentre, table_response or sweep_net] -> puncture or
    surface_force -> post_puncture [shaft_forces, lateral_guidance] ->
    handle_stop (the handle on the skin: the stop's spring from the needle to the device) ->
    twirl_phase (winding: torque, grasp) -> bone_wall -> danger_phase -> locate -> clamp
    -> render_local -> danger_render   (the danger phases: a point's structures, servo/danger.py)

Every phase takes the NamedTuples of :mod:`haptic_acu.servo.state` (``inp``: TickIn, ``m``: Model,
``s``: State, ``d``: the DIAG record) plus at most a layer or slot index; values one phase hands the
next live in the ``work`` record (``q``, ``rho``, ``front``, ``f``...). :class:`NeedleModel` is the
thin Python object that owns the arrays.

States per layer and insertion site: UNTOUCHED -> PRESSING (a force net is active) -> PUNCTURED.
The needle presses at most one layer at a time, the first one not yet punctured (the "front").
Force on the needle (and so on the hand): the pressed layer's net reaction (eq. 6) with N1 held at the
tip's radial depth d below that layer's rest surface and no lateral offset, along grad(-d) (so a
function of the tip's position alone, the gradient of a potential: sliding is smooth and no closed
path on an intact surface returns energy; the net is re-centred under a sliding tip only where it is
drawn; docs/model.md s2), plus,
once the skin is broken, the axial force of the layers the shaft is in (:mod:`haptic_acu.tissue.postpuncture`:
``needle.mechanics = "rich"``: cutting at the tip into uncut tissue + stick-point Karnopp shaft
friction + viscous friction, each per layer in proportion to the needle length in it;
``"table1"``: the paper's ``-(sum_k d_k h_k) v_axial a``), with h_k the physical needle length in
layer k, measured along the needle's axis from the rest boundaries (docs/model.md s3, s9).

Compression. When layer k breaks the tip is its dent depth below that layer's rest surface, and the
tissue beneath has been pushed down with it. The model keeps that compression as an offset ``o``
along the insertion axis: collision and depths use the tip lifted by ``o``. On withdrawal ``o`` never
exceeds the tip's depth below the entry point, so the skin is dragged back up with the needle (it
tents) and the needle leaves the tissue exactly when it is back at the entry point.

Axis and entry. When the skin breaks, the needle's axis is the device's (``TickIn.axis``) where it
knows it, else the direction of travel since the tip first crossed the rest skin surface; the entry
is where that line crosses the rest skin surface (:func:`haptic_acu.tissue.postpuncture.begin_insertion`).

Tracks and holes. Every insertion extends a track (entry, axis, per layer the arc-length range cut;
mechanics.py). A layer touched where a track opened it (half the needle's cross-section or more)
is entered straight (no surface force, no net); elsewhere the tip meets a new net. Every puncture
also records a hole (point, layer, axis) for display. Both persist across insertions.

Lateral constraint. Once the skin is pierced the tip is pulled back to the insertion line through
the entry point along the axis by a spring as stiff as the shaft is held (``lateral_stiffness``
times the inserted fraction of the needle), as a needle in tissue cannot slide sideways. Bone: a
penalty wall at the muscle/bone boundary.

The handle. No more of the needle than its length goes in: the needle's tip (``work.tip``, what
every phase, the sample row and so every output reads) is the device's, except that along the
insertion it stays at most the needle's length below the entry; a device further in has the
handle on the skin and is pulled back to the needle by a spring as stiff as the bone wall, out
along the axis (:func:`hold_at_handle`, :func:`handle_stop`).

Safety. A non-finite tip position or velocity gives zero force and latches a fault; the output is
always finite and its magnitude never exceeds ``force_limit``.

Threading (see :mod:`haptic_acu.session.engine`): each layer has two net buffers ("slots"). ``owner`` per slot
is FREE, SERVO_OWNS (pressing) or VISUAL_OWNS (springback after puncture). The servo builds into a slot it
owns or a free one, hands a slot over by setting owner 2 after copying the displaced positions onto the
curved surface, and never touches an owner-2 slot again unless both slots are owner 2, when it takes
the older one back (its generation counter changes, which tells the visual loop to drop it).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from . import state as ss
from ..tissue import shf
from .clamp import clamp_force
from .cptr import address_of as _address_of
from .cptr import i64p as _i64p
from .danger import DANGER, MAX_DANGER, danger_phase, danger_render, structure_rows
from ..tissue.forcenet import (NetArrays, NetParams, Springs, Surface, Topology, build_net, force_on, lattice,
                       n_particles, relax, ring_w_mean_deflection, sync_curved)
from ..tissue.mechanics import UNCUT, mech_params, puncture_threshold, rupture_fields
from ..tissue.netresponse import lay_field, lookup
from ..tissue.netresponse import pack as pack_tables
from ..tissue.netresponse import table_for
from ..tissue.postpuncture import begin_insertion, find_track, shaft_forces
from .state import (DIAG, FREE, MAX_HOLES, N_LAYERS, N_SLOTS, PRESSING, PUNCTURED, SERVO_OWNS,
                         STATE_NAMES, UNTOUCHED, VISUAL_OWNS, Model, State, TickIn)
from ..tissue.baselines import (BEM, FEM, KIND_CODES, MSM, baseline_response, baseline_slope, contact_for,
                                contact_release, contact_response, msm_release, msm_response)
from ..tissue.body import Tissue, boundary_radii_grad
from ..tissue.twirl import TwirlParams, WindState, wind_step
from ..tissue.twirl import params_from_config as twirl_params

SERVO_DT_S = 1e-3  # the servo period the model is built for (Session sets its own into params.dt)

__all__ = ["NeedleModel", "step_kernel", "step_entry", "surface_normal", "UNTOUCHED", "PRESSING", "PUNCTURED",
           "STATE_NAMES", "N_LAYERS", "N_SLOTS", "MAX_HOLES"]


@nb.njit(cache=True, nogil=True, _nrt=False)
def _surface_at(coeffs_k, lmax, ux, uy, uz):
    """Point (relative to the centre) of a radial SH surface in direction u (any length)."""
    th, ph, rr = shf.direction_of(ux, uy, uz, 0.0, 0.0, 0.0)
    r = shf.eval_point(coeffs_k, lmax, th, ph)
    return ux / rr * r, uy / rr * r, uz / rr * r


@nb.njit(cache=True, nogil=True, inline="always")
def tangents(ux, uy, uz):
    """Two unit tangents (t1, t2) orthogonal to the unit direction u and to each other (t1 from
    u x the x axis, or the y axis near it), as six floats."""
    if abs(ux) < 0.9:
        ax, ay, az = 1.0, 0.0, 0.0
    else:
        ax, ay, az = 0.0, 1.0, 0.0
    t1x = uy * az - uz * ay
    t1y = uz * ax - ux * az
    t1z = ux * ay - uy * ax
    m1 = math.sqrt(t1x * t1x + t1y * t1y + t1z * t1z)
    t1x /= m1
    t1y /= m1
    t1z /= m1
    return t1x, t1y, t1z, uy * t1z - uz * t1y, uz * t1x - ux * t1z, ux * t1y - uy * t1x


@nb.njit(cache=True, nogil=True, _nrt=False)
def surface_normal(coeffs_k, lmax, centre, p, out):
    """Outward unit normal of a radial SH surface at its point toward ``p`` (central differences
    along two tangents). Allocation-free."""
    dx = p[0] - centre[0]
    dy = p[1] - centre[1]
    dz = p[2] - centre[2]
    m = math.sqrt(dx * dx + dy * dy + dz * dz)
    dx /= m
    dy /= m
    dz /= m
    t1x, t1y, t1z, t2x, t2y, t2z = tangents(dx, dy, dz)
    h = 1e-4
    ax_, ay_, az_ = _surface_at(coeffs_k, lmax, dx + h * t1x, dy + h * t1y, dz + h * t1z)
    bx_, by_, bz_ = _surface_at(coeffs_k, lmax, dx - h * t1x, dy - h * t1y, dz - h * t1z)
    cx_, cy_, cz_ = _surface_at(coeffs_k, lmax, dx + h * t2x, dy + h * t2y, dz + h * t2z)
    ex_, ey_, ez_ = _surface_at(coeffs_k, lmax, dx - h * t2x, dy - h * t2y, dz - h * t2z)
    s1x = ax_ - bx_
    s1y = ay_ - by_
    s1z = az_ - bz_
    s2x = cx_ - ex_
    s2y = cy_ - ey_
    s2z = cz_ - ez_
    nx = s1y * s2z - s1z * s2y
    ny = s1z * s2x - s1x * s2z
    nz = s1x * s2y - s1y * s2x
    nm = math.sqrt(nx * nx + ny * ny + nz * nz)
    sgn = 1.0 if (nx * dx + ny * dy + nz * dz) > 0 else -1.0
    out[0] = sgn * nx / nm
    out[1] = sgn * ny / nm
    out[2] = sgn * nz / nm


# ---- views ------------------------------------------------------------------------------------------

@nb.njit(cache=True, nogil=True, inline="always")
def net_views(m, s, idx):
    """Slot ``idx`` (= 2*layer + slot)'s net: (xf, X0f, X0, x, rest, axis) views into the state."""
    lay = m.layout[0]
    n = n_particles_of(m, ss.net_layer(idx))
    n_all = lay.n_all[ss.net_layer(idx)]
    return NetArrays(s.pos[lay.xf[idx]:lay.xf[idx] + n], s.pos[lay.X0f[idx]:lay.X0f[idx] + n],
                     s.pos[lay.X0[idx]:lay.X0[idx] + n_all], s.pos[lay.x[idx]:lay.x[idx] + n_all],
                     s.rest[lay.rest[idx]:lay.rest[idx] + n], s.axes[idx])


@nb.njit(cache=True, nogil=True, inline="always")
def lattice_views(m, k):
    """Layer ``k``'s lattice: (nbr, ring, plane) rows of the force net and its margin."""
    lay = m.layout[0]
    t0 = lay.topo[k]
    t1 = t0 + lay.n_all[k]
    return Topology(m.nbr[t0:t1], m.ring[t0:t1], m.plane[t0:t1])


@nb.njit(cache=True, nogil=True, inline="always")
def springs_of(m, k):
    """Layer ``k``'s net constants as the force-net kernels take them."""
    lay = m.layer[k]
    return Springs(lay.w, lay.k_virtual, lay.k_surface, lay.spacing, lay.pretension)


@nb.njit(cache=True, nogil=True, inline="always")
def n_particles_of(m, k):
    w = m.layer[k].w
    return 1 + 3 * w * (w - 1)


# ---- the phases -------------------------------------------------------------------------------------

@nb.njit(cache=True, nogil=True, inline="always")
def check_input(inp, s, d):
    """A non-finite tip position, velocity or roll latches the fault; False while it is latched (zero force)."""
    sv = s.servo[0]
    for c in range(3):
        if not (math.isfinite(inp.p[c]) and math.isfinite(inp.v[c])):
            sv.fault = 1
    if not math.isfinite(inp.roll[0]):
        sv.fault = 1
    if sv.fault != 0:
        d.fault = 1.0
        return False
    return True


@nb.njit(cache=True, nogil=True, inline="always")
def lift_tip(s):
    """The needle's tip in the compressed tissue's frame: ``q = tip - offset * axis``."""
    sv = s.servo[0]
    wk = s.work[0]
    o = sv.offset
    for c in range(3):
        wk.q[c] = wk.tip[c] - o * sv.axis[c]


@nb.njit(cache=True, nogil=True, inline="always")
def device_tip(inp, s):
    """The needle's tip where the device puts it (``work.tip``, ``work.tip_v``): what every phase
    reads; :func:`hold_at_handle` holds it at the needle's length."""
    wk = s.work[0]
    for c in range(3):
        wk.tip[c] = inp.p[c]
        wk.tip_v[c] = inp.v[c]


@nb.njit(cache=True, nogil=True, inline="always")
def hold_at_handle(inp, m, s, s_p):
    """The needle is a real needle: no more of it than its length goes into the tissue. A device
    ``s_p`` along the insertion from the entry, past the needle's length L, puts the handle on the
    skin: the needle's tip stays L below the entry on the insertion line (``work.tip``: the device's
    tip moved back along the axis; its velocity without the part along the axis) and the device's
    excess goes into ``work.over`` (the stop's spring, :func:`handle_stop`). Returns the needle's
    depth, min(s_p, L)."""
    wk = s.work[0]
    length = m.params[0].needle_length
    over = s_p - length
    if over <= 0.0:
        return s_p
    a = s.servo[0].axis
    va = inp.v[0] * a[0] + inp.v[1] * a[1] + inp.v[2] * a[2]
    for c in range(3):
        wk.tip[c] = inp.p[c] - over * a[c]
        wk.tip_v[c] = inp.v[c] - va * a[c]
    wk.over = over
    return length


@nb.njit(cache=True, nogil=True, inline="always")
def track_entry(inp, m, s):
    """Depth along the insertion since the entry point (``work.s_p``: the needle's, held at its
    length by the handle, :func:`hold_at_handle`); back above the entry point the needle has left
    the tissue (the holes stay); on withdrawal the offset never exceeds that depth (the skin tents
    up with the needle). Lifts the tip."""
    sv = s.servo[0]
    wk = s.work[0]
    p = inp.p
    a = sv.axis
    e = sv.entry
    o = sv.offset
    if sv.inserted != 0:
        s_p = ((p[0] - e[0]) * a[0] + (p[1] - e[1]) * a[1] + (p[2] - e[2]) * a[2])
        if s_p < -1e-6:
            sv.inserted = 0
            sv.engaged = 0
            o = 0.0
            for k in range(N_LAYERS):
                sv.state[k] = UNTOUCHED
                sv.lengths[k] = 0.0
        else:
            s_p = hold_at_handle(inp, m, s, s_p)
            if o > s_p:
                o = max(s_p, 0.0)
        wk.s_p = s_p
    sv.offset = o
    lift_tip(s)


@nb.njit(cache=True, nogil=True, inline="always")
def tip_radii(m, s, k):
    """Every boundary's radius toward the lifted tip (``s.radii``) and the tip's own (``work.rho``);
    for a layer ``k`` < N_LAYERS (the front layer, the one a tick can press) also its rest surface's
    gradient on the unit sphere there (``work.gs``), from the same evaluation of the four surfaces.
    The centre itself has no direction (the contact point and the bone wall's push would divide by
    rho = 0): a tip exactly there is moved 1e-12 m onto the +z pole, the direction
    ``shf.direction_of`` gives the centre."""
    wk = s.work[0]
    lmax = m.params[0].lmax
    kg = k if k < N_LAYERS else -1
    rho = boundary_radii_grad(m.coeffs, lmax, m.centre, wk.q, s.radii, kg, wk.gs)
    if rho == 0.0:
        wk.q[2] = m.centre[2] + 1e-12
        rho = boundary_radii_grad(m.coeffs, lmax, m.centre, wk.q, s.radii, kg, wk.gs)
    wk.rho = rho


@nb.njit(cache=True, nogil=True, inline="always")
def front_layer(s):
    """The first layer not punctured (N_LAYERS: all), into ``work.front``."""
    sv = s.servo[0]
    front = N_LAYERS
    for k in range(N_LAYERS):
        if sv.state[k] != PUNCTURED:
            front = k
            break
    s.work[0].front = front


@nb.njit(cache=True, nogil=True, inline="always")
def contact_point(m, s, k):
    """Layer ``k``'s surface point radially toward the tip, into ``work.cpt``."""
    wk = s.work[0]
    for c in range(3):
        wk.cpt[c] = m.centre[c] + (wk.q[c] - m.centre[c]) / wk.rho * s.radii[k]


@nb.njit(cache=True, nogil=True, _nrt=False)
def take_slot(s, k):
    """The slot to build layer k's new net in: the one in use if the servo owns it, else a free
    one, else (both in springback) the older one."""
    sv = s.servo[0]
    cur = sv.slot[k]
    if sv.owner[k, cur] == SERVO_OWNS:
        return cur
    for sl in range(N_SLOTS):
        if sv.owner[k, sl] == FREE:
            return sl
    if sv.gen[k, 0] <= sv.gen[k, 1]:
        return 0
    return 1


@nb.njit(cache=True, nogil=True, _nrt=False)
def build_slot(m, s, k, idx):
    """Build slot ``idx``'s net of layer ``k`` at the contact point ``work.cpt`` (normal computed here)."""
    wk = s.work[0]
    lmax = m.params[0].lmax
    surface_normal(m.coeffs[k], lmax, m.centre, wk.cpt, wk.nrm)
    build_net(Surface(m.coeffs[k], lmax, m.centre), net_views(m, s, idx), lattice_views(m, k), springs_of(m, k),
              wk.cpt, wk.nrm)


@nb.njit(cache=True, nogil=True, _nrt=False)
def touch(inp, m, s, k):
    """First touch of layer ``k``: where an earlier pass opened it (a track, ``find_track``: straight
    in, PUNCTURED; through the skin that begins the insertion along the track) or onto a new net
    (PRESSING). The skin's first touch is kept (``servo.touch``: the direction of travel from there
    gives the axis). Returns the layer's new state."""
    sv = s.servo[0]
    contact_point(m, s, k)
    if k == 0:
        for c in range(3):
            sv.touch[c] = s.work[0].q[c]
    h = find_track(m, s, k)
    if h >= 0:
        sv.state[k] = PUNCTURED
        if k == 0:
            begin_insertion(inp, m, s, h)
        return PUNCTURED
    sl = take_slot(s, k)
    sv.slot[k] = sl
    sv.owner[k, sl] = SERVO_OWNS
    sv.gen[k, sl] += 1
    build_slot(m, s, k, ss.net_index(k, sl))
    sv.state[k] = PRESSING
    return PRESSING


@nb.njit(cache=True, nogil=True, inline="always")
def tip_on_net(s, X0f, ax):
    """The tip relative to N1's rest position (``work.r``) and N1's deflection along the axis
    (``work.dz1``); returns the squared lateral distance."""
    wk = s.work[0]
    rx = wk.q[0] - X0f[0, 0]
    ry = wk.q[1] - X0f[0, 1]
    rz = wk.q[2] - X0f[0, 2]
    dz1 = -(rx * ax[0] + ry * ax[1] + rz * ax[2])
    wk.r[0] = rx
    wk.r[1] = ry
    wk.r[2] = rz
    wk.dz1 = dz1
    return (rx + dz1 * ax[0]) ** 2 + (ry + dz1 * ax[1]) ** 2 + (rz + dz1 * ax[2]) ** 2


@nb.njit(cache=True, nogil=True, _nrt=False)
def recentre(m, s, k, idx, use_table):
    """The tip slid half a spacing sideways: rebuild the net under it (where it is drawn and, at a
    puncture, handed to springback). The force does not change: it is read with N1 at the tip's
    depth and no lateral offset, before and after. A swept net keeps its ring-mean deflection
    profile as the warm start."""
    wk = s.work[0]
    w = m.layer[k].w
    n = n_particles_of(m, k)
    ringk = lattice_views(m, k)[1]
    xf, X0f, X0, x, rl, ax = net_views(m, s, idx)
    if not use_table:
        for j in range(w):
            wk.wr[j] = 0.0
            wk.cnt[j] = 0.0
        for i in range(n):
            r_i = ringk[i] - 1
            wk.wr[r_i] += -((xf[i, 0] - X0f[i, 0]) * ax[0] + (xf[i, 1] - X0f[i, 1]) * ax[1]
                            + (xf[i, 2] - X0f[i, 2]) * ax[2])
            wk.cnt[r_i] += 1.0
    contact_point(m, s, k)
    build_slot(m, s, k, idx)
    s.servo[0].gen[k, ss.net_slot(idx)] += 1
    if not use_table:
        for i in range(n):
            r_i = ringk[i] - 1
            dz = wk.wr[r_i] / wk.cnt[r_i]
            for c in range(3):
                xf[i, c] = X0f[i, c] - dz * ax[c]


@nb.njit(cache=True, nogil=True, inline="always")
def depth_gradient(m, s, k):
    """The tip's depth below layer ``k``'s rest surface, d(q) = r_k(u) - |q - c| (radial, about the
    body's centre c; u the tip's direction), and the gradient of -d into ``work.gd``:
    grad(-d) = u - grad_S r_k(u) / |q - c|, grad_S r_k the surface gradient on the unit sphere, which
    ``tip_radii`` evaluated analytically with the radii (``work.gs``; ``k`` is the front layer).
    Returns d. The intact surface's force f(d) * grad(-d) is then the gradient of the potential
    -int_0^d f: conservative."""
    wk = s.work[0]
    rho = wk.rho
    for c in range(3):
        wk.gd[c] = (wk.q[c] - m.centre[c]) / rho - wk.gs[c] / rho
    return s.radii[k] - rho


@nb.njit(cache=True, nogil=True, inline="always")
def table_response(m, s, k, idx):
    """The tabulated net's static response with N1 held at the tip's depth ``work.dz1`` straight
    below its rest point (lateral offset 0): (N1's reaction along the axis, ring-w deflection). Its
    shape is laid onto the particles only when someone looks (the visual loop, from the tip kept in
    ``servo.slot_q``; the puncture hand-over)."""
    wk = s.work[0]
    fn, rw = lookup(m.tab, m.tmeta[k], 0.0, wk.dz1)
    for c in range(3):
        s.servo[0].slot_q[idx, c] = wk.q[c]
    return fn, rw


@nb.njit(cache=True, nogil=True, _nrt=False)
def sweep_net(m, s, k, idx, sweeps):
    """N1 held ``work.dz1`` straight below its rest point, ``sweeps`` relaxation sweeps of the net:
    (N1's reaction along the axis, ring-w deflection). N1 is then drawn at the tip."""
    sv = s.servo[0]
    wk = s.work[0]
    net = net_views(m, s, idx)
    topo = lattice_views(m, k)
    springs = springs_of(m, k)
    ax = net.axis
    for c in range(3):
        net.xf[0, c] = net.X0f[0, c] - wk.dz1 * ax[c]
    for it in range(sweeps):
        relax(net, topo, springs, sv.sweep[k] % 2)
        sv.sweep[k] += 1
    force_on(0, net, topo, springs, wk.fo)
    fn = wk.fo[0] * ax[0] + wk.fo[1] * ax[1] + wk.fo[2] * ax[2]
    rw = ring_w_mean_deflection(net, topo, springs.w)
    for c in range(3):
        net.xf[0, c] = wk.q[c]
    return fn, rw


@nb.njit(cache=True, nogil=True, _nrt=False)
def puncture(inp, m, s, d, k, idx, use_table):
    """Layer ``k`` breaks: its net goes to springback (shape laid, copied onto the curved surface,
    owner VISUAL_OWNS), the hole is recorded, a skin break fixes the entry point and axis, and the
    tissue beneath stays compressed by the dent (the offset grows; the tip is lifted again)."""
    sv = s.servo[0]
    wk = s.work[0]
    n = n_particles_of(m, k)
    net = net_views(m, s, idx)
    xf, X0f, ax = net.xf, net.X0f, net.axis
    sv.state[k] = PUNCTURED
    if use_table:
        lay_field(m.tab, m.tmeta[k], wk.dz1, n, X0f, ax, xf)
        for c in range(3):
            xf[0, c] = wk.q[c]
    sync_curved(net)
    sv.owner[k, ss.net_slot(idx)] = VISUAL_OWNS
    d.puncture = k
    if k == 0:
        # The insertion axis (the device's, else the direction of travel since the first touch,
        # else the net's inward normal), its entry on the rest skin surface, the track.
        for c in range(3):
            sv.axis[c] = -ax[c]
        begin_insertion(inp, m, s, -1)
    a = sv.axis
    hole = s.holes[sv.nholes % MAX_HOLES]
    for c in range(3):
        hole.point[c] = X0f[0, c]
        hole.axis[c] = a[c]
    hole.layer = k
    sv.nholes += 1
    # The tissue beneath stays pushed down by the dent (wk.dz1 along the net's normal): along the
    # axis that is dz1 / cos(axis, inward normal).
    cosn = -(a[0] * ax[0] + a[1] * ax[1] + a[2] * ax[2])
    if cosn < 0.2:
        cosn = 0.2
    comp = wk.dz1 / cosn
    if comp > 0.0:
        sv.offset += comp
    lift_tip(s)
    tip_radii(m, s, N_LAYERS)
    wk.front = k + 1


@nb.njit(cache=True, nogil=True, inline="always")
def surface_force(s, d, k, fn):
    """The pressed surface's force ``fn * grad(-d)`` (``work.gd``; a surface only pushes: fn >= 0),
    added to ``work.f``; its magnitude into ``d.f_surface``."""
    wk = s.work[0]
    if fn < 0.0:
        fn = 0.0
    g = wk.gd
    for c in range(3):
        wk.f[c] += fn * g[c]
    mag = fn * math.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
    d.f_surface = mag
    d.f_layer[k] = mag


@nb.njit(cache=True, nogil=True, inline="always")
def press(inp, m, s, d, k):
    """Layer ``k`` is being pressed (intact). The force is a function of the tip's position alone:
    the net's response with N1 at the tip's depth d below the layer's rest surface and no lateral
    offset (table or sweeps), along grad(-d) (:func:`depth_gradient`); the puncture test reads the
    same response. Lifted off (d <= 0): the net goes, nothing broke. The net is re-centred under
    the tip when it slid half a spacing away: that moves the drawn net, not the force."""
    sv = s.servo[0]
    wk = s.work[0]
    idx = ss.net_index(k, sv.slot[k])
    dep = s.radii[k] - wk.rho
    if dep <= 0.0:
        sv.state[k] = UNTOUCHED
        sv.owner[k, ss.net_slot(idx)] = FREE
        if m.params[0].kind == MSM:
            msm_release(m, s, k)
        elif m.params[0].kind == FEM or m.params[0].kind == BEM:
            contact_release(s)
        return
    X0f = net_views(m, s, idx)[1]
    ax = s.axes[idx]
    lat2 = tip_on_net(s, X0f, ax)
    sweeps = m.params[0].sweeps
    use_table = m.tmeta[k].nr > 0
    if lat2 > (0.5 * m.layer[k].spacing) ** 2:
        recentre(m, s, k, idx, use_table)
        sweeps *= 2
        tip_on_net(s, X0f, ax)
    wk.dz1 = dep
    depth_gradient(m, s, k)
    if m.params[0].kind == MSM:  # the MSM's lattice, one step (docs/model.md s12.2)
        fn, broke = msm_response(inp, m, s, k, idx, dep, ax)
        rw = 0.0
    elif m.params[0].kind == FEM or m.params[0].kind == BEM:  # the contact set on the disc (s12.6)
        fn, broke = contact_response(inp, m, s, k, idx, dep, ax)
        rw = 0.0
    elif m.params[0].kind != 0:  # a baseline model (docs/model.md s12); the net is only drawn
        fn, broke = baseline_response(inp, m, s, k, idx, dep, ax)
        rw = 0.0
    else:
        if use_table:
            fn, rw = table_response(m, s, k, idx)
        else:
            fn, rw = sweep_net(m, s, k, idx, sweeps)
        broke = rw > puncture_threshold(m.layer[k].threshold, wk.tip_v, ax, m.params[0])
    d.ringw = rw
    d.dz1 = dep
    if broke:
        puncture(inp, m, s, d, k, idx, use_table)
    else:
        surface_force(s, d, k, fn)


@nb.njit(cache=True, nogil=True, inline="always")
def front_contact(inp, m, s, d):
    """The front layer: first touch (hole or new net), then pressing."""
    k = s.work[0].front
    st = s.servo[0].state[k]
    if st == UNTOUCHED and s.radii[k] - s.work[0].rho >= 0.0:
        st = touch(inp, m, s, k)
    if st == PRESSING:
        press(inp, m, s, d, k)


@nb.njit(cache=True, nogil=True, inline="always")
def lateral_stiffness(m, s):
    """The lateral guidance's stiffness: ``k_lateral`` times the needle length in the tissue over the
    needle's length (every layer the shaft crosses holds it; ``k_lateral`` with the whole shaft in)."""
    sv = s.servo[0]
    held = sv.lengths[0] + sv.lengths[1] + sv.lengths[2]
    return m.params[0].k_lateral * min(held / m.params[0].needle_length, 1.0)


@nb.njit(cache=True, nogil=True, inline="always")
def lateral_guidance(inp, m, s, d):
    """A spring pulling the tip back to the insertion line through the entry point, as stiff as the
    shaft is held: ``k_lateral`` times the needle length in the tissue over the needle's length
    (every layer the shaft crosses holds it; ``k_lateral`` with the whole shaft in)."""
    sv = s.servo[0]
    wk = s.work[0]
    a = sv.axis
    p = wk.tip
    ex = p[0] - sv.entry[0]
    ey = p[1] - sv.entry[1]
    ez = p[2] - sv.entry[2]
    t = ex * a[0] + ey * a[1] + ez * a[2]
    lx = ex - t * a[0]
    ly = ey - t * a[1]
    lz = ez - t * a[2]
    kl = lateral_stiffness(m, s)
    wk.f[0] -= kl * lx
    wk.f[1] -= kl * ly
    wk.f[2] -= kl * lz
    d.f_lateral = kl * math.sqrt(lx * lx + ly * ly + lz * lz)


@nb.njit(cache=True, nogil=True, inline="always")
def post_puncture(inp, m, s, d):
    """Forces of a needle inside the tissue: along the axis (Table 1, or cutting and shaft friction:
    ``postpuncture.shaft_forces``), lateral guidance, and the depth below the skin (physical: along
    the axis from the entry on the rest skin surface)."""
    wk = s.work[0]
    shaft_forces(inp, m, s, d)
    if m.params[0].lateral_on != 0:
        lateral_guidance(inp, m, s, d)
    dep = wk.s_p
    d.depth_skin = dep if dep > 0.0 else 0.0


@nb.njit(cache=True, nogil=True, inline="always")
def handle_stop(m, s, d):
    """The handle on the skin: the needle's tip is held at the needle's length below the entry
    (:func:`hold_at_handle`) and the device, ``work.over`` further along the insertion, is pulled
    back to it by a spring as stiff as the bone wall (``k_bone``), out along the axis. The tissue's
    forces act at the needle's tip; this is the part the hand feels of the stop (with the device's
    limit, a stop the hand cannot push through)."""
    wk = s.work[0]
    over = wk.over
    if over > 0.0:
        a = s.servo[0].axis  # handle to tip: the stop pushes along -axis
        kh = m.params[0].k_bone
        for c in range(3):
            wk.f[c] -= kh * over * a[c]


@nb.njit(cache=True, nogil=True, inline="always")
def twirl_phase(inp, m, s, d):
    """The tissue wound around the shaft by the needle's roll (:func:`haptic_acu.tissue.twirl.wind_step`,
    per layer with the needle's length in it, ``servo.lengths`` from the post-puncture phase): the
    torque about the axis into ``d.torque``, each
    layer's grasp factor on its shaft friction into ``servo.grasp`` (docs/model.md section 11). Runs
    every tick: with the needle out every layer is unwound (grasp 1)."""
    sv = s.servo[0]
    pr = m.params[0]
    ws = WindState(sv.twist, sv.engage, sv.wind_len, sv.torque_layer, sv.grasp, sv.roll_play, sv.wind_primed)
    tp = TwirlParams(pr.k_twist, pr.twist_slip, pr.twist_tau, pr.engage_rad, pr.engage_tau, pr.grasp_coil,
                     pr.grasp_engage, pr.play_rad)
    d.torque = wind_step(ws, inp.roll[0], sv.lengths, pr.dt, tp)


@nb.njit(cache=True, nogil=True, inline="always")
def bone_wall(m, s, d):
    """A penalty wall at the muscle/bone boundary, once every layer is punctured."""
    wk = s.work[0]
    rho = wk.rho
    pen = s.radii[N_LAYERS] - rho
    if wk.front >= N_LAYERS and pen > 0.0:
        kb = m.params[0].k_bone
        for c in range(3):
            wk.f[c] += kb * pen * (wk.q[c] - m.centre[c]) / rho
        d.f_bone = kb * pen


@nb.njit(cache=True, nogil=True, inline="always")
def locate(s, d):
    """Where the tip is: ``d.layer`` (-1 outside, 3 bone; pressing a surface is not being inside
    that layer), ``d.depth`` into it, ``d.front``."""
    radii = s.radii
    rho = s.work[0].rho
    front = s.work[0].front
    layer = -1
    if rho <= radii[0]:
        layer = N_LAYERS
        for j in range(N_LAYERS):
            if rho > radii[j + 1]:
                layer = j
                break
    if layer > front - 1 and front < N_LAYERS:
        layer = front - 1
    # On the tick a layer breaks the lifted tip sits on that layer's rest surface, where rounding
    # alone would decide the side: the tip is in the layer it broke.
    broke = int(d.puncture)
    if broke >= 0 and layer < broke:
        layer = broke
    d.layer = layer
    if layer >= 0:
        dep = radii[layer] - rho
        if layer < N_LAYERS:
            thick = radii[layer] - radii[layer + 1]
            if dep > thick:
                dep = thick
        d.depth = dep if dep > 0.0 else 0.0
    d.front = front


@nb.njit(cache=True, nogil=True, inline="always")
def clamp(m, s, d):
    """The safety clamp (no fastmath here: isfinite must work): a non-finite force latches the
    fault and stays zero; a force above the limit is scaled to it. Writes ``d.force``."""
    f = s.work[0].f
    fx, fy, fz = f[0], f[1], f[2]
    if not (math.isfinite(fx) and math.isfinite(fy) and math.isfinite(fz)):
        s.servo[0].fault = 1
        d.fault = 1.0
        return
    # exact in floating point: never 1 ulp over the limit, the limit (not 0 N) for a huge force
    fx, fy, fz, c = clamp_force(fx, fy, fz, m.params[0].force_limit)
    if c > 0.0:
        d.clamped = 1.0
    d.force[0] = fx
    d.force[1] = fy
    d.force[2] = fz


# A swept (untabulated) net's stiffness along its axis for the rendering layer: an upper bound of
# the nets' 1.5 N/mm (skin) and 2.2 N/mm (muscle) at the break; an upper bound only slows
# the proxy (rendering.TissueLocal).
SWEPT_K_ALONG = 2500.0


@nb.njit(cache=True, nogil=True, inline="always")
def pressed_slope(m, s, k, idx):
    """The pressed surface's stiffness along grad(-d) (N/m) at the tip: the tabulated response's
    slope over one row ahead (the nets stiffen with depth, so ahead is the larger) times |grad d|^2,
    or :data:`SWEPT_K_ALONG` for a swept net."""
    if m.params[0].kind != 0:
        return baseline_slope(m, s, k)
    if m.tmeta[k].nr <= 0:
        return SWEPT_K_ALONG
    wk = s.work[0]
    dep = wk.dz1
    h = m.tmeta[k].h
    f0 = lookup(m.tab, m.tmeta[k], 0.0, dep)[0]
    f1 = lookup(m.tab, m.tmeta[k], 0.0, dep + h)[0]
    g = wk.gd
    slope = (f1 - f0) / h * (g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
    return slope if slope > 0.0 else 0.0


@nb.njit(cache=True, nogil=True, inline="always")
def render_local(m, s, d):
    """What a rendering layer linearises the tissue about (rendering.TissueLocal) into ``d.r_*``:
    the force without the shaft's friction and viscous parts (the cutting at the tip stays: it
    follows the tip's position), the axis (the insertion axis inside the tissue, a pressed net's
    axis before), the axial viscous coefficient (``d.axial_damping``: Table 1's sum in the paper's
    mode), the stiffness along it (a pressed net's table slope; the bone wall's) and across it (the
    lateral guidance, as the post-puncture phase scaled it), the shaft friction's breakaway level
    and a release flag (a puncture this tick)."""
    sv = s.servo[0]
    wk = s.work[0]
    along = 0.0
    across = 0.0
    for c in range(3):
        d.r_axis[c] = 0.0
    front = wk.front
    if front < N_LAYERS and sv.state[front] == PRESSING:
        idx = 2 * front + sv.slot[front]
        along = pressed_slope(m, s, front, idx)
        g = wk.gd
        gn = math.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
        for c in range(3):
            d.r_axis[c] = g[c] / gn
    if sv.inserted != 0:
        a = sv.axis
        for c in range(3):
            d.r_axis[c] = a[c]
        if m.params[0].lateral_on != 0:
            across = lateral_stiffness(m, s)
        if front >= N_LAYERS and s.radii[N_LAYERS] - wk.rho > -1e-3:
            along = max(along, m.params[0].k_bone)
        if wk.s_p - m.params[0].needle_length > -1e-3:  # the handle at (or near) the skin
            along = max(along, m.params[0].k_bone)
    shaft = d.f_damp - d.f_cut  # friction + viscous along +axis (Table 1's damping in the paper's mode)
    for c in range(3):
        d.r_force[c] = d.force[c] - shaft * d.r_axis[c]
    d.r_damping = d.axial_damping
    d.r_k_along = along
    d.r_k_across = across
    d.r_friction = d.breakaway
    d.r_released = 1.0 if d.puncture >= 0.0 else 0.0


@nb.njit(cache=True, nogil=True, _nrt=False)
def step_kernel(inp, m, s, out):
    """One servo tick. ``inp``: :class:`~haptic_acu.servo.state.TickIn` (tip position, m; velocity,
    m/s; scene frame); ``m``: the read-only :class:`~haptic_acu.servo.state.Model`; ``s``: the
    mutable :class:`~haptic_acu.servo.state.State`; ``out``: a one-row :data:`DIAG` record array,
    which receives the force on the needle (``force``) and the tick's diagnostics."""
    d = out[0]
    ss.clear(out)
    ss.clear(s.work)
    d.puncture = -1.0
    d.layer = -1.0
    s.servo[0].tick += 1
    device_tip(inp, s)
    if not check_input(inp, s, d):
        return
    track_entry(inp, m, s)
    front_layer(s)
    tip_radii(m, s, s.work[0].front)
    if s.work[0].front < N_LAYERS:
        front_contact(inp, m, s, d)
    if s.servo[0].inserted != 0:
        post_puncture(inp, m, s, d)
        handle_stop(m, s, d)
    twirl_phase(inp, m, s, d)
    bone_wall(m, s, d)
    danger_phase(inp, m, s, d)
    locate(s, d)
    clamp(m, s, d)
    render_local(m, s, d)
    danger_render(s, d)


@nb.njit(cache=True, nogil=True, _nrt=False)
def reset_servo(sv, keep_holes=False):
    """Fresh tissue (:meth:`NeedleModel.reset`; in compiled code a recording's ``reset`` event, the
    keyboard's ``r``): the needle out, every layer untouched, the insertion axis back to -z, nothing
    wound, the last output cleared; the holes and the insertion tracks too unless ``keep_holes``."""
    s = sv.state
    nholes = s.servo[0].nholes
    ss.clear(s.servo)
    s.servo[0].axis[2] = -1.0
    for k in range(s.servo[0].grasp.shape[0]):
        s.servo[0].grasp[k] = 1.0  # nothing wound: the shaft friction as it is
    if keep_holes:
        s.servo[0].nholes = nholes
    else:
        ss.clear(s.holes)
        s.tr_entry[:] = 0.0
        s.tr_axis[:] = 0.0
        s.tr_axis[:, 2] = -1.0
        s.tr_lo[:] = UNCUT
        s.tr_hi[:] = -UNCUT
        s.tr_count[:] = 0
    s.msm_qv[:, :] = 0.0  # the MSM's lattice at rest
    ss.clear(sv.out.diag)


_STEP_C = None


@nb.njit(cache=True, nogil=True, inline="always")
def step_servo(sv):
    """:func:`step_kernel` on a :class:`~haptic_acu.servo.state.Servo`."""
    step_kernel(sv.inp, sv.model, sv.state, sv.out.diag)


def step_entry():
    """:func:`step_kernel` as a C function ``void step(int64_t *table)`` (a cached numba cfunc):
    called through ctypes with one pointer it costs about half of a numba dispatch that checks and
    unboxes every array, which is most of a tick called from Python."""
    global _STEP_C
    if _STEP_C is None:
        key = ss.LAYOUT_KEY  # in the closure: a new layout is a new cache entry
        words = ss.HEADER + ss.SERVO_TABLE

        # Only plain values in the closure: numba's cache key hashes the closure's contents, and a
        # numba type or intrinsic there pickles differently in every process (a cache miss and a
        # recompile on every run). The helpers are module globals.
        @nb.cfunc(nb.types.void(nb.types.voidptr), nopython=True, cache=True)
        def step_c(data):
            t = nb.carray(_i64p(_address_of(data)), words)
            if ss.accept(t, key):
                step_servo(ss.unpack_servo(t, ss.HEADER))

        import ctypes

        _STEP_C = ctypes.CFUNCTYPE(None, ctypes.c_void_p)(step_c.address), step_c
    return _STEP_C[0]


class NeedleModel:
    """The layered needle-tissue model for one scene: owns every array the servo step touches, as
    the NamedTuples of :mod:`haptic_acu.servo.state` (``model``, ``state``, ``inp``, ``out``).

    ``step(p, v)`` runs one servo tick and returns the force on the needle (N, a view into
    ``diag``; copy it if you keep it). ``diag`` is the tick's :data:`~haptic_acu.servo.state.DIAG`
    record (``model.diag["puncture"]``). Build it once, call :meth:`warm_up` before real-time loops.
    """

    def __init__(self, cfg, tissue: Tissue | None = None):
        self.cfg = cfg
        self.tissue = tissue if tissue is not None else Tissue.from_config(cfg)
        t = self.tissue
        self.lmax = t.lmax
        self.coeffs = t.coeffs
        self.centre = t.centre
        self.params = [NetParams.from_layer(layer) for layer in cfg.layers]
        margin = cfg.springback.margin_rings
        self.lattices = [lattice(prm.w + margin) for prm in self.params]
        self.n = [n_particles(prm.w) for prm in self.params]
        self.n_all = [lat.ring.size for lat in self.lattices]
        # The servo's fast path: each layer's tabulated static net response (netresponse.py).
        tol = cfg.solver.static_tolerance_um * 1e-6
        self.tables = [table_for(prm, tol) if cfg.solver.servo_net == "table" else None for prm in self.params]
        tab, tmeta = pack_tables(self.tables, N_LAYERS)
        layout, rows, rest_rows = self._layout()
        contact = contact_for(cfg)  # the MSM's lattices' modes (a (1, 1) stand-in otherwise)
        msm_tab = np.ascontiguousarray(contact.msm_tab if contact is not None else np.zeros((1, 1)))
        # the FEM's / BEM's contact discs ((1, 1) stand-ins otherwise)
        ct = [np.ascontiguousarray(getattr(contact, f) if contact is not None else np.zeros((1, 1)))
              for f in ("ct_c", "ct_ref", "ct_h")]
        nodes = ct[0].shape[1]
        self.model = Model(coeffs=self.coeffs, centre=self.centre, layer=self._layer_params(cfg),
                           params=self._needle_params(cfg), layout=layout,
                           nbr=np.ascontiguousarray(np.concatenate([lat.nbr for lat in self.lattices])),
                           ring=np.ascontiguousarray(np.concatenate([lat.ring for lat in self.lattices])),
                           plane=np.ascontiguousarray(np.concatenate([lat.plane for lat in self.lattices])),
                           tab=tab, tmeta=tmeta, danger=np.zeros(MAX_DANGER, DANGER), msm=msm_tab,
                           ct_c=ct[0], ct_ref=ct[1], ct_h=ct[2])
        tr = (ss.MAX_TRACKS, 3)
        self.state = ss.zeros(State, pos=(rows, 3), rest=(rest_rows, 6), axes=(N_LAYERS * N_SLOTS, 3),
                              holes=(MAX_HOLES,), radii=(N_LAYERS + 1,), tr_entry=tr, tr_axis=tr, tr_lo=tr,
                              tr_hi=tr, dstate=(MAX_DANGER,), msm_qv=(2, msm_tab.shape[1]),
                              ct_p=(nodes, nodes), ct_f=(3, nodes), ct_i=(2, nodes))
        self.state.axes[:, 2] = 1.0
        self.inp = ss.zeros(TickIn, p=(3,), v=(3,), fr=(3,), axis=(3,), roll=(1,))
        self.inp.axis[:] = np.nan
        self.out = ss.zeros(ss.Out)
        self.servo = ss.Servo(self.inp, self.model, self.state, self.out)  # what a tick reads and writes
        self.rec = self.state.servo[0]  # the servo record (a view: reads see the servo's writes)
        self.diag = self.out.diag[0]  # the last tick's DIAG record (a view)
        self._force = self.out.diag["force"][0]  # its force (a view, made once: step() returns it)
        self._p, self._v, self._roll = self.inp.p, self.inp.v, self.inp.roll
        self._slot_views()
        self._step_c = None  # step()'s C entry point, bound on first use
        self.reset(keep_holes=False)

    @staticmethod
    def _layer_params(cfg) -> np.ndarray:
        lp = np.zeros(N_LAYERS, ss.LAYER)
        mp = mech_params(cfg.layers, cfg.needle)
        for k, layer in enumerate(cfg.layers):
            prm = NetParams.from_layer(layer)
            r = lp[k]
            for name, value in (("k_virtual", prm.k_virtual), ("k_surface", prm.k_surface), ("spacing", prm.spacing_m),
                                ("pretension", prm.pretension), ("threshold", prm.threshold_m), ("w", prm.w),
                                ("damping", layer.damping_n_s_per_m_per_mm * 1e3),
                                ("thickness", layer.thickness_mm * 1e-3), ("cut", mp.cut[k]), ("fs", mp.fs[k]),
                                ("fc", mp.fc[k]), ("visc", mp.b[k])):
                r[name] = value
        contact = contact_for(cfg)  # a baseline model's per-layer contact (None: the force net)
        if contact is not None:
            lp["bl_k"] = contact.stiffness
            lp["bl_crit"] = contact.crit_depth
            if cfg.model.kind == "msm":
                lp["msm_n"] = contact.msm_count
                lp["msm_g"] = contact.msm_g
                lp["msm_eps"] = cfg.model.msm_puncture_strain
            if len(contact.ct_n):
                lp["ct_n"] = contact.ct_n
                lp["ct_row"] = np.arange(N_LAYERS) * contact.ct_c.shape[1]
        return lp

    def _needle_params(self, cfg) -> np.ndarray:
        nd = cfg.needle
        mp = mech_params(cfg.layers, nd)
        prm = np.zeros(1, ss.PARAMS)
        r = prm[0]
        for name, value in (("lmax", self.lmax), ("lateral_on", 1 if nd.lateral_constraint else 0),
                            ("k_lateral", nd.lateral_stiffness_n_per_mm * 1e3),
                            ("k_bone", nd.bone_stiffness_n_per_mm * 1e3), ("force_limit", cfg.safety.force_limit_n),
                            ("sweeps", cfg.solver.sweeps_per_tick),
                            ("mechanics", ss.TABLE1 if nd.mechanics == "table1" else ss.RICH),
                            ("kind", KIND_CODES[cfg.model.kind]),
                            ("needle_radius", mp.radius), ("needle_length", mp.length), ("k_stick", mp.k_stick),
                            ("decay", mp.decay), ("dt", SERVO_DT_S)):
            r[name] = value
        tw = twirl_params(cfg.twirl, N_LAYERS)
        for name, value in (("k_twist", tw.k_twist), ("twist_slip", tw.twist_slip_rad), ("twist_tau", tw.twist_tau_s),
                            ("engage_rad", tw.engage_rad), ("engage_tau", tw.engage_tau_s),
                            ("grasp_coil", tw.grasp_coil), ("grasp_engage", tw.grasp_engage),
                            ("play_rad", tw.play_rad)):
            r[name] = value
        for name, value in rupture_fields(cfg.rupture):
            r[name] = value
        return prm

    def _layout(self):
        """Where each (layer, slot) net lives in the packed particle and rest-length storage."""
        lay = np.zeros(1, ss.LAYOUT)
        rows = 0
        rest_rows = 0
        for k in range(N_LAYERS):
            for sl in range(N_SLOTS):
                idx = ss.net_index(k, sl)
                for block, size in (("xf", self.n[k]), ("X0f", self.n[k]), ("X0", self.n_all[k]),
                                    ("x", self.n_all[k])):
                    lay[block][0, idx] = rows
                    rows += size
                lay["rest"][0, idx] = rest_rows
                rest_rows += self.n[k]
        lay["n_all"][0] = self.n_all
        lay["topo"][0] = np.concatenate([[0], np.cumsum(self.n_all)[:-1]])
        return lay, rows, rest_rows

    def _slot_views(self) -> None:
        """Per-slot views (xf, X0f, X0, x, rest_len, axes) and per-layer lattices, for the visual side."""
        lay = self.model.layout[0]
        pos = self.state.pos
        slots = range(N_LAYERS * N_SLOTS)

        def view(block, i, size):
            return pos[lay[block][i]:lay[block][i] + size]

        self.xf = tuple(view("xf", i, self.n[ss.net_layer(i)]) for i in slots)
        self.X0f = tuple(view("X0f", i, self.n[ss.net_layer(i)]) for i in slots)
        self.X0 = tuple(view("X0", i, self.n_all[ss.net_layer(i)]) for i in slots)
        self.x = tuple(view("x", i, self.n_all[ss.net_layer(i)]) for i in slots)
        self.rest_len = tuple(self.state.rest[lay["rest"][i]:lay["rest"][i] + self.n[ss.net_layer(i)]] for i in slots)
        self.axes = tuple(self.state.axes[i] for i in slots)
        self.nbr = tuple(lat.nbr for lat in self.lattices)
        self.ring = tuple(lat.ring for lat in self.lattices)
        self.plane = tuple(lat.plane for lat in self.lattices)

    def reset(self, keep_holes: bool = True) -> None:
        """Needle out, every layer untouched; holes kept unless ``keep_holes`` is False
        (:func:`reset_servo`, the one reset the compiled drivers run too)."""
        reset_servo(self.servo, bool(keep_holes))

    def set_structures(self, anatomy) -> None:
        """A point's danger structures (:func:`haptic_acu.tissue.patient.realise`) into
        ``model.danger`` (in place: a C entry point's table stays valid); None removes them."""
        if anatomy is None:
            self.model.danger[:] = np.zeros(1, DANGER)[0]
        else:
            structure_rows(anatomy, self.cfg.needle.bone_stiffness_n_per_mm, out=self.model.danger)
        self.state.dstate[:] = 0.0

    def kernel_args(self) -> tuple:
        """Everything :func:`step_kernel` takes: (inp, model, state, diag)."""
        return (self.inp, self.model, self.state, self.out.diag)

    def copy_state(self) -> tuple:
        """A copy of the mutable state (with the last tick's output), for :meth:`restore_state`."""
        return State(*(a.copy() for a in self.state)), self.out.diag.copy()

    def restore_state(self, snap) -> None:
        state, diag = snap
        for a, b in zip(self.state, state):
            a[...] = b
        self.out.diag[...] = diag

    def step(self, p, v, roll: float = 0.0, axis=None) -> np.ndarray:
        """One servo tick at tip position ``p`` (m) and velocity ``v`` (m/s), needle roll ``roll``
        (rad, cumulative) and ``axis`` (unit, handle to tip; None: unknown): the force (N). Calls
        :func:`step_kernel` through its C entry point (:func:`step_entry`)."""
        self.inp.p[:] = p
        self.inp.v[:] = v
        self.inp.axis[:] = np.nan if axis is None else axis
        self._roll[0] = roll
        if self._step_c is None:
            self._bind_step()
        else:
            self._step_c(self._step_arg)
        return self._force

    def _bind_step(self) -> None:
        from ctypes import c_void_p

        self._step_table = ss.address_table(self.servo)  # the arrays are never reallocated
        self._step_arg = c_void_p(self._step_table.ctypes.data)
        step_c = step_entry()
        step_c(self._step_arg)  # a tick at the current input; then the check that it ran
        if self._step_table[1] != 1:
            raise RuntimeError("haptic_acu.servo.step: the compiled servo step was built for another state layout "
                               "(stale numba cache): remove haptic_acu/__pycache__/*.nbi and *.nbc")
        self._step_c = step_c

    def warm_up(self) -> None:
        """Compile (or load from cache) every kernel the servo step calls, and the visual loop's
        read of a pressing net, then reset."""
        self.step(np.array([0.0, 0.0, 1e-3]), np.zeros(3))
        self.step(np.array([0.0, 0.0, -1e-4]), np.zeros(3))
        for k in range(N_LAYERS):
            if self.tables[k] is not None:
                self.pressed_net_flat(2 * k)
        self.reset(keep_holes=False)

    # -- read-outs ------------------------------------------------------------------------------
    @property
    def states(self) -> tuple[int, int, int]:
        return tuple(int(s) for s in self.rec["state"])

    @property
    def fault(self) -> bool:
        return bool(self.rec["fault"])

    @property
    def inserted(self) -> bool:
        return bool(self.rec["inserted"])

    @property
    def offset(self) -> float:
        return float(self.rec["offset"])

    @property
    def axis(self) -> np.ndarray:
        return self.rec["axis"].copy()

    @property
    def entry(self) -> np.ndarray:
        return self.rec["entry"].copy()

    @property
    def tip(self) -> np.ndarray:
        """The needle's tip after the last tick (m): the device's, but with the handle on the skin
        held at the needle's length below the entry along the insertion."""
        return self.state.work[0]["tip"].copy()

    @property
    def holes_list(self) -> np.ndarray:
        """The holes so far as HOLE records (``point``, ``layer``, ``axis``)."""
        return self.state.holes[: min(int(self.rec["nholes"]), MAX_HOLES)].copy()

    def active_slot(self, k: int) -> int:
        return ss.net_index(k, int(self.rec["slot"][k]))

    def owner(self, idx: int) -> int:
        return int(self.rec["owner"][ss.net_layer(idx), ss.net_slot(idx)])

    def generation(self, idx: int) -> int:
        return int(self.rec["gen"][ss.net_layer(idx), ss.net_slot(idx)])

    def pressed_net_flat(self, idx: int) -> np.ndarray:
        """Flat-lattice positions of a pressing (owner SERVO_OWNS) net: the relaxed particles, or for
        a tabulated net its equilibrium shape at the tip the servo last held N1 at."""
        k = ss.net_layer(idx)
        if self.tables[k] is None:
            return self.xf[idx].copy()
        n = self.n[k]
        q = self.rec["slot_q"][idx].copy()
        axis = self.axes[idx].copy()
        X0f = self.X0f[idx]
        out = np.empty((n, 3))
        lay_field(self.model.tab, self.model.tmeta[k], float(-((q - X0f[0]) @ axis)), n, X0f, axis, out)
        out[0] = q
        return out

    def net_positions(self, idx: int) -> np.ndarray:
        """Current curved-surface positions of slot ``idx``'s particles (force net + margin)."""
        k = ss.net_layer(idx)
        n = self.n[k]
        if self.owner(idx) == SERVO_OWNS:
            out = self.X0[idx].copy()
            out[:n] += self.pressed_net_flat(idx) - self.X0f[idx]
            return out
        return self.x[idx].copy()

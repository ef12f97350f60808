"""The needle in layered tissue: per-layer state machine, Table 1 forces, holes, safety.

One servo tick is one call of :func:`step_kernel` (numba, ``nogil``, allocation-free): SH collision
of the tip against all four boundaries, the pressed layer's force net, puncture, the damping of the
layers passed, the lateral constraint, the bone wall, and the safety clamp. :class:`NeedleModel` is the
thin Python object that owns the arrays.

States per layer and insertion site: UNTOUCHED -> PRESSING (a force net is active) -> PUNCTURED.
The needle presses at most one layer at a time, the first one not yet punctured (the "front").
Force on the needle (and so on the hand), Table 1:

    pressing layer k:  F_k (net reaction along its normal) + damping of the layers above
    inside layer k:    -(sum_{j<k} d_j h_j + d_k h) v_axial a        (a: insertion axis, into tissue)

with h_j the thickness of a passed layer and h the depth into the current one, d read per mm of
needle in the layer (MODEL.md section 3). Damping needs v along the axis and opposes it (it pulls
back on withdrawal).

Compression. When layer k breaks the tip is its dent depth below that layer's rest surface, and the
tissue beneath has been pushed down with it. The model keeps that compression as an offset ``o``
along the insertion axis: collision and depths use the tip lifted by ``o``. On withdrawal ``o`` never
exceeds the tip's depth below the entry point, so the skin is dragged back up with the needle (it
tents) and the needle leaves the tissue exactly when it is back at the entry point.

Holes. Every puncture records a hole (point on that layer's surface, layer, axis). When the tip
later touches a layer within ``hole_radius`` of one of its holes it goes straight in (no surface
force, no net); elsewhere it meets a new net. The hole list persists across insertions.

Lateral constraint. Once the skin is pierced the tip is pulled back to the insertion line through
the entry point along the axis by a spring (``lateral_stiffness``), as a needle in tissue cannot
slide sideways. Bone: a penalty wall at the muscle/bone boundary.

Safety. A non-finite tip position or velocity gives zero force and latches a fault; the output is
always finite and its magnitude never exceeds ``force_limit``.

Threading (see :mod:`haptic_acu.engine`): each layer has two net buffers ("slots"). ``owner`` per slot
is 0 free, 1 servo (pressing), 2 visual (springback after puncture). The servo builds into a slot it
owns or a free one, hands a slot over by setting owner 2 after copying the displaced positions onto the
curved surface, and never touches an owner-2 slot again unless both slots are owner 2, when it takes
the older one back (its generation counter changes, which tells the visual loop to drop it).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from . import shf
from .cptr import address_of, address_table, f64p, i64p
from .forcenet import (NetParams, build_net, force_on, lattice, n_particles, relax,
                       ring_w_mean_deflection, sync_curved)
from .netresponse import TM_NR, lay_field, lookup
from .netresponse import pack as pack_tables
from .netresponse import table_for
from .tissue import Tissue, boundary_radii

UNTOUCHED, PRESSING, PUNCTURED = 0, 1, 2
STATE_NAMES = ("untouched", "pressing", "punctured")
N_LAYERS = 3
N_SLOTS = 2
MAX_HOLES = 64

# layer parameter columns (lp[k, :])
LP_K, LP_KS, LP_L, LP_PRE, LP_THRESH, LP_W, LP_D, LP_THICK = range(8)
# needle parameter entries (npar[:])
NP_HOLE_R, NP_LAT_ON, NP_K_LAT, NP_K_BONE, NP_LIMIT, NP_SWEEPS = range(6)
# integer state (si[:])
SI_STATE = 0  # 3 entries: layer states
SI_SLOT = 3  # 3 entries: slot in use per layer
SI_OWNER = 6  # 6 entries: owner per (layer, slot)
SI_GEN = 12  # 6 entries: generation per (layer, slot)
SI_INSERTED = 18
SI_FAULT = 19
SI_NHOLES = 20
SI_SWEEP = 21  # 3 entries: sweep counters per layer (alternate sweep direction)
SI_TICK = 24
SI_SIZE = 25
# float state (sf[:])
SF_OFFSET = 0
SF_AXIS = 1  # 3
SF_ENTRY = 4  # 3
SF_SLOT_Q = 7  # 3 per slot: the (lifted) tip holding N1 of a tabulated pressing net (its shape is laid from it)
SF_SIZE = 7 + 3 * 6
# diagnostics out (diag[:])
D_FX, D_FY, D_FZ = 0, 1, 2
D_F_SURFACE = 3  # magnitude of the pressed layer's surface force (N)
D_F_DAMP = 4  # axial damping force (N, signed along -a)
D_F_LATERAL = 5
D_F_BONE = 6
D_LAYER = 7  # layer the tip is in: -1 outside, 0 skin, 1 fat, 2 muscle, 3 bone
D_DEPTH = 8  # depth into that layer (m)
D_FRONT = 9  # first layer not punctured (3: all)
D_RINGW = 10  # ring-w mean deflection of the pressed net (m)
D_DZ1 = 11  # N1 deflection of the pressed net (m)
D_PUNCTURE = 12  # layer punctured this tick, or -1
D_FAULT = 13
D_DEPTH_SKIN = 14  # tip depth below the skin along the insertion (effective, m)
D_CLAMPED = 15  # 1 if the safety clamp scaled the force this tick
D_F_LAYER = 16  # 3 entries: force attributed to each layer (surface or damping), N
D_SIZE = 19


@nb.njit(cache=True, nogil=True)
def _surface_at(coeffs_k, lmax, ux, uy, uz):
    """Point (relative to the centre) of a radial SH surface in direction u (any length)."""
    th, ph, rr = shf.direction_of(ux, uy, uz, 0.0, 0.0, 0.0)
    r = shf.eval_point(coeffs_k, lmax, th, ph)
    return ux / rr * r, uy / rr * r, uz / rr * r


@nb.njit(cache=True, nogil=True)
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
    if abs(dx) < 0.9:
        ax, ay, az = 1.0, 0.0, 0.0
    else:
        ax, ay, az = 0.0, 1.0, 0.0
    t1x = dy * az - dz * ay
    t1y = dz * ax - dx * az
    t1z = dx * ay - dy * ax
    m1 = math.sqrt(t1x * t1x + t1y * t1y + t1z * t1z)
    t1x /= m1
    t1y /= m1
    t1z /= m1
    t2x = dy * t1z - dz * t1y
    t2y = dz * t1x - dx * t1z
    t2z = dx * t1y - dy * t1x
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


@nb.njit(cache=True, nogil=True)
def _radii_at_tip(coeffs, lmax, centre, q, radii):
    """``boundary_radii`` for the (lifted) tip ``q``. The centre itself has no direction (the contact
    point and the bone wall's push would divide by rho = 0): a tip exactly there is moved 1e-12 m onto
    the +z pole, the direction ``shf.direction_of`` gives the centre."""
    rho = boundary_radii(coeffs, lmax, centre, q, radii)
    if rho == 0.0:
        q[2] = centre[2] + 1e-12
        rho = boundary_radii(coeffs, lmax, centre, q, radii)
    return rho


@nb.njit(cache=True, nogil=True)
def _take_slot(si, k):
    """Pick the slot to build layer k's new net in: the one in use if the servo owns it, else a free
    one, else (both in springback) the older one."""
    cur = si[SI_SLOT + k]
    if si[SI_OWNER + 2 * k + cur] == 1:
        return cur
    for s in range(N_SLOTS):
        if si[SI_OWNER + 2 * k + s] == 0:
            return s
    if si[SI_GEN + 2 * k] <= si[SI_GEN + 2 * k + 1]:
        return 0
    return 1


@nb.njit(cache=True, nogil=True)
def step_kernel(p, v, coeffs, lmax, centre, lp, npar, pos, rest_all, axes, nbr_all, ring_all, plane_all,
                offs, tab, tmeta, si, sf, holes, radii, scratch, diag):
    """One servo tick. ``p``/``v``: tip position (m) and velocity (m/s), scene frame. Writes the force
    on the needle into ``diag[0:3]`` and diagnostics into the rest of ``diag`` (see D_* indices).

    Every net lives in a few packed arrays (one call unboxes few arguments): ``pos`` holds, for each
    slot ``idx = 2*layer + slot``, the blocks xf, X0f (n rows) and X0, x (n_all rows) starting at
    ``offs[4*idx + 0..3]``; ``rest_all`` its rest lengths from ``offs[24 + idx]``; ``axes[idx]`` its
    axis; the lattice of layer k (``nbr_all``, ``ring_all``, ``plane_all``) starts at ``offs[30 + k]``
    and has ``offs[33 + k]`` rows. See :class:`NeedleModel` for the layout. ``tab``/``tmeta``: the
    layers' tabulated static responses (:mod:`haptic_acu.netresponse`); a layer whose
    ``tmeta[k, TM_NR]`` is 0 has none, and its net is relaxed by ``NP_SWEEPS`` sweeps per tick.
    """
    for i in range(D_SIZE):
        diag[i] = 0.0
    diag[D_PUNCTURE] = -1.0
    diag[D_LAYER] = -1.0
    si[SI_TICK] += 1
    # ---- safety: non-finite input latches a fault and zero force -------------------------------
    ok = True
    for k in range(3):
        if not (math.isfinite(p[k]) and math.isfinite(v[k])):
            ok = False
    if not ok:
        si[SI_FAULT] = 1
    if si[SI_FAULT] != 0:
        diag[D_FAULT] = 1.0
        return

    o = sf[SF_OFFSET]
    a0 = sf[SF_AXIS]
    a1 = sf[SF_AXIS + 1]
    a2 = sf[SF_AXIS + 2]
    inserted = si[SI_INSERTED] != 0
    s_p = 0.0
    if inserted:
        s_p = ((p[0] - sf[SF_ENTRY]) * a0 + (p[1] - sf[SF_ENTRY + 1]) * a1 + (p[2] - sf[SF_ENTRY + 2]) * a2)
        if s_p < -1e-6:
            # Back above the entry point: the needle has left the tissue. Holes stay.
            inserted = False
            si[SI_INSERTED] = 0
            o = 0.0
            for k in range(N_LAYERS):
                si[SI_STATE + k] = UNTOUCHED
        elif o > s_p:
            o = max(s_p, 0.0)  # withdrawal: the skin tents up with the needle
    sf[SF_OFFSET] = o
    q = scratch[0:3]
    q[0] = p[0] - o * a0
    q[1] = p[1] - o * a1
    q[2] = p[2] - o * a2

    rho = _radii_at_tip(coeffs, lmax, centre, q, radii)
    front = N_LAYERS
    for k in range(N_LAYERS):
        if si[SI_STATE + k] != PUNCTURED:
            front = k
            break
    fx = 0.0
    fy = 0.0
    fz = 0.0
    nrm = scratch[3:6]
    # ---- the front layer: contact, net, puncture --------------------------------------------------
    if front < N_LAYERS:
        k = front
        w = int(lp[k, LP_W])
        n = 1 + 3 * w * (w - 1)
        t0 = offs[30 + k]
        n_all = offs[33 + k]
        nbrk = nbr_all[t0:t0 + n_all]
        ringk = ring_all[t0:t0 + n_all]
        planek = plane_all[t0:t0 + n_all]
        st = si[SI_STATE + k]
        if st == UNTOUCHED and radii[k] - rho >= 0.0:
            # First touch of layer k: contact point on its surface radially toward the tip.
            cpt = scratch[6:9]
            for c in range(3):
                cpt[c] = centre[c] + (q[c] - centre[c]) / rho * radii[k]
            hole = -1
            hr2 = npar[NP_HOLE_R] * npar[NP_HOLE_R]
            for h in range(min(si[SI_NHOLES], MAX_HOLES)):
                if int(holes[h, 3]) == k:
                    d2 = (holes[h, 0] - cpt[0]) ** 2 + (holes[h, 1] - cpt[1]) ** 2 + (holes[h, 2] - cpt[2]) ** 2
                    if d2 <= hr2:
                        hole = h
                        break
            if hole >= 0:
                si[SI_STATE + k] = PUNCTURED
                st = PUNCTURED
                if k == 0:
                    inserted = True
                    si[SI_INSERTED] = 1
                    for c in range(3):
                        sf[SF_ENTRY + c] = holes[hole, c]
                        sf[SF_AXIS + c] = holes[hole, 4 + c]
                    a0 = sf[SF_AXIS]
                    a1 = sf[SF_AXIS + 1]
                    a2 = sf[SF_AXIS + 2]
            else:
                s = _take_slot(si, k)
                si[SI_SLOT + k] = s
                si[SI_OWNER + 2 * k + s] = 1
                si[SI_GEN + 2 * k + s] += 1
                idx = 2 * k + s
                surface_normal(coeffs[k], lmax, centre, cpt, nrm)
                build_net(coeffs[k], lmax, centre, cpt, nrm, lp[k, LP_L], planek, nbrk, n, lp[k, LP_PRE],
                          pos[offs[4 * idx + 2]:offs[4 * idx + 2] + n_all],
                          pos[offs[4 * idx + 3]:offs[4 * idx + 3] + n_all],
                          pos[offs[4 * idx + 1]:offs[4 * idx + 1] + n], pos[offs[4 * idx]:offs[4 * idx] + n],
                          rest_all[offs[24 + idx]:offs[24 + idx] + n], axes[idx])
                si[SI_STATE + k] = PRESSING
                st = PRESSING
        if st == PRESSING:
            s = si[SI_SLOT + k]
            idx = 2 * k + s
            ax = axes[idx]
            xfk = pos[offs[4 * idx]:offs[4 * idx] + n]
            X0fk = pos[offs[4 * idx + 1]:offs[4 * idx + 1] + n]
            X0k = pos[offs[4 * idx + 2]:offs[4 * idx + 2] + n_all]
            xk = pos[offs[4 * idx + 3]:offs[4 * idx + 3] + n_all]
            rlk = rest_all[offs[24 + idx]:offs[24 + idx] + n]
            # N1 follows the tip.
            rx = q[0] - X0fk[0, 0]
            ry = q[1] - X0fk[0, 1]
            rz = q[2] - X0fk[0, 2]
            dz1 = -(rx * ax[0] + ry * ax[1] + rz * ax[2])
            if dz1 <= 0.0:
                si[SI_STATE + k] = UNTOUCHED  # lifted off: the net goes, nothing broke
                si[SI_OWNER + idx] = 0
            else:
                lat2 = (rx + dz1 * ax[0]) ** 2 + (ry + dz1 * ax[1]) ** 2 + (rz + dz1 * ax[2]) ** 2
                sweeps = int(npar[NP_SWEEPS])
                use_table = tmeta[k, TM_NR] > 0.0
                if lat2 > (0.5 * lp[k, LP_L]) ** 2:
                    # Slid half a spacing sideways: re-centre the net under the tip, keeping its
                    # ring-mean deflection profile as the warm start.
                    # (A tabulated net needs no warm start: it is read at its new offset at once.)
                    wr = scratch[16:16 + w]
                    cnt = scratch[16 + 40:16 + 40 + w]
                    if not use_table:
                        for j in range(w):
                            wr[j] = 0.0
                            cnt[j] = 0.0
                        for i in range(n):
                            r_i = ringk[i] - 1
                            wr[r_i] += -((xfk[i, 0] - X0fk[i, 0]) * ax[0] + (xfk[i, 1] - X0fk[i, 1]) * ax[1]
                                         + (xfk[i, 2] - X0fk[i, 2]) * ax[2])
                            cnt[r_i] += 1.0
                    cpt = scratch[6:9]
                    for c in range(3):
                        cpt[c] = centre[c] + (q[c] - centre[c]) / rho * radii[k]
                    surface_normal(coeffs[k], lmax, centre, cpt, nrm)
                    build_net(coeffs[k], lmax, centre, cpt, nrm, lp[k, LP_L], planek, nbrk, n, lp[k, LP_PRE],
                              X0k, xk, X0fk, xfk, rlk, ax)
                    si[SI_GEN + idx] += 1
                    if not use_table:
                        for i in range(n):
                            r_i = ringk[i] - 1
                            dz = wr[r_i] / cnt[r_i]
                            for c in range(3):
                                xfk[i, c] = X0fk[i, c] - dz * ax[c]
                    sweeps *= 2
                    rx = q[0] - X0fk[0, 0]
                    ry = q[1] - X0fk[0, 1]
                    rz = q[2] - X0fk[0, 2]
                    dz1 = -(rx * ax[0] + ry * ax[1] + rz * ax[2])
                fn_table = 0.0
                if use_table:
                    # The net's static response at this (lateral offset, depth). Its shape is laid
                    # onto the particles only when someone looks: the visual loop (from the tip
                    # kept in sf, NeedleModel.net_positions) and the puncture hand-over below.
                    lat2 = (rx + dz1 * ax[0]) ** 2 + (ry + dz1 * ax[1]) ** 2 + (rz + dz1 * ax[2]) ** 2
                    fn_table, rw = lookup(tab, tmeta[k], lat2, dz1)
                    for c in range(3):
                        sf[SF_SLOT_Q + 3 * idx + c] = q[c]
                else:
                    for c in range(3):
                        xfk[0, c] = q[c]
                    for it in range(sweeps):
                        relax(xfk, X0fk, rlk, nbrk, ringk, n, w, ax, lp[k, LP_K], lp[k, LP_KS],
                              lp[k, LP_L], si[SI_SWEEP + k] % 2)
                        si[SI_SWEEP + k] += 1
                    rw = ring_w_mean_deflection(xfk, X0fk, ringk, n, w, ax)
                diag[D_RINGW] = rw
                diag[D_DZ1] = dz1
                if rw > lp[k, LP_THRESH]:
                    # Puncture: virtual springs go, surface force vanishes, net handed to springback.
                    si[SI_STATE + k] = PUNCTURED
                    if use_table:
                        lay_field(tab, tmeta[k], dz1, n, X0fk, ax, xfk)
                        for c in range(3):
                            xfk[0, c] = q[c]
                    sync_curved(xk, X0k, xfk, X0fk, n)
                    si[SI_OWNER + idx] = 2
                    diag[D_PUNCTURE] = k
                    if k == 0:
                        # The insertion axis: from the contact point to the tip at the break.
                        m = math.sqrt(rx * rx + ry * ry + rz * rz)
                        if m > 1e-4:
                            a0, a1, a2 = rx / m, ry / m, rz / m
                        else:
                            a0, a1, a2 = -ax[0], -ax[1], -ax[2]
                        sf[SF_AXIS] = a0
                        sf[SF_AXIS + 1] = a1
                        sf[SF_AXIS + 2] = a2
                        for c in range(3):
                            sf[SF_ENTRY + c] = X0fk[0, c]
                        inserted = True
                        si[SI_INSERTED] = 1
                    # Record the hole.
                    h = si[SI_NHOLES] % MAX_HOLES
                    for c in range(3):
                        holes[h, c] = X0fk[0, c]
                    holes[h, 3] = k
                    holes[h, 4] = a0
                    holes[h, 5] = a1
                    holes[h, 6] = a2
                    si[SI_NHOLES] += 1
                    # The tissue beneath stays compressed by the dent: lift the tip's frame.
                    comp = rx * a0 + ry * a1 + rz * a2
                    if comp > 0.0:
                        o += comp
                    sf[SF_OFFSET] = o
                    q[0] = p[0] - o * a0
                    q[1] = p[1] - o * a1
                    q[2] = p[2] - o * a2
                    rho = _radii_at_tip(coeffs, lmax, centre, q, radii)
                    front = k + 1
                else:
                    if use_table:
                        fn = fn_table
                    else:
                        fo = scratch[9:12]
                        force_on(0, xfk, X0fk, rlk, nbrk, ax, lp[k, LP_K], lp[k, LP_KS], fo)
                        fn = fo[0] * ax[0] + fo[1] * ax[1] + fo[2] * ax[2]
                    if fn < 0.0:
                        fn = 0.0  # a surface only pushes
                    fx += fn * ax[0]
                    fy += fn * ax[1]
                    fz += fn * ax[2]
                    diag[D_F_SURFACE] = fn
                    diag[D_F_LAYER + k] = fn

    # ---- damping of the layers passed (Table 1) --------------------------------------------------
    if inserted:
        v_ax = v[0] * a0 + v[1] * a1 + v[2] * a2
        total_d = 0.0
        for j in range(N_LAYERS):
            if si[SI_STATE + j] == PUNCTURED:
                h = radii[j] - rho
                thick = radii[j] - radii[j + 1]
                if h < 0.0:
                    h = 0.0
                if h > thick:
                    h = thick
                cj = lp[j, LP_D] * h
                total_d += cj
                diag[D_F_LAYER + j] += -cj * v_ax
        fd = -total_d * v_ax
        fx += fd * a0
        fy += fd * a1
        fz += fd * a2
        diag[D_F_DAMP] = fd
        # ---- lateral constraint ---------------------------------------------------------------------
        if npar[NP_LAT_ON] != 0.0:
            ex = p[0] - sf[SF_ENTRY]
            ey = p[1] - sf[SF_ENTRY + 1]
            ez = p[2] - sf[SF_ENTRY + 2]
            t = ex * a0 + ey * a1 + ez * a2
            lx = ex - t * a0
            ly = ey - t * a1
            lz = ez - t * a2
            kl = npar[NP_K_LAT]
            fx -= kl * lx
            fy -= kl * ly
            fz -= kl * lz
            diag[D_F_LATERAL] = kl * math.sqrt(lx * lx + ly * ly + lz * lz)
        diag[D_DEPTH_SKIN] = s_p - o if s_p - o > 0.0 else 0.0
    # ---- bone wall -------------------------------------------------------------------------------
    if front >= N_LAYERS and radii[3] - rho > 0.0:
        pen = radii[3] - rho
        kb = npar[NP_K_BONE]
        fx += kb * pen * (q[0] - centre[0]) / rho
        fy += kb * pen * (q[1] - centre[1]) / rho
        fz += kb * pen * (q[2] - centre[2]) / rho
        diag[D_F_BONE] = kb * pen

    # ---- where the tip is ----------------------------------------------------------------------
    layer = -1
    if rho <= radii[0]:
        layer = 3
        for j in range(N_LAYERS):
            if rho > radii[j + 1]:
                layer = j
                break
    if layer > front - 1 and front < N_LAYERS:
        layer = front - 1  # pressing a surface is not being inside that layer
    diag[D_LAYER] = layer
    if layer >= 0:
        dep = radii[layer] - rho
        if layer < N_LAYERS:
            thick = radii[layer] - radii[layer + 1]
            if dep > thick:
                dep = thick
        diag[D_DEPTH] = dep if dep > 0.0 else 0.0
    diag[D_FRONT] = front

    # ---- safety clamp (no fastmath here: isfinite must work) -----------------------------------
    if not (math.isfinite(fx) and math.isfinite(fy) and math.isfinite(fz)):
        si[SI_FAULT] = 1
        diag[D_FAULT] = 1.0
        return
    mag = math.sqrt(fx * fx + fy * fy + fz * fz)
    lim = npar[NP_LIMIT]
    if mag > lim:
        sc = lim / mag
        fx *= sc
        fy *= sc
        fz *= sc
        diag[D_CLAMPED] = 1.0
    diag[D_FX] = fx
    diag[D_FY] = fy
    diag[D_FZ] = fz


# step_kernel's model arrays (everything after p, v but lmax), in its order: what the C entry points
# (step_entry here, the OMNI callback in omniloop.py) read through an address table (cptr.py).
MODEL_ARRAYS = (("coeffs", np.float64, 2), ("centre", np.float64, 1), ("lp", np.float64, 2), ("npar", np.float64, 1),
                ("pos", np.float64, 2), ("rest_all", np.float64, 2), ("axes", np.float64, 2),
                ("nbr_all", np.int64, 2), ("ring_all", np.int64, 1), ("plane_all", np.float64, 2),
                ("offs", np.int64, 1), ("tab", np.float64, 1), ("tmeta", np.float64, 2), ("si", np.int64, 1),
                ("sf", np.float64, 1), ("holes", np.float64, 2), ("radii", np.float64, 1),
                ("scratch", np.float64, 1), ("diag", np.float64, 1))
STEP_ARRAYS = (("p", np.float64, 1), ("v", np.float64, 1)) + MODEL_ARRAYS


@nb.njit(cache=True, nogil=True)
def model_views(t, b):
    """The :data:`MODEL_ARRAYS` of an address table ``t`` whose entry ``b`` is ``coeffs``, as arrays."""
    o = 3 * b
    return (nb.carray(f64p(t[o]), (t[o + 1], t[o + 2])), nb.carray(f64p(t[o + 3]), t[o + 4]),
            nb.carray(f64p(t[o + 6]), (t[o + 7], t[o + 8])), nb.carray(f64p(t[o + 9]), t[o + 10]),
            nb.carray(f64p(t[o + 12]), (t[o + 13], t[o + 14])), nb.carray(f64p(t[o + 15]), (t[o + 16], t[o + 17])),
            nb.carray(f64p(t[o + 18]), (t[o + 19], t[o + 20])), nb.carray(i64p(t[o + 21]), (t[o + 22], t[o + 23])),
            nb.carray(i64p(t[o + 24]), t[o + 25]), nb.carray(f64p(t[o + 27]), (t[o + 28], t[o + 29])),
            nb.carray(i64p(t[o + 30]), t[o + 31]), nb.carray(f64p(t[o + 33]), t[o + 34]),
            nb.carray(f64p(t[o + 36]), (t[o + 37], t[o + 38])), nb.carray(i64p(t[o + 39]), t[o + 40]),
            nb.carray(f64p(t[o + 42]), t[o + 43]), nb.carray(f64p(t[o + 45]), (t[o + 46], t[o + 47])),
            nb.carray(f64p(t[o + 48]), t[o + 49]), nb.carray(f64p(t[o + 51]), t[o + 52]),
            nb.carray(f64p(t[o + 54]), t[o + 55]))


_STEP_C = None


def step_entry():
    """:func:`step_kernel` as a C function ``void step(int64_t *table, int64_t lmax)`` (a cached numba
    cfunc): called through ctypes with one pointer it costs about half of a numba dispatch that
    checks and unboxes 22 arrays, which is most of a tick called from Python."""
    global _STEP_C
    if _STEP_C is None:
        from numba import types

        @nb.cfunc(types.void(types.voidptr, types.int64), nopython=True, cache=True)
        def step_c(data, lmax):
            t = nb.carray(i64p(address_of(data)), 3 * len(STEP_ARRAYS))
            m = model_views(t, 2)
            step_kernel(nb.carray(f64p(t[0]), t[1]), nb.carray(f64p(t[3]), t[4]), m[0], lmax, m[1], m[2], m[3],
                        m[4], m[5], m[6], m[7], m[8], m[9], m[10], m[11], m[12], m[13], m[14], m[15], m[16], m[17],
                        m[18])

        import ctypes

        _STEP_C = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_int64)(step_c.address), step_c
    return _STEP_C[0]


class NeedleModel:
    """The layered needle-tissue model for one scene: owns every array the servo step touches.

    ``step(p, v)`` runs one servo tick and returns the force on the needle (N, a view into
    ``diag``; copy it if you keep it). Build it once, call :meth:`warm_up` before real-time loops.
    """

    def __init__(self, cfg, tissue: Tissue | None = None):
        self.cfg = cfg
        self.tissue = tissue if tissue is not None else Tissue.from_config(cfg)
        t = self.tissue
        self.lmax = t.lmax
        self.coeffs = t.coeffs
        self.centre = t.centre
        self.params = [NetParams.from_layer(layer) for layer in cfg.layers]
        self.lp = np.zeros((N_LAYERS, 8))
        for k, (layer, prm) in enumerate(zip(cfg.layers, self.params)):
            self.lp[k] = [prm.k_virtual, prm.k_surface, prm.spacing_m, prm.pretension, prm.threshold_m,
                          prm.w, layer.damping_n_s_per_m_per_mm * 1e3, layer.thickness_mm * 1e-3]
        nd = cfg.needle
        self.npar = np.array([nd.hole_radius_mm * 1e-3, 1.0 if nd.lateral_constraint else 0.0,
                              nd.lateral_stiffness_n_per_mm * 1e3, nd.bone_stiffness_n_per_mm * 1e3,
                              cfg.safety.force_limit_n, float(cfg.solver.sweeps_per_tick)])
        margin = cfg.springback.margin_rings
        self.lattices = [lattice(prm.w + margin) for prm in self.params]
        self.n = [n_particles(prm.w) for prm in self.params]
        # Packed storage (see step_kernel); the tuples below are views into it.
        self.n_all = [lat.ring.size for lat in self.lattices]
        self.offs = np.zeros(36, dtype=np.int64)
        rows = 0
        rl_rows = 0
        for k in range(N_LAYERS):
            for s in range(N_SLOTS):
                idx = 2 * k + s
                for b, size in enumerate((self.n[k], self.n[k], self.n_all[k], self.n_all[k])):
                    self.offs[4 * idx + b] = rows
                    rows += size
                self.offs[24 + idx] = rl_rows
                rl_rows += self.n[k]
        topo = 0
        for k in range(N_LAYERS):
            self.offs[30 + k] = topo
            self.offs[33 + k] = self.n_all[k]
            topo += self.n_all[k]
        self.pos = np.zeros((rows, 3))
        self.rest_all = np.zeros((rl_rows, 6))
        self.axes_all = np.zeros((N_LAYERS * N_SLOTS, 3))
        self.axes_all[:, 2] = 1.0
        self.nbr_all = np.ascontiguousarray(np.concatenate([lat.nbr for lat in self.lattices]))
        self.ring_all = np.ascontiguousarray(np.concatenate([lat.ring for lat in self.lattices]))
        self.plane_all = np.ascontiguousarray(np.concatenate([lat.plane for lat in self.lattices]))
        o = self.offs

        def view(idx, b, size):
            return self.pos[o[4 * idx + b]:o[4 * idx + b] + size]

        slots = range(N_LAYERS * N_SLOTS)
        self.xf = tuple(view(i, 0, self.n[i // 2]) for i in slots)
        self.X0f = tuple(view(i, 1, self.n[i // 2]) for i in slots)
        self.X0 = tuple(view(i, 2, self.n_all[i // 2]) for i in slots)
        self.x = tuple(view(i, 3, self.n_all[i // 2]) for i in slots)
        self.rest_len = tuple(self.rest_all[o[24 + i]:o[24 + i] + self.n[i // 2]] for i in slots)
        self.axes = tuple(self.axes_all[i] for i in slots)
        self.nbr = tuple(lat.nbr for lat in self.lattices)
        self.ring = tuple(lat.ring for lat in self.lattices)
        self.plane = tuple(lat.plane for lat in self.lattices)
        self.si = np.zeros(SI_SIZE, dtype=np.int64)
        self.sf = np.zeros(SF_SIZE)
        self.holes = np.zeros((MAX_HOLES, 7))
        self.radii = np.zeros(4)
        # The servo's fast path: each layer's tabulated static net response (netresponse.py).
        tol = cfg.solver.static_tolerance_um * 1e-6
        self.tables = [table_for(prm, tol) if cfg.solver.servo_net == "table" else None for prm in self.params]
        self.tab, self.tmeta = pack_tables(self.tables, N_LAYERS)
        self.scratch = np.zeros(16 + 80)
        self.diag = np.zeros(D_SIZE)
        self._p = np.zeros(3)
        self._v = np.zeros(3)
        self._step_c = None  # step()'s C entry point, bound on first use
        self.reset(keep_holes=False)

    def reset(self, keep_holes: bool = True) -> None:
        """Needle out, every layer untouched; holes kept unless ``keep_holes`` is False."""
        nh = self.si[SI_NHOLES]
        self.si[:] = 0
        self.sf[:] = 0.0
        self.sf[SF_AXIS + 2] = -1.0
        if keep_holes:
            self.si[SI_NHOLES] = nh
        else:
            self.holes[:] = 0.0
        self.diag[:] = 0.0

    def model_arrays(self) -> dict:
        """The model's arrays by their :data:`MODEL_ARRAYS` names, in that order (what the C entry
        points' address tables hold, and :func:`step_kernel`'s arguments but ``lmax``)."""
        return dict(coeffs=self.coeffs, centre=self.centre, lp=self.lp, npar=self.npar, pos=self.pos,
                    rest_all=self.rest_all, axes=self.axes_all, nbr_all=self.nbr_all, ring_all=self.ring_all,
                    plane_all=self.plane_all, offs=self.offs, tab=self.tab, tmeta=self.tmeta, si=self.si,
                    sf=self.sf, holes=self.holes, radii=self.radii, scratch=self.scratch, diag=self.diag)

    def kernel_args(self) -> tuple:
        """Everything :func:`step_kernel` takes after ``p, v``, in order."""
        coeffs, *rest = self.model_arrays().values()
        return (coeffs, self.lmax, *rest)

    def step(self, p, v) -> np.ndarray:
        """One servo tick at tip position ``p`` (m) and velocity ``v`` (m/s): the force (N).
        Calls :func:`step_kernel` through its C entry point (:func:`step_entry`)."""
        self._p[:] = p
        self._v[:] = v
        if self._step_c is None:
            self._bind_step()
        self._step_c(self._step_arg, self.lmax)
        return self.diag[0:3]

    def _bind_step(self) -> None:
        from ctypes import c_void_p

        arrays = dict(p=self._p, v=self._v, **self.model_arrays())
        self._step_table = address_table(arrays, STEP_ARRAYS)  # the arrays are never reallocated
        self._step_arg = c_void_p(self._step_table.ctypes.data)
        self._step_c = step_entry()

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
        return tuple(int(s) for s in self.si[SI_STATE:SI_STATE + N_LAYERS])

    @property
    def fault(self) -> bool:
        return bool(self.si[SI_FAULT])

    @property
    def inserted(self) -> bool:
        return bool(self.si[SI_INSERTED])

    @property
    def axis(self) -> np.ndarray:
        return self.sf[SF_AXIS:SF_AXIS + 3].copy()

    @property
    def entry(self) -> np.ndarray:
        return self.sf[SF_ENTRY:SF_ENTRY + 3].copy()

    @property
    def holes_list(self) -> np.ndarray:
        return self.holes[: min(int(self.si[SI_NHOLES]), MAX_HOLES)].copy()

    def active_slot(self, k: int) -> int:
        return 2 * k + int(self.si[SI_SLOT + k])

    def owner(self, idx: int) -> int:
        return int(self.si[SI_OWNER + idx])

    def generation(self, idx: int) -> int:
        return int(self.si[SI_GEN + idx])

    def pressed_net_flat(self, idx: int) -> np.ndarray:
        """Flat-lattice positions of a pressing (owner 1) net: the relaxed particles, or for a
        tabulated net its equilibrium shape at the tip the servo last held N1 at."""
        k = idx // 2
        if self.tables[k] is None:
            return self.xf[idx].copy()
        n = self.n[k]
        q = self.sf[SF_SLOT_Q + 3 * idx:SF_SLOT_Q + 3 * idx + 3].copy()
        axis = self.axes[idx].copy()
        X0f = self.X0f[idx]
        out = np.empty((n, 3))
        lay_field(self.tab, self.tmeta[k], float(-((q - X0f[0]) @ axis)), n, X0f, axis, out)
        out[0] = q
        return out

    def net_positions(self, idx: int) -> np.ndarray:
        """Current curved-surface positions of slot ``idx``'s particles (force net + margin)."""
        k = idx // 2
        n = self.n[k]
        if self.owner(idx) == 1:
            out = self.X0[idx].copy()
            out[:n] += self.pressed_net_flat(idx) - self.X0f[idx]
            return out
        return self.x[idx].copy()

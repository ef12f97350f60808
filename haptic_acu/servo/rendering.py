"""The rendering layer between the tissue simulation and a force device (numba kernels, SI units).

The simulation computes the tissue's force on a *proxy* (the virtual needle tip); the device is tied
to the proxy by a virtual coupling, a spring-damper whose stiffness and damping stay within the
device's nominal maxima (Colgate, Stanley & Brown 1995; Adams & Hannaford 1999). The proxy is
massless and is moved once per tick by an implicit (backward-Euler) step of

    0 = f_tissue(x_p, v_p) + K (x_d - x_p) + B (v_d - v_p)

with the tissue force linearised about the proxy's last position from what the tissue step
reports there (:class:`TissueLocal`, which also flags a puncture: see ``released``): its position-dependent force, and along its axis a damping
coefficient, a stiffness and a Coulomb friction level, and a stiffness across the axis. Solved
per direction in closed form, with the friction as a set-valued (stick/slip) term, so a tissue
damping of 93 N*s/m or a stiff stick-slip friction cannot make the update unstable, however large.
The device feels ``K (x_p - x_d) + B (v_p - v_d)``: with a massless proxy exactly the linearised
tissue force at the proxy's new position, low-passed in the way a spring in series with the
tissue passes it.

The device's velocity comes from a first-order adaptive window estimate (Janabi-Sharifi, Hayward &
Chen 2000, "end-fit" FOAW): the longest window, up to ``HIST`` ticks, over which the straight line
through its two end positions passes within one encoder step of every position in it. A still
hand gets a long window (a near-zero velocity), a fast one a short window (little lag); never a
raw one-tick difference of quantised positions.

Output safety (always, in this order): a fault (latched in the state, or a non-finite input)
gives zero force that very tick; the force is clamped to the device's maximum; a sustained force
above the device's continuous limit is ramped down: the RMS of the demanded force over a time
constant ``continuous_tau_s`` (motor heating goes with the current squared) sets a target scale
``min(1, F_cont / F_rms)`` that the output scale follows at no more than ``ramp_per_s`` per second,
down and back up; the status flag LIMITING says so while the scale is below one.

Kernels are ``nogil``, ``cache``, never ``fastmath``; :func:`render_step` is callable from a
compiled servo tick.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

HIST = 48  # device positions kept for the velocity estimate (ticks)

# render_step status bits
CLAMPED = 1  # the force was clamped to the device's maximum
LIMITING = 2  # the continuous-force protection is scaling the force down
FAULT = 4  # a fault: the force is zero

AUX_DTYPE = np.dtype([("n_hist", np.int64), ("head", np.int64), ("initialised", np.int64), ("fault", np.int64),
                      ("f_sq_avg", np.float64), ("scale", np.float64), ("status", np.int64),
                      ("off_x", np.float64), ("off_y", np.float64), ("off_z", np.float64)])  # release offset (m)

# After a release the coupling's anchor (the device shifted by the release offset) rejoins the device
# at this speed: the proxy catches up no faster than the hand plus this, so the tissue (and a replay
# of the recorded proxy path) sees a velocity a hand could have, not a jump over one tick. Ours:
# a fifth of the 25 mm/s a fine needle is pushed at most in the bundled sessions; 1.2 mm (a firm
# grip's compression at the muscle's break) is spent in about 0.2 s.
RELEASE_CATCH_UP_M_S = 5e-3


class DeviceLimits(NamedTuple):
    """What the device can render, read at run time (SI)."""
    max_force_n: float
    continuous_force_n: float
    stiffness_n_per_m: float
    damping_n_s_per_m: float


def limits_from_hd(max_force_n: float, continuous_force_n: float, stiffness_n_per_mm: float,
                   damping_n_per_mm_s: float) -> DeviceLimits:
    """:class:`DeviceLimits` from the HD API's HD_NOMINAL_MAX_FORCE, _CONTINUOUS_FORCE (N),
    _STIFFNESS (N/mm) and _DAMPING (N/(mm/s)). Raises ValueError on a value that is not positive."""
    vals = (float(max_force_n), float(continuous_force_n), float(stiffness_n_per_mm) * 1e3,
            float(damping_n_per_mm_s) * 1e3)
    for name, v in zip(DeviceLimits._fields, vals):
        if not (math.isfinite(v) and v > 0.0):
            raise ValueError(f"device limit {name} = {v!r}: expected a positive number")
    return DeviceLimits(*vals)


class CouplingParams(NamedTuple):
    """The virtual coupling and the output protection. Stiffness and damping are requests: the
    kernel uses at most the device's nominal maxima."""
    stiffness_n_per_m: float
    damping_n_s_per_m: float
    encoder_step_m: float  # the velocity estimate's tolerance: one encoder step
    continuous_tau_s: float  # time constant of the force's running RMS
    ramp_per_s: float  # how fast the continuous-force scale may change
    dt_s: float


# The limits and the coupling's parameters as one record, as the compiled ticks read them (the OMNI
# callback's ``rlim``, the scripted device's model's ``prm``), in the scene frame; on = 0: no layer.
LIMITS = np.dtype([("on", "f8"), ("max_force", "f8"), ("cont_force", "f8"), ("k_max", "f8"), ("b_max", "f8"),
                   ("k", "f8"), ("b", "f8"), ("enc", "f8"), ("tau", "f8"), ("ramp", "f8"), ("dt", "f8")])


def limits_record(limits: DeviceLimits, p: CouplingParams, on: bool = True) -> np.ndarray:
    """A (1,) :data:`LIMITS` record of ``limits`` and the coupling parameters ``p``."""
    out = np.zeros(1, LIMITS)
    r = out[0]
    for name, value in (("on", 1.0 if on else 0.0), ("max_force", limits.max_force_n),
                        ("cont_force", limits.continuous_force_n), ("k_max", limits.stiffness_n_per_m),
                        ("b_max", limits.damping_n_s_per_m), ("k", p.stiffness_n_per_m), ("b", p.damping_n_s_per_m),
                        ("enc", p.encoder_step_m), ("tau", p.continuous_tau_s), ("ramp", p.ramp_per_s), ("dt", p.dt_s)):
        r[name] = value
    return out


def default_params(limits: DeviceLimits, dt_s: float = 1e-3, encoder_step_m: float = 0.055e-3) -> CouplingParams:
    """Half the device's nominal stiffness and damping (a margin below where OpenHaptics says the
    device buzzes), a 5 s RMS window (a motor's windings heat over seconds: a puncture's 1.5 N peak
    is not sustained force) and a ramp of 0.5 per second."""
    return check_params(CouplingParams(0.5 * limits.stiffness_n_per_m, 0.5 * limits.damping_n_s_per_m,
                                       encoder_step_m, 5.0, 0.5, dt_s))


def check_params(params: CouplingParams) -> CouplingParams:
    """``params`` if every field is finite and positive (the encoder step may be 0: exact
    positions); else ValueError naming the field."""
    for name, v in zip(CouplingParams._fields, params):
        v = float(v)
        if not math.isfinite(v) or v < 0.0 or (v == 0.0 and name != "encoder_step_m"):
            raise ValueError(f"coupling parameter {name} = {v!r}: expected a positive number")
    return params


class TissueLocal(NamedTuple):
    """What the tissue step reports at the proxy (evaluated at its last position and velocity).

    ``force``: the position-dependent part of the tissue's force on the proxy (N; without the
    damping and friction below). ``axis``: unit vector the next three act along (the insertion
    axis inside tissue, a pressed net's axis; zeros: none, then ``stiffness_across`` acts in every
    direction). ``damping``: N*s/m along the axis; ``stiffness_along``/``stiffness_across``: N/m
    (an upper bound is safe: it only slows the proxy); ``friction``: Coulomb level along the axis (N).
    ``released``: 1.0 when the tissue let go this tick (a puncture). The coupling spring's
    compression along the axis (a rendering artefact: the device is deeper than a rigid needle would
    be) is relaxed at once by offsetting its anchor (:func:`anchor_point`), so the drop is felt
    within the tick, and for this one proxy step the tissue's damping and friction are left out; the
    proxy does not jump: the offset shrinks at :data:`RELEASE_CATCH_UP_M_S`, so the tissue, and a
    replay of the recorded proxy path, never see a catch-up faster than the hand plus that (a
    one-tick jump of the compression, 0.35 mm with a firm grip at the muscle's break, put -8 N of
    viscous shaft friction, clamped, into the simulated force). Relaxing a spring and dropping a
    dissipative term for one step store no energy: passive.
    """
    force: np.ndarray
    axis: np.ndarray
    damping: float
    stiffness_along: float
    stiffness_across: float
    friction: float
    released: float


class CouplingState(NamedTuple):
    proxy: np.ndarray  # (3,) m
    proxy_v: np.ndarray  # (3,) m/s
    history: np.ndarray  # (HIST, 3) device positions, a ring (m)
    device_v: np.ndarray  # (3,) the velocity estimate (m/s)
    force: np.ndarray  # (3,) the force to command (N)
    demand: np.ndarray  # (3,) the coupling force before clamp and continuous scaling (N)
    aux: np.ndarray  # one record of AUX_DTYPE


def new_state() -> CouplingState:
    aux = np.zeros(1, dtype=AUX_DTYPE)
    aux[0]["scale"] = 1.0
    return CouplingState(np.zeros(3), np.zeros(3), np.zeros((HIST, 3)), np.zeros(3), np.zeros(3), np.zeros(3), aux)


def no_tissue() -> TissueLocal:
    """Free space: no force, no axis, nothing to linearise."""
    return TissueLocal(np.zeros(3), np.zeros(3), 0.0, 0.0, 0.0, 0.0, 0.0)


@nb.njit(cache=True, nogil=True, inline="always")
def tissue_from_diag(d, force_buf, axis_buf):
    """The :class:`TissueLocal` a servo's DIAG record ``d`` (its ``r_*`` fields: the tissue's
    linearisation at the proxy) reports, its vectors copied into ``force_buf``/``axis_buf`` (3,)."""
    for c in range(3):
        force_buf[c] = d.r_force[c]
        axis_buf[c] = d.r_axis[c]
    return TissueLocal(force_buf, axis_buf, d.r_damping, d.r_k_along, d.r_k_across, d.r_friction, d.r_released)


@nb.njit(cache=True, nogil=True)
def foaw_velocity(history, n_hist, head, tol, dt, out):
    """End-fit first-order adaptive window velocity per axis. ``history`` is a ring of positions
    with the newest at ``head`` and ``n_hist`` valid entries; ``tol``: the allowed deviation (one
    encoder step). Writes the velocity into ``out``."""
    H = history.shape[0]
    for c in range(3):
        y0 = history[head, c]
        best = 0.0
        for n in range(1, n_hist):
            yn = history[(head - n) % H, c]
            slope = (y0 - yn) / (n * dt)
            ok = True
            for j in range(1, n):
                yj = history[(head - j) % H, c]
                if abs(yj - (y0 - slope * j * dt)) > tol:
                    ok = False
                    break
            if not ok:
                break
            best = slope
        out[c] = best


@nb.njit(cache=True, nogil=True)
def _solve_dir(r, a_lin, friction):
    """The displacement u solving ``r - a_lin u - friction sign(u) = 0`` (friction set-valued at 0)."""
    if abs(r) <= friction:
        return 0.0
    if r > 0.0:
        return (r - friction) / a_lin
    return (r + friction) / a_lin


@nb.njit(cache=True, nogil=True)
def move_proxy(k, b, tissue, state, device_pos, dt):
    """One implicit step of the massless proxy coupled to the device by (k, b) (see the module)."""
    x0 = state.proxy
    f = tissue.force
    v = state.device_v
    r0 = f[0] + k * (device_pos[0] - x0[0]) + b * v[0]
    r1 = f[1] + k * (device_pos[1] - x0[1]) + b * v[1]
    r2 = f[2] + k * (device_pos[2] - x0[2]) + b * v[2]
    a = tissue.axis
    an = math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    across = tissue.stiffness_across + b / dt + k
    ua = 0.0
    a0 = a1 = a2 = ra = 0.0
    if an > 0.0:
        a0 = a[0] / an
        a1 = a[1] / an
        a2 = a[2] / an
        ra = r0 * a0 + r1 * a1 + r2 * a2
        if tissue.released != 0.0:
            along = tissue.stiffness_along + b / dt + k
            ua = _solve_dir(ra, along, 0.0)
        else:
            along = tissue.stiffness_along + (tissue.damping + b) / dt + k
            ua = _solve_dir(ra, along, tissue.friction)
    u0 = ua * a0 + (r0 - ra * a0) / across
    u1 = ua * a1 + (r1 - ra * a1) / across
    u2 = ua * a2 + (r2 - ra * a2) / across
    state.proxy[0] = x0[0] + u0
    state.proxy[1] = x0[1] + u1
    state.proxy[2] = x0[2] + u2
    state.proxy_v[0] = u0 / dt
    state.proxy_v[1] = u1 / dt
    state.proxy_v[2] = u2 / dt


@nb.njit(cache=True, nogil=True)
def anchor_point(aux, tissue, proxy, device_pos, dt, out):
    """The point the coupling ties the proxy to, into ``out``: the device shifted by the release
    offset. A release (puncture) sets the offset's part along the tissue's axis to the coupling's
    compression, so the spring is relaxed at once (the drop is felt this tick) without moving the
    proxy; the offset then shrinks at :data:`RELEASE_CATCH_UP_M_S` back to zero."""
    a = tissue.axis
    an = math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    ox, oy, oz = aux.off_x, aux.off_y, aux.off_z
    if tissue.released != 0.0 and an > 0.0:
        a0, a1, a2 = a[0] / an, a[1] / an, a[2] / an
        gap = (proxy[0] - device_pos[0]) * a0 + (proxy[1] - device_pos[1]) * a1 + (proxy[2] - device_pos[2]) * a2
        old = ox * a0 + oy * a1 + oz * a2
        ox += (gap - old) * a0
        oy += (gap - old) * a1
        oz += (gap - old) * a2
    else:
        m = math.sqrt(ox * ox + oy * oy + oz * oz)
        if m > 0.0:
            keep = m - RELEASE_CATCH_UP_M_S * dt
            f = keep / m if keep > 0.0 else 0.0
            ox *= f
            oy *= f
            oz *= f
    aux.off_x, aux.off_y, aux.off_z = ox, oy, oz
    out[0] = device_pos[0] + ox
    out[1] = device_pos[1] + oy
    out[2] = device_pos[2] + oz


@nb.njit(cache=True, nogil=True)
def _zero(state, aux):
    for c in range(3):
        state.force[c] = 0.0
        state.demand[c] = 0.0
    aux.status = FAULT
    return FAULT


@nb.njit(cache=True, nogil=True)
def _protect(limits, params, state, aux):
    """Clamp ``state.demand`` to the device's maximum, scale it for the continuous limit, write
    ``state.force``; returns the status bits."""
    f = state.demand
    mag = math.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2])
    status = 0
    s_clamp = 1.0
    if mag > limits.max_force_n:
        s_clamp = limits.max_force_n / mag
        status |= CLAMPED
    fm = mag * s_clamp
    alpha = params.dt_s / params.continuous_tau_s
    if alpha > 1.0:
        alpha = 1.0
    aux.f_sq_avg += alpha * (fm * fm - aux.f_sq_avg)
    target = 1.0
    rms = math.sqrt(aux.f_sq_avg)
    if rms > limits.continuous_force_n:
        target = limits.continuous_force_n / rms
    step = params.ramp_per_s * params.dt_s
    s = aux.scale
    if target < s - step:
        s -= step
    elif target > s + step:
        s += step
    else:
        s = target
    aux.scale = s
    if s < 1.0:
        status |= LIMITING
    for c in range(3):
        state.force[c] = f[c] * s_clamp * s
    return status


@nb.njit(cache=True, nogil=True)
def render_step(limits, params, state, tissue, device_pos):
    """One servo tick of the rendering layer: the device is at ``device_pos`` (m, as the encoders
    report it); ``tissue`` is what the tissue step reported at the proxy last tick. Moves the proxy
    (``state.proxy``/``state.proxy_v``: where the tissue step runs next), writes the force to
    command into ``state.force`` and returns the status bits (CLAMPED, LIMITING, FAULT). A fault
    latched in ``state.aux[0].fault`` (set it to signal one) or any non-finite input gives zero
    force this tick, and every tick until :func:`reset`."""
    aux = state.aux[0]
    ok = aux.fault == 0
    for c in range(3):
        ok = ok and math.isfinite(device_pos[c]) and math.isfinite(tissue.force[c]) and math.isfinite(tissue.axis[c])
    ok = ok and math.isfinite(tissue.damping) and math.isfinite(tissue.stiffness_along)
    ok = ok and math.isfinite(tissue.stiffness_across) and math.isfinite(tissue.friction)
    ok = ok and tissue.damping >= 0.0 and tissue.stiffness_along >= 0.0 and tissue.stiffness_across >= 0.0
    ok = ok and tissue.friction >= 0.0 and math.isfinite(tissue.released)
    if not ok:
        aux.fault = 1
        return _zero(state, aux)
    H = state.history.shape[0]
    if aux.initialised == 0:
        for c in range(3):
            state.proxy[c] = device_pos[c]
            state.proxy_v[c] = 0.0
        aux.initialised = 1
        aux.n_hist = 0
        aux.head = H - 1
    aux.head = (aux.head + 1) % H
    for c in range(3):
        state.history[aux.head, c] = device_pos[c]
    if aux.n_hist < H:
        aux.n_hist += 1
    foaw_velocity(state.history, aux.n_hist, aux.head, params.encoder_step_m, params.dt_s, state.device_v)
    k = min(params.stiffness_n_per_m, limits.stiffness_n_per_m)
    b = min(params.damping_n_s_per_m, limits.damping_n_s_per_m)
    anchor = state.force  # scratch until _protect writes the force below
    anchor_point(aux, tissue, state.proxy, device_pos, params.dt_s, anchor)
    move_proxy(k, b, tissue, state, anchor, params.dt_s)
    for c in range(3):
        state.demand[c] = k * (state.proxy[c] - anchor[c]) + b * (state.proxy_v[c] - state.device_v[c])
    status = _protect(limits, params, state, aux)
    aux.status = status
    return status


@nb.njit(cache=True, nogil=True)
def signal_fault(state):
    """Latch a fault: the next :func:`render_step` (and every one after) commands zero; the force
    in ``state.force`` is zeroed at once, for a caller that sends it without another step."""
    aux = state.aux[0]
    aux.fault = 1
    _zero(state, aux)


def reset(state: CouplingState) -> None:
    """Clear the state (fault, proxy, history, protection) for a new session."""
    for arr in (state.proxy, state.proxy_v, state.history, state.device_v, state.force, state.demand):
        arr[:] = 0.0
    state.aux[:] = 0
    state.aux[0]["scale"] = 1.0


def warm_up(limits: DeviceLimits | None = None) -> None:
    """Compile (or load from cache) the kernels before a real-time loop starts."""
    lim = limits if limits is not None else DeviceLimits(3.3, 0.88, 1260.0, 3.0)
    st = new_state()
    render_step(lim, default_params(lim), st, no_tissue(), np.zeros(3))
    signal_fault(st)

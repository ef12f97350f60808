"""Twirling: the needle's roll about its own axis, the tissue wound around the shaft, the torque
it returns and the needle grasp it produces (docs/model.md section 11, "Twirling, needle grasp and technique metrics").

What is modelled. Rotating an inserted acupuncture needle winds the connective tissue around the
shaft (Langevin et al. 2001, J Appl Physiol 91:2471; 2002, FASEB J 16:872). Two things follow:
a torque about the needle axis that grows linearly with the rotation angle (Han et al. 2015,
Integr Med Res 4:57) and a "needle grasp": the force needed to pull the needle out rises, by
167% after unidirectional rotation and by 52% after bidirectional rotation (Langevin 2001).

Per tissue layer i (skin, fat, muscle; any number) the state holds, with L_i the length of
needle in the layer and dtheta the needle's roll increment over the step (after a backlash
"play" of width ``play_rad`` that keeps encoder jitter from winding anything):

* the twist phi_i (rad) of the tissue held by the shaft: it follows the needle,
  ``phi += dtheta``; relaxes, ``phi *= exp(-dt / twist_tau_s)``; and slips past
  ``|phi| <= twist_slip_rad`` (the tissue lets go of the shaft). Rotating back unwinds it.
* the engagement e_i in [0, 1] of tissue fibres with the shaft: any rotation, either way, raises
  it, ``e += (1 - e) (1 - exp(-|dtheta| / engage_rad))``; only time relaxes it,
  ``e *= exp(-dt / engage_tau_s)``. It is what bidirectional rotation leaves behind.
* both are intensive (per unit length): when the needle advances into fresh, unwound tissue the
  wound amount L_i phi_i and L_i e_i are conserved (phi and e are diluted by L_old / L_new);
  withdrawing keeps them; a layer the needle has left (L_i = 0) is cleared.

Outputs, per layer:

* torque_i = k_twist_i L_i phi_i (N*m), the torque the hand must apply to hold the needle's
  roll, positive clockwise seen from the handle (the sign of the roll). Linear in angle below
  the slip limit. It cannot be rendered by a 3-DOF device; it is recorded and shown.
* grasp_i = 1 + grasp_coil_i |phi_i| / twist_slip_rad_i + grasp_engage_i e_i (>= 1): the factor
  by which the layer's shaft friction (stiction and Coulomb levels of the Karnopp friction in
  :mod:`haptic_acu.tissue.mechanics`, each proportional to L_i) is multiplied. The grasp reaches the
  hand through the axial force.

Calibration (docs/model.md): ``k_twist`` from Han 2015's torque-angle line at 0.15 Hz with the
needle 30 mm in tissue (:func:`han_torque_slope`); ``grasp_coil`` and ``grasp_engage`` so that the
two rotation protocols :data:`UNI` and :data:`BI` reproduce Langevin 2001's pull-out ratios 2.67
and 1.52 against :data:`NO` with a stand-in pull-out force, baseline friction times the grasp
factor (:func:`run_protocol`, :func:`calibrate_grasp`).

Roll. :class:`RollState` holds the unwrapped roll angle (rad, positive clockwise seen from the
handle) and its rate (rad/s, low-passed with ``rate_tau_s``). :func:`roll_from_wrapped` takes an
angle that wraps at +-pi (the OMNI's third gimbal angle) and unwraps it, the roll starting at 0
on the first sample; :func:`roll_from_cumulative` takes a cumulative angle (a trajectory's
``roll_deg`` in radians, the keyboard's integrated twirl). Both refuse a non-finite input
(return False, state untouched) so the step can raise its fault.

Kernels are numba ``njit(nogil=True, cache=True)``, allocation-free, no fastmath; state and
parameters are NamedTuples of arrays (per-layer arrays of length n_layers). SI units throughout.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from .layers import N_LAYERS

TWO_PI = 2.0 * math.pi

# ------------------------------------------------------------------------------- published figures
# Han et al. 2015 (Integr Med Res 4:57-65): torque vs rotation angle at 0.15 Hz, needle force
# measurement system in a tissue model. A second sweep (60 deg, rotation frequency varied) gave
# 0.023-0.118 N*mm; the model's torque hardly depends on frequency, so it is not fitted to it.
HAN_ANGLE_DEG = (60.0, 180.0)
HAN_TORQUE_NMM = (0.082, 0.292)
HAN_FREQ_HZ = 0.15
HAN_SECOND_SWEEP_NMM = (0.023, 0.118)
# Our assumption (Han's insertion depth is not in the sources available): the needle is 30 mm in
# tissue, the bundled acupoint depth (trajectories/default.csv goes to z = -30 mm).
HAN_LENGTH_M = 30e-3
# Langevin et al. 2001 (J Appl Physiol 91:2471-2478), 60 subjects: mean pull-out force after
# unidirectional / bidirectional rotation relative to no rotation.
LANGEVIN_UNI_RATIO = 2.67
LANGEVIN_BI_RATIO = 1.52

# --------------------------------------------------------------------------------- our assumptions
# The servo reads these from the config's [twirl] section (params_from_config); config/tissue.toml
# holds exactly these values (a test checks), docs/model.md section 11 says where each comes from.
TWIST_SLIP_RAD = TWO_PI  # one turn of twist held before the tissue slips on the shaft
TWIST_TAU_S = 30.0       # twist (torque) relaxation
ENGAGE_RAD = TWO_PI      # one turn of rotation raises engagement to 1 - 1/e
ENGAGE_TAU_S = 60.0      # engagement relaxation (grasp outlasts the torque)
PLAY_RAD = math.radians(1.0)  # backlash width on the roll feeding the winding
RATE_TAU_S = 0.010       # roll-rate low-pass (RollState only: the servo step computes no roll rate)


class Protocol(NamedTuple):
    """A rotation protocol for the pull-out stand-in: rotate ``turns`` (a sequence of signed turns,
    each at ``rev_per_s``), wait ``wait_s``, then the pull-out starts (its breakaway force is read
    on the first tick)."""

    name: str
    turns: tuple
    rev_per_s: float
    wait_s: float


# Our documented stand-ins for Langevin 2001's three modes (the paper's own rotation counts, speed
# and waiting time could not be checked here; see docs/model.md): 4 turns clockwise; 2 cycles of
# one turn clockwise and one back; no rotation. All at 1 turn/s, pull-out 1 s after the rotation.
UNI = Protocol("unidirectional", (4.0,), 1.0, 1.0)
BI = Protocol("bidirectional", (1.0, -1.0, 1.0, -1.0), 1.0, 1.0)
NO = Protocol("none", (), 1.0, 5.0)


# ------------------------------------------------------------------------------------------- roll
class RollParams(NamedTuple):
    rate_tau_s: float  # low-pass time constant of the roll rate (s)


class RollState(NamedTuple):
    angle: np.ndarray     # (1,) rad, unwrapped roll, positive clockwise seen from the handle
    rate: np.ndarray      # (1,) rad/s, low-passed
    last_raw: np.ndarray  # (1,) rad, the previous raw input
    primed: np.ndarray    # (1,) int64, 0 until the first input


def new_roll_state() -> RollState:
    return RollState(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1, dtype=np.int64))


def default_roll_params() -> RollParams:
    return RollParams(RATE_TAU_S)


@nb.njit(cache=True, nogil=True, inline="always")
def _roll_advance(rs, d, raw, dt, rp):
    rs.angle[0] += d
    if dt > 0.0:
        a = dt / (rp.rate_tau_s + dt)
        rs.rate[0] += a * (d / dt - rs.rate[0])
    rs.last_raw[0] = raw


@nb.njit(cache=True, nogil=True)
def roll_from_wrapped(rs, raw_rad, dt, rp):
    """Advance the roll from an angle wrapping at +-pi (the OMNI stylus roll); the roll starts at 0
    on the first sample. False (state untouched) if ``raw_rad`` is not finite."""
    if not math.isfinite(raw_rad):
        return False
    if rs.primed[0] == 0:
        rs.primed[0] = 1
        rs.angle[0] = 0.0
        rs.rate[0] = 0.0
        rs.last_raw[0] = raw_rad
        return True
    d = raw_rad - rs.last_raw[0]
    d -= TWO_PI * math.floor(d / TWO_PI + 0.5)  # the shortest way round: |d| <= pi
    _roll_advance(rs, d, raw_rad, dt, rp)
    return True


@nb.njit(cache=True, nogil=True)
def roll_from_cumulative(rs, angle_rad, dt, rp):
    """Advance the roll to a cumulative angle (a trajectory's ``roll_deg`` in rad, the keyboard's
    integrated twirl). False (state untouched) if ``angle_rad`` is not finite."""
    if not math.isfinite(angle_rad):
        return False
    if rs.primed[0] == 0:
        rs.primed[0] = 1
        rs.angle[0] = angle_rad
        rs.rate[0] = 0.0
        rs.last_raw[0] = angle_rad
        return True
    _roll_advance(rs, angle_rad - rs.last_raw[0], angle_rad, dt, rp)
    return True


# ---------------------------------------------------------------------------------- winding, grasp
class TwirlParams(NamedTuple):
    k_twist: np.ndarray       # (nl,) N*m per rad per m of needle in the layer (= N/rad)
    twist_slip_rad: np.ndarray  # (nl,) twist at which the tissue slips on the shaft
    twist_tau_s: np.ndarray   # (nl,) twist relaxation time
    engage_rad: np.ndarray    # (nl,) rotation per e-fold of engagement growth
    engage_tau_s: np.ndarray  # (nl,) engagement relaxation time
    grasp_coil: np.ndarray    # (nl,) grasp gain at full twist (|phi| = slip)
    grasp_engage: np.ndarray  # (nl,) grasp gain at full engagement (e = 1)
    play_rad: float           # backlash width on the roll feeding the winding


class WindState(NamedTuple):
    twist_rad: np.ndarray  # (nl,) phi_i
    engage: np.ndarray     # (nl,) e_i in [0, 1]
    length_m: np.ndarray   # (nl,) needle length in the layer at the last step
    torque_nm: np.ndarray  # (nl,) output: torque of the layer (N*m)
    grasp: np.ndarray      # (nl,) output: friction multiplier of the layer (>= 1)
    roll_play: np.ndarray  # (1,) rad, the roll after the backlash
    primed: np.ndarray     # (1,) int64, 0 until the first step


def new_wind_state(n_layers: int = N_LAYERS) -> WindState:
    z = np.zeros
    return WindState(z(n_layers), z(n_layers), z(n_layers), z(n_layers), np.ones(n_layers),
                     z(1), z(1, dtype=np.int64))


def han_torque_slope() -> float:
    """Least-squares slope through the origin (N*m per rad) of Han 2015's torque-range vs swing."""
    a = np.radians(np.asarray(HAN_ANGLE_DEG))
    t = np.asarray(HAN_TORQUE_NMM) * 1e-3
    return float(a @ t / (a @ a))


def maxwell_range_factor(freq_hz: float, tau_s: float) -> float:
    """Steady-state torque range of a relaxing twist over the elastic one for a sinusoidal twirl:
    w tau / sqrt(1 + (w tau)^2), w = 2 pi f."""
    wt = TWO_PI * freq_hz * tau_s
    return wt / math.sqrt(1.0 + wt * wt)


def calibrated_k_twist(tau_s: float = TWIST_TAU_S) -> float:
    """k_twist (N/rad) that puts a sinusoidal twirl at Han's 0.15 Hz, needle 30 mm in tissue, on
    Han's torque-angle line."""
    return han_torque_slope() / (HAN_LENGTH_M * maxwell_range_factor(HAN_FREQ_HZ, tau_s))


# grasp gains solved by calibrate_grasp() for UNI/BI above; a test checks they still are
GRASP_COIL = 1.2662
GRASP_ENGAGE = 0.4684


def default_params(n_layers: int = N_LAYERS, grasp_coil: float = GRASP_COIL,
                   grasp_engage: float = GRASP_ENGAGE) -> TwirlParams:
    """The calibrated defaults, the same in every layer (no per-layer data exist)."""
    f = np.full
    return TwirlParams(f(n_layers, calibrated_k_twist()), f(n_layers, TWIST_SLIP_RAD),
                       f(n_layers, TWIST_TAU_S), f(n_layers, ENGAGE_RAD), f(n_layers, ENGAGE_TAU_S),
                       f(n_layers, float(grasp_coil)), f(n_layers, float(grasp_engage)),
                       PLAY_RAD)


def params_from_config(tc, n_layers: int = N_LAYERS) -> TwirlParams:
    """Kernel parameters (SI) from the config's ``[twirl]`` section (:class:`haptic_acu.base.config.TwirlingParams`):
    per-layer lists as arrays, turns and degrees as radians. config/tissue.toml's values are this
    module's defaults (:func:`default_params`), exactly."""
    def per_layer(v):
        a = np.asarray(v, dtype=np.float64)
        if a.shape != (n_layers,):
            raise ValueError(f"expected {n_layers} per-layer values, got {v!r}")
        return a.copy()

    f = np.full
    return TwirlParams(per_layer(tc.k_twist_n_per_rad), f(n_layers, tc.twist_slip_turns * TWO_PI),
                       f(n_layers, float(tc.twist_tau_s)), f(n_layers, tc.engage_turns * TWO_PI),
                       f(n_layers, float(tc.engage_tau_s)), per_layer(tc.grasp_coil),
                       per_layer(tc.grasp_engage), math.radians(tc.play_deg))


@nb.njit(cache=True, nogil=True, inline="always")
def play(y, x, half):
    """Backlash operator of half-width ``half``: the new output for input ``x`` and output ``y``
    (it follows the input only beyond +-half)."""
    if x > y + half:
        return x - half
    if x < y - half:
        return x + half
    return y


@nb.njit(cache=True, nogil=True, inline="always")
def dilute(old_m, new_m):
    """Factor on a layer's twist and engagement when its length goes from ``old_m`` to ``new_m``:
    0 for a layer entered or left, old/new on advancing into fresh tissue, else 1."""
    if new_m <= 0.0 or old_m <= 0.0:
        return 0.0
    if new_m > old_m:
        return old_m / new_m
    return 1.0


@nb.njit(cache=True, nogil=True, inline="always")
def wind_layer(phi, e, d, dt, slip, twist_tau, engage_rad, engage_tau):
    """One layer's (twist, engagement) after a roll increment ``d`` over ``dt``: wind, relax, slip."""
    phi += d
    if d != 0.0:
        e += (1.0 - e) * (1.0 - math.exp(-abs(d) / engage_rad))
    phi *= math.exp(-dt / twist_tau)
    e *= math.exp(-dt / engage_tau)
    if phi > slip:
        phi = slip
    elif phi < -slip:
        phi = -slip
    return phi, e


@nb.njit(cache=True, nogil=True, _nrt=False)
def wind_step(ws, roll_rad, length_m, dt, p):
    """One step of every layer's winding: ``roll_rad`` the needle's roll (rad, unwrapped),
    ``length_m`` (n_layers,) the needle length in each layer (m), ``dt`` (s). Updates ``ws``
    (its ``torque_nm`` and ``grasp`` are the outputs) and returns the total torque (N*m)."""
    twist, engage, length, torque, grasp = ws.twist_rad, ws.engage, ws.length_m, ws.torque_nm, ws.grasp
    if ws.primed[0] == 0:
        ws.primed[0] = 1
        ws.roll_play[0] = roll_rad
    y = ws.roll_play[0]
    ws.roll_play[0] = play(y, roll_rad, 0.5 * p.play_rad)
    d = ws.roll_play[0] - y
    total = 0.0
    for i in range(twist.shape[0]):
        L = length_m[i]
        f = dilute(length[i], L)
        length[i] = L if L > 0.0 else 0.0
        if L <= 0.0:
            twist[i] = 0.0
            engage[i] = 0.0
            torque[i] = 0.0
            grasp[i] = 1.0
            continue
        slip = p.twist_slip_rad[i]
        phi, e = wind_layer(twist[i] * f, engage[i] * f, d, dt, slip, p.twist_tau_s[i],
                            p.engage_rad[i], p.engage_tau_s[i])
        twist[i] = phi
        engage[i] = e
        torque[i] = p.k_twist[i] * L * phi
        grasp[i] = 1.0 + p.grasp_coil[i] * abs(phi) / slip + p.grasp_engage[i] * e
        total += torque[i]
    return total


@nb.njit(cache=True, nogil=True)
def wind_reset(ws):
    """Forget all winding (fresh tissue): every layer unwound, grasp 1, torque 0; the next
    :func:`wind_step` takes the roll it is given as the start."""
    for i in range(ws.twist_rad.shape[0]):
        ws.twist_rad[i] = 0.0
        ws.engage[i] = 0.0
        ws.length_m[i] = 0.0
        ws.torque_nm[i] = 0.0
        ws.grasp[i] = 1.0
    ws.primed[0] = 0


@nb.njit(cache=True, nogil=True)
def grasped_friction(ws, friction_n, out):
    """``out[i] = grasp[i] * friction_n[i]``: the layers' friction levels under the grasp; returns
    their sum. (The stand-in pull-out force when ``friction_n`` holds the layers' breakaway
    levels.)"""
    s = 0.0
    for i in range(out.shape[0]):
        out[i] = ws.grasp[i] * friction_n[i]
        s += out[i]
    return s


def compile_kernels() -> None:
    """Compile (or load from cache) every kernel before a real-time loop starts."""
    rs, rp = new_roll_state(), default_roll_params()
    roll_from_wrapped(rs, 0.0, 1e-3, rp)
    roll_from_cumulative(new_roll_state(), 0.0, 1e-3, rp)
    ws, p = new_wind_state(), default_params()
    wind_step(ws, 0.0, np.zeros(N_LAYERS), 1e-3, p)
    wind_reset(ws)
    grasped_friction(ws, np.zeros(N_LAYERS), np.zeros(N_LAYERS))


# ------------------------------------------------------------------------------ display (Python)
def twist_direction(axis_to_tip, roll_rad) -> np.ndarray:
    """A unit vector across the needle that turns with its roll, for drawing the twist: the scene's
    +x (or +y if the needle lies along x) made perpendicular to the needle, turned by ``roll_rad``
    clockwise as seen from the handle (a right-handed turn about ``axis_to_tip``, the unit vector
    from the handle to the tip). Also for many at once: ``axis_to_tip`` (..., 3), ``roll_rad`` (...)."""
    d = np.asarray(axis_to_tip, dtype=np.float64)
    d = d / np.sqrt(np.sum(d * d, axis=-1, keepdims=True))
    ref = np.zeros(d.shape)
    along_x = np.abs(d[..., 0]) >= 0.9
    ref[..., 0] = np.where(along_x, 0.0, 1.0)
    ref[..., 1] = np.where(along_x, 1.0, 0.0)
    e0 = ref - np.sum(ref * d, axis=-1, keepdims=True) * d
    e0 = e0 / np.sqrt(np.sum(e0 * e0, axis=-1, keepdims=True))
    across = np.cross(d, e0)
    r = np.asarray(roll_rad, dtype=np.float64)[..., None]
    return np.cos(r) * e0 + np.sin(r) * across


# ----------------------------------------------------------------------------- protocols (Python)
def protocol_roll(proto: Protocol, dt: float = 1e-3) -> np.ndarray:
    """The roll (rad) per tick of a protocol up to the start of the pull-out, from 0."""
    pieces = [np.zeros(1)]
    for turns in proto.turns:
        n = max(1, int(round(abs(turns) / proto.rev_per_s / dt)))
        pieces.append(pieces[-1][-1] + np.linspace(0.0, TWO_PI * turns, n + 1)[1:])
    roll = np.concatenate(pieces)
    wait = np.full(int(round(proto.wait_s / dt)), roll[-1])
    return np.concatenate([roll, wait])


def run_protocol(proto: Protocol, p: TwirlParams | None = None, length_m=None,
                 friction_n=None, dt: float = 1e-3) -> tuple[float, WindState]:
    """The stand-in pull-out force (N) at the end of ``proto``: each layer's baseline breakaway
    friction ``friction_n`` (default 1 N per layer in the needle, so the result is the mean grasp
    times the count) times its grasp factor, the needle held at ``length_m`` (default 0.8, 8.4 and
    20.8 mm: the bundled acupoint at 30 mm). Returns (force, final state)."""
    p = default_params() if p is None else p
    nl = p.k_twist.shape[0]
    length = np.array([0.8e-3, 8.4e-3, 20.8e-3]) if length_m is None else np.asarray(length_m, float)
    fric = np.where(length > 0, 1.0, 0.0) if friction_n is None else np.asarray(friction_n, float)
    ws = new_wind_state(nl)
    for r in protocol_roll(proto, dt):
        wind_step(ws, float(r), length, dt, p)
    return float(grasped_friction(ws, fric, np.zeros(nl))), ws


def pullout_ratios(p: TwirlParams | None = None, uni: Protocol = UNI, bi: Protocol = BI,
                   no: Protocol = NO) -> tuple[float, float]:
    """Stand-in pull-out force after ``uni`` and ``bi`` over that after ``no``."""
    f0 = run_protocol(no, p)[0]
    return run_protocol(uni, p)[0] / f0, run_protocol(bi, p)[0] / f0


def calibrate_grasp(uni: Protocol = UNI, bi: Protocol = BI,
                    targets=(LANGEVIN_UNI_RATIO, LANGEVIN_BI_RATIO), pullout=None) -> tuple[float, float]:
    """(grasp_coil, grasp_engage) that make ``uni`` and ``bi`` give the target pull-out ratios
    against :data:`NO`.

    ``pullout(protocol, params) -> force`` measures a pull-out; None is the stand-in
    (:func:`run_protocol`), in which the grasp is linear in both gains given the state, so two
    unit-gain runs per protocol solve it exactly. Any other (a pull-out through the real friction,
    whose compliance lets the needle move before it breaks away) is solved by ``scipy.optimize.root``
    from the stand-in's answer."""
    rows = []
    for proto in (uni, bi):
        c = run_protocol(proto, default_params(grasp_coil=1.0, grasp_engage=0.0))[0]
        e = run_protocol(proto, default_params(grasp_coil=0.0, grasp_engage=1.0))[0]
        f0 = run_protocol(proto, default_params(grasp_coil=0.0, grasp_engage=0.0))[0]
        rows.append((c - f0, e - f0, f0))
    f_no = run_protocol(NO, default_params())[0]  # no rotation: grasp 1 whatever the gains
    A = np.array([[r[0], r[1]] for r in rows])
    b = np.array([targets[k] * f_no - rows[k][2] for k in range(2)])
    coil, engage = np.linalg.solve(A, b)
    if pullout is None:
        return float(coil), float(engage)
    from scipy.optimize import root

    def resid(x):
        p = default_params(grasp_coil=x[0], grasp_engage=x[1])
        f_none = pullout(NO, p)
        return [pullout(uni, p) / f_none - targets[0], pullout(bi, p) / f_none - targets[1]]

    sol = root(resid, [coil, engage], method="hybr", options={"xtol": 1e-6})
    if not sol.success:
        raise RuntimeError(f"grasp calibration did not converge: {sol.message}")
    return float(sol.x[0]), float(sol.x[1])

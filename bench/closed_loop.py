"""Offline closed-loop harness: a hand holding the stylus of an OMNI-like device, the tissue model,
and the force the device renders, with or without :mod:`haptic_acu.servo.rendering` (SI units, 1 kHz).

The plant is :mod:`haptic_acu.servo.stylus`, the HD emulator's physical stylus in numba: a 45 g
stylus held by a hand (a spring-damper to a scripted hand path), pushed by the commanded force
held over each tick, its position reported quantised to the 0.055 mm encoder step. The tissue is
the :class:`haptic_acu.servo.step.NeedleModel`, driven through its public ``step``.

Modes:
* ``naive``: the force path without a rendering layer: the tissue step at the reported position with the device's
  velocity, the force clamped to the device's maximum. ``velocity="raw"`` is a one-tick difference
  of quantised positions, ``"hd"`` the HD API's filtered estimate (a
  50 Hz first-order low-pass of it, as the emulator reports).
* ``rendered``: the rendering layer: the tissue step runs at the proxy; the device feels the
  virtual coupling.

The session: the hand inserts at the acupoint to 25 mm at 10 mm/s, holds 2 s, makes
three 5 mm lift-thrust cycles at 1 Hz, holds 1 s, withdraws, moves 15 mm aside, presses 1 mm into
intact skin and slides 10 mm along it at 10 mm/s, lifts off and returns to its start: a closed path.

Reported per phase: the buzz (RMS of the force above 40 Hz: a zero-phase 4th-order Butterworth
high-pass over the session, 30 ms before to 60 ms after each puncture left out, since a puncture's
drop is content above 40 Hz by design and the filter is zero-phase); each puncture's force: the
largest of the 5 ms before it, the smallest within 20 ms after it, and the force 20 ms after it;
the largest difference between the rendered and the simulated force while the hand moves
smoothly (inserting or sliding, not within 100 ms of a puncture or a phase change), at the same
tick and against the tick before (the rendering uses the tissue's report of the tick before: a
jump of the simulated force, such as a pressed net re-centring under a sliding tip, reaches the
device one tick later); the energy the
device puts into the hand over each lift-thrust cycle and over the whole closed session.

Run: ``python -m bench.closed_loop`` (a table; ``--json`` for the numbers).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math

import numpy as np
from scipy.signal import butter, sosfiltfilt

from haptic_acu.servo import rendering as R
from haptic_acu.servo import stylus
from haptic_acu.base.config import load_config
from haptic_acu.servo.step import PRESSING, PUNCTURED, NeedleModel

DT = 1e-3
ENCODER_STEP_M = 0.055e-3
# The emulator's defaults for an OMNI (hd_emulator.c): HD_NOMINAL_MAX_* (SI here).
OMNI_LIMITS = R.limits_from_hd(3.3, 0.88, 1.26, 0.003)
# The stiffness reported while a layer is pressed. The nets stiffen to 1.5 N/mm (skin) and 2.2 N/mm
# (muscle) at the break; the proxy step converges for any true stiffness below
# 2 (this + B/T) + K (with the coupling's B/T = 1500 N/m, K = 630 N/m: 6.6 N/mm), and monotonically
# below this + B/T. A larger value only adds a drag of (value) * dt * speed (0.015 N at 10 mm/s).
PRESS_STIFFNESS = 1500.0


@dataclasses.dataclass(frozen=True)
class Grip:
    name: str
    stiffness_n_per_m: float
    damping_n_s_per_m: float
    mass_kg: float = 0.045

    @property
    def model(self) -> stylus.Grip:
        return stylus.Grip(self.stiffness_n_per_m, self.damping_n_s_per_m, self.mass_kg)


LOOSE = Grip("loose", *stylus.LOOSE[:2])
FIRM = Grip("firm", *stylus.FIRM[:2])


def _contact_z(model: NeedleModel, x: float) -> float:
    """z (m) where a tip moving down at (x, 0) first presses the skin (a scratch run; reset after)."""
    model.reset(keep_holes=False)
    for z in np.arange(10e-3, -30e-3, -5e-6):
        model.step(np.array([x, 0.0, z]), np.array([0.0, 0.0, -0.01]))
        if model.states[0] == PRESSING:
            model.reset(keep_holes=False)
            return float(z)
    raise RuntimeError(f"no skin under x = {x * 1e3:.1f} mm")


def _segment(p0, p1, speed):
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    n = max(1, int(round(np.linalg.norm(p1 - p0) / (speed * DT))))
    s = np.arange(1, n + 1) / n
    return p0 + s[:, None] * (p1 - p0)


def session_path(model: NeedleModel):
    """The hand path (one row per tick, the first the start) and its phases [(name, i0, i1)]."""
    z0 = _contact_z(model, 0.0)
    xs = 15e-3
    zs = _contact_z(model, xs)
    top = z0 + 3e-3
    rows = [np.array([[0.0, 0.0, top]])]
    phases = []

    def add(name, pts):
        i0 = sum(len(r) for r in rows) - 1
        rows.append(pts)
        phases.append((name, i0, i0 + len(pts)))

    deep = z0 - 25e-3
    add("insert", _segment([0, 0, top], [0, 0, deep], 0.01))
    add("hold", np.tile([0.0, 0.0, deep], (2000, 1)))
    t = DT * np.arange(1, 3001)
    add("lift_thrust", np.column_stack([np.zeros(3000), np.zeros(3000), deep + 2.5e-3 * (1 - np.cos(2 * np.pi * t))]))
    add("hold_again", np.tile([0.0, 0.0, deep], (1000, 1)))
    add("withdraw", _segment([0, 0, deep], [0, 0, top], 0.01))
    add("move", _segment([0, 0, top], [xs, 0, zs + 3e-3], 0.02))
    add("press", _segment([xs, 0, zs + 3e-3], [xs, 0, zs - 1e-3], 0.01))
    add("slide", _segment([xs, 0, zs - 1e-3], [xs + 10e-3, 0, zs - 1e-3], 0.01))
    add("lift_return", np.vstack([_segment([xs + 10e-3, 0, zs - 1e-3], [xs + 10e-3, 0, top], 0.01),
                                  _segment([xs + 10e-3, 0, top], [0, 0, top], 0.02),
                                  np.tile([0.0, 0.0, top], (300, 1))]))
    return np.vstack(rows), phases


class NeedleAdapter:
    """The NeedleModel seen through :class:`haptic_acu.servo.rendering.TissueLocal` (read-only: from
    its diagnostics and state after each step). The damping along the axis comes from the step's
    own damping force over the axial velocity it was given (exact, Table 1 is linear in v; kept
    while the proxy is still); a pressed net's stiffness is bounded above; the lateral constraint's
    and the bone's stiffnesses are the model's; a puncture (``diag["puncture"]``) is a release. Coulomb
    friction: none in this adapter."""

    def __init__(self, model: NeedleModel):
        self.m = model
        self.c = 0.0

    def naive(self, p, v):
        return np.array(self.m.step(p, v), float)

    def puncture(self):
        return int(self.m.diag["puncture"])

    def step(self, p, v):
        m = self.m
        f = np.array(m.step(p, v), float)
        a = m.axis
        states = m.states
        inserted = m.inserted
        fd = m.diag["f_damp"]
        v_ax = float(v @ a)
        if inserted:
            if abs(v_ax) > 1e-7:
                self.c = max(0.0, -fd / v_ax)
        else:
            self.c = 0.0
        elastic = f - fd * a if inserted else f
        pressing = any(s == PRESSING for s in states)
        along = PRESS_STIFFNESS if pressing else 0.0
        across = m.model.params[0]["k_lateral"] if inserted else 0.0
        if all(s == PUNCTURED for s in states):
            along = max(along, m.model.params[0]["k_bone"])
        axis = a if (inserted or pressing) else np.zeros(3)
        if pressing and not inserted:
            axis = m.state.axes[m.active_slot(next(k for k, s in enumerate(states) if s == PRESSING))]
            across = 0.0  # a pressed net only pushes along its axis; it re-centres under a sliding tip
        return f, R.TissueLocal(np.ascontiguousarray(elastic), np.ascontiguousarray(axis), float(self.c),
                                float(along), float(across), 0.0, 1.0 if m.diag["puncture"] >= 0 else 0.0)


class DiagTissue:
    """The servo's own report for the rendering layer (the DIAG ``r_*`` fields that
    :func:`haptic_acu.servo.step.render_local` writes): exactly what the OMNI path and the scripted
    device's model render from."""

    def __init__(self, model: NeedleModel):
        self.m = model

    def naive(self, p, v):
        return np.array(self.m.step(p, v), float)

    def puncture(self):
        return int(self.m.diag["puncture"])

    def step(self, p, v):
        f = np.array(self.m.step(p, v), float)
        d = self.m.diag
        return f, R.TissueLocal(np.array(d["r_force"]), np.array(d["r_axis"]), float(d["r_damping"]),
                                float(d["r_k_along"]), float(d["r_k_across"]), float(d["r_friction"]),
                                float(d["r_released"]))


def run(grip: Grip, mode: str, velocity: str = "hd", params: R.CouplingParams | None = None,
        cfg=None, limits: R.DeviceLimits = OMNI_LIMITS, tissue: str = "adapter", until: str | None = None) -> dict:
    """The closed-loop session (:func:`session_path`) on the tissue model; see :func:`closed_loop`.
    ``tissue``: "adapter" (:class:`NeedleAdapter`, reading the model from Python) or "diag"
    (:class:`DiagTissue`, the servo's own report); ``until``: the last phase to run (None: all)."""
    cfg = cfg if cfg is not None else load_config()
    model = NeedleModel(cfg)
    H, phases = session_path(model)
    if until is not None:
        names = [p[0] for p in phases]
        phases = phases[:names.index(until) + 1]
        H = H[:phases[-1][2] + 1]
    model.reset(keep_holes=False)
    adapter = DiagTissue(model) if tissue == "diag" else NeedleAdapter(model)
    return closed_loop(grip, H, phases, adapter, mode, velocity, params, limits)


def buzz_table(quick: bool = False) -> dict:
    """The bench's closed-loop rows: per grip, the rendered session on the servo's own report
    (:class:`DiagTissue`) — buzz per phase, punctures, rendered vs simulated, energy into the hand —
    and, in the full run, the naive path (the HD velocity, no rendering layer) beside it. ``quick``:
    the insertion and the hold only."""
    out = {}
    for grip in (LOOSE, FIRM):
        m = metrics(run(grip, "rendered", tissue="diag", until="hold" if quick else None))
        out[grip.name] = {"rendered": m}
        if not quick:
            out[grip.name]["naive_hd_velocity"] = {"buzz_n": metrics(run(grip, "naive", "hd"))["buzz_n"]}
    return out


class FrictionTissue:
    """A stand-in for a tissue with Coulomb friction (the model's next step: cutting and friction
    along the needle): below z = 0, friction ``mu`` (N) and damping ``c`` (N*s/m) along z."""

    def __init__(self, mu: float = 0.5, c: float = 50.0):
        self.mu, self.c = mu, c
        self.axis = np.array([0.0, 0.0, 1.0])

    def force(self, p, v):
        if p[2] >= 0.0:
            return np.zeros(3)
        s = 0.0 if v[2] == 0.0 else math.copysign(1.0, v[2])
        return -(self.c * v[2] + self.mu * s) * self.axis

    def naive(self, p, v):
        return self.force(p, v)

    def step(self, p, v):
        inside = p[2] < 0.0
        local = R.TissueLocal(np.zeros(3), self.axis.copy(), self.c if inside else 0.0, 0.0, 0.0,
                              self.mu if inside else 0.0, 0.0)
        return self.force(p, v), local

    def puncture(self):
        return -1


def friction_path():
    """Into the friction region 10 mm at 10 mm/s, three 5 mm lift-thrust cycles at 1 Hz, hold 1 s."""
    top = np.array([0.0, 0.0, 1e-3])
    deep = np.array([0.0, 0.0, -10e-3])
    rows = [top[None, :]]
    phases = []

    def add(name, pts):
        i0 = sum(len(r) for r in rows) - 1
        rows.append(pts)
        phases.append((name, i0, i0 + len(pts)))

    add("insert", _segment(top, deep, 0.01))
    t = DT * np.arange(1, 3001)
    add("lift_thrust", np.column_stack([np.zeros(3000), np.zeros(3000), deep[2] + 2.5e-3 * (1 - np.cos(2 * np.pi * t))]))
    add("hold", np.tile(deep, (1000, 1)))
    return np.vstack(rows), phases


def closed_loop(grip: Grip, H, phases, tissue_model, mode: str, velocity: str = "hd",
                params: R.CouplingParams | None = None, limits: R.DeviceLimits = OMNI_LIMITS) -> dict:
    """One closed-loop session along the hand path ``H`` (m, one row per tick); returns per-tick
    arrays and the phases. ``tissue_model`` has ``naive(p, v)`` (the force at the device) and
    ``step(p, v)`` (the force and a :class:`TissueLocal` at the proxy) and ``puncture()``."""
    n = len(H) - 1
    params = params if params is not None else R.default_params(limits, DT, ENCODER_STEP_M)
    st = R.new_state()
    plant = np.zeros(6)
    plant[:3] = H[0]
    hand_f = np.zeros(3)
    force = np.zeros(3)
    out = {k: np.zeros((n, 3)) for k in ("rendered", "simulated", "stylus", "hand_force", "proxy")}
    out["puncture"] = np.full(n, -1)
    out["status"] = np.zeros(n, dtype=np.int64)
    hand_v = np.diff(H, axis=0) / DT
    tissue = R.no_tissue()
    xq_prev = None
    v_hd = np.zeros(3)
    alpha = 1.0 - math.exp(-2 * math.pi * 50.0 * DT)
    for i in range(n):
        stylus.stylus_tick(plant, H[i], H[i + 1], force, grip.model, DT, hand_f)
        xq = ENCODER_STEP_M * np.round(plant[:3] / ENCODER_STEP_M)
        raw = np.zeros(3) if xq_prev is None else (xq - xq_prev) / DT
        xq_prev = xq
        v_hd = raw if velocity == "raw" else v_hd + alpha * (raw - v_hd)
        if mode == "naive":
            sim = tissue_model.naive(xq, v_hd)
            mag = np.linalg.norm(sim)
            force = sim * (min(1.0, limits.max_force_n / mag) if mag > 0 else 1.0)
        else:
            out["status"][i] = R.render_step(limits, params, st, tissue, xq)
            force = st.force.copy()
            sim, tissue = tissue_model.step(st.proxy.copy(), st.proxy_v.copy())
            out["proxy"][i] = st.proxy
        out["puncture"][i] = tissue_model.puncture()
        out["rendered"][i] = force
        out["simulated"][i] = sim
        out["stylus"][i] = plant[:3]
        out["hand_force"][i] = hand_f
    out["hand"] = H[1:]
    out["hand_v"] = hand_v
    out["phases"] = phases
    out["mode"] = mode
    return out


def buzz_mask(n, punctures, before_s=0.03, after_s=0.06):
    keep = np.ones(n, bool)
    for i in punctures:
        keep[max(0, i - int(before_s / DT)):i + int(after_s / DT)] = False
    return keep


def metrics(res) -> dict:
    F = res["rendered"]
    n = len(F)
    sos = butter(4, 40.0, btype="highpass", fs=1.0 / DT, output="sos")
    hp = sosfiltfilt(sos, F, axis=0)
    punct = np.where(res["puncture"] >= 0)[0]
    keep = buzz_mask(n, punct)
    out = {"buzz_n": {}, "punctures": [], "energy_into_hand_j": {}, "punctures_per_phase": {}}
    for name, i0, i1 in res["phases"]:
        sel = np.zeros(n, bool)
        sel[i0:i1] = True
        sel &= keep
        out["buzz_n"][name] = float(np.sqrt(np.mean(np.sum(hp[sel] ** 2, axis=1)))) if sel.any() else 0.0
        out["punctures_per_phase"][name] = int(np.count_nonzero((punct >= i0) & (punct < i1)))
    mag = np.linalg.norm(F, axis=1)
    for i in punct:
        before = float(mag[max(0, i - 5):i + 1].max())
        out["punctures"].append({"layer": int(res["puncture"][i]), "t_s": (i + 1) * DT, "before_n": before,
                                 "min_within_20ms_n": float(mag[i + 1:i + 21].min()),
                                 "at_20ms_n": float(mag[min(n - 1, i + 20)])})
    # rendered vs simulated while moving smoothly
    smooth = np.zeros(n, bool)
    for name, i0, i1 in res["phases"]:
        if name in ("insert", "slide"):
            smooth[i0 + 100:i1 - 100] = True
    for i in punct:
        smooth[max(0, i - 100):i + 100] = False
    diff = np.linalg.norm(res["rendered"] - res["simulated"], axis=1)
    out["render_minus_sim_max_n"] = float(diff[smooth].max()) if smooth.any() else 0.0
    # the rendering runs on the tissue's report of the tick before: compare with that tick's force
    lag1 = np.linalg.norm(res["rendered"][1:] - res["simulated"][:-1], axis=1)
    out["render_minus_sim_lag1_max_n"] = float(lag1[smooth[1:]].max()) if smooth.any() else 0.0
    if res["mode"] == "naive":  # the device gets the simulated force itself, at the same tick
        out["render_minus_sim_lag1_max_n"] = None
    # energy the device puts into the hand: the stylus pushes the hand with -hand_force
    p = -np.sum(res["hand_force"] * res["hand_v"], axis=1) * DT
    for name, i0, i1 in res["phases"]:
        if name == "lift_thrust":
            per = (i1 - i0) // 3
            out["energy_into_hand_j"]["lift_thrust_cycles"] = [float(p[i0 + k * per:i0 + (k + 1) * per].sum())
                                                               for k in range(3)]
    out["energy_into_hand_j"]["closed_session"] = float(p.sum())
    out["max_force_n"] = float(mag.max())
    out["mean_force_n"] = {name: float(mag[i0:i1].mean()) for name, i0, i1 in res["phases"]}
    out["limiting_ticks"] = int(np.count_nonzero(res["status"] & R.LIMITING))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    rows = {}
    for grip in (LOOSE, FIRM):
        for label, mode, vel in (("naive_raw_velocity", "naive", "raw"), ("naive_hd_velocity", "naive", "hd"),
                                 ("rendered", "rendered", "hd")):
            rows[f"{grip.name}/{label}"] = metrics(run(grip, mode, vel))
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    phases = list(next(iter(rows.values()))["buzz_n"])
    print("buzz (N RMS above 40 Hz) per phase")
    print(f"{'':32s}" + "".join(f"{p:>12s}" for p in phases))
    for key, m in rows.items():
        print(f"{key:32s}" + "".join(f"{m['buzz_n'][p]:12.4f}" for p in phases))
    for key, m in rows.items():
        pun = ", ".join(f"L{p['layer']} {p['before_n']:.2f}->{p['min_within_20ms_n']:.2f} ({p['at_20ms_n']:.2f}) N"
                        for p in m["punctures"])
        e = m["energy_into_hand_j"]
        lag1 = m["render_minus_sim_lag1_max_n"]
        print(f"{key}: punctures [{pun}]; |rendered - simulated| max {m['render_minus_sim_max_n']:.3f} N"
              + (f" (vs the tick before: {lag1:.3f} N); " if lag1 is not None else "; ") +
              f"energy into hand: cycles {[round(x * 1e3, 3) for x in e.get('lift_thrust_cycles', [])]} mJ, "
              f"session {e['closed_session'] * 1e3:.3f} mJ; max force {m['max_force_n']:.2f} N; "
              f"limiting ticks {m['limiting_ticks']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

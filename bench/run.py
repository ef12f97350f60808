"""Every measurement of ``haptic-acu bench``, the table and the JSON.

Pieces (each a function taking a :class:`Sizes`, returning part of the result dict):

* :func:`net_tables`: solving each net's static-response table (:mod:`haptic_acu.tissue.netresponse`),
  the one-off cost before a new set of net parameters' first tick.
* :func:`servo`: the servo step on the :mod:`bench.scenarios` paths, three ways: ``model.step``
  (a tick called from Python: through the step's C entry point, one pointer), ``step_kernel(*args)``
  alone (numba's dispatch of the same step with its 22 arrays), and ticks run inside one compiled
  loop (:func:`haptic_acu.servo.tick.run_ticks`, blocks of :data:`BLOCK` ticks, per-tick means: no
  Python at all); and the same paths through :mod:`bench.numpy_reference`; and, for comparison, the
  research mode ``solver.servo_net = "sweeps"`` (the net relaxed inside every tick).
* :func:`loop`: a real ``Session(clock="realtime")`` on a ``ScriptedDevice`` playing the default
  trajectory looped, with the visual loop doing springback, dent evaluation and rerun logging to a
  temporary .rrd file (the compiled servo loop, :mod:`haptic_acu.servo.rtloop`); in the full run also
  without rerun, with rerun in this process, with the servo loop in Python (``--python-servo``), and
  the machine's floor (a bare Python 1 kHz loop).
* :func:`omni_loop` (full run): ``haptic-acu run --device omni`` against the HD API emulator, with
  the compiled servo callback and with the Python one.
* :func:`closed_loop_buzz`: the closed-loop buzz table (bench/closed_loop.py): per phase, loose and
  firm grips, the rendering layer on the servo's own report (``--quick``: insertion and hold).
* :func:`sh`: SH evaluation (three layer meshes at 64 x 128 directions, lmax 15) and fitting
  (10,000 samples, lmax 15) against pyshtools (``MakeGridPoint``, ``SHExpandLSQ``, orthonormal
  harmonics with the Condon-Shortley phase: the same convention as ours, so coefficients map one
  to one), with the two fits' agreement.
* :func:`springback`, :func:`replay`, :func:`cold_start`, :func:`scaling`.
* :func:`first_run` (the first `make demo` replay with empty caches), :func:`cohort` (the
  cohort throughput of bench/cohort_bench.py).

The bench never fails on a number, only on a crash: targets are reported as pass/miss.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numba as nb
import numpy as np

from haptic_acu.base.errors import UserError

from . import measure, scenarios
from .measure import percentiles, ratio, time_calls
from haptic_acu.session.sink import Sink

BLOCK = 25  # ticks per compiled block in the "compiled" servo timing


@dataclasses.dataclass(frozen=True)
class Sizes:
    """How much of everything to measure."""

    servo_ticks: int  # timed ticks per scenario and per way of calling
    numpy_ticks: int  # timed ticks of the NumPy reference per scenario
    numpy_scenarios: tuple  # scenario names the NumPy reference runs on
    loop_s: float  # real-time session length
    loop_plain_s: float  # a second real-time session without rerun logging (0: none)
    sh_repeats: int  # evaluations / fits timed
    fit_samples: int
    sh_grid: tuple
    springback_calls: int
    replay_runs: int  # per mode (with / without .rrd)
    cold_runs: int  # measured runs
    cold_full_process: bool  # let the cold-start replays finish (process_total), or stop at the first tick
    scaling_ticks: int
    omni_s: float = 0.0  # the OMNI through the HD emulator, per servo callback (0: not measured)
    closed_loop_quick: bool = False  # the closed-loop rows on the insertion and the hold only
    scaling_w: tuple = (4, 8, 12, 16)
    scaling_lmax: tuple = (5, 10, 15, 20)
    trajectory: str | None = None  # None: the bundled default
    cohort_sessions: int = 8  # synthetic cohort replayed by `haptic-acu cohort` (0: not measured)
    cohort_session_s: float = 10.0  # trajectory seconds per session
    cohort_dask: bool = True  # also on a Dask LocalCluster (its overhead against the local pool)
    first_run: bool = True  # the first replay with empty numba and table caches
    end_to_end_runs: int = 3  # `haptic-acu replay` commands timed per mode (with / without .rrd; 0: not measured)
    end_to_end_batch: int = 4  # copies of the trajectory in the one batch command timed
    wheel_first_run: bool = True  # build the wheel, install it into a fresh venv, time its first command
    floor_s: float = 0.0  # the machine-floor loops' length (0: loop_plain_s, or 3 s without it)
    fem_mesh_ratio: float | None = None  # the FEM models' mesh grading in `models` (None: the model's own, fem.RATIO)


FULL = Sizes(servo_ticks=5000, numpy_ticks=1000,
             numpy_scenarios=("press_skin_w10", "press_muscle_w10", "inside_muscle"), loop_s=30.0, loop_plain_s=10.0,
             sh_repeats=20, fit_samples=10_000, sh_grid=(64, 128), springback_calls=5000, replay_runs=3,
             cold_runs=3, cold_full_process=True, scaling_ticks=3000, omni_s=10.0)
QUICK = dataclasses.replace(FULL, servo_ticks=2000, numpy_ticks=200, loop_s=5.0, loop_plain_s=0.0, sh_repeats=5,
                            springback_calls=1000, replay_runs=1, cold_runs=1, cold_full_process=False,
                            scaling_ticks=1000, numpy_scenarios=("press_skin_w10", "inside_muscle"), omni_s=0.0,
                            cohort_sessions=4, cohort_session_s=5.0, cohort_dask=False,
                            closed_loop_quick=True, end_to_end_runs=1, end_to_end_batch=2, wheel_first_run=False)

# The targets: (label, how to read the value from the result, comparison, limit, unit)
SERVO_HEADLINE = "press_skin_w10"


def _log(progress, msg):
    if progress:
        print(f"bench: {msg}", file=sys.stderr, flush=True)


# ---- servo step ----------------------------------------------------------------------------------

def _snapshot(model):
    return model.copy_state()


def _restore(model, snap):
    model.restore_state(snap)


@nb.njit(cache=True, nogil=True)
def empty_kernel(inp, m, s, diag):
    """Takes what :func:`haptic_acu.servo.step.step_kernel` takes and does nothing: calling it from
    Python costs exactly the dispatch and argument unboxing of a servo call."""
    return


def servo_scenario(sc: scenarios.Scenario, n: int, numpy_ticks: int = 0, ways=("step", "kernel", "compiled")) -> dict:
    """Time one scenario's ticks, the ways interleaved tick by tick (so each sees the same machine
    load), each on its own model brought to the same state:

    * ``step``: ``NeedleModel.step(p, v)``, a tick called from Python (the keyboard's loop, the
      ``--python-servo`` paths): p, v copied in, the step's C entry point called through ctypes;
    * ``kernel``: ``step_kernel(*args)`` with preassembled arguments (p, v written before),
      through numba's dispatcher;
    * ``dispatch``: :func:`empty_kernel` with the same arguments: the dispatcher's own cost;
    * ``compiled``: every :data:`BLOCK` ticks, those ticks inside one compiled loop
      (:func:`haptic_acu.servo.tick.run_ticks`, the loop the headless replay runs between frames); per-tick means,
      of wall time and (``compiled_cpu``) of the thread's CPU time: the tick's own cost without the
      host's preemptions.

    Optionally the NumPy reference on the same path (``numpy_ticks`` ticks, after the ones above).
    Returns percentile objects in microseconds.
    """
    from haptic_acu.servo.step import step_kernel
    from haptic_acu.servo.state import TIMING, Ring, Timing
    from haptic_acu.servo.tick import call_frames, run_ticks, tick_block, tick_table
    from haptic_acu.tissue.springback import Springback
    from haptic_acu.servo.samples import NCOL

    P = np.ascontiguousarray(sc.P[:n])
    V = np.ascontiguousarray(sc.V[:n])
    n = P.shape[0]
    R = np.ascontiguousarray(sc.R[:n])  # the needle's roll: every scenario twirls
    T = np.arange(n) * scenarios.DT
    models = {}
    for way in ("step", "kernel", "compiled"):
        if way not in ways:
            continue
        m = scenarios.model_for(sc.cfg)
        m.warm_up()
        for p, v in zip(sc.pre_P, sc.pre_V):
            m.step(p, v)
        scenarios.check_state(m, sc)
        models[way] = m
    any_model = next(iter(models.values()))
    out = {"particles": any_model.n[sc.layer] if sc.layer >= 0 else 0}
    buf = np.zeros((BLOCK, NCOL))
    if "compiled" in models:
        c = models["compiled"]
        rows = Ring(buf, np.zeros(1, np.int64))
        timing = Timing(np.zeros(1), np.zeros(1, TIMING))
        table = tick_table(c.servo, rows, timing)  # rows and timing outlive it
        snap = _snapshot(c)
        A = np.full_like(P, np.nan)  # no device axis: the step takes the direction of travel
        ticks = tick_block(P, V, A, R, T)
        no_ends = np.zeros(0, np.int64)
        sb = Springback.from_config(c, sc.cfg).args()
        call_frames(ticks[:1], 0, no_ends, table, *sb)  # load the compiled loop
        _restore(c, snap)
    if "kernel" in models:
        k = models["kernel"]
        k_args = k.kernel_args()
        kp, kv, kr = k.inp.p, k.inp.v, k.inp.roll
        empty_kernel(*k_args)
    times = {w: [] for w in ("step", "kernel", "dispatch", "compiled", "compiled_cpu")}
    clock = time.perf_counter_ns
    cpu_clock = time.thread_time_ns
    with measure.gc_paused():
        for i in range(n):
            if "step" in models:
                m = models["step"]
                t0 = clock()
                m.step(P[i], V[i], R[i])
                times["step"].append(clock() - t0)
            if "kernel" in models:
                kp[:] = P[i]
                kv[:] = V[i]
                kr[0] = R[i]
                t0 = clock()
                step_kernel(*k_args)
                t1 = clock()
                empty_kernel(*k_args)
                t2 = clock()
                times["kernel"].append(t1 - t0)
                times["dispatch"].append(t2 - t1)
            if "compiled" in models and (i + 1) % BLOCK == 0:
                s = i + 1 - BLOCK
                c0 = cpu_clock()
                t0 = clock()
                run_ticks(ticks, s, i + 1, 0, table)
                t1 = clock()
                times["compiled_cpu"].append((cpu_clock() - c0) / BLOCK)
                times["compiled"].append((t1 - t0) / BLOCK)
    for m in models.values():
        scenarios.check_state(m, sc)  # still the state being measured at the end of the path
    for way, t in times.items():
        if t:
            out[way] = percentiles(np.array(t), 1e-3)
    if len(models) > 1:
        f = [m.diag["force"].copy() for m in models.values()]
        out["ways_agree"] = all(np.array_equal(f[0], g) for g in f[1:])

    if numpy_ticks:
        from .numpy_reference import NumpyNeedle

        ref = NumpyNeedle(sc.cfg, any_model.tissue)
        for p, v in zip(sc.pre_P, sc.pre_V):
            ref.step(p, v)
        k = min(numpy_ticks, sc.P.shape[0])
        t_np = time_calls(lambda i: ref.step(sc.P[i], sc.V[i]), k)
        out["numpy"] = percentiles(t_np, 1e6)
        out["numpy_states_match"] = _same_phase(ref.states, sc)
    return out


def _same_phase(states, sc) -> bool:
    if sc.layer >= 0:
        return states[sc.layer] == scenarios.PRESSING
    return all(s == scenarios.PUNCTURED for s in states)


def servo(sizes: Sizes, progress=False) -> dict:
    scen = [scenarios.press(sizes.servo_ticks, layer=0, w=10), scenarios.press(sizes.servo_ticks, layer=2, w=10),
            scenarios.inside_muscle(sizes.servo_ticks)]
    res = {k: {} for k in ("servo_tick_us", "servo_kernel_us", "servo_dispatch_us", "servo_compiled_us",
                           "servo_tick_numpy_us", "speedup_vs_numpy", "servo_particles")}
    notes = []
    for sc in scen:
        _log(progress, f"servo step, {sc.name}")
        r = servo_scenario(sc, sizes.servo_ticks, sizes.numpy_ticks if sc.name in sizes.numpy_scenarios else 0)
        res["servo_tick_us"][sc.name] = r["step"]
        res["servo_kernel_us"][sc.name] = r["kernel"]
        res["servo_dispatch_us"][sc.name] = r["dispatch"]
        res["servo_compiled_us"][sc.name] = r.get("compiled")
        res["servo_particles"][sc.name] = r["particles"]
        if not r.get("ways_agree", True):
            notes.append(f"servo {sc.name}: the ways of calling the step ended with different forces")
        if "numpy" in r:
            res["servo_tick_numpy_us"][sc.name] = r["numpy"]
            res["speedup_vs_numpy"][sc.name] = ratio(r["numpy"]["p50"], r["step"]["p50"])
            if not r["numpy_states_match"]:
                notes.append(f"servo {sc.name}: the NumPy reference was not in the measured state")
    # The research mode, for comparison: the net relaxed by
    # solver.sweeps_per_tick Gauss-Seidel-Newton sweeps inside every tick.
    res["servo_tick_sweeps_us"] = {}
    for sc in scen:
        if sc.layer < 0:
            continue
        _log(progress, f"servo step, {sc.name}, net relaxed by sweeps every tick")
        sw = dataclasses.replace(sc, cfg=scenarios.config_copy(sc.cfg, servo_net="sweeps"))
        res["servo_tick_sweeps_us"][sc.name] = servo_scenario(sw, sizes.servo_ticks, ways=("step",))["step"]
    res["notes"] = notes
    return res


# The tissue models the bench times: every model.kind, then the FEM and BEM with a hemispherical tip
# (their contact set changes as the tip presses: the capacitance matrix's rank-one updates).
MODEL_VARIANTS = {"fem-hemi": ("fem", {"tip_shape": "hemisphere"}), "bem-hemi": ("bem", {"tip_shape": "hemisphere"})}


def models(sizes: Sizes, progress=False) -> dict:
    """Each tissue model (model.kind, and :data:`MODEL_VARIANTS`): the compiled tick pressing the
    skin and inside the muscle (microseconds per tick, p50/p99 of :data:`BLOCK`-tick means, of wall
    time and of the thread's CPU time), the precomputation's build time (the baselines' contact,
    uncached; the force net's three response tables; wall and CPU seconds) and its tables' memory."""
    from haptic_acu.base.config import MODEL_KINDS, load_config
    from haptic_acu.tissue import baselines, netresponse
    from haptic_acu.tissue.forcenet import NetParams

    out = {"model_tick_us": {}, "model_tick_cpu_us": {}, "model_build_s": {}, "model_build_cpu_s": {},
           "model_table_bytes": {}}
    base = load_config()
    fem_mesh = {"ratio": sizes.fem_mesh_ratio} if sizes.fem_mesh_ratio else None
    runs = {kind: (kind, {}) for kind in MODEL_KINDS} | MODEL_VARIANTS
    for label, (kind, extra) in runs.items():
        cfg = scenarios.with_kind(base, kind, **extra)
        _log(progress, f"tissue model {label}: precomputation")
        t0 = time.perf_counter()
        c0 = time.process_time()
        if kind == "forcenet":
            tol = cfg.solver.static_tolerance_um * 1e-6
            tabs = [netresponse.build(NetParams.from_layer(layer), tol) for layer in cfg.layers]
            nbytes = sum(t.F.nbytes + t.R.nbytes + t.D.nbytes for t in tabs)
        else:
            nbytes = baselines.build_contact(cfg, fem_mesh=fem_mesh).table_bytes
        out["model_build_s"][label] = round(time.perf_counter() - t0, 3)
        out["model_build_cpu_s"][label] = round(time.process_time() - c0, 3)  # on a loaded host, what an idle one pays
        out["model_table_bytes"][label] = int(nbytes)
        ticks, cpu = {}, {}
        for sc in (scenarios.press(sizes.servo_ticks, layer=0, base=cfg), scenarios.inside_muscle(sizes.servo_ticks, base=cfg)):
            _log(progress, f"tissue model {label}: {sc.name}")
            r = servo_scenario(sc, sizes.servo_ticks, ways=("compiled",))
            ticks[sc.name.split("_w")[0]] = r.get("compiled")
            cpu[sc.name.split("_w")[0]] = r.get("compiled_cpu")
        out["model_tick_us"][label] = ticks
        out["model_tick_cpu_us"][label] = cpu
    return {"models": out}


def net_tables(sizes: Sizes, progress=False) -> dict:
    """Solving each net's static-response table (netresponse.build, no cache): what the first
    session with a new set of net parameters pays once, before its first tick."""
    from haptic_acu.base.config import load_config
    from haptic_acu.tissue.forcenet import NetParams
    from haptic_acu.tissue.netresponse import build

    cfg = load_config()
    tol = cfg.solver.static_tolerance_um * 1e-6
    nets = [(layer.name, layer) for layer in cfg.layers]
    nets.append(("skin_w10_never_breaks", scenarios.press(1, layer=0, w=10).cfg.skin))
    out = {}
    for name, layer in nets:
        _log(progress, f"net table, {name}")
        t = build(NetParams.from_layer(layer), tol)
        out[name] = {"build_s": t.build_s, "rings": layer.rings, "rows": int(t.F.shape[1]),
                     "columns": int(t.F.shape[0]), "sweeps": t.sweeps,
                     "megabytes": (t.F.nbytes + t.R.nbytes + t.D.nbytes) / 1e6}
    return {"net_table_build": out}


# ---- real-time loop ------------------------------------------------------------------------------

def looped_trajectory(src, dst, min_duration_s: float) -> float:
    """Write ``src`` repeated back to back until it lasts ``min_duration_s``; returns its duration."""
    from haptic_acu.session.trajectory import TrajectoryWriter, load

    tr = load(src)
    t = tr.t_s - tr.t_s[0]
    period = t[-1] + (t[1] - t[0])
    copies = max(1, math.ceil(min_duration_s / period) + 1)
    with TrajectoryWriter(dst, comments=[f"{Path(src).name} repeated {copies} times (haptic-acu bench)"]) as w:
        for c in range(copies):
            w.append_rows(np.column_stack([t + c * period, tr.pos_m]))
    return copies * period - (t[1] - t[0])


class _DentProbe(Sink):
    """The visual loop's dent evaluation without rerun: reads every live dent grid each frame (the
    rerun sink does the same before logging them)."""

    def on_frame(self, frame):
        for k in frame.dents:
            frame.dents[k]


def realtime_session(cfg, trajectory, duration_s: float, rerun, tmp, progress=False, compiled_loop=True,
                     pin_cores=False) -> dict:
    """A real-time Session on the scripted device playing ``trajectory`` looped for ``duration_s``;
    with ``rerun``, logging to a .rrd file in ``tmp`` (falls back to dents only if the sink is
    missing); ``compiled_loop=False``: the Python servo loop instead of the compiled one. Returns the
    session's stats plus what ran."""
    from haptic_acu.devices.scripted import ScriptedDevice
    from haptic_acu.session.engine import Session

    traj = Path(tmp) / "looped.csv"
    looped_trajectory(trajectory, traj, duration_s + 1.0)
    dev = ScriptedDevice(traj, max_hand_speed_m_per_s=cfg.scene.max_hand_speed_m_per_s, realtime=True,
                         force_limit_n=cfg.safety.force_limit_n)
    dev.open()
    rrd = Path(tmp) / "loop.rrd"
    note = None
    sinks = [_DentProbe()]
    if rerun:
        try:
            if rerun == "inproc":
                from haptic_acu.session.rerun_log import RerunSink
                sinks = [RerunSink.to_file(rrd)]
            else:  # what `haptic-acu run --rrd` does: the logger in a child process
                import haptic_acu.session.rerun_log  # noqa: F401  (the child imports it; fail here if it cannot)
                from haptic_acu.session.sinkproc import rerun_file_sink
                sinks = [rerun_file_sink(rrd)]
        except ImportError as e:
            rerun = False
            note = f"rerun logging not available ({e}); the loop ran without it"
    session = Session(cfg, dev, sinks, clock="realtime", duration_s=duration_s, compiled_loop=compiled_loop,
                      pin_cores=pin_cores)
    session.warm_up()
    _log(progress, f"real-time loop, {duration_s:.0f} s, {'with' if rerun else 'without'} rerun logging"
         + ("" if compiled_loop else ", Python servo loop") + (", servo and logger pinned" if pin_cores else ""))
    with measure.StealSampler() as steal:
        result = session.run()  # the engine restores this thread's scheduling policy when the loop ends
    fifo = bool(result.stats.get("sched_fifo"))
    dev.close()
    st = dict(result.stats)
    errs = session._timing.errs
    n = min(session._n_err, errs.size)
    st["steal"] = measure.split_by_steal(errs[:n], session.t0_perf or 0.0, session.servo_dt, steal)
    st.update(rerun_rrd=bool(rerun), rerun_mode=rerun or "none", rrd_bytes=rrd.stat().st_size if rrd.exists() else 0, sched_fifo=bool(fifo),
              fault=result.fault, note=note)
    return st


def loop(sizes: Sizes, progress=False) -> dict:
    """The live session's loop: real time, visual loop with springback, dents and rerun logging; and, if
    ``sizes.loop_plain_s``, a shorter run without rerun logging, to tell its share of the tail."""
    from haptic_acu.base.config import load_config
    from haptic_acu.session.replay import DEFAULT_TRAJECTORY

    cfg = load_config()
    traj = sizes.trajectory or DEFAULT_TRAJECTORY
    notes = []
    with tempfile.TemporaryDirectory(prefix="haptic-acu-bench-") as tmp:
        st = realtime_session(cfg, traj, sizes.loop_s, "process", tmp, progress)
    if st["note"]:
        notes.append(st["note"])
    if st["fault"]:
        notes.append(f"real-time session stopped: {st['fault']}")
    out = {"loop_period_error_us": st["period_error_us"], "ticks": int(st["ticks"]),
           "missed_ticks": int(st["missed_ticks"]),
           "loop": {"duration_s": sizes.loop_s, "wall_s": st["wall_s"], "frames": st["frames"],
                    "servo_hz": st["servo_hz"], "visual_hz": st["visual_hz"], "dropped_rows": st["dropped_rows"],
                    "rerun_rrd": st["rerun_rrd"], "rrd_bytes": st["rrd_bytes"], "sched_fifo": st["sched_fifo"],
                    "fault": st["fault"]},
           "loop_steal": st["steal"], "loop_no_rerun": None, "notes": notes}
    if sizes.loop_plain_s:
        with tempfile.TemporaryDirectory(prefix="haptic-acu-bench-") as tmp:
            plain = realtime_session(cfg, traj, sizes.loop_plain_s, False, tmp, progress)
        out["loop_no_rerun"] = {"duration_s": sizes.loop_plain_s, "period_error_us": plain["period_error_us"],
                                "ticks": int(plain["ticks"]), "missed_ticks": int(plain["missed_ticks"]),
                                "frames": plain["frames"], "sched_fifo": plain["sched_fifo"], "fault": plain["fault"],
                                "steal": plain["steal"]}
        if plain["fault"]:
            notes.append(f"real-time session without rerun logging stopped: {plain['fault']}")
        with tempfile.TemporaryDirectory(prefix="haptic-acu-bench-") as tmp:
            inproc = realtime_session(cfg, traj, sizes.loop_plain_s, "inproc", tmp, progress)
        out["loop_rerun_in_process"] = {"duration_s": sizes.loop_plain_s, "period_error_us": inproc["period_error_us"],
                                        "ticks": int(inproc["ticks"]), "missed_ticks": int(inproc["missed_ticks"]),
                                        "fault": inproc["fault"], "steal": inproc["steal"]}
        # the servo thread pinned to one core, the logging child to the other (haptic_acu.servo.affinity)
        with tempfile.TemporaryDirectory(prefix="haptic-acu-bench-") as tmp:
            pin = realtime_session(cfg, traj, sizes.loop_plain_s, "process", tmp, progress, pin_cores=True)
        out["loop_pinned"] = {"duration_s": sizes.loop_plain_s, "period_error_us": pin["period_error_us"],
                              "ticks": int(pin["ticks"]), "missed_ticks": int(pin["missed_ticks"]),
                              "pinned": bool(pin.get("pinned")), "fault": pin["fault"], "steal": pin["steal"]}
        # for comparison: the same session with the servo loop in Python (--python-servo)
        with tempfile.TemporaryDirectory(prefix="haptic-acu-bench-") as tmp:
            py = realtime_session(cfg, traj, sizes.loop_plain_s, "process", tmp, progress, compiled_loop=False)
        out["loop_python_servo"] = {"duration_s": sizes.loop_plain_s, "period_error_us": py["period_error_us"],
                                    "ticks": int(py["ticks"]), "missed_ticks": int(py["missed_ticks"]),
                                    "fault": py["fault"], "steal": py["steal"]}
    floor_s = sizes.floor_s or sizes.loop_plain_s or 3.0
    out["machine_floor"] = machine_floor(floor_s, progress)
    out["compiled_floor"] = compiled_floor(floor_s, progress)
    return out


def machine_floor(duration_s: float, progress=False) -> dict:
    """The host's own floor: a bare Python 1 kHz loop (absolute deadlines, sleep-then-spin, SCHED_FIFO
    if allowed, switch interval 0.2 ms) doing no work. Whatever tail it shows is the machine's (a
    virtual machine's CPU can be taken away for milliseconds), not the simulator's."""
    from haptic_acu.servo.tick import SLEEP_AFTER_NS, SPIN_NS  # the engine's wait rule

    _log(progress, f"machine floor: a bare 1 kHz loop, {duration_s:.0f} s")
    sleep_after, spin = SLEEP_AFTER_NS / 1e9, SPIN_NS / 1e9
    old = sys.getswitchinterval()
    sys.setswitchinterval(2e-4)
    n = int(duration_s * 1000)
    errs = np.empty(n)
    perf = time.perf_counter
    steal = measure.StealSampler()
    steal.__enter__()
    try:
        with measure.sched_fifo():
            t0 = perf() + 0.01
            for k in range(n):
                d = t0 + k * 1e-3
                r = d - perf()
                if r > sleep_after:
                    time.sleep(r - spin)
                while perf() < d:
                    pass
                errs[k] = perf() - d
    finally:
        steal.__exit__(None, None, None)
        sys.setswitchinterval(old)
    return {"duration_s": duration_s, "period_error_us": percentiles(errs, 1e6), "ticks": n,
            "missed_ticks": int(np.count_nonzero(errs > 1e-3)),
            "steal": measure.split_by_steal(errs, t0, 1e-3, steal)}


def compiled_floor(duration_s: float, progress=False) -> dict:
    """The compiled loop's floor (:func:`measure.compiled_floor`): its timing rule with no work, alone
    on the servo's core as ``--pin-cores`` runs it."""
    _log(progress, f"machine floor: the compiled loop's timing with no work, pinned, {duration_s:.0f} s")
    return measure.compiled_floor(duration_s)


# ---- the OMNI, through the HD API emulator ----------------------------------------------------------

_SESSION_LINE = re.compile(r"session: (\d+) ticks in [\d.]+ s, (\d+) missed; period error p50 (\d+) us, "
                           r"p99 (\d+) us, max (\d+) us; (\w+) servo loop")


def closed_loop_buzz(sizes: Sizes, progress=False) -> dict:
    """The closed-loop rows (bench/closed_loop.py): a 45 g stylus held by a loose (0.3 N/mm)
    and a firm (2 N/mm) hand on the closed-loop session, the force rendered by the rendering layer from
    the servo's own report (DIAG ``r_*``), as the OMNI path does: buzz (N RMS above 40 Hz) per phase,
    puncture drops, rendered vs simulated, energy into the hand; the full run adds the naive path
    (no rendering layer) for comparison. ``--quick``: the insertion and the hold only."""
    from . import closed_loop

    quick = sizes.closed_loop_quick
    _log(progress, "closed loop: stylus, hand and rendering layer, loose and firm grips"
         + (" (insertion and hold)" if quick else ""))
    return {"closed_loop": closed_loop.buzz_table(quick=quick)}


def omni_loop(sizes: Sizes, progress=False) -> dict:
    """``haptic-acu run --device omni`` against the HD API emulator (tests/hd_emulator, built with
    the system C compiler), pressing the skin and letting go for ``sizes.omni_s``, with the compiled
    callback and with the Python one (``--python-servo``), rerun logging to a file in both. The
    emulator's 1 kHz scheduler thread asks for SCHED_FIFO (priority 10), as a servo thread on a
    real-time setup runs (``emulator_sched_fifo`` says whether it got it; if not, that thread's own
    jitter is in both figures). Period errors from the session's closing line (us, rounded)."""
    if not sizes.omni_s:
        return {"omni_loop": None}
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    try:
        from hd_emulator.build import build_emulator, emulator_env, find_compiler
    except ImportError as e:
        return {"omni_loop": None, "notes": [f"OMNI loop not measured: no HD emulator ({e})"]}
    finally:
        sys.path.pop(0)
    if find_compiler() is None:
        return {"omni_loop": None, "notes": ["OMNI loop not measured: no C compiler for the HD emulator"]}
    from haptic_acu.base.config import load_config

    z0 = -load_config().workspace.offset_mm[2]  # device z of the scene's z = 0 (the acupoint)
    knots, t = [(0.0, 0.0, 0.0, z0 + 5.0)], 0.0
    while t < sizes.omni_s + 2.0:  # press 1.2 mm into the skin and back, 0.6 s each way
        knots += [(t + 0.6, 0.0, 0.0, z0 - 1.2), (t + 1.2, 0.0, 0.0, z0 + 2.0)]
        t += 1.2
    out = {}
    with tempfile.TemporaryDirectory(prefix="haptic-acu-bench-") as tmp:
        lib = build_emulator(Path(tmp) / "hd")
        for servo in ("compiled", "python"):
            _log(progress, f"OMNI through the HD emulator, {sizes.omni_s:.0f} s, {servo} servo callback")
            env = emulator_env(lib, path=knots, nominal_max_force=3.3, sched_fifo=10)
            cmd = [sys.executable, "-m", "haptic_acu", "run", "--verbose", "--device", "omni", "--duration", str(sizes.omni_s),
                   "--no-status", "--rrd", str(Path(tmp) / f"{servo}.rrd"), "--out", str(Path(tmp) / f"{servo}-session")] + (["--python-servo"] if servo == "python" else [])
            proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
            m = _SESSION_LINE.search(proc.stderr)
            if proc.returncode != 0 or not m:
                out[servo] = {"error": proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else proc.returncode}
                continue
            ticks, missed, p50, p99, mx, kind = m.groups()
            out[servo] = {"ticks": int(ticks), "missed_ticks": int(missed), "period_error_us":
                          {"p50": float(p50), "p99": float(p99), "max": float(mx)}, "servo_loop": kind,
                          "emulator_sched_fifo": "hd_emulator: SCHED_FIFO" not in proc.stderr}
    return {"omni_loop": {"duration_s": sizes.omni_s, **out}}


# ---- spherical harmonics -------------------------------------------------------------------------

def to_pyshtools(coeffs: np.ndarray) -> np.ndarray:
    """Our real orthonormal coefficients (column l*l + l + m, Condon-Shortley phase) as a pyshtools
    ``cilm`` array for ``norm=4`` (orthonormal), ``csphase=-1``: the same functions, so
    cilm[0, l, m] = c[l, m] and cilm[1, l, m] = c[l, -m]."""
    from haptic_acu.tissue import shf

    lmax = shf.lmax_of(coeffs.size)
    cilm = np.zeros((2, lmax + 1, lmax + 1))
    for l in range(lmax + 1):
        base = l * l + l
        for m in range(l + 1):
            cilm[0, l, m] = coeffs[base + m]
            if m > 0:
                cilm[1, l, m] = coeffs[base - m]
    return cilm


def from_pyshtools(cilm: np.ndarray) -> np.ndarray:
    """Inverse of :func:`to_pyshtools`."""
    lmax = cilm.shape[1] - 1
    c = np.zeros((lmax + 1) ** 2)
    for l in range(lmax + 1):
        base = l * l + l
        c[base: base + l + 1] = cilm[0, l, : l + 1]
        for m in range(1, l + 1):
            c[base - m] = cilm[1, l, m]
    return c


def import_pyshtools():
    """The pyshtools module, or None when it is not installed (``pip install .[bench]``)."""
    try:
        import pyshtools
    except ImportError:
        return None
    return pyshtools


def lat_lon(theta, phi):
    """pyshtools' latitude and longitude (degrees) of our polar angle and azimuth (radians)."""
    return 90.0 - np.degrees(np.ravel(theta)), np.degrees(np.ravel(phi))


def fit_samples(n: int):
    """``n`` directions and the default skin surface's radius there (m): the fit benchmark's data."""
    from haptic_acu.base.config import load_config
    from haptic_acu.tissue.body import limb_radius, sample_directions

    body = load_config().body
    th, ph = sample_directions(n, seed=1)
    return th, ph, limb_radius(th, ph, np.array(body.semi_axes_mm) * 1e-3, body.bulge)


def sh(sizes: Sizes, coeffs: np.ndarray, progress=False) -> dict:
    """``coeffs``: the layer surfaces' coefficients (k, (lmax+1)^2), evaluated on the grid."""
    from haptic_acu.tissue import shf

    lmax = shf.lmax_of(coeffs.shape[1])
    T, P = shf.grid(*sizes.sh_grid)
    reps = sizes.sh_repeats
    _log(progress, "SH evaluation and fit")
    shf.evaluate(coeffs[0], T[:1, :1], P[:1, :1])
    ours = [None]

    def eval_ours(_):
        ours[0] = [shf.evaluate(c, T, P) for c in coeffs]

    res = {"sh_lmax": lmax, "sh_grid": list(sizes.sh_grid), "sh_surfaces": int(coeffs.shape[0]),
           "fit_samples": sizes.fit_samples}
    res["shf_eval_ms"] = percentiles(time_calls(eval_ours, reps), 1e3)
    th, ph, r = fit_samples(sizes.fit_samples)
    few = np.linspace(0, th.size - 1, 2 * (lmax + 1) ** 2).astype(int)  # spread over the sphere
    shf.fit(th[few], ph[few], r[few], lmax)  # load the basis kernel before timing
    fit_out = [None]

    def fit_ours(_):
        fit_out[0] = shf.fit(th, ph, r, lmax)

    res["shf_fit_ms"] = percentiles(time_calls(fit_ours, max(2, reps // 4)), 1e3)
    notes = []
    psh = import_pyshtools()
    res.update({"pyshtools_eval_ms": None, "pyshtools_fit_ms": None, "pyshtools_grid_dh_ms": None,
                "shf_speedup_vs_pyshtools": None, "sh_agreement_m": None})
    if psh is None:
        notes.append("pyshtools not installed: pip install '.[bench]' for the pyshtools rows")
        res["notes"] = notes
        return res
    res["pyshtools_version"] = psh.__version__
    lat, lon = lat_lon(T, P)
    cilms = [to_pyshtools(c) for c in coeffs]
    theirs = [None]

    def eval_theirs(_):
        theirs[0] = [psh.expand.MakeGridPoint(c, lat, lon, norm=4, csphase=-1) for c in cilms]

    eval_theirs(0)
    res["pyshtools_eval_ms"] = percentiles(time_calls(eval_theirs, reps), 1e3)
    # pyshtools' own grid: the FFT synthesis on its 64 x 128 Driscoll-Healy grid (other points).
    n_lat = sizes.sh_grid[0]
    dh = lambda _: [psh.expand.MakeGridDH(c, lmax=n_lat // 2 - 1, norm=4, csphase=-1, sampling=2) for c in cilms]
    dh(0)
    res["pyshtools_grid_dh_ms"] = percentiles(time_calls(dh, reps), 1e3)
    la, lo = lat_lon(th, ph)
    cilm_fit = [None]

    def fit_theirs(_):
        cilm_fit[0] = psh.expand.SHExpandLSQ(r, la, lo, lmax, norm=4, csphase=-1)[0]

    res["pyshtools_fit_ms"] = percentiles(time_calls(fit_theirs, max(2, reps // 4)), 1e3)
    res["shf_speedup_vs_pyshtools"] = {
        "eval": ratio(res["pyshtools_eval_ms"]["p50"], res["shf_eval_ms"]["p50"]),
        "fit": ratio(res["pyshtools_fit_ms"]["p50"], res["shf_fit_ms"]["p50"])}
    theirs_fit = from_pyshtools(cilm_fit[0])
    res["sh_agreement_m"] = {
        "eval_max_abs": float(max(np.abs(a.ravel() - b).max() for a, b in zip(ours[0], theirs[0]))),
        "fit_surface_max_abs": float(np.abs(shf.evaluate(fit_out[0], T, P) - shf.evaluate(theirs_fit, T, P)).max()),
        "fit_coeff_max_abs": float(np.abs(fit_out[0] - theirs_fit).max())}
    res["notes"] = notes
    return res


# ---- springback, replay, cold start, scaling -----------------------------------------------------

def springback(sizes: Sizes, progress=False) -> dict:
    """One visual-frame springback step of a w = 10 net and its margin rings, from a pressed shape."""
    from haptic_acu.tissue.springback import springback_step

    _log(progress, "springback")
    sc = scenarios.press(400, layer=0, w=10)
    model = scenarios.model_for(sc.cfg)
    for p, v in zip(np.vstack([sc.pre_P, sc.P]), np.vstack([sc.pre_V, sc.V])):
        model.step(p, v)
    idx = model.active_slot(0)
    X0 = model.X0[idx].copy()
    deformed = model.net_positions(idx)
    x = deformed.copy()
    goals = np.zeros_like(x)
    n_net = model.n[0]
    springback_step(x, X0, n_net, 0.5, goals)
    t = time_calls(lambda i: springback_step(x, X0, n_net, 0.5, goals), sizes.springback_calls,
                   lambda i: np.copyto(x, deformed))
    return {"springback_us": percentiles(t, 1e6), "springback_particles": int(x.shape[0]),
            "springback_net_particles": int(n_net)}


def replay(sizes: Sizes, progress=False) -> dict:
    """Simulated seconds per wall second of the headless replay (the session run, as
    ``haptic-acu replay`` reports it), without and with the .rrd recording; each mode after one
    untimed replay (the kernels loaded, the figure's and the logger's modules imported)."""
    from haptic_acu.session.replay import DEFAULT_TRAJECTORY, replay_one

    traj = sizes.trajectory or DEFAULT_TRAJECTORY
    runs = {"no_rrd": [], "rrd": []}
    cpu_runs = {"no_rrd": [], "rrd": []}
    notes = []
    with tempfile.TemporaryDirectory(prefix="haptic-acu-bench-") as tmp:
        for mode in ("no_rrd", "rrd"):
            _log(progress, f"replay, {mode.replace('_', ' ')}")
            try:  # untimed: its kernels loaded and its modules imported, as the compiled tick's are before timing
                replay_one(traj, Path(tmp) / f"{mode}-warm", rrd=(mode == "rrd"), progress=False)
            except ImportError:
                pass
            for i in range(sizes.replay_runs):
                try:
                    s = replay_one(traj, Path(tmp) / f"{mode}-{i}", rrd=(mode == "rrd"), progress=False)
                except ImportError as e:
                    notes.append(f"replay with .rrd not available ({e})")
                    break
                runs[mode].append(s["duration_s"] / s["_wall_s"])
                cpu_runs[mode].append(s["duration_s"] / s["_cpu_s"])
    med = {k: (float(np.median(v)) if v else None) for k, v in runs.items()}
    cpu = {k: (float(np.median(v)) if v else None) for k, v in cpu_runs.items()}
    return {"replay_speed_x": {**med, "runs": runs, "cpu": cpu, "cpu_runs": cpu_runs, "trajectory": Path(traj).name},
            "notes": notes}


# The third-party libraries a replay command loads (tests/test_startup.py checks that it does): a bare
# interpreter importing them is the floor under the command's wall time that no work of ours removes.
_REPLAY_LIBS = ("numpy", "scipy.linalg", "numba", "matplotlib.figure", "matplotlib.backends.backend_agg")
REPLAY_IMPORTS = {"no_rrd": _REPLAY_LIBS, "rrd": _REPLAY_LIBS + ("rerun",)}
# Any program that runs a numba kernel also pays numba's target set-up on its first one, cached or not
# (about 0.17 s on this host): the floor child loads one trivial cached kernel after its imports.
_FLOOR_KERNEL = "import numba\n\n\n@numba.njit(cache=True)\ndef one(x):\n    return x + 1.0\n"


def _floor_command(mode: str) -> list:
    """The floor child's command (run in the folder holding ``floor_kernel.py``): the imports of
    :data:`REPLAY_IMPORTS` and one call of a cached trivial kernel."""
    return [sys.executable, "-c", "import " + ", ".join(REPLAY_IMPORTS[mode]) + "; import floor_kernel; floor_kernel.one(1.0)"]


def end_to_end(sizes: Sizes, progress=False) -> dict:
    """The replay command as a user waits for it: the wall time of ``python -m haptic_acu replay TRAJ
    --quiet --out DIR`` (a child process, warm caches), with its .rrd (as ``make demo``) and with
    ``--no-rrd`` (the median of ``sizes.end_to_end_runs`` each), the replay's ticks (its
    summary.json), and one batch command of ``sizes.end_to_end_batch`` copies of the trajectory
    (``--jobs 1``: the start-up shared, not the cores), per file. :func:`ratios` sets them against
    the compiled tick."""
    if not sizes.end_to_end_runs:
        return {"end_to_end": None}
    import shutil

    from haptic_acu.session.replay import DEFAULT_TRAJECTORY

    traj = Path(sizes.trajectory or DEFAULT_TRAJECTORY)
    env = dict(os.environ)
    runs = {"rrd": [], "no_rrd": []}
    cpu = {"rrd": [], "no_rrd": []}
    floor = {"rrd": [], "no_rrd": []}
    ticks = None
    with tempfile.TemporaryDirectory(prefix="haptic-acu-e2e-") as tmp:
        tmp = Path(tmp)
        (tmp / "floor_kernel.py").write_text(_FLOOR_KERNEL)
        _timed_child(_floor_command("no_rrd"), env, tmp)  # untimed: the trivial kernel compiled and cached
        for i in range(sizes.end_to_end_runs):
            for mode in ("rrd", "no_rrd"):
                _log(progress, f"replay command, {mode.replace('_', ' ')}, run {i + 1}")
                out = tmp / f"{mode}-{i}"
                cmd = [sys.executable, "-m", "haptic_acu", "replay", str(traj), "--quiet", "--out", str(out)]
                runs[mode].append(_timed_child(cmd + (["--no-rrd"] if mode == "no_rrd" else []), env, tmp, cpu[mode]))
                ticks = json.loads((out / "summary.json").read_text())["ticks"]
                floor[mode].append(_timed_child(_floor_command(mode), env, tmp))
        batch = None
        if sizes.end_to_end_batch > 1:
            _log(progress, f"replay command, a batch of {sizes.end_to_end_batch}")
            src = tmp / "batch-in"
            src.mkdir()
            for j in range(sizes.end_to_end_batch):
                shutil.copy(traj, src / f"{traj.stem}-{j}.csv")
            cmd = [sys.executable, "-m", "haptic_acu", "replay", str(src), "--quiet", "--jobs", "1", "--out",
                   str(tmp / "batch-out")]
            batch = _timed_child(cmd, env, tmp) / sizes.end_to_end_batch
    med = {k: float(np.median(v)) for k, v in runs.items()}
    return {"end_to_end": {"trajectory": traj.name, "ticks": ticks, "cli_s": med, "runs": runs,
                           "cli_cpu_s": {k: float(np.median(v)) for k, v in cpu.items()},
                           "import_floor_s": {k: float(np.median(v)) for k, v in floor.items()},
                           "import_floor_modules": REPLAY_IMPORTS,
                           "batch_files": sizes.end_to_end_batch, "batch_per_file_s": batch,
                           "method": "wall time of `python -m haptic_acu replay TRAJ --quiet --out DIR` in a child "
                                     "process (caches warm), with the .rrd and with --no-rrd, and its CPU time (user + "
                                     "system: what a loaded host's waiting leaves out); the batch: one command "
                                     "on a folder of copies, --jobs 1, wall time over the files; the import "
                                     "floor: a bare interpreter importing the libraries the command loads and running one "
                                     "cached trivial numba kernel (numba's set-up on its first kernel)"}}


def wheel_first_run(sizes: Sizes, progress=False) -> dict:
    """The first command after installing the wheel: ``pip wheel`` of this source tree (its build
    compiles the kernels into the wheel, setup.py), installed with ``--no-deps`` into a fresh venv
    whose dependencies come from this environment through a path line, then ``haptic-acu replay
    TRAJ --quiet`` timed twice in it with an empty ``HAPTIC_ACU_CACHE``: ``first`` and ``warm``.
    None (with a note) outside a source tree."""
    if not sizes.wheel_first_run:
        return {"wheel_first_run_s": None}
    import sysconfig

    from haptic_acu.session.replay import DEFAULT_TRAJECTORY

    root = Path(__file__).resolve().parent.parent
    if not (root / "pyproject.toml").is_file() or not (root / "haptic_acu").is_dir():
        return {"wheel_first_run_s": None, "notes": ["wheel first run: not a source tree, nothing to build"]}
    traj = str(sizes.trajectory or DEFAULT_TRAJECTORY)
    with tempfile.TemporaryDirectory(prefix="haptic-acu-wheel-") as tmp:
        tmp = Path(tmp)
        _log(progress, "wheel first run: building the wheel (its kernels compile now)")
        env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "PYTHONPATH")}
        t = time.perf_counter()
        subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp / "dist"), str(root)],
                       check=True, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        build_s = time.perf_counter() - t
        (wheel,) = (tmp / "dist").glob("haptic_acu-*.whl")
        venv = tmp / "venv"
        subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
        subprocess.run([sys.executable, "-m", "pip", "--python", str(venv / "bin" / "python"), "install", "-q",
                        "--no-deps", "--no-index", str(wheel)], check=True, env=env, stdout=subprocess.DEVNULL)
        site = subprocess.run([str(venv / "bin" / "python"), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                              check=True, capture_output=True, text=True).stdout.strip()
        (Path(site) / "zz_bench_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
        env = dict(env, HAPTIC_ACU_CACHE=str(tmp / "tables"), PATH=str(venv / "bin") + os.pathsep + env.get("PATH", ""))
        out = {}
        for key in ("first", "warm"):
            _log(progress, f"wheel first run: {key}")
            cmd = [str(venv / "bin" / "haptic-acu"), "replay", traj, "--quiet", "--out", str(tmp / key)]
            out[key] = _timed_child(cmd, env, tmp)
    out.update(build_s=build_s, trajectory=Path(traj).name, method=(
        "pip wheel of this tree (setup.py compiles the kernels into it), installed --no-deps into a fresh venv, "
        "then `haptic-acu replay TRAJ --quiet` (with .rrd) twice with an empty HAPTIC_ACU_CACHE"))
    return {"wheel_first_run_s": out}


def ratios(res: dict) -> dict:
    """The figures a user meets, as ratios within this run: the replay command against its ticks'
    compute bound (ticks x the compiled tick's p50 pressing the skin), the replay's speed against
    that tick's (1 ms of simulated time per tick), a batch's file against one file's command, the
    first run against the warm one, Dask against the local pool. None where a part was not measured."""
    p50 = _get(res, "servo_compiled_us", SERVO_HEADLINE, "p50")
    e2e = res.get("end_to_end") or {}
    out = {}
    if p50 and e2e.get("ticks"):
        bound = e2e["ticks"] * p50 * 1e-6
        e2e.update(tick_p50_us=p50, bound_s=bound, tick_bound_x=1e3 / p50)
        out["replay_cli_rrd_vs_bound"] = e2e["cli_s"]["rrd"] / bound
        out["replay_cli_no_rrd_vs_bound"] = e2e["cli_s"]["no_rrd"] / bound
        if e2e.get("import_floor_s"):  # the part of the command that is ours: its time above the imports' floor
            out["import_floor_no_rrd_vs_bound"] = e2e["import_floor_s"]["no_rrd"] / bound
            out["replay_cli_rrd_above_floor_vs_bound"] = (e2e["cli_s"]["rrd"] - e2e["import_floor_s"]["rrd"]) / bound
            out["replay_cli_no_rrd_above_floor_vs_bound"] = (e2e["cli_s"]["no_rrd"]
                                                             - e2e["import_floor_s"]["no_rrd"]) / bound
        if e2e.get("cli_cpu_s"):  # CPU time: a loaded host's waiting left out, as the tick's p50 leaves it out
            out["replay_cli_rrd_cpu_vs_bound"] = e2e["cli_cpu_s"]["rrd"] / bound
            out["replay_cli_no_rrd_cpu_vs_bound"] = e2e["cli_cpu_s"]["no_rrd"] / bound
    if e2e.get("batch_per_file_s"):
        out["batch_per_file_vs_single"] = e2e["batch_per_file_s"] / e2e["cli_s"]["rrd"]
    speed = _get(res, "replay_speed_x", "no_rrd")
    out["replay_speed_vs_tick_bound"] = speed * p50 * 1e-3 if speed and p50 else None
    speed_cpu = _get(res, "replay_speed_x", "cpu", "no_rrd")
    out["replay_speed_cpu_vs_tick_bound"] = speed_cpu * p50 * 1e-3 if speed_cpu and p50 else None
    fr = res.get("first_run_s") or {}
    out["first_run_vs_warm"] = ratio(fr["empty_caches"], fr["after_install"]) if fr.get("after_install") else None
    wf = res.get("wheel_first_run_s") or {}
    out["wheel_first_vs_warm"] = ratio(wf["first"], wf["warm"]) if wf.get("warm") else None
    out["dask_vs_local"] = _get(res, "cohort", "dask", "overhead_x")
    return out


def cold_start(sizes: Sizes, progress=False) -> dict:
    """Process start to the first servo tick of ``python -m haptic_acu replay --no-rrd --quiet``,
    with a warm numba cache (:func:`collect` runs it after :func:`replay`, whose runs load or
    compile, and so cache, every kernel the replay calls).

    The child (:mod:`bench.cold_start_child`) is that command with the scripted device's
    ``set_force`` wrapped to print the wall-clock time of the first force command, which follows
    the first block of servo ticks; the parent takes its own wall clock just before starting the
    process. ``first_tick`` is the difference. With ``sizes.cold_full_process`` the child runs the
    whole replay (plots and files included) and ``process_total`` is its wall time, an upper bound;
    otherwise it is stopped at its first tick.
    """
    from haptic_acu.session.replay import DEFAULT_TRAJECTORY

    traj = str(sizes.trajectory or DEFAULT_TRAJECTORY)
    first, total = [], []
    with tempfile.TemporaryDirectory(prefix="haptic-acu-bench-") as tmp:
        for i in range(sizes.cold_runs):
            _log(progress, f"cold start, run {i + 1}")
            cmd = [sys.executable, "-m", "haptic_acu.bench.cold_start_child", "replay", traj, "--no-rrd", "--quiet",
                   "--out", str(Path(tmp) / f"run{i}")]
            t0 = time.time()
            # cwd: a clean folder, so nothing there can shadow the packages on sys.path
            proc = subprocess.Popen(cmd, cwd=tmp, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
            t_first = None
            lines = []
            for line in proc.stderr:
                m = re.match(r"FIRST_TICK_DONE ([0-9.]+)", line)
                if m:
                    t_first = float(m.group(1))
                    if not sizes.cold_full_process:
                        proc.kill()
                        break
                else:
                    lines.append(line)
            proc.stderr.close()
            rc = proc.wait()
            t1 = time.time()
            if t_first is None or (sizes.cold_full_process and rc != 0):
                tail = (lines or ["no output"])[-1].strip()
                raise RuntimeError(f"cold-start replay failed (exit {rc}): {tail}")
            first.append(t_first - t0)
            if sizes.cold_full_process:
                total.append(t1 - t0)
    return {"cold_start_s": {
        "first_tick": float(np.median(first)), "process_total": float(np.median(total)) if total else None,
        "runs_first_tick": first, "runs_process_total": total,
        "method": "parent's wall clock just before starting `python -m bench.cold_start_child replay --no-rrd "
                  "--quiet` to the child's wall clock at its first set_force (after the first servo ticks); "
                  "process_total: the whole replay process, an upper bound"}}


def cohort(sizes: Sizes, progress=False) -> dict:
    """Cohort throughput (:func:`bench.cohort_bench.measure`): a synthetic class of
    ``sizes.cohort_sessions`` sessions replayed by ``haptic-acu cohort`` on the local pool (and on a
    Dask LocalCluster unless ``sizes.cohort_dask`` is off)."""
    if not sizes.cohort_sessions:
        return {"cohort": None}
    from . import cohort_bench

    _log(progress, f"cohort, {sizes.cohort_sessions} sessions of {sizes.cohort_session_s:g} s")
    return {"cohort": cohort_bench.measure(sizes.cohort_sessions, sizes.cohort_session_s, dask=sizes.cohort_dask)}


def _timed_child(cmd, env, cwd, cpu: list | None = None) -> float:
    """The wall time of the child ``cmd``; its CPU time (user + system, from the children's rusage)
    appended to ``cpu`` if given."""
    import resource

    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run(cmd, env=env, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        tail = (p.stderr.strip().splitlines() or ["no output"])[-1]
        raise RuntimeError(f"{' '.join(str(c) for c in cmd[:4])} ... failed (exit {p.returncode}): {tail}")
    if cpu is not None:
        cpu.append((r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime))
    return wall


def first_run(sizes: Sizes, progress=False) -> dict:
    """The first ``make demo`` replay (``haptic-acu replay`` of the bundled default, .rrd included),
    in child processes whose numba cache (``NUMBA_CACHE_DIR``) and net-table cache
    (``HAPTIC_ACU_CACHE``) start as empty temporary folders: ``empty_caches`` is a first run with
    nothing cached (what a plain ``pip install`` gives); ``after_install`` the same replay once the
    caches hold what that first run (the same work ``make``'s ``python -m haptic_acu.cli.precompile``
    does at install) left there: the target is under 10 s."""
    if not sizes.first_run:
        return {"first_run_s": None}
    from haptic_acu.session.replay import DEFAULT_TRAJECTORY

    traj = str(sizes.trajectory or DEFAULT_TRAJECTORY)
    out = {}
    with tempfile.TemporaryDirectory(prefix="haptic-acu-first-run-") as tmp:
        env = dict(os.environ, NUMBA_CACHE_DIR=str(Path(tmp) / "numba"), HAPTIC_ACU_CACHE=str(Path(tmp) / "tables"))
        for key, run_dir in (("empty_caches", "cold"), ("after_install", "warm")):
            _log(progress, f"first run, {key.replace('_', ' ')}")
            cmd = [sys.executable, "-m", "haptic_acu", "replay", traj, "--quiet", "--out", str(Path(tmp) / run_dir)]
            out[key] = _timed_child(cmd, env, tmp)
    out["trajectory"] = Path(traj).name
    out["method"] = ("wall time of `python -m haptic_acu replay TRAJ --quiet --out DIR` (with .rrd, as make demo) in a "
                     "child with NUMBA_CACHE_DIR and HAPTIC_ACU_CACHE at empty temporary folders; after_install: "
                     "the same replay again, the caches filled by the first")
    return {"first_run_s": out}


def scaling(sizes: Sizes, progress=False) -> dict:
    """Servo tick (model.step, skin pressed) for several net sizes; SH evaluation of one surface on
    the grid for several degrees."""
    from haptic_acu.tissue import shf

    out = {"servo_tick_us": {}, "servo_tick_sweeps_us": {}, "particles": {}, "sh_eval_ms": {},
           "sh_eval_point_us": {}}
    for w in sizes.scaling_w:
        _log(progress, f"scaling, w = {w}")
        sc = scenarios.press(sizes.scaling_ticks, layer=0, w=w)
        r = servo_scenario(sc, sizes.scaling_ticks, ways=("step",))
        out["servo_tick_us"][str(w)] = r["step"]
        out["particles"][str(w)] = r["particles"]
        sw = dataclasses.replace(sc, cfg=scenarios.config_copy(sc.cfg, servo_net="sweeps"))
        out["servo_tick_sweeps_us"][str(w)] = servo_scenario(sw, sizes.scaling_ticks, ways=("step",))["step"]
    T, P = shf.grid(*sizes.sh_grid)
    rng = np.random.default_rng(0)
    for lmax in sizes.scaling_lmax:
        c = rng.standard_normal((lmax + 1) ** 2) / (1.0 + np.arange((lmax + 1) ** 2))
        shf.evaluate(c, T[:1, :1], P[:1, :1])
        t = time_calls(lambda i: shf.evaluate(c, T, P), max(3, sizes.sh_repeats))
        out["sh_eval_ms"][str(lmax)] = percentiles(t, 1e3)
        out["sh_eval_point_us"][str(lmax)] = out["sh_eval_ms"][str(lmax)]["p50"] * 1e3 / T.size
    return {"scaling": out}


# ---- targets, table, JSON ------------------------------------------------------------------------

def _get(res, *path):
    for p in path:
        if res is None:
            return None
        res = res.get(p) if isinstance(res, dict) else None
    return res


def targets(res: dict) -> list[dict]:
    """The targets, each with the measured value and pass / miss (None: not measured)."""
    ticks = res.get("ticks") or 0
    missed = res.get("missed_ticks")
    rows = [
        ("servo tick p99, w=10 pressing skin (us)", _get(res, "servo_tick_us", SERVO_HEADLINE, "p99"), "<=", 30.0),
        ("speedup over the NumPy reference, w=10 (x)", _get(res, "speedup_vs_numpy", SERVO_HEADLINE), ">=", 20.0),
        ("loop period error p99 (us)", _get(res, "loop_period_error_us", "p99"), "<=", 100.0),
        ("loop period error p99.9 (us)", _get(res, "loop_period_error_us", "p999"), "<=", 500.0),
        ("missed ticks per 10,000", (1e4 * missed / ticks) if ticks and missed is not None else None, "<=", 1.0),
        ("SH eval vs pyshtools (x faster)", _get(res, "shf_speedup_vs_pyshtools", "eval"), ">=", 1.0),
        ("SH fit vs pyshtools (x faster)", _get(res, "shf_speedup_vs_pyshtools", "fit"), ">=", 1.0),
        ("SH fit agreement with pyshtools (m)", _get(res, "sh_agreement_m", "fit_surface_max_abs"), "<=", 1e-10),
        ("springback step p99 (us)", _get(res, "springback_us", "p99"), "<=", 100.0),
        ("replay without .rrd (x real time)", _get(res, "replay_speed_x", "no_rrd"), ">=", 50.0),
        ("replay with .rrd (x real time)", _get(res, "replay_speed_x", "rrd"), ">=", 10.0),
        ("cold start to first tick (s)", _get(res, "cold_start_s", "first_tick"), "<=", 5.0),
        ("first make demo replay after install (s)", _get(res, "first_run_s", "after_install"), "<=", 10.0),
        ("replay command with .rrd / its ticks' compute bound (x)", _get(res, "ratios", "replay_cli_rrd_vs_bound"),
         "<=", 20.0),
        ("replay command --no-rrd / its ticks' compute bound (x)", _get(res, "ratios", "replay_cli_no_rrd_vs_bound"),
         "<=", 8.0),
        ("replay speed / the compiled tick's (frac)", _get(res, "ratios", "replay_speed_vs_tick_bound"), ">=", 0.7),
        ("first command after a wheel install / warm (x)", _get(res, "ratios", "wheel_first_vs_warm"), "<=", 4.0),
        ("cohort on Dask / the local pool (x)", _get(res, "ratios", "dask_vs_local"), "<=", 1.1),
    ]
    md = res.get("models") or {}
    skin = [t["press_skin"]["p99"] for t in md.get("model_tick_cpu_us", {}).values() if t.get("press_skin")]
    rows.append(("tissue model tick p99 pressing skin, worst, CPU (us)", max(skin) if skin else None, "<=", 50.0))
    build = list(md.get("model_build_cpu_s", {}).values())
    rows.append(("tissue model precomputation, worst, CPU (s)", max(build) if build else None, "<=", 30.0))
    cl = res.get("closed_loop") or {}
    for grip in ("loose", "firm"):
        m = (cl.get(grip) or {}).get("rendered")
        rows.append((f"closed-loop buzz, {grip} grip, worst phase (N)",
                     max(m["buzz_n"].values()) if m else None, "<=", 0.02))
        rows.append((f"closed-loop puncture drop, {grip}, worst (frac)",
                     max((p["min_within_20ms_n"] / p["before_n"] for p in m["punctures"] if p["before_n"] > 0),
                         default=None) if m else None, "<=", 0.5))
    out = []
    for label, value, op, limit in rows:
        ok = None if value is None else (value <= limit if op == "<=" else value >= limit)
        out.append({"target": label, "value": value, "op": op, "limit": limit, "pass": ok})
    return out


REQUIRED_KEYS = ("machine", "servo_tick_us", "servo_kernel_us", "servo_dispatch_us", "servo_compiled_us",
                 "servo_tick_sweeps_us", "net_table_build",
                 "servo_tick_numpy_us", "speedup_vs_numpy", "loop_period_error_us", "ticks", "missed_ticks",
                 "loop_no_rerun", "machine_floor", "compiled_floor", "shf_eval_ms", "shf_fit_ms",
                 "pyshtools_eval_ms", "pyshtools_fit_ms", "shf_speedup_vs_pyshtools", "sh_agreement_m",
                 "springback_us", "replay_speed_x", "cold_start_s", "scaling", "closed_loop", "targets", "notes",
                 "cohort", "first_run_s", "end_to_end", "wheel_first_run_s", "ratios")


def collect(sizes: Sizes, progress=False) -> dict:
    """Run every piece; the result dict (the JSON)."""
    from haptic_acu.base.config import load_config

    t0 = time.perf_counter()
    res = {"quick": sizes == QUICK, "sizes": dataclasses.asdict(sizes), "machine": measure.machine_info()}
    notes = []
    walls = {}
    tissue = scenarios.tissue_for(load_config())
    pieces = [("net_tables", lambda: net_tables(sizes, progress)),
              ("servo", lambda: servo(sizes, progress)),
              ("models", lambda: models(sizes, progress)),
              ("sh", lambda: sh(sizes, tissue.coeffs[:3], progress)),
              ("springback", lambda: springback(sizes, progress)),
              ("scaling", lambda: scaling(sizes, progress)),
              ("replay", lambda: replay(sizes, progress)),
              ("cold_start", lambda: cold_start(sizes, progress)),  # after replay: warm numba cache
              ("end_to_end", lambda: end_to_end(sizes, progress)),
              ("wheel_first_run", lambda: wheel_first_run(sizes, progress)),
              ("first_run", lambda: first_run(sizes, progress)),  # its own empty caches
              ("cohort", lambda: cohort(sizes, progress)),
              ("loop", lambda: loop(sizes, progress)),
              ("omni_loop", lambda: omni_loop(sizes, progress)),
              ("closed_loop", lambda: closed_loop_buzz(sizes, progress))]
    for name, fn in pieces:
        t = time.perf_counter()
        part = fn()
        walls[name] = round(time.perf_counter() - t, 2)
        notes += part.pop("notes", [])
        res.update(part)
    res["piece_wall_s"] = walls
    res["machine"]["pyshtools"] = res.pop("pyshtools_version", None)
    res["machine"]["load_average_end"] = measure.load_average()
    res["notes"] = notes
    res["ratios"] = ratios(res)
    res["targets"] = targets(res)
    res["bench_wall_s"] = time.perf_counter() - t0
    return res


def _fmt(x, digits=3):
    if x is None:
        return "-"
    if isinstance(x, (int, np.integer)):
        return str(x)
    if x != 0 and (abs(x) >= 1e5 or abs(x) < 1e-3):
        return f"{x:.2e}"
    return f"{x:.{digits}g}"


def model_lines(md) -> list:
    """One row per tissue model (model.kind): compiled tick pressing the skin and inside the muscle
    (p50 / p99 of wall time, p99 of CPU time, us), precomputation time (wall, CPU) and table memory."""
    if not md:
        return []
    lines = ["tissue models: compiled tick, us (wall p50 / p99, CPU p99); precomputation; tables",
             f"  {'':9s}{'press skin':>22s}{'inside muscle':>22s}{'build s':>8s}{'cpu s':>7s}{'kB':>10s}"]
    cpu_ticks = md.get("model_tick_cpu_us", {})
    for kind, ticks in md["model_tick_us"].items():
        cells = ""
        for sc in ("press_skin", "inside_muscle"):
            t, c = ticks.get(sc), cpu_ticks.get(kind, {}).get(sc)
            cells += f"{(_fmt(t['p50']) + ' / ' + _fmt(t['p99'])) if t else '-':>15s}{_fmt(c['p99']) if c else '-':>7s}"
        cpu = md.get("model_build_cpu_s", {}).get(kind)
        lines.append(f"  {kind:9s}{cells}{_fmt(md['model_build_s'][kind]):>8s}{_fmt(cpu) if cpu is not None else '-':>7s}"
                     f"{_fmt(md['model_table_bytes'][kind] / 1e3):>10s}")
    return lines


def closed_loop_lines(cl) -> list:
    """The closed-loop buzz table: per grip, buzz per phase (N RMS above 40 Hz), then the punctures,
    rendered vs simulated and the energy into the hand."""
    if not cl:
        return []
    phases = list(next(iter(cl.values()))["rendered"]["buzz_n"])
    lines = ["closed loop (45 g stylus, hand grip, rendering layer): buzz, N RMS above 40 Hz",
             f"  {'':26s}" + "".join(f"{p:>12s}" for p in phases)]
    for grip, rows in cl.items():
        for label, m in rows.items():
            lines.append(f"  {grip + ', ' + label:26s}" + "".join(f"{_fmt(m['buzz_n'].get(p)):>12s}" for p in phases))
    for grip, rows in cl.items():
        m = rows["rendered"]
        pun = ", ".join(f"layer {p['layer']} {p['before_n']:.2f} -> {p['min_within_20ms_n']:.2f} N"
                        for p in m["punctures"])
        lag1 = m.get("render_minus_sim_lag1_max_n")
        lines.append(f"  {grip}: punctures (before -> least within 20 ms) {pun}; |rendered - simulated| max "
                     f"{_fmt(m['render_minus_sim_max_n'])} N (vs the tick before {_fmt(lag1)} N) while moving "
                     f"smoothly; energy into the hand over the session {_fmt(m['energy_into_hand_j']['closed_session'] * 1e3)} mJ")
    return lines


_TABLE_HEAD = f"{'':46s} {'p50':>9s} {'p99':>9s} {'p99.9':>9s} {'max':>9s}"


def _prow(lines: list, label: str, p) -> None:
    """One percentile row (p50, p99, p99.9, max), or a dash where not measured."""
    if p is None:
        lines.append(f"{label:46s} {'-':>9s}")
    else:
        lines.append(f"{label:46s} " + " ".join(f"{_fmt(p[k]):>9s}" for k in ("p50", "p99", "p999", "max")))


def _loop_row(lines: list, r, label: str, extra: str = "") -> None:
    """One loop's period-error row (``label`` with ``{s}``: its seconds), its tick count, and the
    host's stolen-CPU line (nothing if the loop was not run)."""
    if not r:
        return
    _prow(lines, label.format(s=f"{r['duration_s']:.0f}"), r["period_error_us"])
    lines.append(f"  {r['ticks']} ticks, {r['missed_ticks']} missed"
                 + ("" if r.get("pinned", True) else " (pinning refused: ran unpinned)") + extra
                 + (f"; STOPPED: {r['fault']}" if r.get("fault") else ""))
    _steal_line(lines, r.get("steal"))


def _share(loop, floor) -> str:
    """The pinned loop's misses beside its floor's (per 10,000 ticks): how many the session adds."""
    if not loop or not loop.get("ticks") or not floor.get("ticks"):
        return ""
    a = 1e4 * loop["missed_ticks"] / loop["ticks"]
    b = 1e4 * floor["missed_ticks"] / floor["ticks"]
    return f"; per 10,000 ticks: the pinned session {a:.1f}, this floor {b:.1f}"


def _steal_line(lines: list, st) -> None:
    """The host's stolen-CPU line under a loop row (nothing if not measured)."""
    if not st or not st.get("available") or "steal_share" not in st:
        return
    q = st.get("quiet_period_error_us")
    line = (f"  host: {100 * st['steal_share']:.1f}% of CPU time stolen by the hypervisor; in the "
            f"{st['quiet_windows']} of {st['windows']} windows of 0.25 s with none stolen: "
            f"{st['quiet_missed']} missed in {st['quiet_ticks']} ticks")
    if q:
        line += f", p99 {_fmt(q['p99'])} us, p99.9 {_fmt(q['p999'])} us"
    line += f"; elsewhere {st['other_missed']} missed in {st['other_ticks']}"
    lines.append(line)


def _table_servo(res: dict, lines: list) -> None:
    """The machine line, then the servo tick's rows per net size and the net tables' builds."""
    prow = functools.partial(_prow, lines)
    m = res["machine"]
    lines.append(f"haptic-acu bench ({'quick' if res.get('quick') else 'full'}) on {m['cpu']}, "
                 f"{m['cores_available']} cores, python {m['python']}, numpy {m['numpy']}, numba {m['numba']}, "
                 f"{m['date']}; load average {m['load_average_start']} -> {m.get('load_average_end')}")

    lines.append("")
    lines.append(_TABLE_HEAD)
    for name in res["servo_tick_us"]:
        lines.append(f"servo tick, {name} ({res['servo_particles'][name]} particles)")
        prow("  model.step (us)", res["servo_tick_us"][name])
        prow("  step_kernel alone (us)", res["servo_kernel_us"][name])
        prow("  call overhead: empty kernel, same args (us)", res["servo_dispatch_us"][name])
        prow(f"  in a compiled loop, per tick of {BLOCK} (us)", res["servo_compiled_us"][name])
        if name in res["servo_tick_numpy_us"]:
            prow("  NumPy reference (us)", res["servo_tick_numpy_us"][name])
            lines.append(f"  speedup over NumPy (p50): {_fmt(res['speedup_vs_numpy'][name])}x")
        if name in res.get("servo_tick_sweeps_us", {}):
            prow("  net relaxed by sweeps every tick instead (us)", res["servo_tick_sweeps_us"][name])
    for name, t in res.get("net_table_build", {}).items():
        lines.append(f"net table {name} (w={t['rings']}): solved in {_fmt(t['build_s'])} s, {t['rows']} rows x "
                     f"{t['columns']} columns, {_fmt(t['megabytes'])} MB (cached after the first session)")


def _table_loops(res: dict, lines: list) -> None:
    """The real-time loops' period errors (compiled, without rerun, Python servo, floor, OMNI)."""
    prow = functools.partial(_prow, lines)
    lp = res["loop"]
    prow(f"loop period error, {lp['duration_s']:.0f} s real time (us)", res["loop_period_error_us"])
    lines.append(f"  {res['ticks']} ticks, {res['missed_ticks']} missed, {lp['frames']} frames "
                 f"({_fmt(lp['visual_hz'])} Hz), rerun .rrd: {'yes' if lp['rerun_rrd'] else 'NO'}, "
                 f"SCHED_FIFO: {'yes' if lp['sched_fifo'] else 'no'}"
                 + (f"; STOPPED: {lp['fault']}" if lp["fault"] else ""))
    _steal_line(lines, res.get("loop_steal"))
    for key, what in (("loop_no_rerun", "without rerun logging"), ("loop_rerun_in_process", "rerun logging in this process"),
                      ("loop_pinned", "servo thread and logging child pinned apart"),
                      ("loop_python_servo", "servo loop in Python instead")):
        _loop_row(lines, res.get(key), f"  same, {{s}} s, {what} (us)")
    mf = res.get("machine_floor")
    _loop_row(lines, mf, "  machine floor: bare Python 1 kHz loop, {s} s (us)", " (the host's share of any tail)")
    cf = res.get("compiled_floor")
    if cf:
        _loop_row(lines, cf, "  machine floor: compiled loop timing, no work, pinned, {s} s (us)",
                  f", SCHED_FIFO: {'yes' if cf['sched_fifo'] else 'no'}" + _share(res.get("loop_pinned"), cf))
    om = res.get("omni_loop")
    if om:
        for servo in ("compiled", "python"):
            r = om.get(servo) or {}
            if "period_error_us" in r:
                pe = r["period_error_us"]
                lines.append(f"OMNI via the HD emulator, {om['duration_s']:.0f} s, {servo} callback: period error p50 "
                             f"{_fmt(pe['p50'])} us, p99 {_fmt(pe['p99'])} us, max {_fmt(pe['max'])} us; "
                             f"{r['missed_ticks']} missed in {r['ticks']} ticks; emulator's scheduler thread "
                             + ("SCHED_FIFO" if r.get("emulator_sched_fifo") else "ordinary (SCHED_FIFO refused)"))
            else:
                lines.append(f"OMNI via the HD emulator, {servo} callback: failed ({r.get('error')})")
    lines += closed_loop_lines(res.get("closed_loop"))
    lines += model_lines(res.get("models"))


def _table_kernels(res: dict, lines: list) -> None:
    """SH evaluation and fit (and pyshtools), springback, replay speed, cold start, scaling."""
    prow = functools.partial(_prow, lines)
    g = res["sh_grid"]
    prow(f"SH eval, {res['sh_surfaces']} surfaces at {g[0]}x{g[1]}, lmax {res['sh_lmax']} (ms)", res["shf_eval_ms"])
    if res["pyshtools_eval_ms"] is None:
        lines.append(f"{'  pyshtools MakeGridPoint':46s} pyshtools not installed")
    else:
        prow("  pyshtools MakeGridPoint, same points (ms)", res["pyshtools_eval_ms"])
        prow("  pyshtools MakeGridDH, its own grid (ms)", res["pyshtools_grid_dh_ms"])
    prow(f"SH fit, {res['fit_samples']} samples, lmax {res['sh_lmax']} (ms)", res["shf_fit_ms"])
    if res["pyshtools_fit_ms"] is None:
        lines.append(f"{'  pyshtools SHExpandLSQ':46s} pyshtools not installed")
    else:
        prow("  pyshtools SHExpandLSQ (ms)", res["pyshtools_fit_ms"])
        a = res["sh_agreement_m"]
        lines.append(f"  agreement with pyshtools: eval {_fmt(a['eval_max_abs'])} m, fitted surface "
                     f"{_fmt(a['fit_surface_max_abs'])} m")
    prow(f"springback step, {res['springback_particles']} particles (us)", res["springback_us"])
    rs = res["replay_speed_x"]
    lines.append(f"replay {rs['trajectory']}: {_fmt(rs['no_rrd'])}x real time without .rrd, "
                 f"{_fmt(rs['rrd'])}x with it")
    cs = res["cold_start_s"]
    lines.append(f"cold start: first servo tick {_fmt(cs['first_tick'])} s after process start"
                 + (f" (whole replay process {_fmt(cs['process_total'])} s)" if cs["process_total"] else ""))
    fr = res.get("first_run_s")
    if fr:
        lines.append(f"first run of make demo ({fr['trajectory']}, .rrd included): {_fmt(fr['empty_caches'])} s with "
                     f"empty numba and table caches, {_fmt(fr['after_install'])} s once they are filled (after install)")
    wf = res.get("wheel_first_run_s")
    if wf:
        lines.append(f"first command after installing the wheel into a fresh venv: {_fmt(wf['first'])} s, then "
                     f"{_fmt(wf['warm'])} s warm (the wheel built, kernels compiled into it, in {_fmt(wf['build_s'])} s)")
    e2e, r = res.get("end_to_end"), res.get("ratios") or {}
    if e2e:
        lines.append(f"replay command ({e2e['trajectory']}, {e2e['ticks']} ticks): {_fmt(e2e['cli_s']['rrd'])} s with "
                     f".rrd, {_fmt(e2e['cli_s']['no_rrd'])} s without: {_fmt(r.get('replay_cli_rrd_vs_bound'))}x and "
                     f"{_fmt(r.get('replay_cli_no_rrd_vs_bound'))}x the ticks' compiled bound "
                     f"({_fmt(e2e.get('bound_s'))} s); a batch of {e2e['batch_files']}: "
                     f"{_fmt(e2e['batch_per_file_s'])} s per file")
    if e2e and e2e.get("import_floor_s"):
        fl = e2e["import_floor_s"]
        lines.append(f"  the imports alone (a bare interpreter loading numpy, scipy, numba, matplotlib, and rerun "
                     f"with the .rrd, and running one cached trivial kernel): {_fmt(fl['rrd'])} s and {_fmt(fl['no_rrd'])} s, "
                     f"{_fmt(r.get('import_floor_no_rrd_vs_bound'))}x the bound without .rrd; the command above "
                     f"them: {_fmt(r.get('replay_cli_rrd_above_floor_vs_bound'))}x and "
                     f"{_fmt(r.get('replay_cli_no_rrd_above_floor_vs_bound'))}x")
    if r.get("replay_cli_no_rrd_cpu_vs_bound") is not None:
        lines.append(f"  in CPU time: {_fmt(e2e['cli_cpu_s']['rrd'])} s and {_fmt(e2e['cli_cpu_s']['no_rrd'])} s, "
                     f"{_fmt(r['replay_cli_rrd_cpu_vs_bound'])}x and {_fmt(r['replay_cli_no_rrd_cpu_vs_bound'])}x the bound")
    if r.get("replay_speed_vs_tick_bound") is not None:
        lines.append(f"replay speed against the compiled tick's bound: {_fmt(r['replay_speed_vs_tick_bound'])}"
                     + (f" (in the session's CPU time {_fmt(r['replay_speed_cpu_vs_tick_bound'])})"
                        if r.get("replay_speed_cpu_vs_tick_bound") is not None else ""))
    co = res.get("cohort")
    if co:
        loc = co["local"]
        lines.append(f"cohort: {co['sessions']} sessions of {_fmt(co['session_s'])} s on {co['workers']} workers: "
                     f"{_fmt(loc['sessions_per_s_per_core'])} sessions/s per core, {_fmt(loc['sim_s_per_wall_s'])}x "
                     f"real time (replays {_fmt(loc['replay_s'])} s, all {_fmt(loc['total_s'])} s)")
        if co.get("dask"):
            d = co["dask"]
            lines.append(f"  on a Dask LocalCluster: {_fmt(d['replay_s'])} s, overhead {_fmt(d['overhead_x'])}x "
                         f"({_fmt(d['overhead_with_cluster_start_x'])}x with the cluster's start); identical tables: "
                         f"{'yes' if d['identical_tables'] else 'NO'}")
    sc = res["scaling"]
    lines.append("scaling, servo tick p50 / p99 (us): " + ", ".join(
        f"w={w} ({sc['particles'][w]} p) {_fmt(p['p50'])} / {_fmt(p['p99'])}" for w, p in sc["servo_tick_us"].items()))
    if sc.get("servo_tick_sweeps_us"):
        lines.append("  with the net relaxed by sweeps every tick instead: " + ", ".join(
            f"w={w} {_fmt(p['p50'])} / {_fmt(p['p99'])}" for w, p in sc["servo_tick_sweeps_us"].items()))
    lines.append("scaling, SH eval of one surface p50 (ms; us per point): " + ", ".join(
        f"lmax {l} {_fmt(p['p50'])} ({_fmt(sc['sh_eval_point_us'][l])})" for l, p in sc["sh_eval_ms"].items()))


def _table_targets(res: dict, lines: list) -> None:
    """The targets with pass / miss, then the notes."""
    lines.append("")
    lines.append(f"{'target':46s} {'measured':>10s} {'':>3s} {'limit':>8s}  result")
    for t in res["targets"]:
        verdict = "not measured" if t["pass"] is None else ("pass" if t["pass"] else "MISS")
        lines.append(f"{t['target']:46s} {_fmt(t['value']):>10s} {t['op']:>3s} {_fmt(t['limit']):>8s}  {verdict}")
    for n in res["notes"]:
        lines.append(f"note: {n}")
    lines.append("Timings on a shared machine are noisy; the bench reports, it does not judge.")


def format_table(res: dict) -> str:
    """The human-readable table: percentiles per row, then the targets with pass / miss."""
    lines = []
    for part in (_table_servo, _table_loops, _table_kernels, _table_targets):
        part(res, lines)
    return "\n".join(lines)


def write_json(res: dict, path, overwrite: bool = True) -> None:
    from haptic_acu.base.outputs import write_new

    write_new(Path(path), json.dumps(res, indent=2, sort_keys=False, default=float) + "\n", overwrite=overwrite)


def check_json_path(path) -> None:
    """Fail before two minutes of measuring if the JSON file cannot be written."""
    if path is None:
        return
    p = Path(path)
    if p.is_dir():
        raise UserError(f"{p}: --json wants a file name, this is a folder")
    if not p.parent.is_dir():
        raise UserError(f"{p}: --json folder {p.parent} does not exist")
    if not os.access(p.parent, os.W_OK):
        raise UserError(f"{p}: --json folder {p.parent} is not writable")


def main(quick: bool = False, json_path=None, progress: bool = True, out=None, overwrite: bool = True) -> int:
    check_json_path(json_path)
    res = collect(QUICK if quick else FULL, progress=progress)
    print(format_table(res), file=out or sys.stdout)
    if json_path is not None:
        write_json(res, json_path, overwrite=overwrite)
    return 0

"""Timing helpers, percentiles and machine information for the bench.

Every timing here is wall-clock ``time.perf_counter_ns``; the garbage collector is paused inside
timed loops (as the real-time engine freezes it). Percentile objects are
``{"p50", "p99", "p999", "max", "n"}`` in the unit the caller's key names (us, ms or s).
"""
from __future__ import annotations

import contextlib
import datetime
import gc
import os
import platform
import sys
import time

import numpy as np


def percentiles(values, scale: float = 1.0) -> dict:
    """p50, p99, p99.9 and max of ``values`` times ``scale`` (plus the sample count ``n``)."""
    v = np.asarray(values, dtype=float).ravel() * scale
    if v.size == 0:
        return {"p50": None, "p99": None, "p999": None, "max": None, "n": 0}
    p = np.percentile(v, [50.0, 99.0, 99.9])
    return {"p50": float(p[0]), "p99": float(p[1]), "p999": float(p[2]), "max": float(v.max()), "n": int(v.size)}


@contextlib.contextmanager
def gc_paused():
    """Collect once, then keep the garbage collector off for the block."""
    was = gc.isenabled()
    gc.collect()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def time_calls(fn, n: int, setup=None) -> np.ndarray:
    """Wall time (s) of ``n`` calls ``fn(i)``; ``setup(i)``, if given, runs untimed before each."""
    out = np.empty(n)
    clock = time.perf_counter_ns
    with gc_paused():
        for i in range(n):
            if setup is not None:
                setup(i)
            t0 = clock()
            fn(i)
            out[i] = clock() - t0
    return out * 1e-9


def ratio(numerator, denominator):
    """numerator / denominator, or None when either is missing or the denominator is not > 0."""
    if numerator is None or denominator is None or not denominator > 0:
        return None
    return float(numerator) / float(denominator)


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version(module: str):
    try:
        mod = __import__(module)
    except ImportError:
        return None
    return getattr(mod, "__version__", "?")


def load_average():
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def machine_info() -> dict:
    """Where and when the numbers were taken."""
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:
        affinity = os.cpu_count()
    return {
        "cpu": _cpu_model(),
        "logical_cores": os.cpu_count(),
        "cores_available": affinity,
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "numpy": _version("numpy"),
        "numba": _version("numba"),
        "scipy": _version("scipy"),
        "pyshtools": None,  # filled in when the SH benchmark imports it
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "OPENBLAS_CORETYPE": os.environ.get("OPENBLAS_CORETYPE"),
        "thread_env": {k: os.environ.get(k) for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "NUMBA_NUM_THREADS")},
        "load_average_start": load_average(),
    }


class StealSampler:
    """CPU time the hypervisor took from this virtual machine (``steal`` in /proc/stat), sampled every
    ``period_s`` by a thread: the host's share of a real-time loop's misses, measured directly
    (a 1 kHz loop cannot run while its virtual CPU is descheduled). Resolution: one USER_HZ tick
    (10 ms) summed over all CPUs. ``available`` is False where /proc/stat has no steal column."""

    def __init__(self, period_s: float = 0.25):
        import threading

        self.period_s = period_s
        self.samples: list[tuple[float, int]] = []
        self.hz = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
        self.available = self._read() is not None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="steal-sampler", daemon=True)

    @staticmethod
    def _read():
        try:
            with open("/proc/stat") as f:
                fields = f.readline().split()
            return int(fields[8]) if fields[0] == "cpu" and len(fields) > 8 else None
        except (OSError, ValueError):
            return None

    def _sample(self):
        v = self._read()
        if v is not None:
            self.samples.append((time.perf_counter(), v))

    def _run(self):
        self._sample()
        while not self._stop.wait(self.period_s):
            self._sample()
        self._sample()  # the last window ends at the stop

    def __enter__(self):
        if self.available:
            self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        if self.available:
            self._thread.join()

    def windows(self):
        """(start, end, stolen seconds) for each sampling interval."""
        return [(a, b, (sb - sa) / self.hz) for (a, sa), (b, sb) in zip(self.samples, self.samples[1:])]


def split_by_steal(errs_s, t0: float, dt: float, sampler: "StealSampler") -> dict:
    """The loop's period errors (tick k at ``t0 + k*dt``) split into the sampling windows in which
    the hypervisor took no CPU time and the rest: how the loop does when the host leaves it alone."""
    errs_s = np.asarray(errs_s, dtype=float)
    wins = sampler.windows()
    if not wins or errs_s.size == 0:
        return {"available": sampler.available and bool(wins)}
    t_tick = t0 + np.arange(errs_s.size) * dt
    quiet = np.zeros(errs_s.size, dtype=bool)
    stolen_total = 0.0
    span = 0.0
    for a, b, stolen in wins:
        stolen_total += stolen
        span += b - a
        if stolen == 0.0:
            quiet |= (t_tick >= a) & (t_tick < b)
    covered = (t_tick >= wins[0][0]) & (t_tick < wins[-1][1])
    cpus = os.cpu_count() or 1
    out = {"available": True, "steal_share": stolen_total / (span * cpus) if span > 0 else 0.0,
           "stolen_s": stolen_total, "windows": len(wins),
           "quiet_windows": sum(1 for w in wins if w[2] == 0.0),
           "quiet_ticks": int(quiet.sum()), "quiet_missed": int(np.count_nonzero(errs_s[quiet] > dt)),
           "other_ticks": int((covered & ~quiet).sum()),
           "other_missed": int(np.count_nonzero(errs_s[covered & ~quiet] > dt))}
    if quiet.any():
        out["quiet_period_error_us"] = percentiles(np.abs(errs_s[quiet]), 1e6)
    return out


@contextlib.contextmanager
def sched_fifo(priority: int = 10):
    """The calling thread at SCHED_FIFO ``priority`` (not inherited by children) while inside, as the
    session's servo thread runs; yields whether the system allowed it, and restores the policy."""
    prev = None
    if hasattr(os, "sched_setscheduler"):
        try:
            prev = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
            os.sched_setscheduler(0, os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0),
                                  os.sched_param(priority))
        except OSError:
            prev = None
    try:
        yield prev is not None
    finally:
        if prev is not None:
            os.sched_setscheduler(0, prev[0], os.sched_param(prev[1]))


def compiled_floor(duration_s: float, pin: bool = True) -> dict:
    """The compiled real-time loop's own floor on this machine: :func:`haptic_acu.servo.rtloop.floor_loop`
    (the servo loop's timing rule with no work) for ``duration_s`` on a thread set up as ``run
    --pin-cores`` sets the servo's (SCHED_FIFO where allowed; with ``pin``, alone on the
    highest-numbered core, this process's other threads moved to the rest). Whatever it misses the
    machine took: beside the servo loop's own count, the host's share of it."""
    import threading

    from haptic_acu.servo import affinity, rtloop

    rtloop.floor_loop(np.zeros(2, np.int64), 0, 1_000_000, np.zeros(1, np.int64))  # compiled before
    n = max(1, int(round(duration_s * 1000)))
    errs = np.zeros(n, np.int64)
    out: dict = {}
    cores = affinity.split() if pin else None

    def run():
        with sched_fifo() as fifo:
            prev_cpus = affinity.pin_thread({cores[0]}) if cores else None
            others = affinity.pin_other_threads(cores[1], threading.get_native_id()) if prev_cpus is not None else {}
            try:
                ts = np.zeros(2, np.int64)
                t0 = rtloop.now_ns(ts) + 10_000_000
                out.update(t0=t0 * 1e-9, fifo=fifo, pinned=prev_cpus is not None,
                           missed=int(rtloop.floor_loop(ts, t0, 1_000_000, errs)))
            finally:
                affinity.restore_threads(others)
                affinity.restore(prev_cpus)

    with StealSampler() as steal:
        th = threading.Thread(target=run, name="haptic-acu-floor")
        th.start()
        th.join()
    ran = errs[errs >= 0] * 1e-9
    late = np.where(errs >= 0, errs * 1e-9, 1.0)  # a skipped tick as a whole second late: missed
    return {"duration_s": duration_s, "period_error_us": percentiles(ran, 1e6), "ticks": n,
            "missed_ticks": out["missed"], "skipped_ticks": int(np.count_nonzero(errs < 0)),
            "sched_fifo": out["fifo"], "pinned": out["pinned"],
            "steal": split_by_steal(late, out["t0"], 1e-3, steal)}

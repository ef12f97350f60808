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

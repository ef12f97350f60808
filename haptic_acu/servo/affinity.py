"""CPU pinning for a live session (Linux ``sched_setaffinity``): the servo thread alone on one core,
the rerun logging child and every other thread of the session's process on the others, so neither
the logger's bursts nor the visual loop, the feed or the recorder can take the servo's core. What
the machine itself still takes is measured by the compiled loop's floor (``bench.measure.compiled_floor``:
the same pinning and timing with no work; docs/performance.md).

Used by :class:`haptic_acu.session.engine.Session` when ``pin_cores`` is on; a host with one usable core,
or without ``sched_setaffinity``, runs unpinned (:func:`split` returns None).
"""
from __future__ import annotations

import os


def split():
    """``(servo_core, other_cores)`` from the cores this process may use (the servo gets the
    highest-numbered one: interrupts are usually steered to core 0), or None with fewer than two."""
    if not hasattr(os, "sched_getaffinity"):
        return None
    cores = sorted(os.sched_getaffinity(0))
    if len(cores) < 2:
        return None
    return cores[-1], set(cores[:-1])


def pin_thread(cores):
    """Pin the calling thread (Linux: pid 0 is this thread) to ``cores``; returns its previous set
    for :func:`restore`, or None if refused."""
    try:
        prev = os.sched_getaffinity(0)
        os.sched_setaffinity(0, set(cores))
        return prev
    except (AttributeError, OSError):
        return None


def restore(prev) -> None:
    if prev is not None:
        try:
            os.sched_setaffinity(0, prev)
        except OSError:
            pass


def pin_process(pid: int, cores) -> bool:
    """Pin process ``pid`` (every thread it starts from now on inherits it) to ``cores``."""
    try:
        os.sched_setaffinity(pid, set(cores))
        return True
    except (AttributeError, OSError):
        return False


def pin_other_threads(cores, keep_tid: int) -> dict:
    """Pin every thread of this process but ``keep_tid`` (a native thread id) to ``cores``; threads
    they start later inherit it. Returns ``{tid: previous set}`` for :func:`restore_threads`
    (threads that refuse or have ended are skipped)."""
    prev = {}
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return prev
    for tid in tids:
        if tid == keep_tid:
            continue
        try:
            before = os.sched_getaffinity(tid)
            os.sched_setaffinity(tid, set(cores))
            prev[tid] = before
        except (AttributeError, OSError):
            continue
    return prev


def restore_threads(prev: dict) -> None:
    for tid, cores in prev.items():
        try:
            os.sched_setaffinity(tid, cores)
        except OSError:
            pass

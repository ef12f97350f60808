"""CPU pinning for a live session (Linux ``sched_setaffinity``): the servo thread on one core, the
rerun logging child on the others, so the logger's bursts cannot take the servo's core (issue 13:
with the logging child the compiled loop missed 12 ticks in 30 s, without it none in 10 s).

Used by :class:`haptic_acu.engine.Session` when ``pin_cores`` is on; a host with one usable core,
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

"""What a cohort asks of each Dask worker while it runs (imported only with dask.distributed).

A Dask worker samples the stacks of its running tasks every 10 ms (its statistical profiler,
``distributed.worker.profile``) from its event loop thread. Each sample takes the GIL from the
replay between two compiled blocks and walks its Python stack; on a busy host every hand-over waits
for the scheduler of the operating system, and the replays measured 30-60 % slower than in a local
process. :class:`CohortWorkerPlugin` pauses the sampling on every worker (those that join later too)
for as long as the cohort's plugin is registered, and resumes it when the run unregisters it; two
cohorts on one cluster share the pause (a count on the worker).

A worker that a Dask nanny started has ``MALLOC_TRIM_THRESHOLD_`` in its environment (Dask's
``distributed.nanny.pre-spawn-environ``, so that freed memory goes back to the system at once).
Setting it turns off glibc's sliding mmap threshold: every array of 128 KiB or more that a replay
makes is mapped, faulted in page by page and unmapped again (the default replay's 60-s sessions
took two to three times the page faults and system time of a local worker's). For the cohort's
run the plugin lets such arrays reuse the heap (:data:`RUN_MALLOC`, the top of glibc's own sliding
thresholds) and puts Dask's values back when the run ends (glibc on Linux; elsewhere nothing). Everything else a worker keeps
between sessions (numba's loaded kernels, the tissue of the configuration:
:func:`haptic_acu.cohort.sessions._tissue`) lives in the worker process and is loaded by its first
session, once per process.
"""
from __future__ import annotations

import ctypes
import os

from distributed.diagnostics.plugin import WorkerPlugin

PROFILER_CALLBACKS = ("profile", "profile-cycle")  # distributed.Worker.periodic_callbacks' names
_COUNT = "_haptic_acu_cohorts"  # cohorts running on the worker (an attribute of the Worker)
_PAUSED = "_haptic_acu_paused"  # the profiler callbacks this pause stopped ("allocator": and the thresholds)
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt() parameters
MMAP_THRESHOLD_DEFAULT = 128 * 1024  # glibc's mmap threshold when it is fixed (as the variable fixes it)
RUN_MALLOC = {M_MMAP_THRESHOLD: 32 << 20, M_TRIM_THRESHOLD: 64 << 20}  # during a cohort's run


def _mallopt(values: dict) -> bool:
    """glibc's ``mallopt`` for each (parameter, value); False where there is none (not glibc)."""
    try:
        fn = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    return all(fn(ctypes.c_int(k), ctypes.c_int(v)) == 1 for k, v in values.items())


def run_allocator() -> bool:
    """Large arrays reuse the heap for the run, if Dask fixed the thresholds (see the module)."""
    return "MALLOC_TRIM_THRESHOLD_" in os.environ and _mallopt(RUN_MALLOC)


def dask_allocator() -> None:
    """Dask's thresholds again: the trim threshold of the environment, glibc's fixed mmap threshold."""
    trim = os.environ.get("MALLOC_TRIM_THRESHOLD_", "")
    if trim.isdigit():
        _mallopt({M_MMAP_THRESHOLD: MMAP_THRESHOLD_DEFAULT, M_TRIM_THRESHOLD: int(trim)})


class CohortWorkerPlugin(WorkerPlugin):
    """Pauses the worker's sampling profiler while a cohort runs, and lets its large arrays reuse the
    heap under a Dask nanny's allocator settings (see the module)."""

    def __init__(self, name: str):
        self.name = name

    def setup(self, worker) -> None:
        n = getattr(worker, _COUNT, 0)
        setattr(worker, _COUNT, n + 1)
        if n:
            return
        paused = []
        for key in PROFILER_CALLBACKS:
            pc = worker.periodic_callbacks.get(key)
            if pc is not None and pc.is_running():
                pc.stop()
                paused.append(key)
        setattr(worker, _PAUSED, paused + (["allocator"] if run_allocator() else []))

    def teardown(self, worker) -> None:
        n = getattr(worker, _COUNT, 0) - 1
        setattr(worker, _COUNT, max(n, 0))
        if n > 0:
            return
        for key in getattr(worker, _PAUSED, ()):
            if key == "allocator":
                dask_allocator()
                continue
            pc = worker.periodic_callbacks.get(key)
            if pc is not None and not pc.is_running():
                pc.start()
        setattr(worker, _PAUSED, [])


def profiler_running(dask_worker) -> bool:
    """(For ``client.run``) whether the worker's sampling profiler runs."""
    pc = dask_worker.periodic_callbacks.get("profile")
    return bool(pc is not None and pc.is_running())

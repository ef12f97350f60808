"""What a cohort asks of each Dask worker while it runs (imported only with dask.distributed).

A Dask worker samples the stacks of its running tasks every 10 ms (its statistical profiler,
``distributed.worker.profile``) from its event loop thread. Each sample takes the GIL from the
replay between two compiled blocks and walks its Python stack; on a busy host every hand-over waits
for the scheduler of the operating system, and the replays measured 30-60 % slower than in a local
process. :class:`CohortWorkerPlugin` pauses the sampling on every worker (those that join later too)
for as long as the cohort's plugin is registered, and resumes it when the run unregisters it; two
cohorts on one cluster share the pause (a count on the worker). Everything else a worker keeps
between sessions (numba's loaded kernels, the tissue of the configuration:
:func:`haptic_acu.cohort.sessions._tissue`) lives in the worker process and is loaded by its first
session, once per process.
"""
from __future__ import annotations

from distributed.diagnostics.plugin import WorkerPlugin

PROFILER_CALLBACKS = ("profile", "profile-cycle")  # distributed.Worker.periodic_callbacks' names
_COUNT = "_haptic_acu_cohorts"  # cohorts running on the worker (an attribute of the Worker)
_PAUSED = "_haptic_acu_paused"  # the profiler callbacks this pause stopped


class CohortWorkerPlugin(WorkerPlugin):
    """Pauses the worker's sampling profiler while a cohort runs (see the module)."""

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
        setattr(worker, _PAUSED, paused)

    def teardown(self, worker) -> None:
        n = getattr(worker, _COUNT, 0) - 1
        setattr(worker, _COUNT, max(n, 0))
        if n > 0:
            return
        for key in getattr(worker, _PAUSED, ()):
            pc = worker.periodic_callbacks.get(key)
            if pc is not None and not pc.is_running():
                pc.start()
        setattr(worker, _PAUSED, [])


def profiler_running(dask_worker) -> bool:
    """(For ``client.run``) whether the worker's sampling profiler runs."""
    pc = dask_worker.periodic_callbacks.get("profile")
    return bool(pc is not None and pc.is_running())

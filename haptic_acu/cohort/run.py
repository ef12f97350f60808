"""Running a cohort's replays: a local process pool (default) or a Dask distributed cluster.

Both runners call :func:`haptic_acu.cohort.sessions.replay_session` on each :class:`~haptic_acu.cohort.sessions.Job`
and hand every record to ``on_result`` as it arrives (the caller saves it at once, so an
interrupted run keeps every finished session). At most ``2 * workers`` jobs are in flight, so
memory stays bounded whatever the cohort's size; a worker keeps no session's rows in memory (its
metrics are streamed, the path columns read the rows back from a temporary file:
:mod:`haptic_acu.session.pathstream`).

Local: ``concurrent.futures.ProcessPoolExecutor`` with spawned workers started in their own process
group, so a Ctrl-C at the terminal reaches only the parent, which cancels what is queued and ends
its workers. Dask: ``distributed.Client(address)``; the workers must have this package installed
and see the trajectory files at the same (absolute) paths. Results are identical: the same
function on the same inputs, deterministic on the sim clock.
"""
from __future__ import annotations

import os
import sys
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from multiprocessing import get_context
from typing import Callable, Iterable

from .sessions import Job, replay_session
from ..base.errors import UserError


class ProgressLine:
    """``cohort: 12/200 done, 1 failed, 0.8 s/session, ETA 2m31s`` on stderr: redrawn in place on
    a terminal, one line every ``every_s`` seconds (and at the end) otherwise."""

    def __init__(self, total: int, skipped: int = 0, stream=None, every_s: float = 10.0, quiet: bool = False):
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.total, self.skipped = total, skipped
        self.done = self.failed = 0
        self.t0 = time.perf_counter()
        self.every_s = every_s
        self._last = -1e9
        self.quiet = quiet

    def text(self) -> str:
        el = time.perf_counter() - self.t0
        s = f"cohort: {self.done}/{self.total} replayed"
        if self.skipped:
            s += f" ({self.skipped} up to date, skipped)"
        if self.failed:
            s += f", {self.failed} failed"
        if self.done:
            rate = el / self.done
            eta = rate * (self.total - self.done)
            s += f", {rate:.2f} s/session, ETA {int(eta // 60)}m{int(eta % 60):02d}s"
        return s

    def update(self, failed: bool = False) -> None:
        self.done += 1
        self.failed += bool(failed)
        if self.quiet:
            return
        now = time.perf_counter()
        if self.tty:
            self.stream.write("\r" + self.text() + "\x1b[K")
            self.stream.flush()
        elif now - self._last >= self.every_s or self.done == self.total:
            self._last = now
            print(self.text(), file=self.stream, flush=True)

    def message(self, line: str) -> None:
        """A line (a failure) printed without breaking the progress line."""
        if self.tty:
            self.stream.write("\r\x1b[K")
        print(line, file=self.stream, flush=True)

    def close(self) -> None:
        if self.tty and not self.quiet and self.done:
            self.stream.write("\n")
            self.stream.flush()


def _worker_init() -> None:
    os.setpgrp()  # a terminal's Ctrl-C goes to the parent only; it stops the pool


def run_local(jobs: list[Job], workers: int, on_result: Callable[[dict], None]) -> None:
    if not jobs:
        return
    workers = max(1, min(workers, len(jobs)))
    pending = iter(jobs)
    ex = ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"), initializer=_worker_init)
    try:
        inflight = set()
        _fill(ex.submit, pending, inflight, 2 * workers)
        while inflight:
            done, inflight = wait(inflight, return_when=FIRST_COMPLETED)
            for f in done:
                on_result(f.result())
            _fill(ex.submit, pending, inflight, 2 * workers)
    except BaseException:
        for p in list(getattr(ex, "_processes", {}).values()):  # stop running replays now
            p.terminate()
        ex.shutdown(wait=True, cancel_futures=True)
        raise
    ex.shutdown(wait=True)


def _fill(submit, pending: Iterable[Job], inflight: set, limit: int) -> None:
    while len(inflight) < limit:
        job = next(pending, None)
        if job is None:
            return
        inflight.add(submit(replay_session, job))


def scheduler_address(address: str) -> str:
    """``address`` checked as ``PROTOCOL://HOST:PORT`` (``HOST:PORT`` means tcp); UserError otherwise.
    Checked before a Client is made: a Client given a bad address fails, then its finaliser waits
    40 s at exit and prints a traceback."""
    from distributed.comm.addressing import parse_address, parse_host_port

    full = address if "://" in address else f"tcp://{address}"
    try:
        _, location = parse_address(full, strict=True)
        host, port = parse_host_port(location)
    except ValueError as e:
        raise UserError(f"--scheduler {address}: expected tcp://HOST:PORT ({e})") from None
    if not host or not 0 < port < 65536:
        raise UserError(f"--scheduler {address}: expected tcp://HOST:PORT with a port in 1-65535")
    return full


def connect(address: str, timeout_s: float = 20.0):
    """A ``distributed.Client`` to the scheduler at ``address``; UserError if it cannot be reached."""
    try:
        from distributed import Client
    except ImportError:
        raise UserError("--scheduler needs dask.distributed: pip install 'haptic-acu[cohort]'") from None
    address = scheduler_address(address)
    try:
        return Client(address, timeout=timeout_s, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as e:
        raise UserError(f"--scheduler {address}: cannot connect: {e}") from None


def run_dask(jobs: list[Job], client, on_result: Callable[[dict], None]) -> None:
    """Run the jobs on ``client``'s cluster, at most twice its worker threads in flight."""
    if not jobs:
        return
    from distributed import as_completed

    threads = sum(client.nthreads().values()) or 1
    pending = iter(jobs)
    by_future = {}

    def submit(fn, job: Job):
        fut = client.submit(fn, job, pure=False, key=f"cohort-replay-{job.session}-{time.time_ns()}")
        by_future[fut] = job
        return fut

    first = set()
    _fill(submit, pending, first, 2 * threads)
    ac = as_completed(first, loop=client.loop)
    try:
        for fut in ac:
            job = by_future.pop(fut)
            try:
                rec = fut.result()
            except Exception as e:  # the worker died (KilledWorker), lost the task, ...
                rec = {"session": job.session, "file": job.file, "input_sha256": None,
                       "config_sha256": job.config_sha256, "error": f"{job.file}: worker failed: {type(e).__name__}: {e}",
                       "summary": None, "insertions": [], "retry": True}
            on_result(rec)
            more = set()
            _fill(submit, pending, more, 1)
            for f in more:
                ac.add(f)
    except BaseException:
        client.cancel(list(by_future))
        raise

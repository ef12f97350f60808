"""Running a cohort's replays: a local process pool (default) or a Dask distributed cluster.

Both runners call :func:`haptic_acu.cohort.sessions.replay_session` on each :class:`~haptic_acu.cohort.sessions.Job`
and hand every record to ``on_result`` as it arrives (the caller saves it at once, so an
interrupted run keeps every finished session). At most ``2 * workers`` tasks are in flight, so
memory stays bounded whatever the cohort's size; a worker keeps no session's rows in memory (its
metrics are streamed, the path columns read the rows back from a temporary file:
:mod:`haptic_acu.session.pathstream`). A worker process loads numba's kernels and builds the
configuration's tissue on its first session and keeps them for the next ones.

Local: ``concurrent.futures.ProcessPoolExecutor`` with spawned workers started in their own process
group, so a Ctrl-C at the terminal reaches only the parent, which cancels what is queued and ends
its workers; one session a task. Dask: ``distributed.Client(address)``; the workers must have this
package installed and see the trajectory files at the same (absolute) paths. A task replays a batch
of sessions (:func:`batches`), and the workers' sampling profiler is paused while the run lasts
(:mod:`haptic_acu.cohort.daskworker`). Results are identical: the same function on the same inputs,
deterministic on the sim clock.
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
from ..base.signals import sigterm_unwinds


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


PR_SET_PDEATHSIG = 1


def _worker_init(parent: int) -> None:
    """In each local worker: its own process group (a terminal's Ctrl-C goes to the parent only, which
    stops the pool), and death with its parent: the kernel sends it SIGKILL when the parent dies, even
    by SIGKILL (Linux ``PR_SET_PDEATHSIG``; elsewhere the parent's own handlers end it)."""
    os.setpgrp()
    try:
        import ctypes
        import signal

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:  # the parent died before the line above: nothing to work for
        os._exit(1)


def run_local(jobs: list[Job], workers: int, on_result: Callable[[dict], None]) -> None:
    if not jobs:
        return
    workers = max(1, min(workers, len(jobs)))
    pending = iter(jobs)
    # SIGTERM while the pool runs unwinds like Ctrl-C: the pool's workers are ended, every finished
    # session is already saved, and the command exits 143
    with sigterm_unwinds():
        ex = ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"), initializer=_worker_init,
                                 initargs=(os.getpid(),))
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


def _fill(submit, pending: Iterable, inflight: set, limit: int, fn=replay_session) -> None:
    while len(inflight) < limit:
        item = next(pending, None)
        if item is None:
            return
        inflight.add(submit(fn, item))


DASK_SCHEMES = ("tcp", "tls", "ws", "wss", "ucx")  # what a scheduler can listen on (inproc: this process only)
POLL_S = 1.0  # how often a run on a cluster looks at its workers while waiting for results


def scheduler_address(address: str) -> str:
    """``address`` checked as ``PROTOCOL://HOST:PORT`` (``HOST:PORT`` means tcp) with a protocol Dask
    speaks (:data:`DASK_SCHEMES`); UserError otherwise. Checked before a Client is made: a Client given
    a bad address fails, then its finaliser waits 40 s at exit and prints a traceback."""
    from distributed.comm.addressing import parse_address, parse_host_port

    full = address if "://" in address else f"tcp://{address}"
    try:
        scheme, location = parse_address(full, strict=True)
        host, port = parse_host_port(location)
    except ValueError as e:
        raise UserError(f"--scheduler {address}: expected tcp://HOST:PORT ({e})") from None
    if scheme not in DASK_SCHEMES:
        raise UserError(f"--scheduler {address}: '{scheme}://' is not a protocol a Dask scheduler listens on "
                        f"({', '.join(s + '://' for s in DASK_SCHEMES)})")
    if scheme == "ucx":
        from distributed.comm.registry import get_backend
        try:
            get_backend("ucx")
        except Exception as e:  # noqa: BLE001 - the backend's import fails without ucx-py
            raise UserError(f"--scheduler {address}: ucx:// needs the ucx backend ({type(e).__name__})") from None
    if not host or not 0 < port < 65536:
        raise UserError(f"--scheduler {address}: expected tcp://HOST:PORT with a port in 1-65535")
    return full


def _security(address: str):
    """The Dask TLS settings for a tls:// or wss:// scheduler (from Dask's config:
    ``distributed.comm.tls.*``), or None for the others; UserError if none are configured."""
    if not address.startswith(("tls://", "wss://")):
        return None
    from distributed.security import Security

    sec = Security()
    if not (sec.tls_ca_file and sec.tls_client_cert):
        raise UserError(f"--scheduler {address}: TLS needs certificates in Dask's configuration "
                        "(distributed.comm.tls.ca-file, .client.cert, .client.key)")
    return sec


def _probe(address: str, timeout_s: float, security) -> None:
    """Ask the scheduler at ``address`` who it is, all within ``timeout_s``: UserError (one line) if
    nothing answers, something else answers, or it is not a Dask scheduler."""
    import asyncio

    from distributed.comm import connect as comm_connect

    async def ask():
        kw = security.get_connection_args("client") if security is not None else {}
        comm = await comm_connect(address, timeout=timeout_s, **kw)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    try:
        who = asyncio.run(asyncio.wait_for(ask(), timeout_s))
    except Exception as e:  # noqa: BLE001 - OSError, TimeoutError, a handshake with something else
        what = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
        raise UserError(f"--scheduler {address}: cannot connect within {timeout_s:g} s "
                        f"(--scheduler-timeout): {what}") from None
    if not (isinstance(who, dict) and who.get("type") == "Scheduler"):
        kind = who.get("type") if isinstance(who, dict) else type(who).__name__
        raise UserError(f"--scheduler {address}: answers as {kind!r}, not a Dask scheduler")


def connect(address: str, timeout_s: float = 20.0):
    """A ``distributed.Client`` to the scheduler at ``address``; UserError (one line) if it cannot be
    reached within ``timeout_s``."""
    try:
        from distributed import Client
    except ImportError:
        raise UserError("--scheduler needs dask.distributed: pip install 'haptic-acu[cohort]'") from None
    address = scheduler_address(address)
    security = _security(address)
    _probe(address, timeout_s, security)  # a listener that never answers would hold Client() forever
    try:
        return Client(address, timeout=timeout_s, set_as_default=False, security=security)
    except Exception as e:  # noqa: BLE001 - OSError, TimeoutError, a handshake with something else
        what = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
        raise UserError(f"--scheduler {address}: cannot connect within {timeout_s:g} s "
                        f"(--scheduler-timeout): {what}") from None


def wait_for_workers(client, timeout_s: float, stream=None) -> int:
    """Wait up to ``timeout_s`` for a worker to join; returns the cluster's worker threads."""
    threads = sum(client.nthreads().values())
    if threads:
        return threads
    stream = stream if stream is not None else sys.stderr
    addr = client.scheduler.address
    print(f"haptic-acu: waiting up to {timeout_s:g} s (--scheduler-timeout) for a worker to join the "
          f"scheduler at {addr}", file=stream, flush=True)
    try:
        client.wait_for_workers(1, timeout=timeout_s)
    except TimeoutError:
        raise UserError(f"--scheduler {addr}: no worker joined in {timeout_s:g} s (--scheduler-timeout); "
                        f"start one with: dask worker {addr}") from None
    except OSError as e:
        raise UserError(f"--scheduler {addr}: lost the scheduler while waiting for a worker: {e}") from None
    return sum(client.nthreads().values()) or 1


BATCH_MAX = 8  # sessions in one Dask task at most


def batch_size(n_jobs: int, threads: int) -> int:
    """Sessions in the next Dask task with ``n_jobs`` left: at least four tasks for every worker
    thread (a lost worker takes few finished sessions with it), at most :data:`BATCH_MAX`."""
    return max(1, min(BATCH_MAX, n_jobs // (4 * max(1, threads))))


def batches(jobs: list[Job], threads: int):
    """The jobs in consecutive batches sized by :func:`batch_size` on what is left, so they shrink
    to single sessions toward the end and the workers finish together."""
    i = 0
    while i < len(jobs):
        size = batch_size(len(jobs) - i, threads)
        yield jobs[i:i + size]
        i += size


def run_dask(jobs: list[Job], client, on_result: Callable[[dict], None], timeout_s: float = 60.0,
             stream=None) -> None:
    """Run the jobs on ``client``'s cluster in batches (:func:`batches`; one task replays a batch
    in turn and returns its records), at most twice the cluster's worker threads in flight. The
    workers' sampling profiler is paused for the run (:mod:`haptic_acu.cohort.daskworker`). A
    cluster with no worker for ``timeout_s`` (every one lost) stops the run with one line (exit 3);
    every session finished before is already saved, so the next run resumes from there."""
    if not jobs:
        return
    from .sessions import replay_batch

    threads = wait_for_workers(client, timeout_s, stream)
    pending = batches(jobs, threads)
    by_future = {}
    done_count = 0

    def submit(fn, batch: list[Job]):
        key = f"cohort-replay-{batch[0].session}-{len(batch)}-{time.time_ns()}"
        fut = client.submit(fn, batch, pure=False, key=key)
        by_future[fut] = batch
        return fut

    plugin = _pause_profilers(client, timeout_s)
    inflight = set()
    _fill(submit, pending, inflight, 2 * threads, replay_batch)
    lost_since = None
    looked = time.monotonic()
    try:
        while inflight:
            done = {f for f in inflight if f.done()}  # at most twice the worker threads to look at
            if not done:
                time.sleep(0.05)
                if time.monotonic() - looked < POLL_S:
                    continue
                looked = time.monotonic()
            for fut in done:
                inflight.discard(fut)
                batch = by_future.pop(fut)
                try:
                    recs = fut.result(timeout=timeout_s)  # a result lost with its worker is not waited for
                except Exception as e:  # the worker died (KilledWorker), lost the task, ...
                    recs = [{"session": job.session, "file": job.file, "input_sha256": None,
                             "config_sha256": job.config_sha256,
                             "error": f"{job.file}: worker failed: {type(e).__name__}: {e}",
                             "summary": None, "insertions": [], "retry": True} for job in batch]
                else:
                    done_count += len(recs)
                for rec in recs:
                    on_result(rec)
                _fill(submit, pending, inflight, len(inflight) + 1, replay_batch)
            if done:
                lost_since = None
                continue
            if client.nthreads():
                lost_since = None
            elif lost_since is None:
                lost_since = time.monotonic()
            elif time.monotonic() - lost_since > timeout_s:
                left = sum(len(by_future[f]) for f in inflight) + sum(len(b) for b in pending)
                raise UserError(f"--scheduler {client.scheduler.address}: every worker has been lost for "
                                f"{timeout_s:g} s (--scheduler-timeout); {done_count} session(s) finished "
                                f"and kept, {left} left: run again to resume", exit_status=3)
    except BaseException:
        client.cancel(list(by_future))
        raise
    finally:
        _resume_profilers(client, plugin, timeout_s)


def _pause_profilers(client, timeout_s: float) -> str | None:
    """Register :class:`~haptic_acu.cohort.daskworker.CohortWorkerPlugin` within ``timeout_s``: its
    name, or None if the cluster refused it or did not answer (the run goes on, the profiler sampling)."""
    from .daskworker import CohortWorkerPlugin

    name = f"haptic-acu-cohort-{os.getpid()}-{time.time_ns()}"
    try:
        client.sync(client._register_worker_plugin, plugin=CohortWorkerPlugin(name), name=name,
                    idempotent=False, callback_timeout=timeout_s)
    except Exception:  # noqa: BLE001 - an older or restricted cluster, a timeout: slower, not wrong
        return None
    return name


def _resume_profilers(client, name: str | None, timeout_s: float) -> None:
    """Unregister the plugin (the workers' profilers resume), waiting at most ``timeout_s``."""
    if name is None:
        return
    try:
        client.sync(client._unregister_worker_plugin, name=name, nanny=False, callback_timeout=timeout_s)
    except Exception:  # noqa: BLE001 - the scheduler is gone or did not answer: nothing to resume
        pass

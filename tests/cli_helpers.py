"""``haptic-acu ...`` run in the test's own process, seen as a test sees a child process.

:func:`cli` calls :func:`haptic_acu.cli.main` (the console entry's own code: the same parser, checks,
exit status and streams) and returns a :class:`subprocess.CompletedProcess` with the exit status and
what the command wrote to stdout and stderr, without a child's start-up (a second or two of imports
and kernel loading a call). An exception that escapes ``main`` is not caught: it fails the test, as
the traceback a user would see fails a test's one-line check.

A child process stays where the test is about the process: signals and exit statuses made by them, a
terminal, resource limits, what happens at interpreter exit, a fresh interpreter's imports, the
installed entry point.
"""
from __future__ import annotations

import contextlib
import io
import os
import resource
import signal
import subprocess
import sys
import threading

from haptic_acu.cli import main


class CliTimeout(BaseException):
    """The command outlived its ``timeout``: raised out of it (a BaseException, so that no handler of
    the command's takes it for one of its own errors), it fails the test."""


@contextlib.contextmanager
def _environ(env: dict[str, str]):
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def cli(*args, cwd=None, env: dict[str, str] | None = None, stdin: str | None = None,
        timeout: float | None = None) -> subprocess.CompletedProcess:
    """``haptic-acu ARGS`` in this process: ``returncode``, ``stdout``, ``stderr`` as a child's.

    ``cwd``: the working folder while it runs; ``env``: variables set while it runs (on top of this
    process's); ``stdin``: the text it reads on standard input; ``timeout``: seconds after which
    :class:`CliTimeout` is raised in it (the main thread's timer, as a child's ``timeout``)."""
    argv = [str(a) for a in args]
    out, err = io.StringIO(), io.StringIO()
    with contextlib.ExitStack() as stack:
        if timeout is not None:
            stack.enter_context(_deadline(timeout, argv))
        if cwd is not None:
            stack.enter_context(contextlib.chdir(cwd))
        if env:
            stack.enter_context(_environ(env))
        if stdin is not None:
            stack.enter_context(_stdin(stdin))
        stack.enter_context(contextlib.redirect_stdout(out))
        stack.enter_context(contextlib.redirect_stderr(err))
        try:
            code = main(argv)
        except SystemExit as e:  # argparse: --help, --version, a usage error
            code = e.code
    if code is None:
        code = 0
    elif not isinstance(code, int):  # SystemExit("message"): Python prints it and exits 1
        err.write(f"{code}\n")
        code = 1
    return subprocess.CompletedProcess(["haptic-acu", *argv], code, out.getvalue(), err.getvalue())


@contextlib.contextmanager
def _stdin(text: str):
    saved, sys.stdin = sys.stdin, io.StringIO(text)
    try:
        yield
    finally:
        sys.stdin = saved


@contextlib.contextmanager
def _deadline(seconds: float, argv: list[str]):
    if threading.current_thread() is not threading.main_thread():  # no timer off the main thread
        yield
        return

    def expire(signum, frame):
        raise CliTimeout(f"haptic-acu {' '.join(argv)}: still running after {seconds} s")

    old = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


@contextlib.contextmanager
def file_size_limit(limit: int):
    """Writes to a file past ``limit`` bytes fail with EFBIG while it lasts, as on a full disk: this
    process's soft RLIMIT_FSIZE lowered (SIGXFSZ ignored, so the write returns the error), then
    restored."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    old = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, old)


def cohort_sessions_here(monkeypatch) -> list[str]:
    """``cohort``'s local pool replaced, for one test, by its sessions replayed one after another in
    this process: the same :func:`~haptic_acu.cohort.sessions.replay_session` on each job, the job
    and its record each through pickle as the pool sends them, without a spawned worker's start-up
    (its imports, kernels and tissue: seconds a worker). For the tests about what a cohort run
    writes; the pool itself (its workers, interrupts, signals) keeps tests of its own. Returns the
    sessions in the order they were replayed."""
    import pickle

    from haptic_acu.cohort import run
    from haptic_acu.cohort.sessions import replay_session

    replayed: list[str] = []

    def run_local(jobs, workers, on_result):
        assert workers >= 1
        for job in jobs:
            rec = replay_session(pickle.loads(pickle.dumps(job)))
            replayed.append(job.session)
            on_result(pickle.loads(pickle.dumps(rec)))

    monkeypatch.setattr(run, "run_local", run_local)
    return replayed



def interrupt_now(sig: str):
    """What ``sig`` does to this process's main thread at this point of a command, without the
    signal: Ctrl-C's KeyboardInterrupt (Python's SIGINT handler), or a call of the SIGTERM handler
    installed now. If none is (SIGTERM's default action: the process ends at once, no ``finally``
    runs), that is the test's failure, not this process's end."""
    if sig == "SIGINT":
        raise KeyboardInterrupt
    handler = signal.getsignal(signal.SIGTERM)
    assert callable(handler), "SIGTERM here would end the process at once (no handler installed)"
    handler(signal.SIGTERM, None)
    raise AssertionError("the SIGTERM handler returned: the command would go on")

"""Sessions against the HD emulator in processes forked from one warm interpreter.

A session needs a process of its own: the emulator reads its ``HD_EMU_*`` configuration when it is
loaded (pyOpenHaptics loads it as ``libHD.so`` in the session's process), it emulates one device, and
the tests are about what that process does: its exit status, its output, the last force frame it
sent, the emulator's log written at its exit. Most of a fresh process's CPU time goes before the
device opens, though: importing numpy, numba, matplotlib and haptic_acu and loading the compiled
kernels from numba's cache. A :class:`ForkServer` pays that once: a server process imports all of it
and warms it with a scripted session (it never loads the emulator or pyOpenHaptics), then forks one
process per session. The forked process takes the session's environment (which the emulator, loaded
there as in a fresh process, reads), its working folder and its output files, and runs ``python -m
haptic_acu ARGS`` or ``python SCRIPT ARGS`` to its end through the interpreter's normal exit (atexit
hooks, the emulator's destructor): its exit status, stdout and stderr are what a subprocess gives.

The server's environment is the sessions' without the ``HD_EMU_*`` variables (the loader's path to
the emulator, and everything a library reads at import). A session's process gets what its imports
would have added to its environment (``import haptic_acu`` sets the BLAS thread counts unless they
are set). A session whose environment, so completed, differs from the server's in anything but
``HD_EMU_*`` and pytest's name of the current test (another test changed the test process's
environment, say its PATH) gets a new server started with its environment.

Run as ``python forkserver.py``: the server. It reads one JSON request a line on stdin and answers
``{"pid": N}`` when the session's process starts and ``{"status": S}`` (its exit code, or minus the
signal that ended it) when it has ended, or ``{"error": ...}`` for a session it refuses.
"""
from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import NamedTuple

REPO = Path(__file__).resolve().parents[2]


def _session_env(env: dict) -> dict:
    """What a session's process reads of its environment before its device opens: all but the
    emulator's ``HD_EMU_*`` and pytest's name of the current test."""
    return {k: v for k, v in env.items() if not k.startswith("HD_EMU_") and k != "PYTEST_CURRENT_TEST"}


class Subprocesses:
    """Sessions in fresh interpreters: ``subprocess.run`` of ``python -m haptic_acu ARGV`` (or
    ``python SCRIPT ARGV``); :meth:`ForkServer.run`'s signature."""

    def run(self, argv, env: dict, *, cwd=REPO, timeout: float = 300.0, script=None) -> subprocess.CompletedProcess:
        cmd = [sys.executable] + (["-m", "haptic_acu"] if script is None else [str(script)]) + [str(a) for a in argv]
        return subprocess.run(cmd, env=env, cwd=cwd, capture_output=True, text=True, timeout=timeout)


class Emulator(NamedTuple):
    """A test's HD emulator: its ``libHD.so`` and where its sessions run (ForkServer or Subprocesses)."""
    lib: Path
    sessions: object


class ForkServer:
    """A server for sessions whose environment is ``env`` plus ``HD_EMU_*`` variables (see the module
    docstring); ``log``: the server's own stderr (its warm-up's messages), beside which the sessions'
    stdout and stderr are kept."""

    def __init__(self, env: dict, log):
        self.log = Path(log)
        self._n = 0
        self._start(env)

    def _start(self, env: dict) -> None:
        self._log_file = open(self.log, "a")
        self.proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve())], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=self._log_file, env=_session_env(env), cwd=REPO)
        self._buf = b""
        self._ready = False

    def _line(self, timeout: float) -> dict | None:
        """The server's next answer, or None if none came within ``timeout`` seconds."""
        fd = self.proc.stdout.fileno()
        end = time.monotonic() + timeout
        while b"\n" not in self._buf:
            left = end - time.monotonic()
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                return None
            chunk = os.read(fd, 65536)
            if not chunk:
                raise RuntimeError(f"the fork server ended (status {self.proc.wait()}): {self.log.read_text()[-2000:]}")
            self._buf += chunk
        line, self._buf = self._buf.split(b"\n", 1)
        return json.loads(line)

    def run(self, argv, env: dict, *, cwd=REPO, timeout: float = 300.0, script=None) -> subprocess.CompletedProcess:
        """``python -m haptic_acu ARGV`` (or ``python SCRIPT ARGV``) in a forked process with ``env``,
        in ``cwd``: the exit status and the text of stdout and stderr, as ``subprocess.run(...,
        capture_output=True, text=True, timeout=timeout)`` gives them (TimeoutExpired after killing
        the process)."""
        self._n += 1
        out = self.log.with_name(f"{self.log.stem}-{self._n}.out")
        err = self.log.with_name(f"{self.log.stem}-{self._n}.err")
        req = {"argv": [str(a) for a in argv], "env": dict(env), "cwd": str(cwd), "out": str(out), "err": str(err),
               "script": None if script is None else str(script)}
        for attempt in (1, 2):
            if not self._ready:  # the warm-up: imports and a scripted session, once per server
                ready = self._line(600.0)
                if ready != {"ready": True}:
                    raise RuntimeError(f"the fork server did not start: {ready} {self.log.read_text()[-2000:]}")
                self._ready = True
            self.proc.stdin.write((json.dumps(req) + "\n").encode())
            self.proc.stdin.flush()
            started = self._line(120.0)
            if started is None:
                raise RuntimeError(f"the fork server did not answer: {self.log.read_text()[-2000:]}")
            if "error" not in started:
                break
            if attempt == 2:  # refused by a server started with its own environment
                raise ValueError(started["error"])
            self.close()  # another environment: a server of its own
            self._start(env)
        pid = started["pid"]
        done = self._line(timeout)
        if done is None:
            os.kill(pid, signal.SIGKILL)
            self._line(60.0)
            raise subprocess.TimeoutExpired(argv, timeout, out.read_text(), err.read_text())
        args = [sys.executable] + (["-m", "haptic_acu"] if script is None else [str(script)]) + req["argv"]
        return subprocess.CompletedProcess(args, done["status"], out.read_text(), err.read_text())

    def close(self) -> None:
        """End the server (it ends when its stdin closes); no process is left behind."""
        try:
            self.proc.stdin.close()
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        finally:
            self.proc.stdout.close()
            self._log_file.close()


# -- the server ------------------------------------------------------------------------------------

def _warm() -> None:
    """Everything a session imports and loads before and after its device opens, but the device's
    own library: the package, the OMNI's driver modules, and a short scripted session through the
    same command (its compiled servo loop, tissue and sinks, the report and its figure)."""
    import contextlib
    import io
    import tempfile
    import threading

    import haptic_acu.devices.omni  # noqa: F401 - pyOpenHaptics (and the emulator) only load in open()
    import haptic_acu.servo.omniloop  # noqa: F401
    from haptic_acu.cli import main

    assert "pyOpenHaptics" not in sys.modules
    with tempfile.TemporaryDirectory(prefix="hd-forkserver-") as tmp:
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            rc = main(["run", "--device", "scripted", "--trajectory", "default", "--duration", "0.3", "--speed", "4",
                       "--out", str(Path(tmp) / "out"), "--no-status"])
        if rc != 0:
            raise RuntimeError(f"the warm-up session failed ({rc}): {err.getvalue()}")
    for t in threading.enumerate():  # (daemon helpers, e.g. the figure modules' import, end on their own)
        if t is not threading.main_thread():
            t.join(timeout=60)
    tasks = os.listdir("/proc/self/task") if os.path.isdir("/proc/self/task") else ["main"]
    if threading.active_count() != 1 or len(tasks) != 1:
        raise RuntimeError(f"threads left after the warm-up ({threading.enumerate()}, {len(tasks)} tasks): "
                           "a fork would copy them half-done")


def _environment(env: dict, set_by_imports: dict) -> dict:
    """A session's environment as its process's imports leave it."""
    return {**env, **{k: v for k, v in set_by_imports.items() if k not in env}}


def _child(req: dict, proto, set_by_imports: dict) -> None:
    """In the forked process: become the session's process and run it; never returns."""
    for f in proto:
        f.close()
    os.environ.clear()
    os.environ.update(_environment(req["env"], set_by_imports))
    os.chdir(req["cwd"])
    fds = [os.open(os.devnull, os.O_RDONLY), os.open(req["out"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644),
           os.open(req["err"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)]
    for target, fd in enumerate(fds):
        os.dup2(fd, target)
        os.close(fd)
    import runpy

    if req["script"] is None:  # python -m haptic_acu ARGV
        sys.argv = ["-m", *req["argv"]]
        sys.path[0] = os.getcwd()
        runpy.run_module("haptic_acu", run_name="__main__", alter_sys=True)
    else:  # python SCRIPT ARGV
        sys.argv = [req["script"], *req["argv"]]
        sys.path[0] = str(Path(req["script"]).resolve().parent)
        runpy.run_path(req["script"], run_name="__main__")
    raise SystemExit(0)  # the end of the program: the interpreter's normal exit


def serve() -> int:
    import gc

    proto_in = os.fdopen(os.dup(0), "r")
    proto_out = os.fdopen(os.dup(1), "w", buffering=1)
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.dup2(2, 1)  # the server's own prints go to its log
    os.close(null)
    sys.path[0] = str(REPO)  # (not this script's folder), as for python -m haptic_acu run from REPO
    before = dict(os.environ)
    _warm()
    set_by_imports = {k: v for k, v in os.environ.items() if before.get(k) != v}
    print(f"fork server: ready; the imports set {set_by_imports}", file=sys.stderr, flush=True)
    gc.collect()
    gc.freeze()  # the warm interpreter's objects: a session's collections leave them (and their pages) alone
    proto_out.write(json.dumps({"ready": True}) + "\n")
    for line in proto_in:
        req = json.loads(line)
        env, mine = _session_env(_environment(req["env"], set_by_imports)), _session_env(os.environ)
        if env != mine:
            diff = sorted(k for k in set(env) | set(mine) if env.get(k) != mine.get(k))
            proto_out.write(json.dumps({"error": f"a session's environment differs from the fork server's in {diff}"})
                            + "\n")
            continue
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            _child(req, (proto_in, proto_out), set_by_imports)
        proto_out.write(json.dumps({"pid": pid}) + "\n")
        _, status = os.waitpid(pid, 0)
        proto_out.write(json.dumps({"status": os.waitstatus_to_exitcode(status)}) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(serve())

"""Progress messages on stderr for every step that takes over a second.

* :func:`step` wraps a step: if it is still running after ``after_s`` (1 s) a line says what it is
  doing, and when it ends the line says how long it took. Quick steps print nothing.
* :func:`watch_compiles` reports numba compiling (the first run after an install compiles the
  servo and springback kernels for tens of seconds; later runs load them from numba's cache): the
  first compile that lasts over a second prints one line, and the session's first step after it the
  total compile time.

On a terminal the message is rewritten in place (``\\r``) and ends with the time; elsewhere (a pipe,
a CI log, ``make demo > log``) plain lines are printed: ``haptic-acu: <what>...`` and
``haptic-acu: <what>: done in 2.3 s``. A step that fails prints no verdict (on a terminal its line is
erased): the error message follows. :data:`quiet` (set by ``--quiet``) turns everything off.
"""
from __future__ import annotations

import contextlib
import sys
import threading
import time

quiet = False
AFTER_S = 1.0
_open: "Step | None" = None  # a step whose message is open on a terminal line (no newline yet)
_open_lock = threading.Lock()


def _is_tty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


class Step:
    """One step's message (see the module doc). ``stream`` default: stderr at start time."""

    def __init__(self, what: str, after_s: float | None = None, stream=None):
        self.what = what
        self.after_s = AFTER_S if after_s is None else after_s
        self.stream = stream
        self.shown = False
        self._lock = threading.Lock()
        self._timer: threading.Timer | None = None
        self._t0 = 0.0
        self._done = False
        self._broken = False  # another message was printed after this one's open line

    def _write(self, text: str) -> None:
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):
            pass

    def _show(self) -> None:
        global _open
        with self._lock, _open_lock:
            if self._done or self.shown:
                return
            self.shown = True
            if _open is not None:  # end the open line of an enclosing step first
                self._write("\n")
                _open._broken = True
                _open = None
            tty = _is_tty(self.stream)
            self._write(f"haptic-acu: {self.what}..." + ("" if tty else "\n"))
            if tty:
                _open = self

    def start(self) -> "Step":
        if self.stream is None:
            self.stream = sys.stderr
        self._t0 = time.perf_counter()
        if not quiet:
            if self.after_s <= 0:
                self._show()
            else:
                self._timer = threading.Timer(self.after_s, self._show)
                self._timer.daemon = True
                self._timer.start()
        return self

    def stop(self, ok: bool = True) -> float:
        elapsed = time.perf_counter() - self._t0
        if self._timer is not None:
            self._timer.cancel()
            self._timer.join()
        global _open
        with self._lock, _open_lock:
            self._done = True
            if self.shown and not ok:
                # the error that follows is the message: end an open line (erased on a terminal)
                if _open is self:
                    self._write("\r" + " " * (len(self.what) + 15) + "\r")
                    _open = None
            elif self.shown:
                verdict = f"done in {elapsed:.1f} s"
                if _open is self:
                    self._write(f" {verdict}\n")
                    _open = None
                else:
                    if _open is not None:
                        self._write("\n")
                        _open._broken = True
                        _open = None
                    self._write(f"haptic-acu: {self.what}: {verdict}\n")
        return elapsed


@contextlib.contextmanager
def step(what: str, after_s: float | None = None, stream=None):
    """``with step("building the tissue"): ...`` -- see the module doc."""
    s = Step(what, after_s, stream).start()
    ok = False
    try:
        yield s
        ok = True
    finally:
        s.stop(ok)


def note(text: str, stream=None) -> None:
    """One progress line (``haptic-acu: text``) on stderr, after ending an open step line."""
    global _open
    if quiet:
        return
    stream = sys.stderr if stream is None else stream
    with _open_lock:
        try:
            if _open is not None:
                stream.write("\n")
                _open._broken = True
                _open = None
            stream.write(f"haptic-acu: {text}\n")
            stream.flush()
        except (OSError, ValueError):
            pass


# ---- numba compiles ----------------------------------------------------------------------------
class _CompileWatch:
    """A numba event listener: a step message for the outermost compile that lasts over a second."""

    def __init__(self):
        self.depth = 0
        self.step: Step | None = None
        self.total_s = 0.0
        self.count = 0

    def on_start(self, event) -> None:
        self.depth += 1
        if self.depth == 1:
            disp = event.data.get("dispatcher")
            name = getattr(getattr(disp, "py_func", None), "__qualname__", "a kernel")
            why = "" if self.count else " (numba, on the first run after an install; cached afterwards)"
            self.step = Step(f"compiling {name}{why}").start()

    def on_end(self, event) -> None:
        self.depth = max(self.depth - 1, 0)
        if self.depth == 0 and self.step is not None:
            self.total_s += self.step.stop()
            self.count += self.step.shown
            self.step = None


_watch: _CompileWatch | None = None


def watch_compiles() -> None:
    """Report numba compiles of over a second (once per process). A command that runs no kernel
    does not import numba for it: the listener is registered when numba is first imported."""
    global _watch
    if _watch is not None:
        return
    _watch = _CompileWatch()
    if "numba" in sys.modules:
        _listen(_watch)
    else:
        sys.meta_path.insert(0, _AfterImport("numba", lambda: _listen(_watch)))


def _listen(watch: _CompileWatch) -> None:
    try:
        from numba.core import event
    except ImportError:  # pragma: no cover - numba is a dependency
        return

    class Listener(event.Listener):
        def on_start(self, e):
            watch.on_start(e)

        def on_end(self, e):
            watch.on_end(e)

    event.register("numba:compile", Listener())


class _AfterImport:
    """A one-shot import hook: calls ``then()`` once the top-level module ``name`` has been
    imported (by whatever imports it first), then steps out of the way."""

    def __init__(self, name: str, then):
        self.name = name
        self.then = then

    def find_spec(self, fullname, path, target=None):
        if fullname != self.name:
            return None
        import importlib.util

        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(fullname)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        run, then = spec.loader.exec_module, self.then

        def exec_module(module):
            run(module)
            then()

        spec.loader.exec_module = exec_module
        return spec

"""A line answered at a prompt on the terminal (or a pipe), read so that Ctrl-C always ends the wait.

:func:`input` writes its prompt and then blocks in ``read()``. Python runs a signal's handler
between two steps of Python code; the signal itself only sets a flag, and it interrupts a
blocking read only if it arrives while the read is in progress on the main thread. A Ctrl-C that
arrives after the prompt is written and before the read starts (the process descheduled there,
on a loaded machine, for milliseconds), or that the kernel hands to another thread, leaves the
read waiting: nothing happens until the next line comes, and only then the KeyboardInterrupt.

:func:`read_line` writes the prompt, then waits in ``select`` on the input and on a wake-up pipe
that the interpreter writes whenever a signal it handles arrives (:func:`signal.set_wakeup_fd`),
whenever and on whichever thread it arrives: the wait ends at once and the handler runs (Ctrl-C:
KeyboardInterrupt). It reads the input's file descriptor itself, a line at a time (the bytes read
past a line are kept for the next call); on a terminal, the line is edited by the terminal's own
line discipline. Off the main thread, or for an input without a file descriptor (a
``StringIO``), it is :func:`input`.
"""
from __future__ import annotations

import os
import select
import signal
import sys
import threading
import weakref

_CHUNK = 4096
_after_line: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # per input stream: bytes read past a line
_wake: list[int] = []  # the wake-up pipe's (read end, write end), once made


def read_line(prompt: str = "") -> str:
    """Write ``prompt`` to stdout and return the line read from stdin, without its line end, as
    :func:`input` does (EOFError at the end of the input); a signal whose handler raises (Ctrl-C)
    ends the wait however early it arrives."""
    fd = _fileno(sys.stdin)
    if fd is None or os.name != "posix" or threading.current_thread() is not threading.main_thread():
        return input(prompt)
    sys.stdout.write(prompt)
    sys.stdout.flush()
    pending = _after_line.setdefault(sys.stdin, bytearray())
    if b"\n" not in pending:
        _read_until_line_end(fd, pending)
    cut = pending.find(b"\n")
    if cut < 0:  # the input ended without a line end
        if not pending:
            raise EOFError("EOF when reading a line")
        cut = len(pending)
    line = bytes(pending[:cut])
    del pending[:cut + 1]
    encoding = getattr(sys.stdin, "encoding", None) or "utf-8"
    return line.decode(encoding, errors="replace").removesuffix("\r")


def _read_until_line_end(fd: int, pending: bytearray) -> None:
    """Read ``fd`` into ``pending`` until it holds a line end or the input ends, waiting on the
    interpreter's wake-up pipe beside it."""
    wake = _wake_pipe()
    old = signal.set_wakeup_fd(wake, warn_on_full_buffer=False)
    try:
        _drain(_wake[0])  # bytes of signals handled before (a signal before the drain: see below)
        while True:
            # a signal caught before this wait has its handler run at _ready's call (Python code)
            if _wake[0] in _ready(fd, _wake[0]):
                _drain(_wake[0])  # the handler runs before the next wait; one that returns: wait on
                continue
            chunk = os.read(fd, _CHUNK)
            pending += chunk
            if not chunk or b"\n" in chunk:
                return
    finally:
        signal.set_wakeup_fd(old)


def _wake_pipe() -> int:
    """The write end of this process's wake-up pipe (made once, never closed: a wake-up fd left set
    by an exception between two steps of Python code still names this pipe, not a reused number)."""
    if not _wake:
        _wake.extend(os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC))
    return _wake[1]


def _drain(fd: int) -> None:
    try:
        while os.read(fd, 512):
            pass
    except BlockingIOError:
        pass


def _ready(*fds: int) -> list[int]:
    return select.select(fds, [], [])[0]


def _fileno(stream) -> int | None:
    try:
        return stream.fileno()
    except (AttributeError, OSError, ValueError):  # io.UnsupportedOperation is an OSError and a ValueError
        return None

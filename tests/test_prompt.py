"""The prompt's line reader (haptic_acu/base/prompt.py): the lines it returns are input()'s, and a
Ctrl-C ends its wait even when the signal does not interrupt the read.

The Ctrl-C that was lost at the ratings' prompt arrived after the prompt was written and before the
read started: the interpreter only set its flag, and the read then waited for the next line. The
same state is made here without timing: the main thread waits at the prompt, asleep in the kernel,
and the SIGINT is sent to another thread of the process (``signal.pthread_kill``), so its handler's
flag is set while the main thread's wait gets no EINTR. A plain input() stays blocked then (the
control case); read_line must not.
"""
from __future__ import annotations

import os
import signal
import sys
import threading
import time

import pytest

from haptic_acu.base.prompt import read_line

LOST_AFTER_S = 5.0  # a wait still blocked this long after the signal: the Ctrl-C was lost (it ends in microseconds)


def _wchan(tid: int) -> str:
    with open(f"/proc/self/task/{tid}/wchan") as f:
        return f.read().strip()


def _asleep_in_a_read(tid: int) -> bool:
    """Thread ``tid`` of this process asleep in the kernel, not on a lock (the GIL is a futex)."""
    try:
        with open(f"/proc/self/task/{tid}/stat") as f:
            state = f.read().rpartition(") ")[2][:1]
        wchan = _wchan(tid)
    except OSError:
        return False
    return state == "S" and wchan not in ("", "0") and "futex" not in wchan


@pytest.fixture(scope="module")
def proc_wchan():
    """Skip where /proc does not say where a thread sleeps (the test waits for the read on it)."""
    r, w = os.pipe()
    tid = []
    t = threading.Thread(target=lambda: (tid.append(threading.get_native_id()), os.read(r, 1)))
    t.start()
    try:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not (tid and _asleep_in_a_read(tid[0])):
            time.sleep(0.01)
        ok = bool(tid) and _asleep_in_a_read(tid[0])
    finally:
        os.write(w, b"x")
        t.join()
        os.close(r)
        os.close(w)
    if not ok:
        pytest.skip("/proc/PID/task/TID/wchan does not show a read's sleep here")


@pytest.fixture
def stdin_pipe(monkeypatch):
    """stdin a pipe (the write end yielded); SIGINT raises KeyboardInterrupt meanwhile (a test runner's
    worker may ignore it)."""
    r, w = os.pipe()
    stream = open(r, encoding="utf-8")
    monkeypatch.setattr(sys, "stdin", stream)
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield w
    finally:
        signal.signal(signal.SIGINT, old)
        stream.close()
        os.close(w)


def _no_op():
    """A Python call: a signal's handler flagged before it runs at its start."""


def _ctrl_c_beside_the_wait(reader, w, capsys, lost_after_s=LOST_AFTER_S) -> tuple[bool, bool]:
    """Call ``reader`` at a prompt; once the main thread sleeps in its wait, SIGINT to another
    thread. (KeyboardInterrupt raised, a line had to be written to end the wait: still waiting
    ``lost_after_s`` after the signal.)"""
    main = threading.get_native_id()
    done = threading.Event()
    rescued = []

    def ctrl_c():
        deadline = time.monotonic() + 60
        while not done.is_set() and not _asleep_in_a_read(main) and time.monotonic() < deadline:
            time.sleep(0.005)
        signal.pthread_kill(threading.get_ident(), signal.SIGINT)  # this thread takes it: no EINTR in main
        if not done.wait(lost_after_s):
            rescued.append(True)
            os.write(w, b"5\n")  # a lost Ctrl-C's wait ends only with a line

    t = threading.Thread(target=ctrl_c, name="ctrl-c")
    interrupted = False
    try:
        t.start()
        reader("  3/7 real-time : ")
        _no_op()  # a flagged KeyboardInterrupt comes out here at the latest
    except KeyboardInterrupt:
        interrupted = True
    finally:
        done.set()
        t.join()
    assert capsys.readouterr().out == "  3/7 real-time : "
    return interrupted, bool(rescued)


def test_a_ctrl_c_that_does_not_interrupt_the_read_ends_the_prompt(proc_wchan, stdin_pipe, capsys):
    interrupted, rescued = _ctrl_c_beside_the_wait(read_line, stdin_pipe, capsys)
    assert interrupted and not rescued, "the Ctrl-C was lost: the prompt waited for the next line"
    assert signal.set_wakeup_fd(-1) == -1  # the interpreter's wake-up fd restored (none here)


def test_the_same_ctrl_c_is_lost_by_a_plain_input(proc_wchan, stdin_pipe, capsys):
    # the control: the state made above is the one that loses a Ctrl-C at input() (which cannot
    # return without a line, so a short wait shows it)
    interrupted, rescued = _ctrl_c_beside_the_wait(input, stdin_pipe, capsys, lost_after_s=0.5)
    assert rescued and interrupted  # (the KeyboardInterrupt comes only once the line is read)


def _lines_of(reader, data: bytes, monkeypatch, n: int) -> list:
    """``n`` calls of ``reader`` on stdin holding ``data`` then its end: each line, or "EOF"."""
    r, w = os.pipe()
    os.write(w, data)
    os.close(w)
    with open(r, encoding="utf-8") as stream:
        monkeypatch.setattr(sys, "stdin", stream)
        out = []
        for _ in range(n):
            try:
                out.append(reader(""))
            except EOFError:
                out.append("EOF")
        return out


def test_the_lines_are_inputs_lines(monkeypatch):
    # typed ahead (several lines in one read), CRLF, a line without its end, then the end of the input
    data = "7\n8.5\r\n\n  6 \n caf\u00e9\nlast".encode()
    got = _lines_of(read_line, data, monkeypatch, 8)
    assert got == _lines_of(input, data, monkeypatch, 8)
    assert got[-3:] == ["last", "EOF", "EOF"]


def test_a_handler_that_returns_leaves_the_wait_on(proc_wchan, stdin_pipe, capsys):
    # a signal whose handler raises nothing (SIGUSR1 here) wakes the wait, which goes on to the line
    seen = []
    old = signal.signal(signal.SIGUSR1, lambda signum, frame: seen.append(signum))
    main = threading.get_native_id()

    def later():
        deadline = time.monotonic() + 60
        while not _asleep_in_a_read(main) and time.monotonic() < deadline:
            time.sleep(0.005)
        signal.pthread_kill(threading.get_ident(), signal.SIGUSR1)
        time.sleep(0.05)
        os.write(stdin_pipe, b"9\n")

    t = threading.Thread(target=later)
    try:
        t.start()
        assert read_line("? ") == "9"
    finally:
        t.join()
        signal.signal(signal.SIGUSR1, old)
    assert seen == [signal.SIGUSR1]

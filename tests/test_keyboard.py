"""KeyboardDevice and the status line, driven through a real pseudo-terminal.

Key bytes are written to the pty's master side; the device reads the slave side as its terminal.
Nothing asserts on wall-clock durations: displacements are checked against the device's own
reported time (``DeviceState.t_s``), and waits for the reader thread poll with a generous deadline.
"""
from __future__ import annotations

import fcntl
import io
import os
import re
import select
import signal
import struct
import subprocess
import sys
import termios
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from physics_helpers import sphere_config

from haptic_acu.devices.base import Device, DeviceState
from haptic_acu.devices.keyboard import (LATERAL_STEP_M, LATERAL_STEP_S, NOT_A_TTY, SPEED_DEFAULT_M_S, SPEED_MAX_M_S,
                              SPEED_MIN_M_S, START_MM, TWIRL_HOLD_S, TWIRL_RATE_DEFAULT_DEG_S, TWIRL_RATES_DEG_S,
                              KeyboardDevice, KeyParser)
from haptic_acu.session.engine import Frame, Session, SessionResult
from haptic_acu.base.errors import UserError
from haptic_acu.servo.samples import COL, NCOL
from haptic_acu.session.status import StatusLine

ROOT = Path(__file__).resolve().parent.parent
PY = sys.executable
START = np.array(START_MM) * 1e-3
WAIT_S = 20.0  # deadline for the reader thread to see a key (a loaded machine is slow, never this slow)

UP, DOWN, RIGHT, LEFT = b"\x1b[A", b"\x1b[B", b"\x1b[C", b"\x1b[D"


@pytest.fixture
def pty_pair():
    master, slave = os.openpty()
    stdin = os.fdopen(slave, "rb", buffering=0)
    yield master, stdin
    stdin.close()
    try:
        os.close(master)
    except OSError:
        pass


@pytest.fixture
def kb(pty_pair):
    master, stdin = pty_pair
    out = io.StringIO()
    dev = KeyboardDevice(force_limit_n=3.3, stdin=stdin, out=out)
    dev.open()
    dev.read()  # start the device clock
    yield dev, master
    dev.close()


def press(dev, master, keys: bytes, n: int = 1) -> DeviceState:
    """Write ``keys``, wait until the reader has queued ``n`` more commands, return the next read
    (the read that applies them)."""
    before = dev.keys_handled
    os.write(master, keys)
    deadline = time.monotonic() + WAIT_S
    while dev.keys_handled < before + n:
        assert time.monotonic() < deadline, f"the key reader never saw {keys!r}"
        time.sleep(0.001)
    return dev.read()


def run_for(dev, device_s: float) -> list[DeviceState]:
    """Read as a 1 kHz servo would until the device's own clock has advanced ``device_s``."""
    states = [dev.read()]
    t0 = states[0].t_s
    while states[-1].t_s - t0 < device_s:
        time.sleep(0.001)
        states.append(dev.read())
    return states


# -- construction and terminal handling ----------------------------------------------------------------

def test_not_a_tty_is_one_line_user_error(tmp_path):
    f = tmp_path / "keys.txt"
    f.write_text("iiii\n")
    with open(f, "rb") as stdin, pytest.raises(UserError) as e:
        KeyboardDevice(stdin=stdin)
    assert str(e.value) == NOT_A_TTY and "\n" not in str(e.value)
    with pytest.raises(UserError, match="needs a terminal"):
        KeyboardDevice(stdin=io.StringIO("i"))  # no file descriptor at all


def test_not_a_tty_through_the_cli(tmp_path, monkeypatch, capsys):
    """`haptic-acu run --device keyboard < file`: one stderr line, exit 2, no traceback. (The command
    in process, its standard input the file: the device asks the file descriptor, as in a child.)"""
    from haptic_acu.cli import main

    f = tmp_path / "keys.txt"
    f.write_text("q\n")
    monkeypatch.chdir(tmp_path)
    with open(f, "rb") as stdin:
        monkeypatch.setattr(sys, "stdin", stdin)
        rc = main(["run", "--device", "keyboard"])
    err = capsys.readouterr().err
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err
    assert "needs a terminal" in lines[0] and "--device scripted" in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keys.txt"]  # no session folder left


def test_info(pty_pair):
    _, stdin = pty_pair
    dev = KeyboardDevice(force_limit_n=2.5, stdin=stdin, out=io.StringIO())
    assert isinstance(dev, Device)
    assert dev.info.name == "keyboard" and dev.info.drives_clock is False and dev.info.force_limit_n == 2.5


def test_cbreak_while_open_and_mode_restored_on_close(pty_pair):
    master, stdin = pty_pair
    fd = stdin.fileno()
    before = termios.tcgetattr(fd)
    assert before[3] & termios.ICANON and before[3] & termios.ECHO  # a fresh pty is cooked, echoing
    out = io.StringIO()
    dev = KeyboardDevice(stdin=stdin, out=out)
    dev.open()
    during = termios.tcgetattr(fd)
    assert not during[3] & termios.ICANON and not during[3] & termios.ECHO
    assert during[3] & termios.ISIG  # Ctrl-C still raises SIGINT
    assert "i/k" in out.getvalue() and out.getvalue().count("\n") == 1  # the one-line help
    dev.close()
    assert termios.tcgetattr(fd) == before
    dev.close()  # twice is fine
    assert termios.tcgetattr(fd) == before
    dev.open()  # and it can be opened again
    assert not termios.tcgetattr(fd)[3] & termios.ECHO
    dev.close()
    assert termios.tcgetattr(fd) == before


def test_mode_restored_when_the_session_code_raises(pty_pair):
    _, stdin = pty_pair
    fd = stdin.fileno()
    before = termios.tcgetattr(fd)
    with pytest.raises(RuntimeError):
        with KeyboardDevice(stdin=stdin, out=io.StringIO()):
            assert termios.tcgetattr(fd) != before
            raise RuntimeError("boom")
    assert termios.tcgetattr(fd) == before


_SIGTERM_CHILD = """
import sys, time
from haptic_acu.devices.keyboard import KeyboardDevice
dev = KeyboardDevice(stdin=sys.stdin, out=sys.stdout)
dev.open()
sys.stdout.flush()
time.sleep(120)
"""


def test_mode_restored_on_sigterm_outside_a_session(pty_pair):
    """A process killed by SIGTERM while the device is open (e.g. during warm-up) restores the tty
    and still dies of SIGTERM."""
    _, stdin = pty_pair
    fd = stdin.fileno()
    before = termios.tcgetattr(fd)
    child = subprocess.Popen([PY, "-c", _SIGTERM_CHILD], stdin=fd, stdout=subprocess.PIPE, cwd=ROOT)
    try:
        assert b"i/k" in child.stdout.readline()  # the help line: the device is open
        assert not termios.tcgetattr(fd)[3] & termios.ECHO
        child.send_signal(signal.SIGTERM)
        assert child.wait(timeout=60) == -signal.SIGTERM
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
        child.stdout.close()
    assert termios.tcgetattr(fd) == before


# -- keys and motion --------------------------------------------------------------------------------------

def test_starts_above_the_acupoint_at_rest(kb):
    dev, _ = kb
    s = dev.read()
    np.testing.assert_array_equal(s.position_m, START)
    np.testing.assert_array_equal(s.velocity_m_s, 0.0)
    np.testing.assert_array_equal(s.axis, [0.0, 0.0, 1.0])
    assert not s.done and not s.reset


def _check_axial_motion(states, direction: float, speed: float):
    """Between consecutive reads z moves by direction*speed*(own elapsed time); x, y stay put; the
    device's clock advances by at most the wall time between reads (it never runs ahead)."""
    t = np.array([s.t_s for s in states])
    p = np.array([s.position_m for s in states])
    assert t[-1] > t[0]
    np.testing.assert_allclose(p[:, 2] - p[0, 2], direction * speed * (t - t[0]), rtol=1e-6, atol=1e-9)
    np.testing.assert_array_equal(p[:, :2], np.repeat(p[:1, :2], len(p), axis=0))
    for s in states:
        np.testing.assert_allclose(s.velocity_m_s, [0.0, 0.0, direction * speed], atol=1e-15)


def test_insert_moves_down_the_axis_at_the_set_speed(kb):
    dev, master = kb
    w0 = time.perf_counter()
    s0 = press(dev, master, b"i")
    states = [s0] + run_for(dev, 0.1)
    wall = time.perf_counter() - w0
    _check_axial_motion(states, -1.0, SPEED_DEFAULT_M_S)
    assert states[-1].position_m[2] < START[2]
    assert states[-1].t_s - s0.t_s <= wall + 1e-9


def test_space_stops_and_the_opposite_key_reverses(kb):
    dev, master = kb
    press(dev, master, b"i")
    run_for(dev, 0.05)
    s = press(dev, master, b" ")
    np.testing.assert_array_equal(s.velocity_m_s, 0.0)
    still = run_for(dev, 0.05)
    assert all(np.array_equal(x.position_m, s.position_m) for x in still)
    # insert again, then the opposite key (no space in between) reverses
    press(dev, master, b"i")
    run_for(dev, 0.03)
    s = press(dev, master, b"k")
    states = [s] + run_for(dev, 0.05)
    _check_axial_motion(states, +1.0, SPEED_DEFAULT_M_S)
    # the arrows do the same: Down withdraws, Up inserts
    s = press(dev, master, UP)
    _check_axial_motion([s] + run_for(dev, 0.03), -1.0, SPEED_DEFAULT_M_S)
    s = press(dev, master, DOWN)
    _check_axial_motion([s] + run_for(dev, 0.03), +1.0, SPEED_DEFAULT_M_S)


def _lateral_step(dev, master, key: bytes, axis: int, sign: float):
    s0 = press(dev, master, key)
    p0 = s0.position_m.copy()
    states = [s0] + run_for(dev, LATERAL_STEP_S + 0.03)
    p = np.array([s.position_m for s in states])
    t = np.array([s.t_s for s in states])
    # the step is exactly 0.5 mm on that axis, nothing else moves
    np.testing.assert_allclose(p[-1, axis] - p0[axis], sign * LATERAL_STEP_M, atol=1e-12)
    other = [k for k in range(3) if k != axis]
    np.testing.assert_array_equal(p[:, other], np.repeat(p0[None, other], len(p), axis=0))
    # moved smoothly: no read moves it faster than 0.5 mm per 50 ms of the device's time ...
    speed = LATERAL_STEP_M / LATERAL_STEP_S
    assert np.all(np.abs(np.diff(p[:, axis])) <= speed * np.diff(t) + 1e-12)
    # ... so it takes the device at least 50 ms, and it reports that velocity while moving
    arrived = np.abs(p[:, axis] - p0[axis]) >= LATERAL_STEP_M - 1e-12
    assert t[arrived].min() - t[0] >= LATERAL_STEP_S - 1e-9
    assert abs(s0.velocity_m_s[axis] - sign * speed) < 1e-12
    np.testing.assert_array_equal(states[-1].velocity_m_s, 0.0)
    return p[-1]


def test_lateral_steps_of_half_a_millimetre(kb):
    dev, master = kb
    _lateral_step(dev, master, RIGHT, 0, +1.0)
    _lateral_step(dev, master, LEFT, 0, -1.0)
    _lateral_step(dev, master, b"l", 0, +1.0)
    _lateral_step(dev, master, b"h", 0, -1.0)
    _lateral_step(dev, master, b"u", 1, +1.0)
    p = _lateral_step(dev, master, b"n", 1, -1.0)
    np.testing.assert_allclose(p, START, atol=1e-12)  # back where it started
    # other arrow encodings: application mode (ESC O C) and with a modifier (ESC [ 1 ; 5 C)
    _lateral_step(dev, master, b"\x1bOC", 0, +1.0)
    _lateral_step(dev, master, b"\x1b[1;5D", 0, -1.0)


def test_speed_keys_double_and_halve_within_limits(kb):
    dev, master = kb
    assert dev.speed_m_s == SPEED_DEFAULT_M_S
    press(dev, master, b"+")
    assert dev.speed_m_s == 2 * SPEED_DEFAULT_M_S
    s = press(dev, master, b"i")
    _check_axial_motion([s] + run_for(dev, 0.05), -1.0, 2 * SPEED_DEFAULT_M_S)
    press(dev, master, b"+++++", n=5)
    assert dev.speed_m_s == SPEED_MAX_M_S
    press(dev, master, b"---------", n=9)
    assert dev.speed_m_s == SPEED_MIN_M_S
    s = press(dev, master, b"=")  # '+' without shift
    _check_axial_motion([s] + run_for(dev, 0.03), -1.0, 2 * SPEED_MIN_M_S)


def test_r_resets_the_tissue_once_and_returns_to_the_start(kb):
    dev, master = kb
    press(dev, master, b"i")
    press(dev, master, b"l")
    run_for(dev, 0.08)
    assert not np.allclose(dev.read().position_m, START)
    s = press(dev, master, b"r")
    assert s.reset is True
    np.testing.assert_array_equal(s.position_m, START)
    np.testing.assert_array_equal(s.velocity_m_s, 0.0)
    after = run_for(dev, 0.03)
    assert not any(x.reset for x in after)
    assert all(np.array_equal(x.position_m, START) for x in after)  # motion was stopped too


def _check_twirl(states, direction: float, rate_deg_s: float):
    """Between consecutive reads the roll turns by direction * rate * (own elapsed time), the tip
    stays put."""
    t = np.array([s.t_s for s in states])
    r = np.degrees([s.roll_rad for s in states])
    np.testing.assert_allclose(np.diff(r), direction * rate_deg_s * np.diff(t), rtol=1e-9, atol=1e-9)
    assert all(np.array_equal(s.position_m, states[0].position_m) for s in states)


def test_twirl_keys_roll_the_needle_while_held(kb):
    dev, master = kb
    assert dev.read().roll_rad == 0.0
    s = press(dev, master, b"]")
    held = [s] + run_for(dev, 0.2)  # well inside the hold: turning clockwise at the default rate
    assert held[-1].t_s - s.t_s < TWIRL_HOLD_S
    _check_twirl(held, 1.0, TWIRL_RATE_DEFAULT_DEG_S)
    # the other key reverses at once
    s = press(dev, master, b"[")
    back = [s] + run_for(dev, 0.1)
    _check_twirl(back, -1.0, TWIRL_RATE_DEFAULT_DEG_S)
    # let go (no auto-repeat): the roll stops TWIRL_HOLD_S after the last key, at rate x hold
    rest = run_for(dev, TWIRL_HOLD_S + 0.1)
    assert rest[-1].t_s - s.t_s > TWIRL_HOLD_S
    # from the key's read on: the roll turned back exactly rate x hold (the hold ends within a read)
    turned = np.degrees(s.roll_rad - rest[-1].roll_rad)
    assert turned == pytest.approx(TWIRL_RATE_DEFAULT_DEG_S * TWIRL_HOLD_S, rel=1e-9)
    assert rest[-1].roll_rad == rest[-2].roll_rad  # stopped
    # auto-repeat holds it: keys arriving within the hold keep it turning
    s0 = press(dev, master, b"]")
    states = [s0]
    for _ in range(4):
        states += run_for(dev, 0.1)
        states.append(press(dev, master, b"]"))
    _check_twirl(states, 1.0, TWIRL_RATE_DEFAULT_DEG_S)
    # space stops it
    press(dev, master, b" ")
    after = run_for(dev, 0.05)
    assert len({x.roll_rad for x in after}) == 1


def test_twirl_rate_key_cycles_and_reset_zeroes_the_roll(kb):
    dev, master = kb
    assert dev.twirl_rate_deg_s == TWIRL_RATE_DEFAULT_DEG_S
    seen = []
    for _ in range(len(TWIRL_RATES_DEG_S)):
        press(dev, master, b"t")
        seen.append(dev.twirl_rate_deg_s)
    assert sorted(seen) == sorted(TWIRL_RATES_DEG_S) and seen[-1] == TWIRL_RATE_DEFAULT_DEG_S
    press(dev, master, b"t")
    rate = dev.twirl_rate_deg_s
    assert rate != TWIRL_RATE_DEFAULT_DEG_S
    s = press(dev, master, b"[")
    _check_twirl([s] + run_for(dev, 0.1), -1.0, rate)
    assert max(TWIRL_RATES_DEG_S) / 360.0 < 10.0  # within the hand-twirl limit a trajectory allows
    s = press(dev, master, b"r")
    assert s.reset and s.roll_rad == 0.0
    assert all(x.roll_rad == 0.0 for x in run_for(dev, 0.05))


def test_q_sets_done_and_keeps_it(kb):
    dev, master = kb
    press(dev, master, b"i")
    s = press(dev, master, b"q")
    assert s.done is True
    np.testing.assert_array_equal(s.velocity_m_s, 0.0)
    assert all(x.done for x in run_for(dev, 0.01))


def test_a_hung_up_terminal_ends_the_session(pty_pair):
    master, stdin = pty_pair
    dev = KeyboardDevice(stdin=stdin, out=io.StringIO())
    dev.open()
    try:
        os.close(master)  # the terminal goes away (SSH connection dropped)
        deadline = time.monotonic() + WAIT_S
        while not dev.read().done:
            assert time.monotonic() < deadline
            time.sleep(0.001)
    finally:
        dev.close()


def test_key_parser_split_sequences_and_unknown_keys():
    p = KeyParser()
    assert p.feed(b"\x1b") == [] and p.pending
    assert p.feed(b"[") == [] and p.pending
    assert p.feed(b"A") == ["insert"] and not p.pending
    assert p.feed(b"\x1b[1;") == []
    assert p.feed(b"2Bq") == ["withdraw", "quit"]
    assert p.feed(b"\x1b[5~x\x1b[Hz") == []  # PageUp, an unmapped key, Home: ignored
    assert p.feed(b"\x1b") == []
    p.flush()  # a lone ESC (the reader flushes after 50 ms of silence)
    assert p.feed(b"[A") == ["twirl-"]  # ... so these are plain '[' (a twirl key) and 'A', not an arrow
    assert p.feed(b"\x1bi") == ["insert"]  # Alt-i
    assert p.feed("é".encode()) == []


# -- the status line -------------------------------------------------------------------------------------

def test_status_line_silent_when_not_a_terminal():
    buf = io.StringIO()
    s = StatusLine(stream=buf)
    assert not s.enabled
    assert StatusLine(stream=buf, force=True).enabled


def _row(t=0.0, layer=-1, depth_mm=0.0, depth_skin_mm=0.0, force=(0.0, 0.0, 0.0), v=(0.0, 0.0, 0.0),
         states=(0, 0, 0), period_err_s=0.0, roll_deg=0.0, torque_nmm=0.0):
    r = np.zeros(NCOL)
    r[COL["roll_deg"]] = roll_deg
    r[COL["torque_nmm"]] = torque_nmm
    r[COL["t_s"]] = t
    r[COL["layer"]] = layer
    r[COL["depth_m"]] = depth_mm * 1e-3
    r[COL["depth_skin_m"]] = depth_skin_mm * 1e-3
    r[COL["fx_n"]:COL["fx_n"] + 3] = force
    r[COL["vx_m_s"]:COL["vx_m_s"] + 3] = v
    r[COL["state_skin"]:COL["state_skin"] + 3] = states
    r[COL["period_err_s"]] = period_err_s
    return r


def _frame(rows, t=None, rates=None):
    rows = np.atleast_2d(np.array(rows))
    return Frame(t_s=rows[-1, 0] if t is None else t, index=0, samples=rows, model=None,
                 rates=rates or {"servo_hz": 998.0, "visual_hz": 59.0})


def test_status_line_content_missed_ticks_and_fault():
    buf = io.StringIO()
    s = StatusLine(stream=buf, force=True)
    # 3 ticks of 50 late by more than a 1 ms period, 2 late by less
    errs = np.zeros(50)
    errs[[3, 17, 40]] = [1.5e-3, 4e-3, 1.01e-3]
    errs[[5, 6]] = [0.9e-3, 0.2e-3]
    rows = [_row(t=0.001 * k, layer=1, depth_mm=1.25, depth_skin_mm=2.5, force=(0.3, 0.0, 0.4),
                 v=(0.0, 0.0, -0.005), states=(2, 1, 0), period_err_s=e) for k, e in enumerate(errs)]
    s.on_frame(_frame(rows))
    s.close(SessionResult(ticks=50, duration_s=0.049, fault="device fault: cable pulled", stats={}))
    text = buf.getvalue()
    line, fault = text.split("\n")[:2]
    assert line.startswith("\rt 0.05 s | x +0.0 y +0.0 mm | fat 1.25 mm | 2.50 mm deep | |F| 0.50 N | v 5.0 mm/s | ")
    assert "skin:punct fat:press muscle:-" in line
    assert "roll" not in line  # never rolled: no roll field
    s2 = StatusLine(stream=io.StringIO(), force=True)
    s2.on_frame(_frame([_row(t=1.0, layer=2, roll_deg=-123.4, torque_nmm=-0.2864, states=(2, 2, 2))]))
    assert "| roll -123 deg | -0.286 N*mm |" in s2.stream.getvalue()  # the roll kept longer than the torque
    assert "servo 998 Hz visual 59 Hz" in line and line.endswith("host late 6.0%, missed 3")  # 3 of 50 ticks
    assert fault == "fault: device fault: cable pulled" and text.endswith("\n")
    # nothing drawn, nothing printed, when the stream is not a terminal
    quiet = io.StringIO()
    q = StatusLine(stream=quiet)
    q.on_frame(_frame(rows))
    q.close(SessionResult(ticks=50, duration_s=0.049, fault="x", stats={}))
    assert quiet.getvalue() == ""


def test_status_line_at_most_ten_a_second_and_within_the_terminal_width(pty_pair):
    master, stdin = pty_pair
    set_winsize(stdin.fileno(), 24, 80)
    term = os.fdopen(os.dup(stdin.fileno()), "w")
    s = StatusLine(stream=term)  # a pty is a terminal: enabled without force
    assert s.enabled
    got = bytearray()
    w0 = time.monotonic()
    for k in range(300):
        s.on_frame(_frame([_row(t=0.001 * k, layer=2, depth_mm=12.5, depth_skin_mm=21.5, force=(0.0, 0.0, 1.0),
                                states=(2, 2, 1))]))
        if k % 20 == 0:
            time.sleep(0.01)
    wall = time.monotonic() - w0
    s.close(None)
    term.close()
    while select.select([master], [], [], 0.2)[0]:
        got.extend(os.read(master, 65536))
    segs = [x for x in re.split(r"[\r\n]", got.decode()) if x.strip()]
    # one draw per 0.1 s at most (the first is immediate), plus the final draw at close
    assert 1 <= s.lines <= 2 + wall / 0.1
    assert len(segs) == s.lines
    for seg in segs:
        assert len(seg) <= 79
        assert seg.startswith("t ") and "muscle 12.50 mm" in seg and "|F| 1.00 N" in seg
        # at 79 columns the depth against the target and the speed stay; the layer states go first
        assert "21.50 mm deep" in seg and "v 0.0 mm/s" in seg


def set_winsize(fd: int, rows: int, cols: int) -> None:
    fcntl.ioctl(fd, termios.TIOCSWINSZ, struct.pack("HHHH", rows, cols, 0, 0))


def _status_lines(text: str) -> list[str]:
    """The status texts drawn on a terminal: segments between carriage returns and newlines."""
    return [seg.strip() for seg in re.split(r"[\r\n]", text) if seg.strip().startswith("t ")]


@pytest.mark.slow
def test_live_session_on_a_pty_with_status_line():
    """A real-time Session with the keyboard on a pty and the status line drawn on it: `i` drives the
    needle through the skin, the status line follows, `q` ends the session, the tty is restored."""
    master, slave = os.openpty()
    set_winsize(slave, 24, 250)  # wide enough for every field
    stdin = os.fdopen(slave, "rb", buffering=0)
    term_out = os.fdopen(os.dup(slave), "w", buffering=1)
    fd = stdin.fileno()
    before = termios.tcgetattr(fd)
    out = bytearray()
    sent_q = threading.Event()

    def operator():
        """Read everything the terminal shows; send `q` once the status line has shown a force over
        0.2 N and then the skin punctured with the rates measured (or after a long deadline, so the
        test cannot hang)."""
        deadline = time.monotonic() + 120
        while True:
            try:
                chunk = os.read(master, 4096)
            except OSError:
                return
            if not chunk:
                return
            out.extend(chunk)
            if sent_q.is_set():
                continue
            lines = _status_lines(out.decode(errors="replace"))
            forces = [float(f) for ln in lines for f in re.findall(r"\|F\| (\d+\.\d+) N", ln)]
            rated = [ln for ln in lines if "skin:punct" in ln and "servo 0 Hz" not in ln]
            if (rated and max(forces) > 0.2) or time.monotonic() > deadline:
                sent_q.set()
                os.write(master, b"q")

    reader = threading.Thread(target=operator, daemon=True)
    reader.start()
    cfg = sphere_config()
    dev = KeyboardDevice(force_limit_n=cfg.safety.force_limit_n, stdin=stdin, out=term_out)
    status = StatusLine(stream=term_out, force=True)
    cap_s = 60.0
    try:
        dev.open()
        assert not termios.tcgetattr(fd)[3] & termios.ECHO
        session = Session(cfg, dev, [status], clock="realtime", duration_s=cap_s, realtime_priority=False,
                          dents=False)
        session.warm_up()
        os.write(master, b"i")
        result = session.run()
    finally:
        dev.close()
        restored = termios.tcgetattr(fd)
        term_out.close()
        stdin.close()
        reader.join(timeout=10)  # EOF on the master once every slave fd is closed
        os.close(master)
    assert restored == before
    assert sent_q.is_set(), out.decode(errors="replace")[-3000:]
    assert result.fault is None
    assert result.duration_s < cap_s  # ended by `q`, not by the duration cap
    text = out.decode(errors="replace")
    assert "i/k" in text  # the help line
    lines = _status_lines(text)
    assert len(lines) >= 3
    pat = re.compile(r"^t (\d+\.\d+) s \| x [-+]\d+\.\d y [-+]\d+\.\d mm \| (\S+)[^|]*"
                     r"(?:\| [\d.]+ mm deep[^|]*)?\| \|F\| (\d+\.\d+) N \| "
                     r"v (\d+\.\d) mm/s(?: \(set [\d.]+\))? \| skin:(\S+) fat:(\S+) muscle:(\S+) \| "
                     r"(?:last puncture \w+ [\d.]+ N \| )?servo (\d+) Hz visual (\d+) Hz \| "
                     r"(?:loop ok|host late [\d.]+%, missed \d+)$")
    parsed = [pat.match(ln) for ln in lines]
    assert all(parsed), [ln for ln, m in zip(lines, parsed) if not m]
    times = [float(m.group(1)) for m in parsed]
    assert times == sorted(times) and times[-1] > times[0]
    forces = [float(m.group(3)) for m in parsed]
    skin = [m.group(5) for m in parsed]
    assert skin[0] == "-" and "punct" in skin  # untouched at the start, then through the skin
    assert max(forces) > 0.2  # the tissue pushed back
    assert float(parsed[-1].group(4)) == pytest.approx(SPEED_DEFAULT_M_S * 1e3, abs=0.05)  # inserting at 5 mm/s
    assert int(parsed[-1].group(8)) > 0 and int(parsed[-1].group(9)) > 0  # measured rates
    assert text.endswith("\n") or text.endswith("\r\n")  # close() ended the line


_CTTY = "import fcntl, os, sys, termios; fcntl.ioctl(0, termios.TIOCSCTTY, 0); os.execv(sys.executable, [sys.executable] + sys.argv[1:])"


@pytest.mark.slow
def test_ctrl_c_in_haptic_acu_run_on_a_controlling_terminal(tmp_path):
    """`haptic-acu run --device keyboard` on a pty that is its controlling terminal: Ctrl-C (SIGINT
    from the line discipline) ends the session cleanly (exit 0, the summary printed) and the
    terminal's mode is as before."""
    toml = (ROOT / "config" / "tissue.toml").read_text()
    for key, value in (("semi_axes_mm", "[200.0, 200.0, 200.0]"), ("bulge", "0.0"), ("lmax", "2"),
                       ("fit_samples", "200")):  # a sphere, fitted in a moment
        toml, n = re.subn(rf"(?m)^{key} = .*$", f"{key} = {value}", toml)
        assert n == 1
    cfg = tmp_path / "sphere.toml"
    cfg.write_text(toml)
    master, slave = os.openpty()
    set_winsize(slave, 24, 250)
    before = termios.tcgetattr(slave)
    # a new session whose controlling terminal is the pty (the wrapper takes it, then execs the CLI)
    child = subprocess.Popen([PY, "-c", _CTTY, "-m", "haptic_acu", "run", "--device", "keyboard", "--duration", "120",
                              "--config", str(cfg), "--out", str(tmp_path / "session")], stdin=slave, stdout=slave, stderr=slave, cwd=ROOT,
                             start_new_session=True)
    out = bytearray()
    state = "start"
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline:
            try:
                chunk = os.read(master, 4096) if select_ready(master, 0.2) else b""
            except OSError:
                break
            out.extend(chunk)
            text = out.decode(errors="replace")
            if state == "start" and "i/k" in text:
                os.write(master, b"i")  # queued until the session's first read
                state = "inserting"
            elif state == "inserting" and "skin:press" in text:
                os.write(master, b"\x03")  # Ctrl-C
                state = "interrupted"
            if child.poll() is not None and not chunk:
                break
        assert child.wait(timeout=60) == 0, out.decode(errors="replace")[-2000:]
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
        after = termios.tcgetattr(slave)
        os.close(slave)
        os.close(master)
    assert state == "interrupted"
    text = out.decode(errors="replace")
    assert "session:" in text and "ticks" in text  # the run command's summary: it ended normally
    assert "Traceback" not in text and "fault" not in text
    assert after == before


def select_ready(fd: int, timeout: float) -> bool:
    return bool(select.select([fd], [], [], timeout)[0])

"""A needle moved from the keyboard, in a plain terminal (works over SSH, no display needed).

The needle starts 5 mm above the acupoint, at (0, 0, +5 mm) in the scene frame, pointing down the
insertion axis -z (the acupoint is the skin's +z pole at the scene origin). Keys:

====================  ===========================================================================
``i`` / Up            insert: move along -z at the set speed until stopped or reversed
``k`` / Down          withdraw: move along +z at the set speed
``space``             stop the axial motion
``h`` / Left          lateral step of 0.5 mm in -x  (each step is moved over 50 ms, not jumped)
``l`` / Right         lateral step of 0.5 mm in +x
``u`` / ``n``         lateral step of 0.5 mm in +y / -y
``+`` (``=``)         axial speed x2 (at most 40 mm/s)
``-`` (``_``)         axial speed /2 (at least 1 mm/s); the default is 5 mm/s
``]`` / ``[``         twirl: roll the needle clockwise / counter-clockwise (seen from the handle) at
                      the set twirl rate while the key is held (see below)
``t``                 twirl rate: the next of 90, 180, 360, 720 deg/s (the default 180)
``r``                 fresh tissue (``DeviceState.reset`` for one read) and the needle back at the start
``q`` / Ctrl-C        quit (``DeviceState.done``)
====================  ===========================================================================

Terminals send no key-up events, so a press starts a motion and ``space`` stops it; the opposite
key reverses it. A twirl key is "held" by the terminal's auto-repeat: each ``[`` / ``]`` keeps the
needle rolling that way for :data:`TWIRL_HOLD_S` (0.6 s, longer than the usual 0.5 s auto-repeat
delay), so holding the key rolls it steadily and a tap rolls it by rate x 0.6 s; the other twirl key
reverses at once, ``space`` stops it. The roll is cumulative (``DeviceState.roll_rad``, rad, positive
clockwise seen from the handle) and back to 0 on ``r``. The tip stays within 60 mm below and 30 mm above the acupoint and 25 mm off the
axis: the axial motion stops at those limits and lateral steps past them are ignored.

Terminal handling: :meth:`KeyboardDevice.open` puts the tty in cbreak mode (no line buffering, no
echo; signals stay on, so Ctrl-C is SIGINT: the engine's handler stops the session and ``close``
runs). ``close`` restores the saved mode; so do an ``atexit`` hook and a SIGTERM handler installed
while the device is open (outside a session, where the engine's own handlers are not in place), so
the shell is never left without echo. Keys are read on a background thread with ``select`` on the
tty's file descriptor; escape sequences (``ESC [ A`` and ``ESC O A`` forms, with or without
modifier parameters) give the arrow keys. The reader only queues commands: the servo thread applies
them in :meth:`KeyboardDevice.read` and never waits on the terminal.

Motion (``read``): the commanded motion is integrated over the wall-clock time since the previous
read (``time.perf_counter``), at most ``max_step_s`` (20 ms) per read, so a stalled loop resumes
without a jump (at 40 mm/s a 20 ms step is 0.8 mm, i.e. 0.8 m/s over one 1 ms tick, inside the 2 m/s
hand-speed limit). ``DeviceState.t_s`` is the device's own time, the sum of those steps. The
insertion advances only while the force on the needle does not push it back out at the device's
force limit (``set_force``'s last force, +z at :data:`HELD_BACK_SHARE` of ``force_limit_n``): against
bone, or with the handle on the skin, the needle stops as a hand limited to that force would.
``velocity_m_s`` is the commanded velocity from this read on. In a session the engine reads with
``read_at(t)`` on its servo clock instead: the motion is integrated over session time and the
velocity is the last step's displacement over its duration, so a replay of the session's recording
(which derives the velocity from the recorded positions) feeds the servo the same numbers. All in
SI, scene frame.

The keyboard has no physical frame, so it works in the scene frame directly: the ``workspace``
argument (the mapping of a physical device's frame) is accepted for a uniform constructor and
kept, but not applied.
"""
from __future__ import annotations

import atexit
import collections
import math
import os
import select
import signal
import sys
import termios
import threading
import time

import numpy as np

from haptic_acu.base.errors import UserError

from .base import Device, DeviceInfo, DeviceState, Workspace

START_MM = (0.0, 0.0, 5.0)  # needle tip at open and after reset (scene frame)
AXIS = (0.0, 0.0, 1.0)  # unit vector from the tip toward the handle: insertion is along -z
LATERAL_STEP_M = 0.5e-3
LATERAL_STEP_S = 0.05  # a lateral step is moved at 0.5 mm / 50 ms = 10 mm/s
SPEED_DEFAULT_M_S = 5e-3
SPEED_MIN_M_S = 1e-3
SPEED_MAX_M_S = 40e-3
DEPTH_LIMIT_M = 60e-3  # below the acupoint (the default tissue's bone is at 48.2 mm)
HEIGHT_LIMIT_M = 30e-3  # above the acupoint
LATERAL_LIMIT_M = 25e-3  # off the axis, in x and in y
TWIRL_RATES_DEG_S = (90.0, 180.0, 360.0, 720.0)  # the ``t`` key cycles through these (2 turns/s at most)
TWIRL_RATE_DEFAULT_DEG_S = 180.0
TWIRL_HOLD_S = 0.6  # a twirl key rolls the needle this long (auto-repeat extends it while held)
ESC_TIMEOUT_S = 0.05  # a lone ESC not followed by more bytes within this is dropped

HELP = ("keyboard: i/k or Up/Down insert/withdraw, space stop, h/l or Left/Right x -/+0.5 mm, "
        "u/n y +/-0.5 mm, +/- speed, ]/[ twirl cw/ccw, t twirl rate, r reset, q quit")
NOT_A_TTY = "the keyboard device needs a terminal (a tty); use --device scripted for files"

# single bytes -> command
_KEYS = {
    b"i": "insert", b"k": "withdraw", b" ": "stop",
    b"h": "x-", b"l": "x+", b"u": "y+", b"n": "y-",
    b"+": "faster", b"=": "faster", b"-": "slower", b"_": "slower",
    b"]": "twirl+", b"[": "twirl-", b"t": "twirl_rate",
    b"r": "reset", b"q": "quit", b"\x03": "quit",
}
# final byte of an ESC [ ... or ESC O ... sequence -> command
_ARROWS = {b"A": "insert", b"B": "withdraw", b"C": "x+", b"D": "x-"}


class KeyParser:
    """Bytes from a terminal -> commands (strings). Keeps an incomplete escape sequence between
    calls to :meth:`feed`; :meth:`flush` drops a pending lone ESC (call it when no byte followed
    within :data:`ESC_TIMEOUT_S`). Unknown keys and sequences are ignored."""

    def __init__(self):
        self._buf = b""

    @property
    def pending(self) -> bool:
        return bool(self._buf)

    def flush(self) -> None:
        self._buf = b""

    def feed(self, data: bytes) -> list[str]:
        buf = self._buf + data
        out = []
        i = 0
        n = len(buf)
        while i < n:
            b = buf[i:i + 1]
            if b != b"\x1b":
                cmd = _KEYS.get(b)
                if cmd is not None:
                    out.append(cmd)
                i += 1
                continue
            if i + 1 >= n:
                break  # ESC alone so far: wait for more
            intro = buf[i + 1:i + 2]
            if intro == b"\x1b":
                i += 1  # ESC ESC: the first is a lone ESC
                continue
            if intro not in (b"[", b"O"):
                i += 1  # ESC + key (Alt-key): treat as the key
                continue
            j = i + 2
            while j < n and not 0x40 <= buf[j] <= 0x7E:  # parameter / intermediate bytes
                j += 1
            if j >= n:
                break  # incomplete sequence: wait for more
            cmd = _ARROWS.get(buf[j:j + 1])
            if cmd is not None:
                out.append(cmd)
            i = j + 1
        self._buf = buf[i:]
        if len(self._buf) > 32:  # a runaway sequence: give up on it
            self._buf = b""
        return out


HELD_BACK_SHARE = 0.999  # of the force limit: the insertion key pushes no further against it


class KeyboardDevice(Device):
    """Keys in the terminal on ``stdin`` move the needle; see the module doc for the keys and the
    motion model. ``out`` receives the one-line help at open. ``force_limit_n`` is reported in
    :class:`DeviceInfo` (nothing is commanded: there is no motor)."""

    def __init__(self, workspace: Workspace | None = None, force_limit_n: float = 3.3, stdin=None, out=None,
                 max_step_s: float = 0.02):
        self.workspace = workspace if workspace is not None else Workspace()
        self.stdin = sys.stdin if stdin is None else stdin
        self.out = sys.stderr if out is None else out
        self.max_step_s = float(max_step_s)
        self._fd = self._tty_fd(self.stdin)
        self.info = DeviceInfo(name="keyboard", model="terminal keyboard", force_limit_n=float(force_limit_n),
                               rate_hz=1000.0, drives_clock=False)
        self.last_force_n = np.zeros(3)
        self.keys_handled = 0  # commands the reader thread has queued (for tests and diagnostics)
        self._commands: collections.deque = collections.deque()
        self._saved_attrs = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._wake_r = self._wake_w = -1
        self._old_sigterm = None
        self._term_lock = threading.Lock()
        self._reset_motion()

    @staticmethod
    def _tty_fd(stream) -> int:
        try:
            fd = stream.fileno()
        except (AttributeError, OSError, ValueError):
            raise UserError(NOT_A_TTY) from None
        if not os.isatty(fd):
            raise UserError(NOT_A_TTY)
        return fd

    def _reset_motion(self) -> None:
        self._p = np.array(START_MM) * 1e-3
        self._axial = 0  # +1 inserting (-z), -1 withdrawing, 0 stopped
        self.speed_m_s = SPEED_DEFAULT_M_S
        self._lateral_left = np.zeros(2)  # lateral displacement still to move (m)
        self._roll = 0.0  # rad, cumulative, + clockwise seen from the handle
        self._twirl = 0  # +1 clockwise, -1 counter-clockwise, 0 still
        self._twirl_until = 0.0  # device time the current twirl key's hold ends
        self.twirl_rate_deg_s = TWIRL_RATE_DEFAULT_DEG_S
        self._t = 0.0
        self._last_wall: float | None = None
        self._done = False
        self._reads = 0  # reads since open: the engine reads once per servo tick
        self.events: list[tuple[int, str]] = []  # (read index = servo tick, name): ("reset") for recordings

    # -- Device interface ----------------------------------------------------------------------
    def open(self) -> None:
        """Terminal to cbreak mode, start the key reader, print the help line."""
        if self._thread is not None:
            return
        self._tty_fd(self.stdin)  # still a tty?
        self._reset_motion()
        self._last_session_t = None  # the engine's clock (read_at); a reset (`r`) does not restart it
        self._commands.clear()
        self._saved_attrs = termios.tcgetattr(self._fd)
        try:
            mode = termios.tcgetattr(self._fd)
            mode[3] &= ~(termios.ICANON | termios.ECHO)  # lflag: no line buffering, no echo; ISIG kept
            mode[6][termios.VMIN] = 1
            mode[6][termios.VTIME] = 0
            termios.tcsetattr(self._fd, termios.TCSANOW, mode)
            atexit.register(self._restore_terminal)
            self._install_sigterm()
            self._wake_r, self._wake_w = os.pipe()
            self._stop.clear()
            self._thread = threading.Thread(target=self._reader, name="haptic-acu-keyboard", daemon=True)
            self._thread.start()
        except BaseException:
            self.close()
            raise
        try:
            print(HELP, file=self.out, flush=True)
        except (OSError, ValueError):
            pass

    def close(self) -> None:
        """Stop the reader and restore the terminal. Safe to call twice."""
        self._stop.set()
        if self._wake_w >= 0:
            try:
                os.write(self._wake_w, b"x")
            except OSError:
                pass
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for fd in (self._wake_r, self._wake_w):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._wake_r = self._wake_w = -1
        self._restore_terminal()
        self._remove_sigterm()
        try:
            atexit.unregister(self._restore_terminal)
        except Exception:  # interpreter shutting down
            pass

    def read(self) -> DeviceState:
        now = time.perf_counter()
        dt = 0.0 if self._last_wall is None else min(max(now - self._last_wall, 0.0), self.max_step_s)
        self._last_wall = now
        self._integrate(dt)
        self._t += dt
        return self._state(None)  # the commanded velocity, after this read's keys

    def read_at(self, t_s: float) -> DeviceState:
        """The state at session time ``t_s`` (the engine's servo clock): the motion integrated over
        the session time since the previous read (at most ``max_step_s``), and ``velocity_m_s`` the
        tip's displacement over that step divided by it (0 on the first read), the velocity a
        replay of the recording derives from the same positions (:mod:`devices.scripted`)."""
        t_s = float(t_s)
        last = getattr(self, "_last_session_t", None)
        dt = 0.0 if last is None else min(max(t_s - last, 0.0), self.max_step_s)
        self._last_session_t = t_s
        p0 = self._p.copy()
        self._integrate(dt)
        self._t += dt
        v = (self._p - p0) / dt if dt > 0.0 else np.zeros(3)
        return self._state(v)

    def _state(self, velocity) -> DeviceState:
        """Apply the queued keys; the state with ``velocity`` (None: the commanded one, after the keys)."""
        reset = False
        while self._commands:
            cmd = self._commands.popleft()
            if cmd == "reset":
                reset = True
            self._apply(cmd)
        if reset:
            self.events.append((self._reads, "reset"))
        self._reads += 1
        if velocity is None:
            velocity = self._velocity()
        return DeviceState(t_s=self._t, position_m=self._p.copy(), velocity_m_s=velocity,
                           axis=np.array(AXIS), done=self._done, reset=reset, roll_rad=self._roll)

    def set_force(self, force_n) -> None:
        self.last_force_n = np.array(force_n, dtype=np.float64).reshape(3)

    # -- motion ----------------------------------------------------------------------------------
    def _lateral_velocity(self) -> np.ndarray:
        left = self._lateral_left
        m = math.hypot(left[0], left[1])
        if m == 0.0:
            return np.zeros(2)
        return left / m * (LATERAL_STEP_M / LATERAL_STEP_S)

    def _velocity(self) -> np.ndarray:
        v = np.zeros(3)
        v[:2] = self._lateral_velocity()
        v[2] = -self._axial * self.speed_m_s
        return v

    def _integrate(self, dt: float) -> None:
        if dt <= 0.0:
            return
        if self._twirl:
            turn = min(dt, max(self._twirl_until - self._t, 0.0))  # the hold ends within this step
            self._roll += self._twirl * math.radians(self.twirl_rate_deg_s) * turn
            if self._t + dt >= self._twirl_until:
                self._twirl = 0
        if self._axial > 0 and self._held_back():
            pass  # the hand cannot push harder than the device's limit: the needle goes no deeper
        elif self._axial:
            z = self._p[2] - self._axial * self.speed_m_s * dt
            lo, hi = -DEPTH_LIMIT_M, HEIGHT_LIMIT_M
            if z <= lo or z >= hi:
                z = min(max(z, lo), hi)
                self._axial = 0
            self._p[2] = z
        left = self._lateral_left
        m = math.hypot(left[0], left[1])
        if m > 0.0:
            move = LATERAL_STEP_M / LATERAL_STEP_S * dt
            if move >= m:
                self._p[:2] += left
                left[:] = 0.0
            else:
                d = left * (move / m)
                self._p[:2] += d
                left -= d

    def _held_back(self) -> bool:
        """The force on the needle pushes it back out (+z) at the device's force limit: an insertion
        into bone or with the handle on the skin stops there, as a hand limited to that force would."""
        lim = float(self.info.force_limit_n)
        f = getattr(self, "last_force_n", None)
        return f is not None and lim > 0.0 and float(f[2]) >= HELD_BACK_SHARE * lim

    def _apply(self, cmd: str) -> None:
        if cmd == "insert":
            self._axial = 1 if self._p[2] > -DEPTH_LIMIT_M else 0
        elif cmd == "withdraw":
            self._axial = -1 if self._p[2] < HEIGHT_LIMIT_M else 0
        elif cmd == "stop":
            self._axial = 0
            self._twirl = 0
        elif cmd in ("twirl+", "twirl-"):
            self._twirl = 1 if cmd == "twirl+" else -1
            self._twirl_until = self._t + TWIRL_HOLD_S
        elif cmd == "twirl_rate":
            i = TWIRL_RATES_DEG_S.index(self.twirl_rate_deg_s) if self.twirl_rate_deg_s in TWIRL_RATES_DEG_S else -1
            self.twirl_rate_deg_s = TWIRL_RATES_DEG_S[(i + 1) % len(TWIRL_RATES_DEG_S)]
        elif cmd in ("x-", "x+", "y-", "y+"):
            k = 0 if cmd[0] == "x" else 1
            step = LATERAL_STEP_M if cmd[1] == "+" else -LATERAL_STEP_M
            target = self._p[k] + self._lateral_left[k] + step
            if abs(target) <= LATERAL_LIMIT_M + 1e-12:
                self._lateral_left[k] += step
        elif cmd == "faster":
            self.speed_m_s = min(self.speed_m_s * 2.0, SPEED_MAX_M_S)
        elif cmd == "slower":
            self.speed_m_s = max(self.speed_m_s / 2.0, SPEED_MIN_M_S)
        elif cmd == "reset":
            self._p[:] = np.array(START_MM) * 1e-3
            self._axial = 0
            self._roll = 0.0
            self._twirl = 0
            self._lateral_left[:] = 0.0
        elif cmd == "quit":
            self._done = True
            self._axial = 0
            self._twirl = 0
            self._lateral_left[:] = 0.0

    # -- the key reader thread ------------------------------------------------------------------
    def _reader(self) -> None:
        parser = KeyParser()
        fd, wake = self._fd, self._wake_r
        while not self._stop.is_set():
            timeout = ESC_TIMEOUT_S if parser.pending else 0.5
            try:
                ready, _, _ = select.select([fd, wake], [], [], timeout)
            except (OSError, ValueError):
                break
            if wake in ready or self._stop.is_set():
                break
            if not ready:
                parser.flush()  # a lone ESC
                continue
            try:
                data = os.read(fd, 256)
            except BlockingIOError:
                continue
            except OSError:  # the terminal went away (hang-up)
                data = b""
            if not data:
                self._commands.append("quit")
                self.keys_handled += 1
                break
            for cmd in parser.feed(data):
                self._commands.append(cmd)
                self.keys_handled += 1

    # -- terminal restoration --------------------------------------------------------------------
    def _restore_terminal(self) -> None:
        with self._term_lock:
            attrs, self._saved_attrs = self._saved_attrs, None
        if attrs is None:
            return
        try:
            termios.tcsetattr(self._fd, termios.TCSADRAIN, attrs)
        except (OSError, termios.error, ValueError):
            pass

    def _install_sigterm(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        try:
            self._old_sigterm = signal.signal(signal.SIGTERM, self._on_sigterm)
        except (ValueError, OSError):
            self._old_sigterm = None

    def _remove_sigterm(self) -> None:
        old, self._old_sigterm = self._old_sigterm, None
        if old is None or threading.current_thread() is not threading.main_thread():
            return
        try:
            if signal.getsignal(signal.SIGTERM) == self._on_sigterm:
                signal.signal(signal.SIGTERM, old)
        except (ValueError, OSError):
            pass

    def _on_sigterm(self, signum, frame) -> None:
        """SIGTERM outside a session: restore the terminal, then do what was done before."""
        self._restore_terminal()
        old = self._old_sigterm
        self._remove_sigterm()
        if callable(old):
            old(signum, frame)
        elif old == signal.SIG_IGN:
            return
        else:  # default action: terminate, by the signal
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
            os.kill(os.getpid(), signal.SIGTERM)

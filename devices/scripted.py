"""A device that plays a trajectory file (headless replay, CI, reproducible demos).

The file (format: :mod:`haptic_acu.session.trajectory`) is streamed through a cursor, never loaded whole,
so a recording of any length can be replayed. Its times are session times: the tip holds the
first sample's position until ``t_s`` reaches it, moves linearly between samples, and holds the
last position after it, with ``DeviceState.done`` set from the moment ``t`` reaches the last
sample's time (``duration_s``). Velocity is the interpolant's backward difference over one
1 ms servo tick (see :mod:`haptic_acu.session.trajectory`).

Clocking (``drives_clock`` is False: the engine keeps the clock):

* ``read_at(t_s)``: the state at a session time the caller supplies. The simplest contract; the
  engine's Python servo loop uses it.
* ``read_block(t_s_array)``: positions, velocities and done flags for many increasing times at
  once (the headless engine asks for one visual frame of ticks per call; the compiled real-time
  loop's feeder reads a second ahead with it).
* without the engine (``realtime=False``): the device keeps a simulated clock that the caller moves
  with ``advance(dt)`` (summed without drift), and ``read()`` returns the state at that clock. The
  first ``read()`` before any ``advance`` is at t = 0. (The engine never calls ``advance``.)
* real time (``realtime=True``): ``read()`` uses wall-clock time since the first ``read()``
  (``time.perf_counter``); ``advance`` is ignored.

Optional columns (see :mod:`haptic_acu.session.trajectory`): a ``reset`` event gives ``DeviceState.reset``
on the first read at or after it (``read_at``) and is listed by :meth:`ScriptedDevice.reset_ticks`
for a block of ticks (the headless engine resets the model there); the needle axis
(``axis_x,axis_y,axis_z``) fills ``DeviceState.axis``; ``roll_deg`` fills ``DeviceState.roll_rad``
(and :meth:`ScriptedDevice.roll_block` for a block of ticks: the servo's twirl);
:meth:`ScriptedDevice.pose_block` gives axis and roll for a block of ticks (``None`` when the file
has no such columns).

``seek(t_s)`` sets the clock (a backward seek re-reads the file from its start). ``set_force``
commands nothing (there is no motor): it keeps the last force, the count of commands and the
largest magnitude seen, for tests and summaries.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from haptic_acu.session.trajectory import (
    DEFAULT_MAX_HAND_SPEED_M_PER_S,
    SERVO_TICK_S,
    TrajectoryInfo,
    TrajectoryReader,
)

from .base import Device, DeviceInfo, DeviceState


class ScriptedDevice(Device):
    """Replays ``path``. ``force_limit_n`` defaults to a large value: nothing here can be hurt;
    pass the config's ``safety.force_limit_n`` to make the engine clamp as for a real device.
    ``roll=False`` plays the file without its ``roll_deg`` (no rotation; every other input the same:
    the reference of the technique metrics' grasp felt)."""

    def __init__(self, path, max_hand_speed_m_per_s: float = DEFAULT_MAX_HAND_SPEED_M_PER_S,
                 realtime: bool = False, force_limit_n: float = 1000.0, roll: bool = True):
        self.path = Path(path)
        self.roll = bool(roll)  # False: the file's roll_deg is ignored (the same replay without rotation)
        # reads and checks the header now: a missing or malformed file fails at construction
        self._reader = TrajectoryReader(self.path, max_hand_speed_m_per_s)
        self.gives_axis = bool(self._reader.has_axis)  # a recording of this session carries the file's axis
        self.realtime = bool(realtime)
        self.info = DeviceInfo(name="scripted", model=f"trajectory file {self.path.name}",
                               force_limit_n=float(force_limit_n), rate_hz=1000.0, drives_clock=False)
        self.trajectory_info: TrajectoryInfo | None = None
        self._cursor = None
        self._clock = 0.0
        self._clock_c = 0.0  # Kahan compensation of the summed ticks
        self._wall0: float | None = None
        self.last_force_n = np.zeros(3)
        self.max_force_n = 0.0
        self.force_commands = 0

    # -- Device interface ----------------------------------------------------------------------
    def open(self) -> None:
        """Validate the whole file (streaming it once) and position the cursor at its start."""
        self.trajectory_info = self._reader.validate()
        self._cursor = self._reader.cursor(SERVO_TICK_S)
        self._clock = self._clock_c = 0.0
        self._wall0 = None
        self._last_read_t = -math.inf
        self._reads = 0  # read_at calls since open: one per servo tick in a real-time session
        self.events: list[tuple[int, str]] = []

    def close(self) -> None:
        self._cursor = None

    def read(self) -> DeviceState:
        if self.realtime:
            now = time.perf_counter()
            if self._wall0 is None:
                self._wall0 = now
            return self.read_at(now - self._wall0)
        return self.read_at(self._clock)

    reads_ahead = True

    def read_at(self, t_s: float) -> DeviceState:
        """The tip at session time ``t_s`` (s): position (m), velocity (m/s), ``done``."""
        if self._cursor is None:
            raise RuntimeError("ScriptedDevice: call open() first")
        c = self._cursor
        pos, vel, done = c.sample(t_s)
        extra = {}
        if self._reader.has_axis or self._reader.has_roll:
            ax, roll = c.pose_block(np.array([float(t_s)]))
            if ax is not None:
                extra["axis"] = -ax[0]  # DeviceState: tip -> handle
            if roll is not None and self.roll:
                extra["roll_rad"] = math.radians(float(roll[0]))
        if c.reset_times and any(self._last_read_t < r <= t_s for r in c.reset_times[-4:]):
            extra["reset"] = True
            self.events.append((self._reads, "reset"))  # for a recording: (servo tick, name)
        self._reads += 1
        self._last_read_t = float(t_s)
        return DeviceState(t_s=float(t_s), position_m=pos, velocity_m_s=vel, done=done, **extra)

    def read_block(self, t_s: np.ndarray):
        """States at many increasing session times at once (headless replay): positions (n, 3) m,
        velocities (n, 3) m/s, done flags (n,)."""
        if self._cursor is None:
            raise RuntimeError("ScriptedDevice: call open() first")
        return self._cursor.sample_block(t_s)

    def reset_ticks(self, t_s: np.ndarray) -> list[int]:
        """Indices of the ticks ``t_s`` (just read by :meth:`read_block`) at which the file's
        ``reset`` events take effect: fresh tissue before that tick."""
        return self._cursor.resets_between(np.asarray(t_s, dtype=np.float64))

    def pose_block(self, t_s: np.ndarray):
        """Needle axis (n, 3), unit, handle -> tip, scene frame, and roll (n,) in degrees at the
        times ``t_s``; each ``None`` if the file has no such columns."""
        if self._cursor is None:
            raise RuntimeError("ScriptedDevice: call open() first")
        return self._cursor.pose_block(np.asarray(t_s, dtype=np.float64))

    def roll_block(self, t_s: np.ndarray):
        """The roll (rad, cumulative) at the times ``t_s``, or None if the file has no ``roll_deg``."""
        if not (self._reader.has_roll and self.roll):
            return None
        roll = self.pose_block(t_s)[1]  # None for no times (a block past the file's end)
        return None if roll is None else np.radians(roll)

    def set_force(self, force_n) -> None:
        f = np.array(force_n, dtype=np.float64).reshape(3)
        self.last_force_n = f
        self.max_force_n = max(self.max_force_n, float(np.linalg.norm(f)))
        self.force_commands += 1

    def record_forces(self, count: int, max_magnitude_n: float, last_n) -> None:
        """What a compiled servo loop (haptic_acu.servo.rtloop) commanded without calling ``set_force``
        tick by tick: ``count`` commands, the largest magnitude, the last force."""
        self.force_commands += int(count)
        self.max_force_n = max(self.max_force_n, float(max_magnitude_n))
        self.last_force_n = np.array(last_n, dtype=np.float64).reshape(3)

    # -- clock -----------------------------------------------------------------------------------
    def advance(self, dt_s: float) -> None:
        """Move the simulated clock on by ``dt_s`` (headless mode)."""
        if not (dt_s >= 0 and math.isfinite(dt_s)):
            raise ValueError(f"dt must be finite and >= 0, got {dt_s}")
        y = dt_s - self._clock_c
        t = self._clock + y
        self._clock_c = (t - self._clock) - y
        self._clock = t

    def seek(self, t_s: float) -> None:
        """Set the clock to ``t_s`` (headless), or shift the wall-clock origin (real time)."""
        if self.realtime:
            self._wall0 = time.perf_counter() - float(t_s)
        else:
            self._clock, self._clock_c = float(t_s), 0.0

    @property
    def time_s(self) -> float:
        """The clock ``read()`` would use now."""
        if self.realtime:
            return 0.0 if self._wall0 is None else time.perf_counter() - self._wall0
        return self._clock

    @property
    def has_roll(self) -> bool:
        """The file has a ``roll_deg`` column (and it is played)."""
        return self._reader.has_roll and self.roll

    @property
    def has_events(self) -> bool:
        """The file has an ``event`` column (resets): every servo driver honours them (the headless
        replay and the compiled real-time loop through :meth:`reset_ticks`, the Python loop through
        ``read_at``'s ``reset``)."""
        return self._reader.has_event

    @property
    def end_s(self) -> float:
        """The last sample's session time, as :attr:`duration_s` (after ``open``)."""
        return self.duration_s

    @property
    def duration_s(self) -> float:
        """Session time of the last sample (after ``open``)."""
        if self.trajectory_info is None:
            raise RuntimeError("ScriptedDevice: call open() first")
        return self.trajectory_info.t_last_s


"""The interface every haptic input device implements (after CHAI3D's generic device).

Positions and velocities cross this interface in the *scene* frame, in SI (m, m/s); forces in N.
A device converts from its own frame and units with a :class:`Workspace`.

Two clocking modes (``DeviceInfo.drives_clock``):

* ``False`` (scripted, keyboard): the engine's own 1 kHz timer calls :meth:`Device.read` and
  :meth:`Device.set_force` each tick.
* ``True`` (OMNI): the device's scheduler calls the servo step; the engine hands it a callback
  through :meth:`Device.run_servo`.
"""
from __future__ import annotations

import abc
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np


@dataclass(frozen=True)
class DeviceInfo:
    name: str  # "omni", "keyboard", "scripted"
    model: str  # human-readable model / source
    force_limit_n: float  # the largest force magnitude the device may be commanded
    rate_hz: float  # nominal servo rate
    drives_clock: bool  # True: the device's scheduler calls the servo step


@dataclass
class DeviceState:
    t_s: float = 0.0  # device time of the sample
    position_m: np.ndarray = field(default_factory=lambda: np.zeros(3))  # needle tip, scene frame
    velocity_m_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    buttons: int = 0
    axis: np.ndarray | None = None  # unit vector from tip toward the handle, if the device knows it
    roll_rad: float = 0.0  # the needle's roll about its axis (rad, cumulative, + clockwise seen from the handle)
    done: bool = False  # the source has ended (end of a trajectory, quit key)
    reset: bool = False  # the user asked for a fresh tissue (holes and nets cleared) this tick


@dataclass(frozen=True)
class Workspace:
    """Device frame (mm) -> scene frame (m): p = scale * Rz(rotation) * p_dev + offset."""

    offset_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: float = 1.0
    rotation_z_deg: float = 0.0
    roll_sign: float = 1.0  # +1: the OMNI's third gimbal angle grows with a clockwise roll seen from the handle

    @classmethod
    def from_config(cls, ws) -> "Workspace":
        return cls(tuple(ws.offset_mm), float(ws.scale), float(ws.rotation_z_deg), float(ws.roll_sign))

    def rotation(self) -> np.ndarray:
        """The device-to-scene rotation (3 x 3)."""
        a = math.radians(self.rotation_z_deg)
        c, s = math.cos(a), math.sin(a)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def position_to_scene(self, p_dev_mm) -> np.ndarray:
        return (self.scale * (self.rotation() @ np.asarray(p_dev_mm, float)) + np.asarray(self.offset_mm)) * 1e-3

    def vector_to_scene(self, v_dev_mm) -> np.ndarray:
        """A velocity or displacement (mm or mm/s) into the scene frame (m or m/s)."""
        return self.scale * (self.rotation() @ np.asarray(v_dev_mm, float)) * 1e-3

    def force_to_device(self, f_scene_n) -> np.ndarray:
        """A scene-frame force into the device frame (rotation only: forces are not scaled)."""
        return self.rotation().T @ np.asarray(f_scene_n, float)


class Device(abc.ABC):
    """open / read / set_force / close; see the module doc for the clocking modes."""

    info: DeviceInfo

    @abc.abstractmethod
    def open(self) -> None:
        """Connect. Raises UserError (one line) if the device or its library is missing."""

    @abc.abstractmethod
    def close(self) -> None:
        """Command zero force and disconnect. Safe to call twice."""

    @abc.abstractmethod
    def read(self) -> DeviceState:
        """The latest state. Raises DeviceFault if the device reports an error or stops updating."""

    @abc.abstractmethod
    def set_force(self, force_n: np.ndarray) -> None:
        """Command a force (N, scene frame). The caller has already made it finite and clamped."""

    def pin_servo_thread(self, cores) -> bool:
        """For a device whose own scheduler runs the servo (OMNI): pin that thread to ``cores``
        (``run --pin-cores``). True if done; devices without such a thread return False."""
        return False

    def run_servo(self, step: Callable[[DeviceState], np.ndarray], stop, render=None) -> None:
        """For ``drives_clock`` devices: call ``step(state) -> force`` from the device's scheduler
        at its rate until ``stop`` (a threading.Event) is set or the device faults. ``render``: the
        servo's (DIAG record array, TickIn) for a device with a rendering layer (devices/omni.py)."""
        raise NotImplementedError(f"{self.info.name} does not drive the clock")

    # -- what the engine also uses; each has a default, a device overrides what it can do ---------
    #: The device-to-scene mapping (a device in its own frame and units converts with it; the
    #: OMNI's compiled callback maps positions itself). Default: the identity.
    workspace: Workspace = Workspace()

    #: True if the device gives the needle's axis (``DeviceState.axis``, :meth:`pose_block`): a
    #: recording of the session then carries it (haptic_acu.session.recorder). Default: no.
    gives_axis: bool = False

    #: ``(servo tick, name)`` of the events the device played (the keyboard's and a recording's
    #: ``reset``), for a recording of the session; a device with events keeps a list here and the
    #: engine's drivers append the ones they apply. Default: none.
    events: "list[tuple[int, str]] | tuple" = ()

    def read_at(self, t_s: float) -> DeviceState:
        """The state at session time ``t_s`` on the engine's clock (default: :meth:`read`)."""
        return self.read()

    #: True if :meth:`read_block` can give positions ahead of time (a trajectory): the engine then
    #: runs the real-time servo loop compiled, fed ahead (haptic_acu.servo.rtloop).
    reads_ahead: bool = False

    def read_block(self, t_s: np.ndarray):
        """(positions (n, 3) m, velocities (n, 3) m/s, done flags (n,)) at increasing times ``t_s``;
        only for a device with :attr:`reads_ahead`."""
        raise NotImplementedError(f"{self.info.name} cannot be read ahead")

    #: Session time (s) of the last state :meth:`read_block` gives, when known ahead (a trajectory's
    #: last sample): a headless replay shrinks its last blocks of ticks towards it. Default: unknown.
    end_s: float = math.inf

    def pose_block(self, t_s: np.ndarray):
        """(needle axis (n, 3), unit, handle to tip, scene frame; roll (n,) in degrees) at the ticks
        ``t_s`` (just read by :meth:`read_block`), each None when the device gives none. Default:
        (None, None)."""
        return None, None

    def roll_block(self, t_s: np.ndarray) -> np.ndarray | None:
        """The needle's roll (rad, cumulative) at the ticks ``t_s`` (just read by :meth:`read_block`),
        or None when the device gives none (no rotation). Default: None."""
        return None

    def reset_ticks(self, t_s: np.ndarray) -> list[int]:
        """Indices of the ticks ``t_s`` (just read by :meth:`read_block`) before which the tissue is
        reset (a recording's ``reset`` events). Default: none."""
        return []

    @property
    def has_events(self) -> bool:
        """The device plays events (resets): :meth:`reset_ticks` says where. Default: no."""
        return False

    def record_forces(self, count: int, max_magnitude_n: float, last_n) -> None:
        """What a compiled servo loop commanded without calling :meth:`set_force` tick by tick
        (``count`` commands, the largest magnitude, the last force). Default: nothing to keep."""

    def servo_library(self):
        """For ``drives_clock`` devices whose servo tick can run compiled: the C library the
        compiled callback calls into (a ctypes CDLL), else None (the default: Python callback)."""
        return None

    def servo_guard(self) -> dict:
        """For a compiled callback: the device's safety parameters (``handle``, ``stall_ticks``,
        ``ramp_ticks``, ``velocity_alpha``) as the callback's guard needs them."""
        raise NotImplementedError(f"{self.info.name} has no compiled servo callback")

    def run_servo_compiled(self, callback, table, ictl, fctl, stop) -> None:
        """Run the compiled ``callback`` with user data ``table`` from the device's scheduler until
        ``stop`` is set or the callback ends; report its faults (see haptic_acu.servo.omniloop)."""
        raise NotImplementedError(f"{self.info.name} has no compiled servo callback")

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc):
        self.close()
        return False

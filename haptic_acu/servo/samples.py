"""The servo tick's sample: one float64 row per tick, the columns every consumer agrees on.

The servo thread writes rows into a preallocated ring buffer (:class:`SampleRing`) with a compiled
kernel; the visual loop drains them in blocks and hands them to the sinks (recorder, rerun logger,
replay summary). Columns are SI (m, N, s); states are small integers stored as floats.
"""
from __future__ import annotations

import threading

import numba as nb
import numpy as np

from .state import LAYER_NAMES, N_LAYERS

COLUMNS = (
    "t_s", "tick",
    "x_m", "y_m", "z_m",
    "vx_m_s", "vy_m_s", "vz_m_s",
    "fx_n", "fy_n", "fz_n",
    "f_surface_n", "f_damp_n", "f_lateral_n", "f_bone_n",
    *(f"f_{name}_n" for name in LAYER_NAMES),
    "layer", "depth_m", "depth_skin_m", "front",
    *(f"state_{name}" for name in LAYER_NAMES),
    "ringw_m", "dz1_m", "puncture", "fault", "clamped",
    "period_err_s",
    "fr_x_n", "fr_y_n", "fr_z_n",  # the force rendered to a device (0 without one: replay, keyboard)
    "render_status",  # its status bits (haptic_acu.servo.rendering: 1 clamped, 2 limiting, 4 fault)
    "roll_deg", "torque_nmm",  # the needle's roll (cumulative) and the twist torque about its axis
    # the needle's axis (unit, handle to tip, scene frame): the insertion axis once the skin is broken,
    # before that the axis the device gives (the OMNI's stylus, a trajectory's columns; NaN: none, the
    # direction of travel will decide it at entry)
    "axis_x", "axis_y", "axis_z",
    # the device's tip (the input: where the hand put it). x_m, y_m, z_m and the velocity are the
    # needle's tip, the same but for the handle on the skin: then the device is further along the
    # insertion than the needle's length (haptic_acu.servo.step.hold_at_handle)
    "dev_x_m", "dev_y_m", "dev_z_m",
)
COL = {name: i for i, name in enumerate(COLUMNS)}
NCOL = len(COLUMNS)

C_T, C_TICK = COL["t_s"], COL["tick"]
C_X, C_V, C_F = COL["x_m"], COL["vx_m_s"], COL["fx_n"]
C_DEV = COL["dev_x_m"]


# column indices, by name (numba reads module-level integers as constants)
_T, _TICK, _X, _V, _F = COL["t_s"], COL["tick"], COL["x_m"], COL["vx_m_s"], COL["fx_n"]
_F_SURFACE, _F_DAMP, _F_LATERAL, _F_BONE = COL["f_surface_n"], COL["f_damp_n"], COL["f_lateral_n"], COL["f_bone_n"]
_F_LAYER = COL[f"f_{LAYER_NAMES[0]}_n"]
_STATE = COL[f"state_{LAYER_NAMES[0]}"]
_LAYER, _DEPTH, _DEPTH_SKIN, _FRONT = COL["layer"], COL["depth_m"], COL["depth_skin_m"], COL["front"]
_RINGW, _DZ1, _PUNCTURE, _FAULT, _CLAMPED = COL["ringw_m"], COL["dz1_m"], COL["puncture"], COL["fault"], COL["clamped"]
_PERIOD_ERR = COL["period_err_s"]
_FR, _RSTAT = COL["fr_x_n"], COL["render_status"]
_ROLL, _TORQUE = COL["roll_deg"], COL["torque_nmm"]
_AXIS = COL["axis_x"]
_DEV = COL["dev_x_m"]
_DEG = 180.0 / 3.141592653589793


@nb.njit(cache=True, nogil=True, inline="always")
def write_sample(buf, row, t, tick, inp, s, diag, period_err):
    """Fill ``buf[row]`` from one tick: its time and index, the input ``inp`` (TickIn: the device's
    tip), the servo state ``s`` (State: the needle's tip, ``work.tip``) and output ``diag`` (the
    one-row DIAG record array). Allocation-free."""
    r = buf[row]
    d = diag[0]
    sv = s.servo[0]
    wk = s.work[0]
    r[_T] = t
    r[_TICK] = tick
    for k in range(3):
        r[_X + k] = wk.tip[k]
        r[_V + k] = wk.tip_v[k]
        r[_F + k] = d.force[k]
        r[_DEV + k] = inp.p[k]
    r[_F_SURFACE] = d.f_surface
    r[_F_DAMP] = d.f_damp
    r[_F_LATERAL] = d.f_lateral
    r[_F_BONE] = d.f_bone
    for k in range(N_LAYERS):
        r[_F_LAYER + k] = d.f_layer[k]
        r[_STATE + k] = sv.state[k]
    r[_LAYER] = d.layer
    r[_DEPTH] = d.depth
    r[_DEPTH_SKIN] = d.depth_skin
    r[_FRONT] = d.front
    r[_RINGW] = d.ringw
    r[_DZ1] = d.dz1
    r[_PUNCTURE] = d.puncture
    r[_FAULT] = d.fault
    r[_CLAMPED] = d.clamped
    r[_PERIOD_ERR] = period_err
    for k in range(3):
        r[_FR + k] = inp.fr[k]
    r[_RSTAT] = inp.rstat[0]
    r[_ROLL] = inp.roll[0] * _DEG
    r[_TORQUE] = d.torque * 1e3
    for k in range(3):
        r[_AXIS + k] = sv.axis[k] if sv.inserted != 0 else inp.axis[k]


class SampleRing:
    """Single-producer (servo) / single-consumer (visual) ring of sample rows.

    The producer writes row ``head % capacity`` and then advances ``head``; the consumer copies rows
    ``[tail, head)`` and advances ``tail``. ``head`` lives in a one-element int64 array (``ctr``),
    so the compiled real-time loop (:mod:`haptic_acu.servo.rtloop`) can publish rows without the GIL; no
    lock is held by either side. If the consumer falls ``capacity`` rows behind, the oldest rows are lost
    and counted in ``dropped`` (size the ring for several visual frames: the default holds 8 s).
    """

    def __init__(self, capacity: int = 8192):
        self.buf = np.zeros((capacity, NCOL))
        self.capacity = capacity
        self.ctr = np.zeros(1, dtype=np.int64)  # head, in an array so a compiled producer can publish it
        self.tail = 0
        self.dropped = 0
        self._lock = threading.Lock()  # consumer side only (drain may be called from two threads at stop)

    @property
    def head(self) -> int:
        """Rows written so far (the producer advances it after writing a row)."""
        return int(self.ctr[0])

    @head.setter
    def head(self, value: int) -> None:
        self.ctr[0] = value

    def next_row(self) -> int:
        return self.head % self.capacity

    def commit(self) -> None:
        self.ctr[0] += 1

    def drain(self, most: int | None = None) -> np.ndarray:
        """Copy out every row written since the last drain (at most its ``most`` oldest), oldest
        first."""
        with self._lock:
            head = self.head
            tail = self.tail
            if head - tail > self.capacity:
                self.dropped += head - tail - self.capacity
                tail = head - self.capacity
            n = head - tail if most is None else min(head - tail, most)
            if n <= 0:
                return np.zeros((0, NCOL))
            a = tail % self.capacity
            b = a + n
            if b <= self.capacity:
                out = self.buf[a:b].copy()
            else:
                out = np.concatenate([self.buf[a:], self.buf[: b - self.capacity]])
            self.tail = tail + n
            return out

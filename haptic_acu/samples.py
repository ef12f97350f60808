"""The servo tick's sample: one float64 row per tick, the columns every consumer agrees on.

The servo thread writes rows into a preallocated ring buffer (:class:`SampleRing`) with a compiled
kernel; the visual loop drains them in blocks and hands them to the sinks (recorder, rerun logger,
replay summary). Columns are SI (m, N, s); states are small integers stored as floats.
"""
from __future__ import annotations

import threading

import numba as nb
import numpy as np

from . import needle as nd

COLUMNS = (
    "t_s", "tick",
    "x_m", "y_m", "z_m",
    "vx_m_s", "vy_m_s", "vz_m_s",
    "fx_n", "fy_n", "fz_n",
    "f_surface_n", "f_damp_n", "f_lateral_n", "f_bone_n",
    "f_skin_n", "f_fat_n", "f_muscle_n",
    "layer", "depth_m", "depth_skin_m", "front",
    "state_skin", "state_fat", "state_muscle",
    "ringw_m", "dz1_m", "puncture", "fault", "clamped",
    "period_err_s",
)
COL = {name: i for i, name in enumerate(COLUMNS)}
NCOL = len(COLUMNS)

C_T, C_TICK = COL["t_s"], COL["tick"]
C_X, C_V, C_F = COL["x_m"], COL["vx_m_s"], COL["fx_n"]


@nb.njit(cache=True, nogil=True)
def write_sample(buf, row, t, tick, p, v, diag, si, period_err):
    """Fill ``buf[row]`` from one tick's state. Allocation-free."""
    r = buf[row]
    r[0] = t
    r[1] = tick
    for k in range(3):
        r[2 + k] = p[k]
        r[5 + k] = v[k]
        r[8 + k] = diag[k]
    r[11] = diag[nd.D_F_SURFACE]
    r[12] = diag[nd.D_F_DAMP]
    r[13] = diag[nd.D_F_LATERAL]
    r[14] = diag[nd.D_F_BONE]
    for k in range(3):
        r[15 + k] = diag[nd.D_F_LAYER + k]
    r[18] = diag[nd.D_LAYER]
    r[19] = diag[nd.D_DEPTH]
    r[20] = diag[nd.D_DEPTH_SKIN]
    r[21] = diag[nd.D_FRONT]
    for k in range(3):
        r[22 + k] = si[nd.SI_STATE + k]
    r[25] = diag[nd.D_RINGW]
    r[26] = diag[nd.D_DZ1]
    r[27] = diag[nd.D_PUNCTURE]
    r[28] = diag[nd.D_FAULT]
    r[29] = diag[nd.D_CLAMPED]
    r[30] = period_err


class SampleRing:
    """Single-producer (servo) / single-consumer (visual) ring of sample rows.

    The producer writes row ``head % capacity`` and then advances ``head``; the consumer copies rows
    ``[tail, head)`` and advances ``tail``. ``head`` lives in a one-element int64 array (``ctr``),
    so the compiled real-time loop (:mod:`haptic_acu.rtloop`) can publish rows without the GIL; no
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

    def drain(self) -> np.ndarray:
        """Copy out every row written since the last drain, oldest first."""
        with self._lock:
            head = self.head
            tail = self.tail
            if head - tail > self.capacity:
                self.dropped += head - tail - self.capacity
                tail = head - self.capacity
            n = head - tail
            if n <= 0:
                return np.zeros((0, NCOL))
            a = tail % self.capacity
            b = a + n
            if b <= self.capacity:
                out = self.buf[a:b].copy()
            else:
                out = np.concatenate([self.buf[a:], self.buf[: b - self.capacity]])
            self.tail = head
            return out

"""Session recording: every tick's tip position (plus force and states) as a trajectory file.

The file is the format :class:`devices.scripted.ScriptedDevice` plays (``t_s,x_mm,y_mm,z_mm``; the
extra columns are ignored on replay), so any OMNI or keyboard session replays headless later. Rows
are appended and flushed once per visual frame: a crash or Ctrl-C loses at most the last frame, and
on a fault the engine's final flush writes every tick up to the fault.
"""
from __future__ import annotations

import numpy as np

from .samples import COL
from .trajectory import TrajectoryWriter

EXTRA = ("fx_n", "fy_n", "fz_n", "layer", "state_skin", "state_fat", "state_muscle", "depth_mm")
_SRC = [COL["t_s"], COL["x_m"], COL["y_m"], COL["z_m"], COL["fx_n"], COL["fy_n"], COL["fz_n"], COL["layer"],
        COL["state_skin"], COL["state_fat"], COL["state_muscle"], COL["depth_m"]]


class RecorderSink:
    def __init__(self, path):
        self.path = path
        self._w = TrajectoryWriter(path, extra_columns=EXTRA,
                                   formats={"layer": "%d", "state_skin": "%d", "state_fat": "%d", "state_muscle": "%d"},
                                   comments=["haptic-acu session recording: replay with `haptic-acu replay FILE`"])
        self._last_t = -np.inf
        self.rows = 0

    def on_frame(self, frame) -> None:
        rows = frame.samples
        if rows.shape[0] == 0:
            return
        out = rows[:, _SRC].copy()
        out[:, -1] *= 1e3  # depth in mm
        # a recording must strictly increase in time (a device clock can repeat a timestamp): keep
        # the rows later than every row before them (not just the previous one, which may be dropped)
        t = out[:, 0]
        before = np.fmax.accumulate(np.concatenate([[self._last_t], t[:-1]]))
        out = out[t > before]
        finite = np.all(np.isfinite(out[:, :4]), axis=1)
        out = out[finite]
        out[:, 4:] = np.nan_to_num(out[:, 4:])
        if out.shape[0]:
            self._w.append_rows(out)
            self._last_t = out[-1, 0]
            self.rows += out.shape[0]

    def close(self, result) -> None:
        self._w.close()

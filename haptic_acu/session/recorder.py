"""Session recording: every tick's device position (plus force and states) as a trajectory file.

The file is the format :class:`devices.scripted.ScriptedDevice` plays (``t_s,x_mm,y_mm,z_mm``, the
header on line 1; the extra columns are ignored on replay), so any OMNI or keyboard session
replays headless later. ``x_mm, y_mm, z_mm`` are the device's tip (the servo's input: the samples'
``dev_*`` columns), which the needle's tip follows but for the handle on the skin: a device further
along the insertion than the needle's length holds the needle there (``depth_skin_mm``, the
needle's depth in the tissue, is at most its length; :mod:`haptic_acu.servo.step`). ``layer`` and the ``state_*`` columns are names (``outside``, ``skin``...,
``untouched``, ``pressing``, ``punctured``), as in ``samples.csv``; ``event`` names what happened
on that tick (``reset``: the keyboard's ``r``, fresh tissue; the replay honours it); ``roll_deg`` is
the needle's roll (cumulative degrees, + clockwise seen from the handle: the OMNI's stylus roll, the
keyboard's twirl keys), which the replay plays into the servo, so a session replays with its twirling. Rows are
appended once per visual frame, unbuffered: a crash or Ctrl-C loses at most the last frame, and on a
fault the engine's final flush writes every tick up to the fault.

A replay of the recording runs the session's own ticks: the device's position and roll are written to
the last bit (``%.17g``: the replay derives the velocity from consecutive positions), and at the end
one more row holds the last position half a tick after the last tick (:data:`END_AFTER_S`): a
trajectory is done when the replay's time reaches its last row, so without it the replay would stop
one tick short.

Safety of the user's files: :meth:`RecorderSink.open` (called once the session can start, after
the device opened) creates the file, refusing an existing one unless ``overwrite`` and always
refusing the session's own input trajectory. An I/O error while recording (a full disk) cuts the
file back to its last whole row and is raised, so the engine reports it as a fault (force zero,
exit 3); the recording stops there and still replays.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..base.errors import UserError
from ..servo.samples import COL
from .trajectory import AXIS_COLUMNS, EVENT_COLUMN, EVENT_CODES, LAYER_CODES, ROLL_COLUMN, STATE_CODES, TrajectoryWriter
from .sink import Sink

EXTRA = ("fx_n", "fy_n", "fz_n", "layer", "state_skin", "state_fat", "state_muscle", "depth_mm",
         "depth_skin_mm",  # the needle's depth in the tissue along the insertion (at most its length)
         "fr_x_n", "fr_y_n", "fr_z_n",  # the force rendered to the device (0 without one)
         ROLL_COLUMN, EVENT_COLUMN)
PLACES = {code: name for name, code in LAYER_CODES.items()}  # layer codes -1..3 -> names
STATES = {code: name for name, code in STATE_CODES.items()}
EVENTS = {code: name for name, code in EVENT_CODES.items()}
_SRC = [COL["t_s"], COL["dev_x_m"], COL["dev_y_m"], COL["dev_z_m"], COL["fx_n"], COL["fy_n"], COL["fz_n"], COL["layer"],
        COL["state_skin"], COL["state_fat"], COL["state_muscle"], COL["depth_m"], COL["depth_skin_m"],
        COL["fr_x_n"], COL["fr_y_n"], COL["fr_z_n"], COL["roll_deg"]]
_DEPTHS = [_SRC.index(COL["depth_m"]), _SRC.index(COL["depth_skin_m"])]
_SRC_AXIS = [COL["axis_x"], COL["axis_y"], COL["axis_z"]]
# with a device that gives the needle axis (the OMNI's stylus): axis_x,axis_y,axis_z before the event
EXTRA_AXIS = EXTRA[:-1] + AXIS_COLUMNS + EXTRA[-1:]


EXACT = "%.17g"  # a float64 to the last bit
END_AFTER_S = 0.5e-3  # the end row: half a servo tick after the last tick


class RecordingError(Exception):
    """Writing the recording failed (the file ends on its last whole row)."""


class RecorderSink(Sink):
    """Records a session to ``path``. ``device`` (optional) may list ``events`` as (tick, name)
    pairs (the keyboard's resets); they become the ``event`` column of those ticks' rows."""

    def __init__(self, path, overwrite: bool = False, device=None):
        self.path = Path(path)
        # a device that gives the needle axis (devices.omni: the stylus orientation) has it recorded
        # (samples' axis_*: the insertion axis once inserted, else the device's, nan where it gave
        # none), so the replay takes the same axis at each entry
        self.axis = bool(getattr(device, "gives_axis", False))
        self.overwrite = bool(overwrite)
        self.device = device
        self._w: TrajectoryWriter | None = None
        self._last_t = -np.inf
        self._events_seen = 0
        self._pending: list[tuple[int, str]] = []
        self.failed: str | None = None
        self._last_row: np.ndarray | None = None
        self.rows = 0

    def open(self) -> None:
        """Create the file now (call once the session can start). Refuses an existing file unless
        ``overwrite``; a file that cannot be created is a one-line UserError."""
        if self._w is not None:
            return
        try:
            axis_fmt = {c: "%.9f" for c in AXIS_COLUMNS} if self.axis else {}
            # the tip's position and roll to the last bit (shortest round-trip digits): the replay
            # derives the velocity from consecutive positions, and 0.1 um over a 1 ms tick is
            # 0.1 mm/s, which the damping turns into millinewtons
            exact = {c: EXACT for c in ("x_mm", "y_mm", "z_mm", ROLL_COLUMN)}
            self._w = TrajectoryWriter(self.path, extra_columns=EXTRA_AXIS if self.axis else EXTRA,
                                       open_mode="w" if self.overwrite else "x",
                                       formats={"layer": PLACES, "state_skin": STATES, "state_fat": STATES,
                                                "state_muscle": STATES, EVENT_COLUMN: EVENTS,
                                                **exact, **axis_fmt},
                                       write_header=False)
        except FileExistsError:
            raise UserError(f"{self.path}: exists; choose another file or add --overwrite") from None

    def start(self, info) -> None:
        self.open()

    def _events(self, ticks: np.ndarray) -> np.ndarray:
        """The event code of each row (0: none); events of dropped rows move to the next row."""
        evs = getattr(self.device, "events", None)
        if evs is not None and len(evs) > self._events_seen:
            new = list(evs[self._events_seen:])
            self._events_seen += len(new)
            self._pending += new
        codes = np.zeros(len(ticks))
        keep = []
        for tick, name in self._pending:
            if name not in EVENT_CODES:  # an event this file format has no name for yet
                continue
            i = int(np.searchsorted(ticks, tick, side="left"))
            if i < len(ticks):
                codes[i] = EVENT_CODES[name]
            else:  # a tick the engine has not drained yet: the next frame
                keep.append((tick, name))
        self._pending = keep
        return codes

    def on_frame(self, frame) -> None:
        rows = frame.samples
        if rows.shape[0] == 0 or self.failed is not None:
            return
        if self._w is None:
            self.open()
        out = rows[:, _SRC].copy()
        out[:, _DEPTHS] *= 1e3  # depths in mm
        ticks = rows[:, COL["tick"]]
        # a recording must strictly increase in time (a device clock can repeat a timestamp): keep
        # the rows later than every row before them (not just the previous one, which may be dropped)
        t = out[:, 0]
        before = np.fmax.accumulate(np.concatenate([[self._last_t], t[:-1]]))
        keep = (t > before) & np.all(np.isfinite(out[:, :4]), axis=1)
        out[:, 4:] = np.nan_to_num(out[:, 4:])
        if self.axis:  # nan (all three) where the device gave no axis: the replay's travel then
            ax = rows[:, _SRC_AXIS]
            ax[~np.isfinite(ax).all(axis=1)] = np.nan
            out = np.column_stack([out, ax])
        ev = self._events(ticks)
        if not keep.all() and ev.any():  # an event on a dropped row moves to the next kept row
            idx = np.flatnonzero(keep)
            for i in np.flatnonzero(ev * ~keep):
                j = idx[np.searchsorted(idx, i)] if np.searchsorted(idx, i) < len(idx) else None
                if j is not None:
                    ev[j] = ev[j] or ev[i]
                else:
                    self._pending.append((int(ticks[i]) + 1, EVENTS[int(ev[i])]))
        out = np.column_stack([out[keep], ev[keep]])
        if out.shape[0]:
            try:
                self._w.append_rows(out)
            except OSError as e:
                self.failed = e.strerror or str(e)
                at = f"t = {self._last_t:.3f} s" if self.rows else "its start"
                raise RecordingError(f"{self.path}: recording stopped at {at} ({self.rows} rows, the "
                                     f"file ends on a whole row): {e.strerror or e}") from None
            self._last_t = out[-1, 0]
            self._last_row = out[-1].copy()
            self.rows += out.shape[0]

    def close(self, result) -> None:
        if self._w is not None:
            if self.failed is None and self._last_row is not None:
                end = self._last_row.copy()  # the session's end: half a tick after its last tick
                end[0] += END_AFTER_S
                end[-1] = 0.0  # no event
                try:
                    self._w.append_rows(end[None, :])
                    self.rows += 1
                except OSError:
                    pass
            if self.failed is None:
                try:
                    self._w.write_header()  # a session that ended before its first frame
                except OSError:
                    pass
            self._w.close()


def tick_rows(tr):
    """A loaded recording (:class:`~haptic_acu.session.trajectory.Trajectory`) without its end row
    (the one :data:`END_AFTER_S` after the last tick, when it has one): one row per servo tick."""
    import dataclasses

    if len(tr.t_s) >= 2 and abs((tr.t_s[-1] - tr.t_s[-2]) - END_AFTER_S) < 1e-9:
        return dataclasses.replace(tr, t_s=tr.t_s[:-1], pos_m=tr.pos_m[:-1],
                                   extra={k: v[:-1] for k, v in tr.extra.items()})
    return tr

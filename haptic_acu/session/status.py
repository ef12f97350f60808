"""The live status line: one terminal line rewritten in place while a session runs.

A sink (see :mod:`haptic_acu.session.engine`): every visual frame it takes the newest sample row and,
at most ``max_hz`` (10) times a second, rewrites the line with ``\\r`` (no scrolling)::

    t 3.21 s | x +0.0 y +0.0 mm | fat 1.20 mm | 2.05 mm deep (target 15-30) | |F| 0.41 N | v 5.0 mm/s (set 5) | roll +90 deg +0.041 N*mm | skin:punct fat:press muscle:- | last puncture skin 1.450 N | servo 1000 Hz visual 60 Hz | loop ok

* for 1.5 s after a puncture (session time), ``SKIN PUNCTURED`` (``FAT``, ``MUSCLE``) first on the line;
* the warnings, first: ``FORCE LIMIT`` while the commanded force is clamped to the safety limit,
  ``ON BONE: withdraw`` with the tip on the bone, and ``12.40 mm deep, 2.4 PAST 30`` in place of
  the target once the needle is deeper than the target range, ``40.00 mm deep: HANDLE ON SKIN``
  while the whole needle is in (the device pushes past its length);
* the session time (s) of the newest servo tick;
* the tip's position relative to the acupoint (x, y in mm, the scene frame's origin);
* where the tip is: in the air with its height above the rest skin, ``pressing skin`` with how far
  the skin is pushed in, or the layer (``bone`` past the muscle) with the depth into that layer and
  below the skin along the needle (mm), against the config's ``scene.target_depth_mm``;
* the force on the needle |F| (N) and the tip speed (mm/s), with the keyboard's set speed;
* once the needle has been rolled: its roll (deg, cumulative, + clockwise seen from the handle),
  kept before the position and rates, and the twist torque of the tissue wound around the shaft
  (N*mm, :mod:`haptic_acu.tissue.twirl`);
* each layer's state: ``-`` untouched, ``press`` pressing (a force net is active), ``punct`` punctured;
* the last puncture and its peak |F| (N, the report's number: :class:`haptic_acu.session.report.SessionScan`);
* ``CONTINUOUS FORCE LIMIT: easing off`` while the rendering layer's
  continuous-force protection scales the device's force down (sample column ``render_status``);
* the servo and visual rates the engine measured (``Frame.rates``, Hz);
* the loop's health in words: ``loop ok``, or ``host late 0.3%, missed 12``: the share and count of
  servo ticks whose start was more than one servo period late (the sample column
  ``period_err_s``; the engine's own count, ``SessionResult.stats["missed_ticks"]``, uses the same
  rule).

The line must fit the terminal's width (a wrapped line could not be rewritten in place): on a narrow
terminal the least important fields go first (the rates, the layer states, the position, torque and
loop health, the last puncture, then the time, place, speed and roll; the puncture flash, the
warnings, the depth against the target and the force stay: within 80 columns). It is padded over the previous one. It is drawn only when the
stream is a terminal, or with ``force=True``. ``close(result)`` ends the line with a newline and
prints the fault reason, if any.
"""
from __future__ import annotations

import math
import os
import sys
import time

import numpy as np

from ..base.config import LAYER_NAMES
from ..servo.samples import COL
from ..servo.state import PLACE_NAMES
from .sink import Sink

_STATE_SHORT = ("-", "press", "punct")  # short forms of servostate.STATE_NAMES
_PLACE = {i - 1: name for i, name in enumerate(PLACE_NAMES)}  # the DIAG.layer values (-1 air ... 3 bone)
_C_F = COL["fx_n"]
_C_V = COL["vx_m_s"]
_C_STATE = COL["state_skin"]
_C_LAYER, _C_DEPTH, _C_DEPTH_SKIN = COL["layer"], COL["depth_m"], COL["depth_skin_m"]
_C_PERR = COL["period_err_s"]
_C_T = COL["t_s"]
SEP = " | "


_C_X = COL["x_m"]
_C_DEV = COL["dev_x_m"]
_C_CLAMP = COL["clamped"]
_C_RSTAT = COL["render_status"]
_LIMITING = 2  # haptic_acu.servo.rendering.LIMITING (not imported: the status line loads no numba kernels)
_C_ROLL, _C_TORQUE = COL["roll_deg"], COL["torque_nmm"]
_BONE = 3


def loop_health(missed: int, ticks: int) -> str:
    """The servo loop's health in words: "loop ok", or how often the host was late (ticks that started
    over a period late) with the count."""
    if not missed:
        return "loop ok"
    pct = 100.0 * missed / max(ticks, 1)
    return f"host late {pct:.1f}%, missed {missed}"


FLASH_S = 1.5  # a puncture is announced this long (session time) after it happens


def handle_on_skin(row: np.ndarray) -> bool:
    """The handle on the skin: the device is further along the insertion than the needle's length,
    so the needle's tip (``x_m``...) is not the device's (``dev_x_m``...; haptic_acu.servo.step)."""
    dev, tip = row[_C_DEV:_C_DEV + 3], row[_C_X:_C_X + 3]
    return bool(np.isfinite(dev).all() and np.any(dev != tip))


def status_fields(t_s: float, row: np.ndarray, rates: dict, missed: int | None, *, ticks: int | None = None,
                  tip_depth_mm: float | None = None, target_mm=None, last_puncture: dict | None = None,
                  speed_set_mm_s: float | None = None, warning: str = "") -> list[tuple[int, str]]:
    """The status fields, in display order, each with its priority (0 most important) for when the
    terminal is too narrow for all of them. ``row`` is a sample row (:data:`haptic_acu.servo.samples.COLUMNS`).
    Optional: ``tip_depth_mm`` (below the rest skin; negative above it), ``target_mm`` (the scene's
    target depth range), ``last_puncture`` (layer and peak_force_n), ``speed_set_mm_s`` (the
    keyboard's set axial speed), ``ticks`` (for the late fraction), ``warning`` (``--point`` with
    guided feedback: a danger structure near the tip)."""
    layer = int(row[_C_LAYER])
    x_mm, y_mm = row[_C_X] * 1e3, row[_C_X + 1] * 1e3
    # priorities (0 stays longest): what the trainee acts on (where the tip is against the target,
    # force, speed, warnings) before the roll and last puncture, then position and loop health, then
    # the layer states, then the rates
    # the position relative to the acupoint matters most in the air, while aiming
    fields = []
    # a puncture just now, by name: the first thing on the line while it lasts
    if last_puncture is not None and 0.0 <= t_s - last_puncture.get("t_s", -math.inf) <= FLASH_S:
        fields.append((0, f"{last_puncture['layer'].upper()} PUNCTURED"))
    fields += [(2, f"t {t_s:.2f} s"), (1 if layer < 0 else 3, f"x {x_mm:+.1f} y {y_mm:+.1f} mm")]
    if layer >= 0:
        fields.append((1, f"{_PLACE.get(layer, '?')} {row[_C_DEPTH] * 1e3:.2f} mm"))
        depth = row[_C_DEPTH_SKIN] * 1e3
        deep = f"{depth:.2f} mm deep"
        if handle_on_skin(row):  # the whole needle in: before (and in place of) the target
            deep += ": HANDLE ON SKIN"
        elif target_mm is not None and depth > target_mm[1]:
            deep += f", {depth - target_mm[1]:.1f} PAST {target_mm[1]:g}"
        elif target_mm is not None:
            deep += f" (target {target_mm[0]:g}-{target_mm[1]:g})"
        fields.append((0, deep))
    elif int(row[_C_STATE]) == 1 and tip_depth_mm is not None:
        fields.append((0, f"pressing skin {max(tip_depth_mm, 0.0):.2f} mm"))
    elif tip_depth_mm is not None:
        fields.append((0, f"air, {max(-tip_depth_mm, 0.0):.2f} mm above skin"))
    else:
        fields.append((0, "air"))
    fields.append((0, f"|F| {float(np.linalg.norm(row[_C_F:_C_F + 3])):.2f} N"))
    v = f"v {float(np.linalg.norm(row[_C_V:_C_V + 3])) * 1e3:.1f} mm/s"
    if speed_set_mm_s is not None:
        v += f" (set {speed_set_mm_s:g})"
    fields.append((1, v))
    if row[_C_ROLL] != 0.0 or row[_C_TORQUE] != 0.0:  # once the needle has been rolled: before the position
        fields.append((1, f"roll {row[_C_ROLL]:+.0f} deg"))
        fields.append((3, f"{row[_C_TORQUE]:+.3f} N*mm"))
    fields.append((4, " ".join(f"{name}:{_STATE_SHORT[int(s)] if 0 <= int(s) < 3 else '?'}"
                               for name, s in zip(LAYER_NAMES, row[_C_STATE:_C_STATE + 3]))))
    if last_puncture is not None:
        fields.append((2, f"last puncture {last_puncture['layer']} {last_puncture['peak_force_n']:.3f} N"))
    if layer == _BONE:
        fields.insert(0, (0, "ON BONE: withdraw"))
    if warning:
        fields.append((0, warning))
    if row[_C_CLAMP]:
        fields.insert(0, (0, "FORCE LIMIT"))
    if int(row[_C_RSTAT]) & _LIMITING:  # the rendering layer's continuous-force protection
        fields.append((0, "CONTINUOUS FORCE LIMIT: easing off"))
    fields.append((5, f"servo {rates.get('servo_hz', 0.0):.0f} Hz visual {rates.get('visual_hz', 0.0):.0f} Hz"))
    if missed is not None:
        fields.append((3, loop_health(missed, ticks if ticks is not None else 0)))
    return fields


def format_status(t_s: float, row: np.ndarray, rates: dict, missed: int | None, width: int | None = None,
                  **extra) -> str:
    """The status text; with ``width``, the least important fields are left out one by one (the
    last of the lowest priority first) until it fits in ``width`` characters (and as a last resort
    it is cut). ``extra``: see :func:`status_fields`."""
    fields = status_fields(t_s, row, rates, missed, **extra)
    text = SEP.join(f for _, f in fields)
    if width is None:
        return text
    while len(text) > width and len(fields) > 1:  # one field at a time: the last of the least important
        worst = max(p for p, _ in fields)
        if worst == 0:
            break
        drop = max(i for i, (p, _) in enumerate(fields) if p == worst)
        fields = fields[:drop] + fields[drop + 1:]
        text = SEP.join(f for _, f in fields)
    return text[:width]


class StatusLine(Sink):
    """Status-line sink writing to ``stream`` (default stderr). See the module doc."""

    def __init__(self, stream=None, force: bool = False, max_hz: float = 10.0, target_mm=None,
                 force_limit_n: float | None = None, device=None, point=None):
        self.stream = sys.stderr if stream is None else stream
        self.point = point  # --point: a PointSetup whose guided feedback warns of its structures
        self.target_mm = target_mm
        self.force_limit_n = force_limit_n
        self.device = device  # for the keyboard's set speed (``speed_m_s``), if it has one
        self.ticks = 0
        self.tissue = None
        self._scan = None
        self.enabled = bool(force) or self._is_tty(self.stream)
        self.min_interval_s = 1.0 / max_hz
        self.servo_period_s = 1e-3
        self.missed = 0
        self.lines = 0  # lines drawn
        self._last_draw = -float("inf")
        self._last_len = 0
        self._row: np.ndarray | None = None
        self._t = 0.0
        self._rates: dict = {}

    @staticmethod
    def _is_tty(stream) -> bool:
        try:
            return stream.isatty()
        except (AttributeError, ValueError, OSError):
            return False

    def _width(self) -> int:
        """The terminal's width in columns (200 if it does not say: a pipe, or a pty of size 0)."""
        try:
            cols = os.get_terminal_size(self.stream.fileno()).columns
        except (AttributeError, ValueError, OSError):
            return 200
        return cols if cols > 0 else 200

    # -- sink interface --------------------------------------------------------------------------
    def start(self, info: dict) -> None:
        dev = info.get("device")
        model = info.get("model")
        if getattr(model, "tissue", None) is not None:
            from .report import SessionScan
            self.tissue = model.tissue
            self._scan = SessionScan(self.tissue)  # the punctures and their peaks, as the report finds them
        rate = getattr(dev, "rate_hz", 0.0)
        if rate and rate > 0:
            self.servo_period_s = 1.0 / rate

    def on_frame(self, frame) -> None:
        if not self.enabled:
            return
        rows = frame.samples
        if rows.shape[0]:
            self.missed += int(np.count_nonzero(rows[:, _C_PERR] > self.servo_period_s))
            self.ticks += rows.shape[0]
            if self._scan is not None:
                self._scan.feed(rows)
            self._row = rows[-1].copy()
            self._t = float(self._row[_C_T])  # the servo time of the row shown (frame times can lead it)
        self._rates = dict(frame.rates)
        now = time.monotonic()
        if self._row is None or now - self._last_draw < self.min_interval_s:
            return
        self._last_draw = now
        self._draw()

    def _draw(self) -> None:
        extra = {"ticks": self.ticks, "target_mm": self.target_mm}
        if self.tissue is not None:
            from .report import tip_depth_m
            extra["tip_depth_mm"] = float(tip_depth_m(self._row[_C_X:_C_X + 3], self.tissue)[0]) * 1e3
        if self._scan is not None and self._scan.punctures:
            extra["last_puncture"] = self._scan.punctures[-1]
        if self.point is not None:
            extra["warning"] = self.point.warning(self._row[_C_X:_C_X + 3] * 1e3, self._t)
        speed = getattr(self.device, "speed_m_s", None)
        if isinstance(speed, (int, float)):
            extra["speed_set_mm_s"] = speed * 1e3
        text = format_status(self._t, self._row, self._rates, self.missed, width=max(self._width() - 1, 20), **extra)
        pad = " " * max(self._last_len - len(text), 0)
        self._last_len = len(text)
        try:
            self.stream.write("\r" + text + pad)
            self.stream.flush()
        except (OSError, ValueError):  # the terminal went away: stop drawing, never fail the session
            self.enabled = False
            return
        self.lines += 1

    def close(self, result) -> None:
        if not self.enabled:
            return
        try:
            if self._row is not None:
                self._draw()  # the final state
            if self.lines:
                self.stream.write("\n")
            fault = getattr(result, "fault", None)
            if fault:
                self.stream.write(f"fault: {fault}\n")
            self.stream.flush()
        except (OSError, ValueError):
            pass

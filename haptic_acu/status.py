"""The live status line: one terminal line rewritten in place while a session runs.

A sink (see :mod:`haptic_acu.engine`): every visual frame it takes the newest sample row and,
at most ``max_hz`` (10) times a second, rewrites the line with ``\\r`` (no scrolling)::

    t 3.21 s | fat 1.20 mm | 2.05 mm below skin | |F| 0.41 N | v 5.0 mm/s | skin:punct fat:press muscle:- | servo 1000 Hz visual 60 Hz | missed 0

* the session time (s) of the newest servo tick;
* the layer the tip is in (``air`` above the skin, including while it presses the skin; ``bone``
  past the muscle) with the depth into that layer and below the skin (mm);
* the force on the needle |F| (N) and the tip speed (mm/s);
* each layer's state: ``-`` untouched, ``press`` pressing (a force net is active), ``punct`` punctured;
* the servo and visual rates the engine measured (``Frame.rates``, Hz);
* missed servo ticks: ticks whose start was more than one servo period late (the sample column
  ``period_err_s``; the engine's own count, ``SessionResult.stats["missed_ticks"]``, uses the same
  rule).

The line must fit the terminal's width (a wrapped line could not be rewritten in place): on a narrow
terminal the least important fields go first (speed, depth below skin, missed ticks, rates; the
time, place, force and states stay). It is padded over the previous one. It is drawn only when the
stream is a terminal, or with ``force=True``. ``close(result)`` ends the line with a newline and
prints the fault reason, if any.
"""
from __future__ import annotations

import os
import sys
import time

import numpy as np

from .config import LAYER_NAMES
from .samples import COL
from .servostate import PLACE_NAMES

_STATE_SHORT = ("-", "press", "punct")  # short forms of servostate.STATE_NAMES
_PLACE = {i - 1: name for i, name in enumerate(PLACE_NAMES)}  # the DIAG.layer values (-1 air ... 3 bone)
_C_F = COL["fx_n"]
_C_V = COL["vx_m_s"]
_C_STATE = COL["state_skin"]
_C_LAYER, _C_DEPTH, _C_DEPTH_SKIN = COL["layer"], COL["depth_m"], COL["depth_skin_m"]
_C_PERR = COL["period_err_s"]
_C_T = COL["t_s"]
SEP = " | "


def status_fields(t_s: float, row: np.ndarray, rates: dict, missed: int | None) -> list[tuple[int, str]]:
    """The status fields, in display order, each with its priority (0 most important) for when the
    terminal is too narrow for all of them. ``row`` is a sample row (:data:`haptic_acu.samples.COLUMNS`)."""
    layer = int(row[_C_LAYER])
    fields = [(0, f"t {t_s:.2f} s")]
    if layer >= 0:
        fields.append((0, f"{_PLACE.get(layer, '?')} {row[_C_DEPTH] * 1e3:.2f} mm"))
        fields.append((4, f"{row[_C_DEPTH_SKIN] * 1e3:.2f} mm below skin"))
    else:
        fields.append((0, "air"))
    fields.append((0, f"|F| {float(np.linalg.norm(row[_C_F:_C_F + 3])):.2f} N"))
    fields.append((5, f"v {float(np.linalg.norm(row[_C_V:_C_V + 3])) * 1e3:.1f} mm/s"))
    fields.append((1, " ".join(f"{name}:{_STATE_SHORT[int(s)] if 0 <= int(s) < 3 else '?'}"
                               for name, s in zip(LAYER_NAMES, row[_C_STATE:_C_STATE + 3]))))
    fields.append((2, f"servo {rates.get('servo_hz', 0.0):.0f} Hz visual {rates.get('visual_hz', 0.0):.0f} Hz"))
    if missed is not None:
        fields.append((3, f"missed {missed}"))
    return fields


def format_status(t_s: float, row: np.ndarray, rates: dict, missed: int | None, width: int | None = None) -> str:
    """The status text; with ``width``, the least important fields are left out until it fits in
    ``width`` characters (and as a last resort it is cut)."""
    fields = status_fields(t_s, row, rates, missed)
    text = SEP.join(f for _, f in fields)
    if width is None:
        return text
    while len(text) > width and len(fields) > 1:
        worst = max(p for p, _ in fields)
        if worst == 0:
            break
        fields = [fp for fp in fields if fp[0] != worst]
        text = SEP.join(f for _, f in fields)
    return text[:width]


class StatusLine:
    """Status-line sink writing to ``stream`` (default stderr). See the module doc."""

    def __init__(self, stream=None, force: bool = False, max_hz: float = 10.0):
        self.stream = sys.stderr if stream is None else stream
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
        rate = getattr(dev, "rate_hz", 0.0)
        if rate and rate > 0:
            self.servo_period_s = 1.0 / rate

    def on_frame(self, frame) -> None:
        if not self.enabled:
            return
        rows = frame.samples
        if rows.shape[0]:
            self.missed += int(np.count_nonzero(rows[:, _C_PERR] > self.servo_period_s))
            self._row = rows[-1].copy()
            self._t = float(self._row[_C_T])  # the servo time of the row shown (frame times can lead it)
        self._rates = dict(frame.rates)
        now = time.monotonic()
        if self._row is None or now - self._last_draw < self.min_interval_s:
            return
        self._last_draw = now
        self._draw()

    def _draw(self) -> None:
        text = format_status(self._t, self._row, self._rates, self.missed, width=max(self._width() - 1, 20))
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

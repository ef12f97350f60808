"""Needle-tip trajectory files: stream, validate, load, interpolate and write them.

What is modelled: the path of the needle tip held by a hand, as timed samples in the scene frame
(acupoint at the origin, outward skin normal +z). A file is a recording or a script; the replay
device (:mod:`devices.scripted`) and the headless engine play it back at the 1 kHz servo rate.

File format (CSV, UTF-8, comma separated, no quoted newlines)::

    t_s,x_mm,y_mm,z_mm[,extra columns...]
    0.000000,0.0000,0.0000,5.0000

The header is on line 1 in what this module writes (so ``pandas.read_csv`` needs no options);
the reader still skips ``#`` comment lines and blank lines anywhere. The four columns ``t_s`` (s)
and ``x_mm``, ``y_mm``, ``z_mm`` (mm) are required, named exactly, in any order; other columns (a
recording's ``fx_n,fy_n,fz_n,layer,...``) are ignored unless asked for by name (``layer`` and
``state_*`` are written as names and read back as their codes). Everything this module *returns*
is SI: seconds, metres, m/s.

Optional columns, parsed and validated whenever present and exposed on :class:`Block`, by
:meth:`TrajectoryCursor.pose_block` and by the scripted device:

* ``axis_x,axis_y,axis_z``: the needle axis, a unit vector from the handle to the tip, scene
  frame (all three or none; refused if its length is off 1 by more than 1%). A row may give all
  three as ``nan``: no axis at that moment (a recording of a device that gave none then), and the
  direction of travel decides the axis as for a file without the columns;
* ``roll_deg``: cumulative roll of the needle, degrees, positive clockwise seen from the handle
  (refused if faster than 10 turns per second);
* ``event``: empty, or ``reset`` (the hand lifted and put back with fresh tissue: the keyboard's
  ``r``). A reset sample is a step (the tip holds the sample before it until the reset's time),
  the hand-speed and roll-rate checks start anew there, velocity does not difference across it,
  and headless replay resets the model at the first tick at or after it. Unknown events are
  refused.

Validation (each problem is a one-line :class:`~haptic_acu.base.errors.UserError` naming the file and,
for anything inside it, the line): missing or unreadable file, a pipe or device instead of a file,
empty file, header only, missing columns (named), a row with the wrong number of fields, a
non-numeric cell (column named), NaN or infinite values, a coordinate over 10 m from the acupoint,
time not strictly increasing, fewer than 2 samples, binary data / text that is not UTF-8, a
carriage return inside a line (old Mac line endings), a field csv cannot read (over 128 kB). The
first problem in file order is the one reported.

Hand speed: the straight-line speed between consecutive samples may not exceed
``max_hand_speed_m_per_s`` (default 2.0 m/s, config ``scene.max_hand_speed_m_per_s``). A faster
jump is not something a hand did (a glitch, a unit mistake, a missing row), and replaying it
would slam the tip through the tissue in one servo tick, so the file is REFUSED, with an error
naming the line and the speed; it is not clipped, slowed or skipped.

Interpolation: the tip position between samples is linear in time; before the first sample it
holds the first position, after the last the last. Velocity is the backward finite difference of
that interpolant over one servo tick, ``v(t) = (p(t) - p(t - h)) / h`` with ``h = 1 ms``: what
a 1 kHz servo differentiating the positions it is fed would see; exact for constant-velocity
motion. :class:`Trajectory` does this on arrays held in memory; :class:`TrajectoryCursor` does it
on a streamed file in O(1) amortised time per query for increasing ``t`` (a backward jump
re-reads the file), keeping only a small window of samples.

Writing: :class:`TrajectoryWriter` writes the same format incrementally, unbuffered, whole rows
only (a failed write is cut back to the last whole row).
Numbers are written with fixed decimals, deterministically: ``%.6f`` for seconds (1 us),
``%.4f`` for mm (0.1 um), ``%.5f`` for newtons (10 uN), chosen by the column's unit suffix;
other extra columns ``%.10g``.

Reading speed: whole lines are read in blocks of bytes and parsed by ``numpy.loadtxt``; a
line-by-line Python path (the ``csv`` module) takes over only for blocks with comments, quotes,
non-ASCII text or an error, and is the one that names the faulty line. Validation streams the
file once, in memory that does not grow with its size; playback through the cursor parses small
blocks (:data:`CURSOR_BLOCK_BYTES`) as the ticks reach them.
"""
from __future__ import annotations

import csv
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np

from ..base.errors import UserError

REQUIRED_COLUMNS = ("t_s", "x_mm", "y_mm", "z_mm")
AXIS_COLUMNS = ("axis_x", "axis_y", "axis_z")  # optional: needle axis, unit vector handle -> tip
ROLL_COLUMN = "roll_deg"  # optional: cumulative stylus roll, degrees, + clockwise seen from the handle
EVENT_COLUMN = "event"  # optional: a named event on the row's tick (empty: none)
EVENTS = ("reset",)  # known events; "reset": fresh tissue, and the hand-speed check starts anew
# Columns written as names (a recording's layer, states and event), read back as their codes when
# asked for as extra columns (a number is accepted too: older recordings wrote the codes).
LAYER_CODES = {"outside": -1, "skin": 0, "fat": 1, "muscle": 2, "bone": 3}
STATE_CODES = {"untouched": 0, "pressing": 1, "punctured": 2}
EVENT_CODES = {"": 0, "reset": 1}
CATEGORY_COLUMNS = {"layer": LAYER_CODES, "state_skin": STATE_CODES, "state_fat": STATE_CODES,
                    "state_muscle": STATE_CODES, EVENT_COLUMN: EVENT_CODES}
MAX_COORD_MM = 10_000.0  # 10 m from the acupoint: a unit mistake, not a hand
AXIS_OUT_Z = 0.5  # an axis with axis_z above this points out of the skin (within 60 degrees of +z)
AXIS_UNIT_TOLERANCE = 0.01  # |axis| must be within 1% of 1
MAX_ROLL_DEG_PER_S = 3600.0  # 10 turns per second: faster is not a hand twirling a needle
DEFAULT_MAX_HAND_SPEED_M_PER_S = 2.0
SERVO_TICK_S = 1e-3  # the velocity finite-difference step: one 1 kHz servo tick
BLOCK_BYTES = 1 << 18  # bytes parsed at a time when streaming a whole file (~7000 rows)
CURSOR_BLOCK_BYTES = 1 << 13  # smaller blocks for playback (~230 rows)
KEEP_ROWS = 20_000  # a validated file of at most this many samples (about 1 MB parsed) is kept for playback
from ..base.csvin import MAX_LINE_BYTES  # noqa: E402 - the input layer's line limit (1 MB)

_NUMBER = re.compile(
    r"[+-]?(?:\d+\.?\d*(?:[eE][+-]?\d+)?|\.\d+(?:[eE][+-]?\d+)?|nan|inf|infinity)",
    re.IGNORECASE | re.ASCII,
)
_CONTROL = re.compile(r"[\x00-\x08\x0b\x0c\x0e-\x1f\x7f]")
_CONTROL_BYTES = bytes([*range(0, 9), 11, 12, *range(14, 32), 127])  # as _CONTROL
_FORMAT_BY_SUFFIX = (("_s", "%.6f"), ("_mm", "%.4f"), ("_n", "%.5f"))


def _binary_error(path: Path, line: int, what: str) -> UserError:
    return UserError(f"{path}: line {line}: {what}; a trajectory is a UTF-8 CSV text file")


@dataclass(frozen=True)
class Block:
    """Consecutive validated samples: ``t_s`` (k,) s, ``pos_m`` (k, 3) m, ``line`` (k,) the
    1-based line of each sample in the file, ``extra`` (k, n) the requested extra columns; the
    optional columns when the file has them (``axis``, ``roll_deg``, ``event``)."""

    t_s: np.ndarray
    pos_m: np.ndarray
    line: np.ndarray | None = None
    extra: np.ndarray | None = None
    axis: np.ndarray | None = None  # (k, 3) unit vectors, if the file has axis_x,axis_y,axis_z
    roll_deg: np.ndarray | None = None  # (k,) if the file has roll_deg
    event: np.ndarray | None = None  # (k,) str ("" for none), if the file has an event column


@dataclass(frozen=True)
class TrajectoryInfo:
    """What :func:`validate` found: sample count, time span (s), fastest hand speed (m/s)."""

    path: str
    samples: int
    t_first_s: float
    t_last_s: float
    max_speed_m_per_s: float

    @property
    def duration_s(self) -> float:
        return self.t_last_s - self.t_first_s


class TrajectoryReader:
    """Streams a trajectory file in validated :class:`Block` s without loading it whole.

    The header is read (and checked) on construction; :meth:`blocks` re-opens the file each time
    it is called, so a reader can be streamed more than once. ``extra_columns`` names further
    columns to return in ``Block.extra``; they must exist and hold finite numbers.
    """

    def __init__(self, path, max_hand_speed_m_per_s: float = DEFAULT_MAX_HAND_SPEED_M_PER_S,
                 extra_columns: Sequence[str] = (), block_bytes: int = BLOCK_BYTES):
        if not max_hand_speed_m_per_s > 0:
            raise ValueError(f"max_hand_speed_m_per_s must be > 0, got {max_hand_speed_m_per_s}")
        if block_bytes < 1:
            raise ValueError(f"block_bytes must be >= 1, got {block_bytes}")
        self.path = Path(path)
        self.max_hand_speed_m_per_s = float(max_hand_speed_m_per_s)
        self.extra_columns = tuple(extra_columns)
        self.block_bytes = int(block_bytes)
        self._kept: list | None = None  # the blocks of a small file, once validated
        with self._open() as f:
            self.columns, self.header_line = self._read_header(f)
        want = REQUIRED_COLUMNS + self.extra_columns
        missing = [c for c in want if c not in self.columns]
        if missing:
            hint = ""
            if self.columns and _NUMBER.fullmatch(self.columns[0]):
                hint = " (is the header line missing?)"
            raise UserError(
                f"{self.path}: line {self.header_line}: missing column(s) {', '.join(missing)}; the "
                f"header must name {','.join(want)} (found: {','.join(self.columns)}){hint}")
        for c in want:
            if self.columns.count(c) > 1:
                raise UserError(f"{self.path}: line {self.header_line}: column {c} appears more "
                                "than once")
        axis_given = [c for c in AXIS_COLUMNS if c in self.columns]
        if axis_given and len(axis_given) != 3:
            missing = [c for c in AXIS_COLUMNS if c not in self.columns]
            raise UserError(f"{self.path}: line {self.header_line}: column(s) {', '.join(missing)} "
                            f"missing; the needle axis takes all of {','.join(AXIS_COLUMNS)}")
        optional = (AXIS_COLUMNS if axis_given else ()) + (
            (ROLL_COLUMN,) if ROLL_COLUMN in self.columns else ())
        for c in optional + ((EVENT_COLUMN,) if EVENT_COLUMN in self.columns else ()):
            if self.columns.count(c) > 1:
                raise UserError(f"{self.path}: line {self.header_line}: column {c} appears more "
                                "than once")
        names = want + tuple(c for c in optional if c not in want)
        self._usecols = [self.columns.index(c) for c in names]
        self._names = names
        self._cat = {k: CATEGORY_COLUMNS[c] for k, c in enumerate(names) if c in self.extra_columns
                     and c in CATEGORY_COLUMNS}  # position in names -> {name: code}
        self._num_pos = [k for k in range(len(names)) if k not in self._cat]
        self.has_axis = bool(axis_given)
        self.has_roll = ROLL_COLUMN in self.columns
        self.has_event = EVENT_COLUMN in self.columns
        self._axis_idx = [names.index(c) for c in AXIS_COLUMNS] if self.has_axis else None
        self._roll_idx = names.index(ROLL_COLUMN) if self.has_roll else None
        self._event_col = self.columns.index(EVENT_COLUMN) if self.has_event else None

    # -- file access -------------------------------------------------------------------------
    def _open(self):
        from ..base.csvin import check_source

        try:
            check_source(self.path, "trajectory file")  # the input layer's rule: a regular file
        except UserError as e:
            if "no such file" in str(e):
                raise UserError(f"{self.path}: trajectory file not found") from None
            raise
        try:
            return open(self.path, "rb")
        except FileNotFoundError:
            raise UserError(f"{self.path}: trajectory file not found") from None
        except OSError as e:
            raise UserError(f"{self.path}: cannot read trajectory file: {e.strerror}") from None

    def _decode(self, raw: bytes, line: int) -> str:
        try:
            text = raw.decode("utf-8-sig" if line == 1 else "utf-8")
        except UnicodeDecodeError:
            raise _binary_error(self.path, line,
                                "not UTF-8 text (binary data or another encoding)") from None
        if _CONTROL.search(text):
            raise _binary_error(self.path, line, "binary data (control characters)")
        if "\r" in text.rstrip("\r\n"):
            raise UserError(f"{self.path}: line {line}: a carriage return inside the line (old Mac "
                            "line endings?); save the file with LF or CRLF line endings")
        return text

    def _fields(self, text: str, line: int) -> list[str]:
        try:
            return next(csv.reader([text]))
        except csv.Error as e:  # a field over csv's 128 kB limit, a stray quote
            raise UserError(f"{self.path}: line {line}: not a CSV row ({e})") from None

    def _read_header(self, f) -> tuple[list[str], int]:
        line = 0
        while raw := f.readline(MAX_LINE_BYTES + 1):
            line += 1
            if len(raw) > MAX_LINE_BYTES:
                raise _binary_error(self.path, line, "a line of over 1 MB (binary data?)")
            text = self._decode(raw, line).strip()
            if not text or text.startswith("#"):
                continue
            names = self._fields(text, line)
            return [n.strip() for n in names], line
        raise UserError(f"{self.path}: line {line + 1}: empty file, expected a header "
                        f"{','.join(REQUIRED_COLUMNS)}")

    # -- parsing -------------------------------------------------------------------------------
    def _parse_fast(self, blob: bytes, n_lines: int):
        """All lines are data rows of plain ASCII numbers: parse in C, else None. Returns
        (values, events or None)."""
        if not blob.isascii() or b"#" in blob or b'"' in blob:
            return None
        if len(blob.translate(None, _CONTROL_BYTES)) != len(blob):
            return None
        a = np.frombuffer(blob, dtype=np.uint8)
        # every line must hold exactly len(columns) - 1 commas (blank lines hold none)
        ends = np.flatnonzero(a == 10) + 1
        if len(ends) < n_lines:
            ends = np.append(ends, len(a))  # the file's last line, without a newline
        per_line = np.diff(np.searchsorted(np.flatnonzero(a == 44), ends), prepend=0)
        if np.any(per_line != len(self.columns) - 1):
            return None
        lines = blob.decode("ascii").splitlines()
        if len(lines) != n_lines:
            return None  # a lone carriage return
        try:
            num = np.loadtxt(lines, delimiter=",", usecols=[self._usecols[k] for k in self._num_pos],
                             comments=None, ndmin=2, dtype=np.float64)
        except ValueError:
            return None
        if num.shape[0] != n_lines:
            return None
        events = None
        if self._event_col is None and not self._cat:
            return num, None
        if not self._cat and self._event_col == len(self.columns) - 1:
            # the usual recording: the event column last and nearly always empty
            empty = blob.count(b",\n") + (1 if not blob.endswith(b"\n") and blob.endswith(b",") else 0)
            if empty == n_lines:
                return num, np.full(n_lines, "", dtype=object)
        cells = [ln.split(",") for ln in lines]
        if self._event_col is not None:
            j = self._event_col
            events = np.array([c[j].strip() for c in cells], dtype=object)
        vals = np.empty((n_lines, len(self._names)))
        vals[:, self._num_pos] = num
        for k, codes in self._cat.items():
            j = self._usecols[k]
            try:
                vals[:, k] = [codes[c[j].strip()] if c[j].strip() in codes else float(c[j])
                              for c in cells]
            except ValueError:
                return None  # the slow path names the line
        return vals, events

    def _parse_slow(self, lines: list[bytes], first: int):
        """Line by line; returns (values, line numbers, the first error or None)."""
        rows, nums, events = [], [], []
        err = None
        for k, raw in enumerate(lines):
            n = first + k
            try:
                text = self._decode(raw, n).strip()
            except UserError as e:
                err = e
                break
            if not text or text.startswith("#"):
                continue
            try:
                fields = self._fields(text, n)
            except UserError as e:
                err = e
                break
            if len(fields) != len(self.columns):
                err = UserError(f"{self.path}: line {n}: {len(fields)} fields, but the header "
                                f"(line {self.header_line}) has {len(self.columns)}")
                break
            vals = []
            for k, (j, name) in enumerate(zip(self._usecols, self._names)):
                cell = fields[j].strip()
                if k in self._cat and cell in self._cat[k]:
                    vals.append(float(self._cat[k][cell]))
                    continue
                if not _NUMBER.fullmatch(cell):
                    if k in self._cat:
                        err = UserError(f"{self.path}: line {n}: column {name}: {cell[:40]!r} is "
                                        f"not one of {', '.join(repr(c) for c in self._cat[k])}")
                        break
                    what = "is empty" if not cell else f"{cell[:40]!r} is not a number"
                    err = UserError(f"{self.path}: line {n}: column {name} {what}")
                    break
                vals.append(float(cell))
            if err is not None:
                break
            rows.append(vals)
            nums.append(n)
            if self._event_col is not None:
                events.append(fields[self._event_col].strip())
        vals = np.array(rows, dtype=np.float64).reshape(-1, len(self._usecols))
        ev = np.array(events, dtype=object) if self._event_col is not None else None
        return vals, np.array(nums, dtype=np.int64), ev, err

    # -- streaming -------------------------------------------------------------------------------
    def blocks(self, block_bytes: int | None = None) -> Iterator[Block]:
        """Validated blocks of samples, in file order. Raises UserError at the first problem."""
        return self._blocks(self._checker(), block_bytes or self.block_bytes)

    def _checker(self) -> "_Checker":
        return _Checker(self.path, self.max_hand_speed_m_per_s, self._names, self._axis_idx,
                        self._roll_idx)

    def _text_blocks(self, f, block_bytes: int) -> Iterator[tuple[bytes, int]]:
        """Whole lines, about ``block_bytes`` at a time: (bytes, number of lines)."""
        carry = b""
        while True:
            chunk = f.read(block_bytes)
            if not chunk:
                if carry:
                    yield carry, 1
                return
            data = carry + chunk if carry else chunk
            cut = data.rfind(b"\n") + 1
            if cut == 0:
                carry = data
                if len(carry) > MAX_LINE_BYTES:
                    yield carry, 1  # no row is this long: the parsers report it
                    return
                continue
            carry = data[cut:]
            yield data[:cut], data.count(b"\n", 0, cut)

    def _blocks(self, check: "_Checker", block_bytes: int) -> Iterator[Block]:
        with self._open() as f:
            for _ in range(self.header_line):
                f.readline(MAX_LINE_BYTES + 1)
            first = self.header_line + 1
            for blob, n_lines in self._text_blocks(f, block_bytes):
                fast = self._parse_fast(blob, n_lines)
                err = None
                if fast is not None:
                    vals, events = fast
                    nums = np.arange(first, first + n_lines, dtype=np.int64)
                else:
                    lines = blob.split(b"\n")
                    if blob.endswith(b"\n"):
                        lines.pop()
                    vals, nums, events, err = self._parse_slow(lines, first)
                first += n_lines
                if len(vals):
                    check(vals, nums, events)  # rows before a parse error may hold an earlier problem
                if err is not None:
                    raise err
                if len(vals):
                    n_extra = len(self.extra_columns)
                    yield Block(vals[:, 0].copy(), vals[:, 1:4] / 1000.0, nums,
                                vals[:, 4:4 + n_extra].copy() if n_extra else None,
                                _unit(vals[:, self._axis_idx]) if self.has_axis else None,
                                vals[:, self._roll_idx].copy() if self.has_roll else None,
                                events)
        check.finish(self.header_line)

    def rows(self) -> Iterator[tuple[float, np.ndarray]]:
        """One ``(t_s, pos_m)`` per sample, streamed."""
        for b in self.blocks():
            yield from zip(b.t_s.tolist(), b.pos_m)

    def validate(self) -> TrajectoryInfo:
        """Read the whole file once, checking everything; a summary is kept, and the blocks
        themselves when the file holds at most :data:`KEEP_ROWS` samples (:meth:`cursor` then
        plays them without reading the file again)."""
        check = self._checker()
        t_first = t_last = math.nan
        kept: list | None = []
        for b in self._blocks(check, self.block_bytes):
            if math.isnan(t_first):
                t_first = float(b.t_s[0])
            t_last = float(b.t_s[-1])
            if kept is not None and check.count <= KEEP_ROWS:
                kept.append(b)
            else:
                kept = None
        self._kept = kept
        return TrajectoryInfo(str(self.path), check.count, t_first, t_last, check.max_speed)

    def cursor(self, velocity_step_s: float = SERVO_TICK_S) -> "TrajectoryCursor":
        """A playback cursor over this file: the blocks :meth:`validate` kept, else the file
        streamed in small blocks."""
        kept = self._kept
        if kept is not None:
            return TrajectoryCursor(lambda: iter(kept), velocity_step_s)
        size = min(self.block_bytes, CURSOR_BLOCK_BYTES)
        return TrajectoryCursor(lambda: self.blocks(size), velocity_step_s)


def _unit(a: np.ndarray) -> np.ndarray:
    return a / np.linalg.norm(a, axis=1, keepdims=True)


class _Checker:
    """Value checks across blocks: finite, coordinates in range, time strictly increasing, hand
    speed (anew after a ``reset`` event), needle axis unit, roll rate, known events, sample count."""

    def __init__(self, path: Path, vmax: float, names: Sequence[str], axis_idx=None, roll_idx=None):
        self.path, self.vmax, self.names = path, vmax, names
        self.axis_idx, self.roll_idx = axis_idx, roll_idx
        self.prev: tuple[np.ndarray, int] | None = None  # the last row's values and line
        self.count = 0
        self.first_line = 0
        self.max_speed = 0.0

    def _row_problems(self, vals: np.ndarray, events) -> list:
        problems = []  # (row, priority, message)
        finite = np.isfinite(vals)
        if self.axis_idx is not None:  # a row with no axis (all three nan) is allowed
            finite[:, self.axis_idx] |= np.isnan(vals[:, self.axis_idx]).all(axis=1)[:, None]
        bad = np.flatnonzero(~finite.all(axis=1))
        if len(bad):
            r = int(bad[0])
            j = int(np.flatnonzero(~finite[r])[0])
            problems.append((r, 0, f"column {self.names[j]} is {float(vals[r, j])!r}; values must "
                                   "be finite" + (" (an axis may be nan on all three columns)"
                                                  if self.axis_idx is not None and j in self.axis_idx else "")))
        with np.errstate(invalid="ignore"):
            far = np.abs(vals[:, 1:4]) > MAX_COORD_MM
        bad = np.flatnonzero(far.any(axis=1))
        if len(bad):
            r = int(bad[0])
            j = 1 + int(np.flatnonzero(far[r])[0])
            problems.append((r, 0, f"column {self.names[j]} is {float(vals[r, j]):.6g} mm, more than "
                                   f"{MAX_COORD_MM:g} mm from the acupoint (are the units mm?)"))
        if self.axis_idx is not None:
            with np.errstate(invalid="ignore"):
                n = np.linalg.norm(vals[:, self.axis_idx], axis=1)
                bad = np.flatnonzero((np.abs(n - 1.0) > AXIS_UNIT_TOLERANCE) & ~np.isnan(n))
            if len(bad):
                r = int(bad[0])
                problems.append((r, 0, f"the needle axis (axis_x,axis_y,axis_z) has length "
                                       f"{n[r]:.6g}; it must be a unit vector (within "
                                       f"{AXIS_UNIT_TOLERANCE:.0%})"))
        if events is not None:
            for r, e in enumerate(events):
                if e and e not in EVENTS:
                    problems.append((r, 0, f"unknown event {e[:40]!r} (known: {', '.join(EVENTS)})"))
                    break
        return problems

    def __call__(self, vals: np.ndarray, lines: np.ndarray, events=None) -> None:
        problems = self._row_problems(vals, events)
        reset = (np.array([e == "reset" for e in events], dtype=bool) if events is not None
                 else np.zeros(len(vals), dtype=bool))
        if self.prev is not None:
            vv = np.vstack((self.prev[0], vals))
            ll = np.concatenate(([self.prev[1]], lines))
            rr = np.concatenate(([False], reset))
        else:
            vv, ll, rr = vals, lines, reset
        off = len(vv) - len(vals)  # row r of this block is index r + off in vv
        if len(vv) > 1:
            tt = vv[:, 0]
            dt = np.diff(tt)
            anew = rr[1:]  # a reset row: the hand may be anywhere; no speed from the row before
            with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
                speed = np.linalg.norm(np.diff(vv[:, 1:4] / 1000.0, axis=0), axis=1) / dt
                speed[anew] = 0.0
                bad_t = np.flatnonzero(~(dt > 0))
                bad_v = np.flatnonzero(speed > self.vmax)
                if self.roll_idx is not None:
                    # over at least one servo tick: a device samples the roll once a tick, and a
                    # recording's late ticks run back to back (rows much closer than a tick)
                    turn = np.abs(np.diff(vv[:, self.roll_idx])) / np.maximum(dt, SERVO_TICK_S)
                    turn[anew] = 0.0
                    bad_r = np.flatnonzero(turn > MAX_ROLL_DEG_PER_S)
                else:
                    bad_r = []
            if len(bad_t):
                i = int(bad_t[0])
                problems.append((i + 1 - off, 1,
                                 f"t_s = {tt[i + 1]:.9g} s is not after t_s = {tt[i]:.9g} s on line "
                                 f"{ll[i]}; time must strictly increase"))
            if len(bad_v):
                i = int(bad_v[0])
                problems.append((i + 1 - off, 2,
                                 f"the tip moves at {speed[i]:.3g} m/s since line {ll[i]}, faster "
                                 f"than a hand can (max_hand_speed_m_per_s = {self.vmax:g}); "
                                 "trajectory refused"))
            if self.axis_idx is not None:
                # entering the skin at the acupoint (z through 0) with the axis pointing out of it: the
                # needle would go in handle first (the axis runs from the handle to the tip)
                z, az = vv[:, 3], vv[:, self.axis_idx[2]]
                with np.errstate(invalid="ignore"):
                    bad_a = np.flatnonzero((z[:-1] > 0) & (z[1:] <= 0) & ~anew & (az[1:] > AXIS_OUT_Z))
                if len(bad_a):
                    i = int(bad_a[0])
                    problems.append((i + 1 - off, 2,
                                     f"the tip enters the skin (z_mm {z[i]:g} to {z[i + 1]:g}) against its "
                                     f"needle axis (axis_z = {az[i + 1]:+.3g} points out of the skin; the axis "
                                     "runs from the handle to the tip)"))
            if len(bad_r):
                i = int(bad_r[0])
                problems.append((i + 1 - off, 2,
                                 f"roll_deg turns at {turn[i] / 360.0:.3g} turns/s since line "
                                 f"{ll[i]}, faster than a hand twirls a needle "
                                 f"({MAX_ROLL_DEG_PER_S / 360.0:g} turns/s); trajectory refused"))
            if not problems:
                self.max_speed = max(self.max_speed, float(np.max(speed)))
        if problems:
            r, _, msg = min(problems, key=lambda q: (q[0], q[1]))
            raise UserError(f"{self.path}: line {lines[r]}: {msg}")
        if self.count == 0:
            self.first_line = int(lines[0])
        self.count += len(vals)
        self.prev = (vals[-1].copy(), int(lines[-1]))

    def finish(self, header_line: int) -> None:
        if self.count == 0:
            raise UserError(f"{self.path}: line {header_line}: header only, no samples")
        if self.count == 1:
            raise UserError(f"{self.path}: line {self.first_line}: only one sample; a trajectory "
                            f"needs at least 2")


def validate(path, max_hand_speed_m_per_s: float = DEFAULT_MAX_HAND_SPEED_M_PER_S) -> TrajectoryInfo:
    """Check a whole trajectory file, streaming it; raise UserError at its first problem."""
    return TrajectoryReader(path, max_hand_speed_m_per_s).validate()


@dataclass(frozen=True)
class Trajectory:
    """A trajectory held in memory: ``t_s`` (n,) s, strictly increasing; ``pos_m`` (n, 3) m;
    ``extra`` maps requested extra column names to (n,) arrays."""

    t_s: np.ndarray
    pos_m: np.ndarray
    path: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def t_first_s(self) -> float:
        return float(self.t_s[0])

    @property
    def t_last_s(self) -> float:
        return float(self.t_s[-1])

    @property
    def duration_s(self) -> float:
        return self.t_last_s - self.t_first_s

    def position_at(self, t) -> np.ndarray:
        """Tip position (m), linear between samples, held outside them; ``t`` scalar or array."""
        t = np.asarray(t, dtype=np.float64)
        return np.stack([np.interp(t, self.t_s, self.pos_m[:, k]) for k in range(3)], axis=-1)

    def velocity_at(self, t, step_s: float = SERVO_TICK_S) -> np.ndarray:
        """Tip velocity (m/s): ``(p(t) - p(t - step_s)) / step_s`` of the interpolant."""
        t = np.asarray(t, dtype=np.float64)
        return (self.position_at(t) - self.position_at(t - step_s)) / step_s

    def cursor(self, velocity_step_s: float = SERVO_TICK_S) -> "TrajectoryCursor":
        return TrajectoryCursor(lambda: iter((Block(self.t_s, self.pos_m),)), velocity_step_s)


def load(path, max_hand_speed_m_per_s: float = DEFAULT_MAX_HAND_SPEED_M_PER_S,
         extra_columns: Sequence[str] = ()) -> Trajectory:
    """Read and validate a whole trajectory file into memory (for files that fit)."""
    reader = TrajectoryReader(path, max_hand_speed_m_per_s, extra_columns)
    ts, ps, xs = [], [], []
    for b in reader.blocks():
        ts.append(b.t_s)
        ps.append(b.pos_m)
        if b.extra is not None:
            xs.append(b.extra)
    extra = {}
    if extra_columns:
        ex = np.concatenate(xs)
        extra = {name: ex[:, k].copy() for k, name in enumerate(extra_columns)}
    return Trajectory(np.concatenate(ts), np.concatenate(ps), str(path), extra)


class TrajectoryCursor:
    """Plays a stream of :class:`Block` s: position and velocity at a time ``t`` (s).

    ``open_blocks()`` returns a fresh iterator over the blocks (called again to rewind). The cursor
    keeps a window of samples from the one before ``t - velocity_step_s`` onward, pulling blocks as
    ``t`` advances, so memory stays bounded by the block size; each query is O(1) amortised for
    increasing ``t``. A query earlier than the window re-opens the stream from the start.

    A ``reset`` event on a sample (the hand was lifted and put back: the keyboard's ``r``) is a
    step, not a glide: the tip holds the sample before it until the event's time, then is at the
    event's sample, and the velocity starts anew there (the backward difference never reaches
    across it). :attr:`reset_times` lists the events' times seen so far; :meth:`resets_between`
    says which ticks of a block meet one. The optional needle axis and roll are interpolated by
    :meth:`pose_block` (``None`` when the file has none).
    """

    def __init__(self, open_blocks: Callable[[], Iterable[Block]],
                 velocity_step_s: float = SERVO_TICK_S):
        if not velocity_step_s > 0:
            raise ValueError(f"velocity_step_s must be > 0, got {velocity_step_s}")
        self._open_blocks = open_blocks
        self.velocity_step_s = float(velocity_step_s)
        self.rewinds = 0
        self._rewind()
        self.rewinds = 0

    def _rewind(self) -> None:
        self.rewinds += 1
        self._it = iter(self._open_blocks())
        self._t = np.empty(0)
        self._p = np.empty((0, 3))
        self._ax = None  # (n, 3) needle axis, if the blocks carry one
        self._roll = None  # (n,) roll (deg), if the blocks carry it
        self.reset_times: list[float] = getattr(self, "reset_times", [])
        self._eof = False
        self._hint = [0, 0]
        while not self._eof and len(self._t) < 2:
            self._pull(0)
        if len(self._t) < 2:
            raise ValueError("a trajectory needs at least 2 samples")
        self.t_first_s = float(self._t[0])

    def _pull(self, keep_from: int) -> None:
        try:
            b = next(self._it)
        except StopIteration:
            self._eof = True
            return
        if keep_from > 0:
            self._hint = [max(h - keep_from, 0) for h in self._hint]
        t, p, ax, roll = b.t_s, b.pos_m, getattr(b, "axis", None), getattr(b, "roll_deg", None)
        ev = getattr(b, "event", None)
        if ev is not None and len(self._t) + len(t) > 1:
            rows = [r for r, e in enumerate(ev) if e == "reset" and (r > 0 or len(self._t))]
            if rows:
                t, p, ax, roll = self._hold_before_resets(rows, t, p, ax, roll)
        self._t = np.concatenate((self._t[keep_from:], t))
        self._p = np.concatenate((self._p[keep_from:], p))
        if ax is not None:
            self._ax = ax if self._ax is None else np.concatenate((self._ax[keep_from:], ax))
        if roll is not None:
            self._roll = roll if self._roll is None else np.concatenate((self._roll[keep_from:], roll))

    def _hold_before_resets(self, rows, t, p, ax, roll):
        """Insert, just before each reset sample, a copy of the sample before it (a step)."""
        cols = [t[:, None], p] + ([ax] if ax is not None else []) + (
            [roll[:, None]] if roll is not None else [])
        a = np.hstack(cols)
        prev_row = None
        if len(self._t):
            prev_cols = [self._t[-1:, None], self._p[-1:]]
            if ax is not None:
                prev_cols.append(self._ax[-1:])
            if roll is not None:
                prev_cols.append(self._roll[-1:, None])
            prev_row = np.hstack(prev_cols)[0]
        out, start = [], 0
        for r in rows:
            before = a[r - 1] if r > 0 else prev_row
            te = float(a[r, 0])
            hold_t = float(np.nextafter(te, -np.inf))
            out.append(a[start:r])
            if before[0] < hold_t:
                h = before.copy()
                h[0] = hold_t
                out.append(h[None, :])
            start = r
            if not self.reset_times or te > self.reset_times[-1]:
                self.reset_times.append(te)
        out.append(a[start:])
        a = np.vstack(out)
        k = 4
        ax2 = a[:, k:k + 3] if ax is not None else None
        k += 3 if ax is not None else 0
        roll2 = a[:, k] if roll is not None else None
        return a[:, 0].copy(), a[:, 1:4].copy(), ax2, roll2

    def _ensure(self, lo: float, hi: float) -> None:
        """Make the window hold the segment containing ``lo`` and reach past ``hi`` (or the end)."""
        if lo < self._t[0] and self._t[0] > self.t_first_s:  # the samples needed were dropped
            self._rewind()
        while not self._eof and self._t[-1] <= hi:
            self._pull(max(int(np.searchsorted(self._t, lo, side="right")) - 1, 0))

    def _at(self, t: float, which: int) -> np.ndarray:
        T = self._t
        last = len(T) - 1
        if t <= T[0]:
            return self._p[0].copy()
        if t >= T[last]:
            return self._p[last].copy()
        i = self._hint[which]
        if i >= last or T[i] > t:
            i = int(np.searchsorted(T, t, side="right")) - 1
        else:
            steps = 0
            while T[i + 1] <= t:
                i += 1
                steps += 1
                if steps > 8:
                    i = int(np.searchsorted(T, t, side="right")) - 1
                    break
        self._hint[which] = i
        p0 = self._p[i]
        return p0 + ((t - T[i]) / (T[i + 1] - T[i])) * (self._p[i + 1] - p0)

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray, bool]:
        """``(position_m, velocity_m_s, done)`` at time ``t``; ``done`` once ``t`` reaches the
        last sample."""
        t = float(t)
        h = self.velocity_step_s
        self._ensure(t - h, t)
        p = self._at(t, 0)
        back = self._back_times(np.array([t]))[0]
        v = (p - self._at(back, 1)) / h
        return p, v, bool(self._eof and t >= self._t[-1])

    def _back_times(self, t: np.ndarray) -> np.ndarray:
        """``t - h``, but never before the latest reset at or before ``t``."""
        back = t - self.velocity_step_s
        if self.reset_times:
            rt = np.asarray(self.reset_times)
            i = np.searchsorted(rt, t, side="right") - 1
            hit = i >= 0
            back[hit] = np.maximum(back[hit], rt[i[hit]])
        return back

    def resets_between(self, t: np.ndarray) -> list[int]:
        """Indices ``i`` of the increasing tick times ``t`` that are the first at or after a reset
        (a reset lying in ``(t[i] - h, t[i]]``, ``h`` the velocity step); ``sample_block(t)`` must
        have been called first (it reads that far)."""
        if not self.reset_times or len(t) == 0:
            return []
        rt = np.asarray(self.reset_times)
        rt = rt[(rt > t[0] - self.velocity_step_s) & (rt <= t[-1])]
        return sorted(set(np.searchsorted(t, rt, side="left").tolist()))

    def pose_block(self, t: np.ndarray):
        """The optional pose at times ``t`` (n,): needle axis (n, 3), unit, and roll (n,) degrees;
        each ``None`` when the file has no such columns."""
        t = np.asarray(t, dtype=np.float64)
        if t.size == 0:
            return None, None
        self._ensure(float(t[0]), float(t[-1]))
        axis = roll = None
        if self._ax is not None:
            axis = _unit(np.stack([np.interp(t, self._t, self._ax[:, k]) for k in range(3)], axis=-1))
        if self._roll is not None:
            roll = np.interp(t, self._t, self._roll)
        return axis, roll

    def sample_block(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Vectorised :meth:`sample` for increasing times ``t`` (n,): positions (n, 3), velocities
        (n, 3) and done flags (n,). Used by headless replay, one visual frame of ticks per call."""
        t = np.asarray(t, dtype=np.float64)
        if t.size == 0:
            return np.empty((0, 3)), np.empty((0, 3)), np.zeros(0, dtype=bool)
        h = self.velocity_step_s
        self._ensure(float(t[0]) - h, float(t[-1]))
        T = self._t
        P = self._p
        pos = np.empty((t.size, 3))
        back = np.empty((t.size, 3))
        tb = self._back_times(t)
        for k in range(3):
            pos[:, k] = np.interp(t, T, P[:, k])
            back[:, k] = np.interp(tb, T, P[:, k])
        done = (t >= T[-1]) if self._eof else np.zeros(t.size, dtype=bool)
        return pos, (pos - back) / h, done

    def position_at(self, t: float) -> np.ndarray:
        return self.sample(t)[0]

    def velocity_at(self, t: float) -> np.ndarray:
        return self.sample(t)[1]


class TrajectoryWriter:
    """Writes a trajectory file incrementally (a recording): header on line 1, rows in blocks.

    ``append_rows(rows)`` takes an array (k, 4 + len(extra_columns)): time (s), tip position x, y, z
    in METRES (converted to the file's mm here), then the extra columns as given (their names say
    their units, e.g. ``fz_n``). Each call writes whole rows and flushes. Time must strictly
    increase across all rows and every value must be finite (ValueError otherwise: that is a bug
    in the caller, and such a file could not be read back). Formats by column suffix: ``_s``
    ``%.6f``, ``_mm`` ``%.4f``, ``_n`` ``%.5f``, others ``%.10g``; ``formats={"name": "%d"}``
    overrides, and ``formats={"name": {code: "text", ...}}`` writes a name for each integer code
    (layers, states, events: a plain CSV reads names, not codes). ``comments``, if any, go to a
    sidecar ``FILE.json`` (``{"comments": [...]}``), never into the CSV: its line 1 is the header.

    ``open_mode="x"`` refuses an existing file (FileExistsError). ``write_header=False`` defers the
    header to the first rows (or :meth:`write_header`). An OSError while writing (a full
    disk) truncates the file back to its last whole row before it propagates, so the file always
    ends on a whole row and replays.
    """

    def __init__(self, path, extra_columns: Sequence[str] = (), formats: dict | None = None,
                 comments: Sequence[str] = (), open_mode: str = "w", write_header: bool = True):
        self.path = Path(path)
        self.columns = REQUIRED_COLUMNS + tuple(extra_columns)
        for c in extra_columns:
            if not c or c != c.strip() or any(ch in c for ch in ',"#\r\n'):
                raise ValueError(f"bad extra column name {c!r}")
        if len(set(self.columns)) != len(self.columns):
            raise ValueError(f"duplicate column names in {self.columns}")
        if open_mode not in ("w", "x"):
            raise ValueError(f"open_mode must be 'w' or 'x', got {open_mode!r}")
        formats = dict(formats or {})
        unknown = set(formats) - set(self.columns)
        if unknown:
            raise ValueError(f"formats for unknown columns {sorted(unknown)}")
        self._names: dict[int, dict] = {}  # column index -> {code: name}
        fmts = []
        for j, c in enumerate(self.columns):
            f = formats.get(c)
            if isinstance(f, dict):
                self._names[j] = {int(k): str(v) for k, v in f.items()}
                f = "%s"
            fmts.append(f or next((f for s, f in _FORMAT_BY_SUFFIX if c.endswith(s)), "%.10g"))
        self._fmt = ",".join(fmts) + "\n"
        try:
            self._f = open(self.path, open_mode + "b", buffering=0)
        except FileExistsError:
            raise
        except OSError as e:
            raise UserError(f"{self.path}: cannot write trajectory file: {e.strerror}") from None
        self._good = 0  # bytes of whole rows written
        self.rows_written = 0
        self._last_t = -math.inf
        self._header_done = False
        if write_header:
            self.write_header()
        if comments:
            import json
            sidecar = self.path.with_name(self.path.name + ".json")
            sidecar.write_text(json.dumps({"comments": [str(c) for c in comments]}, indent=2) + "\n")

    def write_header(self) -> None:
        """Write the header line now (once; ``append_rows`` does it before the first rows)."""
        if not self._header_done and not self._f.closed:
            self._write((",".join(self.columns) + "\n").encode())
            self._header_done = True

    def _write(self, data: bytes) -> None:
        """Write ``data`` (whole rows) straight to the file (unbuffered: nothing is left half in a
        buffer); on an I/O error cut the file back to the last whole row and re-raise."""
        view = memoryview(data)
        try:
            while view:
                n = self._f.write(view)
                view = view[n:]
        except OSError:
            try:
                os.ftruncate(self._f.fileno(), self._good)
                self._f.seek(self._good)
            except OSError:
                pass
            raise
        self._good += len(data)

    def append_rows(self, rows) -> None:
        a = np.asarray(rows, dtype=np.float64)
        if a.ndim == 1:
            a = a[None, :]
        if a.ndim != 2 or a.shape[1] != len(self.columns):
            raise ValueError(f"rows must have shape (k, {len(self.columns)}) for columns "
                             f"{','.join(self.columns)}, got {a.shape}")
        if len(a) == 0:
            return
        if self._f.closed:
            raise ValueError(f"{self.path}: writer is closed")
        finite = np.isfinite(a)
        ax = [self.columns.index(c) for c in AXIS_COLUMNS if c in self.columns]
        if len(ax) == 3:  # no axis on a row: all three nan (the reader's convention)
            finite[:, ax] |= np.isnan(a[:, ax]).all(axis=1)[:, None]
        if not finite.all():
            r = int(np.flatnonzero(~finite.all(axis=1))[0])
            raise ValueError(f"{self.path}: refusing to write non-finite values (row {r} of the block)")
        t = a[:, 0]
        if not (t[0] > self._last_t and np.all(np.diff(t) > 0)):
            raise ValueError(f"{self.path}: time must strictly increase (last written "
                             f"{self._last_t}, block starts {t[0]})")
        out = a.copy()
        out[:, 1:4] *= 1000.0
        out += 0.0  # -0.0 -> 0.0
        cols: list = [c for c in out.T.tolist()]
        for j, names in self._names.items():
            try:
                cols[j] = [names[int(v)] for v in cols[j]]
            except KeyError as e:
                raise ValueError(f"{self.path}: column {self.columns[j]}: no name for code {e}") from None
        fmt = self._fmt
        text = "".join([fmt % r for r in zip(*cols)])
        if not self._header_done:
            text = ",".join(self.columns) + "\n" + text
        self._write(text.encode())
        self._header_done = True
        self.rows_written += len(a)
        self._last_t = float(t[-1])

    def close(self) -> None:
        if not self._f.closed:
            try:
                self._f.close()
            except OSError:  # nothing is buffered after a flush; a failing close loses nothing
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

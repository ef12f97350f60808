"""The input layer for every CSV the tool reads (docs/outputs.md, "Input limits").

Trajectories and recordings are streamed (:mod:`haptic_acu.session.trajectory`, a window of rows
in memory); curves, manifests, ratings and Delphi rounds are read whole by :func:`read_table`.
Both keep the same rules, checked here:

* the path must be a regular file: a folder, a FIFO, a socket or a device (``/dev/zero``, a
  terminal) is refused before a byte is read (:func:`check_source`);
* text is UTF-8 (a byte-order mark on line 1 is accepted), without control characters or a
  carriage return inside a line; ``\\n`` and ``\\r\\n`` line endings;
* a line is at most :data:`MAX_LINE_BYTES`, a field at most :data:`MAX_FIELD_BYTES` (the ``csv``
  module's own limit), a quoted field never spans lines (an unclosed quote is reported on its
  line, it does not swallow the rows after it);
* a table read whole is at most :data:`MAX_TABLE_BYTES` and :data:`MAX_TABLE_LINES`, so reading
  one never holds more than that in memory.

Every problem is one :class:`UserError` line naming the file and the line.
"""
from __future__ import annotations

import csv
import os
import re
import stat
from dataclasses import dataclass, field
from pathlib import Path

from .errors import UserError

MAX_LINE_BYTES = 1 << 20  # a longer "line" is binary data, not a row
MAX_FIELD_BYTES = 128 * 1024  # csv's field_size_limit: a longer cell is not a value
MAX_TABLE_BYTES = 64 << 20  # a table read whole (manifest, ratings, curve)
MAX_TABLE_LINES = 1_000_000

_CONTROL = re.compile(r"[\x00-\x08\x0b\x0c\x0e-\x1f\x7f]")


def _size(n: int) -> str:
    return f"{n >> 20} MB" if n >= 1 << 20 else f"{n >> 10} kB"


def check_source(path, what: str = "file") -> os.stat_result:
    """``path`` is a regular file that can be read to its end: one line otherwise (missing, a
    folder, a pipe, a socket, a device such as /dev/zero or a terminal)."""
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise UserError(f"{p}: no such file (expected a {what})") from None
    except OSError as e:
        raise UserError(f"{p}: cannot read {what}: {e.strerror or e}") from None
    if stat.S_ISDIR(st.st_mode):
        raise UserError(f"{p}: is a directory, not a {what}")
    if not stat.S_ISREG(st.st_mode):
        kind = "a pipe" if stat.S_ISFIFO(st.st_mode) else "a socket" if stat.S_ISSOCK(st.st_mode) else "a device"
        raise UserError(f"{p}: is {kind}, not a {what} (save it to a file first)")
    return st


def decode_line(path, raw: bytes, line: int, what: str = "file") -> str:
    """One line's bytes as text (its line ending kept off), or a one-line error naming it."""
    try:
        text = raw.decode("utf-8-sig" if line == 1 else "utf-8")
    except UnicodeDecodeError:
        raise UserError(f"{path}: line {line}: not UTF-8 text (binary data or another encoding); "
                        f"a {what} is a UTF-8 CSV text file") from None
    text = text[:-1] if text.endswith("\n") else text
    text = text[:-1] if text.endswith("\r") else text
    if _CONTROL.search(text):
        raise UserError(f"{path}: line {line}: binary data (control characters); a {what} is a "
                        "UTF-8 CSV text file")
    if "\r" in text:
        raise UserError(f"{path}: line {line}: a carriage return inside the line (old Mac line "
                        "endings?); save the file with LF or CRLF line endings")
    return text


def split_row(path, text: str, line: int) -> list[str]:
    """The fields of one CSV line; a field over :data:`MAX_FIELD_BYTES`, an unclosed quote or bad
    quoting is one line naming ``line``."""
    if len(text) > MAX_FIELD_BYTES and any(len(f) > MAX_FIELD_BYTES for f in text.split(",")):
        raise UserError(f"{path}: line {line}: a field of over {_size(MAX_FIELD_BYTES)} (a CSV cell "
                        "holds a value, not a document)")
    try:
        return next(csv.reader([text], strict=True))
    except csv.Error as e:
        if text.count('"') % 2:
            raise UserError(f"{path}: line {line}: an unclosed quote (a quoted field must end on "
                            "its own line)") from None
        if "field larger" in str(e):
            raise UserError(f"{path}: line {line}: a field of over {_size(MAX_FIELD_BYTES)}") from None
        raise UserError(f"{path}: line {line}: not a CSV row ({e})") from None
    except StopIteration:
        return []


@dataclass(frozen=True)
class Row:
    line: int
    fields: list[str]


@dataclass
class Table:
    """A CSV read whole: ``header`` (stripped names) on ``header_line``, then ``rows``."""

    path: Path
    header: list[str]
    header_line: int
    rows: list[Row] = field(default_factory=list)


def iter_lines(path, what: str = "file", max_bytes: int = MAX_TABLE_BYTES,
               max_lines: int = MAX_TABLE_LINES):
    """(line number, text) of every line of ``path``, checked as the module says, in memory that
    never exceeds one line."""
    p = Path(path)
    st = check_source(p, what)
    if st.st_size > max_bytes:
        raise UserError(f"{p}: {st.st_size / 1e6:.0f} MB; a {what} is read whole and may be at most "
                        f"{_size(max_bytes)}")
    try:
        f = open(p, "rb")
    except OSError as e:
        raise UserError(f"{p}: cannot read {what}: {e.strerror or e}") from None
    total = 0
    with f:
        line = 0
        while True:
            try:
                raw = f.readline(MAX_LINE_BYTES + 1)
            except OSError as e:
                raise UserError(f"{p}: line {line + 1}: cannot read: {e.strerror or e}") from None
            if not raw:
                return
            line += 1
            total += len(raw)
            if len(raw) > MAX_LINE_BYTES:
                raise UserError(f"{p}: line {line}: a line of over {_size(MAX_LINE_BYTES)} (binary "
                                "data?)")
            if line > max_lines or total > max_bytes:
                raise UserError(f"{p}: line {line}: over {max_lines:,} lines or {_size(max_bytes)}; a "
                                f"{what} is read whole (split it)")
            yield line, decode_line(p, raw, line, what)


def read_table(path, what: str = "file", comments: bool = True, max_bytes: int = MAX_TABLE_BYTES,
               max_lines: int = MAX_TABLE_LINES) -> Table:
    """Read a CSV whole: blank lines (and, with ``comments``, lines starting with ``#``) skipped; the
    first other line is the header. Raises :class:`UserError` (one line) on anything the module
    lists, and on a file with no header."""
    p = Path(path)
    table = None
    for line, text in iter_lines(p, what, max_bytes, max_lines):
        s = text.strip()
        if not s or (comments and s.startswith("#")):
            continue
        fields = split_row(p, text, line)
        if table is None:
            table = Table(p, [h.strip() for h in fields], line)
        elif any(c.strip() for c in fields):
            table.rows.append(Row(line, fields))
    if table is None:
        raise UserError(f"{p}: empty file (expected a {what}'s header line)")
    return table

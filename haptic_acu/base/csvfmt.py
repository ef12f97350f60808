"""Fast, deterministic CSV formatting of numeric sample blocks (numba).

A headless replay writes one row per servo tick (16,000 rows of some 40 columns for the default
insertion), too many for Python's per-value formatting. :class:`RowFormatter` writes a whole block
in one compiled call: each column is either a fixed-decimal number (rounded half away from zero at
its number of decimals, never "-0.000") or a category (an integer code looked up in a table of
names). Identical values give identical bytes.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

FIXED, CATEGORY = 0, 1


_U10 = np.uint64(10)
_POW10 = np.array([10 ** k for k in range(20)], dtype=np.uint64)
# "00" "01" ... "99": the digits go two per division by 100
_PAIRS = np.frombuffer("".join(f"{i:02d}" for i in range(100)).encode("ascii"), dtype=np.uint8).copy()
_E1, _E2, _E3, _E4, _E5, _E6, _E7, _E8 = (np.uint64(10 ** k) for k in range(1, 9))
_E9, _E10, _E11, _E12, _E13, _E14, _E15 = (np.uint64(10 ** k) for k in range(9, 16))
_ONE, _TWO = np.uint64(1), np.uint64(2)
_EXACT = 2.0 ** 53  # below it floor(x) is x's truncation to an integer of at most 16 digits


@nb.njit(cache=True, nogil=True)
def _put_fixed_wide(out, pos, v, d, p10f):
    """``v`` (finite) rounded half away from zero to ``d`` decimals (``p10f`` = 10.0**d), without a
    negative zero, for any magnitude (at most 19 digits), a digit per division by 10; returns the
    new position. :func:`_format_gather` writes the usual magnitudes itself, the same bytes."""
    iv = np.int64(math.floor(abs(v) * p10f + 0.5))
    if iv != 0 and v < 0:
        out[pos] = 45  # '-'
        pos += 1
    u = np.uint64(iv)
    n = 1
    while n < 19 and u >= _POW10[n]:
        n += 1
    if n < d + 1:
        n = d + 1  # "0.0012": a zero before the point
    ln = n + 1 if d > 0 else n
    j = pos + ln - 1
    for _ in range(d):
        out[j] = np.uint8(48 + u % _U10)
        u //= _U10
        j -= 1
    if d > 0:
        out[j] = 46  # '.'
        j -= 1
    while j >= pos:
        out[j] = np.uint8(48 + u % _U10)
        u //= _U10
        j -= 1
    return pos + ln


@nb.njit(cache=True, nogil=True, inline="always")
def _n_digits(u):
    """The number of decimal digits of ``u`` (uint64 below 10**16; 1 for 0), by comparisons."""
    if u < _E8:
        if u < _E4:
            if u < _E2:
                return 1 if u < _E1 else 2
            return 3 if u < _E3 else 4
        if u < _E6:
            return 5 if u < _E5 else 6
        return 7 if u < _E7 else 8
    if u < _E12:
        if u < _E10:
            return 9 if u < _E9 else 10
        return 11 if u < _E11 else 12
    if u < _E14:
        return 13 if u < _E13 else 14
    return 15 if u < _E15 else 16


class Cells(NamedTuple):
    """How each column is written (the compiled passes' view of a :class:`RowFormatter`): ``kinds``
    (FIXED or CATEGORY), ``decimals``, and the category names' bytes (``table`` rows of
    ``table_len`` bytes; a column's first name at row ``table_base``)."""
    kinds: np.ndarray
    decimals: np.ndarray
    table: np.ndarray
    table_len: np.ndarray
    table_base: np.ndarray


@nb.njit(cache=True, nogil=True)
def _format_gather(rows, extra, gather, cells, out):
    """CSV lines of the columns ``v * scale[c] + offset[c]`` (``gather``: src, scale, offset;
    ``offset`` added only where it is not zero), ``v`` from ``rows[:, src[c]]``, or from
    ``extra[:, src[c] - rows.shape[1]]`` where ``src[c]`` is past ``rows``' columns, into ``out``;
    returns the number of bytes.

    A fixed cell is the integer floor(|v| * 10.0**d + 0.5) with a point before its last d digits
    (a "0" before the point at least, a '-' for v < 0 unless that integer is 0); "nan" for a value
    that is not finite. Below 2**53 that floor is the (positive) sum's truncation and its digits are
    written two at a time from a table; above, by :func:`_put_fixed_wide`. A category cell is the
    name of the code ``int(v)``, empty for a negative or non-finite code. The cells are written in
    this one loop, no helper taking an array: an array handed to a function inside the loop costs
    two reference-count updates per cell, more than the cell's digits."""
    src, scale, offset = gather
    kinds, decimals, table, table_len, table_base = cells
    pairs = _PAIRS
    n = rows.shape[0]
    w = rows.shape[1]
    m = src.shape[0]
    pos = 0
    p10f = np.empty(m)
    for c in range(m):
        p10f[c] = 10.0 ** decimals[c]
    for i in range(n):
        for c in range(m):
            if c > 0:
                out[pos] = 44  # ','
                pos += 1
            k = src[c]
            v = (rows[i, k] if k < w else extra[i, k - w]) * scale[c]
            if offset[c] != 0.0:
                v = v + offset[c]
            if kinds[c] == 1:  # a category
                if math.isfinite(v) and v >= 0.0:  # else an empty cell
                    t = table_base[c] + int(v)
                    for b in range(table_len[t]):
                        out[pos] = table[t, b]
                        pos += 1
                continue
            if not math.isfinite(v):
                out[pos] = 110  # "nan"
                out[pos + 1] = 97
                out[pos + 2] = 110
                pos += 3
                continue
            d = decimals[c]
            x = abs(v) * p10f[c] + 0.5
            if not x < _EXACT or d > 15:
                pos = _put_fixed_wide(out, pos, v, d, p10f[c])
                continue
            u = np.uint64(x)
            if u != 0 and v < 0:
                out[pos] = 45  # '-'
                pos += 1
            nd = _n_digits(u)
            ni = nd - d if nd > d else 1  # the digits before the point
            j = pos + ni + d if d > 0 else pos + ni - 1  # the last digit's index
            pos = j + 1
            left = d
            while left >= 2:  # the decimals
                q = u // _E2
                r = (u - q * _E2) * _TWO
                out[j - 1] = pairs[r]
                out[j] = pairs[r + _ONE]
                u = q
                j -= 2
                left -= 2
            if left == 1:
                q = u // _E1
                out[j] = pairs[(u - q * _E1) * _TWO + _ONE]
                u = q
                j -= 1
            if d > 0:
                out[j] = 46  # '.'
                j -= 1
            left = ni
            while left >= 2:  # the integer part
                q = u // _E2
                r = (u - q * _E2) * _TWO
                out[j - 1] = pairs[r]
                out[j] = pairs[r + _ONE]
                u = q
                j -= 2
                left -= 2
            if left == 1:
                out[j] = pairs[u * _TWO + _ONE]
        out[pos] = 10  # '\n'
        pos += 1
    return pos


class RowFormatter:
    """Formats (k, m) float blocks as CSV lines. ``columns`` is a list of ``("fixed", decimals)`` or
    ``("category", names)``; a category cell holds an integer code indexing ``names`` (NaN or
    negative: empty)."""

    def __init__(self, columns):
        self.kinds = np.array([FIXED if c[0] == "fixed" else CATEGORY for c in columns], dtype=np.int64)
        self.decimals = np.array([c[1] if c[0] == "fixed" else 0 for c in columns], dtype=np.int64)
        names = []
        base = []
        for c in columns:
            base.append(len(names))
            if c[0] == "category":
                names.extend(n.encode("ascii") for n in c[1])
        names = names or [b""]
        width = max(len(n) for n in names) or 1
        self.table = np.zeros((len(names), width), dtype=np.uint8)
        self.table_len = np.array([len(n) for n in names], dtype=np.int64)
        for i, n in enumerate(names):
            self.table[i, :len(n)] = np.frombuffer(n, dtype=np.uint8)
        self.table_base = np.array(base, dtype=np.int64)
        self.max_cell = max(24, width + 1)
        self.cells = Cells(self.kinds, self.decimals, self.table, self.table_len, self.table_base)
        self._buf: np.ndarray | None = None  # write_gather's output buffer

    def format(self, values: np.ndarray) -> bytes:
        values = np.ascontiguousarray(values, dtype=np.float64)
        m = values.shape[1]
        return self.format_gather(values, np.zeros((values.shape[0], 0)), np.arange(m), np.ones(m), np.zeros(m))

    def format_gather(self, rows: np.ndarray, extra: np.ndarray, src, scale, offset) -> bytes:
        """Lines of the columns taken from ``rows`` (k, w) and ``extra`` (k, e) without building
        them first: column ``c`` is ``rows[:, src[c]]`` (``extra[:, src[c] - w]`` past ``rows``'
        columns) times ``scale[c]``, plus ``offset[c]`` where that is not zero; then as
        :meth:`format` (the same bytes as :meth:`format` on those columns)."""
        return self._gather(rows, extra, src, scale, offset, None).tobytes()

    def write_gather(self, file, rows: np.ndarray, extra: np.ndarray, src, scale, offset) -> int:
        """:meth:`format_gather`'s bytes written to the binary ``file``, formatted into a buffer the
        formatter keeps (grown as needed; no allocation per block once it is large enough); returns
        the number of bytes."""
        n = self._buf.shape[0] if self._buf is not None else 0
        need = len(rows) * (len(src) * self.max_cell + 1)
        if need > n:
            self._buf = np.empty(max(need, 2 * n), dtype=np.uint8)
        view = self._gather(rows, extra, src, scale, offset, self._buf)
        file.write(memoryview(view))
        return view.shape[0]

    def _gather(self, rows, extra, src, scale, offset, out) -> np.ndarray:
        rows = np.ascontiguousarray(rows, dtype=np.float64)
        extra = np.ascontiguousarray(extra, dtype=np.float64)
        if extra.ndim != 2:
            extra = extra.reshape(rows.shape[0], -1)
        src = np.asarray(src, dtype=np.int64)
        if src.shape[0] != self.kinds.shape[0]:
            raise ValueError(f"{src.shape[0]} source columns for {self.kinds.shape[0]} formatted ones")
        if out is None:
            out = np.empty(rows.shape[0] * (src.shape[0] * self.max_cell + 1), dtype=np.uint8)
        gather = (src, np.asarray(scale, dtype=np.float64), np.asarray(offset, dtype=np.float64))
        n = _format_gather(rows, extra, gather, self.cells, out)
        return out[:n]

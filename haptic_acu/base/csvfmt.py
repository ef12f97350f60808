"""Fast, deterministic CSV formatting of numeric sample blocks (numba).

Python's per-value string formatting was most of a headless replay's time (16,000 rows x 25
columns). :func:`format_rows` writes a whole block in one compiled call: each column is either a
fixed-decimal number (rounded half away from zero at its number of decimals, never "-0.000") or a
category (an integer code looked up in a table of names). Identical values give identical bytes.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

FIXED, CATEGORY = 0, 1


_U10 = np.uint64(10)
_POW10 = np.array([10 ** k for k in range(20)], dtype=np.uint64)


@nb.njit(cache=True, nogil=True, inline="always")
def _put_fixed(out, pos, v, d, p10f):
    """``v`` (finite) rounded half away from zero to ``d`` decimals (``p10f`` = 10.0**d), without a
    negative zero; returns the new position. Its digits are written from the last one back, by
    unsigned division by the constant 10 (a multiply, not a division, once compiled)."""
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


@nb.njit(cache=True, nogil=True)
def _format_rows(values, kinds, decimals, table, table_len, table_base, out):
    n, m = values.shape
    pos = 0
    p10f = np.empty(m)
    for c in range(m):
        p10f[c] = 10.0 ** decimals[c]
    for i in range(n):
        for c in range(m):
            if c > 0:
                out[pos] = 44  # ','
                pos += 1
            v = values[i, c]
            if kinds[c] == 1:
                if math.isfinite(v) and v >= 0.0:  # else an empty cell
                    t = table_base[c] + int(v)
                    for b in range(table_len[t]):
                        out[pos] = table[t, b]
                        pos += 1
            elif not math.isfinite(v):
                out[pos] = 110  # "nan"
                out[pos + 1] = 97
                out[pos + 2] = 110
                pos += 3
            else:
                pos = _put_fixed(out, pos, v, decimals[c], p10f[c])
        out[pos] = 10  # '\n'
        pos += 1
    return pos


@nb.njit(cache=True, nogil=True)
def _format_gather(rows, extra, src, scale, offset, kinds, decimals, table, table_len, table_base, out):
    """:func:`_format_rows` of the columns ``v * scale[c] + offset[c]`` (``offset`` added only where
    it is not zero), ``v`` from ``rows[:, src[c]]``, or from ``extra[:, src[c] - rows.shape[1]]``
    where ``src[c]`` is past ``rows``' columns."""
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
            if kinds[c] == 1:
                if math.isfinite(v) and v >= 0.0:  # else an empty cell
                    t = table_base[c] + int(v)
                    for b in range(table_len[t]):
                        out[pos] = table[t, b]
                        pos += 1
            elif not math.isfinite(v):
                out[pos] = 110  # "nan"
                out[pos + 1] = 97
                out[pos + 2] = 110
                pos += 3
            else:
                pos = _put_fixed(out, pos, v, decimals[c], p10f[c])
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

    def format(self, values: np.ndarray) -> bytes:
        values = np.ascontiguousarray(values, dtype=np.float64)
        out = np.empty(values.shape[0] * (values.shape[1] * self.max_cell + 1), dtype=np.uint8)
        n = _format_rows(values, self.kinds, self.decimals, self.table, self.table_len, self.table_base, out)
        return out[:n].tobytes()

    def format_gather(self, rows: np.ndarray, extra: np.ndarray, src, scale, offset) -> bytes:
        """Lines of the columns taken from ``rows`` (k, w) and ``extra`` (k, e) without building
        them first: column ``c`` is ``rows[:, src[c]]`` (``extra[:, src[c] - w]`` past ``rows``'
        columns) times ``scale[c]``, plus ``offset[c]`` where that is not zero; then as
        :meth:`format` (the same bytes as :meth:`format` on those columns)."""
        rows = np.ascontiguousarray(rows, dtype=np.float64)
        extra = np.ascontiguousarray(extra, dtype=np.float64).reshape(rows.shape[0], -1)
        src = np.asarray(src, dtype=np.int64)
        if src.shape[0] != self.kinds.shape[0]:
            raise ValueError(f"{src.shape[0]} source columns for {self.kinds.shape[0]} formatted ones")
        out = np.empty(rows.shape[0] * (src.shape[0] * self.max_cell + 1), dtype=np.uint8)
        n = _format_gather(rows, extra, src, np.asarray(scale, dtype=np.float64), np.asarray(offset, dtype=np.float64),
                           self.kinds, self.decimals, self.table, self.table_len, self.table_base, out)
        return out[:n].tobytes()

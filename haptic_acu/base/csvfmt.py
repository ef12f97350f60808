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


@nb.njit(cache=True, nogil=True)
def _put_uint(out, pos, v):
    """Write the decimal digits of the non-negative int64 ``v``; return the new position."""
    if v == 0:
        out[pos] = 48
        return pos + 1
    start = pos
    while v > 0:
        out[pos] = 48 + v % 10
        v //= 10
        pos += 1
    # reverse in place
    i = start
    j = pos - 1
    while i < j:
        t = out[i]
        out[i] = out[j]
        out[j] = t
        i += 1
        j -= 1
    return pos


@nb.njit(cache=True, nogil=True)
def _format_rows(values, kinds, decimals, table, table_len, table_base, out):
    n, m = values.shape
    pos = 0
    for i in range(n):
        for c in range(m):
            if c > 0:
                out[pos] = 44  # ','
                pos += 1
            v = values[i, c]
            if kinds[c] == 1:
                if not math.isfinite(v):
                    continue  # empty cell
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
            scale = 10.0 ** d
            r = math.floor(abs(v) * scale + 0.5)
            iv = np.int64(r)
            if iv != 0 and v < 0:
                out[pos] = 45  # '-'
                pos += 1
            if d == 0:
                pos = _put_uint(out, pos, iv)
                continue
            p10 = np.int64(1)
            for _ in range(d):
                p10 *= 10
            pos = _put_uint(out, pos, iv // p10)
            out[pos] = 46  # '.'
            pos += 1
            frac = iv % p10
            div = p10 // 10
            for _ in range(d):
                out[pos] = 48 + (frac // div) % 10
                div //= 10
                pos += 1
        out[pos] = 10  # '\n'
        pos += 1
    return pos


class RowFormatter:
    """Formats (k, m) float blocks as CSV lines. ``columns`` is a list of ``("fixed", decimals)`` or
    ``("category", names)``; a category cell holds an integer code indexing ``names`` (NaN: empty)."""

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

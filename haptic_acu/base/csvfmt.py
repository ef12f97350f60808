"""Fast, deterministic CSV formatting of numeric sample blocks (numba).

A headless replay writes one row per servo tick (16,000 rows of some 40 columns for the default
insertion), too many for Python's per-value formatting. :class:`RowFormatter` writes a whole block
in one compiled call: each column is either a fixed-decimal number (rounded half away from zero at
its number of decimals, never "-0.000") or a category (an integer code looked up in a table of
names). Identical values give identical bytes.

The compiled pass writes eight bytes at a time (unaligned little-endian stores, the byte order of
x86-64 and arm64; the output buffer has eight bytes to spare): a number's digits are made eight at
once in a 64-bit word (:func:`_digits8`), and a cell whose source value equals the row above's is
that row's cell again, copied with its neighbours in one run (most of a replay's cells: zeros, the
states, constants over the run).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

FIXED, CATEGORY = 0, 1
SPARE = 8  # bytes past the output a store may touch (then overwritten or cut)

_U = np.uint64  # numba mixing uint64 with int64 gives float64: every constant of the digit words is uint64
_U10 = _U(10)
_POW10 = np.array([10 ** k for k in range(20)], dtype=np.uint64)
_E1, _E2, _E3, _E4, _E5, _E6, _E7, _E8 = (_U(10 ** k) for k in range(1, 9))
_B8, _B16, _B32 = _U(8), _U(16), _U(32)
_DOT = _U(ord("."))
_NAN = _U(int.from_bytes(b"nan", "little"))
_FAST = 1e16  # below it (at most 7 decimals) a fixed cell's integer is written by _put_fixed


@intrinsic
def _store8(typingctx, arr, pos, word):
    """Store the uint64 ``word`` at ``arr``'s byte ``pos`` (a uint8 array; 8 bytes, unaligned,
    little-endian: the word's low byte first), no bounds check."""
    sig = types.void(arr, pos, word)

    def codegen(context, builder, signature, args):
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        ptr = builder.bitcast(builder.gep(data, [args[1]]), ir.IntType(64).as_pointer())
        builder.store(args[2], ptr, align=1)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def _load8(typingctx, arr, pos):
    """The 8 bytes at ``arr``'s byte ``pos`` (a contiguous uint8 array) as a uint64, as :func:`_store8`
    stores them; no bounds check."""
    sig = types.uint64(arr, pos)

    def codegen(context, builder, signature, args):
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        ptr = builder.bitcast(builder.gep(data, [args[1]]), ir.IntType(64).as_pointer())
        return builder.load(ptr, align=1)

    return sig, codegen


@nb.njit(cache=True, nogil=True, inline="always")
def _copy(out, dst, src, n):
    """``out[dst:dst + n] = out[src:src + n]`` eight bytes at a time, for ``src + n <= dst`` (a copy
    from earlier output; it may write up to 7 bytes past ``dst + n``)."""
    for b in range(0, n, 8):
        _store8(out, dst + b, _load8(out, src + b))


@nb.njit(cache=True, nogil=True, inline="always")
def _digits8(x):
    """``x`` (uint64 below 10**8) as 8 ASCII digits with leading zeros, its first digit in the low
    byte (the first in memory): the two halves of 4 digits in 32-bit lanes, then each lane's two
    pairs in 16-bit lanes, then each pair's digits in bytes, by multiply-and-shift divisions
    (``(v * 10486) >> 20`` is ``v // 100`` below 10**4, ``(v * 103) >> 10`` is ``v // 10`` below 100)."""
    hi = x // _E4
    v = hi | ((x - hi * _E4) << _B32)
    q = ((v * _U(10486)) >> _U(20)) & _U(0x0000007F0000007F)
    v = q | ((v - q * _E2) << _B16)
    q = ((v * _U(103)) >> _U(10)) & _U(0x000F000F000F000F)
    v = q | ((v - q * _U10) << _B8)
    return v + _U(0x3030303030303030)


@nb.njit(cache=True, nogil=True, inline="always")
def _n_digits8(u):
    """The number of decimal digits of ``u`` (uint64 below 10**8; 1 for 0), by comparisons."""
    if u < _E4:
        if u < _E2:
            return 1 if u < _E1 else 2
        return 3 if u < _E3 else 4
    if u < _E6:
        return 5 if u < _E5 else 6
    return 7 if u < _E7 else 8


@nb.njit(cache=True, nogil=True, inline="always")
def _put_fixed(out, pos, u, d):
    """The digits of ``u`` (uint64 below 10**16) with a point before its last ``d`` (at most 7), a
    "0" before the point at least, at ``pos``; returns the new position. The integer part is stored
    first (the low digit word's extra bytes overwritten by the point and decimals after it)."""
    if u < _E8:
        lo = _digits8(u)
        nd = max(_n_digits8(u), d + 1)
        _store8(out, pos, lo >> (_B8 * _U(8 - nd)))
    else:
        hi = u // _E8
        nh = _n_digits8(hi)
        lo = _digits8(u - hi * _E8)
        _store8(out, pos, _digits8(hi) >> (_B8 * _U(8 - nh)))
        _store8(out, pos + nh, lo)
        nd = nh + 8
    pos += nd - d
    if d > 0:
        _store8(out, pos, _DOT | ((lo >> (_B8 * _U(8 - d))) << _B8))
        pos += d + 1
    return pos


@nb.njit(cache=True, nogil=True)
def _put_fixed_wide(out, pos, v, d, p10f):
    """``v`` (finite) rounded half away from zero to ``d`` decimals (``p10f`` = 10.0**d), without a
    negative zero, for any magnitude (at most 19 digits), a digit per division by 10; returns the
    new position. :func:`_format_gather` writes the usual magnitudes by :func:`_put_fixed`, the
    same bytes."""
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


class Cells(NamedTuple):
    """How each column is written (the compiled passes' view of a :class:`RowFormatter`): ``kinds``
    (FIXED or CATEGORY), ``decimals``, and the category names' bytes (``table`` rows of
    ``table_len`` bytes, zero-padded to whole 8-byte words; a column's first name at row
    ``table_base``)."""
    kinds: np.ndarray
    decimals: np.ndarray
    table: np.ndarray
    table_len: np.ndarray
    table_base: np.ndarray


@nb.njit(cache=True, nogil=True)
def _format_gather(rows, extra, gather, cells, out):
    """CSV lines of the columns ``v * scale[c] + offset[c]`` (``gather``: src, scale, offset;
    ``offset`` added only where it is not zero), ``v`` from ``rows[:, src[c]]``, or from
    ``extra[:, src[c] - rows.shape[1]]`` where ``src[c]`` is past ``rows``' columns, into ``out``
    (with :data:`SPARE` bytes to spare); returns the number of bytes.

    A fixed cell is the integer floor(|v| * 10.0**d + 0.5) with a point before its last d digits
    (a "0" before the point at least, a '-' for v < 0 unless that integer is 0); "nan" for a value
    that is not finite. Below 10**16 and at most 7 decimals that integer is the (positive) sum's
    truncation, written by :func:`_put_fixed`; else by :func:`_put_fixed_wide`. A category cell is
    the name of the code ``int(v)``, empty for a negative or non-finite code.

    A cell whose ``v`` equals (``==``) the row above's is that row's cell, bytes and separator:
    equal values give equal cells (0.0 and -0.0 too: neither writes a sign), and a NaN, never equal,
    is written anew. Such cells next to each other are one run, copied at the next written cell or
    the line's end; ``start`` and ``size`` hold where each cell of the line above is."""
    src, scale, offset = gather
    kinds, decimals, table, table_len, table_base = cells
    n = rows.shape[0]
    w = rows.shape[1]
    m = src.shape[0]
    width = table.shape[1]
    p10f = np.empty(m)
    fast = np.empty(m)  # a fixed column's bound for _put_fixed (0: a category or many decimals)
    for c in range(m):
        p10f[c] = 10.0 ** decimals[c]
        fast[c] = _FAST if kinds[c] == FIXED and decimals[c] <= 7 else 0.0
    start = np.zeros(m, dtype=np.int64)
    size = np.zeros(m, dtype=np.int64)
    pos = 0
    run = 0  # the bytes of the pending run of cells repeated from the row above, from run_src
    run_src = 0
    for i in range(n):
        for c in range(m):
            k = src[c]
            v = rows[i, k] if k < w else extra[i, k - w]
            if i > 0 and v == (rows[i - 1, k] if k < w else extra[i - 1, k - w]):
                if run == 0:
                    run_src = start[c]
                start[c] = pos + run
                run += size[c]
                continue
            if run > 0:
                _copy(out, pos, run_src, run)
                pos += run
                run = 0
            start[c] = pos
            v = v * scale[c]
            if offset[c] != 0.0:
                v = v + offset[c]
            x = abs(v) * p10f[c] + 0.5
            if x < fast[c]:  # a usual number (a NaN is not)
                u = _U(x)
                out[pos] = 45  # '-', kept for a negative nonzero
                if v < 0 and u != 0:
                    pos += 1
                pos = _put_fixed(out, pos, u, decimals[c])
            elif kinds[c] == CATEGORY:
                if math.isfinite(v) and v >= 0.0:  # else an empty cell
                    t = table_base[c] + int(v)
                    _store8(out, pos, _load8(table, t * width))
                    for b in range(8, table_len[t], 8):
                        _store8(out, pos + b, _load8(table, t * width + b))
                    pos += table_len[t]
            elif not math.isfinite(v):
                _store8(out, pos, _NAN)
                pos += 3
            else:
                pos = _put_fixed_wide(out, pos, v, decimals[c], p10f[c])
            out[pos] = 44 if c < m - 1 else 10  # ',' or '\n'
            pos += 1
            size[c] = pos - start[c]
        if run > 0:
            _copy(out, pos, run_src, run)
            pos += run
            run = 0
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
        width = max(len(n) for n in names)
        self.table = np.zeros((len(names), -(-max(width, 1) // 8) * 8), dtype=np.uint8)  # whole words
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
        need = len(rows) * (len(src) * self.max_cell + 1) + SPARE
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
            out = np.empty(rows.shape[0] * (src.shape[0] * self.max_cell + 1) + SPARE, dtype=np.uint8)
        gather = (src, np.asarray(scale, dtype=np.float64), np.asarray(offset, dtype=np.float64))
        n = _format_gather(rows, extra, gather, self.cells, out)
        return out[:n]

"""One insertion's metrics streamed in bounded memory: :class:`InsertionStream`.

:func:`haptic_acu.analysis.metrics.insertion_metrics` needs the insertion's rows; a 10-minute hold in muscle
is 600,000 of them. This module computes the same dict from the rows as they arrive, keeping only:

* running extremes and counts (entry, peaks per layer and of |F|, the tip's depth, lateral ticks,
  the first tick at the target's lower bound, the deepest point and so the insertion direction u);
* the depth's *records* (ticks deeper than every earlier one) not shallower than 90% of the
  deepest so far: the insertion speed's end tick and the lift-thrust start are among them;
* the reversals of the roll (twirling) and of the continuous depth (lift-thrust strokes) as found
  by :func:`haptic_acu.analysis.technique.turning_points` run sample by sample (:func:`_zz_step`,
  in one compiled pass over each block), each stroke's sums (moving samples, speed, force
  vector: the resistance is linear in u);
* the troughs of the continuous depth with their prominences, found sample by sample with a stack
  of open peaks (:class:`TroughScan`, the result of :func:`haptic_acu.analysis.metrics.find_troughs`);
  troughs before the lift-thrust start are dropped at the end (the start is a depth record, before
  which every sample is shallower, so it changes no later trough's prominence);
* the withdrawal window's peak and mean resistances (only with a reference replay).

Memory is bounded by the number of lift-thrust and twirl cycles, not the insertion's length. One
quantity needs the final insertion direction u before the rows are seen: the continuous depth adds
back the depth frame's steps at the fat and muscle punctures, each the tip's advance along u on
that tick. So the first :data:`BUFFER_ROWS` rows (20 s at 1 kHz, ~1.6 MB) are kept; an insertion
that ends within them is measured with its final u (exactly as :func:`insertion_metrics`); a
longer one fixes u for the steps at that point. Its continuous depth then differs from the batch
one only if the tip later goes deeper than ever before (changing u), by at most the step ticks'
one-tick advance times the change of u: :attr:`InsertionStream.step_error_bound_m` (e.g. 10 um x
0.05 rad = 0.5 um, below the metrics' 1 um rounding). Everything else is exact up to the order of
floating-point sums (means of strokes and of the grasp window: relative 1e-13, far below the
rounding of the outputs); tests/test_metrics_stream.py compares with the batch functions.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from .common import dot3
from .common import C_CLAMPED, C_DEPTH, C_F, C_LAT, C_LAYER, C_LAYER_F, C_PUNCT, C_ROLL, C_T, C_TICK, C_TORQUE, C_X
from .technique import DEPTH_MIN_STROKE_MM, MIN_SPEED_MM_S, ROLL_MIN_SWING_DEG, classify

_BLOCK_COLS = np.array([C_T, C_DEPTH, C_X, C_X + 1, C_X + 2, C_F, C_F + 1, C_F + 2, C_PUNCT])
BUFFER_ROWS = 20_000  # rows kept before the continuous depth's steps are fixed (module docstring)
PLATEAU_T_CAP = 4096  # times kept for the middle of a flat trough (beyond: interpolated, <1 tick off)

NONE, NEW, REV = 0, 1, 2


# the reversal rule's state: [d (the direction, 0 before the first swing), xhi, xlo, started]
ZZ_D, ZZ_HI, ZZ_LO, ZZ_STARTED = 0, 1, 2, 3


@nb.njit(cache=True, nogil=True, inline="always")
def _zz_step(zz, ms, v):
    """:func:`haptic_acu.analysis.technique.turning_points` one sample ``v`` at a time (state ``zz``,
    ZZ_*; minimum swing ``ms``): NEW when the pending reversal (the running extreme, once the signal
    has moved ``ms`` from its start) moves to this sample, REV when the pending one is confirmed
    (this sample becomes the next pending one), else NONE."""
    if zz[ZZ_STARTED] == 0.0:
        zz[ZZ_STARTED] = 1.0
        zz[ZZ_HI] = v
        zz[ZZ_LO] = v
        return NONE
    d = zz[ZZ_D]
    if d == 0.0:
        if v > zz[ZZ_HI]:
            zz[ZZ_HI] = v
        if v < zz[ZZ_LO]:
            zz[ZZ_LO] = v
        if v - zz[ZZ_LO] >= ms:
            zz[ZZ_D] = 1.0
            zz[ZZ_HI] = v
            return NEW
        if zz[ZZ_HI] - v >= ms:
            zz[ZZ_D] = -1.0
            zz[ZZ_LO] = v
            return NEW
        return NONE
    if d > 0.0:
        if v > zz[ZZ_HI]:
            zz[ZZ_HI] = v
            return NEW
        if zz[ZZ_HI] - v >= ms:
            zz[ZZ_D] = -1.0
            zz[ZZ_LO] = v
            return REV
        return NONE
    if v < zz[ZZ_LO]:
        zz[ZZ_LO] = v
        return NEW
    if v - zz[ZZ_LO] >= ms:
        zz[ZZ_D] = 1.0
        zz[ZZ_HI] = v
        return REV
    return NONE


@nb.njit(cache=True, nogil=True, inline="always")
def _block_max(rows, c, absolute):
    """numpy's ``max`` of column ``c`` of ``rows`` (of its absolute values with ``absolute``): NaN if
    any value is NaN."""
    m = -np.inf
    for i in range(rows.shape[0]):
        v = abs(rows[i, c]) if absolute else rows[i, c]
        if v != v:
            return v
        if v > m:
            m = v
    return m


# _Twirl's running values: the first and last roll, the total rotation (sum of |roll increments|),
# the peak |torque|, and whether a block was seen
TW_FIRST, TW_LAST, TW_TOTAL, TW_PEAK, TW_SEEN = 0, 1, 2, 3, 4


@nb.njit(cache=True, nogil=True)
def _twirl_pass(zz, acc, rows, cand, revs):
    """:class:`_Twirl` over a block of rows (roll, t and torque from their columns): the running
    values ``acc`` (TW_*), the reversals (state ``zz``, minimum swing ROLL_MIN_SWING_DEG) of the
    samples where the roll moved (a repeated value never changes a zigzag) and the first one;
    ``cand`` (roll, t, cumulative rotation) the pending reversal, confirmed ones into ``revs`` (k,
    3). The cumulative rotation at a sample is the total before the block plus the block's running
    sum (numpy's ``total + cumsum(steps)``). Returns the reversals' count."""
    k = rows.shape[0]
    peak = _block_max(rows, C_TORQUE, True)
    if peak > acc[TW_PEAK]:  # Python's max(peak so far, the block's): a NaN block is passed over
        acc[TW_PEAK] = peak
    if acc[TW_SEEN] == 0.0:
        acc[TW_FIRST] = rows[0, C_ROLL]
        acc[TW_LAST] = rows[0, C_ROLL]
        acc[TW_SEEN] = 1.0
    prev = acc[TW_LAST]
    total = acc[TW_TOTAL]
    run = 0.0
    cum = total
    n = 0
    for j in range(k):
        v = rows[j, C_ROLL]
        step = abs(v - prev)
        prev = v
        run += step
        cum = total + run
        if step == 0.0 and (j > 0 or zz[ZZ_STARTED] != 0.0):
            continue
        ev = _zz_step(zz, ROLL_MIN_SWING_DEG, v)
        if ev == REV:
            revs[n, 0] = cand[0]
            revs[n, 1] = cand[1]
            revs[n, 2] = cand[2]
            n += 1
        if ev != NONE:
            cand[0] = v
            cand[1] = rows[j, C_T]
            cand[2] = cum
    acc[TW_TOTAL] = cum
    acc[TW_LAST] = prev
    return n


# _Strokes' pending reversal (cand) and last confirmed one (last): [set, index, dcm, P (20), Q (20)];
# a withdrawal window: [set, start dcm, max res, max ref, sum res, sum ref, n, closed]
NS = 20
C_SET, C_IDX, C_DCM, C_P = 0, 1, 2, 3
C_Q = C_P + NS


@nb.njit(cache=True, nogil=True, inline="always")
def _window_add(w, r, q, v):
    if w[0] != 0.0 and w[7] == 0.0:
        if r > w[2]:
            w[2] = r
        if q > w[3]:
            w[3] = q
        w[4] += r
        w[5] += q
        w[6] += 1.0
        w[7] = 1.0 if v <= 0.0 else 0.0


@nb.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _speeds(samples, k, grad):
    """numpy.gradient's uniform and general formulas at sample ``k`` of ``samples`` (columns t, dc,
    dcm): the speed of dcm, as :meth:`InsertionStream._process` states them (the same operations
    in the same order; a missing neighbour is NaN). ``grad``: the samples to do (m), the sample
    before the first (t, dcm; NaN if none) and the first tick interval (NaN if none)."""
    m, left_t, left_f, dx0 = grad
    m_t = samples[k, 0]
    m_f = samples[k, 2]
    l_t = samples[k - 1, 0] if k > 0 else left_t
    l_f = samples[k - 1, 2] if k > 0 else left_f
    r_t = samples[k + 1, 0] if k + 1 < samples.shape[0] else np.nan
    r_f = samples[k + 1, 2] if k + 1 < samples.shape[0] else np.nan
    dx1 = m_t - l_t
    dx2 = r_t - m_t
    ca = -(dx2) / (dx1 * (dx1 + dx2))
    cb = (dx2 - dx1) / (dx1 * dx2)
    cc = dx1 / (dx2 * (dx1 + dx2))
    return (r_f - l_f) / (2. * dx0), ca * l_f + cb * m_f + cc * r_f


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _strokes_pass(rules, has_ref, i0, samples, grad, carried, out_sgn, out_sums):
    """:class:`_Strokes`' per-sample pass over a block: the running prefix sums (``carry``, NS) of
    the per-sample contributions (for numpy.gradient's uniform and general formulas, :func:`_speeds`,
    each sign: moving, speed, force x, y, z), the depth's reversals (``zz``), each confirmed stroke's
    sign and sums (the pending reversal's P minus the last one's Q) into ``out_sgn``, ``out_sums``,
    and the withdrawal windows (with ``has_ref``). Returns the strokes' count."""
    # from sample i0, the first m (grad[0]) rows of samples: columns t, dc, dcm, f (3), res, rres;
    # rules: the minimum swing and speed; carried (to the next block): zz, carry, cand, last,
    # win_cand, win_conf
    ms, min_speed = rules
    zz, carry, cand, last, win_cand, win_conf = carried
    n = 0
    q_row = np.empty(NS)
    for k in range(grad[0]):
        for c in range(NS):
            q_row[c] = carry[c]
        v_uni, v_non = _speeds(samples, k, grad)
        col = 0
        for form in range(2):
            vel = v_uni if form == 0 else v_non
            for sg in range(2):
                sv = (1.0 if sg == 0 else -1.0) * vel
                moving = sv > min_speed
                carry[col] = carry[col] + (1.0 if moving else 0.0)
                carry[col + 1] = carry[col + 1] + (sv if moving else 0.0)
                for j in range(3):
                    carry[col + 2 + j] = carry[col + 2 + j] + (samples[k, 3 + j] if moving else 0.0)
                col += 5
        v = samples[k, 2]
        ev = _zz_step(zz, ms, v)
        if ev == REV:
            if last[C_SET] != 0.0:
                out_sgn[n] = 1.0 if cand[C_DCM] > last[C_DCM] else -1.0
                for c in range(NS):
                    out_sums[n, c] = cand[C_P + c] - last[C_Q + c]
                n += 1
            for c in range(last.shape[0]):
                last[c] = cand[c]
            if has_ref:
                for c in range(win_conf.shape[0]):
                    win_conf[c] = win_cand[c]
        if ev != NONE:
            cand[C_SET] = 1.0
            cand[C_IDX] = i0 + k
            cand[C_DCM] = v
            for c in range(NS):
                cand[C_P + c] = carry[c]
                cand[C_Q + c] = q_row[c]
            if has_ref:
                win_cand[0] = 1.0
                win_cand[1] = v
                win_cand[2] = -np.inf
                win_cand[3] = -np.inf
                win_cand[4] = 0.0
                win_cand[5] = 0.0
                win_cand[6] = 0.0
                win_cand[7] = 0.0
        if has_ref:
            _window_add(win_cand, samples[k, 6], samples[k, 7], v)
            _window_add(win_conf, samples[k, 6], samples[k, 7], v)
    return n


class TroughScan:
    """Troughs of a depth signal with their prominences (:func:`haptic_acu.analysis.metrics.find_troughs`,
    i.e. scipy's peak rules on minus the depth), sample by sample. Open peaks (no strictly higher
    sample after them yet) sit on a stack, each with its left base and the minimum of the samples
    from it to the next open peak; a peak is closed, and its prominence known, at the first
    strictly higher sample or at :meth:`finish`. ``found``: (index, t, prominence) of those with at
    least ``prominence``. Each block is one compiled pass (:func:`_trough_pass`)."""

    def __init__(self, prominence: float):
        self.prom = float(prominence)
        # the stack's rows: x, index, t, left base, segment minimum; row 0 a sentinel above every sample
        self.stack = np.empty((64, 5))
        self.stack[0] = (math.inf, -1, 0.0, math.inf, math.inf)
        self.pt = np.empty(PLATEAU_T_CAP)  # the times of the current plateau after a rise (its first ones)
        # [stack size, has prev, prev, rising, plateau start, plateau times kept, last plateau time]
        self.state = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
        self.found: list[tuple[int, float, float]] = []

    def feed(self, i0: int, x, t) -> None:
        """Samples ``x`` (minus the depth) at times ``t``; ``i0`` the first one's index."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        t = np.ascontiguousarray(t, dtype=np.float64)
        k = x.shape[0]
        if not k:
            return
        need = int(self.state[0]) + k + 1  # a sample pushes at most one peak
        if need > self.stack.shape[0]:
            grown = np.empty((max(need, 2 * self.stack.shape[0]), 5))
            grown[:int(self.state[0])] = self.stack[:int(self.state[0])]
            self.stack = grown
        idx = np.empty(need, np.int64)
        tf = np.empty((need, 2))
        n = _trough_pass((self.stack, self.pt, self.state), self.prom, int(i0), x, t, idx, tf)
        self.found.extend(zip(idx[:n].tolist(), tf[:n, 0].tolist(), tf[:n, 1].tolist()))

    def _emit(self, e, right: float) -> None:
        p = e[0] - max(e[3], right)
        if p >= self.prom:
            self.found.append((int(e[1]), float(e[2]), float(p)))

    def finish(self) -> list[tuple[int, float, float]]:
        acc = math.inf
        size = int(self.state[0])
        while size > 1:
            size -= 1
            e = self.stack[size].tolist()
            acc = min(acc, e[4])
            self._emit(e, acc)
        self.state[0] = size
        return sorted(self.found)


@nb.njit(cache=True, nogil=True)
def _trough_pass(scan, prom, i0, x, t, out_idx, out_tp):
    """:class:`TroughScan` over one block (its stack ``st``, plateau times ``pt`` and ``state`` carried
    across blocks); the troughs closed in it, in order, into ``out_idx`` (index) and ``out_tp`` (t,
    prominence). Returns their count."""
    st, pt, state = scan
    size = int(state[0])
    has_prev = state[1] != 0.0
    prev = state[2]
    rising = state[3] != 0.0
    ps = int(state[4])
    npt = int(state[5])
    pt_last = state[6]
    n = 0
    for q in range(x.shape[0]):
        v = x[q]
        tk = t[q]
        i = i0 + q
        if has_prev:
            if v > prev:
                rising = True
                ps = i
                pt[0] = tk
                npt = 1
                pt_last = tk
            elif v < prev:
                if rising:
                    c = (ps + i - 1) // 2
                    kk = c - ps  # the middle of the plateau: its time
                    if kk < npt:
                        tc = pt[kk]
                    else:  # a very long flat trough: linear in the index
                        t0 = pt[0]
                        tc = t0 + (pt_last - t0) * kk / (i - 1 - ps)
                    acc = np.inf  # push (prev, c, tc): equal peaks are not strictly higher
                    j = size - 1
                    while st[j, 0] <= prev:
                        if st[j, 4] < acc:
                            acc = st[j, 4]
                        j -= 1
                    if st[j, 4] < acc:
                        acc = st[j, 4]
                    st[size, 0] = prev
                    st[size, 1] = c
                    st[size, 2] = tc
                    st[size, 3] = acc
                    st[size, 4] = prev
                    size += 1
                    rising = False
            elif rising:
                if npt < pt.shape[0]:
                    pt[npt] = tk
                    npt += 1
                pt_last = tk
        if st[size - 1, 0] < v:
            acc = np.inf
            while st[size - 1, 0] < v:
                size -= 1
                if st[size, 4] < acc:
                    acc = st[size, 4]
                left = st[size, 3]
                p = st[size, 0] - (acc if acc > left else left)
                if p >= prom:
                    out_idx[n] = np.int64(st[size, 1])
                    out_tp[n, 0] = st[size, 2]
                    out_tp[n, 1] = p
                    n += 1
            if acc < st[size - 1, 4]:
                st[size - 1, 4] = acc
        if v < st[size - 1, 4]:
            st[size - 1, 4] = v
        prev = v
        has_prev = True
    state[0] = size
    state[1] = 1.0 if has_prev else 0.0
    state[2] = prev
    state[3] = 1.0 if rising else 0.0
    state[4] = ps
    state[5] = npt
    state[6] = pt_last
    return n


class _Twirl:
    """:func:`haptic_acu.analysis.technique.twirl_metrics` on a streamed roll: its reversals (roll, t and the
    cumulative |roll increments| there), the first and last roll, the total rotation, peak torque."""

    def __init__(self):
        self.zz = np.zeros(4)  # the reversal rule's state (_zz_step, ZZ_*), minimum swing ROLL_MIN_SWING_DEG
        self.revs: list[tuple[float, float, float]] = []
        self.cand = np.zeros(3)  # the pending reversal: roll, t, cumulative rotation
        self.acc = np.zeros(5)  # first and last roll, total rotation, peak torque, seen (TW_*)

    def feed(self, rows: np.ndarray) -> None:
        """Rows (k >= 1, NCOL; C-contiguous float64): their roll, t and torque."""
        revs = np.empty((len(rows), 3))
        n = _twirl_pass(self.zz, self.acc, rows, self.cand, revs)
        self.revs.extend(map(tuple, revs[:n].tolist()))

    def result(self) -> dict:
        from .technique import _r
        n = len(self.revs)
        swing = freq = speed = None
        if n >= 2:
            r = np.array([x[0] for x in self.revs])
            swing = float(np.abs(np.diff(r)).mean())
            span = float(self.revs[-1][1] - self.revs[0][1])
            if span > 0:
                freq = (n - 1) / 2.0 / span
                speed = (self.revs[-1][2] - self.revs[0][2]) / span
        return {
            "cycles": (n + 1) // 2,
            "reversals": n,
            "swing_deg": _r(swing, 2),
            "frequency_hz": _r(freq, 3),
            "mean_speed_deg_s": _r(speed, 1),
            "net_rotation_deg": _r(self.acc[TW_LAST] - self.acc[TW_FIRST], 2),
            "total_rotation_deg": _r(self.acc[TW_TOTAL], 2),
            "peak_torque_nmm": _r(self.acc[TW_PEAK], 4),
        }


class _Strokes:
    """The lift-thrust strokes of :func:`haptic_acu.analysis.technique.stroke_forces` and the withdrawal window
    of :func:`~haptic_acu.analysis.technique.grasp_felt`, on the streamed continuous depth (mm).

    Per sample, for both signs of a stroke and both of numpy.gradient's formulas (uniform spacing
    or not: known only at the end), the moving-sample count, speed sum and force-vector sum are
    summed into running prefixes; a stroke between reversals a and b is then P(b) - Q(a) (Q: the
    prefix before a sample)."""

    def __init__(self, has_ref: bool):
        self.zz = np.zeros(4)  # the reversal rule's state (_zz_step, ZZ_*), minimum swing DEPTH_MIN_STROKE_MM
        self.carry = np.zeros(NS)
        self.cand = np.zeros(C_Q + NS)  # the pending reversal (C_*: set, index, dcm, P row, Q row)
        self.last_rev = np.zeros(C_Q + NS)  # the last confirmed one
        self.strokes: list[tuple[float, np.ndarray]] = []  # (sign, its 10 sums: 5 per formula)
        self.has_ref = has_ref
        # the withdrawal windows [set, start dcm, max res, max ref, sum res, sum ref, n, closed]
        self.win_cand = np.zeros(8)
        self.win_conf = np.zeros(8)
        self.last_dcm = None

    def feed(self, i0, samples, grad) -> None:
        """Samples from index ``i0``: the first ``grad[0]`` rows of ``samples`` (float64, columns t,
        dc, dcm, f (3), res, rres; the row after them, if any, their right neighbour); ``grad`` as
        :func:`_speeds` takes it."""
        k = grad[0]
        if not k:
            return
        sgn = np.empty(k)
        sums = np.empty((k, NS))
        carried = (self.zz, self.carry, self.cand, self.last_rev, self.win_cand, self.win_conf)
        n = _strokes_pass((float(DEPTH_MIN_STROKE_MM), float(MIN_SPEED_MM_S)), self.has_ref, int(i0),
                          np.ascontiguousarray(samples, dtype=np.float64), grad, carried, sgn, sums)
        self.strokes.extend(zip(sgn[:n].tolist(), sums[:n].copy()))
        self.last_dcm = float(samples[k - 1, 2])

    def stroke_result(self, uniform: bool, u: np.ndarray) -> dict:
        from .technique import summarise_strokes
        off = 0 if uniform else 10
        per = []
        for sgn, sums in self.strokes:
            j = off + (0 if sgn > 0 else 5)
            n = sums[j]
            if n <= 0:
                continue
            fsum = sums[j + 2:j + 5]
            res = sgn * -float(fsum[0] * u[0] + fsum[1] * u[1] + fsum[2] * u[2]) / n
            per.append((sgn, float(sums[j + 1]) / n, res))
        return summarise_strokes(per)

    def grasp_result(self) -> dict:
        from .technique import _r
        w = self.win_conf
        if not self.last_rev[C_SET] or not w[0] or self.last_dcm >= self.last_rev[C_DCM]:
            return {"peak_ratio": None, "mean_ratio": None, "peak_n": None, "reference_peak_n": None}
        peak, ref_peak = float(w[2]), float(w[3])
        mean, ref_mean = float(w[4]) / int(w[6]), float(w[5]) / int(w[6])
        return {
            "peak_ratio": _r(peak / ref_peak, 3) if ref_peak > 0 else None,
            "mean_ratio": _r(mean / ref_mean, 3) if ref_mean > 0 else None,
            "peak_n": _r(peak, 4),
            "reference_peak_n": _r(ref_peak, 4),
        }


# _Press's peaks: per layer (skin, fat, muscle) the largest |layer force|, then the largest |F| and tip depth
P_LAYER, P_F, P_TIP = 0, 3, 4


@nb.njit(cache=True, nogil=True, inline="always")
def nan_max(x):
    """numpy's ``max`` of ``x`` (k >= 1): NaN if any value is NaN."""
    m = -np.inf
    for i in range(x.shape[0]):
        if x[i] != x[i]:
            return x[i]
        if x[i] > m:
            m = x[i]
    return m


@nb.njit(cache=True, nogil=True)
def _press_pass(rows, f, tip, peaks):
    """:class:`_Press` over a block of rows (C-contiguous), their |F| (``f``) and tip depths
    (``tip``, or empty): each peak (P_*) raised to the block's numpy ``max`` where that is larger
    (Python's ``max`` of the two: a block with a NaN leaves it)."""
    for j in range(3):
        m = _block_max(rows, C_LAYER_F[j], True)
        if m > peaks[P_LAYER + j]:
            peaks[P_LAYER + j] = m
    m = nan_max(f)
    if m > peaks[P_F]:
        peaks[P_F] = m
    if tip.shape[0]:
        m = nan_max(tip)
        if m > peaks[P_TIP]:
            peaks[P_TIP] = m


_NO_TIP = np.zeros(0)


class _Press:
    """The skin's pressing run before a puncture: where it began and its window peaks so far."""

    def __init__(self, index: int, row: np.ndarray):
        self.index = index
        self.t = float(row[C_T])
        self.entry = row[C_X:C_X + 3].copy()
        self.peaks = np.array([0.0, 0.0, 0.0, 0.0, -math.inf])  # P_*

    @property
    def layer_peak(self) -> list[float]:
        return self.peaks[P_LAYER:P_LAYER + 3].tolist()

    @property
    def f_peak(self) -> float:
        return float(self.peaks[P_F])

    @property
    def tip_max(self) -> float:
        return float(self.peaks[P_TIP])

    def feed(self, rows: np.ndarray, tip) -> None:
        """Rows (k >= 1, NCOL; C-contiguous float64) and their tip depths or None."""
        f = rows[:, C_F:C_F + 3]
        _press_pass(rows, np.sqrt(np.einsum("ij,ij->i", f, f)),
                    _NO_TIP if tip is None else np.ascontiguousarray(tip, dtype=np.float64), self.peaks)


# InsertionStream's running values: lateral ticks over the comfort bound and the largest lateral
# force, ticks in bone and clamped, the deepest depth so far, the first tick interval (and whether
# it is set), whether every interval equals it, and the last t
R_LAT_OVER, R_LAT_MAX, R_BONE, R_CLAMPED, R_MAX_DEPTH, R_DX0, R_HAS_DX0, R_UNIFORM, R_T_LAST = range(9)


@nb.njit(cache=True, nogil=True)
def _run_pass(rows, limits, run, rec):
    """:class:`InsertionStream`'s running values ``run`` (R_*) over a block of rows (C-contiguous),
    as numpy would count them on the block and Python's ``max`` would join them; ``limits``: the
    lateral comfort bound (N), the target's lower bound (m) and the rows seen before the block.
    The block's depth records (rows deeper than every earlier one, numpy's ``maximum.accumulate``:
    none after a NaN) go into ``rec``. Returns (their count, the block's first row at the lower
    bound or -1)."""
    comfort, lo, seen = limits
    k = rows.shape[0]
    for i in range(k):
        if rows[i, C_LAT] > comfort:
            run[R_LAT_OVER] += 1.0
        if rows[i, C_LAYER] == 3.0:
            run[R_BONE] += 1.0
        if rows[i, C_CLAMPED] != 0.0:
            run[R_CLAMPED] += 1.0
        if i > 0 or seen > 0:
            d = rows[i, C_T] - (rows[i - 1, C_T] if i > 0 else run[R_T_LAST])
            if run[R_HAS_DX0] == 0.0:
                run[R_DX0] = d
                run[R_HAS_DX0] = 1.0
            if d != run[R_DX0]:
                run[R_UNIFORM] = 0.0
    run[R_T_LAST] = rows[k - 1, C_T]
    m = _block_max(rows, C_LAT, False)
    if m > run[R_LAT_MAX]:
        run[R_LAT_MAX] = m
    n = 0
    hit = -1
    deepest = run[R_MAX_DEPTH]
    for i in range(k):
        v = rows[i, C_DEPTH]
        if hit < 0 and v >= lo:
            hit = i
        if v > deepest:
            rec[n] = i
            n += 1
        if v != v or deepest != deepest:
            deepest = np.nan
        elif v > deepest:
            deepest = v
    if n:
        run[R_MAX_DEPTH] = rows[rec[n - 1], C_DEPTH]
    return n, hit


class InsertionStream:
    """:func:`haptic_acu.analysis.metrics.insertion_metrics` of one insertion fed block by block (module
    docstring). ``press``: its entry's pressing run (:class:`_Press`), opened at the run's first row
    if it had none; ``inward``: the inward skin normal at the entry; ``ref_rows``: the session
    replayed without rotation for the grasp felt, as (ticks, forces (n, 3)), or None."""

    def __init__(self, press: _Press, target_mm, inward: np.ndarray, comfort_n: float, ref_rows=None):
        self.press = press
        self.entry = press.entry
        self.lo = float(target_mm[0])
        self.target = (float(target_mm[0]), float(target_mm[1]))
        self.inward = inward
        self.comfort = comfort_n
        self.ref = ref_rows
        self.ref_ok = ref_rows is not None
        self.n = 0
        self.t0 = self.t_last = 0.0
        self.p0 = None
        self.skin_punctured = False
        self.run = np.zeros(9)  # the running values (R_*)
        self.run[[R_LAT_MAX, R_MAX_DEPTH]] = -math.inf
        self.run[R_UNIFORM] = 1.0
        self.p_deep = None
        self.records: list[np.ndarray] = []  # rows (index, depth, t, px, py, pz), depth-pruned
        self.k_lo = None  # (index, t) of the first tick at the target's lower bound
        self.twirl = _Twirl()
        self.strokes = _Strokes(ref_rows is not None)
        self.troughs = TroughScan(1e-3)
        self.buf: list[np.ndarray] = []
        self.nbuf = 0
        self.u_steps = None  # the direction the continuous depth's steps use, once fixed
        self.step_rows: list[np.ndarray] = []  # (p, prev p) at the step ticks, for the error bound
        self.s_carry = 0.0
        self.tail = None  # the last two processed samples: (t, depth, axial, dcm rows)
        self.next_i = 0  # samples through the strokes and troughs so far
        self.step_dp = 0.0  # summed |one-tick tip motion| at the step ticks
        self.step_error_bound_m = 0.0
        self.pend = None  # the sample waiting for its right neighbour
        self.left = None  # (t, dcm) of the sample before it

    # -- direction -------------------------------------------------------------------------------
    def direction(self, angle: bool = True):
        """(u, angle in degrees or None) from the entry to the deepest point so far; without
        ``angle``, (u, None)."""
        from .common import angle_deg as _angle_deg
        direction = self.p_deep - self.entry
        length = float(np.linalg.norm(direction))
        if length > 1e-6:
            u = direction / length
            return u, (_angle_deg(u, self.inward) if angle else None)
        return self.inward, None

    # -- the running values (R_*) ------------------------------------------------------------------
    lat_over = property(lambda self: int(self.run[R_LAT_OVER]))
    lat_max = property(lambda self: float(self.run[R_LAT_MAX]))
    bone_ticks = property(lambda self: int(self.run[R_BONE]))  # ticks with the tip in bone
    clamped_ticks = property(lambda self: int(self.run[R_CLAMPED]))  # ticks with the force clamped
    max_depth = property(lambda self: float(self.run[R_MAX_DEPTH]))
    # the run's first tick interval (None before one), and whether every interval equals it
    # (numpy.gradient's uniform formula then)
    dx0 = property(lambda self: float(self.run[R_DX0]) if self.run[R_HAS_DX0] else None)
    uniform = property(lambda self: bool(self.run[R_UNIFORM]))

    # -- feeding ---------------------------------------------------------------------------------
    def feed(self, rows: np.ndarray, tip) -> None:
        """Rows of the run (skin punctured; C-contiguous float64), oldest first; ``tip``: their tip
        depth or None."""
        k = len(rows)
        if k == 0:
            return
        t = rows[:, C_T]
        i0 = self.n
        if self.n == 0:
            self.t0, self.p0 = float(t[0]), rows[0, C_X:C_X + 3].copy()
            self.skin_punctured = bool(rows[0, C_PUNCT] == 0)
        rec = np.empty(k, dtype=np.int64)
        n_rec, hit = _run_pass(rows, (float(self.comfort), self.lo * 1e-3, i0), self.run, rec)
        self.n += k
        self.t_last = float(t[-1])
        self.press.feed(rows, tip)
        if n_rec:
            self._records(i0 + rec[:n_rec], rows[rec[:n_rec]])
        if self.k_lo is None and hit >= 0:
            self.k_lo = (i0 + hit, float(t[hit]))
        self.twirl.feed(rows)
        if self.ref is not None:
            block = np.empty((k, len(_BLOCK_COLS) + 3))
            block[:, :len(_BLOCK_COLS)] = rows[:, _BLOCK_COLS]
            block[:, len(_BLOCK_COLS):] = self._ref_forces(rows[:, C_TICK])
        else:
            block = rows[:, _BLOCK_COLS]  # one gather: t, depth, p (3), F (3), puncture
        if self.u_steps is None:
            self.buf.append(block)
            self.nbuf += k
            if self.nbuf >= BUFFER_ROWS:
                self._fix_steps()
        else:
            self._dc_block(block)

    def _records(self, index: np.ndarray, rec: np.ndarray) -> None:
        """A block's depth records (its rows deeper than every earlier one, :func:`_run_pass`; their
        indices in the run), kept with the earlier ones not shallower than 90% of the deepest."""
        self.p_deep = rec[-1, C_X:C_X + 3].copy()
        new = np.column_stack([index, rec[:, C_DEPTH], rec[:, C_T], rec[:, C_X:C_X + 3]])
        keep = 0.9 * self.max_depth
        old = [r[r[:, 1] >= keep] for r in self.records]
        self.records = [r for r in old + [new[new[:, 1] >= keep]] if len(r)]
        if len(self.records) > 64:
            self.records = [np.concatenate(self.records)]

    def _ref_forces(self, ticks: np.ndarray) -> np.ndarray:
        """The reference replay's force rows on these ticks (zeros, and no grasp, if it lacks one)."""
        ref_ticks, ref_f = self.ref
        idx = np.searchsorted(ref_ticks, ticks)
        ok = idx < len(ref_ticks)
        if not ok.all() or not np.array_equal(ref_ticks[idx], ticks):
            self.ref_ok = False
            return np.zeros((len(ticks), 3))
        return ref_f[idx]

    def _fix_steps(self) -> None:
        self.u_steps = self.direction(angle=False)[0]
        if len(self.buf) > 1:  # the buffered blocks in one pass, each block's step motion summed alone
            self._dc_block(np.concatenate(self.buf), [len(b) for b in self.buf])
        elif self.buf:
            self._dc_block(self.buf[0])
        self.buf, self.nbuf = [], 0

    def _dc_block(self, b: np.ndarray, parts=None) -> None:
        """Continuous depth (module docstring) of buffered rows ``b``, then strokes and troughs.
        ``parts``: the lengths of the blocks ``b`` joins, if several: the summed one-tick motion at
        the step ticks adds up block by block, as if each were fed alone (the same bits)."""
        u = self.u_steps
        depth, p = b[:, 1], b[:, 2:5]
        axial = dot3(p - self.entry, u)
        first = self.tail is None
        if first:
            jump = np.diff(axial) - np.diff(depth)
            at = b[1:, 8] >= 1
            step = np.concatenate(([0.0], np.where(at, np.maximum(jump, 0.0), 0.0)))
            dp = np.diff(p, axis=0)[at]
        else:
            jump = np.diff(np.concatenate(([self.tail[0]], axial))) - np.diff(np.concatenate(([self.tail[1]], depth)))
            at = b[:, 8] >= 1
            step = np.where(at, np.maximum(jump, 0.0), 0.0)
            dp = np.diff(np.vstack([self.tail[2], p]), axis=0)[at]
        dpn = np.linalg.norm(dp, axis=1)
        if parts is None:
            self.step_dp += float(dpn.sum())
        else:
            at_all = at if not first else np.concatenate(([False], at))  # per row of b
            a = 0
            for n_at in np.add.reduceat(at_all.astype(np.int64), np.cumsum([0, *parts[:-1]])).tolist():
                self.step_dp += float(dpn[a:a + n_at].sum())
                a += n_at
        s = np.cumsum(np.concatenate(([self.s_carry], step)))[1:]
        self.s_carry = float(s[-1])
        self.tail = (float(axial[-1]), float(depth[-1]), p[-1].copy())
        dc = depth + s
        uc = self.direction(angle=False)[0]
        res = -(-dot3(b[:, 5:8], uc))  # a lift's resistance: minus the axial force -F . u
        rres = -(-dot3(b[:, 9:12], uc)) if self.ref is not None else np.zeros(len(b))
        new = np.empty((len(b), 8))
        new[:, 0] = b[:, 0]
        new[:, 1] = dc
        np.multiply(dc, 1e3, out=new[:, 2])
        new[:, 3:6] = b[:, 5:8]
        new[:, 6] = res
        new[:, 7] = rres
        self._process(new)

    def _process(self, new: np.ndarray, final: bool = False) -> None:
        """Strokes and troughs of every sample whose right neighbour is known (all, if ``final``)."""
        a = new if self.pend is None else np.vstack([self.pend, new])
        m = len(a) if final else len(a) - 1
        if m <= 0:
            self.pend = a
            return
        t, dcm = a[:, 0], a[:, 2]
        left = (np.nan, np.nan) if self.left is None else self.left  # (t, dcm) of the sample before a[0]
        # the speeds by numpy.gradient's formulas, sample by sample in the strokes' pass (_speeds):
        # with l, m, r a sample's left neighbour, itself and its right one (NaN where missing),
        # dx1 = m_t - l_t, dx2 = r_t - m_t, the general formula ca * l + cb * m + cc * r (ca =
        # -dx2 / (dx1 (dx1 + dx2)), cb = (dx2 - dx1) / (dx1 dx2), cc = dx1 / (dx2 (dx1 + dx2))), the
        # uniform one (r - l) / (2 dx0)
        g0 = self.next_i
        dx0 = self.dx0 if self.dx0 is not None else np.nan
        self.strokes.feed(g0, a, (int(m), float(left[0]), float(left[1]), float(dx0)))
        self.troughs.feed(g0, -a[:m, 1], t[:m])
        self.next_i += m
        self.left = (float(t[m - 1]), float(dcm[m - 1]))
        self.pend = a[m:]

    # -- the result ------------------------------------------------------------------------------
    def result(self) -> dict:
        """The insertion's dict as :func:`~haptic_acu.analysis.metrics.insertion_metrics` (with dt = 0: the
        caller applies the session's tick period) and without its ``punctures``."""
        from .common import LAYERS, SPEED_DEPTH_FRACTION, depth_verdict
        from .common import round_json as _r
        if self.u_steps is None:
            self._fix_steps()
        self._process(np.zeros((0, 8)), final=True)
        u, angle = self.direction()
        self.step_error_bound_m = self.step_dp * float(np.linalg.norm(u - self.u_steps))
        lo, hi = self.target
        max_depth = self.max_depth
        rec = np.concatenate(self.records) if self.records else np.zeros((0, 6))
        thr = SPEED_DEPTH_FRACTION * max_depth
        hit = np.flatnonzero(rec[:, 1] >= thr)
        k90 = int(rec[hit[0], 0]) if hit.size else 0
        speed = None
        if k90 > 0:
            r = rec[hit[0]]
            if r[2] > self.t0:
                ax = dot3(np.vstack([r[3:6], self.p0]) - self.entry, u)
                speed = (ax[0] - ax[1]) / (r[2] - self.t0) * 1e3
        t_target = None if self.k_lo is None else float(self.k_lo[1] - self.press.t)
        at_depth = min(lo * 1e-3, thr)
        if at_depth == lo * 1e-3:
            k_start = 0 if self.k_lo is None else self.k_lo[0]
        else:
            k_start = k90
        out = {
            "t_entry_s": _r(self.press.t, 4),
            "t_inside_s": _r(self.t0, 4),
            "t_exit_s": _r(self.t_last, 4),
            "skin_punctured": self.skin_punctured,
            "entry_mm": [_r(v * 1e3, 3) for v in self.entry],
            "entry_offset_mm": _r(np.linalg.norm(self.entry) * 1e3, 3),
            "angle_deg": _r(angle, 2),
            "max_depth_mm": _r(max_depth * 1e3, 3),
            "depth_verdict": depth_verdict(max_depth * 1e3, (lo, hi)),
            "insertion_speed_mm_s": _r(speed, 3),
            "time_to_target_s": _r(t_target, 4),
            "peak_layer_force_n": {name: _r(v, 4) for name, v in zip(LAYERS, self.press.layer_peak)},
            "peak_total_force_n": _r(self.press.f_peak, 4),
            "lift_thrust": self._cycles(k_start),
            "lateral": {"ticks_over": self.lat_over, "time_over_s": 0.0, "max_n": _r(self.lat_max, 4)},
            "time_in_tissue_s": 0.0,
            "_bone_ticks": self.bone_ticks, "_clamped_ticks": self.clamped_ticks,  # times at result()
        }
        if self.press.tip_max > -math.inf:
            out["max_tip_depth_mm"] = _r(max(self.press.tip_max, 0.0) * 1e3, 3)
        tw = self.twirl.result()
        st = self.strokes.stroke_result(self.uniform, u)
        grasp = self.strokes.grasp_result() if self.ref_ok else None
        out["technique"] = {"twirl": tw, "lift_thrust_forces": st, "grasp_felt": grasp,
                            "classification": classify(tw, st)}
        return out

    def _cycles(self, k_start: int) -> dict:
        from .common import round_json as _r
        if self.n - k_start < 3:
            return {"cycles": 0, "mean_amplitude_mm": None, "frequency_hz": None}
        tr = [x for x in self.troughs.finish() if x[0] >= k_start]
        n = len(tr)
        amp = float(np.mean(np.array([x[2] for x in tr]))) * 1e3 if n else None
        freq = None
        if n >= 2:
            span = float(tr[-1][1] - tr[0][1])
            freq = (n - 1) / span if span > 0 else None
        return {"cycles": n, "mean_amplitude_mm": _r(amp, 3), "frequency_hz": _r(freq, 3)}

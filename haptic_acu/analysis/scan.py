"""Punctures, per-place time and peak force, and tip depths, scanned from the servo's sample rows
(:mod:`haptic_acu.servo.samples`) in one streaming pass: what every output reports of a session.

Tip depth. Every depth here is the tip's depth below the *rest* skin surface, measured radially from
the body centre: ``r_skin(theta, phi) - |p - c|`` (m; negative above the skin); see
:mod:`haptic_acu.session.report` for why.
"""
from __future__ import annotations

import threading

import numba as nb
import numpy as np

from ..servo.samples import COL, NCOL
from ..servo.state import N_LAYERS, PLACE_NAMES, PRESSING, PUNCTURED, STATE_NAMES  # noqa: F401
from ..tissue.body import Tissue as _Tissue
from .common import C_CLAMPED, C_F, C_FAULT, C_LAYER, C_PUNCT, C_STATE, C_T, C_TICK, C_X
from .insertion_stream import nan_max

_BODY_RADIUS = _Tissue.radius
PLACES = PLACE_NAMES  # sample ``layer`` codes -1..3
LAYERS = PLACES[1:4]


def place_name(code: float) -> str:
    """Name of a sample ``layer`` code: -1 outside, 0 skin, 1 fat, 2 muscle, 3 bone."""
    return PLACES[int(code) + 1]


_RECENT_DEPTHS: list = []  # (tissue, points, depths, first and last point) of the last batches, newest last
RECENT_DEPTHS = 8  # enough for each sink of a replay's block of frames to meet its batches again
RECENT_DEPTHS_ROWS = 65_536  # a larger batch is kept alone
_DEPTH_LOCK = threading.Lock()


def tip_depth_m(xyz: np.ndarray, tissue) -> np.ndarray:
    """Depth (m) of points ``xyz`` (k, 3) below the rest skin surface, radially from the body centre;
    negative above the skin. The last few batches' points and depths are kept: the same points of
    the same tissue again (a session's sinks each reading the tip depth of the same batches of rows:
    samples.csv, the summary's scan, its metrics; a lock keeps the memo whole if two threads ask) are
    answered with a copy, not a second SH evaluation."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    with _DEPTH_LOCK:
        return _tip_depth(xyz, tissue)


def _tip_depth(xyz, tissue):
    if xyz.shape[0]:
        ends = (xyz[0].tolist(), xyz[-1].tolist())  # a cheap look before comparing every point
        for last_tissue, last_xyz, last_depth, last_ends in reversed(_RECENT_DEPTHS):
            if (last_tissue is tissue and last_xyz.shape == xyz.shape and last_ends == ends
                    and np.array_equal(last_xyz, xyz)):
                return last_depth.copy()
    d = xyz - tissue.centre
    rho = np.sqrt(np.einsum("ij,ij->i", d, d))
    safe = np.where(rho > 0.0, rho, 1.0)
    theta = np.arccos(np.clip(d[:, 2] / safe, -1.0, 1.0))
    phi = np.arctan2(d[:, 1], d[:, 0])
    depth = tissue.radius(0, theta, phi) - rho
    _remember(xyz, tissue, depth)
    return depth


def _remember(xyz, tissue, depth) -> None:
    if xyz.shape[0] >= 256:  # a batch of rows (a frame's few are cheaper to evaluate than to compare)
        if xyz.shape[0] > RECENT_DEPTHS_ROWS:  # a whole session's rows: kept alone (memory as one batch)
            _RECENT_DEPTHS.clear()
        _RECENT_DEPTHS.append((tissue, xyz.copy(), depth.copy(), (xyz[0].tolist(), xyz[-1].tolist())))
        del _RECENT_DEPTHS[:-RECENT_DEPTHS]


class TipDepthBuffers:
    """Work arrays for :func:`tip_depth_into` of up to ``rows`` points, made once: the depths of a
    block of rows are computed on the session's tick thread without allocating there (a thread
    that allocates takes a malloc arena of its own, and the peak memory grows)."""

    def __init__(self, rows: int):
        self.rows = int(rows)
        self.d = np.empty((self.rows, 3))
        self.rho = np.empty(self.rows)
        self.safe = np.empty(self.rows)
        self.theta = np.empty(self.rows)
        self.phi = np.empty(self.rows)
        self.ok = np.empty(self.rows, dtype=bool)
        from ..tissue import shf
        self.sh = np.empty((shf.EVAL_WORK_ROWS, shf._CHUNK))


def tip_depth_into(xyz: np.ndarray, tissue, out: np.ndarray, buf: TipDepthBuffers) -> bool:
    """:func:`tip_depth_m` of ``xyz`` (k, 3; k <= ``buf.rows``) into ``out[:k]``, bit for bit (the
    same operations in the same order, into ``buf``'s arrays), allocating nothing. False (``out``
    unspecified) for a body it cannot evaluate so or a point whose direction is not finite: the
    caller then asks :func:`tip_depth_m`, which says what is wrong."""
    k = xyz.shape[0]
    coeffs = getattr(tissue, "coeffs", None)
    if k > buf.rows or type(tissue).radius is not _BODY_RADIUS or coeffs is None:
        return False
    c = coeffs[0]
    if c.ndim != 1 or c.dtype != np.float64 or not c.flags.c_contiguous:
        return False
    d, rho, safe, theta, phi, ok = (buf.d[:k], buf.rho[:k], buf.safe[:k], buf.theta[:k], buf.phi[:k],
                                    buf.ok[:k])
    np.subtract(xyz, tissue.centre, out=d)
    np.einsum("ij,ij->i", d, d, out=rho)
    np.sqrt(rho, out=rho)
    np.greater(rho, 0.0, out=ok)
    safe.fill(1.0)
    np.copyto(safe, rho, where=ok)
    np.divide(d[:, 2], safe, out=theta)
    np.clip(theta, -1.0, 1.0, out=theta)
    np.arccos(theta, out=theta)
    np.arctan2(d[:, 1], d[:, 0], out=phi)
    np.isfinite(theta, out=ok)
    if not ok.all():
        return False
    np.isfinite(phi, out=ok)
    if not ok.all():
        return False
    from ..tissue import shf
    lmax = shf.lmax_of(c.shape[0])
    if lmax > shf.REC_LMAX:
        return False
    r = out[:k]
    shf.eval_many_work(c, lmax, theta, phi, r, buf.sh)
    np.subtract(r, rho, out=r)
    return True


def radial_force_n(rows: np.ndarray, tissue) -> np.ndarray:
    """F . u per row (N): the force along the outward radial direction at the tip (positive resists
    insertion)."""
    d = rows[:, C_X:C_X + 3] - tissue.centre
    rho = np.sqrt(np.einsum("ij,ij->i", d, d))
    u = d / np.where(rho > 0.0, rho, 1.0)[:, None]
    return np.einsum("ij,ij->i", rows[:, C_F:C_F + 3], u)


def _r(x: float, nd: int) -> float:
    """Round for JSON, without negative zeros."""
    return round(float(x), nd) + 0.0


def puncture_records(events) -> list[dict]:
    """:class:`SessionScan` punctures as reported everywhere (summary.json, metrics, text, figures):
    layer, t_s (0.1 ms), tip_depth_mm (1 um), peak_force_n (0.1 mN). Computed and rounded once."""
    return [{"layer": p["layer"], "t_s": _r(p["t_s"], 4), "tip_depth_mm": _r(p["tip_depth_m"] * 1e3, 3),
             "peak_force_n": _r(p["peak_force_n"], 4)} for p in events]


class SessionScan:
    """Streaming scan of sample rows: punctures with their pressing-phase peak force, and per-place
    time and peak force. Feed row blocks in order with :meth:`feed`; it keeps O(1) state.

    A puncture is a row whose ``puncture`` column is a layer index. Its peak force is the largest
    ``|F|`` over the rows of the uninterrupted run in which that layer's state was PRESSING just
    before it (the run restarts if the tip lifts off and touches again); its depth is the tip's depth
    (:func:`tip_depth_m`) at the puncture tick. Time in a place: each row's interval up to the next
    row (t_{i+1} - t_i) counts for the place of row i.
    """

    def __init__(self, tissue):
        self.tissue = tissue
        self.ticks = 0
        self.t_first: float | None = None
        self.t_last: float | None = None
        self.max_force = 0.0
        self.max_depth = -np.inf
        self.time_in = np.zeros(len(PLACES))
        self.peak_in = np.zeros(len(PLACES))
        self.ticks_in = np.zeros(len(PLACES), dtype=np.int64)
        self.punctures: list[dict] = []
        self.clamped_ticks = 0
        self.fault_ticks = 0
        self._prev_place = -1
        self._prev_state = np.zeros(N_LAYERS, dtype=np.int64)
        self._press_peak = np.zeros(N_LAYERS)
        self._press_peak_depth = np.zeros(N_LAYERS)

    def feed(self, rows: np.ndarray, depth: np.ndarray | None = None) -> list[dict]:
        """Scan a block of rows (k, NCOL); returns the punctures found in it (also kept). ``depth``:
        the rows' :func:`tip_depth_m`, if the caller has it already."""
        rows = np.ascontiguousarray(rows, dtype=np.float64)  # the compiled pass reads it by rows
        k = rows.shape[0]
        if k == 0:
            return []
        if rows.ndim != 2 or rows.shape[1] != NCOL:
            raise ValueError(f"sample rows must have shape (k, {NCOL}), got {rows.shape}")
        f = np.sqrt(np.einsum("ij,ij->i", rows[:, C_F:C_F + 3], rows[:, C_F:C_F + 3]))
        if depth is None:
            depth = tip_depth_m(rows[:, C_X:C_X + 3], self.tissue)
        depth = np.ascontiguousarray(depth, dtype=np.float64)
        # time: interval to the next row counts for the place of the earlier row
        if self.t_last is not None:
            self.time_in[self._prev_place] += rows[0, C_T] - self.t_last
        else:
            self.t_first = float(rows[0, C_T])
        self._prev_place = int(rows[-1, C_LAYER]) + 1
        self.t_last = float(rows[-1, C_T])
        self.ticks += k
        # pressing runs, punctures, places and the block's extremes and counts: one compiled pass
        ev = np.empty(k, dtype=np.int64)
        ev_peak = np.empty(k)
        ev_peak_depth = np.empty(k)
        n, f_max, depth_max, clamped, fault = _press_runs(
            rows, f, depth, (self._prev_state, self._press_peak, self._press_peak_depth),
            (ev, ev_peak, ev_peak_depth), (self.time_in, self.ticks_in, self.peak_in))
        self.max_force = max(self.max_force, f_max)  # Python's max: a block's NaN maximum is passed over
        self.max_depth = max(self.max_depth, depth_max)
        self.clamped_ticks += clamped
        self.fault_ticks += fault
        found = [{"layer": LAYERS[int(rows[i, C_PUNCT])], "t_s": float(rows[i, C_T]), "tick": int(rows[i, C_TICK]),
                  "tip_depth_m": float(depth[i]), "peak_force_n": float(pk), "peak_depth_m": float(pd)}
                 for i, pk, pd in zip(ev[:n].tolist(), ev_peak[:n].tolist(), ev_peak_depth[:n].tolist())]
        self.punctures.extend(found)
        return found


@nb.njit(cache=True, nogil=True)
def _press_runs(rows, f, depth, runs, out, places):
    """:meth:`SessionScan.feed`'s pass over a block of ``rows`` (C-contiguous), their |F| ``f`` and
    tip depths ``depth``. Pressing runs: per layer, the largest ``f`` (and the ``depth`` there) over
    the uninterrupted run of PRESSING states, carried in ``runs`` (prev_state, peak, peak_depth)
    across blocks; for each row with a puncture (in order), its row index and that layer's run peak
    and depth into ``out`` (ev, ev_peak, ev_peak_depth: k long). ``places``: (time_in, ticks_in,
    peak_in): per place (layer code + 1), the rows' intervals to their next row in the block, their
    count and their largest ``f`` (numpy.maximum's: a NaN stays), added in row order. Returns the
    punctures' count, numpy's max of ``f`` and of ``depth``, and the rows clamped and faulted."""
    prev_state, peak, peak_depth = runs
    ev, ev_peak, ev_peak_depth = out
    time_in, ticks_in, peak_in = places
    k = rows.shape[0]
    clamped = 0
    fault = 0
    for i in range(k):
        pl = int(rows[i, C_LAYER]) + 1
        if i + 1 < k:
            time_in[pl] += rows[i + 1, C_T] - rows[i, C_T]
        ticks_in[pl] += 1
        if f[i] > peak_in[pl] or f[i] != f[i]:
            peak_in[pl] = f[i]
        if rows[i, C_CLAMPED] != 0.0:
            clamped += 1
        if rows[i, C_FAULT] != 0.0:
            fault += 1
    n = 0
    for i in range(k):
        for j in range(N_LAYERS):
            s = np.int64(rows[i, C_STATE + j])
            if s == PRESSING:
                if prev_state[j] != PRESSING or f[i] > peak[j]:
                    peak[j] = f[i]
                    peak_depth[j] = depth[i]
            prev_state[j] = s
        if rows[i, C_PUNCT] >= 0:
            j = int(rows[i, C_PUNCT])
            ev[n] = i
            ev_peak[n] = peak[j]
            ev_peak_depth[n] = peak_depth[j]
            n += 1
    return n, nan_max(f), nan_max(depth), clamped, fault

"""A cohort session's path metrics without its rows in memory.

The cohort's path length, economy of motion and LDLJ columns (:mod:`haptic_acu.analysis.skill_metrics`) are
taken on the session's path low-passed by a zero-phase filter (``scipy.signal.sosfiltfilt``: forward
over the whole session, then backward from its end), so no bounded *stream* gives them. This module
gives the same numbers, to the bit, in bounded memory:

* :class:`TrackFile` (a frame sink) appends each row's t, x, y, z, skin state and depth (48 bytes)
  to an anonymous temporary file, and counts the tick intervals (their median sets the filter);
* :func:`smoothed_blocks` runs the filter in blocks of :data:`BLOCK` rows: the forward pass keeps
  only its state at each block's start (24 numbers); the backward pass walks the blocks from the end,
  recomputes each block's forward output from its saved state (the same operations, so the same
  bits) and filters it backward. Memory: a few blocks, whatever the session's length;
* :func:`path_columns` sums each insertion's path as numpy does (pairwise, :func:`pairwise_plan`:
  the same additions in the same order, so the same bits) and keeps only each insertion's thrust
  (entry to the depth reached: economy and LDLJ need its samples; it lasts seconds).

tests/test_cohort_memory.py checks the cohort's tables against the whole-row computation.
"""
from __future__ import annotations

import tempfile

import numpy as np

from ..servo.samples import COL
from .sink import Sink

BLOCK = 65_536  # rows per block of the filter's passes (1.6 MB of float64 x, y, z)
TRACK_COLUMNS = ("t_s", "x_m", "y_m", "z_m", "state_skin", "depth_skin_m")  # a track's row: sample columns
TCOL = {name: i for i, name in enumerate(TRACK_COLUMNS)}
_COLS = [COL[name] for name in TRACK_COLUMNS]
_W = len(_COLS)
_T, _X, _STATE, _DEPTH = TCOL["t_s"], TCOL["x_m"], TCOL["state_skin"], TCOL["depth_skin_m"]


class TrackFile(Sink):
    """Frame sink: per row t_s, x, y, z (m), state_skin, depth_skin_m, on disk (module docstring)."""

    def __init__(self):
        from ..analysis.metrics import MedianCounter
        self.f = tempfile.TemporaryFile()
        self.n = 0
        self.dt = MedianCounter()
        self._last_t = None

    def on_frame(self, frame) -> None:
        rows = frame.samples
        if len(rows):
            a = np.ascontiguousarray(rows[:, _COLS], dtype=np.float64)
            self.f.write(a.tobytes())
            t = a[:, _T]
            if self._last_t is not None:
                self.dt.add(np.array([t[0] - self._last_t]))
            self.dt.add(np.diff(t))
            self._last_t = float(t[-1])
            self.n += len(a)

    def read(self, a: int, b: int) -> np.ndarray:
        """Rows a..b-1, (b - a, 6)."""
        self.f.flush()
        self.f.seek(a * _W * 8)
        return np.frombuffer(self.f.read((b - a) * _W * 8), dtype=np.float64).reshape(-1, _W)

    def chunks(self, block: int = BLOCK):
        for a in range(0, self.n, block):
            yield a, self.read(a, min(self.n, a + block))

    def release(self) -> None:
        """Delete the file (not the sink's ``close``: the engine calls that when the session ends)."""
        self.f.close()


def _filter_setup(track: TrackFile, cutoff_hz):
    """(sos, padlen) of :func:`haptic_acu.analysis.skill_metrics.smooth_path` for this track, or None when it
    returns the positions unchanged."""
    from ..analysis.skill_metrics import FILTER_ORDER
    n = track.n
    if cutoff_hz is None or n < 3:
        return None
    from scipy.signal import butter
    fs = 1.0 / float(track.dt.median())
    if cutoff_hz >= 0.5 * fs:
        return None
    sos = butter(FILTER_ORDER, cutoff_hz, fs=fs, output="sos")
    return sos, min(3 * (2 * len(sos) + 1), n - 1)


def smoothed_blocks(track: TrackFile, cutoff_hz, block: int = BLOCK):
    """(first row, smoothed x, y, z rows) of :func:`haptic_acu.analysis.skill_metrics.smooth_path` over the
    whole track, block by block from the end of the session to its start (module docstring)."""
    setup = _filter_setup(track, cutoff_hz)
    n = track.n
    if setup is None:
        for a in reversed(range(0, n, block)):
            yield a, track.read(a, min(n, a + block))[:, _X:_X + 3].copy()
        return
    from scipy.signal import sosfilt, sosfilt_zi
    sos, pad = setup
    head = track.read(0, pad + 1)[:, _X:_X + 3]
    tail = track.read(n - pad - 1, n)[:, _X:_X + 3]
    left = 2 * head[0:1] - head[pad:0:-1]  # scipy.signal odd_ext, its two ends
    right = 2 * tail[-1:] - tail[-2:-(pad + 2):-1]
    zi = sosfilt_zi(sos).reshape(len(sos), 2, 1)
    # the padded signal's blocks: (start row in the padded signal, source); rows are read again later
    spans = [(0, "left")] + [(pad + a, a) for a in range(0, n, block)] + [(pad + n, "right")]

    def rows_of(src):
        if src == "left":
            return left
        if src == "right":
            return right
        return track.read(src, min(n, src + block))[:, _X:_X + 3]

    z = zi * left[0:1]
    states = []
    y_last = None
    for _, src in spans:
        states.append(z)
        y, z = sosfilt(sos, rows_of(src), axis=0, zi=z)
        if len(y):
            y_last = y[-1:]
    zb = zi * y_last
    for (start, src), z0 in zip(reversed(spans), reversed(states)):
        y = sosfilt(sos, rows_of(src), axis=0, zi=z0)[0]
        yb, zb = sosfilt(sos, y[::-1], axis=0, zi=zb)
        if isinstance(src, int):
            yield src, np.ascontiguousarray(yb[::-1])


def pairwise_plan(n: int, leaf: int = 128) -> list[tuple[int, int]]:
    """The (offset, length) leaves of numpy's pairwise summation of ``n`` numbers, in order: sums of
    the leaves (each an ``np.sum`` of at most 128 numbers) combined by :func:`pairwise_combine` give
    ``np.sum``'s bits (tests/test_cohort_memory.py checks lengths up to 600,001)."""
    out: list[tuple[int, int]] = []

    def rec(off, m):
        if m <= leaf:
            out.append((off, m))
            return
        m2 = m // 2
        m2 -= m2 % 8
        rec(off, m2)
        rec(off + m2, m - m2)

    if n > 0:
        rec(0, n)
    return out


def pairwise_combine(sums: dict, n: int, leaf: int = 128) -> float:
    """np.sum of ``n`` numbers from its leaves' sums (``sums``: offset -> np.sum of that leaf)."""
    def rec(off, m):
        if m <= leaf:
            return sums[off]
        m2 = m // 2
        m2 -= m2 % 8
        return rec(off, m2) + rec(off + m2, m - m2)
    return float(rec(0, n)) if n > 0 else 0.0


def insertion_windows(track: TrackFile, reach_tol_m: float) -> list[tuple[int, int, int]]:
    """(entry row, last row inside, row where the thrust ends) of each insertion, as
    :func:`haptic_acu.cohort.sessions.insertion_table` finds them (:func:`haptic_acu.analysis.metrics.insertion_runs`,
    :func:`~haptic_acu.analysis.metrics.entry_tick`, the first tick within ``reach_tol_m`` of the run's
    largest depth), from two passes over the track."""
    from ..analysis.metrics import PRESSING, PUNCTURED
    runs: list[list] = []  # [entry, first, last, max depth]
    prev, press = None, None
    for a, rows in track.chunks():
        st, depth = rows[:, _STATE], rows[:, _DEPTH]
        cut = [0, *(np.flatnonzero(np.diff(st) != 0) + 1).tolist(), len(st)]
        for i, j in zip(cut[:-1], cut[1:]):
            s = st[i]
            if s == PUNCTURED:
                if prev != PUNCTURED:
                    runs.append([press if prev == PRESSING and press is not None else a + i, a + i, a + j - 1, -np.inf])
                runs[-1][2] = a + j - 1
                runs[-1][3] = max(runs[-1][3], float(depth[i:j].max()))
            elif s == PRESSING and prev != PRESSING:
                press = a + i
            prev = s
    out = []
    k = 0
    reach = [None] * len(runs)
    for a, rows in track.chunks():  # the thrust's end: first row of the run at its max depth - tol
        b = a + len(rows)
        while k < len(runs) and runs[k][2] < a:
            k += 1
        for r in range(k, len(runs)):
            e, first, last, dmax = runs[r]
            if first >= b:
                break
            if reach[r] is None:
                lo, hi = max(first, a), min(last + 1, b)
                hit = np.flatnonzero(rows[lo - a:hi - a, 5] >= dmax - reach_tol_m)
                if hit.size:
                    reach[r] = lo + int(hit[0])
    for (e, first, last, _), kr in zip(runs, reach):
        out.append((e, last, kr))
    return out


def path_columns(track: TrackFile, cutoff_hz, reach_tol_m: float) -> list[dict]:
    """Per insertion: ``duration`` (s), ``path`` (mm), ``economy``, ``ldlj`` (the cohort's columns of
    those names, :func:`haptic_acu.cohort.sessions._skill`), to the bit, in bounded memory (module docstring)."""
    wins = insertion_windows(track, reach_tol_m)
    plans = [pairwise_plan(b - e) for e, b, _ in wins]
    offs = [np.array([o for o, _ in p], dtype=np.int64) for p in plans]
    sums: list[dict] = [{} for _ in wins]
    pieces: list[dict] = [{} for _ in wins]
    thrust: list[list] = [[] for _ in wins]  # (t, ps) pieces (copies), latest first
    out: list[dict | None] = [None] * len(wins)
    after = None  # the first smoothed row of the block after the current one
    for s, ps in smoothed_blocks(track, cutoff_hz):
        m = len(ps)
        nxt = ps if after is None else np.vstack([ps, after])
        norms = np.linalg.norm(np.diff(nxt, axis=0), axis=1)  # diff i -> i + 1 for rows s .. s + len - 1
        t = None
        for w, (e, b, kr) in enumerate(wins):
            if out[w] is not None or e >= s + m + 1 or b < s:
                continue
            lo, hi = max(e, s), min(b, s + len(norms))  # diffs i in [e, b - 1] within this block
            if lo < hi:
                _collect(norms[lo - s:hi - s], lo - e, plans[w], offs[w], pieces[w], sums[w])
            lo, hi = max(e, s), min(kr + 1, s + m)
            if lo < hi:
                if t is None:
                    t = track.read(s, s + m)[:, _T].copy()
                thrust[w].append((t[lo - s:hi - s].copy(), ps[lo - s:hi - s].copy()))
            if s <= e:  # the block holding the entry: this insertion is whole
                out[w] = _finish(track, e, b, sums[w], thrust[w])
                thrust[w] = []
        after = ps[0:1].copy()
    return out


def _finish(track: TrackFile, e: int, b: int, sums: dict, thrust: list) -> dict:
    from ..analysis.skill_metrics import economy_of_motion, ldlj
    tt = np.concatenate([x[0] for x in reversed(thrust)] or [np.zeros(0)])
    pp = np.concatenate([x[1] for x in reversed(thrust)] or [np.zeros((0, 3))])
    n = b - e
    length = pairwise_combine(sums, n) if n >= 1 else 0.0
    t_e, t_b = track.read(e, e + 1)[0, 0], track.read(b, b + 1)[0, 0]
    return {"duration": float(t_b - t_e), "path": length * 1e3, "economy": economy_of_motion(pp), "ldlj": ldlj(tt, pp)}


def _collect(vals, j0, plan, offs, pieces, sums) -> None:
    """File ``vals`` (window positions j0 ..) into the pairwise leaves; sum each leaf once whole."""
    j1 = j0 + len(vals)
    k = max(int(np.searchsorted(offs, j0, side="right")) - 1, 0)
    while k < len(plan) and plan[k][0] < j1:
        off, ln = plan[k]
        a, b = max(off, j0), min(off + ln, j1)
        got = pieces.setdefault(off, [])
        got.insert(0, vals[a - j0:b - j0].copy())  # blocks come latest first
        if sum(len(g) for g in got) == ln:
            sums[off] = np.sum(np.concatenate(got))
            del pieces[off]
        k += 1

"""Trainee session metrics: how each insertion was made, from a session's sample rows.

:func:`session_metrics` reads the servo rows of one session (:mod:`haptic_acu.servo.samples`, one row per
tick, SI units) and returns a JSON-ready dict: numbers rounded to fixed places (mm to 1 um, N to
0.1 mN, s to 0.1 ms, degrees to 0.01), so identical rows give identical output.

Insertion. A contiguous run of ticks in which the skin is punctured (``state_skin`` == 2). The
model resets the layer states when the tip comes back above the entry point, so going in again,
even through the existing hole, starts a new insertion. The insertion's *entry tick* is the first
tick of the skin's pressing run just before the run (the tip touching the intact skin); if there is
none, as when the tip re-enters through a hole (untouched -> punctured), it is the run's first tick.

Per insertion:

* ``t_entry_s``, ``t_inside_s``, ``t_exit_s``: session times (s) of the entry tick, the run's first
  tick (the skin's puncture, or the re-entry) and its last tick; ``skin_punctured``: whether the
  run began by breaking intact skin (its first tick carries the skin's ``puncture`` mark).
* ``entry_mm``: the tip position (mm, scene frame) at the entry tick; ``entry_offset_mm`` its
  distance from the acupoint (the origin).
* ``angle_deg``: angle between the insertion direction (entry -> the tip at its deepest, i.e. at
  the first tick of maximum ``depth_skin_m``) and the inward skin normal at the entry: minus
  ``tissue.normal(0, entry)`` when a :class:`~haptic_acu.tissue.body.Tissue` is given, else -z (the
  normal at the acupoint). None if the tip never moved away from the entry.
* ``max_depth_mm``: the largest ``depth_skin_m`` (depth along the insertion below the skin entry,
  in the compressed tissue's frame: see :mod:`haptic_acu.servo.step`), against the config's
  ``scene.target_depth_mm``: ``depth_verdict`` is "in range", "too shallow" or "too deep".
* ``insertion_speed_mm_s``: mean axial speed from the puncture (the run's first tick) to the first
  tick at 90% of the max depth: the tip's displacement along the insertion direction over the time
  between (so the depth frame's steps at deeper punctures, below, do not bias it).
* ``time_to_target_s``: from the entry tick to the first tick whose depth reaches the target's lower
  bound; None if it never does.
* ``peak_layer_force_n``: the largest ``|f_skin_n|``, ``|f_fat_n|``, ``|f_muscle_n|`` (the force
  attributed to each layer: its surface force while pressed, its damping once passed) from the entry
  tick to the end of the run; ``peak_total_force_n`` the largest ``|F|``. Not the puncture peaks:
  those are the total |F| while a layer was pressed (``punctures``, below), which includes the
  other layers' damping.
* ``lift_thrust``: cycles of lifting and thrusting back once the needle is at depth, i.e. from the
  first tick whose depth reaches the target's lower bound (or 90% of the max depth, if that is
  shallower). Each cycle is a trough of the depth signal found by ``scipy.signal.find_peaks`` (on
  minus the depth, computed here by :func:`find_troughs`) with a prominence of at least 1 mm; its ``amplitude`` is that prominence, the
  depth given up on the lift (for a cosine stroke around a fixed depth: the stroke length).
  ``frequency_hz`` is (cycles - 1) over the time from the first trough to the last (None for fewer
  than two). Before peak finding the depth signal is made continuous: when the fat or muscle
  surface breaks, the model lifts its frame by that surface's dent, so ``depth_skin_m`` steps back
  by about 1 mm in one tick; those steps (the drop in depth beyond the tip's own axial motion on
  the puncture tick) are added back, or a puncture could pass for a lift.
* ``max_tip_depth_mm``: the tip's deepest point below the *rest* skin surface over the run (the
  depth of the summary's ``max_depth_mm`` and of force_depth.png's axis,
  :func:`haptic_acu.session.report.tip_depth_m`; larger than ``max_depth_mm`` by the skin's dent).
* ``punctures``: the session's punctures (the summary's, :class:`haptic_acu.session.report.SessionScan`:
  layer, t_s, tip_depth_mm, peak_force_n = the largest |F| while that layer was pressed) from the
  entry tick to the run's end: the same numbers as the summary's, not a second estimate.
* ``lateral``: ticks of the run with ``f_lateral_n`` (the lateral-constraint force) above the comfort
  bound, their duration, and the run's largest lateral force.
* ``time_in_tissue_s``: the run's duration (ticks times the tick period).
* ``time_on_bone_s`` and ``time_at_force_limit_s``: the run's ticks with the tip in bone, and with
  the force clamped to the device's limit (``safety.force_limit_n``), times the tick period.
* ``technique``: the manipulation (:func:`haptic_acu.analysis.technique.technique_metrics`, docs/model.md
  "Technique metrics") over the run, on its continuous depth along the insertion direction (mm), the
  roll (``roll_deg``), the twist torque (``torque_nmm``) and the axial force ``f_axial_n`` = -F . u
  (u the insertion direction: positive pushing the needle out): ``twirl`` (cycles, swing and
  amplitude in degrees, frequency in Hz, net and total rotation, mean speed, peak torque),
  ``lift_thrust_forces`` (thrust and lift resistances and speeds, their ratio), ``grasp_felt`` (the
  withdrawal's resistance against the same withdrawal without rotation: only when the caller passes
  the rows of that replay, ``reference_rows``, and the needle turned; else None) and
  ``classification`` (reinforcing / reducing / even, with its inputs, thresholds and source; no
  label, and ``withheld`` saying why, for a run that touched bone or the force limit: those strokes
  felt the bone or the device's limit, not the tissue: :func:`contact_and_label`).

Session level: ``insertions`` (count), ``skin_punctures`` (insertions that broke intact skin),
``time_in_tissue_s`` and ``lateral`` summed over insertions. The tick period is the median interval
between rows.
"""
from __future__ import annotations

import numpy as np

from ..servo.samples import NCOL
from ..servo.state import LAYER_NAMES as LAYERS
from ..servo.state import PRESSING, PUNCTURED
from .common import SPEED_DEPTH_FRACTION, depth_verdict, dot3  # noqa: F401 (re-exported)
from .common import (C_CLAMPED, C_DEPTH, C_F, C_LAT, C_LAYER, C_LAYER_F, C_PUNCT, C_ROLL, C_STATE, C_T, C_TICK,
                     C_TORQUE, C_X)
from .common import angle_deg as _angle_deg
from .common import round_json as _r
from .insertion_stream import InsertionStream, _Press

DEFAULT_LATERAL_COMFORT_N = 0.5
CYCLE_PROMINENCE_M = 1e-3


def insertion_runs(state_skin: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) row indices of each contiguous run with the skin punctured."""
    inside = np.asarray(state_skin) == PUNCTURED
    if not inside.any():
        return []
    edges = np.diff(inside.astype(np.int8), prepend=0, append=0)
    starts = np.flatnonzero(edges == 1)
    ends = np.flatnonzero(edges == -1) - 1
    return list(zip(starts.tolist(), ends.tolist()))


def entry_tick(state_skin: np.ndarray, first: int) -> int:
    """The first tick of the pressing run that ends just before row ``first``, else ``first``."""
    i = first
    while i > 0 and state_skin[i - 1] == PRESSING:
        i -= 1
    return i


def continuous_depth(depth: np.ndarray, axial: np.ndarray, puncture: np.ndarray) -> np.ndarray:
    """``depth`` (m) with the steps at deeper-layer punctures added back (see the module docstring).

    On a tick whose ``puncture`` is fat or muscle (>= 1), the step is the tip's axial advance over
    that tick minus the change of ``depth``; it is kept for every later tick."""
    step = np.zeros_like(depth)
    if depth.size > 1:
        jump = np.diff(axial) - np.diff(depth)
        at = puncture[1:] >= 1
        step[1:] = np.where(at, np.maximum(jump, 0.0), 0.0)
    return depth + np.cumsum(step)


def _local_maxima(x: np.ndarray) -> np.ndarray:
    """Indices of the local maxima of ``x``: samples higher than the sample before them, followed by
    a run of equal samples and then a lower one; a flat top is taken at its middle (rounded down).
    The first and last samples are never maxima (scipy.signal.find_peaks' rule)."""
    n = x.size
    if n < 3:
        return np.zeros(0, np.int64)
    d = np.diff(x)
    change = np.flatnonzero(d != 0)  # steps that are not flat
    if change.size < 2:
        return np.zeros(0, np.int64)
    up = d[change] > 0
    # a rise at change[k] followed (after equal samples) by a fall at change[k + 1]
    k = np.flatnonzero(up[:-1] & ~up[1:])
    left = change[k] + 1
    right = change[k + 1]
    return (left + right) // 2


def _prominences(x: np.ndarray, peaks: np.ndarray) -> np.ndarray:
    """Each peak's topographic prominence: its height above the higher of the lowest points on either
    side before a strictly higher sample (or the signal's end)."""
    n = x.size
    xs = x.tolist()
    prev_higher = [-1] * n  # the previous strictly higher sample (monotonic stacks)
    stack: list[int] = []
    for i in range(n):
        while stack and xs[stack[-1]] <= xs[i]:
            stack.pop()
        prev_higher[i] = stack[-1] if stack else -1
        stack.append(i)
    next_higher = [n] * n  # the next strictly higher sample
    stack = []
    for i in range(n):
        while stack and xs[stack[-1]] < xs[i]:
            next_higher[stack.pop()] = i
        stack.append(i)
    out = np.empty(peaks.size)
    for j, p in enumerate(peaks.tolist()):
        left = float(x[prev_higher[p] + 1:p + 1].min())
        right = float(x[p:next_higher[p]].min())
        out[j] = x[p] - max(left, right)
    return out


def find_troughs(depth: np.ndarray, prominence: float) -> tuple[np.ndarray, np.ndarray]:
    """Troughs of ``depth`` with at least ``prominence``: (indices, prominences). The same result as
    ``scipy.signal.find_peaks(-depth, prominence=prominence)`` (tests/test_metrics.py compares them),
    without importing scipy.signal (about 2 s, the largest part of a short replay's start)."""
    x = -np.asarray(depth, dtype=np.float64)
    peaks = _local_maxima(x)
    if peaks.size == 0:
        return peaks, np.zeros(0)
    prom = _prominences(x, peaks)
    keep = prom >= prominence
    return peaks[keep], prom[keep]


def lift_thrust_cycles(t: np.ndarray, depth: np.ndarray, prominence_m: float = CYCLE_PROMINENCE_M) -> dict:
    """Lift-thrust cycles in a depth signal (m) sampled at times ``t`` (s): troughs of the depth with
    at least ``prominence_m`` prominence (:func:`find_troughs`)."""
    if depth.size < 3:
        return {"cycles": 0, "mean_amplitude_mm": None, "frequency_hz": None}
    troughs, prominences = find_troughs(depth, prominence_m)
    n = int(troughs.size)
    amp = float(np.mean(prominences)) * 1e3 if n else None
    freq = None
    if n >= 2:
        span = float(t[troughs[-1]] - t[troughs[0]])
        freq = (n - 1) / span if span > 0 else None
    return {"cycles": n, "mean_amplitude_mm": _r(amp, 3), "frequency_hz": _r(freq, 3)}


def _technique(run: np.ndarray, depth_c: np.ndarray, u: np.ndarray, ref: np.ndarray | None) -> dict:
    """The run's technique metrics (see the module docstring); ``ref``: the same rows replayed
    without rotation, or None."""
    from .technique import technique_metrics

    f = run[:, C_F:C_F + 3]
    table = {"t_s": run[:, C_T], "depth_mm": depth_c * 1e3, "roll_deg": run[:, C_ROLL],
             "torque_nmm": run[:, C_TORQUE], "f_axial_n": -dot3(f, u)}
    reference = None
    if ref is not None:
        reference = {"f_axial_n": -dot3(ref[:, C_F:C_F + 3], u)}
    return technique_metrics(table, reference)


def _reference_run(reference_rows, run: np.ndarray) -> np.ndarray | None:
    """The reference replay's rows on the same ticks as ``run``, or None if it does not hold them."""
    if reference_rows is None:
        return None
    ticks = run[:, C_TICK].astype(np.int64)
    ref_ticks = reference_rows[:, C_TICK].astype(np.int64)
    idx = np.searchsorted(ref_ticks, ticks)
    if idx.size == 0 or idx[-1] >= len(ref_ticks) or not np.array_equal(ref_ticks[idx], ticks):
        return None
    return reference_rows[idx]


def insertion_metrics(rows: np.ndarray, first: int, last: int, dt: float, target_mm, tissue=None,
                      lateral_comfort_n: float = DEFAULT_LATERAL_COMFORT_N, punctures=(), tip_depth=None,
                      reference_rows=None) -> dict:
    """Metrics of the insertion in rows ``first..last`` (inclusive; all with the skin punctured);
    ``reference_rows``: the session replayed without rotation (for the grasp felt), or None."""
    state = rows[:, C_STATE]
    e = entry_tick(state, first)
    run = rows[first:last + 1]
    t = run[:, C_T]
    p = run[:, C_X:C_X + 3]
    depth = run[:, C_DEPTH]
    entry = rows[e, C_X:C_X + 3].copy()
    lo, hi = float(target_mm[0]), float(target_mm[1])

    k_deep = int(np.argmax(depth))
    max_depth = float(depth[k_deep])
    direction = p[k_deep] - entry
    length = float(np.linalg.norm(direction))
    if tissue is not None:
        inward = -np.asarray(tissue.normal(0, entry), dtype=np.float64)
    else:
        inward = np.array([0.0, 0.0, -1.0])
    if length > 1e-6:
        u = direction / length
        angle = _angle_deg(u, inward)
    else:
        u = inward
        angle = None
    axial = dot3(p - entry, u)  # row by row, the same bits as the streamed metrics' blocks

    # speed: from the puncture (run's first tick) to the first tick at 90% of the max depth
    speed = None
    k90 = int(np.argmax(depth >= SPEED_DEPTH_FRACTION * max_depth))
    if k90 > 0 and t[k90] > t[0]:
        speed = (axial[k90] - axial[0]) / (t[k90] - t[0]) * 1e3

    reached = np.flatnonzero(depth >= lo * 1e-3)
    t_target = float(t[reached[0]] - rows[e, C_T]) if reached.size else None

    window = rows[e:last + 1]
    peaks = {name: _r(np.abs(window[:, c]).max(), 4) for name, c in zip(LAYERS, C_LAYER_F)}
    f_total = np.sqrt(np.einsum("ij,ij->i", window[:, C_F:C_F + 3], window[:, C_F:C_F + 3]))

    at_depth = min(lo * 1e-3, SPEED_DEPTH_FRACTION * max_depth)
    k_start = int(np.argmax(depth >= at_depth))
    dc = continuous_depth(depth, axial, run[:, C_PUNCT])
    cycles = lift_thrust_cycles(t[k_start:], dc[k_start:])

    lat = run[:, C_LAT]
    over = int(np.count_nonzero(lat > lateral_comfort_n))
    skin_punctured = bool(run[0, C_PUNCT] == 0)
    t_entry, t_exit = _r(rows[e, C_T], 4), _r(t[-1], 4)
    out = {
        "t_entry_s": _r(rows[e, C_T], 4),
        "t_inside_s": _r(t[0], 4),
        "t_exit_s": _r(t[-1], 4),
        "skin_punctured": skin_punctured,
        "entry_mm": [_r(v * 1e3, 3) for v in entry],
        "entry_offset_mm": _r(np.linalg.norm(entry) * 1e3, 3),
        "angle_deg": _r(angle, 2),
        "max_depth_mm": _r(max_depth * 1e3, 3),
        "depth_verdict": depth_verdict(max_depth * 1e3, (lo, hi)),
        "insertion_speed_mm_s": _r(speed, 3),
        "time_to_target_s": _r(t_target, 4),
        "peak_layer_force_n": peaks,
        "peak_total_force_n": _r(f_total.max(), 4),
        "lift_thrust": cycles,
        "lateral": {"ticks_over": over, "time_over_s": _r(over * dt, 4), "max_n": _r(lat.max(), 4)},
        "time_in_tissue_s": _r(len(run) * dt, 4),
    }
    if tip_depth is not None:
        out["max_tip_depth_mm"] = _r(max(float(tip_depth[e:last + 1].max()), 0.0) * 1e3, 3)
    out["punctures"] = [p for p in punctures if t_entry <= p["t_s"] <= t_exit]
    out["technique"] = _technique(run, dc, u, _reference_run(reference_rows, run))
    return contact_and_label(out, int(np.count_nonzero(run[:, C_LAYER] == BONE)),
                             int(np.count_nonzero(run[:, C_CLAMPED])), dt)


def session_metrics(rows, cfg, tissue=None, lateral_comfort_n: float = DEFAULT_LATERAL_COMFORT_N,
                    punctures=None, reference_rows=None) -> dict:
    """Metrics of one session's rows ((n, NCOL) array, oldest first): see the module docstring.

    ``cfg``: the :class:`~haptic_acu.base.config.TissueConfig` (its ``scene.target_depth_mm``).
    ``tissue``: the session's :class:`~haptic_acu.tissue.body.Tissue`, for the skin normal at each entry
    (default: -z, the normal at the acupoint). ``lateral_comfort_n``: the lateral-force comfort
    bound (N). ``punctures``: the summary's puncture list (:meth:`haptic_acu.session.report.SummarySink.summary`)
    if the caller has it; else found here with the same scan (needs ``tissue``). Without ``tissue``
    there is no ``max_tip_depth_mm`` and no ``punctures`` per insertion. ``reference_rows``: the same
    session replayed without rotation (the trajectory's ``roll_deg`` dropped), for each insertion's
    ``technique.grasp_felt``; None leaves it out."""
    rows = np.asarray(rows, dtype=np.float64)
    if rows.ndim != 2 or rows.shape[1] != NCOL:
        raise ValueError(f"sample rows must have shape (n, {NCOL}), got {rows.shape}")
    tip_depth = None
    if tissue is not None:
        from .scan import SessionScan, puncture_records, tip_depth_m
        tip_depth = tip_depth_m(rows[:, C_X:C_X + 3], tissue)
        if punctures is None:
            punctures = puncture_records(SessionScan(tissue).feed(rows, depth=tip_depth))
    target = tuple(float(v) for v in cfg.scene.target_depth_mm)
    dt = float(np.median(np.diff(rows[:, C_T]))) if len(rows) >= 2 else 0.0
    ref = None if reference_rows is None else np.asarray(reference_rows, dtype=np.float64)
    insertions = [insertion_metrics(rows, a, b, dt, target, tissue, lateral_comfort_n, punctures or (), tip_depth,
                                    ref) for a, b in insertion_runs(rows[:, C_STATE])]
    return _session_dict(insertions, int(np.count_nonzero(rows[:, C_STATE] == PUNCTURED)), dt, target,
                         lateral_comfort_n)


from ..tissue.layers import BONE  # noqa: E402 (the sample ``layer`` code of bone)
WITHHELD = ("the tip touched bone or the force was held at the device's limit during this insertion: its "
            "strokes felt the bone or the limit, not the tissue")


def contact_and_label(m: dict, bone_ticks: int, clamped_ticks: int, dt: float) -> dict:
    """An insertion's ``time_on_bone_s`` (ticks with the tip in bone) and ``time_at_force_limit_s``
    (ticks with the force clamped to the device's limit), and what they do to its technique: no
    label (``classification.withheld`` says why) when either is not zero; no grasp felt without
    any rotation. Shared by the batch and the streamed metrics; returns ``m`` updated (its
    technique dicts copied, not changed in place)."""
    m["time_on_bone_s"] = _r(bone_ticks * dt, 4)
    m["time_at_force_limit_s"] = _r(clamped_ticks * dt, 4)
    tech = dict(m["technique"])
    if not tech["twirl"]["total_rotation_deg"]:
        tech["grasp_felt"] = None
    if bone_ticks or clamped_ticks:
        tech["classification"] = dict(tech["classification"], label=None, twirl_vote=None, lift_thrust_vote=None,
                                      withheld=WITHHELD)
    m["technique"] = tech
    return m


def _session_dict(insertions, punctured_rows, dt, target, lateral_comfort_n) -> dict:
    """The session level of :func:`session_metrics` from its per-insertion dicts."""
    ticks_over = sum(m["lateral"]["ticks_over"] for m in insertions)
    max_lat = max((m["lateral"]["max_n"] for m in insertions), default=0.0)
    return {
        "insertions": len(insertions),
        "skin_punctures": sum(m["skin_punctured"] for m in insertions),
        "time_in_tissue_s": _r(punctured_rows * dt, 4),
        "target_depth_mm": list(target),
        "lateral_comfort_n": float(lateral_comfort_n),
        "lateral": {"ticks_over": ticks_over, "time_over_s": _r(ticks_over * dt, 4), "max_n": _r(max_lat, 4)},
        "per_insertion": insertions,
    }


class MedianCounter:
    """The exact median of a stream of values (``numpy.median``'s result) kept as its distinct values
    (sorted) and their counts: a session's tick intervals take a few hundred distinct values at most
    (the last bits of t_{i+1} - t_i), so this stays small."""

    def __init__(self):
        self.values = np.zeros(0)
        self.counts = np.zeros(0, dtype=np.int64)
        self.n = 0

    def add(self, values: np.ndarray) -> None:
        if values.size and self.values.size:  # usually every value has been seen: count them in place
            at = np.searchsorted(self.values, values)
            if at.max() < self.values.size and np.array_equal(self.values[at], values):
                self.counts += np.bincount(at, minlength=self.values.size)
                self.n += int(values.size)
                return
        if values.size:
            v, c = np.unique(values, return_counts=True)
            if self.values.size:
                v, inv = np.unique(np.concatenate((self.values, v)), return_inverse=True)
                c = np.bincount(inv, weights=np.concatenate((self.counts, c)), minlength=v.size).astype(np.int64)
            self.values, self.counts = v, c
            self.n += int(values.size)

    def median(self) -> float:
        if not self.n:
            return float("nan")
        want = np.array([(self.n - 1) // 2, self.n // 2])  # the middle one or two (sorted) positions
        at = np.searchsorted(np.cumsum(self.counts), want, side="right")
        return float(np.mean(self.values[at]))


class SessionMetricsScan:
    """:func:`session_metrics` on a stream of row blocks, in memory that does not grow with the
    session or with any one insertion's length.

    Each insertion is measured as its rows arrive (:class:`haptic_acu.analysis.insertion_stream.InsertionStream`:
    running extremes, reversals, strokes and troughs; no rows beyond its first 20 s), the pressing run
    before it (its entry) by its peaks (:class:`~haptic_acu.analysis.insertion_stream._Press`). The tick
    period (the median interval) is counted as it goes (:class:`MedianCounter`) and applied at
    :meth:`result`. The result equals :func:`session_metrics` on all the rows (tests/test_metrics.py
    on random block splits, tests/test_metrics_stream.py on the bundled trajectories; the
    insertion_stream module docstring states the one approximation, for insertions over 20 s that
    go deeper after it).

    ``entries``: each insertion's entry tick as a row index of the whole stream (for the figure's
    colours, :func:`haptic_acu.session.report.insertion_index`)."""

    def __init__(self, cfg, tissue=None, lateral_comfort_n: float = DEFAULT_LATERAL_COMFORT_N, reference_rows=None):
        self.target = tuple(float(v) for v in cfg.scene.target_depth_mm)
        # the same session replayed without rotation (session_metrics' reference_rows: its rows, or
        # only (ticks, forces (n, 3)) of them), or None
        self.ref = None
        if isinstance(reference_rows, tuple):
            self.ref = (np.asarray(reference_rows[0], dtype=np.float64), np.asarray(reference_rows[1], dtype=np.float64))
        elif reference_rows is not None:
            r = np.asarray(reference_rows, dtype=np.float64)
            self.ref = (r[:, C_TICK].copy(), r[:, C_F:C_F + 3].copy())
        self.tissue = tissue
        self.comfort = float(lateral_comfort_n)
        self.rows_seen = 0
        self.punctured_rows = 0
        self.dt = MedianCounter()
        self.insertions: list[tuple[dict, int]] = []  # (metrics without dt, run length)
        self.entries: list[int] = []
        self.streams: list = []  # the measured insertions' streams (their step_error_bound_m)
        self._press = None  # the open pressing run (a possible entry)
        self._open = None  # the open insertion's stream
        self._last_state = 0.0
        self._last_t: float | None = None
        self._done: dict | None = None

    def feed(self, rows: np.ndarray, tip: np.ndarray | None = None) -> None:
        """Rows (k, NCOL) in order; ``tip``: their tip depth (:func:`~haptic_acu.analysis.scan.tip_depth_m`),
        if the caller has it already."""
        rows = np.ascontiguousarray(rows, dtype=np.float64)  # the compiled passes read it by rows
        k = len(rows)
        if k == 0:
            return
        if rows.ndim != 2 or rows.shape[1] != NCOL:
            raise ValueError(f"sample rows must have shape (k, {NCOL}), got {rows.shape}")
        t = rows[:, C_T]
        self.dt.add(np.diff(t) if self._last_t is None else np.diff(t, prepend=self._last_t))
        self._last_t = float(t[-1])
        st = rows[:, C_STATE]
        self.punctured_rows += int(np.count_nonzero(st == PUNCTURED))
        if self.tissue is None:
            tip = None
        elif tip is None:
            from .scan import tip_depth_m
            tip = tip_depth_m(rows[:, C_X:C_X + 3], self.tissue)
        bounds = [0, *(np.flatnonzero(np.diff(st) != 0) + 1).tolist(), k]
        for a, b in zip(bounds[:-1], bounds[1:]):
            self._segment(rows[a:b], None if tip is None else tip[a:b], self.rows_seen + a, float(st[a]))
        self.rows_seen += k

    def _segment(self, seg: np.ndarray, tip, start: int, state: float) -> None:
        """Rows ``seg`` of one skin state, the first at stream index ``start``."""
        if state == PUNCTURED:
            if self._open is None:
                press = self._press if self._last_state == PRESSING and self._press is not None else _Press(start, seg[0])
                self._press = None
                if self.tissue is not None:
                    inward = -np.asarray(self.tissue.normal(0, press.entry), dtype=np.float64)
                else:
                    inward = np.array([0.0, 0.0, -1.0])
                self._open = InsertionStream(press, self.target, inward, self.comfort, self.ref)
                self.entries.append(press.index)
            self._open.feed(seg, tip)
        else:
            self._close()
            if state == PRESSING:
                if self._last_state != PRESSING or self._press is None:
                    self._press = _Press(start, seg[0])
                self._press.feed(seg, tip)
            else:
                self._press = None
        self._last_state = state

    def _close(self) -> None:
        if self._open is not None:
            self.insertions.append((self._open.result(), self._open.n))
            self.streams.append(self._open)
            self._open = None

    def result(self, punctures=()) -> dict:
        """The :func:`session_metrics` dict (an insertion still open at the end is measured here);
        ``punctures``: the summary's puncture list."""
        self._close()
        dt = self.dt.median() if self.rows_seen >= 2 else 0.0
        insertions = []
        for m, n_run in self.insertions:
            m = dict(m)
            over = m["lateral"]["ticks_over"]
            m["lateral"] = dict(m["lateral"], time_over_s=_r(over * dt, 4))
            m["time_in_tissue_s"] = _r(n_run * dt, 4)
            m["punctures"] = [p for p in punctures if m["t_entry_s"] <= p["t_s"] <= m["t_exit_s"]]
            m["technique"] = m.pop("technique")
            m = contact_and_label(m, m.pop("_bone_ticks"), m.pop("_clamped_ticks"), dt)
            insertions.append(m)
        return _session_dict(insertions, self.punctured_rows, dt, self.target, self.comfort)

"""Technique metrics of needle manipulation: twirling, lift-thrust forces, the grasp felt, and the
reinforcing / reducing / even classification (docs/model.md section 11.3, "Technique metrics").

Pure functions over a *sample table*: a mapping (dict of arrays, numpy structured array, ...)
from column name to a 1-D array, one entry per sample, oldest first. Columns and units (those of
``samples.csv``):

* ``t_s``       time (s), strictly increasing;
* ``depth_mm``  the tip's displacement along the insertion below the skin entry (mm, positive in),
  a continuous signal such as (p - entry) . u: not the model's ``depth_skin`` as it is today,
  which steps back about 1 mm in one tick at the fat and muscle punctures (those steps read as
  lifts; :func:`haptic_acu.analysis.metrics.continuous_depth` removes them);
* ``roll_deg``  the needle's cumulative roll (deg, positive clockwise seen from the handle);
* ``torque_nmm`` the twist torque (N*mm; optional);
* ``f_axial_n`` the tissue's force on the needle along its axis (N), positive pushing the needle
  out of the tissue (optional). It resists a thrust with a positive value and a lift with a
  negative one; the *resistance* of a stroke is ``+f_axial_n`` on a thrust, ``-f_axial_n`` on a
  lift.

Turning points. A signal's reversals are found with hysteresis (a "zigzag"): a reversal is a
running extreme from which the signal has come back by at least ``min_swing`` (5 deg for the
roll, 1 mm for the depth, beyond encoder and hand tremor). The start and end of the table are not
reversals.

Twirling (:func:`twirl_metrics`): ``cycles`` = (reversals + 1) // 2 (a twirl from rest and back
to rest has an odd or even number of reversals as it starts at one end of its swing or in the
middle: both count N for N back-and-forth turns); ``swing_deg`` the mean angle
turned between consecutive reversals, peak to peak (the textbooks' "twirling angle"; a roll of
A sin(2 pi f t) has swing 2A): the one twirl amplitude every output shows; ``frequency_hz`` = (reversals - 1)
/ 2 over the time from the first reversal to the last (exact for a sinusoid); ``net_rotation_deg``
last roll minus first; ``total_rotation_deg`` the sum of |roll increments|; ``mean_speed_deg_s``
the rotation between the first and last reversal over that time; ``peak_torque_nmm`` max |torque|.

Lift-thrust forces (:func:`stroke_forces`): the strokes are the depth's moves between consecutive
reversals (so the insertion before the first reversal and the withdrawal after the last are not
strokes). A thrust deepens the tip, a lift raises it. Over the samples of each stroke moving in its
direction faster than ``min_speed_mm_s`` the mean resistance and mean speed are taken; then the
means over thrusts and over lifts, and ``thrust_to_lift`` = mean thrust resistance / mean lift
resistance.

Grasp felt (:func:`grasp_felt`): the withdrawal is the final lift, from the last depth reversal to
the first sample out of the tissue (depth <= 0) or the end. Its resistance ``-f_axial_n`` is
compared with that of the *same withdrawal without rotation*: the same trajectory replayed
headless with its ``roll_deg`` column dropped (every other input identical), giving a reference
table on the same times. ``peak_ratio`` = peak resistance / reference peak, ``mean_ratio`` the
same with means. 1 means no grasp; Langevin et al. 2001 measured 2.67 after unidirectional and
1.52 after bidirectional rotation.

Classification (:func:`classify`), after the textbook rule (Cheng Xinnong (ed.), *Chinese
Acupuncture and Moxibustion*, Foreign Languages Press, Beijing, 1987; 3rd ed. 2010, reinforcing
and reducing methods): twirling with small amplitude, slowly, is reinforcing; with large amplitude,
fast, is reducing; heavy thrust with light lift is reinforcing, heavy lift with light thrust is
reducing; neither is even. The textbook gives directions, not numbers: the thresholds in
:class:`Rule` are ours, documented. Each available manipulation votes +1 (reinforcing), -1
(reducing) or 0 (even); the label is the sign of the sum ("even" when they cancel), None when the
insertion has neither twirling nor lift-thrust. The inputs are reported beside the label.
"""
from __future__ import annotations

from typing import Mapping, NamedTuple

import numpy as np

ROLL_MIN_SWING_DEG = 5.0
DEPTH_MIN_STROKE_MM = 1.0
MIN_SPEED_MM_S = 0.5
SOURCE = ("Cheng Xinnong (ed.), Chinese Acupuncture and Moxibustion, Foreign Languages Press, "
          "Beijing (1987; 3rd ed. 2010): reinforcing and reducing by twirling and by lifting-thrusting")


class Rule(NamedTuple):
    """Thresholds of the classification (ours; the textbook gives only the directions)."""

    small_swing_deg: float = 90.0   # a twirl of at most this swing is "small"
    large_swing_deg: float = 180.0  # at least this is "large"
    slow_hz: float = 1.0            # at most 60 twirls a minute is "slow"
    fast_hz: float = 2.0            # at least 120 a minute is "fast"
    heavy_ratio: float = 1.25       # thrust/lift resistance at least this: heavy thrust
    min_cycles: int = 2             # fewer twirling cycles do not vote


def _r(x, nd: int):
    if x is None:
        return None
    return round(float(x), nd) + 0.0


def turning_points(x, min_swing: float) -> np.ndarray:
    """Indices of the reversals of ``x`` with hysteresis ``min_swing`` (see the module docstring)."""
    x = np.asarray(x, dtype=np.float64)
    if not min_swing > 0:
        raise ValueError(f"min_swing must be > 0, got {min_swing}")
    out: list[int] = []
    direction = 0  # 0 until the signal first moves min_swing away from its start
    lo = hi = 0  # indices of the running extremes
    for i in range(1, len(x)):
        v = x[i]
        if direction == 0:
            if v > x[hi]:
                hi = i
            if v < x[lo]:
                lo = i
            if v - x[lo] >= min_swing:
                direction, hi = 1, i
            elif x[hi] - v >= min_swing:
                direction, lo = -1, i
        elif direction > 0:
            if v > x[hi]:
                hi = i
            elif x[hi] - v >= min_swing:
                out.append(hi)
                direction, lo = -1, i
        else:
            if v < x[lo]:
                lo = i
            elif v - x[lo] >= min_swing:
                out.append(lo)
                direction, hi = 1, i
    return np.asarray(out, dtype=np.int64)


def twirl_metrics(t_s, roll_deg, torque_nmm=None, min_swing_deg: float = ROLL_MIN_SWING_DEG) -> dict:
    """Twirling of a roll signal (see the module docstring)."""
    t = np.asarray(t_s, dtype=np.float64)
    roll = np.asarray(roll_deg, dtype=np.float64)
    rev = turning_points(roll, min_swing_deg)
    n = int(rev.size)
    swing = freq = speed = None
    if n >= 2:
        swings = np.abs(np.diff(roll[rev]))
        swing = float(swings.mean())
        span = float(t[rev[-1]] - t[rev[0]])
        if span > 0:
            freq = (n - 1) / 2.0 / span
            speed = float(np.abs(np.diff(roll[rev[0]:rev[-1] + 1])).sum()) / span
    peak = None
    if torque_nmm is not None and len(roll):
        peak = float(np.abs(np.asarray(torque_nmm, dtype=np.float64)).max())
    return {
        "cycles": (n + 1) // 2,
        "reversals": n,
        "swing_deg": _r(swing, 2),
        "frequency_hz": _r(freq, 3),
        "mean_speed_deg_s": _r(speed, 1),
        "net_rotation_deg": _r(roll[-1] - roll[0], 2) if len(roll) else 0.0,
        "total_rotation_deg": _r(np.abs(np.diff(roll)).sum(), 2) if len(roll) else 0.0,
        "peak_torque_nmm": _r(peak, 4),
    }


def _stroke_means(t, depth, f_axial, rev, min_speed):
    """Per stroke between consecutive reversals: (direction +1 thrust / -1 lift, mean speed mm/s,
    mean resistance N or None)."""
    v = np.gradient(depth, t)
    out = []
    for a, b in zip(rev[:-1], rev[1:]):
        sgn = 1.0 if depth[b] > depth[a] else -1.0
        seg = slice(a, b + 1)
        moving = sgn * v[seg] > min_speed
        if not moving.any():
            continue
        speed = float(np.mean(sgn * v[seg][moving]))
        res = None if f_axial is None else float(np.mean(sgn * f_axial[seg][moving]))
        out.append((sgn, speed, res))
    return out


def stroke_forces(t_s, depth_mm, f_axial_n=None, min_stroke_mm: float = DEPTH_MIN_STROKE_MM,
                  min_speed_mm_s: float = MIN_SPEED_MM_S) -> dict:
    """Thrust against lift: speeds and resistances of the lift-thrust strokes (module docstring)."""
    t = np.asarray(t_s, dtype=np.float64)
    depth = np.asarray(depth_mm, dtype=np.float64)
    f = None if f_axial_n is None else np.asarray(f_axial_n, dtype=np.float64)
    rev = turning_points(depth, min_stroke_mm)
    return summarise_strokes(_stroke_means(t, depth, f, rev, min_speed_mm_s))


def summarise_strokes(strokes) -> dict:
    """The thrust-against-lift summary of per-stroke ``(sign, speed mm/s, resistance N or None)``
    (+1 thrust, -1 lift): counts, mean speeds and resistances, their ratio. Shared by the batch
    :func:`stroke_forces` and the streamed insertion metrics."""

    def mean(sgn, k):
        vals = [s[k] for s in strokes if s[0] == sgn and s[k] is not None]
        return float(np.mean(vals)) if vals else None

    thrust_f, lift_f = mean(1.0, 2), mean(-1.0, 2)
    ratio = None
    if thrust_f is not None and lift_f is not None and lift_f > 0:
        ratio = thrust_f / lift_f
    return {
        "thrusts": sum(1 for s in strokes if s[0] > 0),
        "lifts": sum(1 for s in strokes if s[0] < 0),
        "thrust_speed_mm_s": _r(mean(1.0, 1), 3),
        "lift_speed_mm_s": _r(mean(-1.0, 1), 3),
        "thrust_resistance_n": _r(thrust_f, 4),
        "lift_resistance_n": _r(lift_f, 4),
        "thrust_to_lift": _r(ratio, 3),
    }


def withdrawal_window(depth_mm, min_stroke_mm: float = DEPTH_MIN_STROKE_MM) -> slice | None:
    """The final lift: from the last depth reversal to the first sample out of the tissue."""
    depth = np.asarray(depth_mm, dtype=np.float64)
    rev = turning_points(depth, min_stroke_mm)
    if rev.size == 0:
        return None
    a = int(rev[-1])
    if depth[-1] >= depth[a]:
        return None  # the table ends deeper than its last reversal: no withdrawal
    out = np.flatnonzero(depth[a:] <= 0.0)
    b = a + int(out[0]) if out.size else len(depth) - 1
    return slice(a, b + 1)


def grasp_felt(depth_mm, f_axial_n, f_axial_ref_n, min_stroke_mm: float = DEPTH_MIN_STROKE_MM) -> dict:
    """The withdrawal's resistance against that of the same withdrawal without rotation
    (``f_axial_ref_n``, on the same samples; module docstring)."""
    w = withdrawal_window(depth_mm, min_stroke_mm)
    if w is None:
        return {"peak_ratio": None, "mean_ratio": None, "peak_n": None, "reference_peak_n": None}
    res = -np.asarray(f_axial_n, dtype=np.float64)[w]
    ref = -np.asarray(f_axial_ref_n, dtype=np.float64)[w]
    peak, ref_peak = float(res.max()), float(ref.max())
    mean, ref_mean = float(res.mean()), float(ref.mean())
    return {
        "peak_ratio": _r(peak / ref_peak, 3) if ref_peak > 0 else None,
        "mean_ratio": _r(mean / ref_mean, 3) if ref_mean > 0 else None,
        "peak_n": _r(peak, 4),
        "reference_peak_n": _r(ref_peak, 4),
    }


def _twirl_vote(tw: dict, rule: Rule):
    if tw["cycles"] < rule.min_cycles or tw["swing_deg"] is None or tw["frequency_hz"] is None:
        return None
    swing, f = tw["swing_deg"], tw["frequency_hz"]
    if swing <= rule.small_swing_deg and f <= rule.slow_hz:
        return 1
    if swing >= rule.large_swing_deg and f >= rule.fast_hz:
        return -1
    return 0


def _lift_thrust_vote(st: dict, rule: Rule):
    ratio = st["thrust_to_lift"]
    if ratio is None:
        return None
    if ratio >= rule.heavy_ratio:
        return 1
    if ratio <= 1.0 / rule.heavy_ratio:
        return -1
    return 0


LABELS = {1: "reinforcing", -1: "reducing", 0: "even"}


def classify(twirl: dict, strokes: dict, rule: Rule = Rule()) -> dict:
    """Reinforcing / reducing / even from :func:`twirl_metrics` and :func:`stroke_forces` results."""
    tv, lv = _twirl_vote(twirl, rule), _lift_thrust_vote(strokes, rule)
    votes = [v for v in (tv, lv) if v is not None]
    label = LABELS[int(np.sign(sum(votes)))] if votes else None
    return {
        "label": label,
        "twirl_vote": None if tv is None else LABELS[tv],
        "lift_thrust_vote": None if lv is None else LABELS[lv],
        "inputs": {
            "twirl_cycles": twirl["cycles"],
            "swing_deg": twirl["swing_deg"],
            "frequency_hz": twirl["frequency_hz"],
            "thrust_to_lift": strokes["thrust_to_lift"],
            "thrust_speed_mm_s": strokes["thrust_speed_mm_s"],
            "lift_speed_mm_s": strokes["lift_speed_mm_s"],
        },
        "rule": rule._asdict(),
        "source": SOURCE,
    }


def technique_metrics(table: Mapping, reference: Mapping | None = None, rule: Rule = Rule()) -> dict:
    """Every technique metric of one insertion's sample table; ``reference`` is the table of the
    same replay without rotation (for the grasp felt; None leaves it out)."""
    t = np.asarray(table["t_s"], dtype=np.float64)
    depth = np.asarray(table["depth_mm"], dtype=np.float64)
    names = set(getattr(table, "keys", lambda: table.dtype.names)())
    roll = table["roll_deg"] if "roll_deg" in names else np.zeros_like(t)
    torque = table["torque_nmm"] if "torque_nmm" in names else None
    f_ax = table["f_axial_n"] if "f_axial_n" in names else None
    tw = twirl_metrics(t, roll, torque)
    st = stroke_forces(t, depth, f_ax)
    grasp = None
    if reference is not None and f_ax is not None:
        grasp = grasp_felt(depth, f_ax, reference["f_axial_n"])
    return {"twirl": tw, "lift_thrust_forces": st, "grasp_felt": grasp,
            "classification": classify(tw, st, rule)}

"""Grading against the point (``--point CODE``): each insertion against the atlas's prescription and
the patient's danger structures (docs/atlas.md, "Grading").

:class:`PointGrader` reads a session's sample rows block by block (bounded memory) and finds the
insertions as :mod:`haptic_acu.analysis.metrics` does (a run of ticks with the skin punctured; the
entry is the first tick of the skin's pressing run just before it, else the run's first tick). Per
insertion:

* ``entry_offset_mm``: the entry's distance from the point (the scene's origin);
* ``angle_from_normal_deg``, ``angle_error_deg``: the insertion direction u (entry -> the tip at its
  deepest along the needle) against the skin normal and against the prescribed direction;
  ``heading_error_deg``: for an oblique or transverse prescription, the angle in the skin plane
  between u's and the prescription's headings (None when perpendicular, or u is too near the
  normal to have a heading); ``direction_verdict``: "on target" within the point's tolerance;
* ``max_depth_mm`` (along the needle, ``depth_skin_m``) and ``depth_verdict`` against the point's
  range (``in range``, ``too shallow``, ``too deep``);
* ``danger_margin_mm``: per structure, the smallest distance from the tip to its surface over the
  insertion (negative: the tip went past the membrane, into the bone or the cylinder), with the
  structure where it was at that tick (breathing moves it);
* ``critical_errors``: each structure the tip reached (margin <= 0): which, when (``t_s``), how deep
  (``tip_depth_mm`` along the needle, and the structure's own depth then), and whether the tip
  broke through it (the servo's spring force past its ``f_break``, :mod:`haptic_acu.servo.danger`).
"""
from __future__ import annotations

import math

import numpy as np

from ..servo.danger import spring_of
from ..servo.samples import COL
from ..servo.state import PRESSING, PUNCTURED

_T, _X, _SKIN, _DEPTH = COL["t_s"], COL["x_m"], COL["state_skin"], COL["depth_skin_m"]
WARN_MM = 5.0  # ours: "guided" feedback warns when a structure is this close to the tip


def _r(x, nd):
    return None if x is None else round(float(x), nd) + 0.0


def depth_verdict(depth_mm: float, lo: float, hi: float) -> str:
    if depth_mm < lo:
        return "too shallow"
    if depth_mm > hi:
        return "too deep"
    return "in range"


def _angle(u, v) -> float:
    c = float(np.clip(np.dot(u, v) / (np.linalg.norm(u) * np.linalg.norm(v)), -1.0, 1.0))
    return math.degrees(math.acos(c))


class _Insertion:
    def __init__(self, entry_t: float, entry_p: np.ndarray, n_structures: int):
        self.entry_t = entry_t
        self.entry_p = entry_p.copy()
        self.deepest = -np.inf
        self.p_deep = entry_p.copy()
        self.t_last = entry_t
        self.margin = np.full(n_structures, np.inf)
        self.margin_depth = np.zeros(n_structures)  # the structure's depth at the smallest margin
        self.first = [None] * n_structures  # (t, tip depth along the needle, structure depth)
        self.max_pen = np.zeros(n_structures)


class PointGrader:
    """Streamed grading of one session's rows against ``anatomy`` (a realised point,
    :func:`haptic_acu.tissue.patient.realise`). Feed row blocks in order; :meth:`result`."""

    def __init__(self, anatomy, k_bone_n_per_mm: float = 1.0):
        self.anatomy = anatomy
        self.point = anatomy.point
        self.structures = anatomy.structures
        self.springs = [spring_of(s.kind, k_bone_n_per_mm) for s in self.structures]
        self.prescribed = np.asarray(self.point.direction.vector())
        self.insertions: list[dict] = []
        self._prev = 0
        self._press = None  # (t, p) of the current pressing run's first tick
        self._cur: _Insertion | None = None

    def feed(self, rows: np.ndarray) -> None:
        rows = np.asarray(rows)
        if rows.shape[0] == 0:
            return
        st = rows[:, _SKIN].astype(np.int64)
        t = rows[:, _T]
        p_mm = rows[:, _X:_X + 3] * 1e3
        depth_mm = rows[:, _DEPTH] * 1e3
        inside = st == PUNCTURED
        n = len(self.structures)
        margins = np.empty((n, rows.shape[0]))
        sdepth = np.empty((n, rows.shape[0]))
        for j, s in enumerate(self.structures):
            margins[j] = s.margin_mm(p_mm, t)
            sdepth[j] = s.depth_at(t)
        prev = np.concatenate(([self._prev], st[:-1]))
        # rows where something changes: a pressing run starts, a run starts or ends
        marks = np.flatnonzero((st != prev))
        bounds = np.concatenate((marks, [rows.shape[0]]))
        start = 0
        for b in bounds:
            if b > start and self._cur is not None:
                seg = slice(start, b)
                if inside[start]:
                    self._update(self._cur, t[seg], p_mm[seg], depth_mm[seg], margins[:, seg], sdepth[:, seg])
            if b >= rows.shape[0]:
                break
            s_new, s_old = st[b], prev[b]
            if s_old == PUNCTURED and self._cur is not None:
                self._close()
            if s_new == PRESSING:
                self._press = (float(t[b]), p_mm[b].copy())
            elif s_new == PUNCTURED:
                if s_old == PRESSING and self._press is not None:
                    et, ep = self._press
                else:
                    et, ep = float(t[b]), p_mm[b].copy()
                self._cur = _Insertion(et, ep, n)
            start = b
        self._prev = int(st[-1])

    def _update(self, ins: _Insertion, t, p, depth, margins, sdepth) -> None:
        k = int(np.argmax(depth))
        if depth[k] > ins.deepest:
            ins.deepest = float(depth[k])
            ins.p_deep = p[k].copy()
        ins.t_last = float(t[-1])
        for j in range(margins.shape[0]):
            m = margins[j]
            i = int(np.argmin(m))
            if m[i] < ins.margin[j]:
                ins.margin[j] = float(m[i])
                ins.margin_depth[j] = float(sdepth[j, i])
            ins.max_pen[j] = max(ins.max_pen[j], float(-m[i]))
            if ins.first[j] is None:
                hit = np.flatnonzero(m <= 0.0)
                if hit.size:
                    h = int(hit[0])
                    ins.first[j] = (float(t[h]), float(depth[h]), float(sdepth[j, h]))

    def _close(self) -> None:
        ins = self._cur
        self._cur = None
        self.insertions.append(self._grade(ins))

    def _grade(self, ins: _Insertion) -> dict:
        pt = self.point
        u = ins.p_deep - ins.entry_p
        normal = np.array([0.0, 0.0, -1.0])
        if np.linalg.norm(u) > 1e-6:
            a_normal = _angle(u, normal)
            a_err = _angle(u, self.prescribed)
            heading = None
            if pt.direction.kind != "perpendicular" and math.hypot(u[0], u[1]) > 1e-3 * np.linalg.norm(u):
                h = math.degrees(math.atan2(u[1], u[0]))
                heading = abs((h - pt.direction.heading_deg + 180.0) % 360.0 - 180.0)
            verdict = "on target" if a_err <= pt.direction.tolerance_deg else "off target"
        else:
            a_normal = a_err = heading = None
            verdict = None
        errors = []
        for j, s in enumerate(self.structures):
            if ins.first[j] is None:
                continue
            t_hit, d_hit, s_depth = ins.first[j]
            k, f_break = self.springs[j]
            errors.append({"structure": s.name, "kind": s.kind, "t_s": _r(t_hit, 4),
                           "tip_depth_mm": _r(d_hit, 3), "structure_depth_mm": _r(s_depth, 3),
                           "pierced": bool(k * ins.max_pen[j] * 1e-3 > f_break)})
        deepest = max(ins.deepest, 0.0)
        return {
            "t_entry_s": _r(ins.entry_t, 4),
            "t_exit_s": _r(ins.t_last, 4),
            "entry_mm": [_r(v, 3) for v in ins.entry_p],
            "entry_offset_mm": _r(float(np.linalg.norm(ins.entry_p)), 3),
            "angle_from_normal_deg": _r(a_normal, 2),
            "angle_error_deg": _r(a_err, 2),
            "heading_error_deg": _r(heading, 2),
            "direction_verdict": verdict,
            "max_depth_mm": _r(deepest, 3),
            "depth_verdict": depth_verdict(deepest, pt.depth.min_mm, pt.depth.max_mm),
            "danger_margin_mm": {s.name: _r(ins.margin[j], 3) if math.isfinite(ins.margin[j]) else None
                                 for j, s in enumerate(self.structures)},
            "critical_errors": errors,
        }

    def result(self) -> list[dict]:
        """The graded insertions (an insertion still open at the end of the rows is closed)."""
        if self._cur is not None:
            self._close()
        return self.insertions


def grade_rows(rows: np.ndarray, anatomy, k_bone_n_per_mm: float = 1.0) -> list[dict]:
    """The graded insertions of a whole session's rows (:class:`PointGrader` in one block)."""
    g = PointGrader(anatomy, k_bone_n_per_mm)
    g.feed(rows)
    return g.result()


def nearest(anatomy, p_mm, t_s: float):
    """(name, margin_mm) of the structure nearest the tip at ``p_mm`` (mm) and time ``t_s``, or
    None without structures: what the "guided" feedback warns of."""
    best = None
    for s in anatomy.structures:
        m = float(s.margin_mm(np.asarray(p_mm, dtype=float)[None, :], t_s)[0])
        if best is None or m < best[1]:
            best = (s.name, m)
    return best


def session_grade(insertions: list[dict]) -> dict:
    """Session totals: insertions, those in range and on target, critical errors by structure."""
    by = {}
    for ins in insertions:
        for e in ins["critical_errors"]:
            by[e["structure"]] = by.get(e["structure"], 0) + 1
    return {"insertions": len(insertions),
            "in_range": sum(1 for i in insertions if i["depth_verdict"] == "in range"),
            "on_target": sum(1 for i in insertions if i["direction_verdict"] == "on target"),
            "critical_errors": sum(by.values()),
            "critical_by_structure": by}

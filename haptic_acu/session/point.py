"""A session at an atlas point (``--point CODE``, ``--patient``, ``--feedback``): the config and the
servo model at the point, the grading sink, and what the summary and the end text gain.

Without a point none of this runs: the session's outputs are byte for byte those of the generic
tissue.
"""
from __future__ import annotations

from dataclasses import dataclass

from ..base.errors import UserError
from .sink import Sink, block_rows

# the grading, the atlas, the patient and the servo model are imported where a point session
# uses them: a command's parser (add_point_args) needs none of them

FEEDBACK = ("guided", "exam")


@dataclass(frozen=True)
class PointSetup:
    point: Point
    patient: Patient
    anatomy: Anatomy
    cfg: object  # the TissueConfig at the point (config_at)
    feedback: str = "guided"

    def model(self, tissue=None) -> NeedleModel:
        """The servo model at the point, its danger structures loaded."""
        from ..servo.step import NeedleModel

        m = NeedleModel(self.cfg, tissue)
        m.set_structures(self.anatomy)
        m.anatomy = self.anatomy  # what the sinks draw (rerun, status)
        return m

    def warning(self, p_mm, t_s: float) -> str:
        """The guided feedback's live warning for the tip at ``p_mm`` (mm), or ""."""
        if self.feedback != "guided":
            return ""
        from ..analysis.grading import WARN_MM, nearest

        near = nearest(self.anatomy, p_mm, t_s)
        if near is None or near[1] > WARN_MM:
            return ""
        name, m = near
        return f"{name.upper()} REACHED" if m <= 0.0 else f"{name} in {m:.1f} mm"


def add_point_args(parser) -> None:
    """``--point``, ``--patient`` and ``--feedback`` for a sub-command."""
    parser.add_argument("--point", metavar="CODE",
                        help="needle an atlas point (haptic-acu points lists them; or a .toml file of the same "
                             "schema): its layers, danger structures, depth range and direction, graded per insertion")
    parser.add_argument("--patient", metavar="SPEC",
                        help="with --point: sex=male|female,bmi=N,age=N (default a man, BMI 22, age 30), or "
                             "'random' / 'random:SEED' (drawn from published distributions, the seed recorded)")
    parser.add_argument("--feedback", choices=FEEDBACK, default="guided",
                        help="with --point: guided (default) warns before a structure; exam gives no live warning")


def setup(cfg, point_spec: str | None, patient_spec: str | None = None, feedback: str = "guided",
          source: str = "--patient") -> PointSetup | None:
    """The point session for ``--point`` (None without one). A patient or feedback without a point is
    refused (one line)."""
    if not point_spec:
        if patient_spec:
            raise UserError("--patient needs --point (the patient varies a point's anatomy)")
        return None
    if feedback not in FEEDBACK:
        raise UserError(f"--feedback: must be guided or exam, got {feedback!r}")
    from ..tissue.atlas import load_point
    from ..tissue.patient import config_at, parse_patient, realise

    point = load_point(point_spec)
    patient = parse_patient(patient_spec, source=source)
    anatomy = realise(point, patient)
    return PointSetup(point, patient, anatomy, config_at(cfg, anatomy), feedback)


def setup_from_args(cfg, args) -> PointSetup | None:
    return setup(cfg, getattr(args, "point", None), getattr(args, "patient", None),
                 getattr(args, "feedback", "guided") or "guided")


class GradeSink(Sink):
    """Grades the session's insertions against the point as the rows arrive (bounded memory)."""

    rows_only = True  # the rows (and the frame's time) only

    def __init__(self, ps: PointSetup):
        from ..analysis.grading import PointGrader

        self.ps = ps
        self.grader = PointGrader(ps.anatomy, ps.cfg.needle.bone_stiffness_n_per_mm)

    def on_frames(self, frames) -> None:
        rows, _ = block_rows(frames)
        if len(rows):
            self.grader.feed(rows)

    def on_frame(self, frame) -> None:
        self.on_frames((frame,))

    def result(self) -> list[dict]:
        return self.grader.result()


# per-insertion keys summary.json's metrics.per_insertion gains (the grading's, by insertion)
MERGED = ("angle_error_deg", "heading_error_deg", "direction_verdict", "danger_margin_mm", "critical_errors")


def add_to_summary(summary: dict, ps: PointSetup, graded: list[dict]) -> dict:
    """``point``, ``patient``, ``anatomy`` and ``point_grading`` into ``summary``; each of
    ``metrics.per_insertion`` gains the grading's :data:`MERGED` keys (same insertions, same order)."""
    from ..analysis.grading import session_grade

    summary["point"] = ps.point.code
    summary["patient"] = ps.patient.as_dict()
    summary["feedback"] = ps.feedback
    summary["anatomy"] = ps.anatomy.as_dict()
    summary["point_grading"] = {"depth_range_mm": [ps.point.depth.min_mm, ps.point.depth.max_mm],
                                "direction": {"kind": ps.point.direction.kind,
                                              "angle_from_normal_deg": ps.point.direction.angle_from_normal_deg,
                                              "heading_deg": ps.point.direction.heading_deg},
                                **session_grade(graded), "per_insertion": graded}
    per = (summary.get("metrics") or {}).get("per_insertion")
    if per is not None:
        for ins, g in zip(per, graded):
            for key in MERGED:
                ins[key] = g[key]
    return summary


def point_lines(summary: dict, width: int = 80) -> list[str]:
    """The end text's lines for a point session (none without one), wrapped to ``width`` columns."""
    if "point" not in summary:
        return []
    import textwrap

    def wrap(text, indent="  "):
        return textwrap.wrap(text, width, initial_indent=indent, subsequent_indent=indent + "  ")

    g = summary["point_grading"]
    p = summary["patient"]
    lo, hi = g["depth_range_mm"]
    seed = f" (random, seed {p['seed']})" if p.get("seed") is not None else ""
    out = wrap(f"point {summary['point']}: {g['direction']['kind']}, {lo:g}-{hi:g} mm; patient {p['sex']}, "
               f"BMI {p['bmi']:g}, age {p['age']:g}{seed}; {g['in_range']}/{g['insertions']} in range, "
               f"{g['on_target']} on target, {g['critical_errors']} critical error(s)")
    for n, i in enumerate(g["per_insertion"], 1):
        margins = ", ".join(f"{k} {'-' if v is None else f'{v:.1f}'} mm" for k, v in i["danger_margin_mm"].items())
        ang = "-" if i["angle_error_deg"] is None else f"{i['angle_error_deg']:.1f}"
        out += wrap(f"insertion {n} at {summary['point']}: {i['max_depth_mm']:.2f} mm, {i['depth_verdict']}; "
                    f"angle error {ang} deg; closest: {margins}")
        for e in i["critical_errors"]:
            out += wrap(f"CRITICAL: {e['structure']} reached at t={e['t_s']:.3f} s, needle {e['tip_depth_mm']:.2f} mm "
                        f"in (the {e['structure']} {e['structure_depth_mm']:.2f} mm deep)"
                        + ("; pierced" if e["pierced"] else ""), "    ")
    return out

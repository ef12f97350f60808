"""``haptic-acu compare A B [C ...]``: sessions side by side (say trainees' and an expert's).

The trajectories are replayed headless on simulated time (the same engine and kernels as
``haptic-acu replay``, no rerun recording) through one tissue built from the config. Their
:mod:`haptic_acu.analysis.metrics` are printed as a table, one column per session: the session totals, then
each insertion (``--insertion N``: only the N-th) with its punctures (the report's numbers:
:func:`haptic_acu.session.report.puncture_records`). Written into the output folder:

* ``compare.json``  every session's metrics; ``differences``: each later session minus the first, per
  insertion (``first_insertion_b_minus_a`` too when there are two sessions);
* ``compare.png``   the force along the outward normal ``F . u`` (N) against the tip's depth below
  the rest skin (mm): the axes and force component of force_depth.png, over the same layer bands,
  one colour per session, one panel per insertion, punctures marked.

``--models forcenet,msm,fem,bem,shf`` replays each trajectory once through each tissue model
(``model.kind``, docs/model.md s12), one column and one colour per model; compare.json's ``models``
then gives each model's precomputation time (``build_s``) and its replay's wall time per servo tick
(``tick_us``: p50 and p99 of one servo step, ``NeedleModel.step``, over 2 s of pressing the skin
at 0.5 mm/s: the cost a model adds, measured the same way for each).

Identical input gives byte-identical files (except ``models``' timings). The folder is built as ``<out>.partial`` and renamed when
complete. Bad input is a one-line error naming the file (and line), exit status 2.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from ..base.bundled import bundled_names, not_found_hint, resolve_trajectory
from ..base.config import MODEL_KINDS
from ..base.errors import UserError
from ..base.outputs import plain_text
from .options import add_config_args, config_from_args
from ..base.progress import step
from .replay import fresh_path
from ..servo.samples import COL, NCOL
from ..analysis.quantities import BY_NAME, QUANTITIES, fmt, value
from ..servo.state import PLACE_NAMES

COLOURS = ("#1f5fa8", "#d9661f", "#2e8b3e", "#8e3fa8", "#c0392b", "#17a2b8", "#7f7f7f", "#b8860b")
# per-insertion numbers whose difference from the first session goes into compare.json (by their one name)
DIFF_KEYS = tuple(q.name for q in QUANTITIES if q.path and q.unit and q.name != "t_entry_s")


def register(sub) -> None:
    p = sub.add_parser("compare", help="replay trajectories and compare their metrics and force-depth curves",
                       description="Replay needle trajectories (CSV t_s,x_mm,y_mm,z_mm), say trainees' and an "
                                   "expert's, headless through the same tissue; print their metrics side by side "
                                   "(every insertion, or --insertion N) and write compare.json and compare.png "
                                   "(force against depth, as in force_depth.png, one colour per session).")
    p.add_argument("sessions", nargs="+", metavar="TRAJECTORY",
                   help="trajectory CSVs, one per session (any number), or bundled trajectories by name ("
                        + bundled_names() + ")")
    add_config_args(p)
    p.add_argument("--out", metavar="DIR", help="output folder (default: a new folder under runs/; must be empty "
                                                "if it exists)")
    p.add_argument("--labels", nargs="+", metavar="NAME",
                   help="a name for each session, in order (default: the file names)")
    p.add_argument("--models", metavar="KIND,...",
                   help="replay each trajectory through each of these tissue models (model.kind: "
                        + ", ".join(MODEL_KINDS) + ")")
    p.add_argument("--insertion", type=int, metavar="N",
                   help="compare only each session's N-th insertion (1 = the first; default: all)")
    from ..session.point import add_point_args
    add_point_args(p)
    p.set_defaults(func=run)


def open_trajectory(path: Path, cfg):
    """A ScriptedDevice on ``path``, opened (the whole file validated). UserError if bad."""
    from haptic_acu.devices.scripted import ScriptedDevice

    if not path.is_file():
        raise UserError(f"{path}: trajectory file not found{not_found_hint()}")
    dev = ScriptedDevice(path, max_hand_speed_m_per_s=cfg.scene.max_hand_speed_m_per_s,
                         force_limit_n=cfg.safety.force_limit_n)
    dev.open()
    from ..session.replay import MAX_REPLAY_DURATION_S
    if dev.duration_s > MAX_REPLAY_DURATION_S:
        raise UserError(f"{path}: spans {dev.duration_s:.6g} s, more than a replay takes "
                        f"({MAX_REPLAY_DURATION_S:g} s); split the file")
    return dev


def parse_models(text: str | None) -> list[str]:
    """``--models a,b,...`` -> the model kinds, in order (UserError naming the option if bad)."""
    if text is None:
        return []
    kinds = [k.strip() for k in text.split(",") if k.strip()]
    for k in kinds:
        if k not in MODEL_KINDS:
            raise UserError(f"--models: unknown model {k!r} (known: {', '.join(MODEL_KINDS)})")
    if not kinds or len(set(kinds)) != len(kinds):
        raise UserError(f"--models: give distinct models separated by commas, got {text!r}")
    return kinds


def with_kind(cfg, kind: str):
    """``cfg`` with ``model.kind`` set to ``kind``."""
    import dataclasses

    return dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, kind=kind))


def replay_session(device, path: Path, cfg, tissue, point=None) -> tuple[dict, list, tuple]:
    """Play an opened device through a fresh model on simulated time: (its metrics, its punctures,
    its :func:`session_curve`); with ``point`` (a --point PointSetup) each insertion's metrics gain its
    grading against the point. Nothing grows with the session's length: the metrics are streamed
    (:class:`haptic_acu.analysis.metrics.SessionMetricsScan`), the figure gets the bounded envelope of
    :class:`haptic_acu.session.report.FigureRows` (every row of a session up to its cap, 50 s at 1 kHz)."""
    from ..session.engine import Session
    from ..servo.step import NeedleModel
    from ..session.report import SummarySink, puncture_records

    sink = SummarySink(cfg, keep_rows=False)
    sinks = [sink]
    if point is not None:
        from ..session.point import GradeSink
        grade = GradeSink(point)
        sinks.append(grade)
    model = point.model(tissue) if point is not None else NeedleModel(cfg, tissue)
    session = Session(cfg, device, sinks, clock="sim", model=model, dents=False)
    result = session.run()
    device.close()
    if result.fault:
        raise UserError(f"{path}: replay stopped: {result.fault}", exit_status=3)
    ev = puncture_records(sink.scan.punctures)
    metrics = sink.metrics(ev)
    if point is not None:
        from ..session.point import MERGED
        for ins, g in zip(metrics["per_insertion"], grade.result()):
            ins.update({k: g[k] for k in MERGED})
    rows, index = sink.figure_rows()
    return metrics, ev, session_curve(rows, tissue, ev, index)


# ---- the table --------------------------------------------------------------------------------
def _fmt(x, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def _tech(i, part: str, key: str):
    """An insertion's ``technique`` number (docs/model.md s11), None where it has none."""
    return ((i.get("technique") or {}).get(part) or {}).get(key)


def _puncture_peak(layer: str):
    def cell(i) -> str:
        peaks = [f"{p['peak_force_n']:.3f}" for p in i.get("punctures", ()) if p["layer"] == layer]
        return "/".join(peaks) or "-"
    return cell


def _quantity_row(q):
    return (q.label, lambda i: fmt(i, q))


# one row per quantity (analysis/quantities.py: the one name, label and resolution of each), and the
# punctures' peaks (the summary's punctures)
INSERTION_ROWS = tuple(_quantity_row(q) for q in QUANTITIES if q.label and q.path
                       and q.name not in ("time_in_tissue_s",)) + (
    ("skin puncture: peak |F| (N)", _puncture_peak("skin")),
    ("fat puncture: peak |F| (N)", _puncture_peak("fat")),
    ("muscle puncture: peak |F| (N)", _puncture_peak("muscle")),
)


def insertion_numbers(metrics, insertion: int | None) -> list[int]:
    """The insertion indices (0-based) to show: ``insertion`` (1-based) or all of the longest session's."""
    n = max((m["insertions"] for m in metrics), default=0)
    if insertion is not None:
        return [insertion - 1]
    return list(range(n))


def _closest(i) -> str:
    """An insertion's smallest margin to a danger structure (--point): 'name mm'."""
    m = {k: v for k, v in (i.get("danger_margin_mm") or {}).items() if v is not None}
    if not m:
        return "-"
    k = min(m, key=m.get)
    return f"{k} {m[k]:.1f}"


POINT_ROWS = (  # with --point
    ("angle error (deg)", lambda i: _fmt(i.get("angle_error_deg"), ".1f")),
    ("closest structure (mm)", _closest),
    ("critical errors", lambda i: ", ".join(e["structure"] for e in i.get("critical_errors", ())) or "none"),
)


def table_lines(labels, metrics, insertion: int | None = None) -> list[str]:
    """The side-by-side table, one column per session: totals, then each insertion shown (with
    --point, its grading against the point too)."""
    bound = metrics[0]["lateral_comfort_n"]
    lo, hi = metrics[0]["target_depth_mm"]
    rows = [
        ("insertions", [str(m["insertions"]) for m in metrics]),
        ("skin punctures", [str(m["skin_punctures"]) for m in metrics]),
        ("time in tissue (s)", [f"{m['time_in_tissue_s']:.3f}" for m in metrics]),
        (f"lateral force > {bound:g} N (s)", [f"{m['lateral']['time_over_s']:.3f}" for m in metrics]),
    ]
    for k in insertion_numbers(metrics, insertion):
        rows.append((f"insertion {k + 1} (target depth {lo:g}-{hi:g} mm):", None))
        graded = any("critical_errors" in i for m in metrics for i in m["per_insertion"])
        for name, fn in INSERTION_ROWS + (POINT_ROWS if graded else ()):
            rows.append((f"  {name}", [fn(m["per_insertion"][k]) if k < len(m["per_insertion"]) else "-"
                                       for m in metrics]))
    w0 = max(len(name) for name, _ in rows)
    widths = [max([len(lab)] + [len(cells[j]) for _, cells in rows if cells]) for j, lab in enumerate(labels)]
    out = ["  ".join([f"{'':<{w0}}"] + [f"{lab:>{w}}" for lab, w in zip(labels, widths)])]
    for name, cells in rows:
        if cells is None:
            out.append(name)
        else:
            out.append("  ".join([f"{name:<{w0}}"] + [f"{c:>{w}}" for c, w in zip(cells, widths)]).rstrip())
    return out


def differences(metrics) -> list[dict]:
    """Each later session minus the first, per insertion index both have (None where either is None)."""
    base = metrics[0]["per_insertion"]
    out = []
    for m in metrics[1:]:
        per = []
        for a, b in zip(base, m["per_insertion"]):
            per.append({k: _diff(a, b, k) for k in DIFF_KEYS})
        out.append({"insertions": m["insertions"] - metrics[0]["insertions"], "per_insertion": per})
    return out


def first_insertion_diff(metrics) -> dict:
    """B minus A for the first insertion's numbers (None where either is missing)."""
    a, b = (m["per_insertion"][0] if m["per_insertion"] else {} for m in metrics[:2])
    return {k: _diff(a, b, k) for k in DIFF_KEYS}


def _diff(a: dict, b: dict, name: str):
    """B minus A of one quantity, at its resolution (None where either has none)."""
    q = BY_NAME[name]
    va, vb = value(a, q), value(b, q)
    if va is None or vb is None:
        return None
    return round(vb - va, q.decimals) + 0.0


# ---- the figure -------------------------------------------------------------------------------
def session_curve(rows, tissue, punctures=None, index=None) -> tuple:
    """One session's curve for :func:`plot_curves`: (tip depth below the rest skin in mm, ``F . u``
    in N, insertion index per row, punctures, each puncture's insertion index, time in s, roll in
    deg). ``rows``: every row or the bounded envelope of
    :class:`haptic_acu.session.report.FigureRows` with its ``index``."""
    from ..session.report import SessionScan, insertion_index, puncture_records, radial_force_n, tip_depth_m, tissue_of

    tissue = tissue_of(tissue)
    rows = np.asarray(rows, dtype=np.float64).reshape(-1, NCOL)
    depth = tip_depth_m(rows[:, COL["x_m"]:COL["x_m"] + 3], tissue)
    if index is None:
        index = insertion_index(rows) if len(rows) else np.zeros(0, np.int64)
    idx = np.maximum(index, 0)
    ev = punctures if punctures is not None else puncture_records(SessionScan(tissue).feed(rows, depth))
    t = rows[:, COL["t_s"]]
    ev_idx = [int(idx[min(int(np.searchsorted(t, e["t_s"] - 5e-5)), len(idx) - 1)]) for e in ev]
    return depth * 1e3, radial_force_n(rows, tissue), idx, ev, ev_idx, t.copy(), rows[:, COL["roll_deg"]].copy()


def plot_compare(rows_list, labels, path, tissue, punctures_list=None, insertion: int | None = None,
                 dpi: int = 110, target_mm=None, force_limit_n=None) -> None:
    """``F . u`` (N) against the tip's depth below the rest skin (mm) for every session, as in
    force_depth.png (:func:`haptic_acu.session.report.tip_depth_m`, :func:`~haptic_acu.session.report.radial_force_n`,
    the same layer bands), one colour and line style per session, one panel per insertion
    (``insertion``, 1-based: that one only; each session's approach is drawn with its first
    insertion), punctures marked (``punctures_list``: each session's
    :func:`~haptic_acu.session.report.puncture_records`; else found here); see :func:`plot_curves`.
    ``tissue``: a Tissue or a TissueConfig (whose target depth and force limit are then drawn unless
    given). PNG without a date or software stamp: identical input gives identical bytes."""
    if hasattr(tissue, "scene"):
        target_mm = target_mm if target_mm is not None else tuple(tissue.scene.target_depth_mm)
        force_limit_n = force_limit_n if force_limit_n is not None else tissue.safety.force_limit_n
    curves = [session_curve(rows, tissue, None if punctures_list is None else punctures_list[j])
              for j, rows in enumerate(rows_list)]
    plot_curves(curves, labels, path, tissue, insertion, dpi, target_mm=target_mm, force_limit_n=force_limit_n)


# per session: line style and width, so sessions drawn on one another stay told apart (a dashed
# line over a solid one of another colour shows both)
STYLES = ("-", (0, (5, 3)), (0, (1.5, 2.5)), (0, (6, 2, 1.5, 2)))
WIDTHS = (2.6, 1.8, 1.4, 1.1)
TARGET_COLOUR = "0.3"  # no session colour: the hatch is told from every curve
LIMIT_COLOUR = "#c62828"
FORCE_SIGN = "+ = the tissue pushes the needle out"


def _style(j: int) -> dict:
    return {"color": COLOURS[j % len(COLOURS)], "ls": STYLES[j % len(STYLES)], "lw": WIDTHS[j % len(WIDTHS)]}


def same_as(curves) -> list[int | None]:
    """Per session: the index of an earlier session with the same curve (force and depth, every
    row), or None."""
    out: list[int | None] = []
    for j, c in enumerate(curves):
        out.append(next((i for i in range(j) if out[i] is None and curves[i][0].shape == c[0].shape
                         and np.array_equal(curves[i][0], c[0]) and np.array_equal(curves[i][1], c[1])), None))
    return out


@plain_text  # names (files, labels) are drawn as text, never as mathtext
def plot_curves(curves, labels, path, tissue, insertion: int | None = None, dpi: int = 110, target_mm=None,
                force_limit_n=None) -> None:
    """:func:`plot_compare` from each session's :func:`session_curve`.

    Top: force against depth, one panel per insertion, over the layer bands at rest, the target
    depth range hatched (``target_mm``) and the device's force limit as a dashed line
    (``force_limit_n``). Below: the same force against time (every session), and, when any session
    rolls the needle, its roll against time. Each session has its colour and line style (widest
    first), and a session whose curve equals an earlier one's says so in the legend."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    from ..session.report import _BAND_COLOURS, MAX_PANELS, tissue_of

    tissue = tissue_of(tissue)
    n_ins = max([int(c[2].max()) + 1 for c in curves if c[2].size] + [1])
    shown = [insertion - 1] if insertion is not None else list(range(min(n_ins, MAX_PANELS)))
    twirl = any(c[6].size and float(np.abs(c[6]).max()) > 0.0 for c in curves)
    ratios = [3.0, 1.6] + ([1.3] if twirl else [])
    fig = Figure(figsize=(max(9.5, 3.4 * len(shown) + 3.6), 5.2 + 2.2 * (len(ratios) - 1)), layout="constrained")
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(len(ratios), len(shown), height_ratios=ratios)
    axes = [fig.add_subplot(gs[0, 0])]
    axes += [fig.add_subplot(gs[0, j], sharex=axes[0], sharey=axes[0]) for j in range(1, len(shown))]
    ax_t = fig.add_subplot(gs[1, :])
    ax_r = fig.add_subplot(gs[2, :], sharex=ax_t) if twirl else None
    bounds = tissue.depths_at_acupoint() * 1e3
    all_d = [d for d, *_ in curves if d.size]
    lo = min([float(d.min()) for d in all_d] + [0.0])
    hi = max([float(d.max()) for d in all_d] + [float(bounds[2])] + ([float(target_mm[1])] if target_mm else []))
    pad = 0.02 * (hi - lo)
    x0, x1 = lo - pad, hi + pad
    edges = [*bounds, max(x1, float(bounds[3]))]
    handles = []
    for name, a, b in zip(PLACE_NAMES[1:], edges[:-1], edges[1:]):
        if b <= x0 or a >= x1:
            continue
        for ax in axes:
            ax.axvspan(a, b, color=_BAND_COLOURS[name], alpha=0.4, lw=0)
        handles.append(Patch(color=_BAND_COLOURS[name], alpha=0.4, label=f"{name} (at rest)"))
    if target_mm is not None:
        for ax in axes:
            ax.axvspan(float(target_mm[0]), float(target_mm[1]), facecolor="none", edgecolor=TARGET_COLOUR,
                       hatch="//", lw=1.0, alpha=0.45)
        handles.append(Patch(facecolor="none", edgecolor=TARGET_COLOUR, hatch="//",
                             label=f"target depth {float(target_mm[0]):g}-{float(target_mm[1]):g} mm"))
    if force_limit_n is not None:
        for ax in axes + [ax_t]:
            ax.axhline(float(force_limit_n), color=LIMIT_COLOUR, ls="--", lw=1.2)
        handles.append(Line2D([], [], color=LIMIT_COLOUR, ls="--", label=f"device force limit {force_limit_n:g} N"))
    f_all = [f for _, f, *_ in curves if f.size]
    for p, (ax, k) in enumerate(zip(axes, shown)):
        ax.axhline(0.0, color="0.6", lw=0.6)
        last = insertion is None and p == len(shown) - 1 and n_ins > len(shown)
        for j, (d, f, idx, ev, ev_idx, *_rest) in enumerate(curves):
            st = _style(j)
            sel = idx >= k if last else idx == k
            ax.plot(np.where(sel, d, np.nan), np.where(sel, f, np.nan), **st)
            for e, ki in zip(ev, ev_idx):
                if ki == k or (last and ki >= k):
                    ax.plot([e["tip_depth_mm"]], [e["peak_force_n"]], marker="v", ms=7, color=st["color"],
                            mec="k", mew=0.5, ls="none")
        ax.set_title(f"insertion {k + 1}{'+' if last else ''}", fontsize=9)
        ax.set_xlabel("tip depth below the rest skin (mm)")
        if p:
            ax.tick_params(labelleft=False)
    axes[0].set_xlim(x0, x1)
    if f_all:
        top = max(float(f.max()) for f in f_all)
        if force_limit_n is not None:
            top = max(top, float(force_limit_n))
        ylim = (min(-0.05, 1.1 * min(float(f.min()) for f in f_all)), max(0.1, 1.12 * top))
        axes[0].set_ylim(*ylim)
        ax_t.set_ylim(*ylim)
    axes[0].set_ylabel(f"force along the outward normal F . u (N)\n{FORCE_SIGN}")
    t_end = 0.0
    for j, c in enumerate(curves):
        t, f = c[5], c[1]
        if t.size:
            ax_t.plot(t, f, **_style(j))
            t_end = max(t_end, float(t[-1]))
            if ax_r is not None:
                ax_r.plot(t, c[6], **_style(j))
    ax_t.axhline(0.0, color="0.6", lw=0.6)
    ax_t.set_ylabel(f"F . u (N)\n{FORCE_SIGN}", fontsize=8)
    ax_t.set_title("force against time", fontsize=9)
    ax_t.set_xlim(0.0, t_end if t_end > 0 else 1.0)
    if ax_r is not None:
        ax_t.tick_params(labelbottom=False)
        ax_r.axhline(0.0, color="0.6", lw=0.6)
        ax_r.set_ylabel("roll (deg)\n+ = clockwise from the handle", fontsize=8)
        ax_r.set_title("twirling: the needle's roll against time", fontsize=9)
        ax_r.set_xlabel("time (s)")
    else:
        ax_t.set_xlabel("time (s)")
    twins = same_as(curves)
    for j, label in enumerate(labels):
        same = f" (same curve as {labels[twins[j]]})" if twins[j] is not None else ""
        handles.append(Line2D([], [], label=label + same, **_style(j)))
    handles.append(Line2D([], [], marker="v", ls="none", color="0.4", mec="k", mew=0.5,
                          label="puncture (peak |F| while pressed)"))
    fig.suptitle("Force against depth: " + " vs ".join(labels))
    axes[-1].legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False,
                    handlelength=3.5)
    fig.savefig(path, format="png", dpi=dpi, metadata={"Software": None})


# ---- the command ------------------------------------------------------------------------------
def _labels(args, paths) -> list[str]:
    if args.labels:
        if len(args.labels) != len(paths):
            raise UserError(f"--labels: give one name per session ({len(paths)}), got {len(args.labels)}")
        return list(args.labels)
    # a session's own recording (run's <out>/recording.csv) is named by its folder
    stems = [p.parent.name if p.stem == "recording" and p.parent.name else p.stem for p in paths]
    if len(set(stems)) == len(stems):
        return stems
    return [f"{s} ({chr(65 + i) if i < 26 else i + 1})" for i, s in enumerate(stems)]


def run(args) -> int:

    cfg = config_from_args(args)
    from ..session.point import setup_from_args
    args.point_setup = setup_from_args(cfg, args)  # --point: every session at the point, graded
    if args.point_setup is not None:
        cfg = args.point_setup.cfg
    paths = [resolve_trajectory(p) for p in args.sessions]
    if args.insertion is not None and args.insertion < 1:
        raise UserError(f"--insertion: 1 is the first insertion, got {args.insertion}")
    kinds = parse_models(args.models)
    if kinds:  # every trajectory through every model
        pairs = [(p, k) for p in paths for k in kinds]
        labels = list(args.labels) if args.labels else [k if len(paths) == 1 else f"{p.stem} {k}" for p, k in pairs]
        if len(labels) != len(pairs):
            raise UserError(f"--labels: give one name per replay ({len(pairs)}), got {len(labels)}")
        paths = [p for p, _ in pairs]
    else:
        labels = _labels(args, paths)
    args.kinds = [k for _, k in pairs] if kinds else [None] * len(paths)
    devices = [open_trajectory(p, cfg) for p in paths]  # all validated before anything runs
    if args.out:
        out = Path(args.out)
    else:
        name = "-vs-".join(p.stem for p in paths[:3]) + ("-etc" if len(paths) > 3 else "")
        out = fresh_path(Path("runs") / f"compare-{name}-{time.strftime('%Y%m%d-%H%M%S')}")
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: exists and is not a folder; choose another --out")
    if out.exists() and any(out.iterdir()):
        raise UserError(f"{out}: output folder exists and is not empty")

    from ..session.replay import OutputFolder  # exclusive and atomic; a user's DIR.partial is never deleted

    folder = OutputFolder(out)
    partial = folder.claim()  # before the work: a folder it may not use is refused at once
    try:
        rows, labels, metrics = _compare_into(partial, args, cfg, devices, paths, labels)
        folder.publish()
    except OSError as e:
        folder.discard()
        raise UserError(f"{out}: cannot write the comparison's files: {e.strerror or e}") from None
    except BaseException:
        folder.discard()
        raise
    finally:
        folder.release()
    for line in table_lines(labels, metrics, args.insertion):
        print(line)
    print(f"files: {out}/", file=sys.stdout)
    return 0


def tick_cost(cfg, tissue, ticks: int = 2000) -> dict:
    """p50 and p99 (us) of one servo step of ``cfg``'s model pressing the skin: straight down the
    z axis at 0.5 mm/s from 0.2 mm above the acupoint (1 mm in 2000 ticks: short of every model's
    break), on a warmed-up model."""
    from ..servo.step import NeedleModel

    model = NeedleModel(cfg, tissue)
    model.warm_up()
    z0 = 2e-4  # the acupoint is the skin's point at the origin, its outward normal +z
    v = np.array([0.0, 0.0, -0.5e-3])
    p = np.zeros(3)
    t = np.empty(ticks)
    clock = time.perf_counter_ns
    for i in range(ticks):
        p[2] = z0 - 0.5e-6 * i
        t0 = clock()
        model.step(p, v)
        t[i] = clock() - t0
    return {"p50": round(float(np.percentile(t, 50)) * 1e-3, 2), "p99": round(float(np.percentile(t, 99)) * 1e-3, 2)}


def _precompute(cfg) -> float:
    """Build (or load) ``cfg``'s tissue model's precomputation; its build time in seconds (0 from the cache)."""
    from ..tissue.baselines import contact_for

    c = contact_for(cfg)
    return 0.0 if c is None else c.build_s


def _compare_into(partial: Path, args, cfg, devices, paths, labels):
    """Replay every session through one tissue, then write compare.json and compare.png into ``partial``."""
    from ..tissue.body import Tissue

    with step("building the tissue"):
        tissue = Tissue.from_config(cfg)
    curves, metrics, costs = [], [], []
    for dev, p, kind in zip(devices, paths, args.kinds):
        c = cfg if kind is None else with_kind(cfg, kind)
        with step(f"replaying {p.name}" + (f" through {kind}" if kind else "")):
            t0 = time.perf_counter()
            build_s = _precompute(c)
            t1 = time.perf_counter()
            m, _, curve = replay_session(dev, p, c, tissue, point=getattr(args, "point_setup", None))
        if kind is not None:
            costs.append({"model": kind, "build_s": round(build_s if build_s else t1 - t0, 3),
                          "tick_us": tick_cost(c, tissue)})
        curves.append(curve)
        metrics.append(m)
    if args.insertion is not None and all(m["insertions"] < args.insertion for m in metrics):
        raise UserError(f"--insertion {args.insertion}: no session has that many insertions "
                        f"(they have {', '.join(str(m['insertions']) for m in metrics)})")
    doc = {
        "labels": labels,
        "sessions": [{"label": lab, "trajectory": p.name, "metrics": m} for lab, p, m in zip(labels, paths, metrics)],
        "differences": differences(metrics),
    }
    if any(args.kinds):
        doc["models"] = [dict(cost, label=lab) for cost, lab in zip(costs, labels)]
    if len(metrics) == 2:
        doc["first_insertion_b_minus_a"] = first_insertion_diff(metrics)
    ps = getattr(args, "point_setup", None)
    if ps is not None:
        doc.update(point=ps.point.code, patient=ps.patient.as_dict(), anatomy=ps.anatomy.as_dict())
    (partial / "compare.json").write_text(json.dumps(doc, indent=2, sort_keys=True, allow_nan=False) + "\n")
    plot_curves(curves, labels, partial / "compare.png", tissue, args.insertion,
                target_mm=tuple(cfg.scene.target_depth_mm), force_limit_n=cfg.safety.force_limit_n)
    return curves, labels, metrics

"""Sessions side by side (``haptic-acu compare``): trajectories replayed headless on simulated time
(the same engine and kernels as a replay, no rerun recording) through one tissue built from the
config, each optionally through several tissue models (``model.kind``, docs/model.md s12). Written
into an output folder by :func:`compare_into`:

* ``compare.json``  every session's metrics; ``differences``: each later session minus the first, per
  insertion (``first_insertion_b_minus_a`` too when there are two sessions;
  :mod:`haptic_acu.analysis.comparison`); with models, ``models``: each model's precomputation time
  (``build_s``) and its wall time per servo tick (``tick_us``, :func:`tick_cost`);
* ``compare.png``   the force along the outward normal ``F . u`` (N) against the tip's depth below
  the rest skin (mm): the axes and force component of force_depth.png, over the same layer bands,
  one colour per session, one panel per insertion, punctures marked (:func:`plot_curves`).

Identical input gives byte-identical files (except ``models``' timings).
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from ..analysis.comparison import differences, first_insertion_diff
from ..base.bundled import not_found_hint
from ..base.errors import UserError
from ..base.figlayout import gc_paused
from ..base.outputs import plain_text
from ..base.progress import step
from ..servo.samples import COL, NCOL

COLOURS = ("#1f5fa8", "#d9661f", "#2e8b3e", "#8e3fa8", "#c0392b", "#17a2b8", "#7f7f7f", "#b8860b")


def open_trajectory(path: Path, cfg):
    """A ScriptedDevice on ``path``, opened (the whole file validated). UserError if bad."""
    from haptic_acu.devices.scripted import ScriptedDevice

    if not path.is_file():
        raise UserError(f"{path}: trajectory file not found{not_found_hint()}")
    dev = ScriptedDevice(path, max_hand_speed_m_per_s=cfg.scene.max_hand_speed_m_per_s,
                         force_limit_n=cfg.safety.force_limit_n)
    dev.open()
    from .replay import MAX_REPLAY_DURATION_S
    if dev.duration_s > MAX_REPLAY_DURATION_S:
        raise UserError(f"{path}: spans {dev.duration_s:.6g} s, more than a replay takes "
                        f"({MAX_REPLAY_DURATION_S:g} s); split the file")
    return dev


def with_kind(cfg, kind: str):
    """``cfg`` with ``model.kind`` set to ``kind``."""
    return dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, kind=kind))


def replay_session(device, path: Path, cfg, tissue, point=None) -> tuple[dict, list, tuple]:
    """Play an opened device through a fresh model of ``cfg`` on simulated time: (its metrics, its
    punctures, its :func:`session_curve`); with ``point`` (a --point PointSetup) the model has the
    point's structures and each insertion's metrics gain its grading against the point. Nothing
    grows with the session's length: the metrics are streamed
    (:class:`haptic_acu.analysis.metrics.SessionMetricsScan`), the figure gets the bounded envelope of
    :class:`haptic_acu.session.report.FigureRows` (every row of a session up to its cap, 50 s at 1 kHz)."""
    from ..servo.step import NeedleModel
    from .engine import Session
    from .report import SummarySink, puncture_records

    sink = SummarySink(cfg, keep_rows=False)
    sinks = [sink]
    if point is not None:
        from .point import GradeSink
        grade = GradeSink(point)
        sinks.append(grade)
    # at a point, the point's structures in ``cfg``'s model (its model.kind: a --models replay)
    if point is not None:
        model = dataclasses.replace(point, cfg=cfg).model(tissue)
    else:
        model = NeedleModel(cfg, tissue)
    session = Session(cfg, device, sinks, clock="sim", model=model, dents=False)
    result = session.run()
    device.close()
    if result.fault:
        raise UserError(f"{path}: replay stopped: {result.fault}", exit_status=3)
    ev = puncture_records(sink.scan.punctures)
    metrics = sink.metrics(ev)
    if point is not None:
        from .point import MERGED
        for ins, g in zip(metrics["per_insertion"], grade.result()):
            ins.update({k: g[k] for k in MERGED})
    rows, index = sink.figure_rows()
    return metrics, ev, session_curve(rows, tissue, ev, index)


# ---- the figure -------------------------------------------------------------------------------
def session_curve(rows, tissue, punctures=None, index=None) -> tuple:
    """One session's curve for :func:`plot_curves`: (tip depth below the rest skin in mm, ``F . u``
    in N, insertion index per row, punctures, each puncture's insertion index, time in s, roll in
    deg). ``rows``: every row or the bounded envelope of
    :class:`haptic_acu.session.report.FigureRows` with its ``index``."""
    from .report import SessionScan, insertion_index, puncture_records, radial_force_n, tip_depth_m, tissue_of

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


@gc_paused()
@plain_text  # names (files, labels) are drawn as text, never as mathtext
def plot_curves(curves, labels, path, tissue, insertion: int | None = None, dpi: int = 110, target_mm=None,
                force_limit_n=None) -> None:
    """:func:`plot_compare` from each session's :func:`session_curve`.

    Top: force against depth, one panel per insertion, over the layer bands at rest, the target
    depth range hatched (``target_mm``) and the device's force limit as a dashed line
    (``force_limit_n``). Below: the same force against time (every session), and, when any session
    rolls the needle, its roll against time. Each session has its colour and line style (widest
    first), and a session whose curve equals an earlier one's says so in the legend."""
    from ..base.figlayout import new_figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    from ..base.figlayout import first_layout, fit_rows, save_png
    from .report import MAX_PANELS, layer_bands, tissue_of

    tissue = tissue_of(tissue)
    n_ins = max([int(c[2].max()) + 1 for c in curves if c[2].size] + [1])
    shown = [insertion - 1] if insertion is not None else list(range(min(n_ins, MAX_PANELS)))
    twirl = any(c[6].size and float(np.abs(c[6]).max()) > 0.0 for c in curves)
    ratios = [3.0, 1.6] + ([1.3] if twirl else [])
    fig = new_figure((max(9.5, 3.4 * len(shown) + 3.6), 5.2 + 2.2 * (len(ratios) - 1)), dpi=dpi)
    grid = first_layout(len(shown), ratios)  # where fit_rows starts; it places every axes before the save
    axes = [fig.add_axes(grid[0][0])]
    axes += [fig.add_axes(grid[0][j], sharex=axes[0], sharey=axes[0]) for j in range(1, len(shown))]
    ax_t = fig.add_axes(grid[1][0])
    ax_r = fig.add_axes(grid[2][0], sharex=ax_t) if twirl else None
    bounds = tissue.depths_at_acupoint() * 1e3
    all_d = [d for d, *_ in curves if d.size]
    lo = min([float(d.min()) for d in all_d] + [0.0])
    hi = max([float(d.max()) for d in all_d] + [float(bounds[2])] + ([float(target_mm[1])] if target_mm else []))
    pad = 0.02 * (hi - lo)
    x0, x1 = lo - pad, hi + pad
    handles = layer_bands(axes, bounds, x0, x1, alpha=0.4)
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
            marks = [(e["tip_depth_mm"], e["peak_force_n"]) for e, ki in zip(ev, ev_idx)
                     if ki == k or (last and ki >= k)]
            if marks:  # the session's punctures in this panel: one marker line, drawn in their order
                ax.plot([m[0] for m in marks], [m[1] for m in marks], marker="v", ms=7, color=st["color"],
                        mec="k", mew=0.5, ls="none")
        ax.set_title(f"insertion {k + 1}{'+' if last else ''}", fontsize=9, y=1.0)
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
    ax_t.set_title("force against time", fontsize=9, y=1.0)
    ax_t.set_xlim(0.0, t_end if t_end > 0 else 1.0)
    if ax_r is not None:
        ax_t.tick_params(labelbottom=False)
        ax_r.axhline(0.0, color="0.6", lw=0.6)
        ax_r.set_ylabel("roll (deg)\n+ = clockwise from the handle", fontsize=8)
        ax_r.set_title("twirling: the needle's roll against time", fontsize=9, y=1.0)
        ax_r.set_xlabel("time (s)")
    else:
        ax_t.set_xlabel("time (s)")
    twins = same_as(curves)
    for j, label in enumerate(labels):
        same = f" (same curve as {labels[twins[j]]})" if twins[j] is not None else ""
        handles.append(Line2D([], [], label=label + same, **_style(j)))
    handles.append(Line2D([], [], marker="v", ls="none", color="0.4", mec="k", mew=0.5,
                          label="puncture (peak |F| while pressed)"))
    suptitle = fig.suptitle("Force against depth: " + " vs ".join(labels))
    axes[-1].legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False,
                    handlelength=3.5)
    fit_rows(fig, [[[ax] for ax in axes], [[ax_t]]] + ([[[ax_r]]] if ax_r is not None else []), ratios, suptitle)
    save_png(fig, path, dpi)


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


def compare_into(partial: Path, cfg, devices, paths, labels, kinds, insertion: int | None = None, point=None):
    """Replay every session (opened ``devices`` of ``paths``; ``kinds``: each one's model.kind, or None
    for ``cfg``'s) through one tissue, then write compare.json and compare.png into ``partial``;
    returns (curves, labels, metrics). ``insertion`` (1-based): the figure's one insertion; ``point``:
    a --point PointSetup (``cfg`` is its config)."""
    from ..tissue.body import Tissue

    with step("building the tissue"):
        tissue = Tissue.from_config(cfg)
    curves, metrics, costs = [], [], []
    for dev, p, kind in zip(devices, paths, kinds):
        c = cfg if kind is None else with_kind(cfg, kind)
        with step(f"replaying {p.name}" + (f" through {kind}" if kind else "")):
            t0 = time.perf_counter()
            build_s = _precompute(c)
            t1 = time.perf_counter()
            m, _, curve = replay_session(dev, p, c, tissue, point=point)
        if kind is not None:
            costs.append({"model": kind, "build_s": round(build_s if build_s else t1 - t0, 3),
                          "tick_us": tick_cost(c, tissue)})
        curves.append(curve)
        metrics.append(m)
    if insertion is not None and all(m["insertions"] < insertion for m in metrics):
        raise UserError(f"--insertion {insertion}: no session has that many insertions "
                        f"(they have {', '.join(str(m['insertions']) for m in metrics)})")
    doc = {
        "labels": labels,
        "sessions": [{"label": lab, "trajectory": p.name, "metrics": m} for lab, p, m in zip(labels, paths, metrics)],
        "differences": differences(metrics),
    }
    if any(kinds):
        doc["models"] = [dict(cost, label=lab) for cost, lab in zip(costs, labels)]
    if len(metrics) == 2:
        doc["first_insertion_b_minus_a"] = first_insertion_diff(metrics)
    if point is not None:
        doc.update(point=point.point.code, patient=point.patient.as_dict(), anatomy=point.anatomy.as_dict())
    (partial / "compare.json").write_text(json.dumps(doc, indent=2, sort_keys=True, allow_nan=False) + "\n")
    plot_curves(curves, labels, partial / "compare.png", tissue, insertion,
                target_mm=tuple(cfg.scene.target_depth_mm), force_limit_n=cfg.safety.force_limit_n)
    return curves, labels, metrics

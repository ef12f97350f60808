"""The cohort report: per-trainee learning curves and a comparison between levels, as
``report.json`` and two PNG figures. Statistics come from scipy.stats; nothing hand-rolled.

Both work on the sessions table (one value per session: the mean over its insertions, see
:mod:`haptic_acu.cohort.tables`); failed sessions are left out. A session without an insertion has
no value: it is left out of the level comparison and is a gap at its place on its trainee's curve.

Learning curve (per trainee, per metric of :data:`REPORT_METRICS`): the trainee's sessions in
order of ``date`` when every one of them has a date, else in manifest order; x is the session's
rank (1, 2, ...), and with dates also the days since the trainee's first session. Reported: the
values, the Theil-Sen slope per session (:func:`scipy.stats.theilslopes`, robust to an odd
session) and Spearman's rho with its p-value (:func:`scipy.stats.spearmanr`), when the trainee has
at least 3 sessions with a value.

Level comparison (when the manifest has a ``level`` column with at least two levels, in order of
first appearance): per level the count, median and quartiles; per pair of levels the
Mann-Whitney U test (:func:`scipy.stats.mannwhitneyu`, two-sided) and two effect sizes from U:
the common-language effect size ``CL = U / (n1 n2)`` (the probability that a session of the first
level has the larger value, ties counting half) and the rank-biserial correlation ``2 CL - 1``
(Cliff's delta); with more than two levels also the Kruskal-Wallis test
(:func:`scipy.stats.kruskal`), and the figure annotates the first level against the last.
Sessions of one trainee are not independent: with few trainees, read the p-values as descriptive.
The pairwise tests grow with the square of the number of levels: with more than :data:`MAX_LEVELS`
levels they are run between the first :data:`MAX_LEVELS` only (``pairs_skipped`` counts the rest,
and a warning says so) and the figure shows those levels; the Kruskal-Wallis test takes them all.

Text from the manifest (trainee and level names) is drawn as text, never as mathtext or TeX.

Every statistic works on the values rounded to the metric's resolution
(:func:`haptic_acu.analysis.quantities.resolution`: the decimals it is reported at), so a difference
below it (economy of motion 1.0 against 0.999999999) is no difference. Each metric's entry in
report.json says which way is better (``better``: "lower", "higher", "zero" or "" for a description,
:func:`haptic_acu.analysis.quantities.better`), and so do the figures' titles.
"""
from __future__ import annotations

from itertools import combinations
from pathlib import Path

import numpy as np

from ..base.outputs import plain_text_figures
from ..analysis.quantities import at_resolution, better, resolution
from .sessions import _parse_date

MAX_LEVELS = 12  # pairwise tests (66 pairs) and the figure's boxes at most for this many levels

# (sessions-table column, axis label) of the metrics reported and plotted
REPORT_METRICS = [
    ("mean_economy_of_motion", "economy of motion"),
    ("mean_ldlj", "LDLJ (smoothness)"),
    ("mean_entry_offset_mm", "entry offset (mm)"),
    ("mean_angle_deg", "angle to normal (deg)"),
    ("mean_depth_error_mm", "depth error (mm)"),
    ("mean_duration_s", "insertion duration (s)"),
    ("mean_insertion_speed_mm_s", "insertion speed (mm/s)"),
    ("mean_peak_total_force_n", "peak |F| (N)"),
]


def _r(x, nd=6):
    if x is None:
        return None
    x = float(x)
    return None if not np.isfinite(x) else round(x, nd) + 0.0


def _sig(x, digits=4):
    """A p-value to ``digits`` significant figures (fixed places would round small ones to 0)."""
    if x is None or not np.isfinite(x):
        return None
    return float(f"{float(x):.{digits}g}")


def _at_resolution(col: str, v):
    """``v`` rounded to the metric's resolution (None stays None)."""
    return at_resolution(col, v)


BETTER_WORDS = {"lower": "lower is better", "higher": "higher is better", "zero": "closer to 0 is better"}


def metric_title(col: str, label: str) -> str:
    """A figure panel's title: the metric and which way is better."""
    b = BETTER_WORDS.get(better(col))
    return f"{label} ({b})" if b else label


def _usable(rows):
    return [r for r in rows if not r.get("error") and r.get("insertions")]


def _ordered(rows: list[dict]) -> list[dict]:
    dates = [_parse_date(r.get("date") or "") for r in rows]
    if rows and all(d is not None for d in dates):
        order = sorted(range(len(rows)), key=lambda i: (dates[i], i))
        return [rows[i] for i in order]
    return list(rows)


def learning_curves(rows: list[dict]) -> dict:
    from scipy import stats

    by_trainee: dict[str, list[dict]] = {}
    # every session that ran keeps its place on the curve; one without an insertion (the skin never
    # punctured) is a gap there, not a reason to shift the trainee's later sessions one place left
    for r in rows:
        if not r.get("error"):
            by_trainee.setdefault(r["trainee"], []).append(r)
    out = {}
    for trainee, rs in by_trainee.items():
        rs = _ordered(rs)
        dates = [_parse_date(r.get("date") or "") for r in rs]
        days = ([_r((d - dates[0]).total_seconds() / 86400.0, 4) for d in dates]
                if all(d is not None for d in dates) else None)
        entry = {"sessions": [r["session"] for r in rs], "dates": [r.get("date") or None for r in rs],
                 "days_since_first": days, "metrics": {}}
        for col, _ in REPORT_METRICS:
            y = [_at_resolution(col, r.get(col)) for r in rs]
            x = [i + 1 for i, v in enumerate(y) if v is not None]
            yv = [v for v in y if v is not None]
            m = {"values": [_r(v) for v in y], "theil_slope_per_session": None, "spearman_rho": None, "spearman_p": None,
                 "better": better(col), "resolution": resolution(col)}
            if len(yv) >= 3 and np.ptp(yv) > 0:
                m["theil_slope_per_session"] = _r(stats.theilslopes(yv, x).slope)
                rho = stats.spearmanr(x, yv)
                m["spearman_rho"], m["spearman_p"] = _r(rho.statistic), _sig(rho.pvalue)
            entry["metrics"][col] = m
        out[trainee] = entry
    return out


def level_comparison(rows: list[dict]) -> dict | None:
    from scipy import stats

    rows = [r for r in _usable(rows) if r.get("level")]
    levels = list(dict.fromkeys(r["level"] for r in rows))
    if len(levels) < 2:
        return None
    out = {"levels": levels, "metrics": {}}
    paired = levels[:MAX_LEVELS]
    if len(levels) > MAX_LEVELS:
        n = len(levels)
        out["pairs_skipped"] = n * (n - 1) // 2 - MAX_LEVELS * (MAX_LEVELS - 1) // 2
        import sys
        print(f"haptic-acu: warning: {n} levels: pairwise tests only between the first {MAX_LEVELS} "
              f"({out['pairs_skipped']} pairs skipped; report.json level_comparison)", file=sys.stderr)
    for col, _ in REPORT_METRICS:
        vals = {lv: np.array([_at_resolution(col, r[col]) for r in rows if r["level"] == lv and r.get(col) is not None],
                             float) for lv in levels}
        per = {lv: {"n": int(v.size), "median": _r(np.median(v)) if v.size else None,
                    "q1": _r(np.percentile(v, 25)) if v.size else None,
                    "q3": _r(np.percentile(v, 75)) if v.size else None} for lv, v in vals.items()}
        pairs = []
        for a, b in combinations(paired, 2):
            va, vb = vals[a], vals[b]
            p = {"a": a, "b": b, "n_a": int(va.size), "n_b": int(vb.size), "mannwhitney_u": None, "p_value": None,
                 "common_language": None, "rank_biserial": None, "median_difference": None}
            if va.size and vb.size:
                p["median_difference"] = _r(np.median(va) - np.median(vb))
                res = stats.mannwhitneyu(va, vb, alternative="two-sided")
                cl = float(res.statistic) / (va.size * vb.size)
                p.update(mannwhitney_u=_r(res.statistic), p_value=_sig(res.pvalue), common_language=_r(cl),
                         rank_biserial=_r(2 * cl - 1))
            pairs.append(p)
        entry = {"by_level": per, "pairs": pairs, "kruskal_h": None, "kruskal_p": None, "better": better(col),
                 "resolution": resolution(col)}
        present = [v for v in vals.values() if v.size]
        if len(levels) > 2 and len(present) >= 2 and np.ptp(np.concatenate(present)) > 0:
            kw = stats.kruskal(*present)
            entry["kruskal_h"], entry["kruskal_p"] = _r(kw.statistic), _sig(kw.pvalue)
        out["metrics"][col] = entry
    return out


def _axes_grid(n: int):
    """A figure (its own Agg canvas, nothing global from pyplot) with ``n`` axes in a grid."""
    from ..base.figlayout import new_figure

    ncol = 4 if n > 6 else 3
    nrow = -(-n // ncol)
    fig = new_figure((4.2 * ncol, 3.2 * nrow))
    axes = fig.subplots(nrow, ncol, squeeze=False)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    return fig, list(axes.flat)


def readable_y(ax, values) -> None:
    """Plain y tick labels (no offset such as ``1e-9+9.99999999e-1``) and, when the values (finite
    ones of ``values``) barely differ, a span of 10% of their size (at least 0.1) around them: a
    metric equal in every session reads as a flat line, not as a range blown up from rounding."""
    ax.ticklabel_format(axis="y", style="plain", useOffset=False)
    v = np.asarray([x for x in values if x is not None], float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return
    centre = 0.5 * (v.min() + v.max())
    half = 0.05 * max(abs(centre), 1.0)
    if v.max() - v.min() < 1e-6 * max(abs(centre), 1.0):
        ax.set_ylim(centre - half, centre + half)


def _session_axis_label(curves: dict) -> str:
    dated = [c["days_since_first"] is not None for c in curves.values()]
    if dated and all(dated):
        return "session number (by date)"
    return "session number (manifest order)" if not any(dated) else "session number (by date, else manifest order)"


def plot_learning_curves(curves: dict, path: Path, dpi: int = 100) -> None:
    from matplotlib import colormaps

    fig, axes = _axes_grid(len(REPORT_METRICS))
    xlabel = _session_axis_label(curves)
    many = len(curves) > 10
    cmap = colormaps["tab10"]
    for ax, (col, label) in zip(axes, REPORT_METRICS):
        longest = max((len(c["sessions"]) for c in curves.values()), default=0)
        table = np.full((len(curves), longest), np.nan)
        for i, (trainee, c) in enumerate(curves.items()):
            y = np.array([np.nan if v is None else v for v in c["metrics"][col]["values"]], float)
            table[i, :y.size] = y
            x = np.arange(1, y.size + 1)
            ax.plot(x, y, "-o", ms=3, lw=1, alpha=0.35 if many else 0.9,
                    color="0.5" if many else cmap(i % 10), label=None if many else trainee)
        if many and longest:
            with np.errstate(all="ignore"):
                med = np.nanmedian(table, axis=0)
            ax.plot(np.arange(1, longest + 1), med, "-", color="k", lw=2, label="median over trainees")
        ax.set_title(metric_title(col, label), fontsize=10)
        ax.set_xlabel(xlabel)
        ax.grid(alpha=0.3)
        readable_y(ax, table.ravel())
        if longest:
            ax.set_xticks(range(1, longest + 1, max(1, longest // 8)))
    handles, labels = axes[0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 8), fontsize=8, frameon=False)
    fig.suptitle("Learning curves: per-session mean over insertions, by trainee")
    fig.tight_layout(rect=(0, 0.06 if handles else 0, 1, 0.96))
    fig.savefig(path, dpi=dpi)


def plot_levels(comp: dict, rows: list[dict], path: Path, dpi: int = 100) -> None:
    fig, axes = _axes_grid(len(REPORT_METRICS))
    levels = comp["levels"][:MAX_LEVELS]
    usable = [r for r in _usable(rows) if r.get("level")]
    rng = np.random.default_rng(0)  # fixed jitter: identical figures for identical tables
    for ax, (col, label) in zip(axes, REPORT_METRICS):
        data = [np.array([_at_resolution(col, r[col]) for r in usable if r["level"] == lv and r.get(col) is not None],
                         float) for lv in levels]
        ax.boxplot([d if d.size else [np.nan] for d in data], tick_labels=levels, showfliers=False, widths=0.5)
        for i, d in enumerate(data):
            ax.plot(i + 1 + rng.uniform(-0.12, 0.12, d.size), d, "o", ms=3, alpha=0.6, color="C0")
        first_last = (levels[0], levels[-1])  # the extremes, when there are more than two levels
        pair = next(p for p in comp["metrics"][col]["pairs"] if (p["a"], p["b"]) == first_last)
        note = ""
        if pair["rank_biserial"] is not None:
            note = f"\n{pair['a']} vs {pair['b']}: r_rb = {pair['rank_biserial']:+.2f}, p = {pair['p_value']:.2g}"
        ax.set_title(metric_title(col, label) + note, fontsize=9.5)
        ax.grid(alpha=0.3, axis="y")
        readable_y(ax, np.concatenate(data) if data else [])
    shown = "" if len(comp["levels"]) <= MAX_LEVELS else f"first {MAX_LEVELS} of {len(comp['levels'])} levels; "
    fig.suptitle(f"Levels ({shown}per-session mean over insertions; box: quartiles; r_rb: rank-biserial effect size, "
                 f"> 0 when {levels[0]} is higher; p: Mann-Whitney)")
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    fig.savefig(path, dpi=dpi)


def write_report(out: Path, session_rows: list[dict], extra: dict) -> dict:
    """Compute the curves and the comparison, draw the figures, return the report dict (the caller
    writes report.json)."""
    curves = learning_curves(session_rows)
    comp = level_comparison(session_rows)
    figures = {}
    with plain_text_figures():  # names from the manifest are data, not markup
        if curves:
            plot_learning_curves(curves, out / "learning_curves.png")
            figures["learning_curves"] = "learning_curves.png"
        if comp:
            plot_levels(comp, session_rows, out / "levels.png")
            figures["levels"] = "levels.png"
    for name in ("learning_curves", "levels"):  # a figure an earlier run drew that this one cannot
        if name not in figures:
            (out / f"{name}.png").unlink(missing_ok=True)
    return dict(extra, learning_curves=curves, level_comparison=comp, figures=figures)

"""``study analyze``: the key is read only here. The paper's comprehensive score per model and the
statistics a reviewer asks for, from ratings.csv; the objective side from the sessions and a
common scripted path.

Outputs (in ``--out``):

* ``ratings_by_model.csv``  the ratings unblinded, in `haptic-acu score`'s format (system = the
  model, rater = the participant; a participant's repeated ratings of one model averaged), so
  ``haptic-acu score ratings_by_model.csv`` gives exactly the scores of ``report.json``
* ``score/``                `haptic-acu score`'s own files on it (weights.csv, scores.csv,
  score.json, scores.png: the Fig. 7-style bars)
* ``descriptives.csv``      per model and index: n, median, quartiles, IQR, mean
* ``friedman.csv``          per index (and the comprehensive score): Friedman chi2, p, Kendall's W
* ``wilcoxon.csv``          per index and pair of models: signed-rank statistic, p, Holm's p
* ``order.csv``             per index and trial position: mean and median rating; Friedman across
  positions, and the carry-over check, in report.json
* ``indices.png``           every index's ratings per model (box plots)
* ``order.png``             mean rating by trial position
* ``objective/``            each model on one scripted path (force against depth overlaid,
  punctures), and the trainees' session metrics per model (metrics_by_model.csv)
* ``report.json``           everything above
"""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from ..analysis import scoring
from ..analysis.scoring import INDICES
from ..base.errors import UserError
from . import stats
from .ratings import LABELS, fmt_score
from .store import Study, _csv_line

COMPREHENSIVE = "comprehensive_score"
DIGITS = 15  # as `haptic-acu score` writes its numbers


def num(x):
    """A number as written: rounded once to 15 significant digits (score's rule); None stays."""
    if x is None:
        return None
    x = float(x)
    return float(f"{x:.{DIGITS}g}") if math.isfinite(x) else None


def unblind(study: Study, key: dict) -> tuple[dict, dict, list]:
    """``values[(participant, model)]``: the list of that participant's rating vectors of the
    model; ``order[participant]``: their sequence of model indices; ``by_trial``: per rated trial
    (participant, trial, model index, values)."""
    _, rows = study.read_ratings()
    index = {m: i for i, m in enumerate(study.models)}
    order = {p: [index[study.model_of(key, t)] for t in study.trials_of(p)] for p in study.participants}
    values: dict = {}
    by_trial = []
    for r in rows:
        t = study.trial_of_rating(r.system, r.rater)
        m = study.model_of(key, t)
        values.setdefault((t.participant, m), []).append(r.values)
        by_trial.append((t.participant, t.trial, index[m], r.values))
    return values, order, by_trial


def ratings_by_model_text(study: Study, values: dict) -> str:
    """score's format, models in the study's order, participants in theirs. One rating: written as
    given; several (each model met K times): their mean, written to round-trip exactly."""
    lines = ["# The study's ratings unblinded by its key: system = model, rater = participant"
             + ("; a participant's ratings of one model averaged over their trials of it"
                if study.trials_per_model > 1 else ""),
             _csv_line(("system", "rater") + INDICES)]
    for m in study.models:
        for p in study.participants:
            vs = values.get((p, m))
            if not vs:
                continue
            if len(vs) == 1:
                cells = [fmt_score(v) for v in vs[0]]
            else:
                cells = [repr(float(np.mean([v[j] for v in vs]))) for j in range(len(INDICES))]
            lines.append(_csv_line([m, p] + cells))
    return "\n".join(lines) + "\n"


def read_by_model(path: Path) -> dict:
    """ratings_by_model.csv back as model -> (raters, matrix): the numbers exactly as score reads them."""
    out: dict = {}
    with open(path, encoding="utf-8") as f:
        rows = [r for r in csv.reader(line for line in f if line.strip() and not line.startswith("#"))]
    for r in rows[1:]:
        raters, xs = out.setdefault(r[0], ([], []))
        raters.append(r[1])
        xs.append([float(c) for c in r[2:]])
    return {m: (raters, np.array(xs)) for m, (raters, xs) in out.items()}


def analyze(study: Study, out: Path, alpha, mu: float) -> dict:
    """The ratings side of the analysis into ``out`` (see the module doc); returns report.json's dict."""
    key = study.key()
    values, order, by_trial = unblind(study, key)
    if not by_trial:
        raise UserError(f"{study.ratings_path}: no ratings yet")
    models = study.models
    people = study.participants
    out.mkdir(parents=True, exist_ok=True)
    by_model_path = out / "ratings_by_model.csv"
    by_model_path.write_text(ratings_by_model_text(study, values), encoding="utf-8")
    table = read_by_model(by_model_path)

    # participants x models x indices (nan: not rated)
    x = np.full((len(people), len(models), len(INDICES)), np.nan)
    for i, p in enumerate(people):
        for j, m in enumerate(models):
            if m in table and p in table[m][0]:
                x[i, j] = table[m][1][table[m][0].index(p)]

    # the paper's comprehensive score (score's computation on score's numbers)
    scored, not_scored = [], {}
    comp = np.full((len(people), len(models)), np.nan)
    for j, m in enumerate(models):
        if m not in table or len(table[m][0]) < 2:
            not_scored[m] = f"{0 if m not in table else len(table[m][0])} rater(s); the objective weights need 2"
            continue
        raters, xm = table[m]
        try:
            s = scoring.score_system(m, raters, xm, alpha, mu)
        except ValueError as e:
            not_scored[m] = str(e)
            continue
        scored.append(s)
        for r, f in zip(s.raters, s.scores):
            comp[people.index(r), j] = f

    report: dict = {
        "study": str(study.folder),
        "models": models,
        "participants": len(people),
        "rated_trials": len(by_trial),
        "planned_trials": len(people) * study.n_trials,
        "complete_participants": int(np.all(np.isfinite(x[:, :, 0]), axis=1).sum()),
        "scale": study.scale,
        "mu": mu,
        "subjective_weights": {n: num(a) for n, a in zip(INDICES, alpha)},
        "scores": {s.name: {"mean_score": num(s.mean_score), "scores": {r: num(f) for r, f in zip(s.raters, s.scores)},
                            "omega_combined": {n: num(w) for n, w in zip(INDICES, s.omega)},
                            "beta_objective": {n: num(w) for n, w in zip(INDICES, s.objective.beta)}}
                   for s in scored},
        "ranking": [s.name for s in sorted(scored, key=lambda s: -s.mean_score)],
        "not_scored": not_scored,
        "indices": {},
    }

    fr_rows, wx_rows, desc_rows, order_rows = [], [], [], []
    columns = [(name, x[:, :, k]) for k, name in enumerate(INDICES)] + [(COMPREHENSIVE, comp)]
    for name, mat in columns:
        fr = stats.friedman(mat)
        pairs = stats.wilcoxon_pairs(mat)
        adj = stats.holm([np.nan if q.p is None else q.p for q in pairs])
        desc = {m: stats.describe(mat[:, j]) for j, m in enumerate(models)}
        entry = {
            "friedman": {"n": fr.n, "k": fr.k, "chi2": num(fr.chi2), "p": num(fr.p), "kendall_w": num(fr.w),
                         "note": fr.note},
            "pairwise": [{"a": models[q.a], "b": models[q.b], "n": q.n, "nonzero": q.nonzero,
                          "statistic": num(q.statistic), "p": num(q.p), "p_holm": num(a),
                          "median_difference": num(q.median_difference)} for q, a in zip(pairs, adj)],
            "models": {m: {"n": d.n, "median": num(d.median), "q1": num(d.q1), "q3": num(d.q3),
                           "iqr": num(d.iqr), "mean": num(d.mean)} for m, d in desc.items()},
        }
        fr_rows.append([name, fr.n, fr.k, num(fr.chi2), num(fr.p), num(fr.w), fr.note])
        wx_rows += [[name, e["a"], e["b"], e["n"], e["nonzero"], e["statistic"], e["p"], e["p_holm"],
                     e["median_difference"]] for e in entry["pairwise"]]
        desc_rows += [[name, m, d["n"], d["median"], d["q1"], d["q3"], d["iqr"], d["mean"]]
                      for m, d in entry["models"].items()]
        if name != COMPREHENSIVE:
            k = INDICES.index(name)
            entry["order"] = _order(study, by_trial, order, k, order_rows, name)
        report["indices"][name] = entry

    _write_csv(out / "friedman.csv", ["index", "n", "k", "chi2", "p", "kendall_w", "note"], fr_rows)
    _write_csv(out / "wilcoxon.csv", ["index", "model_a", "model_b", "n", "nonzero", "statistic", "p", "p_holm",
                                      "median_difference_a_minus_b"], wx_rows)
    _write_csv(out / "descriptives.csv", ["index", "model", "n", "median", "q1", "q3", "iqr", "mean"], desc_rows)
    _write_csv(out / "order.csv", ["index", "position", "n", "mean", "median"], order_rows)
    plot_indices(out / "indices.png", x, comp, models, report)
    plot_order(out / "order.png", report, study.n_trials)
    return report


def _order(study, by_trial, order, k, rows, name) -> dict:
    """Ratings of index ``k`` by trial position: table rows, Friedman across positions, carry-over."""
    people = study.participants
    pos = np.full((len(people), study.n_trials), np.nan)
    ratings = {}
    for p, t, _m, v in by_trial:
        pos[people.index(p), t - 1] = v[k]
        ratings[p, t] = v[k]
    for t in range(study.n_trials):
        d = stats.describe(pos[:, t])
        rows.append([name, t + 1, d.n, num(d.mean), num(d.median)])
    fr = stats.friedman(pos)
    co = stats.carry_over(ratings, order)
    return {"position_friedman": {"n": fr.n, "chi2": num(fr.chi2), "p": num(fr.p), "kendall_w": num(fr.w),
                                  "note": fr.note},
            "position_mean": [num(stats.describe(pos[:, t]).mean) for t in range(study.n_trials)],
            "carry_over": {"kruskal_h": num(co.h), "p": num(co.p), "n": co.n,
                           "mean_residual_after": {study.models[g]: num(v) for g, v in co.mean_residual.items()}}}


def _write_csv(path: Path, header, rows) -> None:
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows([["" if c is None else c for c in r] for r in rows])


def _figure(figsize, nrows: int = 1, ncols: int = 1, **kw):
    """(figure, axes) on its own Agg canvas (nothing global from pyplot); ``kw`` to Figure.subplots."""
    from ..base.figlayout import new_figure

    fig = new_figure(figsize)
    return fig, fig.subplots(nrows, ncols, **kw)


def plot_indices(path: Path, x, comp, models, report=None) -> None:
    """One panel per index (and the comprehensive score): each model's ratings as a box plot
    (median, quartiles) with the participants' ratings as points."""
    names = list(INDICES) + [COMPREHENSIVE]
    fig, axes = _figure((13, 6.5), 2, 4, sharey=True)
    rng = np.random.default_rng(0)  # horizontal jitter of the points only
    for ax, (k, name) in zip(axes.ravel(), enumerate(names)):
        mat = comp if name == COMPREHENSIVE else x[:, :, k]
        data = [mat[:, j][np.isfinite(mat[:, j])] for j in range(len(models))]
        ax.boxplot(data, widths=0.6, showfliers=False, medianprops={"color": "k"})
        for j, d in enumerate(data):
            ax.plot(j + 1 + rng.uniform(-0.18, 0.18, d.size), d, "o", ms=2.5, alpha=0.5, color="tab:blue")
        ax.set_xticks(range(1, len(models) + 1), models, fontsize=8, rotation=30 if len(models) > 5 else 0)
        p = None if report is None else report["indices"][name]["friedman"]["p"]
        ax.set_title(LABELS.get(name, "comprehensive score (eq. 14)")
                     + ("" if p is None else f"\nFriedman p = {p:.2g}"), fontsize=9)
        ax.set_ylim(-0.3, 10.3)
        ax.grid(axis="y", alpha=0.3)
    for ax in axes[:, 0]:
        ax.set_ylabel("rating (0-10)")
    fig.suptitle("Ratings per model and index (box: quartiles, line: median; points: participants)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def plot_order(path: Path, report, n_trials) -> None:
    """Mean rating of each index by trial position: a drift here is an order effect."""
    fig, ax = _figure((7.5, 4.2))
    pos = np.arange(1, n_trials + 1)
    for name in INDICES:
        o = report["indices"][name]["order"]
        y = np.array([np.nan if v is None else v for v in o["position_mean"]])
        p = o["position_friedman"]["p"]
        ax.plot(pos, y, "o-", ms=3, label=f"{LABELS[name]} (p {'-' if p is None else f'{p:.2f}'})")
    ax.set_xticks(pos)
    ax.set_xlabel("trial position")
    ax.set_ylabel("mean rating")
    lo = np.nanmin([v for e in report["indices"].values() if "order" in e
                    for v in e["order"]["position_mean"] if v is not None] or [0.0])
    ax.set_ylim(max(0.0, np.floor(lo) - 1.0), 10.2)
    ax.set_title("Order check: mean rating by trial position (p: Friedman across positions)", fontsize=10)
    ax.legend(fontsize=7, loc="lower left", ncol=2)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


# ---------------------------------------------------------------------------------------------
# the objective side


def session_metrics(study: Study, key: dict) -> list[dict]:
    """One row per trial with a complete session (its latest complete attempt): the model and the
    session's numbers from its summary.json (flattened scalars)."""
    latest = {}
    for a in study.attempts():
        if a.status == "complete" and (a.folder / "summary.json").is_file():
            latest[a.participant, a.trial] = a
    rows = []
    for (p, t), a in sorted(latest.items()):
        try:
            s = json.loads((a.folder / "summary.json").read_text())
        except (OSError, ValueError):
            continue
        trial = study.plan[p, t]
        row = {"participant": p, "trial": t, "model": study.model_of(key, trial),
               "duration_s": s.get("duration_s"), "max_force_n": s.get("max_force_n"),
               "max_tip_depth_mm": s.get("max_tip_depth_mm"), "punctures": len(s.get("punctures", []))}
        for k, v in _flat(s.get("metrics") or {}).items():
            row[f"metrics_{k}"] = v
        rows.append(row)
    return rows


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}_"))
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out[f"{prefix}{k}"] = v
    return out


def metrics_by_model(rows: list[dict], models) -> list[dict]:
    """Per model: the number of sessions and the median of every numeric session metric."""
    cols = []
    for r in rows:
        cols += [c for c in r if c not in cols and c not in ("participant", "trial", "model")]
    out = []
    for m in models:
        mine = [r for r in rows if r["model"] == m]
        row = {"model": m, "sessions": len(mine)}
        for c in cols:
            v = np.array([r[c] for r in mine if isinstance(r.get(c), (int, float))], dtype=float)
            v = v[np.isfinite(v)]
            row[f"median_{c}"] = num(np.median(v)) if v.size else None
        out.append(row)
    return out


def objective(study: Study, out: Path, path, progress=None) -> dict:
    """Each model replayed headless on one scripted path (``path``), the force-depth curves
    overlaid (objective/force_depth.png), and the trainees' metrics per model."""
    from ..session.replay import replay_one

    key = study.key()
    odir = out / "objective"
    odir.mkdir(parents=True, exist_ok=True)
    curves, per_model = {}, {}
    for m in study.models:
        cfg = study.checked_config(key, m)
        summary = replay_one(path, odir / m, rrd=False, progress=False, cfg=cfg)
        per_model[m] = {"max_force_n": num(summary["max_force_n"]),
                        "max_tip_depth_mm": num(summary["max_tip_depth_mm"]),
                        "punctures": [{"layer": q["layer"], "t_s": num(q["t_s"]),
                                       "peak_force_n": num(q["peak_force_n"])} for q in summary["punctures"]]}
        curves[m] = _curve(odir / m / "samples.csv")
        if progress:
            progress(m)
    plot_curves(odir / "force_depth.png", curves, Path(path).name, per_model)
    rows = session_metrics(study, key)
    _write_dicts(odir / "sessions.csv", rows)
    by_model = metrics_by_model(rows, study.models)
    _write_dicts(odir / "metrics_by_model.csv", by_model)
    return {"path": str(path), "models": per_model, "sessions": len(rows), "metrics_by_model": by_model}


def _curve(samples: Path):
    t, depth, f = [], [], []
    with open(samples, newline="") as fh:
        for r in csv.DictReader(fh):
            t.append(float(r["t_s"]))
            depth.append(float(r["tip_depth_mm"]))
            f.append(float(r["f_n"]))
    return np.array(t), np.array(depth), np.array(f)


def plot_curves(path: Path, curves: dict, name: str, per_model: dict | None = None) -> None:
    """Left: force against depth over the first advance (to the deepest point), zoomed to the
    punctures, where the models differ; right: force against time over the whole path."""
    fig, (a1, a2) = _figure((11, 4.2), 1, 2)
    styles = ["-", "--", "-.", ":", (0, (5, 1)), (0, (3, 1, 1, 1)), (0, (1, 2)), (0, (8, 3))]
    reach = 0.0
    for k, (m, (t, d, f)) in enumerate(curves.items()):
        first = int(np.argmax(d)) + 1 if d.size else 0
        a1.plot(d[:first], f[:first], lw=1.2, ls=styles[k % len(styles)], label=m)
        a2.plot(t, f, lw=1.2, ls=styles[k % len(styles)], label=m)
        for q in (per_model or {}).get(m, {}).get("punctures", []):
            reach = max(reach, float(np.interp(q["t_s"], t, d)))
    if reach > 0:
        a1.set_xlim(-1.0, reach + 3.0)
    a1.set_xlabel("tip depth below the skin (mm)")
    a1.set_ylabel("force on the needle (N)")
    a1.set_title("force against depth, first advance" + (" (to the last puncture + 3 mm)" if reach else ""),
                 fontsize=10)
    a2.set_xlabel("time (s)")
    a2.set_title("force against time, the whole path", fontsize=10)
    for a in (a1, a2):
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    fig.suptitle(f"Every model on the same scripted path ({name})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def _write_dicts(path: Path, rows: list[dict]) -> None:
    cols: list[str] = []
    for r in rows:
        cols += [c for c in r if c not in cols]
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=cols or ["model"])
        w.writeheader()
        w.writerows([{k: ("" if v is None else v) for k, v in r.items()} for r in rows])


def analysis_lines(report) -> list[str]:
    """What ``haptic-acu study analyze`` prints of ``report``: the trials rated, the ranking, and per
    index Friedman's p, Kendall's W, the order effects and the Holm-significant pairs."""
    import textwrap

    out = []
    out.append(f"{report['rated_trials']} of {report['planned_trials']} trials rated; "
               f"{report['complete_participants']} participants rated every model")
    if report["ranking"]:
        out.append(textwrap.fill("ranking by mean comprehensive score: " + ", ".join(
            f"{m} {report['scores'][m]['mean_score']:.2f}" for m in report["ranking"]), 80,
            subsequent_indent="  "))
    for m, why in report["not_scored"].items():
        out.append(f"  {m}: not scored: {why}")
    out.append(f"{'index':<22}{'Friedman p':>11}{'W':>6}{'order p':>9}{'carry p':>9}")
    for name, e in report["indices"].items():
        fr = e["friedman"]
        o = e.get("order", {})
        cells = [fr["p"], fr["kendall_w"], o.get("position_friedman", {}).get("p"), o.get("carry_over", {}).get("p")]
        txt = ["-" if v is None else f"{v:.2g}" for v in cells]
        out.append(f"{name[:21]:<22}{txt[0]:>11}{txt[1]:>6}{txt[2] if o else '':>9}{txt[3] if o else '':>9}".rstrip())
        sig = [f"{q['a']} > {q['b']}" if (q["median_difference"] or 0) > 0 else f"{q['b']} > {q['a']}"
               for q in e["pairwise"] if q["p_holm"] is not None and q["p_holm"] < 0.05]
        if sig:
            out.append(textwrap.fill("Holm p < 0.05: " + ", ".join(sig), 80, initial_indent="  ",
                                     subsequent_indent="    "))
    return out

"""``haptic-acu score``: the paper's multi-index comprehensive weighted score (section 4.2).

Input files are CSV (UTF-8; blank lines and lines starting with ``#`` are ignored; the first other
line is the header, columns in any order, every one required, none unknown):

* ratings: ``system,rater,`` + the seven indices of :data:`haptic_acu.analysis.scoring.INDICES`, one row
  per rater and system, scores 0-10. Each system needs at least two raters.
* ``--subjective``: the seven index columns and exactly one row of weights summing to 1.
  Default: the paper's Table 3.
* ``--delphi``: ``round,expert,`` + the seven indices, one row per expert and round (rounds
  numbered 1, 2, ...), each row summing to 1. Each round's mean and standard deviation (population)
  per index are reported; the subjective weights are the mean of the first round in which no
  index's standard deviation exceeds ``--bound``. If no round gets there, the command says so on
  stderr (and in ``score.json``, ``"converged": false``) and uses the last round's mean: the
  statistics of an unfinished Delphi are still worth seeing, but the result is flagged.

Outputs go to ``--out`` (default a new ``runs/score-<timestamp>/``): ``weights.csv`` (per system
and index: E, sigma, alpha, beta, omega), ``scores.csv`` (per rater and system: eq. 14),
``score.json`` (everything, plus the Delphi rounds) and ``scores.png`` (grouped bars as Fig. 7).
"""
from __future__ import annotations

import csv
import datetime as _dt
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..analysis import scoring
from ..base.csvin import read_table
from ..base.errors import UserError
from ..base.outputs import Outputs, claim_folder, fresh_folder, plain_text_figures, safe_cell
from ..analysis.scoring import INDICES


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "score",
        help="multi-index weighted scoring of a user study (paper section 4.2)",
        description="Score rated systems by the paper's comprehensive weighted method: Delphi "
        "subjective weights (or given ones, default Table 3), mean-square-deviation objective "
        "weights per system (eq. 10-12), combined by eq. 13, rater scores by eq. 14.",
    )
    p.add_argument("ratings", metavar="RATINGS.csv",
                   help="columns system,rater," + ",".join(INDICES) + " (scores 0-10)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--subjective", metavar="WEIGHTS.csv",
                     help="the seven subjective weights (one row, summing to 1); default Table 3")
    src.add_argument("--delphi", metavar="ROUNDS.csv",
                     help="Delphi rounds: columns round,expert, + the seven indices")
    p.add_argument("--bound", type=float, default=scoring.PAPER_DELPHI_BOUND,
                   help="Delphi bound on each index's standard deviation (default %(default)s)")
    p.add_argument("--mu", type=float, default=scoring.PAPER_MU,
                   help="preference coefficient of eq. 13, 0 < mu < 1 (default %(default)s)")
    p.add_argument("--out", metavar="DIR", help="output folder (default: runs/score-<timestamp>/)")
    p.set_defaults(func=run)


# ---------------------------------------------------------------------------------------------
# CSV reading with file/line-named errors


@dataclass(frozen=True)
class _Row:
    line: int
    cells: dict[str, str]


def _read_csv(path: str, columns: tuple[str, ...], what: str = "ratings file") -> list[_Row]:
    """Rows of a CSV whose header must be exactly ``columns`` (any order). '#' lines are comments.
    Read by :func:`haptic_acu.base.csvin.read_table` (its limits and one-line errors)."""
    table = read_table(path, what)
    header, header_line = table.header, table.header_line
    seen = set()
    for name in header:
        if name in seen:
            raise UserError(f"{path}: line {header_line}: column {name!r} appears twice")
        seen.add(name)
    unknown = [c for c in header if c not in columns]
    if unknown:
        raise UserError(f"{path}: line {header_line}: unknown column {unknown[0]!r} "
                        f"(expected {','.join(columns)})")
    missing = [c for c in columns if c not in seen]
    if missing:
        raise UserError(f"{path}: line {header_line}: missing column(s) {','.join(missing)}")
    rows: list[_Row] = []
    for row in table.rows:
        fields = [f.strip() for f in row.fields]
        if len(fields) != len(header):
            raise UserError(f"{path}: line {row.line}: {len(fields)} fields, but the header "
                            f"(line {header_line}) has {len(header)}")
        rows.append(_Row(row.line, dict(zip(header, fields))))
    if not rows:
        raise UserError(f"{path}: line {header_line}: header but no data rows")
    return rows


def _number(path: str, row: _Row, col: str, lo: float, hi: float) -> float:
    s = row.cells[col]
    try:
        v = float(s)
    except ValueError:
        raise UserError(f"{path}: line {row.line}: {col} = {s!r} is not a number") from None
    if not math.isfinite(v):
        raise UserError(f"{path}: line {row.line}: {col} = {s!r} is not a finite number")
    if not lo <= v <= hi:
        raise UserError(f"{path}: line {row.line}: {col} = {s} is outside {lo:g}-{hi:g}")
    return v


def _name(path: str, row: _Row, col: str) -> str:
    s = row.cells[col]
    if not s:
        raise UserError(f"{path}: line {row.line}: empty {col}")
    return s


def _weight_row(path: str, row: _Row) -> np.ndarray:
    w = np.array([_number(path, row, c, 0.0, 1.0) for c in INDICES])
    s = math.fsum(w.tolist())
    if abs(s - 1.0) > scoring.WEIGHT_SUM_TOL:
        raise UserError(f"{path}: line {row.line}: weights sum to {s:.9g}, not 1 "
                        f"(tolerance {scoring.WEIGHT_SUM_TOL:g})")
    return w


@dataclass(frozen=True)
class Ratings:
    """One system's ratings as read: rater names, the score matrix and the file lines."""

    system: str
    raters: tuple[str, ...]
    x: np.ndarray  # raters x indices, 0-10
    lines: tuple[int, ...]


def read_ratings(path: str) -> list[Ratings]:
    """Read a ratings CSV into per-system score matrices, systems in order of first appearance."""
    rows = _read_csv(path, ("system", "rater") + INDICES)
    by_system: dict[str, list[tuple[str, np.ndarray, int]]] = {}
    seen: dict[tuple[str, str], int] = {}
    for row in rows:
        system, rater = _name(path, row, "system"), _name(path, row, "rater")
        if (system, rater) in seen:
            raise UserError(f"{path}: line {row.line}: rater {rater!r} already scored system "
                            f"{system!r} on line {seen[system, rater]}")
        seen[system, rater] = row.line
        x = np.array([_number(path, row, c, scoring.SCORE_MIN, scoring.SCORE_MAX) for c in INDICES])
        by_system.setdefault(system, []).append((rater, x, row.line))
    out = []
    for system, entries in by_system.items():
        if len(entries) < 2:
            raise UserError(f"{path}: line {entries[0][2]}: system {system!r} has only one rater; "
                            f"the objective weights need at least 2")
        out.append(Ratings(system, tuple(e[0] for e in entries), np.array([e[1] for e in entries]),
                           tuple(e[2] for e in entries)))
    return out


def read_subjective(path: str) -> np.ndarray:
    """Read a one-row CSV of the seven subjective weights (summing to 1)."""
    rows = _read_csv(path, INDICES, "subjective weights file")
    if len(rows) != 1:
        raise UserError(f"{path}: line {rows[1].line}: expected exactly one row of weights, "
                        f"found {len(rows)}")
    return _weight_row(path, rows[0])


def read_delphi(path: str) -> tuple[list[np.ndarray], list[tuple[int, ...]]]:
    """Read Delphi rounds: per round (1, 2, ...) the experts x indices weight matrix and lines."""
    rows = _read_csv(path, ("round", "expert") + INDICES, "Delphi rounds file")
    rounds: dict[int, list[tuple[np.ndarray, int]]] = {}
    seen: dict[tuple[int, str], int] = {}
    for row in rows:
        s = row.cells["round"]
        try:
            k = int(s)
        except ValueError:
            raise UserError(f"{path}: line {row.line}: round = {s!r} is not a whole number") from None
        if k < 1:
            raise UserError(f"{path}: line {row.line}: round = {k}; rounds are numbered from 1")
        expert = _name(path, row, "expert")
        if (k, expert) in seen:
            raise UserError(f"{path}: line {row.line}: expert {expert!r} already gave round {k} "
                            f"weights on line {seen[k, expert]}")
        seen[k, expert] = row.line
        rounds.setdefault(k, []).append((_weight_row(path, row), row.line))
    numbers = sorted(rounds)
    for want, k in enumerate(numbers, start=1):
        if k != want:
            first = min(line for _, line in rounds[k])
            raise UserError(f"{path}: line {first}: round {k} present but round {want} missing")
    for k in numbers:
        if len(rounds[k]) < 2:
            raise UserError(f"{path}: line {rounds[k][0][1]}: round {k} has only one expert; "
                            f"a standard deviation needs at least 2")
    return ([np.array([w for w, _ in rounds[k]]) for k in numbers],
            [tuple(line for _, line in rounds[k]) for k in numbers])


# ---------------------------------------------------------------------------------------------
# The command


def _fmt_weights(w) -> str:
    return " ".join(f"{n}={v:.3f}" for n, v in zip(INDICES, w))


OUR_FILES = ("weights.csv", "scores.csv", "score.json", "scores.png")


def _out_dir(args):
    """The output folder (``--out``, or a new ``runs/score-<time>``) checked under the output rule
    (new or empty; never one of the inputs) and held alone; returns (folder, lock)."""
    if args.out:
        d = Path(args.out)
    else:
        d = fresh_folder(Path("runs") / f"score-{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}")
    Outputs().input("RATINGS.csv", args.ratings).input("--subjective", args.subjective).input(
        "--delphi", args.delphi).folder("--out", d, files=OUR_FILES).check()
    return d, claim_folder(d)


def run(args) -> int:
    mu, bound = args.mu, args.bound
    if not (math.isfinite(mu) and 0.0 < mu < 1.0):
        raise UserError(f"--mu {mu}: must satisfy 0 < mu < 1")
    if not (math.isfinite(bound) and bound > 0):
        raise UserError(f"--bound {bound}: must be a positive number")

    systems = read_ratings(args.ratings)
    delphi_result = None
    if args.delphi:
        rounds, _ = read_delphi(args.delphi)
        delphi_result = scoring.delphi(rounds, bound)
        alpha = delphi_result.weights
        source = f"Delphi rounds in {args.delphi}"
    elif args.subjective:
        alpha = read_subjective(args.subjective)
        source = args.subjective
    else:
        alpha = np.array(scoring.PAPER_SUBJECTIVE_WEIGHTS)
        source = "paper Table 3 (default)"

    results: list[scoring.SystemScore] = []
    for r in systems:
        try:
            results.append(scoring.score_system(r.system, r.raters, r.x, alpha, mu))
        except ValueError as e:
            raise UserError(f"{args.ratings}: line {r.lines[0]}: system {r.system!r} "
                            f"({len(r.lines)} raters): {e}") from None

    out, lock = _out_dir(args)
    try:
        _report(args, out, results, alpha, mu, source, delphi_result)
    finally:
        lock.release()
    return 0


def _report(args, out: Path, results, alpha, mu, source, delphi_result) -> None:
    if delphi_result is not None:
        _print_delphi(delphi_result, args.delphi)
    print(f"subjective weights alpha from {source}")
    _print_table(results, alpha, mu)
    try:
        _write_weights_csv(out / "weights.csv", results, alpha)
        _write_scores_csv(out / "scores.csv", results)
        _write_json(out / "score.json", args, source, alpha, mu, delphi_result, results)
        with plain_text_figures():  # system and rater names are data, not markup
            _plot(out / "scores.png", results)
    except OSError as e:  # a full disk, a folder gone read-only
        raise UserError(f"{out}: cannot write the score's files: {e.strerror or e}") from None
    print(f"wrote {out}/weights.csv, scores.csv, score.json, scores.png")


def _print_delphi(res: scoring.DelphiResult, path: str) -> None:
    print(f"Delphi rounds ({path}), bound on standard deviation {res.bound:g}:")
    for r in res.rounds:
        over = ", ".join(INDICES[j] for j in r.exceeding) or "none"
        print(f"  round {r.number} ({r.n_experts} experts): above bound: {over}")
        print(f"    mean: {_fmt_weights(r.mean)}")
        print(f"    std:  {_fmt_weights(r.std)}")
    if res.converged:
        print(f"  agreement reached in round {res.converged_round}; its mean is the subjective weights")
        if res.converged_round != res.rounds[-1].number:
            print(f"haptic-acu score: note: rounds after round {res.converged_round} in {path} do not "
                  f"change the result (agreement was already reached)", file=sys.stderr)
    else:
        last = res.rounds[-1]
        over = ", ".join(f"{INDICES[j]} (std {last.std[j]:.3f})" for j in last.exceeding)
        print(f"haptic-acu score: warning: {path}: Delphi did NOT converge: in the last round "
              f"(round {last.number}) {over} still exceed the bound {res.bound:g}; using round "
              f"{last.number}'s mean as the subjective weights anyway (score.json: converged=false)",
              file=sys.stderr)


def _print_table(results, alpha, mu) -> None:
    names = [r.name for r in results]
    width = max(7, *(len(n) + 1 for n in names))
    iw = max(len(i) for i in INDICES) + 2
    print(f"combined weights omega (eq. 13, mu = {mu:g}); alpha = subjective")
    print(f"{'index':<{iw}}{'alpha':>7}" + "".join(f"{n:>{width}}" for n in names))
    for j, idx in enumerate(INDICES):
        print(f"{idx:<{iw}}{alpha[j]:>7.3f}" + "".join(f"{r.omega[j]:>{width}.3f}" for r in results))
    print(f"{'mean score (eq. 14)':<{iw}}{'':>7}" + "".join(f"{r.mean_score:>{width}.2f}" for r in results))
    raters = _all_raters(results)
    rw = max(iw, max(len(x) for x in raters) + 2)
    print("rater scores (eq. 14)")
    print(f"{'rater':<{rw}}" + "".join(f"{n:>{width}}" for n in names))
    for rater in raters:
        cells = []
        for r in results:
            f = dict(zip(r.raters, r.scores)).get(rater)
            cells.append(f"{'-':>{width}}" if f is None else f"{f:>{width}.2f}")
        print(f"{rater:<{rw}}" + "".join(cells))


def _all_raters(results) -> list[str]:
    seen: dict[str, None] = {}
    for r in results:
        for name in r.raters:
            seen.setdefault(name, None)
    return list(seen)


DIGITS = 15  # significant digits of every number written: float arithmetic's noise is in the 16th-17th


def _num(x) -> float:
    """A number as written to weights.csv, scores.csv and score.json: rounded once to DIGITS
    significant digits, so a mean of 7.89 is written 7.89, not the float sum's 7.890000000000001
    (weights still sum to 1 within 1e-14)."""
    return float(f"{float(x):.{DIGITS}g}")


def _write_weights_csv(path: Path, results, alpha) -> None:
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["system", "index", "mean_E", "sigma", "alpha_subjective", "beta_objective",
                    "omega_combined"])
        for r in results:
            for j, idx in enumerate(INDICES):
                w.writerow([safe_cell(r.name), idx, _num(r.objective.mean[j]), _num(r.objective.sigma[j]),
                            _num(alpha[j]), _num(r.objective.beta[j]), _num(r.omega[j])])


def _write_scores_csv(path: Path, results) -> None:
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["system", "rater", "score"])
        for r in results:
            for rater, s in zip(r.raters, r.scores):
                w.writerow([safe_cell(r.name), safe_cell(rater), _num(s)])


def _write_json(path: Path, args, source, alpha, mu, dres, results) -> None:
    def named(v):
        return {n: _num(x) for n, x in zip(INDICES, v)}

    doc = {
        "method": "comprehensive weighted scoring, paper section 4.2, eq. 10-14",
        "ratings": str(args.ratings),
        "mu": mu,
        "subjective": {"source": source, "weights": named(alpha)},
        "delphi": None,
        "systems": [
            {
                "name": r.name,
                "n_raters": len(r.raters),
                "mean_score": _num(r.mean_score),
                "mean_E": named(r.objective.mean),
                "sigma": named(r.objective.sigma),
                "beta_objective": named(r.objective.beta),
                "omega_combined": named(r.omega),
                "scores": {rater: _num(s) for rater, s in zip(r.raters, r.scores)},
            }
            for r in results
        ],
    }
    if dres is not None:
        doc["delphi"] = {
            "file": str(args.delphi),
            "bound": dres.bound,
            "std": "population (divide by the number of experts)",
            "converged": dres.converged,
            "converged_round": dres.converged_round,
            "rounds": [
                {"round": r.number, "n_experts": r.n_experts, "mean": named(r.mean),
                 "std": named(r.std), "exceeding": [INDICES[j] for j in r.exceeding]}
                for r in dres.rounds
            ],
        }
    path.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")


def _plot(path: Path, results) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    raters = _all_raters(results)
    cmap = plt.get_cmap("tab20" if len(raters) <= 20 else "viridis")
    colour = {name: cmap(k / max(1, len(raters) - 1) if len(raters) > 20 else k % 20)
              for k, name in enumerate(raters)}
    fig, ax = plt.subplots(figsize=(max(6.0, 1.6 * len(results) + 2.5), 4.5))
    group = 0.8
    for g, r in enumerate(results):
        bw = group / len(r.raters)
        for k, (rater, s) in enumerate(zip(r.raters, r.scores)):
            x = g - group / 2 + (k + 0.5) * bw
            ax.bar(x, s, width=bw, color=colour[rater], label=rater)
        ax.hlines(r.mean_score, g - group / 2, g + group / 2, colors="k", linewidth=1)
        ax.text(g, min(10.0, float(r.scores.max())) + 0.1, f"mean {r.mean_score:.2f}", ha="center", va="bottom",
                fontsize=8)
    ax.set_xticks(range(len(results)), [r.name for r in results])
    ax.set_ylim(0, 10.6)
    ax.set_ylabel("comprehensive score (eq. 14)")
    ax.set_title("Comprehensive scores per system, one bar per rater (line: mean)")
    handles, labels = [], []
    for h, lab in zip(*ax.get_legend_handles_labels()):
        if lab not in labels:
            handles.append(h)
            labels.append(lab)
    if len(labels) <= 30:
        ax.legend(handles, labels, fontsize=6, ncol=2, loc="center left", bbox_to_anchor=(1.0, 0.5),
                  title="rater", title_fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)

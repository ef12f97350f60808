"""The files of the paper's multi-index weighted score (``haptic-acu score``, section 4.2):
reading the ratings, subjective-weights and Delphi-rounds CSVs (UTF-8; blank lines and ``#`` lines
ignored; the first other line is the header, columns in any order, every one required, none unknown;
every error one line naming the file and line), and writing ``weights.csv``, ``scores.csv``,
``score.json`` and ``scores.png`` (grouped bars as the paper's Fig. 7). The statistics:
:mod:`.scoring`."""
from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..base.csvin import read_table
from ..base.errors import UserError
from ..base.outputs import safe_cell
from . import scoring
from .scoring import INDICES


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


def all_raters(results) -> list[str]:
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


def write_weights_csv(path: Path, results, alpha) -> None:
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["system", "index", "mean_E", "sigma", "alpha_subjective", "beta_objective",
                    "omega_combined"])
        for r in results:
            for j, idx in enumerate(INDICES):
                w.writerow([safe_cell(r.name), idx, _num(r.objective.mean[j]), _num(r.objective.sigma[j]),
                            _num(alpha[j]), _num(r.objective.beta[j]), _num(r.omega[j])])


def write_scores_csv(path: Path, results) -> None:
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["system", "rater", "score"])
        for r in results:
            for rater, s in zip(r.raters, r.scores):
                w.writerow([safe_cell(r.name), safe_cell(rater), _num(s)])


def write_json(path: Path, ratings, delphi_file, source, alpha, mu, dres, results) -> None:
    """score.json: the method, the inputs (``ratings``, ``delphi_file`` the Delphi rounds file or None),
    the subjective weights and their ``source``, each system's numbers and the Delphi rounds (``dres``)."""
    def named(v):
        return {n: _num(x) for n, x in zip(INDICES, v)}

    doc = {
        "method": "comprehensive weighted scoring, paper section 4.2, eq. 10-14",
        "ratings": str(ratings),
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
            "file": str(delphi_file),
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


def plot_scores(path: Path, results) -> None:
    from matplotlib import colormaps
    from ..base.figlayout import new_figure

    raters = all_raters(results)
    cmap = colormaps["tab20" if len(raters) <= 20 else "viridis"]
    colour = {name: cmap(k / max(1, len(raters) - 1) if len(raters) > 20 else k % 20)
              for k, name in enumerate(raters)}
    fig = new_figure((max(6.0, 1.6 * len(results) + 2.5), 4.5))
    ax = fig.subplots()
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

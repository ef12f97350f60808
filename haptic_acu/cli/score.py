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
``score.json`` (everything, plus the Delphi rounds) and ``scores.png`` (grouped bars as Fig. 7),
read and written by :mod:`haptic_acu.analysis.score_files`.
"""
from __future__ import annotations

import datetime as _dt
import math
import sys
from pathlib import Path

import numpy as np

from ..analysis import scoring
from ..analysis.score_files import (all_raters, plot_scores, read_delphi, read_ratings, read_subjective,
                                    write_json, write_scores_csv, write_weights_csv)
from ..analysis.scoring import INDICES
from ..base.errors import UserError
from ..base.outputs import Outputs, claim_folder, fresh_folder, plain_text_figures


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
        write_weights_csv(out / "weights.csv", results, alpha)
        write_scores_csv(out / "scores.csv", results)
        write_json(out / "score.json", args.ratings, args.delphi, source, alpha, mu, delphi_result, results)
        with plain_text_figures():  # system and rater names are data, not markup
            plot_scores(out / "scores.png", results)
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
    raters = all_raters(results)
    rw = max(iw, max(len(x) for x in raters) + 2)
    print("rater scores (eq. 14)")
    print(f"{'rater':<{rw}}" + "".join(f"{n:>{width}}" for n in names))
    for rater in raters:
        cells = []
        for r in results:
            f = dict(zip(r.raters, r.scores)).get(rater)
            cells.append(f"{'-':>{width}}" if f is None else f"{f:>{width}.2f}")
        print(f"{rater:<{rw}}" + "".join(cells))

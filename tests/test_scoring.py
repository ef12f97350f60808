"""The paper's comprehensive weighted scoring (section 4.2, eq. 10-14) and ``haptic-acu score``.

Expected numbers are worked out by hand from the paper's formulas (written out in comments), or
recomputed independently with the ``statistics`` module and plain Python loops.
"""
from __future__ import annotations

import csv
import json
import math
import re
import statistics
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import cli
from haptic_acu.analysis import scoring
from haptic_acu.analysis.scoring import INDICES

REPO = Path(__file__).resolve().parent.parent
EXAMPLE_RATINGS = REPO / "config" / "scoring" / "example_ratings.csv"
EXAMPLE_DELPHI = REPO / "config" / "scoring" / "example_delphi.csv"
TABLE3 = [0.09, 0.17, 0.24, 0.13, 0.10, 0.21, 0.06]
# Table 4, objective weights per system, rows in INDICES order.
TABLE4 = {
    "MSM": [0.097, 0.041, 0.210, 0.204, 0.083, 0.282, 0.084],
    "FEM": [0.116, 0.163, 0.211, 0.023, 0.120, 0.281, 0.087],
    "BEM": [0.124, 0.186, 0.200, 0.058, 0.142, 0.216, 0.073],
    "SHF": [0.097, 0.287, 0.107, 0.148, 0.067, 0.163, 0.132],
    "Ours": [0.159, 0.096, 0.195, 0.116, 0.200, 0.102, 0.133],
}


# --------------------------------------------------------------------------- eq. 10-12


def test_mean_square_deviation_by_hand():
    # Two raters, three indices: columns (6, 8), (5, 5), (4, 8).
    # E = (7, 5, 6); sigma = (1, 0, 2) (population: sqrt(((6-7)^2 + (8-7)^2) / 2) = 1, ...);
    # beta = sigma / 3 = (1/3, 0, 2/3).
    ow = scoring.objective_weights([[6, 5, 4], [8, 5, 8]])
    assert ow.mean == pytest.approx([7, 5, 6], abs=1e-15)
    assert ow.sigma == pytest.approx([1, 0, 2], abs=1e-15)
    assert ow.beta == pytest.approx([1 / 3, 0, 2 / 3], abs=1e-15)


def test_mean_square_deviation_four_raters_by_hand():
    # Columns (2, 4, 4, 6): E = 4, squared deviations 4, 0, 0, 4 -> sigma = sqrt(8/4) = sqrt(2).
    # Columns (1, 1, 3, 3): E = 2, squared deviations all 1 -> sigma = 1.
    ow = scoring.objective_weights([[2, 1], [4, 1], [4, 3], [6, 3]])
    assert ow.mean == pytest.approx([4, 2], abs=1e-15)
    assert ow.sigma == pytest.approx([math.sqrt(2), 1], abs=1e-15)
    s = math.sqrt(2) + 1
    assert ow.beta == pytest.approx([math.sqrt(2) / s, 1 / s], abs=1e-15)


@pytest.mark.parametrize("seed", range(5))
def test_mean_square_deviation_matches_statistics_module(seed):
    rng = np.random.default_rng(seed)
    x = np.round(rng.uniform(0, 10, size=(int(rng.integers(2, 30)), 7)), 1)
    ow = scoring.objective_weights(x)
    cols = [list(map(float, x[:, j])) for j in range(7)]
    sig = [statistics.pstdev(c) for c in cols]
    assert ow.mean == pytest.approx([statistics.fmean(c) for c in cols], rel=1e-12)
    assert ow.sigma == pytest.approx(sig, rel=1e-12)
    assert ow.sigma == pytest.approx(np.std(x, axis=0, ddof=0), rel=1e-12)
    assert ow.beta == pytest.approx([s / sum(sig) for s in sig], rel=1e-12)
    assert math.fsum(ow.beta) == pytest.approx(1.0, abs=1e-12)
    # Properties: shifting every score by a constant does not change the spread-based weights.
    assert scoring.objective_weights(x - 1.5).beta == pytest.approx(ow.beta, rel=1e-9)


def test_constant_index_gets_exactly_zero_weight_and_all_constant_is_refused():
    # 7.3 * 3 / 3 is not exactly 7.3 in floating point; the constant column must still get 0.
    ow = scoring.objective_weights([[7.3, 1.0], [7.3, 2.0], [7.3, 3.0]])
    assert ow.sigma[0] == 0.0 and ow.beta[0] == 0.0 and ow.beta[1] == 1.0
    with pytest.raises(ValueError, match="same score"):
        scoring.objective_weights([[7.3, 0.1], [7.3, 0.1], [7.3, 0.1]])


# --------------------------------------------------------------------------- eq. 13-14


def test_combined_weights_by_hand():
    # omega = 0.4 * (0.5, 0.3, 0.2) + 0.6 * (0.2, 0.2, 0.6) = (0.32, 0.24, 0.44)
    omega = scoring.combined_weights([0.5, 0.3, 0.2], [0.2, 0.2, 0.6], 0.4)
    assert omega == pytest.approx([0.32, 0.24, 0.44], abs=1e-15)
    assert math.fsum(omega) == pytest.approx(1.0, abs=1e-15)
    # mu -> larger: closer to the subjective weights.
    assert scoring.combined_weights([0.5, 0.3, 0.2], [0.2, 0.2, 0.6], 0.9) == pytest.approx(
        [0.47, 0.29, 0.24], abs=1e-15)


@pytest.mark.parametrize("mu", [0.0, 1.0, -0.1, 1.1, float("nan")])
def test_combined_weights_refuses_mu_outside_open_interval(mu):
    with pytest.raises(ValueError, match="mu"):
        scoring.combined_weights([0.5, 0.5], [0.5, 0.5], mu)


def test_final_scores_by_hand():
    # f = 6*0.32 + 5*0.24 + 4*0.44 = 1.92 + 1.2 + 1.76 = 4.88; 10*(sum of weights) = 10.
    f = scoring.final_scores([[6, 5, 4], [10, 10, 10]], [0.32, 0.24, 0.44])
    assert f == pytest.approx([4.88, 10.0], abs=1e-12)


def test_score_system_whole_chain_by_hand():
    # x = [[6,5,4],[8,5,8]] -> beta = (1/3, 0, 2/3) (see above); alpha = (0.5, 0.3, 0.2), mu = 0.4:
    # omega = (0.2 + 0.2, 0.12 + 0, 0.08 + 0.4) = (0.4, 0.12, 0.48)
    # f1 = 6*0.4 + 5*0.12 + 4*0.48 = 2.4 + 0.6 + 1.92 = 4.92; f2 = 3.2 + 0.6 + 3.84 = 7.64.
    s = scoring.score_system("A", ["r1", "r2"], [[6, 5, 4], [8, 5, 8]], [0.5, 0.3, 0.2], 0.4)
    assert s.omega == pytest.approx([0.4, 0.12, 0.48], abs=1e-15)
    assert s.scores == pytest.approx([4.92, 7.64], abs=1e-12)
    assert s.mean_score == pytest.approx(6.28, abs=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_weights_sum_to_one_and_scores_are_convex_combinations(seed):
    rng = np.random.default_rng(100 + seed)
    x = np.round(rng.uniform(0, 10, size=(12, 7)), 1)
    alpha = rng.dirichlet(np.ones(7))
    s = scoring.score_system("S", [f"r{k}" for k in range(12)], x, alpha, rng.uniform(0.05, 0.95))
    assert math.fsum(s.objective.beta) == pytest.approx(1.0, abs=1e-12)
    assert math.fsum(s.omega) == pytest.approx(1.0, abs=1e-12)
    assert np.all(s.omega >= 0)
    # Weights are non-negative and sum to 1, so each score lies between the rater's min and max.
    assert np.all(s.scores >= x.min(axis=1) - 1e-12) and np.all(s.scores <= x.max(axis=1) + 1e-12)
    # Eq. 14 against a plain loop.
    for i in range(12):
        assert s.scores[i] == pytest.approx(math.fsum(s.omega[j] * x[i, j] for j in range(7)), abs=1e-12)


def test_paper_table3_and_table4_give_eq13_combined_weights():
    # Hand-computed eq. 13 with mu = 0.4, e.g. MSM soft tissue 0.4*0.09 + 0.6*0.097 = 0.036 + 0.0582.
    by_hand = {
        "MSM": [0.0942, 0.0926, 0.2220, 0.1744, 0.0898, 0.2532, 0.0744],
        "Ours": [0.1314, 0.1256, 0.2130, 0.1216, 0.1600, 0.1452, 0.1038],
    }
    assert scoring.PAPER_SUBJECTIVE_WEIGHTS == pytest.approx(TABLE3, abs=0)
    assert scoring.PAPER_MU == 0.4
    for system, beta in TABLE4.items():
        omega = scoring.combined_weights(scoring.PAPER_SUBJECTIVE_WEIGHTS, beta, scoring.PAPER_MU)
        expected = by_hand.get(system) or [0.4 * a + 0.6 * b for a, b in zip(TABLE3, beta)]
        assert omega == pytest.approx(expected, abs=1e-12)
        # Table 4's columns are rounded to 3 decimals (they sum to 0.999-1.001); omega's sum is
        # 0.4 * 1 + 0.6 * sum(beta).
        assert math.fsum(omega) == pytest.approx(0.4 + 0.6 * math.fsum(beta), abs=1e-12)
        assert abs(math.fsum(omega) - 1) <= 0.6 * 0.001 + 1e-12


# --------------------------------------------------------------------------- Delphi


def test_delphi_round1_exceeds_round2_agrees_by_hand():
    # Round 1, two experts: (0.6, 0.2, 0.2), (0.2, 0.4, 0.4): mean (0.4, 0.3, 0.3),
    # population std (0.2, 0.1, 0.1): only index 0 exceeds 0.1 (0.1 itself does not).
    # Round 2: (0.45, 0.3, 0.25), (0.35, 0.3, 0.35): mean (0.4, 0.3, 0.3), std (0.05, 0, 0.05).
    r1 = [[0.6, 0.2, 0.2], [0.2, 0.4, 0.4]]
    r2 = [[0.45, 0.3, 0.25], [0.35, 0.3, 0.35]]
    res = scoring.delphi([r1, r2], bound=0.1)
    a, b = res.rounds
    assert a.mean == pytest.approx([0.4, 0.3, 0.3], abs=1e-15)
    assert a.std == pytest.approx([0.2, 0.1, 0.1], abs=1e-15)
    assert a.exceeding == (0,)
    assert b.std == pytest.approx([0.05, 0.0, 0.05], abs=1e-15)
    assert b.exceeding == ()
    assert res.converged and res.converged_round == 2
    assert res.weights == pytest.approx([0.4, 0.3, 0.3], abs=1e-15)


def test_delphi_not_converged_uses_last_round_and_says_so():
    r1 = [[0.9, 0.1], [0.1, 0.9]]  # std 0.4 on both
    r2 = [[0.8, 0.2], [0.2, 0.8]]  # std 0.3 on both; mean (0.5, 0.5)
    res = scoring.delphi([r1, r2], bound=0.1)
    assert not res.converged and res.converged_round is None
    assert res.rounds[-1].exceeding == (0, 1)
    assert res.weights == pytest.approx([0.5, 0.5], abs=1e-15)


def test_delphi_sample_std_option_matches_statistics_stdev():
    rng = np.random.default_rng(3)
    w = rng.dirichlet(np.ones(7), size=9)
    st = scoring.delphi_round(1, w, bound=0.1, ddof=1)
    assert st.std == pytest.approx([statistics.stdev(map(float, w[:, j])) for j in range(7)], rel=1e-12)
    st0 = scoring.delphi_round(1, w, bound=0.1)
    assert st0.std == pytest.approx([statistics.pstdev(map(float, w[:, j])) for j in range(7)], rel=1e-12)


def test_check_weights():
    assert scoring.check_weights(TABLE3) == pytest.approx(TABLE3)
    with pytest.raises(ValueError, match="sum to 0.99"):
        scoring.check_weights([0.5, 0.49])
    with pytest.raises(ValueError, match="negative"):
        scoring.check_weights([1.2, -0.2])


# --------------------------------------------------------------------------- the CLI


def run_cli(*args, cwd=None):
    return cli("score", *args, cwd=cwd)  # in-process: main()'s exit status and streams


def read_csv_rows(path):
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(line for line in f if not line.lstrip().startswith("#")))


HEADER = "system,rater," + ",".join(INDICES)


def test_cli_hand_example(tmp_path):
    # System A, raters r1 = (4,5,5,5,5,5,5) and r2 = (6,5,5,5,5,5,9):
    # sigma = (1,0,0,0,0,0,2) -> beta = (1/3,0,0,0,0,0,2/3). Table 3 alpha, mu = 0.4:
    # omega = (0.036+0.2, 0.068, 0.096, 0.052, 0.04, 0.084, 0.024+0.4)
    #       = (0.236, 0.068, 0.096, 0.052, 0.040, 0.084, 0.424)
    # f1 = 0.236*4 + (0.068+0.096+0.052+0.04+0.084)*5 + 0.424*5 = 0.944 + 1.7 + 2.12 = 4.764
    # f2 = 0.236*6 + 1.7 + 0.424*9 = 1.416 + 1.7 + 3.816 = 6.932; mean 5.848.
    # System B (after a comment line, which must be skipped): r1 scores 3 on every index, r2 7:
    # sigma_j = 2 for all j -> beta_j = 1/7, omega_j = 0.4 alpha_j + 0.6/7; omega sums to 1 and
    # each rater's scores are all equal, so f1 = 3 and f2 = 7; mean 5.
    ratings = tmp_path / "r.csv"
    ratings.write_text("\n".join([
        "# test ratings", HEADER,
        "A,r1,4,5,5,5,5,5,5", "A,r2,6,5,5,5,5,5,9",
        "# system B", "B,r1,3,3,3,3,3,3,3", "B,r2,7,7,7,7,7,7,7", ""]))
    out = tmp_path / "out"
    p = run_cli(ratings, "--out", out)
    assert p.returncode == 0, p.stderr
    omega_a = [0.236, 0.068, 0.096, 0.052, 0.040, 0.084, 0.424]
    w = [r for r in read_csv_rows(out / "weights.csv") if r["system"] == "A"]
    assert [r["index"] for r in w] == list(INDICES)
    assert [float(r["omega_combined"]) for r in w] == pytest.approx(omega_a, abs=1e-12)
    assert [float(r["beta_objective"]) for r in w] == pytest.approx([1 / 3, 0, 0, 0, 0, 0, 2 / 3], abs=1e-12)
    wb = [r for r in read_csv_rows(out / "weights.csv") if r["system"] == "B"]
    assert [float(r["omega_combined"]) for r in wb] == pytest.approx(
        [0.4 * a + 0.6 / 7 for a in TABLE3], abs=1e-12)
    scores = {(r["system"], r["rater"]): float(r["score"]) for r in read_csv_rows(out / "scores.csv")}
    assert scores == pytest.approx({("A", "r1"): 4.764, ("A", "r2"): 6.932,
                                    ("B", "r1"): 3.0, ("B", "r2"): 7.0}, abs=1e-12)
    doc = json.loads((out / "score.json").read_text())
    assert [s["mean_score"] for s in doc["systems"]] == pytest.approx([5.848, 5.0], abs=1e-12)
    assert doc["mu"] == 0.4 and doc["delphi"] is None
    assert (out / "scores.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "5.85" in p.stdout and "4.76" in p.stdout and "6.93" in p.stdout


def test_cli_example_data_against_independent_recomputation(tmp_path):
    """The shipped example, scored by the CLI, against a from-scratch plain-Python recomputation."""
    out = tmp_path / "out"
    p = run_cli(EXAMPLE_RATINGS, "--mu", "0.4", "--out", out)
    assert p.returncode == 0, p.stderr
    rows = read_csv_rows(EXAMPLE_RATINGS)
    systems = list(dict.fromkeys(r["system"] for r in rows))
    assert systems == ["MSM", "FEM", "BEM", "SHF", "Ours"]
    expected_scores, expected_means = {}, {}
    for s in systems:
        mine = [r for r in rows if r["system"] == s]
        assert len(mine) == 20
        sig = [statistics.pstdev(float(r[c]) for r in mine) for c in INDICES]
        omega = [0.4 * a + 0.6 * sj / sum(sig) for a, sj in zip(TABLE3, sig)]
        f = [sum(o * float(r[c]) for o, c in zip(omega, INDICES)) for r in mine]
        expected_scores.update({(s, r["rater"]): v for r, v in zip(mine, f)})
        expected_means[s] = statistics.fmean(f)
    got = {(r["system"], r["rater"]): float(r["score"]) for r in read_csv_rows(out / "scores.csv")}
    assert got == pytest.approx(expected_scores, abs=1e-9)
    doc = json.loads((out / "score.json").read_text())
    means = {s["name"]: s["mean_score"] for s in doc["systems"]}
    assert means == pytest.approx(expected_means, abs=1e-9)
    for s in doc["systems"]:
        assert math.fsum(s["omega_combined"].values()) == pytest.approx(1.0, abs=1e-12)
        assert math.fsum(s["beta_objective"].values()) == pytest.approx(1.0, abs=1e-12)
    # The synthetic data were drawn to resemble the paper's reported means.
    paper = {"MSM": 7.83, "FEM": 7.90, "BEM": 7.93, "SHF": 7.88, "Ours": 8.94}
    assert means == pytest.approx(paper, abs=0.02)


def test_cli_delphi_example_round1_exceeds_round2_agrees(tmp_path):
    out = tmp_path / "out"
    p = run_cli(EXAMPLE_RATINGS, "--delphi", EXAMPLE_DELPHI, "--out", out)
    assert p.returncode == 0, p.stderr
    rows = read_csv_rows(EXAMPLE_DELPHI)
    doc = json.loads((out / "score.json").read_text())["delphi"]
    assert doc["converged"] is True and doc["converged_round"] == 2
    r1, r2 = doc["rounds"]
    for rnd, stats in (("1", r1), ("2", r2)):
        mine = [r for r in rows if r["round"] == rnd]
        for c in INDICES:
            vals = [float(r[c]) for r in mine]
            assert stats["mean"][c] == pytest.approx(statistics.fmean(vals), abs=1e-12)
            assert stats["std"][c] == pytest.approx(statistics.pstdev(vals), abs=1e-12)
        assert stats["exceeding"] == [c for c in INDICES if statistics.pstdev(float(r[c]) for r in mine) > 0.1]
    assert r1["exceeding"] and not r2["exceeding"]
    # Round 2's mean is the paper's Table 3 by construction of the example.
    subj = json.loads((out / "score.json").read_text())["subjective"]["weights"]
    assert [subj[c] for c in INDICES] == pytest.approx(TABLE3, abs=1e-12)
    assert "round 1 (20 experts): above bound:" in p.stdout


def test_cli_delphi_not_converged_warns_and_records(tmp_path):
    d = tmp_path / "d.csv"
    d.write_text("round,expert," + ",".join(INDICES) + "\n"
                 "1,e1,0.70,0.05,0.05,0.05,0.05,0.05,0.05\n"
                 "1,e2,0.10,0.15,0.15,0.15,0.15,0.15,0.15\n")
    out = tmp_path / "out"
    p = run_cli(EXAMPLE_RATINGS, "--delphi", d, "--out", out)
    assert p.returncode == 0, p.stderr
    assert "did NOT converge" in p.stderr and "soft_tissue_material" in p.stderr
    doc = json.loads((out / "score.json").read_text())
    assert doc["delphi"]["converged"] is False
    # mean of (0.7, 0.1) = 0.4; of (0.05, 0.15) = 0.1
    assert [doc["subjective"]["weights"][c] for c in INDICES] == pytest.approx([0.4] + [0.1] * 6, abs=1e-12)


def test_cli_subjective_file_and_default_out_dir(tmp_path):
    wfile = tmp_path / "w.csv"
    wfile.write_text("# equal weights\n" + ",".join(INDICES) + "\n" + ",".join(["0.125"] * 6 + ["0.25"]) + "\n")
    p = run_cli(EXAMPLE_RATINGS, "--subjective", wfile, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    (run,) = list((tmp_path / "runs").glob("score-*"))
    doc = json.loads((run / "score.json").read_text())
    assert [doc["subjective"]["weights"][c] for c in INDICES] == [0.125] * 6 + [0.25]
    for name in ("weights.csv", "scores.csv", "score.json", "scores.png"):
        assert (run / name).is_file()


# Bad inputs: (file name, file text, extra args, substrings the one-line error must contain).
ROW = "A,r1,5,5,5,5,5,5,5"
ROW2 = "A,r2,6,6,6,6,6,6,6"
BAD_RATINGS = [
    ("empty", "", ["empty file"]),
    ("comments_only", "# nothing\n\n", ["empty file"]),
    ("header_only", HEADER + "\n", ["line 1", "header but no data"]),
    ("unknown_column", HEADER + ",comfort\n" + ROW + ",5\n", ["line 1", "unknown column 'comfort'"]),
    ("missing_column", HEADER.rsplit(",", 1)[0] + "\nA,r1,5,5,5,5,5,5\n", ["line 1", "missing column", "system_stability"]),
    ("field_count", HEADER + "\n" + ROW + "\nA,r2,5,5\n", ["line 3", "4 fields"]),
    ("non_numeric", HEADER + "\n" + ROW + "\nA,r2,5,abc,5,5,5,5,5\n", ["line 3", "force_feedback", "'abc'", "not a number"]),
    ("nan", HEADER + "\nA,r1,nan,5,5,5,5,5,5\n" + ROW2 + "\n", ["line 2", "soft_tissue_material", "not a finite"]),
    ("above_10", HEADER + "\n" + ROW + "\nA,r2,5,5,5,5,5,5,10.5\n", ["line 3", "system_stability", "outside 0-10"]),
    ("negative", HEADER + "\n" + ROW + "\nA,r2,5,5,-1,5,5,5,5\n", ["line 3", "acupuncture_effect", "outside 0-10"]),
    ("one_rater", HEADER + "\n" + ROW + "\n" + ROW2 + "\nB,r1,5,5,5,5,5,5,5\n", ["line 4", "'B'", "only one rater"]),
    ("constant", "# c\n" + HEADER + "\n" + ROW + "\nA,r2,5,5,5,5,5,5,5\n", ["line 3", "'A'", "same score"]),
    ("duplicate", HEADER + "\n" + ROW + "\n" + ROW2 + "\nA,r1,7,7,7,7,7,7,7\n", ["line 4", "'r1'", "line 2"]),
    ("empty_rater", HEADER + "\n" + ROW + "\nA,,5,5,5,5,5,5,5\n", ["line 3", "empty rater"]),
]


def assert_one_line_error(p, fname, needles):
    assert p.returncode == 2, (p.stdout, p.stderr)
    err = p.stderr.strip()
    assert "\n" not in err and "Traceback" not in err, err
    assert fname in err, err
    for n in needles:
        assert n in err, (n, err)


@pytest.mark.parametrize("name,text,needles", BAD_RATINGS, ids=[c[0] for c in BAD_RATINGS])
def test_cli_bad_ratings(tmp_path, name, text, needles):
    f = tmp_path / f"{name}.csv"
    f.write_text(text)
    p = run_cli(f, "--out", tmp_path / "out")
    assert_one_line_error(p, f"{name}.csv", needles)


def test_cli_missing_file(tmp_path):
    p = run_cli(tmp_path / "nope.csv")
    assert_one_line_error(p, "nope.csv", ["no such file"])


WHEAD = ",".join(INDICES)
DHEAD = "round,expert," + WHEAD
BAD_WEIGHTS = [
    ("subjective", "w_sum", WHEAD + "\n0.09,0.17,0.24,0.13,0.10,0.21,0.05\n", ["line 2", "sum to 0.99"]),
    ("subjective", "w_two_rows", WHEAD + "\n" + ",".join(map(str, TABLE3)) + "\n" + ",".join(map(str, TABLE3)) + "\n",
     ["line 3", "exactly one row"]),
    ("subjective", "w_header_only", "# w\n" + WHEAD + "\n", ["line 2", "header but no data"]),
    ("subjective", "w_negative", WHEAD + "\n1.0,-0.1,0.1,0,0,0,0\n", ["line 2", "force_feedback", "outside 0-1"]),
    ("delphi", "d_sum", DHEAD + "\n1,e1,0.09,0.17,0.24,0.13,0.10,0.21,0.06\n1,e2,0.2,0.2,0.2,0.2,0.2,0.2,0.2\n",
     ["line 3", "sum to 1.4"]),
    ("delphi", "d_gap", DHEAD + "\n" + "".join(f"{k},e{i},0.4,0.1,0.1,0.1,0.1,0.1,0.1\n" for k in (1, 3) for i in (1, 2)),
     ["line 4", "round 3 present but round 2 missing"]),
    ("delphi", "d_round_text", DHEAD + "\nfirst,e1,0.4,0.1,0.1,0.1,0.1,0.1,0.1\n", ["line 2", "'first'"]),
    ("delphi", "d_one_expert", DHEAD + "\n1,e1,0.4,0.1,0.1,0.1,0.1,0.1,0.1\n", ["line 2", "only one expert"]),
    ("delphi", "d_unknown_col", "round,expert,weight\n1,e1,1\n", ["line 1", "unknown column 'weight'"]),
]


@pytest.mark.parametrize("flag,name,text,needles", BAD_WEIGHTS, ids=[c[1] for c in BAD_WEIGHTS])
def test_cli_bad_weight_files(tmp_path, flag, name, text, needles):
    f = tmp_path / f"{name}.csv"
    f.write_text(text)
    p = run_cli(EXAMPLE_RATINGS, f"--{flag}", f, "--out", tmp_path / "out")
    assert_one_line_error(p, f"{name}.csv", needles)
    assert not (tmp_path / "out").exists()  # nothing written on bad input


@pytest.mark.parametrize("args,needle", [
    (["--mu", "1.5"], "--mu"), (["--mu", "0"], "--mu"), (["--bound", "-0.1"], "--bound"),
    (["--mu", "nan"], "--mu"),
])
def test_cli_bad_parameters(tmp_path, args, needle):
    p = run_cli(EXAMPLE_RATINGS, *args, "--out", tmp_path / "out")
    assert_one_line_error(p, needle, [])


def test_cli_subjective_and_delphi_are_exclusive(tmp_path):
    p = run_cli(EXAMPLE_RATINGS, "--subjective", "a.csv", "--delphi", "b.csv")
    assert p.returncode == 2 and "not allowed with" in p.stderr and "Traceback" not in p.stderr


def test_cli_writes_numbers_without_float_noise(tmp_path):
    """The example's MSM soft-tissue mean E is 7.89 (the mean of its ratings, two
    decimals each), written as 7.89, not 7.890000000000001; no number in the outputs carries more
    than 15 significant digits, and each still equals the exact value within 1e-11 of it."""
    out = tmp_path / "out"
    p = run_cli(EXAMPLE_RATINGS, "--delphi", EXAMPLE_DELPHI, "--out", out)
    assert p.returncode == 0, p.stderr
    rows = read_csv_rows(EXAMPLE_RATINGS)
    msm = [float(r["soft_tissue_material"]) for r in rows if r["system"] == "MSM"]
    exact = statistics.fmean(msm)
    text = (out / "weights.csv").read_text()
    cell = next(r for r in read_csv_rows(out / "weights.csv")
                if r["system"] == "MSM" and r["index"] == "soft_tissue_material")["mean_E"]
    assert float(cell) == pytest.approx(exact, abs=1e-11)
    assert cell == repr(round(exact, 10))  # "7.89", the mean as a person would write it
    assert len(cell.replace(".", "").lstrip("0")) <= 15, cell
    numbers = re.findall(r"\d+\.\d+(?:e-?\d+)?", text + (out / "scores.csv").read_text()
                         + (out / "score.json").read_text())
    assert numbers
    long = [n for n in numbers if len(n.split("e")[0].replace(".", "").lstrip("0")) > 15]
    assert not long, long[:5]

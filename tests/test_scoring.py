"""The paper's multi-index weighted score (section 4.2, eq. 10-14) against hand computations,
the statistics module, and the paper's own Tables 3-4; bad files through the real CLI."""
from __future__ import annotations

import csv
import json
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from haptic_acu import scoring

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "config" / "scoring"
HEADER = "system,rater," + ",".join(scoring.INDICES)

# The paper's Table 4: objective weights per system (columns MSM, FEM, BEM, SHF, Ours), by index.
TABLE4 = {
    "MSM": (0.097, 0.041, 0.210, 0.204, 0.083, 0.282, 0.084),
    "FEM": (0.116, 0.163, 0.211, 0.023, 0.120, 0.281, 0.087),
    "BEM": (0.124, 0.186, 0.200, 0.058, 0.142, 0.216, 0.073),
    "SHF": (0.097, 0.287, 0.107, 0.148, 0.067, 0.163, 0.132),
    "Ours": (0.159, 0.096, 0.195, 0.116, 0.200, 0.102, 0.133),
}


def test_eq10_to_14_by_hand():
    # two raters, two indices: column means 2 and 4, population sigmas 1 and 2
    x = np.array([[1.0, 2.0], [3.0, 6.0]])
    ow = scoring.objective_weights(x)
    assert ow.mean.tolist() == [2.0, 4.0]  # eq. 10
    assert ow.sigma.tolist() == [1.0, 2.0]  # eq. 11
    assert ow.beta == pytest.approx([1 / 3, 2 / 3])  # eq. 12
    omega = scoring.combined_weights([0.5, 0.5], ow.beta, mu=0.4)  # eq. 13
    assert omega == pytest.approx([0.4 * 0.5 + 0.6 / 3, 0.4 * 0.5 + 0.6 * 2 / 3])
    assert omega == pytest.approx([0.4, 0.6])
    assert scoring.final_scores(x, omega) == pytest.approx([1 * 0.4 + 2 * 0.6, 3 * 0.4 + 6 * 0.6])  # eq. 14


def test_objective_weights_match_the_statistics_module():
    rng = np.random.default_rng(7)
    x = np.round(rng.uniform(5, 10, size=(20, 7)), 1)
    ow = scoring.objective_weights(x)
    sig = [statistics.pstdev(x[:, j].tolist()) for j in range(7)]
    assert ow.mean == pytest.approx([statistics.fmean(x[:, j].tolist()) for j in range(7)], rel=1e-12)
    assert ow.sigma == pytest.approx(sig, rel=1e-12)
    assert ow.beta == pytest.approx(np.array(sig) / sum(sig), rel=1e-12)
    assert ow.beta.sum() == pytest.approx(1.0, abs=1e-12)


def test_weights_sum_to_one_for_any_scores():
    rng = np.random.default_rng(3)
    for _ in range(50):
        x = rng.uniform(0, 10, size=(rng.integers(2, 30), 7))
        s = scoring.score_system("S", [f"r{i}" for i in range(len(x))], x, scoring.PAPER_SUBJECTIVE_WEIGHTS,
                                 mu=rng.uniform(0.01, 0.99))
        assert s.omega.sum() == pytest.approx(1.0, abs=1e-12)
        assert np.all(s.omega >= 0)
        # each rater's score is a weighted mean of their index scores: within their own min and max
        assert np.all(s.scores >= x.min(axis=1) - 1e-12) and np.all(s.scores <= x.max(axis=1) + 1e-12)


@pytest.mark.parametrize("system", sorted(TABLE4))
def test_paper_tables_3_and_4_combine_as_eq13(system):
    alpha = np.array(scoring.PAPER_SUBJECTIVE_WEIGHTS)
    beta = np.array(TABLE4[system])
    omega = scoring.combined_weights(alpha, beta, mu=scoring.PAPER_MU)
    by_hand = [0.4 * a + 0.6 * b for a, b in zip(alpha, beta)]
    assert omega.tolist() == pytest.approx(by_hand, abs=1e-15)
    # Table 3 sums to 1; the paper's Table 4 columns are rounded to 3 decimals, so within 0.002
    assert alpha.sum() == pytest.approx(1.0, abs=1e-12)
    assert omega.sum() == pytest.approx(1.0, abs=2e-3)


def test_mu_out_of_range_is_refused():
    for mu in (0.0, 1.0, -0.1, 1.5):
        with pytest.raises(ValueError):
            scoring.combined_weights([0.5, 0.5], [0.5, 0.5], mu)


def test_delphi_rounds_by_hand():
    # three experts, two indices; round 1 spreads widely, round 2 agrees
    r1 = np.array([[0.9, 0.1], [0.5, 0.5], [0.1, 0.9]])
    r2 = np.array([[0.55, 0.45], [0.5, 0.5], [0.45, 0.55]])
    res = scoring.delphi([r1, r2], bound=0.1)
    s1 = statistics.pstdev([0.9, 0.5, 0.1])
    assert res.rounds[0].std.tolist() == pytest.approx([s1, s1])
    assert res.rounds[0].exceeding == (0, 1)
    assert res.rounds[1].exceeding == ()
    assert res.converged and res.converged_round == 2
    assert res.weights.tolist() == pytest.approx([0.5, 0.5])


def test_delphi_never_agreeing_is_reported():
    r = np.array([[0.9, 0.1], [0.1, 0.9]])
    res = scoring.delphi([r], bound=0.1)
    assert not res.converged and res.converged_round is None


def score(*args, timeout=300):
    return subprocess.run([sys.executable, "-m", "haptic_acu", "score", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT)


def test_cli_on_the_examples(tmp_path):
    out = tmp_path / "out"
    r = score(EXAMPLES / "example_ratings.csv", "--out", out)
    assert r.returncode == 0, r.stderr
    data = json.loads((out / "score.json").read_text())
    text = json.dumps(data)
    for name in ("MSM", "FEM", "BEM", "SHF", "Ours"):
        assert name in text
    # recompute one system's mean score independently from the ratings file
    rows = [row for row in csv.DictReader(line for line in open(EXAMPLES / "example_ratings.csv")
                                          if not line.startswith("#")) if row["system"] == "Ours"]
    x = np.array([[float(row[c]) for c in scoring.INDICES] for row in rows])
    sig = np.array([statistics.pstdev(x[:, j].tolist()) for j in range(7)])
    omega = 0.4 * np.array(scoring.PAPER_SUBJECTIVE_WEIGHTS) + 0.6 * sig / sig.sum()
    expected = float(np.mean(x @ omega))
    assert f"{expected:.2f}" in r.stdout
    for name in ("weights.csv", "scores.csv", "scores.png"):
        assert (out / name).is_file()
    assert (out / "scores.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_delphi_example(tmp_path):
    r = score(EXAMPLES / "example_ratings.csv", "--delphi", EXAMPLES / "example_delphi.csv", "--out", tmp_path / "o")
    assert r.returncode == 0, r.stderr
    data = json.loads((tmp_path / "o" / "score.json").read_text())
    assert "0.24" in json.dumps(data)  # round 2's mean is Table 3


def _bad(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


BAD = {
    "empty.csv": "",
    "header_only.csv": HEADER + "\n",
    "unknown_column.csv": HEADER + ",extra\nA,r1,1,2,3,4,5,6,7,8\nA,r2,1,2,3,4,5,6,7,8\n",
    "missing_column.csv": "system,rater,soft_tissue_material\nA,r1,1\nA,r2,2\n",
    "non_numeric.csv": HEADER + "\nA,r1,1,2,3,4,5,6,7\nA,r2,1,2,x,4,5,6,7\n",
    "out_of_range.csv": HEADER + "\nA,r1,1,2,3,4,5,6,7\nA,r2,1,2,3,4,5,6,11\n",
    "nan.csv": HEADER + "\nA,r1,1,2,3,4,5,6,7\nA,r2,1,2,nan,4,5,6,7\n",
    "one_rater.csv": HEADER + "\nA,r1,1,2,3,4,5,6,7\n",
}


@pytest.mark.parametrize("name", sorted(BAD))
def test_cli_bad_ratings_one_line(tmp_path, name):
    f = _bad(tmp_path, name, BAD[name])
    r = score(f, "--out", tmp_path / "out")
    assert r.returncode == 2, r.stdout + r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and name in lines[0] and "Traceback" not in r.stderr


def test_cli_missing_file_and_bad_weights(tmp_path):
    r = score(tmp_path / "nope.csv")
    assert r.returncode == 2 and "nope.csv" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    w = _bad(tmp_path, "w.csv", ",".join(scoring.INDICES) + "\n0.5,0.5,0.5,0,0,0,0\n")
    r = score(EXAMPLES / "example_ratings.csv", "--subjective", w, "--out", tmp_path / "o2")
    assert r.returncode == 2 and "w.csv" in r.stderr and "Traceback" not in r.stderr

"""The study's counterbalancing: Williams squares for 2-8 models (every model once per position
per square, every ordered pair of neighbours equally often), as designed and as written to plan.csv
by `study plan` (read back through the key), and the statistics helpers against closed forms."""
from __future__ import annotations

import csv
import json
from itertools import permutations

import numpy as np
import pytest

from haptic_acu.cli import main
from haptic_acu.study import design, stats


def squares(rows, n):
    """The design's rows cut into its Latin squares (one for even n, two for odd n)."""
    return [rows[k:k + n] for k in range(0, len(rows), n)]


def check_williams(rows, n):
    assert len(rows) == (n if n % 2 == 0 else 2 * n)
    for sq in squares(rows, n):
        assert len(sq) == n
        for row in sq:  # each row a permutation of the models
            assert sorted(row) == list(range(n))
        for k in range(n):  # each position: every model once
            assert sorted(r[k] for r in sq) == list(range(n))
    pairs = {}
    for row in rows:
        for a, b in zip(row[:-1], row[1:]):
            pairs[a, b] = pairs.get((a, b), 0) + 1
    # every ordered pair of different models follows equally often, no model follows itself
    assert set(pairs) == set(permutations(range(n), 2))
    assert len(set(pairs.values())) == 1


@pytest.mark.parametrize("n", range(2, 9))
def test_williams_rows(n):
    check_williams(design.williams_rows(n), n)


@pytest.mark.parametrize("n", [1, 9])
def test_williams_refuses_sizes_out_of_range(n):
    with pytest.raises(ValueError):
        design.williams_rows(n)


@pytest.mark.parametrize("n", range(2, 9))
def test_schedule_is_balanced_over_complete_blocks(n):
    rng = np.random.default_rng(n)
    block = design.square_size(n)
    s = design.schedule(n, 2 * block, 1, rng)
    check_williams(list(s.design), n)
    pos = design.position_counts(s.order, n)
    assert np.all(pos == 2 * block // n)  # every model equally often at every position
    pairs = design.neighbour_pair_counts(s.order, n)
    off = pairs[~np.eye(n, dtype=bool)]
    assert np.all(off == off[0]) and np.all(np.diag(pairs) == 0)
    # each block of participants uses every design row exactly once
    for b in range(2):
        assert sorted(r[0] for r in s.rows[b * block:(b + 1) * block]) == list(range(block))


def test_codes_shared_or_per_participant():
    rng = np.random.default_rng(1)
    shared = design.system_codes(5, 30, False, rng)
    assert all(c == shared[0] for c in shared) and sorted(shared[0]) == [1, 2, 3, 4, 5]
    per = design.system_codes(5, 30, True, rng)
    assert all(sorted(c) == [1, 2, 3, 4, 5] for c in per)
    assert len({tuple(c) for c in per}) > 1


@pytest.fixture(scope="module")
def configs(tmp_path_factory):
    """Eight configs that differ (a model each), from the bundled default."""
    from haptic_acu.base.config import DEFAULT_CONFIG

    d = tmp_path_factory.mktemp("models")
    text = DEFAULT_CONFIG.read_text()
    paths = []
    for k in range(8):
        p = d / f"m{k}.toml"
        p.write_text(text.replace("max_hand_speed_m_per_s = ", f"max_hand_speed_m_per_s = {1 + k}.0 #", 1))
        paths.append(p)
    return paths


@pytest.mark.parametrize("n", [2, 3, 4, 5, 8])
def test_plan_csv_is_a_williams_design(tmp_path, configs, n, capsys):
    names = [f"model{k}" for k in range(n)]
    block = design.square_size(n)
    out = tmp_path / "s"
    rc = main(["study", "plan", "--participants", str(block), "--models",
               ",".join(f"{m}={p}" for m, p in zip(names, configs)), "--out", str(out), "--seed", "7"])
    assert rc == 0
    key = json.loads((out / "key.json").read_text())
    with open(out / "plan.csv", newline="") as f:
        plan = list(csv.DictReader(f))
    seqs = {}
    for r in plan:
        assert r["system"].startswith("System ") and r["system"] not in names
        seqs.setdefault(r["participant"], []).append(names.index(key["systems"][r["participant"]][r["system"]]))
    # the design's rows in the key's order (square, then its mirror for odd n)
    rows = [seqs[p] for p in sorted(seqs, key=lambda p: key["participant_rows"][p][0])]
    assert [key["participant_rows"][p][0] for p in sorted(seqs, key=lambda p: key["participant_rows"][p][0])] \
        == list(range(block))
    check_williams(rows, n)
    assert "note" not in capsys.readouterr().err  # a complete block: nothing to say


def test_plan_says_an_incomplete_block(tmp_path, configs, capsys):
    rc = main(["study", "plan", "--participants", "7", "--models",
               ",".join(f"m{k}={p}" for k, p in enumerate(configs[:3])), "--out", str(tmp_path / "s")])
    assert rc == 0
    err = capsys.readouterr().err
    assert "7 participants is not a multiple of the design's 6 rows" in err
    doc = json.loads((tmp_path / "s" / "study.json").read_text())
    assert doc["balance"]["balanced_participants"] == 6


def test_holm_against_hand_computation():
    # sorted 0.005, 0.01, 0.03, 0.04 -> 4*0.005, 3*0.01, 2*0.03, max(1*0.04, 0.06)
    assert np.allclose(stats.holm([0.01, 0.04, 0.03, 0.005]), [0.03, 0.06, 0.06, 0.02])
    assert np.allclose(stats.holm([0.5, 0.9]), [1.0, 1.0])


def test_kendalls_w_closed_form():
    rng = np.random.default_rng(3)
    # untied ranks: W = 12 S / (m^2 (n^3 - n)), S the squared deviations of the rank sums
    m, n = 9, 4
    x = np.array([rng.permutation(n) + rng.uniform(0, 0.1) for _ in range(m)])
    ranks = np.argsort(np.argsort(x, axis=1), axis=1) + 1
    rs = ranks.sum(axis=0)
    w = 12 * ((rs - rs.mean()) ** 2).sum() / (m ** 2 * (n ** 3 - n))
    assert stats.friedman(x).w == pytest.approx(w, rel=1e-12)
    same = np.tile([1.0, 2.0, 3.0, 4.0], (6, 1))  # perfect agreement
    assert stats.friedman(same).w == pytest.approx(1.0)
    assert stats.friedman(x[:, :2]).p is None  # two models: Wilcoxon's job

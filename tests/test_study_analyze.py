"""`study analyze` recovers a known effect from synthetic ratings, gives exactly `haptic-acu score`'s
numbers on the same ratings, and sees an order effect and a carry-over effect put in by design."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from haptic_acu.analysis.scoring import INDICES
from haptic_acu.cli import main
from haptic_acu.study.store import Study

MODELS = ("Zetamodel", "Kappamodel", "Mumodel")
EFFECT = {"force_feedback": (2.0, 0.0, -2.0), "acupuncture_effect": (0.0, 1.5, -1.5)}  # by design
NULL = [i for i in INDICES if i not in EFFECT]


@pytest.fixture(scope="module")
def configs(tmp_path_factory):
    from haptic_acu.base.config import DEFAULT_CONFIG

    d = tmp_path_factory.mktemp("cfg")
    text = DEFAULT_CONFIG.read_text()
    out = []
    for k, m in enumerate(MODELS):
        p = d / f"{m}.toml"
        p.write_text(text.replace("cutting_n_per_mm_diameter = 1.6", f"cutting_n_per_mm_diameter = {1.6 + k}", 1))
        out.append(p)
    return ",".join(f"{m}={p}" for m, p in zip(MODELS, out))


def make_study(folder: Path, configs: str, participants: int, seed: int) -> tuple[Study, dict]:
    assert main(["study", "plan", "--participants", str(participants), "--models", configs, "--out", str(folder),
                 "--seed", str(seed)]) == 0
    study = Study(folder)
    return study, study.key()


def synthetic(study, key, order_drift=0.0, carry=None, seed=0):
    """Ratings of every trial (strings, as a participant types them), by (participant, model).

    Effect indices: the model's level plus noise. Null indices: each participant gives the models
    a permutation of the same three ratings, the permutation balanced over participants (each model
    gets each value equally often), so the models do not differ by design. ``order_drift`` adds
    that much per trial position to every index; ``carry`` (model -> shift) shifts the rating of
    the trial after that model."""
    rng = np.random.default_rng(seed)
    out = {}
    cycle = [(0, 1, 2), (1, 2, 0), (2, 0, 1)]
    for i, p in enumerate(study.participants):
        base = rng.uniform(5.5, 7.5)
        nullv = base + np.array([-0.8, 0.0, 0.8])
        seq = study.trials_of(p)
        for t in seq:
            m = MODELS.index(key["systems"][p][t.system])
            prev = None if t.trial == 1 else key["systems"][p][seq[t.trial - 2].system]
            v = []
            for name in INDICES:
                if name in EFFECT:
                    x = base + EFFECT[name][m] + rng.normal(0, 0.6)
                else:
                    x = nullv[cycle[i % 3][m]]
                x += order_drift * (t.trial - 2)
                if carry and prev in carry:
                    x += carry[prev]
                v.append(f"{min(10.0, max(0.0, round(x, 1))):g}")
            out[p, key["systems"][p][t.system]] = (t, v)
    return out


def fill(study, ratings):
    for (p, m), (t, v) in ratings.items():
        study.record_ratings(t, [float(x) for x in v], "synthetic")


@pytest.fixture(scope="module")
def analyzed(configs, tmp_path_factory):
    d = tmp_path_factory.mktemp("an")
    study, key = make_study(d / "s", configs, 24, 11)
    ratings = synthetic(study, key, seed=4)
    fill(study, ratings)
    assert main(["study", "analyze", str(study.folder), "--out", str(d / "a"), "--no-objective"]) == 0
    report = json.loads((d / "a" / "report.json").read_text())
    return {"dir": d, "study": study, "ratings": ratings, "report": report, "out": d / "a"}


def test_friedman_recovers_the_designed_effect(analyzed):
    rep = analyzed["report"]["indices"]
    for name in EFFECT:
        assert rep[name]["friedman"]["p"] < 0.01, name
        assert rep[name]["friedman"]["n"] == 24
    for name in NULL:
        assert rep[name]["friedman"]["p"] > 0.05, name
    # force_feedback: Zeta > Kappa > Mu by 2 points each; every pair told apart after Holm
    pairs = {(q["a"], q["b"]): q for q in rep["force_feedback"]["pairwise"]}
    assert all(q["p_holm"] < 0.01 for q in pairs.values())
    assert pairs["Zetamodel", "Kappamodel"]["median_difference"] > 1.0
    assert pairs["Kappamodel", "Mumodel"]["median_difference"] > 1.0
    # Holm's p >= the raw p, and the medians follow the design
    for e in rep.values():
        for q in e["pairwise"]:
            assert q["p_holm"] >= q["p"] - 1e-15
    med = rep["force_feedback"]["models"]
    assert med["Zetamodel"]["median"] > med["Kappamodel"]["median"] > med["Mumodel"]["median"]


def test_descriptives_against_numpy(analyzed):
    """Median and IQR of one model's ratings, from the synthetic ratings directly."""
    v = np.array([float(vals[INDICES.index("acupuncture_effect")])
                  for (p, m), (t, vals) in analyzed["ratings"].items() if m == "Kappamodel"])
    d = analyzed["report"]["indices"]["acupuncture_effect"]["models"]["Kappamodel"]
    q1, med, q3 = np.percentile(v, [25, 50, 75])
    assert d["median"] == pytest.approx(med) and d["iqr"] == pytest.approx(q3 - q1) and d["n"] == 24
    with open(analyzed["out"] / "descriptives.csv", newline="") as f:
        row = next(r for r in csv.DictReader(f) if r["index"] == "acupuncture_effect" and r["model"] == "Kappamodel")
    assert float(row["median"]) == pytest.approx(med)


def test_scores_equal_haptic_acu_score(analyzed, tmp_path):
    """The ratings as an experimenter would unblind them by hand (system = model), scored by
    `haptic-acu score`: exactly analyze's scores and weights."""
    path = tmp_path / "by_model.csv"
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["system", "rater", *INDICES])
        for (p, m), (t, v) in sorted(analyzed["ratings"].items(), key=lambda kv: (MODELS.index(kv[0][1]), kv[0][0])):
            w.writerow([m, p, *v])
    assert main(["score", str(path), "--out", str(tmp_path / "score")]) == 0
    score = json.loads((tmp_path / "score" / "score.json").read_text())
    rep = analyzed["report"]
    assert [s["name"] for s in score["systems"]] == list(MODELS)
    for s in score["systems"]:
        mine = rep["scores"][s["name"]]
        assert mine["mean_score"] == s["mean_score"]
        assert mine["scores"] == s["scores"]
        assert mine["omega_combined"] == s["omega_combined"]
    # analyze's own copy of score's files says the same
    own = json.loads((analyzed["out"] / "score" / "score.json").read_text())
    assert own["systems"] == score["systems"]
    assert (analyzed["out"] / "score" / "scores.png").is_file()
    assert rep["ranking"] == sorted(MODELS, key=lambda m: -rep["scores"][m]["mean_score"])


def test_order_and_carry_over_checks(configs, tmp_path):
    """No order or carry-over effect by design: both checks quiet; a drift of 0.5 per position:
    the position Friedman sees it; a +1.5 after one model: the carry-over check sees it."""
    study, key = make_study(tmp_path / "s", configs, 24, 3)
    clean = synthetic(study, key, seed=1)
    fill(study, clean)
    assert main(["study", "analyze", str(study.folder), "--out", str(tmp_path / "a0"), "--no-objective"]) == 0
    rep0 = json.loads((tmp_path / "a0" / "report.json").read_text())["indices"]

    study2, key2 = make_study(tmp_path / "s2", configs, 24, 3)
    fill(study2, synthetic(study2, key2, order_drift=0.5, carry={"Zetamodel": 1.5}, seed=1))
    assert main(["study", "analyze", str(study2.folder), "--out", str(tmp_path / "a1"), "--no-objective"]) == 0
    rep1 = json.loads((tmp_path / "a1" / "report.json").read_text())["indices"]
    for name in NULL:  # exactly balanced by design without the effects
        assert rep0[name]["order"]["position_friedman"]["p"] > 0.05
        assert rep0[name]["order"]["carry_over"]["p"] > 0.05
        assert rep1[name]["order"]["position_friedman"]["p"] < 0.01
        assert rep1[name]["order"]["carry_over"]["p"] < 0.01
        after = rep1[name]["order"]["carry_over"]["mean_residual_after"]
        assert after["Zetamodel"] > max(after["Kappamodel"], after["Mumodel"])
    for f in ("indices.png", "order.png", "friedman.csv", "wilcoxon.csv", "order.csv"):
        assert (tmp_path / "a1" / f).is_file()


def test_analyze_bad_input(analyzed, tmp_path, capsys):
    study = analyzed["study"]
    assert main(["study", "analyze", str(study.folder), "--out", str(analyzed["out"])]) == 2
    assert "not empty" in capsys.readouterr().err
    assert main(["study", "analyze", str(study.folder), "--out", str(tmp_path / "x"), "--mu", "1.5"]) == 2
    assert "--mu" in capsys.readouterr().err
    # a hand-edited ratings.csv with a rating off the scale: one line naming the file and line
    text = study.ratings_path.read_text().splitlines()
    i = next(k for k, ln in enumerate(text) if ln.startswith("System"))
    bad = tmp_path / "bad"
    import shutil
    shutil.copytree(study.folder, bad)
    cells = text[i].split(",")
    cells[3] = "11"
    text[i] = ",".join(cells)
    (bad / "ratings.csv").write_text("\n".join(text) + "\n")
    assert main(["study", "analyze", str(bad), "--out", str(tmp_path / "y"), "--no-objective"]) == 2
    err = capsys.readouterr().err
    assert f"ratings.csv: line {i + 1}:" in err and "outside 0-10" in err and err.count("\n") == 1


def test_codes_per_participant_and_repeated_trials(configs, tmp_path):
    """Each participant with their own codes and every model met twice: analyze unblinds each
    participant by their own key and averages their two ratings of a model, as `score` is given
    them by hand."""
    assert main(["study", "plan", "--participants", "6", "--models", configs, "--out", str(tmp_path / "s"),
                 "--seed", "2", "--codes-per-participant", "--trials-per-model", "2"]) == 0
    study = Study(tmp_path / "s")
    key = study.key()
    assert len({tuple(sorted(key["systems"][p].items())) for p in study.participants}) > 1
    rng = np.random.default_rng(8)
    given = {}
    for p in study.participants:
        for t in study.trials_of(p):
            m = key["systems"][p][t.system]
            v = [float(f"{rng.uniform(1, 8) + (2.0 if m == 'Zetamodel' else 0.0):.1f}") for _ in INDICES]
            study.record_ratings(t, v, "synthetic")
            given.setdefault((m, p), []).append(v)
    assert all(len(v) == 2 for v in given.values())
    raters = {r.rater for r in study.read_ratings()[1]}
    assert {"P01/1", "P01/2"} <= raters
    by_hand = tmp_path / "by_hand.csv"
    with open(by_hand, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["system", "rater", *INDICES])
        for m in MODELS:
            for p in study.participants:
                a, b = given[m, p]
                w.writerow([m, p, *[repr((x + y) / 2) for x, y in zip(a, b)]])
    assert main(["score", str(by_hand), "--out", str(tmp_path / "sc")]) == 0
    assert main(["study", "analyze", str(study.folder), "--out", str(tmp_path / "a"), "--no-objective"]) == 0
    want = json.loads((tmp_path / "sc" / "score.json").read_text())["systems"]
    rep = json.loads((tmp_path / "a" / "report.json").read_text())
    for s in want:
        assert rep["scores"][s["name"]]["scores"] == s["scores"]
    assert rep["ranking"][0] == "Zetamodel"
    assert len(rep["indices"]["real_time"]["order"]["position_mean"]) == 6


def test_ratings_writes_are_atomic_and_locked(configs, tmp_path, monkeypatch):
    """A write that fails before its rename leaves ratings.csv as it was (no partial row, no
    temporary file); writers at the same time (threads, each with its own lock) lose no row."""
    import os
    import threading

    study, key = make_study(tmp_path / "s", configs, 6, 1)
    trials = [t for p in study.participants for t in study.trials_of(p)]
    study.record_ratings(trials[0], [5.0] * 7, "x")
    before = study.ratings_path.read_bytes()

    def boom(src, dst):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError):
        study.record_ratings(trials[1], [6.0] * 7, "x")
    monkeypatch.undo()
    assert study.ratings_path.read_bytes() == before
    assert [p.name for p in study.folder.iterdir() if p.name.endswith(".tmp")] == []

    errors = []

    def rate(t):
        try:
            Study(study.folder).record_ratings(t, [7.0] * 7, "x")
        except Exception as e:  # pragma: no cover - reported below
            errors.append(e)
    threads = [threading.Thread(target=rate, args=(t,)) for t in trials[1:]]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not errors
    assert len(Study(study.folder).rated()) == len(trials)

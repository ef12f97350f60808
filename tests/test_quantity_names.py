"""One name per quantity: every output's per-insertion columns map one to one onto
haptic_acu.analysis.quantities (the replay's summary.json, compare's table and compare.json, the
cohort's insertion table, and the insertions.csv a batch replay and a cohort write), and the twirl
amplitude is one number (its peak-to-peak swing) in the replay's text, compare.json, the cohort and
the written tables."""
from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from haptic_acu.analysis.quantities import BY_NAME, QUANTITIES, value
from haptic_acu.base.config import load_config
from haptic_acu.cli import main
from haptic_acu.analysis.comparison import DIFF_KEYS, INSERTION_ROWS

REPO = Path(__file__).resolve().parent.parent
TWIRL = REPO / "trajectories" / "twirl_even.csv"


@pytest.fixture(scope="module")
def outputs(tmp_path_factory):
    """A replay and a compare of the bundled twirl_even, in-process."""
    tmp = tmp_path_factory.mktemp("names")
    assert main(["replay", str(TWIRL), "--out", str(tmp / "replay"), "--no-rrd"]) == 0
    assert main(["compare", str(TWIRL), "default", "--out", str(tmp / "compare")]) == 0
    return tmp


def _leaves(d: dict, prefix=()) -> set[tuple]:
    out = set()
    for k, v in d.items():
        if isinstance(v, dict):
            out |= _leaves(v, prefix + (k,))
        else:
            out.add(prefix + (k,))
    return out


def test_names_and_paths_are_one_to_one():
    names = [q.name for q in QUANTITIES]
    paths = [q.path for q in QUANTITIES if q.path]
    labels = [q.label for q in QUANTITIES if q.label]
    assert len(set(names)) == len(names) and len(set(paths)) == len(paths) and len(set(labels)) == len(labels)
    for q in QUANTITIES:  # a number at the top level of the metrics dict has the same name there
        if q.path and len(q.path) == 1:
            assert q.path[0] == q.name, q


def test_cohort_columns_are_the_quantities():
    from haptic_acu.cohort.sessions import INSERTION_COLUMNS
    cols = [c.name for c in INSERTION_COLUMNS]
    assert set(cols) <= set(BY_NAME), sorted(set(cols) - set(BY_NAME))
    assert len(set(cols)) == len(cols)
    for c in INSERTION_COLUMNS:
        assert c.unit == BY_NAME[c.name].unit or (c.unit in ("", "1") and BY_NAME[c.name].unit in ("", "1")), c.name


def test_replay_summary_holds_every_quantity_at_its_path(outputs):
    per = json.loads((outputs / "replay" / "summary.json").read_text())["metrics"]["per_insertion"][0]
    leaves = _leaves(per)
    for q in QUANTITIES:
        if q.path:
            assert q.path in leaves, q.name
    # and each number the summary has under those groups is one quantity (no second name for it)
    claimed = {q.path for q in QUANTITIES if q.path}
    for group in ("lift_thrust", "peak_layer_force_n"):
        for leaf in {lf for lf in leaves if lf[0] == group}:
            assert leaf in claimed, leaf


def test_compare_rows_and_differences_map_one_to_one(outputs, capsys):
    doc = json.loads((outputs / "compare" / "compare.json").read_text())
    diff_keys = set(doc["differences"][0]["per_insertion"][0])
    assert diff_keys == set(DIFF_KEYS) and diff_keys <= set(BY_NAME)
    labels = [label for label, _ in INSERTION_ROWS]
    assert len(set(labels)) == len(labels)
    by_label = {q.label: q for q in QUANTITIES if q.label}
    quantity_rows = [lab for lab in labels if lab in by_label]
    puncture_rows = [lab for lab in labels if lab not in by_label]
    assert all(re.fullmatch(r"(skin|fat|muscle) puncture: peak \|F\| \(N\)", lab) for lab in puncture_rows)
    assert len({by_label[lab].name for lab in quantity_rows}) == len(quantity_rows)


def test_twirl_amplitude_is_one_number_in_text_compare_and_cohort(outputs, capsys):
    from haptic_acu.cohort.sessions import insertion_table
    from haptic_acu.session.replay import replay_rows

    summary = json.loads((outputs / "replay" / "summary.json").read_text())
    swing = value(summary["metrics"]["per_insertion"][0], BY_NAME["twirl_swing_deg"])
    assert swing == pytest.approx(180.0, abs=1.0)  # the file's +-90 deg twirl, peak to peak
    # the replay's text, from the same summary
    from haptic_acu.session.report import result_lines
    text = "\n".join(result_lines(summary))
    assert f"({swing:.0f} deg swing" in text
    doc = json.loads((outputs / "compare" / "compare.json").read_text())
    assert doc["sessions"][0]["metrics"]["per_insertion"][0]["technique"]["twirl"]["swing_deg"] == swing
    cfg = load_config()
    _, rows = insertion_table(replay_rows(TWIRL, cfg), cfg)
    assert rows[0]["twirl_swing_deg"] == swing


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """The tables the tools write, read back from disk: a batch replay's insertions.csv and a
    cohort's insertions.csv (one session: the bundled twirl_even, by name)."""
    import csv

    tmp = tmp_path_factory.mktemp("written")
    assert main(["replay", str(TWIRL), "default", "--out", str(tmp / "batch"), "--no-rrd", "--quiet", "--jobs",
                 "1"]) == 0  # the batch in this process (the worker processes' path: tests/test_replay_cli.py)
    man = tmp / "m.csv"
    man.write_text("session,trainee,file,level\ns1,ann,twirl_even,novice\n")
    assert main(["cohort", str(man), "--out", str(tmp / "cohort"), "--jobs", "1", "--quiet"]) == 0

    def read(path):
        with open(path, newline="") as fh:
            r = csv.reader(fh)
            header = next(r)
            return header, [dict(zip(header, row)) for row in r]
    return read(tmp / "batch" / "insertions.csv"), read(tmp / "cohort" / "insertions.csv")


@pytest.mark.slow  # a batch replay and a cohort run (~25 s)
def test_written_tables_name_each_quantity_once(written):
    from haptic_acu.cohort.sessions import INSERTION_COLUMNS

    (batch, _), (cohort, _) = written
    named = [q for q in QUANTITIES if q.path]
    for header in (batch, cohort):
        assert len(set(header)) == len(header)
        # no quantity under a second name: its summary path flattened is not a column beside its name
        assert not [q.name for q in named if "_".join(q.path) != q.name and "_".join(q.path) in header]
    assert {q.name for q in named} <= set(batch)
    assert [c.name for c in INSERTION_COLUMNS] == [c for c in cohort if c in BY_NAME]
    shared = (set(batch) & set(cohort)) - {"insertion", "trajectory"}
    assert shared and shared <= set(BY_NAME)  # a column both tables have is one quantity, one name


@pytest.mark.slow
def test_twirl_amplitude_is_one_number_in_the_written_tables(outputs, written):
    summary = json.loads((outputs / "replay" / "summary.json").read_text())
    swing = value(summary["metrics"]["per_insertion"][0], BY_NAME["twirl_swing_deg"])
    (_, batch), (_, cohort) = written
    assert float(batch[0]["twirl_swing_deg"]) == pytest.approx(swing, abs=1e-9)
    assert float(cohort[0]["twirl_swing_deg"]) == pytest.approx(swing, abs=1e-9)

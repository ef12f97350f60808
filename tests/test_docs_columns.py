"""The docs' column reference names every column the tool writes ("a column reference in
the docs"); the columns are taken from the writers themselves, so a new column without a line in
docs/output-files.md or docs/trajectory-format.md fails here."""
from __future__ import annotations

import re
from pathlib import Path

from haptic_acu.session import recorder
from haptic_acu.analysis import score_files
from haptic_acu.session.batch import puncture_rows, summary_row
from haptic_acu.session.report import CSV_FIELDS

ROOT = Path(__file__).resolve().parent.parent
OUTPUTS = (ROOT / "docs" / "output-files.md").read_text()
FORMAT = (ROOT / "docs" / "trajectory-format.md").read_text()


def _section(text: str, title: str) -> str:
    """The text of the section whose heading starts with ``title`` (up to the next heading)."""
    m = re.search(rf"^## {re.escape(title)}.*?$(.*?)(?=^## |\Z)", text, re.M | re.S)
    assert m, title
    return m.group(1)


def _table_names(section: str) -> set[str]:
    """Every `name` in the first cell of a table row."""
    names = set()
    for line in section.splitlines():
        if line.startswith("| `"):
            names |= set(re.findall(r"`([^`]+)`", line.split("|")[1]))
    return names


def test_every_samples_csv_column_has_a_row():
    names = _table_names(_section(OUTPUTS, "samples.csv"))
    assert set(CSV_FIELDS) <= names, set(CSV_FIELDS) - names
    assert names <= set(CSV_FIELDS), names - set(CSV_FIELDS)  # none that is gone


def test_every_recording_column_is_described():
    cols = ["t_s", "x_mm", "y_mm", "z_mm", *recorder.EXTRA, *recorder.EXTRA_AXIS]
    table = _table_names(_section(FORMAT, "Columns a trajectory may have")) | _table_names(
        _section(FORMAT, "What a recording adds"))
    assert set(cols) <= table, set(cols) - table


def test_every_batch_table_column_is_described():
    summary = {"trajectory": "a.csv", "duration_s": 1.0, "ticks": 1000, "max_force_n": 0.5, "max_tip_depth_mm": 9.0,
               "layers_reached": ["skin", "fat"],
               "punctures": [{"layer": "skin", "t_s": 0.5, "tip_depth_mm": 1.5, "peak_force_n": 0.47}],
               "metrics": {"insertions": 1, "skin_punctures": 1, "time_in_tissue_s": 0.4,
                           "lateral": {"max_n": 0.0, "ticks_over": 0, "time_over_s": 0.0},
                           "per_insertion": [{"t_entry_s": 0.4, "t_exit_s": 0.9}]}}
    section = _section(OUTPUTS, "A batch")
    names = _table_names(section)
    for col in summary_row(summary):
        generic = re.sub(r"^(skin|fat|muscle)_", "<layer>_", col)
        assert col in names or generic in names, f"summaries.csv column {col} is not in docs/output-files.md"
    for col in puncture_rows(summary)[0]:
        assert col in names, f"punctures.csv column {col} is not in docs/output-files.md"
    for col in ("trajectory", "insertion", "max_depth_mm", "max_tip_depth_mm", "depth_verdict"):
        assert f"`{col}`" in section


def test_score_tables_are_described(tmp_path):
    section = _section(OUTPUTS, "score")
    for col in ("system", "index", "mean_E", "sigma", "alpha_subjective", "beta_objective", "omega_combined",
                "rater", "score"):
        assert f"`{col}`" in section, col
    # and those are the headers the writers put on line 1
    score_files.write_weights_csv(tmp_path / "w.csv", [], [])
    score_files.write_scores_csv(tmp_path / "s.csv", [])
    for f in ("w.csv", "s.csv"):
        for col in (tmp_path / f).read_text().strip().split(","):
            assert f"`{col}`" in section, col

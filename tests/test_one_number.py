"""One name, one number: a key that appears at several levels of summary.json and in the
batch tables means the same quantity and has the same value there. The oblique entry is the case
that told them apart: its needle goes 25 mm into the tissue along a 30 degree axis while its tip is
only about 21.5 mm below the rest skin (25 cos 30 deg = 21.65 mm less the dents), and the summary
used to call the second number ``max_depth_mm`` like the first."""
from __future__ import annotations

import csv
import json
import math

from cli_helpers import cli


def test_tip_depth_and_needle_depth_have_their_own_names(tmp_path):
    r = cli("replay", "oblique_entry", "default", "--no-rrd", "--jobs", "1", "--quiet", "--out", "b", cwd=tmp_path,
            timeout=600)
    assert r.returncode == 0, r.stderr
    s = json.loads((tmp_path / "b" / "oblique_entry" / "summary.json").read_text())
    (ins,) = s["metrics"]["per_insertion"]
    # the two quantities differ here, by the geometry of a 30 degree insertion 25 mm deep
    assert ins["max_depth_mm"] == 25.0
    assert 25.0 * math.cos(math.radians(30)) - 1.0 < ins["max_tip_depth_mm"] < 25.0 * math.cos(math.radians(30))
    # one name each, one value at every level
    assert "max_depth_mm" not in s and s["max_tip_depth_mm"] == ins["max_tip_depth_mm"]
    assert "layers" not in s and set(s["places"]) == {"outside", "skin", "fat", "muscle", "bone"}
    with open(tmp_path / "b" / "summaries.csv", newline="") as f:
        rows = {row["trajectory"]: row for row in csv.DictReader(f)}
    assert "max_depth_mm" not in rows["oblique_entry.csv"]
    assert float(rows["oblique_entry.csv"]["max_tip_depth_mm"]) == s["max_tip_depth_mm"]
    with open(tmp_path / "b" / "insertions.csv", newline="") as f:
        irow = next(row for row in csv.DictReader(f) if row["trajectory"] == "oblique_entry.csv")
    assert float(irow["max_depth_mm"]) == ins["max_depth_mm"]
    assert float(irow["max_tip_depth_mm"]) == ins["max_tip_depth_mm"]


def test_compare_and_replay_show_the_technique_from_the_summary(tmp_path):
    """The twirling and the reinforcing / reducing label are on screen (replay's result lines and
    compare's table), with the numbers of summary.json / compare.json."""
    r = cli("compare", "twirl_reinforcing", "twirl_reducing", "--out", "c", cwd=tmp_path, timeout=600)
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "c" / "compare.json").read_text())
    techs = [s["metrics"]["per_insertion"][0]["technique"] for s in doc["sessions"]]
    assert [t["classification"]["label"] for t in techs] == ["reinforcing", "reducing"]
    rows = {line[:38].strip(): line[38:].split() for line in r.stdout.splitlines() if line.startswith("  ")}
    assert rows["technique"] == ["reinforcing", "reducing"]
    assert rows["twirl cycles"] == [str(t["twirl"]["cycles"]) for t in techs]
    assert rows["twirl swing, peak to peak (deg)"] == [f"{t['twirl']['swing_deg']:.0f}" for t in techs]
    assert rows["twirl frequency (Hz)"] == [f"{t['twirl']['frequency_hz']:.2f}" for t in techs]
    assert rows["thrust / lift resistance"] == [f"{t['lift_thrust_forces']['thrust_to_lift']:.2f}" for t in techs]

    from haptic_acu.session.report import result_lines

    summary = {"trajectory": "x.csv", "duration_s": 1.0, "ticks": 1000, "punctures": [], "max_force_n": 0.0,
               "max_tip_depth_mm": 25.0, "layers_reached": [],
               "metrics": {"target_depth_mm": [15, 30], "insertions": 1, "time_in_tissue_s": 1.0,
                           "per_insertion": [doc["sessions"][1]["metrics"]["per_insertion"][0]]}}
    tw = techs[1]["twirl"]
    line = result_lines(summary)[-1]
    assert line.endswith(f"; {tw['cycles']} twirl cycles ({tw['swing_deg']:.0f} deg swing, peak to peak, {tw['frequency_hz']:.2f} Hz); "
                         "technique: reducing"), line

"""The debrief (haptic_acu.analysis.debrief): findings worst first, the numbers the summary holds,
text that fits the terminal, Markdown for the report folder."""
from __future__ import annotations

import copy

from haptic_acu.analysis.debrief import debrief, debrief_lines, debrief_markdown
from haptic_acu.analysis.metrics import WITHHELD


def _insertion(**over) -> dict:
    m = {"max_depth_mm": 22.0, "entry_offset_mm": 0.4, "angle_deg": 3.0, "time_on_bone_s": 0.0,
         "time_at_force_limit_s": 0.0, "lift_thrust": {"cycles": 0, "mean_amplitude_mm": None, "frequency_hz": None},
         "technique": {"twirl": {"cycles": 0, "swing_deg": None, "frequency_hz": None, "net_rotation_deg": 0.0},
                       "classification": {"label": None, "twirl_vote": None, "lift_thrust_vote": None,
                                          "inputs": {}, "rule": {}}}}
    for k, v in over.items():
        m[k] = v
    return m


def _summary(*insertions) -> dict:
    return {"punctures": [{"layer": "skin"}], "needle_length_mm": 40.0, "force_limit_n": 3.3,
            "metrics": {"target_depth_mm": [15.0, 30.0], "per_insertion": list(insertions)}}


def test_a_session_into_bone_at_the_limit_names_each_fault_worst_first():
    bad = _insertion(max_depth_mm=36.7, time_on_bone_s=1.8, time_at_force_limit_s=1.25)
    bad["technique"]["classification"].update(label=None, withheld=WITHHELD)
    good = _insertion()
    d = debrief(_summary(good, bad))
    assert [i["insertion"] for i in d["insertions"]] == [2, 1]  # the worse insertion first
    texts = [f["text"] for f in d["insertions"][0]["findings"]]
    sev = [f["severity"] for f in d["insertions"][0]["findings"]]
    assert sev == sorted(sev, key=["danger", "fault", "note", "good"].index)
    assert "on bone for 1.80 s" in texts[0] and "limit (3.3 N) for 1.25 s" in texts[1]
    assert any("6.70 mm past the 30 mm limit" in t for t in texts)
    assert any(t.startswith("no technique label") for t in texts)
    assert not any(t.startswith("technique:") for t in texts)
    assert "bone" in d["change"]  # the one thing to change: the worst finding's
    assert all(f["severity"] == "good" for f in d["insertions"][1]["findings"])


def test_needle_fully_in_winding_and_entry():
    m = _insertion(max_depth_mm=40.0, entry_offset_mm=3.2, angle_deg=14.0)
    m["technique"]["twirl"].update(cycles=1, swing_deg=40.0, frequency_hz=0.5, net_rotation_deg=-590.0)
    m["needle_fully_in"] = True
    texts = " | ".join(f["text"] for f in debrief(_summary(m))["insertions"][0]["findings"])
    assert "the whole 40 mm needle went in" in texts
    assert "590 deg net counter-clockwise (1.64 turns)" in texts
    assert "3.20 mm off the acupoint" in texts and "14.0 deg" in texts


def test_the_label_and_why():
    m = _insertion()
    m["technique"]["twirl"].update(cycles=6, swing_deg=60.0, frequency_hz=0.8)
    m["technique"]["classification"] = {
        "label": "reinforcing", "twirl_vote": "reinforcing", "lift_thrust_vote": None,
        "inputs": {"swing_deg": 60.0, "frequency_hz": 0.8, "thrust_to_lift": None},
        "rule": {"small_swing_deg": 90.0, "large_swing_deg": 180.0, "slow_hz": 1.0, "fast_hz": 2.0, "heavy_ratio": 1.25}}
    (line,) = [f["text"] for f in debrief(_summary(m))["insertions"][0]["findings"] if f["text"].startswith("technique")]
    assert line.startswith("technique: reinforcing: twirling votes reinforcing (60 deg swing at 0.80 Hz")


def test_no_puncture_and_text_fits_the_width():
    d = debrief({"punctures": [], "metrics": {"target_depth_mm": [15, 30], "per_insertion": []}})
    assert "never went through the skin" in d["headline"] and d["change"]
    bad = _insertion(max_depth_mm=36.7, time_on_bone_s=1.8, time_at_force_limit_s=1.25)
    s = _summary(bad, copy.deepcopy(bad))
    for width in (40, 80, 120):
        lines = debrief_lines(debrief(s), width)
        assert all(len(x) <= width for x in lines) and len(lines) > 4
    md = debrief_markdown(debrief(s), "Debrief: test")
    assert md.startswith("# Debrief: test") and "## Insertion 1" in md and "**Danger**" in md

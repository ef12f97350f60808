"""``haptic-acu compare`` through the real CLI (its ``main``, in-process: exit status, stdout and stderr
as a shell sees them): the slow and the fast bundled insertions (their speed ratio is their
generator's 30/3), bad input as one-line errors, and the figure's determinism."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import cli as run_cli
from haptic_acu.session.compare import plot_compare
from haptic_acu.base.config import load_config
from haptic_acu.servo.samples import COL, NCOL

ROOT = Path(__file__).resolve().parent.parent
TRAJ = ROOT / "trajectories"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def cli(*args, cwd=None):
    return run_cli("compare", *args, cwd=cwd, timeout=600)


def assert_one_line_error(r, *needles):
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("haptic-acu compare: error: ")
    assert "Traceback" not in r.stderr
    for n in needles:
        assert n in lines[0]


@pytest.mark.slow
def test_slow_vs_fast_insertion(tmp_path):
    out = tmp_path / "cmp"
    r = cli(TRAJ / "slow_insertion.csv", TRAJ / "fast_insertion.csv", "--out", out, "--labels", "trainee", "expert")
    assert r.returncode == 0, r.stderr
    doc = json.loads((out / "compare.json").read_text())
    assert doc["labels"] == ["trainee", "expert"]
    a, b = (s["metrics"] for s in doc["sessions"])
    assert [s["trajectory"] for s in doc["sessions"]] == ["slow_insertion.csv", "fast_insertion.csv"]
    assert a["insertions"] == b["insertions"] == 1
    va = a["per_insertion"][0]["insertion_speed_mm_s"]
    vb = b["per_insertion"][0]["insertion_speed_mm_s"]
    # make_bundled.py: 3 mm/s and 30 mm/s, both at cruise speed by the time the tip reaches the skin
    assert va == pytest.approx(3.0, rel=0.05) and vb == pytest.approx(30.0, rel=0.05)
    assert vb / va == pytest.approx(10.0, rel=0.05)
    assert doc["first_insertion_b_minus_a"]["insertion_speed_mm_s"] == pytest.approx(vb - va, abs=1e-3)
    # the same path at ten times the speed reaches the target depth about ten times sooner
    ta, tb = a["per_insertion"][0]["time_to_target_s"], b["per_insertion"][0]["time_to_target_s"]
    assert ta / tb == pytest.approx(10.0, rel=0.1)
    # the printed table: a header with both labels, then rows with one value per session
    lines = r.stdout.splitlines()
    assert lines[0].split() == ["trainee", "expert"]
    speed = next(ln for ln in lines if "insertion speed" in ln).split()
    assert [float(speed[-2]), float(speed[-1])] == pytest.approx([va, vb], abs=0.01)
    assert lines[-1] == f"files: {out}/"
    png = (out / "compare.png").read_bytes()
    assert png.startswith(PNG_SIGNATURE)
    assert sorted(p.name for p in out.iterdir()) == ["compare.json", "compare.png"]
    assert not (tmp_path / "cmp.partial").exists()


def _bad(tmp_path):
    p = tmp_path / "trainee.csv"
    p.write_text("t_s,x_mm,y_mm,z_mm\n0,0,0,5\n0.01,0,0\n0.02,0,0,4\n")
    return p


def test_malformed_file_names_file_and_line(tmp_path):
    bad = _bad(tmp_path)
    for args in ((bad, TRAJ / "default.csv"), (TRAJ / "default.csv", bad)):
        r = cli(*args, "--out", tmp_path / "out")
        assert_one_line_error(r, str(bad), "line 3")
        assert not (tmp_path / "out").exists() and not (tmp_path / "out.partial").exists()


def test_missing_file_and_bad_arguments(tmp_path):
    r = cli(tmp_path / "nope.csv", TRAJ / "default.csv", "--out", tmp_path / "out")
    assert_one_line_error(r, str(tmp_path / "nope.csv"), "not found")
    r = cli(TRAJ / "default.csv", TRAJ / "fast_insertion.csv", "--config", tmp_path / "none.toml")
    assert_one_line_error(r, "none.toml")
    full = tmp_path / "full"
    full.mkdir()
    (full / "keep.txt").write_text("x")
    r = cli(TRAJ / "default.csv", TRAJ / "fast_insertion.csv", "--out", full)
    assert_one_line_error(r, str(full), "not empty")
    assert sorted(p.name for p in full.iterdir()) == ["keep.txt"]
    r = cli(TRAJ / "default.csv", TRAJ / "fast_insertion.csv", "--labels", "only-one")
    assert_one_line_error(r, "--labels", "one name per session")
    r = cli(TRAJ / "default.csv", TRAJ / "fast_insertion.csv", "--insertion", "0")
    assert_one_line_error(r, "--insertion")
    r = cli(TRAJ / "default.csv", TRAJ / "fast_insertion.csv", "--set", "scene.no_such_key=1")
    assert_one_line_error(r, "--set scene.no_such_key", "unknown key")


@pytest.mark.slow
def test_three_sessions_second_insertion(tmp_path):
    """Any number of sessions; --insertion picks one insertion of each (a session without it shows "-")."""
    out = tmp_path / "cmp3"
    sessions = [TRAJ / "new_site.csv", TRAJ / "second_insertion_same_site.csv", TRAJ / "fast_insertion.csv"]
    r = cli(*sessions, "--insertion", "2", "--out", out)
    assert r.returncode == 0, r.stderr
    doc = json.loads((out / "compare.json").read_text())
    assert doc["labels"] == [p.stem for p in sessions]
    ms = [s["metrics"] for s in doc["sessions"]]
    assert [m["insertions"] for m in ms] == [2, 2, 1]
    # new_site's second insertion is 5 mm along +x (trajectories/README.md); the same-site one is not
    assert ms[0]["per_insertion"][1]["entry_offset_mm"] == pytest.approx(5.0, abs=0.05)
    assert ms[1]["per_insertion"][1]["entry_offset_mm"] < 0.5
    diff = doc["differences"][0]["per_insertion"][1]["entry_offset_mm"]
    assert diff == pytest.approx(ms[1]["per_insertion"][1]["entry_offset_mm"] - 5.0, abs=0.06)
    lines = r.stdout.splitlines()
    assert lines[0].split() == [p.stem for p in sessions]
    assert any(ln.startswith("insertion 2 ") for ln in lines) and not any(ln.startswith("insertion 1 ") for ln in lines)
    offset = next(ln for ln in lines if "entry offset" in ln).split()
    assert offset[-1] == "-" and float(offset[-3]) == pytest.approx(5.0, abs=0.05)
    # the table's puncture peaks are the JSON's, digit for digit at the table's 3 decimals
    skin = next(ln for ln in lines if "skin puncture:" in ln).split()
    want = [p["peak_force_n"] for p in ms[0]["per_insertion"][1]["punctures"] if p["layer"] == "skin"]
    assert skin[-3] == f"{want[0]:.3f}"
    assert (out / "compare.png").read_bytes().startswith(PNG_SIGNATURE)


def _rows(depth_mm, force_n):
    r = np.zeros((len(depth_mm), NCOL))
    r[:, COL["t_s"]] = np.arange(len(depth_mm)) * 1e-3
    r[:, COL["depth_skin_m"]] = np.asarray(depth_mm) * 1e-3
    r[:, COL["z_m"]] = -np.asarray(depth_mm) * 1e-3  # straight down at the acupoint
    r[:, COL["fz_n"]] = force_n
    r[:, COL["state_skin"]] = np.where(np.asarray(depth_mm) > 0, 2, 1)
    return r


def test_figure_bytes_are_deterministic(tmp_path):
    d = np.concatenate([np.zeros(50), np.linspace(0, 20, 400), np.linspace(20, 0, 400)])
    a = _rows(d, 0.05 * d + 0.2 * np.sin(d))
    b = _rows(0.8 * d, 0.08 * d)
    bounds = load_config()  # the tissue is built from it (and reused)
    paths = [tmp_path / "one.png", tmp_path / "two.png"]
    for p in paths:
        plot_compare([a, b], ["trainee", "expert"], p, bounds)
    one, two = (p.read_bytes() for p in paths)
    assert one.startswith(PNG_SIGNATURE) and one == two
    assert b"Software" not in one and b"Date" not in one
    # a different session draws a different picture (the bytes depend on the data)
    plot_compare([a, _rows(0.5 * d, 0.08 * d)], ["trainee", "expert"], paths[1], bounds)
    assert paths[1].read_bytes() != one


def test_point_with_models_runs_the_point_through_each_model(tmp_path):
    """``--point`` with ``--models``: each column is the trajectory at the point through that model.
    The SHF column equals a --point comparison whose config's model is SHF, and is not the force
    net's (their skins break differently)."""
    import json

    from haptic_acu.cli import main

    both, one = tmp_path / "both", tmp_path / "one"
    assert main(["compare", "ST36_correct", "--point", "ST36", "--models", "forcenet,shf", "--out", str(both)]) == 0
    assert main(["compare", "ST36_correct", "--point", "ST36", "--set", "model.kind=shf", "--out", str(one)]) == 0
    doc, ref = (json.loads((d / "compare.json").read_text()) for d in (both, one))
    assert doc["labels"] == ["forcenet", "shf"] and doc["point"] == ref["point"] == "ST36"
    by_model = [s["metrics"] for s in doc["sessions"]]
    assert by_model[1] == ref["sessions"][0]["metrics"]
    assert by_model[0] != by_model[1]
    assert "critical_errors" in by_model[1]["per_insertion"][0]  # graded against the point

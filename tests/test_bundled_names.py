"""Bundled trajectories by name: an installed wheel's trajectories used from an empty folder.

A new user of the wheel has no ``trajectories/`` folder: ``replay NAME``, ``compare A B C`` and
``run --device scripted --trajectory NAME`` take a bundled trajectory's name. A user's own file of
the same name in the working folder wins; a path with a folder part is never replaced.
"""
from __future__ import annotations

import json
from pathlib import Path

from cli_helpers import cli  # in-process, run from the given folder
from haptic_acu.base.bundled import bundled_dir, bundled_trajectories, resolve_trajectory

ROOT = Path(__file__).resolve().parent.parent


def test_names_are_the_bundled_files_stems():
    # the bundled trajectories and the atlas points' (trajectories/points/, replayed with --point)
    files = sorted(p.name for p in (ROOT / "trajectories").glob("*.csv")) + sorted(
        p.name for p in (ROOT / "trajectories" / "points").glob("*.csv"))
    files.sort()
    assert sorted(f"{n}.csv" for n in bundled_trajectories()) == files
    assert "default" in bundled_trajectories() and "lateral_sweep" in bundled_trajectories()


def test_resolve_a_name_with_or_without_csv(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    want = bundled_dir("trajectories") / "lateral_sweep.csv"
    assert resolve_trajectory("lateral_sweep") == want
    assert resolve_trajectory("lateral_sweep.csv") == want
    assert resolve_trajectory("no_such_name") == Path("no_such_name")  # the caller's "not found" names it
    assert resolve_trajectory("sub/default.csv") == Path("sub/default.csv")  # a folder part: never replaced


def test_the_users_own_file_wins(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "default.csv").write_text("t_s,x_mm,y_mm,z_mm\n0,0,0,5\n1,0,0,4\n")
    assert resolve_trajectory("default.csv") == Path("default.csv")
    assert resolve_trajectory("default") == bundled_dir("trajectories") / "default.csv"  # no such file here


def test_replay_and_compare_by_name_from_an_empty_folder(tmp_path):
    r = cli("replay", "new_site", "--no-rrd", "--quiet", "--out", "by_name", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    r = cli("replay", ROOT / "trajectories" / "new_site.csv", "--no-rrd", "--quiet", "--out", "by_path", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    by_name = json.loads((tmp_path / "by_name" / "summary.json").read_text())
    by_path = json.loads((tmp_path / "by_path" / "summary.json").read_text())
    assert by_name["trajectory"] == "new_site.csv" and by_name["punctures"] == by_path["punctures"]
    assert (tmp_path / "by_name" / "samples.csv").read_bytes() == (tmp_path / "by_path" / "samples.csv").read_bytes()

    r = cli("compare", "default", "new_site", "lateral_sweep.csv", "--out", "cmp", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert [s["label"] for s in doc["sessions"]] == ["default", "new_site", "lateral_sweep"]


def test_unknown_name_is_one_line_listing_the_bundled_names(tmp_path):
    for args in (("replay", "nosuch"), ("compare", "default", "nosuch"),
                 ("run", "--device", "scripted", "--trajectory", "nosuch")):
        r = cli(*args, cwd=tmp_path)
        assert r.returncode == 2, (args, r.stderr)
        (line,) = r.stderr.strip().splitlines()
        assert "nosuch: trajectory file not found" in line and "default, " in line and "lateral_sweep" in line
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_run_scripted_plays_a_bundled_trajectory_by_name(tmp_path):
    r = cli("run", "--device", "scripted", "--trajectory", "default", "--duration", "1.5", "--speed", "8",
            "--no-status", "--quiet", "--out", "live", cwd=tmp_path)  # paced 8x: the same 1.5 s of ticks
    assert r.returncode == 0, r.stderr
    rec = (tmp_path / "live" / "recording.csv").read_text().splitlines()
    assert rec[0].startswith("t_s,x_mm,y_mm,z_mm")
    # default.csv starts at z = +5 mm and descends along -z at 10 mm/s: the file was played
    z = [float(line.split(",")[3]) for line in rec[1:]]
    assert z[0] == 5.0 and min(z) < 0.0

"""`haptic-acu cohort`: manifest checks, tables, known geometry through a real replay, resume, Dask."""
from __future__ import annotations

import json
import math
import multiprocessing
import os
import shutil

import numpy as np
import pyarrow.parquet as pq
import pytest

from cli_helpers import cohort_sessions_here
from haptic_acu.bench.cohort_bench import synthetic_cohort
from haptic_acu.cli import main
from haptic_acu.cohort.sessions import CohortDir, config_hash, read_manifest
from haptic_acu.cohort.tables import insertion_columns, session_columns
from haptic_acu.base.config import load_config
from haptic_acu.base.errors import UserError
from haptic_acu.session.trajectory import TrajectoryWriter

OFFSET_MM, ANGLE_DEG, DEPTH_MM = 2.0, 15.0, 22.0


def write_known_insertion(path):
    """A straight insertion entering 2 mm off the acupoint (along -y) at 15 deg to -z (tilted toward
    +x), minimum-jerk to 22 mm along the needle, a hold, and back out: 200 Hz samples."""
    a = math.radians(ANGLE_DEG)
    d = np.array([math.sin(a), 0.0, -math.cos(a)])
    entry = np.array([0.0, -OFFSET_MM, 0.0])
    hover = entry - 5.0 / math.cos(a) * d
    deep = entry + DEPTH_MM * d

    def mj(tau):
        tau = np.clip(tau, 0, 1)
        return tau ** 3 * (10 - 15 * tau + 6 * tau ** 2)

    t = np.arange(0, 5.0 + 1e-9, 1 / 200)
    s_in, s_out = mj((t - 0.3) / 2.0), mj((t - 3.0) / 1.7)
    p = hover + (s_in - s_out)[:, None] * (deep - hover)
    with TrajectoryWriter(path) as w:
        w.append_rows(np.column_stack([t, p * 1e-3]))


@pytest.fixture(scope="module")
def cohort(tmp_path_factory):
    """A small class (2 trainees x 2 sessions, ~5 s each), the known insertion, a malformed
    trajectory and a missing file, replayed once with the local pool."""
    root = tmp_path_factory.mktemp("cohort")
    man = synthetic_cohort(root / "class", trainees=2, sessions=2, duration_s=5.0, seed=3)
    write_known_insertion(root / "class" / "known.csv")
    (root / "class" / "garbled.csv").write_text("t_s,x_mm,y_mm,z_mm\n0,0,0,5\n0.1,0,zero,5\n")
    with open(man, "a") as f:
        f.write("known,trainee09,known.csv,expert,2026-09-09,class-9\n")
        f.write("garbled,trainee09,garbled.csv,expert,2026-09-11,class-9\n")
        f.write("ghost,trainee09,sessions/nope.csv,expert,2026-09-10,class-9\n")
    out = root / "out"
    rc = main(["cohort", str(man), "--out", str(out), "--jobs", "2", "--quiet"])
    return {"root": root, "manifest": man, "out": out, "rc": rc}


def tables(out):
    return {n: pq.read_table(out / f"{n}.parquet") for n in ("insertions", "sessions")}


# ---- the manifest ----------------------------------------------------------------------------
def test_bad_manifest_rows_one_line_each(tmp_path, capsys):
    (tmp_path / "a.csv").write_text("t_s,x_mm,y_mm,z_mm\n0,0,0,5\n1,0,0,4\n")
    man = tmp_path / "m.csv"
    man.write_text("session,trainee,file,level\n"
                   "s1,ann,a.csv,novice\n"
                   "s1,bob,a.csv,novice\n"          # line 3: duplicate session
                   "s2,bob,a.csv,novice,surplus\n"  # line 4: a cell beyond the header
                   "s3,,a.csv,expert\n")            # line 5: empty trainee
    rc = main(["cohort", str(man), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert rc == 2
    assert len(lines) == 3 and "Traceback" not in err
    assert "line 3" in lines[0] and "duplicate session 's1'" in lines[0] and "line 2" in lines[0]
    assert "line 4" in lines[1] and "5 fields" in lines[1]
    assert "line 5" in lines[2] and "'trainee'" in lines[2]
    assert not (tmp_path / "out").exists()  # nothing ran, nothing written


@pytest.mark.parametrize("header, expect", [
    ("session,trainee,level", "missing column 'file'"),
    ("session,trainee,file,economy_of_motion", "unknown column 'economy_of_motion'"),
    ("session,trainee,file,file", "column 'file' appears twice"),
])
def test_bad_manifest_header(tmp_path, capsys, header, expect):
    man = tmp_path / "m.csv"
    man.write_text(header + "\n" + ",".join(["x"] * len(header.split(","))) + "\n")
    assert main(["cohort", str(man), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert expect in err and "line 1" in err and str(man) in err and len(err.strip().splitlines()) == 1


def test_manifest_resolves_relative_paths_and_checks_dates(tmp_path):
    sub = tmp_path / "deep"
    sub.mkdir()
    (sub / "m.csv").write_text("trainee,file,session,date,room\nann,x/a.csv,s1,2026-01-02,12\nbob,/abs/b.csv,s2,,\n")
    m = read_manifest(sub / "m.csv")
    assert [e.path for e in m.entries] == [sub / "x" / "a.csv", __import__("pathlib").Path("/abs/b.csv")]
    assert m.columns == ["trainee", "file", "session", "date", "room"]
    assert m.entries[0].cells["room"] == "12"
    (sub / "m.csv").write_text("session,trainee,file,date\ns1,ann,a.csv,last tuesday\n")
    with pytest.raises(UserError, match="line 2: date 'last tuesday'"):
        read_manifest(sub / "m.csv")


# ---- a whole run -----------------------------------------------------------------------------
def test_failed_session_is_one_row_with_its_error_and_the_others_finish(cohort):
    assert cohort["rc"] == 2  # a session failed
    t = tables(cohort["out"])
    ses = t["sessions"].to_pylist()
    assert [r["session"] for r in ses] == ["t00-s00", "t00-s01", "t01-s00", "t01-s01", "known", "garbled", "ghost"]
    bad = [r for r in ses if r["error"]]
    assert [r["session"] for r in bad] == ["garbled", "ghost"]
    assert "garbled.csv" in bad[0]["error"] and "line 3" in bad[0]["error"] and "y_mm" in bad[0]["error"]
    assert "line 8" in bad[1]["error"] and "nope.csv" in bad[1]["error"] and "not found" in bad[1]["error"]
    assert all(r["insertions"] >= 1 for r in ses if not r["error"])
    ins = t["insertions"].to_pylist()
    for s in ("garbled", "ghost"):
        rows = [r for r in ins if r["session"] == s]
        assert len(rows) == 1 and rows[0]["insertion"] is None and rows[0]["economy_of_motion"] is None
    assert {r["group"] for r in ins} == {"class-0", "class-1", "class-9"}  # extra column carried through


def test_columns_documented_with_units(cohort):
    t = tables(cohort["out"])
    for name, cols in (("insertions", insertion_columns()), ("sessions", session_columns())):
        schema = t[name].schema
        manifest_cols = ["session", "trainee", "file", "level", "date", "group"]
        assert schema.names == manifest_cols + [c.name for c in cols]
        for c in cols:
            meta = schema.field(c.name).metadata
            assert meta[b"unit"].decode() == c.unit and meta[b"description"]
    csv_header = (cohort["out"] / "insertions.csv").read_text().splitlines()[0]
    assert csv_header.replace('"', "").split(",") == t["insertions"].schema.names
    report = json.loads((cohort["out"] / "report.json").read_text())
    assert report["columns"]["insertions"]["path_length_mm"]["unit"] == "mm"


def test_known_angle_offset_and_straight_path_through_a_replay(cohort):
    rows = [r for r in tables(cohort["out"])["insertions"].to_pylist() if r["session"] == "known"]
    assert len(rows) == 1
    r = rows[0]
    assert r["entry_offset_mm"] == pytest.approx(OFFSET_MM, abs=0.05)
    # against the inward skin normal at the entry, which at 2 mm off the pole of the body tilts by
    # well under a degree
    assert r["angle_deg"] == pytest.approx(ANGLE_DEG, abs=1.0)
    assert r["economy_of_motion"] == pytest.approx(1.0, abs=1e-3)
    # the thrust is a minimum-jerk movement entered part-way: smooth, though not the full profile's -5.32
    assert -8.0 < r["ldlj"] < -4.0
    assert r["depth_verdict"] == "in range" and r["depth_error_mm"] == 0.0
    assert r["skin_punctured"] is True
    # in and out along one line: the path is at least twice the depth reached
    assert r["path_length_mm"] >= 2 * r["max_depth_mm"] - 0.05  # (the path is of the smoothed positions)


def test_report_learning_curves_and_levels(cohort):
    rep = json.loads((cohort["out"] / "report.json").read_text())
    ses = tables(cohort["out"])["sessions"].to_pylist()
    assert rep["sessions"] == 7 and rep["failed"] == 2
    assert set(rep["learning_curves"]) == {"trainee00", "trainee01", "trainee09"}
    lc = rep["learning_curves"]["trainee00"]
    assert lc["sessions"] == ["t00-s00", "t00-s01"]
    # the report's statistics work at each metric's resolution (4 decimals for the economy of motion)
    assert lc["metrics"]["mean_economy_of_motion"]["values"] == pytest.approx(
        [round(r["mean_economy_of_motion"], 4) for r in ses if r["trainee"] == "trainee00"], abs=1e-9)
    assert lc["metrics"]["mean_economy_of_motion"]["better"] == "higher"
    assert lc["metrics"]["mean_depth_error_mm"]["better"] == "zero"
    comp = rep["level_comparison"]
    assert comp["levels"] == ["novice", "expert"]
    m = comp["metrics"]["mean_entry_offset_mm"]
    ok = [r for r in ses if not r["error"]]
    for lv in ("novice", "expert"):
        vals = [round(r["mean_entry_offset_mm"], 2) for r in ok if r["level"] == lv]  # at its 0.01 mm resolution
        assert m["by_level"][lv]["n"] == len(vals)
        assert m["by_level"][lv]["median"] == pytest.approx(float(np.median(vals)), abs=1e-6)
    pair = m["pairs"][0]
    # effect size by definition: the share of (novice, expert) pairs with the novice's value larger
    nov = [round(r["mean_entry_offset_mm"], 2) for r in ok if r["level"] == "novice"]
    exp = [round(r["mean_entry_offset_mm"], 2) for r in ok if r["level"] == "expert"]
    share = np.mean([(a > b) + 0.5 * (a == b) for a in nov for b in exp])
    assert pair["common_language"] == pytest.approx(share, abs=1e-6)
    assert pair["rank_biserial"] == pytest.approx(2 * share - 1, abs=1e-6)
    for png in rep["figures"].values():
        assert (cohort["out"] / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_dask_cluster_gives_the_local_tables(cohort, tmp_path, capsys, monkeypatch):
    """The user's path: ``--scheduler tcp://HOST:PORT`` on the command line, to a cluster listening on
    TCP (its workers threads of this process, to spare the test machine's cores); the sessions go
    two to a task, the garbled file's failure in a batch with a good session."""
    distributed = pytest.importorskip("distributed")
    from haptic_acu.cohort import run

    sizes = []
    monkeypatch.setattr(run, "batch_size", lambda n, threads: sizes.append(n) or 2)
    before = set(multiprocessing.active_children())
    import dask

    with dask.config.set({"temporary-directory": str(tmp_path / "dask-scratch")}), \
            distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, protocol="tcp://",
                                     dashboard_address=None) as lc:
        address = lc.scheduler_address
        assert address.startswith("tcp://")
        rc = main(["cohort", str(cohort["manifest"]), "--out", str(tmp_path / "dask"), "--scheduler", address])
    assert rc == 2 and sizes == [6, 4, 2]  # every session but the missing file, in three tasks
    err = capsys.readouterr().err
    assert f"on dask at {address}, 2 worker thread(s)" in err
    assert err.count("session 'garbled' failed") == 1 and "session 'known' failed" not in err
    a, b = tables(cohort["out"]), tables(tmp_path / "dask")
    for n in a:
        assert a[n].equals(b[n]), n
    assert set(multiprocessing.active_children()) <= before


# ---- resume ----------------------------------------------------------------------------------
def replayed_count(err: str) -> tuple[int, int]:
    import re
    m = re.search(r"\((\d+) replayed in .*?, (\d+) up to date\)", err)
    return int(m.group(1)), int(m.group(2))


def test_resume_after_an_interrupted_run(cohort, tmp_path, monkeypatch, capsys):
    root = tmp_path / "class"
    shutil.copytree(cohort["root"] / "class", root)
    man = root / "manifest.csv"
    out = tmp_path / "out"
    saved = []
    real_save = CohortDir.save

    def save_then_interrupt(self, rec):
        real_save(self, rec)
        saved.append(rec["session"])
        if len(saved) == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(CohortDir, "save", save_then_interrupt)
    assert main(["cohort", str(man), "--out", str(out), "--jobs", "2", "--quiet"]) == 130
    monkeypatch.undo()
    assert multiprocessing.active_children() == []  # the pool's workers were ended
    from haptic_acu.base.outputs import FolderLock
    FolderLock(out / ".cohort" / "lock", "still held").acquire().release()  # the interrupted run let go
    assert not (out / "sessions.parquet").exists()
    capsys.readouterr()

    # the re-run replays only what the interrupted run did not finish; the tables match a clean run
    # (its sessions replayed in this process: which ones run is the point here; a pool's run of the
    # same sessions made the tables compared with)
    replayed = cohort_sessions_here(monkeypatch)
    assert main(["cohort", str(man), "--out", str(out), "--jobs", "2"]) == 2
    assert replayed_count(capsys.readouterr().err) == (4, 2)  # the malformed file's record is kept too
    assert len(replayed) == 4 and not set(replayed) & set(saved)
    a, b = tables(cohort["out"]), tables(out)
    for n in a:  # the ghost's error names its absolute path: the copy's differs
        assert a[n].drop_columns(["error"]).equals(b[n].drop_columns(["error"])), n
        assert [bool(e) for e in a[n]["error"].to_pylist()] == [bool(e) for e in b[n]["error"].to_pylist()]

    # nothing changed: nothing replayed; a changed file: that session only
    replayed.clear()
    assert main(["cohort", str(man), "--out", str(out), "--jobs", "1"]) == 2
    assert replayed_count(capsys.readouterr().err) == (0, 6) and replayed == []
    with open(root / "sessions" / "t01-s00.csv", "a") as f:
        f.write("# edited\n")
    assert main(["cohort", str(man), "--out", str(out), "--jobs", "1"]) == 2
    assert replayed_count(capsys.readouterr().err) == (1, 5)
    assert replayed == ["t01-s00"]


def test_config_hash_follows_values_not_file_names(tmp_path):
    cfg = load_config()
    h = config_hash(cfg)
    t = cfg.skin.thickness_mm
    assert config_hash(load_config(overrides=[f"skin.thickness_mm={t}"])) == h  # the value it already has
    assert config_hash(load_config(overrides=[f"skin.thickness_mm={t + 0.2}"])) != h
    copy = tmp_path / "same.toml"
    copy.write_text(open(cfg.path).read())
    assert config_hash(load_config(copy)) == h
    with pytest.raises(UserError, match="--set skin.thick: unknown key"):
        load_config(overrides=["skin.thick=1"])
    with pytest.raises(UserError, match="must be > 0"):
        load_config(overrides=["skin.thickness_mm=-1"])


def test_refuses_a_folder_it_did_not_make_and_a_second_writer(tmp_path, capsys):
    man = tmp_path / "m.csv"
    man.write_text("session,trainee,file\ns1,ann,a.csv\n")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    assert main(["cohort", str(man), "--out", str(mine)]) == 2
    assert "not a cohort output" in capsys.readouterr().err
    assert sorted(os.listdir(mine)) == ["notes.txt"]
    out = tmp_path / "out"
    with CohortDir(out):
        assert main(["cohort", str(man), "--out", str(out)]) == 2
        assert f"(pid {os.getpid()})" in capsys.readouterr().err


def test_report_statistics_on_constructed_sessions(tmp_path):
    from haptic_acu.cohort.report import REPORT_METRICS, write_report

    rows = []
    # trainee a: listed out of date order; metric = 2 * (rank by date) + 1. b: no dates, manifest order.
    for k, day in enumerate([3, 1, 2, 4]):
        rows.append({"session": f"a{k}", "trainee": "a", "level": "novice", "date": f"2026-01-0{day}",
                     "error": "", "insertions": 1, **{c: 2.0 * day + 1 for c, _ in REPORT_METRICS}})
    for k in range(3):
        rows.append({"session": f"b{k}", "trainee": "b", "level": "expert", "date": "", "error": "",
                     "insertions": 1, **{c: 100.0 - k for c, _ in REPORT_METRICS}})
    rows.append({"session": "c0", "trainee": "c", "level": "mid", "date": "", "error": "", "insertions": 1,
                 **{c: 50.0 for c, _ in REPORT_METRICS}})
    rows.append({"session": "bad", "trainee": "a", "level": "novice", "date": "", "error": "boom", "insertions": None})
    rep = write_report(tmp_path, rows, {})
    col = REPORT_METRICS[0][0]
    a = rep["learning_curves"]["a"]
    assert a["sessions"] == ["a1", "a2", "a0", "a3"]  # by date; the failed session left out
    assert a["days_since_first"] == [0.0, 1.0, 2.0, 3.0]
    assert a["metrics"][col]["values"] == [3.0, 5.0, 7.0, 9.0]
    assert a["metrics"][col]["theil_slope_per_session"] == pytest.approx(2.0)
    assert a["metrics"][col]["spearman_rho"] == pytest.approx(1.0)
    b = rep["learning_curves"]["b"]
    assert b["sessions"] == ["b0", "b1", "b2"] and b["days_since_first"] is None and b["metrics"][col]["theil_slope_per_session"] == pytest.approx(-1.0)
    comp = rep["level_comparison"]
    assert comp["levels"] == ["novice", "expert", "mid"]
    m = comp["metrics"][col]
    assert m["by_level"]["novice"]["median"] == pytest.approx(6.0) and m["by_level"]["expert"]["median"] == 99.0
    ne = next(p for p in m["pairs"] if (p["a"], p["b"]) == ("novice", "expert"))
    # every expert session above every novice one: U = 0, CL = 0, rank-biserial -1
    assert ne["mannwhitney_u"] == 0.0 and ne["common_language"] == 0.0 and ne["rank_biserial"] == -1.0
    assert ne["median_difference"] == pytest.approx(6.0 - 99.0)
    # Kruskal-Wallis by hand: ranks novice 1-4, mid 5, expert 6-8 (N = 8, no ties):
    # H = 12 / (N (N + 1)) * (10^2/4 + 5^2/1 + 21^2/3) - 3 (N + 1) = 35/6; p = exp(-H/2) (chi-square, 2 dof)
    assert m["kruskal_h"] == pytest.approx(35 / 6, abs=1e-6)
    assert m["kruskal_p"] == pytest.approx(math.exp(-35 / 12), rel=1e-3)
    assert set(rep["figures"]) == {"learning_curves", "levels"}


def test_progress_line_counts_and_eta():
    import io

    from haptic_acu.cohort.run import ProgressLine

    buf = io.StringIO()  # not a terminal: whole lines, the first at once and the last at the end
    p = ProgressLine(total=3, skipped=2, stream=buf, every_s=1e9)
    for failed in (False, True, False):
        p.update(failed=failed)
    p.close()
    lines = buf.getvalue().splitlines()
    assert len(lines) == 2
    assert lines[0].startswith("cohort: 1/3 replayed (2 up to date, skipped)") and "ETA" in lines[0]
    assert lines[1].startswith("cohort: 3/3 replayed (2 up to date, skipped), 1 failed") and "ETA 0m00s" in lines[1]


def test_session_files_on_request(cohort, tmp_path, monkeypatch):
    replayed = cohort_sessions_here(monkeypatch)  # the pool has tests of its own above
    man = tmp_path / "one.csv"
    man.write_text(f"session,trainee,file\nknown one,ann,{cohort['root'] / 'class' / 'known.csv'}\n")
    out = tmp_path / "out"
    assert main(["cohort", str(man), "--out", str(out), "--jobs", "1", "--quiet", "--session-files"]) == 0
    assert replayed == ["known one"]
    (folder,) = (out / "sessions").iterdir()
    assert folder.name.startswith("known_one-")
    assert sorted(p.name for p in folder.iterdir()) == ["force_depth.png", "samples.csv", "summary.json"]
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["metrics"]["insertions"] == 1 and summary["trajectory"] == "known.csv"
    n_rows = len((folder / "samples.csv").read_text().splitlines()) - 1
    assert n_rows == summary["ticks"]


def test_session_files_asked_on_a_later_run(cohort, tmp_path, capsys, monkeypatch):
    """Sessions up to date but replayed without --session-files are replayed for their files when a
    later run asks for them; a further run with it skips them again."""
    replayed = cohort_sessions_here(monkeypatch)  # the pool has tests of its own above
    man = tmp_path / "one.csv"
    man.write_text(f"session,trainee,file\nknown,ann,{cohort['root'] / 'class' / 'known.csv'}\n")
    out = tmp_path / "out"
    assert main(["cohort", str(man), "--out", str(out), "--jobs", "1"]) == 0
    assert not (out / "sessions").exists()
    capsys.readouterr()
    assert main(["cohort", str(man), "--out", str(out), "--jobs", "1", "--session-files"]) == 0
    assert replayed_count(capsys.readouterr().err) == (1, 0)
    (folder,) = (out / "sessions").iterdir()
    assert (folder / "summary.json").is_file() and (folder / "samples.csv").is_file()
    assert main(["cohort", str(man), "--out", str(out), "--jobs", "1", "--session-files"]) == 0
    assert replayed_count(capsys.readouterr().err) == (0, 1)
    assert replayed == ["known", "known"]  # what the runs said they replayed


def test_learning_curve_keeps_each_session_in_its_place(tmp_path):
    """A session without an insertion is a gap on its trainee's curve: the later sessions keep their
    numbers, and the slope is fitted at those numbers."""
    from haptic_acu.cohort.report import REPORT_METRICS, learning_curves

    col = REPORT_METRICS[0][0]
    rows = []
    for k in range(1, 5):  # session 2 punctured no skin: no value; the others lie on y = 2 x + 1
        value = None if k == 2 else 2.0 * k + 1
        rows.append({"session": f"s{k}", "trainee": "a", "date": f"2026-02-0{k}", "error": "",
                     "insertions": 0 if k == 2 else 1, col: value})
    rows.append({"session": "failed", "trainee": "a", "date": "2026-02-05", "error": "boom", "insertions": None})
    a = learning_curves(rows)["a"]
    assert a["sessions"] == ["s1", "s2", "s3", "s4"]
    assert a["days_since_first"] == [0.0, 1.0, 2.0, 3.0]
    m = a["metrics"][col]
    assert m["values"] == [3.0, None, 7.0, 9.0]
    # at x = 1, 3, 4 the points are collinear: slope 2 (numbered 1, 2, 3 they would give 3)
    assert m["theil_slope_per_session"] == pytest.approx(2.0)
    assert m["spearman_rho"] == pytest.approx(1.0)


def test_figure_axes_read_plain_values():
    """A metric equal in every session up to rounding is drawn flat around its value with plain tick
    labels, not as a range blown up to the axis (matplotlib's offset '1e-9+9.99999999e-1')."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from haptic_acu.cohort.report import readable_y

    fig, (flat, spread) = plt.subplots(1, 2)
    flat_values = [1.0, 0.999999999, 1.0, 0.999999999]
    flat.plot(range(4), flat_values, "o")
    readable_y(flat, flat_values)
    spread.plot(range(3), [3.0, 5.0, 9.0], "o")
    readable_y(spread, [3.0, 5.0, 9.0, None])
    fig.canvas.draw()
    lo, hi = flat.get_ylim()
    assert lo < 0.96 and hi > 1.04 and flat.yaxis.get_offset_text().get_text() == ""
    assert all("e" not in t.get_text() for t in flat.get_yticklabels())
    lo, hi = spread.get_ylim()
    assert lo <= 3.0 and hi >= 9.0 and hi - lo < 8.0  # a real spread keeps matplotlib's own limits
    plt.close(fig)


def test_failed_session_line_names_the_manifest_line(tmp_path, capsys, monkeypatch):
    cohort_sessions_here(monkeypatch)  # the pool has tests of its own above
    (tmp_path / "garbled.csv").write_text("t_s,x_mm,y_mm,z_mm\n0,0,0,5\n0.1,0,zero,5\n")
    man = tmp_path / "m.csv"
    man.write_text("session,trainee,file\n"
                   "g1,ann,garbled.csv\n"
                   "gone,ann,missing.csv\n")
    assert main(["cohort", str(man), "--out", str(tmp_path / "out"), "--jobs", "1", "--quiet"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 2 and all(ln.startswith(f"haptic-acu cohort: error: {man}: line ") for ln in lines)
    assert not (tmp_path / "out").exists()  # every session failed: no output folder left behind
    by_session = {("g1" if "'g1'" in ln else "gone"): ln for ln in lines}
    assert "line 2:" in by_session["g1"] and "garbled.csv: line 3" in by_session["g1"]
    assert "line 3:" in by_session["gone"] and "not found" in by_session["gone"]


@pytest.mark.parametrize("address, expect", [
    ("localhost", "missing port number"),
    ("tcp://scheduler:port", "expected tcp://HOST:PORT"),
    ("tcp://scheduler:0", "a port in 1-65535"),
])
def test_bad_scheduler_address_one_line_nothing_made(tmp_path, address, expect):
    """A malformed --scheduler is one line and exit 2 before any folder is made; the process ends
    at once (a distributed Client made with it waited 40 s at exit and printed a traceback)."""
    import subprocess
    import sys

    man = tmp_path / "m.csv"
    man.write_text("session,trainee,file\ns1,ann,a.csv\n")
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-m", "haptic_acu", "cohort", str(man), "--out", str(out),
                        "--scheduler", address], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"haptic-acu cohort: error: --scheduler {address}: ")
    assert expect in lines[0]
    assert not out.exists()

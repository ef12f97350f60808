"""Every command against a hostile user: each defect found by trying ~330 bad inputs, one test each.

Outcome wanted everywhere: a user's file is never replaced without --overwrite; bad input is one
line on stderr naming the file, line or key, exit 2, no traceback; nothing unbounded. The CLI runs
in-process (haptic_acu.cli.main) unless the test is about processes.
"""
from __future__ import annotations

import os
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import cli as run_cli, cohort_sessions_here
from haptic_acu.base.outputs import claim_folder

REPO = Path(__file__).resolve().parents[1]
DEFAULT = REPO / "trajectories" / "default.csv"
from haptic_acu.analysis.scoring import INDICES  # noqa: E402
PROGRESS = re.compile(r"^haptic-acu: ")
BIG = "x" * 200_000  # over csv's 128 kB field limit


def cli(*argv) -> tuple[int, str]:
    r = run_cli(*argv)
    return r.returncode, r.stderr


def one_line(res, status=2, *names) -> str:
    code, err = res
    assert code == status, (code, err)
    lines = [ln for ln in err.strip().splitlines() if not PROGRESS.match(ln)]
    assert len(lines) == 1 and "Traceback" not in err, err
    for n in names:
        assert str(n) in lines[0], lines[0]
    return lines[0]


def ratings(path: Path, systems=("A", "B"), raters=("r1", "r2"), field=None) -> Path:
    rows = ["system,rater," + ",".join(INDICES)]
    for k, s in enumerate(systems):
        for j, r in enumerate(raters):
            rows.append(f"{s},{r}," + ",".join(str((k + j + i) % 9 + 1) for i in range(len(INDICES))))
    if field is not None:
        rows.append(f"A,{field}," + ",".join("5" for _ in INDICES))
    path.write_text("\n".join(rows) + "\n")
    return path


def curve(path: Path, depth_scale=1.0, force_scale=1.0, bom=False) -> Path:
    """A rise to a break at 4 mm (1.2 N), a drop to 0.5 N and a slow rise: 200 points."""
    x = np.linspace(0.0, 10.0, 200)
    f = np.where(x <= 4.0, 1.2 * (x / 4.0) ** 2, 0.5 + 0.05 * (x - 4.0))
    text = "depth_mm,force_n\n" + "".join(f"{a * depth_scale:.6f},{b * force_scale:.6f}\n" for a, b in zip(x, f))
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode())
    return path


# ---- a user's data is never destroyed -------------------------------------------------------------
def run_args(tmp_path, *extra):
    return ("run", "--device", "scripted", "--trajectory", DEFAULT, "--duration", "0.05", "--no-status",
            "--quiet", *extra)


def test_run_rrd_never_replaces_a_users_file(tmp_path):
    notes = tmp_path / "notes.rrd"
    notes.write_text("precious user notes")
    one_line(cli(*run_args(tmp_path, "--rrd", notes, "--out", tmp_path / "o")), 2, notes, "exists")
    assert notes.read_text() == "precious user notes"
    assert not (tmp_path / "o").exists()


def test_run_rrd_never_replaces_its_own_trajectory(tmp_path):
    g = tmp_path / "G.csv"
    shutil.copy(DEFAULT, g)
    before = g.read_bytes()
    args = ("run", "--device", "scripted", "--trajectory", g, "--duration", "0.05", "--no-status")
    for extra in ((), ("--overwrite",)):
        one_line(cli(*args, "--rrd", g, "--out", tmp_path / "o", *extra), 2, g, "input")
    assert g.read_bytes() == before


@pytest.mark.parametrize("name", ["samples.csv", "summary.json", "force_depth.png", "recording.rrd"])
def test_run_outputs_never_share_a_path(tmp_path, name):
    d = tmp_path / "d"
    one_line(cli(*run_args(tmp_path, "--out", d, "--record", d / name)), 2, "one path")
    one_line(cli(*run_args(tmp_path, "--out", d, "--rrd", d / name if name != "recording.rrd" else d / "samples.csv")),
             2, "one path")
    one_line(cli(*run_args(tmp_path, "--out", d, "--record", tmp_path / "r.csv", "--rrd", tmp_path / "r.csv")),
             2, "one path")
    assert not d.exists()


def test_run_out_is_held_alone(tmp_path):
    """Two sessions to one --out: the second is refused (both exited 0, one report lost)."""
    d = tmp_path / "d"
    lock = claim_folder(d)  # a session running there
    try:
        one_line(cli(*run_args(tmp_path, "--out", d)), 2, d, "another session")
    finally:
        lock.release()


def test_score_out_never_replaces_a_users_files(tmp_path):
    r = ratings(tmp_path / "ratings.csv")
    d = tmp_path / "mine"
    d.mkdir()
    (d / "weights.csv").write_text("my weights")
    (d / "score.json").write_text("my notes")
    one_line(cli("score", r, "--out", d), 2, d, "not empty")
    assert (d / "weights.csv").read_text() == "my weights" and (d / "score.json").read_text() == "my notes"
    assert sorted(os.listdir(d)) == ["score.json", "weights.csv"]


def test_fit_out_never_replaces_an_input(tmp_path):
    mesh = tmp_path / "m.obj"
    mesh.write_text("".join(f"v {np.cos(a):.4f} {np.sin(a):.4f} {z:.1f}\n"
                            for a in np.linspace(0, 6, 40) for z in (-1.0, 1.0)))
    before = mesh.read_bytes()
    one_line(cli("fit", mesh, "--lmax", "1", "--out", mesh), 2, mesh)
    assert mesh.read_bytes() == before
    mine = tmp_path / "mine.npz"
    mine.write_text("my coefficients")
    one_line(cli("fit", mesh, "--lmax", "1", "--out", mine), 2, mine, "--overwrite")
    assert mine.read_text() == "my coefficients"
    assert cli("fit", mesh, "--lmax", "1", "--out", mine, "--overwrite")[0] == 0
    assert mine.read_bytes()[:2] == b"PK"  # an .npz now


# ---- one line, exit 2, bounded ---------------------------------------------------------------------
@pytest.mark.parametrize("where", ["header", "body"])
def test_calibrate_field_over_128kB(tmp_path, where):
    c = tmp_path / "c.csv"
    c.write_text(f"depth_mm,force_n,{BIG}\n0,0,1\n" if where == "header" else f"depth_mm,force_n\n0,{BIG}\n")
    one_line(cli("calibrate", c, "--speed-mm-s", "3", "--out", tmp_path / "f.toml"), 2, c, "line")


@pytest.mark.parametrize("cmd", ["calibrate", "cohort", "score"])
def test_a_device_is_refused_before_a_byte_is_read(tmp_path, cmd):
    argv = {"calibrate": ("calibrate", "/dev/zero", "--speed-mm-s", "3", "--out", tmp_path / "f.toml"),
            "cohort": ("cohort", "/dev/zero", "--out", tmp_path / "o"),
            "score": ("score", "/dev/zero", "--out", tmp_path / "o")}[cmd]
    t0 = time.perf_counter()
    one_line(cli(*argv), 2, "/dev/zero", "device")
    assert time.perf_counter() - t0 < 5


def test_calibrate_speed_whose_ticks_pass_the_budget(tmp_path):
    c = curve(tmp_path / "c.csv")
    one_line(cli("calibrate", c, "--speed-mm-s", "1e-6", "--out", tmp_path / "f.toml"), 2, "--speed-mm-s",
             "ticks")
    assert not (tmp_path / "f.toml").exists()


@pytest.mark.parametrize("scale, what", [(1e-3, "metres"), (1e3, "micrometres")])
def test_calibrate_depth_units(tmp_path, scale, what):
    c = curve(tmp_path / "c.csv", depth_scale=scale)
    one_line(cli("calibrate", c, "--speed-mm-s", "3", "--out", tmp_path / "f.toml"), 2, c, what)


def test_calibrate_force_units(tmp_path):
    c = curve(tmp_path / "c.csv", force_scale=1000.0)  # millinewtons in a newton column
    one_line(cli("calibrate", c, "--speed-mm-s", "3", "--out", tmp_path / "f.toml"), 2, c, "mN")


def test_calibrate_reads_a_bom_like_the_other_readers(tmp_path):
    from haptic_acu.tissue.calibration import read_curve

    x, f = read_curve(curve(tmp_path / "c.csv", bom=True))
    assert len(x) == 200 and x[0] == 0.0


def manifest(path: Path, rows: list[str], header="session,trainee,file,level,date") -> Path:
    path.write_text(header + "\n" + "".join(r + "\n" for r in rows))
    return path


def test_cohort_manifest_field_over_128kB(tmp_path):
    m = manifest(tmp_path / "m.csv", [f"s1,{BIG},a.csv,,"])
    one_line(cli("cohort", m, "--out", tmp_path / "o"), 2, m, "line 2")


def test_cohort_unclosed_quote_does_not_swallow_rows(tmp_path):
    m = manifest(tmp_path / "m.csv", ['s1,"ann,a.csv,,', "s2,bob,b.csv,,", 's3,cy,c.csv,,'])
    one_line(cli("cohort", m, "--out", tmp_path / "o"), 2, m, "line 2", "quote")


def test_dates_with_and_without_zones_sort_one_way(tmp_path):
    from haptic_acu.cohort.report import REPORT_METRICS, write_report

    rows = [{"session": f"s{k}", "trainee": "a", "level": "novice", "date": d, "error": "", "insertions": 1,
             **{c: float(k) for c, _ in REPORT_METRICS}}
            for k, d in enumerate(["2026-01-01T23:00-05:00", "2026-01-01T12:00", "2026-01-03"])]
    rep = write_report(tmp_path, rows, {})
    # 23:00 at UTC-5 is 04:00 UTC on the 2nd: after noon (UTC) on the 1st, before the 3rd
    assert rep["learning_curves"]["a"]["sessions"] == ["s1", "s0", "s2"]


def test_names_with_tex_reach_figures_as_text(tmp_path):
    from haptic_acu.cohort.report import REPORT_METRICS, write_report

    rows = [{"session": f"s{k}", "trainee": t, "level": lv, "date": "", "error": "", "insertions": 1,
             **{c: float(k) for c, _ in REPORT_METRICS}}
            for k, (t, lv) in enumerate([(r"$\foo$", r"$x^$"), (r"$\foo$", r"$x^$"), ("b$", "$\\"), ("b$", "$\\")])]
    rep = write_report(tmp_path, rows, {})
    assert rep["figures"]
    r = ratings(tmp_path / "r.csv", systems=(r"$\foo$", "B"), raters=(r"$\bar$", "r2"))
    assert cli("score", r, "--out", tmp_path / "s")[0] == 0
    assert (tmp_path / "s" / "scores.png").stat().st_size > 0


def test_compare_labels_with_tex(tmp_path):
    one = tmp_path / "a.csv"
    one.write_text("t_s,x_mm,y_mm,z_mm\n0,0,0,3\n0.3,0,0,-2\n")
    code, err = cli("compare", one, one, "--labels", r"$\foo$", r"$\bar", "--out", tmp_path / "c")
    assert code == 0, err
    assert (tmp_path / "c" / "compare.png").stat().st_size > 0


def test_cohort_levels_pairwise_tests_bounded(tmp_path):
    from haptic_acu.cohort.report import MAX_LEVELS, REPORT_METRICS, write_report

    rows = [{"session": f"s{k}", "trainee": f"t{k % 3}", "level": f"L{k % 200}", "date": "", "error": "",
             "insertions": 1, **{c: float(k % 7) for c, _ in REPORT_METRICS}} for k in range(400)]
    rep = write_report(tmp_path, rows, {})
    comp = rep["level_comparison"]
    assert len(comp["levels"]) == 200 and comp.get("pairs_skipped")
    assert all(len(m.get("pairs", [])) <= MAX_LEVELS * (MAX_LEVELS - 1) // 2 for m in comp["metrics"].values())


def test_cohort_formula_cells_are_neutralised(tmp_path, monkeypatch):
    # one session replays (a bundled trajectory), the other fails (its file is missing): the tables
    # are written (a run where every session fails leaves no folder)
    cohort_sessions_here(monkeypatch)  # in this process: the cells are the point, not the pool
    m = manifest(tmp_path / "m.csv", ["@SUM(1),=cmd|' /C calc'!A0,default,+lvl,", "s2,-bob,nope2.csv,,"])
    code, err = cli("cohort", m, "--out", tmp_path / "o", "--quiet")
    assert code == 2 and "nope2.csv" in err  # a failed session is reported and makes the status 2
    text = (tmp_path / "o" / "sessions.csv").read_text()
    assert "'@SUM(1)" in text and "'=cmd|" in text and "'-bob" in text and "'+lvl" in text
    assert not re.search(r"(^|,)[=@+]", text, re.M)


def test_cohort_jobs_bounded_by_cores():
    from haptic_acu.cohort.update import bounded_jobs

    cores = len(os.sched_getaffinity(0))
    n, note = bounded_jobs(16 * cores)
    assert 1 <= n <= cores and note and str(16 * cores) in note
    assert bounded_jobs(1) == (1, None)


def test_set_with_a_huge_integer():
    one_line(cli("replay", "--set", "body.lmax=" + "9" * 5000, "missing.csv"), 2, "body.lmax")


def test_skin_coefficients_not_a_zip(tmp_path):
    bad = tmp_path / "c.npz"
    bad.write_text("not a zip")
    one_line(cli("replay", "--set", f"body.skin_coefficients={bad}", "--out", tmp_path / "o", DEFAULT),
             2, bad)


@pytest.mark.parametrize("d", ["inf", "nan", "-1", "1e300"])
def test_run_duration_not_a_finite_time(tmp_path, d):
    one_line(cli(*run_args(tmp_path)[:6], d, "--out", tmp_path / "o"), 2, "--duration")


# ---- costs refused up front -----------------------------------------------------------------------
def test_rings_times_tolerance_refused_naming_both(tmp_path):
    t0 = time.perf_counter()
    one_line(cli("replay", "--set", "skin.rings=40", "--set", "skin.spring_length_mm=1", "--set",
                 "solver.static_tolerance_um=1e-6", "--out",
                 tmp_path / "o", DEFAULT), 2, "skin.rings=40", "static_tolerance_um", "sweeps")
    assert time.perf_counter() - t0 < 10


def test_lmax_times_samples_refused_naming_both(tmp_path):
    one_line(cli("replay", "--set", "body.lmax=40", "--set", "body.fit_samples=200000", "--out",
                 tmp_path / "o", DEFAULT), 2, "body.lmax=40", "fit_samples", "GB")


# ---- plausibility ----------------------------------------------------------------------------------
def test_net_wider_than_the_body(tmp_path):
    one_line(cli("replay", "--set", "skin.rings=11", "--set", "skin.spring_length_mm=20", "--out", tmp_path / "o",
                 DEFAULT), 2, "skin.rings", "semi_axes")


def test_trajectory_starting_inside_the_tissue(tmp_path):
    t = tmp_path / "t.csv"
    t.write_text("t_s,x_mm,y_mm,z_mm\n0,0,0,-30\n0.2,0,0,-31\n")
    one_line(cli("replay", t, "--no-rrd", "--out", tmp_path / "o"), 2, t, "inside")


def test_trajectory_entering_against_its_axis(tmp_path):
    t = tmp_path / "t.csv"
    t.write_text("t_s,x_mm,y_mm,z_mm,axis_x,axis_y,axis_z\n0,0,0,3,0,0,1\n0.5,0,0,-3,0,0,1\n0.6,0,0,-3,0,0,1\n")
    one_line(cli("replay", t, "--no-rrd", "--out", tmp_path / "o"), 2, t, "line 3", "axis")


def test_needle_shorter_than_its_insertion_is_stated(tmp_path):
    t = tmp_path / "t.csv"
    t.write_text("t_s,x_mm,y_mm,z_mm\n0,0,0,2\n0.6,0,0,-4\n")
    code, err = cli("replay", t, "--no-rrd", "--set", "needle.length_mm=1", "--out", tmp_path / "o")
    assert code == 0, err
    assert "the whole 1 mm needle went in: the handle met the skin" in (tmp_path / "o" / "debrief.md").read_text()


@pytest.mark.slow
def test_session_files_of_an_older_configuration_do_not_stay(tmp_path, monkeypatch):
    """A cohort run with --session-files, then again with --set (every session replayed anew) but
    without them: the old configuration's files are gone, not left beside the new tables."""
    replayed = cohort_sessions_here(monkeypatch)  # in this process: the files are the point, not the pool
    m = manifest(tmp_path / "m.csv", [f"s1,ann,{REPO / 'trajectories' / 'default.csv'},,"])
    out = tmp_path / "o"
    assert cli("cohort", m, "--out", out, "--session-files", "--jobs", "1", "--quiet")[0] == 0
    (sdir,) = list((out / "sessions").iterdir())
    assert (sdir / "summary.json").is_file()
    assert cli("cohort", m, "--out", out, "--jobs", "1", "--quiet", "--set", "needle.length_mm=39")[0] == 0
    assert not sdir.exists()
    assert replayed == ["s1", "s1"]  # the second run replayed it anew

"""`haptic-acu replay` through the real CLI: outputs, determinism, batch, and every bad-input case.

Bad input must give one line on stderr naming the file (and line), exit status 2, no traceback, and
no output folder left behind (a partial one, or one that looks complete).
"""
from __future__ import annotations

import csv
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import cli

ROOT = Path(__file__).resolve().parent.parent
TRAJ = ROOT / "trajectories"


def replay(*args, timeout=600):
    """``haptic-acu replay`` as a user runs it: a child process (the console entry, exit status, streams)."""
    return subprocess.run([sys.executable, "-m", "haptic_acu", "replay", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT)


def replay_here(*args):
    """``haptic-acu replay`` in this process (tests/cli_helpers.py: ``haptic_acu.cli.main``, the same
    parser, checks, exit status and streams as the console entry, without a child's start-up); an
    exception that escapes it fails the test, as a traceback would."""
    return cli("replay", *args, cwd=ROOT)


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def insertion_csv(rows=200, dt=0.01, speed_mm_s=10.0) -> str:
    lines = ["t_s,x_mm,y_mm,z_mm"]
    for i in range(rows):
        lines.append(f"{i * dt:.6f},0,0,{5.0 - speed_mm_s * i * dt:.4f}")
    return "\n".join(lines) + "\n"


def assert_one_line_error(r, name: str, line: int | None = None):
    assert r.returncode == 2, r.stderr
    err = r.stderr.strip().splitlines()
    assert len(err) == 1, r.stderr
    assert "Traceback" not in r.stderr
    assert name in err[0]
    if line is not None:
        assert f"line {line}" in err[0], err[0]


BAD_CASES = {
    "empty": ("", None),
    "header_only": ("t_s,x_mm,y_mm,z_mm\n", 1),
    "missing_column": ("t_s,x_mm,y_mm\n0,0,0\n0.01,0,0\n", 1),
    "wrong_column": ("time,x_mm,y_mm,z_mm\n0,0,0,1\n0.01,0,0,1\n", 1),
    "non_numeric": ("t_s,x_mm,y_mm,z_mm\n0,0,0,5\n0.01,0,abc,5\n", 3),
    "nan": ("t_s,x_mm,y_mm,z_mm\n0,0,0,5\n0.01,0,0,nan\n", 3),
    "infinite": ("t_s,x_mm,y_mm,z_mm\n0,0,0,5\n0.01,inf,0,5\n", 3),
    "time_not_increasing": ("t_s,x_mm,y_mm,z_mm\n0,0,0,5\n0.01,0,0,4.9\n0.01,0,0,4.8\n", 4),
    "too_fast": ("t_s,x_mm,y_mm,z_mm\n0,0,0,5\n0.001,0,0,-5\n", 3),  # 10 mm in 1 ms: 10 m/s
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_trajectory_one_line_error_and_no_output(tmp_path, case):
    text, line = BAD_CASES[case]
    f = write(tmp_path / f"{case}.csv", text)
    out = tmp_path / "out"
    r = replay_here(f, "--out", out, "--no-rrd")
    assert_one_line_error(r, f.name, line)
    assert not out.exists()
    assert not (tmp_path / "out.partial").exists()


def test_missing_file(tmp_path):
    out = tmp_path / "out"
    r = replay_here(tmp_path / "nope.csv", "--out", out)
    assert_one_line_error(r, "nope.csv")
    assert not out.exists()


def test_binary_garbage(tmp_path):
    f = tmp_path / "garbage.csv"
    f.write_bytes(bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8)))
    out = tmp_path / "out"
    r = replay_here(f, "--out", out)
    assert_one_line_error(r, "garbage.csv")
    assert not out.exists()


def test_bad_config_names_the_key(tmp_path):
    text, n = re.subn(r"(?m)^rings = \d+", "rings = 1", (ROOT / "config" / "tissue.toml").read_text(), count=1)
    assert n == 1  # the first layer's (the skin's) ring count
    cfg = write(tmp_path / "bad.toml", text)
    r = replay_here("--config", cfg, "--out", tmp_path / "out", "--no-rrd")
    assert_one_line_error(r, "bad.toml")
    assert "skin.rings" in r.stderr


@pytest.mark.slow  # a million ticks replayed and written (~15-40 s)
def test_million_rows_stream(tmp_path):
    """A long recording (1,000,000 rows at 1 kHz: 1000 s of a tip hovering above the skin) is
    validated and replayed by streaming; the replay writes one sample row per tick."""
    f = tmp_path / "long.csv"
    n = 1_000_000
    t = np.arange(n) * 1e-3
    z = 5.0 + 0.5 * np.sin(2 * np.pi * 0.2 * t)
    with open(f, "w") as fh:  # np.savetxt's bytes (fmt "%.6f,%.1f,%.1f,%.4f") in a third of its time
        fh.write("t_s,x_mm,y_mm,z_mm\n")
        fh.write("".join([f"{a:.6f},0.0,0.0,{b:.4f}\n" for a, b in zip(t.tolist(), z.tolist())]))
    out = tmp_path / "out"
    r = replay_here(f, "--out", out, "--no-rrd", "--quiet")
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ticks"] == n - 1  # ticks at 1 ms up to, not including, the last sample's time
    assert summary["punctures"] == []


def test_default_replay_outputs_and_rrd(tmp_path):
    out = tmp_path / "run"
    r = replay_here("--out", out)
    assert r.returncode == 0, r.stderr
    for name in ("samples.csv", "summary.json", "force_depth.png", "recording.rrd"):
        assert (out / name).is_file(), name
    s = json.loads((out / "summary.json").read_text())
    assert [p["layer"] for p in s["punctures"]] == ["skin", "fat", "muscle"]
    # one samples.csv row per tick, times at exactly 1 ms
    with open(out / "samples.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == s["ticks"]
    t = np.array([float(x["t_s"]) for x in rows])
    assert np.allclose(np.diff(t), 1e-3, atol=1e-9)
    # the .rrd reads back with rerun's own reader and holds one force value per tick, equal to samples.csv's
    import pyarrow as pa
    from rerun.chunk import RrdReader
    store = RrdReader(out / "recording.rrd").store()
    ticks, values = [], []
    for chunk in store.stream().filter(content="/force/total").to_chunks():
        if chunk.entity_path != "/force/total" or chunk.is_static:
            continue
        rb = chunk.to_record_batch()
        if "Scalars:scalars" in rb.schema.names:
            ticks += rb.column("tick").cast(pa.int64()).to_pylist()
            values += rb.column("Scalars:scalars").to_pylist()
    order = np.argsort(ticks, kind="stable")
    assert list(np.array(ticks)[order]) == list(range(s["ticks"]))
    fz_rrd = np.array(values)[order][:, 0]  # the force along the needle: +fz for this vertical needle
    fz_csv = np.array([float(x["fz_n"]) for x in rows])
    assert np.allclose(fz_rrd, fz_csv, atol=6e-6)  # the csv keeps 5 decimals
    verify = subprocess.run([str(Path(sys.executable).parent / "rerun"), "rrd", "verify", str(out / "recording.rrd")],
                            capture_output=True, text=True, timeout=120)
    assert verify.returncode == 0, verify.stderr
    assert "punctured" in r.stdout and "files:" in r.stdout


def test_replay_is_byte_identical(tmp_path):
    # one replay in this process, the other in a child of its own: equal across processes
    a, b = tmp_path / "a", tmp_path / "b"
    for run, out in ((replay_here, a), (replay, b)):
        r = run(TRAJ / "fast_insertion.csv", "--out", out, "--no-rrd", "--quiet")
        assert r.returncode == 0, r.stderr
    for name in ("samples.csv", "summary.json", "force_depth.png"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


def test_existing_output_folder_is_refused(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    r = replay_here(TRAJ / "fast_insertion.csv", "--out", out, "--no-rrd")
    assert_one_line_error(r, "out")
    assert (out / "keep.txt").read_text() == "mine"


def test_batch_folder_in_parallel(tmp_path):
    src = tmp_path / "trajs"
    src.mkdir()
    for name in ("fast_insertion.csv", "lateral_sweep.csv"):
        (src / name).write_bytes((TRAJ / name).read_bytes())
    out = tmp_path / "batch"
    r = replay_here(src, "--out", out, "--no-rrd", "--jobs", "2")
    assert r.returncode == 0, r.stderr
    with open(out / "summaries.csv", newline="") as f:
        rows = {row["trajectory"]: row for row in csv.DictReader(f)}
    assert set(rows) == {"fast_insertion.csv", "lateral_sweep.csv"}
    assert int(rows["lateral_sweep.csv"]["punctures"]) == 0  # the sweep never breaks the skin
    assert int(rows["fast_insertion.csv"]["punctures"]) == 3
    for stem in ("fast_insertion", "lateral_sweep"):
        assert (out / stem / "summary.json").is_file()


def test_batch_with_one_bad_file_reports_it_and_fails(tmp_path):
    src = tmp_path / "trajs"
    src.mkdir()
    (src / "good.csv").write_text(insertion_csv())
    (src / "bad.csv").write_text("t_s,x_mm,y_mm,z_mm\n0,0,0,5\n0.01,0,0,nan\n")
    out = tmp_path / "batch"
    r = replay_here(src, "--out", out, "--no-rrd", "--jobs", "1")
    assert r.returncode == 2
    assert "bad.csv" in r.stderr and "line 3" in r.stderr and "Traceback" not in r.stderr
    assert (out / "good" / "summary.json").is_file()
    assert not (out / "bad").exists()


def test_batch_tables_carry_every_insertions_metrics_and_every_puncture(tmp_path):
    """A batch's insertions.csv has one row per insertion with the trainee metrics of each
    replay's summary.json, punctures.csv every puncture (not only the first per layer), and
    summaries.csv the session-level metrics; all with the header on line 1."""
    src = tmp_path / "trajs"
    src.mkdir()
    for name in ("fast_insertion.csv", "second_insertion_same_site.csv"):
        (src / name).write_bytes((TRAJ / name).read_bytes())
    out = tmp_path / "batch"
    r = replay_here(src, "--out", out, "--no-rrd", "--jobs", "1")
    assert r.returncode == 0, r.stderr
    read = lambda name: list(csv.DictReader(open(out / name, newline="")))  # noqa: E731
    summaries = {row["trajectory"]: row for row in read("summaries.csv")}
    insertions, punctures = read("insertions.csv"), read("punctures.csv")
    for stem in ("fast_insertion", "second_insertion_same_site"):
        s = json.loads((out / stem / "summary.json").read_text())
        name = f"{stem}.csv"
        m = s["metrics"]
        assert int(summaries[name]["insertions"]) == m["insertions"]
        assert float(summaries[name]["time_in_tissue_s"]) == m["time_in_tissue_s"]
        mine = [row for row in insertions if row["trajectory"] == name]
        assert [int(row["insertion"]) for row in mine] == list(range(1, m["insertions"] + 1))
        for row, ins in zip(mine, m["per_insertion"]):
            assert float(row["max_depth_mm"]) == ins["max_depth_mm"]
            assert float(row["entry_mm_x"]) == ins["entry_mm"][0]
            assert float(row["peak_force_fat_n"]) == ins["peak_layer_force_n"]["fat"]  # one name per quantity
            assert "peak_layer_force_n_fat" not in row
            assert int(row["lift_thrust_cycles"]) == ins["lift_thrust"]["cycles"]
            assert row["depth_verdict"] == ins["depth_verdict"]
            assert int(row["punctures"]) == len(ins["punctures"])
        got = [(row["layer"], float(row["t_s"]), float(row["peak_force_n"]), row["insertion"])
               for row in punctures if row["trajectory"] == name]
        want = [(p["layer"], p["t_s"], p["peak_force_n"],
                 str(next(k for k, i in enumerate(m["per_insertion"], 1) if p in i["punctures"])))
                for p in s["punctures"]]
        assert got == want
    assert json.loads((out / "second_insertion_same_site" / "summary.json").read_text())["metrics"]["insertions"] == 2

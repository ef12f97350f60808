"""Replay outputs are exclusive and atomic, through the real CLI.

A second replay to the same ``--out`` is refused while the first runs; a ``DIR.partial`` holding a
user's files is never deleted; a stale one left by a killed replay is replaced; an interrupted
replay exits 130/143 and leaves its files in ``DIR.partial`` (never published as complete), one
stopped before its session starts leaves nothing (nor does `run`); bad
``--out`` places and ``--jobs`` values are one line, exit 2. A replay that is signalled or holds a
folder while another tries it runs as a child; every other command runs in this process.
"""
from __future__ import annotations

import math
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import cli_helpers

ROOT = Path(__file__).resolve().parent.parent


def cli(*args, timeout=600):
    """The command in this process (tests/cli_helpers.py); a replay to be signalled is a child (start)."""
    return cli_helpers.cli(*args, timeout=timeout, cwd=ROOT)


# progress lines ("haptic-acu: step...", "haptic-acu: step: done in 1.2 s") may precede the one error line
PROGRESS = re.compile(r"^haptic-acu: ")


def one_line(r, status=2, *names):
    assert r.returncode == status, (r.returncode, r.stderr)
    lines = [ln for ln in r.stderr.strip().splitlines() if not PROGRESS.match(ln)]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    for n in names:
        assert str(n) in lines[0], lines[0]
    return lines[0]


def short_csv(path: Path) -> Path:
    path.write_text("t_s,x_mm,y_mm,z_mm\n0,0,0,5\n0.5,0,0,2\n")
    return path


def long_csv(path: Path, seconds=3000) -> Path:
    """A slow dip into the skin and back, repeated: long enough to interrupt a headless replay."""
    with open(path, "w") as f:
        f.write("t_s,x_mm,y_mm,z_mm\n")
        for i in range(int(seconds * 10) + 1):
            t = i * 0.1
            f.write(f"{t:.6f},0,0,{5 - 6 * (1 - math.cos(0.5 * t)):.4f}\n")
    return path


def start(*args):
    return subprocess.Popen([sys.executable, "-m", "haptic_acu", *map(str, args)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def wait_for(pred, timeout=300.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.05)
    return False


def samples_rows(path: Path) -> int:
    try:
        with open(path, "rb") as f:
            return f.read().count(b"\n")
    except FileNotFoundError:
        return 0


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_second_replay_refused_and_interrupt_not_published(tmp_path, sig):
    traj = long_csv(tmp_path / "long.csv")
    out = tmp_path / "out"
    partial = tmp_path / "out.partial"
    a = start("replay", "--no-rrd", "--out", out, traj)
    try:
        # the first replay is running once it has written rows
        assert wait_for(lambda: samples_rows(partial / "samples.csv") > 1000 or a.poll() is not None)
        assert a.poll() is None, a.communicate()
        b = cli("replay", "--no-rrd", "--out", out, short_csv(tmp_path / "short.csv"))
        one_line(b, 2, "out.partial", "another replay")
        a.send_signal(sig)
        _, err = a.communicate(timeout=120)
    finally:
        if a.poll() is None:
            os.killpg(a.pid, signal.SIGKILL)
            a.wait()
    assert a.returncode == 128 + sig, err
    # one line says why (a pipe also gets a progress line every 25 % of a replay that is quick enough)
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith("haptic-acu: replaying ")]
    assert len(lines) == 1 and "interrupted" in lines[0] and signal.Signals(sig).name in lines[0], err
    assert not out.exists()  # never published as if complete
    assert (partial / "samples.csv").is_file()
    assert not (partial / "summary.json").exists()
    # the samples written so far are whole rows of the one run (no second writer mixed in)
    text = (partial / "samples.csv").read_text()
    rows = text.splitlines()
    assert rows[0].startswith("tick,")
    ticks = [int(r.split(",", 1)[0]) for r in rows[1:] if r.count(",") == rows[0].count(",")]
    assert ticks == list(range(len(ticks)))


def test_user_files_in_partial_are_never_deleted(tmp_path):
    out = tmp_path / "out"
    partial = tmp_path / "out.partial"
    partial.mkdir()
    (partial / "notes.txt").write_text("mine")
    r = cli("replay", "--no-rrd", "--out", out, short_csv(tmp_path / "s.csv"))
    one_line(r, 2, "out.partial", "did not write")
    assert (partial / "notes.txt").read_text() == "mine"
    assert not out.exists()
    # even a file named like a replay output, without the replay's marker, is the user's
    (partial / "notes.txt").unlink()
    (partial / "samples.csv").write_text("mine too")
    r = cli("replay", "--no-rrd", "--out", out, short_csv(tmp_path / "s.csv"))
    one_line(r, 2, "out.partial")
    assert (partial / "samples.csv").read_text() == "mine too"


def test_stale_partial_of_a_killed_replay_is_replaced(tmp_path):
    out = tmp_path / "out"
    partial = tmp_path / "out.partial"
    partial.mkdir()
    (partial / ".haptic-acu-replay").write_text("pid 1\n")
    (partial / "samples.csv").write_text("tick,t_s\n0,0.0\n")  # what a SIGKILLed replay leaves
    r = cli("replay", "--no-rrd", "--out", out, short_csv(tmp_path / "s.csv"))
    assert r.returncode == 0, r.stderr
    assert not partial.exists()
    assert sorted(p.name for p in out.iterdir()) == ["debrief.md", "force_depth.png", "samples.csv", "summary.json"]


def test_out_is_an_existing_file(tmp_path):
    f = tmp_path / "taken"
    f.write_text("user data")
    r = cli("replay", "--no-rrd", "--out", f, short_csv(tmp_path / "s.csv"))
    one_line(r, 2, "taken", "not a folder")
    assert f.read_text() == "user data"


@pytest.mark.parametrize("where", ["/proc/haptic-acu-out", "/sys/haptic-acu-out"])
def test_out_where_nothing_can_be_written(tmp_path, where):
    r = cli("replay", "--no-rrd", "--out", where, short_csv(tmp_path / "s.csv"))
    one_line(r, 2, where)


def test_out_inside_a_file(tmp_path):
    f = tmp_path / "afile"
    f.write_text("x")
    r = cli("replay", "--no-rrd", "--out", f / "sub", short_csv(tmp_path / "s.csv"))
    one_line(r, 2, "afile")


def test_jobs_negative(tmp_path):
    r = cli("replay", "--jobs", "-1", short_csv(tmp_path / "a.csv"), short_csv(tmp_path / "b.csv"),
            "--out", tmp_path / "batch")
    one_line(r, 2, "--jobs")


def test_absurd_duration_refused_at_once(tmp_path):
    f = tmp_path / "span.csv"
    f.write_text("t_s,x_mm,y_mm,z_mm\n0,0,0,5\n1000000,0,0,5\n")
    r = cli("replay", "--no-rrd", "--out", tmp_path / "out", f, timeout=120)
    one_line(r, 2, "span.csv", "split")
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.partial").exists()


# ------------------------------------------------------- I/O errors in score, fit and compare
RATINGS = ROOT / "config" / "scoring" / "example_ratings.csv"
MESH = ROOT / "config" / "meshes" / "forearm.obj"
TRAJ = ROOT / "trajectories"


@pytest.mark.parametrize("argv,name", [
    (["score", RATINGS, "--out", "/proc/haptic-acu-x"], "/proc/haptic-acu-x"),
    (["score", RATINGS, "--out", "/sys/haptic-acu-x"], "/sys/haptic-acu-x"),
    (["fit", MESH, "--out", "/proc/haptic-acu-x.npz"], "/proc/haptic-acu-x.npz"),
    (["compare", TRAJ / "slow_insertion.csv", TRAJ / "fast_insertion.csv", "--out", "/proc/haptic-acu-x"],
     "/proc/haptic-acu-x"),
    (["compare", TRAJ / "slow_insertion.csv", TRAJ / "fast_insertion.csv", "--out", "/dev/full"],
     "/dev/full"),
])
def test_unwritable_outputs_one_line(argv, name):
    one_line(cli(*argv), 2, name)


def test_compare_never_deletes_a_users_partial(tmp_path):
    out = tmp_path / "cmp"
    partial = tmp_path / "cmp.partial"
    partial.mkdir()
    (partial / "mine.txt").write_text("mine")
    r = cli("compare", TRAJ / "slow_insertion.csv", TRAJ / "fast_insertion.csv", "--out", out)
    one_line(r, 2, "cmp.partial")
    assert (partial / "mine.txt").read_text() == "mine"


def test_compare_refuses_an_absurd_duration(tmp_path):
    f = tmp_path / "span.csv"
    f.write_text("t_s,x_mm,y_mm,z_mm\n0,0,0,5\n1000000,0,0,5\n")
    r = cli("compare", f, TRAJ / "default.csv", "--out", tmp_path / "c", timeout=120)
    one_line(r, 2, "span.csv", "split")


@pytest.mark.parametrize("argv", [
    ["replay", "--no-rrd", "--quiet", ROOT / "trajectories" / "default.csv", "--out"],
    ["score", RATINGS, "--out"],
    ["compare", TRAJ / "slow_insertion.csv", TRAJ / "fast_insertion.csv", "--out"],
])
def test_full_disk_one_line(tmp_path, argv):
    out = tmp_path / "out"
    with cli_helpers.file_size_limit(20_000):  # writes past 20 kB fail (EFBIG), as on a full disk
        r = cli(*argv, out)
    one_line(r, 2, "out")
    assert not out.exists() or not any(out.iterdir()) or argv[0] == "score"


def test_second_batch_to_the_same_folder_refused(tmp_path):
    src = tmp_path / "trajs"
    src.mkdir()
    long_csv(src / "a_long.csv")
    short_csv(src / "b_short.csv")
    out = tmp_path / "batch"
    a = start("replay", "--no-rrd", "--jobs", "1", "--out", out, src)
    try:
        assert wait_for(lambda: samples_rows(out / "a_long.partial" / "samples.csv") > 100
                        or a.poll() is not None)
        assert a.poll() is None
        b = cli("replay", "--no-rrd", "--out", out, src)
        one_line(b, 2, "batch", "another batch")
    finally:
        os.killpg(a.pid, signal.SIGINT)
        a.communicate(timeout=120)


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
@pytest.mark.parametrize("command", ["run", "replay"])
def test_interrupt_while_the_simulator_is_prepared_leaves_no_output(tmp_path, monkeypatch, command, sig):
    """Ctrl-C or SIGTERM during the warm-up (before the session's own signal handling): one line, exit
    130 or 143, and neither the output folder nor a DIR.partial is left."""
    from cli_helpers import interrupt_now
    from haptic_acu.session.engine import Session

    monkeypatch.setattr(Session, "warm_up", lambda self: interrupt_now(sig))
    traj, out = short_csv(tmp_path / "s.csv"), tmp_path / "out"
    if command == "run":
        r = cli("run", "--device", "scripted", "--trajectory", traj, "--speed", "4", "--no-status", "--out", out)
    else:
        r = cli("replay", "--no-rrd", "--out", out, traj)
    line = one_line(r, 128 + signal.Signals[sig], command)
    assert ("interrupted" if sig == "SIGINT" else "terminated (SIGTERM)") in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.csv"]

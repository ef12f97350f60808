"""`haptic-acu run --device scripted` as a user runs it: stopping it with SIGINT and SIGTERM (a
subprocess, at real pace), and replaying its recording headless to the same forces.

That the engine commands zero force on a signal is checked in process (tests/test_engine.py:
the scripted device has no motor to observe from outside); here: the exit status, no traceback, a
recording that is complete (one row per tick the session counted) and parses as a trajectory.

The sessions checked for what they compute and write run in process (``haptic_acu.cli.main``: the
same command, without a child's seconds of imports) and paced with ``--speed``: the compiled loop's
ticks, session times and forces are those of the real-paced session bit for bit
(tests/test_rtloop.py::test_realtime_forces_equal_the_headless_replay), and a paced session never
skips a tick.

Subprocesses run with OPENBLAS_NUM_THREADS=1: the tissue's least-squares fit is several times
faster single-threaded on a loaded 2-core machine, and nothing checked here depends on it.
"""
from __future__ import annotations

import csv
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from haptic_acu.cli import main
from haptic_acu.session import trajectory
from haptic_acu.session.recorder import EXTRA, tick_rows

REPO = Path(__file__).resolve().parents[1]
DEFAULT_TRAJ = REPO / "trajectories" / "default.csv"
LAYERS = ("skin", "fat", "muscle")
TIMEOUT_S = 180
pytestmark = pytest.mark.slow  # a session of a few seconds in each test (children or in process)


def env():
    e = dict(os.environ)
    e["OPENBLAS_NUM_THREADS"] = "1"
    return e


def haptic_acu(*args):
    """The command line; ``run`` with --verbose, whose closing timing line these tests read."""
    args = [*map(str, args)]
    if args[:1] == ["run"]:
        args.insert(1, "--verbose")
    return [sys.executable, "-m", "haptic_acu", *args]


def cli(capsys, *args) -> tuple[int, str, str]:
    """The command in process (``run`` with --verbose, as :func:`haptic_acu`): (exit status, stdout,
    stderr)."""
    capsys.readouterr()
    rc = main(haptic_acu(*args)[3:])
    out, err = capsys.readouterr()
    return rc, out, err


def session_ticks(stderr: str) -> int:
    m = re.search(r"session: (\d+) ticks", stderr)
    assert m, stderr
    return int(m.group(1))


def data_rows(path: Path) -> int:
    if not path.exists():
        return 0
    return sum(1 for line in path.read_bytes().splitlines() if line[:1].isdigit())


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_stops_the_session_cleanly(tmp_path, sig):
    rec = tmp_path / "rec.csv"
    proc = subprocess.Popen(haptic_acu("run", "--device", "scripted", "--trajectory", DEFAULT_TRAJ, "--record", rec,
                                       "--out", tmp_path / "session"),
                            cwd=REPO, env=env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # ~1 s into the session (rows reach the file once per visual frame), then the signal.
        deadline = time.monotonic() + TIMEOUT_S
        while data_rows(rec) < 1000 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        if proc.poll() is not None:
            pytest.fail(f"the session ended before the signal: {proc.communicate()[1]}")
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err  # a requested stop is a clean end, not an error
    assert "Traceback" not in err and "stopped:" not in err
    tr = tick_rows(trajectory.load(rec, extra_columns=EXTRA))  # parses: increasing time, finite values
    n = session_ticks(err)
    assert len(tr.t_s) == n >= 1000
    assert tr.t_s[-1] < 16.0  # stopped by the signal, not at the trajectory's end


def read_samples(path: Path) -> dict:
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    out = {k: np.array([float(r[k]) for r in rows]) for k in ("t_s", "fx_n", "fy_n", "fz_n")}
    for name in LAYERS:
        out[f"state_{name}"] = np.array([{"untouched": 0, "pressing": 1, "punctured": 2}[r[f"state_{name}"]]
                                         for r in rows])
    return out


def punctures(t, states):
    """(layer, time of the first sample with the layer punctured), in order."""
    seq = []
    for k, name in enumerate(LAYERS):
        hit = np.flatnonzero(states[:, k] == 2)
        if hit.size:
            seq.append((hit[0], name, t[hit[0]]))
    return [(name, tp) for _, name, tp in sorted(seq)]


def test_a_recorded_session_replays_to_the_same_forces(tmp_path, capsys):
    """Record 3 s of default.csv live (skin, fat and muscle punctures; paced at 3 times real time),
    replay the recording headless, compare.

    The live servo sampled the trajectory at jittered times t_i (the recording's times); the
    replay samples the recording's positions, linearly interpolated, at exact 1 ms ticks. The
    replay's force is interpolated to the recorded times and compared there. What may differ,
    and by how much:

    * position: the recording's 0.1 um rounding and the interpolation between recorded samples
      (the trajectory is piecewise linear at 200 Hz, so only its corners are cut): < 1 um, i.e.
      < 1 mN at the stiffest (~0.7 N/mm while the skin is pressed);
    * velocity (damping): both are backward differences over 1 ms of nearly the same path;
      mm/s-level differences at ramp corners times <= 3 N s/m per mm over ~20 mm: < 10 mN;
    * a stall on a loaded machine: the live loop skips the ticks it missed (over 10 ms late), so
      the recording has a gap the replay interpolates across, cutting the path's corner there;
      and with `solver.servo_net = "sweeps"` the net lags its equilibrium by a few percent of the
      force for a few ticks after a larger step (the default tabulated net has no such memory);
    * interpolating the replay's 1 ms force to t_i: the force's curvature over 1 ms (< 1 mN away
      from a puncture).

    Hence: |dF| <= 20 mN + 5 % of |F|, outside the ticks around each puncture (a force that drops
    by ~1 N within a tick cannot be compared across a timing shift). The puncture sequence must be
    identical, each puncture within the live session's sampling gap there plus 2 ms.
    """
    rec = tmp_path / "rec.csv"
    rc, _, err = cli(capsys, "run", "--device", "scripted", "--trajectory", DEFAULT_TRAJ, "--duration", 3.0,
                     "--record", rec, "--no-status", "--out", tmp_path / "session", "--speed", 3)
    assert rc == 0, err
    tr = tick_rows(trajectory.load(rec, extra_columns=EXTRA))
    assert len(tr.t_s) == session_ticks(err)

    out = tmp_path / "replay"
    rc, _, err = cli(capsys, "replay", rec, "--no-rrd", "--out", out, "--quiet")
    assert rc == 0, err
    s = read_samples(out / "samples.csv")
    np.testing.assert_allclose(np.diff(s["t_s"]), 1e-3, atol=1.5e-6)  # exact 1 ms ticks (file: 1 us)
    assert tr.t_s[-1] - 1e-3 - 1e-9 <= s["t_s"][-1] <= tr.t_s[-1]  # up to the recording's last sample

    # the puncture sequence
    live_states = np.stack([tr.extra[f"state_{n}"] for n in LAYERS], axis=1)
    rep_states = np.stack([s[f"state_{n}"] for n in LAYERS], axis=1)
    p_live, p_rep = punctures(tr.t_s, live_states), punctures(s["t_s"], rep_states)
    assert [n for n, _ in p_live] == [n for n, _ in p_rep] == list(LAYERS)
    windows = []
    for (_, tl), (_, tp) in zip(p_live, p_rep):
        i = int(np.searchsorted(tr.t_s, tl))
        gap = tl - tr.t_s[max(i - 1, 0)]  # the live session's sampling gap before the puncture
        assert abs(tl - tp) <= gap + 2e-3, (tl, tp, gap)
        windows.append((min(tl, tp) - gap - 3e-3, max(tl, tp) + 3e-3))

    # the forces at the recorded times, away from the punctures
    t = tr.t_s
    keep = (t >= s["t_s"][0]) & (t <= s["t_s"][-1])
    for lo, hi in windows:
        keep &= ~((t >= lo) & (t <= hi))
    assert keep.sum() > 0.95 * len(t)
    for axis in ("fx_n", "fy_n", "fz_n"):
        f_live = tr.extra[axis][keep]
        f_rep = np.interp(t[keep], s["t_s"], s[axis])
        err = np.abs(f_rep - f_live)
        tol = 0.02 + 0.05 * np.abs(f_live)
        assert np.all(err <= tol), (axis, float(err.max()), float(t[keep][np.argmax(err - tol)]))
    # the comparison covered real forces (the fine-needle defaults: skin ~0.5 N, muscle ~0.7 N peaks)
    assert tr.extra["fz_n"].max() > 0.4

    # the recording carries what a modelled OMNI would have rendered (haptic_acu.servo.devicemodel): the
    # simulated force through the coupling, within its 3.3 N, near the simulated one (within 0.15 N)
    # away from the punctures, and zero before the needle touches the skin
    fr = np.stack([tr.extra[c] for c in ("fr_x_n", "fr_y_n", "fr_z_n")], axis=1)
    fs = np.stack([tr.extra[c] for c in ("fx_n", "fy_n", "fz_n")], axis=1)
    assert np.linalg.norm(fr, axis=1).max() <= 3.3 and fr[:, 2].max() > 0.3
    assert np.median(np.linalg.norm(fr - fs, axis=1)[keep]) < 0.05
    first = int(np.argmax(np.linalg.norm(fs, axis=1) > 0))
    assert first > 0 and np.abs(fr[:max(first - 50, 1)]).max() < 1e-6


def test_a_live_session_ends_with_results_and_a_report_folder(tmp_path, capsys, monkeypatch):
    """`run` ends like `replay`: the punctures and the depth against the target on stdout, and
    recording.csv, samples.csv, summary.json and force_depth.png in --out; every number printed is
    the summary's, and the summary's punctures are the metrics' (one computation). (3 s of path
    paced at 3 times real time.)"""
    out = tmp_path / "session"
    monkeypatch.chdir(tmp_path)
    rc, stdout, err = cli(capsys, "run", "--device", "scripted", "--trajectory", DEFAULT_TRAJ, "--duration", 3.0,
                          "--no-status", "--out", out, "--set", "scene.target_depth_mm=[5,20]", "--speed", 3)
    assert rc == 0, err
    assert sorted(p.name for p in out.iterdir()) == ["debrief.md", "force_depth.png", "recording.csv", "samples.csv", "summary.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["session"]  # nothing under runs/ with --out
    s = json.loads((out / "summary.json").read_text())
    assert [p["layer"] for p in s["punctures"]] == list(LAYERS)
    m = s["metrics"]
    assert m["target_depth_mm"] == [5.0, 20.0]  # the --set override reached the session
    (ins,) = m["per_insertion"]
    assert ins["punctures"] == s["punctures"]
    assert ins["max_tip_depth_mm"] == s["max_tip_depth_mm"]
    assert ins["depth_verdict"] == ("too deep" if ins["max_depth_mm"] > 20 else "in range")
    text = stdout
    for p in s["punctures"]:
        assert f"{p['layer']:<6} punctured at t={p['t_s']:.3f} s, tip {p['tip_depth_mm']:.2f} mm below the rest skin, " \
               f"peak |F| {p['peak_force_n']:.3f} N" in text
    assert f"needle {ins['max_depth_mm']:.2f} mm into the tissue" in text and ins["depth_verdict"] in text
    assert "target depth 5-20 mm" in text
    assert f"files: {out}/" in text
    # samples.csv: one row per tick the session counted; the recording replays (header on line 1)
    with open(out / "samples.csv", newline="") as f:
        assert sum(1 for _ in csv.DictReader(f)) == session_ticks(err) == s["ticks"]
    assert (out / "force_depth.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_scripted_session_with_a_reset_runs_compiled_and_records_the_reset(tmp_path, capsys):
    """A trajectory with an ``event`` column runs in the compiled loop (no Python fallback): fresh
    tissue at the reset (the skin breaks twice though the second pass goes down the same hole) and
    the recording carries the reset, so it replays the same way. (2.5 s of path paced at 3 times
    real time.)"""
    traj = tmp_path / "twice.csv"
    traj.write_text("t_s,x_mm,y_mm,z_mm,event\n0,0,0,3,\n0.6,0,0,-3,\n1.2,0,0,3,\n1.3,0,0,3,reset\n"
                    "1.9,0,0,-3,\n2.5,0,0,3,\n")
    out = tmp_path / "live"
    rc, _, err = cli(capsys, "run", "--device", "scripted", "--trajectory", traj, "--no-status", "--out", out,
                     "--speed", 3)
    assert rc == 0, err
    assert "compiled servo loop" in err
    s = json.loads((out / "summary.json").read_text())
    skin = [p for p in s["punctures"] if p["layer"] == "skin"]
    assert len(skin) == 2 and skin[0]["t_s"] < 1.3 < skin[1]["t_s"]
    with open(out / "recording.csv", newline="") as f:
        events = [row for row in csv.DictReader(f) if row.get("event")]
    assert [e["event"] for e in events] == ["reset"] and float(events[0]["t_s"]) == pytest.approx(1.3, abs=1.5e-3)
    rc, _, err = cli(capsys, "replay", out / "recording.csv", "--no-rrd", "--quiet", "--out", tmp_path / "re")
    assert rc == 0, err
    re_skin = [p for p in json.loads((tmp_path / "re" / "summary.json").read_text())["punctures"] if p["layer"] == "skin"]
    assert len(re_skin) == 2

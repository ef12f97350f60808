"""A live session's report equals a replay of its own recording: for every bundled trajectory,
``run --device scripted --speed 32`` (the live path: the compiled loop on its own thread, the feeder,
the visual thread's sinks and recorder, with deadlines 32 times as often as real time) then ``replay``
of the recording it wrote give the same ticks, punctures, peaks and per-insertion metrics, to the
resolution the outputs print. A session's numbers are its ticks' own at any pace (session time is
k x 1 ms); the real-pace loop against the replay, tick by tick, is tests/test_rtloop.py's. A paced
session never skips a late tick, so a busy neighbour delays these sessions without changing them:
they run in the parallel phase.

The force-depth figure both write is not drawn here (tests/test_report.py, test_replay_cli.py and
test_run_cli.py draw and check it): a stand-in takes its rows and insertion index, and the live
session's and the replay's are held to the same ticks and the same insertions."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from haptic_acu.base.bundled import bundled_trajectories
from haptic_acu.cli import main
from haptic_acu.servo.samples import NCOL

SPEED = "32"  # times real time: the ring holds 4 s of wall time, more than any bundled session at this pace

TIMING = {"loop", "trajectory", "_wall_s", "_stats"}  # the clock's own statistics differ by nature


@pytest.fixture
def figures(monkeypatch):
    """Each force-depth figure's (rows, insertion index), in the order drawn, instead of the PNG."""
    from haptic_acu.session import report

    drawn = []

    def take(rows, path, tissue=None, title=None, dpi=110, summary=None, index=None):
        rows = np.asarray(rows)
        assert rows.ndim == 2 and rows.shape[1] == NCOL and summary is not None
        drawn.append((rows.shape[0], None if index is None else np.array(index, copy=True)))

    monkeypatch.setattr(report, "plot_force_depth", take)
    return drawn


def _same_figure_rows(figures, ticks):
    (n_live, i_live), (n_again, i_again) = figures
    assert n_live == n_again == ticks
    assert i_live is not None and np.array_equal(i_live, i_again)


def _close(a, b, path=""):
    """Equal, numbers within one unit of their last printed digit (a float64 sum in another order can
    land on the other side of a rounding half)."""
    if isinstance(a, dict):
        assert set(a) == set(b), (path, set(a) ^ set(b))
        for k in a:
            _close(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _close(x, y, f"{path}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        digits = max(len(repr(a).split(".")[-1]), len(repr(b).split(".")[-1])) if "e" not in repr(a) + repr(b) else 6
        assert abs(a - b) <= 1.01 * 10.0 ** -min(digits, 6), (path, a, b)
    else:
        assert a == b, (path, a, b)


@pytest.mark.slow  # each bundled trajectory played live (a minute or two in all)
@pytest.mark.parametrize("name", sorted(bundled_trajectories()))
def test_run_then_replay_of_its_recording(tmp_path, name, capsys, figures):
    live, again = tmp_path / "live", tmp_path / "replay"
    assert main(["run", "--device", "scripted", "--trajectory", name, "--speed", SPEED, "--out", str(live),
                 "--no-status"]) == 0
    assert main(["replay", str(live / "recording.csv"), "--out", str(again), "--no-rrd"]) == 0
    a = json.loads((live / "summary.json").read_text())
    b = json.loads((again / "summary.json").read_text())
    # (a host too loaded for the visual loop drops rows from the live report; none may be missing)
    assert a["loop"]["dropped_rows"] == 0, "the live session dropped rows: the host was overloaded"
    assert a["ticks"] == b["ticks"] and a["duration_s"] == b["duration_s"]
    assert [p["layer"] for p in a["punctures"]] == [p["layer"] for p in b["punctures"]]
    assert [p["t_s"] for p in a["punctures"]] == [p["t_s"] for p in b["punctures"]]
    for k in set(a) - TIMING - {"debrief"}:
        _close(a[k], b[k], k)
    assert a["debrief"]["insertions"] == b["debrief"]["insertions"]
    _same_figure_rows(figures, a["ticks"])


@pytest.mark.parametrize("args, says", [
    (["--device", "scripted", "--trajectory", "default", "--speed", "0"], "--speed must be a number > 0"),
    (["--device", "scripted", "--trajectory", "default", "--speed", "nan"], "--speed must be a number > 0"),
    (["--device", "scripted", "--trajectory", "default", "--speed", "101"], "at most 100"),
    (["--device", "keyboard", "--speed", "2"], "--speed is for --device scripted, not keyboard"),
])
def test_a_bad_speed_is_one_line_and_status_2(tmp_path, capsys, args, says):
    out = tmp_path / "out"
    assert main(["run", *args, "--out", str(out), "--no-status"]) == 2
    err = capsys.readouterr().err
    assert says in err and err.count("\n") == 1 and "Traceback" not in err, err
    assert not out.exists()  # nothing left behind


def test_a_session_at_the_handle_replays_the_same(tmp_path, figures):
    """A hand pushing 10 mm past a 20 mm needle: the recording keeps the device's path (which goes
    past the needle's length) and the needle's depth (which does not); its replay meets the same
    stop: the same ticks, depths, time at the force limit and debrief."""
    import csv

    traj = tmp_path / "past_the_handle.csv"
    traj.write_text("t_s,x_mm,y_mm,z_mm\n0,0,0,2\n3.2,0,0,-30\n3.7,0,0,-30\n6.9,0,0,2\n")
    live, again = tmp_path / "live", tmp_path / "replay"
    short = ["--set", "needle.length_mm=20"]
    assert main(["run", "--device", "scripted", "--trajectory", str(traj), "--speed", SPEED, "--out", str(live),
                 "--no-status", *short]) == 0
    assert main(["replay", str(live / "recording.csv"), "--out", str(again), "--no-rrd", *short]) == 0
    with open(live / "recording.csv", newline="") as fh:
        rec = list(csv.DictReader(fh))
    assert min(float(r["z_mm"]) for r in rec) == -30.0  # the device's path, past the needle's length
    assert max(float(r["depth_skin_mm"]) for r in rec) == 20.0  # the needle, at its length
    a = json.loads((live / "summary.json").read_text())
    b = json.loads((again / "summary.json").read_text())
    assert a["loop"]["dropped_rows"] == 0, "the live session dropped rows: the host was overloaded"
    assert a["ticks"] == b["ticks"]
    (m,) = a["metrics"]["per_insertion"]
    assert m["max_depth_mm"] == 20.0 and m["time_at_force_limit_s"] > 0.4
    for k in set(a) - TIMING - {"debrief"}:
        _close(a[k], b[k], k)
    assert a["debrief"]["insertions"] == b["debrief"]["insertions"]
    _same_figure_rows(figures, a["ticks"])

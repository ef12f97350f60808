"""Recordings and trajectory files you can trust, through the real CLI.

``--record`` never destroys a file (an existing one, or the session's input) unless told
``--overwrite`` and creates nothing when the session cannot start; a full disk mid-session is a
fault (exit 3, one ``stopped:`` line) and the recording ends on a whole row that replays; plain CSV
(header on line 1, names not codes); hostile trajectory files are one line, exit 2; a ``reset``
event gives fresh tissue on replay.
"""
from __future__ import annotations

import csv
import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import cli, file_size_limit
from haptic_acu.session import trajectory as T
from haptic_acu.base.errors import UserError

ROOT = Path(__file__).resolve().parent.parent
DEFAULT = ROOT / "trajectories" / "default.csv"
SAME_SITE = ROOT / "trajectories" / "second_insertion_same_site.csv"


def cli_here(*args, timeout=300):
    """The command in this process (tests/cli_helpers.py: ``haptic_acu.cli.main``, the same parser,
    checks, exit status and streams as the console entry, without a child's start-up); an exception
    that escapes it fails the test, as a traceback would. The keyboard session is a child (a pty)."""
    return cli(*args, cwd=ROOT, timeout=timeout)


# progress lines ("haptic-acu: step...", "haptic-acu: step: done in 1.2 s") may precede the one error line
PROGRESS = re.compile(r"^haptic-acu: ")


def one_line(r, status, *names):
    assert r.returncode == status, (r.returncode, r.stderr)
    lines = [ln for ln in r.stderr.strip().splitlines() if not PROGRESS.match(ln)]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    for n in names:
        assert str(n) in lines[0], lines[0]
    return lines[0]


# ------------------------------------------------------------------------------ --record safety
def test_record_refuses_an_existing_file(tmp_path):
    rec = tmp_path / "mine.csv"
    rec.write_text("precious\n")
    r = cli_here("run", "--device", "scripted", "--trajectory", DEFAULT, "--record", rec, "--no-status",
            "--duration", 0.2)
    one_line(r, 2, "mine.csv", "--overwrite")
    assert rec.read_text() == "precious\n"


def test_record_refuses_the_input_trajectory_even_with_overwrite(tmp_path):
    src = tmp_path / "in.csv"
    src.write_bytes(DEFAULT.read_bytes())
    for extra in ((), ("--overwrite",)):
        r = cli_here("run", "--device", "scripted", "--trajectory", src, "--record", src, "--no-status",
                "--duration", 0.2, *extra)
        one_line(r, 2, "in.csv", "input")
        assert src.read_bytes() == DEFAULT.read_bytes()


def test_record_creates_nothing_when_the_session_cannot_start(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,x_mm,y_mm,z_mm\n0,0,0,5\n0.001,0,0,-5\n")  # 10 m/s: refused
    rec = tmp_path / "rec.csv"
    r = cli_here("run", "--device", "scripted", "--trajectory", bad, "--record", rec, "--no-status")
    one_line(r, 2, "bad.csv")
    assert not rec.exists()
    rec.write_text("old\n")  # with --overwrite an existing file is kept until the session starts
    r = cli_here("run", "--device", "scripted", "--trajectory", bad, "--record", rec, "--no-status",
            "--overwrite")
    one_line(r, 2, "bad.csv")
    assert rec.read_text() == "old\n"


def test_overwrite_replaces_and_the_recording_is_plain_csv(tmp_path):
    rec = tmp_path / "rec.csv"
    rec.write_text("old\n")
    r = cli_here("run", "--device", "scripted", "--trajectory", DEFAULT, "--record", rec, "--no-status",
                 "--duration", 2.0, "--speed", 8, "--overwrite", "--out", tmp_path / "out")
    assert r.returncode == 0, r.stderr
    with open(rec, newline="") as f:
        rows = list(csv.DictReader(f))  # header on line 1: a plain CSV reader needs no options
    assert {"t_s", "x_mm", "y_mm", "z_mm", "layer", "state_skin", "event"} <= set(rows[0])
    assert {r["layer"] for r in rows} <= {"outside", "skin", "fat", "muscle", "bone"}
    assert {r["state_skin"] for r in rows} == {"untouched", "pressing", "punctured"}  # 2 s: skin breaks
    assert {r["event"] for r in rows} == {""}
    g = np.genfromtxt(rec, delimiter=",", names=True, dtype=None, encoding="utf-8")
    assert g.dtype.names[:4] == ("t_s", "x_mm", "y_mm", "z_mm") and len(g) == len(rows)
    for bundled in sorted((ROOT / "trajectories").glob("*.csv")):  # header on line 1 there too
        names = np.genfromtxt(bundled, delimiter=",", names=True).dtype.names
        assert names[:4] == ("t_s", "x_mm", "y_mm", "z_mm") and set(names[4:]) <= {"roll_deg"}, bundled
    tr = T.load(rec, extra_columns=("layer", "state_skin"))  # names read back as their codes
    assert set(tr.extra["state_skin"]) == {0.0, 1.0, 2.0}


def test_full_disk_mid_session_is_a_fault_and_the_recording_replays(tmp_path):
    rec = tmp_path / "rec.csv"

    with file_size_limit(100_000):  # writes past 100 kB fail (EFBIG), like a disk filling up
        r = cli_here("run", "--device", "scripted", "--trajectory", DEFAULT, "--record", rec, "--no-status",
                     "--out", tmp_path / "out")
    assert r.returncode == 3, r.stderr
    assert "Traceback" not in r.stderr
    stopped = [ln for ln in r.stderr.splitlines() if "stopped:" in ln]
    assert len(stopped) == 1 and "rec.csv" in stopped[0], r.stderr
    data = rec.read_bytes()
    assert 50_000 < len(data) <= 100_000 and data.endswith(b"\n")
    n_fields = data.split(b"\n", 1)[0].count(b",")
    assert all(line.count(b",") == n_fields for line in data.splitlines())  # whole rows only
    out = tmp_path / "replay"
    rep = cli_here("replay", rec, "--no-rrd", "--quiet", "--out", out)
    assert rep.returncode == 0, rep.stderr


def test_record_to_dev_full_is_a_fault(tmp_path):
    r = cli_here("run", "--device", "scripted", "--trajectory", DEFAULT, "--record", "/dev/full",
                 "--overwrite", "--no-status", "--duration", 0.5, "--out", tmp_path / "out")
    assert r.returncode == 3, r.stderr
    assert "Traceback" not in r.stderr
    assert len([ln for ln in r.stderr.splitlines() if "stopped:" in ln and "/dev/full" in ln]) == 1


def test_fifo_trajectory_is_refused_not_waited_on(tmp_path):
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    r = cli_here("run", "--device", "scripted", "--trajectory", fifo, "--no-status", timeout=60)
    one_line(r, 2, "pipe.csv", "pipe")


# ---------------------------------------------------------------------- hostile trajectory files
HOSTILE = {
    "lone_cr": (b"t_s,x_mm,y_mm,z_mm\r0,0,0,5\r0.5,0,0,2\r", 1),
    "lone_cr_later": (b"t_s,x_mm,y_mm,z_mm\n0,0,0,5\n0.5,0,0,2\r0.6,0,0,2\n", 3),
    "huge_field": (b"t_s,x_mm,y_mm,z_mm,note\n0,0,0,5,\"" + b"a" * 200_000 + b"\"\n0.5,0,0,2,b\n", 2),
    "huge_number_field": (b"t_s,x_mm,y_mm,z_mm\n0,0,0,5\n0.5,0,0," + b"1" * 200_000 + b"\n", 3),
    "far_away": (b"t_s,x_mm,y_mm,z_mm\n0,0,0,1e160\n0.5,0,0,1e160\n", 2),
    "axis_not_unit": (b"t_s,x_mm,y_mm,z_mm,axis_x,axis_y,axis_z\n0,0,0,5,0,0,-1\n0.5,0,0,2,0,0,-0.5\n", 3),
    "axis_incomplete": (b"t_s,x_mm,y_mm,z_mm,axis_x,axis_y\n0,0,0,5,0,0\n0.5,0,0,2,0,0\n", 1),
    "axis_nan": (b"t_s,x_mm,y_mm,z_mm,axis_x,axis_y,axis_z\n0,0,0,5,0,0,-1\n0.5,0,0,2,nan,0,-1\n", 3),
    "roll_too_fast": (b"t_s,x_mm,y_mm,z_mm,roll_deg\n0,0,0,5,0\n0.1,0,0,5,360\n0.2,0,0,5,4000\n", 4),
    "roll_inf": (b"t_s,x_mm,y_mm,z_mm,roll_deg\n0,0,0,5,0\n0.1,0,0,5,inf\n", 3),
    "unknown_event": (b"t_s,x_mm,y_mm,z_mm,event\n0,0,0,5,\n0.1,0,0,5,explode\n", 3),
}


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_hostile_trajectory_one_line(tmp_path, case):
    data, line = HOSTILE[case]
    f = tmp_path / f"{case}.csv"
    f.write_bytes(data)
    r = cli_here("replay", f, "--no-rrd", "--out", tmp_path / "out")
    msg = one_line(r, 2, f"{case}.csv")
    assert f"line {line}:" in msg, msg
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.partial").exists()


def test_optional_columns_are_exposed(tmp_path):
    f = tmp_path / "pose.csv"
    s = 1 / np.sqrt(2)
    f.write_text("t_s,x_mm,y_mm,z_mm,axis_x,axis_y,axis_z,roll_deg,event\n"
                 f"0,0,0,5,0,0,-1,0,\n1,0,0,4,{s},0,{-s},180,\n2,0,0,3,0,0,-1,540,\n")
    from haptic_acu.devices.scripted import ScriptedDevice
    dev = ScriptedDevice(f)
    dev.open()
    t = np.array([0.0, 0.5, 1.0, 1.5])
    dev.read_block(t)
    axis, roll = dev.pose_block(t)
    np.testing.assert_allclose(np.linalg.norm(axis, axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(axis[2], [s, 0, -s], atol=1e-12)
    mid = np.array([s / 2, 0, -(1 + s) / 2])  # linear between the samples, then normalised
    np.testing.assert_allclose(axis[1], mid / np.linalg.norm(mid), atol=1e-12)
    np.testing.assert_allclose(roll, [0, 90, 180, 360], atol=1e-9)
    assert dev.reset_ticks(t) == []
    st = dev.read_at(1.0)
    np.testing.assert_allclose(st.axis, [-s, 0, s], atol=1e-12)  # DeviceState: tip -> handle
    plain = ScriptedDevice(DEFAULT)
    plain.open()
    plain.read_block(t)
    assert plain.pose_block(t) == (None, None)


# ------------------------------------------------------------------------------- reset events
def with_reset(src: Path, dst: Path, at_s: float) -> Path:
    """``src`` plus an event column with ``reset`` on the first sample at or after ``at_s``."""
    lines = src.read_text().splitlines()
    out = [lines[0] + ",event"]
    done = False
    for ln in lines[1:]:
        t = float(ln.split(",", 1)[0])
        ev = "reset" if (t >= at_s and not done) else ""
        done = done or bool(ev)
        out.append(f"{ln},{ev}")
    dst.write_text("\n".join(out) + "\n")
    return dst


def test_reset_is_a_step_and_the_speed_check_starts_anew(tmp_path):
    f = tmp_path / "jump.csv"
    # the tip is 20 mm deep, then (reset) 5 mm above the skin 1 ms later: 25 m/s, a jump no hand
    # makes, refused without the event and accepted with it
    f.write_text("t_s,x_mm,y_mm,z_mm,event\n0,0,0,5,\n2.5,0,0,-20,\n2.501,0,0,5,\n3,0,0,5,\n")
    with pytest.raises(UserError, match="line 4: the tip moves at 25 m/s"):
        T.validate(f)
    f.write_text("t_s,x_mm,y_mm,z_mm,event\n0,0,0,5,\n2.5,0,0,-20,\n2.8,0,0,5,reset\n3,0,0,5,\n")
    T.validate(f)
    r = T.TrajectoryReader(f)
    c = r.cursor()
    pos, vel, _ = c.sample_block(np.array([2.6, 2.799, 2.8, 2.801]))
    # held at the sample before the reset until the reset, then at the reset sample: a step
    np.testing.assert_allclose(pos[:, 2] * 1e3, [-20, -20, 5, 5], atol=1e-9)
    np.testing.assert_allclose(vel[2:], 0.0, atol=1e-9)  # the velocity starts anew at the reset
    assert c.reset_times == [2.8]
    assert c.resets_between(np.array([2.799, 2.8, 2.801])) == [1]


def test_replay_honours_a_reset_fresh_tissue(tmp_path):
    """second_insertion_same_site.csv goes in twice through one hole: one skin puncture. With a
    reset between the passes the tissue is fresh: the second pass punctures the skin again."""
    plain = tmp_path / "plain"
    r = cli_here("replay", SAME_SITE, "--no-rrd", "--quiet", "--out", plain)
    assert r.returncode == 0, r.stderr
    layers = [p["layer"] for p in json.loads((plain / "summary.json").read_text())["punctures"]]
    assert layers.count("skin") == 1
    # the pause between the passes: the tip is back at +5 mm from about 4.2 s to 5.7 s
    reset = with_reset(SAME_SITE, tmp_path / "reset.csv", 5.0)
    out = tmp_path / "fresh"
    r = cli_here("replay", reset, "--no-rrd", "--quiet", "--out", out)
    assert r.returncode == 0, r.stderr
    pts = json.loads((out / "summary.json").read_text())["punctures"]
    skin = [p for p in pts if p["layer"] == "skin"]
    assert len(skin) == 2 and skin[1]["t_s"] > 5.0, pts
    # the second skin puncture needs the same force as the first: the tissue really is fresh
    assert skin[1]["peak_force_n"] == pytest.approx(skin[0]["peak_force_n"], rel=0.02)


# ---------------------------------------------------------------- a keyboard session with a reset
def test_keyboard_session_with_reset_records_the_event_and_replays(tmp_path):
    """Through a pty: in at 40 mm/s (skin and fat break), ``r``, in again, ``q``. The recording
    carries one ``reset`` row where the tip jumps back to the start (a jump no hand makes: refused
    without the event) and replays, breaking the fresh skin a second time."""
    import select
    import threading
    import time

    rec = tmp_path / "kb.csv"
    master, slave = os.openpty()
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    p = subprocess.Popen([sys.executable, "-m", "haptic_acu", "run", "--device", "keyboard",
                          "--record", rec, "--no-status", "--out", tmp_path / "out"], stdin=slave, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, cwd=ROOT, env=env, start_new_session=True)
    os.close(slave)
    err: list[bytes] = []
    reader = threading.Thread(target=lambda: err.extend(iter(lambda: p.stderr.read1(4096), b"")),
                              daemon=True)
    reader.start()
    try:
        end = time.monotonic() + 240
        while b"keyboard:" not in b"".join(err) and p.poll() is None and time.monotonic() < end:
            time.sleep(0.05)
        assert p.poll() is None, b"".join(err).decode()
        for keys, wait in ((b"+++", 0.2), (b"i", 0.45), (b"r", 0.4), (b"i", 0.45), (b"q", 0.0)):
            os.write(master, keys)
            time.sleep(wait)
        p.wait(timeout=60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
        reader.join(timeout=5)
        os.close(master)
    stderr = b"".join(err).decode()
    assert p.returncode == 0, stderr
    with open(rec, newline="") as f:
        rows = list(csv.DictReader(f))
    resets = [i for i, r in enumerate(rows) if r["event"] == "reset"]
    assert len(resets) == 1, stderr
    i = resets[0]
    assert float(rows[i - 1]["z_mm"]) < -1.0  # in the tissue before the reset ...
    assert float(rows[i]["z_mm"]) == pytest.approx(5.0, abs=0.05)  # ... at the start on the reset row
    out = tmp_path / "replay"
    r = cli_here("replay", rec, "--no-rrd", "--quiet", "--out", out)
    assert r.returncode == 0, r.stderr
    skin = [q for q in json.loads((out / "summary.json").read_text())["punctures"]
            if q["layer"] == "skin"]
    assert len(skin) == 2, skin
    # without the event the same file is refused (the jump back is no hand's movement)
    stripped = tmp_path / "no_event.csv"
    stripped.write_text(rec.read_text().replace(",reset\n", ",\n"))
    r = cli_here("replay", stripped, "--no-rrd", "--out", tmp_path / "x")
    one_line(r, 2, "no_event.csv", f"line {i + 2}")


def test_recorder_places_events_on_their_ticks(tmp_path):
    """Events (tick, name) from the device land on the row of that tick, in whichever frame it is
    drained; an event on a row dropped for a repeated timestamp moves to the next row."""
    from types import SimpleNamespace

    from haptic_acu.session.recorder import RecorderSink
    from haptic_acu.servo.samples import COL, NCOL

    dev = SimpleNamespace(events=[])
    rec = RecorderSink(tmp_path / "r.csv", device=dev)
    rec.open()

    def frame(ticks, times):
        rows = np.zeros((len(ticks), NCOL))
        rows[:, COL["tick"]] = ticks
        rows[:, COL["t_s"]] = times
        rows[:, COL["z_m"]] = 0.005
        rows[:, COL["layer"]] = -1
        return SimpleNamespace(samples=rows)

    dev.events += [(2, "reset"), (7, "reset"), (4, "twirl")]  # tick 7 is in the next frame
    rec.on_frame(frame([0, 1, 2, 3, 4], [0.000, 0.001, 0.002, 0.003, 0.004]))
    dev.events += [(5, "reset")]  # tick 5 repeats tick 4's time: dropped, its event moves on
    rec.on_frame(frame([5, 6, 7, 8], [0.004, 0.006, 0.007, 0.008]))
    rec.close(None)
    with open(tmp_path / "r.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    got = {r["t_s"]: r["event"] for r in rows if r["event"]}
    assert got == {"0.002000": "reset", "0.006000": "reset", "0.007000": "reset"}
    # the 8 kept ticks, then the end row half a tick after the last (the position held, no event)
    assert len(rows) == 9 and rows[0]["layer"] == "outside"
    assert rows[-1]["t_s"] == "0.008500" and rows[-1]["event"] == "" and rows[-1]["z_mm"] == rows[-2]["z_mm"]


def test_live_scripted_session_honours_a_reset(tmp_path):
    """Played on the wall clock (paced 8 times as fast: the same ticks), a file with a reset event
    gives fresh tissue too (the compiled loop honours the feed's reset flags): two skin punctures,
    as in the headless replay of the same file."""
    reset = with_reset(SAME_SITE, tmp_path / "reset.csv", 5.0)
    rec = tmp_path / "live.csv"
    r = cli_here("run", "--device", "scripted", "--trajectory", reset, "--speed", 8, "--record", rec, "--no-status",
                 "--out", tmp_path / "out")
    assert r.returncode == 0, r.stderr
    tr = T.load(rec, max_hand_speed_m_per_s=10.0, extra_columns=("state_skin", "event"))
    s = tr.extra["state_skin"]
    breaks = np.flatnonzero((s[1:] == 2) & (s[:-1] != 2)) + 1  # the skin becomes punctured
    assert len(breaks) == 2 and tr.t_s[breaks[1]] > 5.0
    assert tr.t_s[np.flatnonzero(s == 0)].max() > 5.0  # untouched again after the reset
    ev = np.flatnonzero(tr.extra["event"] == 1)  # and the recording carries the reset
    assert len(ev) == 1 and 5.0 <= tr.t_s[ev[0]] < 5.01

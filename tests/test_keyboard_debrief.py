"""A trainee on the keyboard, through a real pseudo-terminal: past the target into bone, and a
needle sunk to its handle. The debrief names the overshoot in mm, the bone contact and the time at
the force limit, gives no technique label from those strokes, and the needle never goes deeper than
its length."""
from __future__ import annotations

import json
import os
import pty
import select
import struct
import subprocess
import sys
import termios
import fcntl
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.slow  # two live sessions of ~10 s each, in real time


def session(out: Path, keys, *extra, cols: int = 80, until: bytes | None = None, timeout: float = 240.0):
    """Run ``haptic-acu run --device keyboard`` on a pty of ``cols`` columns; ``keys``: (wait s, bytes)
    pairs sent after the help line (a wait of None waits for ``until`` on the screen first).
    Returns (exit status, everything the terminal showed)."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, cols, 0, 0))
    p = subprocess.Popen([sys.executable, "-m", "haptic_acu", "run", "--device", "keyboard", "--out", str(out),
                          *extra], stdin=slave, stdout=slave, stderr=slave, cwd=ROOT,
                         env=dict(os.environ, COLUMNS=str(cols)))
    os.close(slave)
    buf = b""

    def pump(seconds, want=None):
        nonlocal buf
        end = time.monotonic() + seconds
        while time.monotonic() < end and (want is None or want not in buf):
            r, _, _ = select.select([master], [], [], 0.05)
            if r:
                try:
                    buf += os.read(master, 65536)
                except OSError:
                    return
    try:
        pump(timeout, b"q quit")
        assert b"q quit" in buf, buf[-2000:]
        for wait, k in keys:
            if wait is None:
                pump(60.0, until)
                assert until in buf, buf[-2000:]
            else:
                pump(wait)
            os.write(master, k)
        end = time.monotonic() + timeout
        while p.poll() is None and time.monotonic() < end:
            pump(0.2)
        pump(0.3)
        return p.wait(timeout=5), buf.decode(errors="replace")
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        os.close(master)


def test_past_the_target_into_bone(tmp_path):
    """A 60 mm needle (bone is 48.2 mm under the acupoint) pushed on at 10 mm/s until the device's
    limit stops it on the bone, held there, then quit."""
    out = tmp_path / "bone"
    status, screen = session(out, [(0.3, b"+"), (0.3, b"i"), (None, b"q")],
                             "--set", "needle.length_mm=60", until=b"FORCE LIMIT")
    assert status == 0, screen[-3000:]
    s = json.loads((out / "summary.json").read_text())
    (m,) = s["metrics"]["per_insertion"]
    hi = s["metrics"]["target_depth_mm"][1]
    assert m["max_depth_mm"] > hi and m["time_on_bone_s"] > 0 and m["time_at_force_limit_s"] > 0
    assert m["technique"]["classification"]["label"] is None and m["technique"]["classification"]["withheld"]
    assert m["max_depth_mm"] <= 60.0 and m["max_tip_depth_mm"] <= 60.0  # never deeper than the needle
    lines = [ln.strip() for ln in screen.replace("\r", "\n").splitlines()]
    text = " ".join(lines[next(i for i, ln in enumerate(lines) if ln.startswith("Debrief:")):])
    assert f"{m['max_depth_mm'] - hi:.2f} mm past the {hi:g} mm limit" in text
    assert f"on bone for {m['time_on_bone_s']:.2f} s" in text
    assert f"limit (3.3 N) for {m['time_at_force_limit_s']:.2f} s" in text
    assert "no technique label" in text and "technique: reinforcing" not in text and "technique: even" not in text
    assert "The one thing to change next time" in text
    wide = [ln for ln in screen.replace("\r", "\n").splitlines() if ("Debrief" in ln or ln.startswith("  ")) and len(ln) > 80]
    assert not wide, wide
    md = (out / "debrief.md").read_text()
    assert "mm past the" in md and "on bone" in md
    assert "period error" not in screen and "servo loop" not in screen  # timing only with --verbose
    assert "PAST 30" in screen and "ON BONE" in screen  # the live line warned


def test_the_handle_stops_the_needle_at_its_length(tmp_path):
    """A 25 mm needle pushed in to the handle: the needle's depth is its length, the debrief says
    the whole needle went in, the stop was felt (the force reached the device's limit)."""
    out = tmp_path / "handle"
    status, screen = session(out, [(0.3, b"+"), (0.3, b"i"), (None, b"q")],
                             "--set", "needle.length_mm=25", until=b"FORCE LIMIT")
    assert status == 0, screen[-3000:]
    s = json.loads((out / "summary.json").read_text())
    (m,) = s["metrics"]["per_insertion"]
    assert m["max_depth_mm"] == pytest.approx(25.0, abs=1e-3)  # the needle's depth: its length, no more
    assert m["time_at_force_limit_s"] > 0 and m["time_on_bone_s"] == 0.0
    assert "the whole 25 mm needle went in: the handle met the skin" in " ".join(screen.split())

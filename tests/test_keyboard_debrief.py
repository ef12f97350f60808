"""A trainee on the keyboard, through a real pseudo-terminal: past the target into bone and on to
the needle's handle. The debrief names the overshoot in mm, the bone contact and the time at the
force limit, gives no technique label from those strokes, and the needle never goes deeper than its
length."""
from __future__ import annotations

import csv
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
pytestmark = pytest.mark.slow  # a live session of ~10 s, in real time


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


def _column(path: Path, name: str) -> list[str]:
    with open(path, newline="") as fh:
        return [row[name] for row in csv.DictReader(fh)]


def test_past_the_target_into_bone_and_to_the_handle(tmp_path):
    """A 53 mm needle pushed on at 10 mm/s until the device's limit stops it: bone is 48.2 mm under
    the acupoint at rest, met at about 51.7 mm of needle (the dents of the layers broken above it
    press the tissue down), so the tip goes into bone and then the handle meets the skin. Held
    there, then quit. The needle's length is the config's; the entry is the acupoint (the scene's
    origin, on the skin), the insertion straight down it."""
    out = tmp_path / "bone"
    length = 53.0
    status, screen = session(out, [(0.3, b"+"), (0.3, b"i"), (None, b"q")],
                             "--set", f"needle.length_mm={length:g}", until=b"FORCE LIMIT")
    assert status == 0, screen[-3000:]
    s = json.loads((out / "summary.json").read_text())
    (m,) = s["metrics"]["per_insertion"]
    hi = s["metrics"]["target_depth_mm"][1]
    assert m["max_depth_mm"] > hi and m["time_on_bone_s"] > 0 and m["time_at_force_limit_s"] > 0
    assert m["technique"]["classification"]["label"] is None and m["technique"]["classification"]["withheld"]
    # the tip never deeper than the needle's length below the entry, in every output, while the
    # device (the recording's x_mm, y_mm, z_mm: what a replay feeds back in) went further
    rec, samples = out / "recording.csv", out / "samples.csv"
    assert min(float(z) for z in _column(rec, "z_mm")) < -length
    assert max(float(d) for d in _column(rec, "depth_skin_mm")) <= length
    assert "bone" in _column(rec, "layer")
    assert max(-float(z) for z in _column(samples, "z_mm")) <= length + 1e-4  # samples: 0.1 um
    assert max(float(d) for d in _column(samples, "depth_skin_mm")) <= length + 1e-4
    assert m["max_depth_mm"] == pytest.approx(length, abs=1e-3)  # to the handle, no further
    assert m["max_tip_depth_mm"] <= length + 1e-3 and s["max_tip_depth_mm"] <= length + 1e-3
    lines = [ln.strip() for ln in screen.replace("\r", "\n").splitlines()]
    text = " ".join(lines[next(i for i, ln in enumerate(lines) if ln.startswith("Debrief:")):])
    assert f"{m['max_depth_mm'] - hi:.2f} mm past the {hi:g} mm limit" in text
    assert f"on bone for {m['time_on_bone_s']:.2f} s" in text
    assert f"limit (3.3 N) for {m['time_at_force_limit_s']:.2f} s" in text
    assert f"the whole {length:g} mm needle went in: the handle met the skin" in text
    assert "no technique label" in text and "technique: reinforcing" not in text and "technique: even" not in text
    assert "The one thing to change next time" in text
    wide = [ln for ln in screen.replace("\r", "\n").splitlines() if ("Debrief" in ln or ln.startswith("  ")) and len(ln) > 80]
    assert not wide, wide
    md = (out / "debrief.md").read_text()
    assert "mm past the" in md and "on bone" in md and "the handle met the skin" in md
    assert "period error" not in screen and "servo loop" not in screen  # timing only with --verbose
    assert "PAST 30" in screen and "ON BONE" in screen  # the live line warned

"""The OMNI's stylus as the needle through the real CLI, pyOpenHaptics and the HD
API emulator (tests/hd_emulator): the stylus orientation is the needle's axis, its roll's sign is the
workspace's, and a perfectly still hand is no fault while a frozen device still is.

The emulator reports HD_CURRENT_TRANSFORM for a stylus direction it is given (``stylus_axis``:
handle to tip, device frame; the end-effector frame's -z axis, turned about the stylus by the third
gimbal angle) and runs the stylus either along a scripted path (kinematic) or as a 45 g mass held by
a hand on a scripted path (physical stylus mode, closed loop). Expectations come from the scripted
direction, the workspace formula of config/tissue.toml and the emulator's own log, never from the
code under test.

Sessions run in processes of their own (the emulator is configured per process), forked from a warm
interpreter (tests/conftest.py's ``emulator``), with OPENBLAS_NUM_THREADS=1 (see test_run_omni);
their replays, and the command lines refused before any session, run in-process.
"""
from __future__ import annotations

import contextlib
import csv
import io
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from hd_emulator.build import FAST, FIRM_GRIP, LOOSE_GRIP, emulator_env  # noqa: E402

from haptic_acu.cli import main  # noqa: E402
from haptic_acu.session import trajectory  # noqa: E402
from haptic_acu.base.config import load_config  # noqa: E402
from haptic_acu.session.recorder import EXTRA, tick_rows  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
# Device time only (the emulator's virtual clock, build.FAST): the parallel phase runs these; a test
# that measures the wall (a watchdog, a blocked step) carries @pytest.mark.serial. Slow: a session each.
pytestmark = pytest.mark.slow
FRAME = 0  # emulator log record kind of a committed force frame
TIMEOUT_S = 300
TREMOR = (0.05, 9.0)  # a hand's physiological tremor: 0.05 mm at 9 Hz


def to_device_mm(p_scene_mm):
    """Scene (mm) -> device (mm) for config/tissue.toml's workspace (a turn about z, a scale, an offset)."""
    ws = load_config(None).workspace
    a = np.radians(ws.rotation_z_deg)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return R.T @ ((np.asarray(p_scene_mm, float) - np.asarray(ws.offset_mm)) / ws.scale)


def to_device_dir(d_scene):
    ws = load_config(None).workspace
    a = np.radians(ws.rotation_z_deg)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return R.T @ np.asarray(d_scene, float)


def line_path(d_scene, s0, s1, speed, hold):
    """Knots (t_s, x, y, z device mm) along the scene line s * d through the acupoint (the scene
    origin) from s0 to s1 mm at ``speed`` mm/s after 0.3 s still, then ``hold`` s still; the duration."""
    d = np.asarray(d_scene, float)
    t1 = 0.3 + (s1 - s0) / speed
    knots = [(0.0, s0), (0.3, s0), (t1, s1), (t1 + hold, s1)]
    return [(t, *to_device_mm(s * d)) for t, s in knots], t1 + hold


def run_cli(emulator, tmp_path, path, duration, *, extra_args=(), config=None, **emu):
    log = tmp_path / "forces.csv"
    rec = tmp_path / "rec.csv"
    out = tmp_path / "out"
    env = emulator_env(emulator.lib, path=path, log=log, **{"speed": FAST, **emu})
    env["OPENBLAS_NUM_THREADS"] = "1"
    cmd = ["run", "--verbose", "--device", "omni", "--duration", str(duration), "--record", rec, "--out", out,
           "--no-status", *extra_args]
    if config is not None:
        cmd += ["--config", config]
    proc = emulator.sessions.run(cmd, env, timeout=TIMEOUT_S)
    rows = np.loadtxt(log, delimiter=",", skiprows=1, ndmin=2) if log.exists() else np.zeros((0, 8))
    return proc, rows[rows[:, 1] == FRAME], rec, out


def samples(out) -> dict:
    with open(out / "samples.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    cols = {}
    for key in ("t_s", "axis_x", "axis_y", "axis_z", "clamped", "f_lateral_n", "roll_deg"):
        cols[key] = np.array([float(r[key]) if r[key] not in ("", "nan") else np.nan for r in rows])
    cols["state_skin"] = np.array([r["state_skin"] for r in rows])
    cols["state_muscle"] = np.array([r["state_muscle"] for r in rows])
    cols["axis"] = np.stack([cols["axis_x"], cols["axis_y"], cols["axis_z"]], axis=1)
    return cols


def angle_deg(a, b):
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    c = np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b))
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


OBLIQUE = np.array([np.sin(np.radians(45.0)), 0.0, -np.cos(np.radians(45.0))])  # 45 deg from the normal


@pytest.mark.parametrize("grip_name, grip", [("loose", LOOSE_GRIP), ("firm", FIRM_GRIP)])
def test_an_oblique_insertion_takes_the_stylus_axis_in_closed_loop(emulator, tmp_path, grip_name, grip):
    # A hand inserts at 45 deg from the skin's normal, the stylus held along that line (and
    # rolled a little, which must not tilt the axis), at 10 mm/s through the skin (0.8 mm) into the fat
    # (8.4 mm), 8 mm below the skin. The needle's axis is the stylus's: within 2 deg of the line, with
    # no clamped tick and a small lateral force. (With --travel-axis the same run, firm grip, ends
    # 14 deg off the line with 0.7 N of lateral force; the issue measured 20-30 deg and thousands of
    # clamped ticks headless. Further on, the muscle's break gives 2 clamped ticks in closed loop at
    # any angle, 0 deg too: a puncture transient of the rendering, not of the axis.)
    path, duration = line_path(OBLIQUE, -6.0, 8.0 / np.cos(np.radians(45.0)), 10.0, 0.5)
    gimbal = [(0.0, 0.0, 0.0, 0.0), (duration, 0.0, 0.0, 0.6)]
    proc, frames, rec, out = run_cli(emulator, tmp_path, path, duration,
                                     stylus={**grip, "hand_tremor": TREMOR},
                                     stylus_axis=[(0.0, *to_device_dir(OBLIQUE))], gimbal=gimbal)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr and "compiled servo loop" in proc.stderr
    s = samples(out)
    inserted = s["state_skin"] == "punctured"
    assert inserted.sum() > 800
    err = angle_deg(s["axis"][inserted], OBLIQUE)
    print(grip_name, f"insertion axis off the line: max {err.max():.3f} deg; "
                     f"lateral force max {np.nanmax(s['f_lateral_n']):.4f} N")
    assert err.max() < 2.0
    before = ~inserted
    assert np.all(angle_deg(s["axis"][before], OBLIQUE) < 1e-3)  # the stylus's own, every tick before entry
    assert np.all(s["clamped"] == 0)
    assert np.nanmax(s["f_lateral_n"]) < 0.25
    tr = tick_rows(trajectory.load(rec, extra_columns=EXTRA))
    assert len(tr.t_s) == len(s["t_s"])
    # the recording carries the axis: its headless replay inserts along the same line
    err = io.StringIO()
    with contextlib.redirect_stderr(err):  # in-process: the exit status and stderr are what a subprocess gives
        rc = main(["replay", str(rec), "--no-rrd", "--quiet", "--out", str(tmp_path / "replay")])
    assert rc == 0, err.getvalue()
    r = samples(tmp_path / "replay")
    r_in = r["state_skin"] == "punctured"
    assert r_in.sum() > 800 and np.all(angle_deg(r["axis"][r_in], OBLIQUE) < 2.0)



def test_a_firm_grip_through_the_muscle_has_no_clamped_tick(emulator, tmp_path):
    # A firm grip (2 N/mm) inserting straight down at 10 mm/s through skin, fat and the
    # muscle's break to 20 mm. The coupling's compression at the muscle's break once reached the tissue
    # as a 0.35 m/s proxy jump: -8 N of viscous shaft friction, two ticks clamped at 3.3 N.
    down = np.array([0.0, 0.0, -1.0])
    path, duration = line_path(down, -4.0, 20.0, 10.0, 0.5)
    proc, frames, rec, out = run_cli(emulator, tmp_path, path, duration,
                                     stylus={**FIRM_GRIP, "hand_tremor": TREMOR},
                                     stylus_axis=[(0.0, *to_device_dir(down))])
    assert proc.returncode == 0, proc.stderr
    s = samples(out)
    assert s["state_muscle"][-1] == "punctured"
    assert np.all(s["clamped"] == 0)
    with open(out / "samples.csv", newline="") as f:
        fmag = np.array([float(r["f_n"]) for r in csv.DictReader(f)])
    assert fmag.max() < 1.5, fmag.max()  # the muscle's surface peaks near 0.75 N

@pytest.mark.parametrize("how", ["nan_transform", "travel_switch"])
def test_without_the_stylus_axis_the_travel_decides(emulator, tmp_path, how):
    # A transform whose rotation is NaN (the device gives no orientation) is no fault: the step falls
    # back to the direction of travel. --travel-axis does the same on purpose: here the stylus is held
    # 20 deg off the line of travel (straight down the normal, where the travel's axis is exact), and
    # the needle's axis is the travel's. (Kinematic stylus.)
    travel = np.array([0.0, 0.0, -1.0])
    held = np.array([np.sin(np.radians(20.0)), 0.0, -np.cos(np.radians(20.0))])
    path, duration = line_path(travel, -4.0, 8.0, 10.0, 0.3)
    kw = {"faults": [("nan_orientation", 0.0)]} if how == "nan_transform" else {"extra_args": ["--travel-axis"]}
    proc, frames, rec, out = run_cli(emulator, tmp_path, path, duration, stylus_axis=[(0.0, *to_device_dir(held))],
                                     **kw)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr and "stopped:" not in proc.stderr
    s = samples(out)
    inserted = s["state_skin"] == "punctured"
    assert inserted.sum() > 300
    assert np.all(np.isnan(s["axis"][~inserted]))  # no axis from the device
    err = angle_deg(s["axis"][inserted], travel)
    assert err.max() < 2.0, err.max()
    assert np.all(angle_deg(s["axis"][inserted], held) > 18.0)


def test_the_roll_sign_is_the_workspace_s(emulator, tmp_path):
    # The roll is + clockwise seen from the handle. OpenHaptics documents the third gimbal
    # angle as "CW is +" without saying from which end; workspace.roll_sign (default 1) sets the sign.
    # The emulator turns its stylus 1 rad about the stylus (the transform's x axis turns the right-handed
    # way about the handle -> tip direction: clockwise seen from the handle): roll_deg +57.3 by default,
    # -57.3 with roll_sign = -1.
    z5 = to_device_mm([0.0, 0.0, 5.0])
    path = [(0.0, *z5), (1.0, *z5)]
    gimbal = [(0.0, 0.0, 0.0, 0.0), (0.2, 0.0, 0.0, 0.0), (0.7, 0.0, 0.0, 1.0)]
    text = (REPO / "config" / "tissue.toml").read_text()
    flipped = tmp_path / "flipped.toml"
    flipped.write_text(text.replace("roll_sign = 1", "roll_sign = -1"))
    assert flipped.read_text() != text
    for sign, cfg in ((1.0, None), (-1.0, flipped)):
        sub = tmp_path / f"sign{int(sign)}"
        sub.mkdir()
        proc, frames, rec, out = run_cli(emulator, sub, path, 0.9, config=cfg, gimbal=gimbal)
        assert proc.returncode == 0, proc.stderr
        s = samples(out)
        assert s["roll_deg"][-1] == pytest.approx(sign * np.degrees(1.0), abs=1e-3)
        assert np.all(sign * np.diff(s["roll_deg"]) > -1e-3)  # turning one way only


def test_a_still_hand_on_the_skin_for_5_s_is_no_fault(emulator, tmp_path):
    # A trainee presses the skin (1.2 mm down, short of puncture) and holds perfectly still
    # for 5 s: the stylus kinematic (a hand that does not move at all, not even by an encoder step),
    # so the position is bit-identical under a steady force for 5 s (the old guard stopped such a
    # session after 1 s). The session runs to its end. (A held stylus in the physical mode is never
    # that still: the coupling's force moves it an encoder step every ~15 ms even without tremor.)
    top = to_device_mm([0.0, 0.0, 3.0])
    down = to_device_mm([0.0, 0.0, -1.2])
    path = [(0.0, *top), (0.3, *top), (0.8, *down)]  # past its last knot the emulator holds it exactly
    proc, frames, rec, out = run_cli(emulator, tmp_path, path, 6.0)
    assert proc.returncode == 0, proc.stderr
    assert "stopped:" not in proc.stderr and "Traceback" not in proc.stderr
    tr = tick_rows(trajectory.load(rec, extra_columns=EXTRA))
    assert tr.t_s[-1] > 5.9
    n = len(tr.t_s)
    p = frames[:n, 2:5]
    f = np.linalg.norm(frames[:n, 5:8], axis=1)
    same = np.all(p[1:] == p[:-1], axis=1) & (f[1:] > 0.05)
    run, longest = 0, 0
    for x in same:  # the longest stretch of bit-identical positions under force
        run = run + 1 if x else 0
        longest = max(longest, run)
    print(f"longest bit-identical stretch under force: {longest} ms; force there {f[-1]:.3f} N")
    assert longest > 4500


@pytest.mark.parametrize("args, names", [
    (["--device", "omni", "--set", "workspace.roll_sign=2"], "workspace.roll_sign"),
    (["--device", "keyboard", "--travel-axis"], "--travel-axis")])
def test_bad_roll_sign_or_travel_axis_off_the_omni_is_one_line_and_status_2(tmp_path, capsys, args, names):
    # in-process: refused before any device or session, so the exit status and the output are the CLI's own
    rc = main(["run", *args, "--duration", "1", "--out", str(tmp_path / "out")])
    out, err = capsys.readouterr()
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and names in lines[0] and "Traceback" not in err and out == ""
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("servo", ["compiled", "python"])
def test_the_stylus_axis_wins_over_the_travel_in_both_callbacks(emulator, tmp_path, servo):
    # The same kinematic run as above with the stylus's orientation used: the needle enters along the
    # held stylus (20 deg off the line of travel), through the compiled callback and the Python one.
    travel = np.array([0.0, 0.0, -1.0])
    held = np.array([np.sin(np.radians(20.0)), 0.0, -np.cos(np.radians(20.0))])
    path, duration = line_path(travel, -4.0, 8.0, 10.0, 0.3)
    proc, frames, rec, out = run_cli(emulator, tmp_path, path, duration, stylus_axis=[(0.0, *to_device_dir(held))],
                                     extra_args=["--python-servo"] if servo == "python" else [])
    assert proc.returncode == 0, proc.stderr
    assert f"{servo} servo loop" in proc.stderr
    s = samples(out)
    inserted = s["state_skin"] == "punctured"
    assert inserted.sum() > 300
    assert np.all(angle_deg(s["axis"], held) < 1e-3)  # the stylus's before entry, the insertion axis after

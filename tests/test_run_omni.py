"""`haptic-acu run --device omni` end to end: the CLI, the engine, devices.omni and the real
pyOpenHaptics package, against the HD API emulator (tests/hd_emulator), each session a process of
its own (forked from a warm interpreter: tests/conftest.py's ``emulator``).

The emulator moves the stylus along a scripted path in device time (1 ms ticks from the moment
the CLI opens the device) and logs every force frame it is sent (device frame, N) with the
position the frame was computed from. Expectations come from the path, the workspace formula of
config/tissue.toml (p_scene = scale * Rz * p_device + offset_mm) written out here, and the
emulator's log, never from the code under test:

* every servo tick is one recorded row and one emulator frame, in order, at the same position;
* the force the emulator got is the recorded (engine) force, clamped to the device's limit
  min(safety.force_limit_n, the emulator's nominal maximum);
* pressing the skin (the tip below the acupoint) pushes the stylus back out, along device +z;
* the session ends with a zero-force frame.

Sessions run with OPENBLAS_NUM_THREADS=1: the tissue's least-squares fit is several times
faster single-threaded on a loaded 2-core machine, and nothing checked here depends on it.
"""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from hd_emulator.build import FAST, emulator_env  # noqa: E402

from haptic_acu.session import trajectory  # noqa: E402
from haptic_acu.base.config import load_config  # noqa: E402
from haptic_acu.session.recorder import EXTRA, tick_rows  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
# Device time only (the emulator's virtual clock, build.FAST): the parallel phase runs these; a test
# that measures the wall (a watchdog, a blocked step) carries @pytest.mark.serial. Slow: a session each.
pytestmark = pytest.mark.slow
FRAME = 0  # emulator log record kind of a committed force frame
# the emulated device's nominal maximum: below the config's 3.3 N, so it is the limit, and below the
# ~0.2 N the rendering layer's coupling (0.63 N/mm in series with the skin) passes at the press path's
# 1.3 mm into the fine-needle skin (of its ~1.5 mm to puncture), so it engages
NOMINAL_MAX_N = 0.15
TIMEOUT_S = 180


@pytest.fixture(scope="module")
def workspace():
    ws = load_config(None).workspace
    return np.array(ws.offset_mm, float), float(ws.scale), float(ws.rotation_z_deg)


def to_scene_mm(p_dev_mm, workspace):
    offset, scale, rot = workspace
    a = np.radians(rot)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return scale * np.asarray(p_dev_mm, float) @ R.T + offset


def device_z_of_scene_z(z_scene_mm, workspace):
    offset, scale, rot = workspace
    return (z_scene_mm - offset[2]) / scale  # a turn about z leaves z alone


def run_cli(emulator, tmp_path, path, faults=(), duration=2.0, velocity=True, servo="compiled", config=None,
            speed=FAST):
    log = tmp_path / "forces.csv"
    rec = tmp_path / "rec.csv"
    env = emulator_env(emulator.lib, path=path, faults=faults, log=log, nominal_max_force=NOMINAL_MAX_N,
                       velocity=velocity, speed=speed)
    env["OPENBLAS_NUM_THREADS"] = "1"
    proc = emulator.sessions.run(["run", "--verbose", "--device", "omni", "--duration", str(duration),
                                  "--record", rec, "--out", tmp_path / "out", "--no-status"]
                                 + (["--python-servo"] if servo == "python" else [])
                                 + (["--config", config] if config is not None else []), env, timeout=TIMEOUT_S)
    frames = np.zeros((0, 8))
    if log.exists():
        rows = np.loadtxt(log, delimiter=",", skiprows=1, ndmin=2)
        frames = rows[rows[:, 1] == FRAME]
    return proc, frames, rec


def press_path(workspace):
    """Device-frame knots (t_s, x, y, z mm): 5 mm above the acupoint, down to 1.1 mm below it
    (a dent short of the skin's ~1.5 mm puncture), slowly on to 1.3 mm (never still while loaded,
    or the OMNI's stall detector would rightly fire), back out to 5 mm above."""
    z = lambda zs: device_z_of_scene_z(zs, workspace)  # noqa: E731
    return [(0.0, 0.0, 0.0, z(5.0)), (0.3, 0.0, 0.0, z(5.0)), (0.9, 0.0, 0.0, z(-1.1)),
            (1.5, 0.0, 0.0, z(-1.3)), (1.9, 0.0, 0.0, z(5.0))]


def clamp(f, limit):
    n = np.linalg.norm(f, axis=1, keepdims=True)
    return np.where(n > limit, f * (limit / np.maximum(n, 1e-300)), f)


def check_rows_match_frames(tr, frames, workspace):
    """Recorded row i and emulator frame i are the same servo tick: the device got the recorded
    rendered force (``fr_*_n``, the rendering layer's) clamped to its limit (after the 200-tick
    ramp-in), at the recorded tick time; the recorded position is the proxy the tissue step ran at,
    tied to the stylus by the virtual coupling: within the coupling's stretch at the device's force
    limit plus the tissue's give (a fraction of a millimetre here) of the device's position."""
    n = len(tr.t_s)
    assert len(frames) >= n
    # the device's tick time: 1 ms a row, in step with the emulator's clock (which started at open)
    np.testing.assert_allclose(np.diff(tr.t_s), 1e-3, rtol=0, atol=1e-9)
    np.testing.assert_allclose(frames[:n, 0] - tr.t_s, frames[0, 0] - tr.t_s[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(tr.pos_m * 1e3, to_scene_mm(frames[:n, 2:5], workspace), rtol=0, atol=1.5)
    f_rec = np.stack([tr.extra["fr_x_n"], tr.extra["fr_y_n"], tr.extra["fr_z_n"]], axis=1)
    ramp = np.minimum(1.0, np.arange(n) / 200.0)[:, None]
    a = np.radians(workspace[2])
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    expected = clamp(ramp * f_rec, NOMINAL_MAX_N) @ R  # scene -> device: R^T f (row vectors: f R)
    np.testing.assert_allclose(frames[:n, 5:8], expected, rtol=0, atol=2e-5)  # the file's 10 uN


@pytest.mark.parametrize("servo, velocity", [("compiled", True), ("compiled", False), ("python", True)])
def test_omni_press_through_the_cli(emulator, tmp_path, workspace, servo, velocity):
    # compiled: the HD scheduler runs haptic_acu.servo.omniloop's callback; velocity=False: the device
    # reports none, so both paths filter position differences; python: the ctypes Python callback.
    proc, frames, rec = run_cli(emulator, tmp_path, press_path(workspace), servo=servo, velocity=velocity)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    m = re.search(r"session: (\d+) ticks", proc.stderr)
    assert m, proc.stderr
    ticks = int(m.group(1))
    assert f"{servo} servo loop" in proc.stderr

    tr = tick_rows(trajectory.load(rec, extra_columns=EXTRA))  # parses: strictly increasing time, finite values
    # one row per tick of a 2 s session, to its end (rows carry the device's tick time)
    assert len(tr.t_s) == ticks >= 1000 and 1.8 < tr.t_s[-1] <= 2.0
    check_rows_match_frames(tr, frames, workspace)
    # then only zero frames: the step past --duration, the stop frame, close()'s frame
    assert np.all(frames[ticks:, 5:8] == 0.0) and 1 <= len(frames) - ticks <= 10

    f = frames[:, 5:8]
    assert np.all(np.isfinite(f))
    assert np.linalg.norm(f, axis=1).max() <= min(3.3, NOMINAL_MAX_N) * (1 + 1e-12)
    z_scene = to_scene_mm(frames[:, 2:5], workspace)[:, 2]
    pressing = z_scene < -0.05
    assert pressing.sum() > 300
    assert np.all(f[pressing, 2] > 0.0)  # pushed back out of the skin: +z in the device frame
    assert np.all(np.abs(f[pressing, :2]) < 1e-3 * f[pressing, 2:3] + 1e-9)
    assert np.any(np.linalg.norm(f, axis=1) >= NOMINAL_MAX_N * (1 - 1e-9))  # the device limit engaged
    assert np.all(np.abs(f[z_scene > 0.05]) < 1e-9)  # nothing above the skin (the coupling's rounding)
    assert np.all(f[-1] == 0.0)  # the session ends commanding zero


@pytest.mark.parametrize("servo", ["compiled", "python"])
def test_omni_turned_scaled_workspace_through_the_cli(emulator, tmp_path, servo):
    # The stylus frame turned 90 degrees about z, scaled 1.5x and offset 1.5 mm sideways: the press
    # lands off the acupoint where the skin's normal tilts, so the force has sideways parts, and
    # the emulator must get them turned back into its own frame (R^T), clamped to its limit.
    text = (REPO / "config" / "tissue.toml").read_text()
    start = text.index("[workspace]")
    cfg_path = tmp_path / "turned.toml"
    cfg_path.write_text(text[:start] + "[workspace]\noffset_mm = [1.5, 0.0, -20.0]\nscale = 1.5\n"
                        "rotation_z_deg = 90.0\nroll_sign = 1\n")
    workspace = (np.array([1.5, 0.0, -20.0]), 1.5, 90.0)
    proc, frames, rec = run_cli(emulator, tmp_path, press_path(workspace), servo=servo, config=cfg_path)
    assert proc.returncode == 0, proc.stderr
    assert f"{servo} servo loop" in proc.stderr
    tr = tick_rows(trajectory.load(rec, extra_columns=EXTRA))
    check_rows_match_frames(tr, frames, workspace)
    f_scene = np.stack([tr.extra["fx_n"], tr.extra["fy_n"]], axis=1)
    assert np.abs(f_scene[:, 0]).max() > 1e-3  # a sideways force in the scene, turned into the device's y


FAULT_AT = 1.0  # device time of the fault: the stylus is ~1.17 mm into the skin, pressing, moving slowly


@pytest.mark.parametrize("kind, message", [("device_fault", "HD_DEVICE_FAULT"), ("comm_error", "HD_COMM_ERROR"),
                                           ("nan", "non-finite position")])
@pytest.mark.parametrize("servo", ["compiled", "python"])
def test_omni_fault_mid_session_through_the_cli(emulator, tmp_path, workspace, kind, message, servo):
    path = press_path(workspace)
    proc, frames, rec = run_cli(emulator, tmp_path, path, faults=[(kind, FAULT_AT)], duration=3.0, servo=servo)
    assert f"{servo} servo loop" in proc.stderr
    assert proc.returncode == 3, proc.stderr
    assert "Traceback" not in proc.stderr
    reasons = [ln for ln in proc.stderr.splitlines() if "stopped:" in ln]
    assert len(reasons) == 1 and message in reasons[0], proc.stderr

    f = frames[:, 5:8]
    assert np.all(np.isfinite(f))
    assert np.any(f[frames[:, 0] < FAULT_AT, 2] > 0.5 * NOMINAL_MAX_N)  # it was pressing when the fault came
    assert np.all(f[-1] == 0.0)  # the last frame commanded zero

    tr = tick_rows(trajectory.load(rec, extra_columns=EXTRA))
    n = len(tr.t_s)
    check_rows_match_frames(tr, frames, workspace)  # every tick up to the fault, in order
    assert len(frames) - n == 1  # then only the fault's own zero frame

    # The rows carry the device's tick time: the recording reaches the fault.
    t_last = float(frames[len(tr.t_s) - 1, 0])  # the emulator's device time of the last row
    tick = 1e-3
    # the tick at FAULT_AT reports the error (or NaN): the one before is the last
    assert FAULT_AT - 3 * tick <= t_last <= FAULT_AT


@pytest.mark.parametrize("servo", ["compiled", "python"])
def test_omni_frozen_under_a_steady_force_is_a_still_hand_through_the_cli(emulator, tmp_path, workspace, servo):
    # The encoders freeze at FAULT_AT while the stylus presses the skin with the device's whole
    # (0.15 N) force: bit-identical positions under a force that no longer changes, which is what a
    # trainee holding perfectly still produces too. The guard tells a stalled device by the
    # force/position relation (a force changing by 0.5 N with the position frozen: tests/test_omni.py)
    # and by the HD API's own errors and the scheduler watchdog (above); a steady force on a frozen
    # position is no fault (README, Faults): the session runs to its end, every tick recorded, the
    # force within the device's limit, the last frame zero.
    proc, frames, rec = run_cli(emulator, tmp_path, press_path(workspace), faults=[("freeze", FAULT_AT)],
                                duration=3.0, servo=servo)
    assert proc.returncode == 0, proc.stderr
    assert f"{servo} servo loop" in proc.stderr and "stopped:" not in proc.stderr
    tr = tick_rows(trajectory.load(rec, extra_columns=EXTRA))
    n = len(tr.t_s)
    assert tr.t_s[-1] > 2.9
    check_rows_match_frames(tr, frames, workspace)
    frozen = frames[:n, 0] > FAULT_AT + 2e-3
    assert frozen.sum() > 1800 and np.all(frames[:n][frozen, 2:5] == frames[n - 1, 2:5])
    assert np.linalg.norm(frames[:, 5:8], axis=1).max() <= NOMINAL_MAX_N * (1 + 1e-12)
    assert np.all(frames[-1, 5:8] == 0.0)


@pytest.mark.serial  # the watchdog's 100 ms of wall time, on the real device's free-running clock
def test_omni_scheduler_that_stops_calling_is_a_fault_through_the_cli(emulator, tmp_path, workspace):
    # The compiled callback is not called any more: the device's watchdog (100 ms) stops the session
    # with the output switched off, and every tick that ran is recorded.
    proc, frames, rec = run_cli(emulator, tmp_path, press_path(workspace), faults=[("stop_calling", FAULT_AT)],
                                duration=3.0, speed=1)  # the watchdog counts wall time
    assert proc.returncode == 3, proc.stderr
    assert "compiled servo loop" in proc.stderr and "Traceback" not in proc.stderr
    reasons = [ln for ln in proc.stderr.splitlines() if "stopped:" in ln]
    assert len(reasons) == 1 and "not called" in reasons[0], proc.stderr
    tr = tick_rows(trajectory.load(rec, extra_columns=EXTRA))
    check_rows_match_frames(tr, frames, workspace)
    assert len(frames) == len(tr.t_s)  # no frame after the last tick: none could be sent
    assert abs(frames[-1, 0] - FAULT_AT) <= 3e-3


def test_missing_openhaptics_is_one_line_and_status_2(tmp_path):
    env = emulator_env(tmp_path / "nowhere" / "libHD.so")
    probe = subprocess.run([sys.executable, "-c", "import ctypes; ctypes.CDLL('libHD.so')"], env=env,
                           capture_output=True)
    if probe.returncode == 0:
        pytest.skip("a libHD.so is installed on this machine's loader path")
    proc = subprocess.run([sys.executable, "-m", "haptic_acu", "run", "--verbose", "--device", "omni", "--duration", "1"],
                          env=env, cwd=REPO, capture_output=True, text=True, timeout=TIMEOUT_S)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    msg = lines[0]
    assert msg.startswith("haptic-acu run: error:")
    assert "libHD.so" in msg and "OpenHaptics" in msg and "LD_LIBRARY_PATH" in msg  # what, and how to install
    assert "Traceback" not in proc.stderr and proc.stdout == ""


@pytest.mark.parametrize("servo", ["compiled", "python"])
def test_omni_stylus_roll_is_recorded_through_the_cli(emulator, tmp_path, workspace, servo):
    """The emulator's third gimbal angle (the stylus roll) is the session's roll, unwrapped 1:1 from
    0 at the first tick: the recording's roll_deg follows the scripted gimbal knots at each frame's
    device time (the emulator's log), across a wrap at +-pi (3.0 rad to -3.0 rad the short way)."""
    z = device_z_of_scene_z(5.0, workspace)
    path = [(0.0, 0.0, 0.0, z), (2.0, 0.0, 0.0, z)]
    # roll: 0.5 -> 2.5 rad over 0.5 s, on to 3.13 and through the wrap between two ticks (+3.13 ->
    # -3.13 is +0.023 rad the short way), on to -2.0 (a hand turning at under 1 turn/s throughout)
    gimbal = [(0.0, 0.0, 0.4, 0.5), (0.5, 0.0, 0.4, 2.5), (0.9, 0.0, 0.4, 3.13), (0.9004, 0.0, 0.4, -3.13),
              (1.4, 0.0, 0.4, -2.0)]
    log = tmp_path / "forces.csv"
    rec = tmp_path / "rec.csv"
    env = emulator_env(emulator.lib, path=path, log=log, nominal_max_force=NOMINAL_MAX_N, gimbal=gimbal, speed=FAST)
    env["OPENBLAS_NUM_THREADS"] = "1"
    proc = emulator.sessions.run(["run", "--verbose", "--device", "omni", "--duration", "1.6", "--record", rec,
                                  "--no-status", "--out", tmp_path / "out"] + (["--python-servo"] if servo == "python" else []),
                                 env, timeout=TIMEOUT_S)
    assert proc.returncode == 0, proc.stderr
    rows = np.loadtxt(log, delimiter=",", skiprows=1, ndmin=2)
    frames = rows[rows[:, 1] == FRAME]
    tr = tick_rows(trajectory.load(rec, extra_columns=EXTRA))
    n = len(tr.t_s)
    assert n > 1000 and len(frames) >= n
    t_dev = frames[:n, 0]
    kt = np.array([k[0] for k in gimbal])
    kc = np.array([k[3] for k in gimbal])
    c = np.interp(t_dev, kt, kc)
    wrapped = np.angle(np.exp(1j * np.diff(c)))  # each tick's change the short way round
    expected = np.degrees(np.concatenate([[0.0], np.cumsum(wrapped)]))
    np.testing.assert_allclose(tr.extra["roll_deg"], expected, atol=2e-4)  # the file's 1e-4 deg
    # through the wrap without jumping back: the roll only ever grows, by the gimbal's unwrapped turn
    assert t_dev[0] < 0.9 < t_dev[n - 1]
    assert np.all(np.diff(tr.extra["roll_deg"]) > -2e-4)
    c_end = np.interp(t_dev[n - 1], kt, kc) + (2 * np.pi if t_dev[n - 1] > 0.9004 else 0.0)
    assert tr.extra["roll_deg"][-1] == pytest.approx(np.degrees(c_end - c[0]), abs=1e-3)

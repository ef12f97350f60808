"""devices.omni.OmniDevice through the real pyOpenHaptics package, against the HD API emulator.

The emulator (tests/hd_emulator/hd_emulator.c) is compiled into a libHD.so; each session runs in a
process of its own whose loader path finds it (pyOpenHaptics loads libHD.so at import, so it never
enters this process), forked from a warm interpreter (tests/conftest.py's ``emulator``). The emulator moves the stylus along a scripted path, logs every force it is sent
and injects faults; tests/hd_emulator/run_session.py drives an OmniDevice with a spring standing
in for the physics: F = k * max(0, -z) along +z in the scene frame. Expected forces, positions
and velocities are computed here from the path knots and the workspace formula of
devices/base.py, not taken from OmniDevice.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from hd_emulator.build import FAST, emulator_env  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
# Device time only (the emulator's virtual clock, build.FAST): the parallel phase runs these; a test
# that measures the wall (a watchdog, a blocked step) carries @pytest.mark.serial. Slow: a session each.
pytestmark = pytest.mark.slow
RUN_SESSION = REPO / "tests" / "hd_emulator" / "run_session.py"
FRAME, OUTPUT_DISABLED = 0, 1  # emulator log record kinds

# Workspace used throughout: device (x, y, z) mm -> scene (-y, x, z - 20) mm (a 90 degree turn about z).
WS = {"offset_mm": [0.0, 0.0, -20.0], "scale": 1.0, "rotation_z_deg": 90.0}


def to_scene_m(p_dev_mm) -> np.ndarray:
    p = np.asarray(p_dev_mm, float)
    return np.stack([-p[..., 1], p[..., 0], p[..., 2] - 20.0], axis=-1) * 1e-3


def vec_to_scene_m(v_dev_mm) -> np.ndarray:
    v = np.asarray(v_dev_mm, float)
    return np.stack([-v[..., 1], v[..., 0], v[..., 2]], axis=-1) * 1e-3


def run_session(emulator, tmp_path, scenario: dict, env=None, **emu) -> dict:
    # A shared, loaded test machine may starve a thread for a while: only the tests of the
    # watchdog itself use its default 100 ms.
    scenario = {**scenario, "options": {"watchdog_s": 0.5, **scenario.get("options", {})}}
    tmp_path.mkdir(parents=True, exist_ok=True)
    (tmp_path / "scenario.json").write_text(json.dumps(scenario))
    out = tmp_path / "result.json"
    args = [tmp_path / "scenario.json", out]
    if env is not None:  # an environment without the emulator: a fresh interpreter
        proc = subprocess.run([sys.executable, str(RUN_SESSION), *map(str, args)], env=env, cwd=REPO,
                              capture_output=True, text=True, timeout=120)
    else:
        env = emulator_env(emulator.lib, **{"speed": FAST, **emu})
        env["OPENBLAS_NUM_THREADS"] = "1"  # (the fork server's; nothing here solves a least-squares fit)
        proc = emulator.sessions.run(args, env, script=RUN_SESSION, timeout=120)
    assert proc.returncode == 0, proc.stderr
    res = json.loads(out.read_text())
    res["stderr"] = proc.stderr
    after = res.get("emulator_after_run_servo")
    if after:
        res["log"] = np.array(after["log"]).reshape(-1, 8)
    return res


def frames(res) -> np.ndarray:
    log = res["log"]
    return log[log[:, 1] == FRAME]


def velocity_on_path(path, t):
    """The path's slope (mm/s) at time t, None within 2 ms after a knot (mixed differences)."""
    for (t0, *p0), (t1, *p1) in zip(path, path[1:]):
        if t0 + 2e-3 <= t <= t1:
            return (np.array(p1) - np.array(p0)) / (t1 - t0)
    return None


# A press that starts 10 mm inside the skin (scene z = -10 mm), goes 5 mm deeper, then withdraws
# through the surface and 20 mm beyond. It never stops moving, so the stall detector stays quiet.
PRESS = [(0.0, 1.0, 2.0, 10.0), (0.4, 1.0, 2.0, 5.0), (0.9, 1.0, 2.0, 40.0)]
K = 150.0  # N/m: 15 mm deep -> 2.25 N, above the 2 N limit below, so the clamp is exercised
LIMIT = 2.0


def test_press_forces_ramp_clamp_and_states(emulator, tmp_path):
    res = run_session(emulator, tmp_path, {"workspace": WS, "force_limit_n": LIMIT, "spring_k_n_per_m": K,
                                            "duration_s": 1.0}, path=PRESS, buttons=1)
    assert res["outcome"] == "returned", res["message"]
    assert res["pyOpenHaptics_imported_by_devices_omni"] is False  # imported lazily, in open()
    assert res["info"]["force_limit_n"] == LIMIT and res["info"]["drives_clock"] is True
    assert "hd_emulator" in res["info"]["model"]

    fr = frames(res)
    f, p = fr[:, 5:8], fr[:, 2:5]
    assert np.all(np.isfinite(f))
    assert np.all(np.linalg.norm(f, axis=1) <= LIMIT * (1 + 1e-12))
    assert res["emulator_after_run_servo"]["overforce"] == 0

    # One frame per step call, in order, then the closing zero-force frame(s).
    states = np.array(res["states"])
    n = len(states)
    assert len(fr) > n
    np.testing.assert_allclose(states[:, 1:4], to_scene_m(p[:n]), rtol=0, atol=1e-12)
    assert np.all(f[n:] == 0.0)

    # Spring along +z (device +z is scene +z under a turn about z), ramped in and clamped.
    depth = np.maximum(0.0, -to_scene_m(p[:n])[:, 2])
    assert np.all(f[:n, :2] == 0.0)
    assert f[0, 2] == 0.0  # nothing before (and at) the first valid state
    inside = depth > 0
    assert inside[0]  # the session starts with the tip in the tissue: the ramp matters
    assert np.all(f[1:n][inside[1:], 2] > 0.0) and np.all(f[:n][~inside, 2] == 0.0)
    j = np.arange(n)
    ramp = np.minimum(1.0, j / 200.0)  # linear over 200 ms at 1 kHz
    np.testing.assert_allclose(f[:n, 2], np.minimum(LIMIT, ramp * K * depth), rtol=1e-12, atol=1e-15)
    assert np.any(ramp * K * depth > LIMIT)  # the clamp did engage
    assert np.any(~inside)  # and the stylus did leave the skin

    # Velocity: the path's slope (mm/s) in the scene frame (m/s); buttons passed through. The path
    # is the emulator's: its slope at the emulator's time of that frame (a row's own stamp is the
    # device's tick count, which a late scheduler tick puts behind the emulator's clock).
    checked = 0
    for row, t_emu in zip(states, fr[:n, 0]):
        v = velocity_on_path(PRESS, t_emu)
        if v is not None:
            np.testing.assert_allclose(row[4:7], vec_to_scene_m(v), rtol=0, atol=1e-9)
            checked += 1
    assert checked > 0.8 * n
    assert np.all(states[:, 7] == 1)

    assert res["emulator_after_run_servo"]["output_force"] == [0.0, 0.0, 0.0]
    assert res["close_twice"] == "ok" and res["read_after"] == "ok"


def test_velocity_from_filtered_differences_when_the_device_gives_none(emulator, tmp_path):
    path = [(0.0, 0.0, 0.0, 30.0), (0.3, 6.0, -3.0, 30.0), (0.6, 6.0, -3.0, 36.0)]
    res = run_session(emulator, tmp_path, {"workspace": WS, "duration_s": 0.6}, path=path, velocity=False)
    assert res["outcome"] == "returned", res["message"]
    checked = 0
    for row in res["states"]:
        v = velocity_on_path(path, row[0])
        knot = max(t for t, *_ in path if t <= row[0])
        if v is not None and row[0] >= knot + 0.05:  # the 50 Hz low-pass has settled after 50 ms
            np.testing.assert_allclose(row[4:7], vec_to_scene_m(v), rtol=0, atol=1e-6 * np.abs(v).max() * 1e-3)
            checked += 1
    assert checked > 400


def test_force_is_rotated_into_the_device_frame_and_limited_by_the_device(emulator, tmp_path):
    # Scene +x is device -y under the 90 degree workspace turn; 5 N asked, device nominal max 2.5 N,
    # configured limit 3.3 N: the device's limit wins.
    path = [(0.0, 0.0, 0.0, 30.0), (0.5, 5.0, 0.0, 30.0)]
    res = run_session(emulator, tmp_path, {"workspace": WS, "force_limit_n": 3.3, "constant_n": [5.0, 0.0, 0.0],
                                            "duration_s": 0.5}, path=path, nominal_max_force=2.5)
    assert res["outcome"] == "returned", res["message"]
    assert res["info"]["force_limit_n"] == 2.5
    f = frames(res)[:, 5:8]
    n = len(res["states"])
    assert np.all(np.linalg.norm(f, axis=1) <= 2.5 * (1 + 1e-12))
    # exactly, in rational arithmetic on the commanded doubles (the clamp in
    # omniloop.guard_out is haptic_acu.servo.clamp's; the naive one let the rotation's 6e-17 through)
    from fractions import Fraction
    assert all(sum(Fraction(float(x)) ** 2 for x in row) <= Fraction(2.5) ** 2 for row in f[:n])
    assert res["emulator_after_run_servo"]["overforce"] == 0
    np.testing.assert_allclose(f[250:n], np.tile([0.0, -2.5, 0.0], (n - 250, 1)), rtol=0, atol=1e-12)
    assert np.all(f[:n, 1] <= 0.0) and np.all(np.abs(f[:n, [0, 2]]) < 1e-12)  # cos 90 deg rounds to 6e-17


def test_a_still_stylus_with_no_force_is_not_a_stall(emulator, tmp_path):
    res = run_session(emulator, tmp_path, {"workspace": WS, "spring_k_n_per_m": K, "duration_s": 0.5,
                                            "options": {"stall_s": 0.02}}, path=[(0.0, 0.0, 0.0, 30.0)])
    assert res["outcome"] == "returned", res["message"]
    assert len(res["states"]) >= 500


# Each fault strikes at 0.3 s, while the tip is 10-13 mm inside the tissue and moving.
FAULT_AT = 0.3
DEEP = [(0.0, 0.0, 0.0, 10.0), (3.0, 0.0, 0.0, 0.0)]
FAULTS = {
    "device_fault": "HD_DEVICE_FAULT",
    "comm_error": "HD_COMM_ERROR",
    "freeze": "frozen",
    "nan": "non-finite position",
    "stop_calling": "not called",
}


# Each fault but stop_calling is seen on the device's own ticks (device time, the virtual clock), with
# run_session's watchdog window; stop_calling is the 100 ms watchdog's, which counts wall time: a
# starved thread would be another fault, so that case runs alone on the machine.
@pytest.mark.parametrize("kind", [pytest.param(k, marks=pytest.mark.serial) if k == "stop_calling" else k
                                  for k in sorted(FAULTS)])
def test_fault_mid_session_zeroes_the_force_and_raises_device_fault(emulator, tmp_path, kind):
    # The force wobbles by 1 N at 5 Hz (falling from the fault on: 0.5 N less within 17 ms), so a
    # frozen position is one through a changing force: the force/position relation calls it a stall
    # once the stall window has passed.
    stall_s = 0.05
    options = {"stall_s": stall_s, **({"watchdog_s": 0.1} if kind == "stop_calling" else {})}
    res = run_session(emulator, tmp_path, {"workspace": WS, "force_limit_n": LIMIT, "spring_k_n_per_m": K,
                                            "wobble_n": 1.0, "duration_s": 3.0, "options": options},
                      path=DEEP, faults=[(kind, FAULT_AT)])
    assert res["outcome"] == "DeviceFault", (res["outcome"], res["message"])
    msg = res["message"]
    assert "\n" not in msg and FAULTS[kind] in msg
    assert res["run_servo_raises"] == 1

    log = res["log"]
    fr = frames(res)
    assert np.all(np.isfinite(fr[:, 5:8])) and res["emulator_after_run_servo"]["nonfinite"] == 0
    assert np.any(fr[fr[:, 0] < FAULT_AT, 7] > 0.5)  # it was pushing when the fault came
    # Promptly, counted in device ticks: the error/NaN tick itself, or the stall window.
    window = {"freeze": stall_s}.get(kind, 0.0)
    assert fr[-1, 0] <= FAULT_AT + window + 2e-3
    if kind == "stop_calling":
        # No frame can be sent any more; the output is switched off instead.
        assert np.any(log[log[:, 0] >= fr[-1, 0]][:, 1] == OUTPUT_DISABLED)
    else:
        assert np.all(fr[-1, 5:8] == 0.0)  # the last frame commanded zero force
    assert res["emulator_after_run_servo"]["output_force"] == [0.0, 0.0, 0.0]
    assert res["emulator_after_run_servo"]["scheduler_running"] is False
    states = np.array(res["states"])
    assert np.all(np.isfinite(states))  # the step never saw the NaN position
    assert res["read_after"].startswith("DeviceFault")
    assert res["close_twice"] == "ok"


def test_a_position_frozen_under_a_steady_force_is_a_still_hand_not_a_fault(emulator, tmp_path):
    # A trainee may hold perfectly still on the skin, every encoder bit-for-bit still under
    # a steady force, for as long as they like. The position freezes at 0.3 s (the spring's force then
    # steady, ~1.6 N) and stays frozen to the end, 1.5 s later: 30 stall windows, no fault.
    stall_s = 0.05
    res = run_session(emulator, tmp_path, {"workspace": WS, "force_limit_n": LIMIT, "spring_k_n_per_m": K,
                                            "duration_s": 1.8, "options": {"stall_s": stall_s}},
                      path=DEEP, faults=[("freeze", FAULT_AT)])
    assert res["outcome"] == "returned", res["message"]
    fr = frames(res)
    n = len(res["states"])
    frozen = fr[:n, 0] > FAULT_AT + 2e-3
    assert frozen.sum() > 1400 and np.all(fr[:n][frozen, 2:5] == fr[n - 1, 2:5])  # bit-identical
    assert np.all(np.abs(fr[:n][frozen, 7] - fr[n - 1, 7]) < 1e-12) and fr[n - 1, 7] > 1.0  # under a steady force
    assert res["emulator_after_run_servo"]["output_force"] == [0.0, 0.0, 0.0]


def test_the_stylus_orientation_is_the_state_s_axis_in_the_python_callback(emulator, tmp_path):
    # The emulator's stylus held 30 deg off the device's -z, toward device +x, then a transform with a
    # NaN rotation from 0.3 s: the state's axis (tip -> handle, scene frame) is the stylus direction
    # turned by the workspace (device +x is scene +y), then None (the engine falls back to travel).
    a = np.radians(30.0)
    d_dev = np.array([np.sin(a), 0.0, -np.cos(a)])  # handle -> tip
    res = run_session(emulator, tmp_path, {"workspace": WS, "duration_s": 0.5}, path=[(0.0, 0.0, 0.0, 30.0)],
                      stylus_axis=[(0.0, *d_dev)], faults=[("nan_orientation", 0.3)])
    assert res["outcome"] == "returned", res["message"]
    states = np.array(res["states"], dtype=float)
    fr = frames(res)
    t_emu = fr[:len(states), 0]
    before, after = t_emu < 0.3 - 1e-9, t_emu > 0.3 + 1e-9
    expected = -vec_to_scene_m(d_dev) * 1e3  # DeviceState.axis points from the tip to the handle
    np.testing.assert_allclose(states[before, 8:11], np.tile(expected, (before.sum(), 1)), rtol=0, atol=1e-12)
    assert before.sum() > 250 and after.sum() > 150 and np.all(np.isnan(states[after, 8:11]))


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs Linux CPU affinity and two usable cores")
def test_pin_servo_thread_pins_the_hd_scheduler_thread(emulator, tmp_path):
    # run --pin-cores: a synchronous call on the HD scheduler sets that thread's affinity before the
    # servo callback runs; the emulator reports its scheduler thread's kernel id, and /proc says
    # which cores that thread may run on.
    core = max(os.sched_getaffinity(0))
    res = run_session(emulator, tmp_path, {"workspace": WS, "duration_s": 0.2, "pin_cores": [core]},
                      path=[(0.0, 0.0, 0.0, 30.0)])
    assert res["outcome"] == "returned", res["message"]
    assert res["pinned"] is True
    th = res["sched_thread"]
    assert th["tid"] == th["step_tid"]  # the step runs on the emulator's scheduler thread
    assert th["cpus_allowed_list"] == str(core) and th["affinity"] == [core]
    plain = run_session(emulator, tmp_path / "plain", {"workspace": WS, "duration_s": 0.1},
                        path=[(0.0, 0.0, 0.0, 30.0)])
    assert plain["outcome"] == "returned" and "pinned" not in plain


def test_exception_in_step_zeroes_the_force_and_is_reraised_once(emulator, tmp_path):
    res = run_session(emulator, tmp_path, {"workspace": WS, "force_limit_n": LIMIT, "spring_k_n_per_m": K,
                                            "duration_s": 3.0, "raise_at_s": FAULT_AT}, path=DEEP)
    assert res["outcome"] == "StepBoom" and res["message"].startswith("boom at t=")
    assert res["run_servo_raises"] == 1 and res["step_calls_after_raise"] == 0
    fr = frames(res)
    assert fr[-2, 7] > 0.5 and np.all(fr[-1, 5:8] == 0.0)
    assert res["emulator_after_run_servo"]["output_force"] == [0.0, 0.0, 0.0]
    assert res["emulator_after_run_servo"]["scheduler_running"] is False
    assert res["close_twice"] == "ok"
    assert "Traceback" not in res["stderr"] and "Exception ignored" not in res["stderr"]


def test_non_finite_force_from_step_is_zeroed_and_a_fault(emulator, tmp_path):
    res = run_session(emulator, tmp_path, {"workspace": WS, "spring_k_n_per_m": K, "duration_s": 3.0,
                                            "nan_at_s": FAULT_AT}, path=DEEP)
    assert res["outcome"] == "DeviceFault" and "non-finite force" in res["message"]
    fr = frames(res)
    assert np.all(np.isfinite(fr[:, 5:8])) and np.all(fr[-1, 5:8] == 0.0)
    assert res["emulator_after_run_servo"]["nonfinite"] == 0


def test_init_errors_are_one_line_user_errors(emulator, tmp_path):
    res = run_session(emulator, tmp_path / "a", {"workspace": WS}, init_error=0x0302)
    assert res["outcome"] == "UserError" and "HD_COMM_ERROR" in res["message"] and "\n" not in res["message"]
    res = run_session(emulator, tmp_path / "b", {"workspace": WS, "device_name": "Left OMNI"})
    assert res["outcome"] == "UserError" and "'Left OMNI'" in res["message"] and "HD_" in res["message"]
    res = run_session(emulator, tmp_path / "c", {"workspace": WS, "device_name": "Left OMNI", "duration_s": 0.05},
                      device_name="Left OMNI", path=[(0.0, 0.0, 0.0, 30.0)])
    assert res["outcome"] == "returned"


def test_missing_libhd_is_a_one_line_user_error(tmp_path):
    env = emulator_env(tmp_path / "nowhere" / "libHD.so")
    probe = subprocess.run([sys.executable, "-c", "import ctypes; ctypes.CDLL('libHD.so')"], env=env,
                           capture_output=True)
    if probe.returncode == 0:
        pytest.skip("a libHD.so is installed on this machine's loader path")
    res = run_session(None, tmp_path, {"workspace": WS}, env=env)
    assert res["outcome"] == "UserError"
    msg = res["message"]
    assert "\n" not in msg and "libHD.so" in msg and "OpenHaptics" in msg and "LD_LIBRARY_PATH" in msg


@pytest.mark.parametrize("leave", ["idle", "servo"])
def test_exit_without_close_zeroes_and_disables_the_device(emulator, tmp_path, leave):
    # The HD scheduler thread must not call into a finalising interpreter: an atexit hook closes.
    log = tmp_path / "forces.csv"
    res = run_session(emulator, tmp_path, {"workspace": WS, "constant_n": [0.0, 0.0, 1.0], "read_before": True,
                                            "exit_without_close": leave}, path=[(0.0, 0.0, 0.0, 30.0), (5.0, 0.0, 0.0, 40.0)],
                      log=log)
    assert res["stderr"] == ""
    x, y, z = res["read_before"][1:]  # somewhere on the path: device z 30..40 mm is scene z 10..20 mm
    assert x == 0.0 and y == 0.0 and 0.010 <= z <= 0.020
    rows = np.loadtxt(log, delimiter=",", skiprows=1, ndmin=2)
    kinds = rows[:, 1].astype(int).tolist()
    assert kinds[-1] == 3 and OUTPUT_DISABLED in kinds  # device disabled last, output switched off
    fr = rows[rows[:, 1] == FRAME]
    if leave == "servo":
        assert np.any(fr[:, 7] > 0.5)  # the servo was pushing ...
    assert np.all(fr[-1, 5:8] == 0.0)  # ... and its last frame commanded zero


def test_bad_force_limit_is_a_user_error_before_any_library_is_loaded():
    from haptic_acu.devices.base import Workspace
    from haptic_acu.devices.omni import OmniDevice
    from haptic_acu.base.errors import UserError

    for bad in (float("nan"), 0.0, -1.0, float("inf")):
        with pytest.raises(UserError, match="force limit"):
            OmniDevice(Workspace(), bad)
    dev = OmniDevice(Workspace(), 2.0)
    assert dev.info.drives_clock and dev.info.force_limit_n == 2.0 and dev.info.rate_hz == 1000.0
    dev.close()  # closing a device that was never opened is a no-op


@pytest.mark.serial  # a step blocked 0.6 s on the wall against the 100 ms watchdog
def test_a_step_that_blocks_the_servo_is_a_fault_with_the_output_off(emulator, tmp_path):
    res = run_session(emulator, tmp_path, {"workspace": WS, "spring_k_n_per_m": K, "duration_s": 3.0,
                                            "sleep_at_s": FAULT_AT, "sleep_s": 0.6,
                                            "options": {"watchdog_s": 0.1}}, path=DEEP, speed=1)  # the wall's watchdog
    assert res["outcome"] == "DeviceFault" and "has not returned" in res["message"]
    assert "\n" not in res["message"]
    log = res["log"]
    assert OUTPUT_DISABLED in log[:, 1].tolist()
    assert res["emulator_after_run_servo"]["output_force"] == [0.0, 0.0, 0.0]
    assert res["close_twice"] == "ok"


@pytest.mark.skipif(not hasattr(os, "sched_getscheduler"), reason="needs Linux scheduling calls")
def test_the_emulators_scheduler_thread_runs_sched_fifo_when_asked(emulator, tmp_path):
    # The bench asks for it (a servo thread on a real-time setup); the step runs on that thread.
    path = [(0.0, 0.0, 0.0, 30.0)]
    plain = run_session(emulator, tmp_path / "plain", {"workspace": WS, "duration_s": 0.05}, path=path)
    assert plain["outcome"] == "returned" and plain["step_thread_policy"] == os.SCHED_OTHER
    fifo = run_session(emulator, tmp_path / "fifo", {"workspace": WS, "duration_s": 0.05}, path=path, sched_fifo=10)
    assert fifo["outcome"] == "returned"
    if "SCHED_FIFO priority 10 refused" in fifo["stderr"]:  # not permitted here: it says so, runs as before
        assert fifo["step_thread_policy"] == os.SCHED_OTHER
    else:
        assert fifo["step_thread_policy"] == os.SCHED_FIFO


def test_the_emulator_refuses_a_bad_sched_fifo_priority(emulator, tmp_path):
    env = emulator_env(emulator.lib, path=[(0.0, 0.0, 0.0, 30.0)])
    env["HD_EMU_SCHED_FIFO"] = "200"
    proc = subprocess.run([sys.executable, "-c", "import ctypes; ctypes.CDLL('libHD.so')"], env=env,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "bad HD_EMU_SCHED_FIFO" in proc.stderr

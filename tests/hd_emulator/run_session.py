"""Run one OmniDevice session against the HD emulator and write what happened as JSON.

Usage (in an environment from ``build.emulator_env``, so that ``libHD.so`` is the emulator)::

    python tests/hd_emulator/run_session.py SCENARIO.json RESULT.json

The scenario gives the workspace, the OmniDevice options and a stand-in for the physics:
``F = constant_n + k * max(0, -z) * (0, 0, 1)`` in the scene frame (a spring pushing the tip back
out of the half-space z < 0) plus ``wobble_n * sin(2 pi 5 t)`` along z, optionally raising
``StepBoom`` from ``raise_at_s``, returning a NaN force from ``nan_at_s`` or sleeping ``sleep_s``
once at ``sleep_at_s``. The session stops when the servo time reaches ``duration_s``. With
``pin_cores`` (a list), ``OmniDevice.pin_servo_thread`` is called before the servo runs, and the
step records the scheduler thread's kernel id (the emulator's) and its Cpus_allowed_list from
/proc/self/task/<tid>/status.

The result holds the outcome of run_servo, the scheduling policy of the thread the step ran on,
every state handed to the step, the emulator's force
log (``t_s, kind, x, y, z (mm, device frame), fx, fy, fz (N, device frame)``) and the force the
emulated motors output once run_servo had returned or raised.
"""
from __future__ import annotations

import ctypes
import json
import math
import os
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402

from haptic_acu.devices.base import Workspace  # noqa: E402
from haptic_acu.base.errors import DeviceFault, UserError  # noqa: E402


class StepBoom(RuntimeError):
    pass


def emulator_readback() -> dict:
    lib = ctypes.CDLL("libHD.so")  # already loaded (by pyOpenHaptics): the same library
    lib.emu_force_count.restype = ctypes.c_long
    lib.emu_get_forces.restype = ctypes.c_long
    lib.emu_get_forces.argtypes = [ctypes.POINTER(ctypes.c_double), ctypes.c_long]
    for name in ("emu_tick", "emu_overforce_count", "emu_nonfinite_force_count", "emu_callbacks_called"):
        getattr(lib, name).restype = ctypes.c_long
    n = lib.emu_force_count()
    buf = (ctypes.c_double * (8 * max(n, 1)))()
    n = lib.emu_get_forces(buf, n)
    log = np.frombuffer(buf, dtype=float, count=8 * n).reshape(n, 8)
    out = (ctypes.c_double * 3)()
    lib.emu_get_output_force(out)
    return {
        "log": log.tolist(),
        "output_force": list(out),
        "tick": lib.emu_tick(),
        "overforce": lib.emu_overforce_count(),
        "nonfinite": lib.emu_nonfinite_force_count(),
        "scheduler_running": bool(lib.emu_scheduler_running()),
    }


def main(scenario_path: str, result_path: str) -> int:
    sc = json.loads(Path(scenario_path).read_text())
    res: dict = {"outcome": None, "message": None, "states": [], "step_calls_after_raise": 0}

    from haptic_acu.devices.omni import OmniDevice  # noqa: PLC0415

    res["pyOpenHaptics_imported_by_devices_omni"] = "pyOpenHaptics" in sys.modules
    ws = Workspace(**sc.get("workspace", {}))
    dev = OmniDevice(ws, sc.get("force_limit_n"), sc.get("device_name", "Default Device"), **sc.get("options", {}))
    try:
        dev.open()
    except UserError as e:
        res["outcome"], res["message"] = "UserError", str(e)
        Path(result_path).write_text(json.dumps(res))
        return 0
    res["info"] = {"name": dev.info.name, "model": dev.info.model, "force_limit_n": dev.info.force_limit_n,
                   "rate_hz": dev.info.rate_hz, "drives_clock": dev.info.drives_clock}

    if sc.get("read_before"):  # before the servo runs: a synchronous read (one more frame)
        state0 = dev.read()
        res["read_before"] = [state0.t_s, *state0.position_m]
    k = float(sc.get("spring_k_n_per_m", 0.0))
    const = np.array(sc.get("constant_n", [0.0, 0.0, 0.0]), float)
    leave = sc.get("exit_without_close")  # "idle" or "servo": devices.omni's atexit hook must close
    if leave:
        if leave == "servo":
            def servo():
                try:
                    dev.run_servo(lambda state: const, threading.Event())
                except DeviceFault:  # "closed while running", when the atexit hook closes it
                    pass

            threading.Thread(target=servo, daemon=True).start()
            time.sleep(0.5)
        Path(result_path).write_text(json.dumps(res))
        return 0
    raise_at = sc.get("raise_at_s")
    nan_at = sc.get("nan_at_s")
    sleep_at, slept = sc.get("sleep_at_s"), [False]
    wobble = float(sc.get("wobble_n", 0.0))
    pin = sc.get("pin_cores")
    lib = ctypes.CDLL("libHD.so")
    lib.emu_scheduler_tid.restype = ctypes.c_long
    if pin is not None:
        res["pinned"] = dev.pin_servo_thread(set(pin))
    duration = float(sc.get("duration_s", 1.0))
    stop = threading.Event()
    raised = {"done": False}

    def step(state):
        if "step_thread_policy" not in res and hasattr(os, "sched_getscheduler"):
            res["step_thread_policy"] = os.sched_getscheduler(0)  # Linux: 0 is this thread (HD's scheduler)
        if raised["done"]:
            res["step_calls_after_raise"] += 1
        if "sched_thread" not in res and pin is not None:
            tid = int(lib.emu_scheduler_tid())
            status = Path(f"/proc/self/task/{tid}/status").read_text().splitlines()
            allowed = [ln.split(":", 1)[1].strip() for ln in status if ln.startswith("Cpus_allowed_list:")]
            res["sched_thread"] = {"tid": tid, "step_tid": threading.get_native_id(), "cpus_allowed_list": allowed[0],
                                   "affinity": sorted(os.sched_getaffinity(0))}
        ax = state.axis if state.axis is not None else np.full(3, math.nan)
        res["states"].append([state.t_s, *state.position_m, *state.velocity_m_s, state.buttons,
                              *map(float, ax), state.roll_rad])  # axis NaN: none (JSON's NaN)
        if state.t_s >= duration:
            stop.set()
        if raise_at is not None and state.t_s >= raise_at:
            raised["done"] = True
            raise StepBoom(f"boom at t={state.t_s:.3f} s")
        if sleep_at is not None and state.t_s >= sleep_at and not slept[0]:
            slept[0] = True
            time.sleep(float(sc["sleep_s"]))  # a step far too slow for the servo (a JIT compile, say)
        if nan_at is not None and state.t_s >= nan_at:
            return np.array([math.nan, 0.0, 0.0])
        return const + np.array([0.0, 0.0, k * max(0.0, -state.position_m[2])
                                 + wobble * math.sin(2.0 * math.pi * 5.0 * state.t_s)])

    t0 = time.monotonic()
    raises = 0
    try:
        dev.run_servo(step, stop)
        res["outcome"] = "returned"
    except DeviceFault as e:
        raises += 1
        res["outcome"], res["message"] = "DeviceFault", str(e)
    except StepBoom as e:
        raises += 1
        res["outcome"], res["message"] = "StepBoom", str(e)
    except Exception as e:  # anything else is reported, not hidden
        raises += 1
        res["outcome"], res["message"] = type(e).__name__, str(e)
    res["run_servo_wall_s"] = time.monotonic() - t0
    res["run_servo_raises"] = raises
    res["emulator_after_run_servo"] = emulator_readback()
    try:
        dev.read()
        res["read_after"] = "ok"
    except DeviceFault as e:
        res["read_after"] = f"DeviceFault: {e}"
    try:
        dev.close()
        dev.close()
        res["close_twice"] = "ok"
    except Exception as e:  # noqa: BLE001 - reported to the test
        res["close_twice"] = f"{type(e).__name__}: {e}"
    res["emulator_after_close"] = emulator_readback()
    Path(result_path).write_text(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(*sys.argv[1:3]))

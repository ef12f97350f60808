"""Drive the HD emulator through the raw HD API with a naive virtual wall (no coupling), for tests.

Usage (in an environment from ``build.emulator_env`` with the physical stylus mode on)::

    python tests/hd_emulator/run_wall.py SCENARIO.json RESULT.json

Each servo tick the callback reads HD_CURRENT_POSITION (mm, quantised by the emulated encoder) and
commands, along z only, ``F = -K (z - z_wall)`` where ``z > z_wall`` ("wall": a unilateral wall the
hand pushes up into) or everywhere ("spring": a bilateral virtual spring), K in N/mm. That is the
naive sampled-data rendering Colgate & Schenkel analysed: the force computed from the position at
tick n is held over the next tick. It also reads the HD_NOMINAL_MAX_* values and the gimbal angles.
The result holds them, the per-tick positions the callback saw, and the emulator's physics trace.
"""
from __future__ import annotations

import ctypes
import json
import sys
import threading
from pathlib import Path

HD_CURRENT_POSITION = 0x2050
HD_CURRENT_VELOCITY = 0x2051
HD_CURRENT_GIMBAL_ANGLES = 0x2150
HD_NOMINAL_MAX_STIFFNESS = 0x2602
HD_NOMINAL_MAX_FORCE = 0x2603
HD_NOMINAL_MAX_CONTINUOUS_FORCE = 0x2604
HD_NOMINAL_MAX_DAMPING = 0x2609
HD_CURRENT_FORCE = 0x2700
HD_FORCE_OUTPUT = 0x4000
HD_CALLBACK_DONE, HD_CALLBACK_CONTINUE = 0, 1
TRACE_FIELDS = 19


def main(scenario_path: str, result_path: str) -> int:
    sc = json.loads(Path(scenario_path).read_text())
    lib = ctypes.CDLL("libHD.so")
    lib.hdInitDevice.restype = ctypes.c_uint
    lib.hdInitDevice.argtypes = [ctypes.c_char_p]
    lib.hdScheduleAsynchronous.restype = ctypes.c_ulong
    lib.emu_get_trace.restype = ctypes.c_long
    lib.emu_get_trace.argtypes = [ctypes.POINTER(ctypes.c_double), ctypes.c_long]
    lib.emu_trace_count.restype = ctypes.c_long
    lib.emu_tick.restype = ctypes.c_long
    h = lib.hdInitDevice(None)
    nominal = {}
    for name, what in (("stiffness", HD_NOMINAL_MAX_STIFFNESS), ("damping", HD_NOMINAL_MAX_DAMPING),
                       ("force", HD_NOMINAL_MAX_FORCE), ("continuous_force", HD_NOMINAL_MAX_CONTINUOUS_FORCE)):
        v = ctypes.c_double()
        lib.hdGetDoublev(what, ctypes.byref(v))
        nominal[name] = v.value
    lib.hdEnable(HD_FORCE_OUTPUT)

    k = float(sc.get("k_n_per_mm", 0.0))
    z_wall = float(sc.get("z_wall_mm", 0.0))
    bilateral = sc.get("kind", "wall") == "spring"
    ticks = int(sc.get("ticks", 1000))
    seen = []
    done = threading.Event()
    pos = (ctypes.c_double * 3)()
    vel = (ctypes.c_double * 3)()
    gim = (ctypes.c_double * 3)()
    force = (ctypes.c_double * 3)()

    @ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_void_p)
    def servo(_data):
        lib.hdBeginFrame(h)
        lib.hdGetDoublev(HD_CURRENT_POSITION, pos)
        lib.hdGetDoublev(HD_CURRENT_VELOCITY, vel)
        lib.hdGetDoublev(HD_CURRENT_GIMBAL_ANGLES, gim)
        pen = pos[2] - z_wall
        fz = -k * pen if (bilateral or pen > 0.0) else 0.0
        force[0], force[1], force[2] = 0.0, 0.0, fz
        lib.hdSetDoublev(HD_CURRENT_FORCE, force)
        lib.hdEndFrame(h)
        seen.append([lib.emu_tick() * 1e-3, *pos, *vel, *gim, fz])
        if len(seen) >= ticks:
            done.set()
            return HD_CALLBACK_DONE
        return HD_CALLBACK_CONTINUE

    lib.hdStartScheduler()
    lib.hdScheduleAsynchronous(servo, None, 0xFFFF)
    done.wait(timeout=float(sc.get("timeout_s", 120.0)))
    lib.hdStopScheduler()
    n = lib.emu_trace_count()
    buf = (ctypes.c_double * (TRACE_FIELDS * max(n, 1)))()
    n = lib.emu_get_trace(buf, n)
    lib.hdDisableDevice(h)
    res = {"nominal": nominal, "seen": seen, "trace": [list(buf[i * TRACE_FIELDS:(i + 1) * TRACE_FIELDS]) for i in range(n)]}
    Path(result_path).write_text(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(*sys.argv[1:3]))

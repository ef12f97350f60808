"""Build the HD API emulator (``hd_emulator.c``) into a ``libHD.so`` and run programs against it.

``build_emulator(out_dir)`` compiles the library with the system C compiler and returns its path;
``emulator_env(lib_path, ...)`` returns an environment in which ``CDLL("libHD.so")`` (what
pyOpenHaptics does at import) loads the emulator, configured through the ``HD_EMU_*`` variables
documented at the top of ``hd_emulator.c``. Programs run with that environment - a test driver or
``haptic-acu`` itself - see an emulated PHANTOM instead of OpenHaptics.
"""
from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

SOURCE = Path(__file__).resolve().parent / "hd_emulator.c"

# Fault kinds understood by HD_EMU_FAULTS (and their emu_inject_fault codes).
FAULT_CODES = {"device_fault": 0x0300, "comm_error": 0x0302, "freeze": -1, "nan": -2, "stop_calling": -3, "late": -4,
               "nan_orientation": -5}


class EmulatorBuildError(RuntimeError):
    """No C compiler, or the compiler rejected the source."""


def find_compiler() -> str | None:
    """The C compiler to use: $CC, else cc, gcc or clang on PATH; None if there is none."""
    for cand in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if cand and shutil.which(cand):
            return shutil.which(cand)
    return None


def build_emulator(out_dir) -> Path:
    """Compile the emulator to ``out_dir/libHD.so`` (soname libHD.so) and return that path."""
    cc = find_compiler()
    if cc is None:
        raise EmulatorBuildError("no C compiler (set CC, or install cc/gcc/clang)")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    out = out_dir / "libHD.so"
    cmd = [cc, "-shared", "-fPIC", "-O2", "-pthread", "-Wall", "-Wl,-soname,libHD.so",
           "-o", str(out), str(SOURCE), "-lm"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise EmulatorBuildError(f"{' '.join(cmd)} failed: {proc.stderr.strip()}")
    return out


def _path_spec(path) -> str:
    return ";".join(",".join(repr(float(v)) for v in knot) for knot in path)


# Physical stylus mode (hd_emulator.c): the keys of ``stylus=`` and their HD_EMU_* variables.
STYLUS_VARS = {"mass_g": "HD_EMU_STYLUS_MASS_G", "hand_stiffness_n_per_mm": "HD_EMU_HAND_STIFFNESS",
               "hand_damping_n_s_per_m": "HD_EMU_HAND_DAMPING", "device_damping_n_s_per_m": "HD_EMU_DEVICE_DAMPING",
               "encoder_step_mm": "HD_EMU_ENCODER_STEP_MM", "velocity_cutoff_hz": "HD_EMU_VELOCITY_CUTOFF_HZ",
               "hand_tremor": "HD_EMU_HAND_TREMOR"}
NOMINAL_VARS = {"stiffness_n_per_mm": "HD_EMU_NOMINAL_MAX_STIFFNESS", "damping_n_per_mm_s": "HD_EMU_NOMINAL_MAX_DAMPING",
                "continuous_force_n": "HD_EMU_NOMINAL_MAX_CONTINUOUS_FORCE"}
# The grips: a 45 g stylus held loosely (0.3 N/mm) or firmly (2 N/mm).
LOOSE_GRIP = {"mass_g": 45.0, "hand_stiffness_n_per_mm": 0.3, "hand_damping_n_s_per_m": 2.0}
FIRM_GRIP = {"mass_g": 45.0, "hand_stiffness_n_per_mm": 2.0, "hand_damping_n_s_per_m": 5.0}
# The pace of a session that needs device time only (a simulated hand on the simulated device): a
# session through the CLI drains its sample ring (8192 rows) at the visual rate on the wall, so it gets
# a bounded multiple, not "max" (a raw HD API driver, with no ring, can take "max"). A session of up to
# 8 s of device time (RING_ROWS ticks) cannot lose a row at any pace: FAST. A longer one loses rows if
# its visual thread is starved for RING_ROWS / pace ms of wall: at 8, a cold kernel cache on a host at
# load 9 lost 2226 rows of a 12.5 s session (a second of slack was not enough), so such sessions take
# FAST_LONG (two seconds of slack). The forces are the same at any pace (the closed-loop sessions' buzz
# and punctures agree to the printed digits at 4 and 8).
FAST = 8.0
FAST_LONG = 4.0
RING_ROWS = 8192  # haptic_acu.session.engine's sample ring for a session at the device's own pace


def pace(duration_s: float) -> float:
    """The pace of a CLI session of ``duration_s`` seconds of device time (see FAST)."""
    return FAST if duration_s * 1e3 <= RING_ROWS else FAST_LONG
TRACE_COLUMNS = ("t_s", "hand_x_mm", "hand_y_mm", "hand_z_mm", "hand_vx_mm_s", "hand_vy_mm_s", "hand_vz_mm_s",
                 "x_mm", "y_mm", "z_mm", "vx_mm_s", "vy_mm_s", "vz_mm_s", "motor_fx_n", "motor_fy_n", "motor_fz_n",
                 "hand_fx_n", "hand_fy_n", "hand_fz_n")


def emulator_env(lib_path, *, path=None, faults=(), nominal_max_force=None, velocity=True,
                 init_error=None, buttons=None, device_name=None, log=None, sched_fifo=None, base=None,
                 stylus=None, nominal=None, gimbal=None, trace=None, stylus_axis=None, speed=None) -> dict:
    """An environment whose dynamic loader finds the emulator as ``libHD.so``.

    ``path``: knots ``(t_s, x_mm, y_mm, z_mm)`` of the stylus path in the device frame;
    ``faults``: ``(kind, at_s)`` pairs, kind one of :data:`FAULT_CODES`; ``velocity=False`` makes
    HD_CURRENT_VELOCITY unsupported; ``init_error``: an HD error code hdInitDevice fails with;
    ``log``: a CSV file the force log is written to when the device is disabled and at exit;
    ``sched_fifo``: a priority the scheduler thread asks SCHED_FIFO for (refused: a line on stderr).
    ``stylus``: the physical stylus mode, a dict with keys of :data:`STYLUS_VARS` (``mass_g`` needed;
    e.g. :data:`LOOSE_GRIP`): ``path`` is then the hand's path; ``nominal``: keys of
    :data:`NOMINAL_VARS` (HD_NOMINAL_MAX_*); ``gimbal``: knots ``(t_s, a, b, c)`` of the gimbal angles
    (rad, c the stylus roll); ``trace``: a CSV file of the stylus physics per tick (:data:`TRACE_COLUMNS`);
    ``stylus_axis``: knots ``(t_s, x, y, z)`` of the stylus direction, handle to tip (device frame), that
    HD_CURRENT_TRANSFORM's rotation reports (turned about the stylus by the gimbal's roll).
    ``speed``: the emulated clock's pace, device ms per wall ms (``"max"``: ticks back to back); the
    ticks, path, faults and physics are the same at any pace, so a test that needs only device time
    (:data:`FAST`) runs in a fraction of it; None or 1 is the real device's pace (tests about timing).
    """
    env = dict(os.environ if base is None else base)
    for key in [k for k in env if k.startswith("HD_EMU_")]:
        del env[key]
    lib_dir = str(Path(lib_path).resolve().parent)
    old = env.get("LD_LIBRARY_PATH")
    env["LD_LIBRARY_PATH"] = lib_dir + (os.pathsep + old if old else "")
    if path is not None:
        env["HD_EMU_PATH"] = _path_spec(path)
    if faults:
        for kind, _ in faults:
            if kind not in FAULT_CODES:
                raise ValueError(f"unknown emulator fault {kind!r}; one of {sorted(FAULT_CODES)}")
        env["HD_EMU_FAULTS"] = ",".join(f"{kind}@{float(at)!r}" for kind, at in faults)
    if nominal_max_force is not None:
        env["HD_EMU_NOMINAL_MAX_FORCE"] = repr(float(nominal_max_force))
    if not velocity:
        env["HD_EMU_NO_VELOCITY"] = "1"
    if init_error is not None:
        env["HD_EMU_INIT_ERROR"] = hex(int(init_error))
    if buttons is not None:
        env["HD_EMU_BUTTONS"] = str(int(buttons))
    if device_name is not None:
        env["HD_EMU_DEVICE_NAME"] = device_name
    if log is not None:
        env["HD_EMU_LOG"] = str(log)
    if sched_fifo is not None:
        env["HD_EMU_SCHED_FIFO"] = str(int(sched_fifo))
    for given, table in ((stylus, STYLUS_VARS), (nominal, NOMINAL_VARS)):
        for key, value in (given or {}).items():
            if key not in table:
                raise ValueError(f"unknown emulator option {key!r}; one of {sorted(table)}")
            if key == "hand_tremor":  # (amplitude_mm, frequency_hz)
                env[table[key]] = ",".join(repr(float(x)) for x in value)
            else:
                env[table[key]] = repr(float(value))
    if gimbal is not None:
        env["HD_EMU_GIMBAL"] = _path_spec(gimbal)
    if trace is not None:
        env["HD_EMU_TRACE"] = str(trace)
    if stylus_axis is not None:
        env["HD_EMU_STYLUS_AXIS"] = _path_spec(stylus_axis)
    if speed is not None:
        env["HD_EMU_SPEED"] = "max" if speed == "max" else repr(float(speed))
    return env


if __name__ == "__main__":  # python tests/hd_emulator/build.py OUT_DIR
    import sys

    print(build_emulator(sys.argv[1] if len(sys.argv) > 1 else "."))

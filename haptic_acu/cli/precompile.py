"""Compile and cache everything a first session needs, ahead of time: ``python -m haptic_acu.cli.precompile``.

numba compiles the simulator's kernels on first use (tens of seconds) and caches them next to the
installed sources; the force-net response tables are solved once per parameter set and cached in
``HAPTIC_ACU_CACHE``. ``make`` runs this module right after installing, so the first ``make demo``
loads everything from the caches. It replays the bundled default insertion headless into a temporary
folder (the servo step, springback, the rerun dents, the CSV formatter, the tissue fit and tables)
and warms the real-time servo loop of ``haptic-acu run`` (compiled, never started) and the servo
tick's C entry point the Python drivers call. Nothing is left
behind but the caches. After a plain ``pip install`` the first command does the same work.
"""
from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path


def main() -> int:
    from ..base import progress
    from ..base.config import load_config
    from ..session.engine import Session
    from ..session.replay import DEFAULT_TRAJECTORY, replay_one

    progress.watch_compiles()
    t0 = time.perf_counter()
    cfg = load_config()
    with tempfile.TemporaryDirectory(prefix="haptic-acu-precompile-") as tmp:
        with progress.step("replaying the default insertion once to fill the caches", after_s=0):
            replay_one(DEFAULT_TRAJECTORY, Path(tmp) / "demo", cfg=cfg, progress=False)
    from haptic_acu.devices.scripted import ScriptedDevice
    with progress.step("compiling the real-time servo loop", after_s=0):
        dev = ScriptedDevice(DEFAULT_TRAJECTORY, cfg.scene.max_hand_speed_m_per_s, realtime=True,
                             force_limit_n=cfg.safety.force_limit_n)
        Session(cfg, dev, [], clock="realtime").warm_up()
        from ..servo.tick import tick_entry

        tick_entry()  # the servo tick of the Python drivers (keyboard, the OMNI's Python callback)
    print(f"haptic-acu: caches ready in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""``python -m bench.cold_start_child ARGS``: run ``haptic-acu ARGS`` in this process and print, on
stderr, ``FIRST_TICK_DONE <unix time>`` when the scripted device receives its first force command
(which follows the first servo ticks). Used by :func:`bench.run.cold_start` to time process start
to first tick from outside the project's code: the command itself is unchanged, only the scripted
device's ``set_force`` is wrapped, in this process alone.
"""
from __future__ import annotations

import sys
import time

from haptic_acu.devices.scripted import ScriptedDevice

_set_force = ScriptedDevice.set_force
_reported = []


def _timed_set_force(self, force_n):
    if not _reported:
        _reported.append(time.time())
        print(f"FIRST_TICK_DONE {_reported[0]:.6f}", file=sys.stderr, flush=True)
    return _set_force(self, force_n)


ScriptedDevice.set_force = _timed_set_force

if __name__ == "__main__":
    from haptic_acu.cli import main

    raise SystemExit(main(sys.argv[1:]))

#!/usr/bin/env python3
"""Replay every bundled trajectory with two builds of haptic-acu and compare their outputs byte for byte.

    tools/compare_replays.py --base /path/to/other/checkout/.venv/bin/haptic-acu [--keep DIR]
    tools/compare_replays.py --ref DIR   # compare against outputs already made (DIR/<name>/...)

The build under test is this checkout's ``.venv/bin/haptic-acu``. For each ``trajectories/*.csv``
both builds run ``replay --no-rrd`` into their own folder; ``samples.csv`` and ``summary.json`` must be
identical. Exit status 0 when every pair matches, 1 otherwise (the differing files are named).
"""
from __future__ import annotations

import argparse
import filecmp
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FILES = ("samples.csv", "summary.json")


def replay(exe: str, traj: Path, out: Path) -> None:
    subprocess.run([exe, "replay", str(traj), "--out", str(out), "--no-rrd", "--quiet", "--jobs", "1"],
                   check=True, stdout=subprocess.DEVNULL)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--base", help="the other build's haptic-acu executable")
    g.add_argument("--ref", type=Path, help="a folder of earlier outputs, one subfolder per trajectory")
    ap.add_argument("--exe", default=str(ROOT / ".venv" / "bin" / "haptic-acu"), help="the build under test")
    ap.add_argument("--keep", type=Path, help="write the outputs here instead of a temporary folder")
    a = ap.parse_args(argv)
    work = a.keep or Path(tempfile.mkdtemp(prefix="compare_replays_"))
    bad = 0
    for traj in sorted((ROOT / "trajectories").glob("*.csv")):
        name = traj.stem
        new = work / "new" / name
        replay(a.exe, traj, new)
        if a.base:
            ref = work / "base" / name
            replay(a.base, traj, ref)
        else:
            ref = a.ref / name
        for f in FILES:
            same = (ref / f).exists() and filecmp.cmp(ref / f, new / f, shallow=False)
            print(f"{'same' if same else 'DIFFERENT'}  {name}/{f}")
            bad += not same
    print(f"{bad} file(s) differ" if bad else "all identical")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())

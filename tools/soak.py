"""A live session's memory over a long run: ``haptic-acu run --device scripted`` with ``--record`` and
``--rrd`` on the default insertion repeated for ``--minutes``, the resident memory of the session and
of its rerun logging child sampled every ``--every`` seconds from /proc.

    python tools/soak.py --minutes 10 [--every 10] [--out DIR] [--pin-cores] [--floor]

The session records (``<out>/session/recording.csv``) and logs to rerun (``session.rrd``) as a live
trainee's session does; its own loop line (ticks, missed ticks, period error) is printed at the end
beside the host's hypervisor steal over the run (/proc/stat), so the same run is the 10-minute
zero-missed-tick measurement (``--pin-cores``: servo thread and logging child apart).
``--floor`` then runs the compiled loop's floor for as long (``bench.measure.compiled_floor``: the
same timing rule with no work, pinned alone on the servo's core): what the machine itself misses.

Prints one line per sample (elapsed s, main MB, child MB) and a closing line with each process's
first and last figure and its growth per minute over the second half of the run (the first minutes
include numba's and the SDK's warm-up). Linux only (/proc).
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def rss_mb(pid: int) -> float | None:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def children(pid: int) -> list[int]:
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as f:
            return [int(c) for c in f.read().split()]
    except OSError:
        return []


def tiled(src: Path, minutes: float, out: Path) -> None:
    """``src`` repeated end to end (it starts and ends at the same point) for at least ``minutes``."""
    lines = src.read_text().splitlines()
    header, rows = lines[0], [ln.split(",") for ln in lines[1:] if ln and not ln.startswith("#")]
    span = float(rows[-1][0]) + 0.005
    with open(out, "w") as f:
        f.write(header + "\n")
        k = 0
        while k * span < minutes * 60.0:
            for r in rows:
                f.write(f"{float(r[0]) + k * span:.6f}," + ",".join(r[1:]) + "\n")
            k += 1


def steal_jiffies() -> tuple[int, int]:
    """(steal, total) jiffies of all CPUs so far (/proc/stat's first line)."""
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    return v[7], sum(v)


def growth_per_min(samples: list[tuple[float, float]]) -> float:
    half = [s for s in samples if s[0] >= samples[-1][0] / 2]
    if len(half) < 2 or half[-1][0] == half[0][0]:
        return float("nan")
    return (half[-1][1] - half[0][1]) / (half[-1][0] - half[0][0]) * 60.0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--every", type=float, default=10.0)
    ap.add_argument("--out", help="folder for the session's files (default: a temporary one)")
    ap.add_argument("--pin-cores", action="store_true", help="pass --pin-cores to the session")
    ap.add_argument("--floor", action="store_true",
                    help="then run the compiled loop's timing with no work, pinned, for as long")
    args = ap.parse_args()
    work = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="haptic-acu-soak-"))
    work.mkdir(parents=True, exist_ok=True)
    traj = work / "soak.csv"
    tiled(ROOT / "trajectories" / "default.csv", args.minutes, traj)
    cmd = [sys.executable, "-m", "haptic_acu", "run", "--verbose", "--device", "scripted", "--trajectory", str(traj),
           "--duration", str(args.minutes * 60.0), "--no-status", "--out", str(work / "session"),
           "--rrd", str(work / "session.rrd")] + (["--pin-cores"] if args.pin_cores else [])
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    t0 = time.monotonic()
    st0 = steal_jiffies()
    main_s, child_s = [], []
    try:
        while proc.poll() is None:
            time.sleep(args.every)
            t = time.monotonic() - t0
            m = rss_mb(proc.pid)
            kids = [c for c in children(proc.pid) if rss_mb(c) is not None]
            c = max((rss_mb(k) or 0.0 for k in kids), default=None)
            if m is not None:
                main_s.append((t, m))
            if c is not None:
                child_s.append((t, c))
            print(f"{t:7.1f} s  main {m if m is not None else float('nan'):7.1f} MB  "
                  f"child {c if c is not None else float('nan'):7.1f} MB", flush=True)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, 15)
        out, err = proc.communicate(timeout=60)
    st1 = steal_jiffies()
    print(err.strip().splitlines()[0] if err.strip() else "", file=sys.stderr)
    summary = work / "session" / "summary.json"
    if summary.is_file():
        import json

        loop = json.loads(summary.read_text()).get("loop", {})
        pe = loop.get("period_error_us", {})
        print(f"session: {loop.get('missed_ticks')} missed ticks; period error p50 {pe.get('p50')} us, "
              f"p99 {pe.get('p99')} us, p99.9 {pe.get('p999')} us, max {pe.get('max')} us")
    for line in out.splitlines():
        if "tick" in line or "missed" in line:
            print("session: " + line.strip())
    print(f"host: hypervisor steal {100.0 * (st1[0] - st0[0]) / max(1, st1[1] - st0[1]):.2f}% of CPU time over the run")
    for name, s in (("main", main_s), ("child", child_s)):
        if s:
            print(f"{name}: {s[0][1]:.1f} MB at {s[0][0]:.0f} s -> {s[-1][1]:.1f} MB at {s[-1][0]:.0f} s; "
                  f"second half {growth_per_min(s):+.2f} MB/min")
    if args.floor:
        floor(args.minutes * 60.0)
    return proc.returncode


def floor(seconds: float) -> None:
    """The compiled loop's floor for ``seconds``, printed like the session's loop line."""
    from haptic_acu.bench import measure

    st0 = steal_jiffies()
    r = measure.compiled_floor(seconds)
    st1 = steal_jiffies()
    pe = r["period_error_us"]
    print(f"floor: {r['missed_ticks']} missed of {r['ticks']} ticks ({r['skipped_ticks']} skipped); period error "
          f"p50 {pe['p50']:.1f} us, p99 {pe['p99']:.1f} us, p99.9 {pe['p999']:.1f} us, max {pe['max']:.0f} us; "
          f"pinned {r['pinned']}, SCHED_FIFO {r['sched_fifo']}")
    print(f"host: hypervisor steal {100.0 * (st1[0] - st0[0]) / max(1, st1[1] - st0[1]):.2f}% of CPU time over the floor")


if __name__ == "__main__":
    sys.exit(main())

"""Screenshots of the bundled viewer layouts at the moments a trainee cares about, as rerun's web
viewer draws them in headless Chromium (software WebGL: about a minute a picture).

    python tools/screenshots.py [--out docs/img] [--only NAME ...] [--wait 60] [--size 1600x1000]
                                [--screenshot PATH/TO/rrd-screenshot]

A viewer opened on a recording shows its latest moment, so each picture replays a trajectory cut
at its moment (the first rows of a bundled trajectory up to that time) into a recording with the
layout, and photographs it with the shared ``rrd-screenshot`` tool (Debian's chromium, the rerun
binary of this environment). The moments are found from a full replay of the trajectory (its
samples.csv), not hard-coded: the skin pressed in deepest just before it gives way, the tip 6 mm
into fat, 12 and 24 mm deep, 3 mm past the target, half-way through the twirling.

Writes OUT/viewer-<layout>-<moment>.png and prints each path.
"""
from __future__ import annotations

import argparse
import csv
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCREENSHOT = Path(os.environ.get("RRD_SCREENSHOT", ROOT.parent.parent / "shared" / "tools" / "rrd-screenshot"))


def _replay(traj: Path, out: Path, layout: str) -> None:
    from haptic_acu.cli import main

    status = main(["replay", str(traj), "--out", str(out), "--layout", layout, "--quiet"])
    if status not in (0, None):
        raise SystemExit(f"screenshots: replay of {traj} failed ({status})")


def _samples(out: Path) -> dict:
    with open(out / "samples.csv") as f:
        rows = [r for r in csv.reader(ln for ln in f if not ln.startswith("#"))]
    head, body = rows[0], rows[1:]
    cols = {}
    for j, name in enumerate(head):
        vals = [r[j] for r in body]
        try:
            cols[name] = np.array(vals, dtype=float)
        except ValueError:
            cols[name] = np.array(vals)
    return cols


def _cut(traj: Path, t_end: float, dest: Path) -> Path:
    """The trajectory's rows up to ``t_end`` (s), then one row at ``t_end`` interpolated."""
    with open(traj) as f:
        lines = f.read().splitlines()
    head, body = lines[0], [ln.split(",") for ln in lines[1:] if ln.strip()]
    keep = [r for r in body if float(r[0]) <= t_end]
    nxt = next((r for r in body if float(r[0]) > t_end), None)
    if nxt is not None and keep and float(keep[-1][0]) < t_end:
        a, b = keep[-1], nxt
        w = (t_end - float(a[0])) / (float(b[0]) - float(a[0]))
        keep.append([f"{t_end:.6f}"] + [f"{float(x) + w * (float(y) - float(x)):.4f}" for x, y in zip(a[1:], b[1:])])
    dest.write_text("\n".join([head] + [",".join(r) for r in keep]) + "\n")
    return dest


def _past_target(dest: Path, depth_mm: float) -> Path:
    """A straight insertion at the acupoint (10 mm/s, 200 Hz) from 5 mm above to ``depth_mm``."""
    t, rows = 0.0, []
    z = 5.0
    rows.append((0.0, z))
    while z > -depth_mm:
        t += 0.005
        z = max(5.0 - 10.0 * (t - 0.5), -depth_mm) if t > 0.5 else 5.0
        rows.append((t, z))
    dest.write_text("t_s,x_mm,y_mm,z_mm\n" + "".join(f"{a:.6f},0.0000,0.0000,{b:.4f}\n" for a, b in rows))
    return dest


def moments(work: Path) -> list[tuple[str, str, Path, float]]:
    """(name, layout, trajectory, cut time s) of every picture."""
    from haptic_acu.base.bundled import resolve_trajectory

    default = resolve_trajectory("default")
    full = work / "full-default"
    _replay(default, full, "trainee")
    s = _samples(full)
    t, depth = s["t_s"], s["depth_skin_mm"]
    skin = s["state_skin"]
    pressed = np.nonzero(skin == "punctured")[0][0] - 1  # the last tick before the skin gives way
    six_in_fat = int(np.argmax(depth >= 6.0))
    deep12 = int(np.argmax(depth >= 12.0))
    deep24 = int(np.argmax(depth >= 24.0))
    past = _past_target(work / "past_target.csv", 33.2)
    twirl = resolve_trajectory("twirl_even")
    with open(twirl) as f:
        tw = np.array([[float(x) for x in ln.split(",")] for ln in f.read().splitlines()[1:] if ln.strip()])
    turned = np.nonzero(np.abs(tw[:, 4]) >= 150.0)[0]  # near the ends of the turns
    mid_twirl = tw[turned[len(turned) // 2], 0]
    return [
        ("skin-pressed", "trainee", default, float(t[pressed])),
        ("fat-6mm", "trainee", default, float(t[six_in_fat])),
        ("muscle-12mm", "trainee", default, float(t[deep12])),
        ("muscle-24mm", "trainee", default, float(t[deep24])),
        ("past-target", "trainee", past, 1e9),
        ("mid-twirl", "trainee", twirl, float(mid_twirl)),
        ("after-session", "instructor", default, 1e9),
    ]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "img"))
    ap.add_argument("--only", nargs="*", help="moment names (default: all)")
    ap.add_argument("--wait", type=float, default=90.0, help="seconds the viewer gets before each picture")
    ap.add_argument("--size", default="1600x1000")
    ap.add_argument("--screenshot", default=str(SCREENSHOT), help="the rrd-screenshot script")
    args = ap.parse_args(argv)
    if not Path(args.screenshot).is_file():
        print(f"screenshots: {args.screenshot}: no rrd-screenshot script (--screenshot PATH)", file=sys.stderr)
        return 2
    rerun = Path(sys.executable).with_name("rerun")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="haptic-acu-shots-") as tmp:
        work = Path(tmp)
        for name, layout, traj, t_end in moments(work):
            if args.only and name not in args.only:
                continue
            cut = _cut(Path(traj), t_end, work / f"{name}.csv")
            rec = work / name
            _replay(cut, rec, layout)
            png = out / f"viewer-{layout}-{name}.png"
            subprocess.run(["bash", args.screenshot, str(rec / "recording.rrd"), str(png), "--wait", str(args.wait),
                            "--size", args.size, "--rerun", str(rerun)], check=True, cwd=ROOT)
            shutil.rmtree(rec, ignore_errors=True)
            print(png)
    return 0


if __name__ == "__main__":
    sys.exit(main())

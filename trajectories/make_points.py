"""Generate the bundled trajectories of the atlas's points (deterministic: same bytes on every run).

    python trajectories/make_points.py [--out DIR]      (default: trajectories/points/)

Each point's scene frame is its atlas frame (config/points/<CODE>.toml, docs/atlas.md): the point at
the origin on the skin, z out of the skin. A correct insertion and a dangerous one for GB21, PC6 and
ST36, made like the other bundled files (trajectories/make_bundled.py: 200 Hz, hover 5 mm above the
skin, 10 mm/s with 0.2 s raised-cosine ramps); replay them with ``--point CODE``.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from make_bundled import Script, above  # noqa: E402  (the same path builder as the other files)

try:
    from haptic_acu.session.trajectory import TrajectoryWriter
except ImportError:  # run from a checkout without the package installed
    sys.path.insert(0, str(HERE.parent))
    from haptic_acu.session.trajectory import TrajectoryWriter


def _tilted(depth_mm: float, angle_deg: float, heading_deg: float) -> Script:
    """From 5 mm above the point along the line through it tilted ``angle`` from the normal toward
    ``heading`` (0: +x, 90: +y), ``depth`` mm along the needle, hold 1.5 s, withdraw the same way."""
    th, ph = math.radians(angle_deg), math.radians(heading_deg)
    d = np.round([math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), -math.cos(th)], 12) + 0.0
    start = -d * (5.0 / math.cos(th))
    return Script(start).hold(0.5).move(depth_mm * d).hold(1.5).move(start).hold(0.5)


def _straight(depth_mm: float) -> Script:
    return Script(above()).hold(0.5).move((0, 0, -depth_mm)).hold(1.5).move(above()).hold(0.5)


POINTS = {  # name: (point, make, what it is: trajectories/README.md)
    "GB21_correct": ("GB21", lambda: _straight(11.0), "perpendicular to 11 mm, inside GB21's 5-13 mm"),
    "GB21_pleura": ("GB21", lambda: _straight(25.0), "perpendicular to 25 mm: through the pleura (17.4 mm)"),
    "PC6_correct": ("PC6", lambda: _straight(20.0), "perpendicular to 20 mm, 1.8 mm past the median nerve"),
    "PC6_nerve": ("PC6", lambda: _tilted(20.0, 15.0, 90.0),
                  "20 mm along a needle tilted 15 degrees radially: into the median nerve's radius"),
    "ST36_correct": ("ST36", lambda: _straight(25.0), "perpendicular to 25 mm, inside ST36's 19.5-31.1 mm"),
    "ST36_tibia": ("ST36", lambda: _tilted(30.0, 20.0, 90.0),
                   "30 mm along a needle tilted 20 degrees medially: onto the tibia"),
}


def write(name: str, out_dir: Path) -> Path:
    _, make, _ = POINTS[name]
    t, pos_mm = make().sample()
    path = out_dir / f"{name}.csv"
    with TrajectoryWriter(path) as w:
        w.append_rows(np.column_stack([t, pos_mm / 1000.0 + 0.0]))  # + 0.0: no negative zeros
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=HERE / "points")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for name in POINTS:
        print(write(name, args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

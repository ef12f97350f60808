"""Generate the bundled needle trajectories (deterministic: same bytes on every run).

    python trajectories/make_bundled.py [--out DIR]      (default: this directory)

Scene frame, mm: the acupoint is at the origin on the skin, outward normal +z, the needle goes in
along -z. Every file starts with the tip hovering 5 mm above the acupoint (z = +5) and ends out of
the tissue at z = +5. Samples at 200 Hz; the replay interpolates them to the 1 kHz servo rate.

Moves are straight (or, for the sweep, surface-following) at a cruise speed with raised-cosine
speed ramps of 0.2 s at each end, so the hand never changes velocity instantly; lift-thrust is a
smooth cosine stroke. Insertions and withdrawals are at 10 mm/s unless the file is about speed.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

try:
    from haptic_acu.session.trajectory import TrajectoryWriter
except ImportError:  # run from a checkout without the package installed
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    from haptic_acu.session.trajectory import TrajectoryWriter

RATE_HZ = 200
RAMP_S = 0.2
HOVER_MM = 5.0
SPEED_MM_S = 10.0
# The default body's skin ellipsoid (config/tissue.toml body.semi_axes_mm): semi-axis along x
# and along z; the acupoint is its +z pole. Used only to keep the sweep at a constant depth.
SKIN_A_X_MM, SKIN_C_Z_MM = 110.0, 70.0


class Script:
    """A tip path built from segments; each is (duration s, f(tau) -> position mm)."""

    def __init__(self, start_mm):
        self.pos = np.asarray(start_mm, dtype=float)
        self.segments: list[tuple[float, object]] = []

    def hold(self, seconds: float) -> "Script":
        p = self.pos.copy()
        self.segments.append((seconds, lambda tau: p))
        return self

    def along(self, curve, length_mm: float, speed_mm_s: float) -> "Script":
        """Travel ``curve(s)`` for s in [0, length] at ``speed`` with smooth speed ramps."""
        v = speed_mm_s
        r = min(RAMP_S, length_mm / v)  # short moves: ramps meet in the middle
        total = length_mm / v + r

        def s_of(tau):
            if tau <= 0:
                return 0.0
            if tau >= total:
                return length_mm
            if tau < r:  # speed rises as (1 - cos)/2
                return v * (tau / 2 - r / (2 * math.pi) * math.sin(math.pi * tau / r))
            if tau <= total - r:
                return v * r / 2 + v * (tau - r)
            u = total - tau
            return length_mm - v * (u / 2 - r / (2 * math.pi) * math.sin(math.pi * u / r))

        self.segments.append((total, lambda tau: curve(s_of(tau))))
        self.pos = np.asarray(curve(length_mm), dtype=float)
        return self

    def move(self, target_mm, speed_mm_s: float = SPEED_MM_S) -> "Script":
        a, b = self.pos.copy(), np.asarray(target_mm, dtype=float)
        d = float(np.linalg.norm(b - a))
        return self.along(lambda s: a + (b - a) * (s / d), d, speed_mm_s)

    def lift_thrust(self, amplitude_mm: float, freq_hz: float, cycles: int) -> "Script":
        """Lift the tip by ``amplitude`` along +z and thrust it back, ``cycles`` times."""
        p = self.pos.copy()
        w = 2 * math.pi * freq_hz
        def at(tau):
            return p + np.array([0.0, 0.0, amplitude_mm * (1 - math.cos(w * tau)) / 2])

        self.segments.append((cycles / freq_hz, at))
        return self

    def sample(self) -> tuple[np.ndarray, np.ndarray]:
        """Times (s) at RATE_HZ covering the whole path, positions (mm)."""
        total = sum(d for d, _ in self.segments)
        n = int(math.ceil(total * RATE_HZ - 1e-9)) + 1
        t = np.arange(n) / RATE_HZ
        starts = np.cumsum([0.0] + [d for d, _ in self.segments])
        pos = np.empty((n, 3))
        for k, tk in enumerate(t):
            i = min(int(np.searchsorted(starts, tk, side="right")) - 1, len(self.segments) - 1)
            pos[k] = self.segments[i][1](tk - starts[i])
        return t, pos


def above(x=0.0, y=0.0):
    return (x, y, HOVER_MM)


def default():
    return (Script(above()).hold(0.5).move((0, 0, -30)).hold(1.5).lift_thrust(4.0, 0.75, 4)
            .hold(1.0).move(above()).hold(0.5))


def slow_insertion():
    return Script(above()).hold(0.5).move((0, 0, -30), 3.0).hold(1.0).move(above()).hold(0.5)


def fast_insertion():
    return Script(above()).hold(0.5).move((0, 0, -30), 30.0).hold(1.0).move(above()).hold(0.5)


def oblique_entry():
    a = math.radians(30.0)
    d = np.array([math.sin(a), 0.0, -math.cos(a)])  # needle direction, 30 deg from -z toward +x
    start = -(HOVER_MM / math.cos(a)) * d  # on the line through the acupoint, at z = +5
    return Script(start).hold(0.5).move(25.0 * d).hold(1.5).move(start).hold(0.5)


def second_insertion_same_site():
    return (Script(above()).hold(0.5).move((0, 0, -8)).hold(1.0).move(above()).hold(1.5)
            .move((0, 0, -8)).hold(1.0).move(above()).hold(0.5))


def lateral_sweep():
    def skin_z(x):  # the rest skin surface along x through the acupoint
        return -SKIN_C_Z_MM * (1 - math.sqrt(1 - (x / SKIN_A_X_MM) ** 2))

    depth = 0.5
    s = Script(above()).hold(0.5).move((0, 0, -depth), 5.0).hold(0.5)
    s.along(lambda x: np.array([x, 0.0, skin_z(x) - depth]), 10.0, 5.0).hold(0.3)
    s.along(lambda u: np.array([10.0 - u, 0.0, skin_z(10.0 - u) - depth]), 10.0, 5.0).hold(0.5)
    return s.move(above()).hold(0.5)


def new_site():
    return (Script(above()).hold(0.5).move((0, 0, -8)).hold(1.0).move(above()).move(above(5.0))
            .hold(0.5).move((5, 0, -8)).hold(1.0).move(above(5.0)).hold(0.5))


BUNDLED = {
    "default": (default, "perpendicular insertion at 10 mm/s to z = -30 mm, hold, 4 lift-thrust "
                         "cycles (4 mm, 0.75 Hz), hold, withdrawal at 10 mm/s"),
    "slow_insertion": (slow_insertion, "perpendicular insertion at 3 mm/s to z = -30 mm, hold, "
                                       "withdrawal at 10 mm/s"),
    "fast_insertion": (fast_insertion, "perpendicular insertion at 30 mm/s to z = -30 mm, hold, "
                                       "withdrawal at 10 mm/s"),
    "oblique_entry": (oblique_entry, "entry at the acupoint 30 degrees from the normal (tilted toward "
                                     "+x), 25 mm along the needle at 10 mm/s, hold, withdrawal"),
    "second_insertion_same_site": (second_insertion_same_site, "insertion into fat (z = -8 mm), full "
                                   "withdrawal, re-insertion at the same point"),
    "lateral_sweep": (lateral_sweep, "press the skin 0.5 mm at the acupoint, sweep 10 mm along +x and "
                                     "back at 5 mm/s following the skin, lift off; never punctures"),
    "new_site": (new_site, "insertion into fat (z = -8 mm), withdrawal, re-insertion 5 mm away along x"),
}


def write(name: str, out_dir: Path) -> Path:
    make, _ = BUNDLED[name]
    t, pos_mm = make().sample()
    path = out_dir / f"{name}.csv"
    with TrajectoryWriter(path) as w:  # header on line 1; what each file is: trajectories/README.md
        w.append_rows(np.column_stack([t, pos_mm / 1000.0]))
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for name in BUNDLED:
        print(write(name, args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

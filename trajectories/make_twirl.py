"""Generate the bundled twirling trajectories (deterministic: same bytes on every run).

    python trajectories/make_twirl.py [--out DIR]      (default: this directory)

Same conventions as make_bundled.py: scene frame in mm (acupoint at the origin on the skin,
outward normal +z, the needle goes in along -z), 200 Hz samples, the tip hovering at z = +5 mm at
the start and the end, straight moves at a cruise speed with 0.2 s raised-cosine speed ramps,
insertion and withdrawal at 10 mm/s. They add the column ``roll_deg``: the needle's cumulative
roll (deg, positive clockwise seen from the handle), 0 outside the twirling. The header is the
first line (no comment lines); what each file is lives here and in trajectories/README.md.

Twirls are back-and-forth cosine swings from rest, roll = (S/2)(1 - cos 2 pi f t) over whole
cycles: the roll rate starts and ends at zero, each swing turns S degrees. Textbook rule
(Cheng Xinnong, Chinese Acupuncture and Moxibustion): small and slow twirling with heavy thrust and
light lift reinforces, large and fast twirling with heavy lift and light thrust reduces.

* twirl_even: insertion to z = -25 mm, 1 s hold, 6 twirls of 180 deg at 1.5 Hz, 1 s hold, withdrawal.
* twirl_reinforcing: insertion to -25 mm, 1 s hold, 4 twirls of 60 deg at 0.75 Hz, 0.5 s hold,
  3 lift-thrust strokes of 4 mm (slow lift at 3 mm/s, fast thrust at 12 mm/s), 1 s hold, withdrawal.
* twirl_reducing: insertion to -25 mm, 1 s hold, 10 twirls of 270 deg at 2.5 Hz (peak 5.9 turns/s),
  0.5 s hold, 3 lift-thrust strokes of 4 mm (fast lift at 12 mm/s, slow thrust at 3 mm/s), 1 s hold,
  withdrawal.
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
DEPTH_Z_MM = -25.0


class TwirlScript:
    """Axial tip path and roll built from segments; each is (duration s, f(tau) -> (z mm, roll deg))."""

    def __init__(self, z_mm: float = HOVER_MM):
        self.z = float(z_mm)
        self.roll = 0.0
        self.segments: list[tuple[float, object]] = []

    def hold(self, seconds: float) -> "TwirlScript":
        z, r = self.z, self.roll
        self.segments.append((seconds, lambda tau: (z, r)))
        return self

    def move(self, z_mm: float, speed_mm_s: float = SPEED_MM_S) -> "TwirlScript":
        """Straight along z at ``speed`` with raised-cosine speed ramps at both ends."""
        a, b, r = self.z, float(z_mm), self.roll
        length = abs(b - a)
        ramp = min(RAMP_S, length / speed_mm_s)
        total = length / speed_mm_s + ramp
        sign = 1.0 if b >= a else -1.0

        def s_of(tau):  # distance covered: cruise speed v, ramps of (1 - cos)/2 speed
            v = speed_mm_s
            if tau <= 0.0:
                return 0.0
            if tau >= total:
                return length
            if tau < ramp:
                return v * (tau / 2 - ramp / (2 * math.pi) * math.sin(math.pi * tau / ramp))
            if tau <= total - ramp:
                return v * ramp / 2 + v * (tau - ramp)
            u = total - tau
            return length - v * (u / 2 - ramp / (2 * math.pi) * math.sin(math.pi * u / ramp))

        self.segments.append((total, lambda tau: (a + sign * s_of(tau), r)))
        self.z = b
        return self

    def twirl(self, swing_deg: float, freq_hz: float, cycles: int) -> "TwirlScript":
        """``cycles`` back-and-forth swings of ``swing_deg`` (clockwise first) at ``freq_hz``."""
        z, r0, w = self.z, self.roll, 2 * math.pi * freq_hz
        self.segments.append((cycles / freq_hz,
                              lambda tau: (z, r0 + 0.5 * swing_deg * (1 - math.cos(w * tau)))))
        return self

    def strokes(self, stroke_mm: float, lift_mm_s: float, thrust_mm_s: float, n: int) -> "TwirlScript":
        """``n`` lift-thrust strokes: lift ``stroke_mm`` at one speed, thrust back at another."""
        z0 = self.z
        for _ in range(n):
            self.move(z0 + stroke_mm, lift_mm_s).move(z0, thrust_mm_s)
        return self

    def sample(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Times (s) at RATE_HZ over the whole script, z (mm), roll (deg)."""
        total = sum(d for d, _ in self.segments)
        n = int(math.ceil(total * RATE_HZ - 1e-9)) + 1
        t = np.arange(n) / RATE_HZ
        starts = np.cumsum([0.0] + [d for d, _ in self.segments])
        z = np.empty(n)
        roll = np.empty(n)
        for k, tk in enumerate(t):
            i = min(int(np.searchsorted(starts, tk, side="right")) - 1, len(self.segments) - 1)
            z[k], roll[k] = self.segments[i][1](tk - starts[i])
        return t, z, roll


def twirl_even():
    return (TwirlScript().hold(0.5).move(DEPTH_Z_MM).hold(1.0).twirl(180.0, 1.5, 6).hold(1.0)
            .move(HOVER_MM).hold(0.5))


def twirl_reinforcing():
    return (TwirlScript().hold(0.5).move(DEPTH_Z_MM).hold(1.0).twirl(60.0, 0.75, 4).hold(0.5)
            .strokes(4.0, 3.0, 12.0, 3).hold(1.0).move(HOVER_MM).hold(0.5))


def twirl_reducing():
    return (TwirlScript().hold(0.5).move(DEPTH_Z_MM).hold(1.0).twirl(270.0, 2.5, 10).hold(0.5)
            .strokes(4.0, 12.0, 3.0, 3).hold(1.0).move(HOVER_MM).hold(0.5))


BUNDLED = {"twirl_even": twirl_even, "twirl_reinforcing": twirl_reinforcing,
           "twirl_reducing": twirl_reducing}


def write(name: str, out_dir: Path) -> Path:
    t, z_mm, roll = BUNDLED[name]().sample()
    path = out_dir / f"{name}.csv"
    rows = np.column_stack([t, np.zeros_like(t), np.zeros_like(t), z_mm / 1000.0, roll])
    with TrajectoryWriter(path, extra_columns=("roll_deg",), formats={"roll_deg": "%.4f"}) as w:
        w.append_rows(rows)
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

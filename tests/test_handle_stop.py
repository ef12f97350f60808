"""The needle is a real needle: no more of it than its length goes into the tissue. A device pushed
past the needle's length puts the handle on the skin: the needle's tip stays its length below the
entry, the force on the hand is a stop at the device's limit out along the needle, the stop is
stable through the rendering layer in closed loop, and what every output calls the depth is the
needle's. The length is read from the config here; the entry is the acupoint, the origin of the
scene frame on the skin, where a straight vertical insertion crosses it."""
from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from physics_helpers import replace, sphere_config, sphere_tissue, straight_line

from haptic_acu.base.config import load_config
from haptic_acu.cli import main
from haptic_acu.servo.step import NeedleModel

SPEED = 0.01  # m/s


@pytest.fixture(scope="module")
def pushed():
    """A 15 mm needle in the 200 mm sphere (bone 26 mm down): the device straight down the normal at
    the acupoint to 10 mm past the needle's length, held, then back out; every tick's device
    position, the needle's tip, its depth and the force."""
    cfg = replace(sphere_config(), "needle", length_mm=15.0)
    model = NeedleModel(cfg, sphere_tissue(cfg))
    length = cfg.needle.length_mm * 1e-3
    down, v_down = straight_line(2e-3, -(length + 10e-3), SPEED)
    hold = np.tile(down[-1], (300, 1))
    up, v_up = straight_line(-(length + 10e-3), 2e-3, SPEED)
    path = np.vstack([down, hold, up])
    vel = np.vstack([np.tile(v_down, (len(down), 1)), np.zeros((len(hold), 3)), np.tile(v_up, (len(up), 1))])
    ticks = []
    for p, v in zip(path, vel):
        f = np.array(model.step(p, v), float)
        ticks.append((p.copy(), model.tip, float(model.diag["depth_skin"]), f, model.inserted))
    return cfg, length, len(down), len(hold), ticks


def test_the_needle_stays_at_its_length_however_far_the_device_goes(pushed):
    cfg, length, n_down, n_hold, ticks = pushed
    dev = np.array([t[0] for t in ticks])
    tip = np.array([t[1] for t in ticks])
    depth = np.array([t[2] for t in ticks])
    assert -dev[:, 2].min() == pytest.approx(length + 10e-3, abs=1e-9)  # the device went 10 mm further
    assert depth.max() <= length and -tip[:, 2].max() <= length  # the needle never did
    assert depth.max() == pytest.approx(length, abs=1e-12)  # it did reach its handle
    np.testing.assert_array_equal(tip[:, :2], 0.0)  # on the insertion line
    held = -dev[:, 2] > length + 1e-9
    assert held.sum() > n_hold  # the handle was on the skin for the whole hold and either side of it
    np.testing.assert_allclose(-tip[held, 2], length, atol=1e-12)
    # off the skin (the handle not reached, or back out) the needle's tip is the device's (to the
    # rounding of the entry point's place on the skin)
    np.testing.assert_allclose(tip[~held], dev[~held], rtol=0, atol=1e-15)


def test_the_stop_is_the_device_limit_out_along_the_needle(pushed):
    cfg, length, n_down, n_hold, ticks = pushed
    limit = cfg.safety.force_limit_n
    forces = np.array([t[3] for t in ticks])
    assert np.isfinite(forces).all() and np.linalg.norm(forces, axis=1).max() <= limit * (1 + 1e-12)
    for p, tip, depth, f, inserted in ticks[n_down - 1:n_down + n_hold]:  # 10 mm past, held
        assert np.linalg.norm(f) == pytest.approx(limit, rel=1e-9)
        assert f[2] / np.linalg.norm(f) > 1.0 - 1e-9  # +z: out of the skin, along the needle (axis -z)
    # the stop is a spring from the needle to the device, growing with the device's travel past the
    # needle's length (k_bone, 1 N/mm) until the limit; the needle held still, the tissue's own
    # friction on it barely changes over 1 mm of the device's travel
    over = np.array([-t[0][2] - length for t in ticks[:n_down]])
    fz = np.array([t[3][2] for t in ticks[:n_down]])
    i1, i2 = int(np.argmax(over > 1e-3)), int(np.argmax(over > 2e-3))
    k = cfg.needle.bone_stiffness_n_per_mm * 1e3
    assert fz[i2] - fz[i1] == pytest.approx(k * (over[i2] - over[i1]), abs=0.05)


@pytest.fixture(scope="module")
def replayed(tmp_path_factory):
    """A replay of a trajectory straight down at the acupoint to 10 mm past a 20 mm needle (the
    default tissue: bone 48 mm down), held 0.5 s, withdrawn."""
    length = 20.0
    tmp = tmp_path_factory.mktemp("handle")
    traj = tmp / "past_the_handle.csv"
    deep = length + 10.0
    t1 = (deep + 2.0) / 10.0
    traj.write_text("t_s,x_mm,y_mm,z_mm\n"
                    f"0,0,0,2\n{t1:.6f},0,0,{-deep}\n{t1 + 0.5:.6f},0,0,{-deep}\n{2 * t1 + 0.5:.6f},0,0,2\n")
    out = tmp / "out"
    import contextlib
    import io

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = main(["replay", str(traj), "--out", str(out), "--no-rrd", "--quiet",
                     "--set", f"needle.length_mm={length:g}"])
    assert code == 0, err.getvalue()
    with open(out / "samples.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    return length, json.loads((out / "summary.json").read_text()), rows, err.getvalue(), out


def test_a_replay_past_the_handle_reports_the_needles_depth(replayed):
    length, summary, rows, err, out = replayed
    (m,) = summary["metrics"]["per_insertion"]
    assert m["max_depth_mm"] == pytest.approx(length, abs=1e-3)
    assert summary["max_tip_depth_mm"] <= length + 1e-3 and m["max_tip_depth_mm"] <= length + 1e-3
    assert max(-float(r["z_mm"]) for r in rows) <= length + 1e-4  # samples.csv: the needle's tip
    assert max(float(r["depth_skin_mm"]) for r in rows) <= length + 1e-4
    assert m["time_at_force_limit_s"] >= 0.5 and m["time_on_bone_s"] == 0.0
    limit = load_config().safety.force_limit_n
    deepest = [r for r in rows if float(r["t_s"]) > 3.3 and float(r["t_s"]) < 3.7]
    for r in deepest:  # the hold, 10 mm past the length: the limit, straight out of the skin
        assert float(r["fz_n"]) == pytest.approx(limit, abs=1e-5) and float(r["f_n"]) == pytest.approx(limit, abs=1e-5)
        assert math.hypot(float(r["fx_n"]), float(r["fy_n"])) <= 1e-5
    texts = [f["text"] for f in summary["debrief"]["insertions"][0]["findings"]]
    assert f"the whole {length:g} mm needle went in: the handle met the skin" in texts
    assert "the handle met the skin" in (out / "debrief.md").read_text()


class _Watched:
    """The servo's own report for the rendering layer (bench.closed_loop.DiagTissue), keeping the
    needle's depth after every step."""

    def __init__(self, diag_tissue):
        self.inner = diag_tissue
        self.depth = []

    def naive(self, p, v):
        return self.inner.naive(p, v)

    def puncture(self):
        return self.inner.puncture()

    def step(self, p, v):
        out = self.inner.step(p, v)
        self.depth.append(float(self.inner.m.diag["depth_skin"]))
        return out


@pytest.mark.parametrize("grip", ["loose", "firm"])
def test_the_stop_is_stable_in_closed_loop(grip):
    """The bench's closed-loop session (a hand on the stylus, the rendering layer on the servo's own
    report) with a 20 mm needle: its insertion goes 25 mm deep, holds, lifts and thrusts against the
    handle. No buzz, no energy into the hand, the force within the limit, the needle at most its length."""
    from haptic_acu.bench import closed_loop as C

    cfg = replace(load_config(), "needle", length_mm=20.0)
    model = NeedleModel(cfg)
    H, phases = C.session_path(model)
    model.reset(keep_holes=False)
    watch = _Watched(C.DiagTissue(model))
    res = C.closed_loop(C.LOOSE if grip == "loose" else C.FIRM, H, phases, watch, "rendered")
    m = C.metrics(res)
    length = cfg.needle.length_mm * 1e-3
    assert max(watch.depth) <= length and max(watch.depth) == pytest.approx(length, abs=1e-12)
    assert np.isfinite(res["rendered"]).all() and m["max_force_n"] <= cfg.safety.force_limit_n * (1 + 1e-12)
    assert max(m["buzz_n"].values()) <= 0.02, m["buzz_n"]
    assert all(e <= 0.0 for e in m["energy_into_hand_j"]["lift_thrust_cycles"]), m["energy_into_hand_j"]
    assert m["energy_into_hand_j"]["closed_session"] <= 0.0
    hold = next((i0, i1) for name, i0, i1 in phases if name == "hold")
    assert m["mean_force_n"]["hold"] > 0.6  # the stop holds the hand back (0.3 N with a 40 mm needle)
    assert (-res["stylus"][hold[0]:hold[1], 2]).max() > length  # the stylus past the handle (the entry: z = 0)

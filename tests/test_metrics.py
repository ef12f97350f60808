"""Session metrics: synthetic sessions built here from analytic depth signals (every expected number
is known in closed form), a spherical tissue's radial normal, and end-to-end replays of the bundled
trajectories against what trajectories/README.md says they do."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from haptic_acu.base.config import load_config
from haptic_acu.analysis.metrics import session_metrics
from haptic_acu.servo.samples import COL, NCOL

from physics_helpers import replace, sphere_config, sphere_tissue
from haptic_acu.session.sink import Sink

ROOT = Path(__file__).resolve().parent.parent
DT = 1e-3  # s, one servo tick
V = 10.0  # mm/s, approach and withdrawal speed of the synthetic sessions


@pytest.fixture(scope="module")
def cfg():
    # The synthetic sessions below are written for a 10-25 mm target; pin it so a change of the
    # shipped default (config/tissue.toml) does not change what these tests check.
    return replace(load_config(), "scene", target_depth_mm=(10.0, 25.0))


class Session:
    """Synthetic sample rows, one per 1 ms tick, built segment by segment.

    The tip moves along a straight needle line ``entry + s * u`` (mm, u a unit direction into the
    tissue). As in the model (haptic_acu/servo/step.py): untouched while s < 0, pressing the skin while
    0 <= s < dent, punctured from the first tick with s >= dent (that tick carries puncture = 0), with
    the tissue compressed by the dent, so depth_skin = s - dent; back at s < 0 the skin is untouched.
    """

    def __init__(self):
        self.t0 = 0.0
        self.blocks = []

    def _add(self, t, tip_mm, state, depth_mm, puncture=None, f_layers=None, f_lat=None, force=None):
        n = len(t)
        r = np.zeros((n, NCOL))
        r[:, COL["t_s"]] = t
        r[:, COL["tick"]] = np.round(t / DT)
        r[:, COL["x_m"]:COL["x_m"] + 3] = np.asarray(tip_mm) * 1e-3
        r[:, COL["state_skin"]] = state
        r[:, COL["depth_skin_m"]] = np.asarray(depth_mm) * 1e-3
        r[:, COL["puncture"]] = -1 if puncture is None else puncture
        r[:, COL["layer"]] = np.where(np.asarray(state) == 2, 0, -1)
        if f_layers is not None:
            r[:, COL["f_skin_n"]:COL["f_skin_n"] + 3] = f_layers
        if f_lat is not None:
            r[:, COL["f_lateral_n"]] = f_lat
        if force is not None:
            r[:, COL["fx_n"]:COL["fx_n"] + 3] = force
        self.blocks.append(r)
        self.t0 = float(t[-1]) + DT
        return r

    def ticks(self, n):
        return self.t0 + DT * np.arange(n)

    def insertion(self, depth_mm, entry_mm=(0.0, 0.0, 0.0), direction=(0.0, 0.0, -1.0), dent_mm=1.5,
                  approach_mm=2.0, through_hole=False):
        """Approach at V from ``approach_mm`` above the entry, press the skin (unless ``through_hole``),
        follow ``depth_mm`` (one value per tick after the puncture, starting at 0), withdraw at V from
        the last depth back above the entry. Returns the rows of each phase."""
        e = np.asarray(entry_mm, dtype=float)
        u = np.asarray(direction, dtype=float)
        u = u / np.linalg.norm(u)
        step = V * DT
        dent = 0.0 if through_hole else dent_mm
        s_in = np.arange(-round(approach_mm / step), round(dent / step)) * step  # s < dent
        t = self.ticks(len(s_in))
        state = np.where(s_in < 0, 0, 1)
        phases = {"approach": self._add(t, e + s_in[:, None] * u, state, np.zeros(len(t)))}
        d = np.asarray(depth_mm, dtype=float)
        s = dent + d
        t = self.ticks(len(d))
        punct = np.full(len(d), -1.0)
        if not through_hole:
            punct[0] = 0.0
        phases["inside"] = self._add(t, e + s[:, None] * u, np.full(len(d), 2), d, punct)
        # withdrawal: the tip goes back from its last depth to above the entry; depth falls at V to 0
        # (the skin tents with the needle) and the skin is left at s < 0
        d_out = d[-1] - step * np.arange(1, int(d[-1] / step) + 1)
        s_out = np.concatenate([dent + d_out, dent - step * np.arange(1, round((dent + approach_mm) / step) + 1)])
        dep = np.concatenate([d_out, np.zeros(len(s_out) - len(d_out))])
        t = self.ticks(len(s_out))
        phases["out"] = self._add(t, e + s_out[:, None] * u, np.where(s_out < 0, 0, 2), dep)
        return phases

    def hold_outside(self, seconds, tip_mm=(0.0, 0.0, 5.0)):
        t = self.ticks(round(seconds / DT))
        self._add(t, np.tile(tip_mm, (len(t), 1)), np.zeros(len(t)), np.zeros(len(t)))

    def rows(self):
        return np.concatenate(self.blocks)


def ramp(v_mm_s, depth_mm):
    """Depth from 0 to ``depth_mm`` at ``v_mm_s`` (one value per tick)."""
    return np.arange(0.0, depth_mm + 1e-9, v_mm_s * DT)


def hold(depth_mm, seconds):
    return np.full(round(seconds / DT), float(depth_mm))


def cosine_strokes(depth_mm, stroke_mm, freq_hz, cycles):
    """Lift by ``stroke_mm`` and thrust back, ``cycles`` times: depth - stroke (1 - cos wt) / 2."""
    tau = np.arange(round(cycles / freq_hz / DT)) * DT
    return depth_mm - stroke_mm * (1 - np.cos(2 * np.pi * freq_hz * tau)) / 2


# ------------------------------------------------------------------------- lift-thrust, speed, depth
def test_plateau_lift_thrust_speed_depth_and_time_to_target(cfg):
    v, depth, stroke, f, n = 8.0, 20.0, 3.0, 0.5, 3
    s = Session()
    s.hold_outside(0.2)
    prof = np.concatenate([ramp(v, depth), hold(depth, 1.0), cosine_strokes(depth, stroke, f, n), hold(depth, 1.0)])
    ph = s.insertion(prof, dent_mm=1.5)
    m = session_metrics(s.rows(), cfg)
    assert m["insertions"] == 1 and m["skin_punctures"] == 1
    ins = m["per_insertion"][0]
    assert ins["skin_punctured"] is True
    assert ins["max_depth_mm"] == pytest.approx(depth, abs=1e-3)
    assert ins["depth_verdict"] == "in range"
    assert ins["insertion_speed_mm_s"] == pytest.approx(v, rel=1e-3)
    # entry at the first pressing tick (s = 0), target's lower bound (10 mm) at s = dent + 10 mm:
    # the approach is at V over the dent, then the profile's ramp at v
    assert ins["time_to_target_s"] == pytest.approx(1.5 / V + 10.0 / v, abs=2 * DT)
    assert ins["t_entry_s"] == pytest.approx(0.2 + 2.0 / V, abs=DT)
    lt = ins["lift_thrust"]
    assert lt["cycles"] == n
    assert lt["mean_amplitude_mm"] == pytest.approx(stroke, abs=1e-3)
    assert lt["frequency_hz"] == pytest.approx(f, rel=1e-3)
    assert ins["angle_deg"] == pytest.approx(0.0, abs=1e-6)
    inside = len(ph["inside"]) + int(np.count_nonzero(ph["out"][:, COL["state_skin"]] == 2))
    assert ins["time_in_tissue_s"] == pytest.approx(inside * DT, abs=1e-4)
    assert m["time_in_tissue_s"] == ins["time_in_tissue_s"]


def test_sinusoid_on_a_ramp_lift_amplitude_closed_form(cfg):
    # depth = v t + A sin(w t): extrema where cos(w t) = -c, c = v / (A w); each lift (a maximum to
    # the next minimum) gives up 2 A sqrt(1 - c^2) - 2 v arccos(c) / w, and troughs are 1/f apart
    v, a, f, T = 4.0, 2.0, 1.0, 8.5
    w = 2 * np.pi * f
    c = v / (a * w)
    lift = 2 * a * math.sqrt(1 - c * c) - 2 * v * math.acos(c) / w
    t = np.arange(round(T / DT)) * DT
    prof = v * t + a * np.sin(w * t)
    assert prof.min() >= 0.0
    s = Session()
    s.insertion(prof)
    ins = session_metrics(s.rows(), cfg)["per_insertion"][0]
    # troughs at t_k = (pi + arccos c) / w + k / f; counted once the depth first reaches 10 mm
    t_k = (math.pi + math.acos(c)) / w + np.arange(10) / f
    d_k = v * t_k - a * math.sqrt(1 - c * c)
    first10 = t[np.argmax(prof >= 10.0)]
    t_max_before = t_k - 2 * math.acos(c) / w  # each trough's preceding maximum
    expected = int(np.count_nonzero((t_k < T) & (t_max_before >= first10) & (d_k > 0)))
    assert expected == 6
    lt = ins["lift_thrust"]
    assert lt["cycles"] == expected
    assert lt["mean_amplitude_mm"] == pytest.approx(lift, abs=2e-3)
    assert lt["frequency_hz"] == pytest.approx(f, rel=1e-3)
    assert ins["max_depth_mm"] == pytest.approx(prof.max(), abs=1e-3)
    assert ins["depth_verdict"] == "too deep"


def test_small_wobble_is_not_a_cycle(cfg):
    # strokes below the 1 mm prominence are tremor, not lift-thrust
    s = Session()
    s.insertion(np.concatenate([ramp(10.0, 15.0), cosine_strokes(15.0, 0.8, 2.0, 4), hold(15.0, 0.5)]))
    assert session_metrics(s.rows(), cfg)["per_insertion"][0]["lift_thrust"]["cycles"] == 0


def test_depth_step_at_a_deeper_puncture_is_not_a_lift(cfg):
    # When a deeper fascia breaks the model lifts its frame by that surface's dent: depth_skin steps
    # back ~1 mm in one tick while the tip keeps going in. That must not count as a lift...
    s = Session()
    prof = np.concatenate([ramp(10.0, 12.0), hold(12.0, 0.5)])
    k = int(np.argmax(prof >= 10.3))
    ph = s.insertion(prof)  # the tip goes straight in to 12 mm past the skin's dent...
    for block in (ph["inside"][k:], ph["out"]):  # ...but the depth frame steps back 1.1 mm at tick k
        block[:, COL["depth_skin_m"]] = np.maximum(block[:, COL["depth_skin_m"]] - 1.1e-3, 0.0)
    ph["inside"][k, COL["puncture"]] = 2.0  # muscle punctured on that tick
    depth = ph["inside"][:, COL["depth_skin_m"]] * 1e3
    m = session_metrics(s.rows(), cfg)["per_insertion"][0]
    assert m["lift_thrust"]["cycles"] == 0
    assert m["insertion_speed_mm_s"] == pytest.approx(10.0, rel=1e-3)  # the tip's own axial speed
    # ... while the same step in depth without a puncture on that tick reads as a 1.1 mm lift
    ph["inside"][k, COL["puncture"]] = -1.0
    m = session_metrics(s.rows(), cfg)["per_insertion"][0]
    assert m["lift_thrust"]["cycles"] == 1
    assert m["lift_thrust"]["mean_amplitude_mm"] == pytest.approx(depth[k - 1] - depth[k], abs=1e-3)


@pytest.mark.parametrize("depth,verdict", [(8.0, "too shallow"), (15.0, "in range"), (30.0, "too deep")])
def test_depth_verdict_against_target_range(cfg, depth, verdict):
    s = Session()
    s.insertion(np.concatenate([ramp(10.0, depth), hold(depth, 0.3)]))
    ins = session_metrics(s.rows(), cfg)["per_insertion"][0]
    assert ins["max_depth_mm"] == pytest.approx(depth, abs=1e-3)
    assert ins["depth_verdict"] == verdict
    assert (ins["time_to_target_s"] is None) == (depth < 10.0)


def test_target_range_comes_from_the_config(cfg):
    s = Session()
    s.insertion(np.concatenate([ramp(10.0, 15.0), hold(15.0, 0.3)]))
    narrow = replace(cfg, "scene", target_depth_mm=(16.0, 20.0))
    m = session_metrics(s.rows(), narrow)
    assert m["target_depth_mm"] == [16.0, 20.0]
    assert m["per_insertion"][0]["depth_verdict"] == "too shallow"
    assert m["per_insertion"][0]["time_to_target_s"] is None


# ----------------------------------------------------------------------------- entry point and angle
@pytest.mark.parametrize("theta_deg,azimuth_deg", [(30.0, 0.0), (45.0, 90.0), (12.5, 210.0)])
def test_oblique_entry_angle(cfg, theta_deg, azimuth_deg):
    th, az = math.radians(theta_deg), math.radians(azimuth_deg)
    u = (math.sin(th) * math.cos(az), math.sin(th) * math.sin(az), -math.cos(th))
    s = Session()
    s.insertion(np.concatenate([ramp(10.0, 20.0), hold(20.0, 0.5)]), direction=u)
    ins = session_metrics(s.rows(), cfg)["per_insertion"][0]
    assert ins["angle_deg"] == pytest.approx(theta_deg, abs=0.01)
    assert ins["entry_offset_mm"] == pytest.approx(0.0, abs=1e-3)
    assert ins["insertion_speed_mm_s"] == pytest.approx(10.0, rel=1e-3)


def test_entry_three_mm_off_the_acupoint(cfg):
    a = math.radians(37.0)
    e = (3.0 * math.cos(a), 3.0 * math.sin(a), 0.0)
    s = Session()
    s.insertion(np.concatenate([ramp(10.0, 12.0), hold(12.0, 0.2)]), entry_mm=e)
    ins = session_metrics(s.rows(), cfg)["per_insertion"][0]
    assert ins["entry_offset_mm"] == pytest.approx(3.0, abs=1e-3)
    assert ins["entry_mm"] == pytest.approx(list(e), abs=1e-3)


def test_angle_is_measured_from_the_tissue_normal_at_the_entry():
    # a 200 mm sphere: the normal anywhere is radial, so an entry beta away from the pole with the
    # needle along -z is beta off the inward normal (and 0 off -z, the default without a tissue)
    cfg = sphere_config()
    tissue = sphere_tissue(cfg)
    beta = math.radians(10.0)
    radial = np.array([math.sin(beta), 0.0, math.cos(beta)])
    e_mm = (tissue.centre + 200e-3 * radial) * 1e3
    s = Session()
    s.insertion(np.concatenate([ramp(10.0, 12.0), hold(12.0, 0.2)]), entry_mm=e_mm)
    rows = s.rows()
    assert session_metrics(rows, cfg, tissue)["per_insertion"][0]["angle_deg"] == pytest.approx(10.0, abs=0.05)
    assert session_metrics(rows, cfg)["per_insertion"][0]["angle_deg"] == pytest.approx(0.0, abs=1e-6)


# --------------------------------------------------------------------------------- insertions, forces
def test_reentry_through_the_hole_is_a_new_insertion(cfg):
    s = Session()
    s.insertion(np.concatenate([ramp(10.0, 6.0), hold(6.0, 0.5)]))
    s.hold_outside(1.0)
    ph = s.insertion(np.concatenate([ramp(10.0, 12.0), hold(12.0, 0.5)]), through_hole=True)
    m = session_metrics(s.rows(), cfg)
    assert m["insertions"] == 2 and m["skin_punctures"] == 1
    first, second = m["per_insertion"]
    assert first["skin_punctured"] is True and second["skin_punctured"] is False
    # the re-entry's entry is the tip at its first tick inside (no pressing phase)
    t_in = ph["inside"][0, COL["t_s"]]
    assert second["t_entry_s"] == pytest.approx(t_in, abs=1e-9) == second["t_inside_s"]
    assert second["entry_mm"] == pytest.approx([0.0, 0.0, 0.0], abs=1e-3)
    assert second["time_to_target_s"] == pytest.approx(10.0 / 10.0, abs=2 * DT)
    assert first["time_to_target_s"] is None
    assert m["time_in_tissue_s"] == pytest.approx(first["time_in_tissue_s"] + second["time_in_tissue_s"], abs=1e-4)


def test_two_sites_and_no_insertion(cfg):
    s = Session()
    s.insertion(np.concatenate([ramp(10.0, 6.0), hold(6.0, 0.2)]))
    s.insertion(np.concatenate([ramp(10.0, 6.0), hold(6.0, 0.2)]), entry_mm=(5.0, 0.0, 0.0))
    m = session_metrics(s.rows(), cfg)
    assert m["insertions"] == 2 and m["skin_punctures"] == 2
    assert [i["entry_offset_mm"] for i in m["per_insertion"]] == pytest.approx([0.0, 5.0], abs=1e-3)
    # pressing without breaking the skin is no insertion
    rows = s.rows()
    rows[:, COL["state_skin"]] = np.minimum(rows[:, COL["state_skin"]], 1)
    m = session_metrics(rows, cfg)
    assert m["insertions"] == 0 and m["time_in_tissue_s"] == 0.0 and m["per_insertion"] == []


def test_peak_force_per_layer_includes_the_pressing_phase(cfg):
    s = Session()
    ph = s.insertion(np.concatenate([ramp(10.0, 15.0), hold(15.0, 0.3)]))
    press = ph["approach"][:, COL["state_skin"]] == 1
    k = int(np.count_nonzero(press))
    ph["approach"][press, COL["f_skin_n"]] = np.linspace(0.0, 1.43, k)  # skin surface force up to the break
    n_in = len(ph["inside"])
    ph["inside"][:, COL["f_fat_n"]] = 0.61 * np.sin(np.linspace(0, np.pi, n_in))
    ph["out"][:, COL["f_muscle_n"]] = -0.37  # damping on withdrawal pulls the other way: |F| counts
    f = np.zeros((n_in, 3))
    f[:, 2] = np.linspace(0.0, 1.9, n_in)
    f[:, 0] = 0.3
    ph["inside"][:, COL["fx_n"]:COL["fx_n"] + 3] = f
    s.hold_outside(0.1)
    s.blocks[-1][:, COL["f_skin_n"]] = 2.5  # outside any insertion: not counted
    ins = session_metrics(s.rows(), cfg)["per_insertion"][0]
    assert ins["peak_layer_force_n"] == pytest.approx({"skin": 1.43, "fat": 0.61, "muscle": 0.37}, abs=1e-4)
    assert ins["peak_total_force_n"] == pytest.approx(math.hypot(1.9, 0.3), abs=1e-4)


def test_lateral_force_above_the_comfort_bound(cfg):
    s = Session()
    ph = s.insertion(np.concatenate([ramp(10.0, 15.0), hold(15.0, 1.0)]))
    ph["approach"][:, COL["f_lateral_n"]] = 0.9  # not inside: not counted
    lat = np.full(len(ph["inside"]), 0.3)
    lat[1000:1250] = 0.8
    lat[1100] = 0.95
    ph["inside"][:, COL["f_lateral_n"]] = lat
    m = session_metrics(s.rows(), cfg)
    assert m["lateral_comfort_n"] == 0.5
    ins = m["per_insertion"][0]
    assert ins["lateral"] == {"ticks_over": 250, "time_over_s": pytest.approx(0.25, abs=1e-9), "max_n": 0.95}
    assert m["lateral"]["ticks_over"] == 250
    low = session_metrics(s.rows(), cfg, lateral_comfort_n=0.2)
    assert low["per_insertion"][0]["lateral"]["ticks_over"] == len(ph["inside"])


def test_json_ready_and_deterministic(cfg):
    s = Session()
    s.insertion(np.concatenate([ramp(10.0, 20.0), cosine_strokes(20.0, 3.0, 0.7, 2)]), direction=(0.2, 0.1, -1.0))
    rows = s.rows()
    a = json.dumps(session_metrics(rows, cfg), allow_nan=False, sort_keys=True)
    b = json.dumps(session_metrics(rows.copy(), cfg), allow_nan=False, sort_keys=True)
    assert a == b and "-0.0" not in a


def test_bad_rows_shape(cfg):
    with pytest.raises(ValueError, match="shape"):
        session_metrics(np.zeros((5, NCOL - 1)), cfg)
    assert session_metrics(np.zeros((0, NCOL)), cfg)["insertions"] == 0


# ----------------------------------------------------------------------- end to end: bundled sessions
@pytest.fixture(scope="module")
def bundled(cfg):
    from haptic_acu.devices.scripted import ScriptedDevice
    from haptic_acu.session.engine import Session as EngineSession
    from haptic_acu.servo.step import NeedleModel
    from haptic_acu.tissue.body import Tissue

    tissue = Tissue.from_config(cfg)

    class Collect(Sink):
        def __init__(self):
            self.rows = []

        def on_frame(self, frame):
            self.rows.append(frame.samples)

    def run(name):
        dev = ScriptedDevice(ROOT / "trajectories" / f"{name}.csv", force_limit_n=cfg.safety.force_limit_n)
        dev.open()
        sink = Collect()
        session = EngineSession(cfg, dev, [sink], clock="sim", model=NeedleModel(cfg, tissue), dents=False)
        result = session.run()
        assert result.fault is None
        return session_metrics(np.concatenate(sink.rows), cfg, tissue)

    return run


@pytest.mark.slow
def test_bundled_default(bundled):
    m = bundled("default")
    assert m["insertions"] == 1 and m["skin_punctures"] == 1
    ins = m["per_insertion"][0]
    lt = ins["lift_thrust"]  # README: 4 lift-thrust cycles, lift 4 mm, 0.75 Hz
    assert lt["cycles"] == 4
    assert lt["mean_amplitude_mm"] == pytest.approx(4.0, abs=0.1)
    assert lt["frequency_hz"] == pytest.approx(0.75, abs=0.01)
    assert ins["insertion_speed_mm_s"] == pytest.approx(10.0, rel=0.02)  # README: 10 mm/s
    assert ins["angle_deg"] == pytest.approx(0.0, abs=0.5)
    assert ins["entry_offset_mm"] < 0.1
    # to z = -30 mm: the physical depth below the rest skin along the axis (docs/model.md s3)
    assert ins["max_depth_mm"] == pytest.approx(30.0, abs=0.05)


@pytest.mark.slow
def test_bundled_second_insertion_same_site(bundled):
    m = bundled("second_insertion_same_site")
    assert m["insertions"] == 2
    assert m["skin_punctures"] == 1  # the second pass goes through the hole
    assert [i["entry_offset_mm"] < 0.2 for i in m["per_insertion"]] == [True, True]


@pytest.mark.slow
def test_bundled_oblique_entry(bundled):
    m = bundled("oblique_entry")
    assert m["insertions"] == 1
    ins = m["per_insertion"][0]
    assert ins["angle_deg"] == pytest.approx(30.0, abs=1.0)  # its generator tilts the needle 30 degrees
    assert ins["entry_offset_mm"] < 0.1  # it enters at the acupoint


@pytest.mark.slow
def test_bundled_lateral_sweep(bundled):
    m = bundled("lateral_sweep")
    assert m["insertions"] == 0 and m["time_in_tissue_s"] == 0.0


def test_find_troughs_matches_scipy_find_peaks():
    """metrics.find_troughs is scipy.signal.find_peaks(-x, prominence=p), without importing scipy.signal:
    random walks (ties from quantisation included), noisy strokes, plateaus, edges."""
    from scipy.signal import find_peaks

    from haptic_acu.analysis.metrics import find_troughs

    rng = np.random.default_rng(7)
    signals = [np.round(np.cumsum(rng.normal(size=2000)), 1),
               np.round(np.cumsum(rng.integers(-1, 2, size=3000)) * 0.055, 3),
               20 + 2 * np.cos(np.linspace(0, 30, 5000)) + rng.normal(scale=0.05, size=5000),
               np.array([0, 1, 1, 1, 0, 2, 2, 0, 0, 3, 3, 3, 3, 1, 1, 5, 5]),
               np.array([5, 4, 4, 4]), np.array([1.0, 2.0]), np.zeros(10)]
    for x in signals:
        for prom in (0.0, 0.5, 1.0, 3.0):
            want, props = find_peaks(-x, prominence=prom)
            got, got_prom = find_troughs(x, prom)
            assert np.array_equal(got, want), (x[:20], prom)
            np.testing.assert_allclose(got_prom, props["prominences"], rtol=0, atol=1e-12)


# ------------------------------------------------------------------------- streamed = whole-array
def _cohort_of_insertions(end_inside: bool):
    s = Session()
    s.hold_outside(0.1)
    s.insertion(np.concatenate([ramp(10.0, 12.0), cosine_strokes(12.0, 2.0, 2.0, 3)]))
    s.hold_outside(0.05)
    s.insertion(ramp(6.0, 8.0), entry_mm=(1.0, -0.5, 0.0), direction=(0.2, 0.0, -1.0), through_hole=True)
    s.insertion(np.concatenate([ramp(12.0, 18.0), hold(18.0, 0.3)]), dent_mm=1.0)
    if end_inside:  # the session ends with the needle in: the open insertion is measured at the end
        s.hold_outside(0.02)
        s.insertion(ramp(9.0, 5.0))
        s.blocks.pop()  # no withdrawal
    return s.rows()


@pytest.mark.parametrize("end_inside", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_streamed_metrics_equal_the_whole_array_metrics(cfg, end_inside, seed):
    """SessionMetricsScan (what a replay uses, bounded memory) gives exactly session_metrics' dict for
    the same rows cut into random blocks (1 row to thousands), insertions crossing block edges."""
    from haptic_acu.analysis.metrics import SessionMetricsScan
    rows = _cohort_of_insertions(end_inside)
    punct = [{"layer": "skin", "t_s": round(float(t), 4), "tip_depth_mm": 1.0, "peak_force_n": 0.5}
             for t in rows[rows[:, COL["puncture"]] == 0, COL["t_s"]]]
    whole = session_metrics(rows, cfg, punctures=punct)
    assert whole["insertions"] == (4 if end_inside else 3)
    rng = np.random.default_rng(seed)
    scan = SessionMetricsScan(cfg)
    i = 0
    while i < len(rows):
        k = int(rng.choice([1, 2, 7, 100, 2048, 5000]))
        scan.feed(rows[i:i + k])
        i += k
    got = scan.result(punct)
    assert json.dumps(got, sort_keys=True) == json.dumps(whole, sort_keys=True)
    entries = [m for m in scan.entries]
    assert len(entries) == whole["insertions"]
    assert [round(float(rows[e, COL["t_s"]]), 4) for e in entries] == [m["t_entry_s"] for m in whole["per_insertion"]]


def test_median_counter_is_numpy_median():
    from haptic_acu.analysis.metrics import MedianCounter
    rng = np.random.default_rng(3)
    for n in (1, 2, 3, 10, 11, 1000):
        x = rng.choice([0.001, 0.0010000000000000009, 0.0009999999999999998, 0.002], size=n)
        m = MedianCounter()
        m.add(x[: n // 2])
        m.add(x[n // 2:])
        assert m.median() == np.median(x)

"""Technique metrics (haptic_acu.analysis.technique) on synthetic manipulations of known amplitude, frequency
and speed: the answers are the closed forms of the signals."""
from __future__ import annotations

import numpy as np
import pytest

from haptic_acu.analysis import technique as TQ

DT = 1e-3


def sine_roll(amp_deg, freq_hz, periods, hold_s=1.0):
    n_hold = int(hold_s / DT)
    t_tw = np.arange(int(round(periods / freq_hz / DT))) * DT
    roll = np.concatenate([np.zeros(n_hold), amp_deg * np.sin(2 * np.pi * freq_hz * t_tw),
                           np.zeros(n_hold)])
    return np.arange(len(roll)) * DT, roll


@pytest.mark.parametrize("amp, freq, periods", [(45.0, 1.3, 5), (135.0, 2.5, 8), (20.0, 0.5, 3)])
def test_sinusoidal_twirl(amp, freq, periods):
    t, roll = sine_roll(amp, freq, periods)
    m = TQ.twirl_metrics(t, roll)
    assert m["cycles"] == periods and m["reversals"] == 2 * periods
    assert "amplitude_deg" not in m  # one twirl amplitude: the swing, peak to peak
    assert m["swing_deg"] == pytest.approx(2 * amp, abs=0.02)
    assert m["frequency_hz"] == pytest.approx(freq, rel=1e-3)
    assert m["net_rotation_deg"] == pytest.approx(0.0, abs=0.01 * amp)
    assert m["total_rotation_deg"] == pytest.approx(4 * amp * periods, rel=1e-4)
    assert m["mean_speed_deg_s"] == pytest.approx(4 * amp * freq, rel=1e-3)


@pytest.mark.parametrize("cycles", [1, 2, 7])
def test_one_sided_cosine_twirl(cycles):
    """0 -> S -> 0 back and forth from rest at one end of the swing: 2N - 1 reversals, N cycles."""
    swing, freq = 90.0, 1.5
    t = np.arange(int(round(cycles / freq / DT)) + 1001) * DT
    roll = np.where(t < cycles / freq, 0.5 * swing * (1 - np.cos(2 * np.pi * freq * t)), 0.0)
    m = TQ.twirl_metrics(t, roll)
    assert m["cycles"] == cycles and m["reversals"] == 2 * cycles - 1
    assert m["swing_deg"] == pytest.approx(swing, abs=0.01) if cycles > 1 else m["swing_deg"] is None
    if cycles > 1:
        assert m["frequency_hz"] == pytest.approx(freq, rel=1e-3)


def test_twirl_metrics_ignore_jitter_below_the_hysteresis():
    t, roll = sine_roll(60.0, 1.0, 4)
    rng = np.random.default_rng(1)
    noisy = roll + rng.uniform(-1.0, 1.0, roll.size)  # +-1 deg, well under the 5 deg hysteresis
    m = TQ.twirl_metrics(t, noisy)
    assert m["cycles"] == 4
    assert m["swing_deg"] == pytest.approx(120.0, abs=2.0)
    assert m["frequency_hz"] == pytest.approx(1.0, rel=0.01)


def test_unidirectional_rotation_and_peak_torque():
    t = np.arange(2001) * DT
    roll = 720.0 * t  # two turns per second, one way
    torque = 0.1 * np.sin(3 * t) - 0.25 * t ** 2
    m = TQ.twirl_metrics(t, roll, torque)
    assert m["cycles"] == 0 and m["frequency_hz"] is None and m["swing_deg"] is None
    assert m["net_rotation_deg"] == pytest.approx(1440.0) == m["total_rotation_deg"]
    assert m["peak_torque_nmm"] == pytest.approx(np.abs(torque).max(), abs=1e-4)


def test_turning_points_of_a_known_zigzag():
    x = np.array([0, 2, 10, 9, 3, 4, 12, 12, 11, 5, 5, 6])
    assert TQ.turning_points(x, 5.0).tolist() == [2, 4, 6]
    assert TQ.turning_points(-x, 5.0).tolist() == [2, 4, 6]
    assert TQ.turning_points([0, 1, 2, 3], 1.0).tolist() == []
    with pytest.raises(ValueError):
        TQ.turning_points(x, 0.0)


def piecewise_depth(knots):
    """Depth (mm) through (time s, depth mm) knots, linear between, sampled at DT."""
    kt, kd = np.array(knots, dtype=float).T
    t = np.arange(int(round(kt[-1] / DT)) + 1) * DT
    return t, np.interp(t, kt, kd)


def lift_thrust_session(v_thrust, v_lift, cycles=3, stroke=4.0, depth=20.0):
    knots = [(0.0, -5.0), (0.5, -5.0)]
    knots.append((knots[-1][0] + (depth + 5.0) / 10.0, depth))
    knots.append((knots[-1][0] + 0.5, depth))
    for _ in range(cycles):
        knots.append((knots[-1][0] + stroke / v_lift, depth - stroke))
        knots.append((knots[-1][0] + stroke / v_thrust, depth))
    knots.append((knots[-1][0] + 0.5, depth))
    knots.append((knots[-1][0] + (depth + 5.0) / 10.0, -5.0))
    return piecewise_depth(knots)


def test_stroke_forces_with_a_viscous_resistance():
    """Resistance c * speed: thrust/lift resistance is v_thrust / v_lift."""
    t, d = lift_thrust_session(v_thrust=8.0, v_lift=4.0)
    c = 0.05  # N per mm/s
    f_axial = c * np.gradient(d, t)  # pushes out while thrusting, pulls in while lifting
    m = TQ.stroke_forces(t, d, f_axial)
    assert m["thrusts"] == 3 and m["lifts"] == 3
    assert m["thrust_speed_mm_s"] == pytest.approx(8.0, rel=0.02)
    assert m["lift_speed_mm_s"] == pytest.approx(4.0, rel=0.02)
    assert m["thrust_resistance_n"] == pytest.approx(c * 8.0, rel=0.02)
    assert m["lift_resistance_n"] == pytest.approx(c * 4.0, rel=0.02)
    assert m["thrust_to_lift"] == pytest.approx(2.0, rel=0.02)


def test_no_lift_thrust_means_no_strokes():
    t, d = piecewise_depth([(0, -5), (3.0, 25.0), (4.0, 25.0), (7.0, -5.0)])
    m = TQ.stroke_forces(t, d, np.zeros_like(t))
    assert m["thrusts"] == m["lifts"] == 0 and m["thrust_to_lift"] is None


def test_grasp_felt_compares_the_withdrawal_only():
    t, d = lift_thrust_session(v_thrust=6.0, v_lift=6.0)
    w = TQ.withdrawal_window(d)
    assert d[w.start] == pytest.approx(20.0) and d[w.stop - 1] <= 0.0
    assert np.all(np.diff(d[w]) <= 1e-12)
    ref = -0.3 * (np.gradient(d, t) < -1.0)  # 0.3 N against every lift, none otherwise
    g = 2.2
    with_rot = ref.copy()
    with_rot[w] *= g
    with_rot[: w.start] *= 10.0  # the lifts before the withdrawal do not count
    m = TQ.grasp_felt(d, with_rot, ref)
    assert m["peak_ratio"] == pytest.approx(g, rel=1e-9)
    assert m["mean_ratio"] == pytest.approx(g, rel=1e-9)
    assert m["reference_peak_n"] == pytest.approx(0.3)


@pytest.mark.parametrize("swing, freq, ratio, label, tv, lv", [
    (60.0, 0.75, 1.6, "reinforcing", "reinforcing", "reinforcing"),
    (270.0, 2.5, 0.6, "reducing", "reducing", "reducing"),
    (180.0, 1.5, 1.0, "even", "even", "even"),
    (60.0, 0.75, 1.0, "reinforcing", "reinforcing", "even"),
    (60.0, 0.75, 0.6, "even", "reinforcing", "reducing"),  # contradictory: they cancel
    (60.0, 2.5, None, "even", "even", None),  # small but fast: not the rule's reinforcing
    (None, None, 0.6, "reducing", None, "reducing"),
])
def test_classification_rule(swing, freq, ratio, label, tv, lv):
    tw = {"cycles": 0 if swing is None else 5, "swing_deg": swing, "frequency_hz": freq}
    st = {"thrust_to_lift": ratio, "thrust_speed_mm_s": None, "lift_speed_mm_s": None}
    c = TQ.classify(tw, st)
    assert (c["label"], c["twirl_vote"], c["lift_thrust_vote"]) == (label, tv, lv)
    assert c["inputs"]["swing_deg"] == swing and c["inputs"]["thrust_to_lift"] == ratio
    assert "Chinese Acupuncture and Moxibustion" in c["source"]


def test_nothing_to_classify():
    t, d = piecewise_depth([(0, -5), (3.0, 25.0), (4.0, 25.0), (7.0, -5.0)])
    m = TQ.technique_metrics({"t_s": t, "depth_mm": d})
    assert m["classification"]["label"] is None
    assert m["twirl"]["cycles"] == 0 and m["grasp_felt"] is None


def test_technique_metrics_on_a_structured_table():
    t, d = lift_thrust_session(v_thrust=8.0, v_lift=4.0)
    roll = 30.0 * np.sin(2 * np.pi * 0.8 * t)  # swing 60 deg at 0.8 Hz: small and slow
    f = 0.05 * np.gradient(d, t)
    table = np.zeros(t.size, dtype=[("t_s", float), ("depth_mm", float), ("roll_deg", float),
                                    ("torque_nmm", float), ("f_axial_n", float)])
    table["t_s"], table["depth_mm"], table["roll_deg"], table["f_axial_n"] = t, d, roll, f
    table["torque_nmm"] = 0.001 * roll
    ref = {"f_axial_n": f}
    m = TQ.technique_metrics(table, reference=ref)
    assert m["twirl"]["frequency_hz"] == pytest.approx(0.8, rel=2e-3)
    assert m["twirl"]["peak_torque_nmm"] == pytest.approx(0.03, abs=1e-4)
    assert m["classification"]["label"] == "reinforcing"
    assert m["grasp_felt"]["peak_ratio"] == pytest.approx(1.0)

"""Skill metrics (haptic_acu.analysis.skill_metrics) against closed forms on synthetic paths."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from haptic_acu.analysis import skill_metrics as sm

# Minimum-jerk point-to-point movement x(tau) = A (10 tau^3 - 15 tau^4 + 6 tau^5), tau = t / T:
# v = 30 A/T tau^2 (1 - tau)^2, v_peak = 15 A / (8 T), d2v/dt2 = A/T^3 (60 - 360 tau + 360 tau^2),
# integral of (d2v/dt2)^2 over [0, T] = 720 A^2 / T^5, so the speed-based dimensionless jerk is
# T^3 / v_peak^2 * 720 A^2 / T^5 = 720 * 64 / 225 = 204.8 and LDLJ = -ln 204.8, whatever A and T.
LDLJ_MIN_JERK = -math.log(720 * 64 / 225)
# Raised-cosine speed v = (A/T)(1 - cos 2 pi tau): v_peak = 2A/T, d2v/dt2 = 4 pi^2 A/T^3 cos 2 pi tau,
# integral = 8 pi^4 A^2 / T^5, dimensionless jerk = 2 pi^4.
LDLJ_RAISED_COSINE = -math.log(2 * math.pi ** 4)


def min_jerk(t, T, start, end):
    tau = np.clip(t / T, 0.0, 1.0)
    s = tau ** 3 * (10 - 15 * tau + 6 * tau ** 2)
    return np.asarray(start) + s[:, None] * (np.asarray(end) - np.asarray(start))


def test_straight_line_economy_is_one_and_length_is_the_distance():
    t = np.linspace(0.0, 1.2, 1201)
    a, b = np.array([0.001, -0.002, 0.005]), np.array([0.004, 0.003, -0.020])
    p = min_jerk(t, 1.2, a, b)
    assert sm.path_length(p) == pytest.approx(np.linalg.norm(b - a), rel=1e-12)
    assert sm.economy_of_motion(p) == pytest.approx(1.0, abs=1e-12)
    # still 1 after the low-pass (a straight path stays on its line)
    assert sm.economy_of_motion(sm.smooth_path(t, p)) == pytest.approx(1.0, abs=1e-9)


def test_detours_against_closed_forms():
    # two perpendicular legs of equal length L: straight sqrt(2) L over path 2 L
    leg = np.linspace(0.0, 0.01, 101)
    p = np.vstack([np.column_stack([leg, 0 * leg, 0 * leg]), np.column_stack([0 * leg[1:] + 0.01, leg[1:], 0 * leg[1:]])])
    assert sm.economy_of_motion(p) == pytest.approx(math.sqrt(2) / 2, rel=1e-12)
    # a semicircle of radius r: chord 2r over arc pi r (the polyline's arc converges as n^-2)
    th = np.linspace(0.0, math.pi, 20001)
    r = 0.007
    arc = np.column_stack([r * np.cos(th), r * np.sin(th), np.zeros_like(th)])
    assert sm.path_length(arc) == pytest.approx(math.pi * r, rel=1e-7)
    assert sm.economy_of_motion(arc) == pytest.approx(2 / math.pi, rel=1e-7)
    # out and back: no net displacement
    back = np.vstack([p[:101], p[:100][::-1]])
    assert sm.economy_of_motion(back) == pytest.approx(0.0, abs=1e-12)
    assert sm.economy_of_motion(np.zeros((10, 3))) is None


@pytest.mark.parametrize("amplitude_m, duration_s", [(0.02, 0.8), (0.005, 2.5), (0.03, 0.3)])
def test_ldlj_of_minimum_jerk_is_minus_ln_204_8(amplitude_m, duration_s):
    t = np.linspace(0.0, duration_s, 1001)  # the same relative resolution for every duration
    p = min_jerk(t, duration_s, [0, 0, 0], [amplitude_m * 0.6, 0, -amplitude_m * 0.8])
    assert sm.ldlj(t, p) == pytest.approx(LDLJ_MIN_JERK, abs=0.02)


def test_ldlj_of_raised_cosine_speed():
    T, A = 1.5, 0.01
    t = np.arange(0.0, T + 1e-9, 1e-3)
    v = A / T * (1 - np.cos(2 * math.pi * t / T))
    assert sm.ldlj_of_speed(t, v) == pytest.approx(LDLJ_RAISED_COSINE, abs=0.01)


def test_ldlj_ranks_stop_and_go_below_one_smooth_movement():
    t = np.arange(0.0, 2.0, 1e-3)
    one = min_jerk(t, 2.0, [0, 0, 0], [0, 0, -0.02])
    two = np.where(t[:, None] < 1.0, min_jerk(t, 1.0, [0, 0, 0], [0, 0, -0.01]),
                   min_jerk(t - 1.0, 1.0, [0, 0, -0.01], [0, 0, -0.02]))
    assert sm.ldlj(t, two) < sm.ldlj(t, one) - 1.0


def test_smoothing_recovers_the_closed_form_from_a_200hz_file_interpolated_to_1khz():
    # what a replay sees: a trajectory file at 200 Hz, linearly interpolated to the 1 kHz servo rate
    T = 1.0
    t_file = np.arange(-0.5, T + 0.5 + 1e-9, 1 / 200)
    p_file = min_jerk(np.clip(t_file, 0, T), T, [0, 0, 0], [0, 0, -0.02])
    t = np.arange(-0.5, T + 0.5 + 1e-9, 1e-3)
    p = np.column_stack([np.interp(t, t_file, p_file[:, k]) for k in range(3)])
    w = (t >= -1e-9) & (t <= T + 1e-9)
    raw = sm.ldlj(t[w], p[w])
    smooth = sm.ldlj(t[w], sm.smooth_path(t, p)[w])
    assert raw < LDLJ_MIN_JERK - 2.0  # the interpolant's velocity steps swamp the jerk
    assert smooth == pytest.approx(LDLJ_MIN_JERK, abs=0.06)


def test_ldlj_undefined_for_no_movement():
    t = np.arange(0.0, 1.0, 1e-3)
    assert sm.ldlj(t, np.zeros((t.size, 3))) is None
    assert sm.ldlj(t[:3], np.zeros((3, 3))) is None


@settings(max_examples=25, deadline=None)
@given(scale=st.floats(0.1, 10.0), stretch=st.floats(0.5, 3.0), seed=st.integers(0, 10_000))
def test_ldlj_is_dimensionless_and_economy_in_unit_interval(scale, stretch, seed):
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, 801)
    # a random smooth path: a few sines per coordinate, zero velocity at neither end
    c = rng.normal(size=(3, 3)) * 0.01
    p = np.stack([sum(c[k, j] * np.sin((j + 1) * np.pi * t) for j in range(3)) for k in range(3)], axis=1)
    base = sm.ldlj(t, p)
    assert sm.ldlj(t, scale * p) == pytest.approx(base, abs=1e-9)  # amplitude
    assert sm.ldlj(stretch * t, p) == pytest.approx(base, abs=1e-9)  # duration
    e = sm.economy_of_motion(p)
    assert e is None or 0.0 <= e <= 1.0 + 1e-12

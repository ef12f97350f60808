"""Twirl kernels (haptic_acu.tissue.twirl): torque against angle (Han 2015's line and the closed form of a
relaxing twist), the pull-out protocols against Langevin 2001's ratios (stand-in: baseline friction
times the grasp factor; the test through the real friction runs once the kernels are wired into
the step), unwinding, encoder jitter, dilution, the roll unwrapping, and the kernels against a
second, plain-Python implementation."""
from __future__ import annotations

import math

import numpy as np
import pytest

from haptic_acu.tissue import twirl as T

LENGTHS = np.array([0.8e-3, 8.4e-3, 20.8e-3])  # 30 mm in skin, fat, muscle
DT = 1e-3


def run(roll, length=LENGTHS, p=None, ws=None, dt=DT):
    """Drive wind_step with a roll series (rad); returns (total torque per tick, state)."""
    p = T.default_params() if p is None else p
    ws = T.new_wind_state(len(length)) if ws is None else ws
    length = np.asarray(length, float)
    out = np.empty(len(roll))
    for k, r in enumerate(roll):
        out[k] = T.wind_step(ws, float(r), length if length.ndim == 1 else length[k], dt, p)
    return out, ws


def sine_twirl(swing_rad, freq_hz, cycles, dt=DT):
    t = np.arange(int(round(cycles / freq_hz / dt)) + 1) * dt
    return t, 0.5 * swing_rad * np.sin(2 * np.pi * freq_hz * t)


def last_cycle_range(t, x, freq_hz):
    m = t >= t[-1] - 1.0 / freq_hz
    return float(x[m].max() - x[m].min())


# ------------------------------------------------------------------------------------ torque-angle
def test_torque_range_is_linear_in_swing_on_hans_line():
    swings = np.radians([60.0, 90.0, 120.0, 150.0, 180.0])
    ranges = []
    for s in swings:
        t, roll = sine_twirl(s, T.HAN_FREQ_HZ, 3)
        tq, _ = run(roll)
        ranges.append(last_cycle_range(t, tq, T.HAN_FREQ_HZ))
    ranges = np.array(ranges)
    slope, icept = np.polyfit(swings, ranges, 1)
    # linear through the origin (play of 1 deg costs at most 1 deg of swing)
    assert abs(icept) < 0.02 * ranges[0]
    resid = ranges - np.polyval([slope, icept], swings)
    assert np.abs(resid).max() < 1e-3 * ranges.max()
    # the slope is Han's least-squares line (the play removes 1 deg of each swing)
    eff = (swings - T.PLAY_RAD) / swings
    assert ranges / eff == pytest.approx(T.han_torque_slope() * swings, rel=2e-3)
    # and the published points: 0.082 N*mm at 60 deg (+17%: a line through the origin cannot
    # meet both) and 0.292 N*mm at 180 deg (-1.6% from the fit, -0.6% from the play)
    assert ranges[0] * 1e3 == pytest.approx(0.082, rel=0.2)
    assert ranges[-1] * 1e3 == pytest.approx(0.292, rel=0.03)


def test_relaxing_twist_matches_the_maxwell_closed_form():
    """A twist relaxing with tau under a sinusoidal twirl: torque range = k L S w tau/sqrt(1+(w tau)^2)."""
    tau, f, swing = 0.5, 0.5, math.radians(90.0)
    p = T.default_params()._replace(twist_tau_s=np.full(3, tau), play_rad=0.0)
    t, roll = sine_twirl(swing, f, 6)
    tq, _ = run(roll, p=p)
    expect = p.k_twist[0] * LENGTHS.sum() * swing * T.maxwell_range_factor(f, tau)
    assert last_cycle_range(t, tq, f) == pytest.approx(expect, rel=3e-3)
    assert T.maxwell_range_factor(f, tau) < 0.9  # the relaxation matters here


def test_torque_sign_follows_roll_and_saturates_at_slip():
    p = T.default_params()._replace(play_rad=0.0)
    tq, ws = run(np.linspace(0, math.radians(30.0), 50), p=p)
    assert tq[-1] > 0
    tq, ws = run(-np.linspace(0, 3 * 2 * np.pi, 3000), p=p)  # three turns counter-clockwise
    k_l = p.k_twist * LENGTHS
    assert ws.torque_nm == pytest.approx(-k_l * T.TWIST_SLIP_RAD, rel=1e-12)
    assert tq[-1] == pytest.approx(-(k_l * T.TWIST_SLIP_RAD).sum(), rel=1e-12)


# ------------------------------------------------------------------------------------------ grasp
def test_protocols_reproduce_langevins_pullout_ratios():
    uni, bi = T.pullout_ratios()
    assert uni == pytest.approx(T.LANGEVIN_UNI_RATIO, rel=0.01)
    assert bi == pytest.approx(T.LANGEVIN_BI_RATIO, rel=0.01)


def test_default_gains_are_the_calibration():
    coil, engage = T.calibrate_grasp()
    assert coil == pytest.approx(T.GRASP_COIL, abs=2e-4)
    assert engage == pytest.approx(T.GRASP_ENGAGE, abs=2e-4)


def test_pullout_standin_is_friction_times_grasp_layer_by_layer():
    fric = np.array([0.05, 0.2, 0.6])
    f, ws = T.run_protocol(T.UNI, friction_n=fric)
    assert f == pytest.approx(float(ws.grasp @ fric), rel=1e-12)
    f_no, _ = T.run_protocol(T.NO, friction_n=fric)
    assert f_no == pytest.approx(fric.sum(), rel=1e-12)


def test_unwinding_releases_the_grasp():
    p = T.default_params()
    wind = np.linspace(0, 2 * 2 * np.pi, 2001)  # two turns in 2 s
    _, ws = run(wind, p=p)
    g_wound = ws.grasp.copy()
    held = float(ws.twist_rad[0])
    assert held == pytest.approx(T.TWIST_SLIP_RAD, rel=0.1)
    # rotate back (2 turns/s) until the torque is gone, as a hand unwinds until the needle is free
    ws_back = T.WindState(*[a.copy() for a in ws])
    r, back = float(wind[-1]), []
    while T.wind_step(ws_back, r, LENGTHS, DT, p) > 0.0:
        r -= 2 * 2 * np.pi * DT
        back.append(r)
    assert len(back) < 1000
    coil_left = p.grasp_coil * np.abs(ws_back.twist_rad) / p.twist_slip_rad
    assert coil_left.max() < 0.02
    assert (ws_back.grasp < g_wound - 1.0).all()  # most of the grasp went with the unwinding
    # holding instead of unwinding keeps it
    _, ws_hold = run(np.full(1000, wind[-1]), p=p, ws=T.WindState(*[a.copy() for a in ws]))
    assert (ws_hold.grasp > ws_back.grasp + 1.0).all()
    # and time releases the rest
    _, ws_rest = run(np.full(int(5 * T.ENGAGE_TAU_S / 0.01), back[-1]), p=p, ws=ws_back, dt=0.01)
    assert ws_rest.grasp == pytest.approx(np.ones(3), abs=0.01)


def test_encoder_jitter_winds_nothing():
    rng = np.random.default_rng(3)
    jitter = np.radians(0.45) * rng.choice([-1.0, 1.0], size=5000)  # +-0.45 deg every tick
    jitter[0] = 0.0  # the stylus at rest, then its encoder flickers
    _, ws = run(jitter)
    assert np.all(ws.engage == 0.0) and np.all(ws.twist_rad == 0.0)
    assert np.all(ws.grasp == 1.0)


def test_engagement_under_steady_rotation_matches_closed_form():
    """de/dt = (1 - e) w / theta_e - e / tau_e: e(t) = e_inf (1 - exp(-(w/theta_e + 1/tau_e) t))."""
    w = 2 * np.pi * 0.5  # half a turn per second
    t = np.arange(20001) * DT
    p = T.default_params()._replace(play_rad=0.0)
    es = []
    ws = T.new_wind_state()
    for r in w * t:
        T.wind_step(ws, float(r), LENGTHS, DT, p)
        es.append(ws.engage[0])
    rate = w / T.ENGAGE_RAD + 1 / T.ENGAGE_TAU_S
    e_inf = (w / T.ENGAGE_RAD) / rate
    expect = e_inf * (1 - np.exp(-rate * t))
    assert np.abs(np.array(es) - expect).max() < 2e-3


def test_advancing_dilutes_withdrawing_keeps_leaving_clears():
    p = T.default_params()._replace(twist_tau_s=np.full(3, 1e12), engage_tau_s=np.full(3, 1e12),
                                    play_rad=0.0)
    L0 = np.array([1e-3, 5e-3, 4e-3])
    _, ws = run(np.linspace(0, 1.0, 101), length=L0, p=p)
    wound = ws.twist_rad * ws.length_m
    eng = ws.engage * ws.length_m
    L1 = np.array([1e-3, 5e-3, 12e-3])  # advance 8 mm into fresh muscle
    run(np.full(10, 1.0), length=L1, p=p, ws=ws)
    assert ws.twist_rad * ws.length_m == pytest.approx(wound, rel=1e-12)
    assert ws.engage * ws.length_m == pytest.approx(eng, rel=1e-12)
    twist = ws.twist_rad.copy()
    run(np.full(10, 1.0), length=np.array([1e-3, 5e-3, 2e-3]), p=p, ws=ws)  # withdraw
    assert ws.twist_rad == pytest.approx(twist, rel=1e-12)
    run(np.full(2, 1.0), length=np.array([1e-3, 5e-3, 0.0]), p=p, ws=ws)  # out of the muscle
    assert ws.twist_rad[2] == 0 and ws.engage[2] == 0 and ws.grasp[2] == 1 and ws.torque_nm[2] == 0


# ------------------------------------------------------------------------------------------- roll
def test_roll_unwraps_a_wrapped_angle_and_tracks_its_rate():
    rp = T.default_roll_params()
    turns_per_s, secs = 2.5, 3.0
    t = np.arange(int(secs / DT) + 1) * DT
    start = 2.9  # near the wrap
    cum = start + 2 * np.pi * turns_per_s * t
    wrapped = np.angle(np.exp(1j * cum))
    rs = T.new_roll_state()
    angles = []
    for w in wrapped:
        assert T.roll_from_wrapped(rs, float(w), DT, rp)
        angles.append(rs.angle[0])
    assert np.array(angles) == pytest.approx(cum - start, abs=1e-9)
    assert rs.rate[0] == pytest.approx(2 * np.pi * turns_per_s, rel=1e-6)


def test_roll_from_cumulative_and_refusing_non_finite():
    rp = T.default_roll_params()
    rs = T.new_roll_state()
    assert T.roll_from_cumulative(rs, 1.0, DT, rp)
    assert rs.angle[0] == 1.0 and rs.rate[0] == 0.0
    for k in range(1, 200):
        T.roll_from_cumulative(rs, 1.0 + 0.002 * k, DT, rp)
    assert rs.angle[0] == pytest.approx(1.0 + 0.002 * 199)
    assert rs.rate[0] == pytest.approx(2.0, rel=1e-6)
    before = [a.copy() for a in rs]
    for bad in (math.nan, math.inf, -math.inf):
        assert not T.roll_from_cumulative(rs, bad, DT, rp)
        assert not T.roll_from_wrapped(rs, bad, DT, rp)
    for a, b in zip(rs, before):
        assert np.array_equal(a, b)


# ------------------------------------------------------------------------ second implementation
def reference_step(st, roll, length, dt, p):
    """Plain-Python restatement of the model in the module docstring."""
    if not st["primed"]:
        st["primed"], st["play"] = True, roll
    h = 0.5 * p.play_rad
    d = 0.0
    if roll > st["play"] + h:
        d = roll - h - st["play"]
    elif roll < st["play"] - h:
        d = roll + h - st["play"]
    st["play"] += d
    total = 0.0
    for i in range(len(length)):
        L, old = length[i], st["L"][i]
        if L <= 0:
            st["phi"][i] = st["e"][i] = st["L"][i] = st["tq"][i] = 0.0
            st["g"][i] = 1.0
            continue
        if old <= 0:
            st["phi"][i] = st["e"][i] = 0.0
        elif L > old:
            st["phi"][i] *= old / L
            st["e"][i] *= old / L
        st["L"][i] = L
        phi = st["phi"][i] + d
        e = st["e"][i] + (1 - st["e"][i]) * (1 - math.exp(-abs(d) / p.engage_rad[i]))
        phi *= math.exp(-dt / p.twist_tau_s[i])
        e *= math.exp(-dt / p.engage_tau_s[i])
        phi = min(max(phi, -p.twist_slip_rad[i]), p.twist_slip_rad[i])
        st["phi"][i], st["e"][i] = phi, e
        st["tq"][i] = p.k_twist[i] * L * phi
        st["g"][i] = 1 + p.grasp_coil[i] * abs(phi) / p.twist_slip_rad[i] + p.grasp_engage[i] * e
        total += st["tq"][i]
    return total


def test_kernel_matches_reference_on_random_motion():
    rng = np.random.default_rng(7)
    p = T.default_params()._replace(twist_slip_rad=np.array([1.0, 2.0, 3.0]),
                                    twist_tau_s=np.array([0.3, 2.0, 30.0]),
                                    grasp_coil=np.array([1.0, 0.5, 2.0]))
    n = 4000
    roll = np.cumsum(rng.normal(0, 0.03, n)) + np.where(rng.random(n) < 0.01, 0.5, 0.0).cumsum()
    lengths = np.clip(np.cumsum(rng.normal(0, 2e-4, (n, 3)), axis=0) + [1e-3, 3e-3, 2e-3], -1e-3, None)
    ws = T.new_wind_state()
    st = {"primed": False, "play": 0.0, **{k: np.zeros(3) for k in ("phi", "e", "L", "tq")},
          "g": np.ones(3)}
    for k in range(n):
        a = T.wind_step(ws, float(roll[k]), lengths[k], DT, p)
        b = reference_step(st, float(roll[k]), lengths[k], DT, p)
        assert a == pytest.approx(b, rel=1e-12, abs=1e-18)
    assert ws.grasp == pytest.approx(st["g"], rel=1e-12)
    assert ws.twist_rad == pytest.approx(st["phi"], rel=1e-12, abs=1e-15)
    assert ws.engage == pytest.approx(st["e"], rel=1e-12, abs=1e-15)


def test_twist_direction_turns_clockwise_seen_from_the_handle():
    down = np.array([0.0, 0.0, -1.0])  # handle above, tip below: seen from the handle we look down
    assert T.twist_direction(down, 0.0) == pytest.approx([1.0, 0.0, 0.0])
    # looking down on the xy-plane (x right, y up), clockwise from +x goes to -y
    assert T.twist_direction(down, np.pi / 2) == pytest.approx([0.0, -1.0, 0.0], abs=1e-12)
    rng = np.random.default_rng(5)
    for _ in range(20):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        a, b = rng.uniform(-7, 7, 2)
        ea, eb = T.twist_direction(d, a), T.twist_direction(d, b)
        assert abs(ea @ d) < 1e-12 and np.linalg.norm(ea) == pytest.approx(1.0)
        # the angle between the two markers, signed about d, is b - a
        ang = math.atan2(np.cross(ea, eb) @ d, ea @ eb)
        assert ang == pytest.approx(math.remainder(b - a, 2 * math.pi), abs=1e-9)


def test_reset_forgets_the_winding_and_the_roll_origin():
    _, ws = run(np.linspace(0, 3.0, 500))
    assert ws.grasp[0] > 1.5
    T.wind_reset(ws)
    fresh = T.new_wind_state()
    for name in T.WindState._fields:
        if name != "roll_play":  # kept, but unused until the next step re-primes it
            assert np.array_equal(getattr(ws, name), getattr(fresh, name)), name
    tq, _ = run(np.full(5, 3.0), ws=ws)  # the roll it resumes at is the new start: nothing wound
    assert np.all(tq == 0.0) and np.all(ws.grasp == 1.0)


def test_compile_kernels_runs():
    T.compile_kernels()


def test_twist_directions_at_once_are_each_one():
    rng = np.random.default_rng(8)
    d = rng.normal(size=(12, 3))
    d[0] = [1.0, 0.0, 0.0]  # along x: the reference turns to +y
    roll = rng.uniform(-7, 7, 12)
    many = T.twist_direction(d, roll)
    assert many.shape == (12, 3)
    for i in range(12):
        np.testing.assert_allclose(many[i], T.twist_direction(d[i], roll[i]), rtol=0, atol=1e-15)
    assert T.twist_direction(d[0], 0.0) == pytest.approx([0.0, 1.0, 0.0])

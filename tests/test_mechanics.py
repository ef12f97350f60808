"""Post-puncture mechanics (haptic_acu/tissue/mechanics.py) against closed forms and properties.

Karnopp's friction law (force-input) against the analytic motion of a block; the position-input stick
point against Karnopp's static map (breakaway, sliding force, the swing on reversal) and against a
simulated hand (a mass pushed by a constant force: Karnopp's closed-form stick and terminal
velocity); cutting only into uncut tissue; re-insertion never above the first pass; the disc-overlap
damage against a numerical quadrature; passivity over random closed paths; Table 1 with the physical
depth computed here.
"""
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from haptic_acu.tissue import mechanics as m
from haptic_acu.base.config import CONFIG_DIR, load_config

DT = 1e-3
AX = np.array([0.0, 0.0, -1.0])
BOUNDS = np.array([0.0, 1e-3, 6e-3, 26e-3])  # skin 1 mm, fat 5 mm, muscle 20 mm (m)


def params(cut=(0.4, 0.05, 0.2), fc=(10.0, 2.0, 5.0), ratio=1.5, b=(0.0, 0.0, 0.0), k=600.0, decay=1.0,
           radius=0.125e-3, length=0.04):
    fc = np.array(fc, float)
    return m.MechParams(np.array(cut, float), fc * ratio, fc, np.array(b, float), k, decay, radius, length)


class Needle:
    """One insertion along -z from the origin through BOUNDS, driven tick by tick."""

    def __init__(self, prm, tracks=None, entry=(0.0, 0.0, 0.0)):
        self.prm = prm
        self.st = m.new_friction_state()
        self.tracks = m.new_tracks() if tracks is None else tracks
        self.entry = np.array(entry, float)
        self.j = m.begin_track(self.tracks, self.entry, AX, prm.radius)
        self.L = np.zeros(3)
        self.s_prev = None

    def tick(self, s, punctured=3):
        v = 0.0 if self.s_prev is None else (s - self.s_prev) / DT
        self.s_prev = s
        m.lengths_in_layers(s, BOUNDS, self.prm.length, self.L)
        tip = m.Tip(s, v, self.entry + s * AX, AX, BOUNDS, self.L, punctured)
        return m.post_puncture_force(self.prm, self.st, self.tracks, self.j, tip)

    def path(self, ss, punctured=3):
        return np.array([self.tick(s, punctured) for s in ss])


def ramp(a, b, speed):
    n = int(round(abs(b - a) / (speed * DT)))
    return np.linspace(a, b, n + 1)[1:]


# ---- Karnopp, force input ---------------------------------------------------------------------------
def test_karnopp_block_against_closed_form():
    """A block of mass M from rest under a constant force: stays put below breakaway; above it,
    v(t) = (F - Fc)/b (1 - exp(-b t / M)) (Coulomb plus viscous, Karnopp 1985)."""
    M, fs, fc, b, band = 0.05, 0.3, 0.2, 2.0, 1e-5
    for F in (0.25, 0.5):
        v, x, dt = 0.0, 0.0, 1e-6
        t_end = 0.1
        for _ in range(int(t_end / dt)):
            f = m.karnopp_force(v, F, fs, fc, b, band)
            v += (F + f) / M * dt
            x += v * dt
        if F < fs:
            assert v == 0.0 and x == 0.0
        else:
            want = (F - fc) / b * (1.0 - math.exp(-b * t_end / M))
            assert v == pytest.approx(want, rel=2e-3)


def test_karnopp_static_map():
    assert m.karnopp_force(0.0, 0.1, 0.3, 0.2, 1.0, 1e-4) == -0.1
    assert m.karnopp_force(0.0, 0.5, 0.3, 0.2, 1.0, 1e-4) == -0.3
    assert m.karnopp_force(0.0, -0.5, 0.3, 0.2, 1.0, 1e-4) == 0.3
    assert m.karnopp_force(0.01, 0.0, 0.3, 0.2, 1.0, 1e-4) == pytest.approx(-(0.2 + 0.01))
    assert m.karnopp_force(-0.01, 0.0, 0.3, 0.2, 1.0, 1e-4) == pytest.approx(0.2 + 0.01)


# ---- the stick point (position input) against Karnopp's map -------------------------------------------
def test_stick_point_breakaway_sliding_and_reversal():
    """Constant thresholds: the force is -k s until it passes breakaway Fs, then the Coulomb Fc while
    sliding; on reversal it swings linearly through zero to +Fs after (Fc + Fs)/k, then +Fc."""
    prm = params()
    st_ = m.new_friction_state()
    k, fs, fc = prm.k_stick, 0.3, 0.2
    thr = (fs, fs, fc, fc)
    ss = np.arange(0, 2e-3, 1e-6)
    f = np.array([m.stick_slip(st_, prm.k_stick, prm.decay, s, 1e-3, thr) for s in ss])
    stuck = ss < fs / k - 1e-9
    np.testing.assert_allclose(f[stuck], -k * ss[stuck], atol=1e-12)
    i = np.count_nonzero(stuck)
    assert f[i] == pytest.approx(-fs) and f.min() == pytest.approx(-fs)  # the breakaway peak
    np.testing.assert_allclose(f[i + 2:], -fc)  # then sliding at the Coulomb force
    back = ss[-1] - np.arange(1, 2000) * 1e-6
    g = np.array([m.stick_slip(st_, prm.k_stick, prm.decay, s, -1e-3, thr) for s in back])
    travel = ss[-1] - back  # since the turn
    swing = travel < (fc + fs) / k - 1e-9
    np.testing.assert_allclose(g[swing], -fc + k * travel[swing], atol=1e-9)
    i = np.count_nonzero(swing)
    assert g[i] == pytest.approx(fs)  # breakaway the other way
    np.testing.assert_allclose(g[i + 2:], fc)


@pytest.mark.parametrize("push", [0.15, 0.4])
def test_hand_pushing_against_stick_point_matches_karnopp(push):
    """A hand (mass 0.1 kg) pushing with a constant force through the rendered friction: below the
    breakaway it settles at push / k and stays; above it, it slides at Karnopp's terminal velocity
    (push - Fc - cut) / b."""
    prm = params(cut=(0.0, 0.0, 0.1), fc=(0.0, 0.0, 5.0), ratio=2.0, b=(0.0, 0.0, 3000.0))
    n = Needle(prm)
    s0 = 15e-3  # in muscle: 9 mm of needle there
    Lm = s0 - BOUNDS[2]
    x, v = s0, 0.0
    hist = []
    sub = 20
    for _ in range(800):
        f = n.tick(x)
        for _ in range(sub):  # the hand's dynamics between servo ticks, force held
            v += (push + f) / 0.1 * (DT / sub)
            x += v * (DT / sub)
        hist.append((x, v))
    fs = prm.fs[2] * Lm
    fc = prm.fc[2] * Lm + prm.cut[2]
    assert hist[-1][0] < BOUNDS[3]
    if push < fs + prm.cut[2]:
        assert hist[-1][0] - s0 == pytest.approx(push / prm.k_stick, rel=1e-3)
        assert abs(hist[-1][1]) < 1e-6
    else:
        bL = prm.b[2] * (hist[-1][0] - BOUNDS[2])
        assert hist[-1][1] == pytest.approx((push - prm.fc[2] * (hist[-1][0] - BOUNDS[2]) - prm.cut[2]) / bL, rel=0.02)
        assert hist[-1][1] > 0.0 and fc > 0


def test_relaxation_is_exponential_and_holding_still_ends_with_no_force():
    prm = params(decay=math.exp(-DT / 0.5))
    n = Needle(prm)
    f_push = n.path(ramp(8e-3, 12e-3, 0.005))[-1]
    held = n.path(np.full(4000, 12e-3))
    np.testing.assert_allclose(held, f_push * prm.decay ** np.arange(1, 4001), rtol=1e-9, atol=1e-15)
    assert abs(held[-1]) < 1e-3 * abs(f_push)


# ---- cutting and track memory ---------------------------------------------------------------------------
def steady(prm, s, v_sign, cutting=True):
    """Closed-form sliding force at arc length s (after the stick transient), viscous excluded."""
    L = np.zeros(3)
    m.lengths_in_layers(s, BOUNDS, prm.length, L)
    fric = float(prm.fc @ L)
    k = m.layer_at(s, BOUNDS)
    cut = prm.cut[k] if (cutting and 0 <= k < 3) else 0.0
    return -(fric + cut) if v_sign > 0 else fric


def test_cutting_only_while_advancing_into_uncut_tissue():
    prm = params()
    n = Needle(prm)
    ss = ramp(0.0, 20e-3, 0.01)
    first = n.path(ss)
    back_ss = ramp(20e-3, 5e-3, 0.01)
    back = n.path(back_ss)
    again_ss = ramp(5e-3, 24e-3, 0.01)
    again = n.path(again_ss)
    settle = 3e-3  # the stick transient: (Fc + Fs + cut) / k is under 3 mm here
    for s, f in zip(ss, first):
        if s > settle and abs(s - BOUNDS[2]) > settle:
            assert f == pytest.approx(steady(prm, s, +1), abs=1e-9)
    for s, f in zip(back_ss, back):
        if s < 20e-3 - settle:
            assert f == pytest.approx(steady(prm, s, -1), abs=1e-9)
    for s, f in zip(again_ss, again):
        if s > 5e-3 + settle and s < 20e-3 - 2 * prm.radius and abs(s - BOUNDS[2]) > settle:
            assert f == pytest.approx(steady(prm, s, +1, cutting=False), abs=1e-9)  # friction only
        if s > 20e-3 + settle:
            assert f == pytest.approx(steady(prm, s, +1), abs=1e-9)  # new tissue: cutting again
    tr = n.tracks
    np.testing.assert_allclose(tr.cut_lo[0], BOUNDS[:3])
    np.testing.assert_allclose(tr.cut_hi[0], [BOUNDS[1], BOUNDS[2], 24e-3], atol=1e-12)


def test_pressing_a_surface_is_not_cutting():
    """While the muscle's surface is pressed (2 layers punctured) the tip below the fat/muscle rest
    surface cuts nothing, and the muscle's track stays uncut."""
    prm = params()
    n = Needle(prm)
    f = n.path(ramp(0.0, 9e-3, 0.01), punctured=2)
    L = np.zeros(3)
    m.lengths_in_layers(9e-3, BOUNDS, prm.length, L)
    assert f[-1] == pytest.approx(-float(prm.fc @ L))
    assert n.tracks.cut_hi[0, 2] < n.tracks.cut_lo[0, 2]  # empty


@settings(max_examples=12, deadline=None)
@given(offset=st.floats(0.0, 0.4e-3), speed=st.floats(0.002, 0.03), depth=st.floats(8e-3, 24e-3))
def test_reinsertion_never_more_than_first_pass(offset, speed, depth):
    """A second insertion parallel to the first at a lateral offset meets, at every depth, no more
    than the first pass did, and its cutting is the first pass's times the uncut fraction."""
    prm = params()
    tracks = m.new_tracks()
    first = Needle(prm, tracks)
    ss = ramp(0.0, depth, speed)
    f1 = first.path(ss)
    second = Needle(prm, tracks, entry=(offset, 0.0, 0.0))
    f2 = second.path(ss)
    assert np.all(np.abs(f2) <= np.abs(f1) + 1e-12)
    dmg = m.overlap_damage(offset, prm.radius)
    i = np.searchsorted(ss, depth - 0.5e-3)  # short of the end, where fresh tissue lies one radius ahead
    s = ss[i]
    k = m.layer_at(s, BOUNDS)
    if s - BOUNDS[k] > 3e-3:
        assert f1[i] - f2[i] == pytest.approx(-prm.cut[k] * dmg, abs=1e-9)


def test_overlap_damage_against_quadrature():
    R = 0.125e-3
    g = np.linspace(-R, R, 801)
    X, Y = np.meshgrid(g, g)
    disc = X ** 2 + Y ** 2 <= R * R
    for r in (0.0, 0.3 * R, R, 1.5 * R, 1.99 * R):
        want = np.count_nonzero(disc & ((X - r) ** 2 + Y ** 2 <= R * R)) / np.count_nonzero(disc)
        assert m.overlap_damage(r, R) == pytest.approx(want, abs=5e-3)
    assert m.overlap_damage(0.0, R) == 1.0
    assert m.overlap_damage(2 * R, R) == 0.0 and m.overlap_damage(5 * R, R) == 0.0
    d = [m.overlap_damage(r, R) for r in np.linspace(0, 2 * R, 50)]
    assert np.all(np.diff(d) <= 0)


def test_begin_track_reuses_a_coincident_line_only():
    tr = m.new_tracks()
    a = m.begin_track(tr, np.zeros(3), AX, 1e-4)
    assert m.begin_track(tr, np.array([5e-5, 0, 0]), AX, 1e-4) == a
    tilted = np.array([0.0, math.sin(0.1), -math.cos(0.1)])
    assert m.begin_track(tr, np.zeros(3), tilted, 1e-4) != a
    assert m.begin_track(tr, np.array([3e-4, 0, 0]), AX, 1e-4) not in (a,)
    assert tr.count[0] == 3


# ---- passivity --------------------------------------------------------------------------------------
@settings(max_examples=10, deadline=None)
@given(steps=st.lists(st.floats(-3e-5, 3e-5), min_size=20, max_size=400), start=st.floats(2e-3, 20e-3),
       relax=st.booleans())
def test_passive_over_random_closed_paths(steps, start, relax):
    """Energy returned to the hand over a closed path from rest, sum F_k (s_k - s_(k-1)) (the force
    at each tick's new position, the kernel's own accounting), is never positive: friction, cutting,
    viscous and relaxation only take energy out."""
    prm = params(b=(3e3, 1e3, 3e3), decay=math.exp(-DT / 0.3) if relax else 1.0)
    n = Needle(prm)
    path = start + np.cumsum([0.0] + steps)
    path = np.concatenate([path, ramp(path[-1], start, 0.002) if abs(path[-1] - start) > 1e-9 else [], [start]])
    path = np.clip(path, 0.0, 30e-3)
    e_out = 0.0
    n.tick(start)
    prev = start
    for s in path:
        f = n.tick(s)
        e_out += f * (s - prev)
        prev = s
    assert e_out <= 1e-12, e_out


# ---- Table 1 mode and the lengths in each layer -------------------------------------------------------
def test_table1_with_physical_depth():
    """Table 1 in muscle: -(d_s h_s + d_f h_f + d_m h) v with h the depth below the muscle's rest
    surface, and h_s, h_f the full thicknesses."""
    d = np.array([3.0, 1.0, 3.0]) * 1e3  # Table 2's d per mm -> per m
    L = np.zeros(3)
    out = np.zeros(3)
    for s, v in ((0.5e-3, 0.01), (4e-3, -0.02), (15e-3, 0.003)):
        m.lengths_in_layers(s, BOUNDS, 1.0, L)
        got = m.table1_force(d, L, v, out)
        hs, hf = BOUNDS[1] - BOUNDS[0], BOUNDS[2] - BOUNDS[1]
        if s < BOUNDS[1]:
            want = -d[0] * s * v
        elif s < BOUNDS[2]:
            want = -(d[0] * hs + d[1] * (s - BOUNDS[1])) * v
        else:
            want = -(d[0] * hs + d[1] * hf + d[2] * (s - BOUNDS[2])) * v
        assert got == pytest.approx(want, rel=1e-12)
        assert out.sum() == pytest.approx(want, rel=1e-12)


def test_lengths_in_layers_respects_the_shaft_length():
    L = np.zeros(3)
    assert m.lengths_in_layers(10e-3, BOUNDS, 0.04, L) == pytest.approx(10e-3)
    np.testing.assert_allclose(L, [1e-3, 5e-3, 4e-3])
    m.lengths_in_layers(25e-3, BOUNDS, 5e-3, L)  # a 5 mm needle pushed in to its hub
    np.testing.assert_allclose(L, [0.0, 0.0, 5e-3], atol=1e-15)
    assert m.layer_at(-1e-4, BOUNDS) == -1 and m.layer_at(30e-3, BOUNDS) == 3


def test_config_params_scale_with_diameter():
    """Per-mm-of-diameter keys times the diameter: Okamura 2004's 0.94 N for an 18 G (1.27 mm) needle
    from the muscle's 0.74 N/mm; doubling the diameter doubles cutting and every friction term."""
    import dataclasses

    cfg = load_config()
    a = m.mech_params(cfg.layers, cfg.needle)
    big = dataclasses.replace(cfg.needle, diameter_mm=1.27)
    b = m.mech_params(cfg.layers, big)
    assert b.cut[2] == pytest.approx(0.94, abs=0.005)
    two = m.mech_params(cfg.layers, dataclasses.replace(cfg.needle, diameter_mm=2 * cfg.needle.diameter_mm))
    for name in ("cut", "fs", "fc", "b"):
        np.testing.assert_allclose(getattr(two, name), 2 * getattr(a, name))
    assert two.radius == 2 * a.radius
    paper = load_config(CONFIG_DIR / "presets" / "paper.toml")
    assert paper.needle.mechanics == "table1" and cfg.needle.mechanics == "rich"

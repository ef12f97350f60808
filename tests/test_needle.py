"""The needle in layered tissue (haptic_acu.servo.step) against Table 1, on a synthetic tissue with simple
numbers: a 200 mm sphere, layers 1/5/20 mm thick, damping 3/1/2 N*s/m per mm (physics_helpers).

The tip is driven kinematically along -z through the acupoint (the sphere's top), so every boundary is
crossed radially and every depth is a plain difference of z. The model runs in the paper's mode
(``needle.mechanics = "table1"``; the default's cutting and friction are tested against their closed
forms in test_insertion_mechanics.py). Expected forces are computed here from the known thicknesses,
the tip's physical depth below the rest skin surface and the velocity (docs/model.md section 3). The
surfaces still being pressed are met with the tissue beneath compressed by the dents, an offset
taken from the recorded tip positions at the punctures (needle.py's "Compression"):

    after skin puncture at tip depth s0:  lifted depth = s - s0
    after fat puncture at s1:              lifted depth = s - (s1 - h_s)
    after muscle puncture at s2:           lifted depth = s - (s2 - h_s - h_f)
"""
import dataclasses
import math

import numpy as np
import pytest

from haptic_acu.tissue.forcenet import Net, NetParams
from haptic_acu.servo.step import PRESSING, PUNCTURED, UNTOUCHED, NeedleModel
from physics_helpers import (damping_m, drive, layer_tops_m, replace, sphere_config, sphere_tissue,
                             straight_line, table1_damping)

SPEED = 0.01  # m/s
DOWN = np.array([0.0, 0.0, -SPEED])


@pytest.fixture(scope="module")
def cfg():
    return replace(sphere_config(), "needle", mechanics="table1")


@pytest.fixture(scope="module")
def tissue(cfg):
    return sphere_tissue(cfg)


@pytest.fixture(scope="module")
def insertion(cfg, tissue):
    """One straight insertion at 10 mm/s from 1 mm above the acupoint to 29 mm deep (with the
    compression offset, that stops short of the bone)."""
    model = NeedleModel(cfg, tissue)
    pts, v = straight_line(1e-3, -29e-3, SPEED)
    return drive(model, pts, v)


def depth(tick):
    return -tick.p[2]


def puncture_ticks(ticks):
    return [i for i, t in enumerate(ticks) if t.diag["puncture"] >= 0]


def offsets(cfg, s_punct):
    """Compression offset after each puncture from the tip depths at the punctures (see module doc)."""
    tops, _ = layer_tops_m(cfg)
    return [s - top for s, top in zip(s_punct, tops)]


def phase(ticks, states):
    return [t for t in ticks if t.states == states]


def test_tissue_is_what_the_tests_assume(cfg, tissue):
    tops, thick = layer_tops_m(cfg)
    np.testing.assert_allclose(tissue.depths_at_acupoint(), np.append(tops, tops[-1] + thick[-1]), atol=1e-12)
    np.testing.assert_allclose(tissue.centre, [0.0, 0.0, -0.2], atol=1e-12)


def test_zero_force_outside_the_tissue(cfg, tissue, insertion):
    above = [t for t in insertion if t.p[2] > 0]
    assert len(above) > 50
    for t in above:
        assert np.array_equal(t.force, np.zeros(3)) and t.states == (UNTOUCHED,) * 3
    # anywhere above the skin, at any velocity
    model = NeedleModel(cfg, tissue)
    rng = np.random.default_rng(3)
    for _ in range(300):
        d = rng.normal(size=3)
        d[2] = abs(d[2]) + 0.5
        d /= np.linalg.norm(d)
        p = tissue.centre + d * (0.2 + rng.uniform(1e-6, 0.01))
        f = model.step(p, rng.normal(size=3) * 10 ** rng.uniform(-3, 3))
        assert np.array_equal(f, np.zeros(3))


def test_punctures_in_order_exactly_at_the_threshold(cfg, insertion):
    idx = puncture_ticks(insertion)
    assert [int(insertion[i].diag["puncture"]) for i in idx] == [0, 1, 2]
    for k, i in enumerate(idx):
        thresh = cfg.layers[k].puncture_threshold_um * 1e-6
        pressing = [j for j, t in enumerate(insertion) if t.states[k] == PRESSING]
        assert pressing and pressing == list(range(pressing[0], i)), k  # pressed without a break up to i
        for j in pressing:
            assert insertion[j].diag["ringw"] <= thresh, (k, j)
        assert insertion[i].diag["ringw"] > thresh
        assert insertion[i].states[k] == PUNCTURED
        assert all(t.states[k] == PUNCTURED for t in insertion[i:])
        # the force drops by at least half at the puncture
        before, at = np.linalg.norm(insertion[i - 1].force), np.linalg.norm(insertion[i].force)
        assert before > 0.1 and at <= 0.5 * before, (k, before, at)


def test_compression_offset_is_the_dent_at_the_break(cfg, insertion):
    """N1's deflection at each puncture is the tip's depth below that layer's rest surface."""
    idx = puncture_ticks(insertion)
    s = [depth(insertion[i]) for i in idx]
    o = offsets(cfg, s)
    tops, _ = layer_tops_m(cfg)
    prev = 0.0
    for k, i in enumerate(idx):
        dent = insertion[i].diag["dz1"]
        assert abs(dent - (s[k] - prev - tops[k])) < 1e-9
        assert abs(o[k] - (prev + dent)) < 1e-9
        prev = o[k]


def test_pressing_skin_is_the_net_alone(cfg, insertion):
    pressing = phase(insertion, (PRESSING, UNTOUCHED, UNTOUCHED))
    assert len(pressing) > 100
    for t in pressing:
        # straight down the pole of the fitted sphere: no lateral force beyond the fit's rounding
        # (its coefficients carry ~1e-19 m of asymmetry; the surface's gradient is exact)
        assert abs(t.force[0]) < 1e-15 and abs(t.force[1]) < 1e-15
        assert t.force[2] == pytest.approx(t.diag["f_surface"], abs=1e-12) and t.force[2] > 0


@pytest.mark.parametrize("layer", [0, 1, 2])
def test_inside_a_layer_the_force_is_table1_damping(cfg, insertion, layer):
    """In skin d_s h v; in fat (d_f h + d_s h_s) v; in muscle (d_s h_s + d_f h_f + d_m h) v, with h
    the physical depth into the layer (clipped to its thickness: the layer beneath still pressed)."""
    states = tuple(PUNCTURED if j <= layer else UNTOUCHED for j in range(3))
    ticks = phase(insertion, states)
    assert len(ticks) > 50
    tops, thick = layer_tops_m(cfg)
    d = damping_m(cfg)
    for t in ticks:
        h = min(depth(t) - tops[layer], thick[layer])
        assert h >= -1e-9
        expected = (sum(d[j] * thick[j] for j in range(layer)) + d[layer] * h) * SPEED
        assert t.force[2] == pytest.approx(expected, rel=1e-7, abs=1e-12), depth(t)
        assert t.force[0] == 0 and t.force[1] == 0
        assert t.force[2] == pytest.approx(table1_damping(cfg, depth(t), [True] * (layer + 1) + [False] * (2 - layer),
                                                          SPEED), rel=1e-7, abs=1e-12)


@pytest.mark.parametrize("layer", [1, 2])
def test_pressing_a_deeper_layer_adds_the_damping_above(cfg, insertion, layer):
    """Pressing fat: F_f + d_s h_s v; pressing muscle: F_m + (d_s h_s + d_f h_f) v."""
    states = tuple(PUNCTURED if j < layer else PRESSING if j == layer else UNTOUCHED for j in range(3))
    ticks = phase(insertion, states)
    assert len(ticks) > 50
    flags = [j < layer for j in range(3)]
    for t in ticks:
        surface = t.diag["f_surface"]
        assert surface >= 0
        above = table1_damping(cfg, depth(t), flags, SPEED)  # the layers broken, physical lengths
        assert t.force[2] == pytest.approx(surface + above, rel=1e-7, abs=1e-12)
    # the net dominates before the break (the fine-needle fat: 0.19 N against 0.03 N of skin damping)
    assert max(t.diag["f_surface"] for t in ticks) > 5 * above


def drive_until(model, states, dent_m, cfg):
    """Drive down at 10 mm/s until ``states`` holds and the front layer's dent (computed here from the
    recorded punctures) reaches ``dent_m``; returns (tip position, compression offset)."""
    tops, _ = layer_tops_m(cfg)
    front = states.index(PRESSING)
    s_punct = []
    z = 1e-3
    for _ in range(20000):
        z -= SPEED * 1e-3
        p = np.array([0.0, 0.0, z])
        model.step(p, DOWN)
        if model.diag["puncture"] >= 0:
            s_punct.append(-z)
        o = offsets(cfg, s_punct)[-1] if s_punct else 0.0
        if model.states == states and (-z - o) - tops[front] >= dent_m:
            return p, o
    raise AssertionError("state not reached")


@pytest.mark.parametrize("servo_net, rel_tol", [("sweeps", 1e-6), ("table", 3e-5)])
@pytest.mark.parametrize("layer", [0, 1, 2])
def test_surface_force_is_the_static_net_reaction(cfg, tissue, layer, servo_net, rel_tol):
    """Hold the tip while pressing: the force converges to an independently solved static net at the
    compressed tip position; moving at v then adds exactly the damping of the layers above.
    The sweeps converge to it; the table (solved to the static tolerance, 1e-10 m, and read by
    linear interpolation between rows h = L/400 apart) stays within 3e-5 of it on the axis
    (measured: 8e-6 on the muscle net)."""
    cfg = dataclasses.replace(cfg, solver=dataclasses.replace(cfg.solver, servo_net=servo_net))
    model = NeedleModel(cfg, tissue)
    states = tuple(PUNCTURED if j < layer else PRESSING if j == layer else UNTOUCHED for j in range(3))
    p, o = drive_until(model, states, 0.4e-3, cfg)
    for _ in range(1500):
        f_hold = model.step(p, np.zeros(3)).copy()
    assert model.states == states
    tops, thick = layer_tops_m(cfg)
    net = Net.allocate(NetParams.from_layer(cfg.layers[layer]))
    net.build(tissue.coeffs[layer], tissue.lmax, tissue.centre, [0.0, 0.0, -tops[layer]], [0.0, 0.0, 1.0])
    net.solve(np.array([0.0, 0.0, p[2] + o]), tol_m=1e-14, max_sweeps=100000)
    f_static = net.reaction()
    assert f_static[2] > 0.03  # loaded (the fine-needle skin and fat nets: 0.08 and 0.05 N at 0.4 mm)
    np.testing.assert_allclose(f_hold, f_static, rtol=0, atol=rel_tol * f_static[2])
    f_moving = model.step(p, DOWN).copy()
    above = table1_damping(cfg, -p[2], [j < layer for j in range(3)], SPEED)
    assert f_moving[2] - f_hold[2] == pytest.approx(above, rel=1e-6, abs=1e-9)


def test_damping_opposes_motion_and_ends_as_the_tip_leaves_each_layer(cfg, tissue):
    model = NeedleModel(cfg, tissue)
    # into muscle, 8 mm past its surface
    s_punct = []
    pts, v = straight_line(1e-3, -25e-3, SPEED)
    for p in pts:
        model.step(p, v)
        if model.diag["puncture"] >= 0:
            s_punct.append(-p[2])
    assert model.states == (PUNCTURED,) * 3
    p = pts[-1]
    expected = table1_damping(cfg, -p[2], [True] * 3, SPEED)
    assert expected > 0.1
    assert model.step(p, DOWN)[2] == pytest.approx(expected, rel=1e-9)  # resists the thrust
    assert model.step(p, -DOWN)[2] == pytest.approx(-expected, rel=1e-9)  # pulls back on withdrawal
    assert np.array_equal(model.step(p, np.zeros(3)), np.zeros(3))
    # withdraw all the way out: each layer's damping ends as the tip leaves it
    tops, _ = layer_tops_m(cfg)
    up, vu = straight_line(p[2], 2e-3, SPEED)
    seen = set()
    for q in up:
        f = model.step(q, vu).copy()
        s = -q[2]
        if s >= 0:  # still inside (physical depth below the rest skin)
            expected = -table1_damping(cfg, s, [True] * 3, SPEED)
            seen.add(int(np.searchsorted(tops, s, side="right")) - 1)
        else:
            expected = 0.0
        assert f[2] == pytest.approx(expected, rel=1e-9, abs=1e-12), (q[2], eff)
        assert f[0] == 0 and f[1] == 0
    assert seen == {0, 1, 2}
    assert model.states == (UNTOUCHED,) * 3 and not model.inserted
    assert np.array_equal(f, np.zeros(3))


def insert_and_withdraw(model, xy=(0.0, 0.0), deep=-25e-3):
    down, v = straight_line(1e-3, deep, SPEED, xy=xy)
    ticks = drive(model, down, v)
    up, vu = straight_line(deep, 1e-3, SPEED, xy=xy)
    return ticks, drive(model, up, vu)


def test_holes_stay_and_reentry_meets_no_surface(cfg, tissue):
    model = NeedleModel(cfg, tissue)
    first, _ = insert_and_withdraw(model)
    assert any(t.states[0] == PRESSING for t in first)
    holes = model.holes_list
    tops, _ = layer_tops_m(cfg)
    # one hole per layer, where the needle met each layer's rest surface: straight below the acupoint
    assert holes.shape[0] == 3
    assert [int(h) for h in holes["layer"]] == [0, 1, 2]
    np.testing.assert_allclose(holes["point"], [[0.0, 0.0, -t] for t in tops], atol=1e-9)
    # re-insertion through the same holes: never a pressing state, force is the damping alone
    again, _ = insert_and_withdraw(model)
    assert not any(PRESSING in t.states for t in again)
    assert all(t.diag["f_surface"] == 0 for t in again)
    for t in again:  # no dent this time, so no compression offset
        assert t.force[2] == pytest.approx(table1_damping(cfg, max(depth(t), 0.0), [True] * 3, SPEED),
                                           rel=1e-9, abs=1e-12)
    assert model.holes_list.shape[0] == 3
    # a new site 5 mm away meets the skin's surface force again
    new, _ = insert_and_withdraw(model, xy=(5e-3, 0.0))
    assert any(t.states[0] == PRESSING for t in new)
    assert max(t.diag["f_surface"] for t in new) > 0.5
    assert model.holes_list.shape[0] == 6


def into_fat(cfg, tissue):
    """A model with the tip 2 mm past the fat's puncture, at rest."""
    model = NeedleModel(cfg, tissue)
    pts, v = straight_line(1e-3, -30e-3, SPEED)
    s_fat = None
    for p in pts:
        model.step(p, v)
        if model.diag["puncture"] == 1:
            s_fat = -p[2]
        if s_fat is not None and -p[2] >= s_fat + 2e-3:
            assert model.states == (PUNCTURED, PUNCTURED, UNTOUCHED)
            return model, p
    raise AssertionError("fat not punctured")


def test_lateral_constraint_restores_toward_the_insertion_line(cfg, tissue):
    model, p = into_fat(cfg, tissue)
    assert np.allclose(model.axis, [0.0, 0.0, -1.0]) and np.allclose(model.entry, 0.0, atol=1e-12)
    tops, thick = layer_tops_m(cfg)
    held = sum(min(max(-p[2] - tops[j], 0.0), thick[j]) for j in range(2))  # skin and fat hold the shaft
    k_lat = cfg.needle.lateral_stiffness_n_per_mm * 1e3 * held / (cfg.needle.length_mm * 1e-3)
    rng = np.random.default_rng(5)
    for dist in (0.2e-3, 1e-3, 2e-3):
        phi = rng.uniform(0, 2 * math.pi)
        off = dist * np.array([math.cos(phi), math.sin(phi), 0.0])
        f = model.step(p + off, np.zeros(3))
        np.testing.assert_allclose(f, -k_lat * off, rtol=1e-9, atol=1e-12)
    assert np.array_equal(model.step(p, np.zeros(3)), np.zeros(3))
    # switched off in the config: no lateral force at all
    off_cfg = replace(cfg, "needle", lateral_constraint=False)
    model, p = into_fat(off_cfg, tissue)
    for dist in (0.2e-3, 2e-3):
        assert np.array_equal(model.step(p + [dist, -dist, 0.0], np.zeros(3)), np.zeros(3))


def test_bone_wall_pushes_out_by_its_penetration(cfg, tissue):
    k_bone = cfg.needle.bone_stiffness_n_per_mm * 1e3
    model = NeedleModel(cfg, tissue)
    pts, v = straight_line(1e-3, -31e-3, SPEED)
    s_punct = []
    for p in pts:
        model.step(p, v)
        if model.diag["puncture"] >= 0:
            s_punct.append(-p[2])
    o = offsets(cfg, s_punct)[2]
    tops, thick = layer_tops_m(cfg)
    pen = -pts[-1][2] - o - (tops[2] + thick[2])
    assert pen > 1e-3
    f = model.step(pts[-1], np.zeros(3))
    np.testing.assert_allclose(f, [0.0, 0.0, k_bone * pen], rtol=1e-9, atol=1e-12)


# ---- safety -------------------------------------------------------------------------------------------
def pressing_skin(cfg, tissue):
    model = NeedleModel(cfg, tissue)
    pts, v = straight_line(1e-3, -1e-3, SPEED)
    drive(model, pts, v)
    assert model.states[0] == PRESSING and model.diag["f_surface"] > 0.1  # about half the skin's break force
    return model, pts[-1]


@pytest.mark.parametrize("bad", ["p_nan", "v_nan", "p_inf", "v_inf"])
def test_non_finite_input_gives_zero_force_and_latches_a_fault(cfg, tissue, bad):
    model, p = pressing_skin(cfg, tissue)
    q, v = p.copy(), DOWN.copy()
    target = q if bad.startswith("p") else v
    target[1] = math.nan if bad.endswith("nan") else -math.inf
    assert not model.fault
    assert np.array_equal(model.step(q, v), np.zeros(3))
    assert model.fault
    for _ in range(5):  # latched: finite input afterwards still gives zero
        assert np.array_equal(model.step(p, DOWN), np.zeros(3))
    assert model.fault


def test_force_never_exceeds_the_limit(cfg, tissue):
    """The same deep press with a small limit gives the unlimited force scaled down to the limit."""
    limit = 0.5
    small = NeedleModel(replace(cfg, "safety", force_limit_n=limit), tissue)
    big = NeedleModel(replace(cfg, "safety", force_limit_n=1e6), tissue)
    pts, v = straight_line(1e-3, -40e-3, 0.05)  # through every layer and 10 mm into the bone wall
    clamped = 0
    for p in pts:
        fs = small.step(p, v).copy()
        fb = big.step(p, v).copy()
        nb = np.linalg.norm(fb)
        assert np.linalg.norm(fs) <= limit + 1e-12
        np.testing.assert_allclose(fs, fb * min(1.0, limit / nb) if nb > 0 else fb, rtol=1e-12, atol=1e-15)
        clamped += nb > limit
    assert clamped > 100


def test_tip_exactly_at_the_tissue_centre_is_handled(cfg, tissue):
    """The centre of the SH boundaries is the one point with no direction (shf.direction_of calls it
    the +z pole). A tip there, first touch or deep in the bone wall, must still give a finite force."""
    model = NeedleModel(cfg, tissue)
    f = model.step(tissue.centre.copy(), np.zeros(3))
    assert np.all(np.isfinite(f)) and not model.fault
    # Through the holes of an earlier insertion (no dent, so no compression offset) and on down
    # through the bone to its centre: the wall's penetration is the whole bone radius, its push the
    # +z pole's direction (a needle long enough to reach it: the handle stays off the skin).
    big = NeedleModel(replace(replace(cfg, "safety", force_limit_n=1e6), "needle", length_mm=1000.0), tissue)
    insert_and_withdraw(big)
    pts, v = straight_line(1e-3, tissue.centre[2], 0.1)
    drive(big, pts, v)
    assert big.states == (PUNCTURED,) * 3
    f = big.step(tissue.centre.copy(), np.zeros(3))
    tops, thick = layer_tops_m(cfg)
    bone_radius = 0.2 - tops[2] - thick[2]
    k_bone = cfg.needle.bone_stiffness_n_per_mm * 1e3
    assert not big.fault
    np.testing.assert_allclose(f, [0.0, 0.0, k_bone * bone_radius], rtol=1e-9)


def _exact_norm2(f):
    from fractions import Fraction
    return sum(Fraction(float(x)) ** 2 for x in f)


def test_clamp_is_exact_through_the_step(cfg, tissue):
    """Through the servo step, a clamped force is never above the limit by even 1 ulp (its
    exact rational magnitude), and sits at the limit to within a few ulps."""
    from fractions import Fraction
    limit = 0.5
    model = NeedleModel(replace(cfg, "safety", force_limit_n=limit), tissue)
    pts, v = straight_line(1e-3, -40e-3, 0.05)  # through every layer into the bone wall
    clamped = 0
    for p in pts:
        f = model.step(p, v)
        n2 = _exact_norm2(f)
        assert n2 <= Fraction(limit) ** 2
        if model.diag["clamped"]:
            clamped += 1
            assert float(n2) ** 0.5 >= limit * (1 - 8 * 2.0 ** -52)
    assert clamped > 100


def test_a_huge_stiffness_gives_the_limit_not_zero(cfg, tissue):
    """A bone wall of 1e300 N/mm: the naive clamp's |F|**2 overflowed to inf and commanded 0 N; the
    step must command the limit, along the wall's normal (outwards, +z here)."""
    limit = 3.3
    c = replace(replace(cfg, "safety", force_limit_n=limit), "needle", bone_stiffness_n_per_mm=1e300)
    model = NeedleModel(c, tissue)
    pts, v = straight_line(1e-3, -32e-3, 0.05)  # 1 mm past the compressed bone boundary and more
    f = None
    for p in pts:
        f = model.step(p, v).copy()
    assert not model.fault
    assert model.diag["clamped"] == 1.0
    assert np.all(np.isfinite(f))
    assert _exact_norm2(f) <= _exact_norm2([limit])
    assert np.linalg.norm(f) == pytest.approx(limit, rel=1e-14)
    assert f[2] > 0.99 * limit

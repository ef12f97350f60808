"""The needle inside the tissue through the whole servo step (haptic_acu.tissue.postpuncture wired into
needle.step_kernel), against closed forms computed here from the config:

* Karnopp shaft friction rendered by the stick point: sliding at constant speed meets
  -(cut + sum fc_k L_k + sum b_k L_k v) with L_k the physical needle length per layer; reversal meets
  the breakaway sum fs_k L_k after a travel of (F_slide + F_break) / k_stick; the grasp multiplier
  scales stiction and Coulomb but not the viscous part; a needle held still relaxes as exp(-t / tau);
* the paper preset: exactly Table 1 with h the physical depth below each layer's rest surface;
* straight insertions at 0-75 deg from the normal: the axis, the entry, no clamp, no lateral pull;
  lateral stiffness in proportion to the needle length held;
* re-insertion along a track: no surface to break, no cutting, the first pass minus the cutting.
"""
import math

import numpy as np
import pytest

from haptic_acu.base.config import load_config
from haptic_acu.servo.step import NeedleModel
from physics_helpers import replace, sphere_config, sphere_tissue

DT = 1e-3


def flat_config(base=None, radius_mm=1000.0):
    """The sphere config of physics_helpers (layers 1 / 5 / 20 mm) on a 1 m sphere, with a 60 mm
    needle: a line at 75 deg from the normal reaches the muscle (12 mm down, 46 mm along the line)
    and goes 4 mm further with the handle still off the skin."""
    cfg = sphere_config(base)
    cfg = replace(cfg, "needle", length_mm=60.0)
    return replace(cfg, "body", semi_axes_mm=(radius_mm,) * 3)


def model_for(cfg):
    m = NeedleModel(cfg, sphere_tissue(cfg))
    m.warm_up()
    return m


@pytest.fixture(scope="module")
def rich():
    """Flat layers, friction relaxation off (the stick point's closed forms are then exact)."""
    cfg = replace(flat_config(), "needle", friction_relaxation_s=0.0)
    return cfg, model_for(cfg)


def mech(cfg):
    """Per-layer cutting (N), breakaway and Coulomb (N/m), viscous (N*s/m per m), from the config."""
    dmm = cfg.needle.diameter_mm
    cut = np.array([la.cutting_n_per_mm_diameter * dmm for la in cfg.layers])
    fc = np.array([la.coulomb_n_per_mm2 * dmm * 1e3 for la in cfg.layers])
    fs = fc * np.array([la.stiction_ratio for la in cfg.layers])
    b = np.array([la.viscous_n_s_per_m_per_mm2 * dmm * 1e3 for la in cfg.layers])
    return cut, fs, fc, b


def lengths_at(cfg, depth, held=3):
    """Needle length in each layer for a tip ``depth`` below a flat skin (the first ``held`` layers)."""
    h = np.array([la.thickness_mm for la in cfg.layers]) * 1e-3
    tops = np.concatenate([[0.0], np.cumsum(h)[:-1]])
    return np.array([min(max(depth - tops[k], 0.0), h[k]) if k < held else 0.0 for k in range(3)])


def tick(m, p, v, axis=None):
    f = m.step(p, v, axis=axis).copy()
    return f, m.diag.copy()


def insert(m, depth, speed=3e-3, direction=(0.0, 0.0, -1.0), start=2e-3, axis=None):
    """Drive the tip along ``direction`` from ``start`` above the acupoint to ``depth`` below it;
    returns (depths, forces, diags)."""
    a = np.asarray(direction, float)
    a /= np.linalg.norm(a)
    n = int(round((depth + start) / (speed * DT)))
    ds, fs, dg = [], [], []
    for i in range(1, n + 1):
        s = -start + speed * DT * i
        f, d = tick(m, s * a, speed * a, axis)
        ds.append(s)
        fs.append(f)
        dg.append(d)
    return np.array(ds), np.array(fs), np.array(dg)


def test_sliding_through_the_step_is_karnopp_in_slip(rich):
    cfg, m = rich
    m.reset(keep_holes=False)
    cut, fs, fc, b = mech(cfg)
    v = 3e-3
    depth, force, diag = insert(m, 0.018, speed=v)
    assert m.states == (2, 2, 2)
    k = m.model.params[0]["k_stick"]
    muscle_in = depth[np.flatnonzero(diag["puncture"] == 2)[0]]
    check = depth > muscle_in + (cut.sum() + fs.sum() * 0.04) / k + 1e-3  # past the stick transient
    assert check.sum() > 500
    for s, f, d in zip(depth[check], force[check], diag[check]):
        L = lengths_at(cfg, s)
        want = -(cut[2] + fc @ L + (b @ L) * v)  # Karnopp outside the stick band, plus cutting
        assert f[2] * -1.0 == pytest.approx(want, rel=1e-9, abs=1e-12)  # force along +s = -f_z
        assert d["f_cut"] == pytest.approx(-cut[2], rel=1e-9)
        assert d["f_viscous"] == pytest.approx(-(b @ L) * v, rel=1e-9)
        assert d["f_cut"] + d["f_friction"] + d["f_viscous"] == pytest.approx(d["f_damp"], rel=1e-12)
        assert d["axial_damping"] == pytest.approx(b @ L, rel=1e-9)
        assert d["breakaway"] == pytest.approx(fs @ L, rel=1e-9)
    np.testing.assert_allclose(m.rec["lengths"], lengths_at(cfg, depth[-1]), rtol=1e-9, atol=1e-12)


def test_reversal_breaks_away_after_the_closed_form_travel(rich):
    cfg, m = rich
    cut, fs, fc, b = mech(cfg)
    k = m.model.params[0]["k_stick"]
    # grasp 1: the twirl phase writes servo.grasp every tick from the winding (none here); how the
    # grasp scales the friction is tested through the step in test_twirl_servo.py and test_twirl_friction.py
    for grasp in (1.0,):
        m.reset(keep_holes=False)
        depth, force, _ = insert(m, 0.015, speed=3e-3)
        L = lengths_at(cfg, depth[-1])
        f_slide = -(cut[2] + grasp * fc @ L)  # the spring's force while sliding forward (viscous apart)
        # Hold for one tick, then withdraw slowly (below the stick band's speed, so viscous is tiny).
        s0 = depth[-1]
        v = -5e-5
        # the spring reaches the breakaway, which falls as the muscle lets go of the shaft:
        # f_slide + k t = grasp (fs . L - fs_muscle t)
        travel_break = (grasp * fs @ L - f_slide) / (k + grasp * fs[2])
        n = int(2.0 * travel_break / (abs(v) * DT)) + 50
        seen = []
        for i in range(1, n):
            s = s0 + v * DT * i
            f, d = tick(m, np.array([0.0, 0.0, -s]), np.array([0.0, 0.0, -v]))
            spring = -f[2] - (-(b @ lengths_at(cfg, s)) * v)  # along +s, minus the viscous part
            seen.append((s0 - s, spring, d["f_friction"], d["f_viscous"]))
        seen = np.array(seen)
        # The spring unloads linearly: f_slide + k * travel until the breakaway, then holds it.
        before = seen[:, 0] < travel_break - 2 * abs(v) * DT
        np.testing.assert_allclose(seen[before, 1], f_slide + k * seen[before, 0], rtol=1e-6, atol=1e-9)
        assert seen[:, 1].max() == pytest.approx(grasp * fs @ lengths_at(cfg, s0 - travel_break), rel=2e-3)
        assert seen[-1, 1] == pytest.approx(grasp * fc @ lengths_at(cfg, s0 - seen[-1, 0]), rel=2e-3)  # Coulomb
        np.testing.assert_allclose(seen[:, 3], -np.array([b @ lengths_at(cfg, s0 - t) for t in seen[:, 0]]) * v,
                                   rtol=1e-9, atol=1e-15)  # viscous: never scaled by the grasp


def test_a_needle_held_still_relaxes_to_no_force():
    cfg = flat_config()
    m = model_for(cfg)
    depth, force, _ = insert(m, 0.012, speed=3e-3)
    p = np.array([0.0, 0.0, -depth[-1]])
    f0, _ = tick(m, p, np.zeros(3))
    tau = cfg.needle.friction_relaxation_s
    for i in range(1, 3001):
        f, d = tick(m, p, np.zeros(3))
        if i in (500, 1000, 3000):
            assert f[2] == pytest.approx(f0[2] * math.exp(-i * DT / tau), rel=1e-6)
    assert abs(f[2]) < 0.05 * abs(f0[2])
    # pushing on again meets resistance at once: the stick spring (relaxed by one tick)
    f1, _ = tick(m, p + [0.0, 0.0, -1e-4], np.zeros(3))
    decay = math.exp(-DT / tau)
    assert f1[2] > 0.0 and f1[2] == pytest.approx((m.model.params[0]["k_stick"] * 1e-4 + f[2]) * decay, rel=1e-6)


def test_the_paper_preset_is_table_1_with_the_physical_depth():
    cfg = flat_config(load_config("config/presets/paper.toml"), radius_mm=200.0)
    assert cfg.needle.mechanics == "table1"
    m = model_for(cfg)
    v = 10e-3
    depth, force, diag = insert(m, 0.022, speed=v)
    assert m.states == (2, 2, 2)
    d_per_m = np.array([la.damping_n_s_per_m_per_mm for la in cfg.layers]) * 1e3
    checked = 0
    for s, f, d in zip(depth, force, diag):
        held = int(d["front"])  # layers broken by this tick
        if held == 0 or s <= 0.0:
            continue
        want = -(d_per_m @ lengths_at(cfg, s, held)) * v  # along +s
        assert d["f_damp"] == pytest.approx(want, rel=1e-7, abs=1e-12)
        if d["f_surface"] == 0.0:
            assert -f[2] == pytest.approx(want, rel=1e-7, abs=1e-12)
        checked += 1
    assert checked > 1500


@pytest.fixture(scope="module")
def angled():
    return model_for(flat_config())


@pytest.mark.parametrize("given", [False, True])
@pytest.mark.parametrize("angle", [0, 15, 30, 45, 60, 75])
def test_straight_insertions_at_any_angle(angled, angle, given):
    m = angled
    m.reset(keep_holes=False)
    th = math.radians(angle)
    a = np.array([math.sin(th) * math.cos(0.7), math.sin(th) * math.sin(0.7), -math.cos(th)])
    depth, force, diag = insert(m, 0.012 / math.cos(th) + 4e-3, direction=a, axis=a if given else None)
    assert m.states == (2, 2, 2)
    assert math.degrees(math.acos(min(1.0, float(m.axis @ a)))) < 2.0
    assert np.linalg.norm(m.entry) < 5e-5  # the line crosses the rest skin at the acupoint
    assert diag["clamped"].max() == 0.0
    assert diag["f_lateral"].max() < 5e-3  # nothing pulls the needle off its line


def test_lateral_resistance_grows_with_the_needle_length_held(angled):
    m = angled
    cfg = m.cfg
    ratios = []
    for depth in (0.004, 0.016):
        m.reset(keep_holes=False)
        d_, f_, _ = insert(m, depth)
        held = m.rec["lengths"].sum()
        f, d = tick(m, np.array([1e-4, 0.0, -d_[-1]]), np.zeros(3))
        k_eff = d["f_lateral"] / 1e-4
        want = cfg.needle.lateral_stiffness_n_per_mm * 1e3 * held / (cfg.needle.length_mm * 1e-3)
        assert k_eff == pytest.approx(want, rel=1e-6)
        ratios.append(k_eff)
    assert ratios[1] > 2.0 * ratios[0]


def test_reinsertion_along_a_track_meets_friction_only(rich):
    cfg, m = rich
    cut, fs, fc, b = mech(cfg)
    m.reset(keep_holes=False)
    d1, f1, g1 = insert(m, 0.02)
    # withdraw to 2 mm above the skin
    for i in range(1, int(0.022 / 3e-6) + 1):
        tick(m, np.array([0.0, 0.0, -0.02 + 3e-6 * i]), np.array([0.0, 0.0, 3e-3]))
    assert not m.inserted
    d2, f2, g2 = insert(m, 0.0195)  # stops short of the first pass's front (0.125 mm: one radius)
    assert m.states == (2, 2, 2)
    assert (g2["puncture"] < 0).all() and g2["f_surface"].max() == 0.0  # no surface to break
    assert np.abs(g2["f_cut"]).max() == 0.0  # nothing left to cut
    assert np.abs(f2[:, 2]).max() <= np.abs(f1[:, 2]).max()
    # deep in the muscle both passes slide: they differ by exactly the cutting force
    n = d2.size
    np.testing.assert_allclose(d1[:n], d2)
    late = d2 > 0.017
    np.testing.assert_allclose(-f1[:n][late, 2] - -f2[late, 2], -cut[2], rtol=1e-9)


def test_a_trajectory_s_axis_columns_reach_the_step(angled, tmp_path):
    """A replay (the scripted device, the headless engine's compiled blocks) takes the needle's axis
    from the file's axis_x,axis_y,axis_z: here 10 deg off the direction of travel, and recorded."""
    from haptic_acu.devices.scripted import ScriptedDevice
    from haptic_acu.session.engine import Session

    m = angled
    m.reset(keep_holes=False)
    travel = np.array([math.sin(math.radians(30)), 0.0, -math.cos(math.radians(30))])
    given = np.array([math.sin(math.radians(40)), 0.0, -math.cos(math.radians(40))])
    rows = ["t_s,x_mm,y_mm,z_mm,axis_x,axis_y,axis_z"]
    for i in range(0, 2001, 5):
        t = i * 1e-3
        p = (-2e-3 + 5e-3 * t) * travel * 1e3
        rows.append(f"{t:.3f},{p[0]:.6f},{p[1]:.6f},{p[2]:.6f},{given[0]:.9f},{given[1]:.9f},{given[2]:.9f}")
    path = tmp_path / "axis.csv"
    path.write_text("\n".join(rows) + "\n")
    dev = ScriptedDevice(path)
    dev.open()
    try:
        result = Session(m.cfg, dev, clock="sim", model=m).run()
    finally:
        dev.close()
    assert result.fault is None
    assert m.inserted
    np.testing.assert_allclose(m.axis, given, atol=1e-6)

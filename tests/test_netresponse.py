"""The force net's tabulated static response (haptic_acu.tissue.netresponse), the servo's default fast path.

Checked against independent solutions: the NumPy reference's own multicolour Gauss-Seidel-Newton
solver (bench/numpy_reference.py: its own lattice, sweep order and Newton steps) converged at points
off the table's grid, in every direction of the lateral offset; eq. 6 evaluated from the tabulated
displacement field; and the servo step on the table against the NumPy reference reading the same
table through SciPy's interpolator, tick by tick through every layer.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from haptic_acu.bench import scenarios
from haptic_acu.bench.numpy_reference import NumpyNeedle
from haptic_acu.tissue import netresponse
from haptic_acu.base.config import load_config
from haptic_acu.tissue.forcenet import NetParams, lattice, n_particles
from haptic_acu.servo.step import PUNCTURED

TOL = 1e-10  # the default config's static tolerance (m)


@pytest.fixture(scope="module")
def cfg():
    return load_config()


def _reference_static(ref, k, table, tip_local):
    """Converge the NumPy reference's layer-k net on the flat lattice (axis +z, N1 rest at the
    origin) with N1 held at ``tip_local``; warm start: the table's centred field at that depth.
    Returns (reaction along the axis, ring-w mean deflection)."""
    lay = ref.layers[k]
    net = lay["net"]
    net.axis = np.array([0.0, 0.0, 1.0])
    net.X0f = np.zeros((net.hex.n, 3))
    net.X0f[:, :2] = net.hex.plane * lay["L"]
    c = -tip_local[2]
    i = min(int(c / table.h), table.D.shape[0] - 1)
    net.xf = net.X0f + lay["table"]["D"][i]
    net.xf[0] = tip_local
    for _ in range(20000):
        if ref.sweep(lay) < 1e-13:
            break
    else:
        raise AssertionError("reference static solve did not converge")
    return float(ref.net_reaction(lay) @ net.axis), ref.ring_w_deflection(lay)


@pytest.mark.parametrize("k", [0, 1, 2])
def test_table_matches_an_independent_static_solver_off_its_grid(cfg, k):
    # Points between rows and columns, at random directions psi of the lateral offset (the table
    # is solved at psi = 15 degrees and assumes the lattice's sixfold symmetry): within 1e-3 of
    # the puncture force and 3e-3 of the puncture threshold (measured over 12 random points per layer
    # of the default nets: 2e-4 and 2.2e-3 at worst, the skin's ring w; the earlier defaults' larger
    # nets: 6e-4 and 8e-4).
    tissue = scenarios.tissue_for(cfg)
    ref = NumpyNeedle(cfg, tissue)
    t = ref.tables[k]
    p = NetParams.from_layer(cfg.layers[k])
    tab, meta = t.packed()
    f_punct = t.F[0, int((t.F.shape[1] - 2) / netresponse.ROW_MARGIN)]
    rng = np.random.default_rng(7 + k)
    c_top = (t.F.shape[1] - 1) * t.h / netresponse.ROW_MARGIN
    for _ in range(3):
        rho = rng.uniform(0.0, 0.5 * p.spacing_m)
        psi = rng.uniform(0.0, 2 * math.pi)
        c = rng.uniform(0.1, 1.0) * c_top
        f_ref, r_ref = _reference_static(ref, k, t, np.array([rho * math.cos(psi), rho * math.sin(psi), -c]))
        f, r = netresponse.lookup(tab, meta, rho * rho, c)
        assert abs(f - f_ref) < 1e-3 * f_punct, (rho, psi, c, f, f_ref)
        assert abs(r - r_ref) < 3e-3 * p.threshold_m, (rho, psi, c, r, r_ref)


@pytest.mark.parametrize("k", [0, 1, 2])
def test_tabulated_field_satisfies_eq6_and_gives_ring_w(cfg, k):
    # Eq. 6: at equilibrium F . n = K * sum_i dZ_i over the net (the field's normal components),
    # on every row of the centred column; and ring w's mean deflection is the field's.
    p = NetParams.from_layer(cfg.layers[k])
    t = netresponse.table_for(p, TOL)
    dz = -t.D[:, :, 2]  # (rows, particles), positive pushed in
    c = np.arange(t.D.shape[0]) * t.h
    np.testing.assert_allclose(dz[:, 0], c, rtol=0, atol=1e-15)  # N1 at the tip
    eq6 = p.k_virtual * dz.sum(axis=1)
    np.testing.assert_allclose(t.F[0], eq6, rtol=0, atol=1e-5 * t.F[0].max())
    ring = lattice(p.w).ring[: n_particles(p.w)]
    np.testing.assert_allclose(t.R[0], dz[:, ring == p.w].mean(axis=1), rtol=0, atol=1e-15)


@pytest.mark.parametrize("k", [0, 1, 2])
def test_table_rows_start_at_rest_rise_and_pass_the_threshold(cfg, k):
    p = NetParams.from_layer(cfg.layers[k])
    t = netresponse.table_for(p, TOL)
    assert t.F.shape[0] == netresponse.COLUMNS
    assert math.isclose(t.h, p.spacing_m / netresponse.ROWS_PER_SPACING)
    assert abs(t.F[0, 0]) < 1e-9 and abs(t.R[0, 0]) < 1e-15  # untouched: no force, no deflection
    assert np.all(np.diff(t.F[0]) > 0) and np.all(np.diff(t.R[0]) > 0)  # deeper: harder, more deflection
    # the rows reach past the centred puncture depth by the margin, not much further
    first = int(np.argmax(t.R[0] > p.threshold_m))
    assert t.R[0, -1] > p.threshold_m and first > 0
    assert t.F.shape[1] <= math.ceil(first * netresponse.ROW_MARGIN) + 3
    # near the puncture depth a lateral offset stretches the net more: ring w deflects further
    assert t.R[-1, first] > t.R[0, first]


def test_never_breaking_net_is_tabulated_up_to_the_force_cap(cfg):
    p = NetParams.from_layer(dataclasses.replace(cfg.skin, rings=4, puncture_threshold_um=1e9))
    t = netresponse.build(p, TOL)
    assert t.F[0, -1] > netresponse.F_CAP_N
    assert t.F[0, int((t.F.shape[1] - 3) / netresponse.ROW_MARGIN)] <= netresponse.F_CAP_N


def test_build_is_deterministic_and_the_cache_round_trips(tmp_path, monkeypatch):
    monkeypatch.setenv("HAPTIC_ACU_CACHE", str(tmp_path))
    monkeypatch.setattr(netresponse, "_MEMO", {})
    p = NetParams(w=3, spacing_m=1e-3, k_virtual=100.0, k_surface=1000.0, pretension=0.05, threshold_m=50e-6)
    a = netresponse.table_for(p, TOL)
    files = list(tmp_path.glob("net-*.npz"))
    assert len(files) == 1
    b = netresponse.build(p, TOL)  # solved again on two threads: the same bits
    for x, y in ((a.F, b.F), (a.R, b.R), (a.D, b.D)):
        assert np.array_equal(x, y)
    monkeypatch.setattr(netresponse, "_MEMO", {})
    c = netresponse.table_for(p, TOL)  # from the file
    assert c.build_s == 0.0 and np.array_equal(c.F, a.F) and np.array_equal(c.D, a.D) and c.h == a.h
    # a damaged cache file is solved again, not an error
    files[0].write_bytes(b"not a table")
    monkeypatch.setattr(netresponse, "_MEMO", {})
    d = netresponse.table_for(p, TOL)
    assert np.array_equal(d.F, a.F)
    # another parameter, another key
    assert netresponse.table_key(dataclasses.replace(p, k_surface=1001.0), TOL) != netresponse.table_key(p, TOL)


def test_an_unwritable_cache_is_not_an_error(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    monkeypatch.setenv("HAPTIC_ACU_CACHE", str(blocker / "sub"))
    monkeypatch.setattr(netresponse, "_MEMO", {})
    p = NetParams(w=2, spacing_m=1e-3, k_virtual=100.0, k_surface=1000.0, pretension=0.05, threshold_m=20e-6)
    t = netresponse.table_for(p, TOL)
    assert t.F.shape[0] == netresponse.COLUMNS


def test_servo_on_the_table_matches_the_numpy_reference_through_every_layer(cfg):
    # The default config (every net tabulated): 10 mm/s straight in to 20 mm below the skin, then
    # lift-thrust strokes. Both read the same tables, the compiled step bilinearly, the reference
    # through SciPy's RegularGridInterpolator: the same punctures on the same ticks and the same
    # forces to rounding.
    model = scenarios.model_for(cfg)
    ref = NumpyNeedle(cfg, model.tissue)
    P1, V1 = scenarios.straight(1e-3, -20e-3, 0.01)
    P2, V2 = scenarios.stroke(-20e-3, -4e-3, 1000, period_s=1.0 / 0.75)
    P, V = np.vstack([P1, P2]), np.vstack([V1, V2])
    punct_c, punct_r = [], []
    worst = 0.0
    for i, (p, v) in enumerate(zip(P, V)):
        fc = model.step(p, v).copy()
        fr = ref.step(p, v).copy()
        if model.diag["puncture"] >= 0:
            punct_c.append((int(model.diag["puncture"]), i))
        if ref.punctured_now >= 0:
            punct_r.append((ref.punctured_now, i))
        worst = max(worst, float(np.abs(fc - fr).max()))
    assert [k for k, _ in punct_c] == [0, 1, 2]
    assert punct_r == punct_c
    assert model.states == (PUNCTURED,) * 3
    assert worst < 1e-9  # measured 6e-12: the two collisions (SciPy vs compiled SH) differ in rounding
    assert np.abs(fc).max() > 0.05


def test_servo_on_the_table_tracks_converged_sweeps(cfg):
    # The same insertion with the net relaxed to (near) convergence every tick: punctures within a
    # tick or two of each other and pressing forces within 0.2% of the puncture force. (With the
    # default two sweeps per tick the sweeps lag the static solution, and break later at higher
    # force: the table is the more exact solution of the same model.)
    swept = scenarios.config_copy(cfg, servo_net="sweeps", sweeps_per_tick=60)
    a = scenarios.model_for(cfg)
    b = scenarios.model_for(swept)
    P, V = scenarios.straight(1e-3, -16e-3, 0.01)
    pa, pb = [], []
    fa, fb = [], []
    for p, v in zip(P, V):
        f1 = a.step(p, v)[2]
        if a.diag["puncture"] >= 0:
            pa.append(float(-p[2]))
        f2 = b.step(p, v)[2]
        if b.diag["puncture"] >= 0:
            pb.append(float(-p[2]))
        if len(pa) == len(pb):
            fa.append(f1)
            fb.append(f2)
    assert len(pa) == len(pb) == 3
    np.testing.assert_allclose(pa, pb, rtol=0, atol=2.5e-5)  # 2.5 ticks at 10 mm/s
    peak = max(max(fa), max(fb))
    assert np.abs(np.array(fa) - np.array(fb)).max() < 2e-3 * peak


def test_the_rendered_pressing_net_is_the_static_solution_at_the_tip(cfg):
    # Straight down at the acupoint into the skin, held 1 mm past first touch: the net the visual
    # loop reads (laid from the table at the tip the servo held) against the package's own static
    # solve of a net built at the same contact point with N1 at the same tip.
    from haptic_acu.tissue.forcenet import Net

    model = scenarios.model_for(cfg)
    P, V = scenarios.straight(1e-3, -1.0e-3, 0.01)
    for p, v in zip(P, V):
        model.step(p, v)
    assert model.states[0] == 1  # pressing
    idx = model.active_slot(0)
    flat = model.pressed_net_flat(idx)
    net = Net.allocate(NetParams.from_layer(cfg.skin))
    net.build(model.coeffs[0], model.lmax, model.centre, model.X0f[idx][0], model.axes[idx])
    net.solve(flat[0].copy(), tol_m=1e-13, max_sweeps=200000)
    np.testing.assert_allclose(flat, net.xf, rtol=0, atol=2e-7)
    assert np.abs(flat - model.X0f[idx]).max() > 5e-4  # a real dent, not the rest shape


def test_reference_lays_the_same_shape_as_the_compiled_model(cfg):
    # The NumPy reference's laid_shape (its own lattice order, numpy interpolation and frame) against
    # the compiled model's pressed net, at the same contact and tip, mapped by lattice position.
    model = scenarios.model_for(cfg)
    ref = NumpyNeedle(cfg, model.tissue)
    P, V = scenarios.straight(1e-3, -0.8e-3, 0.01)
    for p, v in zip(P, V):
        model.step(p, v)
        ref.step(p, v)
    assert model.states[0] == 1 and ref.states[0] == 1
    idx = model.active_slot(0)
    ours = model.pressed_net_flat(idx)
    lay = ref.layers[0]
    theirs = ref.laid_shape(lay, lay["net"].xf[0].copy())
    pkg = {tuple(np.round(xy * 4).astype(int)): i for i, xy in enumerate(lattice(cfg.skin.rings).plane)}
    perm = np.array([pkg[tuple(np.round(xy * 4).astype(int))] for xy in lay["net"].hex.plane])
    np.testing.assert_allclose(theirs, ours[perm], rtol=0, atol=1e-12)

"""The four baseline tissue models (model.kind = msm, fem, bem, shf; haptic_acu.tissue.baselines),
held to closed forms and published rules, then run through the servo on every bundled trajectory.

FEM against Sneddon's flat punch F = 2 a E d / (1 - nu^2) and Boussinesq's surface displacement
u(r) = F (1 - nu^2) / (pi E r) on a thick homogeneous body, with a refinement study; BEM against
the FEM; the MSM lattice's Young's modulus from a simulated compression test; the SHF's break at
its configured force.
"""
from __future__ import annotations

import filecmp
import math

import numpy as np
import pytest

from haptic_acu.base.config import MODEL_KINDS, load_config
from haptic_acu.base.errors import UserError
from haptic_acu.cli import main
from haptic_acu.tissue import baselines as B
from haptic_acu.tissue import bem, fem, msm

A = 0.125e-3  # the default needle's radius (0.25 mm diameter)
E = 30e3
NU = 0.3  # linear tetrahedra lock as nu -> 0.5; the closed forms hold for any nu
SNEDDON = 2 * A * E / (1 - NU ** 2)  # N per m of indentation
BASELINES = [k for k in MODEL_KINDS if k != "forcenet"]


# ---- config ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("item, key", [
    ("model.kind=tetra", "model.kind"),
    ("model.poisson_ratio=[0.5,0.45,0.45]", "model.poisson_ratio"),
    ("model.young_modulus_kpa=[-420,3.25,30]", "model.young_modulus_kpa"),
    ("model.msm_spacing_mm=0", "model.msm_spacing_mm"),
    ("model.fracture_toughness_j_per_m2=[1136,0,550]", "model.fracture_toughness_j_per_m2"),
])
def test_a_bad_model_config_is_one_line_naming_the_key(item, key, capsys, tmp_path):
    with pytest.raises(UserError, match=rf"key '{key}'"):
        load_config(overrides=[item])
    assert main(["replay", "default", "--set", item, "--out", str(tmp_path / "o"), "--no-rrd", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and key in err[0], err


def test_a_config_without_the_model_section_is_the_force_net(tmp_path):
    text = (B.__file__ and load_config().path)
    src = open(text, encoding="utf-8").read()
    cut = src[:src.index("[model]")]
    (tmp_path / "old.toml").write_text(cut)
    cfg = load_config(tmp_path / "old.toml")
    assert cfg.model.kind == "forcenet"
    assert load_config(tmp_path / "old.toml", ["model.kind=fem"]).model.kind == "fem"


def test_the_retired_break_depth_key_is_read_with_a_one_line_warning(tmp_path, capsys):
    src = open(load_config().path, encoding="utf-8").read()
    old = src.replace("fracture_toughness_j_per_m2 =", "puncture_depth_mm = [1.5, 1.0, 1.0]\nfracture_toughness_j_per_m2 =")
    (tmp_path / "old.toml").write_text(old)
    cfg = load_config(tmp_path / "old.toml", ["model.kind=fem"])
    assert cfg.model.fracture_toughness_j_per_m2 == load_config().model.fracture_toughness_j_per_m2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "model.puncture_depth_mm" in err[0] and "fracture_toughness_j_per_m2" in err[0]


def test_the_retired_spring_strain_key_is_read_with_a_one_line_warning(tmp_path, capsys):
    src = open(load_config().path, encoding="utf-8").read()
    old = src.replace("msm_gauge_strain =", "msm_puncture_strain = [0.22, 0.2, 0.2]\nmsm_gauge_strain =")
    (tmp_path / "old.toml").write_text(old)
    cfg = load_config(tmp_path / "old.toml", ["model.kind=msm"])
    assert cfg.model.msm_gauge_strain == load_config().model.msm_gauge_strain
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "model.msm_puncture_strain" in err[0] and "msm_gauge_strain" in err[0]


# ---- MSM: the lattice's E and nu, its dynamics ----------------------------------------------------

@pytest.mark.parametrize("E_pa, nu, h", [(420e3, 0.45, 0.5e-3), (3.25e3, 0.49, 1e-3), (30e3, 0.45, 0.25e-3),
                                         (30e3, 0.25, 0.5e-3), (420e3, 0.3, 0.5e-3), (30e3, 0.1, 0.5e-3)])
def test_msm_lattice_compression_gives_the_young_modulus_and_poisson_ratio_it_was_built_from(E_pa, nu, h):
    # a free cube between rolling plates, 0.1% strain: stress / strain and lateral / axial strain
    E_eff, nu_eff = msm.compression_test(E_pa, nu, h, cells=5)
    assert E_eff == pytest.approx(E_pa, rel=0.10)
    assert nu_eff == pytest.approx(nu, rel=0.10)


def test_msm_without_the_volume_energy_is_the_cauchy_lattice():
    # the springs alone (the volume term's lambda - mu set to 0) give nu = 1/4, whatever nu was asked:
    # the Cauchy relation, which is why the volume energy is there
    n, h, mu = 6, 1e-3, 1e3
    K, _ = msm.stiffness_matrix(n, n, n, h, np.full((5, 5, 5), mu), np.zeros((5, 5, 5)))
    idx = np.arange(n ** 3).reshape(n, n, n)
    top, bottom = idx[:, :, -1].ravel(), idx[:, :, 0].ravel()
    fixed = np.concatenate([3 * bottom + 2, 3 * top + 2, [0, 1, 3 * idx[-1, 0, 0] + 1]])
    vals = np.concatenate([np.zeros(bottom.size), np.full(top.size, -5e-6), [0.0, 0.0, 0.0]])
    u = msm._solve_fixed(K, fixed, vals).reshape(-1, 3)
    lateral = (u[idx[-1].ravel(), 0] - u[idx[0].ravel(), 0]).mean()
    assert lateral / 5e-6 == pytest.approx(0.25, rel=1e-6)


def test_msm_springs_follow_the_rule_and_sum_at_layer_interfaces():
    # inside a homogeneous lattice every spring is mu h; an edge spring on a face between two
    # materials gets a quarter of mu h from each of its four cubes
    h = 1e-3
    n = 4
    cube = np.full((n - 1, n - 1, n - 1), 1e3)
    i, j, k, nv = msm.springs(n, n, n, h, cube)
    inner_edge = (i == 21) & (j == 22)  # node (1,1,1) -> (1,1,2): an edge inside
    assert k[inner_edge][0] == pytest.approx(1e3 * h)
    cube[:, :, 1:] = 3e3  # the upper two cube layers stiffer
    i, j, k, nv = msm.springs(n, n, n, h, cube)
    flat_edge = (i == 1 * 16 + 1 * 4 + 1) & (j == 2 * 16 + 1 * 4 + 1)  # along x in the plane z = 1
    assert k[flat_edge][0] == pytest.approx(0.25 * h * (2 * 1e3 + 2 * 3e3))


SMALL = dict(E=[420e3, 3.25e3], nu=[0.45, 0.45], rho=[1109.0, 911.0], thick=[1e-3, 5e-3], h=0.5e-3,
             half_cells=3, depth=2e-3)


def _full_lattice(E, nu, rho, thick, h, half_cells, depth):
    """The same patch, every degree of freedom: (K free-free, lumped masses, the tip's dof, n, nz)."""
    n, nz, cmu, clv, crho = msm._patch(E, nu, rho, thick, h, half_cells, depth)
    K, _ = msm.stiffness_matrix(n, n, nz, h, cmu, clv)
    mass = np.repeat(msm.lumped_masses(n, n, nz, h, crho), 3)
    free = np.nonzero(np.repeat(np.tile(np.arange(nz), n * n) > 0, 3))[0]
    c = n // 2
    tip = 3 * ((c * n + c) * nz + nz - 1) + 2
    return K[free][:, free].tocsc(), mass[free], int(np.nonzero(free == tip)[0][0]), n, nz


def test_msm_symmetric_modes_give_the_full_lattices_static_stiffness():
    import scipy.sparse.linalg as spla

    p = SMALL
    md = msm.modes(p["E"], p["nu"], p["rho"], p["thick"], p["h"], p["half_cells"], p["depth"])
    K, _, tip, _, _ = _full_lattice(p["E"], p["nu"], p["rho"], p["thick"], p["h"], p["half_cells"], p["depth"])
    e = np.zeros(K.shape[0])
    e[tip] = 1.0
    u = spla.spsolve(K, e)  # a unit upward force at the tip
    assert md.stiffness == pytest.approx(1.0 / u[tip], rel=1e-8)
    # the reduction keeps a fraction of the modes: those the square's symmetries leave unchanged
    assert len(md.phi) < K.shape[0] / 6


def test_msm_patch_is_stable_below_a_quarter_too():
    # below nu = 1/4 the volume energy's stiffness is negative; the springs keep the patch positive
    p = SMALL
    for nu in (0.0, 0.1):
        md = msm.modes(p["E"], [nu, nu], p["rho"], p["thick"], p["h"], p["half_cells"], p["depth"])
        assert md.omega.min() > 2 * math.pi * 10 and md.stiffness > 0


def test_msm_servo_step_is_the_full_lattices_backward_euler_with_unilateral_contact():
    # the modal step (msm_tick, undamped modes: backward Euler's own dissipation only) against backward
    # Euler on every degree of freedom of the same lattice, the contact solved the same way
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    p = SMALL
    dt = 1e-3
    md = msm.modes(p["E"], p["nu"], p["rho"], p["thick"], p["h"], p["half_cells"], p["depth"])
    tab, count, g = msm.pack([md], 1, zeta=0.0, dt=dt)
    K, mass, tip, _, _ = _full_lattice(p["E"], p["nu"], p["rho"], p["thick"], p["h"], p["half_cells"], p["depth"])
    lu = spla.splu((sp.diags(mass) + dt * dt * K).tocsc())
    e = np.zeros(K.shape[0])
    e[tip] = -1.0  # the tip pushes down
    resp = lu.solve(dt * dt * e)  # the step's displacement per newton of contact force
    g_full = -resp[tip]
    assert g[0] == pytest.approx(g_full, rel=1e-8)
    u = np.zeros(K.shape[0])
    v = np.zeros(K.shape[0])
    q = np.zeros((2, tab.shape[1]))
    # in 3 ms to 0.3 mm, held, out fast (the surface, slower, leaves the tip), back in
    path = np.concatenate([np.linspace(0.1e-3, 0.3e-3, 3), np.full(20, 0.3e-3), np.linspace(0.2e-3, -0.2e-3, 5),
                           np.full(5, -0.2e-3), np.linspace(0.0, 0.2e-3, 5)])
    fs, ff = [], []
    for dep in path:
        f_m, _ = msm.msm_tick(tab, 0, count[0], g[0], q[0], q[1], dep, dt)
        # full: (M + dt^2 K) v' = M v - dt K u + dt F; u' = u + dt v'
        v_free = lu.solve(mass * v - dt * (K @ u))
        u_free = -(u + dt * v_free)[tip]  # downward
        f = max(0.0, (dep - u_free) / g_full)
        v = v_free + f * resp / dt
        u = u + dt * v
        fs.append(f_m)
        ff.append(f)
    fs, ff = np.array(fs), np.array(ff)
    assert np.all(fs >= 0.0) and fs.max() > 0
    assert np.allclose(fs, ff, rtol=1e-6, atol=1e-9 * ff.max())
    assert (fs == 0).any() and (ff == 0).any()  # the contact let go somewhere, in both


def test_msm_held_press_settles_to_the_static_force_and_stays_bounded():
    # the servo's damped step at 1 ms: a 1 mm press at once (far beyond a hand's speed), held: the force
    # settles to the static k d, never above the first tick's (backward Euler is unconditionally stable)
    p = SMALL
    md = msm.modes(p["E"], p["nu"], p["rho"], p["thick"], p["h"], p["half_cells"], p["depth"])
    tab, count, g = msm.pack([md], 1)
    q = np.zeros((2, tab.shape[1]))
    f = np.array([msm.msm_tick(tab, 0, count[0], g[0], q[0], q[1], 1e-3, 1e-3)[0] for _ in range(400)])
    assert np.isfinite(f).all() and f.max() <= f[0] * (1 + 1e-9)
    assert f[-1] == pytest.approx(md.stiffness * 1e-3, rel=1e-4)
    assert np.abs(np.diff(f[-50:])).max() < 1e-6 * f[-1]


def test_msm_press_reports_the_static_spring_strain():
    p = SMALL
    md = msm.modes(p["E"], p["nu"], p["rho"], p["thick"], p["h"], p["half_cells"], p["depth"])
    tab, count, g = msm.pack([md], 1)
    q = np.zeros((2, tab.shape[1]))
    for _ in range(400):
        _, strain = msm.msm_tick(tab, 0, count[0], g[0], q[0], q[1], 0.2e-3, 1e-3)
    assert strain == pytest.approx(md.strain_per_m * 0.2e-3, rel=1e-4)


def test_msm_gauge_strain_is_the_full_lattices_static_column_shortening():
    # the servo's strain row (modal, on the symmetric modes) against the full lattice's statics, read
    # off the column under the tip by hand: the relative shortening over GAUGE_M (1 mm, two cells)
    import scipy.sparse.linalg as spla

    p = SMALL
    md = msm.modes(p["E"], p["nu"], p["rho"], p["thick"], p["h"], p["half_cells"], p["depth"])
    K, _, tip, n, nz = _full_lattice(p["E"], p["nu"], p["rho"], p["thick"], p["h"], p["half_cells"], p["depth"])
    e = np.zeros(K.shape[0])
    e[tip] = -1.0
    u = spla.spsolve(K, e)  # a unit downward force at the tip
    two_cells_down = tip - 3 * 2  # the same column's node 1 mm (2 x 0.5 mm) below, its z dof
    shortening = (u[two_cells_down] - u[tip]) / 1e-3
    assert msm.GAUGE_M == 1e-3
    assert md.strain_per_m == pytest.approx(shortening / -u[tip], rel=1e-8)


@pytest.fixture(scope="module")
def msm_refinement():
    """A lattice's statics at two spacings, on the same 2 mm wide, 2 mm deep block: (homogeneous
    fat-like, skin over fat) -> {h: (k, gauge strain per m, tip spring strain per m)}."""
    bodies = {"homogeneous": ([3.25e3], [0.45], [8e-3]), "layered": ([420e3, 3.25e3], [0.45, 0.45], [0.8e-3, 8e-3])}
    return {name: {h: msm.static_press(E_, nu, th, h, 2e-3, 2e-3) for h in (0.5e-3, 0.25e-3)}
            for name, (E_, nu, th) in bodies.items()}


def test_msm_break_depth_on_a_homogeneous_layer_holds_under_refinement(msm_refinement):
    # the gauge strain's static break depth moves < 10% when the spacing halves (measured: 6-7%);
    # a spring's strain at the pushed node is d / h times a constant: its break depth halves
    r = msm_refinement["homogeneous"]
    gauge = r[0.25e-3][1] / r[0.5e-3][1]
    assert 1.0 < gauge < 1.10
    spring = r[0.25e-3][2] / r[0.5e-3][2]
    assert spring == pytest.approx(2.0, rel=0.05)
    # and E cancels: the same strains for a body 100 times stiffer
    stiff = msm.static_press([3.25e5], [0.45], [8e-3], 0.5e-3, 2e-3, 2e-3)
    assert stiff[1] == pytest.approx(r[0.5e-3][1], rel=1e-9) and stiff[0] == pytest.approx(100 * r[0.5e-3][0], rel=1e-9)


def test_msm_point_contact_localises_under_refinement(msm_refinement):
    # a pushed node is a point load: its stiffness halves with the spacing, and on the stiff skin over
    # soft fat the dent localises, so the gauge strain there still grows (documented in docs/model.md
    # s12.2): the break depth of a point-driven lattice is a property of its spacing
    for name in ("homogeneous", "layered"):
        r = msm_refinement[name]
        assert r[0.25e-3][0] < 0.75 * r[0.5e-3][0]
    r = msm_refinement["layered"]
    assert 1.2 < r[0.25e-3][1] / r[0.5e-3][1] < 2.0


def test_the_energy_criterion_on_a_force_curve_meets_its_closed_forms():
    # a linear contact: the curve's break depth is sqrt(2 J pi a^2 / k) (exact: trapezoids are exact
    # on a line); Hertz's F = c d^1.5 stores 0.4 c d^2.5, so d_c = (J pi a^2 / (0.4 c))^0.4
    J, k = 1136.0, 41.0
    d = np.linspace(0.0, 10e-3, 2001)
    assert B.rupture_depth_curve(d, k * d, J, A) == pytest.approx(B.rupture_depth(k, J, A), rel=1e-12)
    c = 300.0
    want = (J * math.pi * A * A / (0.4 * c)) ** 0.4
    assert B.rupture_depth_curve(d, c * d ** 1.5, J, A) == pytest.approx(want, rel=1e-5)
    assert B.rupture_depth_curve(d[:5], k * d[:5], J, A) == math.inf  # the curve ends first


def test_a_hemispherical_tip_breaks_by_the_stored_energy_of_its_own_contact():
    # the BEM's skin with a rounded tip: its force lies below the flat tip's k d (less of the disc is
    # held) and above the flat tip's moved back by the tip's height a (the rounded end lies within a
    # of the flat one), so the energy criterion's depth lies between the flat tip's and that plus a
    flat = B.contact_for(load_config(overrides=["model.kind=bem"]))
    round_ = B.contact_for(load_config(overrides=["model.kind=bem", "model.tip_shape=hemisphere"]))
    d0, d1 = flat.crit_depth, round_.crit_depth
    assert np.all(d1 > d0 * 1.001) and np.all(d1 < d0 + A)
    # and the force curve it integrates is the servo's own contact solve, which at that depth holds
    # less force than the flat tip's k d
    from haptic_acu.tissue import contact
    C = round_.ct_c[:round_.ct_n[0], :round_.ct_n[0]]
    rho = np.hypot(*bem.disc_elements(A)[1].T)
    f, _, _ = contact.press_curve(C, contact.tip_heights(rho, A, "hemisphere"), np.linspace(0, d1[0], 200))
    assert 0 < f[-1] < flat.stiffness[0] * d1[0]


# ---- FEM against closed forms; BEM against the FEM ------------------------------------------------

@pytest.fixture(scope="module")
def fem_refinement():
    """The flat punch on a 16 mm homogeneous block at three refinements (elements across the tip)."""
    return {n: fem.flat_punch([E], [NU], [16e-3], A, n_in=n, ratio=r, half_width=16e-3, depth=16e-3)
            for n, r in ((1, 1.5), (2, 1.45), (3, 1.35))}


@pytest.mark.slow
def test_fem_flat_punch_meets_sneddon(fem_refinement):
    assert fem_refinement[3].stiffness == pytest.approx(SNEDDON, rel=0.15)


@pytest.mark.slow
def test_fem_force_converges_under_refinement(fem_refinement):
    err = [abs(fem_refinement[n].stiffness / SNEDDON - 1) for n in (1, 2, 3)]
    assert err[0] > err[1] > err[2], err
    steps = [fem_refinement[1].stiffness - fem_refinement[2].stiffness,
             fem_refinement[2].stiffness - fem_refinement[3].stiffness]
    assert steps[0] > steps[1] > 0, steps  # the changes shrink: converging from above


@pytest.mark.slow
@pytest.mark.parametrize("r_mm", [1.5, 2.0])
def test_fem_surface_displacement_falls_off_as_boussinesq(fem_refinement, r_mm):
    res = fem_refinement[3]
    i = int(np.argmin(abs(res.profile_r - r_mm * 1e-3)))
    r = res.profile_r[i]
    expect = res.stiffness * (1 - NU ** 2) / (math.pi * E * r)  # per metre of indentation
    assert res.profile_u[i] == pytest.approx(expect, rel=0.20)


@pytest.mark.slow
def test_bem_contact_force_is_the_fems_within_10_percent(fem_refinement):
    assert bem.flat_punch(E, NU, A) == pytest.approx(fem_refinement[3].stiffness, rel=0.10)


def test_bem_meets_sneddon():
    for nu in (0.0, 0.3, 0.45):
        assert bem.flat_punch(E, nu, A) == pytest.approx(2 * A * E / (1 - nu ** 2), rel=0.03)


def test_fem_condensed_patch_is_symmetric_positive_definite():
    res = fem.flat_punch([E], [NU], [8e-3], A, n_in=1, ratio=1.6, half_width=8e-3, depth=8e-3)
    assert np.allclose(res.schur, res.schur.T)
    assert np.linalg.eigvalsh(res.schur).min() > 0


@pytest.fixture(scope="module")
def body_mesh():
    """The servo's FEM mesh of the default body from the skin down, around the acupoint."""
    from haptic_acu.tissue.body import Tissue

    tis = Tissue.from_config(load_config())
    bnd = fem.sh_boundaries(tis.coeffs, tis.centre, 0)
    return tis, fem.body_mesh(bnd, np.zeros(3), A)


def _radius_toward(tis, k, pts):
    from haptic_acu.tissue import shf

    d = pts - tis.centre
    rho = np.linalg.norm(d, axis=1)
    theta = np.arccos(d[:, 2] / rho)
    phi = np.arctan2(d[:, 1], d[:, 0])
    return rho, shf.evaluate(tis.coeffs[k], theta, phi)


def test_fem_mesh_nodes_on_each_interface_lie_on_its_sh_boundary(body_mesh):
    # the skin surface and skin/fat (the block is 8 mm deep): every node meshed at that boundary's
    # nominal depth sits on the SH surface r_k(theta, phi) in its own direction (evaluated here, apart
    # from the mesher)
    tis, bm = body_mesh
    nominal = tis.depths_at_acupoint()
    p = bm.mesh.p.T
    for k in range(2):
        on = np.isclose(bm.depth, nominal[k], atol=1e-9)
        assert on.sum() >= 100, k
        rho, r_k = _radius_toward(tis, k, p[on])
        assert np.abs(rho - r_k).max() < 1e-9, k
    # the body is curved over the block: the skin surface's nodes are not on one plane
    top = p[np.isclose(bm.depth, 0.0)]
    assert np.ptp(top[:, 2]) > 0.2e-3


def test_fem_mesh_is_conforming_and_each_element_in_its_layer(body_mesh):
    tis, bm = body_mesh
    p = bm.mesh.p
    t = bm.mesh.t

    def volumes(q):
        d1, d2, d3 = (q[:, t[i]] - q[:, t[0]] for i in (1, 2, 3))
        return np.einsum("ij,ij->j", d1, np.cross(d2.T, d3.T).T) / 6.0

    vol = volumes(p)
    chart = volumes(np.vstack([bm.lateral, -bm.depth]))  # the same tetrahedra in the (x, y, depth) chart
    assert (np.abs(vol) > 0).all()
    assert (np.sign(vol) == np.sign(chart)).all()  # none inverted by the mapping onto the boundaries
    # every face is shared by at most two elements (conforming: no hanging faces inside)
    faces = np.sort(np.concatenate([t[[0, 1, 2]], t[[0, 1, 3]], t[[0, 2, 3]], t[[1, 2, 3]]], axis=1), axis=0)
    _, counts = np.unique(faces, axis=1, return_counts=True)
    assert counts.max() == 2
    # each element's centroid lies radially between its layer's SH boundaries
    c = p[:, t].mean(axis=1).T
    for j in range(3):
        sel = bm.layer == j
        if not sel.any():
            continue
        rho, r_top = _radius_toward(tis, j, c[sel])
        _, r_bot = _radius_toward(tis, j + 1, c[sel])
        assert (rho < r_top).all() and (rho > r_bot).all(), j


def test_fem_on_the_curved_body_is_the_flat_blocks_within_a_few_percent():
    # the default limb's curvature radii at the acupoint are 55 mm and more: over a needle's radius
    # the layered body is locally flat, so its muscle's stiffness is the flat body's, and a little softer
    # (a convex surface)
    from haptic_acu.tissue.body import Tissue

    cfg = load_config(overrides=["model.kind=fem"])
    tis = Tissue.from_config(cfg)
    Es = [v * 1e3 for v in cfg.model.young_modulus_kpa]
    nus = list(cfg.model.poisson_ratio)
    thick = [layer.thickness_mm * 1e-3 for layer in cfg.layers]
    curved = fem.tissue_press(tis, 2, Es[2:], nus[2:], A, n_in=1, ratio=1.8, half_width=6e-3, depth=6e-3)
    flat = fem.press(fem.sphere_boundaries(1.0, thick[2:]), np.zeros(3), Es[2:], nus[2:], A, n_in=1, ratio=1.8,
                     half_width=6e-3, depth=6e-3)  # the same mesh on a sphere of 1 m: flat over the block
    assert curved.stiffness == pytest.approx(flat.stiffness, rel=0.03)
    assert curved.stiffness < flat.stiffness


# ---- through the servo ------------------------------------------------------------------------------

def _press_straight_down(kind, overrides=()):
    from haptic_acu.servo.step import NeedleModel

    cfg = load_config(overrides=[f"model.kind={kind}", *overrides])
    nm = NeedleModel(cfg)
    v = np.array([0.0, 0.0, -0.01])
    rows = []
    for i in range(2500):  # 10 mm/s, 25 mm down
        z = 1e-3 - i * 1e-5
        f = nm.step(np.array([0.0, 0.0, z]), v)
        rows.append((z, float(np.linalg.norm(f)), float(nm.diag["puncture"])))
    return cfg, nm, np.array(rows)


@pytest.mark.parametrize("kind", BASELINES)
def test_each_baseline_breaks_every_layer_pressing_straight_in(kind):
    cfg, nm, rows = _press_straight_down(kind)
    assert nm.states == (2, 2, 2)
    assert np.isfinite(rows[:, 1]).all() and rows[:, 1].max() <= cfg.safety.force_limit_n
    broke = rows[rows[:, 2] >= 0]
    assert list(broke[:, 2]) == [0, 1, 2]
    # the skin broke at its configured criterion (the reference speed is this press's 10 mm/s)
    z_skin = broke[0, 0]
    m = cfg.model
    contact = B.contact_for(cfg)
    if kind == "shf":
        before = rows[np.nonzero(rows[:, 2] == 0)[0][0] - 1, 1]
        assert before == pytest.approx(m.shf_puncture_force_n[0], abs=m.shf_stiffness_n_per_mm[0] * 1e3 * 2e-5)
    elif kind in ("fem", "bem"):
        # the energy criterion: the energy stored, k d^2 / 2, pays the toughness over the tip's section
        stored = 0.5 * contact.stiffness[0] * z_skin ** 2
        assert stored == pytest.approx(m.fracture_toughness_j_per_m2[0] * math.pi * A ** 2, rel=0.03)
    else:  # the MSM: at 10 mm/s the lattice is near its statics; its strain threshold's static depth
        assert contact.crit_depth[0] == pytest.approx(m.msm_gauge_strain[0] / msm.modes(
            [v * 1e3 for v in m.young_modulus_kpa], m.poisson_ratio, msm.DENSITY_KG_M3,
            [layer.thickness_mm * 1e-3 for layer in cfg.layers], m.msm_spacing_mm * 1e-3).strain_per_m)
        assert -z_skin == pytest.approx(contact.crit_depth[0], abs=5e-5)


def test_msm_lattice_state_is_the_servos_and_a_reset_puts_it_at_rest():
    from haptic_acu.servo.step import NeedleModel

    nm = NeedleModel(load_config(overrides=["model.kind=msm"]))
    v = np.array([0.0, 0.0, -0.05])

    def press():  # 50 mm/s to 1 mm into the skin, then out
        zs = list(np.arange(0.2e-3, -1.0e-3, -5e-5)) + [0.5e-3] * 5
        return np.array([np.linalg.norm(nm.step(np.array([0.0, 0.0, z]), v)) for z in zs])

    first = press()
    assert first.max() > 0 and np.abs(nm.state.msm_qv).max() > 0 and nm.rec["msm_layer"] == 1
    assert first[-1] == 0.0  # off the surface: no force, the lattice moving on
    nm.reset()
    assert not nm.state.msm_qv.any()
    assert np.array_equal(press(), first)


def test_the_baselines_differ_where_their_sources_do():
    # skin's contact stiffness (N/m): the half-space of skin (BEM) is stiffer than the layered FEM body
    # (skin on soft fat), and SHF's is its configured secant
    ks = {k: B.contact_for(load_config(overrides=[f"model.kind={k}"])).stiffness for k in BASELINES}
    assert ks["bem"][0] > ks["fem"][0]
    assert ks["shf"][0] == pytest.approx(333.3)
    # fat on muscle: FEM and MSM within a factor 2 of each other and of the half-space of fat
    assert 0.5 < ks["fem"][1] / ks["msm"][1] < 2 and 0.5 < ks["fem"][1] / ks["bem"][1] < 2


@pytest.mark.slow
@pytest.mark.parametrize("kind", BASELINES)
def test_every_bundled_trajectory_replays_through_each_model(kind, tmp_path, monkeypatch):
    import json

    from haptic_acu.base.bundled import bundled_trajectories
    from haptic_acu.servo.samples import NCOL
    from haptic_acu.session import report

    draw = report.plot_force_depth
    drawn = []

    def take(rows, path, tissue=None, title=None, dpi=110, summary=None, index=None):
        # the figure of every other trajectory: its rows and summary taken, not drawn (the PNG is
        # most of a replay's time; the default's is drawn, twice, and held byte-identical below)
        assert np.shape(rows) == (summary["ticks"], NCOL)
        drawn.append(summary["trajectory"])

    limit = load_config().safety.force_limit_n
    for name, traj in bundled_trajectories().items():
        monkeypatch.setattr(report, "plot_force_depth", draw if name == "default" else take)
        outs = []
        for rep in (1, 2) if name == "default" else (1,):  # byte-identical again: shown on one trajectory
            out = tmp_path / f"{name}-{rep}"
            assert main(["replay", str(traj), "--set", f"model.kind={kind}", "--out", str(out), "--no-rrd",
                         "--quiet", "--jobs", "1"]) == 0
            outs.append(out)
        if len(outs) == 2:
            assert filecmp.cmp(outs[0] / "samples.csv", outs[1] / "samples.csv", shallow=False), name
            assert filecmp.cmp(outs[0] / "summary.json", outs[1] / "summary.json", shallow=False), name
            assert (outs[0] / "force_depth.png").stat().st_size > 10_000
            assert filecmp.cmp(outs[0] / "force_depth.png", outs[1] / "force_depth.png", shallow=False), name
        summary = json.loads((outs[0] / "summary.json").read_text())
        assert summary["fault"] in (None, "", False), name
        assert math.isfinite(summary["max_force_n"]) and summary["max_force_n"] <= limit, name
        if name == "default":
            assert summary["clamped_ticks"] == 0
            assert [p["layer"] for p in summary["punctures"]] == ["skin", "fat", "muscle"]
    assert sorted(drawn) == sorted(f"{n}.csv" for n in bundled_trajectories() if n != "default")


def test_compare_models_replays_one_trajectory_through_each(tmp_path, capsys):
    import json

    out = tmp_path / "cmp"
    assert main(["compare", "default", "--models", "forcenet,shf", "--out", str(out)]) == 0
    doc = json.loads((out / "compare.json").read_text())
    assert doc["labels"] == ["forcenet", "shf"]
    assert [m["model"] for m in doc["models"]] == ["forcenet", "shf"]
    assert all(0 < m["tick_us"]["p50"] <= m["tick_us"]["p99"] for m in doc["models"])
    skin = [next(p for p in s["metrics"]["per_insertion"][0]["punctures"] if p["layer"] == "skin")
            for s in doc["sessions"]]
    # SHF's skin breaks at its configured 0.5 N; the force net's at its fitted target, within 10%
    assert skin[1]["peak_force_n"] == pytest.approx(0.5, abs=0.01)
    assert skin[0]["peak_force_n"] == pytest.approx(0.5, rel=0.10)
    assert (out / "compare.png").stat().st_size > 0
    assert main(["compare", "default", "--models", "forcenet,tetra", "--out", str(tmp_path / "bad")]) == 2
    assert "--models" in capsys.readouterr().err


@pytest.mark.slow
def test_a_live_session_runs_a_baseline_with_rerun_logging_and_its_recording_replays(tmp_path):
    import json

    out = tmp_path / "run"
    rec = tmp_path / "session.csv"
    assert main(["run", "--device", "scripted", "--trajectory", "default", "--duration", "2.5", "--speed", "8", "--set",
                 "model.kind=bem", "--out", str(out), "--record", str(rec), "--rrd", str(tmp_path / "s.rrd"),
                 "--no-status", "--quiet"]) == 0
    live = json.loads((out / "summary.json").read_text())
    skin = [p for p in live["punctures"] if p["layer"] == "skin"]
    # the half-space of skin's stiffness (0.131 N/mm) at its energy-criterion break (0.92 mm): 0.12 N, not
    # the force net's 0.5 N
    c = B.contact_for(load_config(overrides=["model.kind=bem"]))
    assert len(skin) == 1 and skin[0]["peak_force_n"] == pytest.approx(c.stiffness[0] * c.crit_depth[0], abs=0.03)
    assert (tmp_path / "s.rrd").stat().st_size > 0
    assert main(["replay", str(rec), "--set", "model.kind=bem", "--out", str(tmp_path / "rep"), "--no-rrd",
                 "--quiet"]) == 0
    again = json.loads((tmp_path / "rep" / "summary.json").read_text())
    assert [p["layer"] for p in again["punctures"]] == [p["layer"] for p in live["punctures"]]

"""The FEM's and BEM's contact set (haptic_acu.tissue.contact): the capacitance matrix kept by
rank-one updates against direct solves of the same constrained system, Signorini's conditions
against an independent non-negative least-squares solve, Hertz's sphere and Sneddon's flat punch,
and the servo's contact through the step.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import nnls

from haptic_acu.base.config import load_config
from haptic_acu.tissue import baselines as B
from haptic_acu.tissue import bem, fem
from haptic_acu.tissue import contact as ct

A = 0.125e-3  # the default needle's radius
E = 30e3
NU = 0.3
ESTAR = E / (1 - NU ** 2)


@pytest.fixture(scope="module")
def fem_patch():
    """A homogeneous block's FEM condensed onto the surface nodes within 0.6 mm (the stiffness S)."""
    return fem.press(fem.sphere_boundaries(1.0, [4e-3]), np.zeros(3), [E], [NU], A, n_in=2, ratio=1.5,
                     half_width=2e-3, depth=2e-3, patch=0.6e-3)


def _direct(S, act, g):
    """The condensed stiffness with the nodes ``act`` held at ``g`` and the rest free (no force):
    the forces on ``act``, by numpy.linalg.solve on S."""
    o = np.setdiff1d(np.arange(len(S)), act)
    u_o = np.linalg.solve(S[np.ix_(o, o)], -S[np.ix_(o, act)] @ g)
    return S[np.ix_(act, act)] @ g + S[np.ix_(act, o)] @ u_o


def test_rank_one_updates_equal_a_direct_solve_of_the_constrained_fem_for_random_contact_sets(fem_patch):
    S = fem_patch.schur
    C = np.ascontiguousarray(np.linalg.inv(S))  # the patch's compliance (m/N)
    m = len(C)
    rng = np.random.default_rng(7)
    P = np.zeros((m, m))
    act = np.zeros(m, np.int64)
    u = np.zeros(m)
    c = np.zeros(m)
    n = 0
    checked = 0
    for step in range(400):  # nodes join and leave at random; 40 sets checked along the way
        inside = set(act[:n].tolist())
        if n <= 1 or (n < m and rng.random() < 0.6):
            j = int(rng.choice([i for i in range(m) if i not in inside]))
            assert ct.cap_add(C, 0, P, act, n, j, u, c) > 0  # C is positive definite: every node adds
            n += 1
        else:
            n = ct.cap_remove(P, act, n, int(rng.integers(n)))
        if step % 10 == 9:
            a = act[:n].copy()
            g = rng.uniform(0.0, 1e-4, n)
            f = P[:n, :n] @ g
            ref = _direct(S, a, g)
            assert np.abs(f - ref).max() <= 1e-9 * np.abs(ref).max()
            assert np.abs(P[:n, :n] - np.linalg.inv(C[np.ix_(a, a)])).max() <= 1e-9 * np.abs(P[:n, :n]).max()
            checked += 1
    assert checked == 40


def _signorini_reference(C, h, d):
    """min 1/2 f^T C f - g^T f over f >= 0 (Signorini's conditions are its optimality conditions), as
    a non-negative least-squares problem: C = L L^T, ||L^T f - L^-1 g||^2."""
    L = np.linalg.cholesky(C)
    f, _ = nnls(L.T, np.linalg.solve(L, d - h), maxiter=50 * len(C))
    return f


@pytest.mark.parametrize("source", ["bem", "fem"])
def test_the_compiled_contact_solve_meets_signorini_and_an_independent_nnls(source, fem_patch):
    if source == "bem":
        C = bem.compliance(E, NU, A, 6)
        s, xy = bem.disc_elements(A, 6)
        rho = np.hypot(xy[:, 0], xy[:, 1])
    else:
        C, rho = fem.disc_compliance(fem_patch, A)
    h = ct.tip_heights(rho, A, "hemisphere")
    depths = np.concatenate([np.linspace(1e-6, 1.3 * A, 40), np.linspace(1.3 * A, 1e-6, 40)])  # in, then out
    F, N, K = ct.press_curve(C, h, depths)
    for d, Fd in zip(depths, F):
        f = _signorini_reference(C, h, d)
        assert Fd == pytest.approx(f.sum(), rel=1e-9)
    assert N[np.argmax(depths)] == N.max() > 0.6 * len(C) and N[-1] < 0.1 * len(C)  # grew, then shrank
    assert K.sum() > 0


def test_warm_started_ticks_change_the_set_by_few_nodes_and_agree_with_cold_solves():
    C = bem.compliance(E, NU, A, 8)
    s, xy = bem.disc_elements(A, 8)
    h = ct.tip_heights(np.hypot(xy[:, 0], xy[:, 1]), A, "hemisphere")
    depths = np.linspace(1e-6, 0.5 * A, 500)  # a slow press: 0.1 um a tick
    F, N, K = ct.press_curve(C, h, depths)
    cold = np.array([ct.press_curve(C, h, [d])[0][0] for d in depths[::25]])
    assert np.allclose(F[::25], cold, rtol=1e-9, atol=0)
    assert K.max() <= 8 and K.sum() < 3 * N.max()  # a ring of equidistant nodes at most, per tick


def test_a_hemispherical_tip_stiffens_as_hertz_and_sneddons_sphere():
    # the contact set grows with depth: Hertz's F = 4/3 E* R^1/2 d^3/2 (R = a) while the contact radius
    # sqrt(R d) is well inside the tip, and Sneddon's rigid sphere (exact in the sphere's shape) deeper:
    # d = c/2 ln((R+c)/(R-c)), F = E*/2 ((c^2 + R^2) ln((R+c)/(R-c)) - 2 c R), c the contact radius
    C = bem.compliance(E, NU, A, 12)
    s, xy = bem.disc_elements(A, 12)
    h = ct.tip_heights(np.hypot(xy[:, 0], xy[:, 1]), A, "hemisphere")
    d = np.geomspace(0.03 * A, 0.2 * A, 12)
    F, N, K = ct.press_curve(C, h, d)
    assert np.allclose(F, ct.hertz(E, NU, A, d), rtol=0.10)
    slope = np.polyfit(np.log(d), np.log(F), 1)[0]
    assert slope == pytest.approx(1.5, abs=0.1)
    c = np.linspace(0.2, 0.7, 6) * A
    lg = np.log((A + c) / (A - c))
    d_sn, F_sn = c / 2 * lg, ESTAR / 2 * ((c ** 2 + A ** 2) * lg - 2 * c * A)
    F2, N2, _ = ct.press_curve(C, h, d_sn)
    assert np.allclose(F2, F_sn, rtol=0.10)
    assert np.all(np.diff(N2) > 0)  # the set grows with depth
    assert (F2 < ct.press_curve(C, np.zeros(len(C)), d_sn)[0]).all()  # softer than the flat tip


def test_a_flat_tip_holds_the_whole_disc_at_once_and_meets_sneddons_punch():
    C = bem.compliance(E, NU, A)
    d = np.linspace(1e-6, 0.3 * A, 20)
    F, N, K = ct.press_curve(C, np.zeros(len(C)), d)
    assert (N == len(C)).all() and K.sum() == 0  # the precomputed whole disc: no rank-one change
    assert np.allclose(F, 2 * A * ESTAR * d, rtol=0.03)


@pytest.mark.parametrize("kind", ["bem", "fem"])
def test_the_servo_contact_with_a_flat_tip_is_the_precomputed_stiffness(kind):
    # the flat tip holds the whole disc from the first touch: F = k d with the layer's stiffness (held
    # to Sneddon in test_baselines), through the step
    from haptic_acu.servo.step import NeedleModel

    cfg = load_config(overrides=[f"model.kind={kind}"])
    nm = NeedleModel(cfg)
    k = B.contact_for(cfg).stiffness[0]
    v = np.array([0.0, 0.0, -0.01])
    for z in np.arange(0.1e-3, -0.3e-3, -1e-5):
        nm.step(np.array([0.0, 0.0, z]), v)
        dz = float(nm.diag["dz1"])
        if dz > 0:
            assert float(nm.diag["f_surface"]) == pytest.approx(k * dz, rel=1e-9)
            assert nm.rec["ct_n"] == B.contact_for(cfg).ct_n[0]


@pytest.mark.parametrize("kind", ["bem", "fem"])
def test_the_servo_contact_with_a_hemispherical_tip_grows_with_depth(kind):
    from haptic_acu.servo.step import NeedleModel

    cfg = load_config(overrides=[f"model.kind={kind}", "model.tip_shape=hemisphere"])
    nm = NeedleModel(cfg)
    c = B.contact_for(cfg)
    m = int(c.ct_n[0])
    C = c.ct_c[:m, :m]
    h = c.ct_h[0, :m]
    v = np.array([0.0, 0.0, -0.01])
    sizes = []
    for z in np.arange(0.05e-3, -0.3e-3, -1e-5):
        nm.step(np.array([0.0, 0.0, z]), v)
        dz = float(nm.diag["dz1"])
        if dz > 0:
            sizes.append(int(nm.rec["ct_n"]))
            ref = _signorini_reference(C, h, dz).sum()
            assert float(nm.diag["f_surface"]) == pytest.approx(ref, rel=1e-9)
    assert 0 < sizes[0] < sizes[-1] <= m and np.all(np.diff(sizes) >= 0)  # the set grows with depth
    assert float(nm.diag["f_surface"]) < c.stiffness[0] * float(nm.diag["dz1"])  # softer than the flat tip


def test_a_bad_tip_shape_is_one_line_naming_the_key():
    from haptic_acu.base.errors import UserError

    with pytest.raises(UserError, match="key 'model.tip_shape'"):
        load_config(overrides=["model.tip_shape=cone"])

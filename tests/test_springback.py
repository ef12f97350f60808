"""Springback (haptic_acu.tissue.springback, eq. 7-9, MODEL.md section 4): shape matching goals, the polar
rotation against scipy, eta's two ends, and the net's return to rest with its centroid kept."""

import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from haptic_acu.base.config import load_config
from haptic_acu.tissue.forcenet import Net, NetParams, n_particles
from haptic_acu.servo.step import N_LAYERS, N_SLOTS, NeedleModel
from haptic_acu.tissue.springback import Springback, polar_rotation, shape_matching_goals, springback_step
from physics_helpers import sh_sphere, sphere_config, sphere_tissue, straight_line

R = 0.07
CENTRE = np.array([0.0, 0.0, -R])


def dented_net(margin_rings=3, depth=1.5e-3, layer="skin"):
    """A skin net (with margin rings) on a 70 mm sphere, pressed ``depth`` in and solved statically."""
    params = NetParams.from_layer(getattr(load_config(), layer))
    net = Net.allocate(params, margin_rings=margin_rings)
    net.build(sh_sphere(R), 2, CENTRE, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    net.solve(np.array([0.0, 0.0, -depth]), tol_m=1e-12)
    return net, n_particles(params.w)


def run_springback(x, X0, n_net, eta_rate, eta_min, frames):
    goals = np.zeros_like(x)
    eta = 1.0
    history = []
    for _ in range(frames):
        springback_step(x, X0, n_net, eta, goals)
        eta = max(eta_min, eta - eta_rate)
        history.append(x.copy())
    return history


# ---- the polar rotation ---------------------------------------------------------------------------------
def random_matrix(seed, sign):
    rng = np.random.default_rng(seed)
    while True:
        A = rng.normal(size=(3, 3))
        if np.sign(np.linalg.det(A)) == sign and np.linalg.cond(A) < 1e3:
            return A


@pytest.mark.parametrize("seed", range(20))
def test_polar_rotation_matches_scipy_polar(seed):
    A = random_matrix(seed, +1)
    Rm = polar_rotation(A)
    np.testing.assert_allclose(Rm.T @ Rm, np.eye(3), atol=1e-12)
    assert np.linalg.det(Rm) == pytest.approx(1.0, abs=1e-12)
    U, P = scipy.linalg.polar(A)  # A = U P, U orthogonal, P symmetric positive semi-definite
    np.testing.assert_allclose(Rm, U, atol=1e-10)


@pytest.mark.parametrize("seed", range(20))
def test_polar_rotation_of_a_reflecting_matrix_is_the_closest_proper_rotation(seed):
    """det A < 0: the rotation (det +1) maximising tr(R^T A), i.e. Wahba's problem, which scipy's
    Rotation.align_vectors solves with a_i = A's columns, b_i = the unit axes (sum a_i b_i^T = A)."""
    A = random_matrix(seed, -1)
    Rm = polar_rotation(A)
    np.testing.assert_allclose(Rm.T @ Rm, np.eye(3), atol=1e-12)
    assert np.linalg.det(Rm) == pytest.approx(1.0, abs=1e-12)
    best, _ = Rotation.align_vectors(A.T, np.eye(3))
    np.testing.assert_allclose(Rm, best.as_matrix(), atol=1e-9)


def test_polar_rotation_of_a_flat_matrix():
    """A flat set of particles gives a rank-2 A; its rotation is still unique and proper."""
    Q = Rotation.from_rotvec([0.3, -1.1, 0.4]).as_matrix()
    Rm = polar_rotation(Q @ np.diag([3.0, 2.0, 0.0]))
    np.testing.assert_allclose(Rm, Q, atol=1e-12)


# ---- shape matching goals (eq. 7-8) ---------------------------------------------------------------------
@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), noise=st.floats(0.0, 0.5))
def test_goals_follow_a_rigid_rotation_of_the_current_positions(seed, noise):
    rng = np.random.default_rng(seed)
    p0 = rng.normal(size=(30, 3))
    p = p0 @ Rotation.random(random_state=rng).as_matrix().T + noise * rng.normal(size=(30, 3)) + rng.normal(size=3)
    Q = Rotation.random(random_state=rng).as_matrix()
    g = np.zeros_like(p)
    gq = np.zeros_like(p)
    shape_matching_goals(p, p0, g)
    shape_matching_goals(p @ Q.T, p0, gq)
    np.testing.assert_allclose(gq, g @ Q.T, atol=1e-10)
    # goals keep the current centroid and are the rest shape moved rigidly
    np.testing.assert_allclose(g.mean(axis=0), p.mean(axis=0), atol=1e-12)
    d0 = np.linalg.norm(p0[:, None] - p0[None], axis=-1)
    np.testing.assert_allclose(np.linalg.norm(g[:, None] - g[None], axis=-1), d0, atol=1e-10)


def test_goals_of_a_rigidly_moved_shape_are_the_shape():
    rng = np.random.default_rng(11)
    p0 = rng.normal(size=(20, 3))
    Q = Rotation.random(random_state=rng).as_matrix()
    p = p0 @ Q.T + [0.1, -2.0, 0.5]
    g = np.zeros_like(p)
    shape_matching_goals(p, p0, g)
    np.testing.assert_allclose(g, p, atol=1e-12)


# ---- eq. 9 on a dented net ------------------------------------------------------------------------------
def test_eta_one_holds_the_particles_still():
    net, n = dented_net()
    x = net.x.copy()
    before = x.copy()
    assert np.abs(before - net.X0).max() > 1e-3
    goals = np.zeros_like(x)
    for _ in range(10):
        assert springback_step(x, net.X0, n, 1.0, goals) < 1e-15
    np.testing.assert_allclose(x, before, rtol=0, atol=1e-15)


def test_eta_min_zero_returns_the_net_to_rest_with_its_centroid():
    net, n = dented_net()
    x = net.x.copy()
    dent0 = np.linalg.norm(x[:n] - net.X0[:n], axis=1).max()
    offset0 = np.linalg.norm(x.mean(axis=0) - net.X0.mean(axis=0))
    assert dent0 > 1e-3 and offset0 > 1e-6
    history = run_springback(x, net.X0, n, 0.05, 0.0, 120)
    # eta starts at 1: the first frame moves nothing; then the dent shrinks
    np.testing.assert_allclose(history[0], net.x, atol=1e-15)
    err = [np.linalg.norm(h[:n] - net.X0[:n], axis=1).max() for h in history]
    assert err[-1] <= 0.01 * dent0, (err[-1], dent0)
    assert err[10] < err[0]
    # the margin rings never move, and the whole set's centroid ends where it was at rest
    for h in history:
        np.testing.assert_array_equal(h[n:], net.X0[n:])
    assert np.linalg.norm(history[-1].mean(axis=0) - net.X0.mean(axis=0)) <= 1e-3 * offset0


def test_without_margin_the_goals_only_restore_the_shape_translated():
    """Why the margin rings are there (MODEL.md s4): matching the net alone keeps its centroid, so
    the dent flattens out at the dented centroid instead of at rest."""
    net, n = dented_net(margin_rings=0)
    assert net.x.shape[0] == n
    x = net.x.copy()
    shift = x.mean(axis=0) - net.X0.mean(axis=0)
    assert shift[2] < -1e-5
    history = run_springback(x, net.X0, n, 0.05, 0.0, 120)
    np.testing.assert_allclose(history[-1], net.X0 + shift, atol=1e-9)


# ---- the Springback schedule on a punctured net in the needle model -------------------------------------
def test_springback_class_returns_a_punctured_skin_to_the_rest_surface():
    cfg = sphere_config()
    tissue = sphere_tissue(cfg)
    model = NeedleModel(cfg, tissue)
    pts, v = straight_line(1e-3, -3e-3, 0.01)
    for p in pts:
        model.step(p, v)
        if model.diag["puncture"] == 0:
            break
    handed = [i for i in range(N_LAYERS * N_SLOTS) if model.owner(i) == 2]
    assert len(handed) == 1
    idx = handed[0]
    radius = 0.2  # the sphere's skin
    dent = lambda: np.abs(np.linalg.norm(model.net_positions(idx) - tissue.centre, axis=1) - radius)
    dent0 = dent().max()
    assert dent0 > 1e-3
    sb = Springback(model, cfg.springback.eta_rate_per_frame, 0.0)
    moved = [sb.frame() for _ in range(150)]
    assert moved[0] == 1 and moved[-1] == 0  # it ran, then settled
    assert dent().max() <= 0.01 * dent0

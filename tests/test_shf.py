"""Real spherical harmonics and SH surfaces (haptic_acu.tissue.shf) against scipy, quadrature and geometry."""
import math

import numpy as np
import pytest
from scipy.special import sph_harm_y

from haptic_acu.tissue import shf

SQRT2 = math.sqrt(2.0)


def random_directions(n, seed):
    """Uniform random directions as (theta in [0, pi], phi in [0, 2 pi), unit vectors)."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    return np.arccos(np.clip(u[:, 2], -1, 1)), np.arctan2(u[:, 1], u[:, 0]) % (2 * np.pi), u


def scipy_real_basis(lmax, theta, phi):
    """The real basis built from scipy's complex Y_l^m (Condon-Shortley phase included):
    Y_l0 = Y_l^0, Y_lm = sqrt(2) Re Y_l^m, Y_l-m = sqrt(2) Im Y_l^m for m > 0; column l*l + l + m."""
    out = np.empty((theta.size, (lmax + 1) ** 2))
    for l in range(lmax + 1):
        out[:, l * l + l] = sph_harm_y(l, 0, theta, phi).real
        for m in range(1, l + 1):
            y = sph_harm_y(l, m, theta, phi)
            out[:, l * l + l + m] = SQRT2 * y.real
            out[:, l * l + l - m] = SQRT2 * y.imag
    return out


def test_real_sph_harm_matches_scipy_to_degree_20():
    theta, phi, _ = random_directions(400, seed=1)
    # Include the poles and points a hair away from them.
    theta = np.concatenate([theta, [0.0, np.pi, 1e-9, np.pi - 1e-9, np.pi / 2]])
    phi = np.concatenate([phi, [0.3, 1.7, 4.0, 5.5, 0.0]])
    ours = shf.real_sph_harm(20, theta, phi)
    ref = scipy_real_basis(20, theta, phi)
    assert ours.shape == (theta.size, 441)
    np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-10)


@pytest.mark.parametrize("lmax", [0, 1, 7, 20])
def test_orthonormal_by_exact_quadrature(lmax):
    # Products of two degree-<=lmax harmonics are polynomials of degree <= 2 lmax in cos(theta)
    # (times sin^2k theta, which is polynomial in cos) and trigonometric of degree <= 2 lmax in phi:
    # Gauss-Legendre with lmax+2 nodes and 2 lmax + 2 equal phi steps integrate them exactly.
    x, w = np.polynomial.legendre.leggauss(lmax + 2)
    n_phi = 2 * lmax + 2
    theta = np.repeat(np.arccos(x), n_phi)
    phi = np.tile(np.arange(n_phi) * 2 * np.pi / n_phi, x.size)
    weights = np.repeat(w, n_phi) * (2 * np.pi / n_phi)
    basis = shf.real_sph_harm(lmax, theta, phi)
    gram = basis.T @ (basis * weights[:, None])
    np.testing.assert_allclose(gram, np.eye((lmax + 1) ** 2), rtol=0, atol=1e-12)


def test_fit_recovers_band_limited_radial_function():
    lmax = 10
    rng = np.random.default_rng(2)
    coeffs = rng.normal(size=(lmax + 1) ** 2) / (1 + np.arange((lmax + 1) ** 2)) ** 0.5
    coeffs[0] = 10.0
    theta, phi, _ = random_directions(600, seed=3)
    values = scipy_real_basis(lmax, theta, phi) @ coeffs  # sampled with scipy's harmonics
    fitted = shf.fit(theta, phi, values, lmax)
    np.testing.assert_allclose(fitted, coeffs, rtol=0, atol=1e-8)
    # and the reconstruction (eq. 5) reproduces the function at fresh directions
    t2, p2, _ = random_directions(300, seed=4)
    np.testing.assert_allclose(shf.evaluate(fitted, t2, p2), scipy_real_basis(lmax, t2, p2) @ coeffs,
                               rtol=0, atol=1e-8)


def test_ellipsoid_fit_error_falls_with_degree():
    semi = np.array([1.3, 0.8, 1.0])

    def radius(u):  # an ellipsoid's radius about its centre: not band-limited
        return 1.0 / np.sqrt(((u / semi) ** 2).sum(axis=-1))

    theta, phi, u = random_directions(2000, seed=5)
    t2, p2, u2 = random_directions(2000, seed=6)  # judge the fit away from the samples
    errors = []
    for lmax in (2, 4, 8, 12):
        c = shf.fit(theta, phi, radius(u), lmax)
        errors.append(np.sqrt(np.mean((shf.evaluate(c, t2, p2) - radius(u2)) ** 2)))
    assert all(b < 0.5 * a for a, b in zip(errors, errors[1:])), errors
    assert errors[-1] < 1e-4 * semi.min()


def test_eval_point_agrees_with_evaluate_and_scipy():
    lmax = 12
    rng = np.random.default_rng(7)
    coeffs = rng.normal(size=(lmax + 1) ** 2)
    theta, phi, _ = random_directions(200, seed=8)
    ref = scipy_real_basis(lmax, theta, phi) @ coeffs
    pointwise = np.array([shf.eval_point(coeffs, lmax, t, p) for t, p in zip(theta, phi)])
    np.testing.assert_allclose(pointwise, ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(shf.evaluate(coeffs, theta, phi), ref, rtol=0, atol=1e-10)
    # evaluate keeps the input's shape
    assert shf.evaluate(coeffs, theta.reshape(20, 10), phi.reshape(20, 10)).shape == (20, 10)


def test_sphere_radius_and_depth_below_match_geometry():
    # A sphere of radius R about c: only Y_00 = 1/sqrt(4 pi) is present, with coefficient R sqrt(4 pi).
    R, lmax = 0.07, 6
    centre = np.array([0.01, -0.02, 0.03])
    coeffs = np.zeros((lmax + 1) ** 2)
    coeffs[0] = R * math.sqrt(4 * math.pi)
    rng = np.random.default_rng(9)
    for p in centre + rng.uniform(-0.15, 0.15, size=(100, 3)):
        dist = np.linalg.norm(p - centre)
        assert shf.depth_below(coeffs, lmax, centre, p) == pytest.approx(R - dist, abs=1e-14)
        r, rho = shf.radius_toward(coeffs, lmax, centre, p)
        assert r == pytest.approx(R, abs=1e-14) and rho == pytest.approx(dist, abs=1e-14)
    # the centre itself: depth is the full radius
    assert shf.depth_below(coeffs, lmax, centre, centre.copy()) == pytest.approx(R, abs=1e-14)


def test_depth_below_uses_direction_from_the_centre():
    # A non-spherical surface: depth_below(p) = r(direction of p - c) - |p - c| with the
    # direction computed here independently.
    lmax = 8
    rng = np.random.default_rng(10)
    coeffs = 0.002 * rng.normal(size=(lmax + 1) ** 2)
    coeffs[0] = 0.05 * math.sqrt(4 * math.pi)
    centre = np.array([0.0, 0.0, -0.05])
    for p in rng.uniform(-0.08, 0.08, size=(50, 3)):
        d = p - centre
        rho = np.linalg.norm(d)
        theta, phi = math.acos(d[2] / rho), math.atan2(d[1], d[0]) % (2 * math.pi)
        r = (scipy_real_basis(lmax, np.array([theta]), np.array([phi])) @ coeffs)[0]
        assert shf.depth_below(coeffs, lmax, centre, p) == pytest.approx(r - rho, abs=1e-12)


def test_parametric_fit_of_a_sphere_recovers_its_points():
    R = 0.04
    centre = np.array([0.1, -0.2, 0.3])
    theta, phi, u = random_directions(300, seed=11)
    coeffs = shf.fit(theta, phi, centre + R * u, lmax=4)
    assert coeffs.shape == (25, 3)
    # x, y, z of a sphere in this basis (CS phase): Y_11 = -sqrt(3/4pi) sin(t) cos(p),
    # Y_1-1 = -sqrt(3/4pi) sin(t) sin(p), Y_10 = sqrt(3/4pi) cos(t); constants sit on Y_00.
    expected = np.zeros((25, 3))
    expected[0] = centre * math.sqrt(4 * math.pi)
    s = R * math.sqrt(4 * math.pi / 3)
    expected[3, 0], expected[1, 1], expected[2, 2] = -s, -s, s
    np.testing.assert_allclose(coeffs, expected, rtol=0, atol=1e-12)
    t2, p2, u2 = random_directions(100, seed=12)
    np.testing.assert_allclose(shf.evaluate(coeffs, t2, p2), centre + R * u2, rtol=0, atol=1e-12)


def _cap_samples(n, cap_deg, seed):
    """``n`` random directions within ``cap_deg`` of the north pole, and a smooth, not band-limited
    function sampled there with noise (so the least-squares residual is not zero)."""
    rng = np.random.default_rng(seed)
    theta = np.arccos(rng.uniform(math.cos(math.radians(cap_deg)), 1.0, n))
    phi = rng.uniform(0.0, 2 * np.pi, n)
    values = np.exp(np.cos(theta)) * np.sin(3 * phi) + 0.01 * rng.normal(size=n)
    return theta, phi, values


@pytest.mark.parametrize("cap_deg, lmax", [(180, 15), (120, 10), (90, 10), (60, 10)])
def test_fit_equals_an_svd_least_squares_solution_however_the_samples_are_spread(cap_deg, lmax):
    # The fit solves the semi-normal equations with a correction step, falling back to an SVD solve
    # when the basis is ill conditioned; either way it must give numpy's SVD-based least squares
    # (cond(B) here: ~2, ~1e4, ~1e7, ~1e11). Compared on what a fit is for, the fitted surface at
    # the samples, and on the coefficients where the basis leaves them well determined. (The basis
    # itself is checked against scipy above; at cond 1e7 its 1e-16 differences would move the SVD
    # solution by more than the solvers differ.)
    theta, phi, values = _cap_samples(4000, cap_deg, seed=cap_deg)
    basis = shf.real_sph_harm(lmax, theta, phi)
    ref = np.linalg.lstsq(basis, values, rcond=None)[0]
    ours = shf.fit(theta, phi, values, lmax)
    scale = np.abs(values).max()
    np.testing.assert_allclose(basis @ ours, basis @ ref, rtol=0, atol=1e-10 * scale)
    if np.linalg.cond(basis) < 1e5:
        np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-10 * np.abs(ref).max())
    # the residual is orthogonal to the basis (the normal equations hold, to the rounding of the
    # sums B^T (y - B x), which grows with |B| |x| where the coefficients are large)
    resid = values - basis @ ours
    size = np.abs(values).sum() + (np.abs(basis) @ np.abs(ours)).sum()
    assert np.abs(basis.T @ resid).max() < 1e-12 * np.abs(basis).max() * size


def test_seminormal_solve_hands_an_ill_conditioned_basis_to_the_svd_solver():
    # cond(B) ~ 1e7 at a 90 degree cap, lmax 10: Cholesky of B^T B loses everything past
    # eps * cond^2 ~ 1e-2, so the correction step is large and the fit must not keep it.
    theta, phi, values = _cap_samples(4000, 90, seed=90)
    basis = shf.real_sph_harm(10, theta, phi)
    assert np.linalg.cond(basis) > 1e6
    assert shf._fit_seminormal(basis, values) is None
    theta, phi, values = _cap_samples(4000, 180, seed=180)  # well spread: kept
    basis = shf.real_sph_harm(10, theta, phi)
    x = shf._fit_seminormal(basis, values)
    assert x is not None
    np.testing.assert_allclose(x, np.linalg.lstsq(basis, values, rcond=None)[0], rtol=0, atol=1e-13)


def test_bad_inputs_raise_value_error():
    theta, phi, _ = random_directions(30, seed=13)
    values = np.ones(30)
    with pytest.raises(ValueError, match="too few"):
        shf.fit(theta, phi, values, lmax=5)  # needs 36
    bad = values.copy()
    bad[4] = np.nan
    with pytest.raises(ValueError, match="finite"):
        shf.fit(theta, phi, bad, lmax=2)
    t_bad = theta.copy()
    t_bad[0] = np.inf
    with pytest.raises(ValueError, match="finite"):
        shf.fit(t_bad, phi, values, lmax=2)
    with pytest.raises(ValueError):
        shf.fit(theta, phi[:-1], values, lmax=2)  # theta/phi mismatch
    with pytest.raises(ValueError):
        shf.fit(theta, phi, values[:-1], lmax=2)  # values/theta mismatch
    with pytest.raises(ValueError):
        shf.fit(theta, phi, np.ones((30, 2)), lmax=2)  # neither (n,) nor (n, 3)
    with pytest.raises(ValueError):
        shf.fit(theta, phi, values, lmax=-1)
    with pytest.raises(ValueError):
        shf.real_sph_harm(-1, theta, phi)
    with pytest.raises(ValueError, match="rank"):  # enough samples but all in one direction
        shf.fit(np.full(30, 0.4), np.full(30, 1.0), values, lmax=2)
    with pytest.raises(ValueError):
        shf.evaluate(np.ones(10), theta, phi)  # 10 is not (lmax+1)^2
    with pytest.raises(ValueError):
        shf.lmax_of(0)


def test_finite_and_correct_at_the_poles():
    lmax = 20
    theta = np.array([0.0, 1e-300, 1e-12, np.pi - 1e-12, np.pi, np.pi])
    phi = np.array([0.0, 2.0, 5.0, 1.0, 0.0, 3.0])
    basis = shf.real_sph_harm(lmax, theta, phi)
    assert np.all(np.isfinite(basis))
    # Exactly at a pole only m = 0 survives, with Y_l0 = sqrt((2l+1)/4pi) (+-1)^l, whatever phi is.
    for row, sign in ((basis[0], 1.0), (basis[4], -1.0), (basis[5], -1.0)):
        for l in range(lmax + 1):
            for m in range(-l, l + 1):
                want = math.sqrt((2 * l + 1) / (4 * math.pi)) * sign ** l if m == 0 else 0.0
                assert row[l * l + l + m] == pytest.approx(want, abs=1e-12)
    coeffs = np.random.default_rng(14).normal(size=(lmax + 1) ** 2)
    values = [shf.eval_point(coeffs, lmax, t, p) for t, p in zip(theta, phi)]
    assert np.all(np.isfinite(values))
    np.testing.assert_allclose(values, basis @ coeffs, rtol=0, atol=1e-10)
    # a point straight above or below the centre
    centre = np.zeros(3)
    for z in (0.5, -0.5):
        assert np.isfinite(shf.depth_below(coeffs, lmax, centre, np.array([0.0, 0.0, z])))


def test_grid_and_unit_vectors():
    th, ph = shf.grid(6, 8)
    assert th.shape == ph.shape == (6, 8)
    assert 0 < th.min() and th.max() < np.pi  # no pole rows
    u = shf.unit_vectors(th, ph)
    np.testing.assert_allclose(np.linalg.norm(u, axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(u[..., 2], np.cos(th), atol=1e-15)
    np.testing.assert_allclose(np.arctan2(u[..., 1], u[..., 0]) % (2 * np.pi), ph, atol=1e-12)


@pytest.mark.parametrize("lmax", [2, 15, 30])
def test_eval_direction_agrees_with_scipy_anywhere_and_at_the_poles(lmax):
    """eval_direction (no transcendental calls: the pressed surface's slope kernel) against SciPy's
    harmonics at random directions of random lengths, at the poles and next to them."""
    rng = np.random.default_rng(21 + lmax)
    coeffs = rng.normal(size=(lmax + 1) ** 2)
    theta, phi, u = random_directions(300, seed=22)
    near = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1e-9, 0.0, 1.0], [0.0, -1e-9, -1.0], [1e-12, 1e-12, 1.0]])
    u = np.vstack([u, near / np.linalg.norm(near, axis=1)[:, None]])
    theta = np.arctan2(np.hypot(u[:, 0], u[:, 1]), u[:, 2])  # (arccos loses 1e-9 rad at a pole)
    phi = np.arctan2(u[:, 1], u[:, 0])
    ref = scipy_real_basis(lmax, theta, phi) @ coeffs
    scale = rng.uniform(1e-3, 1e3, size=len(u))
    got = np.array([shf.eval_direction(coeffs, lmax, *(v * k)) for v, k in zip(u, scale)])
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-10 * np.abs(coeffs).sum())


def scipy_real_basis_derivatives(lmax, theta, phi):
    """d/dtheta and d/dphi of :func:`scipy_real_basis` from SciPy's own derivatives (diff_n=1)."""
    dth = np.empty((theta.size, (lmax + 1) ** 2))
    dph = np.empty_like(dth)
    for l in range(lmax + 1):
        for m in range(0, l + 1):
            _, d = sph_harm_y(l, m, theta, phi, diff_n=1)
            yt, yp = d[..., 0], d[..., 1]
            if m == 0:
                dth[:, l * l + l] = yt.real
                dph[:, l * l + l] = yp.real
            else:
                dth[:, l * l + l + m], dth[:, l * l + l - m] = SQRT2 * yt.real, SQRT2 * yt.imag
                dph[:, l * l + l + m], dph[:, l * l + l - m] = SQRT2 * yp.real, SQRT2 * yp.imag
    return dth, dph


@pytest.mark.parametrize("lmax", [2, 15, 30])
def test_eval_point4_grad_values_bit_for_bit_and_derivatives_against_scipy(lmax):
    """The four surfaces' radii exactly as eval_point gives them, and one surface's dr/dtheta and
    (dr/dphi) / sin(theta) against SciPy's derivatives of its harmonics, away from the poles."""
    rng = np.random.default_rng(40 + lmax)
    coeffs = np.ascontiguousarray(rng.normal(size=(4, (lmax + 1) ** 2)))
    theta, phi, _ = random_directions(200, seed=41)
    theta = np.concatenate([theta, [1e-3, np.pi - 1e-3, np.pi / 2]])
    phi = np.concatenate([phi, [0.4, 2.2, 5.0]])
    dth, dph = scipy_real_basis_derivatives(lmax, theta, phi)
    out = np.empty(4)
    grad = np.empty(3)
    tol = 1e-10 * np.abs(coeffs).sum(axis=1).max() * max(1, lmax) ** 2
    for i, (t, p) in enumerate(zip(theta, phi)):
        for k in range(4):
            shf.eval_point4_grad(coeffs, lmax, t, p, out, k, grad)
            assert [out[j] == shf.eval_point(coeffs[j], lmax, t, p) for j in range(4)] == [True] * 4
            assert abs(grad[0] - dth[i] @ coeffs[k]) < tol
            assert abs(grad[1] - dph[i] @ coeffs[k] / math.sin(t)) < tol


@pytest.mark.parametrize("lmax", [3, 15])
def test_eval_point4_grad_at_the_poles_is_the_limit_of_its_neighbours(lmax):
    """At theta = 0 and pi, where (dr/dphi) / sin(theta) is 0/0, the surface gradient it gives equals
    the one SciPy gives a hair away from the pole (the field is continuous there)."""
    rng = np.random.default_rng(50 + lmax)
    coeffs = np.ascontiguousarray(rng.normal(size=(4, (lmax + 1) ** 2)))
    out = np.empty(4)
    grad = np.empty(3)
    for pole in (0.0, np.pi):
        for p in (0.0, 1.1, -2.5):
            shf.eval_point4_grad(coeffs, lmax, pole, p, out, 2, grad)
            # the same tangent vector in Cartesian form, ours at the pole and SciPy's 1e-7 rad away
            # along the meridian phi = p (e_theta, e_phi are continuous along it)
            eps = 1e-7 if pole == 0.0 else np.pi - 1e-7
            dth, dph = scipy_real_basis_derivatives(lmax, np.array([eps]), np.array([p]))
            ref = (dth[0] @ coeffs[2], dph[0] @ coeffs[2] / math.sin(eps))
            scale = np.abs(coeffs[2]).sum() * lmax ** 2
            assert abs(grad[0] - ref[0]) < 1e-5 * scale
            assert abs(grad[1] - ref[1]) < 1e-5 * scale


def test_evaluate_many_points_is_eval_point_bit_for_bit():
    """evaluate (points side by side in chunks) gives eval_point's bits for every point, whatever
    the number of points or where a point falls in a chunk: random directions, the poles, the
    phi = +-pi seam, for the four boundaries of the default body and a random expansion."""
    from haptic_acu.base.config import load_config
    from haptic_acu.tissue.body import Tissue

    rng = np.random.default_rng(21)
    n = 60_000
    theta = np.arccos(rng.uniform(-1.0, 1.0, n))
    phi = rng.uniform(-np.pi, np.pi, n)
    edges = [(0.0, 0.0), (np.pi, np.pi), (1e-300, -np.pi), (np.pi - 1e-16, 0.0), (np.pi / 2, np.pi),
             (0.0, -np.pi), (np.pi, 0.0), (1e-8, 3.0), (np.pi / 2, -np.pi), (np.pi / 2, 0.0)]
    theta[:len(edges)], phi[:len(edges)] = zip(*edges)
    body = Tissue.from_config(load_config()).coeffs
    sets = [*body, rng.normal(size=shf.n_coeffs(shf.REC_LMAX)), rng.normal(size=shf.n_coeffs(3))]
    for c in sets:
        c = np.ascontiguousarray(c)
        lmax = shf.lmax_of(c.size)
        want = np.array([shf.eval_point(c, lmax, a, b) for a, b in zip(theta, phi)])
        assert shf.evaluate(c, theta, phi).tobytes() == want.tobytes()
        for a, k in ((0, 1), (3, 63), (5, 64), (7, 65), (11, 129), (1, 1000)):
            assert shf.evaluate(c, theta[a:a + k], phi[a:a + k]).tobytes() == want[a:a + k].tobytes()

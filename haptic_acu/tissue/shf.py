"""Real spherical harmonics and SH surfaces (the paper's eq. 1-5; MODEL.md section 1).

Convention, used everywhere in this package:

* ``theta`` is the polar angle (0 at +z), ``phi`` the azimuth from +x, both in radians.
* Real orthonormal harmonics: the integral of Y_lm^2 over the unit sphere is 1.
  With N_lm P_l^m the orthonormalised associated Legendre function *including* the
  Condon-Shortley phase (-1)^m,

      Y_l0  = N_l0 P_l^0(cos theta)
      Y_lm  = sqrt(2) N_lm P_l^m(cos theta) cos(m phi)     m > 0
      Y_l-m = sqrt(2) N_lm P_l^m(cos theta) sin(m phi)     m > 0

  so Y_lm = sqrt(2) Re Y_l^m and Y_l-m = sqrt(2) Im Y_l^m for scipy's complex ``sph_harm_y``.
* Column (coefficient index) of (l, m) is ``l*l + l + m`` (the paper's j - 1).

P_l^m comes from the standard stable three-term recurrences on the normalised functions, never
from eq. 2's derivative formula. The kernels are numba-compiled with ``nogil=True`` so the visual
thread can evaluate surfaces beside the servo thread; the scalar ones allocate nothing, so the servo
step can call them every tick.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

_INV_SQRT_4PI = 1.0 / math.sqrt(4.0 * math.pi)
_SQRT2 = math.sqrt(2.0)


def n_coeffs(lmax: int) -> int:
    """Number of coefficients of an expansion to degree ``lmax``: (lmax+1)^2."""
    return (lmax + 1) ** 2


def lmax_of(ncoeffs: int) -> int:
    """Degree of an expansion with ``ncoeffs`` coefficients; ValueError if not a square."""
    lmax = int(round(math.sqrt(ncoeffs))) - 1
    if lmax < 0 or (lmax + 1) ** 2 != ncoeffs:
        raise ValueError(f"{ncoeffs} coefficients is not (lmax+1)^2 for any lmax")
    return lmax


@nb.njit(cache=True, nogil=True)
def _basis_row(lmax, theta, phi, out):
    """Fill ``out[(lmax+1)^2]`` with every Y_lm at one direction."""
    x = math.cos(theta)
    s = math.sin(theta)
    pmm = _INV_SQRT_4PI  # normalised P_0^0
    for m in range(lmax + 1):
        if m > 0:
            # P_m^m from P_{m-1}^{m-1}; the minus sign is the Condon-Shortley phase.
            pmm = -math.sqrt((2.0 * m + 1.0) / (2.0 * m)) * s * pmm
        cm = math.cos(m * phi)
        sm = math.sin(m * phi)
        p_lm2 = 0.0
        p_lm1 = pmm
        for l in range(m, lmax + 1):
            if l == m:
                p = pmm
            elif l == m + 1:
                p = math.sqrt(2.0 * m + 3.0) * x * pmm
            else:
                a = math.sqrt((4.0 * l * l - 1.0) / (l * l - m * m))
                b = math.sqrt(((l - 1.0) * (l - 1.0) - m * m) / (4.0 * (l - 1.0) * (l - 1.0) - 1.0))
                p = a * (x * p_lm1 - b * p_lm2)
            if l > m:
                p_lm2 = p_lm1
                p_lm1 = p
            base = l * l + l
            if m == 0:
                out[base] = p
            else:
                out[base + m] = _SQRT2 * p * cm
                out[base - m] = _SQRT2 * p * sm


@nb.njit(cache=True, nogil=True)
def _basis_matrix(lmax, theta, phi, out):
    for i in range(theta.shape[0]):
        _basis_row(lmax, theta[i], phi[i], out[i])


# The recurrences' factors, precomputed for the point kernels (the servo evaluates four boundaries
# every tick): the same IEEE expressions as in _basis_row, so the values are bit for bit the same.
REC_LMAX = 40  # the largest body.lmax a config may ask for
_REC_MM = np.array([0.0] + [math.sqrt((2.0 * m + 1.0) / (2.0 * m)) for m in range(1, REC_LMAX + 1)])
_REC_M1 = np.array([math.sqrt(2.0 * m + 3.0) for m in range(REC_LMAX + 1)])
_REC_A = np.zeros((REC_LMAX + 1, REC_LMAX + 1))
_REC_B = np.zeros((REC_LMAX + 1, REC_LMAX + 1))
for _l in range(REC_LMAX + 1):
    for _m in range(_l - 1):
        _REC_A[_l, _m] = math.sqrt((4.0 * _l * _l - 1.0) / (_l * _l - _m * _m))
        _REC_B[_l, _m] = math.sqrt(((_l - 1.0) * (_l - 1.0) - _m * _m) / (4.0 * (_l - 1.0) * (_l - 1.0) - 1.0))
del _l, _m


@nb.njit(cache=True, nogil=True, inline="always")
def _next_plm(l, m, x, pmm, p_lm1, p_lm2):
    """One step of the associated Legendre recurrence in l at order m (from P_mm = ``pmm`` at
    cos theta = ``x``): (P_lm, the new P_l-1,m, the new P_l-2,m), given the previous two."""
    if l == m:
        return pmm, p_lm1, p_lm2
    if l == m + 1:
        p = _REC_M1[m] * x * pmm
    else:
        p = _REC_A[l, m] * (x * p_lm1 - _REC_B[l, m] * p_lm2)
    return p, p, p_lm1


@nb.njit(cache=True, nogil=True, inline="always")
def _add_order(coeffs, lmax, m, pmm, x, cm, sm, total):
    """``total`` plus order m's terms, l = m..lmax (the associated Legendre recurrence from
    P_mm = ``pmm`` at cos theta = ``x``; cm, sm: cos and sin of m phi), in the order
    :func:`eval_point` and :func:`eval_direction` always summed them."""
    p_lm2 = 0.0
    p_lm1 = pmm
    for l in range(m, lmax + 1):
        p, p_lm1, p_lm2 = _next_plm(l, m, x, pmm, p_lm1, p_lm2)
        base = l * l + l
        if m == 0:
            total += coeffs[base] * p
        else:
            total += _SQRT2 * p * (coeffs[base + m] * cm + coeffs[base - m] * sm)
    return total


@nb.njit(cache=True, nogil=True, _nrt=False)
def eval_point(coeffs, lmax, theta, phi):
    """r(theta, phi) = sum_lm c_lm Y_lm for one direction: O(lmax^2), allocates nothing.
    ``lmax`` <= REC_LMAX (the config's limit; not checked here)."""
    x = math.cos(theta)
    s = math.sin(theta)
    pmm = _INV_SQRT_4PI
    total = 0.0
    for m in range(lmax + 1):
        if m > 0:
            pmm = -_REC_MM[m] * s * pmm
        total = _add_order(coeffs, lmax, m, pmm, x, math.cos(m * phi), math.sin(m * phi), total)
    return total


@nb.njit(cache=True, nogil=True)
def eval_direction(coeffs, lmax, dx, dy, dz):
    """r in the direction (dx, dy, dz) (any length > 0) without a transcendental call: cos theta,
    sin theta and cos/sin(phi) from the components, cos/sin(m phi) by angle addition. Equal to
    :func:`eval_point` at that direction to rounding (not bit for bit); for kernels that evaluate a
    surface at several nearby directions every tick (the pressed surface's slope). Allocates nothing."""
    n = math.sqrt(dx * dx + dy * dy + dz * dz)
    x = dz / n
    sxy = math.sqrt(dx * dx + dy * dy)
    s = sxy / n
    if sxy > 0.0:
        c1 = dx / sxy
        s1 = dy / sxy
    else:
        c1 = 1.0  # the pole: phi = 0, as direction_of gives it
        s1 = 0.0
    pmm = _INV_SQRT_4PI
    cm = 1.0
    sm = 0.0
    total = 0.0
    for m in range(lmax + 1):
        if m > 0:
            pmm = -_REC_MM[m] * s * pmm
            t = cm * c1 - sm * s1
            sm = sm * c1 + cm * s1
            cm = t
        total = _add_order(coeffs, lmax, m, pmm, x, cm, sm, total)
    return total


@nb.njit(cache=True, nogil=True, _nrt=False)
def _eval_point4(coeffs, lmax, theta, phi, out):
    """eval_point for four rows at once (the tissue's boundaries): one Legendre recurrence and one set
    of cos/sin(m phi), the four sums in registers and formed in eval_point's order (bit for bit)."""
    t0 = 0.0
    t1 = 0.0
    t2 = 0.0
    t3 = 0.0
    c0 = coeffs[0]
    c1 = coeffs[1]
    c2 = coeffs[2]
    c3 = coeffs[3]
    x = math.cos(theta)
    s = math.sin(theta)
    pmm = _INV_SQRT_4PI
    for m in range(lmax + 1):
        if m > 0:
            pmm = -_REC_MM[m] * s * pmm
        cm = math.cos(m * phi)
        sm = math.sin(m * phi)
        p_lm2 = 0.0
        p_lm1 = pmm
        for l in range(m, lmax + 1):
            p, p_lm1, p_lm2 = _next_plm(l, m, x, pmm, p_lm1, p_lm2)
            base = l * l + l
            if m == 0:
                t0 += c0[base] * p
                t1 += c1[base] * p
                t2 += c2[base] * p
                t3 += c3[base] * p
            else:
                sp = _SQRT2 * p
                t0 += sp * (c0[base + m] * cm + c0[base - m] * sm)
                t1 += sp * (c1[base + m] * cm + c1[base - m] * sm)
                t2 += sp * (c2[base + m] * cm + c2[base - m] * sm)
                t3 += sp * (c3[base + m] * cm + c3[base - m] * sm)
    out[0] = t0
    out[1] = t1
    out[2] = t2
    out[3] = t3


@nb.njit(cache=True, nogil=True, _nrt=False)
def eval_point4_grad(coeffs, lmax, theta, phi, out, k, grad):
    """:func:`_eval_point4` (``out``: the four rows' r, bit for bit) and row ``k``'s (0 <= k < 4)
    derivatives in the same pass: ``grad[0]`` = dr_k/dtheta, ``grad[1]`` = (dr_k/dphi) / sin(theta)
    (the surface gradient's components along e_theta and e_phi). dP_lm/dtheta follows the Legendre
    recurrence differentiated term by term (no division by sin theta, exact at the poles); at
    sin theta = 0 the phi component is its limit (:func:`_pole_dphi`). Allocates nothing."""
    t0 = 0.0
    t1 = 0.0
    t2 = 0.0
    t3 = 0.0
    gt = 0.0  # dr_k/dtheta
    gp = 0.0  # dr_k/dphi
    c0 = coeffs[0]
    c1 = coeffs[1]
    c2 = coeffs[2]
    c3 = coeffs[3]
    ck = coeffs[k]
    x = math.cos(theta)
    s = math.sin(theta)
    pmm = _INV_SQRT_4PI
    dmm = 0.0  # dP_mm/dtheta
    for m in range(lmax + 1):
        if m > 0:
            dmm = -_REC_MM[m] * (x * pmm + s * dmm)
            pmm = -_REC_MM[m] * s * pmm
        cm = math.cos(m * phi)
        sm = math.sin(m * phi)
        p_lm2 = 0.0
        p_lm1 = pmm
        d_lm2 = 0.0
        d_lm1 = dmm
        for l in range(m, lmax + 1):
            # d/dtheta of _next_plm's step (dx/dtheta = -sin theta), from the P values before it
            if l == m:
                dp = dmm
            elif l == m + 1:
                dp = _REC_M1[m] * (x * dmm - s * pmm)
            else:
                dp = _REC_A[l, m] * (x * d_lm1 - s * p_lm1 - _REC_B[l, m] * d_lm2)
            if l > m:
                d_lm2 = d_lm1
                d_lm1 = dp
            p, p_lm1, p_lm2 = _next_plm(l, m, x, pmm, p_lm1, p_lm2)
            base = l * l + l
            if m == 0:
                t0 += c0[base] * p
                t1 += c1[base] * p
                t2 += c2[base] * p
                t3 += c3[base] * p
                gt += ck[base] * dp
            else:
                sp = _SQRT2 * p
                t0 += sp * (c0[base + m] * cm + c0[base - m] * sm)
                t1 += sp * (c1[base + m] * cm + c1[base - m] * sm)
                t2 += sp * (c2[base + m] * cm + c2[base - m] * sm)
                t3 += sp * (c3[base + m] * cm + c3[base - m] * sm)
                cc = ck[base + m]
                cs = ck[base - m]
                gt += _SQRT2 * dp * (cc * cm + cs * sm)
                gp += sp * m * (cs * cm - cc * sm)
    out[0] = t0
    out[1] = t1
    out[2] = t2
    out[3] = t3
    grad[0] = gt
    grad[1] = gp / s if s != 0.0 else _pole_dphi(ck, lmax, x, phi)


@nb.njit(cache=True, nogil=True, _nrt=False)
def _pole_dphi(ck, lmax, x, phi):
    """(dr/dphi) / sin(theta) at sin(theta) = 0 (x = cos theta = +-1): its limit, order 1's terms
    alone with P_l1 / sin(theta) from the same recurrence started at P_11 / sin(theta)."""
    q11 = -_REC_MM[1] * _INV_SQRT_4PI  # P_11 / sin(theta)
    cm = math.cos(phi)
    sm = math.sin(phi)
    q_lm1 = q11
    q_lm2 = 0.0
    total = 0.0
    for l in range(1, lmax + 1):
        q, q_lm1, q_lm2 = _next_plm(l, 1, x, q11, q_lm1, q_lm2)
        base = l * l + l
        total += _SQRT2 * q * (ck[base - 1] * cm - ck[base + 1] * sm)
    return total


@nb.njit(cache=True, nogil=True, _nrt=False)
def eval_point_many(coeffs, lmax, theta, phi, out):
    """``out[k] = eval_point(coeffs[k], ...)`` for every row of ``coeffs`` (bit for bit); four rows,
    the tissue's boundaries, share one recurrence (:func:`_eval_point4`). Allocates nothing."""
    if coeffs.shape[0] == 4:
        _eval_point4(coeffs, lmax, theta, phi, out)
        return
    for k in range(coeffs.shape[0]):
        out[k] = eval_point(coeffs[k], lmax, theta, phi)


@nb.njit(cache=True, nogil=True, _nrt=False)
def direction_of(px, py, pz, cx, cy, cz):
    """(theta, phi, rho) of point p seen from centre c; the direction of c itself is the +z pole."""
    dx = px - cx
    dy = py - cy
    dz = pz - cz
    rho = math.sqrt(dx * dx + dy * dy + dz * dz)
    if rho == 0.0:
        return 0.0, 0.0, 0.0
    ct = dz / rho
    if ct > 1.0:
        ct = 1.0
    elif ct < -1.0:
        ct = -1.0
    return math.acos(ct), math.atan2(dy, dx), rho


@nb.njit(cache=True, nogil=True)
def radius_toward(coeffs, lmax, centre, p):
    """Radius of the surface (about ``centre``) in the direction of point ``p``, and |p - centre|."""
    theta, phi, rho = direction_of(p[0], p[1], p[2], centre[0], centre[1], centre[2])
    return eval_point(coeffs, lmax, theta, phi), rho


@nb.njit(cache=True, nogil=True)
def depth_below(coeffs, lmax, centre, p):
    """Signed radial distance of ``p`` below the surface: r(direction of p) - |p - c|.

    Positive inside (below the surface), negative outside, zero on it.
    """
    r, rho = radius_toward(coeffs, lmax, centre, p)
    return r - rho


def _as_angles(theta, phi):
    theta = np.ascontiguousarray(np.asarray(theta, dtype=np.float64).ravel())
    phi = np.ascontiguousarray(np.asarray(phi, dtype=np.float64).ravel())
    if theta.shape != phi.shape:
        raise ValueError(f"theta has {theta.size} values but phi has {phi.size}")
    if not (np.all(np.isfinite(theta)) and np.all(np.isfinite(phi))):
        raise ValueError("theta and phi must be finite (found NaN or infinity)")
    return theta, phi


def real_sph_harm(lmax: int, theta, phi) -> np.ndarray:
    """Real orthonormal harmonics, shape (n, (lmax+1)^2), column l*l + l + m (see module doc)."""
    lmax = int(lmax)
    if lmax < 0:
        raise ValueError(f"lmax must be >= 0, got {lmax}")
    theta, phi = _as_angles(theta, phi)
    out = np.empty((theta.size, n_coeffs(lmax)))
    _basis_matrix(lmax, theta, phi, out)
    return out


def fit(theta, phi, values, lmax: int) -> np.ndarray:
    """Least-squares SH coefficients (eq. 4) of samples ``values`` at directions (theta, phi).

    ``values`` is (n,) for a radial surface r(theta, phi) or (n, 3) for a parametric x/y/z one;
    the result is ((lmax+1)^2,) or ((lmax+1)^2, 3).

    Solved by the corrected semi-normal equations (Bjorck): a Cholesky factor of B^T B, then one
    refinement step with the residual computed from B itself, which brings the error back from
    eps * cond(B)^2 to about that of an orthogonal solver. Where the step's correction shows the
    first solve was poor (samples bunched so that B is ill conditioned) or B^T B is not positive
    definite, it falls back to ``numpy.linalg.lstsq`` (SVD-based; reports a deficient rank). Only
    numpy's linear algebra, which releases the GIL (scipy's does not), so a fit can run beside the
    servo thread.
    """
    theta, phi = _as_angles(theta, phi)
    values = np.asarray(values, dtype=np.float64)
    if values.ndim not in (1, 2) or values.shape[0] != theta.size or (values.ndim == 2 and values.shape[1] != 3):
        raise ValueError(f"values must have shape ({theta.size},) or ({theta.size}, 3), got {values.shape}")
    if not np.all(np.isfinite(values)):
        raise ValueError("values must be finite (found NaN or infinity)")
    k = n_coeffs(int(lmax))
    if theta.size < k:
        raise ValueError(f"{theta.size} samples are too few for lmax {lmax}: need at least (lmax+1)^2 = {k}")
    basis = real_sph_harm(lmax, theta, phi)
    coeffs = _fit_seminormal(basis, values)
    if coeffs is None:
        coeffs, _, rank, _ = np.linalg.lstsq(basis, values, rcond=None)
        if rank < k:
            raise ValueError(f"samples do not determine a degree-{lmax} expansion (rank {rank} < {k}); spread them over the sphere")
    return coeffs


SEMINORMAL_MAX_CORRECTION = 1e-6  # relative size of the refinement step beyond which lstsq decides


def _fit_seminormal(basis: np.ndarray, values: np.ndarray) -> np.ndarray | None:
    """x minimising |basis x - values| by Cholesky of basis^T basis and one correction step, or
    None when the first solve's error (the step's size) says the basis is too ill conditioned."""
    try:
        chol = np.linalg.cholesky(basis.T @ basis)
    except np.linalg.LinAlgError:
        return None

    def solve(rhs):  # (L L^T) x = rhs: two 256 x 256 solves at lmax 15, well under a millisecond
        return np.linalg.solve(chol.T, np.linalg.solve(chol, rhs))

    x = solve(basis.T @ values)
    step = solve(basis.T @ (values - basis @ x))
    x = x + step
    if not np.all(np.isfinite(x)):
        return None
    if np.abs(step).max() > SEMINORMAL_MAX_CORRECTION * max(np.abs(x).max(), 1e-300):
        return None
    return x


def evaluate(coeffs, theta, phi) -> np.ndarray:
    """Reconstruct (eq. 5): r(theta, phi) for (K,) coefficients, or x/y/z for (K, 3)."""
    coeffs = np.asarray(coeffs, dtype=np.float64)
    if coeffs.ndim not in (1, 2) or (coeffs.ndim == 2 and coeffs.shape[1] != 3):
        raise ValueError(f"coefficients must have shape (K,) or (K, 3), got {coeffs.shape}")
    lmax = lmax_of(coeffs.shape[0])
    if lmax > REC_LMAX:
        raise ValueError(f"lmax {lmax} is above the point kernels' {REC_LMAX}")
    shape = np.shape(theta)
    theta, phi = _as_angles(theta, phi)
    if coeffs.ndim == 1:
        out = np.empty(theta.size)
        _eval_many(np.ascontiguousarray(coeffs), lmax, theta, phi, out)
        return out.reshape(shape)
    return (real_sph_harm(lmax, theta, phi) @ coeffs).reshape(shape + (3,))


_CHUNK = 64  # points evaluated side by side by _eval_many
# numba with Intel's SVML vectorises cos/sin across a loop's iterations, not to glibc's bits: then
# _eval_many evaluates one point at a time (eval_point's own calls)
_SIDE_BY_SIDE = not getattr(nb.config, "USING_SVML", False)


@nb.njit(cache=True, nogil=True)
def _eval_many(coeffs, lmax, theta, phi, out):
    eval_many_work(coeffs, lmax, theta, phi, out, np.empty((EVAL_WORK_ROWS, _CHUNK)))


EVAL_WORK_ROWS = 8  # eval_many_work's ``work``: (EVAL_WORK_ROWS, _CHUNK)


@nb.njit(cache=True, nogil=True)
def eval_many_work(coeffs, lmax, theta, phi, out, work):
    """``out[i] = eval_point(coeffs, lmax, theta[i], phi[i])`` bit for bit, into ``out`` with the
    caller's ``work`` (EVAL_WORK_ROWS, _CHUNK) array (allocates nothing): points in chunks of
    _CHUNK, each step of eval_point's recurrence and sum (the same operations in the same order for
    every point) taken across the chunk's points, which the compiler can do several at a time."""
    n = theta.shape[0]
    if not _SIDE_BY_SIDE:
        for i in range(n):
            out[i] = eval_point(coeffs, lmax, theta[i], phi[i])
        return
    x, s, pmm, total, cm, sm, p1, p2 = work[0], work[1], work[2], work[3], work[4], work[5], work[6], work[7]
    for a in range(0, n, _CHUNK):
        k = min(_CHUNK, n - a)
        for j in range(k):
            x[j] = math.cos(theta[a + j])
            s[j] = math.sin(theta[a + j])
            pmm[j] = _INV_SQRT_4PI
            total[j] = 0.0
        for m in range(lmax + 1):
            if m > 0:
                r = _REC_MM[m]
                for j in range(k):
                    pmm[j] = -r * s[j] * pmm[j]
                for j in range(k):
                    f = m * phi[a + j]
                    cm[j] = math.cos(f)
                    sm[j] = math.sin(f)
            for j in range(k):
                p2[j] = 0.0
                p1[j] = pmm[j]
            for l in range(m, lmax + 1):  # _add_order's terms, _next_plm's recurrence
                base = l * l + l
                if l == m:
                    for j in range(k):
                        p = pmm[j]
                        if m == 0:
                            total[j] += coeffs[base] * p
                        else:
                            total[j] += _SQRT2 * p * (coeffs[base + m] * cm[j] + coeffs[base - m] * sm[j])
                    continue
                if l == m + 1:
                    c1 = _REC_M1[m]
                    for j in range(k):
                        p = c1 * x[j] * pmm[j]
                        p2[j] = p1[j]
                        p1[j] = p
                else:
                    ca = _REC_A[l, m]
                    cb = _REC_B[l, m]
                    for j in range(k):
                        p = ca * (x[j] * p1[j] - cb * p2[j])
                        p2[j] = p1[j]
                        p1[j] = p
                if m == 0:
                    c0 = coeffs[base]
                    for j in range(k):
                        total[j] += c0 * p1[j]
                else:
                    cp = coeffs[base + m]
                    cn = coeffs[base - m]
                    for j in range(k):
                        total[j] += _SQRT2 * p1[j] * (cp * cm[j] + cn * sm[j])
        for j in range(k):
            out[a + j] = total[j]


def grid(n_theta: int, n_phi: int) -> tuple[np.ndarray, np.ndarray]:
    """A (n_theta, n_phi) grid of directions: cell-centred in theta (no pole rows), uniform in phi."""
    theta = (np.arange(n_theta) + 0.5) * (np.pi / n_theta)
    phi = np.arange(n_phi) * (2.0 * np.pi / n_phi)
    return np.meshgrid(theta, phi, indexing="ij")


def unit_vectors(theta, phi) -> np.ndarray:
    """Unit direction vectors, shape theta.shape + (3,)."""
    theta = np.asarray(theta, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64)
    st = np.sin(theta)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], axis=-1)

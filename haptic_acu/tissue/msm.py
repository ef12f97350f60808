"""The MSM baseline: a volumetric mass-spring lattice of the layers, integrated at the servo rate
(docs/model.md section 12.2).

The lattice: cubes of side ``h``, nodes at their corners, springs along the cube edges and face
diagonals. Each cube of shear modulus ``mu`` gives each of its 12 edges ``mu h / 4`` and each of its
12 face diagonals ``mu h / 2`` (a spring sums its cubes' shares): inside a homogeneous region every
spring is ``k = mu h``, and the lattice's elastic constants are ``C44 = C12 = k / h``,
``C11 = 3 k / h``: isotropic, shear modulus ``mu``, first Lame constant ``mu`` (nu = 1/4, the Cauchy
relation of central springs). The hybrid rule of Golec et al. (Vis. Comput. 2020) supplements the
springs with an energy of the volume alone, one per cube, ``(lambda - mu) V (dV / V)^2 / 2``, which
adds ``lambda - mu`` to the first Lame constant: the lattice then has the ``E`` and ``nu`` it was
built from. ``dV / V`` is the cube's mean divergence (its trilinear interpolation's, at the centre),
linear in its nodes' displacements.

The dynamics: lumped masses (each cube's ``rho h^3`` in eighths to its corners), modal damping, the
bottom fixed, the sides free, the tip's node pushed along the surface normal by a unilateral
contact. The patch is symmetric about the vertical axis through the tip's node (the square's eight
symmetries) and is driven only there, so only its fully symmetric motions are excited: the
lattice's equations are projected onto them (an exact reduction), their modes computed once, and
the servo advances each mode by backward Euler (:func:`msm_tick`), the contact force solved
implicitly with them.

Puncture: the tissue's mean axial strain over a gauge of ``GAUGE_M`` below the tip (the relative
shortening of the column under the pushed node, its displacement at the gauge's depth interpolated
between nodes), a linear function of the modal coordinates like every quantity here. A spring's
strain at the pushed node would not do: under a point push it is ``d / h`` times a factor set by
``nu`` and the layers' modulus ratios alone, so a threshold on it is a break depth proportional to
the spacing ``h`` (:func:`static_press` measures both).
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numba as nb
import numpy as np

_EDGE = ((1, 0, 0), (0, 1, 0), (0, 0, 1))
_DIAG = ((1, 1, 0), (1, -1, 0), (1, 0, 1), (1, 0, -1), (0, 1, 1), (0, 1, -1))
EDGE_SHARE = 0.25  # a cube's share to each edge, times mu h
DIAG_SHARE = 0.5  # to each face diagonal, times mu h
HALF_CELLS = 6  # the patch spans +-6 cells around the tip
DEPTH_M = 6e-3  # and at most this deep (fixed below)
DAMPING_RATIO = 0.2  # every mode's damping ratio (ours)
# skin, fat, muscle (kg/m^3): the IT'IS Foundation's tissue properties database (docs/model.md s12.2)
DENSITY_KG_M3 = (1109.0, 911.0, 1090.0)
DT = 1e-3  # the servo period the modes are integrated at (s)
GAUGE_M = 1e-3  # the puncture strain's gauge below the tip (ours: two cells of the default spacing)
N_STRAIN = 1  # strain rows per layer in the servo's table: the gauge's
# the rows of one layer's block in the model's table (msm_pack): per mode
ROW_PHI, ROW_W2DT, ROW_INVD, ROW_G = 0, 1, 2, 3
ROWS = ROW_G + N_STRAIN


def lame(E, nu):
    """(lambda, mu) of Young's modulus ``E`` and Poisson's ratio ``nu``."""
    E = np.asarray(E, float)
    nu = np.asarray(nu, float)
    return E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))


def springs(nx, ny, nz, h, cube_mu):
    """The lattice's springs: (i, j, stiffness, unit direction) for nodes on an (nx, ny, nz) grid of
    spacing h (node index ``(ix * ny + iy) * nz + iz``); ``cube_mu[cx, cy, cz]`` is each cube's shear
    modulus. A spring's stiffness sums, over the cubes it borders, ``mu h / 4`` (an edge, up to four
    cubes) or ``mu h / 2`` (a face diagonal, up to two)."""
    idx = np.arange(nx * ny * nz).reshape(nx, ny, nz)
    rows = []
    shape = cube_mu.shape
    for off, share in [(o, EDGE_SHARE) for o in _EDGE] + [(o, DIAG_SHARE) for o in _DIAG]:
        dx, dy, dz = off
        ax = np.arange(nx - abs(dx)) + max(0, -dx)
        ay = np.arange(ny - abs(dy)) + max(0, -dy)
        az = np.arange(nz - abs(dz)) + max(0, -dz)
        I, J, L = np.meshgrid(ax, ay, az, indexing="ij")
        i0 = idx[I, J, L].ravel()
        i1 = idx[I + dx, J + dy, L + dz].ravel()
        kk = np.zeros(i0.size)
        lo = np.stack([np.minimum(I, I + dx), np.minimum(J, J + dy), np.minimum(L, L + dz)], -1).reshape(-1, 3)
        # the cubes bordering the spring start at lo, or one cell back along each axis it lies across
        for m in itertools.product(*[(0, -1) if dv == 0 else (0,) for dv in off]):
            cx, cy, cz = lo[:, 0] + m[0], lo[:, 1] + m[1], lo[:, 2] + m[2]
            ok = (cx >= 0) & (cy >= 0) & (cz >= 0) & (cx < shape[0]) & (cy < shape[1]) & (cz < shape[2])
            kk[ok] += share * cube_mu[cx[ok], cy[ok], cz[ok]] * h
        n = np.array(off, float) / np.linalg.norm(off)
        good = kk > 0
        rows.append((i0[good], i1[good], kk[good], np.tile(n, (int(good.sum()), 1))))
    return tuple(np.concatenate([r[c] for r in rows]) for c in range(4))


def stiffness_matrix(nx, ny, nz, h, cube_mu, cube_lv):
    """The lattice's stiffness matrix (3 nodes square, sparse CSR): the springs' and, per cube, the
    volume energy's ``lambda_v h^3 b b^T`` (``b . u`` the cube's mean divergence, ``lambda_v`` its
    ``cube_lv``). Also returns the springs (:func:`springs`)."""
    import scipy.sparse as sp

    nn = nx * ny * nz
    i, j, k, n = springs(nx, ny, nz, h, cube_mu)
    blocks = k[:, None, None] * n[:, :, None] * n[:, None, :]
    r, c, v = [], [], []
    for a_, b_, sgn in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
        for p in range(3):
            for q in range(3):
                r.append(3 * a_ + p)
                c.append(3 * b_ + q)
                v.append(sgn * blocks[:, p, q])
    # the volume term: cube (cx, cy, cz)'s corner (bx, by, bz) in {0, 1}^3, b = sign / (4 h) per axis
    idx = np.arange(nn).reshape(nx, ny, nz)
    CX, CY, CZ = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), np.arange(nz - 1), indexing="ij")
    lv = cube_lv[CX, CY, CZ].ravel() * h ** 3
    dofs, bvec = [], []
    for bx, by, bz in itertools.product((0, 1), repeat=3):
        node = idx[CX + bx, CY + by, CZ + bz].ravel()
        for axis, bit in enumerate((bx, by, bz)):
            dofs.append(3 * node + axis)
            bvec.append(np.full(node.size, (2 * bit - 1) / (4 * h)))
    dofs = np.stack(dofs, 1)  # (cubes, 24)
    bvec = np.stack(bvec, 1)
    for p in range(24):
        for q in range(24):
            r.append(dofs[:, p])
            c.append(dofs[:, q])
            v.append(lv * bvec[:, p] * bvec[:, q])
    K = sp.csr_matrix((np.concatenate(v), (np.concatenate(r), np.concatenate(c))), shape=(3 * nn, 3 * nn))
    return K, (i, j, k, n)


def lumped_masses(nx, ny, nz, h, cube_rho):
    """Each node's mass (kg): an eighth of each cube's ``rho h^3`` it is a corner of."""
    m = np.zeros((nx, ny, nz))
    cm = cube_rho * h ** 3 / 8.0
    for bx, by, bz in itertools.product((0, 1), repeat=3):
        m[bx:nx - 1 + bx, by:ny - 1 + by, bz:nz - 1 + bz] += cm
    return m.ravel()


def _solve_fixed(K, fixed_dofs, fixed_vals):
    import scipy.sparse.linalg as spla

    n = K.shape[0]
    u = np.zeros(n)
    u[fixed_dofs] = fixed_vals
    free = np.setdiff1d(np.arange(n), fixed_dofs)
    rhs = -(K[free][:, fixed_dofs] @ u[fixed_dofs])
    u[free] = spla.spsolve(K[free][:, free].tocsc(), rhs)
    return u


def compression_test(E, nu, h, cells=6, strain=1e-3):
    """A homogeneous lattice cube of ``cells`` cells a side, built from ``E`` (Pa) and ``nu``,
    compressed by ``strain`` between a rolling bottom and a rolling top (the sides free): (its
    effective Young's modulus, stress over strain, Pa; its effective Poisson's ratio, the sides'
    mean lateral strain over the axial strain)."""
    n = cells + 1
    lam, mu = lame(E, nu)
    shape = (cells, cells, cells)
    K, _ = stiffness_matrix(n, n, n, h, np.full(shape, float(mu)), np.full(shape, float(lam - mu)))
    idx = np.arange(n ** 3).reshape(n, n, n)
    bottom, top = idx[:, :, 0].ravel(), idx[:, :, -1].ravel()
    dz = strain * cells * h
    fixed = np.concatenate([3 * bottom + 2, 3 * top + 2, [3 * idx[0, 0, 0], 3 * idx[0, 0, 0] + 1,
                                                          3 * idx[-1, 0, 0] + 1]])
    vals = np.concatenate([np.zeros(bottom.size), np.full(top.size, -dz), [0.0, 0.0, 0.0]])
    u = _solve_fixed(K, fixed, vals).reshape(-1, 3)
    force = -(K @ u.ravel())[3 * top + 2].sum()
    E_eff = force / (cells * h) ** 2 / strain
    # lateral: the mean widening of the block, x faces and y faces
    wx = (u[idx[-1].ravel(), 0] - u[idx[0].ravel(), 0]).mean()
    wy = (u[idx[:, -1].ravel(), 1] - u[idx[:, 0].ravel(), 1]).mean()
    lateral = 0.5 * (wx + wy) / (cells * h)
    return float(E_eff), float(lateral / strain)


def gauge_row(uz, column, nz, h, gauge=GAUGE_M):
    """The gauge's strain (the column's relative shortening over ``gauge`` below its surface node,
    positive in compression) as a linear function: ``uz(node)`` is the node's upward displacement
    (a number or a row of them), ``column`` the first node of the column (``column + nz - 1`` its
    surface node), ``h`` the spacing. The gauge is cut to the patch's depth."""
    ell = min(gauge, (nz - 1) * h)
    j = min(int(ell / h), nz - 2)
    t = ell / h - j
    top = column + nz - 1
    below = (1.0 - t) * uz(top - j) + t * uz(top - j - 1)
    return (below - uz(top)) / ell


def static_press(E, nu, thick, h, half_width, depth, gauge=GAUGE_M):
    """The patch of :func:`modes`, ``half_width`` (m) on each side of the tip, statically pressed
    by a unit push of its tip's node (every degree of freedom, a sparse solve): (its stiffness, N/m;
    the gauge's strain per metre of push; the largest strain of a spring at the tip's node per
    metre of push)."""
    half_cells = max(1, int(round(half_width / h)))
    n, nz, cmu, clv, _ = _patch(E, nu, np.ones(len(E)), thick, h, half_cells, depth)
    K, (si, sj, _, sn) = stiffness_matrix(n, n, nz, h, cmu, clv)
    c = n // 2
    col = (c * n + c) * nz
    tip = col + nz - 1
    bottom = np.arange(n * n) * nz
    fixed = np.concatenate([3 * bottom, 3 * bottom + 1, 3 * bottom + 2, [3 * tip + 2]])
    vals = np.zeros(fixed.size)
    vals[-1] = -1.0
    u = _solve_fixed(K, fixed, vals)
    force = -(K @ u)[3 * tip + 2]
    U = u.reshape(-1, 3)
    at = (si == tip) | (sj == tip)
    ext = ((U[sj[at]] - U[si[at]]) * sn[at]).sum(axis=1)

    def xyz(i):
        return np.stack([(i // nz) // n, (i // nz) % n, i % nz], axis=-1) * h

    length = np.linalg.norm(xyz(sj[at]) - xyz(si[at]), axis=1)
    return float(force), float(gauge_row(lambda node: U[node, 2], col, nz, h, gauge)), float(np.abs(ext / length).max())


# ---- the patch around the tip --------------------------------------------------------------------

def _patch(E, nu, rho, thick, h, half_cells, depth):
    """The patch's grid and per-cube materials: (n, nz, cube_mu, cube_lv, cube_rho). Node z index 0
    is the (fixed) bottom, nz - 1 the surface."""
    nz = max(2, int(round(min(depth, float(np.sum(thick))) / h)) + 1)
    n = 2 * half_cells + 1
    zc = (np.arange(nz - 1) + 0.5) * h  # cube centre depths from the surface
    bounds = np.concatenate([[0.0], np.cumsum(thick)[:-1], [np.inf]])
    layer = (np.searchsorted(bounds, zc, side="right") - 1)[::-1]  # bottom first
    lam, mu = lame(np.asarray(E, float), np.asarray(nu, float))

    def cubes(per_layer):
        return np.broadcast_to(np.asarray(per_layer, float)[layer][None, None, :], (n - 1, n - 1, nz - 1)).copy()

    return n, nz, cubes(mu), cubes(lam - mu), cubes(rho)


def _symmetric_basis(n, nz, free_nodes_mask):
    """An orthonormal basis (sparse, 3 n n nz rows) of the displacements of an (n, n, nz) grid that the
    square's eight symmetries about its centre column leave unchanged, on the free nodes only."""
    c = n // 2
    mats = []
    for swap in (False, True):
        for sx in (1, -1):
            for sy in (1, -1):
                mats.append((swap, sx, sy))

    def image(ix, iy, swap, sx, sy):
        x, y = ix - c, iy - c
        if swap:
            x, y = y, x
        return c + sx * x, c + sy * y

    def comp_image(comp, swap, sx, sy):
        # a displacement component under the same map: (component, sign)
        if comp == 2:
            return 2, 1.0
        if swap:
            comp = 1 - comp
        return comp, float(sx if comp == 0 else sy)

    rows, cols, vals = [], [], []
    ncol = 0
    N = 3 * n * n * nz
    for ix in range(c, n):
        for iy in range(c, ix + 1):
            for iz in range(nz):
                if not free_nodes_mask[(ix * n + iy) * nz + iz]:
                    continue
                vecs = []
                for comp in range(3):
                    w = {}
                    for swap, sx, sy in mats:
                        jx, jy = image(ix, iy, swap, sx, sy)
                        cc, sg = comp_image(comp, swap, sx, sy)
                        dof = 3 * ((jx * n + jy) * nz + iz) + cc
                        w[dof] = w.get(dof, 0.0) + sg / 8.0
                    vecs.append(w)
                support = sorted({d for w in vecs for d in w})
                A = np.zeros((len(support), 3))
                pos = {d: t for t, d in enumerate(support)}
                for t, w in enumerate(vecs):
                    for d, val in w.items():
                        A[pos[d], t] = val
                U, S, _ = np.linalg.svd(A, full_matrices=False)
                for t in range(3):
                    if S[t] > 1e-9:
                        rows.extend(support)
                        vals.extend(U[:, t])
                        cols.extend([ncol] * len(support))
                        ncol += 1
    import scipy.sparse as sp

    return sp.csc_matrix((vals, (rows, cols)), shape=(N, ncol))


class _Rows:
    """Rows of ``P @ V`` on demand."""

    def __init__(self, P, V):
        self.P = P.tocsr()
        self.V = V

    def __getitem__(self, sl):
        out = np.asarray(self.P[sl] @ self.V)
        return out[0] if isinstance(sl, (int, np.integer)) else out


@dataclass
class MsmModes:
    """One pressed layer's lattice, reduced to its symmetric modes (what the servo reads)."""

    phi: np.ndarray  # (modes,) each mass-normalised mode's normal displacement at the tip's node (down +)
    omega: np.ndarray  # (modes,) rad/s
    strain: np.ndarray  # (N_STRAIN, modes) the gauge's strain (shortening +) per unit modal coordinate
    stiffness: float  # N/m: the static force per metre of push
    strain_per_m: float  # the gauge's strain per metre of static push
    nodes: int  # the patch's nodes
    mass: float  # kg: the patch's mass


def modes(E, nu, rho, thick, h, half_cells=HALF_CELLS, depth=DEPTH_M) -> MsmModes:
    """The lattice of the layers (moduli ``E`` Pa, Poisson's ratios ``nu``, densities ``rho`` kg/m^3,
    thicknesses ``thick`` m from the top, the last one continuing to ``depth``): the bottom fixed,
    the sides free, its symmetric modes about the surface node at the centre."""
    import scipy.linalg as sla

    n, nz, cmu, clv, crho = _patch(E, nu, rho, thick, h, half_cells, depth)
    K, (si, sj, sk, sn) = stiffness_matrix(n, n, nz, h, cmu, clv)
    mass = lumped_masses(n, n, nz, h, crho)
    iz = np.tile(np.arange(nz), n * n)
    free = iz > 0
    P = _symmetric_basis(n, nz, free)
    import scipy.sparse as sp

    Kr = (P.T @ K @ P).toarray()
    Kr = 0.5 * (Kr + Kr.T)
    Mr = (P.T @ sp.diags(np.repeat(mass, 3)) @ P).toarray()
    w2, V = sla.eigh(Kr, Mr)
    c = n // 2
    tip = (c * n + c) * nz + nz - 1
    Phi = _Rows(P, V)  # mass-normalised modes, full grid (the rows asked for)
    phi = -Phi[3 * tip + 2]  # a push is downward: +phi is a mode's downward displacement at the tip
    G = gauge_row(lambda node: Phi[3 * node + 2], (c * n + c) * nz, nz, h)[None, :]
    keep = np.abs(phi) > 1e-12 * np.abs(phi).max()
    phi, w2, G = phi[keep], w2[keep], G[:, keep]
    omega = np.sqrt(np.maximum(w2, 0.0))
    # statics: a unit force at the tip displaces it sum(phi^2 / w^2); k is its inverse
    comp = float(np.sum(phi * phi / w2))
    q_unit = phi / w2 / comp  # the modal coordinates of a unit static push
    strain = np.abs(G @ q_unit)
    return MsmModes(phi.copy(), omega, np.ascontiguousarray(G), 1.0 / comp, float(strain.max()), n * n * nz,
                    float(mass.sum()))


# ---- the servo's side ------------------------------------------------------------------------------

def pack(layer_modes, n_layers, zeta=DAMPING_RATIO, dt=DT):
    """The servo's table of every layer's modes (``Model.msm``, rows ``k * ROWS + ROW_*``, a column
    per mode) and per layer (modes, the contact's backward-Euler compliance g in m/N)."""
    width = max([1] + [len(md.phi) for md in layer_modes if md is not None])
    tab = np.zeros((n_layers * ROWS, width))
    count = np.zeros(n_layers, np.int64)
    g = np.zeros(n_layers)
    for k, md in enumerate(layer_modes):
        if md is None:
            continue
        nm = len(md.phi)
        D = 1.0 + 2.0 * zeta * md.omega * dt + md.omega ** 2 * dt * dt
        b = k * ROWS
        tab[b + ROW_PHI, :nm] = md.phi
        tab[b + ROW_W2DT, :nm] = md.omega ** 2 * dt
        tab[b + ROW_INVD, :nm] = 1.0 / D
        tab[b + ROW_G:b + ROW_G + N_STRAIN, :nm] = md.strain
        count[k] = nm
        g[k] = float(np.sum(md.phi ** 2 * dt * dt / D))
    return tab, count, g


@nb.njit(cache=True, nogil=True, _nrt=False)
def msm_tick(tab, k, nm, g, q, v, dep, dt):
    """One backward-Euler step of layer ``k``'s lattice (its ``nm`` modes in ``tab``; their
    coordinates ``q`` and velocities ``v``, updated in place) with the tip ``dep`` below the rest
    surface: the unilateral contact's force f >= 0 is solved with the step (the tip's node ends at
    ``dep`` while pressed, free otherwise). Returns (f, N; the gauge's |strain|)."""
    b = k * ROWS
    free = 0.0  # the tip node's displacement after the step without the contact's force
    for i in range(nm):
        vi = (v[i] - tab[b + ROW_W2DT, i] * q[i]) * tab[b + ROW_INVD, i]
        free += tab[b + ROW_PHI, i] * (q[i] + dt * vi)
    f = (dep - free) / g
    if f < 0.0:
        f = 0.0
    for i in range(nm):
        vi = (v[i] - tab[b + ROW_W2DT, i] * q[i] + dt * tab[b + ROW_PHI, i] * f) * tab[b + ROW_INVD, i]
        v[i] = vi
        q[i] += dt * vi
    smax = 0.0
    for t in range(N_STRAIN):
        s = 0.0
        row = b + ROW_G + t
        for i in range(nm):
            s += tab[row, i] * q[i]
        s = abs(s)
        if s > smax:
            smax = s
    return f, smax

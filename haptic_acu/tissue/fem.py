"""The FEM baseline: linear elastostatics on tetrahedra between the SH boundaries, condensed onto
the surface around the contact point (DiMaio & Salcudean 2005; Bro-Nielsen 1998; docs/model.md
section 12.3).

The mesh is structured in (r, theta, phi): a tensor grid of columns around the contact point, each
column a radial line from the body's centre (a gnomonic chart of the unit sphere about the contact
direction, so the pole needs no special case), with nodes on each column at the actual radii of
the SH boundaries ``r_k(theta, phi)`` and, between two boundaries, at fixed fractions of the
layer's radial thickness in that direction. Each hexahedron of the grid is split into six
tetrahedra the same way everywhere (scikit-fem's ``MeshTet.init_tensor``), so the mesh is
conforming and every layer interface lies on element faces. Cells are ``a / n_in`` across the
tip's radius ``a`` and grow geometrically away from it, laterally and in depth.

P1 elements, each layer its own ``E`` and ``nu``; the bottom of the meshed block is fixed, its
sides free. The stiffness is condensed (Schur complement) onto the radial displacements of the
surface nodes within ``patch`` of the contact point; a flat frictionless tip of radius ``a``
holds the nodes within ``a`` at the indentation ``d`` and leaves the rest of the patch free.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import shf

# The servo's mesh (ours): N_IN elements across the tip's radius, then cells growing by RATIO; the
# block is HALF_WIDTH wide on each side and at most DEPTH deep (the body below is taken as fixed:
# at 64 tip radii it moves the tip's stiffness by about 1%).
N_IN = 2
RATIO = 1.6
HALF_WIDTH_M = 8e-3
DEPTH_M = 8e-3
PATCH_M = 1e-3  # surface nodes kept by the condensation (within this of the contact point)
PERMC = "MMD_AT_PLUS_A"  # SuperLU column ordering: minimum degree on A^T + A suits a symmetric 3D stiffness


def graded_grid(a: float, n_in: int, ratio: float, length: float) -> np.ndarray:
    """0 .. length: n_in equal cells across ``a``, then cells growing by ``ratio``."""
    h = a / n_in
    pts = list(np.linspace(0.0, a, n_in + 1))
    while pts[-1] + 1.5 * h * ratio < length:
        h *= ratio
        pts.append(pts[-1] + h)
    pts.append(length)
    return np.array(pts)


def depth_grid(a: float, n_in: int, ratio: float, interfaces, depth: float) -> np.ndarray:
    """Depths 0 .. depth graded from the surface, with every layer interface a grid plane."""
    z = graded_grid(a, n_in, ratio, depth)
    keep = [v for v in z if v in (0.0, depth) or all(abs(v - s) > 0.3 * _local_h(z, v) for s in interfaces)]
    return np.unique(np.concatenate([keep, [s for s in interfaces if 0.0 < s < depth]]))


def _local_h(z, v):
    i = min(int(np.searchsorted(z, v)), len(z) - 1)
    return z[i] - z[i - 1] if i > 0 else z[1] - z[0]


# ---- the layered body's boundaries --------------------------------------------------------------

@dataclass(frozen=True)
class Boundaries:
    """Nested radial surfaces about ``centre``: ``radius(k, dirs)`` is boundary k's radius (m) along
    the unit directions ``dirs`` (n, 3); boundary 0 is the outermost one meshed (the pressed
    layer's top), boundary j + 1 the bottom of layer j."""

    radius: object  # callable (k, dirs) -> (n,) radii
    centre: np.ndarray
    count: int  # number of boundaries (layers + 1)


def sh_boundaries(coeffs, centre, first: int) -> Boundaries:
    """The SH boundaries ``first`` .. last of a body (``tissue.body.Tissue``'s ``coeffs``, m)."""
    c = np.asarray(coeffs, float)[first:]

    def radius(k, dirs):
        theta = np.arccos(np.clip(dirs[:, 2], -1.0, 1.0))
        phi = np.arctan2(dirs[:, 1], dirs[:, 0])
        return shf.evaluate(c[k], theta, phi)

    return Boundaries(radius, np.asarray(centre, float), len(c))


def sphere_boundaries(radius_m: float, thick) -> Boundaries:
    """Concentric spheres: the outer one of ``radius_m`` centred below the origin (its top at the
    origin), then one below each layer of thicknesses ``thick`` (m). A homogeneous body of a large
    radius is the closed forms' half-space."""
    offs = np.concatenate([[0.0], np.cumsum(thick)])

    def radius(k, dirs):
        return np.full(len(dirs), radius_m - offs[k])

    return Boundaries(radius, np.array([0.0, 0.0, -radius_m]), len(offs))


def _frame(axis):
    n = axis / np.linalg.norm(axis)
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t1 = ref - n * (ref @ n)
    t1 /= np.linalg.norm(t1)
    return n, t1, np.cross(n, t1)


@dataclass
class BodyMesh:
    mesh: object  # skfem.MeshTet, nodes at their physical positions (m)
    layer: np.ndarray  # (elements,) index of each element's layer (0 = the pressed one)
    radial: np.ndarray  # (3, nodes) each node's column direction (unit, outward)
    lateral: np.ndarray  # (2, nodes) each node's column in the chart (m from the contact point)
    depth: np.ndarray  # (nodes,) each node's nominal depth below the surface (m)
    block_depth: float


def body_mesh(bnd: Boundaries, point, a, n_in=N_IN, ratio=RATIO, half_width=HALF_WIDTH_M, depth=DEPTH_M,
              quarter=False) -> BodyMesh:
    """The structured tetrahedral mesh of the layers between ``bnd``'s boundaries around ``point``
    (m, on or near boundary 0). ``quarter``: only the quarter x, y >= 0 of the chart (for a body
    symmetric about the two planes through the axis, with symmetry conditions on them)."""
    from skfem import MeshTet

    axis, t1, t2 = _frame(np.asarray(point, float) - bnd.centre)
    r_top = float(bnd.radius(0, axis[None, :])[0])
    r_axis = np.array([float(bnd.radius(k, axis[None, :])[0]) for k in range(bnd.count)])
    z_nom = r_axis[0] - r_axis  # nominal interface depths along the axis: 0, h0, h0 + h1, ...
    depth = min(depth, float(z_nom[-1]))
    near = [z for z in z_nom[1:] if abs(z - depth) < 0.1 * depth]
    depth = float(near[0]) if near else depth  # a bottom close to an interface: the interface
    g = graded_grid(a, n_in, ratio, half_width)
    xs = g if quarter else np.concatenate([-g[:0:-1], g])
    zs = depth_grid(a, n_in, ratio, list(z_nom[1:-1]), depth)
    mesh = MeshTet.init_tensor(xs, xs, -zs[::-1])
    X, Y, Zp = mesh.p
    s = -Zp  # nominal depth
    # each column's direction, then the boundary radii along it (evaluated once per column)
    cols, inv = np.unique(np.round(np.stack([X, Y], 1) / (a * 1e-6)).astype(np.int64), axis=0, return_inverse=True)
    inv = inv.ravel()
    cx = np.zeros(len(cols))
    cy = np.zeros(len(cols))
    cx[inv] = X
    cy[inv] = Y
    d = axis[None, :] + (cx[:, None] * t1[None, :] + cy[:, None] * t2[None, :]) / r_top
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    R = np.stack([bnd.radius(k, d) for k in range(bnd.count)], 1)  # (columns, boundaries)
    j = np.clip(np.searchsorted(z_nom, s, side="right") - 1, 0, bnd.count - 2)
    frac = (s - z_nom[j]) / (z_nom[j + 1] - z_nom[j])
    r = R[inv, j] - frac * (R[inv, j] - R[inv, j + 1])
    dn = d[inv]
    mesh = MeshTet(np.ascontiguousarray((bnd.centre[None, :] + r[:, None] * dn).T), mesh.t)
    zc = s[mesh.t].mean(axis=0)
    layer = np.clip(np.searchsorted(z_nom, zc, side="right") - 1, 0, bnd.count - 2)
    return BodyMesh(mesh, layer, np.ascontiguousarray(dn.T), np.stack([X, Y]), s, depth)


# ---- the condensed contact ----------------------------------------------------------------------

@dataclass
class FemResult:
    stiffness: float  # N/m: flat-tip force per metre of indentation
    patch_xy: np.ndarray  # (n, 2) the condensed surface nodes in the chart (m from the contact point)
    schur: np.ndarray  # (n, n) the stiffness condensed onto their radial displacements (N/m)
    profile_r: np.ndarray  # surface nodes along the chart's first axis (m)
    profile_u: np.ndarray  # their inward radial displacement per metre of indentation
    nodes: int
    elements: int


def press(bnd: Boundaries, point, E, nu, a, n_in=N_IN, ratio=RATIO, half_width=HALF_WIDTH_M, depth=DEPTH_M,
          patch=PATCH_M, quarter=False) -> FemResult:
    """A flat rigid tip of radius ``a`` pressed (frictionless, radially) into the layered body at
    ``point``: layer j between boundaries j and j + 1 of ``bnd`` has Young's modulus ``E[j]`` (Pa)
    and Poisson ratio ``nu[j]``. Returns the condensed patch and the stiffness."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla
    from skfem import Basis, ElementTetP1, ElementVector, asm
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    bm = body_mesh(bnd, point, a, n_in, ratio, half_width, depth, quarter)
    mesh = bm.mesh
    e = ElementVector(ElementTetP1())
    K = None
    for j in range(len(E)):
        sel = np.nonzero(bm.layer == j)[0]
        if sel.size == 0:
            continue
        # scikit-fem 12: lame_parameters(E, nu) returns (lambda, mu), linear_elasticity takes (Lambda, Mu)
        Kj = asm(linear_elasticity(*lame_parameters(E[j], nu[j])), Basis(mesh, e, elements=sel))
        K = Kj if K is None else K + Kj
    nn = mesh.p.shape[1]
    dofs = Basis(mesh, e).nodal_dofs  # (3, nodes)
    X, Y = bm.lateral
    top = np.isclose(bm.depth, 0.0)
    rho = np.hypot(X, Y)
    pnodes = np.nonzero(top & (rho <= patch * (1 + 1e-9)))[0]
    # the patch's dofs rotated to (radial, t1, t2): u = T u', T = blockdiag(rotations) on the patch
    axis, t1, t2 = _frame(np.asarray(point, float) - bnd.centre)
    keep = np.ones(3 * nn, bool)
    keep[dofs[:, pnodes].ravel()] = False
    rows, cols, vals = [np.nonzero(keep)[0]], [np.nonzero(keep)[0]], [np.ones(int(keep.sum()))]
    dr = bm.radial[:, pnodes]
    e1 = t1[:, None] - dr * (t1 @ dr)[None, :]
    e1 /= np.linalg.norm(e1, axis=0, keepdims=True)
    e2 = np.cross(dr.T, e1.T).T
    basis = (dr, e1, e2)
    for c in range(3):
        for q in range(3):
            rows.append(dofs[c, pnodes])
            cols.append(dofs[q, pnodes])
            vals.append(basis[q][c])
    T = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * nn, 3 * nn))
    K = (T.T @ K @ T).tocsr()
    fixed = dofs[:, np.isclose(bm.depth, bm.block_depth)].ravel()
    if quarter:  # symmetry planes x = 0 and y = 0 of the chart (the axis along z)
        fixed = np.concatenate([fixed, dofs[0, np.isclose(X, 0.0) & ~top], dofs[1, np.isclose(Y, 0.0) & ~top]])
        # on the patch the tangential dofs are rotated; at x = 0 (y = 0) the radial column lies in the
        # symmetry plane, so e1 (e2) is its normal
        fixed = np.concatenate([fixed, dofs[1, pnodes[np.isclose(X[pnodes], 0.0)]],
                                dofs[2, pnodes[np.isclose(Y[pnodes], 0.0)]]])
        fixed = np.concatenate([fixed, dofs[0, np.nonzero(top & np.isclose(X, 0.0) & (rho > patch * (1 + 1e-9)))[0]],
                                dofs[1, np.nonzero(top & np.isclose(Y, 0.0) & (rho > patch * (1 + 1e-9)))[0]]])
    b = dofs[0, pnodes]  # the patch's radial dofs
    fixed = np.setdiff1d(np.unique(fixed), b)
    inner = np.setdiff1d(np.arange(K.shape[0]), np.concatenate([fixed, b]))
    Kii = K[inner][:, inner].tocsc()
    Kib = K[inner][:, b].toarray()
    X_ = spla.splu(Kii, permc_spec=PERMC).solve(Kib)  # K_ii^-1 K_ib
    S = K[b][:, b].toarray() - Kib.T @ X_  # the Schur complement onto the patch's radial dofs
    S = 0.5 * (S + S.T)
    inside = rho[pnodes] <= a * (1 + 1e-9)
    c = np.nonzero(inside)[0]
    o = np.nonzero(~inside)[0]
    Soo_inv_Soc = np.linalg.solve(S[np.ix_(o, o)], S[np.ix_(o, c)])
    Sc = S[np.ix_(c, c)] - S[np.ix_(c, o)] @ Soo_inv_Soc
    k = float(Sc.sum()) * (4.0 if quarter else 1.0)
    # a unit indentation (inward): the patch's radial displacement, then the interior's
    ub = np.zeros(len(b))
    ub[c] = -1.0
    ub[o] = Soo_inv_Soc @ np.ones(len(c))
    u = np.zeros(K.shape[0])
    u[b] = ub
    u[inner] = -X_ @ ub
    ug = (T @ u)[dofs]  # (3, nodes), global
    along = np.nonzero(top & np.isclose(Y, 0.0) & (X >= 0))[0]
    along = along[np.argsort(X[along])]
    inward = -(ug[:, along] * bm.radial[:, along]).sum(axis=0)
    return FemResult(k, np.stack([X[pnodes], Y[pnodes]], 1), S, X[along].copy(), inward, nn, mesh.t.shape[1])


def disc_compliance(res: FemResult, a: float):
    """The compliance (m/N) of the condensed surface nodes within ``a`` of the contact point, the
    rest of the patch free: that block of the Schur complement's inverse; and the nodes' lateral
    distances (m). The contact's precomputed matrix (``tissue.contact``)."""
    rho = np.hypot(res.patch_xy[:, 0], res.patch_xy[:, 1])
    d = np.nonzero(rho <= a * (1 + 1e-9))[0]
    C = np.linalg.inv(res.schur)[np.ix_(d, d)]
    return 0.5 * (C + C.T), rho[d]


def flat_punch(E, nu, thick, a, n_in=N_IN, ratio=RATIO, half_width=HALF_WIDTH_M, depth=DEPTH_M, patch=PATCH_M,
               radius_m=1.0) -> FemResult:
    """:func:`press` on concentric spheres of ``radius_m`` (1 m: flat within 0.1 mm over the block,
    the closed forms' half-space), layers of thicknesses ``thick`` (m) from the top, the last one
    continuing to ``depth``; a quarter block by symmetry."""
    thick = list(thick)
    thick[-1] = max(thick[-1], depth)
    return press(sphere_boundaries(radius_m, thick), np.zeros(3), E, nu, a, n_in, ratio, half_width, depth, patch,
                 quarter=True)


def tissue_press(tissue, first: int, E, nu, a, point=None, **kw) -> FemResult:
    """:func:`press` on ``tissue``'s SH boundaries from layer ``first`` down (its top boundary's
    point toward ``point``, default the acupoint at the origin)."""
    bnd = sh_boundaries(tissue.coeffs, tissue.centre, first)
    p = np.zeros(3) if point is None else np.asarray(point, float)
    d = p - tissue.centre
    d /= np.linalg.norm(d)
    r0 = float(bnd.radius(0, d[None, :])[0])
    return press(bnd, tissue.centre + r0 * d, E, nu, a, **kw)


def sneddon(E, nu, a) -> float:
    """Sneddon's flat punch stiffness on a half-space, 2 a E / (1 - nu^2) (N/m)."""
    return 2.0 * a * E / (1.0 - nu * nu)

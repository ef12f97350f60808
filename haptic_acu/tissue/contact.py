"""Frictionless contact of a rigid tip with a precomputed surface compliance, the contact set solved
at the servo's rate by low-rank updates of its capacitance matrix (James & Pai 1999, 2001;
docs/model.md section 12.6).

The surface under the tip is ``m`` nodes (the FEM's condensed surface nodes, the BEM's elements)
whose inward normal displacements ``w`` answer normal nodal forces ``f`` through a symmetric
positive definite compliance matrix, ``w = C f`` (precomputed once per parameter set: the inverse
of the FEM's Schur complement, or the BEM's Green's functions). The tip, its apex ``dep`` below the
rest surface, would put node ``i`` at the inward displacement ``g_i = dep - h_i``, ``h_i`` the
tip's height above its apex over that node. Signorini's conditions pick the contact set ``A``:

    f_i >= 0,   w_i >= g_i,   f_i (w_i - g_i) = 0,

so on ``A`` the nodes sit on the tip, ``C_AA f_A = g_A``, and the force on the tip is the sum of
``f_A``. The inverse ``P = C_AA^-1`` is the contact set's capacitance matrix (James & Pai's name);
the servo keeps it between ticks and, when nodes enter or leave the set, changes it by bordering,
a rank-one update per node (the Sherman-Morrison-Woodbury identity on a principal submatrix),
``O(|A|^2)`` per node instead of a new ``O(|A|^3)`` factorisation. A tick starts from the last
tick's set (from the precomputed capacitance of the whole disc when a tip that reaches every node
touches), and runs the active-set iteration (drop the most negative force, add the most
penetrated node) until Signorini's conditions hold.

Everything here is compiled without the GIL or reference counting; the arrays are the servo's
(``Model.ct_c`` etc.) or a test's.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from ..base.config import TIP_SHAPES  # noqa: F401 (model.tip_shape's values)


def tip_heights(rho, a: float, shape: str) -> np.ndarray:
    """The tip's height above its apex (m) at lateral distances ``rho`` (m) from its axis, for a tip
    of radius ``a``: 0 for the flat end (Sneddon's punch), ``a - sqrt(a^2 - rho^2)`` for a
    hemispherical end."""
    rho = np.asarray(rho, float)
    if shape == "flat":
        return np.zeros_like(rho)
    if shape == "hemisphere":
        return a - np.sqrt(np.maximum(a * a - rho * rho, 0.0))
    raise ValueError(f"unknown tip shape {shape!r}")


class Disc(NamedTuple):
    """The contact discs' precomputed tables (the servo's ``Model.ct_c``, ``ct_ref``, ``ct_h``)."""

    c: np.ndarray  # (layers * nodes, nodes) each disc's compliance (m/N), layer k's from row r0
    ref: np.ndarray  # (layers * nodes, nodes) its inverse: the whole disc's capacitance matrix (N/m)
    h: np.ndarray  # (layers, nodes) the tip's height above its apex over each node (m)


class Scratch(NamedTuple):
    """The contact set between ticks and the solve's scratch (the servo's ``State.ct_p``, ``ct_f``,
    ``ct_i``)."""

    p: np.ndarray  # (nodes, nodes) the set's capacitance matrix
    f: np.ndarray  # (3, nodes) the forces on the set's nodes (N); scratch u, c
    i: np.ndarray  # (2, nodes) int64: the set's nodes; scratch flags


# ---- the capacitance matrix's rank-one changes ------------------------------------------------------

@nb.njit(cache=True, nogil=True, _nrt=False)
def cap_add(C, r0, P, act, n, j, u, c):
    """Node ``j`` joins the set ``act[:n]`` whose capacitance matrix is ``P[:n, :n]``
    (``(C_AA)^-1``, ``C``'s rows from ``r0``, ``C`` symmetric): bordering by the Schur complement
    ``s = C_jj - c^T P c`` (``c = C_Aj``, gathered into ``c``; ``u = P c``). Returns ``s`` (not
    positive: the node is already held by the others, nothing changed); ``act[n] = j`` when added.
    ``u``, ``c``: scratch of at least ``n``, holding ``P c`` and ``c`` on return."""
    row = r0 + j
    for q in range(n):
        c[q] = C[row, act[q]]
    s = C[row, j]
    for p in range(n):
        acc = 0.0
        for q in range(n):
            acc += P[p, q] * c[q]
        u[p] = acc
        s -= c[p] * acc
    if not s > 1e-12 * C[row, j]:
        return s
    inv = 1.0 / s
    for p in range(n):
        up = u[p] * inv
        for q in range(n):
            P[p, q] += up * u[q]
        P[p, n] = -up
        P[n, p] = -up
    P[n, n] = inv
    act[n] = j
    return s


@nb.njit(cache=True, nogil=True, _nrt=False)
def cap_remove(P, act, n, p):
    """The node at position ``p`` of ``act[:n]`` leaves: ``P <- P_rr - P_rp P_pr / P_pp`` on the
    rest, then the last node moves into position ``p``. Returns ``n - 1``."""
    piv = 1.0 / P[p, p]
    for i in range(n):
        if i == p:
            continue
        a = P[i, p] * piv
        for k in range(n):
            if k != p:
                P[i, k] -= a * P[p, k]
    last = n - 1
    if p != last:
        for i in range(n):
            P[p, i] = P[last, i]
        for i in range(n):
            P[i, p] = P[i, last]
        act[p] = act[last]
    return last


@nb.njit(cache=True, nogil=True, _nrt=False)
def cap_load(Cref, r0, m, P, act):
    """The whole disc's precomputed capacitance matrix (``Cref``'s rows from ``r0``) into ``P``.
    Returns ``m``."""
    for i in range(m):
        act[i] = i
        for k in range(m):
            P[i, k] = Cref[r0 + i, k]
    return m


# ---- one tick's contact ---------------------------------------------------------------------------

@nb.njit(cache=True, nogil=True, _nrt=False)
def contact_solve(disc, k, r0, m, dep, sc, n):
    """Signorini's contact of the tip ``dep`` below the rest surface (module docstring) on layer
    ``k``'s ``m`` nodes, whose compliance is ``disc.c[r0:r0+m, :m]`` (symmetric; ``disc.ref``: the
    capacitance of all ``m``; ``disc.h[k]``: the tip's heights over them), starting from the set
    ``sc.i[0][:n]`` with capacitance ``sc.p`` (:class:`Scratch`; ``sc.f[0]`` receives the forces
    on the set's nodes). The forces follow each rank-one change in O(|A|) (a node ``j`` joining:
    ``f_A -= u delta``, ``f_j = delta``, ``delta = (g_j - c^T f_A) / s``; node ``p`` leaving:
    ``f_r -= P_rp f_p / P_pp``). Returns (the set's new size, the force on the tip (N), rank-one
    changes made)."""
    C = disc.c
    Cref = disc.ref
    h = disc.h[k]
    P = sc.p
    act = sc.i[0]
    flag = sc.i[1]
    f = sc.f[0]
    u = sc.f[1]
    c = sc.f[2]
    if dep <= 0.0:
        return 0, 0.0, 0
    # from the last tick's set; from none, the whole disc's precomputed capacitance when the tip
    # reaches every node undeformed (a flat tip's first touch: no rank-one change at all)
    if n == 0:
        reach = 0
        for i in range(m):
            if dep - h[i] > 0.0:
                reach += 1
        if reach == m:
            n = cap_load(Cref, r0, m, P, act)
    for p in range(n):  # the forces that hold the set on the tip: f = P g
        acc = 0.0
        for q in range(n):
            acc += P[p, q] * (dep - h[act[q]])
        f[p] = acc
    for i in range(m):
        flag[i] = 0
    for p in range(n):
        flag[act[p]] = 1
    changes = 0
    tol = 1e-12 * dep
    for it in range(4 * m + 4):
        # a node pulling on the tip leaves (the most negative force first)
        fsum = 0.0
        worst = -1
        fmin = 0.0
        for p in range(n):
            fsum += abs(f[p])
            if f[p] < fmin:
                fmin = f[p]
                worst = p
        if worst >= 0 and fmin < -1e-12 * fsum:
            a = f[worst] / P[worst, worst]
            for p in range(n):
                f[p] -= P[p, worst] * a
            flag[act[worst]] = 0
            last = n - 1
            n = cap_remove(P, act, n, worst)
            f[worst] = f[last]
            changes += 1
            continue
        # else the node the tip would push through the deepest joins (w_i = C_iA f_A < g_i)
        best = -1
        vmax = tol
        for i in range(m):
            if flag[i] == 1:
                continue
            w = 0.0
            row = r0 + i
            for p in range(n):
                w += C[row, act[p]] * f[p]
            if dep - h[i] - w > vmax:
                vmax = dep - h[i] - w
                best = i
        if best < 0:
            break
        sj = cap_add(C, r0, P, act, n, best, u, c)
        if not sj > 1e-12 * C[r0 + best, best]:
            break
        delta = vmax / sj
        for p in range(n):
            f[p] -= u[p] * delta
        f[n] = delta
        flag[best] = 1
        n += 1
        changes += 1
    total = 0.0
    for p in range(n):
        total += f[p] if f[p] > 0.0 else 0.0
    return n, total, changes


def pack(discs, layers: int, a: float, shape: str):
    """The servo's contact tables from per-layer ``(C, rho)`` (compliance, the nodes' lateral
    distances): ``(ct_c, ct_ref, ct_h, ct_n)``, layer k's block from row ``k * nodes``."""
    nodes = max(len(r) for _, r in discs)
    ct_c = np.zeros((layers * nodes, nodes))
    ct_ref = np.zeros((layers * nodes, nodes))
    ct_h = np.zeros((layers, nodes))
    ct_n = np.zeros(layers, np.int64)
    for k, (C, rho) in enumerate(discs):
        q = len(rho)
        ct_c[k * nodes:k * nodes + q, :q] = C
        R = np.linalg.inv(C)
        ct_ref[k * nodes:k * nodes + q, :q] = 0.5 * (R + R.T)
        ct_h[k, :q] = tip_heights(rho, a, shape)
        ct_n[k] = q
    return ct_c, ct_ref, ct_h, ct_n


def press_curve(C, h, depths):
    """The compiled contact solve along ``depths`` (m), warm-started tick to tick as in the servo:
    (forces (N), contact set sizes, rank-one changes per depth). For tests and figures."""
    C = np.ascontiguousarray(C, float)
    m = C.shape[0]
    disc = Disc(C, np.ascontiguousarray(np.linalg.inv(C)), np.ascontiguousarray(np.reshape(h, (1, m)), float))
    sc = Scratch(np.zeros((m, m)), np.zeros((3, m)), np.zeros((2, m), np.int64))
    n = 0
    F, N, K = [], [], []
    for d in depths:
        n, tot, ch = contact_solve(disc, 0, 0, m, float(d), sc, n)
        F.append(tot)
        N.append(n)
        K.append(ch)
    return np.array(F), np.array(N), np.array(K)


def hertz(E: float, nu: float, R: float, d) -> np.ndarray:
    """Hertz's sphere of radius ``R`` pressed ``d`` into a half-space: F = 4/3 E* R^1/2 d^3/2,
    E* = E / (1 - nu^2) (N)."""
    return 4.0 / 3.0 * E / (1.0 - nu * nu) * math.sqrt(R) * np.asarray(d, float) ** 1.5

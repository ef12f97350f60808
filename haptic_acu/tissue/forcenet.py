"""The mass-spring force net (the paper's section 3.2, Fig. 1-2, eq. 6; MODEL.md section 2).

A net is built on a layer's surface when the needle first touches it, centred on the contact point
N1. Particles sit on a hexagonal (triangular) lattice: ring 1 is N1, ring j >= 2 holds 6(j-1)
particles at spacing L, w rings in all (1 + 3w(w-1) particles), mapped onto the curved SH surface by
radial projection from the tangent plane. Neighbours are joined by surface springs of stiffness
``ks`` whose rest length is (1 - pretension) times the spacing: the net is a taut membrane whose
tension, stretched by the dent, makes the response stiffen with depth. Each particle also has a
"vertical" virtual spring of stiffness K acting along the net's axis n (the surface normal at N1;
Fig. 2 draws them parallel).

The mechanics are solved on the net's reference lattice in the tangent plane at N1 (``Xf``): the
patch is treated as locally flat (its sagitta is (wL)^2/2R, about 1.4 mm for the skin net on the
70 mm limb), and each particle's displacement ``u = xf - X0f`` is carried onto its rest point on the
curved SH surface (``x = X0 + u``) for rendering, springback and the SH radius. Solving the membrane
on the curved patch instead makes its tension lift the outer ring (the chords to ring w-1 point
outward on a dome), so ring w's deflection changes sign with depth and cannot signal puncture.

Boundary conditions: N1 is held at the needle tip; ring w (the outermost) is held laterally and free
along n; every other particle is free in 3D. At static equilibrium, summing the forces on the whole
net and projecting on n (surface springs and the preload sum to zero, ring w's constraint forces are
perpendicular to n) gives exactly eq. 6:

    F . n = K * sum_i dZ_i = K dZ_1 + K * sum_{j=2..w} 6(j-1) mean(dZ_j),     dZ_i = -(x_i - X0_i) . n

where F is the net's reaction on the needle at N1. The solver is a Gauss-Seidel sweep of per-particle
Newton steps (3x3 for free particles, 1x1 along n for ring w), alternating direction, warm-started
from the previous tick: a static solver, so it cannot ring; steps are limited to L/4, so it cannot
explode. The surface breaks (puncture) when ring w's mean deflection passes the layer's threshold.
By default the servo does not sweep at all: it reads the static response these sweeps converge to,
tabulated once per parameter set (:mod:`haptic_acu.tissue.netresponse`, ``solver.servo_net = "table"``).

All kernels are pure, numba-compiled (``nogil``, ``cache``), allocation-free, and take named inputs:
a net's arrays (:class:`NetArrays`), its lattice (:class:`Topology`), its constants (:class:`Springs`)
and, to build one, the surface (:class:`Surface`); the servo passes views into its state
(:func:`haptic_acu.servo.step.net_views`), :class:`Net` its own arrays.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numba as nb
import numpy as np

from . import shf

# Axial hexagonal-lattice neighbour offsets.
_HEX_DIRS = ((1, 0), (0, 1), (-1, 1), (-1, 0), (0, -1), (1, -1))


def n_particles(w: int) -> int:
    """Particles in a net of w rings: 1 + 3w(w-1)."""
    return 1 + 3 * w * (w - 1)


@dataclass(frozen=True)
class Lattice:
    """The topology of a w-ring hexagonal net, ordered ring by ring (ring 1 = index 0)."""

    w: int
    ring: np.ndarray  # (n,) ring number, 1-based
    plane: np.ndarray  # (n, 2) position in units of L in the tangent plane
    nbr: np.ndarray  # (n, 6) neighbour indices, -1 where absent


def lattice(w: int) -> Lattice:
    """Hexagonal lattice of w rings (ring j = hex distance j-1 from the centre), ring by ring,
    counter-clockwise within a ring."""
    cells = []
    for q in range(-(w - 1), w):
        for r in range(-(w - 1), w):
            d = max(abs(q), abs(r), abs(q + r))
            if d <= w - 1:
                ang = math.atan2(r * math.sqrt(3) / 2, q + r / 2)
                cells.append((d, round(ang % (2 * math.pi), 12), q, r))
    cells.sort()
    index = {(q, r): i for i, (_, _, q, r) in enumerate(cells)}
    n = len(cells)
    ring = np.array([d + 1 for d, _, _, _ in cells], dtype=np.int64)
    plane = np.array([[q + r / 2.0, r * math.sqrt(3) / 2.0] for _, _, q, r in cells])
    nbr = -np.ones((n, 6), dtype=np.int64)
    for i, (_, _, q, r) in enumerate(cells):
        for k, (dq, dr) in enumerate(_HEX_DIRS):
            nbr[i, k] = index.get((q + dq, r + dr), -1)
    return Lattice(w, ring, plane, nbr)


class NetArrays(NamedTuple):
    """One net's arrays as the kernels take them (views; the first three have the force net's n rows)."""

    xf: np.ndarray  # (n, 3) particles on the flat reference lattice (the mechanics)
    X0f: np.ndarray  # (n, 3) their rest positions
    X0: np.ndarray  # (n_all, 3) rest positions on the curved SH surface (force net + margin)
    x: np.ndarray  # (n_all, 3) current positions on the curved surface
    rest_len: np.ndarray  # (n, 6) rest length of the spring to each neighbour (0: none)
    axis: np.ndarray  # (3,) outward normal at N1: the virtual springs' direction


class Topology(NamedTuple):
    """A lattice's arrays as the kernels take them (:class:`Lattice`, rows of force net + margin)."""

    nbr: np.ndarray  # (n_all, 6) neighbour indices, -1 where absent
    ring: np.ndarray  # (n_all,) ring number, 1-based
    plane: np.ndarray  # (n_all, 2) position in units of L in the tangent plane


class Springs(NamedTuple):
    """One layer's net constants as the kernels take them (SI)."""

    w: int  # rings
    kv: float  # K, the virtual springs (N/m)
    ks: float  # ks, the surface springs (N/m)
    spacing: float  # L (m)
    pretension: float  # rest length = (1 - pretension) * L


class Surface(NamedTuple):
    """A radial SH surface as :func:`build_net` projects onto it."""

    coeffs: np.ndarray  # SH coefficients of the surface
    lmax: int
    centre: np.ndarray  # (3,)


@dataclass
class NetParams:
    """One layer's net parameters in SI."""

    w: int
    spacing_m: float  # L
    k_virtual: float  # K, N/m
    k_surface: float  # ks, N/m
    pretension: float  # rest length = (1 - pretension) * L
    threshold_m: float  # ring-w mean deflection at puncture

    def springs(self) -> Springs:
        return Springs(int(self.w), float(self.k_virtual), float(self.k_surface), float(self.spacing_m),
                       float(self.pretension))

    @classmethod
    def from_layer(cls, layer) -> "NetParams":
        return cls(layer.rings, layer.spring_length_mm * 1e-3, layer.k_virtual_n_per_mm * 1e3,
                   layer.k_surface_n_per_mm * 1e3, layer.pretension, layer.puncture_threshold_um * 1e-6)


@dataclass
class Net:
    """A force net's state: preallocated once per layer, rebuilt in place at each new contact.

    ``xf``/``X0f``: current and rest positions of the force-net particles on the flat reference
    lattice (the mechanics). ``x``/``X0``: current and rest positions on the curved SH surface;
    particles ``[0, n)`` are the force net, ``[n, n_all)`` the undeformed margin rings that only
    springback's shape matching uses.
    """

    params: NetParams
    lat: Lattice  # lattice of w + margin rings; its first n particles are the force net
    n: int
    x: np.ndarray = field(init=False)
    X0: np.ndarray = field(init=False)
    xf: np.ndarray = field(init=False)
    X0f: np.ndarray = field(init=False)
    rest_len: np.ndarray = field(init=False)
    axis: np.ndarray = field(init=False)  # outward normal at N1 (the virtual springs' direction)

    def __post_init__(self):
        n_all = self.lat.ring.size
        self.x = np.zeros((n_all, 3))
        self.X0 = np.zeros((n_all, 3))
        self.xf = np.zeros((self.n, 3))
        self.X0f = np.zeros((self.n, 3))
        self.rest_len = np.zeros((self.n, 6))
        self.axis = np.array([0.0, 0.0, 1.0])

    @classmethod
    def allocate(cls, params: NetParams, margin_rings: int = 0) -> "Net":
        return cls(params, lattice(params.w + margin_rings), n_particles(params.w))

    # -- convenience wrappers over the kernels (tests, tools; the servo calls the kernels) --------
    def arrays(self) -> NetArrays:
        return NetArrays(self.xf, self.X0f, self.X0, self.x, self.rest_len, self.axis)

    def topology(self) -> Topology:
        return Topology(self.lat.nbr, self.lat.ring, self.lat.plane)

    def build(self, coeffs, lmax, centre, contact, normal) -> None:
        build_net(Surface(coeffs, int(lmax), centre), self.arrays(), self.topology(), self.params.springs(),
                  np.asarray(contact, float), np.asarray(normal, float))

    def relax(self, sweeps: int, first: int = 0) -> float:
        big = 0.0
        net, topo, springs = self.arrays(), self.topology(), self.params.springs()
        for s in range(sweeps):
            big = relax(net, topo, springs, (first + s) % 2)
        return big

    def solve(self, tip, sweeps: int = 0, tol_m: float = 1e-10, max_sweeps: int = 20000) -> int:
        """Hold N1 at ``tip``; run ``sweeps`` sweeps, or (sweeps=0) sweep to a static solution.
        Returns the sweeps run."""
        self.xf[0] = tip
        if sweeps > 0:
            self.relax(sweeps)
            done = sweeps
        else:
            done = max_sweeps
            for s in range(max_sweeps):
                if self.relax(1, s) < tol_m:
                    done = s + 1
                    break
        self.sync()
        return done

    def sync(self) -> None:
        """Carry the flat-lattice displacements onto the curved surface (``x``)."""
        sync_curved(self.arrays())

    def reaction(self) -> np.ndarray:
        """The net's force on the needle at N1 (N, 3D)."""
        out = np.zeros(3)
        force_on(0, self.arrays(), self.topology(), self.params.springs(), out)
        return out

    def deflection(self) -> np.ndarray:
        """dZ_i = -(x_i - X0_i) . n for the force-net particles (m; positive pushed in)."""
        return -((self.xf - self.X0f) @ self.axis)

    def ring_mean_deflection(self) -> np.ndarray:
        """Mean dZ of each ring 1..w (index j-1)."""
        dz = self.deflection()
        ring = self.lat.ring[: self.n]
        return np.array([dz[ring == j].mean() for j in range(1, self.params.w + 1)])

    def eq6_force(self) -> float:
        """Eq. 6 evaluated from the ring-mean deflections: K dZ_1 + K sum_j 6(j-1) dZ_j."""
        m = self.ring_mean_deflection()
        j = np.arange(2, self.params.w + 1)
        return self.params.k_virtual * (m[0] + np.sum(6 * (j - 1) * m[1:]))


@nb.njit(cache=True, nogil=True, _nrt=False)
def tangent_frame(axis):
    """The net's tangent frame (e1, e2) at unit normal ``axis``: e1 = axis x (x, or y near the x
    axis), normalised; e2 = axis x e1. Returns e1x, e1y, e1z, e2x, e2y, e2z."""
    if abs(axis[0]) < 0.9:
        ax, ay, az = 1.0, 0.0, 0.0
    else:
        ax, ay, az = 0.0, 1.0, 0.0
    e1x = axis[1] * az - axis[2] * ay
    e1y = axis[2] * ax - axis[0] * az
    e1z = axis[0] * ay - axis[1] * ax
    m1 = math.sqrt(e1x * e1x + e1y * e1y + e1z * e1z)
    e1x /= m1
    e1y /= m1
    e1z /= m1
    e2x = axis[1] * e1z - axis[2] * e1y
    e2y = axis[2] * e1x - axis[0] * e1z
    e2z = axis[0] * e1y - axis[1] * e1x
    return e1x, e1y, e1z, e2x, e2y, e2z


@nb.njit(cache=True, nogil=True, _nrt=False)
def build_net(surf, net, topo, springs, contact, normal):
    """Lay the lattice ``topo`` around ``contact`` with outward ``normal``: the flat reference lattice
    in the tangent plane, and its radial projection onto the SH surface ``surf`` (:class:`Surface`),
    into ``net`` (:class:`NetArrays`). Allocation-free."""
    X0, x, X0f, xf, rest_len, axis = net.X0, net.x, net.X0f, net.xf, net.rest_len, net.axis
    coeffs, lmax, centre = surf.coeffs, surf.lmax, surf.centre
    plane, nbr, n = topo.plane, topo.nbr, xf.shape[0]
    spacing, pretension = springs.spacing, springs.pretension
    nn = math.sqrt(normal[0] ** 2 + normal[1] ** 2 + normal[2] ** 2)
    for k in range(3):
        axis[k] = normal[k] / nn
    e1x, e1y, e1z, e2x, e2y, e2z = tangent_frame(axis)
    for i in range(plane.shape[0]):
        a = plane[i, 0] * spacing
        b = plane[i, 1] * spacing
        fx = contact[0] + a * e1x + b * e2x
        fy = contact[1] + a * e1y + b * e2y
        fz = contact[2] + a * e1z + b * e2z
        if i < n:
            X0f[i, 0] = fx
            X0f[i, 1] = fy
            X0f[i, 2] = fz
            xf[i, 0] = fx
            xf[i, 1] = fy
            xf[i, 2] = fz
        if i == 0:
            for k in range(3):
                X0[0, k] = contact[k]
        else:
            theta, phi, rho = shf.direction_of(fx, fy, fz, centre[0], centre[1], centre[2])
            r = shf.eval_point(coeffs, lmax, theta, phi)
            X0[i, 0] = centre[0] + (fx - centre[0]) / rho * r
            X0[i, 1] = centre[1] + (fy - centre[1]) / rho * r
            X0[i, 2] = centre[2] + (fz - centre[2]) / rho * r
        for k in range(3):
            x[i, k] = X0[i, k]
    for i in range(n):
        for k in range(6):
            j = nbr[i, k]
            rest_len[i, k] = (1.0 - pretension) * spacing if (j >= 0 and j < n) else 0.0


@nb.njit(cache=True, nogil=True, _nrt=False)
def sync_curved(net):
    """x_i = X0_i + (xf_i - X0f_i) for the force-net particles of ``net`` (:class:`NetArrays`)."""
    x, X0, xf, X0f = net.x, net.X0, net.xf, net.X0f
    for i in range(xf.shape[0]):
        for k in range(3):
            x[i, k] = X0[i, k] + xf[i, k] - X0f[i, k]


@nb.njit(cache=True, nogil=True, _nrt=False)
def force_on(i, net, topo, springs, out):
    """Total net force on particle i (surface springs + virtual spring) into ``out[3]``."""
    xf, X0f, rest_len, axis, nbr = net.xf, net.X0f, net.rest_len, net.axis, topo.nbr
    kv, ks = springs.kv, springs.ks
    d = (xf[i, 0] - X0f[i, 0]) * axis[0] + (xf[i, 1] - X0f[i, 1]) * axis[1] + (xf[i, 2] - X0f[i, 2]) * axis[2]
    fx = -kv * d * axis[0]
    fy = -kv * d * axis[1]
    fz = -kv * d * axis[2]
    n = xf.shape[0]
    for k in range(6):
        j = nbr[i, k]
        if j >= 0 and j < n:
            dx = xf[j, 0] - xf[i, 0]
            dy = xf[j, 1] - xf[i, 1]
            dz = xf[j, 2] - xf[i, 2]
            ln = math.sqrt(dx * dx + dy * dy + dz * dz)
            if ln > 0.0:
                s = ks * (ln - rest_len[i, k]) / ln
                fx += s * dx
                fy += s * dy
                fz += s * dz
    out[0] = fx
    out[1] = fy
    out[2] = fz


@nb.njit(cache=True, nogil=True, _nrt=False)
def _relax_one(i, net, topo, springs, max_step):
    """One particle's Newton step (its largest component limited to ``max_step``); returns its size."""
    xf, X0f, rest_len, axis, nbr = net.xf, net.X0f, net.rest_len, net.axis, topo.nbr
    kv, ks = springs.kv, springs.ks
    n = xf.shape[0]
    ax0 = axis[0]
    ax1 = axis[1]
    ax2 = axis[2]
    d = (xf[i, 0] - X0f[i, 0]) * ax0 + (xf[i, 1] - X0f[i, 1]) * ax1 + (xf[i, 2] - X0f[i, 2]) * ax2
    fx = -kv * d * ax0
    fy = -kv * d * ax1
    fz = -kv * d * ax2
    # Tangent stiffness H (symmetric 3x3): kv n n^T + sum of spring tangents.
    h00 = kv * ax0 * ax0
    h01 = kv * ax0 * ax1
    h02 = kv * ax0 * ax2
    h11 = kv * ax1 * ax1
    h12 = kv * ax1 * ax2
    h22 = kv * ax2 * ax2
    for k in range(6):
        j = nbr[i, k]
        if j >= 0 and j < n:
            dx = xf[j, 0] - xf[i, 0]
            dy = xf[j, 1] - xf[i, 1]
            dz = xf[j, 2] - xf[i, 2]
            l2 = dx * dx + dy * dy + dz * dz
            if l2 <= 0.0:
                continue
            inv = 1.0 / math.sqrt(l2)
            s = ks * (1.0 - rest_len[i, k] * inv)  # tension / length
            fx += s * dx
            fy += s * dy
            fz += s * dz
            geo = s if s > 0.0 else 0.0  # a compressed spring adds no lateral stiffness (keeps H positive)
            # H += geo*I + (ks - geo) u u^T with u = d/|d|: (ks - geo)/|d|^2 d d^T
            c = (ks - geo) * inv * inv
            h00 += geo + c * dx * dx
            h01 += c * dx * dy
            h02 += c * dx * dz
            h11 += geo + c * dy * dy
            h12 += c * dy * dz
            h22 += geo + c * dz * dz
    if topo.ring[i] == springs.w:
        # Outer ring: held laterally, free along the axis: a 1D Newton step along n.
        hn = (ax0 * (h00 * ax0 + h01 * ax1 + h02 * ax2) + ax1 * (h01 * ax0 + h11 * ax1 + h12 * ax2)
              + ax2 * (h02 * ax0 + h12 * ax1 + h22 * ax2))
        if not hn > 0.0:
            return 0.0
        t = (fx * ax0 + fy * ax1 + fz * ax2) / hn
        if t > max_step:
            t = max_step
        elif t < -max_step:
            t = -max_step
        xf[i, 0] += t * ax0
        xf[i, 1] += t * ax1
        xf[i, 2] += t * ax2
        return abs(t)
    # Free particle: solve H dx = f (adjugate of the symmetric 3x3).
    c00 = h11 * h22 - h12 * h12
    c01 = h02 * h12 - h01 * h22
    c02 = h01 * h12 - h02 * h11
    det = h00 * c00 + h01 * c01 + h02 * c02
    scale = h00 + h11 + h22
    if not det > 1e-12 * scale * scale * scale:
        return 0.0
    c11 = h00 * h22 - h02 * h02
    c12 = h01 * h02 - h00 * h12
    c22 = h00 * h11 - h01 * h01
    sx = (c00 * fx + c01 * fy + c02 * fz) / det
    sy = (c01 * fx + c11 * fy + c12 * fz) / det
    sz = (c02 * fx + c12 * fy + c22 * fz) / det
    m = math.sqrt(sx * sx + sy * sy + sz * sz)
    if m > max_step:
        sx *= max_step / m
        sy *= max_step / m
        sz *= max_step / m
        m = max_step
    xf[i, 0] += sx
    xf[i, 1] += sy
    xf[i, 2] += sz
    return m


@nb.njit(cache=True, nogil=True, _nrt=False)
def relax(net, topo, springs, backward):
    """One Gauss-Seidel-Newton sweep over particles 1..n-1 of ``net`` (:class:`NetArrays`; lattice
    ``topo``, constants ``springs``), outward, or inward if ``backward``.

    N1 (particle 0) is not moved: the caller holds it at the needle tip. Returns the largest step (m).
    """
    n = net.xf.shape[0]
    max_step = 0.25 * springs.spacing
    biggest = 0.0
    for s in range(1, n):
        i = n - s if backward else s
        m = _relax_one(i, net, topo, springs, max_step)
        if m > biggest:
            biggest = m
    return biggest


@nb.njit(cache=True, nogil=True, _nrt=False)
def ring_w_mean_deflection(net, topo, w):
    """Mean dZ = -(x - X0) . n over ring w of ``net`` (m)."""
    xf, X0f, axis, ring, n = net.xf, net.X0f, net.axis, topo.ring, net.xf.shape[0]
    total = 0.0
    count = 0
    for i in range(n):
        if ring[i] == w:
            total -= (xf[i, 0] - X0f[i, 0]) * axis[0] + (xf[i, 1] - X0f[i, 1]) * axis[1] + (xf[i, 2] - X0f[i, 2]) * axis[2]
            count += 1
    return total / count


@nb.njit(cache=True, nogil=True)
def dent_on_grid(theta, phi, centre, X0, x, n, support_m, out):
    """Radial dent of the surface at directions (theta, phi) from the net particles (m, into ``out``).

    Each particle's radial deflection |X0_i - c| - |x_i - c| is its dent (the paper's tie between
    dZ and the SH radius); between particles it is interpolated with compactly supported Shepard
    weights of radius ``support_m``; away from the net the dent is 0. Runs in the visual loop.
    """
    u = np.empty((n, 3))
    r0 = np.empty(n)
    dr = np.empty(n)
    cx = 0.0
    cy = 0.0
    cz = 0.0
    for i in range(n):
        rx = X0[i, 0] - centre[0]
        ry = X0[i, 1] - centre[1]
        rz = X0[i, 2] - centre[2]
        r0[i] = math.sqrt(rx * rx + ry * ry + rz * rz)
        u[i, 0] = rx / r0[i]
        u[i, 1] = ry / r0[i]
        u[i, 2] = rz / r0[i]
        px = x[i, 0] - centre[0]
        py = x[i, 1] - centre[1]
        pz = x[i, 2] - centre[2]
        dr[i] = r0[i] - math.sqrt(px * px + py * py + pz * pz)
        cx += u[i, 0]
        cy += u[i, 1]
        cz += u[i, 2]
    cm = math.sqrt(cx * cx + cy * cy + cz * cz)
    cx /= cm
    cy /= cm
    cz /= cm
    # angular radius of the net's cap, plus the support
    cap = 0.0
    rmin = 1e300
    for i in range(n):
        d = cx * u[i, 0] + cy * u[i, 1] + cz * u[i, 2]
        a = math.acos(min(1.0, max(-1.0, d)))
        if a > cap:
            cap = a
        if r0[i] < rmin:
            rmin = r0[i]
    cos_cap = math.cos(min(math.pi, cap + 1.5 * support_m / rmin))
    for g in range(theta.shape[0]):
        st = math.sin(theta[g])
        ux = st * math.cos(phi[g])
        uy = st * math.sin(phi[g])
        uz = math.cos(theta[g])
        out[g] = 0.0
        if ux * cx + uy * cy + uz * cz < cos_cap:
            continue
        wsum = 0.0
        acc = 0.0
        for i in range(n):
            # distance on the surface ~ chord between unit directions times the radius
            ddx = ux - u[i, 0]
            ddy = uy - u[i, 1]
            ddz = uz - u[i, 2]
            d2 = (ddx * ddx + ddy * ddy + ddz * ddz) * r0[i] * r0[i]
            if d2 < support_m * support_m:
                q = 1.0 - d2 / (support_m * support_m)
                wgt = q * q
                acc += wgt * dr[i]
                wsum += wgt
        if wsum > 0.0:
            out[g] = acc / wsum

"""The servo step written plainly with NumPy and SciPy: the peer the compiled kernel is measured against.

This is what a Python developer would write first for the layered needle model of
:mod:`haptic_acu.servo.step` (MODEL.md sections 1-3), vectorised wherever the maths allows, and kept
independent of the compiled code (it shares only the fitted tissue coefficients and the config):

* collision: the real orthonormal SH basis (Condon-Shortley phase, column ``l*l + l + m``) at the
  tip's direction from SciPy's complex ``sph_harm_y`` (Y_l0 = Re Y_l^0, Y_lm = sqrt(2) Re Y_l^m,
  Y_l-m = sqrt(2) Im Y_l^m), then one matrix-vector product for the four boundary radii;
* the force net: its own hexagonal lattice, and a *multicolour* Gauss-Seidel-Newton sweep: the
  triangular lattice is 3-coloured by (q - r) mod 3 (no two neighbours share a colour), so every
  particle of one colour takes its per-particle Newton step at once, as batched 3x3 solves
  (``numpy.linalg.solve``); ring w moves along the axis only, N1 is held at the tip, steps are
  limited to L/4. It visits particles in another order than the compiled lexicographic sweep, so
  the two agree exactly only at the static solution (both converge to the same equilibrium);
* with ``solver.servo_net = "table"`` (the default), the net's static response is read from the
  layer's tabulated response (:mod:`haptic_acu.tissue.netresponse`: the same F, R and displacement-field
  arrays the compiled step reads) through SciPy's ``RegularGridInterpolator`` (linear, extrapolating
  past the last row); the tabulated shape is laid onto the net (one matrix product, ``laid_shape``)
  only for rendering, as in the compiled model: what a NumPy developer would write for that
  design; with ``"sweeps"`` the multicolour sweeps above run instead;
* an intact surface's force is a function of the tip's position alone: the net's response with N1
  at the tip's radial depth d below the layer's rest surface and no lateral offset, along grad(-d)
  (central differences of d along the scene axes, not the compiled step's tangent-plane
  differences); the net is re-centred under the sliding tip only to be drawn there;
* puncture at the ring-w mean deflection threshold (read at the same depth; times the speed
  factor); the needle's axis (the device's, else the direction of travel since the skin's first
  touch) and its entry and boundary crossings (a scan and SciPy's ``brentq`` along the line); the compression offset; after a puncture, on the physical
  needle length per broken layer, either Table 1's damping (``needle.mechanics = "table1"``) or
  cutting at the crack front plus a stick-point Karnopp friction and viscous friction (docs/model.md
  s9); the lateral constraint as stiff as the shaft is held, the bone wall, the non-finite fault
  latch and the force clamp, as in the compiled step.

Left out, because no benchmark path exercises them and they do not change what one pressing tick
costs: tracks (re-entry through an earlier pass; the one insertion's own cut range is the deepest
point reached), the grasp multiplier (1), the two net slots per layer and their hand-over
to springback, and the undeformed margin rings (springback only). One net per layer; a model is
meant for one insertion from a fresh state.

SI throughout: metres, newtons, seconds.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.interpolate import RegularGridInterpolator
from scipy.optimize import brentq
from scipy.special import sph_harm_y

UNTOUCHED, PRESSING, PUNCTURED = 0, 1, 2
_HEX = np.array([(1, 0), (0, 1), (-1, 1), (-1, 0), (0, -1), (1, -1)])


class SHBasis:
    """Real orthonormal SH basis up to ``lmax`` from SciPy's complex harmonics."""

    def __init__(self, lmax: int):
        self.lmax = int(lmax)
        ls, ms = [], []
        for l in range(self.lmax + 1):
            for m in range(l + 1):
                ls.append(l)
                ms.append(m)
        self.l = np.array(ls)
        self.m = np.array(ms)
        self.k = (self.lmax + 1) ** 2
        self.col_pos = self.l * self.l + self.l + self.m  # Y_lm, m >= 0
        pos = self.m > 0
        self.col_neg = (self.l * self.l + self.l - self.m)[pos]  # Y_l-m
        self._pos = pos
        self.scale = np.where(pos, math.sqrt(2.0), 1.0)

    def rows(self, theta, phi) -> np.ndarray:
        """Basis at directions (theta, phi) (1-D arrays, radians): shape (n, (lmax+1)^2)."""
        theta = np.atleast_1d(np.asarray(theta, dtype=float))
        phi = np.atleast_1d(np.asarray(phi, dtype=float))
        y = sph_harm_y(self.l[None, :], self.m[None, :], theta[:, None], phi[:, None])
        out = np.empty((theta.size, self.k))
        out[:, self.col_pos] = self.scale * y.real
        out[:, self.col_neg] = math.sqrt(2.0) * y.imag[:, self._pos]
        return out


def directions(points, centre):
    """(theta, phi, rho) of points (n, 3) seen from ``centre``."""
    d = np.atleast_2d(points) - centre
    rho = np.sqrt(np.einsum("ij,ij->i", d, d))
    theta = np.arccos(np.clip(d[:, 2] / rho, -1.0, 1.0))
    phi = np.arctan2(d[:, 1], d[:, 0])
    return theta, phi, rho


class HexNet:
    """Topology of a w-ring hexagonal net (ring 1 = the centre, index 0) and its 3-colouring."""

    def __init__(self, w: int):
        q, r = np.meshgrid(np.arange(-(w - 1), w), np.arange(-(w - 1), w), indexing="ij")
        q = q.ravel()
        r = r.ravel()
        dist = np.max(np.abs(np.stack([q, r, q + r])), axis=0)
        keep = dist <= w - 1
        q, r, dist = q[keep], r[keep], dist[keep]
        order = np.lexsort((np.abs(q) + np.abs(r), dist))  # centre first
        q, r, dist = q[order], r[order], dist[order]
        self.w = w
        self.n = q.size
        self.ring = dist + 1
        self.plane = np.column_stack([q + 0.5 * r, r * math.sqrt(3.0) / 2.0])  # units of L
        lookup = -np.ones((2 * w + 1, 2 * w + 1), dtype=np.int64)
        lookup[q + w, r + w] = np.arange(self.n)
        nq = q[:, None] + _HEX[None, :, 0]
        nr = r[:, None] + _HEX[None, :, 1]
        self.nbr = lookup[nq + w, nr + w]  # (n, 6), -1 where absent (the padding row/column is -1)
        colour = (q - r) % 3
        self.colours = [np.nonzero((colour == c) & (np.arange(self.n) > 0))[0] for c in range(3)]
        self.outer = self.ring == w


class Net:
    """One layer's force net: flat reference lattice ``X0f`` and current positions ``xf`` (n, 3)."""

    def __init__(self, hexnet: HexNet, spacing, pretension):
        self.hex = hexnet
        self.L = spacing
        self.rest = np.where(hexnet.nbr >= 0, (1.0 - pretension) * spacing, 0.0)
        self.X0f = np.zeros((hexnet.n, 3))
        self.xf = np.zeros((hexnet.n, 3))
        self.X0 = np.zeros((hexnet.n, 3))  # rest positions on the curved surface (for rendering)
        self.axis = np.array([0.0, 0.0, 1.0])
        self.sweeps_done = 0


def tangent_frame(axis):
    """Two unit tangents (e1, e2) at a unit normal ``axis`` (e1 from x, or from y near the x axis)."""
    ref = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(axis, ref)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


class NumpyNeedle:
    """The layered needle model, one ``step(p, v)`` per servo tick, in NumPy/SciPy.

    ``tissue`` is a :class:`haptic_acu.tissue.body.Tissue` (coefficients and centre); ``cfg`` the config.
    After a step: ``force`` (N), ``states``, ``layer`` (-1 outside .. 3 bone), ``punctured_now``
    (layer broken this tick or -1), ``offset`` (compression, m), ``fault``.
    """

    def __init__(self, cfg, tissue):
        self.coeffs = np.asarray(tissue.coeffs, dtype=float)
        self.centre = np.asarray(tissue.centre, dtype=float)
        self.basis = SHBasis(tissue.lmax)
        self.layers = []
        for layer in cfg.layers:
            hexnet = HexNet(layer.rings)
            self.layers.append(dict(
                kv=layer.k_virtual_n_per_mm * 1e3, ks=layer.k_surface_n_per_mm * 1e3,
                L=layer.spring_length_mm * 1e-3, thresh=layer.puncture_threshold_um * 1e-6,
                d=layer.damping_n_s_per_m_per_mm * 1e3, thick=layer.thickness_mm * 1e-3,
                net=Net(hexnet, layer.spring_length_mm * 1e-3, layer.pretension)))
        self.damping = np.array([lay["d"] for lay in self.layers])
        nd = cfg.needle
        dmm = nd.diameter_mm
        self.table1 = nd.mechanics == "table1"
        self.cut = np.array([la.cutting_n_per_mm_diameter * dmm for la in cfg.layers])
        self.fc = np.array([la.coulomb_n_per_mm2 * dmm * 1e3 for la in cfg.layers])
        self.fs = self.fc * np.array([la.stiction_ratio for la in cfg.layers])
        self.b = np.array([la.viscous_n_s_per_m_per_mm2 * dmm * 1e3 for la in cfg.layers])
        self.k_stick = nd.stick_stiffness_n_per_mm * 1e3
        self.decay = math.exp(-1e-3 / nd.friction_relaxation_s) if nd.friction_relaxation_s > 0 else 1.0
        self.needle_len = nd.length_mm * 1e-3
        self.radius = 0.5e-3 * dmm
        self.lateral_on = bool(nd.lateral_constraint)
        self.k_lat = nd.lateral_stiffness_n_per_mm * 1e3
        self.k_bone = nd.bone_stiffness_n_per_mm * 1e3
        self.limit = cfg.safety.force_limit_n
        self.sweeps = int(cfg.solver.sweeps_per_tick)
        rp = cfg.rupture  # the threshold's speed dependence (docs/model.md section 2.2)
        self.rupture = (rp.high_speed_ratio, rp.speed_scale_mm_s * 1e-3, rp.reference_speed_mm_s * 1e-3)
        self.tables = None
        if cfg.solver.servo_net == "table":
            from haptic_acu.tissue.forcenet import NetParams, lattice
            from haptic_acu.tissue.netresponse import table_for

            tol = cfg.solver.static_tolerance_um * 1e-6
            self.tables = []
            for layer, lay in zip(cfg.layers, self.layers):
                t = table_for(NetParams.from_layer(layer), tol)
                nr, nc = t.F.shape
                grid = (np.linspace(0.0, 1.0, nr), np.arange(nc) * t.h)
                lay["table"] = dict(
                    F=RegularGridInterpolator(grid, t.F, bounds_error=False, fill_value=None),
                    R=RegularGridInterpolator(grid, t.R, bounds_error=False, fill_value=None),
                    D=t.D, h=t.h, rho2=t.rho_max ** 2)
                self.tables.append(t)
                # the table's field is in the package lattice's particle order; this net's order differs
                pkg = {tuple(np.round(xy * 4).astype(int)): i for i, xy in enumerate(lattice(layer.rings).plane)}
                perm = np.array([pkg[tuple(np.round(xy * 4).astype(int))] for xy in lay["net"].hex.plane])
                lay["table"]["D"] = np.ascontiguousarray(t.D[:, perm, :])
        self.states = [UNTOUCHED] * 3
        self.inserted = False
        self.fault = False
        self.offset = 0.0
        self.axis = np.array([0.0, 0.0, -1.0])
        self.entry = np.zeros(3)
        self.touch = np.zeros(3)
        self.bounds = np.zeros(4)
        self.anchor, self.mode, self.engaged, self.deepest = 0.0, 0, False, 0.0
        self.force = np.zeros(3)
        self.layer = -1
        self.punctured_now = -1
        self.surface_force = 0.0

    def rupture_factor(self, v, axis):
        """The puncture threshold's factor at tip velocity ``v`` on a net whose ``axis`` points out of
        the tissue: 1 if the high-speed ratio is 1, else the ratio of the two blends of 1 and the
        ratio at the approach speed and at the reference speed."""
        r, vc, vref = self.rupture
        if r >= 1.0:
            return 1.0
        u = max(-float(np.dot(v, axis)), 0.0)
        blend = lambda speed: r + (1.0 - r) * vc / (vc + speed)  # noqa: E731
        return blend(u) / blend(vref)

    # -- geometry ---------------------------------------------------------------------------------
    def radii(self, q):
        """Every boundary's radius toward point ``q`` and |q - centre|."""
        th, ph, rho = directions(q, self.centre)
        return self.coeffs @ self.basis.rows(th, ph)[0], rho[0]

    def depth_gradient(self, k, q, h=1e-6):
        """grad of the depth below rest boundary k, d(q) = r_k(direction of q) - |q - centre|: central
        differences along the scene axes (h = 1 um; the six points in one basis evaluation)."""
        pts = q + np.concatenate([np.eye(3), -np.eye(3)]) * h
        th, ph, rho = directions(pts, self.centre)
        d = self.coeffs[k] @ self.basis.rows(th, ph).T - rho
        return (d[:3] - d[3:]) / (2.0 * h)

    def gap(self, k, x):
        """How far point ``x`` lies outside rest boundary k (radially)."""
        r, rho = self.radii(x)
        return rho - r[k]

    def crossing(self, k, x0, a, t0, t1, step=2e-4):
        """The first t from t0 toward t1 where the line x0 + t a crosses boundary k (None if none)."""
        ts = np.arange(t0, t1, step if t1 > t0 else -step)
        g = [self.gap(k, x0 + t * a) for t in ts]
        for i in range(len(ts) - 1):
            if g[i] == 0.0:
                return float(ts[i])
            if g[i] * g[i + 1] < 0.0:
                return brentq(lambda t: self.gap(k, x0 + t * a), ts[i], ts[i + 1], xtol=1e-13, rtol=1e-12)
        return None

    def begin_insertion(self, p, axis, fallback):
        """Axis, entry on the rest skin along it, and the deeper boundaries' arc lengths."""
        if axis is not None and np.all(np.isfinite(axis)):
            a = np.asarray(axis, float) / np.linalg.norm(axis)
        elif np.linalg.norm(p - self.touch) > 2e-5:
            a = (p - self.touch) / np.linalg.norm(p - self.touch)
        else:
            a = fallback
        self.axis = a
        back = float((p - self.touch) @ a)
        t = self.crossing(0, p, a, -back + 2e-3, -back - 2e-3, step=1e-4)
        self.entry = p + (t if t is not None else -back) * a
        self.bounds[0] = 0.0
        for k in range(1, 4):
            prev = self.bounds[k - 1]
            c = self.crossing(k, self.entry, a, prev, prev + 0.12) if prev < 1.0 else None
            self.bounds[k] = c if c is not None and c >= prev else 1.0
        self.inserted = True
        self.engaged = False
        self.deepest = float((p - self.entry) @ a)
        self.hi = np.full(3, -np.inf)

    def axial(self, s, v, front):
        """The post-puncture force along the axis (N, + into the tissue) for a tip at arc length s."""
        b = self.bounds
        L = np.array([max(min(b[k + 1], s) - max(b[k], s - self.needle_len), 0.0) if k < front else 0.0
                      for k in range(3)])
        self.lengths = L
        if self.table1:
            return -float(self.damping @ L) * v
        self.deepest = max(self.deepest, s)
        kc = next((k for k in range(3) if s < b[k + 1]), 3) if s >= b[0] else -1
        cut = 0.0
        if 0 <= kc < front and self.cut[kc] > 0.0:
            # uncut tissue one radius past the deepest point (within the layer) resists
            probe = min(self.deepest + self.radius, b[kc + 1] - 1e-9)
            if probe > self.hi[kc]:
                reach = 1.0 - 0.5 * (self.deepest - s) * self.k_stick / self.cut[kc]
                cut = self.cut[kc] * max(reach, 0.0)
        st, co = float(self.fs @ L), float(self.fc @ L)
        if not self.engaged:
            self.anchor, self.mode, self.engaged = s, 0, True
        f = self.k_stick * (self.anchor - s) * self.decay
        fwd = co + cut if self.mode == 1 else st + cut
        back = co if self.mode == -1 else st
        if f < -fwd:
            f, self.mode = -fwd, 1
        elif f > back:
            f, self.mode = back, -1
        elif not ((self.mode == 1 and v > 1e-4) or (self.mode == -1 and v < -1e-4)):
            self.mode = 0
        self.anchor = s + f / self.k_stick
        return f - float(self.b @ L) * v

    def record(self, s, v, front):
        """An advancing tip has opened each broken layer down to where it is."""
        if v > 0.0:
            for k in range(min(front, 3)):
                self.hi[k] = max(self.hi[k], min(s, self.bounds[k + 1]))

    def surface_points(self, k, points):
        """Radial projections of ``points`` (n, 3) onto boundary k."""
        th, ph, rho = directions(points, self.centre)
        r = self.basis.rows(th, ph) @ self.coeffs[k]
        return self.centre + (points - self.centre) * (r / rho)[:, None]

    def normal(self, k, p, h=1e-4):
        """Outward unit normal of boundary k at its point toward ``p``: central differences of the
        surface along two tangents of the radial direction."""
        u = (p - self.centre) / np.linalg.norm(p - self.centre)
        t1, t2 = tangent_frame(u)
        dirs = np.array([u + h * t1, u - h * t1, u + h * t2, u - h * t2])
        s = self.surface_points(k, self.centre + dirs)
        n = np.cross(s[0] - s[1], s[2] - s[3])
        n /= np.linalg.norm(n)
        return n if n @ u > 0 else -n

    def build(self, k, contact):
        """Lay layer k's net around ``contact``: flat lattice in the tangent plane, curved copy."""
        lay = self.layers[k]
        net = lay["net"]
        net.axis = self.normal(k, contact)
        e1, e2 = tangent_frame(net.axis)
        pl = net.hex.plane * lay["L"]
        net.X0f = contact + pl[:, :1] * e1 + pl[:, 1:] * e2
        net.xf = net.X0f.copy()
        net.X0 = net.X0f.copy()
        net.X0[1:] = self.surface_points(k, net.X0f[1:])
        net.X0[0] = contact
        net.sweeps_done = 0

    # -- the force net ----------------------------------------------------------------------------
    def _colour_step(self, lay, idx):
        """One Newton step for every particle in ``idx`` (one colour: no two are neighbours)."""
        net = lay["net"]
        xf, a = net.xf, net.axis
        kv, ks = lay["kv"], lay["ks"]
        J = net.hex.nbr[idx]
        valid = J >= 0
        d = np.where(valid[..., None], xf[J] - xf[idx][:, None, :], 0.0)  # (m, 6, 3)
        l2 = np.einsum("mkc,mkc->mk", d, d)
        valid &= l2 > 0.0
        inv = np.where(valid, 1.0 / np.sqrt(np.where(valid, l2, 1.0)), 0.0)
        s = np.where(valid, ks * (1.0 - net.rest[idx] * inv), 0.0)  # tension / length
        defl = (xf[idx] - net.X0f[idx]) @ a
        f = -kv * defl[:, None] * a + np.einsum("mk,mkc->mc", s, d)
        geo = np.maximum(s, 0.0)
        c = (ks - geo) * inv * inv * valid
        H = (kv * np.outer(a, a) + geo.sum(1)[:, None, None] * np.eye(3)
             + np.einsum("mk,mki,mkj->mij", c, d, d))
        outer = net.hex.outer[idx]
        step = np.zeros_like(f)
        max_step = 0.25 * lay["L"]
        if outer.any():
            hn = np.einsum("i,mij,j->m", a, H[outer], a)
            t = np.where(hn > 0.0, (f[outer] @ a) / np.where(hn > 0.0, hn, 1.0), 0.0)
            step[outer] = np.clip(t, -max_step, max_step)[:, None] * a
        free = ~outer
        if free.any():
            Hf = H[free]
            det = np.linalg.det(Hf)
            tr = np.trace(Hf, axis1=1, axis2=2)
            ok = det > 1e-12 * tr ** 3
            sol = np.zeros((Hf.shape[0], 3))
            if ok.any():
                sol[ok] = np.linalg.solve(Hf[ok], f[free][ok][..., None])[..., 0]
            norm = np.sqrt(np.einsum("mc,mc->m", sol, sol))
            sol *= np.minimum(1.0, max_step / np.maximum(norm, 1e-300))[:, None]
            step[free] = sol
        xf[idx] += step
        return np.abs(step).max() if step.size else 0.0

    def sweep(self, lay):
        """One multicolour Gauss-Seidel-Newton sweep (colour order alternates); largest step (m)."""
        net = lay["net"]
        order = net.hex.colours if net.sweeps_done % 2 == 0 else net.hex.colours[::-1]
        net.sweeps_done += 1
        return max(self._colour_step(lay, idx) for idx in order)

    def net_reaction(self, lay):
        """The net's force on the needle at N1 (surface springs + N1's virtual spring)."""
        net = lay["net"]
        xf, a = net.xf, net.axis
        valid = net.hex.nbr[0] >= 0
        d = xf[net.hex.nbr[0][valid]] - xf[0]
        ln = np.sqrt(np.einsum("kc,kc->k", d, d))
        f = lay["ks"] * ((ln - net.rest[0][valid]) / ln) @ d
        return f - lay["kv"] * ((xf[0] - net.X0f[0]) @ a) * a

    @staticmethod
    def laid_shape(lay, q):
        """A tabulated net's equilibrium shape with N1 at ``q`` (what the visual loop renders)."""
        net, tab = lay["net"], lay["table"]
        dz1 = -((q - net.X0f[0]) @ net.axis)
        x = min(max(dz1, 0.0) / tab["h"], tab["D"].shape[0] - 1.0)
        i = min(int(x), tab["D"].shape[0] - 2)
        d = (1.0 - (x - i)) * tab["D"][i] + (x - i) * tab["D"][i + 1]
        e1, e2 = tangent_frame(net.axis)
        out = net.X0f + d @ np.array([e1, e2, net.axis])
        out[0] = q
        return out

    @staticmethod
    def ring_w_deflection(lay):
        net = lay["net"]
        o = net.hex.outer
        return float(-((net.xf[o] - net.X0f[o]) @ net.axis).mean())

    # -- the servo step ---------------------------------------------------------------------------
    def step(self, p, v, sweeps: int | None = None, axis=None):
        """One servo tick at tip ``p`` (m) moving at ``v`` (m/s), needle ``axis`` (None: unknown): the
        force on the needle (N)."""
        p = np.asarray(p, dtype=float)
        v = np.asarray(v, dtype=float)
        self.punctured_now = -1
        self.surface_force = 0.0
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(v))):
            self.fault = True
        if self.fault:
            self.force = np.zeros(3)
            return self.force
        sweeps = self.sweeps if sweeps is None else sweeps
        a = self.axis
        s_p = 0.0
        if self.inserted:
            s_p = float((p - self.entry) @ a)
            if s_p < -1e-6:  # back above the entry point: out of the tissue
                self.inserted = False
                self.offset = 0.0
                self.engaged = False
                self.states = [UNTOUCHED] * 3
            elif self.offset > s_p:
                self.offset = max(s_p, 0.0)  # withdrawal: the skin tents up with the needle
        q = p - self.offset * a
        radii, rho = self.radii(q)
        front = next((k for k in range(3) if self.states[k] != PUNCTURED), 3)
        f = np.zeros(3)
        if front < 3:
            k = front
            lay = self.layers[k]
            net = lay["net"]
            if self.states[k] == UNTOUCHED and radii[k] >= rho:
                if k == 0:
                    self.touch = q.copy()
                self.build(k, self.centre + (q - self.centre) * (radii[k] / rho))
                self.states[k] = PRESSING
            if self.states[k] == PRESSING:
                dep = radii[k] - rho  # the tip's depth below the layer's rest surface (radial)
                if dep <= 0.0:
                    self.states[k] = UNTOUCHED  # lifted off
                else:
                    n_sweeps = sweeps
                    r = q - net.X0f[0]
                    lateral = r + (-(r @ net.axis)) * net.axis
                    if lateral @ lateral > (0.5 * lay["L"]) ** 2:
                        # slid sideways: a new net under the tip (where it is drawn), warm-started
                        # with the old net's ring-mean deflections
                        dz = -((net.xf - net.X0f) @ net.axis)
                        ring = net.hex.ring
                        mean = np.bincount(ring, dz)[1:] / np.bincount(ring)[1:]
                        self.build(k, self.centre + (q - self.centre) * (radii[k] / rho))
                        net.xf = net.X0f - mean[ring - 1][:, None] * net.axis
                        n_sweeps *= 2
                    # the response with N1 at depth dep straight below its rest point, whatever the
                    # lateral offset; the force along grad(-dep)
                    tab = lay.get("table")
                    if tab is not None:
                        pt = np.array([[0.0, dep]])
                        fn = float(tab["F"](pt)[0])
                        ring_w = float(tab["R"](pt)[0])
                    else:
                        net.xf[0] = net.X0f[0] - dep * net.axis
                        for _ in range(n_sweeps):
                            self.sweep(lay)
                        ring_w = self.ring_w_deflection(lay)
                        fn = float(self.net_reaction(lay) @ net.axis)
                    net.xf[0] = q  # N1 drawn at the tip (a tabulated shape is laid only for rendering)
                    if ring_w > lay["thresh"] * self.rupture_factor(v, net.axis):
                        self.states[k] = PUNCTURED
                        self.punctured_now = k
                        if k == 0:
                            self.begin_insertion(p, axis, -net.axis)
                            a = self.axis
                        comp = dep / max(-float(a @ net.axis), 0.2)  # the dent along the axis
                        if comp > 0.0:
                            self.offset += comp  # the tissue beneath stays compressed by the dent
                        q = p - self.offset * a
                        radii, rho = self.radii(q)
                        front = k + 1
                    else:
                        fn = max(fn, 0.0)  # a surface only pushes
                        g = self.depth_gradient(k, q)
                        f -= fn * g
                        self.surface_force = fn * float(np.linalg.norm(g))
        if self.inserted:
            s = float((p - self.entry) @ a)
            f += self.axial(s, float(v @ a), front) * a
            self.record(s, float(v @ a), front)
            if self.lateral_on:
                e = p - self.entry
                f -= self.k_lat * min(self.lengths.sum() / self.needle_len, 1.0) * (e - (e @ a) * a)
        if front >= 3 and radii[3] > rho:
            f += self.k_bone * (radii[3] - rho) * (q - self.centre) / rho
        layer = -1
        if rho <= radii[0]:
            layer = next((j for j in range(3) if rho > radii[j + 1]), 3)
        if front < 3 and layer > front - 1:
            layer = front - 1
        if self.punctured_now >= 0:
            layer = max(layer, self.punctured_now)  # the tip is in the layer it broke this tick
        self.layer = layer
        if not np.all(np.isfinite(f)):
            self.fault = True
            self.force = np.zeros(3)
            return self.force
        mag = float(np.linalg.norm(f))
        if mag > self.limit:
            f *= self.limit / mag
        self.force = f
        return f

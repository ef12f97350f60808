"""Springback of a punctured layer's surface: shape matching slowed by eq. 9 (eq. 7-9; MODEL.md s4).

After a puncture the net's particles (and the undeformed margin rings around it, which keep the
centroid from drifting) are matched to their rest shape each visual frame:

    A   = sum_i M_i (p_i - p_cm)(p0_i - p0_cm)^T            (eq. 7, equal masses)
    R   = rotation of A's polar decomposition A = R S        (eq. 8's "alpha / A", read as Mueller 2005)
    g_i = R (p0_i - p0_cm) + p_cm                            (eq. 8)
    g_i = g_i + eta (p_i - g_i),  eta <- max(eta_min, eta - eta_r)   (eq. 9)

and the net's particles move to their goals; the margin particles stay at rest. With eta = 1 nothing
moves; with eta_min = 0 the surface returns to its rest shape. R comes from an SVD with the
reflection fixed (det R = +1), robust for any A including a degenerate (flat) one.

This runs in the 60 Hz visual loop, on nets the servo has handed over (see :mod:`haptic_acu.servo.step`).
"""
from __future__ import annotations

import numba as nb
import numpy as np

from .layers import N_SLOTS, VISUAL_OWNS


@nb.njit(cache=True, nogil=True)
def polar_rotation(A):
    """The rotation R of the polar decomposition A = R S (det R = +1)."""
    U, s, Vt = np.linalg.svd(A)
    R = U @ Vt
    # R is orthogonal (det +-1): the cofactor expansion's sign is its determinant's; element by element
    # (numba compiles a slice assignment's shape check, with its message, for seconds)
    det = (R[0, 0] * (R[1, 1] * R[2, 2] - R[1, 2] * R[2, 1]) - R[0, 1] * (R[1, 0] * R[2, 2] - R[1, 2] * R[2, 0])
           + R[0, 2] * (R[1, 0] * R[2, 1] - R[1, 1] * R[2, 0]))
    if det < 0.0:
        U2 = U.copy()
        for i in range(3):
            U2[i, 2] = -U2[i, 2]
        R = U2 @ Vt
    return R


@nb.njit(cache=True, nogil=True)
def shape_matching_goals(p, p0, goals):
    """Goals g_i = R (p0_i - p0_cm) + p_cm for every particle (eq. 7-8, equal masses)."""
    n = p.shape[0]
    cm = np.zeros(3)
    cm0 = np.zeros(3)
    for i in range(n):
        for k in range(3):
            cm[k] += p[i, k]
            cm0[k] += p0[i, k]
    cm /= n
    cm0 /= n
    A = np.zeros((3, 3))
    for i in range(n):
        for a in range(3):
            for b in range(3):
                A[a, b] += (p[i, a] - cm[a]) * (p0[i, b] - cm0[b])
    R = polar_rotation(A)
    for i in range(n):
        for a in range(3):
            acc = cm[a]
            for b in range(3):
                acc += R[a, b] * (p0[i, b] - cm0[b])
            goals[i, a] = acc


@nb.njit(cache=True, nogil=True)
def springback_step(x, X0, n_net, eta, goals):
    """One visual frame: move particles ``[0, n_net)`` of ``x`` to their eta-slowed goals (eq. 9);
    particles ``[n_net, len)`` (the undeformed margin) stay at rest. Returns the largest move (m)."""
    n_all = x.shape[0]
    for i in range(n_net, n_all):
        for k in range(3):
            x[i, k] = X0[i, k]
    shape_matching_goals(x, X0, goals)
    biggest = 0.0
    for i in range(n_net):
        m2 = 0.0
        for k in range(3):
            g = goals[i, k] + eta * (x[i, k] - goals[i, k])
            d = g - x[i, k]
            m2 += d * d
            x[i, k] = g
        if m2 > biggest:
            biggest = m2
    return np.sqrt(biggest)


@nb.njit(cache=True, nogil=True)
def springback_frame(owner, gen, pos, x_at, X0_at, n_all, sb, goals):
    """One visual frame of springback on every handed-over net (owner VISUAL_OWNS) of the packed
    particle storage ``pos`` (net ``idx`` of layer ``k = idx // N_SLOTS``: its particles at rows
    ``x_at[idx]``, rest ones at ``X0_at[idx]``, ``n_all[k]`` of them, the first ``sb.n_net[k]`` the
    force net's). ``owner`` and ``gen`` are the servo's (layer, slot) arrays; ``sb``
    (:func:`sb_dtype`, one record) holds each net's eta, the generation it was seen at and whether it
    has settled, each layer's force-net size, and the schedule; ``goals`` is scratch of at least ``max(n_all)`` rows. A net whose
    generation changed restarts at eta 1. Returns how many nets moved."""
    s = sb[0]
    moved = 0
    for idx in range(s.eta.shape[0]):
        k = idx // N_SLOTS
        sl = idx % N_SLOTS
        if owner[k, sl] != VISUAL_OWNS:
            continue
        g = gen[k, sl]
        if g != s.gen[idx]:
            s.gen[idx] = g
            s.eta[idx] = 1.0
            s.settled[idx] = 0
        if s.settled[idx]:
            continue
        na = n_all[k]
        step = springback_step(pos[x_at[idx]:x_at[idx] + na], pos[X0_at[idx]:X0_at[idx] + na], s.n_net[k],
                               s.eta[idx], goals[:na])
        s.eta[idx] = max(s.eta_min, s.eta[idx] - s.eta_rate)
        if s.eta[idx] <= s.eta_min and step < s.settle_m:
            s.settled[idx] = 1
        moved += 1
    return moved


def sb_dtype(n_nets: int, n_layers: int) -> np.dtype:
    """The springback record for ``n_nets`` nets of ``n_layers`` layers (:func:`springback_frame`'s
    ``sb``): per net its eta, the generation it was seen at, whether it has settled; per layer the
    force net's particle count (``n_net``); the schedule."""
    return np.dtype([("eta", "f8", (n_nets,)), ("gen", "i8", (n_nets,)), ("settled", "u1", (n_nets,)),
                     ("n_net", "i8", (n_layers,)), ("eta_rate", "f8"), ("eta_min", "f8"), ("settle_m", "f8")])


class Springback:
    """Per-slot springback schedules for a :class:`~haptic_acu.servo.step.NeedleModel`.

    Call :meth:`frame` once per visual frame (or pass :meth:`args` to a compiled loop that calls
    :func:`springback_frame` itself). It runs only on slots the servo has handed over (owner 2) and
    restarts a slot's eta at 1 whenever the slot's generation changes (a new puncture, or the servo
    took the slot back for a new net).
    """

    def __init__(self, model, eta_rate: float, eta_min: float, settle_m: float = 1e-9):
        self.model = model
        self.eta_rate = float(eta_rate)
        self.eta_min = float(eta_min)
        self.settle_m = settle_m
        n_slots = len(model.x)
        self.sb = np.zeros(1, sb_dtype(n_slots, len(model.n)))
        rec = self.sb[0]
        rec["n_net"] = np.asarray(model.n, dtype=np.int64)
        rec["eta"] = 1.0
        rec["gen"] = -1
        rec["eta_rate"], rec["eta_min"], rec["settle_m"] = self.eta_rate, self.eta_min, settle_m
        self.eta, self.gen, self.settled = rec["eta"], rec["gen"], rec["settled"]  # views
        self.n_net = rec["n_net"]  # a view
        self.goals = np.zeros((max(len(x) for x in model.x), 3))

    @classmethod
    def from_config(cls, model, cfg) -> "Springback":
        return cls(model, cfg.springback.eta_rate_per_frame, cfg.springback.eta_min)

    def args(self) -> tuple:
        """:func:`springback_frame`'s arguments after ``owner, gen, pos, x_at, X0_at, n_all`` (the
        servo's): ``(sb, goals)``."""
        return self.sb, self.goals

    def frame(self) -> int:
        """Advance every handed-over net by one frame; returns how many nets moved."""
        m = self.model
        lay = m.model.layout[0]
        return springback_frame(m.rec["owner"], m.rec["gen"], m.state.pos, lay["x"], lay["X0"], lay["n_all"],
                                *self.args())

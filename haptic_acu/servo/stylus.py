"""A model of a force device's stylus held by a hand (SI units): what a trainee on an OMNI would
feel, for sessions without one (a scripted device's live session, the offline closed-loop bench).

The stylus is a point mass pushed by the commanded force (held over each servo tick, as a device's
servo applies it) and by a hand holding it through a spring-damper to the hand's path, as the HD
emulator's physical stylus mode (tests/hd_emulator/hd_emulator.c) does; the encoders report its
position quantised to their step. Integrated in semi-implicit Euler substeps.

Grips: a 45 g stylus held loosely (0.3 N/mm) or firmly (2 N/mm); the hand's damping
(ours) gives each a damping ratio of about 0.3 and 0.26: 2 and 5 N*s/m.
"""
from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

SUBSTEPS = 20


class Grip(NamedTuple):
    stiffness_n_per_m: float
    damping_n_s_per_m: float
    mass_kg: float


LOOSE = Grip(300.0, 2.0, 0.045)
FIRM = Grip(2000.0, 5.0, 0.045)


@nb.njit(cache=True, nogil=True)
def stylus_tick(state, hand0, hand1, force, grip, dt, out_hand_force):
    """One servo tick of the stylus (``state``: x(3), v(3), m and m/s) with ``force`` (N) held, the
    hand moving linearly from ``hand0`` to ``hand1`` (m); writes the tick's mean force of the hand
    on the stylus (N) into ``out_hand_force``."""
    h = dt / SUBSTEPS
    k = grip.stiffness_n_per_m
    b = grip.damping_n_s_per_m
    m = grip.mass_kg
    for c in range(3):
        hv = (hand1[c] - hand0[c]) / dt
        x = state[c]
        v = state[3 + c]
        acc_f = 0.0
        for i in range(1, SUBSTEPS + 1):
            hp = hand0[c] + hv * i * h
            fh = k * (hp - x) + b * (hv - v)
            v += h * (force[c] + fh) / m
            x += h * v
            acc_f += fh
        state[c] = x
        state[3 + c] = v
        out_hand_force[c] = acc_f / SUBSTEPS


@nb.njit(cache=True, nogil=True)
def encoder(x, step, out):
    """Positions ``x`` (m) as encoders of ``step`` (m) report them (round to nearest; 0: exact)."""
    for c in range(3):
        out[c] = step * np.round(x[c] / step) if step > 0.0 else x[c]

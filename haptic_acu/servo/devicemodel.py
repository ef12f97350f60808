"""A model of the force device a trainee would hold, for live sessions without one (the scripted
device): the rendered force its recordings carry (``fr_*_n`` columns), what an OMNI would have
output on that path.

The device: :mod:`haptic_acu.servo.stylus`'s 45 g stylus held by a hand following the session's path
(the scripted tip) with the firm grip (:data:`haptic_acu.servo.stylus.FIRM`, 2 N/mm: a trainee guiding
the needle deliberately), pushed by the rendered force, its position reported by 0.055 mm encoders;
and the rendering layer (:mod:`haptic_acu.servo.rendering`) with an OMNI's nominal limits
(:data:`OMNI_LIMITS`: 3.3 N peak, 0.88 N continuous, 1.26 N/mm, 3 N*s/m, the values the HD
emulator reports as HD_NOMINAL_MAX_*). The tissue step itself stays at the scripted tip (the
recording replays exactly); its report there (the DIAG ``r_*`` fields) is what the coupling
renders, so the rendered force is the simulated one as the device would have delivered it: through
the coupling's stiffness and damping, the encoder quantisation, the clamp and the continuous-force
protection.
"""
from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

from . import rendering as R
from . import stylus

OMNI_LIMITS = R.limits_from_hd(3.3, 0.88, 1.26, 0.003)
ENCODER_STEP_M = 0.055e-3

GRIP = np.dtype([("k", "f8"), ("b", "f8"), ("m", "f8")])
PRM = R.LIMITS  # the rendering layer's limits and parameters (the OMNI callback's rlim)


class DeviceModel(NamedTuple):
    prm: np.ndarray  # (1,) PRM (on = 0: no model; the rows' fr columns stay 0)
    grip: np.ndarray  # (1,) GRIP
    plant: np.ndarray  # (6,) stylus position and velocity (m, m/s)
    hand: np.ndarray  # (3,) the hand's previous position (m)
    xq: np.ndarray  # (3,) the encoders' report
    hand_f: np.ndarray  # (3,) the hand's force on the stylus (N)
    cs: tuple  # rendering.CouplingState
    tf: np.ndarray  # (3,) TissueLocal.force
    ta: np.ndarray  # (3,) TissueLocal.axis


def new(dt_s: float, on: bool = True, limits: R.DeviceLimits = OMNI_LIMITS, grip: stylus.Grip = stylus.FIRM) -> DeviceModel:
    """A device model for a session at ``dt_s`` per tick (``on=False``: an inert one)."""
    p = R.default_params(limits, dt_s, ENCODER_STEP_M)
    prm = R.limits_record(limits, p, on)
    g = np.zeros(1, GRIP)
    g[0]["k"], g[0]["b"], g[0]["m"] = grip.stiffness_n_per_m, grip.damping_n_s_per_m, grip.mass_kg
    return DeviceModel(prm, g, np.zeros(6), np.zeros(3), np.zeros(3), np.zeros(3), R.new_state(), np.zeros(3),
                       np.zeros(3))


@nb.njit(cache=True, nogil=True)
def model_tick(dm, inp, diag):
    """One tick of the device model: the hand at ``inp.p`` (the scripted tip; ``diag``: the
    previous tick's DIAG, the tissue's report there). Moves the stylus (the force of the tick
    before held), reads its encoders, renders; the force and its status bits into ``inp.fr`` /
    ``inp.rstat``. Leaves ``inp.p``/``inp.v`` alone."""
    q = dm.prm[0]
    if q.on == 0.0:
        for c in range(3):
            inp.fr[c] = 0.0
        inp.rstat[0] = 0.0
        return 0
    cs = dm.cs
    aux = cs.aux[0]
    if aux.initialised == 0:  # the stylus starts at rest in the hand
        for c in range(3):
            dm.plant[c] = inp.p[c]
            dm.plant[3 + c] = 0.0
            dm.hand[c] = inp.p[c]
    g = dm.grip[0]
    grip = stylus.Grip(g.k, g.b, g.m)
    stylus.stylus_tick(dm.plant, dm.hand, inp.p, cs.force, grip, q.dt, dm.hand_f)
    for c in range(3):
        dm.hand[c] = inp.p[c]
    stylus.encoder(dm.plant[:3], q.enc, dm.xq)
    tissue = R.tissue_from_diag(diag[0], dm.tf, dm.ta)
    limits = R.DeviceLimits(q.max_force, q.cont_force, q.k_max, q.b_max)
    params = R.CouplingParams(q.k, q.b, q.enc, q.tau, q.ramp, q.dt)
    status = R.render_step(limits, params, cs, tissue, dm.xq)
    for c in range(3):
        inp.fr[c] = cs.force[c]
    inp.rstat[0] = status
    return status


def warm_up() -> None:
    """Compile (or load) :func:`model_tick` before a real-time loop starts."""
    from . import state as ss

    dm = new(1e-3)
    inp = ss.TickIn(np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(1), np.full(3, np.nan), np.zeros(1))
    model_tick(dm, inp, np.zeros(1, ss.DIAG))

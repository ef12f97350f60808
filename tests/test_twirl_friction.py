"""The grasp through the real shaft friction: Langevin 2001's pull-out ratios with the stick-point
Karnopp friction of haptic_acu.tissue.mechanics (built in parallel). Skipped until that module
is merged; then it is the pull-out test of the kernels as they will be wired: the grasp factors
multiply each layer's friction levels (its breakaway and Coulomb thresholds: ``shaft_thresholds``
gets ``grasp * lengths``), not the viscous part.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from haptic_acu.tissue import twirl as T

mech = pytest.importorskip("haptic_acu.tissue.mechanics", reason="post-puncture mechanics not merged yet")

DT = 1e-3
LENGTHS = np.array([0.8e-3, 8.4e-3, 20.8e-3])  # tip 30 mm deep: skin, fat, muscle
PULL_MM_S = 10.0


def params():
    """The friction of a 0.25 mm needle as config/tissue.toml has it on the mechanics branch
    (Coulomb 10, 2, 5 N/m; breakaway 1.5x; stick spring 0.6 N/mm; 1 s relaxation)."""
    fc = np.array([10.0, 2.0, 5.0])
    return mech.MechParams(cut=np.zeros(3), fs=1.5 * fc, fc=fc, b=np.zeros(3), k_stick=600.0,
                           decay=math.exp(-DT / 1.0), radius=0.125e-3, length=40e-3)


def pullout_peak(proto, p=None):
    """Twirl per ``proto`` with the needle still, then pull out at 10 mm/s for 0.5 s: the peak force
    resisting the withdrawal (N)."""
    prm, st, ws = params(), mech.new_friction_state(), T.new_wind_state()
    p = T.default_params() if p is None else p
    s = float(LENGTHS.sum())
    roll = T.protocol_roll(proto, DT)
    for r in roll:
        T.wind_step(ws, float(r), LENGTHS, DT, p)
        mech.stick_slip(st, prm.k_stick, prm.decay, s, 0.0,
                        mech.shaft_thresholds(prm.fs, prm.fc, ws.grasp * LENGTHS, 0.0))
    peak = 0.0
    for k in range(1, 501):
        s_k = s - PULL_MM_S * 1e-3 * DT * k
        lengths = LENGTHS.copy()
        lengths[2] = max(0.0, lengths[2] - (s - s_k))
        T.wind_step(ws, float(roll[-1]), lengths, DT, p)
        f = mech.stick_slip(st, prm.k_stick, prm.decay, s_k, -PULL_MM_S * 1e-3,
                            mech.shaft_thresholds(prm.fs, prm.fc, ws.grasp * lengths, 0.0))
        peak = max(peak, f)  # along +s: positive resists the withdrawal
    return peak


def test_pullout_ratios_through_the_karnopp_friction():
    """With the stand-in's gains: within 6% (the stick spring lets the needle move out a little,
    losing length and grasp, before it breaks away, more so the stronger the grasp)."""
    f_no = pullout_peak(T.NO)
    assert f_no > 0
    assert pullout_peak(T.UNI) / f_no == pytest.approx(T.LANGEVIN_UNI_RATIO, rel=0.06)
    assert pullout_peak(T.BI) / f_no == pytest.approx(T.LANGEVIN_BI_RATIO, rel=0.06)


def test_recalibrated_through_the_friction():
    coil, engage = T.calibrate_grasp(pullout=pullout_peak)
    p = T.default_params(grasp_coil=coil, grasp_engage=engage)
    f_no = pullout_peak(T.NO, p)
    assert pullout_peak(T.UNI, p) / f_no == pytest.approx(T.LANGEVIN_UNI_RATIO, rel=1e-3)
    assert pullout_peak(T.BI, p) / f_no == pytest.approx(T.LANGEVIN_BI_RATIO, rel=1e-3)

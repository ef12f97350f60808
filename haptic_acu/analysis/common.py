"""Small measures shared by the batch metrics (:mod:`.metrics`) and their streamed form
(:mod:`.insertion_stream`), so that both compute them from one definition; and the sample columns
they and the scan (:mod:`.scan`) read, named once."""
from __future__ import annotations

import numpy as np

from ..servo.samples import COL
from ..servo.state import LAYER_NAMES as LAYERS  # noqa: F401 (re-exported)

# the sample columns (:data:`haptic_acu.servo.samples.COL`) the analysis reads: a vector's first column
C_X, C_F, C_T, C_TICK = COL["x_m"], COL["fx_n"], COL["t_s"], COL["tick"]
C_LAYER, C_STATE, C_PUNCT, C_CLAMPED = COL["layer"], COL["state_skin"], COL["puncture"], COL["clamped"]
C_FAULT = COL["fault"]
C_DEPTH, C_LAT = COL["depth_skin_m"], COL["f_lateral_n"]
C_LAYER_F = (COL["f_skin_n"], COL["f_fat_n"], COL["f_muscle_n"])
C_ROLL, C_TORQUE = COL["roll_deg"], COL["torque_nmm"]

SPEED_DEPTH_FRACTION = 0.9  # the insertion speed is measured up to this fraction of the insertion's depth


def round_json(x, nd: int):
    """Round for JSON without negative zeros; None stays None."""
    if x is None:
        return None
    return round(float(x), nd) + 0.0


def depth_verdict(depth_mm: float, target_mm) -> str:
    lo, hi = target_mm
    if depth_mm < lo:
        return "too shallow"
    if depth_mm > hi:
        return "too deep"
    return "in range"


def angle_deg(u: np.ndarray, n: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(u, n)), float(np.dot(u, n)))))


def dot3(d: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Row-wise d . u for (k, 3) ``d``, the same bits whatever k (a BLAS matrix-vector product
    rounds a row differently in blocks of different sizes)."""
    return d[:, 0] * u[0] + d[:, 1] * u[1] + d[:, 2] * u[2]

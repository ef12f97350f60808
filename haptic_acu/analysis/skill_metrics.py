"""Motor-skill metrics of a tip path: pure functions of sampled times and positions.

These complement :mod:`haptic_acu.analysis.metrics` (where and how deep an insertion went) with the
standard measures of *how* the hand moved, as used in surgical and needling skill studies:

* :func:`path_length` (m): the length of the polyline through the samples, ``sum |p[i+1] - p[i]|``.
* :func:`economy_of_motion` (1): straight-line distance between the first and last sample over the
  path length; 1 for a path that never leaves the segment joining its ends and never turns back,
  smaller for a detour. None for a path of (numerically) zero length.
* :func:`ldlj` (1): the log dimensionless jerk of the speed profile, after Balasubramanian,
  Melendez-Calderon and Burdet (2012, IEEE TBME 59(8):2126) and Balasubramanian, Melendez-Calderon,
  Roby-Brami and Burdet (2015, J NeuroEng Rehabil 12:112), speed-based form::

      LDLJ = -ln( (t2 - t1)^3 / v_peak^2 * integral_{t1}^{t2} (d^2 v / dt^2)^2 dt )

  with ``v = |dp/dt|`` the tip speed and ``v_peak`` its maximum over ``[t1, t2]``. Dimensionless
  (independent of the movement's amplitude and duration); larger (closer to zero) is smoother. A
  minimum-jerk point-to-point movement gives ``-ln(4096/20) = -ln 204.8 = -5.32`` whatever its
  length and duration. None when the tip does not move.

Derivatives are central differences (:func:`numpy.gradient`) and the integral the trapezoid rule
on the samples' own times. Recorded and replayed paths are noisy at the servo rate (a trajectory
file's samples are linearly interpolated to 1 kHz, so its velocity steps every few ms; an encoder
quantises the position), and the second derivative of the speed amplifies that noise without
bound, so :func:`smooth_path` first low-passes the positions with a zero-phase Butterworth filter
(:func:`scipy.signal.sosfiltfilt`, 4th order, ``cutoff_hz`` = 10 Hz by default: voluntary hand
movement has its power below about 10 Hz). Filter a whole session once and slice the window of
interest out of the result, so the window's ends are not filter edges.
"""
from __future__ import annotations

import numpy as np

DEFAULT_CUTOFF_HZ = 10.0
FILTER_ORDER = 4
MIN_PATH_M = 1e-9


def smooth_path(t: np.ndarray, p: np.ndarray, cutoff_hz: float | None = DEFAULT_CUTOFF_HZ) -> np.ndarray:
    """Positions ``p`` (n, 3) sampled at increasing times ``t`` (n,), low-passed per coordinate by a
    zero-phase Butterworth filter (order 4, ``cutoff_hz``); ``cutoff_hz=None`` returns a copy.
    Assumes (nearly) uniform sampling: the rate is the median sample interval."""
    t = np.asarray(t, dtype=np.float64)
    p = np.asarray(p, dtype=np.float64)
    if cutoff_hz is None or len(t) < 3:
        return p.copy()
    from scipy.signal import butter, sosfiltfilt

    fs = 1.0 / float(np.median(np.diff(t)))
    if cutoff_hz >= 0.5 * fs:  # nothing above Nyquist to remove
        return p.copy()
    sos = butter(FILTER_ORDER, cutoff_hz, fs=fs, output="sos")
    padlen = min(3 * (2 * len(sos) + 1), len(t) - 1)
    return sosfiltfilt(sos, p, axis=0, padlen=padlen)


def path_length(p: np.ndarray) -> float:
    """Length (units of ``p``) of the polyline through the points ``p`` (n, d)."""
    p = np.asarray(p, dtype=np.float64)
    if len(p) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def economy_of_motion(p: np.ndarray) -> float | None:
    """Straight-line distance between the ends of ``p`` (n, d) over its path length (1 at best)."""
    p = np.asarray(p, dtype=np.float64)
    length = path_length(p)
    if length <= MIN_PATH_M:
        return None
    return float(np.linalg.norm(p[-1] - p[0]) / length)


def speed(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Speed ``|dp/dt|`` at each sample (central differences on the sample times)."""
    t = np.asarray(t, dtype=np.float64)
    v = np.gradient(np.asarray(p, dtype=np.float64), t, axis=0)
    return np.linalg.norm(v.reshape(len(t), -1), axis=1)


def ldlj_of_speed(t: np.ndarray, v: np.ndarray) -> float | None:
    """Log dimensionless jerk of a speed profile ``v`` sampled at times ``t`` (see the module)."""
    t = np.asarray(t, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    if len(t) < 5:
        return None
    v_peak = float(np.max(np.abs(v)))
    duration = float(t[-1] - t[0])
    if v_peak <= 0.0 or duration <= 0.0:
        return None
    d2v = np.gradient(np.gradient(v, t), t)
    integral = float(np.trapezoid(d2v * d2v, t))
    dlj = duration ** 3 / v_peak ** 2 * integral
    if not dlj > 0.0:
        return None
    return float(-np.log(dlj))


def ldlj(t: np.ndarray, p: np.ndarray) -> float | None:
    """Log dimensionless jerk of the path ``p`` (n, d) at times ``t``: :func:`ldlj_of_speed` of its
    speed. Smooth the positions first (:func:`smooth_path`) if they are noisy."""
    return ldlj_of_speed(t, speed(t, p))

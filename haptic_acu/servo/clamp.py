"""A force clamp that holds exactly in floating point: the servo step's clamp phase
(``needle.clamp``) and the OMNI guard's clamps in both frames (``omniloop.guard_out``) call it.

The naive clamp, ``mag = sqrt(fx*fx + fy*fy + fz*fz); if mag > lim: f *= lim / mag``, fails two ways:

* rounding: about half of all clamped vectors come out 1 ulp above the limit (|f| =
  3.3000000000000003 N for a 3.3 N device), which a device checking ``|f| <= nominal`` strictly
  refuses; any later frame change (the workspace rotation) adds its own ulps;
* overflow: a component beyond ~1.3e154 N squares to inf, ``lim / inf`` is 0 and the clamp
  commands 0 N where it should command the limit (a stiffness of 1e300 N/mm did that); below
  ~1e-154 N the squares underflow and the direction is lost.

:func:`clamp_force` fixes both: it measures the magnitude on the vector divided by its largest
component (every square in [0, 1], no overflow or underflow), and scales by ``lim / mag`` shrunk
by 4 ulps, which covers the rounding of the scaling (1/2 ulp per component) and of any later
magnitude computation (sum of three squares and a square root: under 3 ulps). The result's exact
(rational) magnitude is <= ``lim`` for every finite input (tests/test_clamp.py checks it against
exact rational arithmetic). Not ``fastmath``: ``isfinite`` must work.
"""
from __future__ import annotations

import math

import numba as nb

_SHRINK = 1.0 - 4.0 * 2.0 ** -52  # 4 ulps below 1


@nb.njit(cache=True, nogil=True, _nrt=False)
def clamp_force(fx, fy, fz, lim):
    """``(fx, fy, fz, clamped)``: the force scaled to magnitude <= ``lim`` (exactly, in real
    arithmetic on the returned floats), ``clamped`` 1.0 if it was scaled. Non-finite input: zero
    force and ``clamped`` = -1.0 (the caller's fault path)."""
    if not (math.isfinite(fx) and math.isfinite(fy) and math.isfinite(fz)):
        return 0.0, 0.0, 0.0, -1.0
    m = max(abs(fx), abs(fy), abs(fz))
    if m == 0.0:
        return 0.0, 0.0, 0.0, 0.0
    ux = fx / m
    uy = fy / m
    uz = fz / m
    mag = m * math.sqrt(ux * ux + uy * uy + uz * uz)  # may round to inf for |f| near 1.8e308
    if mag <= lim * _SHRINK:
        return fx, fy, fz, 0.0
    # the direction u / |u| at magnitude lim: ux ... are in [-1, 1], so nothing overflows
    s = (lim / math.sqrt(ux * ux + uy * uy + uz * uz)) * _SHRINK
    return ux * s, uy * s, uz * s, 1.0

"""The exact force clamp (haptic_acu.servo.clamp) against exact rational arithmetic."""
from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from haptic_acu.servo.clamp import clamp_force


def exact_norm2(f) -> Fraction:
    return sum(Fraction(x) ** 2 for x in f)


def naive(f, lim):
    mag = math.sqrt(sum(x * x for x in f))
    return [x * (lim / mag) for x in f] if mag > lim else list(f)


def test_the_naive_clamp_overshoots_and_overflows():
    """What the servo does today: 1 ulp over a 3.3 N limit, and 0 N for a huge force."""
    f = [-7.312715117751976, 6.9486747387446535, 5.275492379532281]
    assert exact_norm2(naive(f, 3.3)) > Fraction(3.3) ** 2
    assert naive([1e300, 0.0, 0.0], 3.3) == [0.0, 0.0, 0.0]
    fx, fy, fz, c = clamp_force(*f, 3.3)
    assert c == 1.0 and exact_norm2((fx, fy, fz)) <= Fraction(3.3) ** 2


finite = st.floats(allow_nan=False, allow_infinity=False)


@settings(max_examples=300, deadline=None)
@given(finite, finite, finite, st.sampled_from([3.3, 0.88, 1.0, 1e-3, 100.0]))
def test_never_above_the_limit_exactly(fx, fy, fz, lim):
    gx, gy, gz, c = clamp_force(fx, fy, fz, lim)
    out = (gx, gy, gz)
    assert all(math.isfinite(v) for v in out)
    assert exact_norm2(out) <= Fraction(lim) ** 2  # exact, not within a tolerance
    assert math.sqrt(gx * gx + gy * gy + gz * gz) <= lim or max(map(abs, out)) < 1e-150
    n = exact_norm2((fx, fy, fz))
    if n <= (Fraction(lim) * Fraction(1 - 8 * 2 ** -52)) ** 2:
        assert out == (fx, fy, fz) and c == 0.0  # small forces pass untouched
    if c == 1.0:
        # the same direction, at the limit (within 8 ulps)
        assert float(exact_norm2(out)) ** 0.5 >= lim * (1 - 8 * 2 ** -52)
        m = max(abs(fx), abs(fy), abs(fz))
        u = np.array([fx, fy, fz]) / m
        np.testing.assert_allclose(np.array(out) / lim, u / np.linalg.norm(u), rtol=0, atol=1e-14)


def test_non_finite_is_zero_and_flagged():
    for bad in (math.nan, math.inf, -math.inf):
        assert clamp_force(bad, 0.0, 1.0, 3.3) == (0.0, 0.0, 0.0, -1.0)

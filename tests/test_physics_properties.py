"""Safety properties of the needle model (haptic_acu.servo.step) over random layer parameters and random
tip trajectories (hypothesis): whatever the hand does, the force is finite, within the limit, the
model's arrays stay finite, and there is no force while the needle is out of the tissue and pressing
nothing.

"Out of the tissue" is: tip outside the skin surface, and the needle not in an entry hole
(``model.inserted`` false). A needle still in its hole whose tip has been swung far sideways until it
comes back out through the skin keeps feeling the lateral constraint, by design.
"""
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from haptic_acu.servo.step import PRESSING, NeedleModel
from physics_helpers import SPHERE_R_MM, replace, sphere_config, sphere_tissue, state_arrays

R_SKIN = SPHERE_R_MM * 1e-3


@pytest.fixture(scope="module")
def base():
    cfg = sphere_config()
    return cfg, sphere_tissue(cfg)


layer_params = st.fixed_dictionaries({
    "k_virtual_n_per_mm": st.floats(0.005, 2.0),
    "k_surface_n_per_mm": st.floats(0.005, 20.0),
    "spring_length_mm": st.floats(0.3, 4.0),
    "pretension": st.floats(0.0, 0.49),
    "rings": st.integers(2, 10),
    "puncture_threshold_um": st.floats(0.01, 500.0),
    "damping_n_s_per_m_per_mm": st.floats(0.0, 10.0),
})
needle_params = st.fixed_dictionaries({
    "lateral_constraint": st.booleans(),
    "lateral_stiffness_n_per_mm": st.floats(0.01, 5.0),
    "bone_stiffness_n_per_mm": st.floats(0.01, 5.0),
})


def configured(base_cfg, skin, fat, muscle, needle, limit, sweeps):
    cfg = base_cfg
    for name, prm in (("skin", skin), ("fat", fat), ("muscle", muscle)):
        cfg = replace(cfg, name, **prm)
    cfg = replace(cfg, "needle", **needle)
    cfg = replace(cfg, "safety", force_limit_n=limit)
    return replace(cfg, "solver", sweeps_per_tick=sweeps)


def random_walk(seed, n):
    """Tip positions and velocities: thrusts, withdrawals, sideways wiggles, holds and rare jumps,
    around the acupoint at the top of the sphere; velocities either consistent with the motion or
    random over 12 decades (up to 1e9 m/s)."""
    rng = np.random.default_rng(seed)
    dt = 1e-3
    p = np.array([rng.uniform(-5e-3, 5e-3), rng.uniform(-5e-3, 5e-3), rng.uniform(0.0, 3e-3)])
    ps, vs = [], []
    mode, left = 0, 0
    for _ in range(n):
        if left == 0:
            mode = rng.choice(5, p=[0.45, 0.2, 0.15, 0.15, 0.05])
            left = int(rng.integers(5, 60))
            speed = 10 ** rng.uniform(-3.5, 0.0)
        left -= 1
        if mode == 0:  # thrust
            step = np.array([0.0, 0.0, -speed * dt]) + rng.normal(scale=1e-5, size=3)
        elif mode == 1:  # withdraw
            step = np.array([0.0, 0.0, speed * dt]) + rng.normal(scale=1e-5, size=3)
        elif mode == 2:  # sideways
            step = np.append(rng.normal(scale=speed * dt, size=2), 0.0)
        elif mode == 3:  # hold
            step = np.zeros(3)
        else:  # jump anywhere nearby
            step = rng.normal(scale=10e-3, size=3)
            left = 0
        p = p + step
        if rng.random() < 0.3:
            v = rng.normal(size=3) * 10 ** rng.uniform(-3, 9)
        else:
            v = step / dt
        ps.append(p.copy())
        vs.append(v)
    return np.array(ps), np.array(vs)


@pytest.mark.slow  # forty random tissues, each building its own force-net tables (~40 s)
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(skin=layer_params, fat=layer_params, muscle=layer_params, needle=needle_params,
       limit=st.floats(0.05, 10.0), sweeps=st.integers(1, 8), seed=st.integers(0, 2 ** 32 - 1))
def test_force_is_finite_limited_and_zero_outside(base, skin, fat, muscle, needle, limit, sweeps, seed):
    cfg, tissue = base
    model = NeedleModel(configured(cfg, skin, fat, muscle, needle, limit, sweeps), tissue)
    arrays = state_arrays(model)
    assert len(arrays) > 10
    ps, vs = random_walk(seed, 400)
    for p, v in zip(ps, vs):
        f = model.step(p, v)
        assert np.all(np.isfinite(f)), (p, v)
        assert math.sqrt(float(f @ f)) <= limit + 1e-12
        for name, a in arrays:
            if a is model.inp.axis:  # NaN: the needle's axis unknown to this device (TickIn.axis)
                continue
            assert np.all(np.isfinite(a)), name
        outside = np.linalg.norm(p - tissue.centre) > R_SKIN
        if outside and PRESSING not in model.states and not model.inserted:
            assert np.array_equal(f, np.zeros(3)), (p, model.states)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), at=st.integers(0, 199), which=st.integers(0, 5),
       bad=st.sampled_from([math.nan, math.inf, -math.inf]))
def test_a_non_finite_input_anywhere_latches_zero_force(base, seed, at, which, bad):
    cfg, tissue = base
    model = NeedleModel(cfg, tissue)
    arrays = state_arrays(model)
    ps, vs = random_walk(seed, 200)
    for i, (p, v) in enumerate(zip(ps, vs)):
        if i == at:
            (p if which < 3 else v)[which % 3] = bad
        f = model.step(p, v)
        assert np.all(np.isfinite(f))
        if i >= at:
            assert model.fault and np.array_equal(f, np.zeros(3))
            for name, a in arrays:  # the model's copy of this tick's input is not its state
                is_input = a is model.inp.axis or any(np.array_equal(a, x, equal_nan=True) for x in (p, v))
                assert is_input or np.all(np.isfinite(a)), name

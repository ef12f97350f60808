"""The servo's named data (haptic_acu.servo.state) and the step's phases (haptic_acu.servo.step) on their own.

The address tables are checked against NumPy (what compiled code unpacks is the arrays themselves);
the phases against closed forms: Table 1 damping over the layers the needle is in (physical lengths
along the axis), the lateral spring's perpendicular pull in proportion to the needle length held, the safety clamp's scaling and fault latch, on a state written by hand.
"""
import math

import numba as nb
import numpy as np
import pytest

from haptic_acu.servo import step as needle
from haptic_acu.tissue import postpuncture
from haptic_acu.servo import state as ss
from haptic_acu.servo.step import NeedleModel
from physics_helpers import sphere_config, sphere_tissue


@pytest.fixture(scope="module")
def model():
    cfg = sphere_config()
    m = NeedleModel(cfg, sphere_tissue(cfg))
    m.warm_up()
    return m


@nb.njit
def _sums_from_table(t):
    sv = ss.unpack_servo(t, ss.HEADER)
    m = sv.model
    return (m.coeffs.sum(), m.nbr.sum(), m.layer[2].threshold, m.params[0].lmax, sv.state.pos.shape[0],
            sv.state.holes.shape[0], sv.inp.p[2], sv.out.diag.shape[0])


def test_an_address_table_unpacks_to_the_same_arrays(model):
    model.inp.p[:] = [0.0, 0.0, 0.125]
    t = ss.address_table(model.servo)
    assert t[0] == ss.LAYOUT_KEY and t.size == ss.HEADER + ss.SERVO_TABLE
    got = _sums_from_table(t)
    want = (model.model.coeffs.sum(), model.model.nbr.sum(), model.model.layer["threshold"][2],
            model.lmax, model.state.pos.shape[0], ss.MAX_HOLES, 0.125, 1)
    assert got == want


def test_an_address_table_names_the_field_it_refuses():
    bad = ss.TickIn(np.zeros(3, np.float32), np.zeros(3), np.zeros(3), np.zeros(1), np.full(3, np.nan), np.zeros(1))
    with pytest.raises(TypeError, match=r"TickIn\.p"):
        ss.address_table(bad)


def test_the_step_entry_refuses_a_table_for_another_layout(model):
    model.step(np.array([0.0, 0.0, 5e-3]), np.zeros(3))
    tick = int(model.rec["tick"])
    model._step_table[0] += 1  # as a table written for another layout would be
    try:
        model.step(np.array([0.0, 0.0, 5e-3]), np.zeros(3))
        assert int(model.rec["tick"]) == tick  # nothing ran, nothing was written
    finally:
        model._step_table[0] -= 1
    model.step(np.array([0.0, 0.0, 5e-3]), np.zeros(3))
    assert int(model.rec["tick"]) == tick + 1


@nb.njit
def _damping_phase(inp, m, s, out):
    postpuncture.shaft_forces(inp, m, s, out[0])


@nb.njit
def _lateral_phase(inp, m, s, out):
    needle.lateral_guidance(inp, m, s, out[0])


@nb.njit
def _clamp_phase(m, s, out):
    needle.clamp(m, s, out[0])


@pytest.fixture
def fresh(model):
    """The model with every layer punctured along -z through the origin, work zeroed; restored after."""
    snap = model.copy_state()
    model.reset(keep_holes=False)
    model.state.work[:] = np.zeros(1, ss.WORK)
    rec = model.rec
    rec["state"][:] = ss.PUNCTURED
    rec["inserted"] = 1
    rec["axis"][:] = [0.0, 0.0, -1.0]
    rec["entry"][:] = [0.0, 0.0, 0.0]
    rec["bounds"][:] = [0.0, 0.001, 0.006, 0.026]  # the layers along -z
    model.state.work[0]["front"] = 3
    yield model
    model.restore_state(snap)


@pytest.mark.parametrize("depth", [0.0005, 0.003, 0.015, 0.030])
def test_damping_of_the_layers_held_is_table_1(fresh, depth):
    m = fresh
    m.model.params["mechanics"] = ss.TABLE1
    bounds = m.rec["bounds"].copy()
    m.state.work[0]["s_p"] = depth
    v = np.array([0.001, 0.0, -0.02])  # 20 mm/s into the tissue, a little sideways
    m.state.work[0]["tip_v"] = v  # the needle's tip (step.device_tip: the device's, the handle off the skin)
    out = np.zeros(1, ss.DIAG)
    try:
        _damping_phase(m.inp, m.model, m.state, out)
    finally:
        m.model.params["mechanics"] = ss.RICH
    d = m.model.layer["damping"]
    h = [min(max(depth - bounds[j], 0.0), bounds[j + 1] - bounds[j]) for j in range(3)]
    v_ax = 0.02
    want = -sum(d[j] * h[j] for j in range(3)) * v_ax
    assert out[0]["f_damp"] == pytest.approx(want, rel=1e-12)
    np.testing.assert_allclose(m.state.work[0]["f"], [0.0, 0.0, -want], rtol=1e-12, atol=0)
    np.testing.assert_allclose(out[0]["f_layer"], [-d[j] * h[j] * v_ax for j in range(3)], rtol=1e-12)


def test_lateral_guidance_pulls_back_to_the_insertion_line(fresh):
    m = fresh
    m.state.work[0]["tip"] = [0.002, -0.001, -0.010]  # the needle's tip 10 mm deep, (2, -1) mm off the line
    m.rec["lengths"][:] = [0.001, 0.005, 0.004]  # the shaft held over 10 mm
    out = np.zeros(1, ss.DIAG)
    _lateral_phase(m.inp, m.model, m.state, out)
    k = m.model.params[0]["k_lateral"] * 0.010 / m.model.params[0]["needle_length"]
    np.testing.assert_allclose(m.state.work[0]["f"], [-k * 0.002, k * 0.001, 0.0], rtol=1e-12, atol=1e-15)
    assert out[0]["f_lateral"] == pytest.approx(k * math.hypot(0.002, 0.001), rel=1e-12)


def test_the_clamp_scales_to_the_limit_and_latches_a_non_finite_force(fresh):
    m = fresh
    lim = m.model.params[0]["force_limit"]
    m.state.work[0]["f"] = [3.0 * lim, 4.0 * lim, 0.0]
    out = np.zeros(1, ss.DIAG)
    _clamp_phase(m.model, m.state, out)
    np.testing.assert_allclose(out[0]["force"], [0.6 * lim, 0.8 * lim, 0.0], rtol=1e-12)
    assert out[0]["clamped"] == 1.0 and m.rec["fault"] == 0
    m.state.work[0]["f"] = [0.1, math.nan, 0.0]
    out = np.zeros(1, ss.DIAG)
    _clamp_phase(m.model, m.state, out)
    assert not np.any(out[0]["force"]) and out[0]["fault"] == 1.0 and m.rec["fault"] == 1


def _compiled_callees(fn):
    """The numba dispatchers ``fn``'s source names (module globals, ``module.attribute``, its closure)."""
    import types

    from numba.core.dispatcher import Dispatcher

    names = set()

    def walk(code):
        names.update(code.co_names)
        for c in code.co_consts:
            if isinstance(c, types.CodeType):
                walk(c)

    walk(fn.__code__)
    g = fn.__globals__
    cells = [c.cell_contents for c in (fn.__closure__ or ())]
    for v in [g.get(n) for n in names] + cells:
        if isinstance(v, Dispatcher):
            yield v
        elif isinstance(v, types.ModuleType):
            yield from (w for w in (getattr(v, a, None) for a in names) if isinstance(w, Dispatcher))


def test_no_kernel_the_servo_tick_calls_counts_references():
    """The tick's arrays are owned by Python (the model's NamedTuples) or viewed from an address table
    without a reference count; a kernel compiled with numba's reference counting still calls
    NRT_incref / NRT_decref (not inlined) on every array it touches, hundreds of calls a tick. Every
    kernel the step and the replay's tick loop reach, other than those inlined into their caller (which
    take the caller's flags), is compiled without it (``_nrt=False``: it also refuses to allocate)."""
    from haptic_acu.servo.tick import run_ticks

    seen, todo = {}, [needle.step_kernel, run_ticks, needle.reset_servo]
    while todo:
        d = todo.pop()
        key = f"{d.py_func.__module__}.{d.py_func.__qualname__}"
        if key not in seen:
            seen[key] = d
            todo.extend(_compiled_callees(d.py_func))
    assert {"haptic_acu.tissue.shf.eval_point4_grad", "haptic_acu.tissue.netresponse.lookup",
            "haptic_acu.servo.clamp.clamp_force", "haptic_acu.tissue.twirl.wind_step"} <= set(seen)
    counting = sorted(k for k, d in seen.items()
                      if d.targetoptions.get("inline", "never") != "always" and d.targetoptions.get("_nrt", True))
    assert counting == []

"""haptic_acu.servo.rendering against closed forms: a spring tissue in series with the coupling, a damper's
steady force c v, Coulomb stick-slip at the friction level, the continuous-force limit, the
velocity estimate on quantised encoders, faults, and passivity over random closed paths
(hypothesis): the work the rendered force does on the device never exceeds what a sampled spring of
the coupling's stiffness does (K/2 sum |dx|^2, Colgate & Schenkel's K T / 2 damping requirement),
however stiff, viscous or sticky the tissue."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from haptic_acu.servo import rendering as R

DT = 1e-3
STEP = 0.055e-3
LIM = R.DeviceLimits(3.3, 0.88, 1260.0, 3.0)
PAR = R.default_params(LIM, DT, STEP)
K = min(PAR.stiffness_n_per_m, LIM.stiffness_n_per_m)
B = min(PAR.damping_n_s_per_m, LIM.damping_n_s_per_m)
Z = np.array([0.0, 0.0, 1.0])


class LinearTissue:
    """A tissue along ``axis`` through ``w``: spring ``k`` (along and across), damper ``c`` and
    Coulomb friction ``mu`` along the axis; it reports exactly what it is (or ``k_report``)."""

    def __init__(self, k=0.0, c=0.0, mu=0.0, axis=Z, w=np.zeros(3), k_report=None):
        self.k, self.c, self.mu, self.axis, self.w = k, c, mu, np.asarray(axis, float), np.asarray(w, float)
        self.k_report = k if k_report is None else k_report

    def report(self, proxy, released=0.0):
        f = -self.k * (proxy - self.w)
        return R.TissueLocal(f, self.axis.copy(), self.c, self.k_report, self.k_report, self.mu, released)


def drive(path, tissue=None, limits=LIM, params=PAR, quantise=False):
    """Device positions ``path`` (n, 3) through render_step; the tissue re-evaluated at the proxy."""
    state = R.new_state()
    rep = R.no_tissue() if tissue is None else tissue.report(path[0])
    F = np.zeros((len(path), 3))
    status = np.zeros(len(path), dtype=np.int64)
    V = np.zeros((len(path), 3))
    for i, x in enumerate(path):
        xq = STEP * np.round(x / STEP) if quantise else np.asarray(x, float)
        status[i] = R.render_step(limits, params, state, rep, xq)
        F[i] = state.force
        V[i] = state.device_v
        if tissue is not None:
            rep = tissue.report(state.proxy.copy())
    return F, status, V, state


def test_limits_from_hd_converts_the_hd_units_and_refuses_nonsense():
    lim = R.limits_from_hd(3.3, 0.88, 1.26, 0.003)
    assert lim == R.DeviceLimits(3.3, 0.88, pytest.approx(1260.0), pytest.approx(3.0))
    for bad in ((0.0, 0.88, 1.0, 0.003), (3.3, float("nan"), 1.0, 0.003), (3.3, 0.88, -1.0, 0.003),
                (3.3, 0.88, 1.0, float("inf"))):
        with pytest.raises(ValueError, match="device limit"):
            R.limits_from_hd(*bad)


def test_coupling_parameters_are_checked():
    assert R.check_params(PAR) is PAR
    for field, bad in (("stiffness_n_per_m", -1.0), ("damping_n_s_per_m", math.nan), ("dt_s", 0.0),
                       ("continuous_tau_s", math.inf), ("encoder_step_m", -1e-5)):
        with pytest.raises(ValueError, match=field):
            R.check_params(PAR._replace(**{field: bad}))
    assert R.check_params(PAR._replace(encoder_step_m=0.0)).encoder_step_m == 0.0


def test_coupling_stays_within_the_devices_stiffness_and_damping():
    # a request far above the device's nominal values is cut to them: a spring tissue of 1e6 N/m met
    # 1 mm deep renders the coupling's stiffness (in series with a much stiffer tissue: ~K)
    params = PAR._replace(stiffness_n_per_m=1e5, damping_n_s_per_m=1e3)
    path = np.tile([0.0, 0.0, 1e-3], (300, 1))
    F, *_ = drive(path, LinearTissue(k=1e6), params=params)
    series = LIM.stiffness_n_per_m * 1e6 / (LIM.stiffness_n_per_m + 1e6)
    assert F[-1, 2] == pytest.approx(-series * 1e-3, rel=1e-3)


@pytest.mark.parametrize("k_report", [None, 0.0, 20000.0])  # exact, unknown, a 10x upper bound
def test_a_spring_tissue_is_rendered_in_series_with_the_coupling(k_report):
    # the device presses 2 mm into a 2.2 N/mm spring (the muscle net at the break) over 0.2 s and holds
    kt = 2200.0
    z = -2e-3 * np.minimum(1.0, np.arange(600) / 200)
    path = np.column_stack([np.zeros(600), np.zeros(600), z])
    F, *_ = drive(path, LinearTissue(k=kt, k_report=k_report))
    series = K * kt / (K + kt)
    assert F[-1, 2] == pytest.approx(series * 2e-3, rel=1e-6)
    assert np.all(np.abs(F[:, 2]) <= series * 2e-3 * 1.02)  # no overshoot beyond the coupling's damping
    assert np.all(np.abs(F[:, 2] + series * path[:, 2]) <= 0.05)  # follows the series spring as it goes


@pytest.mark.parametrize("c", [48.0, 93.0, 1e5])
def test_a_damper_tissue_renders_c_times_v_in_steady_motion_without_ringing(c):
    # the device moves along the axis at 10 mm/s (quantised by the encoder); Table 1's damping
    # deep in muscle is 48-93 N*s/m: the steady force is c v, at most the device's maximum
    v = 0.01
    n = 3000
    path = np.column_stack([np.zeros(n), np.zeros(n), -v * DT * np.arange(n)])
    F, status, *_ = drive(path, LinearTissue(c=c), quantise=True)
    steady = F[-500:, 2]
    expected = min(c * v, LIM.max_force_n)
    tau = (c + B) / K
    if 5 * tau < n * DT / 2:
        assert np.mean(steady) == pytest.approx(expected, rel=0.02)
        assert np.std(steady) < 0.02  # the encoder steps do not turn into a buzz
    assert np.all(np.diff(F[:, 2]) > -0.03)  # the force builds up without oscillating back


def test_coulomb_friction_sticks_then_slips_at_its_level():
    mu = 0.5
    v = 0.005
    n = 1500
    z = np.concatenate([v * DT * np.arange(n), v * DT * (n - np.arange(n))])  # out and back
    path = np.column_stack([np.zeros(2 * n), np.zeros(2 * n), z])
    F, *_ = drive(path, LinearTissue(mu=mu))
    # stick: the coupling spring loads at K per metre of travel until mu, then it slips at mu
    stick = int(mu / K / (v * DT)) - 5
    np.testing.assert_allclose(F[1:stick, 2], -K * z[1:stick] - B * v * 0, atol=B * v + 1e-3)
    assert np.mean(F[n - 300:n, 2]) == pytest.approx(-mu - 0.0, abs=B * v + 1e-3)
    assert np.mean(F[-300:, 2]) == pytest.approx(mu, abs=B * v + 1e-3)  # reversed: the other way
    assert np.abs(F[:, 2]).max() <= mu + B * v + 1e-3


def test_the_velocity_estimate_suits_quantised_encoders():
    rng = np.random.default_rng(1)
    n = 400
    # a still hand whose stylus dithers between two encoder counts: a raw difference is 55 mm/s
    dither = np.column_stack([np.zeros(n), np.zeros(n), STEP * rng.integers(0, 2, n)])
    _, _, V, _ = drive(dither)
    assert np.abs(V[R.HIST:]).max() <= STEP / ((R.HIST - 1) * DT) * 1.001
    # a steady 10 mm/s, quantised: within 10% after the window filled, and never a whole-step spike
    ramp = np.column_stack([np.zeros(n), 0.01 * DT * np.arange(n), np.zeros(n)])
    _, _, V, _ = drive(ramp, quantise=True)
    assert np.abs(V[100:, 1] - 0.01).max() < 0.001
    assert np.abs(V[:, 1]).max() < 0.02


def test_the_force_never_exceeds_the_devices_maximum():
    path = np.tile([0.0, 0.0, -0.02], (200, 1))
    F, status, *_ = drive(path, LinearTissue(k=1e5))
    assert np.linalg.norm(F, axis=1).max() <= LIM.max_force_n * (1 + 1e-12)
    assert status[-1] & R.CLAMPED


def test_sustained_force_above_the_continuous_limit_ramps_down_and_back():
    # a 2 N push held 40 s, then 0.5 N held 40 s: the output's scale falls no faster than the ramp,
    # the output settles at the continuous limit, the flag says so, and it all comes back after
    push = LinearTissue(k=0.0)
    n = 40000
    state = R.new_state()
    out = np.zeros(2 * n)
    scale = np.zeros(2 * n)
    flags = np.zeros(2 * n, dtype=np.int64)
    x = np.zeros(3)
    for i in range(2 * n):
        f = np.array([0.0, 0.0, 2.0 if i < n else 0.5])
        rep = R.TissueLocal(f, Z.copy(), 0.0, 0.0, 0.0, 0.0, 0.0)
        flags[i] = R.render_step(LIM, PAR, state, rep, x)
        out[i] = np.linalg.norm(state.force)
        scale[i] = state.aux[0]["scale"]
    del push
    assert np.all(np.abs(np.diff(scale)) <= PAR.ramp_per_s * DT * (1 + 1e-9))
    assert out[:200].max() == pytest.approx(2.0, rel=1e-3)  # a short push is not limited
    assert out[n - 2000:n].mean() == pytest.approx(LIM.continuous_force_n, rel=0.02)
    assert np.all(flags[n - 2000:n] & R.LIMITING)
    assert out[-1000:].mean() == pytest.approx(0.5, rel=1e-3) and scale[-1] == 1.0
    assert not np.any(flags[-1000:] & R.LIMITING)


def test_a_fault_zeroes_the_force_in_the_same_tick_and_stays():
    state = R.new_state()
    tis = LinearTissue(k=2000.0)
    x = np.array([0.0, 0.0, -1e-3])
    for _ in range(50):
        R.render_step(LIM, PAR, state, tis.report(state.proxy.copy()), x)
    assert np.linalg.norm(state.force) > 0.3
    assert R.render_step(LIM, PAR, state, tis.report(state.proxy.copy()), np.array([0.0, math.nan, 0.0])) == R.FAULT
    assert np.all(state.force == 0.0)
    assert R.render_step(LIM, PAR, state, tis.report(state.proxy.copy()), x) == R.FAULT  # latched
    assert np.all(state.force == 0.0)
    R.reset(state)
    R.render_step(LIM, PAR, state, tis.report(x), x)
    assert np.all(np.isfinite(state.force))
    # a tissue report that is not finite, or a fault signalled from outside: the same
    bad = R.TissueLocal(np.array([math.inf, 0.0, 0.0]), Z.copy(), 0.0, 0.0, 0.0, 0.0, 0.0)
    assert R.render_step(LIM, PAR, state, bad, x) == R.FAULT and np.all(state.force == 0.0)
    R.reset(state)
    R.render_step(LIM, PAR, state, tis.report(x), x + 1e-3)
    R.signal_fault(state)
    assert np.all(state.force == 0.0) and state.aux[0]["fault"] == 1


def test_a_release_spends_the_coupling_compression_at_once():
    # a device held still 2 mm into a tissue of damping 93 N*s/m and a 2.2 N/mm spring that then breaks
    # (stiffness gone, damping stays): with the release flag the force drops to zero within the tick
    # (the linearised tissue force at the proxy's new place: nothing elastic left, damping left out);
    # without it the damping takes over the coupling's compression, c / (c + B + K T) of it
    def run(flag):
        state = R.new_state()
        tis = LinearTissue(k=2200.0, c=93.0)
        x = np.array([0.0, 0.0, -2e-3])
        for _ in range(1500):  # settled: (c + B) / (K + k) = 33 ms
            R.render_step(LIM, PAR, state, tis.report(state.proxy.copy()), x)
        before = abs(state.force[2])
        broken = LinearTissue(k=0.0, c=93.0)
        R.render_step(LIM, PAR, state, broken.report(state.proxy.copy(), released=flag), x)
        return before, abs(state.force[2])

    before, after = run(1.0)
    assert before > 0.9 and after < 1e-9
    _, slow = run(0.0)
    assert slow == pytest.approx(before * 93.0 / (93.0 + B + K * DT), rel=1e-6)


def test_a_release_under_a_moving_hand_relaxes_the_coupling_without_a_proxy_jump():
    # The device advances at 10 mm/s into a stiff surface that then breaks (nothing left but its
    # damping): the coupling's compression is relaxed in the release tick (the force is the broken
    # tissue's, 0 here), while the proxy's velocity, which the tissue sees next tick and a replay
    # of the recorded proxy path sees too, never exceeds the hand's plus RELEASE_CATCH_UP_M_S
    # (a one-tick jump of the compression once clamped the simulated force at a muscle's break).
    state = R.new_state()
    tis = LinearTissue(k=2200.0, c=93.0)
    speed = 0.01
    x = np.zeros(3)
    for i in range(1500):
        x = np.array([0.0, 0.0, -1e-3 - speed * DT * i])
        R.render_step(LIM, PAR, state, tis.report(state.proxy.copy()), x)
    before = abs(state.force[2])
    gap = state.proxy[2] - x[2]
    assert before > 0.5 and gap > 0.5e-3  # the compression: the device is well past the proxy
    broken = LinearTissue(k=0.0, c=93.0)
    released = 1.0
    speeds, forces = [], []
    n = int(gap / R.RELEASE_CATCH_UP_M_S / DT) + 1500
    for i in range(n):
        x = x - np.array([0.0, 0.0, speed * DT])
        R.render_step(LIM, PAR, state, broken.report(state.proxy.copy(), released=released), x)
        released = 0.0
        speeds.append(-state.proxy_v[2])
        forces.append(abs(state.demand[2]))  # before the continuous-force protection (0.88 N here)
    assert forces[0] < 1e-9  # relaxed in the release tick
    assert max(speeds) <= speed + R.RELEASE_CATCH_UP_M_S + 1e-3, max(speeds)
    # the anchor has rejoined the device (the gap at 5 mm/s) and the coupling has settled (its time
    # constant with the damper, (c + B) / K, is 0.15 s): the damper at the hand's speed, c v
    assert forces[-1] == pytest.approx(93.0 * speed, rel=0.02), forces[-1]


def _closed_path(amps, freqs, phases, n):
    t = np.arange(n + 1) / n
    p = np.zeros((n + 1, 3))
    for a, f, ph in zip(amps, freqs, phases):
        p += np.outer(np.sin(2 * np.pi * f * t + ph) - np.sin(ph), a)
    return p  # starts and ends at the origin


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(amps=st.lists(st.tuples(*[st.floats(-4e-3, 4e-3)] * 3), min_size=1, max_size=3),
       freqs=st.lists(st.integers(1, 4), min_size=3, max_size=3),
       phases=st.lists(st.floats(0, 2 * np.pi), min_size=3, max_size=3),
       k=st.floats(0.0, 3000.0), c=st.floats(0.0, 100.0), mu=st.floats(0.0, 1.0),
       axis=st.tuples(*[st.floats(-1, 1)] * 3), quantise=st.booleans())
def test_the_coupling_is_passive_over_random_closed_paths(amps, freqs, phases, k, c, mu, axis, quantise):
    a = np.array(axis)
    if np.linalg.norm(a) < 0.1:
        a = Z
    a = a / np.linalg.norm(a)
    n = 2000
    path = _closed_path([np.array(x) for x in amps], freqs, phases, n)
    F, *_ = drive(path, LinearTissue(k=k, c=c, mu=mu, axis=a), quantise=quantise)
    dx = np.diff(path, axis=0)
    work_on_device = float(np.sum(F[:-1] * dx))  # force held over each tick, the device moves dx
    sampled_spring = 0.5 * K * float(np.sum(dx * dx))
    assert work_on_device <= sampled_spring + 1e-6


def test_the_passivity_measure_catches_a_naive_stiff_tissue():
    # The same measure for the tissue's 2.2 N/mm rendered directly: K_t/2 sum |dx|^2 > K/2 sum |dx|^2.
    path = _closed_path([np.array([0.0, 1e-3, 3e-3])], [2, 1, 1], [0.3, 0, 0], 2000)
    kt = 2200.0
    F = -kt * path
    dx = np.diff(path, axis=0)
    assert float(np.sum(F[:-1] * dx)) > 0.5 * K * float(np.sum(dx * dx)) + 1e-6


def test_render_step_is_callable_from_a_compiled_tick():
    # what the OMNI's compiled servo tick will do: build the named tuples inside nopython code
    import numba as nb

    @nb.njit(nogil=True)
    def tick(limits, params, state, f, axis, coef, x):
        tissue = R.TissueLocal(f, axis, coef[0], coef[1], coef[2], coef[3], 0.0)
        return R.render_step(limits, params, state, tissue, x)

    state = R.new_state()
    x = np.array([0.0, 0.0, -1e-3])
    for _ in range(300):
        f = -2000.0 * state.proxy
        status = tick(LIM, PAR, state, f, Z.copy(), np.array([0.0, 2000.0, 2000.0, 0.0]), x)
    assert status == 0
    assert state.force[2] == pytest.approx(K * 2000.0 / (K + 2000.0) * 1e-3, rel=1e-6)


def test_tissue_from_diag_reads_the_diag_records_report():
    # the OMNI's compiled tick and the scripted device's model both turn the DIAG record's r_* fields
    # into a TissueLocal through this one helper: every field lands in its place, the vectors copied
    import numba as nb

    from haptic_acu.servo.state import DIAG

    rng = np.random.default_rng(7)
    diag = np.zeros(1, DIAG)
    d = diag[0]
    d["r_force"] = rng.normal(size=3)
    d["r_axis"] = rng.normal(size=3)
    for name in ("r_damping", "r_k_along", "r_k_across", "r_friction", "r_released"):
        d[name] = rng.uniform(0.1, 10.0)

    @nb.njit(nogil=True)
    def read(diag, fb, ab):
        t = R.tissue_from_diag(diag[0], fb, ab)
        return (t.force[0], t.force[1], t.force[2], t.axis[0], t.axis[1], t.axis[2], t.damping,
                t.stiffness_along, t.stiffness_across, t.friction, t.released)

    fb, ab = np.zeros(3), np.zeros(3)
    got = read(diag, fb, ab)
    want = (*d["r_force"], *d["r_axis"], d["r_damping"], d["r_k_along"], d["r_k_across"], d["r_friction"],
            d["r_released"])
    assert got == tuple(float(x) for x in want)
    np.testing.assert_array_equal(fb, d["r_force"])
    np.testing.assert_array_equal(ab, d["r_axis"])
    d["r_force"] = 0.0  # a copy, not a view of the record
    assert np.any(fb != 0.0)


# -- the servo's own report (DIAG r_* fields, needle.render_local) against independent evaluations ----
@pytest.fixture(scope="module")
def needle():
    from haptic_acu.base.config import load_config
    from haptic_acu.servo.step import NeedleModel

    return NeedleModel(load_config())


def _contact_z(m):
    m.reset(keep_holes=False)
    for z in np.arange(5e-3, -10e-3, -5e-6):
        m.step(np.array([0.0, 0.0, z]), np.zeros(3))
        if m.states[0] == 1:
            return float(z)
    raise AssertionError("no skin")


def test_the_pressed_nets_reported_stiffness_is_the_slope_of_its_force(needle):
    # the reported stiffness along the axis against a finite difference of the step's own force,
    # stepping the tip statically 0.6 and 0.62 mm into the skin (a second evaluation, not the table)
    m = needle
    z0 = _contact_z(m)
    out = []
    for d in (0.6e-3, 0.62e-3):
        m.reset(keep_holes=False)
        for z in np.linspace(z0 + 1e-3, z0 - d, 400):
            m.step(np.array([0.0, 0.0, z]), np.zeros(3))
        out.append((float(np.linalg.norm(m.diag["force"])), float(m.diag["r_k_along"]), np.array(m.diag["r_axis"])))
    assert m.states[0] == 1
    slope = (out[1][0] - out[0][0]) / 0.02e-3
    assert slope > 0
    # the table's forward slope over one column step brackets the local slope from above (the nets stiffen)
    assert 0.8 * slope <= out[0][1] <= 3.0 * slope + 50.0, (slope, out[0][1])
    assert abs(abs(out[0][2][2]) - 1.0) < 0.05  # the net's axis: along z at the acupoint


def test_inside_the_tissue_the_report_holds_the_shaft_and_the_lateral_spring(needle):
    """Inside the tissue the report linearises about the shaft: the viscous part is linear in the
    axial speed (its coefficient is r_damping), the friction and viscous parts are left out of
    r_force (the cutting at the tip stays in), the friction level is the breakaway, and the lateral
    spring is as stiff as the held length makes it."""
    m = needle
    z0 = _contact_z(m)
    m.reset(keep_holes=False)
    v = np.array([0.0, 0.0, -0.01])
    for z in np.arange(z0 + 1e-3, z0 - 8e-3, -1e-5):
        m.step(np.array([0.0, 0.0, z]), v)
    assert m.inserted
    d = m.diag
    a = np.array(m.axis)
    v_ax = float(v @ a)
    assert d["r_damping"] > 0
    assert abs(-float(d["f_viscous"]) / v_ax - float(d["r_damping"])) <= 1e-9 * float(d["r_damping"])
    shaft = float(d["f_damp"]) - float(d["f_cut"])
    assert shaft == pytest.approx(float(d["f_friction"]) + float(d["f_viscous"]), abs=1e-12)
    np.testing.assert_allclose(np.array(d["r_force"]), np.array(d["force"]) - shaft * a, atol=1e-12)
    np.testing.assert_allclose(np.array(d["r_axis"]), a)
    held = float(np.sum(m.rec["lengths"]))
    k_held = float(m.model.params[0]["k_lateral"]) * min(held / float(m.model.params[0]["needle_length"]), 1.0)
    assert float(d["r_k_across"]) == pytest.approx(k_held, rel=1e-12) and 0 < k_held
    assert float(d["r_released"]) == 0.0 and float(d["r_friction"]) == float(d["breakaway"]) > 0.0


def test_a_puncture_is_reported_as_a_release(needle):
    m = needle
    m.reset(keep_holes=False)
    released = []
    for z in np.arange(5e-3, -6e-3, -1e-5):
        m.step(np.array([0.0, 0.0, z]), np.array([0.0, 0.0, -0.01]))
        released.append((float(m.diag["puncture"]), float(m.diag["r_released"])))
    punct = [r for p, r in released if p >= 0]
    assert punct and all(r == 1.0 for r in punct)
    assert sum(r for _, r in released) == len(punct)


def test_the_scripted_devices_model_renders_the_simulated_force_through_an_omnis_limits(needle):
    # haptic_acu.servo.devicemodel on a slow press into the skin: zero in the air, the simulated force
    # within 0.1 N while the hand moves smoothly, never above the OMNI's 3.3 N
    from haptic_acu.servo import devicemodel

    m = needle
    z0 = _contact_z(m)
    m.reset(keep_holes=False)
    dm = devicemodel.new(DT)
    v = np.array([0.0, 0.0, -0.005])
    sim, ren = [], []
    for z in np.arange(z0 + 2e-3, z0 - 1.2e-3, -5e-6):
        m.inp.p[:] = (0.0, 0.0, z)
        devicemodel.model_tick(dm, m.inp, m.out.diag)
        sim.append(np.array(m.step(np.array([0.0, 0.0, z]), v)))
        ren.append(m.inp.fr.copy())
    sim, ren = np.array(sim), np.array(ren)
    n = len(sim)
    air = np.linalg.norm(sim, axis=1) == 0.0
    assert np.abs(ren[air][:100]).max() < 1e-6
    steady = slice(n // 2, n)
    assert np.abs(sim[steady, 2]).max() > 0.1
    assert np.abs(ren[steady] - sim[steady]).max() < 0.1
    assert np.linalg.norm(ren, axis=1).max() <= 3.3

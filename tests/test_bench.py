"""The bench's pieces: the NumPy reference agrees with the compiled servo step, the pyshtools
convention mapping is right, and every piece runs (tiny sizes) into a JSON with every key.

No timing is asserted anywhere (the machines are shared): only that the bench measures the thing it
says it measures, and that its peers compute the same answers.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import sys

import numpy as np
import pytest

from haptic_acu.bench import run, scenarios
from haptic_acu.bench.numpy_reference import HexNet, NumpyNeedle, SHBasis
from haptic_acu.tissue import shf
from haptic_acu.tissue.forcenet import lattice, n_particles
from haptic_acu.servo.step import PRESSING, PUNCTURED
from haptic_acu.session.trajectory import TrajectoryWriter


# ---- the NumPy reference ---------------------------------------------------------------------------

def test_reference_basis_is_the_real_orthonormal_basis():
    # Exact quadrature on a Gauss-Legendre x uniform grid: the reference's basis (from scipy's complex
    # harmonics) is orthonormal, and its columns are the package's (same order, phase, normalisation).
    lmax = 6
    x, wx = np.polynomial.legendre.leggauss(lmax + 1)
    n_phi = 2 * lmax + 2
    th, ph = np.meshgrid(np.arccos(x), np.arange(n_phi) * 2 * np.pi / n_phi, indexing="ij")
    w = np.repeat(wx, n_phi) * (2 * np.pi / n_phi)
    B = SHBasis(lmax).rows(th.ravel(), ph.ravel())
    np.testing.assert_allclose(B.T @ (B * w[:, None]), np.eye((lmax + 1) ** 2), atol=1e-12)
    np.testing.assert_allclose(B, shf.real_sph_harm(lmax, th, ph), atol=1e-13)


@pytest.mark.parametrize("w", [2, 5, 10])
def test_reference_lattice_is_the_hexagonal_net_and_three_coloured(w):
    h = HexNet(w)
    assert h.n == n_particles(w) == lattice(w).ring.size
    np.testing.assert_array_equal(np.bincount(h.ring)[1:], [1] + [6 * (j - 1) for j in range(2, w + 1)])
    # neighbours are symmetric, one spacing apart, and never share a colour
    for i in range(h.n):
        for j in h.nbr[i][h.nbr[i] >= 0]:
            assert i in h.nbr[j]
            assert np.isclose(np.linalg.norm(h.plane[i] - h.plane[j]), 1.0)
    colour = np.full(h.n, -1)
    for c, idx in enumerate(h.colours):
        colour[idx] = c
    assert colour[0] == -1 and np.all(colour[1:] >= 0)  # N1 is held, everyone else in one colour
    for i in range(1, h.n):
        for j in h.nbr[i][h.nbr[i] > 0]:
            assert colour[i] != colour[j]


def _converge(model, ref, p, sweeps=200, max_ticks=40):
    """Hold the tip at ``p`` with ``sweeps`` sweeps per tick until neither force changes by more
    than 1e-13 N between ticks; returns both forces."""
    saved = model.model.params["sweeps"][0]
    model.model.params["sweeps"][0] = sweeps
    fc_prev = fr_prev = None
    try:
        for _ in range(max_ticks):
            fc = model.step(p, np.zeros(3)).copy()
            fr = ref.step(p, np.zeros(3), sweeps=sweeps).copy()
            if fc_prev is not None and np.abs(fc - fc_prev).max() < 1e-13 and np.abs(fr - fr_prev).max() < 1e-13:
                return fc, fr
            fc_prev, fr_prev = fc, fr
    finally:
        model.model.params["sweeps"][0] = saved
    raise AssertionError("the static press did not converge")


def test_reference_matches_compiled_step_on_a_converged_static_press():
    # w = 10 skin net (271 particles) pressed and never punctured, as in the benchmark. Both solve
    # the same static equilibrium (the net's energy is strictly convex: K > 0 on every particle), in
    # different sweep orders, so they agree once both have converged. Both stop when the force no
    # longer changes by 1e-13 N; a residual position error d gives a force error of at most
    # (K + 6 ks) d, so 1e-9 N leaves orders of magnitude of margin and still catches any difference
    # in the model (a 1e-6 relative change of K or ks, a wrong neighbour, a wrong normal).
    # (The servo's default tabulated response is checked against both solvers in test_netresponse.py.)
    sc = scenarios.press(10, layer=0, w=10)
    cfg = scenarios.config_copy(sc.cfg, servo_net="sweeps")
    model = scenarios.model_for(cfg)
    ref = NumpyNeedle(cfg, model.tissue)
    for p, v in zip(sc.pre_P, sc.pre_V):
        model.step(p, v)
        ref.step(p, v)
    assert model.states == (PRESSING, 0, 0) and ref.states[0] == PRESSING
    z_c = sc.pre_P[-1, 2]
    forces = []
    for depth in (0.4e-3, 1.2e-3):
        fc, fr = _converge(model, ref, np.array([0.0, 0.0, z_c - depth]))
        np.testing.assert_allclose(fr, fc, rtol=0, atol=1e-9)
        forces.append(fc[2])
    assert 0.1 < forces[0] < forces[1]  # a real press: the surface pushes back, harder when deeper


def test_reference_matches_compiled_step_through_every_layer():
    # The default tissue (its nets are small: w = 3 / 4 / 4), 10 mm/s straight in to 20 mm below the
    # skin, then a lift-thrust stroke. With 20 sweeps per tick (both), the small nets track their
    # static solutions closely enough that their ring-w deflections differ by a few per cent of one
    # tick's change at most, so each layer breaks on the same tick. (On a w = 10 net the two sweep
    # orders lag the static solution by visibly different amounts and a break can fall one tick
    # apart: the converged comparison above covers such a net.) While a layer is pressed the forces
    # differ only by what 20 sweeps leave unsolved: 1e-4 N against presses of 0.2-0.6 N. Once every
    # layer is broken no net is left and the force (damping of the layers passed, lateral spring,
    # clamp) depends only on where the punctures happened, so the two agree to rounding.
    cfg = scenarios.config_copy(sweeps_per_tick=20, servo_net="sweeps")
    model = scenarios.model_for(cfg)
    ref = NumpyNeedle(cfg, model.tissue)
    P1, V1 = scenarios.straight(1e-3, -20e-3, 0.01)
    P2, V2 = scenarios.stroke(-20e-3, -4e-3, 1000, period_s=1.0 / 0.75)
    P, V = np.vstack([P1, P2]), np.vstack([V1, V2])
    punct_c, punct_r = [], []
    after_all = []
    for i, (p, v) in enumerate(zip(P, V)):
        fc = model.step(p, v).copy()
        fr = ref.step(p, v).copy()
        if model.diag["puncture"] >= 0:
            punct_c.append((int(model.diag["puncture"]), i))
        if ref.punctured_now >= 0:
            punct_r.append((ref.punctured_now, i))
        if all(s == PUNCTURED for s in model.states) and not model.diag["puncture"] >= 0:
            after_all.append(np.abs(fc - fr).max())
        else:
            assert np.abs(fc - fr).max() < 1e-4, (i, fc, fr)
    assert [k for k, _ in punct_c] == [0, 1, 2]
    assert punct_r == punct_c
    assert math.isclose(ref.offset, model.offset, rel_tol=0, abs_tol=1e-15)
    assert len(after_all) > 1000 and max(after_all) < 1e-9
    assert np.abs(fc).max() > 0.05  # the stroke meets real damping, not zero force


def test_reference_clamps_and_latches_faults_like_the_compiled_step():
    sc = scenarios.press(300, layer=0, w=4)
    limit = 0.02  # N: well under what the press reaches (the fine-needle skin: about 0.06 N by its end)
    clamped = dataclasses.replace(sc.cfg, safety=dataclasses.replace(sc.cfg.safety, force_limit_n=limit))
    model = scenarios.model_for(clamped)
    ref = NumpyNeedle(clamped, model.tissue)
    free = NumpyNeedle(sc.cfg, model.tissue)  # the config's own limit (3.3 N) is not reached here
    n_clamped = 0
    for p, v in zip(np.vstack([sc.pre_P, sc.P]), np.vstack([sc.pre_V, sc.V])):
        fc = model.step(p, v).copy()
        fr = ref.step(p, v).copy()
        ff = free.step(p, v).copy()
        if np.linalg.norm(ff) > limit:
            n_clamped += 1
            np.testing.assert_allclose(fr, ff * limit / np.linalg.norm(ff), rtol=1e-9)  # scaled, not cut
        else:
            np.testing.assert_array_equal(fr, ff)
        assert np.linalg.norm(fr) <= limit * (1 + 1e-12) and np.linalg.norm(fc) <= limit * (1 + 1e-12)
    assert n_clamped > 100
    for m in (ref, model):
        assert np.all(m.step(np.array([np.nan, 0.0, 0.0]), np.zeros(3)) == 0.0)
        assert np.all(m.step(sc.P[-1], np.zeros(3)) == 0.0)  # latched: finite input no longer helps
    assert ref.fault and model.fault


# ---- pyshtools ---------------------------------------------------------------------------------------

def test_pyshtools_mapping_round_trips():
    c = np.random.default_rng(3).standard_normal((7 + 1) ** 2)
    cilm = run.to_pyshtools(c)
    assert cilm.shape == (2, 8, 8)
    # cosine terms for m <= l only, no sine term at m = 0
    assert np.all(cilm[1, :, 0] == 0.0) and np.all(np.triu(cilm[0], 1) == 0.0) and np.all(np.triu(cilm[1], 1) == 0.0)
    assert cilm[0, 3, 2] == c[3 * 3 + 3 + 2] and cilm[1, 3, 2] == c[3 * 3 + 3 - 2]
    np.testing.assert_array_equal(run.from_pyshtools(cilm), c)


def test_pyshtools_agrees_on_evaluation_and_fit():
    psh = pytest.importorskip("pyshtools")
    # A band-limited surface with known coefficients, sampled through scipy's harmonics (the
    # reference basis, independent of ours and of pyshtools); both fits must recover it.
    lmax = 15
    rng = np.random.default_rng(7)
    c_true = rng.standard_normal((lmax + 1) ** 2) * 1e-3
    c_true[0] = 0.07 * math.sqrt(4 * math.pi)
    th, ph, _ = run.fit_samples(2000)
    values = SHBasis(lmax).rows(th, ph) @ c_true
    lat, lon = run.lat_lon(th, ph)
    np.testing.assert_allclose(psh.expand.MakeGridPoint(run.to_pyshtools(c_true), lat, lon, norm=4, csphase=-1),
                               values, rtol=0, atol=1e-12)
    cilm, _ = psh.expand.SHExpandLSQ(values, lat, lon, lmax, norm=4, csphase=-1)
    np.testing.assert_allclose(run.from_pyshtools(cilm), c_true, rtol=0, atol=1e-10)
    np.testing.assert_allclose(shf.fit(th, ph, values, lmax), c_true, rtol=0, atol=1e-10)


# ---- the pieces, tiny ------------------------------------------------------------------------------

def _percentile_object(p):
    assert set(p) >= {"p50", "p99", "p999", "max"}
    assert 0 <= p["p50"] <= p["p99"] <= p["p999"] <= p["max"]


@pytest.mark.slow  # calling step_kernel straight from Python compiles it for that call's signature (~13 s)
def test_servo_scenario_times_one_step_three_ways():
    sc = scenarios.press(50, layer=0, w=4)
    r = run.servo_scenario(sc, 50, numpy_ticks=10)
    for way in ("step", "kernel", "dispatch", "compiled", "numpy"):
        _percentile_object(r[way])
    assert r["step"]["n"] == r["kernel"]["n"] == 50 and r["compiled"]["n"] == 50 // run.BLOCK
    assert r["particles"] == n_particles(4)
    assert r["ways_agree"]  # the same kernel on the same path ends in the same state, however called
    assert r["numpy_states_match"]


def test_looped_trajectory_repeats_the_file(tmp_path):
    from haptic_acu.session.trajectory import load

    src = tmp_path / "one.csv"
    with TrajectoryWriter(src) as w:
        w.append_rows([[0.0, 0.0, 0.0, 5e-3], [0.5, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 5e-3]])
    dur = run.looped_trajectory(src, tmp_path / "loop.csv", 2.2)
    one, loop = load(src), load(tmp_path / "loop.csv")
    assert math.isclose(dur, loop.duration_s) and loop.duration_s >= 2.2
    period = 1.0 + 0.5  # the file's length plus one sample interval between copies (held still)
    t = np.linspace(0.0, 1.0, 41)
    copies = int(round((loop.duration_s + 0.5) / period))
    assert copies >= 2
    for c in range(copies):
        np.testing.assert_allclose(loop.position_at(t + c * period), one.position_at(t), atol=1e-9)


def test_sh_rows_say_pyshtools_is_missing_when_it_is(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyshtools", None)  # what `import pyshtools` meets when not installed
    tiny = dataclasses.replace(run.QUICK, sh_repeats=1, fit_samples=200, sh_grid=(4, 8))
    coeffs = np.random.default_rng(0).standard_normal((3, (4 + 1) ** 2))
    res = run.sh(tiny, coeffs)
    _percentile_object(res["shf_eval_ms"])
    _percentile_object(res["shf_fit_ms"])
    assert res["pyshtools_eval_ms"] is None and res["pyshtools_fit_ms"] is None
    assert res["shf_speedup_vs_pyshtools"] is None
    assert any("pyshtools not installed" in n for n in res["notes"])


@pytest.mark.slow
@pytest.mark.serial  # counts the ticks of a real-time second
def test_loop_runs_without_the_rerun_sink_and_says_so(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "haptic_acu.session.rerun_log", None)
    traj = tmp_path / "short.csv"
    with TrajectoryWriter(traj) as w:
        w.append_rows([[0.0, 0.0, 0.0, 1e-3], [0.2, 0.0, 0.0, -1e-3]])
    policy = os.sched_getscheduler(0)
    res = run.loop(dataclasses.replace(run.QUICK, loop_s=0.3, floor_s=0.2, trajectory=str(traj)))
    assert os.sched_getscheduler(0) == policy  # the engine's SCHED_FIFO does not outlive the loop
    assert res["loop"]["rerun_rrd"] is False and any("rerun logging not available" in n for n in res["notes"])
    assert 200 < res["ticks"] < 400 and res["loop"]["frames"] > 5  # 0.3 s at 1 kHz, visual frames ran
    _percentile_object(res["loop_period_error_us"])
    assert res["machine_floor"]["duration_s"] == 0.2 and res["compiled_floor"]["ticks"] == 200  # the floors ran, 0.2 s


@pytest.mark.slow
def test_collect_tiny_has_every_key_and_a_table(tmp_path):
    traj = tmp_path / "short.csv"
    with TrajectoryWriter(traj) as w:  # press the skin through and come back out: 0.9 s
        w.append_rows([[0.0, 0.0, 0.0, 1e-3], [0.4, 0.0, 0.0, -3e-3], [0.9, 0.0, 0.0, 1e-3]])
    tiny = dataclasses.replace(
        run.QUICK, servo_ticks=30, numpy_ticks=5, numpy_scenarios=("press_skin_w10",), loop_s=0.3, loop_plain_s=0.2,
        sh_repeats=1,
        fit_samples=600, sh_grid=(8, 16), springback_calls=20, replay_runs=1, cold_runs=1, scaling_ticks=25,
        scaling_w=(3, 4), scaling_lmax=(2, 4), trajectory=str(traj), cohort_sessions=0, first_run=False,
        fem_mesh_ratio=4.0)  # the FEM rows' build on a coarser mesh: the same assembly, solve and condensation
    res = run.collect(tiny)
    for key in run.REQUIRED_KEYS:
        assert key in res, key
    for name in ("press_skin_w10", "press_muscle_w10", "inside_muscle"):
        _percentile_object(res["servo_tick_us"][name])
    for name in ("press_skin_w10", "press_muscle_w10"):  # the previous design, for comparison
        _percentile_object(res["servo_tick_sweeps_us"][name])
    assert set(res["net_table_build"]) == {"skin", "fat", "muscle", "skin_w10_never_breaks"}
    assert all(t["build_s"] > 0 and t["rows"] > 8 for t in res["net_table_build"].values())
    _percentile_object(res["loop_period_error_us"])
    assert 0 < res["ticks"] and 0 <= res["missed_ticks"] <= res["ticks"]
    assert res["loop_no_rerun"]["ticks"] > 0
    assert res["loop_python_servo"]["ticks"] > 0 and res["loop_rerun_in_process"]["ticks"] > 0
    for key in ("shf_eval_ms", "shf_fit_ms", "springback_us"):
        _percentile_object(res[key])
    assert res["replay_speed_x"]["no_rrd"] > 0 and res["cold_start_s"]["first_tick"] > 0
    assert set(res["scaling"]["servo_tick_us"]) == {"3", "4"} and set(res["scaling"]["sh_eval_ms"]) == {"2", "4"}
    assert set(res["scaling"]["servo_tick_sweeps_us"]) == {"3", "4"}
    assert res["cohort"] is None and res["first_run_s"] is None  # not asked for (measured below)
    assert len(res["targets"]) == 24 and all(t["pass"] in (True, False, None) for t in res["targets"])
    md = res["models"]  # every tissue model's tick, wall and CPU, and the FEM's and BEM's hemispherical tips
    from haptic_acu.base.config import MODEL_KINDS
    assert set(md["model_tick_us"]) == set(md["model_tick_cpu_us"]) == set(MODEL_KINDS) | set(run.MODEL_VARIANTS)
    assert set(md["model_build_s"]) == set(md["model_tick_us"]) and md["model_table_bytes"]["fem"] > 0
    for label, cpu in md["model_tick_cpu_us"].items():
        _percentile_object(cpu["press_skin"])
        assert cpu["press_skin"]["p50"] > 0
    if res["pyshtools_eval_ms"] is not None:
        assert res["sh_agreement_m"]["fit_surface_max_abs"] < 1e-10
    table = run.format_table(res)
    assert "servo tick, press_skin_w10 (271 particles)" in table
    assert all(t["target"] in table for t in res["targets"])
    # the closed-loop buzz table: both grips, the insertion and the hold (quick), every puncture a drop
    for grip in ("loose", "firm"):
        m = res["closed_loop"][grip]["rendered"]
        assert set(m["buzz_n"]) == {"insert", "hold"} and all(0 <= v < 0.05 for v in m["buzz_n"].values())
        assert m["punctures"] and all(p["min_within_20ms_n"] <= 0.5 * p["before_n"] for p in m["punctures"])
    assert "closed loop (45 g stylus" in table and res["loop_pinned"]["ticks"] > 0
    cf = res["compiled_floor"]  # the compiled loop's timing with no work: as long as the plain loop
    assert cf["ticks"] == 200 and 0 <= cf["skipped_ticks"] <= cf["missed_ticks"] <= cf["ticks"]
    assert cf["period_error_us"]["n"] == cf["ticks"] - cf["skipped_ticks"]
    assert "machine floor: compiled loop timing, no work, pinned" in table
    out = tmp_path / "bench.json"
    run.write_json(res, out)
    assert set(json.loads(out.read_text())) == set(res)


def test_split_by_steal_counts_misses_inside_and_outside_steal_free_windows():
    # Three 1 s windows; the hypervisor took 20 ms in the middle one. 3000 ticks at 1 ms from t0 = 10 s,
    # late by 2 ms at ticks 100 (first window), 1500 and 1501 (middle) and 2999 (last): the split
    # must put one miss in the quiet windows' 2000 ticks and two in the middle's 1000.
    from haptic_acu.bench.measure import StealSampler, split_by_steal

    s = StealSampler()
    s.samples = [(10.0, 500), (11.0, 500), (12.0, 502), (13.0, 502)]
    errs = np.full(3000, 1e-6)
    errs[[100, 1500, 1501]] = 2e-3
    errs[2999] = 5e-4  # late, but within the period: not a miss
    out = split_by_steal(errs, 10.0, 1e-3, s)
    assert out["windows"] == 3 and out["quiet_windows"] == 2
    assert out["quiet_ticks"] == 2000 and out["quiet_missed"] == 1
    assert out["other_ticks"] == 1000 and out["other_missed"] == 2
    assert out["stolen_s"] == pytest.approx(2 / s.hz)
    assert out["quiet_period_error_us"]["max"] == pytest.approx(2000.0)
    assert out["steal_share"] == pytest.approx((2 / s.hz) / (3.0 * (os.cpu_count() or 1)))


@pytest.mark.slow
@pytest.mark.serial  # counts the ticks of a real-time second
def test_omni_loop_runs_both_callbacks_through_the_emulator():
    sys.path.insert(0, os.path.dirname(__file__))
    try:
        from hd_emulator.build import find_compiler
    finally:
        sys.path.pop(0)
    if find_compiler() is None:
        pytest.skip("no C compiler to build the HD API emulator")
    res = run.omni_loop(dataclasses.replace(run.QUICK, omni_s=1.0))["omni_loop"]
    for servo in ("compiled", "python"):
        r = res[servo]
        assert r["servo_loop"] == servo, r
        assert 500 <= r["ticks"] <= 1001 and 0 <= r["missed_ticks"] <= r["ticks"]  # 1 s; a loaded host costs ticks
        assert 0 <= r["period_error_us"]["p50"] <= r["period_error_us"]["p99"] <= r["period_error_us"]["max"]


# (the first-run row, bench.run.first_run, is tested in test_wheel.py: its replays compile every kernel
# from empty caches, the compile the installed wheel's commands need anyway)

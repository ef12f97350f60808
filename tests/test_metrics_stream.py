"""Per-insertion metrics streamed in bounded memory (haptic_acu/analysis/insertion_stream.py)
against the batch functions that hold every row: metrics.session_metrics / find_troughs and
technique.turning_points. Tolerance: the JSON (rounded to 1 um, 0.1 mN, 0.1 ms, 0.01 deg) is
identical; the raw prominences equal to the bit."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from haptic_acu.base.config import load_config
from haptic_acu.analysis.insertion_stream import BUFFER_ROWS, TroughScan, _zz_step
from haptic_acu.analysis.metrics import SessionMetricsScan, find_troughs, session_metrics
from haptic_acu.servo.samples import COL, NCOL
from haptic_acu.analysis.technique import turning_points

ROOT = Path(__file__).resolve().parent.parent


def _signals():
    rng = np.random.default_rng(11)
    yield np.round(np.cumsum(rng.normal(size=3000)), 1)
    yield np.round(np.cumsum(rng.integers(-1, 2, size=4000)) * 0.055, 3)
    yield 20 + 2 * np.cos(np.linspace(0, 40, 6000)) + rng.normal(scale=0.05, size=6000)
    yield np.array([0, 1, 1, 1, 0, 2, 2, 0, 0, 3, 3, 3, 3, 1, 1, 5, 5], dtype=float)
    yield np.array([5, 4, 4, 4], dtype=float)
    yield np.concatenate([np.linspace(0, 25, 2500), 22 + 3 * np.cos(np.linspace(0, 60, 8000))])


def _blocks(n, rng):
    i = 0
    while i < n:
        k = int(rng.choice([1, 2, 5, 64, 1000]))
        yield i, min(n, i + k)
        i += k


@pytest.mark.parametrize("prom", [0.0, 0.5, 1.0, 3.0])
def test_trough_scan_is_find_troughs(prom):
    """Streamed troughs and prominences (random block splits) = find_troughs (itself = scipy's)."""
    rng = np.random.default_rng(1)
    for depth in _signals():
        want, want_prom = find_troughs(depth, prom)
        ts = TroughScan(prom)
        t = np.arange(depth.size) * 1e-3
        for a, b in _blocks(depth.size, rng):
            ts.feed(a, (-depth[a:b]).tolist(), t[a:b].tolist())
        got = ts.finish()
        assert [g[0] for g in got] == want.tolist()
        assert [g[2] for g in got] == want_prom.tolist()  # the same bits
        assert [g[1] for g in got] == t[want].tolist()


def test_trough_scan_from_a_record_equals_the_sliced_signal():
    """Troughs of depth[k:] for k a depth record (every earlier sample shallower) = the whole signal's
    troughs from k on, with the same prominences: why the lift-thrust start can be applied last."""
    rng = np.random.default_rng(2)
    for depth in _signals():
        prior = np.maximum.accumulate(np.concatenate(([-np.inf], depth)))[:-1]
        records = np.flatnonzero(depth > prior)
        idx, prom = find_troughs(depth, 1.0)
        for k in rng.choice(records, size=min(10, records.size), replace=False):
            i2, p2 = find_troughs(depth[k:], 1.0)
            keep = idx >= k
            assert (i2 + k).tolist() == idx[keep].tolist() and p2.tolist() == prom[keep].tolist()


@pytest.mark.parametrize("ms", [1.0, 5.0])
def test_zigzag_is_turning_points(ms):
    for x in _signals():
        want = turning_points(x, ms).tolist()
        zz, cand, got = np.zeros(4), None, []  # the compiled passes' rule, one sample per call
        for i, v in enumerate(x.tolist()):
            ev = _zz_step(zz, float(ms), v)
            if ev == 2:
                got.append(cand)
            if ev:
                cand = i
        assert got == want


# ------------------------------------------------------------------ whole sessions: streamed = batch
@pytest.fixture(scope="module")
def cfg():
    return load_config()


def _stream(rows, cfg, tissue=None, ref=None, seed=0, punct=()):
    rng = np.random.default_rng(seed)
    scan = SessionMetricsScan(cfg, tissue, reference_rows=ref)
    for a, b in _blocks(len(rows), rng):
        scan.feed(rows[a:b])
    return scan, scan.result(list(punct))


BUNDLED = sorted(p.stem for p in (ROOT / "trajectories").glob("*.csv"))


@pytest.mark.slow
@pytest.mark.parametrize("name", BUNDLED)
def test_bundled_trajectories_streamed_equal_batch(cfg, name):
    """Every bundled trajectory replayed: the streamed per-insertion metrics (random block splits)
    equal session_metrics on all the rows, JSON for JSON (twirl files with their reference replay)."""
    from haptic_acu.session.replay import replay_rows
    from haptic_acu.session.report import SessionScan, puncture_records, tip_depth_m
    from haptic_acu.tissue.body import Tissue

    path = ROOT / "trajectories" / f"{name}.csv"
    rows = replay_rows(path, cfg)
    tissue = Tissue.from_config(cfg)
    ref = replay_rows(path, cfg, roll=False) if name.startswith("twirl") else None
    punct = puncture_records(SessionScan(tissue).feed(rows, tip_depth_m(rows[:, COL["x_m"]:COL["x_m"] + 3], tissue)))
    whole = session_metrics(rows, cfg, tissue, punctures=punct, reference_rows=ref)
    for seed in (0, 1):
        _, got = _stream(rows, cfg, tissue, ref, seed, punct)
        assert json.dumps(got, sort_keys=True) == json.dumps(whole, sort_keys=True)
    if ref is not None:
        assert any(i["technique"]["grasp_felt"] is not None for i in whole["per_insertion"])


def _long_insertion(hold_s: float, deeper_after: bool = False):
    """Synthetic rows: press 0.5 mm, thrust to 25 mm at 10 mm/s (fat and muscle depth-frame steps of
    1 mm on the way), then lift-thrust 3 mm at 0.5 Hz for ``hold_s``, out. With ``deeper_after``
    the strokes end 2 mm deeper (the deepest point comes after BUFFER_ROWS)."""
    dt = 1e-3
    u = np.array([0.1, 0.05, -1.0])
    u /= np.linalg.norm(u)
    s_in = np.arange(0.0, 25.5, 10.0 * dt)  # mm along u
    th = np.arange(0.0, hold_s, dt)
    s_hold = 25.0 - 1.5 * (1 - np.cos(2 * np.pi * 0.5 * th))
    if deeper_after:
        s_hold = s_hold + 2.0 * (th > 0.8 * hold_s) * np.minimum(1.0, (th - 0.8 * hold_s) / 2.0)
    s_out = np.arange(s_hold[-1], -1.0, -10.0 * dt)
    s = np.concatenate([s_in, s_hold, s_out])
    n = s.size
    rows = np.zeros((n, NCOL))
    t = np.arange(n) * dt
    rows[:, COL["t_s"]] = t
    rows[:, COL["tick"]] = np.arange(n)
    rows[:, COL["x_m"]:COL["x_m"] + 3] = (s[:, None] - 0.5) * u * 1e-3
    state = np.where(s < 0.5, 1, 2)
    state[(np.arange(n) > s_in.size) & (s < 0.5)] = 0
    rows[:, COL["state_skin"]] = state
    depth = (s - 0.5) - 1.0 * (s > 5.0) - 1.0 * (s > 12.0)  # the frame's steps at fat, muscle
    rows[:, COL["depth_skin_m"]] = np.where(state == 2, depth, 0.0) * 1e-3
    punct = np.full(n, -1.0)
    punct[np.argmax(s >= 0.5)] = 0
    punct[np.argmax(s > 5.0)] = 1
    punct[np.argmax(s > 12.0)] = 2
    rows[:, COL["puncture"]] = punct
    rows[:, COL["fx_n"]:COL["fx_n"] + 3] = (0.5 + 0.2 * np.gradient(s))[:, None] * -u[None, :] * 3
    rows[:, COL["f_lateral_n"]] = 0.3 + 0.3 * np.sin(t)
    rows[:, COL["f_muscle_n"]] = np.where(s > 12.0, 0.4 + 0.1 * np.sin(3 * t), 0.0)
    rows[:, COL["roll_deg"]] = np.where(state == 2, 30 * np.sin(2 * np.pi * 1.0 * t), 0.0)
    rows[:, COL["torque_nmm"]] = np.cos(t)
    return rows


def test_long_insertion_streamed_equals_batch(cfg):
    """An insertion four times BUFFER_ROWS long, its deepest point in the first 20 s: exact."""
    rows = _long_insertion(4 * BUFFER_ROWS * 1e-3)
    whole = session_metrics(rows, cfg)
    scan, got = _stream(rows, cfg, seed=3)
    assert whole["insertions"] == 1
    ins = whole["per_insertion"][0]
    assert ins["lift_thrust"]["cycles"] >= 38 and ins["technique"]["twirl"]["cycles"] > 70
    assert json.dumps(got, sort_keys=True) == json.dumps(whole, sort_keys=True)
    assert scan.streams[0].step_error_bound_m == 0.0


def test_long_insertion_going_deeper_late_is_within_the_stated_bound(cfg):
    """Deepest point after BUFFER_ROWS: the steps use the direction at 20 s; every number but the
    continuous depth's is exact, and those differ by no more than step_error_bound_m."""
    rows = _long_insertion(3 * BUFFER_ROWS * 1e-3, deeper_after=True)
    whole = session_metrics(rows, cfg)["per_insertion"][0]
    scan, got = _stream(rows, cfg, seed=4)
    got = got["per_insertion"][0]
    bound_mm = scan.streams[0].step_error_bound_m * 1e3
    assert 0.0 < bound_mm < 1e-3
    for k in ("max_depth_mm", "angle_deg", "insertion_speed_mm_s", "peak_layer_force_n", "lateral"):
        assert got[k] == whole[k]
    assert got["lift_thrust"]["cycles"] == whole["lift_thrust"]["cycles"]
    assert got["lift_thrust"]["mean_amplitude_mm"] == pytest.approx(whole["lift_thrust"]["mean_amplitude_mm"],
                                                                     abs=bound_mm + 1e-3)
    assert got["technique"]["twirl"] == whole["technique"]["twirl"]

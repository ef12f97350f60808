"""Twirling through the servo step: the roll as a tick input, the twirl phase (torque, grasp), the
sample columns, headless replay of the bundled twirls, the recorder.

References are independent of the step: Han et al. 2015's torque-angle line (twirl.HAN_*), Langevin
et al. 2001's pull-out ratios (twirl.LANGEVIN_*), the Maxwell closed form of a relaxing twist, the
trajectory file's own roll_deg column.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from haptic_acu.tissue import twirl
from haptic_acu.base.config import load_config
from haptic_acu.servo.step import NeedleModel
from haptic_acu.servo.samples import COL
from haptic_acu.session.sink import Sink

REPO = Path(__file__).resolve().parents[1]
DT = 1e-3
DOWN = np.array([0.0, 0.0, -10e-3])  # 10 mm/s into the tissue at the acupoint


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def insert(model, depth_m: float, roll: float = 0.0) -> float:
    """Drive the tip down the z axis at 10 mm/s from 5 mm above the acupoint until the needle is
    ``depth_m`` below the skin (the step's own depth_skin), then hold it still for a tick. Returns
    the needle's length in tissue, the sum of the step's per-layer lengths."""
    z = 5e-3
    for _ in range(20000):
        model.step(np.array([0.0, 0.0, z]), DOWN, roll)
        if model.diag["depth_skin"] >= depth_m:
            break
        z -= 10e-3 * DT
    else:
        raise AssertionError("never reached the depth")
    model.step(np.array([0.0, 0.0, z]), np.zeros(3), roll)
    return z


def hold(model, z, rolls):
    """Hold the tip at depth ``z`` while the roll follows ``rolls`` (rad, one per tick); returns the
    torque (N*m) of each tick."""
    p = np.array([0.0, 0.0, z])
    v = np.zeros(3)
    out = np.empty(len(rolls))
    for i, r in enumerate(rolls):
        model.step(p, v, float(r))
        out[i] = model.diag["torque"]
    return out


def length_in_tissue(model) -> float:
    return float(np.sum(model.rec["lengths"]))


def test_roll_reaches_the_step_and_the_samples_columns(cfg):
    m = NeedleModel(cfg)
    m.step(np.array([0.0, 0.0, 5e-3]), np.zeros(3), math.radians(37.5))
    assert m.inp.roll[0] == pytest.approx(math.radians(37.5))
    from haptic_acu.servo.samples import write_sample
    buf = np.zeros((1, len(COL)))
    write_sample(buf, 0, 0.0, 0, m.inp, m.state, m.out.diag, 0.0)
    assert buf[0, COL["roll_deg"]] == pytest.approx(37.5)
    assert buf[0, COL["torque_nmm"]] == 0.0  # in the air: nothing wound
    assert np.all(m.rec["grasp"] == 1.0)


def test_non_finite_roll_latches_the_fault(cfg):
    m = NeedleModel(cfg)
    z = insert(m, 10e-3)
    f = m.step(np.array([0.0, 0.0, z]), np.zeros(3), float("nan"))
    assert m.fault and np.all(f == 0.0)
    assert np.all(m.step(np.array([0.0, 0.0, z]), np.zeros(3), 0.0) == 0.0)  # latched


@pytest.mark.parametrize("swing_deg", [60.0, 120.0, 180.0])
def test_torque_range_against_angle_through_the_step_on_hans_line(cfg, swing_deg):
    """A symmetric sinusoidal twirl at Han's 0.15 Hz with the needle held 30 mm below the skin: the
    torque range over a cycle is Han's least-squares line through the origin (0.0915 N*mm/rad x
    swing) scaled to the needle's length in tissue, less the 1 deg play and the Maxwell factor."""
    m = NeedleModel(cfg)
    z = insert(m, twirl.HAN_LENGTH_M)
    L = length_in_tissue(m)
    assert L == pytest.approx(twirl.HAN_LENGTH_M, rel=0.05)
    S = math.radians(swing_deg)
    f = twirl.HAN_FREQ_HZ
    n = int(round(1.0 / f / DT))
    t = np.arange(2 * n) * DT
    tq = hold(m, z, 0.5 * S * np.sin(2 * math.pi * f * t))[n:]  # the second cycle
    rng = (tq.max() - tq.min()) * 1e3  # N*mm
    wt = 2 * math.pi * f * twirl.TWIST_TAU_S
    han = twirl.han_torque_slope() * 1e3 * (S - math.radians(1.0)) * L / twirl.HAN_LENGTH_M
    assert rng == pytest.approx(han * wt / math.sqrt(1 + wt * wt), rel=0.01)
    # and against Han's published points themselves: within the documented fit error (+15% at 60 deg)
    pub = np.interp(swing_deg, twirl.HAN_ANGLE_DEG, twirl.HAN_TORQUE_NMM) * L / twirl.HAN_LENGTH_M
    assert abs(rng / pub - 1.0) < 0.16


def test_torque_is_linear_in_angle_and_signed(cfg):
    """A slow one-way turn: the torque is k_t * L * (angle - play/2), a line through the play's edge
    (relaxation over 0.5 s at tau = 30 s: < 1%), with the roll's sign."""
    for sign in (1.0, -1.0):
        m = NeedleModel(cfg)
        z = insert(m, 20e-3)
        L = length_in_tissue(m)
        angles = sign * np.linspace(0.0, math.pi, 501)
        tq = hold(m, z, angles)
        k = twirl.calibrated_k_twist()
        moved = np.abs(angles) > math.radians(0.5)  # past the play's half-width
        expected = k * L * (angles - sign * math.radians(0.5))
        np.testing.assert_allclose(tq[moved], expected[moved], rtol=0.01)
        assert np.all(tq[~moved] == 0.0)  # inside the play nothing winds
        slope = np.polyfit(angles[moved], tq[moved], 1)[0]
        assert slope == pytest.approx(k * L, rel=0.01)


def _protocol_grasp(cfg, proto):
    m = NeedleModel(cfg)
    z = insert(m, twirl.HAN_LENGTH_M)
    hold(m, z, twirl.protocol_roll(proto, DT))
    lengths = m.rec["lengths"].copy()
    return m.rec["grasp"].copy(), lengths


def test_pullout_protocols_through_the_step_give_langevins_ratios(cfg):
    """UNI and BI (twirl.UNI / BI) through the step with the needle held 30 mm deep: the breakaway
    stand-in (each layer's friction level, proportional to its length, times its grasp) over the
    same without rotation is Langevin's 2.67 and 1.52. (The pull-out through the wired shaft friction
    awaits the mechanics phase: tests/test_twirl_friction.py checks it on the kernels.)"""
    fc = np.array([layer.coulomb_n_per_mm2 for layer in cfg.layers])
    out = {}
    for proto in (twirl.UNI, twirl.BI, twirl.NO):
        g, L = _protocol_grasp(cfg, proto)
        out[proto.name] = float(np.sum(g * fc * L))
    assert out["unidirectional"] / out["none"] == pytest.approx(twirl.LANGEVIN_UNI_RATIO, rel=0.01)
    assert out["bidirectional"] / out["none"] == pytest.approx(twirl.LANGEVIN_BI_RATIO, rel=0.01)


def test_unwinding_releases_the_grasp_through_the_step(cfg):
    m = NeedleModel(cfg)
    m.model.params[0]["engage_tau"][:] = 1.0  # fast engagement relaxation, so the test is short
    z = insert(m, 20e-3)
    two = np.linspace(0.0, 2 * 2 * math.pi, 2001)
    hold(m, z, two)
    wound = m.rec["grasp"].copy()
    assert np.all(wound > 2.0) and m.diag["torque"] > 0
    t_wound = m.diag["torque"]
    r = two[-1]
    while m.diag["torque"] > 0.0:  # turn back until the torque is gone (the tissue slipped at a turn)
        r -= 2 * math.pi / 1000
        hold(m, z, [r])
        assert r > 0.0
    assert two[-1] - r == pytest.approx(2 * math.pi, rel=0.1)  # about the turn held before the slip
    assert abs(m.diag["torque"]) < 0.01 * t_wound
    unwound = m.rec["grasp"].copy()
    assert np.all(unwound < wound - 1.0)  # the coil part of the grasp is released
    hold(m, z, np.full(5000, r))  # still, for 5 engagement time constants
    assert np.all(m.rec["grasp"] < 1.0 + 0.01 * twirl.GRASP_ENGAGE)


def test_withdrawal_and_reset_clear_the_winding(cfg):
    m = NeedleModel(cfg)
    z = insert(m, 15e-3)
    hold(m, z, np.linspace(0.0, 4 * math.pi, 1001))
    assert np.all(m.rec["grasp"][:2] > 1.5)
    m.reset()
    assert np.all(m.rec["grasp"] == 1.0) and np.all(m.rec["twist"] == 0.0)
    # a reset does not turn the roll it starts from into a twist: the first tick primes
    z = insert(m, 15e-3, roll=4 * math.pi)
    assert m.diag["torque"] == 0.0 and np.all(m.rec["grasp"] == 1.0)
    hold(m, z, np.linspace(4 * math.pi, 6 * math.pi, 500))
    assert m.diag["torque"] > 0.0
    # out of the tissue: every layer cleared
    for zz in np.linspace(z, 5e-3, 3000):
        m.step(np.array([0.0, 0.0, zz]), -DOWN, 6 * math.pi)
    assert not m.inserted and np.all(m.rec["grasp"] == 1.0) and m.diag["torque"] == 0.0


def test_session_dt_sets_the_relaxation_clock(cfg):
    """The twist relaxes on the servo's period (Session writes 1/servo_hz into params.dt): a twist
    held for 2 s at tau = 1 s decays by exp(-2)."""
    m = NeedleModel(cfg)
    m.model.params[0]["twist_tau"][:] = 1.0
    z = insert(m, 20e-3)
    hold(m, z, np.linspace(0.0, math.pi / 2, 11))
    t0 = m.diag["torque"]
    tq = hold(m, z, np.full(2000, math.pi / 2))
    assert tq[-1] / t0 == pytest.approx(math.exp(-2.0), rel=1e-3)


# -- headless replay of the bundled twirls ----------------------------------------------------------------

@pytest.mark.parametrize("name", ["twirl_even", "twirl_reinforcing", "twirl_reducing"])
def test_bundled_twirls_replay_with_their_roll(cfg, name):
    from haptic_acu.devices.scripted import ScriptedDevice
    from haptic_acu.session.engine import Session
    from haptic_acu.session import trajectory

    class Keep(Sink):
        def __init__(self):
            self.rows = []

        def on_frame(self, frame):
            self.rows.append(frame.samples)

    path = REPO / "trajectories" / f"{name}.csv"
    keep = Keep()
    with ScriptedDevice(path) as dev:
        res = Session(cfg, dev, sinks=[keep], clock="sim", dents=False).run()
    assert res.fault is None
    rows = np.concatenate(keep.rows)
    tr = trajectory.load(path, extra_columns=("roll_deg",))
    np.testing.assert_allclose(rows[:, COL["roll_deg"]], np.interp(rows[:, COL["t_s"]], tr.t_s, tr.extra["roll_deg"]),
                               atol=1e-9)
    tq = rows[:, COL["torque_nmm"]]
    twirling = np.abs(np.diff(rows[:, COL["roll_deg"]])) > 0
    assert twirling.sum() > 1000
    assert np.abs(tq).max() > 0.05  # N*mm: a twirl of >= 60 deg with >= 20 mm of needle in tissue
    # the torque follows the roll's swings: its sign agrees with the roll's offset from the middle
    # of the swing once the twist has built (correlation over the twirling ticks)
    r = rows[1:, COL["roll_deg"]][twirling]
    assert np.corrcoef(r - r.mean(), tq[1:][twirling])[0, 1] > 0.9


# -- technique metrics in the summary -----------------------------------------------------------------------

def _synthetic_rows(roll_deg, t):
    """Sample rows of one insertion at the acupoint: skin punctured throughout, the tip 20 mm deep
    along -z, rolled by ``roll_deg``; a torque column proportional to the roll."""
    from haptic_acu.servo.samples import NCOL
    rows = np.zeros((len(t), NCOL))
    rows[:, COL["t_s"]] = t
    rows[:, COL["tick"]] = np.arange(len(t))
    rows[:, COL["z_m"]] = -20e-3 * np.minimum(t / 1.0, 1.0)
    rows[:, COL["depth_skin_m"]] = -rows[:, COL["z_m"]]
    rows[:, COL["state_skin"]] = 2
    rows[:, COL["roll_deg"]] = roll_deg
    rows[:, COL["torque_nmm"]] = 1e-3 * roll_deg
    return rows


def test_session_metrics_report_the_twirl_of_each_insertion(cfg):
    """A sinusoidal twirl of known amplitude and frequency in the sample rows: the per-insertion
    technique metrics read them back (closed forms: amplitude A, swing 2A, frequency f, N cycles)."""
    from haptic_acu.analysis.metrics import session_metrics
    t = np.arange(0, 8.0, DT)
    A, f = 45.0, 0.5
    roll = np.where(t >= 2.0, A * np.sin(2 * np.pi * f * (t - 2.0)), 0.0)  # 3 cycles from t = 2 s
    m = session_metrics(_synthetic_rows(roll, t), cfg)
    tw = m["per_insertion"][0]["technique"]["twirl"]
    assert tw["cycles"] == 3
    assert tw["swing_deg"] == pytest.approx(2 * A, abs=0.02)
    assert tw["frequency_hz"] == pytest.approx(f, rel=1e-3)
    assert tw["peak_torque_nmm"] == pytest.approx(1e-3 * A, rel=1e-3)
    cl = m["per_insertion"][0]["technique"]["classification"]
    assert cl["twirl_vote"] == "reinforcing" and cl["inputs"]["swing_deg"] == pytest.approx(90.0, abs=0.02)
    assert m["per_insertion"][0]["technique"]["grasp_felt"] is None  # no reference replay given


@pytest.mark.parametrize("name, label", [("twirl_reinforcing", "reinforcing"), ("twirl_reducing", "reducing"),
                                         ("twirl_even", "even")])
def test_replay_summary_has_technique_metrics_and_the_grasp_felt(cfg, tmp_path, name, label):
    from haptic_acu.session.replay import replay_one
    s = replay_one(REPO / "trajectories" / f"{name}.csv", tmp_path / "out", rrd=False, progress=False, cfg=cfg)
    ins = s["metrics"]["per_insertion"]
    assert len(ins) == 1
    tech = ins[0]["technique"]
    assert tech["classification"]["label"] == label
    assert tech["twirl"]["cycles"] >= 4 and tech["twirl"]["peak_torque_nmm"] > 0.05
    g = tech["grasp_felt"]  # the same replay without rotation is the reference
    assert g is not None and g["peak_ratio"] is not None and g["peak_ratio"] >= 1.0 - 1e-9
    import json
    on_disk = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert on_disk["metrics"]["per_insertion"][0]["technique"]["classification"]["label"] == label
    import csv
    with open(tmp_path / "out" / "samples.csv") as fh:
        header = next(csv.reader(fh))
    assert "roll_deg" in header and "torque_nmm" in header


def test_cohort_insertion_table_has_the_technique_columns(cfg):
    from haptic_acu.cohort.sessions import INSERTION_COLUMNS, insertion_table
    from haptic_acu.session.replay import replay_rows
    path = REPO / "trajectories" / "twirl_reducing.csv"
    rows, ref = replay_rows(path, cfg), replay_rows(path, cfg, roll=False)
    assert np.all(ref[:, COL["roll_deg"]] == 0.0) and np.all(ref[:, COL["torque_nmm"]] == 0.0)
    _, ins = insertion_table(rows, cfg, None, ref)
    names = {c.name for c in INSERTION_COLUMNS}
    assert {"twirl_cycles", "twirl_swing_deg", "twirl_frequency_hz", "twirl_net_rotation_deg",
            "twirl_peak_torque_nmm", "thrust_to_lift", "grasp_felt_ratio", "technique"} <= names
    (row,) = ins
    assert row["technique"] == "reducing"
    # the file's own twirl: 10 twirls of 270 deg at 2.5 Hz (trajectories/make_twirl.py)
    assert row["twirl_cycles"] == 10
    assert row["twirl_swing_deg"] == pytest.approx(270.0, rel=0.02)
    assert row["twirl_frequency_hz"] == pytest.approx(2.5, rel=0.02)
    assert row["grasp_felt_ratio"] >= 1.0 - 1e-9


def test_a_recording_replays_with_its_twirling(cfg, tmp_path):
    """A session recorded (RecorderSink) writes roll_deg; replaying the recording gives the same
    roll and the same torque, tick for tick."""
    from haptic_acu.devices.scripted import ScriptedDevice
    from haptic_acu.session.engine import Session
    from haptic_acu.session.recorder import EXTRA, RecorderSink
    from haptic_acu.session.replay import replay_rows
    from haptic_acu.session import trajectory

    src = REPO / "trajectories" / "twirl_even.csv"
    rec = tmp_path / "rec.csv"
    with ScriptedDevice(src) as dev:
        assert Session(cfg, dev, [RecorderSink(rec)], clock="sim", dents=False).run().fault is None
    assert "roll_deg" in EXTRA
    tr = trajectory.load(rec, extra_columns=EXTRA)
    a = replay_rows(src, cfg)
    b = replay_rows(rec, cfg)
    n = min(len(a), len(b), len(tr.t_s))
    assert n > 0.9 * len(a)
    np.testing.assert_allclose(tr.extra["roll_deg"][:n], a[:n, COL["roll_deg"]], atol=1e-4)
    np.testing.assert_allclose(b[:n, COL["roll_deg"]], a[:n, COL["roll_deg"]], atol=1e-4)
    np.testing.assert_allclose(b[:n, COL["torque_nmm"]], a[:n, COL["torque_nmm"]], rtol=1e-3, atol=1e-5)


def _pullout_peak(cfg, turns: float) -> tuple[float, float]:
    """Insert 25 mm, twirl ``turns`` one way in 4 s holding still, wait 1 s, then withdraw 3 mm at
    1 mm/s: the peak force resisting the withdrawal (N, along +z) and the largest layer grasp."""
    m = NeedleModel(cfg)
    z = insert(m, 25e-3)
    rolls = np.linspace(0.0, turns * 2 * math.pi, 4000)
    hold(m, z, np.concatenate([rolls, np.full(1000, rolls[-1])]))
    grasp = float(m.rec["grasp"].max())
    peak = 0.0
    for i in range(1, 3001):
        f = m.step(np.array([0.0, 0.0, z + 1e-3 * DT * i]), np.array([0.0, 0.0, 1e-3]), float(rolls[-1]))
        peak = max(peak, -float(f[2]))  # withdrawing up +z: the tissue pulls back down
    return peak, grasp


def test_twirling_raises_the_pullout_force_through_the_shaft_friction(cfg):
    """The grasp reaches the hand through the axial force: after a one-way twirl the shaft friction's
    levels are multiplied by each layer's grasp (> 1), so the withdrawal meets more force than the
    same withdrawal without rotation (the cutting and viscous parts are not scaled, so the ratio of
    the totals lies between 1 and the grasp)."""
    plain, g0 = _pullout_peak(cfg, 0.0)
    wound, g = _pullout_peak(cfg, 4.0)
    assert g0 == 1.0 and g > 1.5
    assert plain > 0.0 and 1.2 < wound / plain <= g + 1e-9

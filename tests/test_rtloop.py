"""The compiled, GIL-free real-time servo loop (haptic_acu.servo.rtloop) behind Session(clock="realtime")
for devices that can be read ahead (the scripted device).

Checked against independent references: the headless replay of the same trajectory (ticks of the
real-time loop read the trajectory at k * 1 ms, so every force must equal the simulated clock's bit
for bit), the device's own log of what it returned, Python's clock, and faults injected by devices
(real Device implementations) whose ``read_block`` returns NaN or fails. No timing asserts: a
loaded machine may delay a tick, and the tests say what must hold whatever the delays.
"""
from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from haptic_acu.devices.scripted import ScriptedDevice
from haptic_acu.servo import devicemodel, rtloop
from haptic_acu.base.config import load_config
from haptic_acu.session.engine import Session
from haptic_acu.servo.step import NeedleModel
from haptic_acu.servo.state import TIMING, Ring, Timing
from haptic_acu.servo.tick import call_driver, tick_table
from haptic_acu.servo.samples import COL
from haptic_acu.tissue.body import Tissue
from haptic_acu.session.trajectory import TrajectoryWriter
from haptic_acu.session.sink import Sink

REPO = Path(__file__).resolve().parents[1]
DEFAULT_TRAJ = REPO / "trajectories" / "default.csv"


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


@pytest.fixture(scope="module")
def tissue(cfg):
    return Tissue.from_config(cfg)


class Rows(Sink):
    """A sink keeping every drained row."""

    def __init__(self):
        self.blocks = []

    def on_frame(self, frame):
        if frame.samples.shape[0]:
            self.blocks.append(frame.samples.copy())

    @property
    def rows(self):
        return np.vstack(self.blocks) if self.blocks else np.zeros((0, len(COL)))


class StopAfter(Rows):
    """Rows, and ``session.stop()`` called (from the visual thread) once ``n`` rows have arrived."""

    def __init__(self, n):
        super().__init__()
        self.n, self.session, self.stopped_at, self.stopper = n, None, None, None

    def on_frame(self, frame):
        super().on_frame(frame)
        seen = sum(b.shape[0] for b in self.blocks)
        if self.stopped_at is None and seen >= self.n:
            self.stopped_at, self.stopper = seen, threading.current_thread()
            self.session.stop()


def run(cfg, tissue, device, clock, duration_s, **kw):
    # Never skip ticks after a stall unless a test asks to: a loaded host may stall the loop for
    # 10+ ms, and these tests check which ticks run and what they compute, not when.
    kw.setdefault("skip_after_ticks", None)
    sink = Rows()
    s = Session(cfg, device, [sink], clock=clock, duration_s=duration_s, model=NeedleModel(cfg, tissue),
                realtime_priority=False, **kw)
    s.warm_up()
    result = s.run()
    return s, result, sink.rows


def test_clock_is_perf_counters_clock_and_sleep_reaches_its_deadline():
    ts = np.zeros(2, np.int64)
    a = time.perf_counter_ns()
    b = rtloop.now_ns(ts)
    c = time.perf_counter_ns()
    assert a <= b <= c  # the same CLOCK_MONOTONIC
    for delay in (0, 200_000, 2_000_000):
        target = rtloop.now_ns(ts) + delay
        assert rtloop.sleep_until_ns(ts, target) == 0
        assert rtloop.now_ns(ts) >= target


def test_realtime_forces_equal_the_headless_replay(cfg, tissue):
    # 2.5 s of the default insertion (skin and fat punctured, into muscle) in real time, against
    # the simulated clock: each tick reads the trajectory at k * 1 ms in both, so the rows carry the
    # same times, positions and forces exactly. The loop is told never to skip (a stall on this
    # shared host would otherwise skip ticks and the two runs would part there).
    dev = ScriptedDevice(DEFAULT_TRAJ, realtime=True)
    dev.open()
    s, result, rt = run(cfg, tissue, dev, "realtime", 2.5)
    dev.close()
    assert s.compiled_loop and result.fault is None
    dev2 = ScriptedDevice(DEFAULT_TRAJ)
    dev2.open()
    _, _, sim = run(cfg, tissue, dev2, "sim", 2.5)
    dev2.close()
    ticks = rt[:, COL["tick"]].astype(int)
    np.testing.assert_array_equal(ticks, np.arange(2501))  # every tick, once, in order
    assert result.ticks == 2501 and sim.shape == rt.shape
    cols = [COL[c] for c in ("t_s", "x_m", "y_m", "z_m", "fx_n", "fy_n", "fz_n", "state_skin", "state_fat", "ringw_m")]
    np.testing.assert_array_equal(rt[:, cols], sim[:, cols])
    assert rt[:, COL["state_fat"]].max() == 2  # the comparison went through two punctures
    assert dev.force_commands >= result.ticks and dev.max_force_n == pytest.approx(np.abs(rt[:, COL["fz_n"]]).max(), abs=1e-3)
    assert not np.any(dev.last_force_n)  # the session ended with zero force
    # The same session paced 8 times as fast as real time: the ticks keep their session times, so the
    # rows are the same bit for bit; its deadlines 125 us apart make it no shorter than 2500 of them,
    # and shorter than the same session at real pace (a ratio within one run, with a margin of 4).
    dev3 = ScriptedDevice(DEFAULT_TRAJ, realtime=True)
    dev3.open()
    s3, fast, paced = run(cfg, tissue, dev3, "realtime", 2.5, speed=8.0)
    dev3.close()
    assert s3.compiled_loop and fast.fault is None and fast.ticks == 2501
    np.testing.assert_array_equal(paced[:, COL["tick"]].astype(int), np.arange(2501))
    np.testing.assert_array_equal(paced[:, cols], sim[:, cols])
    assert fast.stats["wall_s"] >= 2500 * 125e-6
    assert fast.stats["wall_s"] < 0.5 * result.stats["wall_s"], (fast.stats["wall_s"], result.stats["wall_s"])


def _loop_on_a_fixed_feed(cfg, tissue, period_ns, k_limit, skip_after):
    """servo_loop called directly: a feed of 4096 distinct positions above the skin, ``k_limit``
    ticks at ``period_ns``; returns the control words and the rows written."""
    m = NeedleModel(cfg, tissue)
    fcap = 4096
    feed_p = np.zeros((fcap, 3))
    feed_p[:, 0] = np.arange(fcap) * 1e-7  # tick k's row is recognisable by its x
    feed_p[:, 2] = 5e-3
    feed_v = np.zeros((fcap, 3))
    ctl = np.zeros(1, rtloop.CTL)
    ctl["fed"] = fcap
    ctl["end"] = rtloop.NO_END
    ctl["skip_after"] = skip_after
    ring = np.zeros((fcap, len(COL)))
    rctr = np.zeros(1, np.int64)
    timing = Timing(np.zeros(fcap), np.zeros(1, TIMING))
    errs = timing.errs
    ts = np.zeros(2, np.int64)
    rows = Ring(ring, rctr)
    status = call_driver(rtloop.servo_loop, rtloop.Loop(ctl, np.zeros(1, rtloop.FL), ts, devicemodel.new(1e-3, on=False)), rtloop.now_ns(ts),
                         period_ns, k_limit, rtloop.FeedRows(feed_p, feed_v, np.full_like(feed_p, np.nan), np.zeros(len(feed_p))),
                         tick_table(m.servo, rows, timing))
    assert status == rtloop.LIMIT
    rows = ring[:rctr[0]]
    ticks = rows[:, COL["tick"]].astype(int)
    np.testing.assert_array_equal(rows[:, COL["x_m"]], feed_p[ticks, 0])  # each row is its own tick's
    np.testing.assert_allclose(rows[:, COL["t_s"]], ticks * period_ns * 1e-9, rtol=0, atol=1e-15)
    assert ctl[0]["ran"] == rctr[0] == timing.count[0]["n_err"]
    return timing.count[0]["missed"], ticks, errs[:rctr[0]] * 1e9 / period_ns


def test_a_loop_late_by_more_than_its_threshold_skips_ahead_and_counts_what_it_skipped(cfg, tissue):
    # A period of 100 ns (far shorter than any tick) keeps the loop late by many periods at every
    # tick: with the threshold at 2 periods, every late tick jumps to the present.
    missed, ticks, late = _loop_on_a_fixed_feed(cfg, tissue, 100, 3000, 2)
    # The whole session is 0.3 ms of the clock: a host that takes the core away for longer (this VM
    # deschedules its vCPU for 1-12 ms) leaves one tick run, or none, and every other one skipped.
    if len(ticks) == 0:
        assert missed == 3000
        return
    gaps = np.diff(ticks)
    # the first tick may itself be skipped: on a loaded host the loop can start more than 200 ns late
    assert ticks[0] >= 0 and np.all(gaps >= 1) and (len(ticks) == 1 or gaps.max() > 1)
    assert ticks[-1] < 3000 and len(ticks) < 3000  # ticks were skipped, none past the limit
    assert np.all(late[1:] <= 2 + 1e-9)  # after a skip a tick is never more than the threshold late
    # skipped: before the first row, between rows, and after the last up to the limit
    skipped = int(ticks[0]) + int((gaps - 1).sum()) + (3000 - 1 - ticks[-1])
    # every skipped tick of the session is missed (none past its end), and so is every tick run
    # more than a period late
    assert missed == skipped + int((late > 1).sum())


def test_a_loop_that_never_skips_runs_every_tick_however_late(cfg, tissue):
    missed, ticks, late = _loop_on_a_fixed_feed(cfg, tissue, 100, 3000, rtloop.NO_END)
    np.testing.assert_array_equal(ticks, np.arange(3000))
    assert late[-1] > 1000  # far behind by the end, and still every tick ran
    assert missed == int((late > 1).sum())


def test_stop_from_another_thread_ends_at_once_with_zero_force_and_every_row(cfg, tissue):
    # The stop comes from the visual thread once the loop has run (a timer started before run()
    # could fire before the first tick on a loaded host).
    dev = ScriptedDevice(DEFAULT_TRAJ, realtime=True)
    dev.open()
    sink = StopAfter(300)
    s = Session(cfg, dev, [sink], clock="realtime", duration_s=10.0, model=NeedleModel(cfg, tissue),
                realtime_priority=False)
    sink.session = s
    s.warm_up()
    result = s.run()
    dev.close()
    rows = sink.rows
    assert sink.stopped_at >= 300 and sink.stopper is not threading.main_thread()
    assert result.fault is None and 300 <= result.ticks < 9000
    ticks = rows[:, COL["tick"]]
    assert ticks[0] == 0 and np.all(np.diff(ticks) >= 1)  # every tick run is there once, in order
    assert len(ticks) == result.ticks  # up to the last one
    assert not np.any(dev.last_force_n)


class NanAt(ScriptedDevice):
    """The scripted device whose positions turn NaN from session time ``t_nan`` on."""

    def __init__(self, path, t_nan, **kw):
        super().__init__(path, **kw)
        self.t_nan = t_nan

    def read_block(self, t_s):
        P, V, done = super().read_block(t_s)
        P = P.copy()
        P[np.asarray(t_s) >= self.t_nan - 1e-9] = np.nan
        return P, V, done


class FailsAt(ScriptedDevice):
    """The scripted device whose reads fail (an I/O error) once asked past ``t_fail``."""

    def __init__(self, path, t_fail, **kw):
        super().__init__(path, **kw)
        self.t_fail = t_fail

    def read_block(self, t_s):
        if np.asarray(t_s)[-1] >= self.t_fail:
            raise OSError("trajectory file became unreadable")
        return super().read_block(t_s)


def test_nan_from_the_device_faults_on_that_tick_with_zero_force(cfg, tissue):
    # paced at 8 times real time (the compiled loop's ticks and session times as at real pace, see
    # test_realtime_forces_equal_the_headless_replay): the fault is a tick's, not a moment's
    dev = NanAt(DEFAULT_TRAJ, t_nan=1.3, realtime=True)  # while pressing / inside the skin
    dev.open()
    s, result, rows = run(cfg, tissue, dev, "realtime", 5.0, speed=8.0)
    assert s.compiled_loop and s.speed == 8.0
    assert result.fault is not None and "non-finite" in result.fault and "tick 1300" in result.fault
    assert result.ticks == len(rows) and rows[-1, COL["tick"]] == 1300 and rows[-1, COL["fault"]] == 1
    assert np.all(rows[-1, [COL["fx_n"], COL["fy_n"], COL["fz_n"]]] == 0)
    assert not np.any(dev.last_force_n)


def test_a_device_that_stops_answering_faults_with_every_row_kept(cfg, tissue, tmp_path):
    traj = tmp_path / "long.csv"
    with TrajectoryWriter(traj) as w:  # 12 s hovering above the skin, then pressing
        w.append_rows([[0.0, 0.0, 0.0, 2e-3], [12.0, 0.0, 0.0, -1e-3]])
    dev = FailsAt(traj, t_fail=2.0, realtime=True)
    dev.open()
    s, result, rows = run(cfg, tissue, dev, "realtime", 10.0)
    assert result.fault is not None and "device fault" in result.fault and "unreadable" in result.fault
    # the loop ran on what was read ahead (up to 2 s), every tick recorded, none after
    assert 1000 <= rows[-1, COL["tick"]] <= 2000 and result.ticks == len(rows)
    assert not np.any(dev.last_force_n)


def test_duration_limit_counts_ticks_like_the_python_loop(cfg, tissue):
    dev = ScriptedDevice(DEFAULT_TRAJ, realtime=True)
    dev.open()
    s, result, rows = run(cfg, tissue, dev, "realtime", 0.3)
    assert result.fault is None and rows[-1, COL["tick"]] == 300 and result.ticks == len(rows)
    assert s.compiled_loop
    # the Python loop, asked for explicitly, runs the same session length: on the wall clock (a
    # stall on a loaded host drops ticks there, so not the tick count), no tick past the limit
    dev = ScriptedDevice(DEFAULT_TRAJ, realtime=True)
    dev.open()
    s2, result2, rows2 = run(cfg, tissue, dev, "realtime", 0.3, compiled_loop=False)
    ended = time.perf_counter()
    assert not s2.compiled_loop and result2.fault is None and result2.ticks == len(rows2) > 0
    assert rows2[-1, COL["t_s"]] <= 0.3 and result2.duration_s == pytest.approx(rows2[-1, COL["t_s"]], abs=1e-6)
    assert ended - s2.t0_perf > 0.3  # it ran until the limit, not less


@pytest.mark.parametrize("bad", [0, -3, 2.5, "10"])
def test_a_skip_threshold_that_is_not_a_whole_number_of_ticks_is_refused(cfg, tissue, bad):
    with pytest.raises(ValueError, match="skip_after_ticks"):
        Session(cfg, ScriptedDevice(DEFAULT_TRAJ, realtime=True), clock="realtime", model=NeedleModel(cfg, tissue),
                skip_after_ticks=bad)


def test_a_reset_model_answers_as_a_fresh_one(cfg, tissue):
    """needle.reset_servo (NeedleModel.reset, and what the compiled loop runs on a reset event), from
    a needle deep in the tissue with holes made, leaves a model that answers a new insertion exactly as
    a freshly built one does, tick for tick; ``keep_holes`` keeps the holes and the tracks."""
    from haptic_acu.servo.tick import reset_servo
    model = NeedleModel(cfg, tissue)
    v = np.array([0.0, 0.0, -0.01])
    path = np.arange(5e-3, -15e-3, -1e-5)
    for z in path:
        model.step(np.array([0.0, 0.0, z]), v)
    assert model.rec["nholes"] > 0 and max(model.rec["state"]) == 2
    deep = model.copy_state()
    reset_servo(model.servo)  # the compiled loop's call
    fresh = NeedleModel(cfg, tissue)
    assert model.rec.tobytes() == fresh.rec.tobytes() and model.diag.tobytes() == fresh.diag.tobytes()
    for x in path:  # a second insertion, beside the first (the same site would be the same too)
        p = np.array([1e-3, 0.0, x])
        assert model.step(p, v).tobytes() == fresh.step(p, v).tobytes()
    assert model.rec["nholes"] > 0
    model.restore_state(deep)
    model.reset(keep_holes=True)
    assert max(model.rec["state"]) == 0 and not model.inserted
    assert model.rec["nholes"] == deep[0].servo[0]["nholes"]
    for name in ("holes", "tr_entry", "tr_axis", "tr_lo", "tr_hi", "tr_count"):
        assert getattr(model.state, name).tobytes() == getattr(deep[0], name).tobytes()


def test_a_reset_event_in_the_compiled_loop_equals_the_headless_replay(cfg, tissue, tmp_path):
    """second_insertion_same_site.csv with a reset between its two passes, live through the compiled
    loop (no Python fallback): every row equals the headless replay's, and the second pass breaks the
    fresh skin again. Paced at 8 times real time: the same compiled loop, ticks and session times as
    at real pace (test_realtime_forces_equal_the_headless_replay shows a paced session's rows equal
    the real-paced ones bit for bit), so 8 s of path take 1 s."""
    src = REPO / "trajectories" / "second_insertion_same_site.csv"
    lines = src.read_text().splitlines()
    out, done = [lines[0] + ",event"], False
    for ln in lines[1:]:
        ev = "reset" if float(ln.split(",", 1)[0]) >= 5.0 and not done else ""
        done = done or bool(ev)
        out.append(f"{ln},{ev}")
    traj = tmp_path / "reset.csv"
    traj.write_text("\n".join(out) + "\n")
    dev = ScriptedDevice(traj, realtime=True)
    dev.open()
    s, result, rt = run(cfg, tissue, dev, "realtime", 8.0, speed=8.0)
    dev.close()
    assert s.speed == 8.0 and dev.has_events and s._servo_kind() == "compiled" and result.fault is None
    dev2 = ScriptedDevice(traj)
    dev2.open()
    _, _, sim = run(cfg, tissue, dev2, "sim", 8.0)
    dev2.close()
    assert sim.shape == rt.shape
    np.testing.assert_array_equal(rt[:, :COL["period_err_s"]], sim[:, :COL["period_err_s"]])
    skin = np.flatnonzero(rt[:, COL["puncture"]] == 0)
    assert len(skin) == 2 and rt[skin[1], COL["t_s"]] > 5.0
    # the event is logged for a recording (RecorderSink reads device.events) at the tick it took effect
    t_reset = min(float(ln.split(",", 1)[0]) for ln in out[1:] if ln.endswith(",reset"))
    k = int(np.ceil(t_reset / 1e-3 - 1e-9))
    assert dev.events == [(k, "reset")]


def _floor_identity(errs, period_ns, missed):
    """The floor's count is the servo loop's rule: every skipped tick, and every tick run later than
    a period; a tick that ran is never more than the skip threshold (10 periods) late."""
    assert np.all(errs >= -1)
    ran = errs[errs >= 0]
    assert np.all(ran <= 10 * period_ns)
    assert missed == int((errs == -1).sum()) + int((ran > period_ns).sum())


def test_the_floor_loop_counts_missed_ticks_as_the_servo_loop_does():
    # 100 ns periods: every tick is late by many periods, so the loop skips again and again
    ts = np.zeros(2, np.int64)
    errs = np.zeros(3000, np.int64)
    missed = rtloop.floor_loop(ts, rtloop.now_ns(ts), 100, errs)
    _floor_identity(errs, 100, missed)
    assert (errs == -1).sum() > 0 and missed > 0


def test_a_floor_loop_entered_50_ms_late_skips_those_ticks_then_keeps_time():
    ts = np.zeros(2, np.int64)
    errs = np.zeros(120, np.int64)
    period = 1_000_000
    missed = rtloop.floor_loop(ts, rtloop.now_ns(ts) - 50 * period, period, errs)
    _floor_identity(errs, period, missed)
    assert np.all(errs[:50] == -1)  # the ticks whose deadlines had passed before it started
    assert missed >= 50
    assert (errs[50:] >= 0).mean() > 0.5  # then it keeps time (a host stall may skip a few more)

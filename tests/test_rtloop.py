"""The compiled, GIL-free real-time servo loop (haptic_acu.rtloop) behind Session(clock="realtime")
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

from devices.scripted import ScriptedDevice
from haptic_acu import rtloop
from haptic_acu.config import load_config
from haptic_acu.engine import Session
from haptic_acu.needle import NeedleModel
from haptic_acu.samples import COL
from haptic_acu.tissue import Tissue
from haptic_acu.trajectory import TrajectoryWriter

REPO = Path(__file__).resolve().parents[1]
DEFAULT_TRAJ = REPO / "trajectories" / "default.csv"


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


@pytest.fixture(scope="module")
def tissue(cfg):
    return Tissue.from_config(cfg)


class Rows:
    """A sink keeping every drained row."""

    def __init__(self):
        self.blocks = []

    def on_frame(self, frame):
        if frame.samples.shape[0]:
            self.blocks.append(frame.samples.copy())

    @property
    def rows(self):
        return np.vstack(self.blocks) if self.blocks else np.zeros((0, len(COL)))


def run(cfg, tissue, device, clock, duration_s, **kw):
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
    # same times, positions and forces exactly, up to the first tick a stall made the loop skip.
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
    assert ticks[0] == 0 and np.all(np.diff(ticks) >= 1)
    gaps = np.nonzero(np.diff(ticks) > 1)[0]
    n = gaps[0] + 1 if gaps.size else ticks.size  # rows before any skip
    assert n > 1000
    cols = [COL[c] for c in ("t_s", "x_m", "y_m", "z_m", "fx_n", "fy_n", "fz_n", "state_skin", "state_fat", "ringw_m")]
    np.testing.assert_array_equal(rt[:n][:, cols], sim[:n][:, cols])
    assert rt[:n, COL["state_fat"]].max() == 2  # the comparison went through two punctures
    assert ticks[-1] == 2500 and result.ticks == len(ticks)  # every tick run is a row
    assert dev.force_commands >= result.ticks and dev.max_force_n == pytest.approx(np.abs(rt[:, COL["fz_n"]]).max(), abs=1e-3)
    assert not np.any(dev.last_force_n)  # the session ended with zero force


def test_stop_from_another_thread_ends_at_once_with_zero_force_and_every_row(cfg, tissue):
    dev = ScriptedDevice(DEFAULT_TRAJ, realtime=True)
    dev.open()
    sink = Rows()
    s = Session(cfg, dev, [sink], clock="realtime", duration_s=10.0, model=NeedleModel(cfg, tissue),
                realtime_priority=False)
    s.warm_up()
    threading.Timer(0.6, s.stop).start()
    result = s.run()
    dev.close()
    rows = sink.rows
    assert result.fault is None and 100 < result.ticks < 9000
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
    dev = NanAt(DEFAULT_TRAJ, t_nan=1.3, realtime=True)  # while pressing / inside the skin
    dev.open()
    s, result, rows = run(cfg, tissue, dev, "realtime", 5.0)
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
    # the Python loop, asked for explicitly, runs the same session length
    dev = ScriptedDevice(DEFAULT_TRAJ, realtime=True)
    dev.open()
    s2, result2, _ = run(cfg, tissue, dev, "realtime", 0.3, compiled_loop=False)
    assert not s2.compiled_loop and result2.fault is None and 290 <= result2.ticks <= 302

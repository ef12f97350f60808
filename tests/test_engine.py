"""The real-time engine (haptic_acu.session.engine.Session) under faults, signals, and headless replay.

Fault injection uses small test devices (real implementations of devices.base.Device, not mocks of
the engine): a press along -z into the skin on the engine's own timer that misbehaves at read N -
raises DeviceFault, returns NaN, returns a stale state, blocks, or refuses a force - and a sink
whose on_frame raises. Whatever the fault, the engine must: command zero force (the device's own
log of commands ends in zero), stop both loops, report exactly one one-line reason, close every
sink, and leave a recording (RecorderSink) that holds every tick up to the fault. Tick counts are
checked against the device's count of reads and the recorded positions against the positions the
device returned, not against the engine's own bookkeeping alone.

No timing asserts: every expectation is in ticks and counts, never in wall time.
"""
from __future__ import annotations

import json
import math
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from haptic_acu.devices.base import Device, DeviceInfo, DeviceState
from haptic_acu.devices.scripted import ScriptedDevice
from haptic_acu.session import trajectory
from haptic_acu.base.config import load_config
from haptic_acu.session.engine import Session
from haptic_acu.base.errors import DeviceFault
from haptic_acu.servo.step import NeedleModel
from haptic_acu.session.recorder import EXTRA, tick_rows, RecorderSink
from haptic_acu.tissue.body import Tissue
from haptic_acu.session.sink import Sink

REPO = Path(__file__).resolve().parents[1]
DEFAULT_TRAJ = REPO / "trajectories" / "default.csv"

FAULT_TICK = 300  # the press touches the skin at t = 0.2 s: by read 300 (t >= 0.3 s) it is loaded
Z0_M = 1e-3  # the tip starts 1 mm above the acupoint ...
SPEED_M_S = 5e-3  # ... and goes down along -z at 5 mm/s


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


@pytest.fixture(scope="module")
def tissue(cfg):
    return Tissue.from_config(cfg)  # the expensive SH fit, once; every session gets a fresh model


def session(cfg, tissue, device, sinks, clock="realtime", **kw) -> Session:
    kw.setdefault("duration_s", 5.0)  # a backstop: every test here ends well before
    s = Session(cfg, device, sinks, clock=clock, model=NeedleModel(cfg, tissue), **kw)
    s.warm_up()
    return s


class PressDevice(Device):
    """The tip at (0, 0, Z0 - SPEED * t) on the engine's clock (``read_at``), misbehaving from read
    ``at`` on according to ``mode``:

    * ``"raise"``: read raises DeviceFault;
    * ``"nan"``: the position is NaN;
    * ``"stale"``: the previous state again (device time and position stop advancing);
    * ``"block"``: read ``at`` blocks for ``block_s``, then returns a fresh state;
    * ``"set_force"``: set_force raises on any non-zero force (zero is still accepted);
    * ``None``: no fault.

    Logs every state it returned (``states``: t, x, y, z) and every force it accepted (``forces``),
    with whether a read was blocked at the time (``zeroed_while_blocked``).
    """

    def __init__(self, mode=None, at=FAULT_TICK, block_s=1.2):
        self.info = DeviceInfo("test-press", f"test press device ({mode})", 3.3, 1000.0, False)
        self.mode, self.at, self.block_s = mode, at, block_s
        self.reads = 0
        self.states: list[tuple] = []
        self.forces: list[np.ndarray] = []
        self.in_read = False
        self.zeroed_while_blocked = False
        self._last: DeviceState | None = None
        self.closed = False

    def open(self):
        pass

    def close(self):
        self.closed = True

    def read(self):  # the engine uses read_at when a device has it
        raise AssertionError("the engine should call read_at")

    def read_at(self, t):
        n = self.reads
        if n >= self.at and self.mode == "raise":
            raise DeviceFault(f"test device lost at read {n}")
        if n >= self.at and self.mode == "stale" and self._last is not None:
            self.reads += 1
            return self._last
        if n == self.at and self.mode == "block":
            self.in_read = True
            time.sleep(self.block_s)
            self.in_read = False
        p = np.array([0.0, 0.0, Z0_M - SPEED_M_S * t])
        if n >= self.at and self.mode == "nan":
            p[2] = math.nan
        state = DeviceState(t_s=t, position_m=p, velocity_m_s=np.array([0.0, 0.0, -SPEED_M_S]))
        self.reads += 1
        self._last = state
        self.states.append((t, *p))
        return state

    def set_force(self, force_n):
        f = np.array(force_n, dtype=float)
        if self.mode == "set_force" and self.reads > self.at and np.any(f != 0.0):
            raise RuntimeError(f"test actuator refused {f[2]:.3f} N")
        if self.in_read and not np.any(f):
            self.zeroed_while_blocked = True
        self.forces.append(f)


class Counter(Sink):
    """A sink counting rows and calls."""

    def __init__(self):
        self.rows = 0
        self.frames = 0
        self.started = 0
        self.closed = 0
        self.result = None

    def start(self, info):
        self.started += 1

    def on_frame(self, frame):
        self.frames += 1
        self.rows += len(frame.samples)

    def close(self, result):
        self.closed += 1
        self.result = result


class Bomb(Sink):
    """A sink that raises from its ``at``-th frame on (a broken renderer)."""

    def __init__(self, at=5):
        self.at = at
        self.calls = 0
        self.closed = 0

    def on_frame(self, frame):
        self.calls += 1
        if self.calls >= self.at:
            raise RuntimeError(f"boom in frame {frame.index}")

    def close(self, result):
        self.closed += 1


def visual_threads():
    return [t for t in threading.enumerate() if t.name == "haptic-acu-visual" and t.is_alive()]


def recorded(path) -> trajectory.Trajectory:
    return tick_rows(trajectory.load(path, extra_columns=EXTRA))


def check_stopped(result, dev, counter, reason_part):
    """Common to every fault: one one-line reason, zero force last, both loops and sinks closed."""
    assert isinstance(result.fault, str) and reason_part in result.fault, result.fault
    assert "\n" not in result.fault
    assert dev.forces and not np.any(dev.forces[-1]), "the last commanded force must be zero"
    assert visual_threads() == []
    assert counter.closed == 1 and counter.result is result
    assert counter.rows == result.ticks  # every tick reached the sinks, once


def check_recording(rec_path, dev, n_rows):
    """The recording parses as a trajectory and holds exactly the first ``n_rows`` states the
    device returned, in order (positions to the file's 0.1 um)."""
    tr = recorded(rec_path)
    assert len(tr.t_s) == n_rows
    st = np.array(dev.states[:n_rows])
    np.testing.assert_allclose(tr.t_s, st[:, 0], rtol=0, atol=0.6e-6)
    np.testing.assert_allclose(tr.pos_m, st[:, 1:4], rtol=0, atol=0.6e-7)
    return tr


# -- faults ------------------------------------------------------------------------------------


@pytest.mark.parametrize("clock", ["realtime", "sim"])
def test_device_fault_zeroes_force_and_keeps_the_recording(cfg, tissue, tmp_path, clock):
    dev, counter = PressDevice("raise"), Counter()
    rec = tmp_path / "rec.csv"
    result = session(cfg, tissue, dev, [RecorderSink(rec), counter], clock=clock).run()
    check_stopped(result, dev, counter, "device fault: test device lost at read 300")
    assert dev.reads == FAULT_TICK == result.ticks  # read 300 raised: ticks 0..299 ran
    assert dev.forces[FAULT_TICK - 1][2] > 0.05  # pressing the skin (+z) up to the fault ...
    assert all(not np.any(f) for f in dev.forces[FAULT_TICK:])  # ... zero from the faulting tick on
    tr = check_recording(rec, dev, FAULT_TICK)
    assert tr.extra["fz_n"][-1] > 0.05


@pytest.mark.parametrize("clock", ["realtime", "sim"])
def test_nan_position_is_a_fault_within_one_tick(cfg, tissue, tmp_path, clock):
    dev, counter = PressDevice("nan"), Counter()
    rec = tmp_path / "rec.csv"
    result = session(cfg, tissue, dev, [RecorderSink(rec), counter], clock=clock).run()
    check_stopped(result, dev, counter, "non-finite")
    # The NaN tick itself ran (its row is in the ring) and commanded zero; nothing after it.
    assert result.ticks == FAULT_TICK + 1 == dev.reads
    assert dev.forces[FAULT_TICK - 1][2] > 0.05
    assert all(not np.any(f) for f in dev.forces[FAULT_TICK:])
    check_recording(rec, dev, FAULT_TICK)  # a NaN row cannot be in a trajectory file: the rest is


def test_stale_device_is_a_fault(cfg, tissue, tmp_path):
    # From read 300 the device hands back the same state: its time stops while the tip presses the
    # skin. The engine allows stale_s of session time, then faults before commanding the stale force again.
    dev, counter = PressDevice("stale"), Counter()
    rec = tmp_path / "rec.csv"
    result = session(cfg, tissue, dev, [RecorderSink(rec), counter], stale_s=0.05).run()
    check_stopped(result, dev, counter, "stopped updating")
    assert "device time stuck" in result.fault
    detecting = dev.reads - 1  # the read that found the state stale did not become a tick
    assert result.ticks == detecting > FAULT_TICK + 1  # at least one stale tick ran first (50 ms)
    assert dev.forces[detecting - 1][2] > 0.05  # the stale state was still pressing ...
    assert all(not np.any(f) for f in dev.forces[detecting:])  # ... then zero, within the tick
    # The recording holds every tick: the fresh states, then the stale position repeated on the
    # engine's clock until the fault.
    tr = recorded(rec)
    assert len(tr.t_s) == result.ticks
    fresh = np.array(dev.states)
    assert len(fresh) == FAULT_TICK
    np.testing.assert_allclose(tr.pos_m[:FAULT_TICK], fresh[:, 1:4], rtol=0, atol=0.6e-7)
    np.testing.assert_allclose(tr.pos_m[FAULT_TICK:], np.tile(fresh[-1, 1:4], (result.ticks - FAULT_TICK, 1)),
                               rtol=0, atol=0.6e-7)


def test_a_read_that_blocks_trips_the_servo_watchdog(cfg, tissue, tmp_path):
    dev, counter = PressDevice("block", block_s=1.2), Counter()
    rec = tmp_path / "rec.csv"
    result = session(cfg, tissue, dev, [RecorderSink(rec), counter], servo_watchdog_s=0.3).run()
    check_stopped(result, dev, counter, "no servo tick")
    assert dev.zeroed_while_blocked  # the visual loop commanded zero while the read was stuck
    assert result.ticks == FAULT_TICK  # the late state was not used: the session had ended
    assert dev.forces[FAULT_TICK - 1][2] > 0.05
    check_recording(rec, dev, FAULT_TICK)


def test_a_stalled_tick_does_not_turn_session_time_back(cfg, tissue, tmp_path):
    # Read 300 takes 50 ms (well under the watchdog): the next tick is > 10 periods late, and the
    # servo re-anchors its deadlines instead of bursting. Session time must still only increase
    # (it once restarted from the new anchor, and the recorder refused the block: a fault).
    dev, counter = PressDevice("block", block_s=0.05), Counter()
    rec = tmp_path / "rec.csv"
    result = session(cfg, tissue, dev, [RecorderSink(rec), counter], duration_s=0.6).run()
    assert result.fault is None
    assert result.ticks == dev.reads == counter.rows and counter.closed == 1
    t = np.array(dev.states)[:, 0]
    assert np.all(np.diff(t) > 0)
    # session time is the tick's own (k x 1 ms, as a replay's): the 50 ms stall is a late tick in the
    # loop's timing, not a jump in session time
    assert t[FAULT_TICK + 1] - t[FAULT_TICK] == pytest.approx(1e-3, abs=1e-9)
    assert result.stats["period_error_us"]["max"] >= 40_000
    check_recording(rec, dev, result.ticks)


@pytest.mark.parametrize("clock", ["realtime", "sim"])
def test_exception_in_the_servo_step(cfg, tissue, tmp_path, clock):
    dev, counter = PressDevice("set_force"), Counter()
    rec = tmp_path / "rec.csv"
    result = session(cfg, tissue, dev, [RecorderSink(rec), counter], clock=clock).run()
    check_stopped(result, dev, counter, "RuntimeError: test actuator refused")
    # The tick writes its row, then its driver commands the force (as the compiled drivers do):
    # set_force of tick 300 raised after its row was written, so ticks 0..300 are the session and
    # no read after it was used.
    assert result.ticks == FAULT_TICK + 1 == dev.reads
    assert dev.forces[FAULT_TICK - 1][2] > 0.05 and not np.any(dev.forces[-1])
    check_recording(rec, dev, FAULT_TICK + 1)


@pytest.mark.parametrize("clock", ["realtime", "sim"])
def test_exception_in_the_visual_loop(cfg, tissue, tmp_path, clock):
    # The broken sink comes first: the recorder after it must still get every row.
    dev, counter, bomb = PressDevice(None), Counter(), Bomb(at=20)
    rec = tmp_path / "rec.csv"
    result = session(cfg, tissue, dev, [bomb, RecorderSink(rec), counter], clock=clock).run()
    check_stopped(result, dev, counter, "RuntimeError: boom in frame 19")
    assert bomb.closed == 1
    # a read under way when the fault came is not used
    assert dev.reads - 1 <= result.ticks <= dev.reads and result.ticks > 0
    assert result.ticks < 5000  # it stopped on the fault, not on the 5 s duration
    check_recording(rec, dev, result.ticks)


# -- signals -----------------------------------------------------------------------------------


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_stops_cleanly_with_zero_force(cfg, tissue, tmp_path, sig):
    # Paced at 8 times real time: the signal handling and the compiled loop are those of a real-paced
    # session, whose ticks and forces a paced one has bit for bit (tests/test_rtloop.py), so the
    # 1.6 s of path to the signal take 0.2 s.
    dev = ScriptedDevice(DEFAULT_TRAJ, realtime=True)
    dev.open()
    rec = tmp_path / "rec.csv"
    counter = Counter()
    s = session(cfg, tissue, dev, [RecorderSink(rec), counter], duration_s=10.0, speed=8.0)
    late = []

    def ours(signum, frame):  # a signal that arrived after the session had ended lands here, not in pytest
        late.append(signum)

    before = signal.signal(sig, ours)

    def send():  # once the tip is through the skin (default.csv: skin at 1.1-1.25 s, fat after 1.45 s)
        while s.tick < 1600 and not s._stop.is_set():
            time.sleep(0.01)
        if not s._stop.is_set():
            os.kill(os.getpid(), sig)

    killer = threading.Thread(target=send)
    killer.start()
    try:
        result = s.run()
        killer.join()
        restored = signal.getsignal(sig)
    finally:
        killer.join()
        signal.signal(sig, before)
    dev.close()
    assert result.fault is None and late == []
    assert 1600 <= result.ticks < 10000
    assert restored is ours  # the session put the previous handler back
    assert dev.max_force_n > 0.1 and not np.any(dev.last_force_n)
    assert visual_threads() == [] and counter.closed == 1 and counter.rows == result.ticks
    tr = recorded(rec)
    assert len(tr.t_s) == result.ticks and np.all(np.diff(tr.t_s) > 0)
    assert tr.extra["fz_n"][-1] > 0.02  # inserting (+z drag) when the signal came: the zero is the engine's


# -- headless replay ---------------------------------------------------------------------------


def test_headless_replay_is_deterministic(cfg, tissue, tmp_path):
    """Two sim-clock replays of the same trajectory, each with a fresh model: byte-identical
    samples and identical summaries (when the report sinks exist)."""
    report = pytest.importorskip("haptic_acu.session.report")
    outs = []
    for i in range(2):
        dev = ScriptedDevice(DEFAULT_TRAJ, force_limit_n=cfg.safety.force_limit_n)
        dev.open()
        summary = report.SummarySink(cfg)
        counter = Counter()
        rec = tmp_path / f"rec{i}.csv"
        result = session(cfg, tissue, dev, [report.SamplesCsvSink(tmp_path / f"samples{i}.csv"), summary,
                                            RecorderSink(rec), counter], clock="sim", duration_s=None).run()
        dev.close()
        assert result.fault is None
        outs.append((result.ticks, json.dumps(summary.summary(), sort_keys=True)))
    assert outs[0] == outs[1]
    a, b = (tmp_path / "samples0.csv").read_bytes(), (tmp_path / "samples1.csv").read_bytes()
    assert a == b and a.count(b"\n") == outs[0][0] + 1
    assert (tmp_path / "rec0.csv").read_bytes() == (tmp_path / "rec1.csv").read_bytes()
    # and the replay ran the whole file: 1 ms ticks from 0 to its last sample
    info = trajectory.validate(DEFAULT_TRAJ)
    assert outs[0][0] == math.floor(info.t_last_s * 1000 + 1e-6)


class ReadAtOnly(ScriptedDevice):
    """The scripted device without read-ahead: the engine must read and tick it one tick at a time
    (the Python driver, through the servo tick's C entry point)."""

    reads_ahead = False


def test_ticks_one_by_one_from_python_equal_the_compiled_blocks(cfg, tissue, tmp_path):
    """The same trajectory on simulated time, read ahead (run_frames, many frames per compiled call)
    and read tick by tick (the Python driver): identical sample rows, so both call the one servo tick."""
    report = pytest.importorskip("haptic_acu.session.report")
    out = []
    for cls in (ScriptedDevice, ReadAtOnly):
        dev = cls(DEFAULT_TRAJ, force_limit_n=cfg.safety.force_limit_n)
        dev.open()
        path = tmp_path / f"{cls.__name__}.csv"
        s = session(cfg, tissue, dev, [report.SamplesCsvSink(path)], clock="sim", duration_s=3.0)
        result = s.run()
        dev.close()
        assert result.fault is None and result.stats["servo_loop"] == "simulated"
        out.append((result.ticks, path.read_bytes(), dev.force_commands > 0))
    assert out[0][0] == out[1][0] == 3001
    assert out[0][1] == out[1][1] and b",muscle," in out[0][1]  # 3 s: past all three punctures
    assert out[1][2]  # the driver ticking one by one commands the force tick by tick


def test_recorder_keeps_only_rows_later_than_all_before_them(tmp_path):
    """A device clock can repeat or step back a timestamp; the recording (a trajectory file) must
    strictly increase. Expected rows from a plain loop over the same times."""
    from types import SimpleNamespace

    from haptic_acu.servo.samples import COL, NCOL

    blocks = [[0.001, 0.003, 0.002, 0.0025, 0.004, 0.004], [0.0035, 0.005, 0.006], [0.006], [0.0061]]
    rec = tmp_path / "rec.csv"
    sink = RecorderSink(rec)
    expected, latest = [], -math.inf
    for i, times in enumerate(blocks):
        rows = np.zeros((len(times), NCOL))
        rows[:, COL["t_s"]] = times
        rows[:, COL["z_m"]] = 0.01 * np.array(times) + 1e-6 * np.arange(len(times))  # which row it was
        rows[:, COL["dev_z_m"]] = rows[:, COL["z_m"]]  # the device where the needle is (what is recorded)
        sink.on_frame(SimpleNamespace(samples=rows))
        for t, z in zip(times, rows[:, COL["dev_z_m"]]):
            if t > latest:
                expected.append((t, z))
                latest = t
    sink.close(None)
    tr = recorded(rec)
    np.testing.assert_allclose(tr.t_s, [t for t, _ in expected], rtol=0, atol=1e-9)
    np.testing.assert_allclose(tr.pos_m[:, 2], [z for _, z in expected], rtol=0, atol=6e-8)  # file: 0.1 um


def test_a_session_takes_only_declared_sinks_and_a_sink_overrides_only_what_it_needs(cfg, tissue):
    class OnlyFrames:  # the old duck-typed shape: on_frame and nothing else
        def on_frame(self, frame):
            pass

    with pytest.raises(TypeError, match="OnlyFrames"):
        session(cfg, tissue, PressDevice(), [OnlyFrames()])

    class Frames(Sink):  # the same, declared: the base supplies warm_up, pin, start and close
        def __init__(self):
            self.rows = 0

        def on_frame(self, frame):
            self.rows += len(frame.samples)

    sink = Frames()
    res = session(cfg, tissue, PressDevice(), [sink], clock="sim", duration_s=0.05).run()
    assert res.fault is None and sink.rows == res.ticks > 0

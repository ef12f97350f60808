"""ScriptedDevice: replays a trajectory tick by tick, as the engine's 1 kHz loop will drive it."""
from __future__ import annotations

import math
import os
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from haptic_acu.devices.base import Device, DeviceState
from haptic_acu.devices.scripted import ScriptedDevice
from haptic_acu.base.errors import UserError

ROOT = Path(__file__).resolve().parent.parent
DEFAULT = ROOT / "trajectories" / "default.csv"
HEADER = "t_s,x_mm,y_mm,z_mm\n"


def _ramp(tmp_path, name="ramp.csv"):
    """z from +5 mm down at 10 mm/s, samples every 7 ms from t = 0.05 s to 0.75 s (not on ticks)."""
    t = 0.05 + 0.007 * np.arange(101)
    z = 5.0 - 10.0 * (t - 0.05)
    path = tmp_path / name
    path.write_text(HEADER + "".join(f"{a:.6f},1.0,-2.0,{b:.4f}\n" for a, b in zip(t, z)))
    return path, t, z


def test_info_and_interface(tmp_path):
    path, _, _ = _ramp(tmp_path)
    dev = ScriptedDevice(path)
    assert isinstance(dev, Device)
    assert dev.info.name == "scripted"
    assert dev.info.rate_hz == 1000
    assert dev.info.drives_clock is False
    assert dev.info.force_limit_n >= 3.3
    assert ScriptedDevice(path, force_limit_n=3.3).info.force_limit_n == 3.3


def test_missing_and_malformed_files_fail_at_construction(tmp_path):
    with pytest.raises(UserError, match="absent.csv.*not found"):
        ScriptedDevice(tmp_path / "absent.csv")
    bad = tmp_path / "bad.csv"
    bad.write_text("t,x,y,z\n0,0,0,0\n")
    with pytest.raises(UserError, match=r"bad.csv: line 1: missing column"):
        ScriptedDevice(bad)
    # a fault deep in the file is found by open(), before the session starts
    late = tmp_path / "late.csv"
    late.write_text(HEADER + "".join(f"{k * 0.01:.6f},0,0,{5 - k * 0.1:.4f}\n" for k in range(500))
                    + "5.000000,0,0,-900\n")
    dev = ScriptedDevice(late)
    with pytest.raises(UserError, match=r"late.csv: line 502: .*m/s"):
        dev.open()


def test_headless_replay_tick_by_tick(tmp_path):
    path, t, z = _ramp(tmp_path)
    ticks = []
    with ScriptedDevice(path) as dev:
        assert dev.duration_s == pytest.approx(t[-1])
        state = dev.read()
        assert state.t_s == 0.0
        while not state.done:
            ticks.append(state)
            dev.set_force(np.zeros(3))
            dev.advance(1e-3)
            state = dev.read()
        ticks.append(state)
    times = np.array([s.t_s for s in ticks])
    # exactly 1 ms apart, no drift, done at the first tick at or after the last sample
    np.testing.assert_allclose(np.diff(times), 1e-3, rtol=0, atol=1e-12)
    assert times[-1] >= t[-1] - 1e-12 and times[-2] < t[-1]
    assert len(ticks) == math.ceil(round(t[-1] * 1000, 6)) + 1
    # positions: the file's samples linearly interpolated (numpy's interp as the reference), in m
    pos = np.array([s.position_m for s in ticks])
    np.testing.assert_allclose(pos[:, 2], np.interp(times, t, z) / 1000, rtol=0, atol=1e-12)
    np.testing.assert_allclose(pos[:, :2], np.broadcast_to([1e-3, -2e-3], (len(pos), 2)), atol=1e-15)
    # velocity: -10 mm/s along z once a whole tick is inside the ramp, 0 before it starts
    vel = np.array([s.velocity_m_s for s in ticks])
    moving = (times - 1e-3 >= t[0]) & (times <= t[-1])
    np.testing.assert_allclose(vel[moving], np.broadcast_to([0, 0, -0.01], (moving.sum(), 3)), atol=1e-9)
    np.testing.assert_array_equal(vel[times <= t[0]], 0.0)
    assert all(isinstance(s, DeviceState) and s.buttons == 0 for s in ticks)


def test_read_block_matches_tick_by_tick(tmp_path):
    """The engine's headless loop asks for a visual frame of ticks at once."""
    path, t, z = _ramp(tmp_path)
    with ScriptedDevice(path) as a, ScriptedDevice(path) as b:
        ticks = np.arange(0, 800) * 1e-3
        P, V, D = [], [], []
        for k in range(0, len(ticks), 17):
            p, v, d = b.read_block(ticks[k:k + 17])
            P.append(p)
            V.append(v)
            D.append(d)
        one = [a.read_at(x) for x in ticks]
    np.testing.assert_allclose(np.concatenate(P), [s.position_m for s in one], rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.concatenate(V), [s.velocity_m_s for s in one], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(np.concatenate(D), [s.done for s in one])
    np.testing.assert_allclose(np.concatenate(P)[:, 2], np.interp(ticks, t, z) / 1000, atol=1e-12)


def test_read_at_seek_and_the_ends(tmp_path):
    path, t, z = _ramp(tmp_path)
    dev = ScriptedDevice(path)
    with pytest.raises(RuntimeError):
        dev.read_at(0.1)
    dev.open()
    # before the first sample: held at it, not done
    s = dev.read_at(0.0)
    assert s.position_m[2] == pytest.approx(5e-3) and not s.done
    # forward, then backward (re-reads the file), then past the end
    for tq in (0.3, 0.6, 0.1234, 0.7):
        s = dev.read_at(tq)
        assert s.t_s == tq
        assert s.position_m[2] == pytest.approx(np.interp(tq, t, z) / 1000, abs=1e-12)
    s = dev.read_at(t[-1] + 1.0)
    assert s.done
    assert s.position_m[2] == pytest.approx(z[-1] / 1000, abs=1e-12)
    np.testing.assert_array_equal(s.velocity_m_s, 0.0)
    # seek sets the clock read() uses
    dev.seek(0.4)
    assert dev.read().t_s == 0.4
    dev.advance(0.5e-3)
    dev.advance(0.5e-3)
    assert dev.read().t_s == pytest.approx(0.401, abs=1e-15)
    dev.close()
    dev.close()  # twice is safe


def test_set_force_is_recorded(tmp_path):
    path, _, _ = _ramp(tmp_path)
    with ScriptedDevice(path) as dev:
        f = np.array([0.1, -0.2, 2.0])
        dev.set_force(f)
        f[:] = 99.0  # the device kept its own copy
        np.testing.assert_array_equal(dev.last_force_n, [0.1, -0.2, 2.0])
        dev.set_force([0.0, 0.0, -3.0])
        assert dev.force_commands == 2
        assert dev.max_force_n == pytest.approx(3.0)
        np.testing.assert_array_equal(dev.last_force_n, [0.0, 0.0, -3.0])


def test_realtime_mode_uses_the_wall_clock(tmp_path):
    path, t, z = _ramp(tmp_path)
    with ScriptedDevice(path, realtime=True) as dev:
        states = [dev.read() for _ in range(200)]
        dev.advance(10.0)  # ignored in real time
        later = dev.read()
    times = [s.t_s for s in states] + [later.t_s]
    assert times[0] == 0.0
    assert all(b >= a for a, b in zip(times, times[1:]))
    assert later.t_s < 10.0
    for s in states[::20] + [later]:
        assert s.position_m[2] == pytest.approx(np.interp(s.t_s, t, z) / 1000, abs=1e-12)


def test_default_replay_inserts_at_10_mm_per_s():
    with ScriptedDevice(DEFAULT) as dev:
        assert 15.0 <= dev.duration_s <= 20.0
        vz = []
        while True:
            s = dev.read()
            vz.append(s.velocity_m_s[2])
            if s.done:
                break
            dev.advance(1e-3)
    vz = np.array(vz)
    assert -vz.min() == pytest.approx(0.010, rel=0.02)  # the 10 mm/s insertion and withdrawal
    assert vz.max() == pytest.approx(0.010, rel=0.02)
    assert len(vz) == pytest.approx(dev.duration_s * 1000, abs=2)


def test_device_streams_the_file_during_playback(tmp_path):
    """Playing a 200,000-row file (7 MB) keeps a small window, not the file (validation's own
    bounded memory is tested on a million rows in test_trajectory.py)."""
    path = tmp_path / "long.csv"
    n = 200_000
    k = np.arange(n)
    z = 5.0 - 2.0 * np.sin(k * 1e-4)  # mm, at t = k ms
    path.write_text(HEADER + "".join(f"{a:.6f},0.0000,0.0000,{b:.4f}\n" for a, b in zip(k * 1e-3, z)))
    size = os.path.getsize(path)
    dev = ScriptedDevice(path)
    dev.open()
    tracemalloc.start()
    try:
        for tq in np.arange(0.0, 200.0, 0.25):
            s = dev.read_at(tq)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert dev.trajectory_info.samples == n
    assert s.position_m[2] == pytest.approx((5.0 - 2.0 * math.sin(199.75 / 10)) / 1000, abs=1e-7)
    assert peak < size / 20

"""A cohort worker no longer keeps a session's rows: the metrics are streamed, the
reference replay keeps ticks and forces, the smoothness columns a six-column track. Its tables equal
the whole-row computation (cohort.insertion_table on every row), and a worker replaying long
sessions peaks far below what keeping their rows took."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from test_replay_memory import tiled

ROOT = Path(__file__).resolve().parent.parent


def _job(path: Path, cfg):
    from haptic_acu.cohort.sessions import Job, config_hash, file_sha256
    return Job(session=path.stem, file=str(path), cfg=cfg, input_sha256=file_sha256(path), config_sha256=config_hash(cfg))


def test_pairwise_plan_gives_numpy_sum_bits():
    from haptic_acu.session.pathstream import pairwise_combine, pairwise_plan
    rng = np.random.default_rng(5)
    for n in [*range(1, 300), 1000, 8191, 8192, 8193, 65537, 600001]:
        a = rng.random(n) * rng.choice([1e-6, 1.0, 1e5])
        sums = {off: np.sum(a[off:off + ln]) for off, ln in pairwise_plan(n)}
        assert pairwise_combine(sums, n) == float(np.sum(a))


def test_blockwise_zero_phase_filter_is_smooth_path_to_the_bit():
    from types import SimpleNamespace

    from haptic_acu.session.pathstream import TrackFile, smoothed_blocks
    from haptic_acu.servo.samples import COL, NCOL
    from haptic_acu.analysis.skill_metrics import smooth_path
    rng = np.random.default_rng(6)
    for n in (2, 3, 40, 1000, 70_001, 150_000):
        rows = np.zeros((n, NCOL))
        t = np.arange(n) * 1e-3
        rows[:, COL["t_s"]] = t
        rows[:, COL["x_m"]:COL["x_m"] + 3] = np.cumsum(rng.normal(size=(n, 3)), axis=0) * 1e-5
        tr = TrackFile()
        i = 0
        while i < n:
            k = int(rng.integers(1, 5000))
            tr.on_frame(SimpleNamespace(samples=rows[i:i + k]))
            i += k
        want = smooth_path(t, rows[:, COL["x_m"]:COL["x_m"] + 3])
        got = np.full_like(want, np.nan)
        for a, ps in smoothed_blocks(tr, 10.0, block=int(rng.integers(50, 40_000))):
            got[a:a + len(ps)] = ps
        tr.release()
        assert np.array_equal(got, want), n


@pytest.mark.slow
@pytest.mark.parametrize("name", ["default", "second_insertion_same_site", "twirl_reducing", "tiled"])
def test_worker_tables_equal_the_whole_row_computation(name, tmp_path):
    from haptic_acu.cohort.sessions import _tissue, insertion_table, replay_session
    from haptic_acu.base.config import load_config
    from haptic_acu.devices.scripted import ScriptedDevice
    from haptic_acu.session.engine import Session
    from haptic_acu.servo.step import NeedleModel
    from haptic_acu.session.replay import replay_rows
    from haptic_acu.session.report import SummarySink

    cfg = load_config()
    path = ROOT / "trajectories" / f"{name}.csv"
    if name == "tiled":  # 80 s: more rows than one of the filter's blocks (pathstream.BLOCK)
        path = tmp_path / "tiled.csv"
        tiled(ROOT / "trajectories" / "default.csv", 80 / 60, path)
    job = _job(path, cfg)
    rec = replay_session(job)
    assert rec["error"] is None
    # the unbounded computation, as the worker did it before: every row kept
    dev = ScriptedDevice(path, max_hand_speed_m_per_s=cfg.scene.max_hand_speed_m_per_s, realtime=False,
                         force_limit_n=cfg.safety.force_limit_n)
    dev.open()
    sink = SummarySink(cfg)
    s = Session(cfg, dev, [sink], clock="sim", model=NeedleModel(cfg, _tissue(job)))
    s.warm_up()
    s.run()
    dev.close()
    ref = replay_rows(path, cfg, roll=False) if name.startswith("twirl") else None
    sm, want = insertion_table(sink.rows(), cfg, _tissue(job), ref)
    assert len(want) == sm["insertions"] >= 1
    assert json.dumps(rec["insertions"], sort_keys=True) == json.dumps(want, sort_keys=True)
    if ref is not None:
        assert any(r["grasp_felt_ratio"] is not None for r in want)


CHILD = """
import sys
from pathlib import Path
from haptic_acu.cohort.sessions import Job, config_hash, file_sha256, replay_session
from haptic_acu.base.config import load_config
cfg = load_config()
for f in sys.argv[1:]:
    p = Path(f)
    rec = replay_session(Job(p.stem, str(p), cfg, file_sha256(p), config_hash(cfg)))
    assert rec["error"] is None, rec["error"]
hwm = next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM:"))
print("VMHWM_KB", hwm)
"""


def worker_peak_mb(paths) -> float:
    p = subprocess.Popen([sys.executable, "-c", CHILD, *map(str, paths)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True, cwd=ROOT)
    try:
        so, se = p.communicate(timeout=1200)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    assert p.returncode == 0, se
    return int(next(ln for ln in so.splitlines() if ln.startswith("VMHWM_KB")).split()[1]) / 1024


@pytest.mark.slow
def test_worker_peak_on_long_sessions(tmp_path):
    """Three 2-minute sessions through one worker against two short ones: the rows alone were
    ~30 MB a session (and the metrics copied them); now ~6 MB of track and the filter's temporaries."""
    src = ROOT / "trajectories" / "default.csv"
    long = []
    for k in range(3):
        p = tmp_path / f"long{k}.csv"
        tiled(src, 2.0, p)
        long.append(p)
    short_mb = worker_peak_mb([src, ROOT / "trajectories" / "slow_insertion.csv"])
    long_mb = worker_peak_mb(long)
    print({"short_mb": short_mb, "long_mb": long_mb})
    assert long_mb - short_mb < 40.0, (short_mb, long_mb)
    assert np.isfinite(long_mb)

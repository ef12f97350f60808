"""Cohort throughput: sessions per second per core on a synthetic cohort, local pool against Dask.

    python -m haptic_acu.bench.cohort_bench [--sessions N] [--duration S] [--workers W] [--no-dask]

:func:`synthetic_cohort` writes a reproducible class of trainees (half "novice", half "expert"),
each session a trajectory of needle insertions whose quality depends on the trainee's skill and
improves session by session (entry offset, angle, depth, stop-and-go approach, wobble). It is also
the tests' fixture. :func:`cohort` (the ``haptic-acu bench`` hook, ``cohort(sizes, progress)``
like the other benchmarks in ``run.py``) replays it with the local pool and with a Dask
``LocalCluster`` of as many single-threaded worker processes, and reports wall time, sessions per
second per core and the Dask run's overhead (its wall time over the mean of two local runs, one
before it and one after), and checks the runs give identical tables.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

RATE_HZ = 200.0
HOVER_MM = 5.0


def _min_jerk(tau):
    tau = np.clip(tau, 0.0, 1.0)
    return tau ** 3 * (10 - 15 * tau + 6 * tau ** 2)


class _Path:
    """Segments of a tip path: (duration s, f(time array within segment) -> positions (n, 3) mm)."""

    def __init__(self, start):
        self.pos = np.asarray(start, float)
        self.segs = []

    def hold(self, s):
        p = self.pos.copy()
        self.segs.append((s, lambda t: np.repeat(p[None], len(t), 0)))

    def move(self, target, speed_mm_s, parts=1, wobble_mm=0.0, rng=None):
        """To ``target`` in ``parts`` consecutive minimum-jerk submovements (stop-and-go for parts > 1),
        with a lateral wobble of ``wobble_mm`` (zero at both ends)."""
        a, b = self.pos.copy(), np.asarray(target, float)
        d = b - a
        length = float(np.linalg.norm(d))
        dur = max(0.2, 1.875 * length / speed_mm_s)  # a min-jerk move's peak speed is 1.875 x its mean
        if parts > 1:
            cuts = np.sort(rng.uniform(0.15, 0.85, parts - 1))
            fr = np.diff(np.r_[0.0, cuts, 1.0])
        else:
            fr = np.array([1.0])
        side = np.cross(d / max(length, 1e-9), [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 * length else [0.0, 1.0, 0.0])
        side /= max(np.linalg.norm(side), 1e-12)
        f_w = 1.5 + (rng.uniform(0, 1) if rng is not None else 0.0)

        def at(t):
            tau = t / dur
            s = np.zeros_like(tau)
            edges = np.r_[0.0, np.cumsum(fr)]
            for i in range(len(fr)):
                s += fr[i] * _min_jerk((tau - edges[i]) / fr[i])
            lat = wobble_mm * np.sin(np.pi * tau) * np.sin(2 * np.pi * f_w * t)
            return a + s[:, None] * d + lat[:, None] * side

        self.segs.append((dur, at))
        self.pos = b.copy()

    def lift_thrust(self, direction, amplitude_mm, freq_hz, cycles):
        p, u = self.pos.copy(), np.asarray(direction, float)
        self.segs.append((cycles / freq_hz,
                          lambda t: p - (amplitude_mm * (1 - np.cos(2 * np.pi * freq_hz * t)) / 2)[:, None] * u))

    def sample(self):
        total = sum(d for d, _ in self.segs)
        n = int(math.ceil(total * RATE_HZ - 1e-9)) + 1
        t = np.arange(n) / RATE_HZ
        starts = np.cumsum([0.0] + [d for d, _ in self.segs])
        idx = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(self.segs) - 1)
        pos = np.empty((n, 3))
        for i, (_, f) in enumerate(self.segs):
            k = idx == i
            if k.any():
                pos[k] = f(t[k] - starts[i])
        return t, pos


def _insertion(path: _Path, rng, skill: float) -> None:
    r = (1.0 - skill) * 4.0 + abs(rng.normal(0, 0.4))
    phi = rng.uniform(0, 2 * np.pi)
    entry = np.array([r * np.cos(phi), r * np.sin(phi), 0.0])
    alpha = np.radians((1.0 - skill) * 20.0 + abs(rng.normal(0, 2.0)))
    beta = rng.uniform(0, 2 * np.pi)
    d = np.array([np.sin(alpha) * np.cos(beta), np.sin(alpha) * np.sin(beta), -np.cos(alpha)])
    depth = float(np.clip(rng.normal(22.0, 2.0 + 8.0 * (1.0 - skill)), 6.0, 33.0))
    hover = entry - HOVER_MM / np.cos(alpha) * d
    path.move(hover, 20.0, rng=rng)
    path.hold(0.3)
    parts = 1 + int(round((1.0 - skill) * 2 * rng.uniform(0.5, 1.0)))
    path.move(entry + depth * d, rng.uniform(8.0, 14.0), parts=parts, wobble_mm=(1.0 - skill) * 0.8, rng=rng)
    path.hold(0.4)
    path.lift_thrust(d, rng.uniform(2.0, 4.0), rng.uniform(0.8, 1.2), int(rng.integers(1, 4)))
    path.hold(0.3)
    path.move(hover, rng.uniform(12.0, 18.0), rng=rng)
    path.hold(0.3)


def synthetic_session(file: Path, skill: float, seed: int, duration_s: float = 6.0) -> float:
    """Write one session's trajectory (CSV, 200 Hz) of insertions until ``duration_s`` is filled
    (at least one); returns its length (s)."""
    from haptic_acu.session.trajectory import TrajectoryWriter

    rng = np.random.default_rng(seed)
    path = _Path([0.0, 0.0, HOVER_MM])
    path.hold(0.2)
    while True:
        _insertion(path, rng, skill)
        if sum(d for d, _ in path.segs) >= duration_s - 4.0:
            break
    t, pos = path.sample()
    with TrajectoryWriter(file, comments=[f"synthetic session, skill {skill:.3f}, seed {seed}"]) as w:
        w.append_rows(np.column_stack([t, pos * 1e-3]))
    return float(t[-1])


def synthetic_cohort(folder, trainees: int = 4, sessions: int = 3, duration_s: float = 6.0, seed: int = 0,
                     extra_column: bool = True) -> Path:
    """A class of ``trainees`` (first half novice, second half expert) with ``sessions`` each, files in
    ``folder/sessions/``, manifest ``folder/manifest.csv`` (relative paths); returns the manifest."""
    folder = Path(folder)
    (folder / "sessions").mkdir(parents=True, exist_ok=True)
    lines = ["session,trainee,file,level,date" + (",group" if extra_column else "")]
    for i in range(trainees):
        expert = i >= trainees // 2
        for j in range(sessions):
            skill = min(1.0, (0.75 if expert else 0.15) + 0.12 * j)
            sid = f"t{i:02d}-s{j:02d}"
            synthetic_session(folder / "sessions" / f"{sid}.csv", skill, seed * 100_003 + i * 1000 + j, duration_s)
            row = f"{sid},trainee{i:02d},sessions/{sid}.csv,{'expert' if expert else 'novice'},2026-09-{j + 1:02d}"
            lines.append(row + (f",class-{i % 2}" if extra_column else ""))
    (folder / "manifest.csv").write_text("\n".join(lines) + "\n")
    return folder / "manifest.csv"


def _tables(out: Path):
    import pyarrow.parquet as pq

    return {n: pq.read_table(out / f"{n}.parquet") for n in ("insertions", "sessions")}


def measure(n_sessions: int = 8, duration_s: float = 10.0, workers: int = 0, dask: bool = True,
            progress: bool = False) -> dict:
    """Replay a synthetic cohort of ``n_sessions`` with the local pool (and a Dask LocalCluster)."""
    from haptic_acu.cohort.sessions import read_manifest
    from haptic_acu.cohort.update import run_cohort
    from haptic_acu.base.config import load_config

    workers = workers or max(1, len(os.sched_getaffinity(0)))
    cfg = load_config()
    res = {"sessions": n_sessions, "session_s": duration_s, "workers": workers}
    with tempfile.TemporaryDirectory(prefix="haptic-acu-cohort-bench-") as tmp:
        tmp = Path(tmp)
        trainees = max(2, n_sessions // 4)
        man = synthetic_cohort(tmp / "class", trainees, -(-n_sessions // trainees), duration_s)
        manifest = read_manifest(man)
        manifest.entries = manifest.entries[:n_sessions]
        st = {}
        run_cohort(manifest, tmp / "local", cfg, jobs=workers, quiet=not progress, stats=st)
        sim_s = float(sum(_tables(tmp / "local")["sessions"]["session_duration_s"].to_pylist()))
        res["trajectory_s"] = sim_s
        wall = st["replay_s"]
        res["local"] = {"replay_s": wall, "total_s": st["total_s"], "sessions_per_s_per_core": n_sessions / wall / workers,
                        "sim_s_per_wall_s": sim_s / wall}
        if dask:
            from distributed import Client, LocalCluster

            import dask

            t = time.perf_counter()
            with dask.config.set({"temporary-directory": str(tmp / "dask-scratch")}), \
                    LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None) as lc, \
                    Client(lc) as client:
                start_s = time.perf_counter() - t
                st = {}
                run_cohort(manifest, tmp / "dask", cfg, scheduler=client, quiet=not progress, stats=st)
            wall_d, total_d = st["replay_s"], st["total_s"]
            # the local pool once more after Dask: the ratio is against the mean of the runs on either
            # side, so a host that speeds up or slows down over the minutes favours neither
            st = {}
            run_cohort(manifest, tmp / "local-after", cfg, jobs=workers, quiet=not progress, stats=st)
            res["local"]["replay_s_after"] = st["replay_s"]
            around = (wall + st["replay_s"]) / 2
            res["dask"] = {"cluster_start_s": start_s, "replay_s": wall_d, "total_s": total_d,
                           "sessions_per_s_per_core": n_sessions / wall_d / workers,
                           "local_replay_s_around": around,
                           "overhead_x": wall_d / around, "overhead_with_cluster_start_x": (wall_d + start_s) / around}
            a, b, c = _tables(tmp / "local"), _tables(tmp / "dask"), _tables(tmp / "local-after")
            res["dask"]["identical_tables"] = all(a[n].equals(b[n]) and a[n].equals(c[n]) for n in a)
    return res


def cohort(sizes=None, progress: bool = False) -> dict:
    """The ``haptic-acu bench`` hook: a small cohort (8 sessions of 10 s)."""
    return {"cohort": measure(8, 10.0, progress=progress)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="cohort_bench", description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=8)
    ap.add_argument("--duration", type=float, default=10.0, help="seconds of trajectory per session")
    ap.add_argument("--workers", type=int, default=0)
    ap.add_argument("--no-dask", action="store_true")
    a = ap.parse_args(argv)
    print(json.dumps(measure(a.sessions, a.duration, a.workers, not a.no_dask, progress=True), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

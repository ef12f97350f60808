"""The cohort's distributed path against a hostile world: schemes Dask does not speak, a scheduler
with no worker, a cluster that loses every worker mid-run, and a local pool that is terminated.

Each ends within its stated time with one line; finished sessions are kept; no process is left.
"""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from haptic_acu.base.errors import UserError

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("address, expect", [
    ("udp://127.0.0.1:8786", "'udp://' is not a protocol"),
    ("http://127.0.0.1:8787", "'http://' is not a protocol"),
    ("inproc://127.0.0.1:1", "'inproc://' is not a protocol"),
])
def test_schemes_dask_does_not_speak(address, expect):
    from haptic_acu.cohort.run import scheduler_address

    with pytest.raises(UserError, match=expect):
        scheduler_address(address)


def test_tls_without_certificates_is_one_line():
    from haptic_acu.cohort.run import connect

    with pytest.raises(UserError, match="certificates"):
        connect("tls://127.0.0.1:8786", timeout_s=2)


def test_a_listener_that_is_not_a_scheduler(tmp_path):
    """tcp:// to something that accepts and says nothing: one line within the timeout, no traceback."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(4)
    port = srv.getsockname()[1]
    man = tmp_path / "m.csv"
    man.write_text("session,trainee,file\ns1,ann,a.csv\n")
    try:
        t0 = time.monotonic()
        p = subprocess.run([sys.executable, "-m", "haptic_acu", "cohort", str(man), "--out", str(tmp_path / "o"),
                            "--scheduler", f"tcp://127.0.0.1:{port}", "--scheduler-timeout", "1"],
                           capture_output=True, text=True, timeout=120, cwd=REPO)
        took = time.monotonic() - t0
    finally:
        srv.close()
    assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr
    lines = [ln for ln in p.stderr.strip().splitlines() if not ln.startswith("haptic-acu: ")]
    assert len(lines) == 1 and "cannot connect within 1 s" in lines[0], p.stderr
    assert took < 60
    assert not (tmp_path / "o").exists()


@pytest.fixture
def cluster(tmp_path):
    distributed = pytest.importorskip("distributed")
    import dask

    with dask.config.set({"temporary-directory": str(tmp_path / "dask-scratch")}), \
            distributed.LocalCluster(n_workers=0, processes=False, protocol="tcp://",
                                     dashboard_address=None) as lc:
        yield lc


def test_no_worker_joins_within_the_timeout(cluster, tmp_path, capsys):
    from haptic_acu.cli import main

    man = tmp_path / "m.csv"
    man.write_text(f"session,trainee,file\ns1,ann,{REPO / 'trajectories' / 'default.csv'}\n")
    t0 = time.monotonic()
    rc = main(["cohort", str(man), "--out", str(tmp_path / "o"), "--scheduler", cluster.scheduler_address,
               "--scheduler-timeout", "2"])
    err = capsys.readouterr().err
    assert rc == 2 and time.monotonic() - t0 < 30
    assert "waiting up to 2 s" in err and "no worker joined in 2 s" in err, err


def test_losing_every_worker_stops_with_one_line_and_keeps_finished_sessions(cluster, tmp_path):
    """One worker; once the first session is saved the worker goes: the run stops within the timeout
    (exit 3, one line) and the finished session is on disk for the next run."""
    from haptic_acu.base.config import load_config
    from haptic_acu.cohort.run import run_dask
    from haptic_acu.cohort.sessions import Job, config_hash, file_sha256

    traj = REPO / "trajectories" / "default.csv"
    cfg = load_config()
    csha = config_hash(cfg)
    jobs = [Job(f"s{k}", str(traj), cfg, file_sha256(traj), csha, None) for k in range(4)]
    from distributed import Client

    client = Client(cluster.scheduler_address, set_as_default=False, timeout=30)
    cluster.scale(1)
    saved = []

    def on_result(rec):
        saved.append(rec)
        if len(saved) == 1:  # the cluster loses its only worker
            threading.Thread(target=lambda: cluster.scale(0), daemon=True).start()

    t0 = time.monotonic()
    try:
        with pytest.raises(UserError) as e:
            run_dask(jobs, client, on_result, timeout_s=3)
    finally:
        client.close()
    assert e.value.exit_status == 3 and "every worker has been lost" in str(e.value)
    assert time.monotonic() - t0 < 120
    assert saved and saved[0]["summary"] is not None and not saved[0].get("error")


def test_batches_sized_to_the_workers():
    """At least four tasks per worker thread, at most BATCH_MAX sessions a task, never empty."""
    from haptic_acu.cohort.run import BATCH_MAX, batch_size

    assert batch_size(1, 8) == 1 and batch_size(7, 2) == 1
    assert batch_size(40, 2) == 5 and 40 / batch_size(40, 2) >= 4 * 2
    assert batch_size(200, 2) == BATCH_MAX
    assert batch_size(10, 0) == 2  # no thread counted yet: as one


def test_batches_cover_every_session_once_and_end_single():
    """Consecutive, in order, every job once; the last tasks one session each (the workers finish
    together)."""
    from haptic_acu.cohort.run import BATCH_MAX, batches

    jobs = list(range(200))
    got = list(batches(jobs, 2))
    assert [j for b in got for j in b] == jobs
    sizes = [len(b) for b in got]
    assert sizes[0] == BATCH_MAX and sizes == sorted(sizes, reverse=True) and sizes[-8:] == [1] * 8
    assert list(batches([], 2)) == []


def test_a_cohort_on_dask_pauses_the_profiler_and_builds_the_tissue_once(cluster, monkeypatch):
    """The workers' sampling profiler (every 10 ms, it takes the GIL from the replay) stops for the
    run and runs again once it is over; three sessions in three tasks on one worker build the
    configuration's tissue once."""
    from distributed import Client

    from haptic_acu.base.config import load_config
    from haptic_acu.cohort import sessions
    from haptic_acu.cohort.daskworker import profiler_running
    from haptic_acu.cohort.run import batch_size, run_dask
    from haptic_acu.tissue.body import Tissue

    built = []
    real = Tissue.from_config.__func__
    monkeypatch.setattr(Tissue, "from_config", classmethod(lambda cls, cfg: built.append(1) or real(cls, cfg)))
    monkeypatch.setattr(sessions, "_TISSUE", {})  # the worker is a thread of this process: a fresh one
    traj = REPO / "trajectories" / "default.csv"
    cfg = load_config()
    jobs = [sessions.Job(f"s{k}", str(traj), cfg, sessions.file_sha256(traj), sessions.config_hash(cfg), None)
            for k in range(3)]
    assert batch_size(len(jobs), 1) == 1
    cluster.scale(1)
    client = Client(cluster.scheduler_address, set_as_default=False, timeout=30)
    try:
        client.wait_for_workers(1, timeout=30)
        assert list(client.run(profiler_running).values()) == [True]  # Dask's default: sampling
        during = []
        run_dask(jobs, client, lambda rec: during.append((rec, client.run(profiler_running))), timeout_s=30)
        after = client.run(profiler_running)
    finally:
        client.close()
    assert sorted(rec["session"] for rec, _ in during) == ["s0", "s1", "s2"]
    assert all(rec["error"] is None and rec["summary"] is not None for rec, _ in during)
    assert [list(running.values()) for _, running in during] == [[False]] * 3
    assert list(after.values()) == [True]
    assert len(built) == 1


def _children(pid: int) -> set[int]:
    out = set()
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            out |= {int(c) for c in (task / "children").read_text().split()}
        except OSError:
            pass
    return out


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie waiting for its parent is gone for this purpose
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_a_terminated_local_pool_takes_its_workers(tmp_path, sig):
    from haptic_acu.bench.cohort_bench import synthetic_cohort

    man = synthetic_cohort(tmp_path / "class", trainees=2, sessions=2, duration_s=60.0, seed=1)
    p = subprocess.Popen([sys.executable, "-m", "haptic_acu", "cohort", str(man), "--out", str(tmp_path / "o"),
                          "--jobs", "2", "--quiet"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         start_new_session=True)
    workers: set[int] = set()
    try:
        end = time.monotonic() + 120
        while time.monotonic() < end and p.poll() is None:
            workers = {c for c in _children(p.pid) if "multiprocessing" in Path(f"/proc/{c}/cmdline").read_text()}
            if len(workers) >= 2:
                break
            time.sleep(0.2)
        assert len(workers) >= 2, "the pool did not start"
        p.send_signal(sig)
        _, err = p.communicate(timeout=60)
        end = time.monotonic() + 30
        while time.monotonic() < end and any(_alive(w) for w in workers):
            time.sleep(0.2)
        assert not any(_alive(w) for w in workers)
        if sig == signal.SIGTERM:
            assert p.returncode == 143, err.decode(errors="replace")[-2000:]
    finally:
        for w in workers:
            try:
                os.kill(w, signal.SIGKILL)
            except ProcessLookupError:
                pass
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


def test_the_cohort_plugin_lets_large_arrays_reuse_the_heap_under_a_nannys_settings(tmp_path):
    """Under ``MALLOC_TRIM_THRESHOLD_`` (what a Dask nanny sets) every 2 MiB array is mapped and
    faulted in anew; while the cohort's plugin is set up the heap is reused (few page faults, counted
    by the kernel), and its teardown puts the nanny's behaviour back."""
    code = (
        "import json, resource, types\n"
        "import numpy as np\n"
        "from haptic_acu.cohort.daskworker import CohortWorkerPlugin\n"
        "def faults():\n"
        "    r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
        "    for _ in range(40):\n"
        "        a = np.ones(1 << 18)\n"
        "        del a\n"
        "    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0\n"
        "w = types.SimpleNamespace(periodic_callbacks={})\n"
        "p = CohortWorkerPlugin('x')\n"
        "before = faults()\n"
        "p.setup(w)\n"
        "during = faults()\n"
        "p.teardown(w)\n"
        "print(json.dumps([before, during, faults()]))\n")
    env = dict(os.environ, MALLOC_TRIM_THRESHOLD_="65536")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    before, during, after = json.loads(r.stdout.splitlines()[-1])
    pages = 40 * (8 << 18) // 4096  # every page of every array
    assert before > 0.9 * pages and after > 0.9 * pages, (before, after)
    assert during < 0.1 * pages, during

"""The built wheel, installed into a fresh virtual environment, works from any folder.

The wheel is built from this checkout (``pip wheel``; its build backend comes from pip's configured
indexes), installed with ``--no-deps`` into a new venv whose dependencies come from the test's own
environment through a ``.pth`` line (fast, offline), and its console script runs ``replay``, ``fit``
and ``score`` in an empty folder. Independently of what those commands read, every file the
repository keeps under ``config/`` and ``trajectories/`` must be in the wheel as package data, and no
top-level ``devices`` or ``bench`` package may be installed.

The wheel goes in without compiled kernels, so its first command compiles them: that one compile
serves the bench's first-run row too (``bench.run.first_run``, timed in children of the installed
wheel's interpreter with empty numba and table caches), and the commands after it load the kernels
that run left.
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
TIMEOUT_S = 900


def _git_files(*folders) -> list[str]:
    r = subprocess.run(["git", "ls-files", *folders], cwd=ROOT, capture_output=True, text=True, timeout=60)
    if r.returncode != 0:
        pytest.skip("not a git checkout: the repository's file list is unknown")
    return [ln for ln in r.stdout.splitlines() if ln]


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    base = tmp_path_factory.mktemp("wheel")
    dist = base / "dist"
    # without the kernels compiled into it (setup.py; the bench's wheel_first_run measures those):
    # the first run below compiles them, from empty caches
    env = dict(os.environ, HAPTIC_ACU_NO_PRECOMPILE="1")
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(dist), str(ROOT)],
                       capture_output=True, text=True, timeout=TIMEOUT_S, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    (wheel,) = dist.glob("haptic_acu-*.whl")
    venv = base / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    py = venv / "bin" / "python"
    r = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "-q", "--no-deps", "--no-index",
                        str(wheel)], capture_output=True, text=True, timeout=TIMEOUT_S)
    assert r.returncode == 0, r.stderr[-3000:]
    site = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               capture_output=True, text=True, check=True, timeout=60).stdout.strip())
    # the dependencies: this environment's site-packages, after the venv's own (a plain path line: the
    # editable install's own .pth files there are not processed, so the checkout is not importable)
    (site / "zz_test_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    work = base / "elsewhere"
    work.mkdir()
    return {"wheel": wheel, "venv": venv, "site": site, "work": work}


@pytest.fixture(scope="module")
def first_run(installed, tmp_path_factory):
    """``bench.run.first_run`` on a tiny trajectory, its two replays run by the installed wheel's
    interpreter (the child command is the bench's own, only its interpreter swapped): what each
    child saw, the result, and a copy of the caches its runs filled (the bench removes its own)."""
    from haptic_acu.bench import run
    from haptic_acu.session.trajectory import TrajectoryWriter

    base = tmp_path_factory.mktemp("first_run")
    traj = base / "short.csv"
    with TrajectoryWriter(traj) as w:
        w.append_rows([[0.0, 0.0, 0.0, 1e-3], [0.3, 0.0, 0.0, -2e-3], [0.6, 0.0, 0.0, 1e-3]])
    seen = []
    real = run._timed_child
    kept = base / "caches"

    def spy(cmd, env, cwd):
        assert cmd[:4] == [sys.executable, "-m", "haptic_acu", "replay"], cmd
        seen.append((env["NUMBA_CACHE_DIR"], env["HAPTIC_ACU_CACHE"], sorted(Path(env["NUMBA_CACHE_DIR"]).glob("*"))))
        child_env = {k: v for k, v in env.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
        wall = real([str(installed["venv"] / "bin" / "python"), *cmd[1:]], child_env, cwd)
        if len(seen) == 2:  # the warm run: keep what the cold one compiled, for the commands below
            for key, name in (("NUMBA_CACHE_DIR", "numba"), ("HAPTIC_ACU_CACHE", "tables")):
                if Path(env[key]).is_dir():
                    shutil.copytree(env[key], kept / name)
        return wall

    mp = pytest.MonkeyPatch()
    mp.setattr(run, "_timed_child", spy)
    try:
        res = run.first_run(dataclasses.replace(run.QUICK, trajectory=str(traj)))["first_run_s"]
    finally:
        mp.undo()
    return {"seen": seen, "res": res, "caches": kept}


def _run(installed, *args, cwd=None, caches=None):
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    if caches is not None:  # the kernels and tables the first run compiled and built (see first_run)
        env.update(NUMBA_CACHE_DIR=str(caches / "numba"), HAPTIC_ACU_CACHE=str(caches / "tables"))
    env["PATH"] = str(installed["venv"] / "bin") + os.pathsep + env.get("PATH", "")
    return subprocess.run([str(installed["venv"] / "bin" / "haptic-acu"), *map(str, args)], cwd=cwd or installed["work"],
                          env=env, capture_output=True, text=True, timeout=TIMEOUT_S)


@pytest.mark.slow
def test_wheel_carries_the_bundled_data_inside_the_package(installed):
    names = set(zipfile.ZipFile(installed["wheel"]).namelist())
    for f in _git_files("config", "trajectories"):
        assert f"haptic_acu/_bundled/{f}" in names, f"{f} is not package data in the wheel"
    for f in _git_files("haptic_acu/session/layouts"):
        assert f in names, f"{f} (a viewer layout) is not package data in the wheel"
    tops = {n.split("/")[0] for n in names}
    assert tops == {"haptic_acu", f"haptic_acu-{installed['wheel'].name.split('-')[1]}.dist-info"}, tops
    for f in _git_files("devices", "bench"):
        if f.endswith(".py"):
            assert f"haptic_acu/{f}" in names
    assert not (installed["site"] / "devices").exists() and not (installed["site"] / "bench").exists()
    # HAPTIC_ACU_NO_PRECOMPILE: no compiled kernels nor tables went in (setup.py honours it)
    assert not any(n.endswith((".nbi", ".nbc")) or "/_bundled/tables/" in n for n in names)


@pytest.mark.slow
def test_first_run_times_a_replay_with_empty_caches(first_run):
    """The bench's first-run row: two replays of a tiny trajectory in children whose numba and table
    caches are fresh temporary folders (the second finds the first's caches), removed afterwards."""
    res, seen = first_run["res"], first_run["seen"]
    assert res["empty_caches"] > 0 and res["after_install"] > 0
    assert seen[0][2] == [] and seen[1][2] != []  # empty at first; the second run found the first's cache
    assert seen[0][:2] == seen[1][:2] and not Path(seen[0][0]).exists()  # removed afterwards


@pytest.mark.slow
def test_installed_commands_run_from_another_folder(installed, first_run):
    r = subprocess.run([str(installed["venv"] / "bin" / "python"), "-c", "import haptic_acu; print(haptic_acu.__file__)"],
                       cwd=installed["work"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and Path(r.stdout.strip()).is_relative_to(installed["site"]), r.stdout + r.stderr

    caches = first_run["caches"]
    r = _run(installed, "fit", caches=caches)
    assert r.returncode == 0, r.stderr
    r = _run(installed, "replay", "--no-rrd", "--out", "demo", caches=caches)
    assert r.returncode == 0, r.stderr
    out = installed["work"] / "demo"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["trajectory"] == "default.csv"
    assert [p["layer"] for p in summary["punctures"]] == ["skin", "fat", "muscle"]
    assert {p.name for p in out.iterdir()} == {"summary.json", "samples.csv", "force_depth.png", "debrief.md"}
    scoring = installed["site"] / "haptic_acu" / "_bundled" / "config" / "scoring"
    r = _run(installed, "score", scoring / "example_ratings.csv", "--delphi", scoring / "example_delphi.csv",
             "--out", "score", caches=caches)
    assert r.returncode == 0, r.stderr
    assert any((installed["work"] / "score").iterdir())
    assert sorted(p.name for p in installed["work"].iterdir()) == ["demo", "score"]  # nothing else written here

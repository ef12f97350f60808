"""What a command imports before it does its job: `--help` and `score` run no kernel and log nothing,
so they import neither numba nor rerun; a replay without its .rrd does not import rerun. Each runs in a
fresh interpreter (the only way to see what one command imports: a test process has imported
everything already). numba's compiles are still reported once numba is imported later."""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from haptic_acu.base.bundled import bundled_dir

HEAVY = ("numba", "rerun", "matplotlib", "scipy")
# What a replay never calls: the modelled OMNI's stylus and rendering kernels (live sessions), the
# process pool of a batch with --jobs > 1.
NOT_FOR_A_REPLAY = ("haptic_acu.servo.devicemodel", "haptic_acu.servo.rendering", "haptic_acu.servo.stylus",
                    "multiprocessing", "concurrent.futures.process")


def _imported_by(argv: list[str], tmp_path, names=HEAVY) -> dict:
    code = textwrap.dedent(f"""
        import contextlib, io, json, sys
        from haptic_acu.cli import main
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            try:
                status = main({argv!r})
            except SystemExit as e:
                status = e.code
        print(json.dumps({{"status": status, **{{m: m in sys.modules for m in {tuple(names)!r}}}}}))
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.splitlines()[-1])


def test_help_imports_no_kernel_and_no_plotting(tmp_path):
    got = _imported_by(["--help"], tmp_path)
    assert got["status"] == 0
    assert not any(got[m] for m in HEAVY), got


def test_every_command_help_imports_no_numba(tmp_path):
    from haptic_acu.cli.app import COMMANDS
    code = textwrap.dedent(f"""
        import sys
        from haptic_acu.cli.app import build_parser
        for name in {list(COMMANDS)!r}:
            build_parser(name)
        print(sorted(m for m in {HEAVY!r} if m in sys.modules))
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"


def test_score_imports_no_numba_and_no_rerun(tmp_path):
    ratings = bundled_dir("config") / "scoring" / "example_ratings.csv"
    got = _imported_by(["score", str(ratings), "--out", str(tmp_path / "sc")], tmp_path)
    assert got["status"] == 0
    assert (tmp_path / "sc" / "score.json").is_file()
    assert not got["numba"] and not got["rerun"], got


def test_replay_without_rrd_imports_no_rerun(tmp_path):
    """... nor the modules a replay never calls (NOT_FOR_A_REPLAY), and loads every library the bench's
    import floor for the command imports (the floor is a part of the command's wall time, not more
    than it)."""
    from haptic_acu.bench.run import REPLAY_IMPORTS

    got = _imported_by(["replay", "default", "--no-rrd", "--quiet", "--out", str(tmp_path / "r")], tmp_path,
                       names=HEAVY + REPLAY_IMPORTS["no_rrd"] + NOT_FOR_A_REPLAY)
    assert got["status"] == 0
    assert (tmp_path / "r" / "samples.csv").is_file()
    assert got["numba"] and not got["rerun"], got
    assert not any(got[m] for m in NOT_FOR_A_REPLAY), got
    assert all(got[m] for m in REPLAY_IMPORTS["no_rrd"]), got
    assert REPLAY_IMPORTS["rrd"] == REPLAY_IMPORTS["no_rrd"] + ("rerun",)  # the .rrd's sink adds rerun alone


def test_compiles_are_reported_when_numba_comes_after_the_watch(tmp_path):
    """The compile listener is registered by the first import of numba, whoever makes it."""
    code = textwrap.dedent("""
        import sys
        from haptic_acu.base import progress
        progress.AFTER_S = 0.0
        progress.watch_compiles()
        assert "numba" not in sys.modules
        import numba
        f = numba.njit(lambda x: 2 * x)
        assert f(3) == 6
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "haptic-acu: compiling " in r.stderr and ": done in " in r.stderr, r.stderr


def test_only_the_console_entry_freezes_the_heap(tmp_path):
    """main() without arguments is the process's one command: its heap is frozen at exit, after the
    exit handlers its libraries add (haptic_acu/base/gcpolicy.py); main([...]) called in-process
    leaves the collector as it was (nothing frozen, CPython's thresholds)."""
    ratings = bundled_dir("config") / "scoring" / "example_ratings.csv"
    code = textwrap.dedent(f"""
        import atexit, contextlib, gc, io, json, sys
        from haptic_acu.cli import main
        seen = {{}}
        atexit.register(lambda: print(json.dumps({{**seen, "at_exit": gc.get_freeze_count()}})))  # called last
        with contextlib.redirect_stdout(io.StringIO()):
            seen["in_process"] = [main(["score", {str(ratings)!r}, "--out", "a"]), gc.get_freeze_count(),
                                  gc.get_threshold()]
        sys.argv = ["haptic-acu", "score", {str(ratings)!r}, "--out", "b"]
        with contextlib.redirect_stdout(io.StringIO()):
            seen["entry"] = [main(), gc.get_freeze_count()]
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout.splitlines()[-1])
    assert got["in_process"] == [0, 0, [700, 10, 10]], got  # CPython's thresholds, untouched
    assert got["entry"] == [0, 0], got  # score sets up no session: nothing frozen before exit
    assert got["at_exit"] > 1000, got
    assert (tmp_path / "a" / "score.json").read_bytes() == (tmp_path / "b" / "score.json").read_bytes()


@pytest.mark.slow  # a real command and an in-process replay (~2 s): make test runs it, make test-fast does not
def test_replay_command_process_leaves_complete_outputs(tmp_path):
    """The command as a user runs it (its heap frozen after set-up and at exit): the same samples and
    summary as the replay run in-process, a whole PNG, and an .rrd that rerun's own check accepts."""
    from cli_helpers import cli

    r = subprocess.run([sys.executable, "-m", "haptic_acu", "replay", "default", "--quiet", "--out", "p"],
                       capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    here = cli("replay", "default", "--quiet", "--no-rrd", "--out", str(tmp_path / "h"), cwd=tmp_path)
    assert here.returncode == 0, here.stderr
    for name in ("samples.csv", "summary.json"):
        assert (tmp_path / "p" / name).read_bytes() == (tmp_path / "h" / name).read_bytes(), name
    assert (tmp_path / "p" / "force_depth.png").read_bytes()[-12:] == b"\0\0\0\0IEND\xaeB`\x82"
    exe = Path(sys.executable).with_name("rerun")
    if exe.exists():
        v = subprocess.run([str(exe), "rrd", "verify", str(tmp_path / "p" / "recording.rrd")], capture_output=True,
                           text=True, timeout=120)
        assert v.returncode == 0, v.stderr[-2000:]


def test_gc_policy_of_a_command_process(tmp_path):
    """Full collections rarer while the command sets up; at settle() the thresholds come back and
    what is alive is frozen, once (a batch's later files are collected as usual)."""
    code = textwrap.dedent("""
        import gc, json
        from haptic_acu.base import gcpolicy
        before = gc.get_threshold()
        gcpolicy.settle()  # not a command's process: nothing happens
        out = [before, gc.get_freeze_count()]
        gcpolicy.command_process()
        out.append(gc.get_threshold())
        gcpolicy.settle()
        out += [gc.get_threshold(), gc.get_freeze_count()]
        keep = [[i] for i in range(1000)]  # new objects after the freeze
        gcpolicy.settle()
        out.append(gc.get_freeze_count())
        print(json.dumps(out))
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    before, frozen0, setup, after, frozen1, frozen2 = json.loads(r.stdout.splitlines()[-1])
    assert frozen0 == 0
    assert setup == [before[0], before[1], 100] and after == before
    assert frozen1 > 1000 and frozen2 == frozen1


def test_the_figure_preload_thread_is_waited_for_at_exit():
    # A replay imports matplotlib on a thread while its session runs. An interrupted replay exits
    # at once; the interpreter must wait for that import (a daemon thread killed inside matplotlib's
    # C++ extensions aborts the process with "terminate called without an active exception").
    # A fresh interpreter starts the preload and returns at once: it exits 0 with matplotlib loaded.
    code = ("import atexit, sys\n"
            "from haptic_acu.session.report import preload_figure_modules\n"
            "t = preload_figure_modules()\n"
            "assert not t.daemon\n"
            "atexit.register(lambda: print('figure' in sys.modules.get('matplotlib.figure', object()).__name__))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "True" and "terminate" not in r.stderr

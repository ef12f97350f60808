"""What a command imports before it does its job: `--help` and `score` run no kernel and log nothing,
so they import neither numba nor rerun; a replay without its .rrd does not import rerun. Each runs in a
fresh interpreter (the only way to see what one command imports: a test process has imported
everything already). numba's compiles are still reported once numba is imported later."""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap

from haptic_acu.base.bundled import bundled_dir

HEAVY = ("numba", "rerun", "matplotlib", "scipy")


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
    """... and loads every library the bench's import floor for the command imports (the floor is a
    part of the command's wall time, not more than it)."""
    from haptic_acu.bench.run import REPLAY_IMPORTS

    got = _imported_by(["replay", "default", "--no-rrd", "--quiet", "--out", str(tmp_path / "r")], tmp_path,
                       names=HEAVY + REPLAY_IMPORTS["no_rrd"])
    assert got["status"] == 0
    assert (tmp_path / "r" / "samples.csv").is_file()
    assert got["numba"] and not got["rerun"], got
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

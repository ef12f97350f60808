"""The command line's conveniences: ``--set`` overrides, progress lines, ``--spawn`` without a
display, the status line's fields, and help texts."""
from __future__ import annotations

import io
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from haptic_acu.base import progress
from haptic_acu.cli import COMMANDS, build_parser
from haptic_acu.base.config import load_config
from haptic_acu.base.errors import UserError
from haptic_acu.base.overrides import apply_overrides, parse_set
from haptic_acu.servo.samples import COL, NCOL
from haptic_acu.session.status import format_status, loop_health
from haptic_acu.session.viewer import NO_DISPLAY, NO_DISPLAY_REPLAY, has_display

ROOT = Path(__file__).resolve().parent.parent


def haptic_acu(*args, env=None, timeout=120):
    return subprocess.run([sys.executable, "-m", "haptic_acu", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=env, cwd=ROOT)


# -- --set ---------------------------------------------------------------------------------------
def test_parse_set_reads_toml_values_else_strings():
    assert parse_set("scene.target_depth_mm=[5, 20]") == ("scene", "target_depth_mm", [5, 20])
    assert parse_set("skin.thickness_mm=1.5") == ("skin", "thickness_mm", 1.5)
    assert parse_set("solver.servo_net=sweeps") == ("solver", "servo_net", "sweeps")
    assert parse_set('solver.servo_net="table"') == ("solver", "servo_net", "table")
    for bad in ("scene", "scene.target_depth_mm", "=1", "a.b.c=1", ".x=1"):
        with pytest.raises(UserError, match="expected section.key=value"):
            parse_set(bad)


def test_overrides_change_one_key_and_are_validated_like_the_file():
    base = load_config()
    cfg = load_config(overrides=["scene.target_depth_mm=[5,20]", "skin.thickness_mm=1.5"])
    assert cfg.scene.target_depth_mm == (5.0, 20.0) and cfg.skin.thickness_mm == 1.5
    assert cfg.fat == base.fat and cfg.body == base.body  # nothing else changed
    with pytest.raises(UserError, match=r"key 'scene.target_depth_mm': must be \[low, high\]"):
        load_config(overrides=["scene.target_depth_mm=[20,5]"])
    with pytest.raises(UserError, match="key 'skin.thickness_mm': must be > 0"):
        load_config(overrides=["skin.thickness_mm=-1"])
    with pytest.raises(UserError, match=r"--set skin.thicknes: unknown key \(known: .*thickness_mm"):
        load_config(overrides=["skin.thicknes=1"])
    with pytest.raises(UserError, match="--set skn.thickness_mm: unknown section 'skn'"):
        load_config(overrides=["skn.thickness_mm=1"])
    data = {"scene": {"a": 1}}
    assert apply_overrides(data, ["scene.a=2"]) == {"scene": {"a": 2}} and data == {"scene": {"a": 1}}  # a copy


def test_every_command_with_config_takes_set():
    for name in COMMANDS:
        parser = build_parser(name)
        sub = parser._subparsers._group_actions[0].choices[name]
        opts = {o for a in sub._actions for o in a.option_strings}
        if "--config" in opts:
            assert "--set" in opts, name


def test_bad_set_on_the_command_line_is_one_line_exit_2():
    r = haptic_acu("fit", "--set", "body.lmax=100")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "body.lmax" in r.stderr and "Traceback" not in r.stderr


# -- help ----------------------------------------------------------------------------------------
def test_every_option_has_help_text():
    for name in COMMANDS:
        sub = build_parser(name)._subparsers._group_actions[0].choices[name]
        assert sub.description, name
        for a in sub._actions:
            if a.option_strings and a.dest != "help":
                assert a.help, f"{name} {a.option_strings}"
    top = haptic_acu("--help")
    assert top.returncode == 0
    for name in COMMANDS:
        assert name in top.stdout


def test_command_reference_lists_every_option():
    """The command reference (docs/commands.md, linked from the README) names every option of every
    command."""
    readme = (ROOT / "docs" / "commands.md").read_text()
    for name in COMMANDS:
        sub = build_parser(name)._subparsers._group_actions[0].choices[name]
        for a in sub._actions:
            for o in a.option_strings:
                if o.startswith("--") and o != "--help":
                    assert f"`{o}" in readme, f"docs/commands.md does not list `haptic-acu {name} {o}`"


# -- progress ------------------------------------------------------------------------------------
class _Pipe(io.StringIO):
    def isatty(self):
        return False


class _Tty(io.StringIO):
    def isatty(self):
        return True


def test_progress_plain_lines_when_piped_and_nothing_for_quick_steps():
    out = _Pipe()
    with progress.step("building the tissue", after_s=0, stream=out):
        pass
    lines = out.getvalue().splitlines()
    assert lines[0] == "haptic-acu: building the tissue..."
    assert lines[1].startswith("haptic-acu: building the tissue: done in ") and lines[1].endswith(" s")
    quick = _Pipe()
    with progress.step("x", after_s=3600, stream=quick):
        pass
    assert quick.getvalue() == ""


def test_progress_on_a_terminal_ends_the_line_and_nests():
    out = _Tty()
    with progress.step("outer", after_s=0, stream=out):
        with progress.step("inner", after_s=0, stream=out):
            pass
    text = out.getvalue()
    assert text.startswith("haptic-acu: outer...\nhaptic-acu: inner... done in ")
    assert "\nhaptic-acu: outer: done in " in text and text.endswith(" s\n")
    noted = _Tty()
    with progress.step("batch", after_s=0, stream=noted):
        progress.note("1/2 done: a.csv", stream=noted)
    assert noted.getvalue().startswith("haptic-acu: batch...\nhaptic-acu: 1/2 done: a.csv\nhaptic-acu: batch: done in ")
    failed = _Tty()
    with pytest.raises(RuntimeError):
        with progress.step("y", after_s=0, stream=failed):
            raise RuntimeError
    assert failed.getvalue().endswith("\r") and "done" not in failed.getvalue()  # the line is erased


# -- --spawn without a display -------------------------------------------------------------------
def test_has_display_reads_the_environment():
    if sys.platform in ("darwin", "win32"):
        pytest.skip("always a display there")
    assert not has_display({})
    assert has_display({"DISPLAY": ":0"}) and has_display({"WAYLAND_DISPLAY": "wayland-0"})


@pytest.mark.skipif(sys.platform in ("darwin", "win32"), reason="always a display there")
def test_spawn_without_display_is_one_line_at_once(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    for args in (("replay", "--spawn", "--out", tmp_path / "r"),
                 ("run", "--device", "scripted", "--trajectory", ROOT / "trajectories" / "default.csv", "--spawn",
                  "--out", tmp_path / "s")):
        r = haptic_acu(*args, env=env, timeout=60)
        assert r.returncode == 2, r.stderr
        message = NO_DISPLAY_REPLAY if args[0] == "replay" else NO_DISPLAY
        assert r.stderr.strip().splitlines() == [f"haptic-acu {args[0]}: error: {message}"]
        # the alternatives it names are options of that very command (replay has no --rrd)
        sub = build_parser(args[0])._subparsers._group_actions[0].choices[args[0]]
        opts = {o for a in sub._actions for o in a.option_strings}
        named = set(re.findall(r"--[a-z][a-z-]*", message)) - {"--spawn"}
        assert "--connect" in named and named <= opts, (args[0], named - opts)
    assert "--rrd FILE" in NO_DISPLAY and "recording.rrd" in NO_DISPLAY_REPLAY
    assert not (tmp_path / "r").exists() and not (tmp_path / "s").exists()


# -- the status line -----------------------------------------------------------------------------
def _row(x_mm=0.0, y_mm=0.0, layer=-1, states=(0, 0, 0), clamped=0, force=(0.0, 0.0, 0.0)):
    r = np.zeros(NCOL)
    r[COL["x_m"]], r[COL["y_m"]] = x_mm * 1e-3, y_mm * 1e-3
    r[COL["dev_x_m"]], r[COL["dev_y_m"]] = x_mm * 1e-3, y_mm * 1e-3  # the device where the needle's tip is
    r[COL["layer"]] = layer
    r[COL["state_skin"]:COL["state_skin"] + 3] = states
    r[COL["clamped"]] = clamped
    r[COL["fx_n"]:COL["fx_n"] + 3] = force
    return r


RATES = {"servo_hz": 1000.0, "visual_hz": 60.0}


def test_status_in_air_pressing_on_bone_and_at_the_force_limit():
    air = format_status(1.0, _row(x_mm=1.25, y_mm=-0.5), RATES, 0, tip_depth_mm=-3.2)
    assert "x +1.2 y -0.5 mm" in air and "air, 3.20 mm above skin" in air and air.endswith("loop ok")
    press = format_status(1.0, _row(states=(1, 0, 0)), RATES, 0, tip_depth_mm=0.8)
    assert "pressing skin 0.80 mm" in press
    bone = format_status(1.0, _row(layer=3, states=(2, 2, 2), clamped=1, force=(0, 0, 3.3)), RATES, 0,
                         target_mm=(15, 30), speed_set_mm_s=5.0,
                         last_puncture={"layer": "muscle", "peak_force_n": 1.913})
    for want in ("bone ", "(target 15-30)", "ON BONE: withdraw", "FORCE LIMIT", "last puncture muscle 1.913 N",
                 "v 0.0 mm/s (set 5)", "|F| 3.30 N"):
        assert want in bone, want
    # the handle on the skin: the device (dev_*) further along the needle than its tip, 40 mm in
    handle = _row(layer=2, states=(2, 2, 2), clamped=1, force=(0, 0, 3.3))
    handle[COL["depth_skin_m"]], handle[COL["z_m"]], handle[COL["dev_z_m"]] = 0.040, -0.040, -0.042
    line = format_status(1.0, handle, RATES, 0, width=80, target_mm=(15, 30))
    assert "FORCE LIMIT" in line and "40.00 mm deep: HANDLE ON SKIN" in line and "|F| 3.30 N" in line
    assert len(line) <= 80 and "HANDLE" not in format_status(1.0, _row(layer=2), RATES, 0, target_mm=(15, 30))
    # on a narrow terminal the warnings stay, the rates and position go
    narrow = format_status(1.0, _row(layer=3, states=(2, 2, 2), clamped=1), RATES, 0, width=110,
                           last_puncture={"layer": "muscle", "peak_force_n": 1.9})
    assert "ON BONE" in narrow and "FORCE LIMIT" in narrow and "servo" not in narrow and len(narrow) <= 110


def test_status_on_common_terminal_widths_keeps_what_the_trainee_acts_on():
    """The status line's fields on a real terminal: the full line is over 200 columns, so what stays at 80
    and 120 columns matters. Inside the tissue: the depth against the target and the force at 80
    (and the speed at 100), the roll at 120; in the air: the position against the acupoint."""
    r = _row(layer=2, states=(2, 2, 2), force=(0, 0, 0.3))
    r[COL["depth_skin_m"]], r[COL["roll_deg"]], r[COL["torque_nmm"]] = 15.06e-3, 108.0, 0.039
    extra = dict(ticks=7300, tip_depth_mm=15.06, target_mm=(15, 30), speed_set_mm_s=5.0,
                 last_puncture={"layer": "muscle", "peak_force_n": 0.748})
    full = format_status(7.3, r, RATES, 76, **extra)
    for want in ("x +0.0 y +0.0 mm", "15.06 mm deep (target 15-30)", "v 0.0 mm/s (set 5)", "roll +108 deg",
                 "last puncture muscle 0.748 N", "host late 1.0%, missed 76", "servo 1000 Hz"):
        assert want in full, want
    for width, want in ((79, ("15.06 mm deep (target 15-30)", "|F| 0.30 N")),
                        (99, ("15.06 mm deep (target 15-30)", "v 0.0 mm/s (set 5)")),
                        (119, ("15.06 mm deep (target 15-30)", "v 0.0 mm/s (set 5)", "roll +108 deg"))):
        text = format_status(7.3, r, RATES, 76, width=width, **extra)
        assert len(text) <= width and all(w in text for w in want), (width, text)
        assert "servo" not in text  # the rates go first
    air = format_status(1.0, _row(x_mm=1.25, y_mm=-0.5), RATES, 0, width=79, tip_depth_mm=-3.2, speed_set_mm_s=5.0)
    assert "x +1.2 y -0.5 mm" in air and "air, 3.20 mm above skin" in air and len(air) <= 79


def test_status_says_when_the_continuous_force_protection_eases_off():
    from haptic_acu.servo import rendering

    r = _row(layer=2, states=(2, 2, 0), force=(0, 0, 0.9))
    assert "CONTINUOUS FORCE LIMIT" not in format_status(1.0, r, RATES, 0)
    r[COL["render_status"]] = rendering.LIMITING | rendering.CLAMPED
    assert "CONTINUOUS FORCE LIMIT: easing off" in format_status(1.0, r, RATES, 0)
    r[COL["render_status"]] = rendering.CLAMPED
    assert "CONTINUOUS FORCE LIMIT" not in format_status(1.0, r, RATES, 0)


def test_loop_health_in_words():
    assert loop_health(0, 1000) == "loop ok"
    assert loop_health(3, 1000) == "host late 0.3%, missed 3"


def test_rerun_is_found_beside_the_interpreter(monkeypatch, tmp_path):
    """An environment used without activating it: rerun is beside sys.executable, not on PATH."""
    import shutil

    from haptic_acu.session import viewer

    bindir = tmp_path / "venv-bin"
    bindir.mkdir()
    (bindir / "rerun").write_text("#!/bin/sh\n")
    (bindir / "rerun").chmod(0o755)
    monkeypatch.setattr(sys, "executable", str(bindir / "python"))
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    assert shutil.which("rerun") is None
    viewer.rerun_beside_python()
    assert shutil.which("rerun") == str(bindir / "rerun")
    before = os.environ["PATH"]
    viewer.rerun_beside_python()  # already found: PATH unchanged
    assert os.environ["PATH"] == before


@pytest.mark.slow
def test_precompile_fills_the_caches_and_leaves_nothing_behind(tmp_path):
    """`python -m haptic_acu.cli.precompile` (run by make after the install) runs to the end and removes
    its temporary replay folder."""
    env = dict(os.environ, TMPDIR=str(tmp_path))
    r = subprocess.run([sys.executable, "-m", "haptic_acu.cli.precompile"], capture_output=True, text=True,
                       timeout=900, env=env, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "caches ready" in r.stderr.splitlines()[-1]
    assert list(tmp_path.iterdir()) == []


def test_numba_compiles_are_reported(monkeypatch):
    """A real numba compile, with the threshold at 0 s: one line when it starts, one when it ends."""
    from numba import njit

    monkeypatch.setattr(progress, "AFTER_S", 0.0)
    err = _Pipe()
    monkeypatch.setattr(sys, "stderr", err)
    progress.watch_compiles()

    @njit
    def _twice(x):
        return 2 * x

    assert _twice(3) == 6
    lines = err.getvalue().splitlines()
    name = "test_numba_compiles_are_reported.<locals>._twice"
    assert any(ln.startswith(f"haptic-acu: compiling {name}") and ln.endswith("...") for ln in lines), lines
    assert any(ln.startswith(f"haptic-acu: compiling {name}") and ": done in " in ln for ln in lines), lines
    err.truncate(0)
    assert _twice(4) == 8  # compiled: nothing more
    assert err.getvalue().strip("\x00") == ""


def test_a_quiet_command_run_in_process_leaves_the_progress_lines_on():
    """``main([... "--quiet"])`` silences its own progress lines only: the next in-process command
    (or a library caller) still gets them."""
    from haptic_acu.cli import main

    assert progress.quiet is False
    assert main(["replay", "no_such_trajectory.csv", "--quiet"]) == 2  # a one-line error, after --quiet took hold
    assert progress.quiet is False

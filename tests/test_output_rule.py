"""The output rule (haptic_acu.base.outputs) on its own, then enumerated over every command.

The rule: a file the user has is never replaced without --overwrite; outputs never share a path with
each other or with an input (resolved, links followed, hard links found by inode); a claimed folder
is held alone, and a lock taken over from a dead holder goes to exactly one of two racers.
"""
from __future__ import annotations

import multiprocessing
import os
from pathlib import Path

import pytest

from haptic_acu.base import outputs
from haptic_acu.base.errors import UserError
from haptic_acu.base.outputs import COMMAND_OUTPUTS, FolderLock, Outputs, claim_folder, safe_cell, write_new


def test_existing_file_refused_without_overwrite_and_replaced_with_it(tmp_path):
    f = tmp_path / "notes.txt"
    f.write_text("precious")
    with pytest.raises(UserError, match="exists"):
        Outputs().file("--rrd", f).check()
    with pytest.raises(UserError, match="exists"):
        write_new(f, b"new")
    assert f.read_text() == "precious"
    Outputs(overwrite=True).file("--rrd", f).check()
    write_new(f, b"new", overwrite=True)
    assert f.read_text() == "new"
    assert sorted(os.listdir(tmp_path)) == ["notes.txt"]  # no temporary left behind


def test_overwrite_replaces_a_link_never_its_target(tmp_path):
    target = tmp_path / "target.txt"
    target.write_text("theirs")
    link = tmp_path / "link.txt"
    link.symlink_to(target)
    with pytest.raises(UserError, match="exists"):
        Outputs().file("--out", link).check()
    write_new(link, "mine", overwrite=True)
    assert target.read_text() == "theirs" and not link.is_symlink() and link.read_text() == "mine"


@pytest.mark.parametrize("how", ["same", "dotdot", "symlink", "hardlink"])
def test_an_output_never_replaces_an_input_even_with_overwrite(tmp_path, how):
    src = tmp_path / "g.csv"
    src.write_text("t_s,x_mm,y_mm,z_mm\n")
    (tmp_path / "sub").mkdir()
    out = {"same": src, "dotdot": tmp_path / "sub" / ".." / "g.csv", "symlink": tmp_path / "l.csv",
           "hardlink": tmp_path / "h.csv"}[how]
    if how == "symlink":
        out.symlink_to(src)
    if how == "hardlink":
        os.link(src, out)
    with pytest.raises(UserError, match="input --trajectory"):
        Outputs(overwrite=True).input("--trajectory", src).file("--rrd", out).check()


def test_outputs_never_share_a_path(tmp_path):
    d = tmp_path / "d"
    with pytest.raises(UserError, match="one path"):
        Outputs().folder("--out", d, files=("samples.csv", "summary.json")).file(
            "--record", d / "samples.csv").check()
    with pytest.raises(UserError, match="one path"):
        Outputs().file("--record", tmp_path / "a.csv").file("--rrd", tmp_path / "x" / ".." / "a.csv").check()
    with pytest.raises(UserError, match="hold the input"):
        Outputs().input("--trajectory", d / "t.csv").folder("--out", d).check()
    # a folder's content is the command's: another output inside it is refused too
    with pytest.raises(UserError, match="one path"):
        Outputs().folder("--out", d, files=("samples.csv",)).file("--record", d / "mine.csv").check()
    Outputs().folder("--out", d, files=("samples.csv",)).file("--record", tmp_path / "mine.csv").check()


def test_a_folder_must_be_new_or_empty(tmp_path):
    d = tmp_path / "d"
    d.mkdir()
    (d / "weights.csv").write_text("mine")
    with pytest.raises(UserError, match="not empty"):
        Outputs().folder("--out", d).check()
    (d / ".cohort").mkdir()
    Outputs().folder("--out", d, resumable=".cohort").check()


def test_claimed_folder_is_held_alone(tmp_path):
    d = tmp_path / "run"
    lock = claim_folder(d)
    try:
        with pytest.raises(UserError, match="another session"):
            claim_folder(d)
    finally:
        lock.release()
    (d / "summary.json").write_text("{}")  # the first session's files: the folder is not empty
    with pytest.raises(UserError, match="not empty"):
        claim_folder(d)


def _race(path, barrier, results):
    barrier.wait()
    try:
        lock = FolderLock(path, "busy{holder}").acquire()
        results.put("won")
        barrier.wait()  # hold it until both have tried
        lock.release()
    except UserError:
        results.put("lost")
        barrier.wait()


def test_taking_over_a_dead_holders_lock_is_atomic(tmp_path):
    """A lock file left by a process that died (its pid inside, no flock): of two processes taking
    it over at once exactly one wins, every time (the pid-file scheme let both win 12 of 40)."""
    path = tmp_path / "lock"
    path.write_text("999999999\n")  # no such process
    ctx = multiprocessing.get_context("fork")
    for _ in range(10):
        barrier, results = ctx.Barrier(2), ctx.Queue()
        procs = [ctx.Process(target=_race, args=(path, barrier, results)) for _ in range(2)]
        for p in procs:
            p.start()
        for p in procs:
            p.join(30)
        assert sorted(results.get(timeout=5) for _ in procs) == ["lost", "won"]


def test_formula_cells_are_neutralised_numbers_are_not():
    assert safe_cell("=cmd|' /C calc'!A0") == "'=cmd|' /C calc'!A0"
    assert safe_cell("@SUM(1)") == "'@SUM(1)"
    assert safe_cell("+1+2") == "'+1+2" and safe_cell("-x") == "'-x" and safe_cell("\tx") == "'\tx"
    assert safe_cell("-1.5") == "-1.5" and safe_cell("+3") == "+3" and safe_cell(-2.0) == -2.0
    assert safe_cell("ann") == "ann"


def test_every_command_with_outputs_is_listed():
    """COMMAND_OUTPUTS names every command of the CLI (those that write nothing with no outputs)."""
    from haptic_acu.cli.app import COMMANDS

    assert set(COMMANDS) <= set(COMMAND_OUTPUTS), set(COMMANDS) - set(COMMAND_OUTPUTS)

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
from cli_helpers import cli

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


# ---- every output of every command, against the rule ------------------------------------------------
def _cli(*argv):
    r = cli(*argv)  # in-process (tests/cli_helpers.py)
    return r.returncode, r.stderr


REPO = Path(__file__).resolve().parents[1]


def _inputs(d: Path) -> dict:
    """A small valid input of each kind, in ``d``."""
    from haptic_acu.analysis.scoring import INDICES

    t = d / "t.csv"
    t.write_text("t_s,x_mm,y_mm,z_mm\n0,0,0,3\n0.2,0,0,1\n")
    r = d / "ratings.csv"
    r.write_text("system,rater," + ",".join(INDICES) + "\n" + "".join(
        f"{s},{q}," + ",".join(str((k + j + i) % 9 + 1) for i in range(len(INDICES))) + "\n"
        for k, s in enumerate("AB") for j, q in enumerate(("r1", "r2"))))
    m = d / "m.obj"
    m.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0),
                                                             (0, 0, 1), (0, 0, -1)]))
    c = d / "c.csv"
    c.write_text("depth_mm,force_n\n" + "".join(f"{i * 0.25:.2f},{0.1 * i if i < 20 else 0.5:.3f}\n"
                                                for i in range(40)))
    man = d / "man.csv"
    man.write_text("session,trainee,file\ns1,ann,t.csv\n")
    return {"traj": t, "ratings": r, "mesh": m, "curve": c, "manifest": man}


# (command, option) -> argv builder taking (inputs, the output path); every option of COMMAND_OUTPUTS
# has one, so an output added without a case here fails test_every_output_has_a_case
RUN = ("run", "--device", "scripted", "--duration", "0.05", "--no-status", "--trajectory")
CASES = {
    ("replay", "--out"): lambda i, p: ("replay", i["traj"], "--no-rrd", "--out", p),
    ("replay", "--out (batch)"): lambda i, p: ("replay", i["traj"], i["curve"], "--no-rrd", "--out", p),
    ("run", "--out"): lambda i, p: (*RUN, i["traj"], "--out", p),
    ("run", "--record"): lambda i, p: (*RUN, i["traj"], "--record", p, "--out", i["traj"].parent / "o"),
    ("run", "--rrd"): lambda i, p: (*RUN, i["traj"], "--rrd", p, "--out", i["traj"].parent / "o"),
    ("compare", "--out"): lambda i, p: ("compare", i["traj"], i["traj"], "--out", p),
    ("score", "--out"): lambda i, p: ("score", i["ratings"], "--out", p),
    ("fit", "--out"): lambda i, p: ("fit", i["mesh"], "--lmax", "1", "--out", p),
    ("calibrate", "--out"): lambda i, p: ("calibrate", i["curve"], "--speed-mm-s", "3", "--out", p),
    ("cohort", "--out"): lambda i, p: ("cohort", i["manifest"], "--out", p),
    ("bench", "--json"): lambda i, p: ("bench", "--quick", "--json", p),
    ("study", "plan --out"): lambda i, p: ("study", "plan", "--participants", "2", "--models", "forcenet,msm",
                                           "--out", p),
    ("study", "example --out"): lambda i, p: ("study", "example", "--no-sessions", "--out", p),
    ("study", "analyze --out"): lambda i, p: ("study", "analyze", _example_study(i), "--no-objective", "--out", p),
    ("study", "replay --out"): lambda i, p: ("study", "replay", _example_study(i), "--participant", "P01",
                                             "--trial", "1", "--out", p),
}


def _example_study(ins) -> Path:
    """The bundled synthetic study's plan and ratings (no sessions), made once per input folder."""
    s = ins["traj"].parent / "study"
    if not s.exists():
        assert _cli("study", "example", "--no-sessions", "--out", s)[0] == 0
    return s
FOLDERS = {k for k in CASES if k[0] not in ("fit", "calibrate", "bench") and "--out" in k[1]}


def test_every_output_has_a_case():
    listed = {(c, o) for c, opts in COMMAND_OUTPUTS.items() for o in opts}
    assert listed == set(CASES), listed ^ set(CASES)


@pytest.mark.parametrize("case", sorted(CASES), ids=lambda c: f"{c[0]} {c[1]}")
def test_a_users_file_at_every_output_is_kept(tmp_path, case):
    """A user's file where the command would write (inside the folder, or the file itself) is never
    replaced: one line, exit 2, the file as it was."""
    ins = _inputs(tmp_path)
    if case in FOLDERS:
        target = tmp_path / "out"
        target.mkdir()
        name = (COMMAND_OUTPUTS[case[0]][case[1]] or ("x",))[0]
        mine = target / name
    else:
        target = mine = tmp_path / ("mine.npz" if case[0] == "fit" else "mine.toml" if case[0] == "calibrate"
                                    else "mine.json")
    mine.write_text("precious")
    code, err = _cli(*CASES[case](ins, target))
    assert code == 2 and "Traceback" not in err, err
    assert mine.read_text() == "precious"


@pytest.mark.parametrize("case", sorted(k for k in CASES if k[0] not in ("bench", "study")),
                         ids=lambda c: f"{c[0]} {c[1]}")
def test_no_output_is_an_input(tmp_path, case):
    """Every output pointed at the command's own input: refused, the input as it was."""
    ins = _inputs(tmp_path)
    src = {"replay": ins["traj"], "run": ins["traj"], "compare": ins["traj"], "score": ins["ratings"],
           "fit": ins["mesh"], "calibrate": ins["curve"], "cohort": ins["manifest"]}[case[0]]
    before = src.read_bytes()
    code, err = _cli(*CASES[case](ins, src), *(("--overwrite",) if case[0] in ("run", "fit") else ()))
    assert code == 2 and "Traceback" not in err, err
    assert src.read_bytes() == before

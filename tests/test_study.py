"""`haptic-acu study` as an experimenter runs it: plan, trials on the scripted device (a short path;
paced with --speed where a test checks what a trial writes, at real pace where it checks how a
signal ends one), ratings at the prompts, rate, status, replay, analyze.

The models here are two configs that differ in the fat's cutting force (what the needle meets
after the skin breaks), named so that a leak of either name is unmistakable; the model kinds of
``model.kind`` are exercised the same way in tests/test_study_kinds.py.
"""
from __future__ import annotations

import csv
import io
import json
import os
import re
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from haptic_acu.analysis.scoring import INDICES
from haptic_acu.cli import main
from haptic_acu.session import trajectory
from haptic_acu.session.recorder import EXTRA, tick_rows
from haptic_acu.study.store import Study

REPO = Path(__file__).resolve().parents[1]
NAMES = ("Zetamodel", "Kappamodel")
TIMEOUT_S = 300  # a loaded 2-core machine
GOOD = ["7", "8.5", "6", "9", "10", "7.5", "8"]
SPEED = 4.0  # the trials that check what a trial writes, paced (study trial --speed)


def write_path(path: Path, t_end: float = 1.2) -> Path:
    """A short insertion: from 2 mm above the acupoint to 4 mm below the skin in ``t_end`` s."""
    t = np.linspace(0.0, t_end, 25)
    z = np.interp(t, [0.0, 0.25 * t_end, t_end], [2.0, 0.0, -4.0])
    with open(path, "w") as f:
        f.write("t_s,x_mm,y_mm,z_mm\n")
        for a, b in zip(t, z):
            f.write(f"{a:.4f},0,0,{b:.4f}\n")
    return path


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    from haptic_acu.base.config import DEFAULT_CONFIG

    d = tmp_path_factory.mktemp("study")
    text = DEFAULT_CONFIG.read_text()
    a = d / "zeta.toml"
    b = d / "kappa.toml"
    a.write_text(text)
    b.write_text(text.replace("cutting_n_per_mm_diameter = 0.2 ", "cutting_n_per_mm_diameter = 2.0 ", 1))
    assert a.read_text() != b.read_text()
    return {"dir": d, "models": f"{NAMES[0]}={a},{NAMES[1]}={b}", "path": write_path(d / "path.csv"),
            "long_path": write_path(d / "long.csv", t_end=30.0)}


def plan(world, out, participants=2, extra=()):
    assert main(["study", "plan", "--participants", str(participants), "--models", world["models"],
                 "--out", str(out), "--seed", "5", *extra]) == 0
    return Study(out)


def answers(monkeypatch, lines):
    monkeypatch.setattr(sys, "stdin", io.StringIO("".join(f"{x}\n" for x in lines)))


def grep_names(text: str) -> list[str]:
    return [n for n in NAMES if n.lower() in text.lower()]


# ---------------------------------------------------------------------------------------------
# plan


def test_plan_writes_the_key_apart(world, tmp_path, capsys):
    study = plan(world, tmp_path / "s", participants=4)
    out = capsys.readouterr()
    assert not grep_names(out.out + out.err)
    assert sorted(p.name for p in study.folder.iterdir()) == [
        "key.json", "plan.csv", "ratings.csv", "sessions", "study.json"]
    # only the key says which system is which model
    for name in ("plan.csv", "ratings.csv"):
        assert not grep_names((study.folder / name).read_text())
    doc = json.loads((study.folder / "study.json").read_text())
    assert doc["models"] == list(NAMES) and set(doc["config_hash"]) == set(NAMES)
    assert "System" not in json.dumps(doc)
    key = json.loads((study.folder / "key.json").read_text())
    assert {key["systems"]["P01"][c] for c in ("System 1", "System 2")} == set(NAMES)
    # shared codes by default: everyone's System 1 is the same model
    assert len({key["systems"][p]["System 1"] for p in study.participants}) == 1


@pytest.mark.parametrize("argv, message", [
    (["--models", "forcenet"], "1 model(s); a study compares 2-8"),
    (["--models", "forcenet,nosuch"], "unknown model 'nosuch'"),
    (["--models", "a=/no/such.toml,b=/no/such2.toml"], "config file /no/such.toml not found"),
    (["--participants", "0"], "--participants must be >= 1"),
    (["--trials-per-model", "0"], "--trials-per-model must be >= 1"),
])
def test_plan_bad_input_is_one_line(world, tmp_path, capsys, argv, message):
    base = {"--participants": "4", "--models": world["models"], "--trials-per-model": "1"}
    for k, v in zip(argv[::2], argv[1::2]):
        base[k] = v
    args = ["study", "plan", "--out", str(tmp_path / "s")] + [x for kv in base.items() for x in kv]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err
    assert not (tmp_path / "s").exists()


def test_plan_never_overwrites(world, tmp_path, capsys):
    out = tmp_path / "s"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    assert main(["study", "plan", "--participants", "2", "--models", world["models"], "--out", str(out)]) == 2
    assert "not an empty folder" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["mine.txt"]


def test_same_config_twice_is_refused(world, tmp_path, capsys):
    a = world["models"].split(",")[0].split("=")[1]
    assert main(["study", "plan", "--participants", "2", "--models", f"x={a},y={a}", "--out", str(tmp_path / "s")]) == 2
    assert "the same config" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# ratings prompts


def test_prompts_reask_and_record_only_all_seven(world, tmp_path, monkeypatch, capsys):
    from haptic_acu.study.ratings import ask

    shown = []
    lines = iter(["", "11", "seven", "7.25", "-1", "7", "8", "6", "9", "10", "7.5", "8", "n",
                  *GOOD, "y"])
    got = ask("System 2", {"min": 0, "max": 10, "decimals": 1}, read=lambda prompt: next(lines),
              write=shown.append)
    assert got == [float(v) for v in GOOD]
    text = "\n".join(shown)
    for why in ("no answer", "outside 0-10", "not a number", "more decimals", "'-1' is not a number"):
        assert why in text, why
    assert "Again from the first point" in text
    # the input ends at the sixth index: nothing returned
    from haptic_acu.study.ratings import RatingsAbandoned
    lines2 = iter(GOOD[:6])

    def read(prompt):
        try:
            return next(lines2)
        except StopIteration:
            raise EOFError from None
    with pytest.raises(RatingsAbandoned):
        ask("System 1", {"min": 0, "max": 10, "decimals": 1}, read=read, write=shown.append)


# ---------------------------------------------------------------------------------------------
# trials (scripted device, real time)


@pytest.fixture(scope="module")
def ran(world, tmp_path_factory):
    """A study whose P01 ran trial 1 (with --rrd, the status line drawn, ratings at the prompts),
    trial 2 with --ratings-later, then trial 1 again with --redo; every line shown kept. The trials
    are paced at 4 times real time (``--speed``: the compiled loop's ticks and forces as at real
    pace, tests/test_rtloop.py), which trial.json records."""
    from haptic_acu.session import status as status_mod

    mp = pytest.MonkeyPatch()
    out = tmp_path_factory.mktemp("ran") / "s"
    study = plan(world, out)
    mp.setattr(status_mod.StatusLine, "_is_tty", staticmethod(lambda stream: True))
    screen = []
    runs = []
    for argv, lines in (
            (["--rrd"], GOOD + ["y"]),
            (["--ratings-later"], []),
            (["--trial", "1", "--redo"], ["5", "5", "5", "5", "5", "5", "5", "y"])):
        mp.setattr(sys, "stdin", io.StringIO("".join(f"{x}\n" for x in lines)))
        o, e = io.StringIO(), io.StringIO()
        mp.setattr(sys, "stdout", o)
        mp.setattr(sys, "stderr", e)
        rc = main(["study", "trial", str(out), "--participant", "P01", "--device", "scripted", "--trajectory",
                   str(world["path"]), "--speed", str(SPEED), *argv])
        mp.setattr(sys, "stdout", sys.__stdout__)
        mp.setattr(sys, "stderr", sys.__stderr__)
        runs.append((rc, o.getvalue(), e.getvalue()))
        screen.append(o.getvalue() + e.getvalue())
    mp.undo()
    return {"study": Study(out), "runs": runs, "screen": "\n".join(screen), "path": world["path"]}


@pytest.mark.slow  # three trials (the module's fixture), or a subprocess session
def test_trials_run_and_record(ran):
    study = ran["study"]
    assert [r[0] for r in ran["runs"]] == [0, 0, 0], ran["runs"]
    folders = sorted(p.name for p in study.sessions.iterdir())
    assert folders == ["P01-T1", "P01-T1.2", "P01-T2"]
    for name in folders:
        doc = json.loads((study.sessions / name / "trial.json").read_text())
        assert doc["status"] == "complete" and doc["speed"] == SPEED
        for f in ("recording.csv", "samples.csv", "summary.json", "force_depth.png"):
            assert (study.sessions / name / f).is_file(), (name, f)
        tr = tick_rows(trajectory.load(study.sessions / name / "recording.csv", extra_columns=EXTRA))
        assert len(tr.t_s) == doc["ticks"] > 1000
    assert (study.sessions / "P01-T1" / "recording.rrd").is_file()
    assert "\r" in ran["runs"][0][2]  # the status line was drawn


@pytest.mark.slow  # three trials (the module's fixture), or a subprocess session
def test_redo_keeps_earlier_files_and_ratings_history(ran, tmp_path, capsys):
    study = ran["study"]
    text = study.ratings_path.read_text()
    rows = [ln for ln in text.splitlines() if ln and not ln.startswith("#")]
    assert len(rows) == 2  # header + P01's trial 1 (trial 2: ratings later)
    t1 = study.plan["P01", 1]
    assert rows[1] == f"{t1.system},P01,5,5,5,5,5,5,5"
    old = f"{t1.system},P01," + ",".join(GOOD)
    hist = [ln for ln in text.splitlines() if ln.startswith("#") and old in ln]
    assert len(hist) == 1 and "redo" in hist[0]
    # the first attempt's files are untouched by the redo
    first = json.loads((study.sessions / "P01-T1" / "trial.json").read_text())
    assert first["attempt"] == 1 and first["status"] == "complete"
    # score still reads the file
    assert main(["score", str(study.ratings_path), "--out", str(tmp_path / "sc")]) == 2  # one rater: refused
    assert "only one rater" in capsys.readouterr().err


@pytest.mark.slow  # three trials (the module's fixture), or a subprocess session
@pytest.mark.filterwarnings("ignore:RRD file has no footer")  # a live session's file: read as a stream
def test_blinding_nothing_shown_names_a_model(ran):
    study = ran["study"]
    screen = ran["screen"]
    assert "System" in screen and "Please rate" in screen
    assert not grep_names(screen), screen
    # names under sessions/, and every text file's content there
    for p in study.sessions.rglob("*"):
        assert not grep_names(p.name)
        if p.suffix in (".json", ".csv"):
            assert not grep_names(p.read_text()), p
    # the rerun recording: entity paths and every text it holds
    from rerun.chunk import RrdReader
    import pyarrow as pa
    paths, texts = set(), []
    for chunk in RrdReader(study.sessions / "P01-T1" / "recording.rrd").stream().to_chunks():
        paths.add(chunk.entity_path)
        rb = chunk.to_record_batch()
        for name, col in zip(rb.schema.names, rb.columns):
            if "string" in str(col.type) or "utf8" in str(col.type):
                texts.append(str(col.to_pylist()))
    assert any(p.startswith("/world") for p in paths)
    assert not grep_names(" ".join(paths) + " ".join(texts))
    # the key does name them (the test would see a leak)
    assert grep_names((study.folder / "key.json").read_text()) == list(NAMES)


@pytest.mark.slow  # three trials (the module's fixture), or a subprocess session
def test_status_does_not_reveal_the_key(ran, capsys):
    study = ran["study"]
    assert main(["study", "status", str(study.folder)]) == 0
    out = capsys.readouterr().out
    assert not grep_names(out)
    assert all(len(line) <= 80 for line in out.splitlines()[1:])  # (line 1: the folder)
    p01 = next(line for line in out.splitlines() if line.startswith("P01"))
    assert re.search(r"P01\s+1/2\s+1\s+0\s+0\s+rate: 2$", p01), p01
    p02 = next(line for line in out.splitlines() if line.startswith("P02"))
    assert "next: trial 1" in p02


@pytest.mark.slow  # three trials (the module's fixture), or a subprocess session
def test_done_trial_refused_without_redo(ran, capsys):
    study = ran["study"]
    n = len(list(study.sessions.iterdir()))
    assert main(["study", "trial", str(study.folder), "--participant", "P01", "--trial", "1", "--device",
                 "scripted", "--trajectory", "default"]) == 2
    err = capsys.readouterr().err
    assert "is done (rated); --redo" in err and err.count("\n") == 1
    assert len(list(study.sessions.iterdir())) == n
    assert main(["study", "trial", str(study.folder), "--participant", "P01", "--device", "scripted",
                 "--trajectory", "default"]) == 2
    assert "every trial has been run; to rate: trial(s) 2" in capsys.readouterr().err


@pytest.mark.slow  # three trials (the module's fixture), or a subprocess session
def test_rate_enters_and_corrects_with_history(ran, monkeypatch, capsys):
    study = ran["study"]
    before = study.ratings_path.read_text()
    # bad values: one line, nothing written
    assert main(["study", "rate", str(study.folder), "--participant", "P01", "--trial", "2",
                 "--values", "1,2,3"]) == 2
    assert "7 needed" in capsys.readouterr().err
    assert study.ratings_path.read_text() == before
    answers(monkeypatch, GOOD + ["y"])
    assert main(["study", "rate", str(study.folder), "--participant", "P01", "--trial", "2"]) == 0
    t2 = study.plan["P01", 2]
    assert f"{t2.system},P01," + ",".join(GOOD) in study.ratings_path.read_text()
    assert main(["study", "rate", str(study.folder), "--participant", "P01", "--trial", "2",
                 "--values", "1,2,3,4,5,6,7"]) == 0
    text = study.ratings_path.read_text()
    assert f"{t2.system},P01,1,2,3,4,5,6,7" in text
    assert any(ln.startswith("#") and "corrected by study rate" in ln and ",".join(GOOD) in ln
               for ln in text.splitlines())
    # a trial with no session cannot be rated
    assert main(["study", "rate", str(study.folder), "--participant", "P02", "--trial", "1",
                 "--values", "1,2,3,4,5,6,7"]) == 2
    assert "no completed session" in capsys.readouterr().err


@pytest.mark.slow  # three trials (the module's fixture), or a subprocess session
def test_replay_uses_the_trials_model(ran, tmp_path, capsys):
    """The recording replays headless with the model from the key: the forces of the live session
    come back; the other model's config gives other forces (so this can fail)."""
    from haptic_acu.base.config import load_config
    from haptic_acu.session.replay import replay_one

    study = ran["study"]
    assert main(["study", "replay", str(study.folder), "--participant", "P01", "--trial", "2",
                 "--out", str(tmp_path / "r")]) == 0
    assert not grep_names(capsys.readouterr().out)
    rec = tick_rows(trajectory.load(study.sessions / "P01-T2" / "recording.csv", extra_columns=EXTRA))
    t = rec.t_s
    live = np.column_stack([rec.extra["fx_n"], rec.extra["fy_n"], rec.extra["fz_n"]])
    # away from the ticks where a layer breaks (a force step cannot be compared across a timing
    # shift), as tests/test_run_cli.py compares a live session with its replay
    states = np.column_stack([rec.extra[f"state_{n}"] for n in ("skin", "fat", "muscle")])
    change = t[1:][np.any(np.diff(states, axis=0) != 0, axis=1)]
    keep = np.ones(len(t), bool)
    for tc in change:
        keep &= np.abs(t - tc) > 0.01

    def forces(folder):
        with open(folder / "samples.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        ts = np.array([float(r["t_s"]) for r in rows])
        keep_t = keep & (t <= ts[-1])
        return np.column_stack([np.interp(t[keep_t], ts, [float(r[c]) for r in rows])
                                for c in ("fx_n", "fy_n", "fz_n")]), keep_t
    replayed, k = forces(tmp_path / "r")
    assert k.sum() > 0.9 * len(t) and np.abs(live[k]).max() > 0.2
    assert np.all(np.abs(replayed - live[k]) <= 0.02 + 0.05 * np.abs(live[k]))
    key = json.loads((study.folder / "key.json").read_text())
    other = next(m for m in NAMES if m != key["systems"]["P01"][study.plan["P01", 2].system])
    cfg = load_config(key["models"][other]["config"])
    replay_one(study.sessions / "P01-T2" / "recording.csv", tmp_path / "o", rrd=False, progress=False, cfg=cfg)
    f_other, k2 = forces(tmp_path / "o")
    assert np.abs(f_other - live[k2]).max() > 0.2


# ---------------------------------------------------------------------------------------------
# interrupted trials (subprocesses: real signals)


def _env():
    e = dict(os.environ)
    e["OPENBLAS_NUM_THREADS"] = "1"
    return e


def _rows(path: Path) -> int:
    return sum(1 for line in path.read_bytes().splitlines() if line[:1].isdigit()) if path.exists() else 0


@pytest.mark.slow  # three trials (the module's fixture), or a subprocess session
def test_sigterm_mid_session_leaves_the_trial_not_done(world, tmp_path):
    study = plan(world, tmp_path / "s")
    before = study.ratings_path.read_bytes()
    cmd = [sys.executable, "-m", "haptic_acu", "study", "trial", str(study.folder), "--participant", "P01",
           "--device", "scripted", "--trajectory", str(world["long_path"])]
    proc = subprocess.Popen(cmd, cwd=REPO, env=_env(), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    rec = study.sessions / "P01-T1" / "recording.csv"
    try:
        deadline = time.monotonic() + TIMEOUT_S
        while _rows(rec) < 500 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "Traceback" not in err and "interrupted" in err and "Please rate" not in out
    doc = json.loads((study.sessions / "P01-T1" / "trial.json").read_text())
    assert doc["status"] == "interrupted" and doc["signal"] == "SIGTERM"
    tr = tick_rows(trajectory.load(rec, extra_columns=EXTRA))  # complete: parses, one row per tick
    assert len(tr.t_s) == doc["ticks"] >= 500
    assert study.ratings_path.read_bytes() == before
    from haptic_acu.study import overview
    assert overview.states(study)["P01", 1].state == overview.INTERRUPTED
    assert overview.next_trial(study, "P01").trial == 1
    # it replays headless
    assert main(["study", "replay", str(study.folder), "--participant", "P01", "--trial", "1",
                 "--out", str(tmp_path / "r")]) == 0


@pytest.mark.slow  # three trials (the module's fixture), or a subprocess session
@pytest.mark.serial  # its second Ctrl-C lands on a child reading a prompt: once, in the parallel phase, it never ended
def test_sigint_ends_the_session_and_at_the_prompts_records_nothing(world, tmp_path):
    """Ctrl-C mid-session is the usual end of an OMNI session: the trial is complete and the
    ratings are asked; Ctrl-C again at the third prompt records nothing."""
    study = plan(world, tmp_path / "s")
    before = study.ratings_path.read_bytes()
    cmd = [sys.executable, "-u", "-m", "haptic_acu", "study", "trial", str(study.folder), "--participant", "P01",
           "--device", "scripted", "--trajectory", str(world["long_path"])]
    # Ctrl-C's default action in the child whatever the runner's (a shell without job control starts
    # a background job with SIGINT ignored, and a child inherits that; the prompt's Ctrl-C then does nothing)
    proc = subprocess.Popen(cmd, cwd=REPO, env=_env(), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, bufsize=1,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    rec = study.sessions / "P01-T1" / "recording.csv"
    try:
        deadline = time.monotonic() + TIMEOUT_S
        while _rows(rec) < 500 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGINT)  # ends the session
        proc.stdin.write("7\n8\n")  # two of the seven, then Ctrl-C at the third
        proc.stdin.flush()
        got = ""
        deadline = time.monotonic() + TIMEOUT_S  # the report (a figure) is drawn first
        while got.count("/7 ") < 3 and time.monotonic() < deadline and proc.poll() is None:
            if select.select([proc.stdout.fileno()], [], [], 1.0)[0]:  # never blocks past the deadline
                got += os.read(proc.stdout.fileno(), 4096).decode()
        assert got.count("/7 ") >= 3, got
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=TIMEOUT_S)  # before communicate() closes stdin: an EOF at the prompt is another ending
        out, err = proc.communicate(timeout=TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err
    assert "no ratings recorded" in err and "Traceback" not in err
    assert study.ratings_path.read_bytes() == before
    doc = json.loads((study.sessions / "P01-T1" / "trial.json").read_text())
    assert doc["status"] == "complete" and doc["signal"] == "SIGINT" and doc["duration_s"] < 25
    from haptic_acu.study import overview
    assert overview.states(study)["P01", 1].state == overview.TO_RATE
    tr = tick_rows(trajectory.load(rec, extra_columns=EXTRA))
    assert len(tr.t_s) == doc["ticks"] >= 500


# ---------------------------------------------------------------------------------------------
# bad input to a trial: one line, exit 2, no session folder


def test_trial_bad_input_is_one_line(world, tmp_path, capsys):
    study = plan(world, tmp_path / "s")
    base = ["study", "trial", str(study.folder), "--device", "scripted", "--trajectory", str(world["path"])]
    for argv, message in (
            (["study", "trial", str(tmp_path / "nope"), "--participant", "P01", "--device", "keyboard"],
             "no such study folder"),
            (base + ["--participant", "P09"], "--participant P09: not in this study"),
            (base + ["--participant", "P01", "--trial", "3"], "--trial 3: P01 has trials 1-2"),
            (base + ["--participant", "P01", "--duration", "-1"], "--duration must be > 0"),
            (["study", "trial", str(study.folder), "--participant", "P01", "--device", "scripted"],
             "--device scripted needs --trajectory"),
            (base[:-1] + ["/no/such.csv", "--participant", "P01"], "trajectory file not found"),
            (base + ["--participant", "P01", "--speed", "0"], "--speed must be a number > 0"),
            (["study", "trial", str(study.folder), "--participant", "P01", "--device", "keyboard", "--speed", "2"],
             "--speed is for --device scripted")):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1 and "Traceback" not in err, (argv, err)
    assert list(study.sessions.iterdir()) == []


def test_a_changed_config_is_refused_without_naming_the_model(world, tmp_path, capsys):
    """A model's config edited after the plan: the trial refuses it, naming the system code only."""
    d = tmp_path / "m"
    d.mkdir()
    files = []
    for name in NAMES:
        src = Path(dict(x.split("=") for x in world["models"].split(","))[name])
        f = d / f"{name}.toml"
        f.write_text(src.read_text())
        files.append(f)
    out = tmp_path / "s"
    assert main(["study", "plan", "--participants", "2", "--models",
                 ",".join(f"{n}={f}" for n, f in zip(NAMES, files)), "--out", str(out), "--seed", "1"]) == 0
    files[0].write_text(files[0].read_text().replace("thickness_mm = 8.4", "thickness_mm = 8.5", 1))
    study = Study(out)
    key = study.key()
    p = next(p for p in study.participants
             if key["systems"][p][study.plan[p, 1].system] == NAMES[0])
    capsys.readouterr()
    assert main(["study", "trial", str(out), "--participant", p, "--device", "scripted", "--trajectory",
                 str(world["path"])]) == 2
    err = capsys.readouterr().err
    assert study.plan[p, 1].system in err and "no longer matches the plan" in err
    assert not grep_names(err) and err.count("\n") == 1
    assert list(study.sessions.iterdir()) == []


@pytest.mark.slow  # the module's trials, and two replays
def test_analyze_objective_side(ran, tmp_path):
    """Each model on the common path (the key's configs), and the trials' session metrics by model."""
    study = ran["study"]
    out = tmp_path / "a"
    assert main(["study", "analyze", str(study.folder), "--out", str(out), "--path", str(ran["path"])]) == 0
    obj = json.loads((out / "report.json").read_text())["objective"]
    assert set(obj["models"]) == set(NAMES)
    assert obj["sessions"] == 2  # trial 1 (its latest attempt) and trial 2
    by_model = {r["model"]: r for r in obj["metrics_by_model"]}
    assert by_model[NAMES[0]]["sessions"] == by_model[NAMES[1]]["sessions"] == 1
    for m in NAMES:
        assert (out / "objective" / m / "samples.csv").is_file()
    # the fat cuts harder in one model: on the same path its force differs once the skin is through
    f = []
    for m in NAMES:
        with open(out / "objective" / m / "samples.csv", newline="") as fh:
            f.append(np.array([float(r["f_n"]) for r in csv.DictReader(fh)]))
    n = min(len(f[0]), len(f[1]))
    assert np.abs(f[0][:n] - f[1][:n]).max() > 0.1
    assert (out / "objective" / "force_depth.png").is_file()

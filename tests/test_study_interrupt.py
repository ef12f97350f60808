"""`study trial` stopped outside its session's loops: by Ctrl-C or SIGTERM while the simulator is
prepared or the device opens (before the session's own signal handling), or while the session's
files are written after it (before the ratings).

The interrupt is injected at a precise point, in this process: the patched step raises what
Python's SIGINT handler raises, or calls the SIGTERM handler installed at that point (none: the
test fails); one test per signal sends the real signal from the patched step of a child process.
Checked: the exit status and its one line, trial.json, what `study status` shows, and that the
trial then runs again with the same command, the interrupted attempt's files left as they were.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import cli_helpers
from cli_helpers import interrupt_now
from haptic_acu.study import overview
from haptic_acu.study.store import Study

REPO = Path(__file__).resolve().parents[1]
PROGRESS = ("haptic-acu: compiling", "haptic-acu: preparing", "haptic-acu: drawing")
SHOWN = ("P01, trial 1 of 2: System", "session: ")  # the trial's announcement, the session's closing line


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """Two models (the default config, and one with another cutting force) and a 1.2 s path."""
    from haptic_acu.base.config import DEFAULT_CONFIG

    d = tmp_path_factory.mktemp("world")
    text = DEFAULT_CONFIG.read_text()
    (d / "a.toml").write_text(text)
    (d / "b.toml").write_text(text.replace("cutting_n_per_mm_diameter = 0.2 ", "cutting_n_per_mm_diameter = 2.0 ", 1))
    t = np.linspace(0.0, 1.2, 25)
    z = np.interp(t, [0.0, 0.3, 1.2], [2.0, 0.0, -4.0])
    path = d / "path.csv"
    path.write_text("t_s,x_mm,y_mm,z_mm\n" + "".join(f"{a:.4f},0,0,{b:.4f}\n" for a, b in zip(t, z)))
    return {"models": f"Amodel={d / 'a.toml'},Bmodel={d / 'b.toml'}", "path": path}


@pytest.fixture
def study(world, tmp_path) -> Study:
    r = cli_helpers.cli("study", "plan", "--participants", "2", "--models", world["models"], "--out",
                        tmp_path / "s", "--seed", "5")
    assert r.returncode == 0, r.stderr
    return Study(tmp_path / "s")


def trial(study, world, *extra, stdin=None):
    return cli_helpers.cli("study", "trial", study.folder, "--participant", "P01", "--device", "scripted",
                           "--trajectory", world["path"], "--speed", "4", "--no-status", *extra, stdin=stdin,
                           timeout=600)


def said(r) -> list[str]:
    assert "Traceback" not in r.stderr, r.stderr
    return [ln for ln in r.stderr.splitlines() if ln.strip() and not ln.startswith(PROGRESS + SHOWN)]


def status_row(study, p="P01") -> list[str]:
    """`study status`'s row of ``p``: rated, to rate, interrupted, to run, then the notes."""
    r = cli_helpers.cli("study", "status", study.folder)
    assert r.returncode == 0, r.stderr
    row = next(ln for ln in r.stdout.splitlines() if ln.startswith(p + " "))
    return row.split(None, 5)[1:]


def trial_json(folder: Path) -> dict:
    return json.loads((folder / "trial.json").read_text())


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
@pytest.mark.parametrize("where", ["warm_up", "device.open"])
def test_interrupt_before_the_session_marks_the_trial_interrupted_and_it_runs_again(study, world, monkeypatch,
                                                                                   sig, where):
    from haptic_acu.devices.scripted import ScriptedDevice
    from haptic_acu.session.engine import Session

    sigterm_before = signal.getsignal(signal.SIGTERM)
    owner, name = (Session, "warm_up") if where == "warm_up" else (ScriptedDevice, "open")
    monkeypatch.setattr(owner, name, lambda self: interrupt_now(sig))
    ratings = study.ratings_path.read_bytes()
    r = trial(study, world)
    assert r.returncode == 128 + signal.Signals[sig]
    lines = said(r)
    assert len(lines) == 1 and f"P01-T1 interrupted ({sig}) before the session started" in lines[0], lines
    assert "run it again" in lines[0]
    assert signal.getsignal(signal.SIGTERM) == sigterm_before  # the command put SIGTERM's handler back

    folder = study.sessions / "P01-T1"
    doc = trial_json(folder)
    assert doc["status"] == "interrupted" and doc["signal"] == sig and doc["ended"] >= doc["started"]
    assert sorted(p.name for p in folder.iterdir()) == ["trial.json"]  # nothing recorded
    assert study.ratings_path.read_bytes() == ratings
    assert overview.states(study)["P01", 1].state == overview.INTERRUPTED
    assert status_row(study)[:4] == ["0/2", "0", "1", "1"] and "next: trial 1 " in status_row(study)[4]

    # the same command runs the trial again, into the trial's next folder; the first stays as it was
    monkeypatch.undo()
    kept = (folder / "trial.json").read_bytes()
    r = trial(study, world, "--ratings-later")
    assert r.returncode == 0, r.stderr
    assert (folder / "trial.json").read_bytes() == kept
    again = trial_json(study.sessions / "P01-T1.2")
    assert again["status"] == "complete" and again["attempt"] == 2 and again["ticks"] > 1000
    assert (study.sessions / "P01-T1.2" / "recording.csv").is_file()
    assert overview.states(study)["P01", 1].state == overview.TO_RATE
    assert status_row(study)[:4] == ["0/2", "1", "0", "1"]


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_interrupt_after_the_session_keeps_it_recorded_and_asks_no_ratings(study, world, monkeypatch, sig):
    """While the session's figure is drawn: the session is complete and stays so; no prompt, and
    the one line says how to enter the ratings."""
    from haptic_acu.session import report

    monkeypatch.setattr(report, "plot_force_depth", lambda *a, **k: interrupt_now(sig))
    ratings = study.ratings_path.read_bytes()
    r = trial(study, world, stdin="7\n" * 7 + "y\n")  # answers that must not be read
    assert r.returncode == 128 + signal.Signals[sig]
    lines = said(r)
    assert len(lines) == 1 and "P01-T1 is saved" in lines[0] and f"({sig})" in lines[0], lines
    assert "haptic-acu study rate" in lines[0] and "--trial 1" in lines[0]
    assert "Please rate" not in r.stdout and "System" not in r.stdout.split("P01-T1")[-1]
    doc = trial_json(study.sessions / "P01-T1")
    assert doc["status"] == "complete" and doc["ticks"] > 1000 and doc["recording_rows"] > 1000
    assert study.ratings_path.read_bytes() == ratings
    assert overview.states(study)["P01", 1].state == overview.TO_RATE
    assert status_row(study)[:4] == ["0/2", "1", "0", "1"]


_CHILD = """
import os, signal, sys, time
from haptic_acu.session.engine import Session
def warm_up(self):
    os.kill(os.getpid(), signal.{sig})
    for _ in range(6000):  # the handler runs at once; a process still here after a minute is a failure
        time.sleep(0.01)
    sys.exit(99)
Session.warm_up = warm_up
from haptic_acu.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.slow  # a child process: its imports and kernels
@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_the_real_signal_while_the_simulator_is_prepared(study, world, sig):
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    cmd = [sys.executable, "-c", _CHILD.format(sig=sig), "study", "trial", str(study.folder), "--participant",
           "P01", "--device", "scripted", "--trajectory", str(world["path"]), "--no-status"]
    # Ctrl-C's default action in the child whatever the runner's (a background job inherits SIGINT ignored)
    r = subprocess.run(cmd, cwd=REPO, env=env, stdin=subprocess.DEVNULL, capture_output=True, text=True,
                       timeout=600, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert r.returncode == 128 + signal.Signals[sig], r.stderr
    assert len(said(r)) == 1 and "before the session started" in r.stderr, r.stderr
    doc = trial_json(study.sessions / "P01-T1")
    assert doc["status"] == "interrupted" and doc["signal"] == sig
    assert overview.next_trial(study, "P01").trial == 1

"""A study of the model kinds (``model.kind``): one trial of each kind on the scripted device (paced
at 4 times real time, ``study trial --speed``: the compiled loop's ticks and forces as at real pace,
tests/test_rtloop.py), everything shown grepped for every kind's name, and each recording replayed
headless with the kind the key names, to the live session's forces."""
from __future__ import annotations

import csv
import io
import json
import sys

import numpy as np
import pytest

from haptic_acu.base.config import load_config
from haptic_acu.base.errors import UserError
from haptic_acu.cli import main
from haptic_acu.session import trajectory
from haptic_acu.session.recorder import EXTRA
from haptic_acu.study.store import KINDS, Study

from test_study import GOOD, write_path


def _kinds_available() -> bool:
    try:
        load_config(None, overrides=["model.kind=shf"])
        return True
    except UserError:
        return False


pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings("ignore:RRD file has no footer"),
              pytest.mark.skipif(not _kinds_available(), reason="the config has no model.kind yet")]


def leaks(text: str) -> list[str]:
    low = text.lower()
    return [k for k in KINDS + ("model.kind", "baseline") if k in low]


@pytest.fixture(scope="module")
def kinds_study(tmp_path_factory):
    from haptic_acu.session import status as status_mod

    d = tmp_path_factory.mktemp("kinds")
    path = write_path(d / "path.csv", t_end=1.0)
    out = d / "s"
    assert main(["study", "plan", "--participants", "1", "--models", ",".join(KINDS), "--out", str(out),
                 "--seed", "3"]) == 0
    mp = pytest.MonkeyPatch()
    mp.setattr(status_mod.StatusLine, "_is_tty", staticmethod(lambda stream: True))
    screen, codes = [], []
    for t in range(1, len(KINDS) + 1):
        o, e = io.StringIO(), io.StringIO()
        mp.setattr(sys, "stdin", io.StringIO("".join(f"{x}\n" for x in GOOD + ["y"])))
        mp.setattr(sys, "stdout", o)
        mp.setattr(sys, "stderr", e)
        try:
            rc = main(["study", "trial", str(out), "--participant", "P01", "--device", "scripted", "--trajectory",
                       str(path), "--rrd", "--speed", "4"])
        finally:
            mp.setattr(sys, "stdout", sys.__stdout__)
            mp.setattr(sys, "stderr", sys.__stderr__)
        assert rc == 0, e.getvalue()
        screen.append(o.getvalue() + e.getvalue())
    mp.undo()
    return {"study": Study(out), "screen": "\n".join(screen), "dir": d}


def test_every_kind_ran_blind(kinds_study):
    study = kinds_study["study"]
    assert not leaks(kinds_study["screen"]), kinds_study["screen"]
    from rerun.chunk import RrdReader
    for p in study.sessions.rglob("*"):
        assert not leaks(p.name), p
        if p.suffix in (".json", ".csv"):
            assert not leaks(p.read_text()), p
        if p.suffix == ".rrd":
            paths = {c.entity_path for c in RrdReader(p).stream().to_chunks()}
            assert paths and not leaks(" ".join(paths)), paths
    key = json.loads((study.folder / "key.json").read_text())
    assert sorted(key["systems"]["P01"].values()) == sorted(KINDS)
    assert len(study.rated()) == len(KINDS)


def test_every_kind_replays_with_its_model(kinds_study, tmp_path):
    study = kinds_study["study"]
    key = study.key()
    peaks = {}
    for t in study.trials_of("P01"):
        out = tmp_path / f"T{t.trial}"
        assert main(["study", "replay", str(study.folder), "--participant", "P01", "--trial", str(t.trial),
                     "--out", str(out)]) == 0
        rec = trajectory.load(study.sessions / f"P01-T{t.trial}" / "recording.csv", extra_columns=EXTRA)
        with open(out / "samples.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        ts = np.array([float(r["t_s"]) for r in rows])
        fz = np.array([float(r["fz_n"]) for r in rows])
        states = np.column_stack([rec.extra[f"state_{n}"] for n in ("skin", "fat", "muscle")])
        change = rec.t_s[1:][np.any(np.diff(states, axis=0) != 0, axis=1)]
        keep = rec.t_s <= ts[-1]
        for tc in change:
            keep &= np.abs(rec.t_s - tc) > 0.01
        live = rec.extra["fz_n"][keep]
        assert np.all(np.abs(np.interp(rec.t_s[keep], ts, fz) - live) <= 0.02 + 0.05 * np.abs(live)), t
        peaks[study.model_of(key, t)] = float(np.abs(rec.extra["fz_n"]).max())
    assert len(set(round(v, 3) for v in peaks.values())) > 1, peaks  # the kinds are not all the same model

"""The bundled synthetic study (config/study/example.toml): a plan, synthetic ratings under each
participant's codes, and each trial's session replayed headless on a scripted path."""
from __future__ import annotations

import csv
import io
import shutil
import tomllib
from pathlib import Path

from ..analysis.scoring import INDICES
from ..base.bundled import bundled_dir, resolve_trajectory
from ..base.errors import UserError
from .plan import make_plan
from .store import Study, now, parse_models, write_trial_json


def example_spec() -> tuple[dict, Path]:
    path = bundled_dir("config") / "study" / "example.toml"
    return tomllib.loads(path.read_text(encoding="utf-8")), path


def example_ratings(spec: dict, base: Path) -> dict[tuple[str, str], list[str]]:
    """(rater, model) -> the seven ratings as written in the bundled ratings file."""
    text = (base.parent / spec["ratings"]).resolve().read_text(encoding="utf-8")
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.startswith("#")]
    out = {}
    for row in csv.DictReader(io.StringIO("\n".join(lines))):
        out[row["rater"], spec["systems"][row["system"]]] = [row[c] for c in INDICES]
    return out


def write_example(out: Path, sessions: bool = True, progress=None) -> Study:
    spec, path = example_spec()
    specs = parse_models(",".join(spec["models"]), None, [])
    make_plan(out, specs, int(spec["participants"]), int(spec["seed"]))
    study = Study(out)
    key = study.key()
    ratings = example_ratings(spec, path)
    raters = sorted({r for r, _ in ratings})
    if len(raters) != len(study.participants):
        raise UserError(f"{path}: {len(raters)} raters for {len(study.participants)} participants")
    rater_of = dict(zip(study.participants, raters))
    if sessions:
        from ..session.replay import replay_one

        configs = {m: study.checked_config(key, m) for m in study.models}
        paths = [resolve_trajectory(p) for p in spec["sessions"]["paths"]]
        for k, p in enumerate(study.participants):
            traj = paths[k % len(paths)]
            for t in study.trials_of(p):
                folder, attempt = study.new_session_folder(t)
                doc = {"participant": p, "trial": t.trial, "system": t.system, "attempt": attempt,
                       "status": "running", "device": "scripted (replayed headless: synthetic study)",
                       "trajectory": traj.name, "started": now()}
                write_trial_json(folder, doc)
                tmp = folder / "replay"
                summary = replay_one(traj, tmp, rrd=False, progress=False, cfg=configs[study.model_of(key, t)])
                for f in tmp.iterdir():
                    f.rename(folder / f.name)
                tmp.rmdir()
                shutil.copyfile(traj, folder / "recording.csv")
                doc.update(status="complete", ended=now(), duration_s=summary["duration_s"], ticks=summary["ticks"])
                write_trial_json(folder, doc)
            if progress:
                progress(p)
    for p in study.participants:
        for t in study.trials_of(p):
            values = ratings[rater_of[p], study.model_of(key, t)]
            study.record_ratings(t, [float(v) for v in values], "synthetic")
    return study

"""``study plan``: a new study folder (see :mod:`haptic_acu.study.store` for what is in it)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .. import __version__
from ..analysis.scoring import INDICES
from ..base.errors import UserError
from . import design
from .store import (DEFAULT_SCALE, FORMAT, ModelSpec, _csv_line, config_hash, config_text, now, participant_ids,
                    ratings_file_text, write_atomic)


def make_plan(out, specs: list[ModelSpec], n_participants: int, seed: int | None, trials_per_model: int = 1,
              per_participant_codes: bool = False) -> dict:
    """Write a new study into ``out`` (a new or empty folder). Returns a summary for the terminal
    (nothing in it reveals the key)."""
    out = Path(out)
    n = len(specs)
    if not design.MIN_MODELS <= n <= design.MAX_MODELS:
        raise UserError(f"--models: {n} model(s); a study compares {design.MIN_MODELS}-{design.MAX_MODELS}")
    if n_participants < 1:
        raise UserError(f"--participants must be >= 1, got {n_participants}")
    if trials_per_model < 1:
        raise UserError(f"--trials-per-model must be >= 1, got {trials_per_model}")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise UserError(f"{out}: exists and is not an empty folder; choose a new --out")
    hashes = {s.name: config_hash(s) for s in specs}  # validates every model's config first
    dup = [m for m in hashes if list(hashes.values()).count(hashes[m]) > 1]
    if dup:
        raise UserError(f"--models: {' and '.join(dup)} have the same config; the study could not tell them apart")
    if seed is None:
        seed = int(np.random.SeedSequence().entropy % (2**32))
    rng = np.random.default_rng(seed)
    sched = design.schedule(n, n_participants, trials_per_model, rng)
    codes = design.system_codes(n, n_participants, per_participant_codes, rng)
    people = participant_ids(n_participants)
    names = [s.name for s in specs]

    block = sched.block
    complete = n_participants // block * block
    balance = {"design_rows": block, "participants": n_participants, "balanced_participants": complete}
    if n_participants % block:
        balance["note"] = (f"{n_participants} participants is not a multiple of the design's {block} rows: "
                           f"positions and carry-over are balanced over the first {complete} participants only; "
                           f"{block - n_participants % block} more would complete the last block")
    study = {
        "format": FORMAT,
        "created": now(),
        "tool_version": __version__,
        "models": names,
        "config_hash": hashes,
        "seed": seed,
        "participants": people,
        "trials_per_model": trials_per_model,
        "codes": "per-participant" if per_participant_codes else "shared",
        "design": "Williams Latin square" + ("" if n % 2 == 0 else " and its mirror (odd number of models)"),
        "balance": balance,
        "indices": list(INDICES),
        "scale": dict(DEFAULT_SCALE),
    }
    key = {
        "warning": "THE KEY: which system is which model. Keep it from participants and from whoever runs "
                   "the sessions; only `haptic-acu study trial`, `study replay` and `study analyze` read it.",
        "systems": {p: {f"System {codes[i][m]}": names[m] for m in range(n)} for i, p in enumerate(people)},
        "models": {s.name: {"kind": s.kind, "config": s.config, "overrides": list(s.overrides),
                            "config_hash": hashes[s.name], "config_toml": config_text(s)} for s in specs},
        "design_rows": [[names[m] for m in row] for row in sched.design],
        "participant_rows": {p: list(sched.rows[i]) for i, p in enumerate(people)},
    }
    plan_lines = [_csv_line(("participant", "trial", "system"))]
    for i, p in enumerate(people):
        for t, m in enumerate(sched.order[i], 1):
            plan_lines.append(_csv_line((p, t, f"System {codes[i][m]}")))
    try:
        out.mkdir(parents=True, exist_ok=True)
        (out / "sessions").mkdir()
        write_atomic(out / "key.json", json.dumps(key, indent=2) + "\n", exclusive=True)
        write_atomic(out / "plan.csv", "\n".join(plan_lines) + "\n", exclusive=True)
        write_atomic(out / "ratings.csv", ratings_file_text(out.name), exclusive=True)
        write_atomic(out / "study.json", json.dumps(study, indent=2) + "\n", exclusive=True)
    except FileExistsError as e:
        raise UserError(f"{e.filename2 or e.filename}: appeared while the plan was written; choose a new --out") from None
    except OSError as e:
        raise UserError(f"{out}: cannot write the study: {e.strerror or e}") from None
    return study

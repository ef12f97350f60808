"""Where a study stands, per participant and trial, from the plan, the sessions and ratings.csv
(never the key).

A trial is

* ``rated`` (done): its seven ratings are in ratings.csv;
* ``to rate``: a session completed, no ratings yet (``--ratings-later``, or Ctrl-C at the prompts);
* ``interrupted``: every session of it was stopped by SIGTERM, ended by a fault, stopped by Ctrl-C
  or SIGTERM before it started, or never finished (a folder whose trial.json still says
  ``running``: its process was killed outright); it may simply be run again;
* ``to run``: no session yet.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass

from ..base.errors import UserError
from .store import Study, Trial

RATED, TO_RATE, INTERRUPTED, TO_RUN = "rated", "to rate", "interrupted", "to run"


@dataclass(frozen=True)
class TrialState:
    trial: Trial
    state: str
    attempts: int  # session folders of this trial
    last_folder: str | None


def states(study: Study) -> dict[tuple[str, int], TrialState]:
    rated = study.rated()
    attempts: dict = {}
    for a in study.attempts():
        attempts.setdefault((a.participant, a.trial), []).append(a)
    out = {}
    for key, trial in study.plan.items():
        mine = attempts.get(key, [])
        if key in rated:
            s = RATED
        elif any(a.status == "complete" for a in mine):
            s = TO_RATE
        elif mine:
            s = INTERRUPTED
        else:
            s = TO_RUN
        out[key] = TrialState(trial, s, len(mine), mine[-1].folder.name if mine else None)
    return out


def next_trial(study: Study, participant: str, st=None) -> Trial | None:
    """The participant's first trial in plan order without a completed session (and not rated)."""
    st = states(study) if st is None else st
    for t in study.trials_of(participant):
        if st[participant, t.trial].state in (TO_RUN, INTERRUPTED):
            return t
    return None


def table(study: Study) -> list[str]:
    """The status report's lines (80 columns)."""
    st = states(study)
    n = study.n_trials
    total = len(study.participants) * n
    w = max(7, 2 * len(str(total)) + 3)  # the "rated" column: done/planned
    pw = max(11, max(len(p) for p in study.participants)) + 1
    lines = [f"{study.folder}:",
             f"  {len(study.participants)} participants x {n} trials of {len(study.models)} systems "
             f"(codes {study.doc.get('codes', 'shared')})",
             f"{'participant':<{pw}}{'rated':>{w}}{'to rate':>9}{'interr.':>9}{'to run':>8}  next / to rate"]
    totals = {RATED: 0, TO_RATE: 0, INTERRUPTED: 0, TO_RUN: 0}
    for p in study.participants:
        mine = [st[p, t] for t in range(1, n + 1)]
        c = {k: sum(1 for s in mine if s.state == k) for k in totals}
        for k in totals:
            totals[k] += c[k]
        nxt = next_trial(study, p, st)
        notes = []
        if nxt is not None:
            notes.append(f"next: trial {nxt.trial} ({nxt.system})")
        rate = [s.trial.trial for s in mine if s.state == TO_RATE]
        if rate:
            notes.append("rate: " + ",".join(map(str, rate)))
        if not notes:
            notes.append("all done")
        lines.append(f"{p:<{pw}}{f'{c[RATED]}/{n}':>{w}}{c[TO_RATE]:>9}{c[INTERRUPTED]:>9}{c[TO_RUN]:>8}  "
                     + "; ".join(notes))
    lines.append(f"{'total':<{pw}}{f'{totals[RATED]}/{total}':>{w}}{totals[TO_RATE]:>9}{totals[INTERRUPTED]:>9}"
                 f"{totals[TO_RUN]:>8}")
    return lines


def pick_trial(study, participant: str, number: int | None = None, redo: bool = False):
    """The trial to run for ``participant`` and its :class:`TrialState`: trial ``number``, or the next
    one of the plan not yet run. UserError (one line) if there is none, or if ``number`` is out of range
    or already run (unless ``redo``); a note on stderr when ``number`` runs out of the plan's order."""
    p = study.participant(participant)
    st = states(study)
    if number is None:
        trial = next_trial(study, p, st)
        if trial is None:
            rate = [t for t in range(1, study.n_trials + 1) if st[p, t].state == TO_RATE]
            tail = f"; to rate: trial(s) {', '.join(map(str, rate))}" if rate else ""
            raise UserError(f"{p}: every trial has been run{tail} (--trial T --redo runs one again)")
        return trial, st[p, trial.trial]
    if not 1 <= number <= study.n_trials:
        raise UserError(f"--trial {number}: {p} has trials 1-{study.n_trials}")
    trial = study.plan[p, number]
    s = st[p, number]
    if s.state in (RATED, TO_RATE) and not redo:
        what = "is done (rated)" if s.state == RATED else "was run (not rated yet: `study rate`)"
        raise UserError(f"{p} trial {number} {what}; --redo runs it again and keeps the earlier files")
    first = next_trial(study, p, st)
    if s.state in (TO_RUN, INTERRUPTED) and first is not None and first.trial < number:
        print(f"haptic-acu study: note: {p}'s trial {first.trial} comes first in the plan; running trial "
              f"{number} out of order", file=sys.stderr)
    return trial, s

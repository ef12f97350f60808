"""``haptic-acu study``: a blinded, counterbalanced user study of tissue models (the paper's
section 4.2), end to end. See docs/study.md.

* ``study plan``     a Williams-square schedule, the system codes and the key (STUDY/key.json)
* ``study trial``    a participant's next (or given) trial with the hidden model, then its ratings
* ``study rate``     enter or correct a trial's ratings afterwards (the old row is kept)
* ``study status``   what is done and what is left (never the key)
* ``study replay``   a trial's recording replayed headless with its model (from the key)
* ``study analyze``  the key is read: the paper's scores and the statistics, the objective side
* ``study example``  the bundled synthetic study (plan, synthetic ratings, scripted sessions)
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from ..base.errors import UserError
from ..base.signals import Terminated, sigterm_unwinds


def register(sub) -> None:
    p = sub.add_parser("study", help="a blinded, counterbalanced user study of tissue models (plan, trial, rate, "
                                     "status, replay, analyze, example)",
                       description="Run the paper's user study (section 4.2) blind: plan a counterbalanced "
                                   "schedule with hidden models, run each participant's trials, collect the seven "
                                   "ratings, and analyze (the comprehensive score and the statistics). docs/study.md.")
    ss = p.add_subparsers(dest="study_command", metavar="SUBCOMMAND", parser_class=type(p))
    ss.required = True

    q = ss.add_parser("plan", help="a new study: Williams-square schedule, system codes, the key",
                      description="Write a new study folder: study.json, plan.csv (participant,trial,system: "
                                  "codes only), ratings.csv (empty) and key.json (which system is which model; keep "
                                  "it from participants and from whoever runs the sessions).")
    q.add_argument("--participants", type=int, required=True, metavar="N")
    q.add_argument("--models", required=True, metavar="M1,M2,...",
                   help="2-8 models: model.kind values (forcenet, msm, fem, bem, shf) on --config, or "
                        "NAME=FILE.toml for a config of its own")
    q.add_argument("--out", required=True, metavar="STUDY", help="the study folder (new or empty)")
    q.add_argument("--seed", type=int, metavar="S", help="random seed (default: a fresh one, recorded)")
    q.add_argument("--trials-per-model", type=int, default=1, metavar="K",
                   help="times each participant meets each model (default 1)")
    q.add_argument("--codes-per-participant", action="store_true",
                   help="a different numbering of the systems for each participant (default: one for all)")
    from .options import add_config_args
    add_config_args(q)
    q.set_defaults(func=cmd_plan)

    q = ss.add_parser("trial", help="run a participant's next (or given) trial with the hidden model",
                      description="Run one trial: a live session with the hidden model (everything shown names "
                                  "the system code only), into STUDY/sessions/P-T/, then the seven ratings on the "
                                  "terminal, appended to STUDY/ratings.csv. End the session with Ctrl-C (the "
                                  "keyboard: q; a scripted path: its end).")
    q.add_argument("study", metavar="STUDY")
    q.add_argument("--participant", required=True, metavar="P")
    q.add_argument("--trial", type=int, metavar="T", help="the trial number (default: the participant's next)")
    q.add_argument("--device", choices=("omni", "keyboard", "scripted"), required=True)
    q.add_argument("--trajectory", metavar="FILE", help="for --device scripted: the path to play (a file or a "
                                                        "bundled trajectory's name)")
    q.add_argument("--duration", type=float, metavar="S", help="end the session after S seconds")
    q.add_argument("--redo", action="store_true",
                   help="run a trial that was already run or rated (the earlier files are kept; new ratings "
                        "replace the old row, which stays in ratings.csv as a comment)")
    q.add_argument("--ratings-later", action="store_true", help="do not ask the ratings now (`study rate` later)")
    q.add_argument("--rrd", action="store_true", help="also write the rerun recording (recording.rrd)")
    q.add_argument("--no-status", action="store_true", help="no live status line")
    q.add_argument("--pin-cores", action="store_true", help="as `run --pin-cores`")
    q.add_argument("--travel-axis", action="store_true", help="as `run --travel-axis` (OMNI)")
    q.add_argument("--python-servo", action="store_true", help="as `run --python-servo`")
    q.add_argument("--speed", type=float, default=1.0, metavar="X",
                   help="as `run --speed`: --device scripted played X times as fast as real time (a dry run "
                        "of the study; trial.json records the speed)")
    q.set_defaults(func=cmd_trial)

    q = ss.add_parser("rate", help="enter or correct a trial's ratings",
                      description="Enter a trial's seven ratings (asked one by one, or --values), or correct "
                                  "them: the replaced row stays in ratings.csv as a # comment line.")
    q.add_argument("study", metavar="STUDY")
    q.add_argument("--participant", required=True, metavar="P")
    q.add_argument("--trial", type=int, required=True, metavar="T")
    q.add_argument("--values", metavar="V1,...,V7", help="the seven ratings, comma separated, in the order of "
                                                         "docs/study.md (instead of the prompts)")
    q.set_defaults(func=cmd_rate)

    q = ss.add_parser("status", help="what is done and what is left, per participant (never the key)")
    q.add_argument("study", metavar="STUDY")
    q.set_defaults(func=cmd_status)

    q = ss.add_parser("replay", help="replay a trial's recording headless with its model (read from the key)")
    q.add_argument("study", metavar="STUDY")
    q.add_argument("--participant", required=True, metavar="P")
    q.add_argument("--trial", type=int, required=True, metavar="T")
    q.add_argument("--attempt", type=int, metavar="K", help="which session of the trial (default: the latest)")
    q.add_argument("--out", required=True, metavar="DIR", help="output folder (new or empty)")
    q.set_defaults(func=cmd_replay)

    q = ss.add_parser("analyze", help="unblind and analyze: the paper's scores, Friedman/Wilcoxon, order check, "
                                      "the objective side",
                      description="Read the key and analyze the ratings: the paper's comprehensive weighted score "
                                  "(exactly `haptic-acu score` on ratings_by_model.csv), per index Friedman with "
                                  "Kendall's W, pairwise Wilcoxon with Holm's correction, medians and IQRs, the "
                                  "order and carry-over check; each model on a common scripted path and the "
                                  "sessions' metrics per model.")
    q.add_argument("study", metavar="STUDY")
    q.add_argument("--out", required=True, metavar="DIR", help="output folder (new or empty)")
    src = q.add_mutually_exclusive_group()
    src.add_argument("--subjective", metavar="WEIGHTS.csv", help="as `haptic-acu score --subjective`")
    src.add_argument("--delphi", metavar="ROUNDS.csv", help="as `haptic-acu score --delphi`")
    q.add_argument("--bound", type=float, default=0.1, help="as `haptic-acu score --bound` (default %(default)s)")
    q.add_argument("--mu", type=float, default=0.4, help="as `haptic-acu score --mu` (default %(default)s)")
    q.add_argument("--path", default="default", metavar="TRAJECTORY",
                   help="the common scripted path of the objective side (default: the bundled default)")
    q.add_argument("--no-objective", action="store_true", help="skip the objective side (no replays)")
    q.set_defaults(func=cmd_analyze)

    q = ss.add_parser("example", help="write the bundled synthetic study (plan, ratings, scripted sessions)",
                      description="Write the bundled synthetic study into a new folder: 20 participants x 5 "
                                  "models (forcenet, msm, fem, bem, shf), the synthetic ratings of "
                                  "config/scoring/example_ratings.csv under each participant's codes, and each "
                                  "trial's session on a bundled scripted path, replayed headless.")
    q.add_argument("--out", required=True, metavar="STUDY")
    q.add_argument("--no-sessions", action="store_true", help="plan and ratings only (no replays)")
    q.set_defaults(func=cmd_example)


# ---------------------------------------------------------------------------------------------


def _study(path):
    from ..study.store import Study
    return Study(path)


def _participant_trial(study, args) -> str:
    """``--participant``'s name, once ``--trial`` is checked to be one of theirs."""
    p = study.participant(args.participant)
    if not 1 <= args.trial <= study.n_trials:
        raise UserError(f"--trial {args.trial}: {p} has trials 1-{study.n_trials}")
    return p


def _new_folder(arg: str) -> Path:
    """An output folder under the output rule (:mod:`haptic_acu.base.outputs`): new or empty."""
    from ..base.outputs import check_folder

    d = Path(arg)
    check_folder(d, "--out")
    return d


def cmd_plan(args) -> int:
    from ..study.plan import make_plan
    from ..study.store import parse_models

    specs = parse_models(args.models, args.config, args.overrides)
    doc = make_plan(args.out, specs, args.participants, args.seed, args.trials_per_model,
                    args.codes_per_participant)
    out = Path(args.out)
    b = doc["balance"]
    print(f"{out}: {len(doc['participants'])} participants x {len(specs) * args.trials_per_model} trials "
          f"of {len(specs)} systems")
    print(f"  {doc['design']}, {b['design_rows']} rows; seed {doc['seed']}")
    if "note" in b:
        print(f"haptic-acu study: note: {b['note']}", file=sys.stderr)
    print("  plan.csv: the schedule (system codes only); ratings.csv: the ratings")
    print("  key.json: WHICH SYSTEM IS WHICH MODEL. Keep it from the participants and from")
    print("  whoever runs the sessions (only study trial, replay and analyze read it).")
    print(f"next: haptic-acu study trial {out} --participant {doc['participants'][0]} --device omni")
    return 0


def cmd_trial(args) -> int:
    from ..base.bundled import not_found_hint, resolve_trajectory
    from ..study import overview
    from ..study.trial import blind_config, ended_here, run_session
    from .run import make_device

    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise UserError(f"--duration must be > 0, got {args.duration}")
    from .options import check_speed_arg
    check_speed_arg(args)
    study = _study(args.study)
    trial, state = overview.pick_trial(study, args.participant, args.trial, args.redo)
    key = study.key()
    model = study.model_of(key, trial)
    cfg = blind_config(study, key, model, trial)
    if args.trajectory:
        traj = resolve_trajectory(args.trajectory)
        if not traj.is_file():
            raise UserError(f"{traj}: trajectory file not found{not_found_hint()}")
        args.trajectory = str(traj)
    device = make_device(args, cfg)
    with sigterm_unwinds():  # SIGTERM before or after the session's loops: trial.json says how it ended
        res = run_session(study, trial, cfg, device, device_name=args.device, duration_s=args.duration,
                          rrd=args.rrd, status=not args.no_status, compiled=not args.python_servo,
                          pin_cores=args.pin_cores, speed=args.speed)
        stopped = ended_here(study, trial, res)  # a fault or a signal: its one line, the exit status
        if stopped is not None:
            return stopped
        if args.ratings_later:
            print(f"{res.folder.name}: session recorded; ratings later: haptic-acu study rate {study.folder} "
                  f"--participant {trial.participant} --trial {trial.trial}")
            return 0
        return _ask_and_record(study, trial, redo=state.state in (overview.RATED, overview.TO_RATE))


def _ask_and_record(study, trial, redo: bool, previous=None) -> int:
    from ..study.ratings import RatingsAbandoned, ask
    from ..study.trial import no_ratings, signal_name

    later = (f"haptic-acu study rate {study.folder} --participant {trial.participant} --trial {trial.trial}")
    try:
        values = ask(trial.system, study.scale, write=print, previous=previous)
    except (KeyboardInterrupt, Terminated) as e:
        return no_ratings(study, trial, signal_name(e))
    except RatingsAbandoned as e:
        raise UserError(f"ratings: {e}; nothing recorded; enter them with: {later}") from None
    old = study.record_ratings(trial, values, "redo of the trial" if redo else "corrected by study rate")
    print(f"ratings of {trial.participant} trial {trial.trial} ({trial.system}) saved in {study.ratings_path}"
          + (" (the earlier row kept as a comment)" if old is not None else ""))
    return 0


def cmd_rate(args) -> int:
    from ..study import overview
    from ..study.ratings import check_row

    study = _study(args.study)
    p = _participant_trial(study, args)
    trial = study.plan[p, args.trial]
    st = overview.states(study)[p, args.trial]
    if st.state in (overview.TO_RUN, overview.INTERRUPTED):
        raise UserError(f"{p} trial {args.trial} has no completed session yet; run it with `study trial`")
    prev = study.rated().get((p, args.trial))
    if args.values is not None:
        try:
            values = check_row(args.values.split(","), study.scale)
        except ValueError as e:
            raise UserError(f"--values: {e}") from None
        old = study.record_ratings(trial, values, "corrected by study rate")
        print(f"ratings of {p} trial {args.trial} ({trial.system}) saved"
              + (" (the earlier row kept as a comment)" if old is not None else ""))
        return 0
    return _ask_and_record(study, trial, redo=False, previous=None if prev is None else prev.values)


def cmd_status(args) -> int:
    from ..study import overview

    study = _study(args.study)
    for line in overview.table(study):
        print(line)
    return 0


def cmd_replay(args) -> int:
    from ..session.replay import replay_one
    from ..study.trial import blind_config

    study = _study(args.study)
    p = _participant_trial(study, args)
    mine = [a for a in study.attempts_of(p, args.trial) if (a.folder / "recording.csv").is_file()]
    if args.attempt is not None:
        mine = [a for a in mine if a.number == args.attempt]
    if not mine:
        raise UserError(f"{p} trial {args.trial}: no recorded session" +
                        (f" (attempt {args.attempt})" if args.attempt else ""))
    a = mine[-1]
    out = _new_folder(args.out)
    trial = study.plan[p, args.trial]
    key = study.key()
    cfg = blind_config(study, key, study.model_of(key, trial), trial)
    summary = replay_one(a.folder / "recording.csv", out, rrd=False, progress=False, cfg=cfg)
    print(f"{a.folder.name} replayed headless with its model (from the study's key): "
          f"{len(summary['punctures'])} punctures, max force {summary['max_force_n']:.3f} N; files: {out}/")
    return 0


def _subjective(args):
    import numpy as np

    from ..analysis import scoring
    from ..analysis.score_files import read_delphi, read_subjective

    if not (math.isfinite(args.mu) and 0.0 < args.mu < 1.0):
        raise UserError(f"--mu {args.mu}: must satisfy 0 < mu < 1")
    if not (math.isfinite(args.bound) and args.bound > 0):
        raise UserError(f"--bound {args.bound}: must be a positive number")
    if args.delphi:
        rounds, _ = read_delphi(args.delphi)
        return scoring.delphi(rounds, args.bound).weights
    if args.subjective:
        return read_subjective(args.subjective)
    return np.array(scoring.PAPER_SUBJECTIVE_WEIGHTS)


def cmd_analyze(args) -> int:
    import json

    from ..base.bundled import not_found_hint, resolve_trajectory
    from ..base.progress import step
    from ..study.analyze import analysis_lines, analyze, objective
    from . import score as score_cmd

    study = _study(args.study)
    alpha = _subjective(args)  # a bad weights file fails before anything is written
    path = None
    if not args.no_objective:
        path = resolve_trajectory(args.path)
        if not path.is_file():
            raise UserError(f"--path {args.path}: trajectory file not found{not_found_hint()}")
    out = _new_folder(args.out)
    report = analyze(study, out, alpha, args.mu)
    # the paper's scoring: `haptic-acu score` itself on the unblinded ratings
    score_args = argparse.Namespace(ratings=str(out / "ratings_by_model.csv"), subjective=args.subjective,
                                    delphi=args.delphi, bound=args.bound, mu=args.mu, out=str(out / "score"))
    scored = bool(report["scores"]) and not report["not_scored"]
    if scored:
        print("the paper's comprehensive weighted score (haptic-acu score on ratings_by_model.csv):")
        score_cmd.run(score_args)
    else:
        print("score/ not written: `haptic-acu score` needs every model rated by 2 or more participants")
    if path is not None:
        with step(f"replaying {path.name} with each of the {len(study.models)} models"):
            report["objective"] = objective(study, out, path)
    (out / "report.json").write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    for line in analysis_lines(report):
        print(line)
    print(f"wrote {out}/: report.json, ratings_by_model.csv, friedman.csv, wilcoxon.csv,")
    print("  descriptives.csv, order.csv, indices.png, order.png" + (", score/" if scored else "")
          + (", objective/" if path is not None else ""))
    return 0


def cmd_example(args) -> int:
    from ..study.example import write_example

    out = _new_folder(args.out)
    write_example(out, sessions=not args.no_sessions)
    print(f"{out}: the synthetic example study; try: haptic-acu study status {out}; "
          f"haptic-acu study analyze {out} --out {out}-analysis")
    return 0

"""``haptic-acu replay``: headless replay of one or more trajectories (see :mod:`haptic_acu.session.replay`)."""
from __future__ import annotations

import sys
import time
from pathlib import Path

from ..base.bundled import bundled_names
from ..base.errors import UserError
from ..base.outputs import Outputs, claim_folder
from ..base.outputs import fresh_folder as fresh_path
from ..base.signals import sigterm_unwinds

BATCH_FILES = ("summaries.csv", "insertions.csv", "punctures.csv")


def register(sub) -> None:
    p = sub.add_parser("replay", help="replay recorded trajectories headless (the main job)",
                       description="Replay needle trajectories (CSV t_s,x_mm,y_mm,z_mm) through the simulator "
                                   "on simulated time and write samples.csv, summary.json, force_depth.png and "
                                   "recording.rrd. Without TRAJECTORY: the bundled default insertion.")
    p.add_argument("trajectories", nargs="*", metavar="TRAJECTORY",
                   help="CSV files, folders of them, or bundled trajectories by name from any folder ("
                        + bundled_names() + ")")
    from .options import add_config_args
    add_config_args(p)
    p.add_argument("--out", metavar="DIR", help="output folder (default: a new folder under runs/; must be empty "
                                                "if it exists); for a batch, one sub-folder per trajectory")
    p.add_argument("--realtime", action="store_true", help="pace the replay on the wall clock")
    p.add_argument("--no-rrd", action="store_true", help="do not write recording.rrd")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--spawn", action="store_true", help="stream to a new rerun viewer instead of a file (needs a display)")
    g.add_argument("--connect", metavar="ADDR", help="stream to a running rerun viewer at ADDR")
    from .options import add_layout_arg
    add_layout_arg(p, "instructor for a file, trainee with --spawn/--connect")
    p.add_argument("--jobs", type=int, default=0, metavar="N", help="parallel replays for a batch (default: the cores)")
    p.add_argument("--quiet", action="store_true", help="print only where the files are")
    from ..session.point import add_point_args
    add_point_args(p)
    p.add_argument("--verbose", action="store_true", help="also print timing statistics (how fast the replay ran)")
    p.set_defaults(func=run)


def _stamp() -> str:
    return time.strftime("%Y%m%d-%H%M%S")


def print_summary(summary: dict, out_dir: Path, file=None, quiet: bool = False, verbose: bool = False) -> None:
    from ..session.report import print_results
    print_results(summary, out_dir, file=file, quiet=quiet, verbose=verbose)


def _one(args_tuple):
    traj, out_dir, config, rrd, overrides, point, layout = args_tuple
    from ..base.config import load_config
    from ..session.point import setup
    from ..session.replay import replay_one
    try:
        cfg = load_config(config, overrides=overrides)
        s = replay_one(traj, out_dir, config, rrd=rrd, progress=False, cfg=cfg,
                       point=setup(cfg, *point) if point else None, layout=layout)
        return str(traj), s, None
    except UserError as e:
        return str(traj), None, str(e)
    except OSError as e:  # a full disk, a folder made read-only meanwhile
        return str(traj), None, f"{e.filename or out_dir}: {e.strerror or e}"


def _replays(work, jobs: int):
    """Each batch item's (trajectory, summary, error) as it is done: one worker is this process (no
    child to start: its imports and kernels are loaded already), more are spawned processes."""
    if jobs == 1:
        for w in work:
            yield _one(w)
        return
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from multiprocessing import get_context

    from ..base import gcpolicy

    with ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn"),
                             initializer=gcpolicy.command_process) as ex:  # each worker: one batch, then exit
        for f in as_completed([ex.submit(_one, w) for w in work]):
            yield f.result()


def run(args) -> int:
    from .options import config_from_args
    from ..base.bundled import not_found_hint
    from ..session.replay import replay_one, trajectories_from

    if args.jobs < 0:
        raise UserError(f"--jobs must be >= 0 (0: one per core), got {args.jobs}")
    cfg = config_from_args(args)  # a bad config fails before anything runs
    from .options import check_layout_arg
    check_layout_arg(args)
    from ..session.point import setup_from_args
    ps = setup_from_args(cfg, args)  # a bad point or patient too
    if args.spawn:
        from ..session.viewer import NO_DISPLAY_REPLAY, check_spawn
        check_spawn(NO_DISPLAY_REPLAY)
    paths = trajectories_from(args.trajectories)
    from ..base.csvin import check_source
    for p in paths:
        if not (p.exists() or p.is_symlink()):
            raise UserError(f"{p}: trajectory file not found{not_found_hint()}")
        check_source(p, "trajectory file")  # a folder, a pipe or a device: refused unread
    if len(paths) == 1:
        traj = paths[0]
        out = Path(args.out) if args.out else fresh_path(Path("runs") / f"{traj.stem}-{_stamp()}")
        with sigterm_unwinds():  # SIGTERM outside the session's loops: DIR.partial removed, exit 143
            summary = replay_one(traj, out, args.config, realtime=args.realtime, rrd=not args.no_rrd,
                                 spawn=args.spawn, connect=args.connect, cfg=cfg, point=ps, layout=args.layout)
        print_summary(summary, out, quiet=args.quiet, verbose=args.verbose)
        return 0
    if args.spawn or args.connect or args.realtime:
        raise UserError("--spawn, --connect and --realtime take one trajectory, not a batch")
    base = Path(args.out) if args.out else fresh_path(Path("runs") / f"batch-{_stamp()}")
    plan = Outputs().folder("--out", base, files=BATCH_FILES + tuple(p.stem for p in paths))
    for p in paths:
        plan.input("TRAJECTORY", p)
    if args.config:
        plan.input("--config", args.config)
    if not (base.is_dir() and any(base.iterdir())):
        plan.check()  # a folder with files: a batch writing it is named first (claim_folder)
    lock = claim_folder(base, busy=f"{base}: another batch is writing to this folder; wait for it or "
                                   "choose another --out")
    try:
        return _run_batch(args, paths, base, ps)
    finally:
        lock.release()


def _run_batch(args, paths, base: Path, ps=None) -> int:
    from ..session.batch import insertion_rows, puncture_rows, summary_row, write_table

    stems = [p.stem for p in paths]
    if len(set(stems)) != len(stems):
        raise UserError("batch trajectories must have distinct file names")
    from ..cohort.update import bounded_jobs
    jobs, note = bounded_jobs(args.jobs)  # at most the cores and what the memory holds
    if note:
        print(f"haptic-acu: note: {note}", file=sys.stderr)
    jobs = min(jobs, len(paths))
    # a random patient is drawn once for the batch (its seed recorded), so every file meets the same one
    point = ((args.point, args.patient if ps is None or not ps.patient.random else f"random:{ps.patient.seed}",
              args.feedback) if args.point else None)
    work = [(str(p), str(base / p.stem), args.config, not args.no_rrd, args.overrides or None, point, args.layout)
            for p in paths]
    results = {}
    from ..base import progress
    with progress.step(f"replaying {len(paths)} trajectories " + ("in this process" if jobs == 1 else
                                                                    f"in {jobs} processes")):
        for traj, summary, err in _replays(work, jobs):
            results[traj] = (summary, err)
            progress.note(f"{len(results)}/{len(paths)} done: {Path(traj).name}" + (" (failed)" if err else ""))
    failed = 0
    rows, insertions, punctures = [], [], []
    for p, w in zip(paths, work):
        summary, err = results[str(p)]
        if err:
            failed += 1
            print(f"haptic-acu replay: error: {err}", file=sys.stderr)
            continue
        print_summary(summary, Path(w[1]), quiet=args.quiet, verbose=args.verbose)
        rows.append(summary_row(summary))
        insertions += insertion_rows(summary)
        punctures += puncture_rows(summary)
    if rows:
        write_table(base / "summaries.csv", rows)
        write_table(base / "insertions.csv", insertions)
        write_table(base / "punctures.csv", punctures)
        print(f"batch: {len(rows)} replayed, {failed} failed; combined tables in {base}/: summaries.csv (per "
              "trajectory), insertions.csv (trainee metrics per insertion), punctures.csv (every puncture)")
    return 2 if failed else 0

"""``haptic-acu cohort``: a class's recorded sessions replayed into one table (see :mod:`haptic_acu.cohort.sessions`)."""
from __future__ import annotations

import math
import sys
from pathlib import Path

from ..base.errors import UserError
from ..cohort.update import bounded_jobs, run_cohort, session_points
from .options import add_config_args, config_from_args


def register(sub) -> None:
    p = sub.add_parser("cohort", help="replay a class's sessions: per-insertion skill metrics, learning curves, levels",
                       description="Replay every session listed in MANIFEST.csv (columns session,trainee,file "
                                   "[,level,date,...]) headless and write DIR/insertions.parquet/.csv, "
                                   "DIR/sessions.parquet/.csv, DIR/report.json and figures. A re-run replays only "
                                   "sessions whose file or configuration changed.")
    p.add_argument("manifest", metavar="MANIFEST.csv")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created; a re-run updates it)")
    add_config_args(p)
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                   help="run the replays on this Dask distributed scheduler (workers need haptic-acu and the files)")
    p.add_argument("--scheduler-timeout", type=float, default=60.0, metavar="S",
                   help="give up when the scheduler cannot be reached, no worker has joined, or every worker "
                        "has been lost, for this many seconds (default %(default)s)")
    p.add_argument("--jobs", type=int, default=0,
                   help="local worker processes (default: the usable cores; more than the cores, or than the "
                        "memory holds, are lowered with a note)")
    p.add_argument("--force", action="store_true", help="replay every session, even those up to date")
    p.add_argument("--session-files", action="store_true",
                   help="also write each replayed session's samples.csv, summary.json and force_depth.png "
                        "under DIR/sessions/")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    from ..session.point import add_point_args
    add_point_args(p)  # every session at this point, unless the manifest's `point` column names one
    p.set_defaults(func=run)


def run(args) -> int:
    from ..cohort.sessions import read_manifest
    try:
        manifest = read_manifest(args.manifest)
    except UserError as e:
        for line in getattr(e, "lines", [])[:-1]:
            print(f"haptic-acu cohort: error: {line}", file=sys.stderr)
        raise
    cfg = config_from_args(args)
    if args.jobs < 0:
        raise UserError(f"--jobs must be >= 0, got {args.jobs}")
    if not (math.isfinite(args.scheduler_timeout) and 0 < args.scheduler_timeout <= 86400):
        raise UserError(f"--scheduler-timeout must be a number of seconds in (0, 86400], got {args.scheduler_timeout}")
    from ..base.outputs import Outputs
    from ..cohort.sessions import STATE_DIR
    out = Path(args.out)
    Outputs().input("MANIFEST.csv", manifest.path).input("--config", args.config).folder(
        "--out", out, resumable=STATE_DIR, owner="cohort").check()
    points = session_points(manifest, cfg, args.point, args.patient)  # bad names: one line, before any work
    jobs = args.jobs
    if not args.scheduler:
        jobs, note = bounded_jobs(args.jobs)
        if note:
            print(f"haptic-acu: note: {note}", file=sys.stderr)
    return run_cohort(manifest, out, cfg, jobs=jobs, scheduler=args.scheduler,
                      force=args.force, quiet=args.quiet, session_files=args.session_files,
                      timeout_s=args.scheduler_timeout, points=points)

"""``haptic-acu cohort``: a class's recorded sessions replayed into one table (see :mod:`haptic_acu.cohort.sessions`)."""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from ..base.errors import UserError
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
    p.add_argument("--jobs", type=int, default=0, help="local worker processes (default: the usable cores)")
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
    points = session_points(manifest, cfg, args.point, args.patient)  # bad names: one line, before any work
    return run_cohort(manifest, Path(args.out), cfg, jobs=args.jobs, scheduler=args.scheduler,
                      force=args.force, quiet=args.quiet, session_files=args.session_files, points=points)


def session_points(manifest, cfg, point=None, patient=None) -> dict:
    """session -> (point, patient) text for the sessions graded against a point: the manifest's
    `point` and `patient` columns where they have a value, else ``--point`` and ``--patient``. Each
    is checked now (a bad name or value: one line naming the manifest's line)."""
    from ..session.point import setup
    out = {}
    for e in manifest.entries:
        pt = (e.cells.get("point") or "").strip() or point
        pa = (e.cells.get("patient") or "").strip() or patient
        if pt and pa and pa.strip() == "random":
            raise UserError(f"{manifest.path}: line {e.line}: patient: give random:SEED in a cohort (a session "
                            f"replayed again must meet the same patient)")
        where = f"{manifest.path}: line {e.line}: point"
        try:
            setup(cfg, pt, pa, source=f"{manifest.path}: line {e.line}: patient")
        except UserError as err:
            raise UserError(f"{where}: {err}" if "unknown point" in str(err) else str(err)) from None
        if pt:
            out[e.session] = (pt, pa)
    return out


def run_cohort(manifest, out: Path, cfg, jobs: int = 0, scheduler=None, force: bool = False,
               quiet: bool = False, stream=None, stats: dict | None = None, session_files: bool = False,
               points: dict | None = None) -> int:
    """Run the cohort (see the module); returns the exit status: 0, or 2 when a session failed.
    ``scheduler``: None (local pool), a ``tcp://`` address, or a ``distributed.Client``. ``stats``
    (a dict, optional) receives ``replayed``, ``skipped``, ``replay_s`` (the replays' wall time,
    worker start-up included) and ``total_s``."""
    from ..cohort.run import connect

    stream = stream if stream is not None else sys.stderr
    # reach the cluster before the output folder is made or locked: a wrong address leaves nothing
    client = connect(scheduler) if isinstance(scheduler, str) else scheduler
    try:
        return _run(manifest, out, cfg, jobs, client, force, quiet, stream, stats, session_files, points or {})
    finally:
        if isinstance(scheduler, str):
            client.close()


def _run(manifest, out: Path, cfg, jobs, client, force, quiet, stream, stats, session_files, points) -> int:
    from ..cohort import report as cohort_report, tables as cohort_tables
    from ..cohort.sessions import CohortDir, Job, config_hash, file_sha256, point_hash, record_name, up_to_date
    from ..cohort.run import ProgressLine, run_dask, run_local

    csha = config_hash(cfg)
    records, todo, failed_lines = {}, [], []
    t0 = time.perf_counter()
    fresh = not out.exists()  # made by this run: removed again if every session fails
    with CohortDir(out) as cd:
        for e in manifest.entries:
            try:
                isha = file_sha256(e.path)
            except OSError as err:
                msg = f"{manifest.path}: line {e.line}: session '{e.session}': {e.path}: " + (
                    "trajectory file not found" if isinstance(err, FileNotFoundError) else f"cannot read: {err.strerror}")
                records[e.session] = {"session": e.session, "error": msg, "summary": None, "insertions": [],
                                      "input_sha256": None, "config_sha256": csha}
                failed_lines.append(msg)
                continue
            pt = points.get(e.session)
            csha_s = point_hash(csha, pt)  # a session at a point: its record follows the point and patient too
            rec = cd.load(e.session)
            sdir = (out / "sessions" / record_name(e.session)[:-5]).resolve()
            # asked for the session files: a session replayed earlier without them runs again
            files_ok = not session_files or (sdir / "summary.json").is_file()
            if not force and up_to_date(rec, isha, csha_s) and files_ok:
                records[e.session] = rec
            else:
                todo.append(Job(e.session, str(e.path.resolve()), cfg, isha, csha_s, str(sdir) if session_files else None,
                                *(pt or (None, None))))
        skipped = len(manifest.entries) - len(todo) - len(failed_lines)
        progress = ProgressLine(len(todo), skipped, stream=stream, quiet=quiet)
        for line in failed_lines:
            progress.message(f"haptic-acu cohort: error: {line}")

        line_of = {e.session: e.line for e in manifest.entries}

        def on_result(rec):
            records[rec["session"]] = rec
            if not rec.get("retry"):
                cd.save(rec)
            if rec.get("error"):
                progress.message(f"haptic-acu cohort: error: {manifest.path}: line {line_of[rec['session']]}: "
                                 f"session '{rec['session']}' failed: {rec['error']}")
            progress.update(failed=bool(rec.get("error")))

        t_run = time.perf_counter()
        try:
            if client is None:
                workers = jobs or max(1, len(os.sched_getaffinity(0)))
                run_local(todo, workers, on_result)
                where = f"local, {min(workers, max(1, len(todo)))} process(es)"
            else:
                where = f"dask at {client.scheduler.address}, {sum(client.nthreads().values())} worker thread(s)"
                run_dask(todo, client, on_result)
        finally:
            progress.close()
        run_s = time.perf_counter() - t_run
        if fresh and records and all(r.get("error") for r in records.values()):
            all_failed = True  # nothing to show: the folder this run made goes again
        else:
            all_failed = False
            tables = cohort_tables.write(out, manifest, records)
        if not all_failed:
            ses_rows = tables["sessions"].to_pylist()
            failed = sum(1 for r in ses_rows if r["error"])
            extra = {"manifest": str(manifest.path), "sessions": len(ses_rows), "failed": failed,
                     "insertions": sum(r["insertions"] or 0 for r in ses_rows), "config": cfg.path,
                     "config_sha256": csha, "columns": cohort_tables.columns_doc()}
            report = cohort_report.write_report(out, ses_rows, extra)
            from ..cohort.sessions import write_atomic
            write_atomic(out / "report.json", cohort_tables.dumps(report).encode())
    if all_failed:
        import shutil
        shutil.rmtree(out, ignore_errors=True)
        if not quiet:
            print(f"haptic-acu cohort: every session failed: nothing written (no {out}/ left)", file=stream)
        return 2
    if stats is not None:
        stats.update(replayed=len(todo), skipped=skipped, replay_s=run_s, total_s=time.perf_counter() - t0)
    if not quiet:
        print(f"cohort: {len(ses_rows)} sessions ({len(todo)} replayed in {run_s:.1f} s on {where}, "
              f"{skipped} up to date), {extra['insertions']} insertions, {failed} failed; "
              f"{time.perf_counter() - t0:.1f} s in all", file=stream)
        print(f"  files: {out}/ (insertions, sessions .parquet/.csv; report.json; "
              f"{', '.join(report['figures'].values()) or 'no figure'})", file=stream)
    return 2 if failed else 0

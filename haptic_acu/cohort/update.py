"""A cohort's folder brought up to date (``haptic-acu cohort``): every session of a manifest whose
file or configuration changed since the last run is replayed (on a local pool of processes or a Dask
cluster, :mod:`.run`), its record saved, and the tables, figures and report.json written again
(:mod:`.tables`, :mod:`.report`). Also: the local pool's size (:func:`bounded_jobs`) and each
session's point (:func:`session_points`)."""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from ..base.errors import UserError

WORKER_BYTES = 300 << 20  # a replay worker's resident memory (measured: 4.7 GB for 16 workers)


def _available_bytes() -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def bounded_jobs(jobs: int) -> tuple[int, str | None]:
    """The local pool's size: ``jobs`` (0: one per usable core), at most one per usable core (a replay
    is compute bound: more processes only share the cores, and each takes its memory) and at most as
    many as the available memory holds; a note saying why when ``jobs`` was lowered."""
    cores = max(1, len(os.sched_getaffinity(0)))
    avail = _available_bytes()
    by_mem = max(1, avail // WORKER_BYTES) if avail is not None else cores
    n = min(jobs or cores, cores, by_mem)
    if jobs and n < jobs:
        why = (f"{cores} usable core(s)" if n == cores else
               f"{avail / (1 << 30):.1f} GB of memory available, about {WORKER_BYTES >> 20} MB a worker")
        return n, f"--jobs {jobs} lowered to {n}: {why}"
    if not jobs and n < cores:
        return n, (f"{n} worker(s), not one per core: {avail / (1 << 30):.1f} GB of memory available, about "
                   f"{WORKER_BYTES >> 20} MB a worker")
    return n, None


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


SESSION_FILES = {"samples.csv", "summary.json", "force_depth.png"}


def _drop_stale_session_files(sdir: Path) -> None:
    """Remove a session's files folder an earlier run wrote (only those files in it): the session is
    replayed now, with another configuration or input, without --session-files, so the folder would
    otherwise keep the old results beside the new tables, unmarked."""
    import shutil

    if sdir.is_dir() and not sdir.is_symlink():
        names = {q.name for q in sdir.iterdir()}
        if names and names <= SESSION_FILES:
            shutil.rmtree(sdir, ignore_errors=True)


def run_cohort(manifest, out: Path, cfg, jobs: int = 0, scheduler=None, force: bool = False,
               quiet: bool = False, stream=None, stats: dict | None = None, session_files: bool = False,
               timeout_s: float = 60.0, points: dict | None = None) -> int:
    """Run the cohort (see the module); returns the exit status: 0, or 2 when a session failed.
    ``scheduler``: None (local pool), a ``tcp://`` address, or a ``distributed.Client``. ``stats``
    (a dict, optional) receives ``replayed``, ``skipped``, ``replay_s`` (the replays' wall time,
    worker start-up included) and ``total_s``."""
    from .run import connect

    stream = stream if stream is not None else sys.stderr
    # reach the cluster before the output folder is made or locked: a wrong address leaves nothing
    client = connect(scheduler, timeout_s) if isinstance(scheduler, str) else scheduler
    try:
        return _run(manifest, out, cfg, jobs, client, force, quiet, stream, stats, session_files, timeout_s,
                    points or {})
    finally:
        if isinstance(scheduler, str):
            client.close()


def _run(manifest, out: Path, cfg, jobs, client, force, quiet, stream, stats, session_files, timeout_s,
         points) -> int:
    from . import report as cohort_report, tables as cohort_tables
    from .sessions import CohortDir, Job, config_hash, file_sha256, point_hash, record_name, up_to_date
    from .run import ProgressLine, run_dask, run_local, wait_for_workers

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
                if not session_files:
                    _drop_stale_session_files(sdir)  # replayed anew without them: the old ones are not its
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
                threads = wait_for_workers(client, timeout_s, stream)
                where = f"dask at {client.scheduler.address}, {threads} worker thread(s)"
                run_dask(todo, client, on_result, timeout_s=timeout_s, stream=stream)
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
            from .sessions import write_atomic
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

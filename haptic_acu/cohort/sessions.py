"""Cohort analytics: a class's recorded sessions replayed headless into two tables.

``haptic-acu cohort MANIFEST.csv --out DIR`` (:mod:`haptic_acu.cli.cohort`) reads a manifest
(:func:`read_manifest`), replays every session's trajectory headless in a worker (a local process
pool, or a Dask distributed cluster: :mod:`haptic_acu.cohort.run`), and writes:

* ``DIR/insertions.parquet`` and ``.csv``: one row per insertion (columns: :data:`INSERTION_COLUMNS`),
* ``DIR/sessions.parquet`` and ``.csv``: one row per manifest session (:data:`SESSION_COLUMNS`),
* ``DIR/report.json`` and PNG figures (:mod:`haptic_acu.cohort.report`).

Each row starts with the manifest's own columns, carried through as text. A session that fails
(missing file, bad trajectory, a fault in the replay) has its message in the ``error`` column,
empty metrics, and one line on stderr; the others finish.

Resume. Each finished session's metrics are kept in ``DIR/.cohort/sessions/`` with the SHA-256 of
its input file and of the effective configuration (:func:`config_hash`, which also covers
:data:`METRICS_VERSION`). A re-run replays only sessions whose input or configuration changed or
that have no record yet; the tables are then rebuilt from the records of the manifest's sessions.

A worker replays with the engine's sim clock (:class:`~haptic_acu.session.engine.Session` with only a
:class:`~haptic_acu.session.report.SummarySink`): no ``samples.csv``, ``.rrd`` or figure per session, unless
asked (``--session-files``: ``DIR/sessions/<name>/`` gets the replay's ``samples.csv``,
``summary.json`` and ``force_depth.png``).
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import hashlib
import json
import math
import os
import re
import shutil
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..base.errors import UserError
from ..base.outputs import FolderLock

# Bump when a metric's definition changes: every cached session is then replayed again.
METRICS_VERSION = 4  # 4: one name per quantity (analysis/quantities.py), bone and force-limit times
REQUIRED = ("session", "trainee", "file")
OPTIONAL = ("level", "date")
STATE_DIR = ".cohort"
# The thrust phase of an insertion ends at its first tick within this much of its largest depth.
REACH_TOL_MM = 0.2


# ---- the tables' columns ---------------------------------------------------------------------
@dataclass(frozen=True)
class Column:
    """One metric column: its name, unit ("1" for dimensionless, "" for text/counts), meaning and
    the function computing it from an :class:`InsertionContext` (insertion table) ."""

    name: str
    unit: str
    description: str
    get: Callable | None = None
    dtype: str = "float64"  # "float64", "int64", "bool" or "string"


@dataclass
class InsertionContext:
    """What a column function sees: ``m`` the insertion's dict from
    :func:`haptic_acu.analysis.metrics.insertion_metrics`; the session's times ``t`` (s), raw tip positions
    ``p`` (m) and low-passed positions ``ps`` (m); the insertion's window ``w`` (entry tick ..
    last tick inside, a slice of those arrays) and ``k_reach`` (the row where the thrust ends: the
    first tick within :data:`REACH_TOL_MM` of the insertion's largest depth);
    the config ``cfg`` and ``rows`` (the session's sample rows, :mod:`haptic_acu.servo.samples`)."""

    m: dict
    t: np.ndarray
    p: np.ndarray
    ps: np.ndarray
    w: slice
    k_reach: int
    cfg: object
    rows: np.ndarray | None
    skill: dict | None = None  # path, economy, ldlj, duration already computed (pathstream.path_columns)


def _depth_error(c: InsertionContext):
    lo, hi = (float(v) for v in c.cfg.scene.target_depth_mm)
    d = c.m["max_depth_mm"]
    return 0.0 if lo <= d <= hi else (d - hi if d > hi else d - lo)


def _skill(name):
    from ..analysis import skill_metrics as sm

    def path_mm(c):
        if c.skill is not None:
            return c.skill["path"]
        return sm.path_length(c.ps[c.w]) * 1e3

    def economy(c):
        if c.skill is not None:
            return c.skill["economy"]
        return sm.economy_of_motion(c.ps[c.w.start:c.k_reach + 1])

    def ldlj(c):
        if c.skill is not None:
            return c.skill["ldlj"]
        thrust = slice(c.w.start, c.k_reach + 1)
        return sm.ldlj(c.t[thrust], c.ps[thrust])

    return {"path": path_mm, "economy": economy, "ldlj": ldlj}[name]


def _lt(key):
    return lambda c: c.m["lift_thrust"][key]


def _tech(part, key):
    """A technique metric (:mod:`haptic_acu.analysis.technique`, metrics.py ``technique``), None if absent."""
    def get(c):
        d = c.m["technique"][part]
        return None if d is None else d[key]
    return get


def _min_margin(c):
    m = [v for v in (c.m.get("danger_margin_mm") or {}).values() if v is not None]
    return min(m) if m else None


def _critical(c, f):
    e = c.m.get("critical_errors")
    return None if e is None else f(e)


# One entry per column of insertions.parquet after the manifest's columns and `insertion`. Add a
# metric (e.g. twirling) by adding one Column here; sessions.parquet gets its mean automatically.
INSERTION_COLUMNS: list[Column] = [
    Column("t_entry_s", "s", "session time the tip first pressed the intact skin for this insertion (or re-entered)",
           lambda c: c.m["t_entry_s"]),
    Column("duration_s", "s", "from the entry tick to the last tick with the skin punctured",
           lambda c: c.skill["duration"] if c.skill is not None else float(c.t[c.w.stop - 1] - c.t[c.w.start])),
    Column("path_length_mm", "mm", "length of the tip's path over the insertion (low-passed positions)",
           _skill("path")),
    Column("economy_of_motion", "1", "thrust phase (entry -> depth reached): straight-line distance over path "
           "length (1 = straight, no back-and-forth)", _skill("economy")),
    Column("ldlj", "1", "thrust phase: log dimensionless jerk of the tip speed (Balasubramanian et al. 2015; "
           "closer to 0 = smoother)", _skill("ldlj")),
    Column("entry_offset_mm", "mm", "distance of the entry point from the acupoint", lambda c: c.m["entry_offset_mm"]),
    Column("angle_deg", "deg", "angle between the insertion direction and the inward skin normal at the entry",
           lambda c: c.m["angle_deg"]),
    Column("max_depth_mm", "mm", "the needle's largest depth in the tissue, along it from the skin entry",
           lambda c: c.m["max_depth_mm"]),
    Column("depth_error_mm", "mm", "signed distance of max_depth_mm from the target range "
           "(0 inside, negative too shallow, positive too deep)", _depth_error),
    Column("insertion_speed_mm_s", "mm/s", "mean axial speed from the puncture to 90% of the max depth",
           lambda c: c.m["insertion_speed_mm_s"]),
    Column("time_to_target_s", "s", "entry tick to the first tick at the target's lower bound",
           lambda c: c.m["time_to_target_s"]),
    Column("peak_force_skin_n", "N", "largest force attributed to the skin", lambda c: c.m["peak_layer_force_n"]["skin"]),
    Column("peak_force_fat_n", "N", "largest force attributed to the fat", lambda c: c.m["peak_layer_force_n"]["fat"]),
    Column("peak_force_muscle_n", "N", "largest force attributed to the muscle",
           lambda c: c.m["peak_layer_force_n"]["muscle"]),
    Column("peak_total_force_n", "N", "largest |F| over the insertion", lambda c: c.m["peak_total_force_n"]),
    Column("time_on_bone_s", "s", "time with the tip in bone", lambda c: c.m["time_on_bone_s"]),
    Column("time_at_force_limit_s", "s", "time with the force held at the device's limit (safety.force_limit_n)",
           lambda c: c.m["time_at_force_limit_s"]),
    Column("lateral_time_s", "s", "time with the lateral-constraint force above the comfort bound",
           lambda c: c.m["lateral"]["time_over_s"]),
    Column("lateral_max_n", "N", "largest lateral-constraint force", lambda c: c.m["lateral"]["max_n"]),
    Column("lift_thrust_cycles", "", "lift-thrust cycles at depth", _lt("cycles"), "int64"),
    Column("lift_thrust_amplitude_mm", "mm", "mean lift-thrust stroke", _lt("mean_amplitude_mm")),
    Column("lift_thrust_frequency_hz", "Hz", "lift-thrust frequency", _lt("frequency_hz")),
    Column("twirl_cycles", "", "twirling cycles (roll reversals with 5 deg hysteresis)", _tech("twirl", "cycles"), "int64"),
    Column("twirl_swing_deg", "deg", "twirl swing, peak to peak: the mean angle between roll reversals",
           _tech("twirl", "swing_deg")),
    Column("twirl_frequency_hz", "Hz", "twirling frequency", _tech("twirl", "frequency_hz")),
    Column("twirl_net_rotation_deg", "deg", "roll at the insertion's end minus at its start",
           _tech("twirl", "net_rotation_deg")),
    Column("twirl_peak_torque_nmm", "N*mm", "largest twist torque about the needle axis",
           _tech("twirl", "peak_torque_nmm")),
    Column("thrust_to_lift", "1", "mean thrust resistance over mean lift resistance of the lift-thrust strokes",
           _tech("lift_thrust_forces", "thrust_to_lift")),
    Column("grasp_felt_ratio", "1", "needle grasp: peak withdrawal resistance over the same replay's without "
           "rotation (1: no grasp)", _tech("grasp_felt", "peak_ratio")),
    Column("technique", "", "\"reinforcing\", \"reducing\" or \"even\" (textbook rule, docs/model.md), empty "
           "without twirling or lift-thrust", _tech("classification", "label"), "string"),
    Column("skin_punctured", "", "the insertion broke intact skin (false: re-entry through a hole)",
           lambda c: c.m["skin_punctured"], "bool"),
    Column("depth_verdict", "", "\"in range\", \"too shallow\" or \"too deep\"", lambda c: c.m["depth_verdict"], "string"),
    # graded against an atlas point (--point or the manifest's `point`; empty without one: docs/atlas.md)
    Column("angle_error_deg", "deg", "angle between the insertion direction and the point's prescribed direction",
           lambda c: c.m.get("angle_error_deg")),
    Column("danger_margin_min_mm", "mm", "smallest distance from the tip to any danger structure of the point "
           "(negative: past it)", _min_margin),
    Column("critical_errors", "", "danger structures the tip reached", lambda c: _critical(c, len), "int64"),
    Column("critical_structures", "", "their names, space-separated",
           lambda c: _critical(c, lambda e: " ".join(x["structure"].replace(" ", "_") for x in e)), "string"),
]

# sessions.parquet: after the manifest's columns. Then `mean_<name>` for every numeric insertion
# column (the mean over the session's insertions), then the hashes.
SESSION_COLUMNS: list[Column] = [
    Column("error", "", "why the session failed (empty when it did not)", dtype="string"),
    Column("insertions", "", "insertions (runs with the skin punctured)", dtype="int64"),
    Column("skin_punctures", "", "insertions that broke intact skin", dtype="int64"),
    Column("session_duration_s", "s", "the replayed session's length"),
    Column("time_in_tissue_s", "s", "time with the skin punctured"),
    Column("max_force_n", "N", "largest |F| over the session"),
    Column("max_tip_depth_mm", "mm", "deepest tip point below the rest skin surface"),
    Column("lateral_time_s", "s", "time with the lateral force above the comfort bound, summed over insertions"),
    Column("graded_point", "", "the atlas point the session was graded against (empty: none)", dtype="string"),
    Column("graded_patient", "", "its patient (--patient text; empty: the default)", dtype="string"),
]
HASH_COLUMNS: list[Column] = [
    Column("input_sha256", "", "SHA-256 of the trajectory file replayed", dtype="string"),
    Column("config_sha256", "", "SHA-256 of the effective configuration and metrics version", dtype="string"),
]


def mean_columns() -> list[Column]:
    return [Column(f"mean_{c.name}", c.unit, f"mean over the session's insertions of {c.name}")
            for c in INSERTION_COLUMNS if c.dtype in ("float64", "int64")]


def output_column_names() -> set[str]:
    names = {"insertion"} | {c.name for c in INSERTION_COLUMNS} | {c.name for c in SESSION_COLUMNS}
    return names | {c.name for c in mean_columns()} | {c.name for c in HASH_COLUMNS}


# ---- the manifest ----------------------------------------------------------------------------
@dataclass
class Entry:
    """One manifest row: its line number, the manifest's cells (text), and the resolved file."""

    line: int
    cells: dict
    path: Path

    @property
    def session(self) -> str:
        return self.cells["session"]


@dataclass
class Manifest:
    path: Path
    columns: list[str]
    entries: list[Entry] = field(default_factory=list)


class ManifestError(UserError):
    """Bad manifest: ``lines`` holds one message per problem (the CLI prints every one)."""

    def __init__(self, lines: list[str]):
        super().__init__(lines[-1])
        self.lines = lines


def _parse_date(text: str):
    """An ISO date or date-time as a naive UTC datetime, or None. A time with a zone (``+02:00``,
    ``Z``) is converted to UTC; one without a zone is read as UTC (docs/cohort.md), so dates with and
    without zones sort on one time line."""
    try:
        d = _dt.datetime.fromisoformat(text)
    except ValueError:
        return None
    if d.tzinfo is not None:
        d = d.astimezone(_dt.timezone.utc).replace(tzinfo=None)
    return d


def read_manifest(path) -> Manifest:
    """Read and check a manifest CSV (see the module). Raises :class:`ManifestError` listing every
    bad row (missing column, unknown or clashing column, row of the wrong width, empty required
    cell, duplicate session, unparseable date). Missing trajectory files are not checked here:
    such a session fails alone at run time."""
    from ..base.csvin import iter_lines, split_row

    path = Path(path)
    lines = ((n, text) for n, text in iter_lines(path, "manifest"))
    header = None
    for n, text in lines:  # the header: the first line (blank lines before it skipped)
        if text.strip():
            header = split_row(path, text, n)
            break
    if not header or not any(h.strip() for h in header):
        raise UserError(f"{path}: line 1: empty manifest (expected a header {','.join(REQUIRED)},...)")
    header = [h.strip() for h in header]
    problems = []
    taken = output_column_names()
    for i, h in enumerate(header):
        if not h:
            problems.append(f"{path}: line 1: column {i + 1} has no name")
        elif header.index(h) != i:
            problems.append(f"{path}: line 1: column '{h}' appears twice")
        elif h in taken:
            problems.append(f"{path}: line 1: unknown column '{h}' clashes with an output column of that name")
    for r in REQUIRED:
        if r not in header:
            problems.append(f"{path}: line 1: missing column '{r}' (required: {', '.join(REQUIRED)})")
    if problems:
        raise ManifestError(problems)
    m = Manifest(path=path, columns=header)
    seen: dict[str, int] = {}
    base = path.resolve().parent
    for start, text in lines:
        row = split_row(path, text, start)  # an unclosed quote: one line naming it, not the rows after
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            extra = " (unknown column: a cell beyond the header)" if len(row) > len(header) else ""
            problems.append(f"{path}: line {start}: {len(row)} fields, the header has {len(header)}{extra}")
            continue
        cells = {h: c.strip() for h, c in zip(header, row)}
        bad = [r for r in REQUIRED if not cells[r]]
        if bad:
            problems.append(f"{path}: line {start}: empty '{bad[0]}'")
            continue
        s = cells["session"]
        if s in seen:
            problems.append(f"{path}: line {start}: duplicate session '{s}' (first on line {seen[s]})")
            continue
        seen[s] = start
        if cells.get("date") and _parse_date(cells["date"]) is None:
            problems.append(f"{path}: line {start}: date '{cells['date']}' is not an ISO date (YYYY-MM-DD[THH:MM])")
            continue
        f = Path(cells["file"]).expanduser()
        f = f if f.is_absolute() else base / f
        if not f.exists():  # a bundled trajectory's name (every other command takes them)
            from ..base.bundled import resolve_trajectory
            b = resolve_trajectory(cells["file"])
            f = b if b.is_file() and b != Path(cells["file"]) else f
        m.entries.append(Entry(start, cells, f))
    if problems:
        raise ManifestError(problems)
    if not m.entries:
        raise UserError(f"{path}: the manifest lists no session")
    return m


# ---- hashes and the per-session records ------------------------------------------------------
def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def config_hash(cfg) -> str:
    """SHA-256 of the configuration's values (not its file name), the skin-coefficient file's bytes
    if it has one, the metrics' version and the smoothing cutoff."""
    from ..analysis.skill_metrics import DEFAULT_CUTOFF_HZ

    d = dataclasses.asdict(cfg)
    d.pop("path", None)
    coeff = d.get("body", {}).get("skin_coefficients")
    if coeff:
        d["body"]["skin_coefficients"] = file_sha256(Path(coeff))
    d["_metrics_version"] = METRICS_VERSION
    d["_cutoff_hz"] = DEFAULT_CUTOFF_HZ
    return hashlib.sha256(json.dumps(d, sort_keys=True, default=list).encode()).hexdigest()


def point_hash(csha: str, point) -> str:
    """The configuration hash of a session at an atlas point ((point, patient) text; None: ``csha``
    itself): the point file's bytes and the patient join the configuration's."""
    if not point:
        return csha
    from ..tissue.atlas import load_point
    pt, pa = point
    data = Path(load_point(pt).path).read_bytes()
    return hashlib.sha256(csha.encode() + b"\0" + data + b"\0" + (pa or "").encode()).hexdigest()


def record_name(session: str) -> str:
    """A file name for a session id: its safe characters plus a short hash (ids may hold anything)."""
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", session)[:60]
    return f"{safe}-{hashlib.sha256(session.encode()).hexdigest()[:12]}.json"


def write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


# ---- one session: runs in a worker -----------------------------------------------------------
@dataclass(frozen=True)
class Job:
    session: str
    file: str  # absolute path, readable by the worker
    cfg: object  # TissueConfig
    input_sha256: str
    config_sha256: str
    session_dir: str | None = None  # also write the replay's samples.csv, summary.json, force_depth.png here
    point: str | None = None  # --point / the manifest's `point`: the session at that atlas point, graded
    patient: str | None = None  # its patient (--patient text)


_TISSUE: dict = {}  # config hash -> Tissue (a worker builds it once, not per session)
_TISSUE_LOCK = threading.Lock()  # a worker's threads run sessions side by side: one builds, the rest wait


def _tissue(job: Job, cfg=None):
    from ..tissue.body import Tissue

    with _TISSUE_LOCK:
        t = _TISSUE.get(job.config_sha256)
        if t is None:
            _TISSUE.clear()
            t = _TISSUE[job.config_sha256] = Tissue.from_config(cfg if cfg is not None else job.cfg)
    return t


def _num(v):
    if v is None or isinstance(v, (bool, str)):
        return v
    v = float(v)
    return round(v, 9) + 0.0 if math.isfinite(v) else None


def insertion_table(rows: np.ndarray, cfg, tissue=None, reference_rows=None) -> tuple[dict, list[dict]]:
    """(session metrics, one dict per insertion with every :data:`INSERTION_COLUMNS` value) from a
    session's sample rows; ``reference_rows``: the same replay without rotation (the grasp felt)."""
    from ..analysis.metrics import session_metrics
    from ..session.pathstream import TRACK_COLUMNS
    from ..servo.samples import COL

    sm = session_metrics(rows, cfg, tissue, reference_rows=reference_rows)
    track = rows[:, [COL[name] for name in TRACK_COLUMNS]]
    return sm, insertion_rows(sm, track, cfg)


def insertion_rows(sm: dict, track: np.ndarray, cfg) -> list[dict]:
    """The :data:`INSERTION_COLUMNS` of each insertion of ``sm`` (its session metrics) from the
    session's ``track``: per row t_s, x, y, z (m), state_skin, depth_skin_m (the columns of
    :class:`haptic_acu.session.pathstream.TrackFile`)."""
    from ..analysis.metrics import entry_tick, insertion_runs
    from ..session.pathstream import TCOL
    from ..analysis.skill_metrics import smooth_path

    t = track[:, TCOL["t_s"]]
    p = track[:, TCOL["x_m"]:TCOL["x_m"] + 3]
    ps = smooth_path(t, p)
    state = track[:, TCOL["state_skin"]]
    depth = track[:, TCOL["depth_skin_m"]]
    out = []
    for (a, b), m in zip(insertion_runs(state), sm["per_insertion"]):
        e = entry_tick(state, a)
        d = depth[a:b + 1]
        k_reach = a + int(np.argmax(d >= d.max() - REACH_TOL_MM * 1e-3))
        ctx = InsertionContext(m=m, t=t, p=p, ps=ps, w=slice(e, b + 1), k_reach=k_reach, cfg=cfg, rows=None)
        out.append({c.name: _num(c.get(ctx)) for c in INSERTION_COLUMNS})
    return out


def streamed_insertion_rows(sm: dict, track, cfg) -> list[dict]:
    """:func:`insertion_rows` from a :class:`haptic_acu.session.pathstream.TrackFile` (the rows on disk):
    the same values, to the bit, in bounded memory (:func:`haptic_acu.session.pathstream.path_columns`)."""
    from ..session.pathstream import path_columns
    from ..analysis.skill_metrics import DEFAULT_CUTOFF_HZ

    skill = path_columns(track, DEFAULT_CUTOFF_HZ, REACH_TOL_MM * 1e-3)
    out = []
    for m, sk in zip(sm["per_insertion"], skill):
        ctx = InsertionContext(m=m, t=None, p=None, ps=None, w=slice(0, 0), k_reach=0, cfg=cfg, rows=None, skill=sk)
        out.append({c.name: _num(c.get(ctx)) for c in INSERTION_COLUMNS})
    return out


class Interrupted(UserError):
    """The replay stopped early (a signal): its record is not kept, the session runs again."""


def replay_session(job: Job) -> dict:
    """Replay one session headless and return its record (JSON-ready): ``session``, the hashes,
    ``error`` (None) or the failure's one-line message, ``summary`` (session-level values) and
    ``insertions`` (list of dicts); ``retry`` (True) on a record not to keep. Never raises for a bad session: the message goes in ``error``."""
    rec = {"session": job.session, "file": job.file, "input_sha256": job.input_sha256,
           "config_sha256": job.config_sha256, "metrics_version": METRICS_VERSION,
           "error": None, "summary": None, "insertions": []}
    try:
        rec.update(_replay(job))
    except Interrupted as e:
        rec["error"], rec["retry"] = str(e), True
    except UserError as e:
        rec["error"] = str(e)
    except Exception as e:  # a bug or a fault in one session must not stop the cohort
        rec["error"] = f"{job.file}: {type(e).__name__}: {e}"
    return rec


def replay_batch(jobs: list[Job]) -> list[dict]:
    """:func:`replay_session` on each job in turn (one Dask task; the jobs' shared configuration is
    sent once with the batch)."""
    return [replay_session(job) for job in jobs]


def _replay(job: Job) -> dict:
    from haptic_acu.devices.scripted import ScriptedDevice

    from ..session.engine import Session
    from ..servo.step import NeedleModel
    from ..session.report import SummarySink

    cfg = job.cfg
    ps = None
    if job.point:  # the session at an atlas point: its tissue, structures and grading
        from ..session.point import GradeSink, setup
        ps = setup(cfg, job.point, job.patient)
        cfg = ps.cfg
    device = ScriptedDevice(job.file, max_hand_speed_m_per_s=cfg.scene.max_hand_speed_m_per_s,
                            realtime=False, force_limit_n=cfg.safety.force_limit_n)
    device.open()
    tissue = _tissue(job, cfg)
    reference = None
    if device.has_roll:  # the grasp felt: the same replay without rotation (its ticks and forces)
        from ..session.replay import reference_forces
        reference = reference_forces(job.file, cfg)
    # nothing below keeps whole rows: the metrics are streamed, the figure gets a bounded envelope
    sink = _summary_sink(cfg, reference, figure=bool(job.session_dir))
    from ..session.pathstream import TrackFile
    track = TrackFile()  # t, x, y, z, state, depth per row: on disk, for the path columns
    sinks = [sink, track]
    grade = None
    if ps is not None:
        grade = GradeSink(ps)
        sinks.append(grade)
    partial = None
    if job.session_dir:
        from ..session.report import SamplesCsvSink

        partial = Path(job.session_dir + ".partial")
        shutil.rmtree(partial, ignore_errors=True)
        partial.mkdir(parents=True)
        sinks.append(SamplesCsvSink(partial / "samples.csv"))
    try:
        model = ps.model(tissue) if ps is not None else NeedleModel(cfg, tissue)
        session = Session(cfg, device, sinks, clock="sim", model=model)
        session.warm_up()
        result = session.run()
        device.close()
        if result.fault:
            return {"error": f"{job.file}: replay stopped: {result.fault}"}
        if result.duration_s < device.duration_s - 0.01:
            raise Interrupted(f"{job.file}: replay interrupted at {result.duration_s:.3f} s of {device.duration_s:.3f} s")
        summary = sink.summary()
        sm = sink.metrics(summary["punctures"])
        if ps is not None:  # each insertion's grading against the point joins its metrics
            from ..session.point import MERGED, add_to_summary
            graded = grade.result()
            for ins, g in zip(sm["per_insertion"], graded):
                ins.update({k: g[k] for k in MERGED})
            summary["metrics"] = sm
            add_to_summary(summary, ps, graded)
        insertions = streamed_insertion_rows(sm, track, cfg)
        if partial is not None:
            _session_files(partial, Path(job.session_dir), summary, sm, sink.figure_rows(), tissue, job)
    finally:
        track.release()
        if partial is not None:
            shutil.rmtree(partial, ignore_errors=True)
    return {"summary": {
        "insertions": sm["insertions"], "skin_punctures": sm["skin_punctures"],
        "session_duration_s": summary["duration_s"], "time_in_tissue_s": sm["time_in_tissue_s"],
        "max_force_n": summary["max_force_n"], "max_tip_depth_mm": summary["max_tip_depth_mm"],
        "lateral_time_s": sm["lateral"]["time_over_s"], "graded_point": job.point or "",
        "graded_patient": job.patient or ""},
        "insertions": insertions}


def _summary_sink(cfg, reference, figure: bool):
    """A SummarySink without rows (streamed metrics); without the figure's envelope (FigureRows, up
    to 12 MB) unless a figure is drawn (``--session-files``)."""
    from ..session.report import SummarySink

    class NoFigure(SummarySink):
        def start(self, info: dict) -> None:
            super().start(info)
            self.figure = None

    return (SummarySink if figure else NoFigure)(cfg, keep_rows=False, reference_rows=reference)


def _session_files(partial: Path, final: Path, summary: dict, sm: dict, figure, tissue, job: Job) -> None:
    """The replay's own files for one session (``--session-files``), renamed into place when whole."""
    from ..session.report import plot_force_depth

    summary = dict(summary, trajectory=Path(job.file).name, metrics=sm)
    (partial / "summary.json").write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")
    rows, index = figure  # SummarySink.figure_rows(): every row up to FigureRows' cap, then an envelope
    plot_force_depth(rows, partial / "force_depth.png", tissue, title=job.session, index=index)
    if final.exists():
        shutil.rmtree(final)  # this session's files from an earlier run of this cohort
    os.replace(partial, final)


# ---- the output folder -----------------------------------------------------------------------
class CohortDir:
    """The output folder: its records (``.cohort/sessions/*.json``) and a lock so two runs never
    write it at once. Refuses a non-empty folder that is not a cohort's output."""

    def __init__(self, out: Path):
        self.out = Path(out)
        self.state = self.out / STATE_DIR
        self.records = self.state / "sessions"
        self._locked = False

    def open(self) -> None:
        if self.out.exists() and not self.out.is_dir():
            raise UserError(f"{self.out}: output path exists and is not a folder")
        if self.out.is_dir() and any(self.out.iterdir()) and not self.state.is_dir():
            raise UserError(f"{self.out}: folder exists, is not empty and is not a cohort output; "
                            f"choose another --out")
        self.records.mkdir(parents=True, exist_ok=True)
        # an flock, not a pid file: the kernel drops it when the run dies, so of two runs taking over
        # a dead run's folder exactly one gets it
        self._lock = FolderLock(self.state / "lock", f"{self.out}: another cohort run{{holder}} is "
                                                      "writing this folder").acquire()
        self._locked = True

    def close(self) -> None:
        if self._locked:
            self._lock.release()
            self._locked = False

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc):
        self.close()

    def load(self, session: str) -> dict | None:
        try:
            return json.loads((self.records / record_name(session)).read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return None

    def save(self, rec: dict) -> None:
        write_atomic(self.records / record_name(rec["session"]),
                     (json.dumps(rec, sort_keys=True, indent=1) + "\n").encode())


def up_to_date(rec: dict | None, input_sha: str | None, config_sha: str) -> bool:
    return (rec is not None and input_sha is not None and rec.get("input_sha256") == input_sha
            and rec.get("config_sha256") == config_sha and rec.get("metrics_version") == METRICS_VERSION)

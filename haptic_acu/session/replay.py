"""Headless replay of recorded needle trajectories: the project's main job.

:func:`replay_one` plays one trajectory file through a :class:`~haptic_acu.session.engine.Session` on
simulated time (servo ticks at exactly 1 ms, a visual frame every 1/60 s: the same kernels and the
same visual-frame code as a live session) and writes, into one output folder:

* ``samples.csv``     one row per servo tick,
* ``summary.json``    punctures, peaks, depths, per-layer time and peak force, session metrics,
* ``force_depth.png`` force against depth (layers shaded, punctures marked) and against time,
* ``debrief.md``      the debrief: per insertion what was right and wrong, worst first
  (:mod:`haptic_acu.analysis.debrief`; also in summary.json as ``debrief``),
* ``recording.rrd``   the rerun recording (unless ``rrd=False``).

The folder is built as ``<out>.partial`` and renamed only when everything is written, so a failed
replay never leaves a folder that looks complete. Identical input gives byte-identical files.
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path

from ..base.bundled import bundled_dir
from ..base.config import load_config
from ..base.errors import UserError
from .sink import Sink, block_rows

BUNDLED_DIR = bundled_dir("trajectories")
DEFAULT_TRAJECTORY = BUNDLED_DIR / "default.csv"
MAX_REPLAY_DURATION_S = 4 * 3600.0  # a longer file is refused (split it)
MARKER = ".haptic-acu-replay"  # in every DIR.partial a replay makes: the folder is ours
OUR_FILES = {MARKER, "samples.csv", "summary.json", "force_depth.png", "recording.rrd", "compare.json",
             "compare.png", "debrief.md"}


class OutputFolder:
    """One replay's output folder, exclusive and atomic.

    :meth:`claim` builds ``DIR.partial`` as a fresh hidden folder beside ``DIR``, takes an exclusive
    ``flock`` on it, marks it as ours and renames it into place; a second replay to the same ``DIR``
    finds it locked and is refused. A ``DIR.partial`` left by a replay that died (marked, unlocked,
    holding only replay files) is replaced; any other existing ``DIR.partial`` (a user's files) is
    never touched: refused. :meth:`publish` renames ``DIR.partial`` to ``DIR`` (which must not exist
    or be an empty folder: a folder is never mixed). :meth:`discard` removes our ``DIR.partial``;
    :meth:`abandon` leaves it (an interrupted replay); :meth:`release` drops the lock.
    """

    def __init__(self, out_dir: Path):
        self.out = Path(out_dir)
        self.partial = self.out.with_name(self.out.name + ".partial")
        self._fd: int | None = None
        self._claimed = False
        self._keep = False

    def _check_out(self) -> None:
        if self.out.is_dir():
            if any(self.out.iterdir()):
                raise UserError(f"{self.out}: output folder exists and is not empty")
        elif self.out.exists() or self.out.is_symlink():
            raise UserError(f"{self.out}: exists and is not a folder; choose another --out")

    def claim(self) -> Path:
        self._check_out()
        parent = self.out.parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
            tmp = Path(tempfile.mkdtemp(prefix=f".{self.out.name}.", suffix=".tmp", dir=parent))
        except OSError as e:
            raise UserError(f"{self.out}: cannot create the output folder: "
                            f"{e.strerror or e}") from None
        try:
            self._fd = os.open(tmp, os.O_RDONLY | os.O_DIRECTORY)
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            (tmp / MARKER).write_text(f"pid {os.getpid()}\n")
            for _ in range(2):
                try:
                    os.rename(tmp, self.partial)  # fails if DIR.partial exists and is not empty
                    break
                except OSError as e:
                    if e.errno not in (errno.ENOTEMPTY, errno.EEXIST, errno.ENOTDIR):
                        raise
                    self._remove_stale()
            else:
                raise UserError(f"{self.partial}: another replay is writing to {self.out}")
        except BaseException as e:
            shutil.rmtree(tmp, ignore_errors=True)
            self.release()
            if isinstance(e, OSError):
                raise UserError(f"{self.out}: cannot create the output folder: "
                                f"{e.strerror or e}") from None
            raise
        self._claimed = True
        return self.partial

    def _remove_stale(self) -> None:
        """Remove a DIR.partial left by a replay that died, or refuse (one line)."""
        p = self.partial
        if not p.is_dir() or p.is_symlink():
            raise UserError(f"{p}: exists and is not a replay's folder; move it away or choose "
                            "another --out")
        fd = os.open(p, os.O_RDONLY | os.O_DIRECTORY)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise UserError(f"{p}: another replay is writing to {self.out} (its folder is "
                                "locked); wait for it or choose another --out") from None
            names = {q.name for q in p.iterdir()}
            if MARKER not in names or not names <= OUR_FILES or any(
                    not (p / n).is_file() or (p / n).is_symlink() for n in names):
                raise UserError(f"{p}: exists and holds files a replay did not write; move them "
                                "away or choose another --out")
            shutil.rmtree(p)
        finally:
            os.close(fd)

    def publish(self) -> None:
        self._check_out()
        try:
            os.rename(self.partial, self.out)  # replaces an empty folder, never a full one
        except OSError as e:
            if e.errno in (errno.ENOTEMPTY, errno.EEXIST):
                self._keep = True
                raise UserError(f"{self.out}: appeared while this replay ran; its files stay in "
                                f"{self.partial}/") from None
            raise
        (self.out / MARKER).unlink(missing_ok=True)
        self._claimed = False

    def abandon(self) -> None:
        self._keep = True

    def discard(self) -> None:
        if self._claimed and not self._keep:
            shutil.rmtree(self.partial, ignore_errors=True)
            self._claimed = False

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    @contextlib.contextmanager
    def writing(self, what: str):
        """:meth:`claim` ``DIR.partial`` and yield it; :meth:`publish` it when the block ends,
        :meth:`discard` it on an error (an OSError: one line naming ``DIR`` and ``what``), and
        :meth:`release` the lock whatever happens."""
        partial = self.claim()
        try:
            yield partial
            self.publish()
        except OSError as e:
            self.discard()
            raise UserError(f"{self.out}: cannot write {what}: {e.strerror or e}") from None
        except BaseException:
            self.discard()
            raise
        finally:
            self.release()


class Progress(Sink):
    """A percentage on stderr (a sink: called per visual frame): rewritten in place on a terminal;
    elsewhere (a pipe, a log) a plain line every 25 %, once the replay has taken over a second."""

    rows_only = True  # the rows (and the frame's time) only

    def __init__(self, label: str, duration_s: float, stream=None):
        from ..base import progress
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.enabled = duration_s > 0 and not progress.quiet
        self.label = label
        self.duration_s = duration_s
        self._last = -1
        self._wall0 = time.perf_counter()

    def on_frames(self, frames) -> None:
        if len(frames):  # the percentage reached
            self.on_frame(frames[-1])

    def on_frame(self, frame) -> None:
        if not self.enabled:
            return
        pct = int(100 * min(1.0, frame.t_s / self.duration_s))
        if pct == self._last:
            return
        if self.tty:
            self._last = pct
            self.stream.write(f"\r{self.label}: {pct:3d}%")
            self.stream.flush()
        elif pct // 25 > max(self._last, 0) // 25 and time.perf_counter() - self._wall0 > 1.0:
            self._last = pct
            self.stream.write(f"haptic-acu: replaying {self.label}: {pct}%\n")
            self.stream.flush()

    def close(self, result) -> None:
        if self.enabled and self.tty:
            self.stream.write("\r" + " " * (len(self.label) + 6) + "\r")
            self.stream.flush()


class _IOErrors:
    """Remembers the first OSError a file-writing sink raised (the engine reports it as a fault;
    a replay reports it as what it is: the output could not be written)."""

    def __init__(self):
        self.error: str | None = None

    def guard(self, sink: Sink) -> Sink:
        return _Guarded(sink, self)

    def remember(self, e: OSError) -> None:
        if self.error is None:
            self.error = f"{e.filename + ': ' if e.filename else ''}{e.strerror or e}"


class _Guarded(Sink):
    """``sink`` with the first OSError of its start, on_frame or close remembered by ``errors``
    (then raised on, for the engine to report as the session's fault)."""

    def __init__(self, sink: Sink, errors: _IOErrors):
        self.sink = sink
        self.errors = errors
        self.rows_only = sink.rows_only

    def warm_up(self) -> None:
        self.sink.warm_up()

    def pin(self, cores) -> bool:
        return self.sink.pin(cores)

    def start(self, info: dict) -> None:
        self._call(self.sink.start, info)

    def on_frame(self, frame) -> None:
        self._call(self.sink.on_frame, frame)

    def on_frames(self, frames) -> None:
        self._call(self.sink.on_frames, frames)

    def close(self, result=None) -> None:
        self._call(self.sink.close, result)

    def _call(self, method, arg) -> None:
        try:
            method(arg)
        except OSError as e:
            self.errors.remember(e)
            raise


def check_start(trajectory, tissue) -> None:
    """Refuse (one line) a trajectory whose first sample is inside the tissue: a session starts with
    the needle in the air (the tissue is intact until the tip touches it)."""
    from .trajectory import TrajectoryReader

    first = next(iter(TrajectoryReader(trajectory, max_hand_speed_m_per_s=1e9).blocks(1 << 12)), None)
    if first is None:
        return
    layer, _ = tissue.locate(first.pos_m[0])
    if layer >= 0:
        from ..analysis.scan import tip_depth_m
        from ..tissue.layers import PLACE_NAMES

        depth = float(tip_depth_m(first.pos_m[:1], tissue)[0]) * 1e3
        raise UserError(f"{trajectory}: line {int(first.line[0])}: the tip starts inside the tissue "
                        f"({PLACE_NAMES[layer + 1]}, "
                        f"{depth:.3g} mm below the skin); a trajectory starts in the air above the skin (is "
                        "z_mm's sign flipped?)")


def session_summary(summary_sink, name: str, cfg, point=None, grade=None) -> dict:
    """A finished session's summary, as replay and run both report it: the summary sink's numbers,
    the trajectory's name, the metrics and, with a ``point``,
    its grading."""
    summary = summary_sink.summary()
    summary["trajectory"] = name
    summary["metrics"] = summary_sink.metrics(summary["punctures"])
    if point is not None:
        from .point import add_to_summary
        add_to_summary(summary, point, grade.result())
    return summary


RRD_BATCH_FRAMES = 30  # a replay's .rrd: servo series and frames drawn in half-second batches of simulated time
RRD_SEND_BATCHES = 8  # a replay's .rrd gets 8 batches (4 s of simulated time) per send_columns


def replay_one(trajectory, out_dir, config_path=None, realtime: bool = False, rrd: bool = True,
               spawn: bool = False, connect: str | None = None, progress: bool = True, cfg=None,
               point=None, layout: str | None = None) -> dict:
    """Replay ``trajectory`` into ``out_dir``; returns the summary dict. Raises UserError on bad
    input (nothing is left in ``out_dir``) and on a fault during the replay. ``point``: a
    :class:`~haptic_acu.session.point.PointSetup` (``--point``: its tissue, structures and grading)."""
    from haptic_acu.devices.scripted import ScriptedDevice

    from .engine import Session
    from .report import (SamplesCsvSink, SummarySink, add_debrief, plot_force_depth, preload_figure_modules,
                         write_debrief_md)

    cfg = cfg if cfg is not None else load_config(config_path)
    if point is not None:
        cfg = point.cfg
    trajectory = Path(trajectory)
    device = ScriptedDevice(trajectory, max_hand_speed_m_per_s=cfg.scene.max_hand_speed_m_per_s,
                            realtime=realtime, force_limit_n=cfg.safety.force_limit_n)
    device.open()  # validates the whole file before anything is written
    out_dir = Path(out_dir)
    limit = MAX_REPLAY_DURATION_S
    if device.duration_s > limit:
        raise UserError(f"{trajectory}: spans {device.duration_s:.6g} s, more than a replay takes "
                        f"({limit:g} s); split the file")
    out = OutputFolder(out_dir)
    with out.writing("the replay's files") as partial:
        reference = None
        if device.has_roll and not realtime:  # the grasp felt: the same replay without rotation
            reference = reference_forces(trajectory, cfg)  # its ticks and forces, not its rows
        # streamed: memory bounded by the work, not the file
        summary_sink = SummarySink(cfg, keep_rows=False, reference_rows=reference)
        io = _IOErrors()
        sinks = [io.guard(SamplesCsvSink(partial / "samples.csv")), summary_sink]
        if rrd or spawn or connect:
            from .rerun_log import RerunSink
            if spawn:
                sinks.append(RerunSink.spawn(layout))
            elif connect:
                sinks.append(RerunSink.connect(connect, layout))
            else:
                sink = RerunSink.to_file(partial / "recording.rrd", layout)
                sink.batch_frames = RRD_BATCH_FRAMES
                sink.send_batches = RRD_SEND_BATCHES
                sink.flush_frames, sink.flush_before_send = 0, True
                sinks.append(io.guard(sink))
        if progress:
            sinks.append(Progress(trajectory.name, device.duration_s))
        grade = None
        if point is not None:
            from .point import GradeSink
            grade = GradeSink(point)
            sinks.append(grade)
        session = Session(cfg, device, sinks, clock="realtime" if realtime else "sim",
                          model=point.model() if point is not None else None)
        check_start(trajectory, session.model.tissue)
        session.warm_up()
        if not realtime:
            preload_figure_modules()  # matplotlib's import overlaps the session's compiled ticks
        wall0, cpu0 = time.perf_counter(), time.process_time()
        result = session.run()
        cpu = time.process_time() - cpu0
        wall = time.perf_counter() - wall0
        device.close()
        if io.error is not None:  # a full disk: bad ground to write on, not a fault of the session
            raise UserError(f"{out_dir}: cannot write the replay's files: {io.error}")
        if result.fault:
            raise UserError(f"{trajectory}: replay stopped: {result.fault}", exit_status=3)
        signum = getattr(session, "signal_received", None)
        if signum is not None or (not realtime and result.ticks * session.servo_dt + 0.5
                                  < device.duration_s):
            out.abandon()  # the files so far stay in DIR.partial; nothing is published
            name = signal.Signals(signum).name if signum is not None else "a stop request"
            raise UserError(
                f"{trajectory}: replay interrupted by {name} at t = {result.duration_s:.3f} s "
                f"(tick {result.ticks} of about {int(device.duration_s / session.servo_dt)}); "
                f"the files so far are in {partial}/, not published",
                exit_status=128 + (signum or signal.SIGINT))
        summary = session_summary(summary_sink, trajectory.name, cfg, point, grade)
        add_debrief(summary, cfg)
        (partial / "summary.json").write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")
        write_debrief_md(summary, partial)
        fig_rows, fig_index = summary_sink.figure_rows()
        plot_force_depth(fig_rows, partial / "force_depth.png", summary_sink.tissue, summary=summary,
                         index=fig_index)
    summary["_wall_s"] = wall
    summary["_cpu_s"] = cpu  # the process's CPU time over the session (the bench's replay speed)
    summary["_stats"] = result.stats
    return summary


def replay_rows(trajectory, cfg, roll: bool = True):
    """The sample rows of a headless replay of ``trajectory`` (nothing written); ``roll=False``
    without its ``roll_deg`` (the technique metrics' reference: the same withdrawal without rotation).
    None if that replay faults."""
    from haptic_acu.devices.scripted import ScriptedDevice

    from .engine import Session
    from .report import SummarySink

    sink = SummarySink(cfg)
    with ScriptedDevice(trajectory, max_hand_speed_m_per_s=cfg.scene.max_hand_speed_m_per_s,
                        force_limit_n=cfg.safety.force_limit_n, roll=roll) as device:
        result = Session(cfg, device, [sink], clock="sim", dents=False).run()
    return None if result.fault else sink.rows()


class _Forces(Sink):
    """Frame sink keeping per row only its tick and force (the grasp felt's reference)."""

    rows_only = True  # the rows (and the frame's time) only

    def __init__(self):
        from ..servo.samples import COL
        self.cols = [COL["tick"], COL["fx_n"], COL["fx_n"] + 1, COL["fx_n"] + 2]
        self.blocks: list = []

    def on_frames(self, frames) -> None:
        rows, _ = block_rows(frames)
        if len(rows):
            self.blocks.append(rows[:, self.cols])

    def on_frame(self, frame) -> None:
        self.on_frames((frame,))


def reference_forces(trajectory, cfg):
    """(ticks, forces (n, 3)) of :func:`replay_rows` with ``roll=False``: all the grasp felt uses of
    that reference replay (32 of a row's 248 bytes). None if that replay faults."""
    import numpy as np

    from haptic_acu.devices.scripted import ScriptedDevice

    from .engine import Session

    sink = _Forces()
    with ScriptedDevice(trajectory, max_hand_speed_m_per_s=cfg.scene.max_hand_speed_m_per_s,
                        force_limit_n=cfg.safety.force_limit_n, roll=False) as device:
        result = Session(cfg, device, [sink], clock="sim", dents=False).run()
    if result.fault:
        return None
    a = np.concatenate(sink.blocks) if sink.blocks else np.zeros((0, 4))
    return a[:, 0].copy(), a[:, 1:4].copy()


def trajectories_from(args_paths) -> list[Path]:
    """Expand the command line's TRAJECTORY arguments: files as given, folders to their *.csv, the
    name of a bundled trajectory to its file (:func:`haptic_acu.base.bundled.resolve_trajectory`)."""
    from ..base.bundled import resolve_trajectory

    if not args_paths:
        return [DEFAULT_TRAJECTORY]
    out = []
    for a in args_paths:
        p = resolve_trajectory(a)
        if p.is_dir():
            files = sorted(p.glob("*.csv"))
            if not files:
                raise UserError(f"{p}: folder holds no .csv trajectories")
            out.extend(files)
        else:
            out.append(p)
    return out

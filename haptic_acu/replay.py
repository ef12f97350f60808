"""Headless replay of recorded needle trajectories: the project's main job.

:func:`replay_one` plays one trajectory file through a :class:`~haptic_acu.engine.Session` on
simulated time (servo ticks at exactly 1 ms, a visual frame every 1/60 s: the same kernels and the
same visual-frame code as a live session) and writes, into one output folder:

* ``samples.csv``     one row per servo tick,
* ``summary.json``    punctures, peaks, depths, per-layer time and peak force, session metrics,
* ``force_depth.png`` force against depth (layers shaded, punctures marked) and against time,
* ``recording.rrd``   the rerun recording (unless ``rrd=False``).

The folder is built as ``<out>.partial`` and renamed only when everything is written, so a failed
replay never leaves a folder that looks complete. Identical input gives byte-identical files.
"""
from __future__ import annotations

import json
import os
import shutil
import sys
import time
from pathlib import Path

from .bundled import bundled_dir
from .config import load_config
from .errors import UserError

BUNDLED_DIR = bundled_dir("trajectories")
DEFAULT_TRAJECTORY = BUNDLED_DIR / "default.csv"


class Progress:
    """A percentage on stderr (a sink: called per visual frame): rewritten in place on a terminal;
    elsewhere (a pipe, a log) a plain line every 25 %, once the replay has taken over a second."""

    def __init__(self, label: str, duration_s: float, stream=None):
        from . import progress
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.enabled = duration_s > 0 and not progress.quiet
        self.label = label
        self.duration_s = duration_s
        self._last = -1
        self._wall0 = time.perf_counter()

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


def replay_one(trajectory, out_dir, config_path=None, realtime: bool = False, rrd: bool = True,
               spawn: bool = False, connect: str | None = None, progress: bool = True, cfg=None) -> dict:
    """Replay ``trajectory`` into ``out_dir``; returns the summary dict. Raises UserError on bad
    input (nothing is left in ``out_dir``) and on a fault during the replay."""
    from haptic_acu.devices.scripted import ScriptedDevice

    from .engine import Session
    from .report import SamplesCsvSink, SummarySink, plot_force_depth

    cfg = cfg if cfg is not None else load_config(config_path)
    trajectory = Path(trajectory)
    device = ScriptedDevice(trajectory, max_hand_speed_m_per_s=cfg.scene.max_hand_speed_m_per_s,
                            realtime=realtime, force_limit_n=cfg.safety.force_limit_n)
    device.open()  # validates the whole file before anything is written
    out_dir = Path(out_dir)
    if out_dir.exists() and any(out_dir.iterdir()):
        raise UserError(f"{out_dir}: output folder exists and is not empty")
    partial = out_dir.with_name(out_dir.name + ".partial")
    if partial.exists():
        shutil.rmtree(partial)
    partial.mkdir(parents=True)
    try:
        summary_sink = SummarySink(cfg)
        sinks = [SamplesCsvSink(partial / "samples.csv"), summary_sink]
        if rrd or spawn or connect:
            from .rerun_log import RerunSink
            if spawn:
                sinks.append(RerunSink.spawn())
            elif connect:
                sinks.append(RerunSink.connect(connect))
            else:
                sink = RerunSink.to_file(partial / "recording.rrd")
                sink.batch_frames = 30  # servo series in half-second batches of simulated time
                sinks.append(sink)
        if progress:
            sinks.append(Progress(trajectory.name, device.duration_s))
        session = Session(cfg, device, sinks, clock="realtime" if realtime else "sim")
        session.warm_up()
        wall0 = time.perf_counter()
        result = session.run()
        wall = time.perf_counter() - wall0
        device.close()
        if result.fault:
            raise UserError(f"{trajectory}: replay stopped: {result.fault}", exit_status=3)
        summary = summary_sink.summary()
        summary["trajectory"] = trajectory.name
        try:
            from .metrics import session_metrics
            summary["metrics"] = session_metrics(summary_sink.rows(), cfg, summary_sink.tissue,
                                                 punctures=summary["punctures"])
        except ImportError:
            pass
        (partial / "summary.json").write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")
        plot_force_depth(summary_sink.rows(), partial / "force_depth.png", summary_sink.tissue, summary=summary)
        if out_dir.exists():
            out_dir.rmdir()
        os.replace(partial, out_dir)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    summary["_wall_s"] = wall
    summary["_stats"] = result.stats
    return summary


def trajectories_from(args_paths) -> list[Path]:
    """Expand the command line's TRAJECTORY arguments: files as given, folders to their *.csv."""
    if not args_paths:
        return [DEFAULT_TRAJECTORY]
    out = []
    for a in args_paths:
        p = Path(a)
        if p.is_dir():
            files = sorted(p.glob("*.csv"))
            if not files:
                raise UserError(f"{p}: folder holds no .csv trajectories")
            out.extend(files)
        else:
            out.append(p)
    return out

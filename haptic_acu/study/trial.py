"""One trial of a study: a live session with the hidden model, then its seven ratings.

Blinding: everything the participant (or the person running the session) sees names the system
code only: the terminal's lines, the status line, the session folder (``sessions/P01-T3``), the
files in it, the rerun recording's entities and the summary's name. The model's config is loaded
from the key (checked against the plan's config hash) and never printed; an error about it names
the system code, not the file.

End of a session: the device's own end (the scripted path's end, the keyboard's ``q``),
``--duration``, or Ctrl-C (SIGINT: the usual way to end an OMNI session) complete the trial. A
SIGTERM (the process is being shut down) interrupts it: the recording is flushed and complete up
to that tick, the trial is marked ``interrupted`` and not done, no ratings are asked. A fault
(exit 3) is marked ``fault``. Ctrl-C or SIGTERM before the session starts (while the simulator is
prepared) marks the trial ``interrupted`` too, with nothing recorded. Ratings are then asked on the
terminal (:func:`ratings.ask`), and recorded in ratings.csv only once all seven are given; Ctrl-C
there records nothing.
"""
from __future__ import annotations

import json
import signal
import sys
from dataclasses import dataclass
from pathlib import Path

from .. import __version__
from ..base.errors import UserError
from ..base.progress import step
from ..base.signals import Terminated
from .store import Study, Trial, now, write_trial_json


@dataclass
class TrialResult:
    folder: Path
    attempt: int
    status: str  # complete | interrupted | fault
    fault: str | None
    summary: dict | None
    signal: str | None = None  # what interrupted the trial, or (complete) its files after the session
    started: bool = True  # False: stopped before its session started (nothing recorded)


def session_name(trial: Trial) -> str:
    """The name of the session in its summary and figure: the system code only."""
    return f"{trial.participant} trial {trial.trial}: {trial.system}"


def signal_name(e: BaseException) -> str:
    """The signal behind an interrupt: Ctrl-C's KeyboardInterrupt, or SIGTERM's Terminated."""
    return "SIGTERM" if isinstance(e, Terminated) else "SIGINT"


def _session(folder: Path, cfg, device, *, rrd, status, err, **kw):
    """The trial's session and its recorder and summary sinks (nothing opened, nothing written)."""
    from ..session.engine import Session
    from ..session.recorder import RecorderSink
    from ..session.report import SamplesCsvSink, SummarySink

    summary_sink = SummarySink(cfg, keep_rows=False)
    recorder = RecorderSink(folder / "recording.csv", device=device)
    sinks = [recorder, SamplesCsvSink(folder / "samples.csv"), summary_sink]
    if rrd:
        from ..session.sinkproc import rerun_file_sink
        sinks.append(rerun_file_sink((folder / "recording.rrd").resolve()))
    if status:
        from ..session.status import StatusLine
        sinks.append(StatusLine(stream=err, target_mm=cfg.scene.target_depth_mm,
                                force_limit_n=cfg.safety.force_limit_n, device=device))
    return Session(cfg, device, sinks, clock="realtime", **kw), recorder, summary_sink


def run_session(study: Study, trial: Trial, cfg, device, *, device_name: str, duration_s=None, rrd=False,
                status=True, compiled=True, pin_cores=False, speed=1.0, err=None, out=None) -> TrialResult:
    """Run the trial's session on ``device`` (made by the caller, not opened) with the model's
    ``cfg`` into a new session folder; returns how it ended. Never reveals the model. ``speed``: a
    paced session of the scripted device (:class:`~haptic_acu.session.engine.Session`), recorded in
    trial.json when it is not 1.

    trial.json says ``running`` from the folder's creation; whatever ends the trial rewrites it. An
    interrupt (Ctrl-C, or SIGTERM under :func:`~haptic_acu.base.signals.sigterm_unwinds`) before
    the session's loops handle signals (while the simulator is prepared, the device opens) marks it
    ``interrupted`` with the signal and returns (``started`` False: nothing recorded); one while the
    session's files are written after it leaves its status (the session is recorded) and returns
    the signal: no ratings are asked."""
    from ..session.report import plot_force_depth, print_results

    err = sys.stderr if err is None else err
    out = sys.stdout if out is None else out
    folder, attempt = study.new_session_folder(trial)
    doc = {"participant": trial.participant, "trial": trial.trial, "system": trial.system, "attempt": attempt,
           "status": "running", "device": device_name, "started": now(), "tool_version": __version__}
    if speed != 1.0:
        doc["speed"] = speed
    recorder, ran = None, False
    try:
        write_trial_json(folder, doc)
        session, recorder, summary_sink = _session(folder, cfg, device, rrd=rrd, status=status, err=err,
                                                   duration_s=duration_s, compiled_loop=compiled,
                                                   pin_cores=pin_cores, speed=speed)
        with step("preparing the simulator"):
            session.warm_up()
        print(f"{trial.participant}, trial {trial.trial} of {study.n_trials}: {trial.system}. "
              "End the session with Ctrl-C" + (" (or q)" if device_name == "keyboard" else "") + ".", file=err)
        try:
            device.open()
        except Exception as e:  # no device (a missing library, an OMNI not connected): no session
            doc.update(status="fault", ended=now(), fault=f"the device did not open: {e}")
            raise
        try:
            recorder.open()
            ran = True
            result = session.run()
        finally:
            device.close()
    except (KeyboardInterrupt, Terminated) as e:
        doc.update(status="interrupted", ended=now(), signal=signal_name(e))
        if ran:
            doc["recording_rows"] = recorder.rows
        write_trial_json(folder, doc)
        return TrialResult(folder, attempt, "interrupted", None, None, signal=signal_name(e), started=ran)
    except Exception as e:
        if doc["status"] == "running":
            doc.update(status="fault", ended=now(), fault=f"the session did not start: {e}")
        write_trial_json(folder, doc)
        raise
    sig = getattr(session, "signal_received", None)
    state = "fault" if result.fault else ("interrupted" if sig == signal.SIGTERM else "complete")
    summary, stopped = None, None
    try:
        summary = summary_sink.summary()
        summary["trajectory"] = session_name(trial)
        summary["metrics"] = summary_sink.metrics(summary["punctures"])
        (folder / "summary.json").write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")
        rows, index = summary_sink.figure_rows()
        with step("drawing force_depth.png"):
            plot_force_depth(rows, folder / "force_depth.png", summary_sink.tissue, summary=summary, index=index)
        print(f"session: {result.duration_s:.1f} s, {result.ticks} ticks, {result.stats['missed_ticks']} missed",
              file=err)
        print_results(summary, folder, file=out, quiet=True)
    except (KeyboardInterrupt, Terminated) as e:  # the session is recorded; its ratings are not asked
        stopped = signal_name(e)
    finally:
        doc.update(status=state, ended=now(), duration_s=round(result.duration_s, 3), ticks=result.ticks,
                   missed_ticks=result.stats.get("missed_ticks"), recording_rows=recorder.rows)
        if result.fault:
            doc["fault"] = result.fault
        if sig is not None:
            doc["signal"] = signal.Signals(sig).name
        write_trial_json(folder, doc)
    return TrialResult(folder, attempt, state, result.fault, summary,
                       signal=doc["signal"] if state == "interrupted" else stopped)


def ended_here(study: Study, trial: Trial, res: TrialResult) -> int | None:
    """A trial that stops without its ratings: its one line on stderr and the exit status (3 a
    fault; 130 or 143 a signal: before the session, during it (SIGTERM), or after it); None when
    the ratings are to be asked."""
    name = res.folder.name
    if res.status == "fault":
        print(f"haptic-acu study: stopped: {res.fault}; trial not done (its files: {res.folder})", file=sys.stderr)
        return 3
    if res.status == "interrupted":
        sig = res.signal or "SIGTERM"
        what = (" before the session started; nothing recorded" if not res.started else
                "; the recording is complete up to the signal")
        print(f"haptic-acu study: {name} interrupted ({sig}){what}; the trial is not done: run it again",
              file=sys.stderr)
        return 128 + signal.Signals[sig]
    if res.signal is not None:  # while the session's files were written
        return no_ratings(study, trial, res.signal, f"haptic-acu study: the session of {name} is saved; ")
    return None


def no_ratings(study: Study, trial: Trial, sig: str, what: str = "\n") -> int:
    """An interrupt (``sig``) before the ratings were saved: one line saying how to enter them
    (after ``what``; at a prompt, a line end); the exit status, 130 (Ctrl-C) or 143 (SIGTERM)."""
    print(f"{what}no ratings recorded for {trial.participant} trial {trial.trial} ({sig}); enter them with: "
          f"haptic-acu study rate {study.folder} --participant {trial.participant} --trial {trial.trial}",
          file=sys.stderr)
    return 128 + signal.Signals[sig]


def blind_config(study, key, model, trial):
    """The model's config for a trial; an error names the system code, never the model or its file."""
    try:
        return study.checked_config(key, model)
    except UserError:
        raise UserError(f"{study.json_path}: the config of {trial.participant}'s {trial.system} no longer matches "
                        "the plan's config hash (or no longer loads); the study's supervisor can see which "
                        "with `haptic-acu study analyze`") from None

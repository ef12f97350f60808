"""A finished live session's report (``haptic-acu run``): summary.json, debrief.md and
force_depth.png written into its folder and the results printed (:func:`write_report`), with the grasp
felt of each insertion that twirled measured from the session's recording (:func:`grasp_from_recording`),
and the servo loop's timing (:func:`print_loop_timing`)."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from ..base.progress import step


def write_report(summary_sink, cfg, out: Path, name: str, quiet: bool = False, point=None, grade=None,
                 recording=None) -> dict:
    """summary.json, debrief.md and force_depth.png of a finished session into ``out``; print the
    results and the debrief (``point``, ``grade``: a --point session's setup and grading sink;
    ``recording``: the session's recording, for the grasp felt of an insertion that twirled,
    :func:`grasp_from_recording`)."""
    from .replay import session_summary
    from .report import add_debrief, plot_force_depth, print_results, write_debrief_md

    summary = session_summary(summary_sink, name, cfg, point, grade)
    if recording is not None and summary.get("fault") is None:
        grasp_from_recording(summary["metrics"], Path(recording), cfg)
    add_debrief(summary, cfg)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")
    write_debrief_md(summary, out)
    rows, index = summary_sink.figure_rows()
    with step("drawing force_depth.png"):
        plot_force_depth(rows, out / "force_depth.png", summary_sink.tissue, summary=summary, index=index)
    print_results(summary, out, quiet=quiet)
    return summary


def grasp_from_recording(metrics: dict, recording: Path, cfg) -> None:
    """The grasp felt of each insertion that turned the needle, as ``haptic-acu replay`` finds it:
    the withdrawal's resistance against the same session without rotation. The live session cannot
    run that reference beside itself, so its recording is replayed twice headless (with and
    without its roll: the same ticks as the session) and each insertion's ``grasp_felt`` taken
    from there. Nothing happens when no insertion turned (there is no grasp to measure)."""
    per = metrics.get("per_insertion") or []
    if not any((m["technique"]["twirl"].get("total_rotation_deg") or 0.0) > 0.0 for m in per):
        return
    if not recording.is_file():
        return
    from ..devices.scripted import ScriptedDevice
    from .engine import Session
    from .replay import reference_forces
    from .report import SummarySink

    with step("measuring the grasp felt on withdrawal (the session replayed with and without its twirl)"):
        ref = reference_forces(recording, cfg)
        if ref is None:
            return
        sink = SummarySink(cfg, keep_rows=False, reference_rows=ref)
        with ScriptedDevice(recording, max_hand_speed_m_per_s=cfg.scene.max_hand_speed_m_per_s,
                            force_limit_n=cfg.safety.force_limit_n) as device:
            result = Session(cfg, device, [sink], clock="sim", dents=False).run()
        if result.fault:
            return
        again = sink.metrics(sink.summary()["punctures"])["per_insertion"]
    for m, r in zip(per, again):
        if m["t_entry_s"] == r["t_entry_s"]:
            m["technique"]["grasp_felt"] = r["technique"]["grasp_felt"]


LATE_SHARE_SAID = 0.01  # without --verbose the loop's timing is mentioned only when this share of ticks was late


def print_loop_timing(result, verbose: bool = False) -> None:
    """The servo loop's timing of a finished session (``result``: the engine's), on stderr: with
    ``verbose`` always, else a note only when it was often late."""
    st = result.stats
    pe = st["period_error_us"]
    if verbose:
        print(f"session: {result.ticks} ticks in {result.duration_s:.2f} s, {st['missed_ticks']} missed; "
              f"period error p50 {pe['p50']:.0f} us, p99 {pe['p99']:.0f} us, max {pe['max']:.0f} us; "
              f"{st['servo_loop']} servo loop", file=sys.stderr)
    elif st["missed_ticks"] > LATE_SHARE_SAID * max(result.ticks, 1):
        print(f"note: this computer was often late with the force ({100.0 * st['missed_ticks'] / max(result.ticks, 1):.1f}% "
              "of the servo ticks): the feel may have been rough; --verbose gives the timing", file=sys.stderr)

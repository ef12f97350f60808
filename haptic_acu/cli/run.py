"""``haptic-acu run``: a live session on a device (OMNI, keyboard, or a trajectory in real time).

A session ends like ``haptic-acu replay``: the punctures, the depth reached against the config's
``scene.target_depth_mm`` and the per-insertion metrics are printed, and the session's report folder
(``--out``, default a new folder under ``runs/``) holds

* ``recording.csv``   the tip path (replay it with ``haptic-acu replay``; ``--record FILE`` puts it
  elsewhere),
* ``samples.csv``     one row per servo tick,
* ``summary.json``    punctures, depths, peaks, metrics and the loop statistics,
* ``force_depth.png`` force against depth and time,
* ``recording.rrd``   the rerun recording, with ``--rrd`` (or ``--rrd FILE`` elsewhere).

The report sinks are ordinary frame sinks: they run on the visual loop, never on the servo tick, and
the recording and samples are flushed as the session runs, so a fault or Ctrl-C keeps every row up to
it (the figure and summary are written after the session, also after a fault).
"""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

from ..base.bundled import bundled_names, not_found_hint, resolve_trajectory
from ..base.errors import UserError
from ..base.outputs import Outputs, claim_folder, fresh_folder
from .options import add_config_args, check_layout_arg, check_speed_arg, config_from_args
from ..base.progress import step
from ..base.signals import sigterm_unwinds


def register(sub) -> None:
    p = sub.add_parser("run", help="a live session on a haptic device (results and a report folder at the end)",
                       description="Run the simulator live: a 1 kHz servo loop on the device and a 60 Hz visual "
                                   "loop (springback, status line, optional rerun logging). At the end: the "
                                   "punctures, the depth reached against scene.target_depth_mm and the "
                                   "per-insertion metrics, and a report folder (--out) with recording.csv, "
                                   "samples.csv, summary.json and force_depth.png, like `haptic-acu replay`.")
    p.add_argument("--device", choices=("omni", "keyboard", "scripted"), required=True,
                   help="omni: a Geomagic Touch / Phantom Omni through OpenHaptics (pyOpenHaptics, libHD.so); "
                        "keyboard: move the needle with the keys (help on screen); scripted: play --trajectory "
                        "in real time")
    p.add_argument("--trajectory", metavar="FILE", help="trajectory CSV (t_s,x_mm,y_mm,z_mm) for --device scripted, "
                   "or a bundled trajectory's name (" + bundled_names() + ")")
    p.add_argument("--duration", type=float, metavar="S", help="stop after this many seconds")
    p.add_argument("--out", metavar="DIR", help="report folder (default: a new folder runs/<device>-<time>/; "
                                                "must be empty if it exists)")
    p.add_argument("--record", metavar="FILE", help="write the replayable recording to FILE instead of "
                                                    "<out>/recording.csv (an existing file is refused unless "
                                                    "--overwrite; never the session's own --trajectory)")
    p.add_argument("--overwrite", action="store_true", help="let --record and --rrd FILE replace an existing file "
                                                            "(never an input, never the report folder's files)")
    add_config_args(p)
    g = p.add_mutually_exclusive_group()
    g.add_argument("--rrd", metavar="FILE", nargs="?", const="",
                   help="log to a rerun .rrd file (without FILE: <out>/recording.rrd)")
    g.add_argument("--spawn", action="store_true", help="log to a new rerun viewer (needs a display)")
    g.add_argument("--connect", metavar="ADDR", help="log to a running rerun viewer at ADDR (host:port)")
    from .options import add_layout_arg
    add_layout_arg(p, "trainee")
    p.add_argument("--no-status", action="store_true", help="no live status line")
    p.add_argument("--quiet", action="store_true", help="print only where the files are")
    p.add_argument("--verbose", action="store_true",
                   help="also print the servo loop's timing statistics (always in summary.json's loop)")
    p.add_argument("--python-servo", action="store_true",
                   help="run the servo tick as Python instead of compiled and GIL-free (for comparison)")
    p.add_argument("--speed", type=float, default=1.0, metavar="X",
                   help="--device scripted: play the path X times as fast as real time (default 1). Session time "
                        "stays the tick's own, so the results and the recording are those at real pace; the "
                        "loop's timing is against the shorter period (a quick live check, e.g. in CI)")
    p.add_argument("--pin-cores", action="store_true",
                   help="pin the servo thread (the scripted device's, or the OMNI's HD scheduler thread) to one "
                        "core and the rerun logging child to the others")
    from ..session.point import add_point_args
    add_point_args(p)
    p.add_argument("--travel-axis", action="store_true",
                   help="OMNI: ignore the stylus orientation; the needle axis is the direction of travel at entry "
                        "(as for a device that does not know it)")
    p.set_defaults(func=run)


def make_device(args, cfg):
    from haptic_acu.devices.base import Workspace

    ws = Workspace.from_config(cfg.workspace)
    limit = cfg.safety.force_limit_n
    if args.device == "scripted":
        if not args.trajectory:
            raise UserError("--device scripted needs --trajectory FILE")
        from haptic_acu.devices.scripted import ScriptedDevice
        return ScriptedDevice(args.trajectory, cfg.scene.max_hand_speed_m_per_s, realtime=True, force_limit_n=limit)
    if args.trajectory:
        raise UserError(f"--trajectory is for --device scripted, not {args.device}")
    if args.speed != 1.0:
        raise UserError(f"--speed is for --device scripted, not {args.device}")
    if args.travel_axis and args.device != "omni":
        raise UserError(f"--travel-axis is for --device omni, not {args.device}")
    if args.device == "keyboard":
        from haptic_acu.devices.keyboard import KeyboardDevice
        return KeyboardDevice(workspace=ws, force_limit_n=limit, stdin=sys.stdin, out=sys.stderr)
    from haptic_acu.devices.omni import OmniDevice, load_hd_library
    load_hd_library()  # a missing pyOpenHaptics / libHD.so fails now, before the simulator warms up
    return OmniDevice(ws, force_limit_n=limit, stylus_axis=not args.travel_axis)


MAX_DURATION_S = 1e6  # 11.6 days: a longer --duration is a typo


def out_folder(args) -> Path:
    """The report folder's path: ``--out``, else a fresh ``runs/<device>-<time>`` (checked and claimed
    by :func:`output_plan` and :func:`haptic_acu.base.outputs.claim_folder`)."""
    if args.out:
        return Path(args.out)
    return fresh_folder(Path("runs") / f"{args.device}-{time.strftime('%Y%m%d-%H%M%S')}")


def output_plan(args, out: Path, rec: Path, rrd: Path | None) -> Outputs:
    """The session's outputs under the output rule: the report folder and its files, ``--record``
    and ``--rrd`` elsewhere; the trajectory and the config are inputs."""
    own = ["samples.csv", "summary.json", "force_depth.png"]
    own += [] if args.record else ["recording.csv"]
    own += ["recording.rrd"] if rrd is not None and not args.rrd else []
    plan = Outputs(overwrite=args.overwrite).input("--trajectory", args.trajectory).input("--config", args.config)
    plan.folder("--out", out, files=own)
    if args.record:
        plan.file("--record", rec)
    if args.rrd:
        plan.file("--rrd", rrd)
    return plan


def _rerun_sink(args, out: Path):
    # rerun logging runs in a child process (see haptic_acu.session.sinkproc): its calls would otherwise
    # hold the GIL for hundreds of microseconds beside the servo thread
    from ..session.sinkproc import rerun_connect_sink, rerun_file_sink, rerun_spawn_sink
    if args.spawn:
        return rerun_spawn_sink(args.layout)
    if args.connect:
        return rerun_connect_sink(args.connect, args.layout)
    return rerun_file_sink((Path(args.rrd) if args.rrd else out / "recording.rrd").resolve(), args.layout)


def run(args) -> int:
    if args.duration is not None and not (math.isfinite(args.duration) and 0 < args.duration <= MAX_DURATION_S):
        raise UserError(f"--duration must be a number of seconds > 0 and at most {MAX_DURATION_S:g}, got "
                        f"{args.duration}")
    check_speed_arg(args)
    cfg = config_from_args(args)
    check_layout_arg(args)
    from ..session.point import setup_from_args
    ps = setup_from_args(cfg, args)  # --point: the tissue at the point, its structures, the grading
    if ps is not None:
        cfg = ps.cfg
    if args.spawn:
        from ..session.viewer import check_spawn
        check_spawn()  # no display: one line now, not half a minute of viewer errors
    if args.trajectory:  # a file, or a bundled trajectory's name
        traj = resolve_trajectory(args.trajectory)
        if not traj.is_file():
            raise UserError(f"{traj}: trajectory file not found{not_found_hint()}")
        args.trajectory = str(traj)
    out = out_folder(args)
    rec = Path(args.record) if args.record else out / "recording.csv"
    rrd = None if args.rrd is None else Path(args.rrd) if args.rrd else out / "recording.rrd"
    # every output checked now (nothing replaced, nothing shared); the recording is created only
    # once the session can start (after device.open)
    output_plan(args, out, rec, rrd).check()
    device = make_device(args, cfg)
    lock = claim_folder(out)  # held alone until the session's report is written
    try:
        with sigterm_unwinds():  # SIGTERM outside the session's loops: unwinds like Ctrl-C (exit 143)
            return _run(args, cfg, device, out, rec, ps)
    except BaseException:
        lock.discard_if_empty()  # the session could not start (bad input, Ctrl-C): nothing left behind
        raise
    finally:
        lock.release()


def _run(args, cfg, device, out: Path, rec: Path, ps=None) -> int:
    """The session itself, once its outputs are checked and its folder held (``ps``: a --point setup)."""
    from ..session.engine import Session
    from ..session.recorder import RecorderSink
    from ..session.live import print_loop_timing, write_report
    from ..session.report import SamplesCsvSink, SummarySink

    summary_sink = SummarySink(cfg, keep_rows=False)  # streamed: a long session's memory stays flat
    recorder = RecorderSink(rec, overwrite=args.overwrite, device=device)
    sinks = [recorder, SamplesCsvSink(out / "samples.csv"), summary_sink]
    grade = None
    if ps is not None:
        from ..session.point import GradeSink
        grade = GradeSink(ps)
        sinks.append(grade)
    if args.rrd is not None or args.spawn or args.connect:
        sinks.append(_rerun_sink(args, out))
    if not args.no_status:
        from ..session.status import StatusLine
        sinks.append(StatusLine(stream=sys.stderr, target_mm=cfg.scene.target_depth_mm,
                                force_limit_n=cfg.safety.force_limit_n, device=device, point=ps))
    # Compile and warm everything before the device opens: the OMNI's scheduler (and its device
    # time) starts in open(), and should not run for seconds with force output on and no servo.
    session = Session(cfg, device, sinks, clock="realtime", duration_s=args.duration,
                      compiled_loop=not args.python_servo, pin_cores=args.pin_cores, speed=args.speed,
                      model=ps.model() if ps is not None else None)  # the compiled loop honours resets
    if args.device == "scripted":
        from ..session.replay import check_start
        check_start(args.trajectory, session.model.tissue)
    with step("preparing the simulator (numba compiles it on the first run; cached afterwards)"):
        session.warm_up()
    device.open()
    try:
        recorder.open()
        result = session.run()
    finally:
        device.close()
    print_loop_timing(result, args.verbose)
    try:
        write_report(summary_sink, cfg, out, f"{args.device} session", quiet=args.quiet, point=ps, grade=grade,
                     recording=rec)
        if args.record:
            print(f"  recording: {rec}")
    finally:  # the fault is reported even if the report could not be written
        if result.fault:
            print(f"haptic-acu run: stopped: {result.fault}", file=sys.stderr)
    return 3 if result.fault else 0

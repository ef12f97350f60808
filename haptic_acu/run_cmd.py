"""``haptic-acu run``: a live session on a device (OMNI, keyboard, or a trajectory in real time)."""
from __future__ import annotations

import sys
from pathlib import Path

from .errors import UserError


def register(sub) -> None:
    p = sub.add_parser("run", help="a live session on a haptic device",
                       description="Run the simulator live: a 1 kHz servo loop on the device and a 60 Hz visual "
                                   "loop (springback, rerun logging, status line).")
    p.add_argument("--device", choices=("omni", "keyboard", "scripted"), required=True)
    p.add_argument("--trajectory", help="trajectory CSV for --device scripted (played in real time)")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--record", metavar="FILE", help="record the session as a replayable trajectory CSV "
                   "(an existing file is refused unless --overwrite)")
    p.add_argument("--overwrite", action="store_true", help="let --record replace an existing file")
    p.add_argument("--config", help="tissue config TOML (default config/tissue.toml)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--rrd", metavar="FILE", help="log to a rerun .rrd file")
    g.add_argument("--spawn", action="store_true", help="log to a new rerun viewer")
    g.add_argument("--connect", metavar="ADDR", help="log to a running rerun viewer")
    p.add_argument("--no-status", action="store_true", help="no live status line")
    p.add_argument("--python-servo", action="store_true",
                   help="run the servo tick as Python instead of compiled and GIL-free (for comparison)")
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
    if args.device == "keyboard":
        from haptic_acu.devices.keyboard import KeyboardDevice
        return KeyboardDevice(workspace=ws, force_limit_n=limit, stdin=sys.stdin, out=sys.stderr)
    from haptic_acu.devices.omni import OmniDevice, load_hd_library
    load_hd_library()  # a missing pyOpenHaptics / libHD.so fails now, before the simulator warms up
    return OmniDevice(ws, force_limit_n=limit)


def run(args) -> int:
    from .config import load_config
    from .engine import Session

    if args.duration is not None and not args.duration > 0:
        raise UserError(f"--duration must be > 0, got {args.duration}")
    cfg = load_config(args.config)
    recorder = None
    if args.record:  # checked now, created only once the session can start (after device.open)
        from .recorder import RecorderSink, check_target
        rec = check_target(args.record, args.overwrite, inputs=[args.trajectory])
    device = make_device(args, cfg)
    sinks = []
    if args.record:
        recorder = RecorderSink(rec, overwrite=args.overwrite, device=device)
        sinks.append(recorder)
    if args.rrd or args.spawn or args.connect:
        # rerun logging runs in a child process (see haptic_acu.sinkproc): its calls would otherwise
        # hold the GIL for hundreds of microseconds beside the servo thread
        from .sinkproc import rerun_connect_sink, rerun_file_sink, rerun_spawn_sink
        sinks.append(rerun_file_sink(Path(args.rrd).resolve()) if args.rrd else rerun_spawn_sink() if args.spawn
                     else rerun_connect_sink(args.connect))
    if not args.no_status:
        from .status import StatusLine
        sinks.append(StatusLine(stream=sys.stderr))
    # Compile and warm everything before the device opens: the OMNI's scheduler (and its device
    # time) starts in open(), and should not run for seconds with force output on and no servo.
    session = Session(cfg, device, sinks, clock="realtime", duration_s=args.duration,  # resets need read_at:
                      compiled_loop=not args.python_servo and not getattr(device, "has_events", False))
    session.warm_up()
    device.open()
    try:
        if recorder is not None:
            recorder.open()
        result = session.run()
    finally:
        device.close()
    st = result.stats
    pe = st["period_error_us"]
    print(f"session: {result.ticks} ticks in {result.duration_s:.2f} s, {st['missed_ticks']} missed; "
          f"period error p50 {pe['p50']:.0f} us, p99 {pe['p99']:.0f} us, max {pe['max']:.0f} us; "
          f"{st['servo_loop']} servo loop", file=sys.stderr)
    if args.record:
        print(f"recording: {args.record}", file=sys.stderr)
    if result.fault:
        print(f"haptic-acu run: stopped: {result.fault}", file=sys.stderr)
        return 3
    return 0

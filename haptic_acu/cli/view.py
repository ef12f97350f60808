"""``haptic-acu view RECORDING.rrd``: a rerun recording in rerun's web viewer, served on 127.0.0.1.

For a machine without a display (a lab server, a container): the command prints the address to open
and the SSH command that forwards it to another machine (:mod:`haptic_acu.session.webview`). Ctrl-C
stops it.
"""
from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("view", help="serve a .rrd recording in rerun's web viewer on 127.0.0.1 (no display needed)",
                       description="Serve a rerun recording (recording.rrd from `haptic-acu replay`, or "
                                   "`haptic-acu run --rrd`) in rerun's web viewer on 127.0.0.1, and print the "
                                   "address to open and how to reach it from another machine over SSH. "
                                   "Ctrl-C stops it.")
    p.add_argument("recording", metavar="RECORDING.rrd", help="the rerun recording to show")
    p.add_argument("--port", type=int, default=0, metavar="PORT",
                   help="the web viewer's port (default: a free one)")
    p.add_argument("--file-port", type=int, default=0, metavar="PORT",
                   help="the port the recording itself is served on (default: a free one)")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..base.errors import UserError
    from ..session.webview import serve

    for name in ("port", "file_port"):
        v = getattr(args, name)
        if not 0 <= v <= 65535:
            raise UserError(f"--{name.replace('_', '-')} must be a port number 0-65535, got {v}")
    return serve(args.recording, web_port=args.port, file_port=args.file_port)

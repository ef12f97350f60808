"""The ``haptic-acu`` command: one console script, one sub-command per job.

Each sub-command lives in its own module, which exposes ``register(subparsers)``; that adds the
sub-command's parser and sets ``func`` to a function taking the parsed args and returning the
exit status. Bad input raises :class:`~haptic_acu.base.errors.UserError`, printed here as one line on
stderr with no traceback (exit status 2).
"""
from __future__ import annotations

import argparse
import importlib
import sys

from ..base.errors import DeviceFault, UserError
from ..base.signals import Terminated

# name -> module providing register(subparsers); imported only when needed.
COMMANDS = {
    "replay": "haptic_acu.cli.replay",
    "run": "haptic_acu.cli.run",
    "compare": "haptic_acu.cli.compare",
    "fit": "haptic_acu.cli.fit",
    "score": "haptic_acu.cli.score",
    "bench": "haptic_acu.cli.bench",
    "calibrate": "haptic_acu.cli.calibrate",
    "cohort": "haptic_acu.cli.cohort",
    "study": "haptic_acu.cli.study",
    "points": "haptic_acu.cli.points",
    "view": "haptic_acu.cli.view",
}


class _Version(argparse.Action):
    """``--version``: the installed version, looked up only when asked for."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        from .. import __version__

        print(f"haptic-acu {__version__}")
        parser.exit()


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's own errors: one line, status 2
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    parser = _Parser(prog="haptic-acu", description="Haptic simulator of acupuncture needle insertion: replay "
                     "recorded needle paths headless, run live on an OMNI, the keyboard or a scripted path, "
                     "compare sessions, fit tissue surfaces, score trainees.",
                     epilog="Run `haptic-acu COMMAND --help` for a command's options. Every command that takes "
                            "--config also takes --set section.key=value (repeatable). Bad input: one line on "
                            "stderr, exit status 2; a fault during a session: exit status 3.")
    parser.add_argument("--version", action=_Version, help="show the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name, module in COMMANDS.items():
        if only is not None and name != only:
            sub.add_parser(name, help=f"(see haptic-acu {name} --help)")
            continue
        importlib.import_module(module).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """The command line's exit status. Without ``argv`` (the console entry, ``python -m haptic_acu``)
    this process runs the one command and exits: the collector's policy for such a process
    (:mod:`haptic_acu.base.gcpolicy`) applies."""
    if argv is None:
        from ..base import gcpolicy

        gcpolicy.command_process()
        argv = sys.argv[1:]
    return _main(list(argv))


def _main(argv: list[str]) -> int:
    only = next((a for a in argv if a in COMMANDS), None)
    parser = build_parser(only)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    from ..base import progress
    was_quiet, progress.quiet = progress.quiet, bool(getattr(args, "quiet", False))
    progress.watch_compiles()
    try:
        return _dispatch(args)
    finally:  # a command run in-process (main([...])) leaves the progress lines as it found them
        progress.quiet = was_quiet


# What str.splitlines breaks a line at: in an error's text (a user's value quoted in it) each is
# written as its escape, so the error stays one line.
_LINE_BREAKS = {ord(c): c.encode("unicode_escape").decode("ascii") for c in "\n\r\v\f\x1c\x1d\x1e\x85\u2028\u2029"}


def one_line(text) -> str:
    """``text`` with every character that would break its line escaped."""
    return str(text).translate(_LINE_BREAKS)


def _dispatch(args) -> int:
    """The command's exit status; its errors as one line on stderr."""
    try:
        return int(args.func(args) or 0)
    except UserError as e:
        print(f"haptic-acu {args.command}: error: {one_line(e)}", file=sys.stderr)
        return e.exit_status
    except DeviceFault as e:
        print(f"haptic-acu {args.command}: device fault: {one_line(e)}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        print(f"haptic-acu {args.command}: interrupted", file=sys.stderr)
        return 130
    except Terminated as e:  # SIGTERM where a command asked for it to unwind (base/signals.py)
        print(f"haptic-acu {args.command}: terminated (SIGTERM)", file=sys.stderr)
        return int(e.code)
    except BrokenPipeError:
        return 0
    except OSError as e:  # a full disk, a read-only or vanished folder while writing outputs
        where = f"{e.filename}: " if e.filename else ""
        print(f"haptic-acu {args.command}: error: {one_line(f'{where}{e.strerror or e}')}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())

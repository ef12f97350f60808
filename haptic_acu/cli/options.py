"""Options shared by the sub-commands: ``--config FILE``, ``--set section.key=value`` and ``--layout``."""
from __future__ import annotations

from pathlib import Path

from ..base.config import load_config
from ..base.errors import UserError
from ..base.overrides import SET_HELP


def add_config_args(parser) -> None:
    """Add ``--config FILE`` and ``--set section.key=value`` to a sub-command's parser."""
    parser.add_argument("--config", metavar="FILE", help="tissue config TOML (default: the bundled config/tissue.toml)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help=SET_HELP)


def config_from_args(args):
    """The validated config named by ``args.config`` with ``args.overrides`` applied."""
    return load_config(getattr(args, "config", None), overrides=getattr(args, "overrides", None) or None)


LAYOUT_NAMES = ("trainee", "instructor")  # haptic_acu.session.blueprints.LAYOUTS (not imported: it loads rerun)


def add_layout_arg(parser, default: str) -> None:
    """Add ``--layout NAME|FILE.rbl``: the rerun viewer's layout (docs/viewer.md)."""
    parser.add_argument("--layout", metavar="NAME", default=None,
                        help=f"the rerun viewer's layout: {' or '.join(LAYOUT_NAMES)} (see docs/viewer.md), or a "
                             f"blueprint file FILE.rbl saved from the viewer (default: {default})")


def check_layout_arg(args) -> None:
    """One line and exit 2 for a ``--layout`` that is neither a bundled layout nor an existing .rbl."""
    value = getattr(args, "layout", None)
    if value is None or value in LAYOUT_NAMES:
        return
    if not value.endswith(".rbl"):
        raise UserError(f"--layout {value!r}: give {' or '.join(LAYOUT_NAMES)}, or a blueprint file NAME.rbl")
    if not Path(value).is_file():
        raise UserError(f"--layout {value}: no such file")


def check_speed_arg(args) -> None:
    """``--speed`` (run, study trial): a paced session's factor, refused in one line outside
    (0, MAX_SPEED]."""
    import math

    from ..session.engine import MAX_SPEED

    if not (math.isfinite(args.speed) and 0 < args.speed <= MAX_SPEED):
        raise UserError(f"--speed must be a number > 0 and at most {MAX_SPEED:g}, got {args.speed}")

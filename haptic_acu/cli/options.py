"""Options shared by the sub-commands: ``--config FILE`` and ``--set section.key=value``."""
from __future__ import annotations

from ..base.config import load_config
from ..base.overrides import SET_HELP


def add_config_args(parser) -> None:
    """Add ``--config FILE`` and ``--set section.key=value`` to a sub-command's parser."""
    parser.add_argument("--config", metavar="FILE", help="tissue config TOML (default: the bundled config/tissue.toml)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help=SET_HELP)


def config_from_args(args):
    """The validated config named by ``args.config`` with ``args.overrides`` applied."""
    return load_config(getattr(args, "config", None), overrides=getattr(args, "overrides", None) or None)

"""Rerun viewer helpers for ``--spawn``: fail at once without a display, find rerun beside Python.

``rerun`` (the viewer's executable) is installed with rerun-sdk into the environment's ``bin``
folder; when that environment is not activated it is not on ``PATH`` and rerun would tell the user
to install what is installed. :func:`check_spawn` puts the interpreter's folder on ``PATH`` for that
case and, on a machine with no display, stops with one line naming the alternatives instead of
letting the viewer fail for half a minute.
"""
from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

from ..base.errors import UserError

NO_DISPLAY = ("--spawn needs a display to open the rerun viewer, and there is none here (DISPLAY and "
              "WAYLAND_DISPLAY are not set): write a recording with --rrd FILE and open it with `rerun FILE` "
              "where there is a screen, or stream to a viewer running elsewhere with --connect HOST:PORT")


def has_display(environ=None) -> bool:
    """Whether a viewer window can open: always on macOS and Windows, else DISPLAY or WAYLAND_DISPLAY."""
    env = os.environ if environ is None else environ
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(env.get("DISPLAY") or env.get("WAYLAND_DISPLAY"))


def rerun_beside_python() -> None:
    """Put the interpreter's folder first on PATH if rerun is there but not on PATH (an environment
    used without activating it). The interpreter path is not resolved: a venv's python is a link."""
    exe = "rerun.exe" if sys.platform == "win32" else "rerun"
    here = Path(sys.executable).parent
    if shutil.which(exe) is None and (here / exe).is_file():
        os.environ["PATH"] = str(here) + os.pathsep + os.environ.get("PATH", "")


# replay has no --rrd: without --spawn it writes recording.rrd into its output folder
NO_DISPLAY_REPLAY = ("--spawn needs a display to open the rerun viewer, and there is none here (DISPLAY and "
                     "WAYLAND_DISPLAY are not set): leave out --spawn and the replay writes recording.rrd into its "
                     "--out folder (open it with `rerun FILE` where there is a screen), or stream to a viewer "
                     "running elsewhere with --connect HOST:PORT")


def check_spawn(message: str = NO_DISPLAY) -> None:
    """Before a ``--spawn`` sink is built: UserError(``message``: the command's own alternatives) at
    once without a display; rerun found beside the interpreter."""
    if not has_display():
        raise UserError(message)
    rerun_beside_python()

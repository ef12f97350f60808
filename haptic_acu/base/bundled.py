"""Where the bundled data lives: the default tissue, presets, meshes, scoring examples and trajectories.

In a source checkout or an editable install they are the repository's top-level ``config/`` and
``trajectories/``; an installed wheel carries them inside the package as ``haptic_acu/_bundled/``.
"""
from __future__ import annotations

from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent.parent  # haptic_acu/


def bundled_dir(name: str) -> Path:
    """The bundled folder ``name`` ("config" or "trajectories")."""
    installed = _PACKAGE / "_bundled" / name
    if installed.is_dir():
        return installed
    return _PACKAGE.parent / name


def bundled_trajectories() -> dict[str, Path]:
    """The bundled trajectories by name (the file's stem: ``default``, ``lateral_sweep``, ...; the
    atlas points' from ``trajectories/points/``: ``GB21_pleura``, ...)."""
    d = bundled_dir("trajectories")
    return {p.stem: p for p in sorted(d.glob("*.csv")) + sorted((d / "points").glob("*.csv"))}


def resolve_trajectory(arg) -> Path:
    """A TRAJECTORY argument as a path. A file or folder that exists is itself (the user's own file
    wins); a bare name with no folder part that is not a file here but names a bundled trajectory,
    with or without ``.csv`` (``default``, ``lateral_sweep.csv``), is the bundled file, so an
    installed wheel's trajectories can be used from any folder. Anything else is returned as given
    (the caller's "not found" names it, with :func:`not_found_hint`)."""
    p = Path(arg)
    if p.exists() or p.parent != Path("."):
        return p
    name = p.name[:-4] if p.name.endswith(".csv") else p.name
    return bundled_trajectories().get(name, p)


def not_found_hint() -> str:
    """The tail of a "trajectory file not found" message: the bundled names one may use instead."""
    names = ", ".join(bundled_trajectories())
    return f" (bundled trajectories, usable by name from any folder: {names})" if names else ""


def bundled_names() -> str:
    """The bundled trajectories' names, comma separated (for help texts)."""
    return ", ".join(bundled_trajectories())

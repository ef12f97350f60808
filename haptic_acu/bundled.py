"""Where the bundled data lives: the default tissue, presets, meshes, scoring examples and trajectories.

In a source checkout or an editable install they are the repository's top-level ``config/`` and
``trajectories/``; an installed wheel carries them inside the package as ``haptic_acu/_bundled/``.
"""
from __future__ import annotations

from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent


def bundled_dir(name: str) -> Path:
    """The bundled folder ``name`` ("config" or "trajectories")."""
    installed = _PACKAGE / "_bundled" / name
    if installed.is_dir():
        return installed
    return _PACKAGE.parent / name

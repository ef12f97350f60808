"""Keep numba's on-disk kernel cache in step with the sources it was compiled from.

numba decides whether a cached kernel is still valid from its own source file only (the file's
modification time and size, in the ``.nbi`` index). A kernel that calls or inlines a function of
another module keeps the callee's old code when only the callee's file changes: after a ``git
pull`` that edits ``needle.py``, the real-time loop in ``rtloop.py`` would run the old servo step
while a headless replay runs the new one. This module closes that gap for the package as a whole:
a digest of every ``.py`` file of the package (and of the folders installed into its namespace) is
kept beside the caches; when it differs, the package's ``.nbi``/``.nbc`` files are removed before any
kernel loads, and the next use (or ``python -m haptic_acu.cli.precompile``) compiles them again.

Only numba's own cache files in the package's ``__pycache__`` folders are ever removed. A read-only
install (numba then caches elsewhere) and ``NUMBA_CACHE_DIR`` are left alone.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

STAMP = "haptic_acu-kernels.sha256"
CACHE_SUFFIXES = (".nbi", ".nbc")


def source_digest(dirs: list[Path]) -> str:
    """SHA-256 over the relative path and bytes of every ``.py`` file under ``dirs`` (sorted)."""
    h = hashlib.sha256()
    for d in dirs:
        for f in sorted(d.rglob("*.py")):
            h.update(str(f.relative_to(d)).encode())
            h.update(b"\0")
            h.update(f.read_bytes())
            h.update(b"\0")
    return h.hexdigest()


def cache_files(dirs: list[Path]) -> list[Path]:
    """numba's cache files (``.nbi``, ``.nbc``) in the ``__pycache__`` folders under ``dirs``."""
    out = []
    for d in dirs:
        for pc in d.rglob("__pycache__"):
            out.extend(f for f in pc.iterdir() if f.suffix in CACHE_SUFFIXES)
    return out


def guard(dirs: list[Path]) -> bool:
    """Remove the kernel caches under ``dirs`` if their sources changed since the digest kept in
    ``dirs[0]/__pycache__``; write the new digest. True if caches were removed. Never raises on a
    read-only or missing folder (then numba's own rules apply)."""
    dirs = [d for d in dirs if d.is_dir()]
    if not dirs or os.environ.get("NUMBA_CACHE_DIR"):
        return False
    stamp = dirs[0] / "__pycache__" / STAMP
    try:
        digest = source_digest(dirs)
        if stamp.is_file() and stamp.read_text().strip() == digest:
            return False
        stale = cache_files(dirs)
        for f in stale:
            f.unlink(missing_ok=True)
        stamp.parent.mkdir(exist_ok=True)
        tmp = stamp.with_name(f"{STAMP}.{os.getpid()}.tmp")
        tmp.write_text(digest + "\n")
        os.replace(tmp, stamp)
        return bool(stale)
    except OSError:
        return False


def package_dirs() -> list[Path]:
    """The package's folder, then the folders installed into its namespace (``devices/``,
    ``bench/`` beside it in a source tree; inside it in an installed wheel)."""
    pkg = Path(__file__).resolve().parent.parent  # haptic_acu/
    dirs = [pkg]
    for name in ("devices", "bench"):
        for cand in (pkg / name, pkg.parent / name):
            if cand.is_dir() and (cand / "__init__.py").is_file():
                dirs.append(cand)
                break
    return dirs

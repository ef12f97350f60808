"""Keep numba's on-disk kernel cache in step with the sources it was compiled from.

numba decides whether a cached kernel is still valid from its own source file only (a hash of that
file, kept in the ``.nbi`` index). A kernel that calls or inlines a function of another module, or
reads one of its constants, keeps the old code when only that other file changes: after a ``git
pull`` that edits ``tissue/shf.py``, the real-time loop in ``servo/rtloop.py`` would feel the old
surfaces while a headless replay feels the new ones. This module closes that gap before any kernel
loads.

numba names each cache file after the module that holds the kernel (``shf.*.nbi``, ``shf.*.1.nbc``
in ``tissue/__pycache__``). For every module with such files the guard follows its imports within the
package (``import`` and ``from ... import``, relative or absolute, anywhere in the file, with the
packages' ``__init__`` files on the way) to the set of sources the kernels could have compiled in,
and removes that module's cache files when one of those sources changed since the last check; the
next use (or ``python -m haptic_acu.cli.precompile``) compiles them again. A module that registers
numba extensions used without an import (``@overload``, ``typeof_impl``, ``lower_*``, structref
types, ...) counts as a source of every kernel. Edits elsewhere (a command, a bench helper) keep the
caches. The hash and imports of each source are kept beside the caches, in
``haptic_acu/__pycache__/`` (``STAMP``); without it every cache is removed.

Only numba's own cache files in the package's ``__pycache__`` folders are ever removed. A read-only
install (numba then caches elsewhere) and ``NUMBA_CACHE_DIR`` are left alone.
"""
from __future__ import annotations

import ast
import hashlib
import json
import os
import re
from pathlib import Path

STAMP = "haptic_acu-kernels.json"
CACHE_SUFFIXES = (".nbi", ".nbc")
# numba extensions that take effect without the kernel's module importing the one that registers them
GLOBAL_HOOK = re.compile(rb"\b(overload\w*|lower_\w+|typeof_impl|type_callable|register_model|register_default"
                         rb"|make_attribute_wrapper|infer_global|infer_getattr|structref|StructRef)\b")


def sources(dirs: list[Path]) -> dict[str, Path]:
    """Module name -> ``.py`` file, for every file under ``dirs`` (``dirs[0]`` is the package,
    ``dirs[1:]`` folders installed into its namespace)."""
    names = [dirs[0].name] + [f"{dirs[0].name}.{d.name}" for d in dirs[1:]]
    out = {}
    for d, name in zip(dirs, names):
        for f in sorted(d.rglob("*.py")):
            parts = [name, *f.relative_to(d).with_suffix("").parts]
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = f
    return out


def statements(node: ast.AST):
    """Every statement under ``node``, at any depth (imports inside functions included)."""
    for child in ast.iter_child_nodes(node):
        if isinstance(child, (ast.stmt, ast.excepthandler, ast.match_case)):
            yield child
            yield from statements(child)


def imports(src: bytes, module: str, is_package: bool) -> tuple[list[str], bool]:
    """The names within ``module``'s top package that its source could import (for ``from m import
    x`` both ``m`` and ``m.x``: a name that is no module is ignored later), with the packages on the
    way to them and to ``module``, and whether it may register a numba extension that applies
    everywhere (one of the words appears in it)."""
    here = module if is_package else module.rpartition(".")[0]
    names = set()
    for node in statements(ast.parse(src)):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = here.rsplit(".", node.level - 1)[0] if node.level else ""
            base = ".".join(p for p in (base, node.module) if p)
            names.update([base, *(f"{base}.{a.name}" for a in node.names)])
    names |= {n.rsplit(".", i)[0] for n in names | {module} for i in range(1, n.count(".") + 1)}
    top = module.split(".")[0]
    return sorted(n for n in names if n.split(".")[0] == top), GLOBAL_HOOK.search(src) is not None


def closure(start: set[str], deps: dict[str, list[str]]) -> set[str]:
    """``start`` and every name reachable from it through ``deps``."""
    seen, todo = set(), list(start)
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo.extend(deps.get(m, ()))
    return seen


def cache_files(dirs: list[Path]) -> list[Path]:
    """numba's cache files (``.nbi``, ``.nbc``) in the ``__pycache__`` folders under ``dirs``."""
    out = []
    for d in dirs:
        for pc in d.rglob("__pycache__"):
            out.extend(f for f in pc.iterdir() if f.suffix in CACHE_SUFFIXES)
    return out


def source_of(cache_file: Path) -> Path:
    """The source file a numba cache file belongs to: ``d/__pycache__/shf.fit-12.py311.nbi`` (or
    ``cfunc-shf.fit-...``, numba's prefixed form) -> ``d/shf.py``."""
    module = cache_file.name.split(".")[0].rpartition("-")[2]
    return cache_file.parent.parent / f"{module}.py"


def scan(files: dict[str, Path], known: dict) -> dict[str, list]:
    """Module name -> [sha256 of its file's name and source, the names it imports, whether it
    registers a global hook]; a source whose hash is as in ``known`` is not parsed again (the name
    counts: a package's ``__init__`` reads its relative imports from another folder)."""
    out = {}
    for module, f in files.items():
        src = f.read_bytes()
        digest = hashlib.sha256(f.name.encode() + b"\0" + src).hexdigest()
        if known.get(module, [None])[0] == digest:
            out[module] = known[module]
            continue
        try:
            out[module] = [digest, *imports(src, module, f.name == "__init__.py")]
        except (SyntaxError, ValueError, RecursionError):  # it cannot be imported: no kernel compiled it in
            out[module] = [digest, [], False]
    return out


def stale_modules(old: dict, now: dict) -> set[str]:
    """The modules whose kernels may have compiled in a source that changed from ``old`` to ``now``
    (added and removed modules count as changed)."""
    changed = {m for m in old.keys() | now.keys() if old.get(m, [None])[0] != now.get(m, [None])[0]}
    hooks = {m for m, v in (*old.items(), *now.items()) if v[2]}
    deps = {m: v[1] for m, v in now.items()}
    return {m for m in now if changed & closure({m, *hooks}, deps)}


def read_record(stamp: Path) -> dict | None:
    """The record ``guard`` wrote, or None if there is none it could have written."""
    try:
        record = json.loads(stamp.read_text())
    except (OSError, ValueError):
        return None
    ok = isinstance(record, dict) and all(isinstance(v, list) and len(v) == 3 and isinstance(v[0], str)
                                          and isinstance(v[1], list) for v in record.values())
    return record if ok else None


def guard(dirs: list[Path]) -> bool:
    """Remove the cache files of each module under ``dirs`` whose sources changed since the record
    kept in ``dirs[0]/__pycache__`` (all cache files if there is no record) and write the new record.
    ``dirs[0]`` is the package, ``dirs[1:]`` folders installed into its namespace. True if files were
    removed. Never raises on a read-only or missing folder (then numba's own rules apply)."""
    if not dirs or not dirs[0].is_dir() or os.environ.get("NUMBA_CACHE_DIR"):
        return False
    dirs = [dirs[0]] + [d for d in dirs[1:] if d.is_dir()]
    stamp = dirs[0] / "__pycache__" / STAMP
    try:
        files = sources(dirs)
        old = read_record(stamp)
        now = scan(files, old or {})
        if now == old:
            return False
        keep = set() if old is None else {files[m] for m in now.keys() - stale_modules(old, now)}
        stale = [f for f in cache_files(dirs) if source_of(f) not in keep]
        for f in stale:
            f.unlink(missing_ok=True)
        stamp.parent.mkdir(exist_ok=True)
        tmp = stamp.with_name(f"{STAMP}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(now))
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

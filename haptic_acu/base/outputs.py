"""The output rule: what every command may do to the paths it writes (docs/outputs.md).

1. A file the user has is never replaced without ``--overwrite``; a folder never is, and an output
   folder must be new or empty (or, for the commands that resume, a folder they made themselves).
2. A command's outputs never share a path with each other or with its inputs. Paths are compared
   resolved (``..`` and symbolic links followed) and, when both exist, by device and inode (hard
   links); a file inside an output folder counts as one of the folder's files. ``--overwrite``
   never lets an output replace an input.
3. A command holding an output folder holds it alone: :func:`claim_folder` takes an exclusive
   ``flock`` on it (the kernel drops it when the process dies, so taking over a dead run's folder
   is atomic) and re-checks, under the lock, that the folder is still empty.
4. Text cells a command copies from a user's file into an output CSV are neutralised
   (:func:`safe_cell`): a cell starting with ``=``, ``+``, ``-``, ``@``, a tab or a carriage return
   that is not a number gets a leading ``'``, so a spreadsheet shows it as text, never runs it.

Every command declares its outputs and inputs to an :class:`Outputs` plan and calls
:meth:`Outputs.check` before it writes anything; the writers here (:func:`write_new`,
:func:`create_new`) keep the rule at the moment of writing (a file that appeared meanwhile is not
replaced). :data:`COMMAND_OUTPUTS` lists every output path of every command (tests enumerate it).
"""
from __future__ import annotations

import errno
import fcntl
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from .errors import UserError

OVERWRITE_HINT = "choose another path or add --overwrite"

# Every output of every command: (command, what, the file's name or the option naming the path).
# A folder's files are listed by name; "--opt" is an output path the user names.
COMMAND_OUTPUTS: dict[str, dict[str, tuple[str, ...]]] = {
    "replay": {"--out": ("samples.csv", "summary.json", "force_depth.png", "recording.rrd"),
               "--out (batch)": ("summaries.csv", "insertions.csv", "punctures.csv")},
    "run": {"--out": ("recording.csv", "samples.csv", "summary.json", "force_depth.png", "recording.rrd"),
            "--record": (), "--rrd": ()},
    "compare": {"--out": ("compare.json", "compare.png")},
    "score": {"--out": ("weights.csv", "scores.csv", "score.json", "scores.png")},
    "fit": {"--out": ()},
    "calibrate": {"--out": ()},
    "bench": {"--json": ()},
    "points": {},  # prints only
    "view": {},  # serves a recording over HTTP on 127.0.0.1; writes nothing
    "study": {"plan --out": (), "example --out": (), "analyze --out": (), "replay --out": ()},
    "cohort": {"--out": ("insertions.parquet", "insertions.csv", "sessions.parquet", "sessions.csv",
                         "report.json")},
}


def resolved(path) -> Path:
    """``path`` absolute, ``~`` expanded, ``..`` and symbolic links followed (as far as they exist)."""
    return Path(os.path.realpath(Path(path).expanduser()))


def _inode(path: Path):
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def same_path(a, b) -> bool:
    """True if ``a`` and ``b`` name one file: the same resolved path, or the same inode."""
    if resolved(a) == resolved(b):
        return True
    ia = _inode(Path(a))
    return ia is not None and ia == _inode(Path(b))


def within(path, folder) -> bool:
    """True if ``path`` (resolved) is ``folder`` (resolved) or lies inside it."""
    p, f = resolved(path), resolved(folder)
    return p == f or f in p.parents


@dataclass
class _Out:
    label: str
    path: Path
    folder: bool = False
    files: tuple[str, ...] = ()
    resumable: str | None = None  # a marker inside a folder this command made itself
    owner: str = ""  # whose output a resumable folder is ("cohort")


@dataclass
class Outputs:
    """A command's output plan. ``outputs.file("--record", path)``, ``outputs.folder("--out", dir,
    files=(...))``, ``outputs.input("--trajectory", path)``, then ``outputs.check()`` raises one
    :class:`UserError` line on the first breach of the rule (see the module)."""

    overwrite: bool = False
    outs: list[_Out] = field(default_factory=list)
    ins: list[tuple[str, Path]] = field(default_factory=list)

    def input(self, label: str, path) -> "Outputs":
        if path is not None:
            self.ins.append((label, Path(path)))
        return self

    def file(self, label: str, path) -> "Outputs":
        if path is not None:
            self.outs.append(_Out(label, Path(path)))
        return self

    def folder(self, label: str, path, files=(), resumable: str | None = None, owner: str = "") -> "Outputs":
        if path is not None:
            self.outs.append(_Out(label, Path(path), folder=True, files=tuple(files), resumable=resumable,
                                  owner=owner))
        return self

    def _paths(self):
        """(label, path, is_folder, owner) of every output path, a folder's files included (owner:
        the index of the output they belong to)."""
        for k, o in enumerate(self.outs):
            yield o.label, o.path, o.folder, k
            for name in o.files:
                yield f"{o.label}'s {name}", o.path / name, False, k

    def check(self) -> None:
        paths = list(self._paths())
        for label, p, is_folder, _ in paths:
            for ilabel, src in self.ins:
                if same_path(p, src) or (is_folder and within(src, p)):
                    raise UserError(f"{p}: {label} would {'hold' if is_folder else 'replace'} the "
                                    f"input {ilabel} ({src}); choose another path")
        for i, (la, a, fa, ka) in enumerate(paths):
            for lb, b, fb, kb in paths[i + 1:]:
                if ka == kb:
                    continue  # a folder and its own files
                if same_path(a, b) or (fa and within(b, a)) or (fb and within(a, b)):
                    raise UserError(f"{b}: {lb} and {la} ({a}) would be written to one path; give "
                                    "them different paths")
        for o in self.outs:
            if o.folder:
                check_folder(o.path, o.label, o.resumable, o.owner)
            else:
                check_file(o.path, o.label, self.overwrite)


def check_file(path, label: str = "output", overwrite: bool = False) -> None:
    """An output file's path: its folder exists; it is not a folder; it does not exist (or a link)
    unless ``overwrite``."""
    p = Path(path)
    if p.is_dir():
        raise UserError(f"{p}: is a folder; {label} takes a file name")
    if not p.parent.is_dir() and str(p.parent):
        raise UserError(f"{p}: folder {p.parent} does not exist")
    if (p.exists() or p.is_symlink()) and not overwrite:
        raise UserError(f"{p}: exists; {OVERWRITE_HINT}")


def check_folder(path, label: str = "--out", resumable: str | None = None, owner: str = "") -> None:
    """An output folder: new, or an empty folder, or (``resumable``) one holding that marker (a folder
    ``owner``, the command, made)."""
    p = Path(path)
    if p.is_symlink() and not p.is_dir():
        raise UserError(f"{p}: is a link to nothing; choose another {label}")
    if p.exists() and not p.is_dir():
        raise UserError(f"{p}: exists and is not a folder; choose another {label}")
    if p.is_dir() and any(p.iterdir()) and not (resumable and (p / resumable).exists()):
        if resumable:
            raise UserError(f"{p}: folder exists, is not empty and is not a {owner or 'command'} output; "
                            f"choose another {label}")
        raise UserError(f"{p}: output folder exists and is not empty; choose another {label}")


def create_new(path, overwrite: bool = False, mode: str = "wb"):
    """Open ``path`` for writing as a new file (``O_EXCL``): a file that appeared since the check is
    refused unless ``overwrite``. With ``overwrite`` a symbolic link is replaced (never written
    through to its target), a regular file truncated, a device (/dev/null) written, a folder refused."""
    p = Path(path)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0)
    try:
        try:
            fd = os.open(p, flags, 0o644)
        except FileExistsError:
            if not overwrite:
                raise UserError(f"{p}: exists; {OVERWRITE_HINT}") from None
            if p.is_symlink():
                p.unlink()
                fd = os.open(p, flags, 0o644)
            elif p.is_dir():
                raise UserError(f"{p}: is a folder; not replaced") from None
            else:
                fd = os.open(p, os.O_WRONLY | (os.O_TRUNC if p.is_file() else 0) | getattr(os, "O_CLOEXEC", 0))
    except OSError as e:
        raise UserError(f"{p}: cannot create: {e.strerror or e}") from None
    return os.fdopen(fd, mode)


def write_new(path, data: bytes | str, overwrite: bool = False) -> None:
    """Write ``data`` to ``path`` whole or not at all: a temporary file beside it, then linked into
    place (refused if ``path`` exists, unless ``overwrite``: then renamed over it)."""
    p = Path(path)
    if isinstance(data, str):
        data = data.encode("utf-8")
    try:
        fd, tmp = tempfile.mkstemp(dir=p.parent if str(p.parent) else ".", prefix=f".{p.name}.",
                                   suffix=".partial")
    except OSError as e:
        raise UserError(f"{p}: cannot write: {e.strerror or e}") from None
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        if overwrite:
            if p.is_dir() and not p.is_symlink():
                raise UserError(f"{p}: is a folder; not replaced")
            os.replace(tmp, p)
            return
        try:
            os.link(tmp, p)
        except FileExistsError:
            raise UserError(f"{p}: exists; {OVERWRITE_HINT}") from None
        except OSError as e:
            if e.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV):
                raise
            with create_new(p) as f:  # a file system without hard links
                f.write(data)
    except OSError as e:
        raise UserError(f"{p}: cannot write: {e.strerror or e}") from None
    finally:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass


class FolderLock:
    """An exclusive, non-blocking ``flock`` on ``path`` (a folder, or a lock file created if
    missing) held until :meth:`release`. The kernel drops it when the holder dies, so a dead run's
    lock is taken over atomically: of two processes racing for it, exactly one gets it."""

    def __init__(self, path, busy: str):
        self.path = Path(path)
        self.busy = busy
        self.fd: int | None = None

    def acquire(self) -> "FolderLock":
        try:
            if self.path.is_dir():
                fd = os.open(self.path, os.O_RDONLY | os.O_DIRECTORY | getattr(os, "O_CLOEXEC", 0))
            else:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
        except OSError as e:
            raise UserError(f"{self.path}: cannot lock: {e.strerror or e}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = ""
            if not self.path.is_dir():
                try:
                    pid = os.pread(fd, 32, 0).decode(errors="replace").strip()
                    holder = f" (pid {pid})" if pid.isdigit() else ""
                except OSError:
                    pass
            os.close(fd)
            raise UserError(self.busy.format(holder=holder)) from None
        if not self.path.is_dir():
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self.fd = fd
        return self

    def release(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None

    def discard_if_empty(self) -> None:
        """Remove the claimed folder if this command made it and wrote nothing into it (a session that
        could not start leaves nothing behind)."""
        if getattr(self, "created", False):
            try:
                self.path.rmdir()
            except OSError:
                pass

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()


def fresh_folder(path) -> Path:
    """``path``, or ``path-2``, ``path-3``... the first that does not exist (a default output folder)."""
    p = Path(path)
    if not (p.exists() or p.is_symlink()):
        return p
    i = 2
    while p.with_name(f"{p.name}-{i}").exists() or p.with_name(f"{p.name}-{i}").is_symlink():
        i += 1
    return p.with_name(f"{p.name}-{i}")


def plain_text_figures():
    """A context in which every text a figure draws is drawn as given: no mathtext (a name like
    ``$\\foo$`` from a user's file is shown, not parsed as TeX), no LaTeX. Build and save figures in it."""
    import matplotlib

    return matplotlib.rc_context({"text.parse_math": False, "text.usetex": False})


def plain_text(fn):
    """Decorator: ``fn`` (which builds and saves a figure) runs in :func:`plain_text_figures`."""
    import functools

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with plain_text_figures():
            return fn(*args, **kwargs)
    return wrapper


def claim_folder(path, label: str = "--out", busy: str | None = None) -> FolderLock:
    """Make ``path`` (new or empty) and hold it alone: a second command claiming it while this one
    runs is refused (``busy``, one line), as is one after this one wrote into it (not empty).
    Release with ``.release()``."""
    p = Path(path)
    if p.is_symlink() and not p.is_dir():
        raise UserError(f"{p}: is a link to nothing; choose another {label}")
    if p.exists() and not p.is_dir():
        raise UserError(f"{p}: exists and is not a folder; choose another {label}")
    created = not p.exists()
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UserError(f"{p}: cannot create the output folder: {e.strerror or e}") from None
    lock = FolderLock(p, busy or f"{p}: another session is writing to this folder; wait for it or "
                                  f"choose another {label}").acquire()
    lock.created = created
    try:
        check_folder(p, label)  # under the lock: a command that finished before us left its files
    except BaseException:
        lock.release()
        raise
    return lock


_FORMULA_START = ("=", "+", "-", "@", "\t", "\r")


def safe_cell(value):
    """``value`` as written to an output CSV: a text cell a spreadsheet would run as a formula
    (starting with = + - @, a tab or a carriage return, and not a number) gets a leading ``'``."""
    if not isinstance(value, str) or not value.startswith(_FORMULA_START):
        return value
    try:
        float(value)
        return value  # "-1.5", "+3": a number, shown as one
    except ValueError:
        return "'" + value

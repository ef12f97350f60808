"""A study folder: what ``study plan`` writes and every other ``study`` command reads.

::

    STUDY/study.json     models, seed, participants, indices, scale, the tool's version and each
                         model's config hash (no key: which system is which model is not here)
    STUDY/key.json       the key: system code -> model, and each model's config (read only by
                         `study trial` to load the model, `study replay` and `study analyze`; never
                         shown)
    STUDY/plan.csv       participant,trial,system (the codes only)
    STUDY/ratings.csv    `haptic-acu score`'s ratings format: system,rater + the seven indices;
                         corrections keep the replaced row as a `#` comment line above the new one
    STUDY/sessions/P01-T1/        one trial's session (trial.json, recording.csv, samples.csv,
                                  summary.json, force_depth.png); a redo or a second attempt goes
                                  to P01-T1.2, P01-T1.3, ... and the earlier folders stay

Every write of a study file is atomic (a temporary file in the same folder, flushed, then renamed
over the old one) under an exclusive lock on ``STUDY/.lock``: a signal or a crash leaves either the
old file or the new one, never half of a row.
"""
from __future__ import annotations

import contextlib
import csv
import datetime as _dt
import fcntl
import hashlib
import io
import json
import os
import re
import threading
import tomllib
from dataclasses import dataclass
from pathlib import Path

from ..analysis.scoring import INDICES
from ..base.errors import UserError
from .ratings import DEFAULT_SCALE, check_row, fmt_score

FORMAT = "haptic-acu study 1"
KINDS = ("forcenet", "msm", "fem", "bem", "shf")  # model.kind's values
RATINGS_HEADER = ("system", "rater") + INDICES
_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_-]{0,31}$")
_SESSION = re.compile(r"^(?P<p>[A-Za-z0-9]+)-T(?P<t>\d+)(?:\.(?P<a>\d+))?$")


def now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


# ---------------------------------------------------------------------------------------------
# atomic files


def write_atomic(path: Path, text: str, exclusive: bool = False) -> None:
    """``path`` becomes ``text`` all at once (``exclusive``: only if it does not exist yet)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    try:
        with open(tmp, "w", encoding="utf-8", newline="") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        if exclusive:
            os.link(tmp, path)  # fails if path exists: never replaces the user's file
        else:
            os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)


@contextlib.contextmanager
def locked(folder: Path):
    """An exclusive lock on ``folder/.lock`` (one writer of the study's files at a time)."""
    fd = os.open(Path(folder) / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _read_json(path: Path) -> dict:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UserError(f"{path}: not found (is this a study folder made by `haptic-acu study plan`?)") from None
    except (OSError, UnicodeDecodeError) as e:
        raise UserError(f"{path}: cannot read: {getattr(e, 'strerror', None) or e}") from None
    except json.JSONDecodeError as e:
        raise UserError(f"{path}: line {e.lineno}: not valid JSON ({e.msg})") from None
    if not isinstance(doc, dict):
        raise UserError(f"{path}: expected a JSON object")
    return doc


# ---------------------------------------------------------------------------------------------
# models and their configs


@dataclass(frozen=True)
class ModelSpec:
    """One model of the study: a ``model.kind`` on the study's config, or a config file of its own."""

    name: str
    kind: str | None  # model.kind, or None for a config file of its own
    config: str | None  # the config file (absolute), None: the bundled default
    overrides: tuple[str, ...]

    def config_args(self) -> tuple[str | None, list[str]]:
        ov = list(self.overrides)
        if self.kind is not None:
            ov.append(f"model.kind={self.kind}")
        return self.config, ov


def parse_models(text: str, config: str | None, overrides) -> list[ModelSpec]:
    """``--models forcenet,fem`` (``model.kind`` values on ``--config`` + ``--set``) or items
    ``NAME=FILE.toml`` (a config file of its own, plus ``--set``)."""
    items = [s.strip() for s in text.split(",")]
    if any(not s for s in items):
        raise UserError(f"--models {text}: empty name in the list")
    specs = []
    for item in items:
        name, eq, file = item.partition("=")
        name = name.strip()
        if not _NAME.match(name):
            raise UserError(f"--models: {name!r} is not a model name (a letter, then letters, digits, - or _)")
        if eq:
            p = Path(file.strip())
            if not p.is_file():
                raise UserError(f"--models {item}: config file {p} not found")
            specs.append(ModelSpec(name, None, str(p.resolve()), tuple(overrides)))
        else:
            if name not in KINDS:
                raise UserError(f"--models: unknown model {name!r} (model.kind is one of {', '.join(KINDS)}; "
                                "or NAME=FILE.toml for a config of its own)")
            specs.append(ModelSpec(name, name, str(Path(config).resolve()) if config else None, tuple(overrides)))
    names = [s.name for s in specs]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup:
        raise UserError(f"--models: {dup!r} is listed twice")
    return specs


def config_hash(spec: ModelSpec) -> str:
    """sha256 of the model's config as the loader sees it: the TOML after the overrides (keys
    sorted), and the bytes of a skin coefficients file it names. Validates the config first (a bad
    one is a one-line error naming the key)."""
    from ..base.config import DEFAULT_CONFIG, load_config
    from ..base.overrides import apply_overrides

    path, ov = spec.config_args()
    cfg = load_config(path, overrides=ov or None)
    p = Path(path) if path else DEFAULT_CONFIG
    data = apply_overrides(tomllib.loads(p.read_bytes().decode("utf-8-sig")), ov)
    h = hashlib.sha256(json.dumps(data, sort_keys=True, separators=(",", ":")).encode())
    if cfg.body.skin_coefficients:
        h.update(Path(cfg.body.skin_coefficients).read_bytes())
    return h.hexdigest()


def config_text(spec: ModelSpec) -> str:
    from ..base.config import DEFAULT_CONFIG
    return (Path(spec.config) if spec.config else DEFAULT_CONFIG).read_text(encoding="utf-8-sig")


# ---------------------------------------------------------------------------------------------
# the study


@dataclass(frozen=True)
class Trial:
    participant: str
    trial: int
    system: str


@dataclass(frozen=True)
class Attempt:
    """One session folder under STUDY/sessions/ and its trial.json."""

    folder: Path
    participant: str
    trial: int
    number: int  # 1 for P-T, k for P-T.k
    status: str  # running | complete | interrupted | fault
    doc: dict


@dataclass(frozen=True)
class RatingRow:
    line: int
    system: str
    rater: str
    values: tuple[float, ...]


class Study:
    """A study folder, read: study.json, plan.csv, ratings.csv, the sessions. The key is read only
    by :meth:`key`."""

    def __init__(self, folder):
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise UserError(f"{folder}: no such study folder")
        self.json_path = self.folder / "study.json"
        self.doc = _read_json(self.json_path)
        if self.doc.get("format") != FORMAT:
            raise UserError(f"{self.json_path}: not a study file of this tool (format {self.doc.get('format')!r})")
        try:
            self.models: list[str] = list(self.doc["models"])
            self.participants: list[str] = list(self.doc["participants"])
            self.trials_per_model = int(self.doc["trials_per_model"])
            self.scale = dict(self.doc["scale"])
            self.hashes: dict[str, str] = dict(self.doc["config_hash"])
        except (KeyError, TypeError, ValueError) as e:
            raise UserError(f"{self.json_path}: missing or bad entry {e}") from None
        self.n_trials = len(self.models) * self.trials_per_model
        self.plan = self._read_plan()

    # -- paths
    @property
    def plan_path(self) -> Path:
        return self.folder / "plan.csv"

    @property
    def ratings_path(self) -> Path:
        return self.folder / "ratings.csv"

    @property
    def key_path(self) -> Path:
        return self.folder / "key.json"

    @property
    def sessions(self) -> Path:
        return self.folder / "sessions"

    def _read_plan(self) -> dict[tuple[str, int], Trial]:
        path = self.plan_path
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as e:
            raise UserError(f"{path}: cannot read: {e.strerror}") from None
        rows = list(csv.reader(io.StringIO(text)))
        if not rows or [c.strip() for c in rows[0]] != ["participant", "trial", "system"]:
            raise UserError(f"{path}: line 1: expected the header participant,trial,system")
        plan = {}
        for n, row in enumerate(rows[1:], 2):
            if not row:
                continue
            try:
                p, t, s = (c.strip() for c in row)
                t = int(t)
            except ValueError:
                raise UserError(f"{path}: line {n}: expected participant,trial,system") from None
            if p not in self.participants or not 1 <= t <= self.n_trials:
                raise UserError(f"{path}: line {n}: participant {p} trial {t} is not in {self.json_path.name}")
            plan[p, t] = Trial(p, t, s)
        for p in self.participants:
            for t in range(1, self.n_trials + 1):
                if (p, t) not in plan:
                    raise UserError(f"{path}: participant {p} has no trial {t}")
        return plan

    def participant(self, name: str) -> str:
        if name not in self.participants:
            raise UserError(f"--participant {name}: not in this study ({self.participants[0]}-{self.participants[-1]})")
        return name

    def trials_of(self, p: str) -> list[Trial]:
        return [self.plan[p, t] for t in range(1, self.n_trials + 1)]

    def rater_of(self, trial: Trial) -> str:
        """The ``rater`` of a trial's row in ratings.csv: the participant, with ``/k`` (the k-th
        trial of this system) when each model is met more than once."""
        if self.trials_per_model == 1:
            return trial.participant
        k = sum(1 for t in self.trials_of(trial.participant)[:trial.trial] if t.system == trial.system)
        return f"{trial.participant}/{k}"

    def trial_of_rating(self, system: str, rater: str) -> Trial | None:
        p, _, k = rater.partition("/")
        if p not in self.participants:
            return None
        for t in self.trials_of(p):
            if t.system == system and self.rater_of(t) == rater:
                return t
        return None

    # -- the key
    def key(self) -> dict:
        """key.json, checked against study.json (read only where the model must be known)."""
        key = _read_json(self.key_path)
        try:
            systems = key["systems"]
            specs = {m: key["models"][m] for m in self.models}
        except (KeyError, TypeError) as e:
            raise UserError(f"{self.key_path}: missing entry {e}") from None
        for p in self.participants:
            if p not in systems or sorted(systems[p].values()) != sorted(self.models):
                raise UserError(f"{self.key_path}: participant {p}'s systems do not cover the study's models")
        for m, spec in specs.items():
            if spec.get("config_hash") != self.hashes.get(m):
                raise UserError(f"{self.key_path}: model {m}'s config hash differs from {self.json_path.name}'s")
        return key

    def model_of(self, key: dict, trial: Trial) -> str:
        try:
            return key["systems"][trial.participant][trial.system]
        except KeyError:
            raise UserError(f"{self.key_path}: no model for {trial.participant}'s {trial.system}") from None

    def spec(self, key: dict, model: str) -> ModelSpec:
        m = key["models"][model]
        return ModelSpec(model, m.get("kind"), m.get("config"), tuple(m.get("overrides", ())))

    def checked_config(self, key: dict, model: str):
        """The model's validated config, refused (one line) if it is no longer the config the plan
        hashed: the trials of a study must all run the model they were planned with."""
        from ..base.config import load_config

        spec = self.spec(key, model)
        h = config_hash(spec)
        if h != self.hashes[model]:
            where = spec.config or "the bundled config"
            raise UserError(f"{self.json_path}: a model's config ({where}) changed since the plan (hash "
                            f"{h[:12]} instead of {self.hashes[model][:12]}); restore it or plan a new study")
        path, ov = spec.config_args()
        return load_config(path, overrides=ov or None)

    # -- sessions
    def attempts(self) -> list[Attempt]:
        out = []
        if not self.sessions.is_dir():
            return out
        for d in sorted(self.sessions.iterdir()):
            m = _SESSION.match(d.name)
            if not m or not d.is_dir():
                continue
            p, t, a = m.group("p"), int(m.group("t")), int(m.group("a") or 1)
            try:
                doc = json.loads((d / "trial.json").read_text(encoding="utf-8"))
                status = str(doc.get("status", "running"))
            except (OSError, ValueError):
                doc, status = {}, "running"
            out.append(Attempt(d, p, t, a, status, doc))
        out.sort(key=lambda x: (x.participant, x.trial, x.number))
        return out

    def attempts_of(self, p: str, t: int) -> list[Attempt]:
        return [a for a in self.attempts() if a.participant == p and a.trial == t]

    def new_session_folder(self, trial: Trial) -> tuple[Path, int]:
        """The trial's next session folder, created (never one that exists)."""
        self.sessions.mkdir(exist_ok=True)
        k = 1
        while True:
            name = f"{trial.participant}-T{trial.trial}" + ("" if k == 1 else f".{k}")
            d = self.sessions / name
            try:
                d.mkdir()
                return d, k
            except FileExistsError:
                k += 1

    # -- ratings
    def read_ratings(self) -> tuple[list[str], list[RatingRow]]:
        """ratings.csv's lines (kept, for a rewrite) and its data rows, checked: the header, the
        codes and raters against the plan, each value on the scale, no (system, rater) twice."""
        path = self.ratings_path
        try:
            text = path.read_text(encoding="utf-8-sig")
        except FileNotFoundError:
            return [], []
        except OSError as e:
            raise UserError(f"{path}: cannot read: {e.strerror}") from None
        lines = text.splitlines()
        rows, header, seen = [], None, {}
        for n, raw in enumerate(lines, 1):
            s = raw.strip()
            if not s or s.startswith("#"):
                continue
            cells = [c.strip() for c in next(csv.reader([raw]))]
            if header is None:
                if tuple(cells) != RATINGS_HEADER:
                    raise UserError(f"{path}: line {n}: expected the header {','.join(RATINGS_HEADER)}")
                header = cells
                continue
            if len(cells) != len(RATINGS_HEADER):
                raise UserError(f"{path}: line {n}: {len(cells)} fields, expected {len(RATINGS_HEADER)}")
            system, rater = cells[0], cells[1]
            if self.trial_of_rating(system, rater) is None:
                raise UserError(f"{path}: line {n}: rater {rater!r} has no trial of {system!r} in the plan")
            if (system, rater) in seen:
                raise UserError(f"{path}: line {n}: {rater} already rated {system} on line {seen[system, rater]}")
            seen[system, rater] = n
            try:
                values = check_row(cells[2:], self.scale)
            except ValueError as e:
                raise UserError(f"{path}: line {n}: {e}") from None
            rows.append(RatingRow(n, system, rater, tuple(values)))
        return lines, rows

    def rated(self) -> dict[tuple[str, int], RatingRow]:
        """(participant, trial) -> its row in ratings.csv."""
        _, rows = self.read_ratings()
        out = {}
        for r in rows:
            t = self.trial_of_rating(r.system, r.rater)
            out[t.participant, t.trial] = r
        return out

    def record_ratings(self, trial: Trial, values, note: str) -> RatingRow | None:
        """Put a trial's seven ratings into ratings.csv, atomically, under the lock. A row already
        there is replaced, and kept as a ``#`` comment line above the new one (``note`` says why).
        Returns the replaced row, if any."""
        values = check_row([fmt_score(v) for v in values], self.scale)
        rater = self.rater_of(trial)
        new = _csv_line([trial.system, rater] + [fmt_score(v) for v in values])
        with locked(self.folder):
            lines, rows = self.read_ratings()
            if not lines:
                lines = [_csv_line(RATINGS_HEADER)]
            old = next((r for r in rows if r.system == trial.system and r.rater == rater), None)
            if old is None:
                lines.append(new)
            else:
                i = old.line - 1
                lines[i:i + 1] = [f"# {now()} {note}; it replaced: {lines[i]}", new]
            write_atomic(self.ratings_path, "\n".join(lines) + "\n")
        return old


def _csv_line(cells) -> str:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="").writerow(cells)
    return buf.getvalue()


def participant_ids(n: int) -> list[str]:
    width = max(2, len(str(n)))
    return [f"P{k:0{width}d}" for k in range(1, n + 1)]


def write_trial_json(folder: Path, doc: dict) -> None:
    write_atomic(folder / "trial.json", json.dumps(doc, indent=2) + "\n")


def ratings_file_text(study_name: str) -> str:
    return (f"# Ratings of {study_name}, in `haptic-acu score`'s format: one row per trial, the system as "
            "the participant saw it.\n" + _csv_line(RATINGS_HEADER) + "\n")


__all__ = ["Study", "ModelSpec", "parse_models", "config_hash", "participant_ids", "write_atomic", "locked",
           "DEFAULT_SCALE", "FORMAT"]

"""The patient: sex, BMI and age, and what they do to a point's anatomy (docs/atlas.md, "The patient").

``--patient sex=female,bmi=19,age=40`` (any subset; the default patient is a man of BMI 22, age 30),
``--patient random`` or ``random:SEED`` (a patient drawn from published distributions, with each
structure's individual deviation; the seed is recorded so the session can be repeated).

What changes, in order of preference (docs/atlas.md says which point uses which):

* a structure with a published sex difference takes the study's mean for that sex
  (``depth_female_mm``: GB21, GV16, LU1);
* a structure with a published BMI relation scales its depth by ``1 + slope (BMI - bmi_ref)``
  (GB21: Chou et al. 2015's MRI means; BL13: Kim et al. 2002's CT regression);
* otherwise the subcutaneous fat layer scales with the fat mass index, BMI x body-fat fraction, the
  body fat from Deurenberg et al. 1991's adult formula (BF% = 1.2 BMI + 0.23 age - 10.8 sex - 5.4,
  sex 1 for men), relative to the default patient's; structures below the fat move down by the
  fat's change. The proportionality of the layer's thickness to the fat mass index is ours.
* a random patient adds each structure's individual deviation, a normal draw with the study's SD.

Breathing moves a structure (GB21's pleura: Chu et al. 2018) by ``breathing_mm`` peak to peak,
shallowest at inspiration: ``depth(t) = depth - breathing_mm (1 - cos(2 pi t / period)) / 2``.
"""
from __future__ import annotations

import math
import secrets
from dataclasses import asdict, dataclass, field

import numpy as np

from ..base.errors import UserError
from .atlas import Point

SEXES = ("male", "female")
BMI_RANGE = (14.0, 40.0)  # Deurenberg et al. 1991's adults spanned BMI 13.9-40.9
AGE_RANGE = (18.0, 83.0)  # and ages up to 83 (adults from 16)
DEFAULT_SEX, DEFAULT_BMI, DEFAULT_AGE = "male", 22.0, 30.0  # ours (Chen et al. 2018's median age: 29)
# A random patient: BMI from Chou et al. 2015's 394 adults (22.7 +- 4.0 kg/m2), clipped to
# BMI_RANGE; sex even; age uniform 20-70 (ours).
RANDOM_BMI_MEAN, RANDOM_BMI_SD = 22.7, 4.0
RANDOM_AGE = (20.0, 70.0)
MIN_DEPTH_MM = 1.0  # no structure comes closer to the skin than this (a guard for extreme draws)


@dataclass(frozen=True)
class Patient:
    sex: str = DEFAULT_SEX
    bmi: float = DEFAULT_BMI
    age: float = DEFAULT_AGE
    seed: int | None = None  # a random patient's seed (its structures deviate individually)
    spec: str = ""  # as given

    @property
    def random(self) -> bool:
        return self.seed is not None

    def as_dict(self) -> dict:
        d = asdict(self)
        d["bmi"] = round(self.bmi, 2)
        d["age"] = round(self.age, 1)
        return d


DEFAULT_PATIENT = Patient()


def _number(key: str, text: str, lo: float, hi: float, source: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise UserError(f"{source}: {key}: must be a number, got {text!r}") from None
    if not (math.isfinite(v) and lo <= v <= hi):
        raise UserError(f"{source}: {key}: must be within {lo:g}-{hi:g}, got {text}")
    return v


def random_patient(seed: int | None = None, spec: str = "random") -> Patient:
    """A patient drawn from the published distributions (module docstring), from ``seed`` (drawn
    from the OS if None; recorded in the patient)."""
    if seed is None:
        seed = secrets.randbits(32)
    rng = np.random.default_rng([seed, 0])
    sex = SEXES[int(rng.random() < 0.5)]
    bmi = float(np.clip(rng.normal(RANDOM_BMI_MEAN, RANDOM_BMI_SD), *BMI_RANGE))
    age = float(rng.uniform(*RANDOM_AGE))
    return Patient(sex=sex, bmi=round(bmi, 2), age=round(age, 1), seed=int(seed), spec=spec)


def patient_file(path: str) -> str:
    """A patient TOML file (keys ``sex``, ``bmi``, ``age``, or ``random = true`` with an optional
    ``seed``; every key checked, an unknown one refused) as ``--patient`` text."""
    import tomllib
    from pathlib import Path
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UserError(f"{path}: no such patient file") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise UserError(f"{path}: cannot read the patient file: {e}") from None
    for key in data:
        if key not in ("sex", "bmi", "age", "random", "seed"):
            raise UserError(f"{path}: {key}: unknown key (keys: sex, bmi, age, random, seed)")
    if data.get("random", False) is not False:
        if data["random"] is not True or set(data) - {"random", "seed"}:
            raise UserError(f"{path}: random: true, with at most a seed (no sex, bmi or age)")
        seed = data.get("seed")
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or seed < 0):
            raise UserError(f"{path}: seed: must be a non-negative integer, got {seed!r}")
        return "random" if seed is None else f"random:{seed}"
    if "seed" in data:
        raise UserError(f"{path}: seed: only with random = true")
    return ",".join(f"{k}={data[k]}" for k in ("sex", "bmi", "age") if k in data)


def parse_patient(spec: str | None, source: str = "--patient") -> Patient:
    """``sex=female,bmi=19,age=40`` (any subset), ``random`` or ``random:SEED``, or a patient
    ``.toml`` file (:func:`patient_file`); None or "" the default patient. Bad values: one line
    naming ``source`` (the file) and the key."""
    if spec is None or not spec.strip():
        return DEFAULT_PATIENT
    s = spec.strip()
    if s.endswith(".toml"):
        return parse_patient(patient_file(s), source=s)
    if s == "random" or s.startswith("random:"):
        if s == "random":
            return random_patient(None, spec=s)
        text = s.split(":", 1)[1]
        if not text.isdigit():
            raise UserError(f"{source}: seed: must be a non-negative integer, got {text!r}")
        return random_patient(int(text), spec=s)
    values = {}
    for part in s.split(","):
        if "=" not in part:
            raise UserError(f"{source}: {part.strip()!r}: expected key=value (keys: sex, bmi, age) or 'random'")
        key, val = (x.strip() for x in part.split("=", 1))
        if key in values:
            raise UserError(f"{source}: {key}: given twice")
        if key == "sex":
            if val not in SEXES:
                raise UserError(f"{source}: sex: must be male or female, got {val!r}")
            values[key] = val
        elif key == "bmi":
            values[key] = _number("bmi", val, *BMI_RANGE, source)
        elif key == "age":
            values[key] = _number("age", val, *AGE_RANGE, source)
        else:
            raise UserError(f"{source}: {key}: unknown key (keys: sex, bmi, age)")
    return Patient(**values, spec=s)


def body_fat_percent(sex: str, bmi: float, age: float) -> float:
    """Deurenberg, Weststrate and Seidell 1991 (Br J Nutr 65:105-14), adults: % body fat."""
    return 1.2 * bmi + 0.23 * age - 10.8 * (1.0 if sex == "male" else 0.0) - 5.4


def fat_scale(p: Patient) -> float:
    """The subcutaneous fat layer's thickness relative to the default patient's: the ratio of the fat
    mass indices (BMI x body-fat fraction). Floored at 0.2 (a very lean patient keeps some fat)."""
    ref = DEFAULT_BMI * body_fat_percent(DEFAULT_SEX, DEFAULT_BMI, DEFAULT_AGE)
    return max(0.2, p.bmi * body_fat_percent(p.sex, p.bmi, p.age) / ref)


@dataclass(frozen=True)
class PlacedStructure:
    """A structure as this patient has it (local frame, mm)."""

    name: str
    kind: str
    depth_mm: float  # depth at rest (expiration): the plane's distance, a cylinder's depth
    toward: tuple | None = None
    centre_mm: tuple | None = None
    axis: tuple | None = None
    radius_mm: float | None = None
    breathing_mm: float = 0.0
    breathing_period_s: float = 4.0

    def depth_at(self, t_s):
        """Depth (mm) at session time ``t_s`` (scalar or array): breathing lifts it."""
        if self.breathing_mm <= 0.0:
            return self.depth_mm + 0.0 * np.asarray(t_s, dtype=float)
        w = 2.0 * math.pi / self.breathing_period_s
        return self.depth_mm - 0.5 * self.breathing_mm * (1.0 - np.cos(w * np.asarray(t_s, dtype=float)))

    def margin_mm(self, p_mm: np.ndarray, t_s) -> np.ndarray:
        """Distance (mm) from the tip positions ``p_mm`` (k, 3) to the structure's surface at times
        ``t_s``: positive outside, negative inside (past the membrane, into the bone or cylinder)."""
        p = np.atleast_2d(np.asarray(p_mm, dtype=float))
        shift = self.depth_at(t_s) - self.depth_mm  # <= 0: breathing brings it closer
        if self.toward is not None:
            n = np.asarray(self.toward)
            return self.depth_mm + shift - (p[:, 0] * n[0] + p[:, 1] * n[1] + p[:, 2] * n[2])
        c = np.asarray(self.centre_mm)
        a = np.asarray(self.axis)
        u = c / np.linalg.norm(c)  # breathing moves a cylinder along its centre's direction from the point
        shift = np.broadcast_to(np.asarray(shift, dtype=float), (p.shape[0],))
        cc = c[None, :] + shift[:, None] * u[None, :]
        r = p - cc
        along = r[:, 0] * a[0] + r[:, 1] * a[1] + r[:, 2] * a[2]
        perp = r - along[:, None] * a[None, :]
        return np.sqrt(np.einsum("ij,ij->i", perp, perp)) - self.radius_mm

    def as_dict(self) -> dict:
        d = {"name": self.name, "kind": self.kind, "depth_mm": round(self.depth_mm, 3)}
        if self.toward is not None:
            d["toward"] = [round(x, 4) for x in self.toward]
        else:
            d["centre_mm"] = [round(x, 3) for x in self.centre_mm]
            d["axis"] = [round(x, 4) for x in self.axis]
            d["radius_mm"] = round(self.radius_mm, 3)
        if self.breathing_mm > 0.0:
            d["breathing_mm"] = self.breathing_mm
            d["breathing_period_s"] = self.breathing_period_s
        return d


@dataclass(frozen=True)
class Anatomy:
    """A point's anatomy for one patient: the layer stack and the structures (local frame, mm)."""

    point: Point
    patient: Patient
    skin_mm: float
    fat_mm: float
    muscle_mm: float
    structures: tuple[PlacedStructure, ...] = field(default_factory=tuple)

    def as_dict(self) -> dict:
        return {"layers_mm": {"skin": round(self.skin_mm, 3), "fat": round(self.fat_mm, 3),
                              "muscle": round(self.muscle_mm, 3)},
                "structures": [s.as_dict() for s in self.structures]}


def realise(point: Point, patient: Patient = DEFAULT_PATIENT) -> Anatomy:
    """The point's anatomy for ``patient`` (module docstring)."""
    lay = point.layers
    fat = lay.fat_mm * fat_scale(patient)
    dfat = fat - lay.fat_mm
    female = patient.sex == "female"
    placed = []
    for i, s in enumerate(point.structures):
        depth = s.depth_female_mm if female else s.depth_mm
        if not s.lateral:
            if s.bmi_slope_per_unit != 0.0:
                depth *= max(0.3, 1.0 + s.bmi_slope_per_unit * (patient.bmi - s.bmi_ref))
            else:
                depth += dfat
        if patient.random:
            sd = s.depth_female_sd_mm if (female and s.depth_female_sd_mm is not None) else s.depth_sd_mm
            z = float(np.random.default_rng([patient.seed, 1 + i]).standard_normal())
            depth += z * sd
        depth = max(MIN_DEPTH_MM, depth)
        if s.is_plane:
            placed.append(PlacedStructure(s.name, s.kind, depth, toward=s.toward, breathing_mm=s.breathing_mm,
                                          breathing_period_s=s.breathing_period_s))
        else:
            # moved along its own direction from the point by the depth's change
            centre = np.asarray(s.centre_mm) * (depth / s.depth_mm)
            placed.append(PlacedStructure(s.name, s.kind, depth, centre_mm=tuple(float(x) for x in centre),
                                          axis=s.axis, radius_mm=s.radius_mm, breathing_mm=s.breathing_mm,
                                          breathing_period_s=s.breathing_period_s))
    return Anatomy(point, patient, lay.skin_mm, fat, lay.muscle_mm, tuple(placed))


def config_at(cfg, anatomy):
    """The tissue config at a point: ``cfg`` with the anatomy's layer thicknesses and the point's
    depth range as ``scene.target_depth_mm`` (every other setting kept)."""
    from dataclasses import replace
    pt = anatomy.point
    return replace(cfg, skin=replace(cfg.skin, thickness_mm=anatomy.skin_mm),
                   fat=replace(cfg.fat, thickness_mm=anatomy.fat_mm),
                   muscle=replace(cfg.muscle, thickness_mm=anatomy.muscle_mm),
                   scene=replace(cfg.scene, target_depth_mm=(pt.depth.min_mm, pt.depth.max_mm)))

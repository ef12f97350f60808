"""The acupoint atlas: one TOML file a point (``config/points/<CODE>.toml``), loaded strictly.

A point gives its code and name, the body region, the prescribed needling direction (perpendicular,
oblique or transverse: angle from the skin normal and heading in the skin plane), the depth range
graded (mm, with the cun range and cun length it came from, or an imaging study), the layer stack
(skin, fat, muscle thicknesses) and the structures beneath it. docs/atlas.md describes the schema
and says, point by point, where every number comes from and which are ours.

Frames. Each point has its own local frame, which is the scene frame of a session at that point:
the point at the origin, z out of the skin (the needle goes toward -z), x and y in the skin plane
(each file says which way they point anatomically). Lengths in mm.

Structures. ``membrane`` (a thin sheet that breaks: pleura, dura, peritoneum) and ``bone`` (a
wall) are planes: ``toward`` is the unit direction from the point into the body along which
``depth_mm`` is measured, the plane perpendicular to it. ``nerve`` and ``artery`` are cylinders:
``centre_mm`` a point on the axis, ``axis`` its direction, ``radius_mm``; ``depth_mm`` their depth
below the skin (what the patient's variation moves). Any problem: one line naming the file and key
(:class:`~haptic_acu.base.errors.UserError`, exit 2).
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

from ..base.bundled import bundled_dir
from ..base.errors import UserError

POINTS_DIR = bundled_dir("config") / "points"
DIRECTION_KINDS = ("perpendicular", "oblique", "transverse")
PLANE_KINDS = ("membrane", "bone")
CYLINDER_KINDS = ("nerve", "artery")
STRUCTURE_KINDS = PLANE_KINDS + CYLINDER_KINDS
DEPTH_BASES = ("cun", "imaging")
MAX_STRUCTURES = 4  # the servo's rows (haptic_acu.servo.danger.MAX_DANGER)

_TOP = {"code": str, "name": str, "region": str, "location_source": str, "x_toward": str, "y_toward": str,
        "direction": dict, "depth": dict, "layers": dict, "structure": list}
_DIRECTION = {"kind": str, "angle_from_normal_deg": float, "heading_deg": float, "tolerance_deg": float,
              "source": str}
_DEPTH = {"min_mm": float, "max_mm": float, "basis": str, "measured": str, "source": str}
_DEPTH_OPTIONAL = {"cun_min": float, "cun_max": float, "cun_mm": float, "cun_source": str, "textbook_cun": list}
_LAYERS = {"skin_mm": float, "fat_mm": float, "muscle_mm": float, "source": str}
_STRUCTURE = {"name": str, "kind": str, "depth_mm": float, "depth_female_mm": float, "depth_sd_mm": float,
              "measured": str, "source": str, "bmi_ref": float, "bmi_slope_per_unit": float, "bmi_source": str,
              "breathing_mm": float, "breathing_period_s": float, "breathing_source": str}
_STRUCTURE_OPTIONAL = {"depth_female_sd_mm": float, "lateral": bool, "toward": list, "centre_mm": list,
                       "axis": list, "radius_mm": float}


@dataclass(frozen=True)
class Direction:
    kind: str
    angle_from_normal_deg: float
    heading_deg: float
    tolerance_deg: float
    source: str

    def vector(self) -> tuple[float, float, float]:
        """The prescribed needle direction (unit, into the body, local frame)."""
        th = math.radians(self.angle_from_normal_deg)
        ph = math.radians(self.heading_deg)
        return (math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), -math.cos(th))


@dataclass(frozen=True)
class DepthRange:
    min_mm: float
    max_mm: float
    basis: str
    measured: str
    source: str
    cun_min: float | None = None
    cun_max: float | None = None
    cun_mm: float | None = None
    cun_source: str | None = None
    textbook_cun: tuple[float, float] | None = None


@dataclass(frozen=True)
class Layers:
    skin_mm: float
    fat_mm: float
    muscle_mm: float
    source: str


@dataclass(frozen=True)
class Structure:
    name: str
    kind: str
    depth_mm: float  # men's (the default patient's) depth
    depth_female_mm: float
    depth_sd_mm: float
    measured: str
    source: str
    bmi_ref: float
    bmi_slope_per_unit: float  # relative change of the depth per kg/m2 (0: the fat scaling moves it)
    bmi_source: str
    breathing_mm: float  # peak-to-peak movement with breathing (shallower on inspiration)
    breathing_period_s: float
    breathing_source: str
    depth_female_sd_mm: float | None = None
    lateral: bool = False  # a sideways distance: neither the sex nor the fat moves it
    toward: tuple[float, float, float] | None = None  # planes
    centre_mm: tuple[float, float, float] | None = None  # cylinders
    axis: tuple[float, float, float] | None = None
    radius_mm: float | None = None

    @property
    def is_plane(self) -> bool:
        return self.kind in PLANE_KINDS


@dataclass(frozen=True)
class Point:
    code: str
    name: str
    region: str
    location_source: str
    x_toward: str
    y_toward: str
    direction: Direction
    depth: DepthRange
    layers: Layers
    structures: tuple[Structure, ...]
    path: str

    def structure(self, name: str) -> Structure:
        for s in self.structures:
            if s.name == name:
                return s
        raise KeyError(name)


def _bad(path, key: str, what: str) -> UserError:
    return UserError(f"{path}: {key}: {what}")


def _value(path, key: str, v, typ):
    if typ is float:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise _bad(path, key, f"must be a number, got {v!r}")
        v = float(v)
        if not math.isfinite(v):
            raise _bad(path, key, f"must be finite, got {v!r}")
        return v
    if typ is bool:
        if not isinstance(v, bool):
            raise _bad(path, key, f"must be true or false, got {v!r}")
        return v
    if typ is str:
        if not isinstance(v, str) or not v.strip():
            raise _bad(path, key, f"must be a non-empty string, got {v!r}")
        return v
    if not isinstance(v, typ):
        raise _bad(path, key, f"must be a {typ.__name__}, got {v!r}")
    return v


def _table(path, prefix: str, data, required: dict, optional: dict | None = None) -> dict:
    """The keys of one table, each checked: every required key present, no unknown key."""
    optional = optional or {}
    if not isinstance(data, dict):
        raise _bad(path, prefix.rstrip("."), "must be a table")
    for key in data:
        if key not in required and key not in optional:
            raise _bad(path, prefix + key, "unknown key")
    out = {}
    for key, typ in required.items():
        if key not in data:
            raise _bad(path, prefix + key, "missing")
        out[key] = _value(path, prefix + key, data[key], typ)
    for key, typ in optional.items():
        if key in data:
            out[key] = _value(path, prefix + key, data[key], typ)
    return out


def _vector(path, key: str, v, unit: bool) -> tuple[float, float, float]:
    if not isinstance(v, list) or len(v) != 3:
        raise _bad(path, key, f"must be a list of three numbers, got {v!r}")
    xs = tuple(_value(path, key, x, float) for x in v)
    if unit:
        n = math.sqrt(sum(x * x for x in xs))
        if n < 1e-9:
            raise _bad(path, key, "must not be the zero vector")
        xs = tuple(x / n for x in xs)
    return xs


def _positive(path, key: str, v: float, allow_zero: bool = False) -> float:
    if v < 0.0 or (v == 0.0 and not allow_zero):
        raise _bad(path, key, f"must be {'>= 0' if allow_zero else '> 0'}, got {v:g}")
    return v


def _structure(path, i: int, data) -> Structure:
    pre = f"structure[{i}]."
    t = _table(path, pre, data, _STRUCTURE, _STRUCTURE_OPTIONAL)
    kind = t["kind"]
    if kind not in STRUCTURE_KINDS:
        raise _bad(path, pre + "kind", f"must be one of {', '.join(STRUCTURE_KINDS)}, got {kind!r}")
    for key in ("depth_mm", "depth_female_mm", "breathing_period_s"):
        _positive(path, pre + key, t[key])
    for key in ("depth_sd_mm", "breathing_mm"):
        _positive(path, pre + key, t[key], allow_zero=True)
    if "depth_female_sd_mm" in t:
        _positive(path, pre + "depth_female_sd_mm", t["depth_female_sd_mm"], allow_zero=True)
    _positive(path, pre + "bmi_ref", t["bmi_ref"])
    geo = {}
    if kind in PLANE_KINDS:
        if "toward" not in t:
            raise _bad(path, pre + "toward", f"missing (a {kind} is a plane)")
        for key in ("centre_mm", "axis", "radius_mm"):
            if key in t:
                raise _bad(path, pre + key, f"not a key of a {kind} (a plane)")
        geo["toward"] = _vector(path, pre + "toward", t.pop("toward"), unit=True)
    else:
        for key in ("centre_mm", "axis", "radius_mm"):
            if key not in t:
                raise _bad(path, pre + key, f"missing (a {kind} is a cylinder)")
        if "toward" in t:
            raise _bad(path, pre + "toward", f"not a key of a {kind} (a cylinder)")
        geo["centre_mm"] = _vector(path, pre + "centre_mm", t.pop("centre_mm"), unit=False)
        geo["axis"] = _vector(path, pre + "axis", t.pop("axis"), unit=True)
        geo["radius_mm"] = _positive(path, pre + "radius_mm", t.pop("radius_mm"))
        if geo["centre_mm"][2] >= 0.0:
            raise _bad(path, pre + "centre_mm", "must be below the skin (z < 0)")
        if t.get("lateral", False):
            raise _bad(path, pre + "lateral", f"only a plane's distance can be lateral, not a {kind}'s")
    t.update(geo)
    return Structure(**t)


def load_point_file(path) -> Point:
    """One atlas file, checked; :class:`UserError` naming the file and key on any problem."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UserError(f"{path}: no such atlas file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise UserError(f"{path}: cannot read: {e}") from None
    except tomllib.TOMLDecodeError as e:
        raise UserError(f"{path}: not valid TOML: {e}") from None
    top = _table(path, "", data, _TOP)
    d = _table(path, "direction.", top["direction"], _DIRECTION)
    if d["kind"] not in DIRECTION_KINDS:
        raise _bad(path, "direction.kind", f"must be one of {', '.join(DIRECTION_KINDS)}, got {d['kind']!r}")
    if not 0.0 <= d["angle_from_normal_deg"] <= 90.0:
        raise _bad(path, "direction.angle_from_normal_deg", f"must be within 0-90, got {d['angle_from_normal_deg']:g}")
    if d["kind"] == "perpendicular" and d["angle_from_normal_deg"] != 0.0:
        raise _bad(path, "direction.angle_from_normal_deg", "must be 0 for a perpendicular insertion")
    _positive(path, "direction.tolerance_deg", d["tolerance_deg"])
    dep = _table(path, "depth.", top["depth"], _DEPTH, _DEPTH_OPTIONAL)
    if dep["basis"] not in DEPTH_BASES:
        raise _bad(path, "depth.basis", f"must be one of {', '.join(DEPTH_BASES)}, got {dep['basis']!r}")
    _positive(path, "depth.min_mm", dep["min_mm"], allow_zero=True)
    if dep["max_mm"] <= dep["min_mm"]:
        raise _bad(path, "depth.max_mm", f"must exceed depth.min_mm ({dep['min_mm']:g}), got {dep['max_mm']:g}")
    if dep["basis"] == "cun":
        for key in ("cun_min", "cun_max", "cun_mm", "cun_source"):
            if key not in dep:
                raise _bad(path, "depth." + key, "missing (depth.basis is cun)")
    if "textbook_cun" in dep:
        tc = dep["textbook_cun"]
        if len(tc) != 2:
            raise _bad(path, "depth.textbook_cun", f"must be [min, max], got {tc!r}")
        dep["textbook_cun"] = tuple(_value(path, "depth.textbook_cun", x, float) for x in tc)
    lay = _table(path, "layers.", top["layers"], _LAYERS)
    for key in ("skin_mm", "fat_mm", "muscle_mm"):
        _positive(path, "layers." + key, lay[key])
    structures = tuple(_structure(path, i, s) for i, s in enumerate(top["structure"]))
    if not 1 <= len(structures) <= MAX_STRUCTURES:
        raise _bad(path, "structure", f"must list 1-{MAX_STRUCTURES} structures, got {len(structures)}")
    names = [s.name for s in structures]
    if len(set(names)) != len(names):
        raise _bad(path, "structure", "two structures have the same name")
    if top["code"] != path.stem:
        raise _bad(path, "code", f"must match the file's name ({path.stem}), got {top['code']!r}")
    return Point(code=top["code"], name=top["name"], region=top["region"], location_source=top["location_source"],
                 x_toward=top["x_toward"], y_toward=top["y_toward"], direction=Direction(**d),
                 depth=DepthRange(**dep), layers=Layers(**lay), structures=structures, path=str(path))


def point_codes(directory=None) -> list[str]:
    """The codes of the atlas's points (file names), sorted."""
    directory = Path(directory) if directory is not None else POINTS_DIR
    return sorted(p.stem for p in directory.glob("*.toml"))


def load_point(spec: str, directory=None, source: str = "--point") -> Point:
    """A point by its code (``GB21``, any case) from the bundled atlas, or a ``.toml`` file of the
    same schema (the atlas is extensible: a file of one's own works the same way)."""
    if spec.endswith(".toml"):
        return load_point_file(spec)
    directory = Path(directory) if directory is not None else POINTS_DIR
    codes = point_codes(directory)
    match = [c for c in codes if c.upper() == spec.strip().upper()]
    if not match:
        raise UserError(f"{source}: unknown point {spec!r}: the atlas has {', '.join(codes)} "
                        f"(or give a .toml file of the same schema, docs/atlas.md)")
    return load_point_file(directory / f"{match[0]}.toml")


def load_atlas(directory=None) -> list[Point]:
    """Every point of the atlas, checked."""
    directory = Path(directory) if directory is not None else POINTS_DIR
    return [load_point_file(directory / f"{c}.toml") for c in point_codes(directory)]

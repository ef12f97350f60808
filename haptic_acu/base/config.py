"""Configuration: TOML files under ``config/`` loaded into frozen dataclasses.

Units are in the key names (``thickness_mm``, ``k_virtual_n_per_mm``); the loader converts nothing,
the model converts to SI where it uses a value. Every key is required and no unknown key is
accepted: a typo is an error, not a silently ignored setting. Any problem raises
:class:`~haptic_acu.base.errors.UserError` with one line naming the file and the dotted key.
"""
from __future__ import annotations

import dataclasses
import math
import sys
import tomllib
import typing
from dataclasses import dataclass
from pathlib import Path

from .bundled import bundled_dir
from .errors import UserError
from .overrides import apply_overrides

CONFIG_DIR = bundled_dir("config")
DEFAULT_CONFIG = CONFIG_DIR / "tissue.toml"
LAYER_NAMES = ("skin", "fat", "muscle")
MAX_RINGS = 40  # rings of a force net at most (the servo's scratch record is sized by it)


@dataclass(frozen=True)
class BodyParams:
    """The body the layers wrap: a limb-like shape whose skin surface is fitted by SH."""

    semi_axes_mm: tuple[float, float, float]  # skin surface ellipsoid (x along the limb, y, z)
    bulge: float  # relative amplitude of a smooth asymmetric bump (makes it not quite an ellipsoid)
    lmax: int  # SH degree of every boundary's expansion
    fit_samples: int  # points sampled on each boundary for the least-squares fit
    skin_coefficients: str  # "" for the built-in shape, else a .npz written by `haptic-acu fit`


@dataclass(frozen=True)
class LayerParams:
    """One tissue layer (Table 2, plus the parameters of ours the model needs)."""

    thickness_mm: float  # Table 2
    k_virtual_n_per_mm: float  # Table 2: K, virtual (normal) spring per particle
    damping_n_s_per_m_per_mm: float  # Table 2: d, read per mm of needle in the layer (MODEL.md s3)
    rings: int  # Table 2: w, rings of the hexagonal net (ring 1 is the contact point)
    spring_length_mm: float  # Table 2: L, surface-spring spacing
    k_surface_n_per_mm: float  # ours: surface-spring stiffness
    pretension: float  # ours: surface springs' rest length is (1 - pretension) * spacing
    puncture_threshold_um: float  # ours: ring-w mean deflection at which the surface breaks
    # post-puncture mechanics (haptic_acu/tissue/mechanics.py; needle.mechanics = "rich"), per mm of needle diameter
    cutting_n_per_mm_diameter: float  # cutting force at the tip advancing into uncut tissue
    coulomb_n_per_mm2: float  # Coulomb shaft friction per mm of needle in the layer
    stiction_ratio: float  # breakaway / Coulomb friction (>= 1)
    viscous_n_s_per_m_per_mm2: float  # viscous shaft friction per mm of needle in the layer
    name: str = ""


@dataclass(frozen=True)
class NeedleParams:
    lateral_constraint: bool  # resist tip motion off the insertion line once the skin is pierced
    lateral_stiffness_n_per_mm: float
    bone_stiffness_n_per_mm: float  # penalty wall at the muscle/bone boundary
    mechanics: str  # after a puncture: "rich" (cutting + Karnopp friction, mechanics.py) or "table1" (the paper)
    diameter_mm: float  # needle shaft diameter (scales cutting and friction)
    length_mm: float  # needle shaft length (no more than this is in tissue)
    stick_stiffness_n_per_mm: float  # spring of the friction's stick point (position-input rendering)
    friction_relaxation_s: float  # the held friction force relaxes with this time constant (0: never)


@dataclass(frozen=True)
class TwirlingParams:
    """Twirling (haptic_acu/tissue/twirl.py, docs/model.md section 11): the tissue wound around the shaft by
    the needle's roll. Per-layer values are lists in layer order (skin, fat, muscle)."""

    k_twist_n_per_rad: tuple[float, float, float]  # torque per rad of twist per m of needle in the layer (N*m/(rad*m))
    grasp_coil: tuple[float, float, float]  # friction gain at full twist (|twist| = slip)
    grasp_engage: tuple[float, float, float]  # friction gain at full engagement
    twist_slip_turns: float  # twist the shaft holds before the tissue slips on it (turns)
    twist_tau_s: float  # twist (torque) relaxation time
    engage_turns: float  # rotation per e-fold of engagement growth (turns)
    engage_tau_s: float  # engagement (grasp) relaxation time
    play_deg: float  # backlash on the roll feeding the winding (keeps encoder jitter from winding)


@dataclass(frozen=True)
class RuptureParams:
    """Speed dependence of the surface's rupture (haptic_acu/tissue/mechanics.py ``rupture_speed_factor``,
    docs/model.md section 2.2): the ring-w puncture threshold times a factor of the approach speed."""

    high_speed_ratio: float  # threshold at high speed over the quasi-static one (1: no speed dependence)
    speed_scale_mm_s: float  # approach speed over which the threshold falls halfway to its high-speed value
    reference_speed_mm_s: float  # approach speed at which the layers' thresholds apply as configured


@dataclass(frozen=True)
class SpringbackParams:
    eta_rate_per_frame: float  # eq. 9's eta_r: eta drops by this each visual frame
    eta_min: float  # floor of eta (0: full return to the rest shape)
    margin_rings: int  # undeformed rings added around the net so the centroid stays put


@dataclass(frozen=True)
class SolverParams:
    servo_net: str  # "table": the net's tabulated static response (netresponse.py); "sweeps": relax it each tick
    sweeps_per_tick: int  # Gauss-Seidel-Newton sweeps of the force net per servo tick ("sweeps")
    static_tolerance_um: float  # convergence tolerance of a full static solve


@dataclass(frozen=True)
class SafetyParams:
    force_limit_n: float  # commanded force magnitude never exceeds this (OMNI nominal max 3.3 N)


@dataclass(frozen=True)
class SceneParams:
    target_depth_mm: tuple[float, float]  # depth range the acupoint's needling aims for
    max_hand_speed_m_per_s: float  # trajectory jumps faster than this are refused


@dataclass(frozen=True)
class WorkspaceParams:
    """Device frame -> scene frame: p_scene = scale * R_z(rotation) * p_device + offset."""

    offset_mm: tuple[float, float, float]
    scale: float
    rotation_z_deg: float
    roll_sign: float  # +1 or -1: the OMNI's third gimbal angle times this is the roll (+ clockwise from the handle)


MODEL_KINDS = ("forcenet", "msm", "fem", "bem", "shf")  # model.kind: the tissue model before a layer breaks
TIP_SHAPES = ("flat", "hemisphere")  # model.tip_shape: the tip's end the FEM and BEM press with


@dataclass(frozen=True)
class ModelParams:
    """Which tissue model resists the needle before a layer breaks (:mod:`haptic_acu.tissue.baselines`,
    docs/model.md section 12): today's force net or one of the four baselines. Per-layer values are
    lists in layer order (skin, fat, muscle)."""

    kind: str  # "forcenet" (the force net), "msm", "fem", "bem" or "shf"
    young_modulus_kpa: tuple[float, float, float]  # MSM, FEM, BEM: each layer's Young's modulus
    poisson_ratio: tuple[float, float, float]  # MSM, FEM, BEM
    fracture_toughness_j_per_m2: tuple[float, float, float]  # FEM, BEM: the energy criterion's toughness
    shf_stiffness_n_per_mm: tuple[float, float, float]  # SHF: penalty stiffness along the surface normal
    shf_puncture_force_n: tuple[float, float, float]  # SHF: force at which the layer breaks
    msm_spacing_mm: float  # MSM: the lattice's spacing
    msm_puncture_strain: tuple[float, float, float]  # MSM: strain of a spring at the tip at which the layer breaks
    tip_shape: str  # FEM, BEM: the tip's end over its contact disc, "flat" or "hemisphere" (tissue.contact)


@dataclass(frozen=True)
class TissueConfig:
    path: str
    body: BodyParams
    skin: LayerParams
    fat: LayerParams
    muscle: LayerParams
    needle: NeedleParams
    twirl: TwirlingParams
    rupture: RuptureParams
    springback: SpringbackParams
    solver: SolverParams
    safety: SafetyParams
    scene: SceneParams
    workspace: WorkspaceParams
    model: ModelParams

    @property
    def layers(self) -> tuple[LayerParams, LayerParams, LayerParams]:
        return (self.skin, self.fat, self.muscle)


# Keys whose value must be > 0 (by field name, in any section).
_POSITIVE = {
    "thickness_mm", "k_virtual_n_per_mm", "spring_length_mm", "k_surface_n_per_mm",
    "puncture_threshold_um", "lateral_stiffness_n_per_mm", "young_modulus_kpa", "fracture_toughness_j_per_m2",
    "shf_stiffness_n_per_mm", "shf_puncture_force_n", "msm_spacing_mm", "msm_puncture_strain",
    "bone_stiffness_n_per_mm", "force_limit_n", "fit_samples", "sweeps_per_tick",
    "static_tolerance_um", "scale", "max_hand_speed_m_per_s",
    "diameter_mm", "length_mm", "stick_stiffness_n_per_mm", "stiction_ratio",
    "twist_slip_turns", "twist_tau_s", "engage_turns", "engage_tau_s", "high_speed_ratio", "speed_scale_mm_s",
}
_NON_NEGATIVE = {"damping_n_s_per_m_per_mm", "bulge", "eta_rate_per_frame", "eta_min",
                 "margin_rings", "lmax", "pretension",
                 "cutting_n_per_mm_diameter", "coulomb_n_per_mm2", "viscous_n_s_per_m_per_mm2",
                 "friction_relaxation_s", "k_twist_n_per_rad", "grasp_coil", "grasp_engage", "play_deg",
                 "reference_speed_mm_s"}
# Bounds on what a tissue config can ask for (by field name, in any section): far outside any
# tissue or device, and past them the solver hangs, exhausts memory or overflows (a stiffness of
# 1e300 N/mm overflowed the force clamp to 0 N; fit_samples = 2e9 exhausted memory;
# static_tolerance_um = 1e-300 or sweeps_per_tick = 1e6 never finished). (low, high), inclusive.
_BOUNDS = {
    "semi_axes_mm": (1.0, 10_000.0), "lmax": (0, 40), "fit_samples": (2, 200_000),
    "thickness_mm": (1e-3, 1_000.0), "k_virtual_n_per_mm": (1e-6, 1_000.0),
    "damping_n_s_per_m_per_mm": (0.0, 1_000.0), "spring_length_mm": (1e-3, 100.0),
    "k_surface_n_per_mm": (1e-6, 1_000.0), "puncture_threshold_um": (1e-6, 1e6),
    "lateral_stiffness_n_per_mm": (1e-6, 1_000.0),
    "bone_stiffness_n_per_mm": (1e-6, 1_000.0), "eta_rate_per_frame": (0.0, 1.0),
    "margin_rings": (0, 40), "sweeps_per_tick": (1, 100), "static_tolerance_um": (1e-6, 1_000.0),
    "force_limit_n": (1e-3, 100.0), "target_depth_mm": (0.0, 1_000.0),
    "max_hand_speed_m_per_s": (1e-3, 100.0), "offset_mm": (-10_000.0, 10_000.0),
    "scale": (1e-3, 1_000.0), "rotation_z_deg": (-3600.0, 3600.0),
    "diameter_mm": (1e-3, 10.0), "length_mm": (1.0, 1_000.0), "stick_stiffness_n_per_mm": (1e-6, 1_000.0),
    "stiction_ratio": (1.0, 100.0), "cutting_n_per_mm_diameter": (0.0, 1_000.0),
    "coulomb_n_per_mm2": (0.0, 1_000.0), "viscous_n_s_per_m_per_mm2": (0.0, 1e6),
    "friction_relaxation_s": (0.0, 1e4),
    # twirling: k_twist 1 N/rad is a shear modulus of 5 MPa round a 0.25 mm needle (tissue: kPa); a
    # grasp gain of 50 multiplies the friction 51-fold; time constants from 1 ms to 11 days
    "k_twist_n_per_rad": (0.0, 1.0), "grasp_coil": (0.0, 50.0), "grasp_engage": (0.0, 50.0),
    "twist_slip_turns": (1e-3, 100.0), "twist_tau_s": (1e-3, 1e6), "engage_turns": (1e-3, 100.0),
    "engage_tau_s": (1e-3, 1e6), "play_deg": (0.0, 90.0),
    # rupture speed dependence: ratio in (0, 1] (1: off), speeds up to 10 m/s
    "high_speed_ratio": (1e-3, 1.0), "speed_scale_mm_s": (1e-3, 1e4), "reference_speed_mm_s": (0.0, 1e4),
    # baseline tissue models: moduli from a soft gel (0.1 kPa) to cartilage (100 MPa); nu in [0, 0.5)
    "young_modulus_kpa": (0.1, 1e5), "poisson_ratio": (0.0, 0.4999),
    # fracture toughness from a gel's 1 J/m^2 to a tendon's 10^5
    "fracture_toughness_j_per_m2": (1.0, 1e5),
    "shf_stiffness_n_per_mm": (1e-6, 1_000.0), "shf_puncture_force_n": (1e-3, 100.0),
    "msm_spacing_mm": (0.1, 5.0), "msm_puncture_strain": (1e-3, 100.0),
}
# Retired keys, not read: a file that still has one is accepted with a one-line warning on stderr
# (the key has no effect on the model, so such a config means what it says); the message says why.
_REMOVED = {
    "needle.hole_radius_mm": "re-entry is decided by the insertion tracks, whose damage decays over the "
                             "needle's radius (docs/model.md section 9.2)",
    "model.puncture_depth_mm": "the FEM and BEM break by an energy criterion, model.fracture_toughness_j_per_m2 "
                               "(docs/model.md section 12.5)",
}
_SECTIONS = {
    "body": BodyParams, "skin": LayerParams, "fat": LayerParams, "muscle": LayerParams,
    "needle": NeedleParams, "twirl": TwirlingParams, "rupture": RuptureParams, "springback": SpringbackParams, "solver": SolverParams,
    "safety": SafetyParams, "scene": SceneParams, "workspace": WorkspaceParams, "model": ModelParams,
}
# Sections a config file may leave out: taken whole from the bundled config/tissue.toml (a config
# written before the section existed means what it meant: the force net).
_OPTIONAL_SECTIONS = ("model",)


def _fail(path: Path, key: str, msg: str) -> typing.NoReturn:
    raise UserError(f"{path}: key '{key}': {msg}")


def _convert(path: Path, key: str, value, tp):
    origin = typing.get_origin(tp)
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, list) or len(value) != len(args):
            _fail(path, key, f"expected a list of {len(args)} numbers, got {value!r}")
        return tuple(_convert(path, f"{key}[{i}]", v, a) for i, (v, a) in enumerate(zip(value, args)))
    if tp is bool:
        if not isinstance(value, bool):
            _fail(path, key, f"expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            _fail(path, key, f"expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            _fail(path, key, f"expected a number, got {value!r}")
        if not math.isfinite(value):
            _fail(path, key, f"expected a finite number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            _fail(path, key, f"expected a string, got {value!r}")
        return value
    raise TypeError(tp)  # pragma: no cover - schema error, not user input


def _warn_removed(path: Path, name: str, table: dict) -> dict:
    """``table`` without the keys of :data:`_REMOVED`, each reported by one line on stderr."""
    gone = [key for key in table if f"{name}.{key}" in _REMOVED]
    for key in gone:
        print(f"{path}: warning: key '{name}.{key}' is no longer used and is ignored: "
              f"{_REMOVED[name + '.' + key]}; delete it", file=sys.stderr)
    return {k: v for k, v in table.items() if k not in gone} if gone else table


def _section(path: Path, name: str, cls, table) -> object:
    if not isinstance(table, dict):
        _fail(path, name, "expected a table")
    table = _warn_removed(path, name, table)
    hints = typing.get_type_hints(cls)
    fields = [f for f in dataclasses.fields(cls) if f.name != "name"]
    known = {f.name for f in fields}
    for key in table:
        if key not in known:
            _fail(path, f"{name}.{key}", f"unknown key (known: {', '.join(sorted(known))})")
    values = {}
    for f in fields:
        key = f"{name}.{f.name}"
        if f.name not in table:
            _fail(path, key, "missing")
        v = _convert(path, key, table[f.name], hints[f.name])
        for item in (v if isinstance(v, tuple) else (v,)):
            if isinstance(item, (int, float)) and not isinstance(item, bool):
                if f.name in _POSITIVE and not item > 0:
                    _fail(path, key, f"must be > 0, got {item!r}")
                if f.name in _NON_NEGATIVE and not item >= 0:
                    _fail(path, key, f"must be >= 0, got {item!r}")
                lo, hi = _BOUNDS.get(f.name, (-math.inf, math.inf))
                if not lo <= item <= hi:
                    _fail(path, key, f"must be between {lo:g} and {hi:g}, got {item!r}")
        values[f.name] = v
    if cls is LayerParams:
        values["name"] = name
    return cls(**values)


def _check_relations(path: Path, cfg: TissueConfig) -> None:
    for layer in cfg.layers:
        if layer.rings < 2:
            _fail(path, f"{layer.name}.rings", f"w must be >= 2, got {layer.rings}")
        if layer.rings > MAX_RINGS:
            _fail(path, f"{layer.name}.rings", f"w must be <= {MAX_RINGS}, got {layer.rings}")
        if not layer.pretension < 0.5:
            _fail(path, f"{layer.name}.pretension", f"must be < 0.5, got {layer.pretension}")
    for layer in cfg.layers:  # post-puncture mechanics
        if not layer.stiction_ratio >= 1.0:
            _fail(path, f"{layer.name}.stiction_ratio", f"breakaway must be >= Coulomb (>= 1), got {layer.stiction_ratio}")
    if cfg.needle.mechanics not in ("rich", "table1"):
        _fail(path, "needle.mechanics", f"must be \"rich\" or \"table1\", got {cfg.needle.mechanics!r}")
    if cfg.body.lmax > 40:
        _fail(path, "body.lmax", f"must be <= 40, got {cfg.body.lmax}")
    need = (cfg.body.lmax + 1) ** 2
    if cfg.body.fit_samples < 2 * need:
        _fail(path, "body.fit_samples", f"must be >= 2*(lmax+1)^2 = {2 * need}, got {cfg.body.fit_samples}")
    total = sum(layer.thickness_mm for layer in cfg.layers)
    if total >= 0.9 * min(cfg.body.semi_axes_mm):
        _fail(path, "body.semi_axes_mm", f"smallest semi-axis must exceed the layers' total thickness {total} mm by 10%")
    if cfg.body.bulge >= 0.2:
        _fail(path, "body.bulge", f"must be < 0.2, got {cfg.body.bulge}")
    if not cfg.springback.eta_min < 1:
        _fail(path, "springback.eta_min", f"must be < 1, got {cfg.springback.eta_min}")
    if cfg.solver.servo_net not in ("table", "sweeps"):
        _fail(path, "solver.servo_net", f"must be \"table\" or \"sweeps\", got {cfg.solver.servo_net!r}")
    if cfg.model.kind not in MODEL_KINDS:
        _fail(path, "model.kind", f"must be one of {', '.join(MODEL_KINDS)}, got {cfg.model.kind!r}")
    if cfg.model.tip_shape not in TIP_SHAPES:
        _fail(path, "model.tip_shape", f"must be one of {', '.join(TIP_SHAPES)}, got {cfg.model.tip_shape!r}")
    if cfg.workspace.roll_sign not in (1.0, -1.0):
        _fail(path, "workspace.roll_sign", f"must be 1 or -1, got {cfg.workspace.roll_sign}")
    lo, hi = cfg.scene.target_depth_mm
    if not 0 <= lo < hi:
        _fail(path, "scene.target_depth_mm", f"must be [low, high] with 0 <= low < high, got {[lo, hi]}")
    half = min(cfg.body.semi_axes_mm)
    for layer in cfg.layers:  # a net reaching round the body: its flat patch is no longer the surface
        radius = (layer.rings - 1) * layer.spring_length_mm
        if radius > half:
            _fail(path, f"{layer.name}.rings", f"the net's radius (rings - 1) x spring_length_mm = {radius:g} mm "
                  f"is wider than the body's smallest semi-axis body.semi_axes_mm = {half:g} mm")
    _check_costs(path, cfg)


def _check_costs(path: Path, cfg: TissueConfig) -> None:
    """Settings whose product would take more than the budget (:mod:`haptic_acu.base.budget`):
    refused now, naming the keys and the cost, not after minutes of solving."""
    from . import budget

    budget.check_sh_fit(cfg.body.lmax, cfg.body.fit_samples, str(path))
    tables = cfg.solver.servo_net == "table"
    for layer in cfg.layers:
        if tables:
            budget.check_net(layer.name, layer.rings, cfg.solver.static_tolerance_um, str(path))


MAX_CONFIG_BYTES = 1 << 20


def _bundled_section(name: str) -> dict:
    """Section ``name`` of the bundled config/tissue.toml (for a file that leaves it out)."""
    return dict(tomllib.loads(DEFAULT_CONFIG.read_text(encoding="utf-8"))[name])


def load_config(path: str | Path | None = None, overrides=None) -> TissueConfig:
    """Load and validate a tissue config (default ``config/tissue.toml``); ``overrides``: the
    command line's ``--set section.key=value`` items (:mod:`haptic_acu.base.overrides`)."""
    from .csvin import check_source

    path = Path(path) if path is not None else DEFAULT_CONFIG
    try:
        st = check_source(path, "config file")  # a device or a pipe never ends: refused unread
        if st.st_size > MAX_CONFIG_BYTES:
            raise UserError(f"{path}: {st.st_size / 1e6:.0f} MB; a config file is at most "
                            f"{MAX_CONFIG_BYTES >> 20} MB")
        raw = path.read_bytes()
    except UserError as e:
        if "no such file" in str(e):
            raise UserError(f"{path}: config file not found") from None
        raise
    except OSError as e:
        raise UserError(f"{path}: cannot read config: {e.strerror}") from None
    try:
        data = tomllib.loads(raw.decode("utf-8-sig"))  # a UTF-8 BOM (Windows editors) is accepted
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a UTF-8 text file") from None
    except tomllib.TOMLDecodeError as e:
        raise UserError(f"{path}: invalid TOML: {e}") from None
    except ValueError as e:  # an integer of over 4300 digits
        raise UserError(f"{path}: invalid TOML: {e}") from None
    for name in _OPTIONAL_SECTIONS:
        if name not in data and path.resolve() != DEFAULT_CONFIG.resolve():
            data[name] = _bundled_section(name)
    if overrides:
        data = apply_overrides(data, overrides)
    for key in data:
        if key not in _SECTIONS:
            _fail(path, key, f"unknown section (known: {', '.join(_SECTIONS)})")
    sections = {}
    for name, cls in _SECTIONS.items():
        if name not in data:
            _fail(path, name, "missing section")
        sections[name] = _section(path, name, cls, data[name])
    cfg = TissueConfig(path=str(path), **sections)
    _check_relations(path, cfg)
    if cfg.body.skin_coefficients:
        p = Path(cfg.body.skin_coefficients)
        if not p.is_absolute():
            p = path.parent / p
        if not p.is_file():
            _fail(path, "body.skin_coefficients", f"file not found: {p}")
        cfg = dataclasses.replace(cfg, body=dataclasses.replace(cfg.body, skin_coefficients=str(p)))
    return cfg

"""Configs and needle-tip paths the servo step is timed on (SI: metres, m/s, one row per 1 ms tick).

* ``press``: a layer's surface pressed by a slow lift-and-press stroke, with the layer's puncture
  threshold made huge in a config copy so its force net stays active all along (the most
  expensive tick: collision + net sweeps + reaction). ``layer=0`` presses the skin (its rings
  set to ``w``); ``layer=2`` presses the muscle after skin and fat have been punctured (so the
  tick also pays the damping of two layers and the lateral constraint).
* ``inside``: the tip inside muscle after every puncture, making lift-thrust strokes (collision +
  damping + lateral constraint, no net).

Each scenario is a ``pre`` path (untimed: it brings the model to the state) and a ``timed`` path.
Both the compiled model and :mod:`bench.numpy_reference` are driven along the same paths.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from haptic_acu.base.config import LAYER_NAMES, load_config
from haptic_acu.servo.step import PRESSING, PUNCTURED, NeedleModel
from haptic_acu.tissue.body import Tissue

DT = 1e-3
HUGE_THRESHOLD_UM = 1e9  # a ring-w deflection no net reaches: the layer never breaks
LAYER_KEYS = LAYER_NAMES


def config_copy(base=None, layer: int | None = None, w: int | None = None, never_puncture: bool = False,
                **solver):
    """The default config (or ``base``) with ``layer``'s rings set to ``w`` and/or its puncture
    threshold made huge; ``solver`` overrides fields of the ``[solver]`` section."""
    cfg = base if base is not None else load_config()
    if layer is not None:
        key = LAYER_KEYS[layer]
        changes = {}
        if w is not None:
            changes["rings"] = int(w)
        if never_puncture:
            changes["puncture_threshold_um"] = HUGE_THRESHOLD_UM
        cfg = dataclasses.replace(cfg, **{key: dataclasses.replace(getattr(cfg, key), **changes)})
        if never_puncture:  # the baseline models' break criteria too (model.kind)
            def huge(values, big):
                return tuple(big if j == layer else v for j, v in enumerate(values))
            md = cfg.model
            cfg = dataclasses.replace(cfg, model=dataclasses.replace(
                md, fracture_toughness_j_per_m2=huge(md.fracture_toughness_j_per_m2, 1e12), shf_puncture_force_n=huge(md.shf_puncture_force_n, 1e6),
                msm_puncture_strain=huge(md.msm_puncture_strain, 1e9)))
    if solver:
        cfg = dataclasses.replace(cfg, solver=dataclasses.replace(cfg.solver, **solver))
    return cfg


_TISSUES: dict = {}


def with_kind(cfg, kind: str, **model):
    """``cfg`` with ``model.kind`` set to ``kind`` (a baseline tissue model, or the force net) and
    any other ``model`` keys given (``tip_shape="hemisphere"``)."""
    return dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, kind=kind, **model))


def tissue_for(cfg) -> Tissue:
    """The fitted tissue of ``cfg``, built once per body and layer thicknesses (nets and thresholds
    do not change it)."""
    key = (cfg.body, tuple(layer.thickness_mm for layer in cfg.layers))
    if key not in _TISSUES:
        _TISSUES[key] = Tissue.from_config(cfg)
    return _TISSUES[key]


def model_for(cfg) -> NeedleModel:
    """A fresh needle model of ``cfg`` on its (cached) tissue."""
    return NeedleModel(cfg, tissue_for(cfg))


def twirl_roll(n: int, swing_deg: float = 180.0, freq_hz: float = 1.5) -> np.ndarray:
    """``n`` ticks of a sinusoidal twirl (rad) of ``swing_deg`` at ``freq_hz``."""
    t = np.arange(n) * DT
    return np.radians(0.5 * swing_deg) * np.sin(2.0 * np.pi * freq_hz * t)


def straight(z0: float, z1: float, speed: float) -> tuple[np.ndarray, np.ndarray]:
    """Tip along the z axis from z0 to z1 (m) at ``speed`` (m/s), one row per tick."""
    n = max(1, int(round(abs(z1 - z0) / (speed * DT))))
    sign = 1.0 if z1 >= z0 else -1.0
    z = z0 + sign * speed * DT * np.arange(1, n + 1)
    P = np.column_stack([np.zeros(n), np.zeros(n), z])
    V = np.tile([0.0, 0.0, sign * speed], (n, 1))
    return P, V


def stroke(z_top: float, amplitude: float, n: int, period_s: float = 2.0, t0: float = 0.0):
    """Cosine lift-and-press about the z axis: z = z_top - amplitude (1 - cos(2 pi t / T)) / 2,
    starting at ``z_top`` (m); ``n`` ticks; exact velocity."""
    t = t0 + DT * np.arange(1, n + 1)
    w = 2.0 * math.pi / period_s
    z = z_top - 0.5 * amplitude * (1.0 - np.cos(w * t))
    vz = -0.5 * amplitude * w * np.sin(w * t)
    zeros = np.zeros(n)
    return np.column_stack([zeros, zeros, z]), np.column_stack([zeros, zeros, vz])


@dataclasses.dataclass
class Scenario:
    name: str
    cfg: object
    pre_P: np.ndarray
    pre_V: np.ndarray
    P: np.ndarray
    V: np.ndarray
    layer: int  # the layer pressed (or -1: inside, no net)

    @property
    def R(self) -> np.ndarray:
        """The needle's roll (rad) on the measured ticks: a twirl of 180 deg swing at 1.5 Hz (the
        bundled even twirl), so every servo-tick figure includes the twirl phase winding tissue."""
        return twirl_roll(self.P.shape[0])

    @property
    def w(self) -> int:
        return self.cfg.layers[self.layer].rings if self.layer >= 0 else 0


def _find_contact(cfg, layer: int, speed: float = 0.01, z_stop: float = -0.05):
    """Drive a scratch model down the z axis from +1 mm until ``layer`` is pressed; returns the
    pre-path up to and including that tick."""
    m = model_for(cfg)
    P, V = straight(1e-3, z_stop, speed)
    for i in range(P.shape[0]):
        m.step(P[i], V[i])
        if m.states[layer] == PRESSING:
            return P[: i + 1], V[: i + 1]
    raise RuntimeError(f"layer {layer} never pressed on the way to z = {z_stop * 1e3:.1f} mm")


def press(n: int, layer: int = 0, w: int | None = None, base=None) -> Scenario:
    """Press ``layer`` (never puncturing it) for ``n`` ticks: from first touch, a 2 s cosine stroke
    between 0.1 mm and 1.1 mm past the contact point."""
    cfg = config_copy(base, layer=layer, w=w, never_puncture=True)
    pre_P, pre_V = _find_contact(cfg, layer)
    z_c = pre_P[-1, 2]
    # approach the stroke's top at the same speed, then stroke
    a_P, a_V = straight(z_c, z_c - 1e-4, 0.01)
    P, V = stroke(z_c - 1e-4, 1e-3, n)
    return Scenario(f"press_{LAYER_KEYS[layer]}_w{cfg.layers[layer].rings}", cfg,
                    np.vstack([pre_P, a_P]), np.vstack([pre_V, a_V]), P, V, layer)


def inside_muscle(n: int, base=None) -> Scenario:
    """Insert along -z at 10 mm/s to 20 mm below the skin (every layer punctured), then lift-thrust
    strokes of 4 mm at 0.75 Hz for ``n`` ticks."""
    cfg = base if base is not None else load_config()
    pre_P, pre_V = straight(5e-3, -20e-3, 0.01)
    P, V = stroke(-20e-3, -4e-3, n, period_s=1.0 / 0.75)  # negative amplitude: lift first
    return Scenario("inside_muscle", cfg, pre_P, pre_V, P, V, -1)


def check_state(model, scenario: Scenario) -> None:
    """The state each scenario claims: the pressed layer pressing, or every layer punctured."""
    st = model.states
    if scenario.layer >= 0:
        ok = st[scenario.layer] == PRESSING and all(s == PUNCTURED for s in st[: scenario.layer])
    else:
        ok = all(s == PUNCTURED for s in st)
    if not ok:
        raise RuntimeError(f"scenario {scenario.name}: model in states {st}, not the state it measures")

"""Shared helpers for the physics tests: synthetic tissues with simple numbers, config edits, drives.

Everything is SI (metres, newtons, seconds) except config fields, which keep their file units.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from haptic_acu.base.config import load_config
from haptic_acu.tissue.body import Tissue

# The synthetic layered tissue: a big sphere, so the skin is almost flat under the acupoint, every
# boundary is exactly a sphere about the same centre and depths along -z from the acupoint are radial.
SPHERE_R_MM = 200.0
SPHERE_THICK_MM = (1.0, 5.0, 20.0)  # skin, fat, muscle
SPHERE_DAMPING = (3.0, 1.0, 2.0)  # N*s/m per mm of needle in the layer; distinct, so layers can be told apart


def replace(cfg, section: str | None = None, **changes):
    """A copy of the frozen config with ``changes`` applied to ``section`` (or to the top level)."""
    if section is None:
        return dataclasses.replace(cfg, **changes)
    return dataclasses.replace(cfg, **{section: dataclasses.replace(getattr(cfg, section), **changes)})


def sphere_config(base=None, **layer_overrides):
    """config/tissue.toml with a 200 mm spherical body (bulge 0, lmax 2), layers 1/5/20 mm thick and
    damping 3/1/2. ``layer_overrides`` maps a layer name to a dict of field changes."""
    cfg = base if base is not None else load_config()
    cfg = replace(cfg, "body", semi_axes_mm=(SPHERE_R_MM,) * 3, bulge=0.0, lmax=2, fit_samples=200)
    for name, h, d in zip(("skin", "fat", "muscle"), SPHERE_THICK_MM, SPHERE_DAMPING):
        cfg = replace(cfg, name, thickness_mm=h, damping_n_s_per_m_per_mm=d, **layer_overrides.get(name, {}))
    return cfg


def sphere_tissue(cfg=None) -> Tissue:
    """The layered sphere of :func:`sphere_config`, built by the real fitting path."""
    return Tissue.from_config(cfg if cfg is not None else sphere_config())


def sh_sphere(radius_m: float, lmax: int = 2) -> np.ndarray:
    """Radial SH coefficients of a sphere: only the l=0 term, c00 = R sqrt(4 pi) (Y00 = 1/sqrt(4 pi))."""
    c = np.zeros((lmax + 1) ** 2)
    c[0] = radius_m * math.sqrt(4.0 * math.pi)
    return c


def layer_tops_m(cfg) -> np.ndarray:
    """Depth of each layer's top below the skin surface, and each layer's thickness (m)."""
    h = np.array([layer.thickness_mm for layer in cfg.layers]) * 1e-3
    return np.concatenate([[0.0], np.cumsum(h)[:-1]]), h


def damping_m(cfg) -> np.ndarray:
    """Each layer's d in N*s/m per metre of needle (Table 2's d is per mm: MODEL.md section 3)."""
    return np.array([layer.damping_n_s_per_m_per_mm for layer in cfg.layers]) * 1e3


def table1_damping(cfg, depth_m: float, punctured, speed: float) -> float:
    """Table 1's damping magnitude for a tip ``depth_m`` below the (uncompressed) skin surface with the
    layers flagged in ``punctured`` passed: sum_j d_j h_j |v|, h_j the needle length inside layer j."""
    tops, thick = layer_tops_m(cfg)
    d = damping_m(cfg)
    total = 0.0
    for j in range(3):
        if punctured[j]:
            total += d[j] * min(max(depth_m - tops[j], 0.0), thick[j])
    return total * speed


@dataclasses.dataclass
class Tick:
    p: np.ndarray
    v: np.ndarray
    force: np.ndarray
    diag: np.ndarray
    states: tuple


def drive(model, points, velocity) -> list[Tick]:
    """Step ``model`` through tip ``points`` (m), each with ``velocity`` (m/s, one vector or one per
    point); record every tick."""
    points = np.asarray(points, dtype=float)
    vel = np.broadcast_to(np.asarray(velocity, dtype=float), points.shape)
    out = []
    for p, v in zip(points, vel):
        f = model.step(p, v)
        out.append(Tick(p.copy(), v.copy(), np.array(f, dtype=float), model.diag.copy(),
                        model.states))
    return out


def straight_line(z0_m: float, z1_m: float, speed: float, dt: float = 1e-3, xy=(0.0, 0.0)):
    """Tip positions of a straight move along z from z0 to z1 at ``speed`` (m/s), one per tick of
    ``dt``, and the matching velocity vector."""
    n = int(round(abs(z1_m - z0_m) / (speed * dt)))
    sign = -1.0 if z1_m < z0_m else 1.0
    z = z0_m + sign * speed * dt * np.arange(1, n + 1)
    pts = np.column_stack([np.full(n, xy[0]), np.full(n, xy[1]), z])
    return pts, np.array([0.0, 0.0, sign * speed])


def state_arrays(model):
    """Every floating-point numpy array the model holds (directly or in a tuple/list attribute)."""
    found = []
    for name, val in vars(model).items():
        items = val if isinstance(val, (tuple, list)) else (val,)
        for i, a in enumerate(items):
            if isinstance(a, np.ndarray) and a.dtype.kind == "f":
                found.append((f"{name}[{i}]" if items is val else name, a))
    return found

"""The model fitted to one measured force-depth curve (``haptic-acu calibrate``): :func:`read_curve`,
:func:`find_break`, then :func:`fit_curve`, whose config :func:`config_toml` writes out.

Fits the model to one measured (or published) force-depth curve of a perpendicular insertion at
constant speed: the first layer's surface rises, breaks, then the needle cuts on (docs/model.md,
"Calibration"). CURVE.csv has a header with ``depth_mm`` and ``force_n`` (any order, other columns
ignored, ``#`` comments allowed); depth is measured from where the tip first touches the surface and
must increase strictly; force is the resisting force's magnitude.

How the fit works, and why it is fast. Pressing, the servo reads the first layer's force net from its
tabulated static response along the axis (:mod:`haptic_acu.tissue.netresponse`): for a perpendicular
insertion N1 sits on the axis, so the curve is the table's centred column, and the surface breaks at
the first depth where ring w's mean deflection passes the threshold. That column scales exactly: with
the ring count w, the pre-tension and the ratio ks/K fixed, F(c; K, L) = K L f(c / L) and the ring-w
deflection is L r(c / L). So each shape (ks/K, pre-tension) is solved once, dimensionless, and K and
L are fitted by a search over L with K in closed form (least squares); the shape by a coarse grid and
a few Nelder-Mead steps; the threshold is the ring-w deflection at the measured break. The fitted
parameters are then solved once more at the servo table's own resolution to report the fit the servo
will reproduce. After the break the rich mechanics (:mod:`haptic_acu.tissue.mechanics`) slide at the
cutting force plus (Coulomb + viscous x speed) x the needle length in the layer: cutting and Coulomb
are fitted by least squares (viscous and stiction ratio stay the base config's: one speed cannot tell
viscous from Coulomb), and the kernels are run tick by tick at the curve's speed to report the error.
"""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from ..base.errors import UserError

MIN_POINTS = 20
FIT_ROWS_PER_SPACING = 40  # the fit's dimensionless columns (the report uses the servo table's 400)
XI_MAX = 12.0  # deepest c / L the fit considers
MIN_THRESHOLD_UM = 0.05  # a ring-w deflection below this is solver noise, not a usable threshold
RATIOS = (3.0, 12.0, 50.0)
NET_RADIUS_OF_BODY = 0.5  # the net's outer ring (w - 1) L stays within half the body's smallest semi-axis
PRETENSIONS = (0.01, 0.05, 0.2)

# ---- the curve ----------------------------------------------------------------------------------------
MAX_CURVE_DEPTH_MM = 200.0  # deeper than any needle goes: a curve in micrometres?
MIN_CURVE_SPAN_MM = 0.5  # a curve spanning less than this: depth in metres?
MAX_CURVE_FORCE_N = 50.0  # a needle insertion's force is a few newtons: force in millinewtons?


def read_curve(path) -> tuple[np.ndarray, np.ndarray]:
    """(depth_mm, force_n) of a curve file; UserError naming the file and line on anything wrong.
    Read by :func:`haptic_acu.base.csvin.read_table` (its limits; a BOM is accepted); a curve whose
    numbers say they are in other units (metres, millinewtons) is refused."""
    from ..base.csvin import read_table

    path = Path(path)
    table = read_table(path, "curve file")
    header = table.header
    for need in ("depth_mm", "force_n"):
        if need not in header:
            raise UserError(f"{path}: line {table.header_line}: header has no '{need}' column (got "
                            f"{','.join(header)[:200]})")
    ix, ifc = header.index("depth_mm"), header.index("force_n")
    x, f = [], []
    for row in table.rows:
        lineno, cells = row.line, row.fields
        try:
            a, b = float(cells[ix]), float(cells[ifc])
        except (IndexError, ValueError):
            raise UserError(f"{path}: line {lineno}: expected numbers in depth_mm and force_n") from None
        if not (math.isfinite(a) and math.isfinite(b)):
            raise UserError(f"{path}: line {lineno}: not a finite number")
        if x and not a > x[-1]:
            raise UserError(f"{path}: line {lineno}: depth must increase strictly ({a:g} after {x[-1]:g} mm)")
        x.append(a)
        f.append(b)
    if len(x) < MIN_POINTS:
        raise UserError(f"{path}: {len(x)} points; at least {MIN_POINTS} are needed")
    x, f = np.array(x), np.array(f)
    if x[0] < 0:
        raise UserError(f"{path}: depth starts at {x[0]:g} mm; depth is measured from the first touch (>= 0)")
    span, peak = float(x[-1] - x[0]), float(np.abs(f).max())
    if span < MIN_CURVE_SPAN_MM:
        raise UserError(f"{path}: depth_mm spans {span:.3g} mm: is the depth in metres? (depth_mm is in "
                        f"millimetres; a needle insertion spans {MIN_CURVE_SPAN_MM:g} mm at least)")
    if x[-1] > MAX_CURVE_DEPTH_MM:
        raise UserError(f"{path}: depth_mm reaches {x[-1]:.4g} mm: is the depth in micrometres? (depth_mm "
                        f"is in millimetres; at most {MAX_CURVE_DEPTH_MM:g})")
    if peak > MAX_CURVE_FORCE_N:
        raise UserError(f"{path}: force_n reaches {peak:.4g} N: is the force in mN? (force_n is in newtons; "
                        f"a needle insertion's force is at most {MAX_CURVE_FORCE_N:g} N)")
    return x, f


def find_break(path, x, f) -> int:
    """Index of the break: the point before the largest drop within a short window, which must lose at
    least a fifth of the force there, with enough points on both sides."""
    n = len(f)
    win = max(3, n // 100)
    drop = np.array([f[i] - f[i + 1:i + 1 + win].min() for i in range(n - 1)])
    i = int(np.argmax(drop))
    if not (f[i] > 0 and drop[i] >= 0.2 * f[i]):
        raise UserError(f"{path}: no break: the force never drops by a fifth (largest drop {drop[i]:.3g} N "
                        f"at {x[i]:g} mm)")
    if i < 5 or n - 1 - i < 5:
        raise UserError(f"{path}: the break at {x[i]:g} mm leaves fewer than 5 points on one side")
    return i


# ---- the rise: the first layer's net ------------------------------------------------------------------
def solve_centred_column(w, spacing_m, kv, ks, pretension, depth_max_m, rows_per_spacing, tol_m):
    """N1's reaction (N) and ring w's mean deflection (m) at c = i h on the net's axis: the servo
    table's centred column (:func:`haptic_acu.tissue.netresponse.solve_column`)."""
    from .forcenet import NetParams, Topology
    from .netresponse import Column, ColumnOut, _flat_net, flat_column_net, solve_column

    p = NetParams(int(w), spacing_m, kv, ks, pretension, 1.0)
    lat, n, X0f, rest = _flat_net(p)
    h = spacing_m / rows_per_spacing
    nc = int(math.ceil(depth_max_m / h)) + 2
    F, R = np.empty(nc), np.empty(nc)
    solve_column(flat_column_net(X0f, rest), Topology(lat.nbr, lat.ring, lat.plane), p.springs(),
                 Column(0.0, 0.0, h, nc, tol_m, 20000), ColumnOut(F, R, np.empty((0, n, 3))))
    return np.arange(nc) * h, F, R


class RiseFit:
    """Fits (ks/K, pre-tension) by grid + Nelder-Mead, (K, L) by scaling, threshold at the break."""

    def __init__(self, x_mm, f_n, xb_mm, w, tol_m, max_spacing_mm):
        self.x, self.f, self.xb, self.w, self.tol = x_mm, f_n, xb_mm, w, tol_m
        self.max_spacing = max_spacing_mm
        self.cache = {}
        self.sst = float(((f_n - f_n.mean()) ** 2).sum()) or 1.0

    def shape(self, ratio, pre):
        key = (round(ratio, 9), round(pre, 9))
        if key not in self.cache:  # dimensionless: L = 1 mm, K = 1 N/mm
            xi, F, R = solve_centred_column(self.w, 1e-3, 1e3, ratio * 1e3, pre, XI_MAX * 1e-3,
                                            FIT_ROWS_PER_SPACING, self.tol)
            self.cache[key] = (xi * 1e3, F, R * 1e3)  # xi, F (N at K L = 1 N), R (mm at L = 1 mm)
        return self.cache[key]

    def best_scale(self, ratio, pre):
        """(sse, K N/mm, L mm, threshold um) for one shape: L on a log grid, K by least squares."""
        xi, F, R = self.shape(ratio, pre)
        best = (math.inf, 1.0, 1.0, 0.0)
        lo = self.xb / XI_MAX
        hi = max(min(4.0 * self.xb, self.max_spacing), lo)
        for L in np.geomspace(lo, hi, 90):
            g = L * np.interp(self.x / L, xi, F)
            gg = float(g @ g)
            if gg <= 0:
                continue
            K = float(g @ self.f) / gg
            if K <= 0:
                continue
            thr_um = L * float(np.interp(self.xb / L, xi, R)) * 1e3
            sse = float(((K * g - self.f) ** 2).sum())
            if thr_um < MIN_THRESHOLD_UM:
                sse += self.sst * (1.0 + MIN_THRESHOLD_UM / max(thr_um, 1e-12))
            if sse < best[0]:
                best = (sse, K, L, thr_um)
        return best

    def run(self):
        from scipy.optimize import minimize

        grid = [(self.best_scale(r, p)[0], r, p) for r in RATIOS for p in PRETENSIONS]
        _, r0, p0 = min(grid)

        def cost(z):
            r, p = math.exp(z[0]), 1.0 / (1.0 + math.exp(-z[1])) * 0.45  # ratio > 0, 0 < pre < 0.45
            return self.best_scale(r, p)[0]

        z0 = [math.log(r0), -math.log(0.45 / p0 - 1.0)]
        res = minimize(cost, z0, method="Nelder-Mead", options=dict(maxfev=14, xatol=0.05, fatol=1e-9 * self.sst))
        r, p = math.exp(res.x[0]), 1.0 / (1.0 + math.exp(-res.x[1])) * 0.45
        if res.fun > min(grid)[0]:
            r, p = r0, p0
        sse, K, L, thr = self.best_scale(r, p)
        return dict(k_virtual_n_per_mm=float(K), k_surface_n_per_mm=float(K * r), pretension=float(p),
                    spring_length_mm=float(L), rings=int(self.w), puncture_threshold_um=float(thr))


def rise_report(fit, x, f, ib, tol_m):
    """The fitted net solved at the servo table's resolution: R^2 of the rise, the predicted break
    (first depth where ring w passes the threshold, as the servo tests it) and its force."""
    from .netresponse import ROWS_PER_SPACING

    L = fit["spring_length_mm"] * 1e-3
    c, F, R = solve_centred_column(fit["rings"], L, fit["k_virtual_n_per_mm"] * 1e3, fit["k_surface_n_per_mm"] * 1e3,
                                   fit["pretension"], 1.3 * x[ib] * 1e-3, ROWS_PER_SPACING, tol_m)
    over = np.nonzero(R > fit["puncture_threshold_um"] * 1e-6)[0]
    jb = int(over[0]) if over.size else len(c) - 1
    xb_pred, fb_pred = c[jb] * 1e3, float(F[max(jb - 1, 0)])
    rise = slice(0, ib + 1)
    pred = np.interp(x[rise] * 1e-3, c, F)
    sst = float(((f[rise] - f[rise].mean()) ** 2).sum()) or 1.0
    r2 = 1.0 - float(((pred - f[rise]) ** 2).sum()) / sst
    return dict(r2=r2, break_depth_mm=xb_pred, break_force_n=fb_pred)


# ---- after the break: cutting and friction ------------------------------------------------------------
POST_S_PER_TICK = 25e-6  # post_model: a Python loop over the servo kernels, 25 us a tick measured
POST_BYTES_PER_TICK = 16.0  # its tick and force arrays


def check_post_cost(speed_mm_s: float, length_mm: float) -> None:
    """Refuse a curve whose post-break stretch replayed tick by tick at ``speed_mm_s`` would pass the
    cost budget (:mod:`haptic_acu.base.budget`)."""
    from ..base.budget import check_ticks

    ticks = length_mm / speed_mm_s * 1e3
    check_ticks(f"--speed-mm-s {speed_mm_s:g} over the curve's {length_mm:.3g} mm after the break", ticks,
                POST_S_PER_TICK, POST_BYTES_PER_TICK)


def post_model(layer, needle, thickness_mm, x_mm, xb_mm, speed_m_s):
    """Force magnitude (N) the rich mechanics give at depths ``x_mm`` after a break at ``xb_mm``, the
    tip advancing at ``speed_m_s`` in the first layer, run tick by tick with the servo's kernels."""
    from . import mechanics as m

    prm = m.mech_params((layer, layer, layer), needle)
    st, tracks = m.new_friction_state(), m.new_tracks()
    ax = np.array([0.0, 0.0, -1.0])
    j = m.begin_track(tracks, np.zeros(3), ax, prm.radius)
    bounds = np.array([0.0, thickness_mm, thickness_mm + 1e3, thickness_mm + 2e3]) * 1e-3
    L = np.zeros(3)
    s_end = float(x_mm[-1]) * 1e-3
    ticks = np.arange(xb_mm * 1e-3, s_end + speed_m_s * 1e-3, speed_m_s * 1e-3)
    out = np.empty(len(ticks))
    for i, s in enumerate(ticks):
        m.lengths_in_layers(s, bounds, prm.length, L)
        out[i] = -m.post_puncture_force(prm, st, tracks, j, m.Tip(s, speed_m_s, s * ax, ax, bounds, L, 1))
    return np.interp(x_mm * 1e-3, ticks, out)


def fit_post(x, f, ib, speed_m_s, layer, needle, thickness_mm):
    """Cutting (N per mm of diameter), Coulomb (N per mm per mm of diameter) and viscous (N*s/m per mm
    per mm of diameter) from the steady sliding force cut + (fc + b v) L past the stick transient: the
    intercept is the cutting force, the slope is split between Coulomb and viscous in the base
    config's proportion at this speed (one speed cannot tell them apart)."""
    dmm = needle.diameter_mm
    post = slice(ib + 1, None)
    xp, y = x[post], f[post]
    L = np.minimum(xp, thickness_mm)  # mm of needle in the layer (physical depth, one geometry)
    settle = xp > x[ib] + 0.25 * (xp[-1] - x[ib])
    if np.count_nonzero(settle) < 3:
        settle = np.ones_like(xp, dtype=bool)
    A = np.stack([np.ones(np.count_nonzero(settle)), L[settle]], axis=1)
    coef = np.linalg.lstsq(A, y[settle], rcond=None)[0]
    if coef[1] < 0:
        coef = np.array([max(float(y[settle].mean()), 0.0), 0.0])
    if coef[0] < 0:
        coef = np.array([0.0, max(float(L[settle] @ y[settle] / (L[settle] @ L[settle])), 0.0)])
    fc0 = layer.coulomb_n_per_mm2
    bv0 = layer.viscous_n_s_per_m_per_mm2 * speed_m_s
    share = fc0 / (fc0 + bv0) if fc0 + bv0 > 0 else 1.0
    slope = float(coef[1]) / dmm  # N per mm of needle per mm of diameter
    return float(coef[0]) / dmm, share * slope, (1.0 - share) * slope / speed_m_s


# ---- the config ---------------------------------------------------------------------------------------
def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, tuple):
        return "[" + ", ".join(_toml_value(a) for a in v) + "]"
    raise TypeError(type(v))  # pragma: no cover


def config_toml(cfg, header: str) -> str:
    """A complete config file for ``cfg`` (every section and key of the schema)."""
    from ..base.config import _SECTIONS

    lines = ["# " + h for h in header.splitlines()]
    for name in _SECTIONS:
        sec = getattr(cfg, name)
        lines += ["", f"[{name}]"]
        for fld in dataclasses.fields(sec):
            if fld.name != "name":
                lines.append(f"{fld.name} = {_toml_value(getattr(sec, fld.name))}")
    return "\n".join(lines) + "\n"


def _make_room(cfg, first_mm):
    """The first layer ``first_mm`` thick; the layers beneath thinned (muscle first, to 1 mm) so the
    stack is no thicker than the base config's."""
    total = sum(layer.thickness_mm for layer in cfg.layers)
    fat, muscle = cfg.fat.thickness_mm, cfg.muscle.thickness_mm
    excess = first_mm + fat + muscle - total
    if excess > 0:
        take = min(excess, muscle - 1.0)
        muscle -= take
        excess -= take
        fat = max(1.0, fat - excess)
    if first_mm + fat + muscle >= 0.9 * min(cfg.body.semi_axes_mm):
        raise UserError(f"the curve reaches {first_mm:g} mm: deeper than the body allows (body.semi_axes_mm)")
    return dataclasses.replace(cfg, fat=dataclasses.replace(cfg.fat, thickness_mm=round(fat, 6)),
                               muscle=dataclasses.replace(cfg.muscle, thickness_mm=round(muscle, 6)))


def fit_curve(cfg, x, f, ib, speed_mm_s):
    """``cfg`` fitted to the curve (``x`` mm, ``f`` N) that breaks at index ``ib``, inserted at
    ``speed_mm_s``: (the fitted config, the rise's fit, its :func:`rise_report`, the relative error of
    the mean force after the break)."""
    tol_m = cfg.solver.static_tolerance_um * 1e-6
    w = cfg.skin.rings
    max_spacing = NET_RADIUS_OF_BODY * min(cfg.body.semi_axes_mm) / (w - 1)
    fit = RiseFit(x[:ib + 1], f[:ib + 1], float(x[ib]), w, tol_m, max_spacing).run()
    rep = rise_report(fit, x, f, ib, tol_m)
    first_mm = max(cfg.skin.thickness_mm, math.ceil(float(x[-1])) + 1.0)
    cfg = _make_room(cfg, first_mm)
    v = speed_mm_s * 1e-3
    skin = dataclasses.replace(cfg.skin, thickness_mm=first_mm, **fit)
    cut, fc, visc = fit_post(x, f, ib, v, skin, cfg.needle, first_mm)
    skin = dataclasses.replace(skin, cutting_n_per_mm_diameter=cut, coulomb_n_per_mm2=fc,
                               viscous_n_s_per_m_per_mm2=visc)
    # the fitted threshold breaks the skin at the curve's speed: that is the speed thresholds apply at
    cfg = dataclasses.replace(cfg, skin=skin, needle=dataclasses.replace(cfg.needle, mechanics="rich"),
                              rupture=dataclasses.replace(cfg.rupture, reference_speed_mm_s=speed_mm_s))
    post = slice(ib + 1, None)
    pred = post_model(skin, cfg.needle, first_mm, x[post], float(x[ib]), v)
    post_err = abs(pred.mean() - f[post].mean()) / max(abs(f[post].mean()), 1e-9)
    return cfg, fit, rep, post_err

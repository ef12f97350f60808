"""Fit the default surface nets (config/tissue.toml) to the published puncture targets (docs/model.md,
section 2.1), keeping each layer's Table 2 K, and its w and L where the fit allows (LAYOUT below).

Run: ``.venv/bin/python tools/fit_defaults.py`` (about 10 s). It prints, per layer, the target,
the fitted surface-spring stiffness, pre-tension and ring-w threshold, and the fit at the servo
table's own resolution (R^2 of the rise, break depth and force errors). The numbers go into
config/tissue.toml by hand, with the figures into docs/model.md.

How. ``haptic-acu calibrate`` fits the first layer with K and L free (:class:`RiseFit`). Every layer's
net is the same lattice with its own (w, K, L, ks, pre-tension, threshold), and its centred column
scales exactly: F(c) = K L f(c / L; w, ks/K, pre) and ring w's deflection L r(c / L) (docs/model.md
section 10). So the fit reuses :meth:`RiseFit.shape` (the dimensionless column of one shape) for any
layer's w, holds K at Table 2's value and w, L at LAYOUT's, and searches only the shape (ks/K,
pre-tension), on a grid and then Nelder-Mead; the threshold is the ring-w deflection at the target's break depth.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import minimize

from haptic_acu.tissue.calibration import RiseFit, rise_report
from haptic_acu.base.config import load_config

# Rise shape: Okamura, Simone and O'Leary 2004's f = a1 x + a2 x^2 before a puncture, with their
# liver's curvature relative to the break (a2 x_b / a1 = 0.0061 * 16.7 / 0.048 = 2.12), scaled to each
# target's break (depth x_b, force F_b).
CURVATURE = 0.0061 * 16.7 / 0.048
N_POINTS = 60

# Targets for a 0.25 mm acupuncture needle (docs/model.md section 2.1): (break depth mm, break force N)
TARGETS = {
    "skin": (1.5, 0.50),
    "fat": (1.0, 0.20),
    "muscle": (1.0, 0.65),
}
# Ring count w and spacing L per layer. Table 2's (skin 8 / 2 mm, fat 4 / 1 mm, muscle 10 / 2.5 mm) where
# the fit allows. With Table 2's w the skin's and muscle's outer ring moves less than 0.05 um (skin) and
# 0.002 um (muscle) at the target break: a threshold at solver-noise level (the static tolerance is
# 1e-4 um), so those nets get fewer rings. The muscle's rise also needs a shorter spacing: at L = 2.5 mm
# the rise's R^2 stays at 0.944 (below calibrate's 0.95) with any w <= 5; at 1.5 mm (w 3-5) it fits
# with stiff surface springs and almost no pre-tension (ks/K 4), but that net's response depends on
# the direction of a lateral offset (the lattice's sixfold anisotropy, which the servo's table leaves
# out) by up to 9-24% of the threshold; at 0.75 mm it fits with ks ~ K and the anisotropy is 1e-5
# (docs/model.md section 2.1).
LAYOUT = {"skin": (3, 2.0), "fat": (4, 1.0), "muscle": (4, 0.75)}
MIN_THRESHOLD_UM = 1.0  # the smallest ring-w threshold we accept (10^4 times the static tolerance)
RATIO_GRID = (0.05, 0.2, 1.0, 5.0, 25.0, 100.0)
PRE_GRID = (0.01, 0.05, 0.2, 0.4)


def target_curve(xb_mm: float, fb_n: float) -> tuple[np.ndarray, np.ndarray]:
    x = np.linspace(xb_mm / N_POINTS, xb_mm, N_POINTS)
    u = x / xb_mm
    return x, fb_n * (u + CURVATURE * u * u) / (1.0 + CURVATURE)


def fit_fixed_scale(x, f, xb, w, k_n_per_mm, l_mm, tol_m):
    """(ks/K, pre-tension, threshold um) of the net with K and L held, least squares on the rise."""
    rf = RiseFit(x, f, xb, w, tol_m, max_spacing_mm=l_mm)

    def sse(ratio, pre):
        xi, F, R = rf.shape(ratio, pre)
        g = k_n_per_mm * l_mm * np.interp(x / l_mm, xi, F)
        thr_um = l_mm * float(np.interp(xb / l_mm, xi, R)) * 1e3
        cost = float(((g - f) ** 2).sum())
        if thr_um < 0.05:  # calibrate_cmd.MIN_THRESHOLD_UM: below it the threshold is solver noise
            cost += rf.sst
        return cost, thr_um

    grid = [(sse(r, p)[0], r, p) for r in RATIO_GRID for p in PRE_GRID]
    _, r0, p0 = min(grid)

    def cost(z):
        return sse(math.exp(z[0]), 0.45 / (1.0 + math.exp(-z[1])))[0]

    z0 = [math.log(r0), -math.log(0.45 / p0 - 1.0)]
    res = minimize(cost, z0, method="Nelder-Mead", options=dict(maxfev=40, xatol=0.02, fatol=1e-12))
    r, p = math.exp(res.x[0]), 0.45 / (1.0 + math.exp(-res.x[1]))
    if res.fun > min(grid)[0]:
        r, p = r0, p0
    return r, p, sse(r, p)[1]


def main() -> None:
    cfg = load_config()
    tol_m = cfg.solver.static_tolerance_um * 1e-6
    for name, (xb, fb) in TARGETS.items():
        layer = getattr(cfg, name)
        x, f = target_curve(xb, fb)
        K = layer.k_virtual_n_per_mm
        w, L = LAYOUT[name]
        ratio, pre, thr = fit_fixed_scale(x, f, xb, w, K, L, tol_m)
        fit = dict(k_virtual_n_per_mm=K, k_surface_n_per_mm=K * ratio, pretension=pre, spring_length_mm=L,
                   rings=w, puncture_threshold_um=thr)
        rep = rise_report(fit, x, f, len(x) - 1, tol_m)
        print(f"{name}: target break {xb:g} mm at {fb:g} N; K {K:g} N/mm (Table 2), w {w}, L {L:g} mm; "
              f"fitted ks {K * ratio:.4g} N/mm, pre-tension {pre:.4g}, threshold {thr:.4g} um; "
              f"rise R^2 {rep['r2']:.4f}, break {rep['break_depth_mm']:.4g} mm "
              f"({100 * (rep['break_depth_mm'] - xb) / xb:+.1f}%), {rep['break_force_n']:.4g} N "
              f"({100 * (rep['break_force_n'] - fb) / fb:+.1f}%)")
        assert thr >= MIN_THRESHOLD_UM, (name, thr)


if __name__ == "__main__":
    main()

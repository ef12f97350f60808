"""``haptic-acu calibrate CURVE.csv --speed-mm-s V --out FITTED.toml [--config BASE.toml]``.

Fits the model to one measured (or published) force-depth curve of a perpendicular insertion at
constant speed (:mod:`haptic_acu.tissue.calibration`, which says how; docs/model.md,
"Calibration") and writes the fitted config, never over an existing file. CURVE.csv has a header
with ``depth_mm`` and ``force_n`` (any order, other columns ignored, ``#`` comments allowed); depth
is measured from where the tip first touches the surface and must increase strictly; force is the
resisting force's magnitude.
"""
from __future__ import annotations

import dataclasses
import math
import sys
import time
from pathlib import Path

from ..base.errors import UserError
from ..tissue.calibration import check_post_cost, config_toml, find_break, fit_curve, read_curve
from .options import add_config_args, config_from_args


def register(sub) -> None:
    p = sub.add_parser("calibrate", help="fit the first layer and the post-puncture mechanics to a measured curve",
                       description="Fit the first layer's force net (stiffness, surface springs, pre-tension, "
                                   "spacing, threshold) to the rise and break of CURVE.csv (depth_mm,force_n of "
                                   "one perpendicular insertion at constant speed), and the cutting and Coulomb "
                                   "friction to what follows; write a complete config.")
    p.add_argument("curve", metavar="CURVE.csv")
    p.add_argument("--speed-mm-s", type=float, required=True, metavar="V", help="the insertion speed of the curve")
    p.add_argument("--out", required=True, metavar="FITTED.toml", help="the config to write (never overwritten)")
    add_config_args(p)
    p.add_argument("--needle-diameter-mm", type=float, metavar="D",
                   help="diameter of the needle the curve was measured with (default: the config's)")
    p.set_defaults(func=run)


def _write_checked(out: Path, text: str) -> None:
    """Write ``text`` to ``out`` only if it loads as a config, and never over an existing file."""
    import os
    import tempfile

    from ..base.config import load_config

    try:
        fd, tmp = tempfile.mkstemp(dir=out.parent if str(out.parent) else ".", suffix=".toml.partial")
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        try:
            load_config(tmp)
            os.link(tmp, out)  # fails if out appeared meanwhile: nothing is overwritten
        finally:
            os.unlink(tmp)
    except FileExistsError:
        raise UserError(f"{out}: exists; calibrate never overwrites a file (choose another --out)") from None
    except OSError as e:
        raise UserError(f"{out}: cannot write: {e.strerror}") from None


def run(args) -> int:
    from ..base.outputs import Outputs

    t0 = time.perf_counter()
    out = Path(args.out)
    if out.exists() or out.is_symlink():
        raise UserError(f"{out}: exists; calibrate never overwrites a file (choose another --out)")
    Outputs().input("CURVE.csv", args.curve).input("--config", args.config).file("--out", out).check()
    if not (math.isfinite(args.speed_mm_s) and args.speed_mm_s > 0):
        raise UserError(f"--speed-mm-s must be a positive number, got {args.speed_mm_s}")
    cfg = config_from_args(args)
    if args.needle_diameter_mm is not None:
        if not (math.isfinite(args.needle_diameter_mm) and args.needle_diameter_mm > 0):
            raise UserError(f"--needle-diameter-mm must be a positive number, got {args.needle_diameter_mm}")
        cfg = dataclasses.replace(cfg, needle=dataclasses.replace(cfg.needle, diameter_mm=args.needle_diameter_mm))
    x, f = read_curve(args.curve)
    ib = find_break(args.curve, x, f)
    check_post_cost(args.speed_mm_s, float(x[-1] - x[ib]))
    if f[ib] > cfg.safety.force_limit_n:
        print(f"haptic-acu: warning: {args.curve}: the break at {f[ib]:.3g} N is beyond the device's "
              f"{cfg.safety.force_limit_n:g} N (safety.force_limit_n): the fitted skin cannot be felt to break",
              file=sys.stderr)
    cfg, fit, rep, post_err = fit_curve(cfg, x, f, ib, args.speed_mm_s)
    header = (f"written by haptic-acu calibrate from {args.curve} at {args.speed_mm_s:g} mm/s, base "
              f"{cfg.path}\nfitted: skin (the first layer) net, thickness, cutting and Coulomb friction; "
              f"the rest is the base config's")
    _write_checked(out, config_toml(cfg, header))
    _print_report(args, x, f, ib, fit, rep, cfg, post_err, time.perf_counter() - t0)
    return 0


def _print_report(args, x, f, ib, fit, rep, cfg, post_err, elapsed):
    xb, fb = float(x[ib]), float(f[ib])
    d = cfg.needle.diameter_mm
    cut, fc = cfg.skin.cutting_n_per_mm_diameter, cfg.skin.coulomb_n_per_mm2
    print(f"{args.curve}: {len(x)} points, break at {xb:.3g} mm, {fb:.3g} N")
    print(f"  first layer net: K {fit['k_virtual_n_per_mm']:.4g} N/mm, surface springs "
          f"{fit['k_surface_n_per_mm']:.4g} N/mm, pre-tension {fit['pretension']:.3g}, "
          f"L {fit['spring_length_mm']:.4g} mm, "
          f"w {fit['rings']}, threshold {fit['puncture_threshold_um']:.4g} um; thickness {cfg.skin.thickness_mm:g} mm")
    sk = cfg.skin
    print(f"  after the break ({d:g} mm needle): cutting {cut * d:.4g} N ({cut:.4g} N/mm of diameter), Coulomb "
          f"{fc * d:.4g} N per mm of needle ({fc:.4g} N/mm^2), viscous {sk.viscous_n_s_per_m_per_mm2 * d:.4g} "
          f"N*s/m per mm of needle")
    print(f"  rise R^2 {rep['r2']:.4f}; break depth {rep['break_depth_mm']:.4g} mm "
          f"({100 * (rep['break_depth_mm'] - xb) / xb:+.1f}%), force {rep['break_force_n']:.4g} N "
          f"({100 * (rep['break_force_n'] - fb) / fb:+.1f}%); mean force after the break {100 * post_err:.1f}% off")
    print(f"  wrote {args.out} ({elapsed:.1f} s)")

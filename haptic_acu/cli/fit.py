"""``haptic-acu fit``: build the default tissue, or fit a body-surface mesh with spherical harmonics.

* ``haptic-acu fit [--config FILE]`` builds the layered tissue the config describes
  (:meth:`Tissue.from_config`) and prints how well each of its four boundaries is fitted and how deep
  each lies below the acupoint, against the config's layer thicknesses.
* ``haptic-acu fit MESH.obj [--lmax N] [--out FILE.npz]`` reads the mesh's vertices (mm), fits their
  distance from the vertex centroid as a radial surface r(theta, phi) to degree N (default: the
  config's ``body.lmax``) and reports the radial fit error. ``--out`` writes the coefficients for a
  config's ``body.skin_coefficients``: a ``.npz`` file, or a folder (as ``--out`` is for the other
  commands), which gets ``<mesh name>_sh.npz``. The fit assumes the surface is star-shaped about the centroid
  (every ray from it crosses the surface once); a mesh that is not cannot be represented and shows as
  a large fit error.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from ..base.errors import UserError

MAX_LMAX = 40  # the config's limit on body.lmax; a fit for a config need not go further


def register(sub) -> None:
    p = sub.add_parser("fit", help="build the default tissue, or fit a mesh's surface with spherical harmonics",
                       description="Without MESH.obj: build the config's layered tissue and report its fit. "
                                   "With MESH.obj: fit the mesh's vertices (mm) radially about their centroid "
                                   "and report the radial fit error; --out writes the coefficients for "
                                   "body.skin_coefficients.")
    p.add_argument("mesh", nargs="?", metavar="MESH.obj", help="OBJ mesh of a body surface, in mm")
    p.add_argument("--lmax", type=int, metavar="N", help="SH degree of the mesh fit (default: the config's body.lmax)")
    p.add_argument("--overwrite", action="store_true", help="let --out replace an existing file (never the mesh)")
    p.add_argument("--out", metavar="FILE.npz|DIR",
                   help="write the mesh fit's coefficients to FILE.npz, or into the folder DIR as <mesh>_sh.npz")
    from .options import add_config_args
    add_config_args(p)
    p.set_defaults(func=run)


def run(args) -> int:
    if args.mesh is None:
        if args.lmax is not None or args.out is not None:
            raise UserError("--lmax and --out apply to a mesh fit: give MESH.obj (the tissue's degree is "
                            "the config's body.lmax)")
        return _summarise_tissue(args)
    return _fit_mesh(args.mesh, args.lmax, args.out, args)


def _summarise_tissue(args) -> int:
    from .options import config_from_args

    cfg = config_from_args(args)  # before importing the numba kernels: a bad config fails fast
    from ..tissue.body import BOUNDARIES, Tissue

    t0 = time.perf_counter()
    tissue = Tissue.from_config(cfg)  # numba's first compile is reported (haptic_acu.base.progress)
    elapsed = time.perf_counter() - t0
    body = cfg.body
    source = body.skin_coefficients or (f"built-in limb, semi-axes {' x '.join(f'{a:g}' for a in body.semi_axes_mm)}"
                                        f" mm, bulge {body.bulge:g}")
    nominal = np.concatenate([[0.0], np.cumsum(tissue.thickness_m)]) * 1e3
    depth = tissue.depths_at_acupoint() * 1e3
    print(f"tissue from {cfg.path}")
    print(f"  skin surface: {source}")
    print(f"  lmax {tissue.lmax} ({tissue.coeffs.shape[1]} coefficients per boundary), "
          f"{body.fit_samples} samples per boundary")
    print(f"  {'boundary':<13} {'fit RMS':>10} {'fit max':>10} {'depth at acupoint':>18} {'config':>10}")
    for k, name in enumerate(BOUNDARIES):
        print(f"  {name:<13} {tissue.fit_rms_m[k] * 1e3:7.1e} mm {tissue.fit_max_m[k] * 1e3:7.1e} mm "
              f"{depth[k]:15.3f} mm {nominal[k]:7.3f} mm")
    print(f"  built in {elapsed:.3f} s")
    return 0


def _fit_mesh(mesh, lmax, out, args) -> int:
    from ..tissue.objmesh import read_vertices

    if lmax is None:
        from .options import config_from_args

        lmax = config_from_args(args).body.lmax
    if not 0 <= lmax <= MAX_LMAX:
        raise UserError(f"--lmax must be between 0 and {MAX_LMAX}, got {lmax}")
    out_path = Path(out) if out is not None else None
    if out_path is not None and (out_path.is_dir() or out.endswith(("/", os.sep))):
        if not out_path.is_dir():
            raise UserError(f"{out}: cannot write: folder {out_path} does not exist")
        out_path = out_path / f"{Path(mesh).stem}_sh.npz"
    if out_path is not None and out_path.suffix != ".npz":
        raise UserError(f"{out}: --out must name a .npz file or an existing folder")
    if out_path is not None and not out_path.parent.is_dir():
        raise UserError(f"{out}: cannot write: directory {out_path.parent} does not exist")
    if out_path is not None:
        from ..base.outputs import Outputs
        Outputs(overwrite=args.overwrite).input("MESH.obj", mesh).input("--config", getattr(args, "config", None)).file(
            "--out", out_path).check()
    t0 = time.perf_counter()
    pts, lines = read_vertices(mesh)
    from ..base.budget import check_sh_fit
    check_sh_fit(lmax, len(pts), f"{mesh}: --lmax {lmax} with {len(pts):,} vertices", keys=False)
    from ..tissue import shf  # the numba kernels, once the input is known to be good
    from ..tissue.body import save_coefficients
    from ..tissue.objmesh import fit_radial

    need = shf.n_coeffs(lmax)
    coeffs, centre, rho, resid = fit_radial(mesh, pts, lines, lmax)
    rms = float(np.sqrt(np.mean(resid ** 2)))
    worst = int(np.argmax(np.abs(resid)))
    elapsed = time.perf_counter() - t0
    print(f"mesh {mesh}: {len(pts)} vertices, centroid ({', '.join(f'{c * 1e3:.3f}' for c in centre)}) mm, "
          f"radius {rho.min() * 1e3:.2f} to {rho.max() * 1e3:.2f} mm")
    print(f"  lmax {lmax} ({need} coefficients), fitted in {elapsed:.3f} s")
    print(f"  radial fit error: RMS {rms * 1e3:.2e} mm, max {abs(resid[worst]) * 1e3:.2e} mm "
          f"(vertex on line {lines[worst]})")
    if out_path is not None:
        import io

        from ..base.outputs import write_new
        buf = io.BytesIO()
        save_coefficients(buf, coeffs, centre, source=str(mesh))
        write_new(out_path, buf.getvalue(), overwrite=args.overwrite)  # whole, and never over a file unasked
        print(f"  wrote {out_path} (use body.skin_coefficients = \"{out_path.name}\" with body.lmax = {lmax})")
    return 0

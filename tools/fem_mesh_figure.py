"""Draw the FEM baseline's mesh of the default body (docs/img/fem-mesh-section.png): the section of
the structured mesh through the acupoint across the limb (the chart's x = 0 plane, where the skin
curves most), its grid lines coloured by layer, with the SH boundaries evaluated on their own
(docs/model.md section 12.3).

    python tools/fem_mesh_figure.py [OUT.png]
"""
from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from haptic_acu.base.config import load_config  # noqa: E402
from haptic_acu.tissue import fem, shf  # noqa: E402
from haptic_acu.tissue.body import Tissue  # noqa: E402

COLOURS = ("#c0504d", "#e6b84c", "#8064a2")
NAMES = ("skin", "fat", "muscle")


def main(out: str = "docs/img/fem-mesh-section.png") -> int:
    cfg = load_config()
    tis = Tissue.from_config(cfg)
    bnd = fem.sh_boundaries(tis.coeffs, tis.centre, 0)
    a = 0.5 * cfg.needle.diameter_mm * 1e-3
    bm = fem.body_mesh(bnd, np.zeros(3), a)
    X, Y = bm.lateral
    p = bm.mesh.p
    sec = np.isclose(X, 0.0)  # the section's nodes: y across the limb, z up
    fig, ax = plt.subplots(figsize=(8, 4.6), dpi=120)
    ys = np.unique(Y[sec])
    zs = np.unique(bm.depth[sec])
    nominal = tis.depths_at_acupoint()
    for z in zs:  # lines of constant nominal depth
        on = sec & np.isclose(bm.depth, z)
        o = np.argsort(Y[on])
        layer = min(int(np.searchsorted(nominal, z + 1e-12, side="right")) - 1, 2)
        ax.plot(p[1, on][o] * 1e3, p[2, on][o] * 1e3, color=COLOURS[max(layer, 0)], lw=0.6)
    for y in ys:  # the columns (radial lines from the body's centre)
        on = sec & np.isclose(Y, y)
        o = np.argsort(bm.depth[on])
        ax.plot(p[1, on][o] * 1e3, p[2, on][o] * 1e3, color="0.55", lw=0.4)
    # the SH boundaries on their own, a little wider than the block
    t = np.linspace(-10e-3, 10e-3, 200) / -tis.centre[2]
    dirs = np.stack([np.zeros_like(t), np.sin(t), np.cos(t)], 1)
    theta = np.arccos(dirs[:, 2])
    phi = np.arctan2(dirs[:, 1], dirs[:, 0])
    for k in range(3):
        r = shf.evaluate(tis.coeffs[k], theta, phi)
        pts = tis.centre + dirs * r[:, None]
        ax.plot(pts[:, 1] * 1e3, pts[:, 2] * 1e3, "k--", lw=0.8, label="SH boundaries" if k == 0 else None)
    for k in sorted(set(bm.layer.tolist())):
        ax.plot([], [], color=COLOURS[k], label=NAMES[k])
    ax.set_aspect("equal")
    ax.set_xlabel("y across the limb (mm)")
    ax.set_ylabel("z (mm)")
    ax.set_title(f"FEM mesh through the acupoint: {p.shape[1]} nodes, {bm.mesh.t.shape[1]} tetrahedra", fontsize=10)
    ax.legend(loc="center right", fontsize=8)
    fig.tight_layout()
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))

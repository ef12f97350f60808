#!/usr/bin/env python3
"""docs/img/contact-hemisphere.png: the contact solve (haptic_acu.tissue.contact) of a hemispherical
and a flat tip on the BEM's half-space disc against Hertz, Sneddon's rigid sphere and Sneddon's flat
punch, and the contact set's size as the tip presses in.

    tools/contact_figure.py [--out PATH]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from haptic_acu.tissue import bem  # noqa: E402
from haptic_acu.tissue import contact as ct  # noqa: E402

A = 0.125e-3  # the default needle's radius (m)
E, NU = 30e3, 0.3
ESTAR = E / (1 - NU ** 2)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent.parent / "docs" / "img"
                    / "contact-hemisphere.png")
    a = ap.parse_args(argv)
    d = np.linspace(0.002, 0.8, 200) * A
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 4.2))
    for n_in, style, label in ((4, "-", "servo's disc (52 elements)"), (12, "--", "fine disc (448 elements)")):
        C = bem.compliance(E, NU, A, n_in)
        s, xy = bem.disc_elements(A, n_in)
        h = ct.tip_heights(np.hypot(xy[:, 0], xy[:, 1]), A, "hemisphere")
        F, N, K = ct.press_curve(C, h, d)
        ax.plot(d / A, F * 1e3, style, color="C0", label=f"hemisphere, {label}")
        bx.plot(d / A, N / len(C), style, color="C0", label=label)
        Ff, _, _ = ct.press_curve(C, np.zeros(len(C)), d)
        if n_in == 4:
            ax.plot(d / A, Ff * 1e3, style, color="C1", label=f"flat, {label}")
    ax.plot(d / A, 2 * A * ESTAR * d * 1e3, ":", color="C1", label="Sneddon's flat punch")
    c = np.linspace(0.01, 0.9, 200) * A
    lg = np.log((A + c) / (A - c))
    ds = c / 2 * lg
    ax.plot(ds / A, ESTAR / 2 * ((c ** 2 + A ** 2) * lg - 2 * c * A) * 1e3, ":", color="k",
            label="Sneddon's rigid sphere")
    dh = d[d < 0.3 * A]
    ax.plot(dh / A, ct.hertz(E, NU, A, dh) * 1e3, "-.", color="C2", label="Hertz")
    ax.set_xlim(0, 0.8)
    ax.set_ylim(0, None)
    ax.set_xlabel("tip depth d / a")
    ax.set_ylabel("force (mN)")
    ax.set_title(f"tip of radius a = {A * 1e3:g} mm on a half-space, E = {E / 1e3:g} kPa, nu = {NU}", fontsize=9)
    ax.legend(fontsize=7)
    bx.set_xlabel("tip depth d / a")
    bx.set_ylabel("nodes in contact / nodes on the disc")
    bx.set_title("the hemisphere's contact set", fontsize=9)
    bx.set_ylim(0, 1.05)
    bx.legend(fontsize=8)
    fig.tight_layout()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=110)
    print(a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Danger structures felt in the servo: a membrane that breaks, a bone wall, a nerve or artery.

Two small compiled phases of the step (:mod:`haptic_acu.servo.step`), both a no-op without a point
(``Model.danger`` all rows ``NONE``, the first row's kind checked first, so a session without
``--point`` computes exactly what the step computes without these phases):

* :func:`danger_phase` after the bone wall: each structure of ``Model.danger`` (:data:`DANGER`, one
  row each, SI units, the scene frame) acts on the tip (the needle's, ``work.tip``) once the
  skin is pierced:

  - ``MEMBRANE`` (pleura, dura, peritoneum): a plane; the tip pressing past it meets a spring
    ``k`` (N/m) along the plane's normal until the spring's force exceeds ``f_break``; then it
    breaks (``State.dstate[i] = 1``) and the force drops: what lies beneath gives way, and beyond
    the broken membrane the tip cuts nothing (the post-puncture phase's cutting force, ``d.f_cut``
    along the axis, is taken back out: lung, brain and bowel offer no cutting resistance worth
    the name to a fine needle);
  - ``BONE_PLANE`` (a bone surface): the same plane spring, never breaking (a wall);
  - ``NERVE`` / ``ARTERY``: a cylinder (centre ``p``, axis ``n``, ``radius``): a tip inside it is
    pushed out radially by ``k`` times the penetration until that exceeds ``f_break`` (the
    epineurium or the vessel wall gives: the needle has pierced it; no force after).

  A plane's depth rises with breathing by ``amp (1 - cos(omega t)) / 2`` (peak-to-peak ``amp``), a
  cylinder's centre along ``u`` by the same; ``t`` is the servo's tick times its period. The
  reaction's magnitude adds to ``d.f_bone`` (the samples' ``f_bone_n``: the bone wall's or a
  structure's). A structure's broken state lasts while the needle is in the tissue: withdrawn, a
  new insertion meets it intact.
* :func:`danger_render` after the rendering linearisation: the rendering layer's stiffness along
  the axis becomes at least the touching structure's spring (as the bone wall's does).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

NONE, MEMBRANE, BONE_PLANE, NERVE, ARTERY = 0, 1, 2, 3, 4
KIND_CODES = {"membrane": MEMBRANE, "bone": BONE_PLANE, "nerve": NERVE, "artery": ARTERY}
MAX_DANGER = 4  # structures per point at most (the atlas loader enforces it)
# The springs (N/mm) and the force (N) at which each kind gives way: ours, no measurement for a fine
# acupuncture needle was found (docs/atlas.md, "Structures in the physics"). A membrane tents about
# 1.2 mm before it breaks; a nerve's or artery's wall gives after about 1 mm; the bone never does
# (the config's needle.bone_stiffness_n_per_mm, the bone wall's).
SPRINGS = {"membrane": (0.5, 0.6), "nerve": (0.3, 0.3), "artery": (0.2, 0.15)}
DANGER = np.dtype([  # one structure (Model.danger[i]), SI units, scene frame
    ("kind", "i8"),  # NONE, MEMBRANE, BONE_PLANE, NERVE, ARTERY
    ("p", "f8", 3),  # a cylinder's centre (m)
    ("n", "f8", 3),  # a plane's normal into the body (toward), a cylinder's axis (unit)
    ("u", "f8", 3),  # the direction breathing moves a cylinder's centre away from (unit, into the body)
    ("depth", "f8"),  # a plane's distance from the point along n (m)
    ("radius", "f8"),  # a cylinder's (m)
    ("k", "f8"),  # N/m
    ("f_break", "f8"),  # N (inf: never)
    ("amp", "f8"),  # breathing, peak to peak (m)
    ("omega", "f8"),  # breathing, rad/s
])


def spring_of(kind: str, k_bone_n_per_mm: float) -> tuple[float, float]:
    """(k in N/m, breaking force in N) of a structure of ``kind``."""
    if kind == "bone":
        return k_bone_n_per_mm * 1e3, math.inf
    k, f = SPRINGS[kind]
    return k * 1e3, f


def structure_rows(anatomy, k_bone_n_per_mm: float, out: np.ndarray | None = None) -> np.ndarray:
    """The :data:`DANGER` rows of a realised point (:func:`haptic_acu.tissue.patient.realise`),
    written into ``out`` (a Model's ``danger``, :data:`MAX_DANGER` rows) or a new array; rows past
    the structures are ``NONE``."""
    if out is None:
        out = np.zeros(MAX_DANGER, DANGER)
    out[:] = np.zeros(1, DANGER)[0]
    if len(anatomy.structures) > out.shape[0]:
        raise ValueError(f"at most {out.shape[0]} structures a point, got {len(anatomy.structures)}")
    for i, s in enumerate(anatomy.structures):
        r = out[i]
        r["kind"] = KIND_CODES[s.kind]
        r["k"], r["f_break"] = spring_of(s.kind, k_bone_n_per_mm)
        r["amp"] = s.breathing_mm * 1e-3
        r["omega"] = 2.0 * math.pi / s.breathing_period_s
        if s.toward is not None:
            r["n"] = s.toward
            r["depth"] = s.depth_mm * 1e-3
        else:
            c = np.asarray(s.centre_mm, dtype=float)
            r["p"] = c * 1e-3
            r["n"] = s.axis
            r["u"] = c / np.linalg.norm(c)
            r["radius"] = s.radius_mm * 1e-3
    return out


@nb.njit(cache=True, nogil=True)
def danger_phase(inp, m, s, d):
    """The structures' reaction on the tip (module docstring). Writes ``s.work[0].f``, ``d.f_bone``,
    ``s.work[0].k_danger`` and ``s.dstate``."""
    z = m.danger
    if z[0].kind == NONE:
        return
    sv = s.servo[0]
    if sv.inserted == 0:
        for i in range(z.shape[0]):
            s.dstate[i] = 0.0
        return
    wk = s.work[0]
    p = wk.tip  # the needle's tip
    t = sv.tick * m.params[0].dt
    for i in range(z.shape[0]):
        st = z[i]
        if st.kind == NONE:
            break
        lift = 0.5 * st.amp * (1.0 - math.cos(st.omega * t))
        if st.kind == MEMBRANE or st.kind == BONE_PLANE:
            pen = p[0] * st.n[0] + p[1] * st.n[1] + p[2] * st.n[2] - (st.depth - lift)
            if pen <= 0.0:
                continue
            if s.dstate[i] != 0.0:
                if st.kind == MEMBRANE:  # beyond the broken membrane the tip cuts nothing
                    a = sv.axis
                    for c in range(3):
                        wk.f[c] -= d.f_cut * a[c]
                continue
            fmag = st.k * pen
            if fmag > st.f_break:
                s.dstate[i] = 1.0
                continue
            for c in range(3):
                wk.f[c] -= fmag * st.n[c]
            d.f_bone += fmag
            wk.k_danger = max(wk.k_danger, st.k)
        else:
            rx = p[0] - (st.p[0] - lift * st.u[0])
            ry = p[1] - (st.p[1] - lift * st.u[1])
            rz = p[2] - (st.p[2] - lift * st.u[2])
            along = rx * st.n[0] + ry * st.n[1] + rz * st.n[2]
            qx = rx - along * st.n[0]
            qy = ry - along * st.n[1]
            qz = rz - along * st.n[2]
            dist = math.sqrt(qx * qx + qy * qy + qz * qz)
            pen = st.radius - dist
            if pen <= 0.0 or s.dstate[i] != 0.0:
                continue
            fmag = st.k * pen
            if fmag > st.f_break:
                s.dstate[i] = 1.0
                continue
            if dist > 1e-12:
                wk.f[0] += fmag * qx / dist
                wk.f[1] += fmag * qy / dist
                wk.f[2] += fmag * qz / dist
            d.f_bone += fmag
            wk.k_danger = max(wk.k_danger, st.k)


@nb.njit(cache=True, nogil=True)
def danger_render(s, d):
    """The rendering layer's stiffness along the axis: at least a touching structure's spring."""
    k = s.work[0].k_danger
    if k > d.r_k_along:
        d.r_k_along = k

"""``haptic-acu points``: the acupoint atlas (config/points/*.toml, docs/atlas.md).

* ``haptic-acu points``: one block per point: direction, depth range and its basis, the structures
  beneath (depth in men / women and how it was measured).
* ``haptic-acu points CODE [--patient SPEC]`` (or a .toml file): that point in full, with the layer
  stack and the structures as the patient has them, every number with its source.
"""
from __future__ import annotations

import textwrap

from ..tissue.atlas import load_atlas, load_point
from ..tissue.patient import parse_patient, realise

WIDTH = 80


def register(sub) -> None:
    p = sub.add_parser("points", help="list the acupoint atlas (direction, depth range, danger structures)",
                       description="List the atlas's points (config/points/*.toml): each point's prescribed "
                                   "direction, depth range and the structures beneath. With CODE: that point "
                                   "in full, with every number's source, for --patient.")
    p.add_argument("code", nargs="?", metavar="CODE", help="one point (GB21) or an atlas .toml file")
    p.add_argument("--patient", metavar="SPEC", help="sex=male|female,bmi=N,age=N, or random[:SEED] (with CODE)")
    p.set_defaults(func=run)


def _direction(pt) -> str:
    d = pt.direction
    if d.kind == "perpendicular":
        return "perpendicular"
    return f"{d.kind} {d.angle_from_normal_deg:g} deg from the normal toward {_heading(pt)}"


def _heading(pt) -> str:
    h = pt.direction.heading_deg % 360.0
    names = {0.0: f"+x ({pt.x_toward})", 90.0: f"+y ({pt.y_toward})", 180.0: f"-x (away from {pt.x_toward})",
             270.0: f"-y (away from {pt.y_toward})"}
    return names.get(h, f"heading {h:g} deg (+x {pt.x_toward}, +y {pt.y_toward})")


def _range(pt) -> str:
    d = pt.depth
    basis = (f"{d.cun_min:g}-{d.cun_max:g} cun at {d.cun_mm:g} mm" if d.basis == "cun" else "imaging")
    return f"{d.min_mm:g}-{d.max_mm:g} mm ({basis})"


def _wrap(text: str, indent: str) -> list[str]:
    return textwrap.wrap(text, WIDTH, initial_indent=indent, subsequent_indent=indent + "  ")


def _brief(pt) -> list[str]:
    out = _wrap(f"{pt.code} {pt.name}: {pt.region}", "")
    out += _wrap(f"{_direction(pt)}; {_range(pt)}", "  ")
    for s in pt.structures:
        sex = (f"{s.depth_mm:g} mm" if s.depth_female_mm == s.depth_mm
               else f"{s.depth_mm:g} mm (men) / {s.depth_female_mm:g} mm (women)")
        out += _wrap(f"{s.name} ({s.kind}): {sex}, {s.measured}", "  ")
    return out


def _full(pt, patient) -> list[str]:
    a = realise(pt, patient)
    out = [f"{pt.code} {pt.name} ({pt.path})"]
    out += _wrap(f"region: {pt.region} [{pt.location_source}]", "  ")
    out += _wrap(f"direction: {_direction(pt)}, on target within {pt.direction.tolerance_deg:g} deg "
                 f"[{pt.direction.source}]", "  ")
    out += _wrap(f"depth: {_range(pt)}, {pt.depth.measured} [{pt.depth.source}]"
                 + (f"; cun length [{pt.depth.cun_source}]" if pt.depth.cun_source else ""), "  ")
    p = patient
    out += _wrap(f"patient: {p.sex}, BMI {p.bmi:g}, age {p.age:g}" + (f", random seed {p.seed}" if p.random else ""),
                 "  ")
    out += _wrap(f"layers: skin {a.skin_mm:.2f}, fat {a.fat_mm:.2f}, muscle {a.muscle_mm:.2f} mm "
                 f"[{pt.layers.source}]", "  ")
    for s, placed in zip(pt.structures, a.structures):
        geo = (f"{placed.depth_mm:.2f} mm along {tuple(round(x, 3) for x in s.toward)}" if s.is_plane
               else f"{placed.depth_mm:.2f} mm deep, radius {s.radius_mm:g} mm")
        out += _wrap(f"{s.name} ({s.kind}): {geo} for this patient; men {s.depth_mm:g} +- {s.depth_sd_mm:g}, "
                     f"women {s.depth_female_mm:g} mm; {s.measured} [{s.source}]; BMI: [{s.bmi_source}]"
                     + (f"; breathing {s.breathing_mm:g} mm [{s.breathing_source}]" if s.breathing_mm else ""), "  ")
    return out


def run(args) -> int:
    if args.code:
        for line in _full(load_point(args.code, source="points"), parse_patient(args.patient, source="points --patient")):
            print(line)
        return 0
    if args.patient:
        from ..base.errors import UserError
        raise UserError("points: --patient needs a CODE (the patient varies one point's anatomy)")
    for i, pt in enumerate(load_atlas()):
        if i:
            print()
        for line in _brief(pt):
            print(line)
    return 0

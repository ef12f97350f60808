"""One name per quantity: every per-insertion number the tables show, with its one name, where it
sits in an insertion's metrics dict (``summary.json``'s ``metrics.per_insertion``, ``compare.json``),
its row label in ``haptic-acu compare``'s table, its unit, its resolution and which way is better.

* ``name`` is the column of the cohort's ``insertions.parquet`` (``mean_<name>`` in
  ``sessions.parquet``) and the key of ``compare.json``'s ``differences``; where the metrics dict
  has the number at the top level, its key there is the same name.
* ``path`` is where the number sits in an insertion's metrics dict (None: the cohort computes it
  from the positions: path length, economy of motion, LDLJ, the insertion's duration).
* ``label`` is compare's row label (None: compare does not show it).
* ``decimals`` is the resolution the number is reported at (JSON and text); two values that differ
  by less are the same value (the cohort's statistics round to it first).
* ``better``: ``"lower"``, ``"higher"``, ``"zero"`` (closer to 0 is better) or ``""`` (no better
  direction: a description, not a grade). The cohort's report.json and figures say it.

tests/test_quantity_names.py reads every output's columns and checks they map one to one onto
this table.
"""
from __future__ import annotations

from typing import NamedTuple


class Quantity(NamedTuple):
    name: str
    path: tuple | None
    label: str | None
    unit: str
    decimals: int
    better: str


QUANTITIES: tuple[Quantity, ...] = (
    Quantity("t_entry_s", ("t_entry_s",), None, "s", 4, ""),
    Quantity("duration_s", None, None, "s", 4, ""),
    Quantity("path_length_mm", None, None, "mm", 3, "lower"),
    Quantity("economy_of_motion", None, None, "1", 4, "higher"),
    Quantity("ldlj", None, None, "1", 3, "higher"),
    Quantity("entry_offset_mm", ("entry_offset_mm",), "entry offset from acupoint (mm)", "mm", 2, "lower"),
    Quantity("angle_deg", ("angle_deg",), "angle to skin normal (deg)", "deg", 1, "lower"),
    Quantity("max_depth_mm", ("max_depth_mm",), "needle depth in tissue (mm)", "mm", 2, ""),
    Quantity("max_tip_depth_mm", ("max_tip_depth_mm",), "tip below the rest skin (mm)", "mm", 2, ""),
    Quantity("depth_error_mm", None, None, "mm", 2, "zero"),
    Quantity("insertion_speed_mm_s", ("insertion_speed_mm_s",), "insertion speed (mm/s)", "mm/s", 2, ""),
    Quantity("time_to_target_s", ("time_to_target_s",), "time to target depth (s)", "s", 3, ""),
    Quantity("time_in_tissue_s", ("time_in_tissue_s",), "time in tissue (s)", "s", 3, ""),
    Quantity("time_on_bone_s", ("time_on_bone_s",), "time on bone (s)", "s", 3, "lower"),
    Quantity("time_at_force_limit_s", ("time_at_force_limit_s",), "time at the force limit (s)", "s", 3, "lower"),
    Quantity("peak_force_skin_n", ("peak_layer_force_n", "skin"), "peak force on the skin (N)", "N", 3, ""),
    Quantity("peak_force_fat_n", ("peak_layer_force_n", "fat"), "peak force on the fat (N)", "N", 3, ""),
    Quantity("peak_force_muscle_n", ("peak_layer_force_n", "muscle"), "peak force on the muscle (N)", "N", 3, ""),
    Quantity("peak_total_force_n", ("peak_total_force_n",), "peak |F| (N)", "N", 3, "lower"),
    Quantity("lateral_time_s", ("lateral", "time_over_s"), "lateral force over comfort (s)", "s", 3, "lower"),
    Quantity("lateral_max_n", ("lateral", "max_n"), "max lateral force (N)", "N", 3, "lower"),
    Quantity("lift_thrust_cycles", ("lift_thrust", "cycles"), "lift-thrust cycles", "", 0, ""),
    Quantity("lift_thrust_amplitude_mm", ("lift_thrust", "mean_amplitude_mm"), "lift-thrust amplitude (mm)", "mm",
             2, ""),
    Quantity("lift_thrust_frequency_hz", ("lift_thrust", "frequency_hz"), "lift-thrust frequency (Hz)", "Hz", 2, ""),
    Quantity("twirl_cycles", ("technique", "twirl", "cycles"), "twirl cycles", "", 0, ""),
    Quantity("twirl_swing_deg", ("technique", "twirl", "swing_deg"), "twirl swing, peak to peak (deg)", "deg", 0, ""),
    Quantity("twirl_frequency_hz", ("technique", "twirl", "frequency_hz"), "twirl frequency (Hz)", "Hz", 2, ""),
    Quantity("twirl_net_rotation_deg", ("technique", "twirl", "net_rotation_deg"), "twirl net rotation (deg)",
             "deg", 0, "zero"),
    Quantity("twirl_peak_torque_nmm", ("technique", "twirl", "peak_torque_nmm"), "twirl peak torque (N*mm)", "N*mm",
             3, ""),
    Quantity("thrust_to_lift", ("technique", "lift_thrust_forces", "thrust_to_lift"), "thrust / lift resistance",
             "1", 2, ""),
    Quantity("grasp_felt_ratio", ("technique", "grasp_felt", "peak_ratio"), "grasp felt on withdrawal (x)", "1", 2,
             "lower"),
    Quantity("technique", ("technique", "classification", "label"), "technique", "", 0, ""),
    Quantity("skin_punctured", ("skin_punctured",), None, "", 0, ""),
    Quantity("depth_verdict", ("depth_verdict",), "depth against the target", "", 0, ""),
    # graded against an atlas point (--point; docs/atlas.md): the cohort derives the last three from
    # the insertion's danger_margin_mm and critical_errors
    Quantity("angle_error_deg", None, None, "deg", 1, "lower"),  # summary.json: per insertion with --point
    Quantity("danger_margin_min_mm", None, None, "mm", 2, "higher"),
    Quantity("critical_errors", None, None, "", 0, "lower"),
    Quantity("critical_structures", None, None, "", 0, ""),
)
BY_NAME = {q.name: q for q in QUANTITIES}


def value(m: dict, q: Quantity):
    """The quantity's value in an insertion's metrics dict ``m`` (None where it has none)."""
    v = m
    for k in q.path or ():
        if not isinstance(v, dict) or v.get(k) is None:
            return None
        v = v[k]
    return v


def fmt(m: dict, q: Quantity) -> str:
    """The value as the tables print it: at its resolution, ``-`` where there is none."""
    v = value(m, q)
    if v is None:
        return "-"
    if isinstance(v, str):
        return v
    if isinstance(v, bool):
        return "yes" if v else "no"
    return f"{v:.{q.decimals}f}"


def decimals(name: str) -> int | None:
    """The decimals the quantity (or ``mean_<quantity>``) is reported at; None if unknown."""
    q = BY_NAME.get(name[5:] if name.startswith("mean_") and name[5:] in BY_NAME else name)
    return None if q is None else q.decimals


def at_resolution(name: str, v):
    """``v`` rounded as the quantity is reported (Python's ``round`` to its decimals, as the JSON
    outputs are); None and unknown quantities unchanged."""
    d = decimals(name)
    if v is None or d is None or not isinstance(v, (int, float)) or v != v:
        return v
    return round(float(v), d) + 0.0


def resolution(name: str) -> float | None:
    """The resolution of the quantity (or of ``mean_<quantity>``), e.g. 0.01 for 2 decimals."""
    q = BY_NAME.get(name[5:] if name.startswith("mean_") and name[5:] in BY_NAME else name)
    return None if q is None else 10.0 ** -q.decimals


def better(name: str) -> str:
    """Which way is better for the quantity (or ``mean_<quantity>``): "lower", "higher", "zero", ""."""
    q = BY_NAME.get(name[5:] if name.startswith("mean_") and name[5:] in BY_NAME else name)
    return "" if q is None else q.better

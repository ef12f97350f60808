"""What the trainee reads: the tip's place, its depth against the target and the force, in words.

Pure functions of one sample row (:data:`haptic_acu.servo.samples.COLUMNS`) and the scene's
target depth range, shared by the rerun view's verdict line (:mod:`haptic_acu.session.rerun_log`)
and its tests:

* :func:`place` - where the tip is: ``in the air``, ``pressing the skin``, ``in skin``, ``in fat``,
  ``in muscle``, ``on bone``;
* :func:`depth_words` - the depth against the target: ``12.6 mm to go to the target``, ``in range``,
  ``past the target by 3.2 mm``, ``on bone: withdraw``;
* :func:`axial_force` and :func:`force_words` - the force of the tissue on the needle along the
  needle, positive when it pushes the needle back out (resists the insertion), in words:
  ``1.42 N pushing the needle back`` or ``0.31 N pulling the needle in`` (the grip on a withdrawal);
* :func:`verdict_markdown` - the verdict panel's text.
"""
from __future__ import annotations

import numpy as np

from ..servo.samples import COL
from ..tissue.layers import PRESSING

_C_LAYER, _C_STATE = COL["layer"], COL["state_skin"]
_C_DEPTH_SKIN = COL["depth_skin_m"]
_C_F, _C_AXIS = COL["fx_n"], COL["axis_x"]
_C_ROLL, _C_TORQUE = COL["roll_deg"], COL["torque_nmm"]
PLACES = {-1: "in the air", 0: "in skin", 1: "in fat", 2: "in muscle", 3: "on bone"}
FORCE_EPS_N = 0.005  # below this the force reads "no force" (the display's 0.01 N resolution)


def place(row) -> str:
    layer = int(row[_C_LAYER])
    if layer < 0 and int(row[_C_STATE]) == PRESSING:
        return "pressing the skin"
    return PLACES.get(layer, "in the air")


def needle_depth_mm(row, tip_depth_mm: float) -> float:
    """The needle's depth (mm): along the needle below its entry once inside the tissue; before
    that, the tip's depth below the rest skin (negative above it)."""
    return float(row[_C_DEPTH_SKIN]) * 1e3 if int(row[_C_LAYER]) >= 0 else float(tip_depth_mm)


def depth_words(row, depth_mm: float, target_mm) -> str:
    lo, hi = float(target_mm[0]), float(target_mm[1])
    layer = int(row[_C_LAYER])
    if layer == 3:
        return "on bone: withdraw"
    if layer < 0:
        if int(row[_C_STATE]) == PRESSING:
            return f"skin pressed in {max(depth_mm, 0.0):.1f} mm, not yet through"
        return f"{max(-depth_mm, 0.0):.1f} mm above the skin"
    if depth_mm < lo:
        return f"{lo - depth_mm:.1f} mm to go to the target"
    if depth_mm <= hi:
        return "in range"
    return f"past the target by {depth_mm - hi:.1f} mm"


def needle_axes(rows: np.ndarray) -> np.ndarray:
    """The needle's unit axis, handle to tip, of each of ``rows`` (k, NCOL): (k, 3); straight down
    where a row gives none."""
    a = np.asarray(rows, dtype=np.float64)[:, _C_AXIS:_C_AXIS + 3]
    n = np.sqrt(np.einsum("ij,ij->i", a, a))
    n = np.where(np.isfinite(a).all(axis=1), n, 0.0)
    ok = n > 0.5
    out = np.tile([0.0, 0.0, -1.0], (len(a), 1))
    out[ok] = a[ok] / n[ok, None]
    return out


def axial_force(row) -> tuple[float, float]:
    """(axial, across) force (N): the component along the needle, positive pushing the needle back
    toward its handle, and the magnitude of the rest."""
    ax, across = axial_forces(np.asarray(row, dtype=np.float64)[None])
    return float(ax[0]), float(across[0])


def axial_forces(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`axial_force` of each of ``rows`` (k, NCOL) at once: two (k,) arrays."""
    f = np.asarray(rows, dtype=np.float64)[:, _C_F:_C_F + 3]
    back = -needle_axes(rows)
    ax = np.einsum("ij,ij->i", f, back)
    rest = f - ax[:, None] * back
    return ax, np.sqrt(np.einsum("ij,ij->i", rest, rest))


def force_words(axial_n: float, across_n: float = 0.0) -> str:
    if abs(axial_n) < FORCE_EPS_N:
        text = "none along the needle"
    elif axial_n > 0:
        text = f"{axial_n:.2f} N pushing the needle back"
    else:
        text = f"{-axial_n:.2f} N pulling the needle in"
    if across_n >= 0.05:
        text += f", {across_n:.2f} N sideways"
    return text


def verdict_markdown(row, tip_depth_mm: float, target_mm, last_event: str | None = None, force=None) -> str:
    """The verdict panel: a headline (place and depth against the target), the force, the roll
    once the needle has been turned, and the last puncture. ``row``: a sample row (an array or a
    list); ``force``: its :func:`axial_force`, if already known."""
    d = needle_depth_mm(row, tip_depth_mm)
    where = place(row)
    head = f"## Tip {where}: {depth_words(row, d, target_mm)}"
    lo, hi = float(target_mm[0]), float(target_mm[1])
    lines = [head, ""]
    if int(row[_C_LAYER]) >= 0:
        lines.append(f"**Depth {d:.1f} mm** along the needle (target {lo:g}-{hi:g} mm)")
    else:
        lines.append(f"Target {lo:g}-{hi:g} mm below the skin")
    lines.append("")
    ax, across = axial_force(row) if force is None else force
    lines.append(f"**Force: {force_words(ax, across)}**")
    roll, torque = float(row[_C_ROLL]), float(row[_C_TORQUE])
    if roll != 0.0 or torque != 0.0:
        lines += ["", f"Roll {roll:+.0f} deg ({'clockwise' if roll >= 0 else 'anticlockwise'} seen from the "
                  f"handle), twist torque {torque:+.3f} N*mm"]
    if last_event:
        lines += ["", f"Last: {last_event}"]
    return "\n".join(lines)

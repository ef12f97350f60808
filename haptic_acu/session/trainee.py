"""The trainee's view, logged to rerun: the section through the needle, the depth gauge, the
verdict line and the twirl dial (the layouts in :mod:`haptic_acu.session.blueprints`).

Entities (section coordinates in mm, see :mod:`haptic_acu.session.section`; the section view's
points are (u, y, w) with y the depth into the screen: bands behind, needle and labels in front):

    /section/scene                    moved (Transform3D) so that the view follows the needle
    /section/scene/layers/<layer>     each layer's band between its dented top and bottom surfaces
    /section/scene/surfaces           the four boundaries as lines (dented where a net presses)
    /section/scene/labels             the layers' names, at the left of their bands
    /section/scene/target             the target depth range along the needle's line (green)
    /section/scene/needle             the needle (40 mm from the tip back)
    /section/scene/tip                the tip, labelled with its depth
    /section/scene/force              the force along the needle, an arrow beside the tip (8 mm per N)
    /section/scene/punctures          where each layer gave way, with its peak force
    /section/scene/danger/<name>      a danger structure cut by the section (:meth:`TraineeScene.set_structures`)
    /gauge/...                        the depth gauge: layer bands along the needle, 5 mm ticks,
                                      the target, the tip's depth, the punctures
    /twirl/dial/...                   the roll seen from the handle: a pointer with a flag
    /verdict                          the verdict (markdown): place, depth against the target, force

Per-frame values are collected and sent as columns (``send_columns``) every ``flush()``: one call
per entity per batch, however many frames it holds.
"""
from __future__ import annotations

import numpy as np
import rerun as rr

from ..servo.samples import COL
from ..tissue.layers import LAYER_NAMES
from . import verdict as V
from .section import Section, Structure, patch_dent, skin_entry, structure_outline

LAYERS4 = (*LAYER_NAMES, "bone")
BAND_COLOURS = {"skin": (236, 188, 160), "fat": (250, 222, 130), "muscle": (196, 92, 92), "bone": (230, 226, 206)}
SURFACE_COLOUR = (90, 60, 50)
NEEDLE_COLOUR = (40, 40, 48)
TIP_COLOUR = (0, 90, 255)
TARGET_COLOUR = (20, 150, 60)
FORCE_COLOUR = (200, 20, 20)
DANGER_COLOUR = (220, 0, 0)
PUNCTURE_COLOUR = (20, 20, 20)
NEEDLE_MM = 40.0
FORCE_MM_PER_N = 8.0
BONE_SHOWN_MM = 25.0  # how much bone is drawn below its surface
# u samples across the section around the needle: 0.25 mm near it, 2 mm far out
_U = np.concatenate([np.linspace(-30.0, -6.0, 13)[:-1], np.linspace(-6.0, 6.0, 49)[:-1], np.linspace(6.0, 30.0, 13)])
_DENT_EPS_MM = 0.01  # re-log a band when its surface moved by more than this
_Y_BAND, _Y_LINE, _Y_NEEDLE, _Y_LABEL = 0.5, 0.0, -0.5, -1.0
GAUGE_MAX_MM = 50.0
GAUGE_W = 10.0  # width of the gauge's bands (mm of the gauge's own scale)
_G_TARGET = (GAUGE_W + 1.0, 2.0)  # the target bar's left edge and width
_G_POINTER = (GAUGE_W + 12.0, GAUGE_W + 3.5)  # the tip pointer's start and end (x)

_C_X = COL["x_m"]
_C_T, _C_TICK = COL["t_s"], COL["tick"]
_C_ROLL = COL["roll_deg"]
_C_STATE = COL["state_skin"]
MIN_BAND_MM = 1.0  # a band is never drawn thinner than this (or its rest thickness, if less)
PRESS_HALF_WIDTH_MM = 3.0  # half-width of the bump that carries a pressed surface down to the tip


def press_through(u: np.ndarray, w: np.ndarray, uw_tip) -> np.ndarray:
    """The curve ``w`` (mm, over ``u``) carried down to pass through the tip where the tip is below
    it: the difference at the tip's column, spread by a cos^2 bump of half-width
    PRESS_HALF_WIDTH_MM. The dent on the patch grid (about 1.3 mm between samples) smooths the
    net's sharp dent at its contact particle; the particle itself is at the tip."""
    gap = float(uw_tip[1]) - float(np.interp(uw_tip[0], u, w))
    if gap >= 0.0:
        return w
    x = np.clip((u - float(uw_tip[0])) / PRESS_HALF_WIDTH_MM, -1.0, 1.0)
    return w + gap * np.cos(0.5 * np.pi * x) ** 2


def _ns(t_s) -> np.ndarray:
    return np.round(np.asarray(t_s, dtype=np.float64) * 1e9).astype(np.int64).astype("timedelta64[ns]")


def _strip_tris(n: int) -> np.ndarray:
    """Triangles of a band whose vertices are a top row (0..n-1) then a bottom row (n..2n-1)."""
    i = np.arange(n - 1)
    return np.concatenate([np.stack([i, i + n, i + 1], 1), np.stack([i + 1, i + n, i + n + 1], 1)]).astype(np.uint32)


def strips_array(strips, arch):
    """Line strips (a list of (n_i, 2 or 3) arrays, or of (s, n, 2 or 3) arrays each holding s strips
    of n points) as the arrow array rerun would make of them (float32 points, one list per strip),
    built in one piece rather than strip by strip."""
    import pyarrow as pa

    batch = rr.components.LineStrip3DBatch if arch is rr.LineStrips3D else rr.components.LineStrip2DBatch
    dim = 3 if arch is rr.LineStrips3D else 2
    if not len(strips):
        return []
    lengths = []
    for x in strips:
        if np.ndim(x) == 3:
            lengths += [x.shape[1]] * x.shape[0]
        else:
            lengths.append(len(x))
    offsets = np.zeros(len(lengths) + 1, dtype=np.int32)
    np.cumsum(lengths, out=offsets[1:])
    flat = np.ascontiguousarray(np.concatenate([np.asarray(x, dtype=np.float32).reshape(-1, dim) for x in strips]))
    dtype = batch._ARROW_DATATYPE
    points = pa.FixedSizeListArray.from_arrays(flat.reshape(-1), type=dtype.value_type)
    return pa.ListArray.from_arrays(pa.array(offsets), points, type=dtype)


def row_keys(*parts) -> list:
    """Per-row keys from parts, each a (k, m) array (rounded already), a (k,) list, or None (left
    out): row i's key is the tuple of its parts, an array's row as a tuple; equal keys draw the same."""
    cols = [map(tuple, p.tolist()) if isinstance(p, np.ndarray) else p for p in parts if p is not None]
    return list(zip(*cols)) if len(cols) > 1 else list(cols[0])


class Columns:
    """Rows of one entity's archetype collected frame by frame and sent as columns on ``send``: one
    ``send_columns`` per batch instead of one ``log`` per frame. ``partitioned``: each row holds a
    batch of instances (``n`` per row, given to :meth:`add`) rather than one value."""

    def __init__(self, arch, partitioned: bool = False):
        self.arch = arch
        self.partitioned = partitioned
        self.t: list[float] = []
        self.tick: list[int] = []
        self.lengths: list[int] = []
        self.fields: dict[str, list] = {}
        self._last_key = None

    def add(self, t: float, tick: int, n: int = 1, key=None, **fields) -> None:
        """One row at (t, tick). ``key``: what the row shows (rounded to what can be seen); a row
        whose key equals the last one's is dropped (the viewer keeps showing the last)."""
        if key is not None:
            if key == self._last_key:
                return
            self._last_key = key
        self.t.append(t)
        self.tick.append(tick)
        self.lengths.append(n)
        for k, v in fields.items():
            self.fields.setdefault(k, []).append(v)

    def add_rows(self, t: list, tick: list, keys: list | None = None, **fields) -> None:
        """Rows at once, as :meth:`add` one by one would keep them: ``t``, ``tick``, ``keys`` one per
        row; each field one value per row (a (k, ...) array or a list: a partitioned entity's row
        holds one instance, a strips field one strip per row)."""
        if keys is None:
            keep = list(range(len(t)))
        else:
            keep, last = [], self._last_key
            for i, key in enumerate(keys):
                if key != last:
                    keep.append(i)
                    last = key
            self._last_key = last
            if not keep:
                return
        all_rows = len(keep) == len(t)
        self.t += t if all_rows else [t[i] for i in keep]
        self.tick += tick if all_rows else [tick[i] for i in keep]
        self.lengths += [1] * len(keep)
        for k, v in fields.items():
            if isinstance(v, np.ndarray):
                v = v if all_rows else v[keep]
                part = v if self.partitioned else list(v)
            else:
                part = v if all_rows else [v[i] for i in keep]
            if self.partitioned:
                self.fields.setdefault(k, []).append(part)
            else:
                self.fields.setdefault(k, []).extend(part)

    def send(self, rec, path: str) -> None:
        if not self.t:
            return
        cols = {}
        for k, vals in self.fields.items():
            if not self.partitioned:
                cols[k] = vals if isinstance(vals[0], str) else np.asarray(vals)
            elif k == "strips":
                cols[k] = strips_array([x for row in vals for x in (row if isinstance(row, list) else [row])],
                                       self.arch)
            elif isinstance(vals[0], np.ndarray):
                cols[k] = np.concatenate(vals)
            else:
                cols[k] = [x for row in vals for x in row]
        if self.partitioned:
            n = sum(self.lengths)
            bad = [k for k, v in cols.items() if len(v) not in (n, 0)]
            if bad:  # rerun would take the first rows' instances for the wrong rows, silently
                raise ValueError(f"{path}: {bad} hold other than the rows' {n} instances")
        cc = self.arch.columns(**cols)
        if self.partitioned:
            cc = cc.partition(self.lengths)
        rec.send_columns(path, indexes=[rr.TimeColumn("sim_time", duration=_ns(self.t)),
                                        rr.TimeColumn("tick", sequence=np.asarray(self.tick, dtype=np.int64))],
                         columns=cc)
        self.t, self.tick, self.lengths, self.fields = [], [], [], {}


class TraineeScene:
    """Logs the trainee's view of a session into ``rec`` (see the module doc). ``patch_axes``: the
    (theta, phi) axes of the grid the frames' dents come on (haptic_acu.session.engine.PATCH_GRID)."""

    def __init__(self, rec, tissue, target_mm, patch_axes, structures=()):
        self.rec = rec
        self.tissue = tissue
        self.target = (float(target_mm[0]), float(target_mm[1]))
        self.theta_axis, self.phi_axis = (np.asarray(a, dtype=np.float64) for a in patch_axes)
        self.structures: list[Structure] = list(structures)
        self.section: Section | None = None
        self.entry = np.zeros(3)
        self.axis = np.array([0.0, 0.0, -1.0])
        self.u0 = 0.0
        self.curves = [None] * 4  # w (mm) of each boundary along _U + u0, as last logged
        self._curves_logged = 0  # how many times the curves were logged
        self._rest_id = 0  # which section the rest curves are of
        self._rest_seen = None  # (section, curves logged) when a frame at rest was last held against them
        self.bands_logged = [None] * 4
        self.punctures: list[tuple[np.ndarray, str]] = []
        self.depths = np.full(4, np.nan)
        self.last_event: str | None = None
        self._cols = {
            "section/scene": Columns(rr.Transform3D),
            "section/scene/needle": Columns(rr.LineStrips3D, partitioned=True),
            "section/scene/tip": Columns(rr.Points3D, partitioned=True),
            "section/scene/force": Columns(rr.Arrows3D, partitioned=True),
            "gauge/tip": Columns(rr.Arrows3D, partitioned=True),
            "gauge/tip_line": Columns(rr.LineStrips3D, partitioned=True),
            "gauge/target_label": Columns(rr.Points3D, partitioned=True),
            "twirl/dial/pointer": Columns(rr.Arrows2D, partitioned=True),
            "twirl/dial/flag": Columns(rr.LineStrips2D, partitioned=True),
            "twirl/dial/roll": Columns(rr.Points2D, partitioned=True),
            "verdict": Columns(rr.TextDocument),
        }
        for k in range(4):
            self._cols[f"section/scene/layers/{LAYERS4[k]}"] = Columns(rr.Mesh3D, partitioned=True)
        self._cols["section/scene/surfaces"] = Columns(rr.LineStrips3D, partitioned=True)

    # -- static ---------------------------------------------------------------------------------
    def start(self) -> None:
        rec = self.rec
        rec.log("section", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log("gauge", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log("verdict", rr.TextDocument.from_fields(media_type=rr.MediaType.MARKDOWN), static=True)
        tris = _strip_tris(_U.size)
        for name in LAYERS4:
            rec.log(f"section/scene/layers/{name}", rr.Mesh3D.from_fields(
                triangle_indices=tris, albedo_factor=(*BAND_COLOURS[name], 255)), static=True)
        rec.log("section/scene/surfaces", rr.LineStrips3D.from_fields(
            radii=rr.Radius.ui_points(1.5), colors=[SURFACE_COLOUR]), static=True)
        rec.log("section/scene/needle", rr.LineStrips3D.from_fields(radii=[0.2], colors=[NEEDLE_COLOUR]), static=True)
        rec.log("section/scene/tip", rr.Points3D.from_fields(radii=[0.6], colors=[TIP_COLOUR], show_labels=True),
                static=True)
        rec.log("section/scene/force", rr.Arrows3D.from_fields(radii=[0.25], colors=[FORCE_COLOUR], show_labels=True),
                static=True)
        rec.log("gauge/tip", rr.Arrows3D.from_fields(radii=[0.5], colors=[TIP_COLOUR], show_labels=True), static=True)
        rec.log("gauge/tip_line", rr.LineStrips3D.from_fields(radii=[0.35], colors=[TIP_COLOUR]), static=True)
        # the dial: rim, quarter marks, 0 at the top, + clockwise seen from the handle (2D: y down)
        ang = np.linspace(0.0, 2.0 * np.pi, 73)
        rec.log("twirl/dial/rim", rr.LineStrips2D([np.stack([np.sin(ang), -np.cos(ang)], 1)], radii=[0.02],
                                                   colors=[(120, 120, 120)]), static=True)
        q = np.radians([0.0, 90.0, 180.0, 270.0])
        rec.log("twirl/dial/marks", rr.Points2D(np.stack([1.25 * np.sin(q), -1.25 * np.cos(q)], 1), radii=[0.0],
                                                labels=["0", "+90", "180", "-90"], show_labels=True,
                                                colors=[(80, 80, 80)]), static=True)
        rec.log("twirl/dial/pointer", rr.Arrows2D.from_fields(radii=[0.05], colors=[TIP_COLOUR]), static=True)
        rec.log("twirl/dial/roll", rr.Points2D.from_fields(positions=[(0.0, 1.55)], radii=[0.0], colors=[TIP_COLOUR],
                                                           show_labels=True), static=True)
        rec.log("twirl/dial/flag", rr.LineStrips2D.from_fields(radii=[0.03], colors=[TIP_COLOUR]), static=True)
        self._log_gauge_ticks()

    def set_structures(self, structures) -> None:
        """Danger structures to draw (a list of :class:`haptic_acu.session.section.Structure`, scene
        frame, m): each is cut by the section and drawn at ``section/scene/danger/<name>``."""
        self.structures = list(structures)
        if self.section is not None:
            self._log_structures(static_time=None)

    # -- per frame ------------------------------------------------------------------------------
    def frame(self, t: float, tick: int, rows: np.ndarray, tip_depth_mm: float, dents) -> None:
        """One visual frame: ``rows`` the servo rows since the last (the newest drawn), the tip's
        depth below the rest skin (mm) of the newest row, ``dents`` layer -> dent on the patch grid."""
        self.frames([t], [int(tick)], np.asarray(rows)[-1:], np.array([tip_depth_mm], dtype=np.float64),
                    [{k: dents[k] for k in dents} if dents else None])

    def frames(self, t: list, tick: list, rows: np.ndarray, tip_depth_mm: np.ndarray, dents: list) -> None:
        """Consecutive visual frames at once, as :meth:`frame` on each: ``t`` and ``tick`` one per frame,
        ``rows`` (k, NCOL) each frame's newest row, ``tip_depth_mm`` (k,) its tip's depth below the
        rest skin, ``dents`` one dict (layer -> dent on the patch grid) or None per frame."""
        k = len(t)
        axes = V.needle_axes(rows)
        tips = rows[:, _C_X:_C_X + 3]
        inside = (rows[:, COL["layer"]] >= 0).tolist()
        pressing = (rows[:, _C_STATE:_C_STATE + 3] == V.PRESSING).any(axis=1).tolist()
        origin, e_u, u0 = np.empty((k, 3)), np.empty((k, 3)), np.empty(k)
        # each frame's plane (it moves only outside the tissue), then the dented boundaries of them all
        planes, new = [], []
        plane = (self.section, self.axis, self.entry, self.u0, getattr(self, "rest", None),
                 getattr(self, "bone_bottom", None), self.depths)
        for i in range(k):
            nxt = self._next_section(tips[i], axes[i], inside[i], plane[0], plane[1])
            new.append(nxt is not None)
            plane = nxt if nxt is not None else plane
            planes.append(plane)
        dented = self._dented(planes, dents) if any(dents) else None
        for i in range(k):  # the section and the surfaces, frame by frame
            if new[i]:
                self._enter_section(planes[i], t[i], tick[i])
            origin[i], e_u[i], u0[i] = self.section.origin, self.section.e_u, self.u0
            if dents[i] or pressing[i]:
                self._frame_curves(t[i], tick[i], rows[i], dented[i] if dents[i] else {})
            elif self._rest_seen != (self._rest_id, self._curves_logged):
                self._log_curves(t[i], tick[i], self._rest_curves())
                self._rest_seen = (self._rest_id, self._curves_logged)
        c = self._cols
        # the needle, its tip and the force (section coordinates, mm)
        uw_tip = _to_uw(tips, origin, e_u)
        uw_back = _to_uw(tips - NEEDLE_MM * 1e-3 * axes, origin, e_u)
        depth = np.where(inside, rows[:, COL["depth_skin_m"]] * 1e3, tip_depth_mm)
        depths = depth.tolist()
        seen = np.round(np.concatenate([uw_tip, uw_back], axis=1), 3)
        needle = np.stack([_p3(uw_tip, _Y_NEEDLE), _p3(uw_back, _Y_NEEDLE)], axis=1)
        c["section/scene/needle"].add_rows(t, tick, row_keys(seen), strips=needle)
        tip_labels = [f"tip {d:.1f} mm" if d >= 0.0 else "tip" for d in depths]
        c["section/scene/tip"].add_rows(t, tick, row_keys(seen, tip_labels), positions=_p3(uw_tip, _Y_LABEL),
                                        labels=tip_labels)
        ax, across = V.axial_forces(rows)
        back = _direction_uw(-axes, e_u)
        n = np.hypot(back[:, 0], back[:, 1])
        big = n > 1e-9
        back = np.where(big[:, None], back / np.where(big, n, 1.0)[:, None], [0.0, 1.0])
        side = np.stack([back[:, 1], -back[:, 0]], axis=1) * 3.0  # beside the shaft
        vec = back * ax[:, None] * FORCE_MM_PER_N
        f_labels = ["" if abs(a) < V.FORCE_EPS_N else (f"{a:.2f} N back" if a > 0 else f"{-a:.2f} N in")
                    for a in ax.tolist()]
        c["section/scene/force"].add_rows(t, tick, row_keys(seen, np.round(vec, 3), f_labels),
                                          origins=_p3(uw_tip + side, _Y_LABEL),
                                          vectors=np.stack([vec[:, 0], np.zeros(k), vec[:, 1]], axis=1), labels=f_labels)
        # follow the needle: the camera looks at the entry's column, a little below the tip
        w_c = np.minimum(uw_tip[:, 1] + 12.0, -10.0)
        c["section/scene"].add_rows(t, tick, row_keys(np.round(np.stack([u0, w_c], axis=1), 3)),
                                    translation=np.stack([-u0, np.zeros(k), -w_c], axis=1))
        # the gauge
        g = np.minimum(np.maximum(depth, -2.5), GAUGE_MAX_MM)
        words = [f"tip {d:.1f} mm" if d >= 0.0 else f"tip {-d:.1f} mm above" for d in depths]
        g_key = np.round(g[:, None], 3)
        x0, x1 = _G_POINTER
        c["gauge/tip"].add_rows(t, tick, row_keys(g_key, words), origins=np.stack([np.full(k, x0), np.full(k, _Y_LABEL), -g], 1),
                                vectors=np.tile([x1 - x0, 0.0, 0.0], (k, 1)), labels=words)
        lo, hi = self.target  # the target's name at the end of its bar away from the tip's pointer
        z = np.where(g > 0.5 * (lo + hi), -lo + 2.5, -hi - 2.5)
        c["gauge/target_label"].add_rows(t, tick, z.tolist(),
                                         positions=np.stack([np.full(k, _G_TARGET[0] + 1.0), np.full(k, _Y_LABEL), z], 1))
        line = np.zeros((k, 2, 3))
        line[:, 0, 0], line[:, 1, 0] = -0.5, x1
        line[:, :, 1] = _Y_LABEL
        line[:, :, 2] = -g[:, None]
        c["gauge/tip_line"].add_rows(t, tick, row_keys(g_key), strips=line)
        # the dial
        roll = rows[:, _C_ROLL]
        rolls = roll.tolist()
        r = np.radians(roll)
        d = np.stack([np.sin(r), -np.cos(r)], axis=1)
        perp = np.stack([-d[:, 1], d[:, 0]], axis=1)  # 90 deg clockwise of the pointer, on screen (y down)
        roll_keys = [round(x, 1) for x in rolls]
        c["twirl/dial/pointer"].add_rows(t, tick, roll_keys, origins=np.zeros((k, 2)), vectors=0.95 * d)
        c["twirl/dial/roll"].add_rows(t, tick, roll_keys, labels=[
            f"roll {x:+.0f} deg" + (f" ({x / 360.0:+.1f} turns)" if abs(x) >= 360.0 else "") for x in rolls])
        flag = np.stack([0.55 * d, 0.55 * d + 0.35 * perp + 0.1 * d, 0.85 * d], axis=1)
        c["twirl/dial/flag"].add_rows(t, tick, roll_keys, strips=flag)
        # the verdict, when its text changes
        lists = rows.tolist()
        axs, acrosses = ax.tolist(), across.tolist()
        texts = [V.verdict_markdown(lists[i], float(tip_depth_mm[i]), self.target, self.last_event,
                                    force=(axs[i], acrosses[i])) for i in range(k)]
        c["verdict"].add_rows(t, tick, texts, text=texts)

    def _frame_curves(self, t, tick, row, dented) -> None:
        """The section's boundaries at one frame: dented where a net presses (``dented``: layer -> w
        from :meth:`_dented`), a pressed surface carried down to the tip; logged when they moved."""
        s = self.section
        u = _U + self.u0
        curves = list(self.curves)
        curves[3] = self.rest[3]
        for k in range(3):
            curves[k] = dented[k] if k in dented else self.rest[k]
        tip = row[_C_X:_C_X + 3]
        uw_tip = s.to_uw(tip)
        for k in range(3):  # a pressed surface passes through the tip (its net's contact particle)
            if int(row[_C_STATE + k]) == V.PRESSING:
                curves[k] = press_through(u, curves[k], uw_tip)
        self._log_curves(t, tick, _squeeze(curves, self.rest))

    def _rest_curves(self) -> list:
        """The curves of a frame with no dent and no pressed surface (the rest boundaries, as
        :meth:`_frame_curves` makes them), once per section."""
        if self._rest_id != getattr(self, "_rest_curves_of", None):
            self._rest_curves_cache = _squeeze(list(self.rest), self.rest)
            self._rest_curves_of = self._rest_id
        return self._rest_curves_cache

    def puncture(self, ev: dict, tip) -> None:
        """A layer gave way (an event of haptic_acu.analysis.scan.SessionScan) with the tip at ``tip``."""
        depth = ev["tip_depth_m"] * 1e3
        label = f"{ev['layer']} punctured, {ev['peak_force_n']:.2f} N"
        self.last_event = f"{label} at {depth:.1f} mm"
        self.punctures.append((np.asarray(tip, dtype=np.float64).copy(), label))
        rec = self.rec
        rec.set_time("sim_time", duration=_ns(ev["t_s"]))
        rec.set_time("tick", sequence=int(ev["tick"]))
        self._log_punctures()
        pts = np.array([[GAUGE_W, _Y_LABEL, -d] for d in self._puncture_depths()])
        rec.log("gauge/punctures", rr.Points3D(pts, radii=[0.5], colors=[PUNCTURE_COLOUR]))

    def flush(self) -> None:
        for path, col in self._cols.items():
            col.send(self.rec, path)

    # -- pieces ---------------------------------------------------------------------------------
    @staticmethod
    def _p3(uw: np.ndarray, y: float) -> np.ndarray:
        uw = np.asarray(uw, dtype=np.float64).reshape(-1, 2)
        out = np.empty((len(uw), 3))
        out[:, 0], out[:, 1], out[:, 2] = uw[:, 0], y, uw[:, 1]
        return out

    def _puncture_depths(self) -> list[float]:
        out = []
        for tip, _ in self.punctures:
            out.append(float(np.dot(tip - self.entry, self.axis)) * 1e3)
        return out

    def _log_punctures(self) -> None:
        if not self.punctures or self.section is None:
            return
        s = self.section
        back = s.direction_uw(-self.axis)
        side = np.array([back[1], -back[0]])
        side = side / max(np.hypot(*side), 1e-9) * 1.5
        pts = np.array([s.to_uw(p) + side for p, _ in self.punctures])
        self.rec.log("section/scene/punctures", rr.Points3D(self._p3(pts, _Y_LABEL), radii=[0.35],
                                                            colors=[PUNCTURE_COLOUR],
                                                            labels=[lb for _, lb in self.punctures], show_labels=True))

    def _next_section(self, tip, axis, inside: bool, section, section_axis):
        """The plane a frame with its tip at ``tip`` and axis ``axis`` is drawn in, if not ``section``
        (drawn with ``section_axis``): (section, axis, entry, u0, rest curves, bone bottom, depths), or None."""
        if inside and section is not None:
            return None  # the plane stays while the needle is in the tissue
        new = Section.through(self.tissue, axis, tip)
        if section is not None and section.same_plane(new) and float(np.dot(axis, section_axis)) > 0.9998:
            return None
        entry = skin_entry(self.tissue, tip, axis)
        u0 = float(new.to_uw(entry)[0])
        u = _U + u0
        rest = [new.boundary(k, u) for k in range(4)]
        # the bone drawn BONE_SHOWN_MM deep below its top; beside it (where a vertical line misses
        # the bone) the muscle goes down to the same flat bottom
        bone_bottom = float(np.nanmin(rest[3])) - BONE_SHOWN_MM
        rest = [np.where(np.isnan(r), bone_bottom, r) for r in rest]
        return new, axis, entry, u0, rest, bone_bottom, new.depths_along(entry, axis)

    def _enter_section(self, plane, t, tick) -> None:
        self.section, self.axis, self.entry, self.u0, self.rest, self.bone_bottom, self.depths = plane
        self._rest_id += 1
        self.curves = [None] * 4
        rec = self.rec
        rec.set_time("sim_time", duration=_ns(t))
        rec.set_time("tick", sequence=int(tick))
        self._log_plane_labels()
        self._log_gauge_bands()
        self._log_structures(static_time=None)
        self._log_punctures()

    def _dented(self, planes: list, dents: list) -> list:
        """Each frame's dented boundaries (layer -> w (mm) along _U + u0 of its plane), computed for
        all the frames of a plane at once, layer by layer."""
        out = [{} for _ in dents]
        groups: dict = {}
        for i, d in enumerate(dents):
            for k in (d or ()):
                groups.setdefault((id(planes[i][0]), k), []).append(i)
        for (_, k), idx in groups.items():
            section, _, _, u0, rest = planes[idx[0]][:5]
            stack = np.stack([np.asarray(dents[i][k]) for i in idx])
            w = section.boundary(k, _U + u0, start=np.tile(rest[k], (len(idx), 1)),
                                 dent=lambda th, ph: patch_dent(stack, self.theta_axis, self.phi_axis, th, ph))
            for j, i in enumerate(idx):
                out[i][k] = w[j]
        return out

    def _log_curves(self, t, tick, curves) -> None:
        changed = [self.curves[k] is None or np.max(np.abs(curves[k] - self.curves[k])) > _DENT_EPS_MM
                   for k in range(4)]
        if not any(changed):
            return
        u = _U + self.u0
        bottom_bone = np.full(u.shape, self.bone_bottom)
        for k in range(4):
            if not (changed[k] or (k < 3 and changed[k + 1])):
                continue
            lower = curves[k + 1] if k < 3 else bottom_bone
            verts = np.concatenate([self._p3(np.stack([u, curves[k]], 1), _Y_BAND),
                                    self._p3(np.stack([u, lower], 1), _Y_BAND)]).astype(np.float32)
            self._cols[f"section/scene/layers/{LAYERS4[k]}"].add(t, tick, n=len(verts), vertex_positions=verts)
        self._cols["section/scene/surfaces"].add(
            t, tick, n=4, strips=[self._p3(np.stack([u, curves[k]], 1), _Y_LINE).astype(np.float32) for k in range(4)])
        self.curves = [np.asarray(cv, dtype=np.float64).copy() for cv in curves]
        self._curves_logged += 1

    def _log_plane_labels(self) -> None:
        """The layers' names at the left of their bands, and the target range along the needle."""
        s = self.section
        u = _U + self.u0
        i = int(np.argmin(np.abs(_U + 14.0)))  # 14 mm left of the entry
        w = [self.rest[k][i] for k in range(4)] + [self.bone_bottom]
        mids = [0.5 * (w[k] + w[k + 1]) for k in range(4)]
        mids[0] = w[0] + 1.5  # the skin's name above its thin band
        thick = np.diff(self.depths)  # along the needle
        labels = [f"skin ({thick[0]:.1f} mm)", f"fat ({thick[1]:.1f} mm)", f"muscle ({thick[2]:.1f} mm)", "bone"]
        self.rec.log("section/scene/labels", rr.Points3D(self._p3(np.stack([np.full(4, u[i]), mids], 1), _Y_LABEL),
                                                         radii=[0.0], labels=labels, show_labels=True,
                                                         colors=[(0, 0, 0)]))
        lo, hi = self.target
        a, b = self.entry + lo * 1e-3 * self.axis, self.entry + hi * 1e-3 * self.axis
        back = s.direction_uw(-self.axis)
        side = np.array([-back[1], back[0]])
        side = side / max(np.hypot(*side), 1e-9) * 2.0  # left of the shaft
        seg = np.array([s.to_uw(a) + side, s.to_uw(b) + side])
        self.rec.log("section/scene/target", rr.LineStrips3D([self._p3(seg, _Y_NEEDLE)], radii=[0.5],
                                                              colors=[TARGET_COLOUR]))
        self.rec.log("section/scene/target_label", rr.Points3D(self._p3((seg[0] + 2.5 * side)[None], _Y_LABEL),
                                                               radii=[0.0], colors=[TARGET_COLOUR],
                                                               labels=[f"target {lo:g}-{hi:g} mm"], show_labels=True))

    def _log_structures(self, static_time=None) -> None:
        if self.section is None:
            return
        for st in self.structures:
            line = structure_outline(st, self.section)
            path = f"section/scene/danger/{_slug(st.name)}"
            if line is None:
                self.rec.log(path, rr.Clear(recursive=False))
                continue
            self.rec.log(path, rr.LineStrips3D([self._p3(line, _Y_NEEDLE)], radii=[0.3], colors=[DANGER_COLOUR],
                                               labels=[f"{st.name} ({st.kind})"], show_labels=True))

    def _log_gauge_ticks(self) -> None:
        marks = np.arange(0.0, GAUGE_MAX_MM + 0.1, 5.0)
        strips = [np.array([[-1.2, _Y_LINE, -m], [0.0, _Y_LINE, -m]]) for m in marks]
        self.rec.log("gauge/ticks", rr.LineStrips3D(strips, radii=[0.12], colors=[(60, 60, 60)]), static=True)
        self.rec.log("gauge/tick_labels", rr.Points3D(np.stack([np.full(marks.size, -2.6), np.full(marks.size, _Y_LINE),
                                                               -marks], 1), radii=[0.0],
                                                      labels=[f"{m:g}" for m in marks], show_labels=True,
                                                      colors=[(60, 60, 60)]), static=True)

    def _log_gauge_bands(self) -> None:
        d = list(self.depths) + [GAUGE_MAX_MM]
        mins, sizes, colours, labels = [], [], [], []
        for k in range(4):
            top, bot = d[k], min(d[k + 1] if np.isfinite(d[k + 1]) else GAUGE_MAX_MM, GAUGE_MAX_MM)
            if not np.isfinite(top) or top >= GAUGE_MAX_MM:
                continue
            mins.append([0.0, _Y_BAND, -bot])
            sizes.append([GAUGE_W, 0.1, bot - top])
            colours.append(BAND_COLOURS[LAYERS4[k]])
            labels.append(LAYERS4[k])
        self.rec.log("gauge/layers", rr.Boxes3D(mins=mins, sizes=sizes, colors=colours, fill_mode="solid"))
        # the layers' names and their boundary depths beside the bands
        names, pos = [], []
        for k in range(4):
            top = d[k]
            if not np.isfinite(top) or top >= GAUGE_MAX_MM:
                continue
            bot = min(d[k + 1] if np.isfinite(d[k + 1]) else GAUGE_MAX_MM, GAUGE_MAX_MM)
            if bot - top < 3.0:
                continue  # too thin to hold its name (the skin): the section names it
            names.append(LAYERS4[k])
            pos.append([0.5 * GAUGE_W, _Y_LABEL, -0.5 * (top + bot)])
        self.rec.log("gauge/layer_labels", rr.Points3D(pos, radii=[0.0], labels=names, show_labels=True,
                                                       colors=[(0, 0, 0)]))
        lo, hi = self.target
        self.rec.log("gauge/target", rr.Boxes3D(mins=[[_G_TARGET[0], _Y_LINE, -hi]], sizes=[[_G_TARGET[1], 0.1, hi - lo]],
                                                colors=[TARGET_COLOUR], fill_mode="solid"))
        self.rec.log("gauge/target_label", rr.Points3D.from_fields(radii=[0.0], colors=[TARGET_COLOUR],
                                                                   labels=[f"target {lo:g}-{hi:g}"], show_labels=True))


def _squeeze(curves: list, rest: list) -> list:
    """A layer pressed in pushes the surface below once it is squeezed to 1 mm (the skin keeps its
    0.8 mm): no band drawn inverted."""
    for k in range(3):
        keep = np.minimum(rest[k] - rest[k + 1], MIN_BAND_MM)
        curves[k + 1] = np.minimum(curves[k + 1], curves[k] - keep)
    return curves


def _p3(uw: np.ndarray, y: float) -> np.ndarray:
    """Section points (k, 2) as the view's 3D points (u, y, w)."""
    out = np.empty((len(uw), 3))
    out[:, 0], out[:, 1], out[:, 2] = uw[:, 0], y, uw[:, 1]
    return out


def _to_uw(p: np.ndarray, origin: np.ndarray, e_u: np.ndarray) -> np.ndarray:
    """:meth:`Section.to_uw` of points (k, 3), each in its own section (origin, e_u: (k, 3))."""
    d = p - origin
    return np.stack([np.einsum("ij,ij->i", d, e_u), d[:, 2]], axis=-1) * 1e3


def _direction_uw(v: np.ndarray, e_u: np.ndarray) -> np.ndarray:
    """:meth:`Section.direction_uw` of vectors (k, 3), each in its own section."""
    return np.stack([np.einsum("ij,ij->i", v, e_u), v[:, 2]], axis=-1)


def _slug(name: str) -> str:
    return "".join(ch if ch.isalnum() else "_" for ch in name.strip().lower()) or "structure"

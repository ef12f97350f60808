"""Logging a session to rerun (https://rerun.io) as a frame sink: a .rrd file, a spawned viewer, or
a running viewer over gRPC.

Timelines: ``sim_time`` (a duration, s) and ``tick`` (the servo tick, a sequence).

Servo-rate series, one value per tick, sent as columns (``send_columns``); a series that is zero
so far is not sent (its plot's legend shows only what has happened):

    /force/total         the force along the needle (N, + pushes the needle back)
    /force/total/across  the force across the needle (N), once it is not zero (|F| is the hypotenuse
                         of the two)
    /force/total/f<x|y|z> the scene-frame components (N), each once it is neither zero nor the force along
                         the needle itself (a vertical needle's fz)
    /force/layer         the force along the needle by layer: skin, fat, muscle (N, + pushes back)
    /force/part          ... by part: pressed surface, cutting and friction, bone (N, + pushes back)
    /depth/tip           the needle's depth (mm below the skin, drawn downward: the plotted value is
                         minus the depth): along the needle once inside (the summary's depth), before
                         that the tip's depth below the rest skin (haptic_acu.session.report.tip_depth_m)
    /depth/marks         the target range's ends and the layer boundaries along the needle (the same
                         downward mm), at the ends of each batch
    /twirl/series        the needle's roll (deg, cumulative, + clockwise seen from the handle) and the
                         twist torque of the tissue wound around the shaft (N*mm), once it is turned

The trainee's view (section, depth gauge, verdict, twirl dial): haptic_acu.session.trainee.

The 3D body, per visual frame, in metres in the scene frame (+z up, the acupoint at the origin):

    /world/tissue/<layer>/rest    boundary k's surface away from the acupoint (static, coarse)
    /world/tissue/<layer>/patch   the fine patch around the acupoint: radius = rest radius - dent,
                                  the dent from the live nets on haptic_acu.session.engine.PATCH_GRID
                                  (frame.dents); logged only when it changes
    /world/needle                 40 mm of needle from the tip back along the insertion axis
    /world/twist                  a 6 mm bar across the needle's handle end that turns with its roll
                                  (haptic_acu.tissue.twirl.twist_direction): the twirling, seen in 3D
    /world/force                  the force on the needle as an arrow at the tip (10 mm per N)
    /world/nets/<layer>/slot<s>   each live force net's particles and springs (the lattice's
                                  neighbour pairs, drawn as its straight rows); logged when moved
    /rates/servo_hz, visual_hz    the engine's measured loop rates (every 0.5 s)
    /events                       punctures ("skin punctured at t=..., depth ..., peak ..."), faults

Everything that changes frame by frame is collected and sent as columns every ``batch_frames``
frames (1 for a viewer, 30 for a replay to a file). A frame's model is read as the frame comes (the
patches' dents, the nets, whether the needle is inserted); what its rows show (the needle, its twist
bar, the force arrow, the trainee's view) is drawn for all the frames of a batch at once, with numpy
over the frames, when the batch is sent. The layout (``layout``: a name from
haptic_acu.session.blueprints or an .rbl file) goes with the recording as its default blueprint.
``set_time`` is thread-local in rerun: every logging call sets its time in the calling thread.
"""
from __future__ import annotations

import collections
import socket
import sys
import time
import urllib.parse

import numpy as np
import rerun as rr

from ..tissue import shf
from ..base.errors import UserError
from .report import LAYERS, SessionScan, tip_depth_m
from ..servo.samples import COL
from ..tissue.layers import PRESSING
from ..tissue.body import grid_triangles
from ..tissue.twirl import twist_direction
from ..servo.state import FREE, LAYER_NAMES, N_SLOTS, PLACE_NAMES, net_index, net_layer, net_slot
from .blueprints import DEFAULT_FILE, DEFAULT_LIVE
from .blueprints import load as load_layout
from .sink import Sink
from .section import structures_from_anatomy, structures_from_danger
from .trainee import Columns, TraineeScene, row_keys

APP_ID = "haptic-acu"
DEFAULT_URL = "rerun+http://127.0.0.1:9876/proxy"
BOUNDARY_NAMES = PLACE_NAMES[1:]  # boundary k is the top of layer k (3: bone)
NEEDLE_LENGTH_M = 0.040
FORCE_ARROW_M_PER_N = 0.010
_DENT_EPS_M = 5e-6  # re-log a patch when its dent changed by more than this (invisible below)
_NET_EPS_M = 1e-6  # re-log a net when a particle moved by more than this
_RATES_EVERY_S = 0.5

_COLOURS = {"skin": (232, 180, 150), "fat": (245, 218, 120), "muscle": (190, 80, 80), "bone": (236, 232, 214)}
_ALPHA = {"skin": 150, "fat": 200, "muscle": 255, "bone": 255}

_C_X = COL["x_m"]
_C_F = COL["fx_n"]
_C_AXIS = COL["axis_x"]
_C_STATE = COL["state_skin"]
_C_LAYER_F = COL["f_skin_n"]
_C_SURF, _C_DAMP, _C_LAT, _C_BONE = COL["f_surface_n"], COL["f_damp_n"], COL["f_lateral_n"], COL["f_bone_n"]
F_ZERO_N = 1e-4  # a force series below this (0.1 mN, under the plots' resolution) is not yet sent


def needle_back(rows: np.ndarray) -> np.ndarray:
    """(k, 3) unit vectors from tip to handle, per row (straight up where a row has no axis)."""
    a = rows[:, _C_AXIS:_C_AXIS + 3]
    n = np.linalg.norm(a, axis=1)
    ok = np.isfinite(n) & (n > 0.5)
    back = np.zeros_like(a)
    back[:, 2] = 1.0
    back[ok] = -a[ok] / n[ok, None]
    return back


def along_across(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The force along the needle (+ pushes the needle back toward its handle) and across it (N)."""
    f = rows[:, _C_F:_C_F + 3]
    back = needle_back(rows)
    ax = np.einsum("ij,ij->i", f, back)
    return ax, np.linalg.norm(f - ax[:, None] * back, axis=1)


def layer_forces(rows: np.ndarray) -> np.ndarray:
    """(k, 3) the force attributed to skin, fat, muscle, + pushing the needle back: a pressed layer's
    surface force (a magnitude) as it is, a punctured layer's share of the axial force (signed handle
    to tip) negated."""
    f = rows[:, _C_LAYER_F:_C_LAYER_F + 3]
    pressing = rows[:, _C_STATE:_C_STATE + 3] == PRESSING
    return np.where(pressing, f, -f)


def part_forces(rows: np.ndarray) -> np.ndarray:
    """(k, 3) the force by part, + pushing the needle back: the pressed surface, cutting and friction
    after a puncture (the axial force, signed handle to tip, negated), the bone wall."""
    return np.column_stack([rows[:, _C_SURF], -rows[:, _C_DAMP], rows[:, _C_BONE]])


def _scene_component(rows: np.ndarray, j: int) -> np.ndarray:
    """(k, 2): scene component j, and how far it is from zero and from the force along the needle
    (the second column only decides when the series starts: a component that is the along-force
    itself, a vertical needle's fz, would be a second line drawn under the first)."""
    c = rows[:, _C_F + j]
    return np.column_stack([c, np.minimum(np.abs(c), np.abs(np.abs(c) - np.abs(along_across(rows)[0])))])


# entity -> (series names, colours, (rows, needle depth mm) -> (k, m) values, the size below which the
# series is zero and not yet sent (None: sent from the start))
SERIES = {
    "force/total": (["along the needle (+ pushes it back)"], [(31, 119, 180)], lambda r, d: along_across(r)[0][:, None],
                    None),
    "force/total/across": (["across the needle"], [(255, 127, 14)], lambda r, d: along_across(r)[1][:, None], F_ZERO_N),
    "force/total/fx": (["fx (scene)"], [(214, 39, 40)], lambda r, d: _scene_component(r, 0), F_ZERO_N),
    "force/total/fy": (["fy (scene)"], [(44, 160, 44)], lambda r, d: _scene_component(r, 1), F_ZERO_N),
    "force/total/fz": (["fz (scene, + up)"], [(148, 103, 189)], lambda r, d: _scene_component(r, 2), F_ZERO_N),
    "force/layer": (list(LAYER_NAMES), [(215, 140, 100), (200, 160, 30), (170, 40, 40)],
                    lambda r, d: layer_forces(r), F_ZERO_N),
    "force/part": (["pressed surface", "cutting and friction", "bone"], [(31, 119, 180), (255, 127, 14), (110, 110, 110)],
                   lambda r, d: part_forces(r), F_ZERO_N),
    "depth/tip": (["tip"], [(0, 90, 255)], lambda r, d: -d[:, None], None),
    "twirl/series": (["roll (deg)", "twist torque (N*mm)"], [(31, 119, 180), (214, 39, 40)],
                     lambda r, d: r[:, [COL["roll_deg"], COL["torque_nmm"]]], 1e-9),
}
MARKS = (["target (shallow end)", "target (deep end)", "skin | fat", "fat | muscle", "muscle | bone"],
         [(20, 150, 60), (20, 150, 60), (215, 140, 100), (200, 160, 30), (120, 120, 120)])
TWIST_BAR_M = 0.006


def twist_bar(tip, back, roll_deg) -> np.ndarray:
    """The twist bar's two ends (2, 3): across the needle's handle end (``tip`` + 40 mm along
    ``back``, the unit vector toward the handle), along :func:`haptic_acu.tissue.twirl.twist_direction`.
    For many at once: ``tip`` and ``back`` (k, 3), ``roll_deg`` (k,) give (k, 2, 3)."""
    handle = np.asarray(tip) + NEEDLE_LENGTH_M * np.asarray(back)
    d = twist_direction(-np.asarray(back), np.radians(roll_deg)) * (0.5 * TWIST_BAR_M)
    return np.stack([handle - d, handle + d], axis=-2)


STRUCTURE_COLOURS = {"membrane": (178, 24, 43, 110), "bone": (235, 225, 200, 200), "nerve": (240, 200, 30, 255),
                     "artery": (200, 30, 30, 255)}
PLANE_HALF_M = 0.015  # a plane structure is drawn as a 30 mm square around the needle line


def _quat_z_to(a) -> list[float]:
    """The rotation (x, y, z, w) taking +z to the unit vector ``a``."""
    a = np.asarray(a, dtype=float)
    c = float(a[2])
    if c < -1.0 + 1e-9:
        return [1.0, 0.0, 0.0, 0.0]
    v = np.cross([0.0, 0.0, 1.0], a)
    q = np.array([v[0], v[1], v[2], 1.0 + c])
    return (q / np.linalg.norm(q)).tolist()


def log_structures(rec, anatomy) -> None:
    """A --point session's danger structures in the 3D view (static, at rest): a membrane or bone as a
    square of the plane around the needle line, a nerve or artery as its cylinder."""
    for st in anatomy.structures:
        path = f"world/structures/{st.name.replace(' ', '_')}"
        colour = STRUCTURE_COLOURS[st.kind]
        if st.toward is not None:
            n = np.asarray(st.toward, dtype=float)
            centre = n * st.depth_mm * 1e-3
            t1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
            t1 /= np.linalg.norm(t1)
            t2 = np.cross(n, t1)
            h = PLANE_HALF_M
            verts = np.array([centre + h * (sa * t1 + sb * t2) for sa, sb in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
            rec.log(path, rr.Mesh3D(vertex_positions=verts, triangle_indices=[[0, 1, 2], [0, 2, 3]],
                                    albedo_factor=colour), static=True)
        else:
            rec.log(path, rr.Cylinders3D(lengths=[0.04], radii=[st.radius_mm * 1e-3],
                                         centers=[np.asarray(st.centre_mm) * 1e-3],
                                         quaternions=[_quat_z_to(st.axis)], colors=[colour[:3]],
                                         fill_mode="solid"), static=True)


def blueprint(layout: str = DEFAULT_FILE):
    """The default blueprint of a recording: a bundled layout by name or an .rbl file
    (:func:`haptic_acu.session.blueprints.load`)."""
    return load_layout(layout)


def _check_reachable(url: str, timeout_s: float = 2.0) -> None:
    """Raise OSError unless something accepts TCP connections at the URL's host and port."""
    u = urllib.parse.urlparse(url)
    if not u.hostname or not u.port:
        raise OSError(f"not a rerun+http://HOST:PORT/proxy address: {url!r}")
    try:
        socket.create_connection((u.hostname, u.port), timeout=timeout_s).close()
    except OSError as e:
        raise OSError(f"no viewer listening ({e.strerror or e})") from None


def _ns(t_s) -> np.ndarray:
    """Seconds -> timedelta64[ns], rounded (rerun truncates float seconds)."""
    return np.round(np.asarray(t_s, dtype=np.float64) * 1e9).astype(np.int64).astype("timedelta64[ns]")


def _grid_normals(v: np.ndarray) -> np.ndarray:
    """Unit normals of a (n_theta, n_phi, 3) grid surface (theta down from +z, phi wrapping), outward for
    a star-shaped surface."""
    d_th = np.gradient(v, axis=0)
    d_ph = np.roll(v, -1, axis=1) - np.roll(v, 1, axis=1)
    n = np.cross(d_th, d_ph)
    m = np.linalg.norm(n, axis=-1, keepdims=True)
    return n / np.where(m > 0.0, m, 1.0)


def _cap_triangles(n_theta: int, n_phi: int) -> np.ndarray:
    """Triangles of a polar cap: a pole vertex (index n_theta * n_phi) fanned to row 0, then the grid."""
    pole = n_theta * n_phi
    j = np.arange(n_phi)
    fan = np.stack([np.full(n_phi, pole), j, (j + 1) % n_phi], axis=1)
    return np.concatenate([fan, grid_triangles(n_theta, n_phi)]).astype(np.uint32)


def lattice_rows(lat, n: int) -> list[np.ndarray]:
    """The springs between the first n particles of a hexagonal lattice as polylines: every maximal
    straight row of neighbours along each of the three lattice directions. Together the rows hold
    each neighbour pair exactly once (far fewer strips than pairs, so much cheaper to log)."""
    nbr = lat.nbr[:n]
    rows = []
    for d in range(3):  # direction d and d + 3 are opposite (forcenet._HEX_DIRS)
        for i in range(n):
            back = nbr[i, d + 3]
            if 0 <= back < n:
                continue  # not the start of a row
            row = [i]
            j = nbr[i, d]
            while 0 <= j < n:
                row.append(int(j))
                j = nbr[j, d]
            if len(row) > 1:
                rows.append(np.array(row, dtype=np.int64))
    return rows


class RerunSink(Sink):
    """Frame sink that logs a session to rerun. Build it with :meth:`to_file`, :meth:`spawn`,
    :meth:`connect` or :meth:`from_spec`; the engine then calls ``warm_up``, ``start``, ``on_frame``
    (visual thread) and ``close``. ``frame_cost_s`` and ``frame_cpu_s`` keep the wall and thread CPU
    time of every ``on_frame`` (rerun's own encoder and writer threads are not included)."""

    def __init__(self, mode: str = "file", target: str | None = None, *, recording_id: str | None = None,
                 rest_n_theta: int = 40, footer: bool = True, layout: str | None = None, structures=()):
        self.mode = mode
        self.target = target
        self.rest_n_theta = rest_n_theta
        # the trainee's layout for a viewer and a live session's file, the instructor's for a replay's file
        self.layout = layout or (DEFAULT_FILE if mode == "file" and footer else DEFAULT_LIVE)
        self.structures = list(structures)
        bp = blueprint(self.layout)  # a bad --layout fails before anything is created
        self.rec = rr.RecordingStream(APP_ID, recording_id=recording_id)
        try:
            if mode == "file":
                # The .rrd footer (a manifest of every chunk, for random access) is held in memory
                # until the file closes: ~25 MB per minute of a live session, whose servo series
                # make 180 chunks a second. A live session's file goes without it (flat memory;
                # the viewer reads the file in order); headless replays, short and batched, keep it.
                self.rec.save(str(target), default_blueprint=bp, write_footer=footer)
            elif mode == "spawn":
                self.rec.spawn(default_blueprint=bp)
            elif mode == "connect":
                _check_reachable(target)  # rerun itself would retry quietly for seconds
                self.rec.connect_grpc(target, default_blueprint=bp)
            else:
                raise ValueError(f"unknown rerun mode {mode!r}")
        except (OSError, RuntimeError) as e:
            hint = " (start a viewer with `rerun`, or log to a FILE.rrd)" if mode == "connect" else ""
            raise UserError(f"rerun {mode} {target or ''}: {e}{hint}".replace("  ", " ")) from None
        # the last 100,000 frames (28 min at 60 Hz): bounded in a session of any length
        self.frame_cost_s: collections.deque = collections.deque(maxlen=100_000)
        self.frame_cpu_s: collections.deque = collections.deque(maxlen=100_000)
        self._last_t = 0.0
        self._warm = False
        self._started = False
        self._last_tick = 0
        self._rates_next = -np.inf
        # Servo-rate series go out every ``batch_frames`` visual frames (1: every frame, what a live
        # viewer wants; headless replay writing a file sends fewer, larger batches: the SDK's
        # per-call cost, not the data, dominated a replay).
        self.batch_frames = 1
        self._pending: list[np.ndarray] = []
        self._pending_rows = 0
        # the pending frames (drawn with their batch): time, tick, last row's index in the batch,
        # the needle's axis if inserted, the dents
        self._fr_t: list[float] = []
        self._fr_tick: list[int] = []
        self._fr_end: list[int] = []
        self._fr_axis: list = []
        self._fr_dents: list = []
        self._frames_since_send = 0
        # What batches compute is held and sent every ``send_batches`` batches (1 for a viewer):
        # rerun's cost is per send_columns call (about 0.3 ms), not per row, so a replay to a file
        # sends several batches' rows in one call per entity; the rows and their times are the same.
        self.send_batches = 1
        self._batches_held = 0
        self._series_out: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
        # The SDK queues logged data for its encoder/writer thread without bound: when logging
        # outpaces it (a loaded machine, a headless replay) the queue grew ~30 MB per minute of
        # session. A flush every ``flush_frames`` frames waits for it, bounding the backlog to
        # about one second of data; the wait is in this process (the logging child in a live
        # session, whose pipe then holds the visual thread back; never the servo thread).
        self.flush_frames = 60
        self.flush_timeout_s = 5.0
        # Or (``flush_before_send``, a replay to a file): wait for the last send just before the next,
        # so that the SDK encodes and writes one send while the frames of the next are drawn (the
        # backlog stays one send's rows).
        self.flush_before_send = False
        self._frames_since_flush = 0

    # -- constructors ---------------------------------------------------------------------------
    @classmethod
    def to_file(cls, path, layout: str | None = None, **kw) -> "RerunSink":
        """Write a .rrd file (headless); ``layout``: its default blueprint (the instructor's)."""
        return cls("file", str(path), layout=layout, **kw)

    @classmethod
    def to_file_live(cls, path, layout: str | None = None, **kw) -> "RerunSink":
        """Write a .rrd file from a live session of any length: no footer, so memory stays flat
        (default blueprint: the trainee's)."""
        return cls("file", str(path), footer=False, layout=layout, **kw)

    @classmethod
    def spawn(cls, layout: str | None = None, **kw) -> "RerunSink":
        """Start a rerun viewer and stream to it (default blueprint: the trainee's)."""
        return cls("spawn", None, layout=layout, **kw)

    @classmethod
    def connect(cls, addr: str | None = None, layout: str | None = None, **kw) -> "RerunSink":
        """Stream to a running viewer: a ``rerun+http://host:port/proxy`` URL or ``host:port``
        (default: the local viewer's default address, port 9876)."""
        if addr is None:
            addr = DEFAULT_URL
        elif "://" not in addr:
            addr = f"rerun+http://{addr}/proxy"
        return cls("connect", addr, layout=layout, **kw)

    @classmethod
    def from_spec(cls, spec: str, **kw) -> "RerunSink":
        """``spawn``, ``connect[:ADDR]``, or a path ending in .rrd."""
        if spec == "spawn":
            return cls.spawn(**kw)
        if spec == "connect" or spec.startswith("connect:"):
            return cls.connect(spec.partition(":")[2] or None, **kw)
        if spec.startswith("rerun+http://"):
            return cls.connect(spec, **kw)
        if not spec.endswith(".rrd"):
            raise UserError(f"--rerun {spec!r}: give spawn, connect[:HOST:PORT] or a FILE.rrd")
        return cls.to_file(spec, **kw)

    # -- sink interface -------------------------------------------------------------------------
    def warm_up(self) -> None:
        """Pay rerun's first-call costs before the loops start (the first ``send_columns`` takes tens
        of ms, up to ~0.2 s): send each servo series its styling and an empty column batch."""
        if self._warm:
            return
        rec = self.rec
        for path, (names, colours, _, _) in SERIES.items():
            rec.log(path, rr.SeriesLines(names=names, colors=colours, widths=[1.5] * len(names)), static=True)
        rec.log("depth/marks", rr.SeriesLines(names=MARKS[0], colors=MARKS[1], widths=[1.0] * len(MARKS[0])),
                static=True)
        empty = np.zeros((0, 2))
        rec.send_columns("force/total", indexes=[rr.TimeColumn("sim_time", duration=_ns(empty[:, 0])),
                                                 rr.TimeColumn("tick", sequence=np.zeros(0, dtype=np.int64))],
                         columns=rr.Scalars.columns(scalars=empty))
        self._warm = True

    def start(self, info: dict) -> None:
        """Log the static scene: rest surfaces, patch topology, session description, the trainee's
        view's fixed parts."""
        self.warm_up()
        from .engine import PATCH_GRID  # the grid frame.dents are evaluated on

        model = info["model"]
        self.model = model
        self.tissue = tissue = model.tissue
        self.scan = SessionScan(tissue)
        rec = self.rec
        rec.set_time("sim_time", duration=np.timedelta64(0, "ns"))
        rec.set_time("tick", sequence=0)
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        dev = info.get("device")
        cfg = info.get("config")
        doc = [f"clock: {info.get('clock', '?')}"]
        if dev is not None:
            doc.append(f"device: {getattr(dev, 'name', '?')} ({getattr(dev, 'model', '')})")
        if cfg is not None and getattr(cfg, "path", None):
            doc.append(f"config: {cfg.path}")
        anatomy = getattr(model, "anatomy", None)  # --point: the atlas point and its patient
        if anatomy is not None:
            p = anatomy.patient
            doc.append(f"point: {anatomy.point.code} {anatomy.point.name}; patient {p.sex}, BMI {p.bmi:g}, age {p.age:g}")
        rec.log("session", rr.TextDocument("\n".join(doc)), static=True)
        target = tuple(cfg.scene.target_depth_mm) if cfg is not None else (15.0, 30.0)
        self._target = target

        th_p, ph_p = PATCH_GRID
        n_th, n_ph = th_p.shape
        self._patch_dirs = shf.unit_vectors(th_p, ph_p)
        self._patch_tris = _cap_triangles(n_th, n_ph)
        self._patch_rest = []
        # The rest meshes start at the patch's last theta row (same phi columns): no seam, no overlap.
        th_edge = float(th_p[-1, 0])
        for k, name in enumerate(BOUNDARY_NAMES):
            if k < 3:
                th = np.linspace(th_edge, np.pi, self.rest_n_theta)
            else:
                th = np.linspace(0.0, np.pi, self.rest_n_theta)
            T, P = np.meshgrid(th, ph_p[0], indexing="ij")
            verts = tissue.centre + shf.unit_vectors(T, P) * tissue.radius(k, T, P)[..., None]
            colour = (*_COLOURS[name], _ALPHA[name])
            rec.log(f"world/tissue/{name}/rest", rr.Mesh3D(
                vertex_positions=verts.reshape(-1, 3), vertex_normals=_grid_normals(verts).reshape(-1, 3),
                triangle_indices=grid_triangles(*T.shape), albedo_factor=colour), static=True)
            if k < 3:
                r_rest = tissue.radius(k, th_p, ph_p)
                r_pole = float(tissue.radius(k, np.zeros(1), np.zeros(1))[0])
                self._patch_rest.append((r_rest, r_pole))
                rec.log(f"world/tissue/{name}/patch", rr.Mesh3D.from_fields(
                    triangle_indices=self._patch_tris, albedo_factor=colour), static=True)
        self._patch_dent = [None, None, None]
        self._rows = [lattice_rows(lat, n) for lat, n in zip(model.lattices, model.n)]
        self._net_last: dict[int, np.ndarray] = {}
        if anatomy is not None:
            log_structures(rec, anatomy)
        rec.log("world/needle", rr.LineStrips3D.from_fields(radii=rr.Radius.ui_points(3.0), colors=[(90, 90, 100)]),
                static=True)
        rec.log("world/force", rr.Arrows3D.from_fields(radii=rr.Radius.ui_points(2.5), colors=[(220, 30, 30)]),
                static=True)
        rec.log("world/twist", rr.LineStrips3D.from_fields(radii=rr.Radius.ui_points(4.0), colors=[(31, 119, 180)]),
                static=True)
        for k, name in enumerate(LAYERS):
            for s in range(N_SLOTS):
                rec.log(f"world/nets/{name}/slot{s}/particles", rr.Points3D.from_fields(
                    radii=rr.Radius.ui_points(2.0), colors=[_COLOURS[name]]), static=True)
                rec.log(f"world/nets/{name}/slot{s}/springs", rr.LineStrips3D.from_fields(
                    radii=rr.Radius.ui_points(0.75), colors=[(60, 60, 60)]), static=True)
        # frame-rate entities, sent as columns every batch
        self._cols: dict[str, Columns] = {
            "world/needle": Columns(rr.LineStrips3D, partitioned=True),
            "world/twist": Columns(rr.LineStrips3D, partitioned=True),
            "world/force": Columns(rr.Arrows3D, partitioned=True),
            **{f"world/tissue/{BOUNDARY_NAMES[k]}/patch": Columns(rr.Mesh3D, partitioned=True) for k in range(3)},
            "rates/servo_hz": Columns(rr.Scalars),
            "rates/visual_hz": Columns(rr.Scalars),
        }
        self._started_series: set[str] = set()
        structures = info.get("structures") or self.structures
        if not structures and anatomy is not None:  # a --point session's danger structures, by name
            structures = structures_from_anatomy(anatomy)
        elif not structures and getattr(model, "danger", None) is not None:  # the servo's rows, by kind
            structures = structures_from_danger(model.danger)
        self.scene = TraineeScene(rec, tissue, target, (th_p[:, 0], ph_p[0]), structures=structures)
        self.scene.start()
        for k in range(3):
            self._log_patch(k, np.zeros(th_p.shape), 0.0, 0)
        self._started = True

    def _send_series(self, final: bool = False) -> None:
        """A batch: the pending servo rows as one value per tick of each series, the target marks at
        its ends, the puncture events among its rows; sent with the frame-rate columns every
        ``send_batches`` batches (and when ``final``)."""
        if self._pending:
            self._batch()
        self._batches_held += 1
        if final or self._batches_held >= self.send_batches:
            self._batches_held = 0
            self._send_held()

    def _hold(self, path: str, t_s: np.ndarray, ticks: np.ndarray, vals: np.ndarray) -> None:
        self._series_out.setdefault(path, []).append((t_s, ticks, vals))

    def _send_held(self) -> None:
        rec = self.rec
        if self.flush_before_send:
            try:
                rec.flush(timeout_sec=self.flush_timeout_s)
            except RuntimeError:
                pass
        for path, parts in self._series_out.items():
            t_s, ticks, vals = (np.concatenate(x) if len(parts) > 1 else x[0] for x in zip(*parts))
            rec.send_columns(path, indexes=[rr.TimeColumn("sim_time", duration=_ns(t_s)),
                                            rr.TimeColumn("tick", sequence=ticks.astype(np.int64))],
                             columns=rr.Scalars.columns(scalars=vals))
        self._series_out = {}
        self._send_frames()
        rec.set_time("sim_time", duration=_ns(self._last_t))  # this thread's time, as the frames left it
        rec.set_time("tick", sequence=self._last_tick)

    def _batch(self) -> None:
        rows = np.concatenate(self._pending) if len(self._pending) > 1 else self._pending[0]
        self._pending = []
        self._pending_rows = 0
        rec = self.rec
        tip_depth = tip_depth_m(rows[:, _C_X:_C_X + 3], self.tissue)
        self._draw_frames(rows, tip_depth)
        inside = rows[:, COL["layer"]] >= 0
        depth_mm = np.where(inside, rows[:, COL["depth_skin_m"]], tip_depth) * 1e3
        t_s, ticks = rows[:, COL["t_s"]].copy(), rows[:, COL["tick"]].copy()
        for path, (_, _, get, zero) in SERIES.items():
            vals = get(rows, depth_mm)
            if vals.shape[1] > len(SERIES[path][0]):  # a scene component and its distance from the rest
                vals, apart = vals[:, :1], vals[:, 1:]
            else:
                apart = vals
            if zero is not None and path not in self._started_series:
                nz = np.nonzero(np.any(np.abs(apart) > zero, axis=1))[0]
                if not nz.size:
                    continue
                self._started_series.add(path)
                first = max(int(nz[0]) - 1, 0)  # from the last zero: the line starts at zero
                self._hold(path, t_s[first:], ticks[first:], vals[first:])
                continue
            self._hold(path, t_s, ticks, vals)
        # the target and the layer boundaries along the needle, at the batch's ends
        lo, hi = self._target
        marks = np.concatenate([[lo, hi], self.scene.depths[1:4]])
        ends = [0, len(rows) - 1] if len(rows) > 1 else [0]
        self._hold("depth/marks", t_s[ends], ticks[ends], np.tile(-marks, (len(ends), 1)))
        self._events(rows, tip_depth)
        rec.set_time("sim_time", duration=_ns(self._last_t))  # _events moved this thread's time
        rec.set_time("tick", sequence=self._last_tick)

    def _send_frames(self) -> None:
        for path, col in self._cols.items():
            col.send(self.rec, path)
        self.scene.flush()

    def on_frame(self, frame) -> None:
        self.on_frames((frame,))

    def on_frames(self, frames) -> None:
        """Visual frames, oldest first: what each frame's model shows (the patches' dents, the nets,
        whether the needle is inserted) is read at once; what its rows show (the needle, the force,
        the trainee's view) is drawn for every frame of a batch at once when the batch is sent."""
        t_wall = time.perf_counter()
        t_cpu = time.thread_time()
        for frame in frames:
            self._take(frame)
        self.frame_cost_s.append(time.perf_counter() - t_wall)
        self.frame_cpu_s.append(time.thread_time() - t_cpu)

    def _take(self, frame) -> None:
        rec = self.rec
        rows = frame.samples
        k = len(rows)
        if k:
            self._pending.append(rows)
            self._pending_rows += k
            self._last_tick = int(rows[-1, COL["tick"]])
        self._last_t = t = frame.t_s
        tick = self._last_tick
        model = frame.model
        dents = getattr(frame, "dents", None) or {}
        dents = {j: np.asarray(dents[j]) for j in dents} if dents else {}  # each layer's evaluated once
        if k:  # drawn with its batch (_draw_frames)
            self._fr_t.append(t)
            self._fr_tick.append(tick)
            self._fr_end.append(self._pending_rows - 1)
            self._fr_axis.append(model.axis if model.inserted else None)
            self._fr_dents.append(dents or None)
        rates = getattr(frame, "rates", None) or {}
        if rates and frame.t_s >= self._rates_next:
            self._rates_next = frame.t_s + _RATES_EVERY_S
            for key in ("servo_hz", "visual_hz"):
                if key in rates:
                    self._cols[f"rates/{key}"].add(t, tick, scalars=float(rates[key]))
        owners = [model.owner(i) for i in range(N_SLOTS * len(LAYERS))]
        self._patches(owners, dents, t, tick)
        self._nets(model, owners, t, tick)
        self._frames_since_send += 1
        if self._frames_since_send >= self.batch_frames:
            self._frames_since_send = 0
            self._send_series()
        self._frames_since_flush += 1
        if self.flush_frames and self._frames_since_flush >= self.flush_frames:
            self._frames_since_flush = 0
            try:
                rec.flush(timeout_sec=self.flush_timeout_s)
            except RuntimeError:  # a viewer too slow to take it: the backlog waits for the next flush
                pass

    def _draw_frames(self, rows: np.ndarray, tip_depth: np.ndarray) -> None:
        """The frames of a batch (``rows`` its servo rows, ``tip_depth`` (m) theirs), each drawn at its
        newest row: the 3D needle, its twist bar and the force arrow, and the trainee's view."""
        ends = np.asarray(self._fr_end, dtype=np.int64)
        t, tick = self._fr_t, self._fr_tick
        last = rows[ends]
        k = len(ends)
        tip = last[:, _C_X:_C_X + 3]
        back = np.tile([0.0, 0.0, 1.0], (k, 1))
        for i, a in enumerate(self._fr_axis):
            if a is not None:
                back[i] = -a
        roll = last[:, COL["roll_deg"]]
        c = self._cols
        pose = np.round(np.concatenate([tip, back], axis=1), 7)  # to 0.1 um
        poses = row_keys(pose)
        c["world/needle"].add_rows(t, tick, poses, strips=np.stack([tip, tip + NEEDLE_LENGTH_M * back], axis=1))
        c["world/twist"].add_rows(t, tick, list(zip(poses, [round(x, 1) for x in roll.tolist()])),
                                  strips=twist_bar(tip, back, roll))
        vec = last[:, _C_F:_C_F + 3] * FORCE_ARROW_M_PER_N
        c["world/force"].add_rows(t, tick, row_keys(pose, np.round(vec, 6)), origins=tip, vectors=vec)
        self.scene.frames(t, tick, last, tip_depth[ends] * 1e3, self._fr_dents)
        self._fr_t, self._fr_tick, self._fr_end, self._fr_axis, self._fr_dents = [], [], [], [], []

    def close(self, result=None) -> None:
        if self._started:
            self._send_series(final=True)
        fault = getattr(result, "fault", None)
        if fault and self._started:
            self.rec.set_time("sim_time", duration=_ns(self._last_t))  # this thread's time (thread-local)
            self.rec.set_time("tick", sequence=self._last_tick)
            self.rec.log("events", rr.TextLog(f"session stopped: {fault}", level=rr.TextLogLevel.ERROR))
        try:
            self.rec.flush(timeout_sec=10.0)
        except RuntimeError as e:  # a viewer that went away: report, but let the other sinks close
            print(f"haptic-acu: rerun: {e}", file=sys.stderr)
        if self.mode == "file":
            self.rec.disconnect()  # finishes the file (footer)

    # -- pieces ---------------------------------------------------------------------------------
    def _events(self, rows: np.ndarray, depth: np.ndarray) -> None:
        rec = self.rec
        for ev in self.scan.feed(rows, depth):
            rec.set_time("sim_time", duration=_ns(ev["t_s"]))
            rec.set_time("tick", sequence=ev["tick"])
            rec.log("events", rr.TextLog(
                f"{ev['layer']} punctured at t={ev['t_s']:.3f} s, depth {ev['tip_depth_m'] * 1e3:.2f} mm, "
                f"peak {ev['peak_force_n']:.3f} N", level=rr.TextLogLevel.INFO))
            i = int(np.searchsorted(rows[:, COL["tick"]], ev["tick"]))
            self.scene.puncture(ev, rows[min(i, len(rows) - 1), _C_X:_C_X + 3])
        bad = np.nonzero(rows[:, COL["fault"]])[0]
        if bad.size and not getattr(self, "_fault_logged", False):
            i = bad[0]
            rec.set_time("sim_time", duration=_ns(rows[i, COL["t_s"]]))
            rec.set_time("tick", sequence=int(rows[i, COL["tick"]]))
            rec.log("events", rr.TextLog("fault: non-finite needle state, force set to zero",
                                         level=rr.TextLogLevel.ERROR))
            self._fault_logged = True

    def _log_patch(self, k: int, dent: np.ndarray, t: float, tick: int) -> None:
        r_rest, r_pole = self._patch_rest[k]
        verts = self.tissue.centre + self._patch_dirs * (r_rest - dent)[..., None]
        pole = self.tissue.centre + np.array([0.0, 0.0, r_pole - float(dent[0].mean())])
        normals = _grid_normals(verts).reshape(-1, 3)
        v = np.vstack([verts.reshape(-1, 3), pole]).astype(np.float32)
        self._cols[f"world/tissue/{BOUNDARY_NAMES[k]}/patch"].add(
            t, tick, n=len(v), vertex_positions=v,
            vertex_normals=np.vstack([normals, [0.0, 0.0, 1.0]]).astype(np.float32))
        self._patch_dent[k] = dent

    def _patches(self, owners: list, dents: dict, t: float, tick: int) -> None:
        for k in range(3):
            if k in dents:
                dent = np.asarray(dents[k])
            elif any(owners[net_index(k, s)] != FREE for s in range(N_SLOTS)):
                continue  # a settled net: its dent has stopped changing, keep what was logged
            else:
                dent = None
            last = self._patch_dent[k]
            if dent is None:
                if last is not None and np.any(last != 0.0):
                    self._log_patch(k, np.zeros_like(last), t, tick)
                continue
            if last is None or last.shape != dent.shape or np.max(np.abs(dent - last)) > _DENT_EPS_M:
                self._log_patch(k, dent, t, tick)

    def _nets(self, model, owners: list, t: float, tick: int) -> None:
        rec = self.rec
        for idx, owner in enumerate(owners):
            if owner == FREE and idx not in self._net_last:
                continue
            k, s = net_layer(idx), net_slot(idx)
            path = f"world/nets/{LAYERS[k]}/slot{s}"
            if owner == FREE:
                if idx in self._net_last:
                    rec.set_time("sim_time", duration=_ns(t))
                    rec.set_time("tick", sequence=tick)
                    rec.log(f"{path}/particles", rr.Points3D.from_fields(positions=np.zeros((0, 3))))
                    rec.log(f"{path}/springs", rr.LineStrips3D.from_fields(strips=[]))
                    del self._net_last[idx]
                continue
            pos = model.net_positions(idx)[: model.n[k]]
            last = self._net_last.get(idx)
            if last is not None and np.max(np.abs(pos - last)) <= _NET_EPS_M:
                continue
            self._net_last[idx] = pos
            if f"{path}/particles" not in self._cols:
                self._cols[f"{path}/particles"] = Columns(rr.Points3D, partitioned=True)
                self._cols[f"{path}/springs"] = Columns(rr.LineStrips3D, partitioned=True)
            self._cols[f"{path}/particles"].add(t, tick, n=len(pos), positions=pos)
            strips = [pos[r] for r in self._rows[k]]
            self._cols[f"{path}/springs"].add(t, tick, n=len(strips), strips=strips)

    # -- measurements ---------------------------------------------------------------------------
    def frame_cost_ms(self, cpu: bool = False) -> dict:
        """Median, 99th percentile and max of the on_frame wall (or thread CPU) time (ms)."""
        c = np.asarray(self.frame_cpu_s if cpu else self.frame_cost_s) * 1e3
        if c.size == 0:
            return {"frames": 0, "p50": 0.0, "p99": 0.0, "max": 0.0}
        return {"frames": int(c.size), "p50": float(np.percentile(c, 50)), "p99": float(np.percentile(c, 99)),
                "max": float(c.max())}

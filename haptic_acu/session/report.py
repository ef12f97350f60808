"""The session report: the replay summary, the force-depth figure and ``samples.csv``, as frame sinks.

Sinks (see :mod:`haptic_acu.session.engine`) get ``start(info)``, ``on_frame(frame)`` once per visual frame
with the servo rows written since the last frame (:mod:`haptic_acu.servo.samples`), and ``close(result)``.

Tip depth. Every depth reported here is the tip's depth below the *rest* skin surface, measured
radially from the body centre: ``r_skin(theta, phi) - |p - c|`` (m; negative above the skin). For an
insertion perpendicular to the skin (the scene's needle along -z at the acupoint) that is the depth
along the insertion. It is physical, continuous, and independent of the model's internal
compression offset, so a surface is seen to be pushed down ahead of the tip before it breaks: the
skin (0.8 mm thick) breaks with the tip about 1.4 mm below its rest position. (The sample column
``depth_skin_m`` is different: the depth in the compressed tissue's frame, 0 until the skin breaks.)

Force in the figure: the component along the outward radial direction at the tip, ``F . u``
(N; positive resists insertion, negative pulls the needle in, e.g. damping on withdrawal); for the
perpendicular insertion that is the axial force. The summary's forces are magnitudes ``|F|``.
"""
from __future__ import annotations

import csv
import math
import sys
from pathlib import Path

import numpy as np

from ..base.figlayout import first_layout, fit_rows, gc_paused, new_figure, save_png
from ..base.outputs import plain_text
from ..servo.samples import COL, NCOL
from ..servo.state import N_LAYERS, PLACE_NAMES, PRESSING, PUNCTURED, STATE_NAMES  # noqa: F401 (re-exported)
from .sink import RowBatches, Sink, block_rows
from ..analysis.common import C_F, C_LAYER, C_PUNCT, C_STATE, C_T, C_TICK, C_X
from ..analysis.scan import (  # noqa: F401 (re-exported: the report's vocabulary)
    LAYERS, PLACES, SessionScan, _r, place_name, puncture_records, radial_force_n, tip_depth_m)

class SummarySink(Sink):
    """Accumulates the replay summary (and, by default, the rows for the figure and metrics).

    With ``keep_rows=False`` (what replay and run use) no row is kept: the trainee metrics are
    streamed (:class:`haptic_acu.analysis.metrics.SessionMetricsScan`, :meth:`metrics`) and the figure gets a
    bounded min/max envelope of the rows (:class:`FigureRows`, :meth:`figure_rows`), so memory does not
    grow with the session; the numbers are identical either way.

    ``summary()`` is a JSON-ready dict, deterministic for identical rows: forces in N to 0.1 mN,
    depths in mm to 1 um, times in s to 0.1 ms. Keys: ``ticks``, ``duration_s``, ``max_force_n``
    (max |F|), ``max_tip_depth_mm`` (deepest tip point below the rest skin surface, :func:`tip_depth_m`;
    0 if the tip never went below it; named like each insertion's ``max_tip_depth_mm``, not like its
    ``max_depth_mm``, the needle's depth in the tissue), ``layers_reached``, ``punctures`` (see
    :class:`SessionScan`: layer, t_s, tip_depth_mm, peak_force_n), ``places`` (time_s and peak |F|
    per place the tip was in, "outside" including pressing the intact skin: not a layer's puncture
    peak), ``clamped_ticks``, ``fault``, and on
    :meth:`close` the engine's ``loop`` statistics (timing figures there are only deterministic on
    the sim clock). ``cfg`` (optional) is the session's TissueConfig; ``start`` also takes it from
    ``info``.
    """

    rows_only = True  # the rows (and the frame's time) only
    wants_tip_depth = True  # the scan and the figure read each row's tip depth

    BATCH_ROWS = 2048

    def __init__(self, cfg=None, keep_rows: bool = True, reference_rows=None):
        self.keep_rows = keep_rows
        self.reference_rows = reference_rows  # the technique metrics' replay without rotation
        self.scan: SessionScan | None = None
        self.metrics_scan = None  # without keep_rows: the metrics and the figure's rows, streamed
        self.figure: FigureRows | None = None
        self.tissue = None
        self.config = cfg
        self._blocks: list[np.ndarray] = []
        self._batches = RowBatches(self.BATCH_ROWS)
        self.fault: str | None = None
        self.stats: dict | None = None

    # -- sink interface -------------------------------------------------------------------------
    def start(self, info: dict) -> None:
        if info.get("config") is not None:
            self.config = info["config"]
        self.tissue = info["model"].tissue
        if self.config is not None:
            remember_tissue(self.config, self.tissue)
        self.scan = SessionScan(self.tissue)
        if not self.keep_rows:
            from ..analysis.metrics import SessionMetricsScan
            self.metrics_scan = (SessionMetricsScan(self.config, self.tissue, reference_rows=self.reference_rows)
                                 if self.config is not None else None)
            self.figure = FigureRows(self.tissue)
        self._blocks = []
        self._batches = RowBatches(self.BATCH_ROWS)

    def on_frame(self, frame) -> None:
        self.on_frames((frame,))

    def on_frames(self, frames) -> None:
        # Rows are scanned in batches of BATCH_ROWS (a frame holds ~17): the scan's per-call cost,
        # not its per-row cost, dominated a headless replay.
        if self.keep_rows:
            rows, _ = block_rows(frames)
            if len(rows):
                self._blocks.append(rows)
        for rows, depth in self._batches.add(frames):
            self._scan(rows, depth)

    def _scan_pending(self) -> None:
        rows, depth = self._batches.flush()
        if rows is not None:
            self._scan(rows, depth)

    def _scan(self, rows, depth=None) -> None:
        if depth is None:
            depth = tip_depth_m(rows[:, C_X:C_X + 3], self.tissue)
        self.scan.feed(rows, depth)  # the scan, the metrics and the figure share the rows' tip depth
        if self.metrics_scan is not None:
            self.metrics_scan.feed(rows, depth)
        if self.figure is not None:
            self.figure.feed(rows, depth)

    def close(self, result) -> None:
        self._scan_pending()
        self.fault = getattr(result, "fault", None)
        self.stats = getattr(result, "stats", None)

    # -- outputs --------------------------------------------------------------------------------
    def rows(self) -> np.ndarray:
        """Every row seen so far (k, NCOL), if ``keep_rows``."""
        if not self._blocks:
            return np.zeros((0, NCOL))
        if len(self._blocks) > 1:
            self._blocks = [np.concatenate(self._blocks)]
        return self._blocks[0]

    def metrics(self, punctures) -> dict:
        """The session's trainee metrics (:func:`haptic_acu.analysis.metrics.session_metrics`), streamed
        (without ``keep_rows``) or from the kept rows; ``punctures``: the summary's."""
        self._scan_pending()
        if self.metrics_scan is not None:
            return self.metrics_scan.result(punctures)
        from ..analysis.metrics import session_metrics
        return session_metrics(self.rows(), self.config, self.tissue, punctures=punctures)

    def figure_rows(self) -> tuple[np.ndarray, np.ndarray | None]:
        """(rows, insertion index per row or None) for :func:`plot_force_depth`: the bounded
        min/max envelope (:class:`FigureRows`) without ``keep_rows``, else every row."""
        self._scan_pending()
        if self.figure is None:
            return self.rows(), None
        entries = self.metrics_scan.entries if self.metrics_scan is not None else None
        return self.figure.result(entries)

    def summary(self) -> dict:
        s = self.scan
        if s is None:
            raise RuntimeError("SummarySink.summary() before start()")
        self._scan_pending()
        max_depth_mm = max(0.0, s.max_depth * 1e3) if s.ticks else 0.0
        out = {
            "ticks": s.ticks,
            "duration_s": _r((s.t_last - s.t_first) if s.ticks else 0.0, 4),
            "max_force_n": _r(s.max_force, 4),
            "max_tip_depth_mm": _r(max_depth_mm, 3),
            "layers_reached": [name for i, name in enumerate(PLACES) if i > 0 and s.ticks_in[i] > 0],
            "punctures": puncture_records(s.punctures),
            "places": {name: {"time_s": _r(s.time_in[i], 4), "peak_force_n": _r(s.peak_in[i], 4)}
                       for i, name in enumerate(PLACES)},
            "clamped_ticks": s.clamped_ticks,
            "fault": self.fault,
        }
        if self.stats is not None:
            st = self.stats
            loop = {key: st[key] for key in ("clock", "missed_ticks", "dropped_rows", "frames") if key in st}
            if isinstance(st.get("period_error_us"), dict):
                loop["period_error_us"] = {k: _r(v, 1) for k, v in st["period_error_us"].items()}
            out["loop"] = loop
        return out

    def print_summary(self, file=None) -> None:
        file = sys.stdout if file is None else file
        s = self.summary()
        line = (f"session: {s['duration_s']:.3f} s, {s['ticks']} ticks; max |F| {s['max_force_n']:.3f} N, "
                f"max tip depth {s['max_tip_depth_mm']:.2f} mm below the rest skin")
        print(line, file=file)
        if s["punctures"]:
            for p in s["punctures"]:
                print(f"  {p['layer']:<6} punctured at t={p['t_s']:.3f} s, depth {p['tip_depth_mm']:.2f} mm, "
                      f"peak {p['peak_force_n']:.3f} N", file=file)
        else:
            print("  no puncture", file=file)
        parts = [f"{name} {v['time_s']:.3f} s / {v['peak_force_n']:.3f} N" for name, v in s["places"].items()
                 if v["time_s"] > 0 or v["peak_force_n"] > 0]
        print("  time / peak |F| by place: " + ", ".join(parts), file=file)
        if s["clamped_ticks"]:
            print(f"  force clamped on {s['clamped_ticks']} ticks", file=file)
        if s["fault"]:
            print(f"  FAULT: {s['fault']}", file=file)

    def write_figure(self, path) -> None:
        rows, index = self.figure_rows()
        plot_force_depth(rows, path, self.tissue, summary=self.summary(), index=index)


class FigureRows:
    """A bounded copy of a session's rows for the figure: every row up to ``cap`` rows; beyond, the
    rows are binned by tick (bins doubling as the session grows) and each bin keeps only its rows of
    smallest and largest force along and across the normal, tip depth and offset from the acupoint
    (so every peak survives), plus every puncture row, the first and the last row. Memory: at most
    about ``cap`` rows (``cap * NCOL * 8`` bytes) whatever the session's length."""

    CAP = 50_000

    def __init__(self, tissue, cap: int = CAP):
        self.tissue = tissue
        self.cap = int(cap)
        self.bin = 1
        self.seen = 0
        self._rows: list[np.ndarray] = []
        self._gidx: list[np.ndarray] = []
        self._n = 0
        self._last: tuple[np.ndarray, int] | None = None

    def feed(self, rows: np.ndarray, depth: np.ndarray | None = None) -> None:
        k = len(rows)
        if k == 0:
            return
        g = np.arange(self.seen, self.seen + k, dtype=np.int64)
        self.seen += k
        self._last = (rows[-1].copy(), int(g[-1]))
        if self.bin > 1:
            sel = self._select(rows, g, depth)
            rows, g = rows[sel], g[sel]
        self._rows.append(np.array(rows, dtype=np.float64))  # a copy: the caller's block is not pinned
        self._gidx.append(g)
        self._n += len(g)
        if self._n > self.cap:
            self._shrink()

    def _select(self, rows, g, depth=None) -> np.ndarray:
        """Indices of the rows kept with the current bin size (in order)."""
        bins = g // self.bin
        if depth is None:
            depth = tip_depth_m(rows[:, C_X:C_X + 3], self.tissue)
        keep = (rows[:, C_PUNCT] >= 0) | (g == 0)
        for key in (radial_force_n(rows, self.tissue), lateral_force_n(rows, self.tissue), depth,
                    np.hypot(rows[:, C_X], rows[:, C_X + 1])):
            order = np.lexsort((key, bins))  # by bin, then by the key (ties: first row first)
            b = bins[order]
            first = np.ones(len(b), bool)
            first[1:] = b[1:] != b[:-1]
            last = np.ones(len(b), bool)
            last[:-1] = b[1:] != b[:-1]
            keep[order[first | last]] = True
        return np.flatnonzero(keep)

    def _shrink(self) -> None:
        rows = np.concatenate(self._rows)
        g = np.concatenate(self._gidx)
        while len(g) > self.cap // 2:
            self.bin *= 2
            sel = self._select(rows, g)
            rows, g = rows[sel], g[sel]
        self._rows, self._gidx, self._n = [rows], [g], len(g)

    def result(self, entries=None) -> tuple[np.ndarray, np.ndarray | None]:
        """(rows, insertion index per row): the index from ``entries`` (each insertion's entry row
        in the stream, :attr:`haptic_acu.analysis.metrics.SessionMetricsScan.entries`), else None."""
        if not self._rows:
            return np.zeros((0, NCOL)), (None if entries is None else np.zeros(0, np.int64))
        rows = np.concatenate(self._rows)
        g = np.concatenate(self._gidx)
        if self._last is not None and g[-1] != self._last[1]:
            rows = np.vstack([rows, self._last[0]])
            g = np.append(g, self._last[1])
        self._rows, self._gidx = [rows], [g]
        if entries is None:
            return rows, None
        return rows, np.searchsorted(np.asarray(entries, dtype=np.int64), g, side="right") - 1


# ---- the figure -------------------------------------------------------------------------------
_BAND_COLOURS = {"skin": "#e8b89a", "fat": "#f3dc8c", "muscle": "#d98a8a", "bone": "#d8d4c8"}


def layer_bands(axes, bounds, x0: float, x1: float, alpha: float) -> list:
    """Each place's depth band at rest (``bounds``: the boundaries' depths at the acupoint, mm; the
    last band runs to ``x1``) shaded on every axis of ``axes`` where it meets ``x0``-``x1``; returns
    their legend handles."""
    from matplotlib.patches import Patch

    edges = [*bounds, max(x1, bounds[3])]
    handles = []
    for name, a, b in zip(PLACES[1:], edges[:-1], edges[1:]):
        if b <= x0 or a >= x1:
            continue
        for ax in axes:
            ax.axvspan(a, b, color=_BAND_COLOURS[name], alpha=alpha, lw=0)
        handles.append(Patch(color=_BAND_COLOURS[name], alpha=alpha, label=f"{name} (at rest)"))
    return handles


_EVENT_COLOURS = {"skin": "#b5542a", "fat": "#a07d00", "muscle": "#8e1e1e"}


_TISSUES: dict = {}  # config -> Tissue built for it (fitting one takes seconds)


def remember_tissue(cfg, tissue) -> None:
    """Let :func:`plot_force_depth` (given a config) reuse a session's tissue instead of refitting it."""
    try:
        _TISSUES[cfg] = tissue
    except TypeError:  # an unhashable config: nothing to key on
        pass
    while len(_TISSUES) > 4:
        _TISSUES.pop(next(iter(_TISSUES)))


def tissue_of(tissue_or_config=None):
    """A Tissue from a Tissue, a TissueConfig (the one a sink saw, or built and remembered), or None
    (the default config)."""
    if tissue_or_config is not None and hasattr(tissue_or_config, "radius"):
        return tissue_or_config
    from ..base.config import load_config
    from ..tissue.body import Tissue
    cfg = tissue_or_config if tissue_or_config is not None else load_config()
    try:
        hit = _TISSUES.get(cfg)
    except TypeError:
        hit = None
    if hit is None:
        hit = Tissue.from_config(cfg)
        remember_tissue(cfg, hit)
    return hit


# insertion colours: one per insertion (tab10 without the band-like browns), approach in grey
INSERTION_COLOURS = ("#1f5fa8", "#d9661f", "#2e8b3e", "#8e3fa8", "#c0392b", "#17a2b8", "#7f7f7f", "#b8860b")
APPROACH_COLOUR = "0.55"
OFFSET_COLOUR = "k"  # the tip offset on the lateral panel: black, no insertion's colour nor the approach's grey
LATERAL_SHOWN_N = 0.1  # the lateral-force panel is drawn when |F_lateral| exceeds this (N)
LATERAL_TRAVEL_MM = 1.0  # ... or when the tip moves sideways more than this while touching (mm)
MAX_PANELS = 4  # force-depth panels side by side (one per insertion; the rest share the last)


def insertion_index(rows: np.ndarray) -> np.ndarray:
    """Per row: the index of the insertion it belongs to (from that insertion's entry tick, the skin
    first touched, up to the next insertion's entry tick: withdrawal and air included), -1 before
    the first insertion (:func:`haptic_acu.analysis.metrics.insertion_runs`, :func:`~haptic_acu.analysis.metrics.entry_tick`)."""
    from ..analysis.metrics import entry_tick, insertion_runs

    state = rows[:, C_STATE]
    entries = [entry_tick(state, a) for a, _ in insertion_runs(state)]
    return np.searchsorted(np.asarray(entries, dtype=np.int64), np.arange(len(rows)), side="right") - 1


def lateral_force_n(rows: np.ndarray, tissue) -> np.ndarray:
    """|F - (F . u) u| per row (N): the force across the outward radial direction at the tip."""
    d = rows[:, C_X:C_X + 3] - tissue.centre
    rho = np.sqrt(np.einsum("ij,ij->i", d, d))
    u = d / np.where(rho > 0.0, rho, 1.0)[:, None]
    f = rows[:, C_F:C_F + 3]
    across = f - np.einsum("ij,ij->i", f, u)[:, None] * u
    return np.sqrt(np.einsum("ij,ij->i", across, across))


def _lateral_travel_mm(idx: np.ndarray, offset_mm: np.ndarray, rows: np.ndarray) -> float:
    """The largest sideways travel (mm) of the tip while it touches the tissue, within one insertion."""
    touching = np.linalg.norm(rows[:, C_F:C_F + 3], axis=1) > 1e-3
    travel = 0.0
    for k in np.unique(idx):
        sel = touching & (idx == k)
        if sel.any():
            travel = max(travel, float(offset_mm[sel].max() - offset_mm[sel].min()))
    return travel


def _segments(idx: np.ndarray):
    """(label index, slice) runs of equal ``idx``, each extended by one row so the curve is continuous."""
    if idx.size == 0:
        return
    cuts = np.flatnonzero(np.diff(idx)) + 1
    starts = np.concatenate([[0], cuts])
    ends = np.concatenate([cuts, [idx.size]])
    for a, b in zip(starts.tolist(), ends.tolist()):
        yield int(idx[a]), slice(a, min(b + 1, idx.size))


def _colour(k: int) -> str:
    return APPROACH_COLOUR if k < 0 else INSERTION_COLOURS[k % len(INSERTION_COLOURS)]


def _insertion_handles(n_ins: int) -> list:
    """Legend entries for the insertions' colours; a long session's repeat, said once."""
    from matplotlib.lines import Line2D
    out = [Line2D([], [], color=_colour(k), label=f"insertion {k + 1}" if n_ins > 1 else "insertion")
           for k in range(min(n_ins, len(INSERTION_COLOURS)))]
    if n_ins > len(INSERTION_COLOURS):
        out.append(Line2D([], [], color="none", label=f"insertions {len(INSERTION_COLOURS) + 1}-{n_ins}: "
                          "the colours repeat"))
    return out


WITHDRAWAL_MIN_MM = 1.0  # a final rise of the tip shorter than this is not called a withdrawal
WITHDRAWAL_TOL_MM = 0.02  # depth noise allowed within the withdrawal's monotone rise


def withdrawal_start(depth_mm) -> int | None:
    """Index where an insertion's withdrawal starts: the final run over which the tip only rises
    (depth falling, within :data:`WITHDRAWAL_TOL_MM`) to the insertion's end, if it rises more than
    :data:`WITHDRAWAL_MIN_MM`; else None."""
    d = np.asarray(depth_mm, dtype=np.float64)
    if d.size < 2:
        return None
    # walking back from the end, the run goes on while each row is no shallower than the deepest
    # point after it (within the tolerance); it stops after the last row that is
    deepest_after = np.maximum.accumulate(d[::-1])[::-1][1:]
    stops = np.flatnonzero(~(d[:-1] >= deepest_after - WITHDRAWAL_TOL_MM))
    i = int(stops[-1]) + 1 if stops.size else 0
    i += int(np.argmax(d[i:]))  # the run starts at its deepest point
    return i if d[i] - d[-1] > WITHDRAWAL_MIN_MM else None


def preload_figure_modules():
    """Import matplotlib's figure and Agg canvas on a thread and return it: a replay starts this
    before its session, whose compiled ticks release the GIL, so the import (a good part of the
    figure's cost) overlaps the simulation instead of following it. :func:`plot_force_depth`'s own
    imports then find the modules loaded (or wait for the thread's import to finish). The thread is
    not a daemon: a replay interrupted early exits only once the import is done (an interpreter
    that finalizes while a thread is inside matplotlib's C++ extensions aborts the process,
    "terminate called without an active exception")."""
    import threading

    def load():
        try:
            import matplotlib.backends.backend_agg  # noqa: F401
            import matplotlib.figure  # noqa: F401
        except Exception:  # noqa: BLE001 - the plot's own import reports any problem
            pass

    t = threading.Thread(target=load, name="haptic-acu-preload-figure", daemon=False)
    t.start()
    return t


@gc_paused()
@plain_text  # names (files, labels) are drawn as text, never as mathtext
def plot_force_depth(rows, path, tissue=None, title: str | None = None, dpi: int = 110, summary=None,
                     index=None) -> None:
    """The needle-insertion figure, written as a PNG to ``path`` (byte-identical for identical input).

    Top: the force along the outward radial direction at the tip, ``F . u`` (N, positive resists
    insertion; the axial force for a perpendicular insertion), against the tip's depth below the rest
    skin surface (mm, :func:`tip_depth_m`), over bands of the layers at rest under the acupoint (the
    config thicknesses, :meth:`Tissue.depths_at_acupoint`); one colour per insertion
    (:func:`insertion_index`; the approach before the first in grey); each puncture marked with
    the summary's numbers (its depth at the puncture tick, its pressing-phase peak |F|). Middle
    (only when the lateral force exceeds :data:`LATERAL_SHOWN_N`): the force across the radial
    direction (:func:`lateral_force_n`) against time. Bottom: ``F . u`` against time, punctures as
    dashed lines. Legends sit outside the axes. ``tissue``: a Tissue or a TissueConfig (a session
    sink's tissue is reused); default: the default config's. ``summary``: the session's summary
    (its punctures are drawn; else they are found with :class:`SessionScan`). ``index``: the
    insertion index per row if the caller has it (rows thinned by :class:`FigureRows`), else
    :func:`insertion_index`.
    """
    from matplotlib.lines import Line2D

    rows = np.asarray(rows, dtype=np.float64)
    if rows.ndim != 2 or rows.shape[1] != NCOL:
        raise ValueError(f"sample rows must have shape (k, {NCOL}), got {rows.shape}")
    tissue = tissue_of(tissue)
    depth = tip_depth_m(rows[:, C_X:C_X + 3], tissue)
    depth_mm = depth * 1e3
    f_ax = radial_force_n(rows, tissue)
    f_lat = lateral_force_n(rows, tissue)
    t = rows[:, C_T]
    events = summary["punctures"] if summary is not None else puncture_records(SessionScan(tissue).feed(rows, depth))
    idx = (np.asarray(index, dtype=np.int64) if index is not None
           else insertion_index(rows) if rows.size else np.zeros(0, np.int64))
    n_ins = int(idx.max()) + 1 if idx.size else 0
    offset_mm = np.linalg.norm(rows[:, C_X:C_X + 2], axis=1) * 1e3  # tip's distance from the acupoint's axis
    show_lat = bool(rows.size) and (float(f_lat.max()) > LATERAL_SHOWN_N
                                    or _lateral_travel_mm(idx, offset_mm, rows) > LATERAL_TRAVEL_MM)

    n_pan = min(max(n_ins, 1), MAX_PANELS)
    fig = new_figure((max(9.5, 3.2 * n_pan + 2.5), 9.0 if show_lat else 7.5), dpi=dpi)
    ratios = [3, 1.5, 1.5] if show_lat else [3, 2]
    grid = first_layout(n_pan, ratios)  # where fit_rows starts; it places every axes before the save
    panels = [fig.add_axes(grid[0][0])]
    panels += [fig.add_axes(grid[0][j], sharey=panels[0], sharex=panels[0]) for j in range(1, n_pan)]
    ax_t = fig.add_axes(grid[-1][0])
    ax_lat = fig.add_axes(grid[1][0], sharex=ax_t) if show_lat else None

    bounds = tissue.depths_at_acupoint() * 1e3  # [0, skin/fat, fat/muscle, muscle/bone]
    lo = min(float(depth_mm.min()), 0.0) if rows.size else -1.0
    hi = max(float(depth_mm.max()), bounds[1]) if rows.size else bounds[2]
    pad = 0.02 * (hi - lo)
    x0, x1 = lo - pad, hi + pad
    structures = structure_depths(summary)  # --point: the danger structures below the point
    if structures:
        x1 = max(x1, max(d for _, d in structures) + 2.0)
    handles = layer_bands(panels, bounds, x0, x1, alpha=0.45)
    for ax in panels:
        ax.axhline(0.0, color="0.6", lw=0.6)
    withdrew = False
    for k, sl in _segments(idx):
        ax = panels[min(max(k, 0), n_pan - 1)]
        w = withdrawal_start(depth_mm[sl]) if k >= 0 else None
        if w is None:
            ax.plot(depth_mm[sl], f_ax[sl], color=_colour(k), lw=1.0)
        else:  # the withdrawal dashed, and named where it runs
            a = sl.start + w
            ax.plot(depth_mm[sl.start:a + 1], f_ax[sl.start:a + 1], color=_colour(k), lw=1.0)
            ax.plot(depth_mm[a:sl.stop], f_ax[a:sl.stop], color=_colour(k), lw=1.2, ls=(0, (4, 2)))
            mid = a + int(np.argmin(np.abs(depth_mm[a:sl.stop] - 0.5 * (depth_mm[a] + depth_mm[sl.stop - 1]))))
            ax.annotate("withdrawal", (depth_mm[mid], f_ax[mid]), xytext=(0, -18), textcoords="offset points",
                        fontsize=8, color=_colour(k), ha="center",
                        arrowprops={"arrowstyle": "->", "color": _colour(k), "lw": 0.8})
            withdrew = True
        ax_t.plot(t[sl], f_ax[sl], color=_colour(k), lw=1.0)
        if ax_lat is not None:
            ax_lat.plot(t[sl], f_lat[sl], color=_colour(k), lw=1.0)
    if (idx < 0).any():
        handles.append(Line2D([], [], color=APPROACH_COLOUR, label="approach"))
    if withdrew:
        handles.append(Line2D([], [], color="0.3", lw=1.2, ls=(0, (4, 2)), label="withdrawal (dashed)"))
    handles += _insertion_handles(n_ins)
    handles += _draw_punctures(panels, ax_t, events, idx, t)
    handles += _draw_structures(panels, ax_t, structures, summary)
    panels[0].set_xlim(x0, x1)
    if rows.size:
        panels[0].set_ylim(min(-0.05, 1.1 * float(f_ax.min())), max(0.1, 1.3 * float(f_ax.max())))
    for j, ax in enumerate(panels):
        ax.set_xlabel("tip depth below the rest skin (mm)")
        if n_pan > 1:
            last = j == n_pan - 1 and n_ins > n_pan
            ax.set_title(f"insertion {j + 1}{'+' if last else ''}", fontsize=9, y=1.0, color=_colour(j))
        if j:
            ax.tick_params(labelleft=False)
    panels[0].set_ylabel("force along the outward normal F . u (N)\n+ = the tissue pushes the needle out")
    suptitle = fig.suptitle(title or "Needle insertion: force against depth")
    panels[-1].legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False)

    tspan = (float(t[0]), float(t[-1]) if t[-1] > t[0] else float(t[0]) + 1e-3) if rows.size else (0.0, 1.0)
    twin = _draw_lateral(ax_lat, t, f_lat, offset_mm, tspan) if ax_lat is not None else None
    ax_t.axhline(0.0, color="0.6", lw=0.6)
    ax_t.set_xlabel("time (s)")
    ax_t.set_ylabel("F . u (N)")
    ax_t.set_title("force along the outward normal against time (dashed: punctures)", fontsize=9, y=1.0)
    ax_t.set_xlim(*tspan)
    fit_rows(fig, [[[ax] for ax in panels]] + ([[[ax_lat, twin]]] if ax_lat is not None else []) + [[[ax_t]]],
             ratios, suptitle)
    save_png(fig, path, dpi)



def _draw_punctures(panels, ax_t, events, idx, t) -> list:
    """force_depth.png's punctures: a marker with the layer, peak |F| and depth on the insertion's
    panel and a dashed line on the time panel; the legend's handle."""
    from matplotlib.lines import Line2D
    n_pan = len(panels)
    for ev in events:
        c = _EVENT_COLOURS[ev["layer"]]
        x, y = ev["tip_depth_mm"], ev["peak_force_n"]
        k = int(idx[min(int(np.searchsorted(t, ev["t_s"] - 5e-5)), len(idx) - 1)]) if idx.size else 0
        ax = panels[min(max(k, 0), n_pan - 1)]
        ax.plot([x], [y], marker="v", ms=8, color=c, ls="none", mec="k", mew=0.5)
        ax.annotate(f"{ev['layer']}\n{y:.3f} N, {x:.2f} mm", (x, y), xytext=(5, 3),
                    textcoords="offset points", fontsize=7, color=c)
        ax_t.axvline(ev["t_s"], color=c, lw=0.8, ls="--")
    if not events:
        return []
    return [Line2D([], [], marker="v", ls="none", color="0.3", mec="k", mew=0.5,
                   label="puncture (peak |F| while pressed)")]

def _draw_lateral(ax_lat, t, f_lat, offset_mm, tspan):
    """force_depth.png's lateral panel: the force across the needle and, on its own scale, the tip's
    offset from the acupoint's axis (on a twin axes, returned)."""
    ax_lat.set_ylabel("lateral |F| (N)")
    ax_lat.set_xlim(*tspan)
    ax_lat.set_title("force across the needle (lateral)", fontsize=9, y=1.0)
    ax_lat.tick_params(labelbottom=False)
    # the offset in its own colour and scaled to 2/3 of the panel's height: where the lateral
    # force follows the offset (a sweep), the two curves would otherwise be drawn on one line
    tw = ax_lat.twinx()
    tw.plot(t, offset_mm, color=OFFSET_COLOUR, lw=0.9, ls=":")
    tw.set_ylabel("tip offset from the acupoint (mm, dotted)", fontsize=8, color=OFFSET_COLOUR)
    tw.tick_params(axis="y", colors=OFFSET_COLOUR)
    tw.set_ylim(0.0, 1.5 * max(float(offset_mm.max()), 1e-3))
    ax_lat.set_ylim(0.0, 1.05 * max(float(f_lat.max()), 1e-6))
    return tw


STRUCTURE_COLOUR = "#b2182b"


def structure_depths(summary) -> list[tuple[str, float]]:
    """(name, depth in mm below the point along its normal) of each danger structure a --point
    session's summary lists that lies on that line: a plane facing it, a cylinder across it (at
    rest, before breathing)."""
    out = []
    for st in ((summary or {}).get("anatomy") or {}).get("structures", ()):
        if "toward" in st:
            tz = -st["toward"][2]
            if tz > 0.2:  # a plane facing the needle line (not a wall beside it)
                out.append((st["name"], st["depth_mm"] / tz))
        else:
            c = st["centre_mm"]
            if math.hypot(c[0], c[1]) <= st["radius_mm"] + 5.0:  # a cylinder near the line
                out.append((st["name"], -c[2] - st["radius_mm"]))
    return out


def _draw_structures(panels, ax_t, structures, summary) -> list:
    """A --point session's danger structures on force_depth.png: a dashed line at each one's depth
    below the point, and each critical error's time on the time panel; the legend's handles."""
    if not structures:
        return []
    from matplotlib.lines import Line2D
    for name, d in structures:
        for ax in panels:
            ax.axvline(d, color=STRUCTURE_COLOUR, lw=1.2, ls="--")
        panels[-1].annotate(f"{name} {d:.1f} mm", (d, 1.0), xycoords=("data", "axes fraction"), xytext=(-3, -3),
                            textcoords="offset points", rotation=90, ha="right", va="top", fontsize=7,
                            color=STRUCTURE_COLOUR)
    errors = [e for i in (summary.get("point_grading") or {}).get("per_insertion", ()) for e in i["critical_errors"]]
    for e in errors:
        ax_t.axvline(e["t_s"], color=STRUCTURE_COLOUR, lw=1.2)
    out = [Line2D([], [], color=STRUCTURE_COLOUR, ls="--", label=f"{summary['point']}: danger structure (at rest)")]
    if errors:
        out.append(Line2D([], [], color=STRUCTURE_COLOUR, label="critical error (time panel)"))
    return out


RESULT_FORCE = "{:.3f}"  # N: every text output shows forces, depths and times with these decimals
RESULT_DEPTH = "{:.2f}"  # mm
RESULT_TIME = "{:.3f}"   # s


def technique_text(tech) -> str:
    """The insertion's technique for its result line: the twirling (cycles, swing, frequency) when it
    twirled, and the reinforcing / reducing / even label when there is one (docs/model.md s11)."""
    if not tech:
        return ""
    out = ""
    tw = tech.get("twirl") or {}
    if tw.get("cycles"):
        swing = "-" if tw.get("swing_deg") is None else f"{tw['swing_deg']:.0f}"
        frq = "-" if tw.get("frequency_hz") is None else f"{tw['frequency_hz']:.2f}"
        out += f"; {tw['cycles']} twirl cycles ({swing} deg swing, peak to peak, {frq} Hz)"
    label = (tech.get("classification") or {}).get("label")
    if label:
        out += f"; technique: {label}"
    return out


def result_lines(summary: dict) -> list[str]:
    """The session's results as text lines (replay and run): punctures, the depth reached against the
    target, per-insertion metrics. The numbers are the summary's, shown at fixed decimals."""
    F, D, T = RESULT_FORCE.format, RESULT_DEPTH.format, RESULT_TIME.format
    out = [f"{summary['trajectory']}: {T(summary['duration_s'])} s, {summary['ticks']} ticks"]
    if not summary["punctures"]:
        out.append("  no puncture")
    for p in summary["punctures"]:
        out.append(f"  {p['layer']:<6} punctured at t={T(p['t_s'])} s, tip {D(p['tip_depth_mm'])} mm below the rest "
                   f"skin, peak |F| {F(p['peak_force_n'])} N")
    out.append(f"  max |F| {F(summary['max_force_n'])} N; tip at most {D(summary['max_tip_depth_mm'])} mm below the rest "
               f"skin; layers reached: {', '.join(summary['layers_reached']) or 'none'}")
    m = summary.get("metrics")
    if m:
        lo, hi = m["target_depth_mm"]
        out.append(f"  {m['insertions']} insertion(s), {T(m['time_in_tissue_s'])} s in tissue; "
                   f"target depth {lo:g}-{hi:g} mm (scene.target_depth_mm)")
        for n, i in enumerate(m["per_insertion"], 1):
            ang = "-" if i["angle_deg"] is None else f"{i['angle_deg']:.1f}"
            spd = "-" if i["insertion_speed_mm_s"] is None else f"{i['insertion_speed_mm_s']:.2f}"
            lt = i["lift_thrust"]
            cyc = f"{lt['cycles']} lift-thrust cycles"
            if lt["cycles"]:
                amp = "-" if lt["mean_amplitude_mm"] is None else D(lt["mean_amplitude_mm"])
                frq = "-" if lt["frequency_hz"] is None else f"{lt['frequency_hz']:.2f}"
                cyc += f" ({amp} mm, {frq} Hz)"
            tip = f" (tip {D(i['max_tip_depth_mm'])} mm below the rest skin)" if "max_tip_depth_mm" in i else ""
            out.append(f"  insertion {n}: needle {D(i['max_depth_mm'])} mm into the tissue{tip}: {i['depth_verdict']}; "
                       f"entry {D(i['entry_offset_mm'])} mm off the acupoint at {ang} deg to the normal; "
                       f"{spd} mm/s; {cyc}{technique_text(i.get('technique'))}")
    from .point import point_lines
    return out + point_lines(summary)  # with --point: the grading against the point


def add_debrief(summary: dict, cfg) -> dict:
    """Put the session's debrief (:func:`haptic_acu.analysis.debrief.debrief`) into ``summary``
    (key ``debrief``), with what it judged against: the needle's length and the device's force
    limit (``needle_length_mm``, ``force_limit_n``). Returns the debrief."""
    from ..analysis.debrief import debrief

    summary["needle_length_mm"] = float(cfg.needle.length_mm)
    summary["force_limit_n"] = float(cfg.safety.force_limit_n)
    summary["debrief"] = debrief(summary)
    return summary["debrief"]


def write_debrief_md(summary: dict, out_dir) -> None:
    """``debrief.md`` in the report folder: the summary's debrief as Markdown."""
    from ..analysis.debrief import debrief_markdown

    title = f"Debrief: {summary.get('trajectory', 'session')}"
    Path(out_dir, "debrief.md").write_text(debrief_markdown(summary["debrief"], title) + "\n")


def _width(file) -> int:
    """The terminal's width for ``file`` (80 when it is not a terminal or does not say)."""
    import os
    try:
        cols = os.get_terminal_size(file.fileno()).columns
    except (AttributeError, ValueError, OSError):
        import shutil
        cols = shutil.get_terminal_size((80, 24)).columns
    return cols if cols > 0 else 80


def print_results(summary: dict, out_dir, file=None, quiet: bool = False, verbose: bool = False) -> None:
    """:func:`result_lines` and the debrief (unless ``quiet``), and where the files are. On a
    terminal the result lines are wrapped to its width; into a file or a pipe each stays one line
    (what a script greps). The debrief's prose is wrapped to the width (80 off a terminal). Timing
    statistics (how fast a replay ran, the servo loop's) only with ``verbose`` (they are in
    summary.json's ``loop`` either way)."""
    import textwrap

    from ..analysis.debrief import debrief_lines

    file = sys.stdout if file is None else file
    width = max(40, _width(file))
    tty = bool(getattr(file, "isatty", lambda: False)())
    if not quiet:
        for line in result_lines(summary):
            indent = " " * (len(line) - len(line.lstrip()))
            parts = textwrap.wrap(line, width=width, subsequent_indent=indent + "    ",
                                  break_on_hyphens=False) if tty else [line]
            for part in parts or [""]:
                print(part, file=file)
        if summary.get("debrief"):
            for line in debrief_lines(summary["debrief"], width):
                print(line, file=file)
        if verbose and summary.get("_wall_s"):
            print(f"  replayed {summary['duration_s'] / summary['_wall_s']:.0f}x real time", file=file)
    print(f"  files: {out_dir}/", file=file)


# ---- samples.csv ------------------------------------------------------------------------------
# (header, source column or None, scale, decimals); None columns are computed.
_CSV_NUMERIC = (
    ("t_s", "t_s", 1.0, 6),
    ("x_mm", "x_m", 1e3, 4), ("y_mm", "y_m", 1e3, 4), ("z_mm", "z_m", 1e3, 4),
    ("fx_n", "fx_n", 1.0, 5), ("fy_n", "fy_n", 1.0, 5), ("fz_n", "fz_n", 1.0, 5),
)
_CSV_TAIL = (
    ("depth_mm", "depth_m", 1e3, 4),
    ("tip_depth_mm", None, 1e3, 4),
    ("depth_skin_mm", "depth_skin_m", 1e3, 4),
    ("f_n", None, 1.0, 5),
    ("f_surface_n", "f_surface_n", 1.0, 5), ("f_damp_n", "f_damp_n", 1.0, 5),
    ("f_lateral_n", "f_lateral_n", 1.0, 5), ("f_bone_n", "f_bone_n", 1.0, 5),
    ("f_skin_n", "f_skin_n", 1.0, 5), ("f_fat_n", "f_fat_n", 1.0, 5), ("f_muscle_n", "f_muscle_n", 1.0, 5),
    ("roll_deg", "roll_deg", 1.0, 4), ("torque_nmm", "torque_nmm", 1.0, 5),
    ("axis_x", "axis_x", 1.0, 6), ("axis_y", "axis_y", 1.0, 6), ("axis_z", "axis_z", 1.0, 6),
)
CSV_FIELDS = ("tick",) + tuple(h for h, *_ in _CSV_NUMERIC) + (
    "layer", "state_skin", "state_fat", "state_muscle") + tuple(h for h, *_ in _CSV_TAIL) + (
    "puncture", "clamped", "fault")


class SamplesCsvSink(Sink):
    """Writes every servo row to ``samples.csv`` as it arrives (flushed once per frame).

    Columns (:data:`CSV_FIELDS`): ``tick``; ``t_s``; tip position ``x_mm, y_mm, z_mm``; force on the
    needle ``fx_n, fy_n, fz_n``; ``layer`` the tip is in (outside/skin/fat/muscle/bone);
    ``state_skin/fat/muscle`` (untouched/pressing/punctured); ``depth_mm`` depth into that layer;
    ``tip_depth_mm`` depth below the rest skin surface (:func:`tip_depth_m`, negative above);
    ``depth_skin_mm`` depth in the compressed tissue's frame (0 until the skin breaks); ``f_n`` = |F|;
    the force parts (surface, damping, lateral, bone) and per-layer forces; ``roll_deg`` the needle's
    roll (cumulative, + clockwise seen from the handle) and ``torque_nmm`` the twist torque about its
    axis (N*mm, :mod:`haptic_acu.tissue.twirl`); ``axis_x, axis_y, axis_z`` the needle's axis (unit, handle
    to tip: the insertion axis once the skin is broken, before that the device's, ``nan`` if it gives
    none); ``puncture`` (the layer
    punctured on that tick, else empty); ``clamped`` and ``fault`` (0/1). Fixed decimals (t 1 us,
    lengths 0.1 um, forces 10 uN), no negative zeros: identical rows give identical bytes.
    """

    rows_only = True  # the rows (and the frame's time) only
    wants_tip_depth = True  # the tip_depth_mm column

    BATCH_ROWS = SummarySink.BATCH_ROWS  # the same batches: the tip depth is computed once for both

    def __init__(self, path):
        self.path = Path(path)
        self._f = None
        self.tissue = None
        self.rows_written = 0
        self._batches = RowBatches(self.BATCH_ROWS)
        self._fmt = None

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) the CSV formatter before the loops start."""
        self._fmt = _csv_layout()
        fmt, *spec = self._fmt
        fmt.format_gather(np.zeros((1, NCOL)), np.zeros((1, 2)), *spec)

    def start(self, info: dict) -> None:
        self.tissue = info["model"].tissue
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "wb")  # the formatter's ASCII bytes, written as they are
        self._f.write((",".join(CSV_FIELDS) + "\n").encode("ascii"))

    def on_frame(self, frame) -> None:
        self.on_frames((frame,))

    def on_frames(self, frames) -> None:
        # Formatted in batches (a frame holds ~17 rows; formatting is cheaper per row in bulk); a
        # live session loses at most BATCH_ROWS rows of this file on a crash (the recording sink
        # is the one that flushes every frame).
        for rows, depth in self._batches.add(frames):
            self._write_batch(rows, depth)

    def _write_pending(self) -> None:
        rows, depth = self._batches.flush()
        if rows is not None:
            self._write_batch(rows, depth)

    def _write_batch(self, rows, depth=None) -> None:
        try:
            self.write_rows(rows, depth)
            self._f.flush()
        except OSError as e:
            raise OSError(e.errno, f"{self.path}: cannot write: {e.strerror or e}") from None

    def close(self, result=None) -> None:
        if self._f is not None:
            try:
                self._write_pending()
            finally:
                self._f.close()
                self._f = None

    def write_rows(self, rows: np.ndarray, depth: np.ndarray | None = None) -> None:
        """Append ``rows`` (k, NCOL); ``depth``: their :func:`tip_depth_m`, if the caller has it."""
        k = len(rows)
        if k == 0:
            return
        if self._fmt is None:
            self._fmt = _csv_layout()
        fmt, src, scale, offset = self._fmt
        extra = np.empty((k, 2))  # the computed columns, after the row's own: tip_depth_m, |F|
        extra[:, 0] = tip_depth_m(rows[:, C_X:C_X + 3], self.tissue) if depth is None else depth
        extra[:, 1] = np.linalg.norm(rows[:, C_F:C_F + 3], axis=1)
        fmt.write_gather(self._f, rows, extra, src, scale, offset)
        self.rows_written += k


def _csv_layout():
    """samples.csv's formatter (:class:`~haptic_acu.base.csvfmt.RowFormatter`) and, per column, its
    source (a sample column, or past them the computed tip depth and |F|), scale and offset."""
    from ..base.csvfmt import RowFormatter
    computed = {"tip_depth_mm": NCOL, "f_n": NCOL + 1}

    def numeric(specs):
        return [(computed[name] if s is None else COL[s], scale, 0.0, ("fixed", nd)) for name, s, scale, nd in specs]

    cols = [(C_TICK, 1.0, 0.0, ("fixed", 0))] + numeric(_CSV_NUMERIC)
    cols += [(C_LAYER, 1.0, 1.0, ("category", PLACES))]  # codes -1..3: outside..bone
    cols += [(C_STATE + j, 1.0, 0.0, ("category", STATE_NAMES)) for j in range(N_LAYERS)]
    cols += numeric(_CSV_TAIL)
    cols += [(C_PUNCT, 1.0, 0.0, ("category", LAYERS)),  # -1 (none): an empty cell
             (COL["clamped"], 1.0, 0.0, ("fixed", 0)), (COL["fault"], 1.0, 0.0, ("fixed", 0))]
    fmt = RowFormatter([c[3] for c in cols])
    return (fmt, np.array([c[0] for c in cols], np.int64), np.array([c[1] for c in cols]),
            np.array([c[2] for c in cols]))


def read_samples_csv(path) -> list[dict]:
    """Read a ``samples.csv`` back as a list of dicts of strings (for tools and tests)."""
    with open(path, newline="", encoding="ascii") as f:
        return list(csv.DictReader(f))


__all__ = ["SummarySink", "SamplesCsvSink", "SessionScan", "FigureRows", "plot_force_depth", "tip_depth_m", "radial_force_n",
           "place_name", "CSV_FIELDS", "read_samples_csv"]

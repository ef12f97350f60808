"""The session figures' layout and PNG (force_depth.png, compare.png): rows of axes, each row's
axes side by side, every row between one left and one right edge, a title above. The margins are
measured from the text that sits in them (tick labels, axis labels, titles, a legend outside the
axes, a twin's right axis), a few text extents per axes, instead of matplotlib's constrained
layout, which draws the whole figure once more to find them; the axis labels are then fixed where
matplotlib would put them at every draw.

Imports matplotlib only when called, to read its rcParams (the ticks' length and pads).
"""
from __future__ import annotations

import contextlib
import gc


@contextlib.contextmanager
def gc_paused():
    """Python's cyclic garbage collector paused while a figure is built and drawn (also a decorator).
    A figure allocates tens of thousands of objects; in a process that holds numba, scipy and a
    session (10^5 objects and more) they trigger a full collection, which walks every one of them
    (50-150 ms, more than a third of the figure). The figure's own cycles go at the next collection."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()

def new_figure(figsize, dpi=None):
    """A matplotlib Figure of ``figsize`` inches on its own Agg canvas (nothing global from pyplot,
    no process-wide backend switch)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize) if dpi is None else Figure(figsize=figsize, dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


PNG_COMPRESS_LEVEL = 3  # zlib's: a third less encoding time than its default 6, files about 7% larger


def save_png(fig, path, dpi: int) -> None:
    """``fig`` as a PNG at ``dpi``: no Software stamp, the same bytes for the same figure."""
    fig.savefig(path, format="png", dpi=dpi, metadata={"Software": None},
                pil_kwargs={"compress_level": PNG_COMPRESS_LEVEL})


PAD_PT = 3.0  # space (points) at the figure's edges; twice this between one box's text and the next's
MAX_PASSES = 3  # measure, place, until the margins settle (tick labels can change with an axes' size)


def _extent(artist, renderer):
    """The window extent of a text artist as drawn; None when it draws nothing."""
    if artist is None or not artist.get_visible() or not artist.get_text():
        return None
    return artist.get_window_extent(renderer)


def _size(artist, renderer) -> tuple[float, float]:
    """(width, height) in pixels of a text artist as drawn; (0, 0) when it draws nothing."""
    bb = _extent(artist, renderer)
    return (0.0, 0.0) if bb is None else (bb.width, bb.height)


def _pt(renderer, points: float) -> float:
    return renderer.points_to_pixels(points)


def axis_margins(ax, renderer) -> tuple[dict, dict]:
    """(margins, reach): ``margins`` the pixels of ``ax``'s own text outside its box by side
    (left, right, bottom, top): tick labels, the ticks, axis labels with their pad, the offset text
    and the title; ``reach`` per axis (x, y) the pixels its tick labels reach out from the box
    (where :func:`fit_rows` puts the axis label, as matplotlib's own placement would)."""
    import matplotlib as mpl

    rc = mpl.rcParams
    box = ax.bbox
    out = {"left": 0.0, "right": 0.0, "bottom": 0.0, "top": 0.0}
    reach = {}
    beyond = {"left": lambda b: box.x0 - b.x0, "right": lambda b: b.x1 - box.x1,
              "bottom": lambda b: box.y0 - b.y0, "top": lambda b: b.y1 - box.y1}
    for axis, name in ((ax.xaxis, "x"), (ax.yaxis, "y")):
        side = axis.get_label_position()  # our axes keep an axis's ticks and its label on one side
        # the visible tick labels, placed for the axes' current box and limits
        lo, hi = sorted(axis.get_view_interval())
        tol = 1e-10 * (hi - lo)  # matplotlib draws a tick this close outside the view
        boxes = [b for t in axis.get_majorticklabels() if lo - tol <= t.get_position()[name == "y"] <= hi + tol
                 for b in [_extent(t, renderer)] if b is not None]
        # the spine's ticks point out (matplotlib's default): they count as a reach when no label does
        reach[name] = max([_pt(renderer, rc[f"{name}tick.major.size"])] + [beyond[side](b) for b in boxes])
        depth = reach[name]
        lw, lh = _size(axis.label, renderer)
        if lw or lh:
            depth = max(depth, reach[name] + _pt(renderer, axis.labelpad) + (lw if name == "y" else lh))
        out[side] = max(out[side], depth)
        if name == "x" and boxes:  # the end labels can reach past the box sideways
            out["left"] = max(out["left"], max(beyond["left"](b) for b in boxes))
            out["right"] = max(out["right"], max(beyond["right"](b) for b in boxes))
        ow, oh = _size(axis.offsetText, renderer)
        if oh:  # a y axis's offset sits above its box; an x axis's below, past its tick labels
            if name == "y":
                out["top"] = max(out["top"], oh + _pt(renderer, 2.0))
            else:
                out[side] = max(out[side], depth + oh)
    tw, th = _size(ax.title, renderer)
    if th:
        out["top"] = max(out["top"], th + _pt(renderer, rc["axes.titlepad"]))
    return out, reach


def _margins(cell, renderer, reach: dict) -> list[float]:
    """Margins (left, right, bottom, top) of one box: its axes and their twins (same box) together,
    and a legend outside; each axes' tick label reach into ``reach``."""
    box = cell[0].bbox
    m = [0.0, 0.0, 0.0, 0.0]
    for ax in cell:
        own, reach[ax] = axis_margins(ax, renderer)
        m = [max(a, own[side]) for a, side in zip(m, ("left", "right", "bottom", "top"))]
        leg = ax.get_legend()
        if leg is not None:
            lb = leg.get_window_extent(renderer)
            m[0] = max(m[0], box.x0 - lb.x0)
            m[1] = max(m[1], lb.x1 - box.x1)
            m[2] = max(m[2], box.y0 - lb.y0)
            m[3] = max(m[3], lb.y1 - box.y1)
    return m


def first_layout(n_cols: int, height_ratios) -> list[list[tuple[float, float, float, float]]]:
    """Rects (figure fractions) to create the axes at, near where :func:`fit_rows` puts them (their
    tick labels depend on their size): the first row ``n_cols`` side by side, the others one each."""
    left, right, bottom, top, gap = 0.1, 0.75, 0.07, 0.93, 0.08
    total = float(sum(height_ratios))
    free = top - bottom - gap * (len(height_ratios) - 1)
    out, y = [], top
    for r, ratio in enumerate(height_ratios):
        h = free * ratio / total
        n = n_cols if r == 0 else 1
        w = (right - left - 0.02 * (n - 1)) / n
        out.append([(left + j * (w + 0.02), y - h, w, h) for j in range(n)])
        y -= h + gap
    return out


def fit_rows(fig, rows, height_ratios, suptitle=None, pad_pt: float = PAD_PT) -> None:
    """Place the axes of ``rows`` (top to bottom; each a list of cells side by side, a cell a list
    of axes sharing one box: an axes and its twins) so that every text around them is inside the
    figure and clear of its neighbours' text. Rows share the left and the right edge; a row's cells
    share its width equally; the rows share the height by ``height_ratios``. ``suptitle`` (the
    figure's title, a Text) is put at the top. Set every limit, label, title and legend first;
    each axis label is then fixed where it goes (matplotlib would find it again at every draw), and
    a title set with ``y=1.0`` is not moved at draw either (no axes here has tick labels on top)."""
    renderer = fig.canvas.get_renderer()
    W, H = fig.bbox.width, fig.bbox.height
    p = _pt(renderer, pad_pt)
    _, st_h = _size(suptitle, renderer)
    if suptitle is not None:
        suptitle.set_y(1.0 - p / H)
        suptitle.set_verticalalignment("top")
    top_edge = H - p - (st_h + p if st_h else 0.0)
    total = float(sum(height_ratios))
    placed = None
    for _ in range(MAX_PASSES):
        reach: dict = {}
        margins = [[_margins(cell, renderer, reach) for cell in row] for row in rows]
        left = p + max(m[0][0] for m in margins)
        right = W - p - max(m[-1][1] for m in margins)
        tops = [max(c[3] for c in m) for m in margins]
        bottoms = [max(c[2] for c in m) for m in margins]
        free = top_edge - p - sum(tops) - sum(bottoms) - 2 * p * (len(rows) - 1)
        boxes, y = [], top_edge
        for row, m, ratio, top, bottom in zip(rows, margins, height_ratios, tops, bottoms):
            h = free * ratio / total
            y_top = y - top
            gaps = [m[j][1] + m[j + 1][0] + 2 * p for j in range(len(row) - 1)]
            w = (right - left - sum(gaps)) / len(row)
            x = left
            for j, cell in enumerate(row):
                boxes.append((cell, (x / W, (y_top - h) / H, w / W, h / H)))
                x += w + (gaps[j] if j < len(gaps) else 0.0)
            y = y_top - h - bottom - 2 * p
        now = [b for _, b in boxes]
        for cell, rect in boxes:
            for ax in cell:
                ax.set_position(rect)
        if placed is not None and max(abs(a - b) for r0, r1 in zip(placed, now) for a, b in zip(r0, r1)) * max(W, H) < 0.5:
            break
        placed = now
    for ax, r in reach.items():  # each axis label beyond its tick labels, where matplotlib would put it
        _place_label(ax.xaxis, r["x"], renderer)
        _place_label(ax.yaxis, r["y"], renderer)


def _place_label(axis, reach: float, renderer) -> None:
    """Fix ``axis``'s label ``reach`` + its pad pixels out from the axes box, centred along it: the
    position matplotlib finds at every draw from the tick labels' extents, found once."""
    if not axis.label.get_text():
        return
    box = axis.axes.bbox
    off = reach + _pt(renderer, axis.labelpad)
    side = axis.get_label_position()
    if side in ("left", "right"):
        x = -off / box.width if side == "left" else 1.0 + off / box.width
        axis.set_label_coords(x, 0.5)
    else:
        y = -off / box.height if side == "bottom" else 1.0 + off / box.height
        axis.set_label_coords(0.5, y)

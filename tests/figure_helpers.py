"""Checks on a figure as drawn: every text the renderer draws, where it lands."""
from __future__ import annotations

from matplotlib.backends.backend_agg import RendererAgg
from matplotlib.legend import Legend
from matplotlib.text import Annotation, Text


def drawn_texts(fig, monkeypatch) -> list:
    """(text artist, window extent) of every text drawn when ``fig`` is drawn once more."""
    seen, calls = [], [0]
    draw_text, draw = RendererAgg.draw_text, Text.draw

    def count(self, *a, **k):
        calls[0] += 1
        return draw_text(self, *a, **k)

    def record(self, renderer):
        before = calls[0]
        out = draw(self, renderer)
        if calls[0] > before:  # it drew glyphs (a multi-line text: once per line)
            seen.append(self)
        return out

    with monkeypatch.context() as m:
        m.setattr(RendererAgg, "draw_text", count)
        m.setattr(Text, "draw", record)
        fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    return [(t, t.get_window_extent(renderer)) for t in seen]


def _in_legend(text, fig) -> bool:
    return any(isinstance(a, Legend) and text in a.get_texts() for ax in fig.axes for a in [ax.get_legend()])


def assert_texts_fit(fig, monkeypatch) -> int:
    """Every drawn text inside the canvas; every text the layout places (tick labels, axis labels,
    titles, the legend) clear of every other text and of every plot's box. Returns the count."""
    texts = drawn_texts(fig, monkeypatch)
    W, H = fig.canvas.get_width_height()
    for t, b in texts:
        assert b.x0 >= 0 and b.y0 >= 0 and b.x1 <= W and b.y1 <= H, f"{t.get_text()!r} cut at the edge: {b}"
    shrunk = [(t, b.padded(-0.5)) for t, b in texts]  # touching is not overlapping
    for i, (t, b) in enumerate(shrunk):
        for u, c in shrunk[i + 1:]:
            if isinstance(t, Annotation) and isinstance(u, Annotation):
                continue  # labels on the data (a panel's repeated insertions can share a spot)
            assert not b.overlaps(c), f"{t.get_text()!r} overlaps {u.get_text()!r}"
    boxes = [ax.bbox for ax in fig.axes]
    for t, b in shrunk:
        if isinstance(t, Annotation):  # drawn on a plot, by design
            continue
        for box in boxes:
            assert not b.overlaps(box), f"{t.get_text()!r} ({'legend' if _in_legend(t, fig) else 'text'}) over a plot"
    return len(texts)

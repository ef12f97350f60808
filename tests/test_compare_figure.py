"""compare.png read as drawn: three sessions, two of them identical, give three curves one can tell
apart (each session's colour shows on the force-depth panel), the target band, the force limit, a
time panel, a twirl panel only when a session twirls, and the force's sign in words."""
from __future__ import annotations

import numpy as np
import pytest
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure

from haptic_acu.base.config import load_config
from haptic_acu.session.compare import COLOURS, FORCE_SIGN, plot_compare
from haptic_acu.servo.samples import COL, NCOL

from figure_helpers import assert_texts_fit


def _rows(depth_mm, force_n, roll=None):
    r = np.zeros((len(depth_mm), NCOL))
    r[:, COL["t_s"]] = np.arange(len(depth_mm)) * 1e-3
    r[:, COL["depth_skin_m"]] = np.asarray(depth_mm) * 1e-3
    r[:, COL["z_m"]] = -np.asarray(depth_mm) * 1e-3
    r[:, COL["fz_n"]] = force_n
    r[:, COL["state_skin"]] = np.where(np.asarray(depth_mm) > 0, 2, 1)
    r[:, COL["puncture"]] = -1  # no puncture on any tick (the curves alone carry the colours)
    if roll is not None:
        r[:, COL["roll_deg"]] = roll
    return r


@pytest.fixture
def drawn(monkeypatch, tmp_path):
    figs = []
    orig = Figure.savefig

    def keep(self, *a, **k):
        figs.append(self)
        return orig(self, *a, **k)

    monkeypatch.setattr(Figure, "savefig", keep)

    def draw(rows, labels):
        plot_compare(rows, labels, tmp_path / "c.png", load_config())
        fig = figs[-1]
        fig.canvas.draw()
        return fig
    return draw


def _pixels_of(fig, ax, colour, tol=0.12) -> int:
    img = np.asarray(fig.canvas.buffer_rgba())[:, :, :3] / 255.0
    h = img.shape[0]
    b = ax.get_window_extent()
    sub = img[int(h - b.y1):int(h - b.y0), int(b.x0):int(b.x1)]
    return int(np.count_nonzero(np.abs(sub - np.array(to_rgb(colour))).max(axis=2) < tol))


D = np.concatenate([np.zeros(50), np.linspace(0, 25, 500), np.linspace(25, 0, 500)])


def test_three_sessions_two_identical_are_three_curves(drawn):
    same = _rows(D, 0.04 * D)
    fig = drawn([same, same.copy(), _rows(0.8 * D, 0.06 * D)], ["A", "B", "C"])
    depth_ax = next(ax for ax in fig.axes if ax.get_xlabel().startswith("tip depth"))
    for colour in COLOURS[:3]:  # each session's colour is seen on the panel: A under B still shows
        assert _pixels_of(fig, depth_ax, colour) > 150, colour
    lines = [ln for ln in depth_ax.get_lines() if np.isfinite(ln.get_xdata()).sum() > 100]
    styles = {(ln.get_color(), str(ln.get_linestyle()), ln.get_linewidth()) for ln in lines}
    assert len(styles) == 3
    legend = [t.get_text() for t in depth_ax.figure.axes[0].get_legend().get_texts()] if depth_ax.get_legend() \
        else [t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()]
    assert "B (same curve as A)" in legend and "A" in legend and "C" in legend
    assert any(t.startswith("target depth 15-30 mm") for t in legend)
    assert any(t.startswith("device force limit 3.3 N") for t in legend)
    assert FORCE_SIGN in depth_ax.get_ylabel()
    titles = [ax.get_title() for ax in fig.axes]
    assert "force against time" in titles and not any("twirling" in t for t in titles)
    lo, hi = depth_ax.get_ylim()
    assert hi > 3.3  # the limit is on the panel


def test_a_twirl_panel_when_a_session_twirls(drawn):
    roll = np.concatenate([np.zeros(550), 90 * np.sin(np.linspace(0, 6 * np.pi, 500))])
    fig = drawn([_rows(D, 0.04 * D), _rows(D, 0.05 * D, roll)], ["still", "twirled"])
    (ax,) = [ax for ax in fig.axes if ax.get_title().startswith("twirling")]
    assert ax.get_ylabel().startswith("roll (deg)")
    assert _pixels_of(fig, ax, COLOURS[1]) > 100


def test_every_text_is_inside_the_figure_and_clear_of_the_others(drawn, monkeypatch):
    """compare.png's fixed layout: with a twirl panel and two insertion panels, no text is cut at the
    edge, overlaps another, or lies over a plot (the legend's long labels included)."""
    roll = np.concatenate([np.zeros(550), 90 * np.sin(np.linspace(0, 6 * np.pi, 500))])
    two = np.concatenate([D, D])
    rows = _rows(two, 0.04 * two, np.concatenate([roll, roll]))
    rows[len(D):, COL["t_s"]] += 1.0  # the second insertion after a pause
    fig = drawn([rows, _rows(D, 0.05 * D)], ["a trainee with a long name", "the expert"])
    assert len([ax for ax in fig.axes if ax.get_xlabel().startswith("tip depth")]) == 2
    assert any(ax.get_title().startswith("twirling") for ax in fig.axes)
    assert assert_texts_fit(fig, monkeypatch) > 30

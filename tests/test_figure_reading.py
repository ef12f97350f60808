"""force_depth.png reads at a glance, checked on the drawn figure itself (captured at
savefig): one colour and panel per insertion, the lateral panel when the tip moves sideways with the
offset not drawn on top of the lateral force, and legends that cover no axes.

The rows are the real NeedleModel driven engine-free along two paths: two perpendicular insertions
5 mm apart (new_site's shape), and a lateral sweep pressing the skin 0.5 mm (lateral_sweep's shape).
"""
from __future__ import annotations

import numpy as np
import pytest
from matplotlib.figure import Figure

from haptic_acu.servo import samples as S
from haptic_acu.base.config import load_config
from haptic_acu.servo.step import NeedleModel
from haptic_acu.session.report import plot_force_depth

from figure_helpers import assert_texts_fit


def drive(model, path_mm, dt=1e-3) -> np.ndarray:
    """Sample rows along ``path_mm`` (k, 3), one point per 1 ms tick."""
    model.reset(keep_holes=False)
    rows = np.zeros((len(path_mm), S.NCOL))
    prev = path_mm[0] * 1e-3
    for i, p_mm in enumerate(path_mm):
        p = p_mm * 1e-3
        model.step(p, (p - prev) / dt)
        prev = p
        S.write_sample(rows, i, i * dt, i, model.inp, model.state, model.out.diag, 0.0)
    return rows


def line(a, b, speed_mm_s=10.0):
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = max(int(np.linalg.norm(b - a) / speed_mm_s * 1000), 1)
    return a + (b - a) * (np.arange(n)[:, None] / n)


@pytest.fixture(scope="module")
def model():
    m = NeedleModel(load_config())
    m.warm_up()
    return m


@pytest.fixture
def drawn(monkeypatch, tmp_path):
    """plot_force_depth's Figure, kept when it is saved."""
    figs = []
    orig = Figure.savefig

    def keep(self, *a, **k):
        figs.append(self)
        return orig(self, *a, **k)

    monkeypatch.setattr(Figure, "savefig", keep)

    def draw(rows):
        plot_force_depth(rows, tmp_path / "f.png")
        fig = figs[-1]
        fig.canvas.draw()
        return fig
    return draw


def _legends_clear_of_axes(fig):
    boxes = [ax.get_window_extent() for ax in fig.axes]
    legends = [lg for ax in fig.axes for lg in [ax.get_legend()] if lg is not None]
    assert legends
    for lg in legends:
        lb = lg.get_window_extent()
        for box in boxes:
            assert not lb.overlaps(box), "a legend covers a plot"


def test_two_insertions_get_a_panel_and_a_colour_each(model, drawn):
    path = np.concatenate([line((0, 0, 5), (0, 0, -8)), line((0, 0, -8), (0, 0, 5)), line((0, 0, 5), (5, 0, 5)),
                           line((5, 0, 5), (5, 0, -8)), line((5, 0, -8), (5, 0, 5))])
    fig = drawn(drive(model, path))
    depth_panels = [ax for ax in fig.axes if ax.get_xlabel().startswith("tip depth")]
    assert [ax.get_title() for ax in depth_panels] == ["insertion 1", "insertion 2"]
    colours = [{ln.get_color() for ln in ax.get_lines() if len(ln.get_xdata()) > 50} for ax in depth_panels]
    assert all(len(c) >= 1 for c in colours) and not (colours[0] & colours[1]), colours
    _legends_clear_of_axes(fig)


def test_a_lateral_sweep_shows_the_lateral_force_apart_from_the_offset(model, drawn):
    press = line((0, 0, 5), (0, 0, -0.5), 5.0)
    sweep = line((0, 0, -0.5), (10, 0, -0.5), 5.0)
    back = line((10, 0, -0.5), (0, 0, -0.5), 5.0)
    up = line((0, 0, -0.5), (0, 0, 5), 5.0)
    rows = drive(model, np.concatenate([press, sweep, back, up]))
    fig = drawn(rows)
    (lat,) = [ax for ax in fig.axes if ax.get_ylabel() == "lateral |F| (N)"]
    (twin,) = [ax for ax in fig.axes if ax.get_ylabel().startswith("tip offset")]
    force_line = max(lat.get_lines(), key=lambda ln: np.max(ln.get_ydata()))
    (offset_line,) = twin.get_lines()
    assert force_line.get_color() != offset_line.get_color()
    # the two curves' peaks are drawn well apart on screen (pixels), not on one line
    fy = lat.transData.transform((0.0, np.max(force_line.get_ydata())))[1]
    oy = twin.transData.transform((0.0, np.max(offset_line.get_ydata())))[1]
    assert abs(fy - oy) > 20.0, (fy, oy)
    # and both within their panel
    top = lat.get_window_extent().y1
    assert fy <= top + 0.5 and oy <= top + 0.5
    _legends_clear_of_axes(fig)


def _insertions(n, apart_mm=5.0, depth_mm=8.0):
    """``n`` perpendicular insertions ``apart_mm`` apart along x, each to ``depth_mm`` and out."""
    legs = []
    for k in range(n):
        x = k * apart_mm
        legs += [line((x, 0, 5), (x, 0, -depth_mm)), line((x, 0, -depth_mm), (x, 0, 5))]
        if k < n - 1:
            legs.append(line((x, 0, 5), (x + apart_mm, 0, 5)))
    return np.concatenate(legs)


@pytest.mark.parametrize("case", ["one deep insertion", "two insertions", "five insertions", "lateral sweep"])
def test_every_text_is_inside_the_figure_and_clear_of_the_others(model, drawn, monkeypatch, case):
    """The fixed layout leaves room for every tick label, axis label, title and legend entry: none
    is cut at the figure's edge, none overlaps another text, none outside a plot lies over one."""
    if case == "lateral sweep":
        path = np.concatenate([line((0, 0, 5), (0, 0, -0.5), 5.0), line((0, 0, -0.5), (10, 0, -0.5), 5.0),
                               line((10, 0, -0.5), (0, 0, 5), 5.0)])
    else:
        n = {"one deep insertion": 1, "two insertions": 2, "five insertions": 5}[case]
        path = _insertions(n, depth_mm=25.0 if n == 1 else 8.0)
    fig = drawn(drive(model, path))
    depth_panels = [ax for ax in fig.axes if ax.get_xlabel().startswith("tip depth")]
    assert len(depth_panels) == {"five insertions": 4, "two insertions": 2}.get(case, 1)
    if case == "lateral sweep":
        assert any(ax.get_ylabel().startswith("tip offset") for ax in fig.axes)
    assert assert_texts_fit(fig, monkeypatch) > 30  # the tick labels are among the texts checked

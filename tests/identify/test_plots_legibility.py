"""The legibility checks of ``identify.plots.legibility`` on small figures made bad on purpose:
each check flags its bad figure and passes the good one."""

import numpy as np
import pytest
from matplotlib.figure import Figure

from identify.plots.legibility import (
    box_covers_data,
    draw,
    legend_covers_data,
    legend_font_too_small,
    line_points_px,
    marker_points_px,
    overlapping_tick_labels,
)


def axes(size=(4.0, 3.0)):
    fig = Figure(figsize=size, dpi=100)
    ax = fig.add_subplot()
    ax.set(xlim=(0, 1), ylim=(0, 1))
    return ax


def test_draw_gives_a_figure_without_a_canvas_a_renderer():
    ax = axes()
    ax.plot([0, 1], [0, 1])
    assert draw(ax.figure) is not None
    assert ax.get_lines()[0].get_window_extent().width > 0


def test_overlapping_tick_labels():
    good = axes()
    assert overlapping_tick_labels(good) == []
    bad = axes()
    bad.set_xticks(np.linspace(0, 1, 30), [f"label {i}" for i in range(30)])
    pairs = overlapping_tick_labels(bad)
    assert ("label 0", "label 1") in pairs
    assert overlapping_tick_labels(bad.figure) == pairs  # a figure: all its axes
    minor = axes()  # minor labels count too
    minor.set_xticks(np.linspace(0, 1, 3))
    minor.set_xticks(np.linspace(0.01, 0.99, 40), [f"m{i}" for i in range(40)], minor=True)
    assert overlapping_tick_labels(minor)


def test_legend_font_too_small():
    ax = axes()
    ax.plot([0, 1], [0, 0.2], label="line")
    ax.legend(fontsize=5)
    assert legend_font_too_small(ax) == ["line (5 pt)"]
    assert legend_font_too_small(ax, min_pt=5) == []
    ax.legend(fontsize=8)
    assert legend_font_too_small(ax.get_legend()) == []
    with pytest.raises(ValueError):
        legend_font_too_small(axes())


def test_legend_over_a_line_between_its_points():
    # only the drawn segment passes under the legend, no data point does
    ax = axes()
    (ln,) = ax.plot([0, 1], [0.5, 0.5], label="flat")
    ax.legend(loc="center")
    assert legend_covers_data(ax) == [ln]
    ax.legend(loc="lower left")
    ln.set_ydata([0.9, 0.9])
    assert legend_covers_data(ax) == []
    with pytest.raises(ValueError):
        legend_covers_data(axes())


def test_legend_over_a_marker_glyph():
    # the marker's centre lies beside the legend, its glyph reaches under it
    ax = axes()
    (ln,) = ax.plot([0.5], [0.5], "o", ms=20, label="point")
    leg = ax.legend(loc="center")
    r = draw(ax.figure)
    box = leg.get_window_extent(r)
    x, y = ax.transData.inverted().transform((box.x1 + 5, (box.y0 + box.y1) / 2))
    ln.set_data([x], [y])
    assert legend_covers_data(ax) == [ln]
    ln.set_markersize(4)
    assert legend_covers_data(ax) == []


def test_legend_over_a_bar_a_band_and_a_scatter():
    ax = axes()
    bars = ax.bar([0.5], [0.9], width=0.2, label="bar")
    ax.legend(loc="center")
    assert legend_covers_data(ax) == [bars[0]]
    ax.legend(loc="upper left")
    assert legend_covers_data(ax) == []

    ax = axes()
    band = ax.fill_between([0, 1], [0.4, 0.4], [0.6, 0.6], label="band")
    ax.legend(loc="center")
    assert legend_covers_data(ax) == [band]
    assert legend_covers_data(ax, collections=False) == []
    ax.legend(loc="upper right")
    assert legend_covers_data(ax) == []

    ax = axes()
    dots = ax.scatter([0.5, 0.9], [0.5, 0.1], label="dots")
    ax.legend(loc="center")
    assert legend_covers_data(ax) == [dots]
    ax.legend(loc="upper left")
    assert legend_covers_data(ax) == []


def test_a_text_over_a_line():
    ax = axes()
    (ln,) = ax.plot([0, 1], [0.5, 0.5])
    over = ax.text(0.5, 0.5, "(a)", ha="center", va="center")
    beside = ax.text(0.05, 0.95, "(b)", va="top")
    r = draw(ax.figure)
    assert box_covers_data(ax, over.get_window_extent(r)) == [ln]
    assert box_covers_data(ax, beside.get_window_extent(r)) == []


def test_line_points_follow_the_drawn_path():
    ax = axes()
    (steps,) = ax.plot([0, 0.5, 1], [0, 1, 1], drawstyle="steps-post")
    (gap,) = ax.plot([0, 0.4, np.nan, 0.6, 1], [0.5] * 5)
    (dots,) = ax.plot([0.2, 0.8], [0.2, 0.8], "o")
    draw(ax.figure)
    p = line_points_px(steps)
    corner = ax.transData.transform((0.5, 0.0))  # the step drawn at x = 0.5 from y = 0
    assert np.min(np.hypot(*(p - corner).T)) < 1e-6
    g = line_points_px(gap)
    mid = ax.transData.transform((0.5, 0.5))
    left = np.sort(g[g[:, 0] < mid[0], 0])
    assert np.max(np.diff(left)) <= 1.0 + 1e-9  # densified: 1 px apart
    assert np.min(np.abs(g[:, 0] - mid[0])) > 10  # nothing drawn across the NaN
    assert len(line_points_px(dots)) == 0 and len(marker_points_px(dots)) == 2

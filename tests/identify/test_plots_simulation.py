"""The paper's Fig. 13 (``plot_simulation``, ``identify simulate --plot``) is fit for a
paper: legends and panel letters off the curves, every line explained, tick labels
apart, a creeping block's speed in a unit that reads.

Two short simulated runs (20 µm of travel, a few hundredths of a second each).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_hex
from matplotlib.figure import Figure

from identify import simulate
from identify.plots.base import plot_simulation


def run(fp_Hz: float):
    return simulate("FOTAS", spring_constant_N_per_m=2.13, normal_load_uN=8.0, step_frequency_Hz=fp_Hz,
                    travel_um=20.0)


@pytest.fixture(scope="module")
def stick_slip():
    r = run(100.0)  # as `identify simulate ... --fp 100 --travel-um 20 --plot`
    assert r.regime == "stick-slip"
    return r


@pytest.fixture(scope="module")
def creep():
    r = run(1000.0)
    assert r.regime == "creep"
    return r


@pytest.fixture(autouse=True)
def _close_pyplot_figures():
    yield
    import matplotlib.pyplot as plt

    plt.close("all")


def figure_axes():
    """Five stacked axes as ``plot_simulation`` makes them (the CLI's figure)."""
    fig = Figure(figsize=(7, 10), layout="constrained")
    FigureCanvasAgg(fig)
    return fig.subplots(5, 1, sharex=True)


def renderer(fig):
    if not isinstance(fig.canvas, FigureCanvasAgg):
        FigureCanvasAgg(fig)
    fig.canvas.draw()
    return fig.canvas.get_renderer()


def line_points_px(line, per_segment: int = 20) -> np.ndarray:
    """Display points along a line's drawn path (segments densified), inside its axes."""
    xy = line.get_transform().transform(np.asarray(line.get_xydata(), float))
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    if len(xy) > 1:
        s = np.linspace(0, 1, per_segment)[:, None, None]
        xy = (xy[:-1][None] * (1 - s) + xy[1:][None] * s).reshape(-1, 2)
    box = line.axes.get_window_extent()
    keep = (xy[:, 0] >= box.x0) & (xy[:, 0] <= box.x1) & (xy[:, 1] >= box.y0) & (xy[:, 1] <= box.y1)
    return xy[keep]


def assert_covers_no_line(ax, box, what: str) -> None:
    box = box.padded(-1)
    for ln in ax.get_lines():
        p = line_points_px(ln)
        hit = (p[:, 0] > box.x0) & (p[:, 0] < box.x1) & (p[:, 1] > box.y0) & (p[:, 1] < box.y1)
        assert not hit.any(), f"{what} covers {ln.get_label()!r}"


@pytest.mark.parametrize("which", ["stick_slip", "creep"])
def test_legends_and_panel_letters_cover_no_curve(which, request):
    # panel (e)'s legend lay over the friction capacity and spring force curves
    res = request.getfixturevalue(which)
    for axes in (plot_simulation(res), plot_simulation(res, axes=figure_axes())):
        fig = axes[0].figure
        r = renderer(fig)
        legends = 0
        for ax in axes:
            leg = ax.get_legend()
            if leg is not None:
                legends += 1
                assert all(t.get_fontsize() >= 7 for t in leg.get_texts())
                assert_covers_no_line(ax, leg.get_window_extent(r), f"the legend of {ax.get_ylabel()!r}")
            for t in ax.texts:
                assert t.get_fontsize() >= 7
                assert_covers_no_line(ax, t.get_window_extent(r), f"the text {t.get_text()!r}")
        assert legends >= 2
        assert sorted(t.get_text() for ax in axes for t in ax.texts) == [f"({c})" for c in "abcde"]


def test_tick_labels_apart(stick_slip):
    axes = plot_simulation(stick_slip, axes=figure_axes())
    r = renderer(axes[0].figure)
    for ax in axes:
        for axis in (ax.xaxis, ax.yaxis):
            boxes = [t.get_window_extent(r) for t in axis.get_ticklabels() if t.get_visible() and t.get_text()]
            for a, b in itertools.combinations(boxes, 2):
                assert not a.overlaps(b)


def test_every_line_is_in_its_panels_legend(stick_slip):
    # the dotted μmin and μmax lines of panel (d) were not explained
    axes = plot_simulation(stick_slip, axes=figure_axes())
    for ax in (axes[0], axes[3], axes[4]):
        handles = ax.get_legend().legend_handles
        shown = {(to_hex(h.get_color()), h.get_linestyle()) for h in handles}
        for ln in ax.get_lines():
            assert (to_hex(ln.get_color()), ln.get_linestyle()) in shown, ax.get_ylabel()
        colours = [to_hex(h.get_color()) for h in handles]
        assert len(set(colours)) == len(colours)


def test_creeping_block_speed_in_micrometres_per_second(creep, stick_slip):
    # a creeping block's 4 µm/s were drawn as 0.0004 cm/s
    ax = plot_simulation(creep, axes=figure_axes())[1]
    assert ax.get_ylabel() == "velocity (µm/s)"
    assert 1 < np.nanmax(ax.get_lines()[0].get_ydata()) < 1000
    assert plot_simulation(stick_slip, axes=figure_axes())[1].get_ylabel() == "velocity (cm/s)"


def test_returns_the_axes_it_was_given(stick_slip):
    axes = figure_axes()
    assert plot_simulation(stick_slip, axes=axes) is axes
    assert len(plot_simulation(stick_slip, t_window=(0.0, 0.05))) == 5

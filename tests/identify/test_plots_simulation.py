"""The paper's Fig. 13 (``plot_simulation``, ``identify simulate --plot``) is fit for a
paper: legends and panel letters off the curves, every line explained, tick labels
apart, a creeping block's speed in a unit that reads.

Two short simulated runs (20 µm of travel, a few hundredths of a second each).
"""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_hex
from matplotlib.figure import Figure

from identify import simulate
from identify.plots.base import plot_simulation
from identify.plots.legibility import (
    box_covers_data,
    draw,
    legend_covers_data,
    legend_font_too_small,
    overlapping_tick_labels,
)


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


@pytest.mark.parametrize("which", ["stick_slip", "creep"])
def test_legends_and_panel_letters_cover_no_curve(which, request):
    # panel (e)'s legend lay over the friction capacity and spring force curves
    res = request.getfixturevalue(which)
    for axes in (plot_simulation(res), plot_simulation(res, axes=figure_axes())):
        fig = axes[0].figure
        r = draw(fig)
        legends = 0
        for ax in axes:
            leg = ax.get_legend()
            if leg is not None:
                legends += 1
                assert legend_font_too_small(leg) == []
                assert legend_covers_data(ax) == [], f"the legend of {ax.get_ylabel()!r}"
            for t in ax.texts:
                assert t.get_fontsize() >= 7
                assert box_covers_data(ax, t.get_window_extent(r)) == [], f"the text {t.get_text()!r}"
        assert legends >= 2
        assert sorted(t.get_text() for ax in axes for t in ax.texts) == [f"({c})" for c in "abcde"]


def test_tick_labels_apart(stick_slip):
    axes = plot_simulation(stick_slip, axes=figure_axes())
    assert overlapping_tick_labels(axes[0].figure) == []


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

"""The design figures are fit for a paper: legends legible and off the data, tick labels
apart, colours and hatches as the legend says, no bars on a log axis, uncertainty shown.

The result objects are built directly (the paper's springs, a hand-made operating-range
grid, a hand-made experiment plan): no solver and no simulation runs here.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from matplotlib.colors import to_hex
from matplotlib.container import ErrorbarContainer
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Rectangle

from design.experiment import Candidate, ExperimentPlan
from design.ranges import NOT_SIMULATED, OperatingRanges, UsabilityRules
from design.spring_set import SpringSet, SpringSetResult, paper_spring_set
from design.springs import LONG_SUSPENSION, SpringDesign
from identify.plots.base import plot_regime_map
from identify.plots.legibility import draw, legend_covers_data, legend_font_too_small, overlapping_tick_labels
from identify.simulation.regimes import RegimeMap


# ------------------------------------------------------------------------- helpers
def cli_axes(size=(6.5, 5.0)):
    """Axes as ``python -m design ... --plot`` makes them."""
    fig = Figure(figsize=size, layout="constrained")
    return fig.add_subplot()


@pytest.fixture(autouse=True)
def _close_pyplot_figures():
    yield
    import matplotlib.pyplot as plt

    plt.close("all")


def data_lines(ax):
    return [ln for ln in ax.get_lines() if ln.get_visible()]


def assert_legible_legend(ax) -> None:
    """A legend at 7 pt or more that covers no line, marker, bar or band."""
    assert ax.get_legend() is not None, "no legend"
    assert legend_font_too_small(ax) == []
    assert legend_covers_data(ax) == [], "the legend covers data"


def assert_tick_labels_apart(ax) -> None:
    assert overlapping_tick_labels(ax) == []


def effective_order(ax, artist) -> tuple:
    """(zorder, insertion index): what matplotlib draws later lies on top."""
    return artist.get_zorder(), ax.get_children().index(artist)


# ------------------------------------------------------------------ Fig. 3 (springs)
LOAD_RANGE = (0.0276e-6, 452e-6)


@pytest.fixture(scope="module")
def spring_result() -> SpringSetResult:
    # the default `design springs` answer, built without the solver
    ours = SpringSet((SpringDesign(1.5, LONG_SUSPENSION), SpringDesign(4.206, LONG_SUSPENSION),
                      SpringDesign(6.38)), LOAD_RANGE, label="optimised")
    return SpringSetResult(spring_set=ours, reference=paper_spring_set(LOAD_RANGE),
                           requested_load_range_uN=None, attempts=())


def test_fig3_legend_covers_no_line(spring_result):
    # the legend sat over the requested-range line at 452 µN and the Table I boundaries
    ax = spring_result.plot(ax=cli_axes())
    assert_legible_legend(ax)
    assert_tick_labels_apart(ax)


def test_fig3_every_line_colour_is_in_the_legend(spring_result):
    # the dotted Table I boundaries had no legend entry
    ax = spring_result.plot(ax=cli_axes())
    legend = {to_hex(h.get_color()) for h in ax.get_legend().legend_handles if isinstance(h, Line2D)}
    for ln in data_lines(ax):
        assert to_hex(ln.get_color()) in legend, f"line colour {ln.get_color()} not explained"


def test_fig3_requested_range_lies_over_the_spring_caps(spring_result):
    # the 0.0276 µN line coincides with the lowest spring's end cap, which hid it
    ax = spring_result.plot(ax=cli_axes())
    red = [ln for ln in data_lines(ax) if to_hex(ln.get_color()) == to_hex("C3") and len(ln.get_xdata())]
    assert len(red) == 2
    for r in red:
        y = r.get_ydata()[0]
        under = [ln for ln in data_lines(ax) if ln not in red and np.allclose(ln.get_ydata(), y, rtol=1e-2)]  # < 1 px
        assert under, "the test expects a spring cap on the requested-range line"
        for ln in under:
            assert effective_order(ax, ln) < effective_order(ax, r)


def test_fig3_keeps_its_signature(spring_result):
    from design.plots import plot_design, plot_feasible_region, plot_spring_set

    ax = cli_axes()
    assert plot_design(spring_result, ax) is ax
    assert plot_feasible_region(cli_axes()) is not None
    assert plot_spring_set(spring_result.spring_set) is not None


# --------------------------------------------------------------- operating ranges
def ranges(loads, fps, regimes, failed, table=(1.92, 237.0)) -> OperatingRanges:
    shape = (len(loads), len(fps))
    f = np.empty(shape, dtype=object)
    for i, j in np.ndindex(shape):
        f[i, j] = tuple((r, r) for r in failed[i][j])
    return OperatingRanges(
        coating="FOTAS", spring_constant_N_per_m=2.13, stick_speed_m_per_s=1e-5, travel_um=100.0,
        rules=UsabilityRules(), normal_load_range_uN=table, normal_loads_uN=np.asarray(loads, float),
        step_frequencies_Hz=np.asarray(fps, float), regimes=np.asarray(regimes, str), failed=f,
        mean_slip_um=np.ones(shape), n_slips=np.full(shape, 30),
    )


S, C, N = "stick-slip", "creep", NOT_SIMULATED


@pytest.fixture(scope="module")
def grid_on_table_i() -> OperatingRanges:
    # the default grid: its first and last loads are Table I's limits (usable dots on them)
    return ranges(
        [1.92, 13.2, 90.3, 237.0], [10.0, 100.0, 1000.0, 10000.0],
        [[S, S, C, N], [S, S, C, N], [S, S, C, N], [S, S, C, N]],
        [[[], [], ["regime"], ["camera"]],
         [[], [], ["regime"], ["camera"]],
         [["slip_count"], ["slip_count"], ["regime"], ["camera"]],
         [["slip_count"], [], ["regime"], ["camera"]]],
    )


def test_ranges_usable_dots_lie_over_every_line(grid_on_table_i):
    # the Table I limit lines ran through the usable dots at 1.92 µN
    ax = grid_on_table_i.plot(ax=cli_axes())
    dots = [ln for ln in data_lines(ax) if ln.get_marker() == "o"]
    others = [ln for ln in data_lines(ax) if ln.get_marker() in ("None", "", None) or ln.get_linestyle() != "None"]
    assert len(dots) == 5 and others
    assert min(effective_order(ax, d) for d in dots) > max(effective_order(ax, o) for o in others)


def test_ranges_axes_stay_on_the_grid():
    # Table I's 237 µN beyond the grid stretched the axis over a blank, unexplained band
    r = ranges([5.0, 13.2, 34.5], [10.0, 100.0], [[S, S]] * 3, [[[], []]] * 3)
    ax = r.plot(ax=cli_axes())
    lo, hi = ax.get_ylim()
    assert lo == pytest.approx(5.0 / np.sqrt(13.2 / 5.0), rel=1e-6)
    assert hi == pytest.approx(34.5 * np.sqrt(34.5 / 13.2), rel=1e-6)
    assert "1.92" in " ".join(t.get_text() for t in ax.get_legend().get_texts())  # the limits, in words


def test_ranges_ticks_name_the_grid(grid_on_table_i):
    # decade ticks (10^1, 10^2) did not say which load or frequency a row or column is
    ax = grid_on_table_i.plot(ax=cli_axes())
    draw(ax.figure)
    ys = {t.get_text() for t in ax.get_yticklabels() if t.get_visible()}
    xs = {t.get_text() for t in ax.get_xticklabels() if t.get_visible()}
    assert {"1.92", "13.2", "90.3", "237"} <= ys
    assert {"10", "100", "1000", "10000"} <= xs


def test_ranges_dense_grid_tick_labels_apart():
    fps = np.geomspace(10, 3000, 14)
    loads = np.geomspace(1.92, 237, 16)
    r = ranges(loads, fps, [[S] * 14] * 16, [[[]] * 14] * 16)
    for size in ((6.5, 5.0), (4.0, 3.0)):
        ax = r.plot(ax=cli_axes(size))
        assert_tick_labels_apart(ax)
        assert len([t for t in ax.get_xticklabels() if t.get_text()]) >= 3


def test_ranges_each_exclusion_has_its_own_hatch_in_the_legend():
    # Table I and slip-count exclusions shared one hatch and one legend entry
    from design.plots import _cell_edges

    loads, fps = [1.0, 13.2, 90.3], [10.0, 10000.0]
    r = ranges(loads, fps, [[S, N], [S, N], [S, N]],
               [[["table_i"], ["table_i", "camera"]], [[], ["camera"]], [["slip_count"], ["camera"]]])
    ax = r.plot(ax=cli_axes())
    le = _cell_edges(np.array(loads))

    def hatches(i: int, j: int = 0) -> set:
        return {p.get_hatch() for p in ax.patches
                if isinstance(p, Rectangle) and p.get_hatch() and np.isclose(p.get_y(), le[i])
                and np.isclose(p.get_x(), _cell_edges(np.array(fps))[j])}

    def strokes(hs: set) -> set:  # what a hatch draws: 'x' is '/' over '\\'
        return set("".join(hs).replace("x", "/\\").replace("+", "-|"))

    table_only, slip_only, camera = hatches(0), hatches(2), hatches(1, 1)
    assert table_only and slip_only and camera
    assert strokes(table_only).isdisjoint(strokes(slip_only))
    # a cell outside Table I with too few slips shows both hatches: it must not look like camera's
    assert not strokes(camera) <= strokes(table_only | slip_only)
    in_legend = {h.get_hatch() for h in ax.get_legend().legend_handles if getattr(h, "get_hatch", None)}
    assert table_only | slip_only | camera <= in_legend
    assert_legible_legend(ax)


def test_regime_map_legend_names_white_cells():
    # cells never simulated were white without a legend entry
    m = RegimeMap(coating="FOTAS", spring_constant_N_per_m=2.13, stick_speed_m_per_s=0.0, travel_um=20.0,
                  normal_loads_uN=np.array([2.0, 5.0]), step_frequencies_Hz=np.array([10.0, 100.0]),
                  regimes=np.array([[S, N], [C, N]]), n_slips=np.zeros((2, 2), int),
                  mean_slip_um=np.full((2, 2), np.nan), mean_peak_elongation_um=np.full((2, 2), np.nan),
                  wall_time_s=np.zeros((2, 2)))
    ax = plot_regime_map(m, ax=cli_axes())
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["stick-slip", "creep", "not simulated"]
    colours = [to_hex(h.get_facecolor()) for h in ax.get_legend().legend_handles]
    assert len(set(colours)) == len(colours)
    assert_legible_legend(ax)
    assert_tick_labels_apart(ax)


# ------------------------------------------------------------------ experiment plan
FREE = ("mu_max", "mu_min", "tau", "A")
NOMINAL = {"mu_max": 0.796, "mu_min": 0.484, "tau": 0.0674, "A": 0.015, "vc": 1e-6, "dc": 2e-8}


def make_plan(free=FREE, *, monte_carlo=False, reference_nan=()) -> ExperimentPlan:
    rng = np.random.default_rng(0)
    pred = {n: NOMINAL[n] * 10 ** rng.uniform(-3, -1.5) for n in free}
    ref = {n: NOMINAL[n] * 10 ** rng.uniform(-1.5, 1.3) for n in free}
    ref[free[-1]] = NOMINAL[free[-1]] * 20  # the largest error last: where a top-right legend sat
    ref.update({n: float("nan") for n in reference_nan})
    plan = ExperimentPlan(
        coating="FOTAS", criterion="D", free=tuple(free), nominal=NOMINAL,
        plan=[Candidate(2.13, 19.0, 30.0)] * 2 + [Candidate(20.3, 40.4, 100.0)] * 2, predicted_stderr=pred,
        criterion_value=1.0, reference_plan=[Candidate(2.13, 0.98, 10.0)] * 4, reference_stderr=ref,
        reference_criterion_value=0.0,
    )
    if monte_carlo:
        plan.monte_carlo = {"repeats": 10}
        for key, se in (("plan", pred), ("reference", ref)):
            plan.monte_carlo[f"{key}_stderr"] = {n: v * 1.1 for n, v in se.items()}
            plan.monte_carlo[f"{key}_estimates"] = [{}] * 9
    return plan


def test_plan_has_no_bars_on_a_log_axis():
    # bars on a log axis start at an arbitrary bottom: their lengths compare nothing
    ax = make_plan().plot(ax=cli_axes())
    bars = [p for p in ax.patches if isinstance(p, Rectangle)]
    if bars:
        assert ax.get_yscale() == "linear" and ax.get_ylim()[0] <= 0
    assert len([ln for ln in data_lines(ax) if ln.get_marker() not in ("None", "")]) >= 2


@pytest.mark.parametrize("monte_carlo", [False, True])
def test_plan_legend_ticks_and_markers(monte_carlo):
    for ax in (make_plan(monte_carlo=monte_carlo).plot(ax=cli_axes()),
               make_plan(("mu_max", "mu_min", "tau", "A", "vc", "dc"), monte_carlo=monte_carlo).plot()):
        assert_legible_legend(ax)
        assert_tick_labels_apart(ax)
        # no marker on another: centres at least a marker apart
        pts = []
        for ln in data_lines(ax):
            if ln.get_marker() in ("None", "", "_"):
                continue
            xy = ln.get_transform().transform(np.asarray(ln.get_xydata(), float))
            pts += [(p, ln.get_markersize() * ax.figure.dpi / 72) for p in xy if np.all(np.isfinite(p))]
        for (p, s), (q, t) in itertools.combinations(pts, 2):
            assert np.hypot(*(p - q)) >= (s + t) / 2, "two markers overlap"


def test_plan_monte_carlo_carries_its_uncertainty():
    # the measured spreads of 9 fits were drawn as bare points
    ax = make_plan(monte_carlo=True).plot(ax=cli_axes())
    bars = [c for c in ax.containers if isinstance(c, ErrorbarContainer) and c.has_yerr]
    assert len(bars) == 2
    assert any("95" in t.get_text() for t in ax.get_legend().get_texts())


def test_plan_marks_what_cannot_be_determined():
    # a NaN reference error left an empty slot, as if nothing were there to compare
    ax = make_plan(reference_nan=("tau",)).plot(ax=cli_axes())
    assert any("not determined" in t.get_text() for t in ax.texts)


def test_plan_names_parameters_in_words():
    # tick labels were the code names mu_max, mu_min, tau
    ax = make_plan().plot(ax=cli_axes())
    labels = [t.get_text() for t in ax.get_xticklabels()]
    assert "mu_max" not in labels and "tau" not in labels
    assert "aging time" in labels[2] and "τ" in labels[2]

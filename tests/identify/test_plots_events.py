"""Figures of ``analyze`` on the bundled FOTAS runs: a long run as an overview above
zoomed windows, slip marks that leave the frames visible, legends legible and beside the
data, and Fig. 10/11 with confidence bands and the logarithmic law's bound said."""

from pathlib import Path

import numpy as np
import pytest
from matplotlib.collections import PolyCollection

from identify.plots.base import pyplot
from identify.plots.events import ZOOM_SLIPS, plot_events, plot_reduced_fit, plot_reduced_rates
from identify.plots.legibility import legend_covers_data, legend_font_too_small, overlapping_tick_labels
from identify.traces.analyze import analyze

DATA = Path(__file__).resolve().parents[2] / "data" / "FOTAS"
LONG = "FOTAS_k20.3_Nb30uN_fp100Hz"  # 104 slips
SHORT = "FOTAS_k2.13_Nb10uN_fp100Hz"  # 15 slips


@pytest.fixture(scope="module")
def analysis():
    return analyze(DATA)


@pytest.fixture(scope="module")
def events(analysis):
    return {ra.name: ra.events for ra in analysis.runs}


@pytest.fixture
def plt():
    p = pyplot()
    yield p
    p.close("all")


def _as_analyze_does(plt, figsize=(8, 4)):
    """The axes AnalyzeResult.save_plots hands over."""
    fig, ax = plt.subplots(figsize=figsize, constrained_layout=True)
    return ax


def _legend_over_data(ax) -> list:
    """The legend is legible (≥ 7 pt); what of ``ax`` (frames, model, curves, bands) lies under it."""
    assert ax.get_legend() is not None and legend_font_too_small(ax) == []
    return legend_covers_data(ax)


# ----------------------------------------------------------------------------- events
def test_a_long_run_is_an_overview_above_zoomed_windows(events, plt):
    ev = events[LONG]
    assert ev.n_slips > ZOOM_SLIPS
    ax = plot_events(ev, ax=_as_analyze_does(plt))
    fig = ax.figure
    assert len(fig.axes) == 4 and fig.get_size_inches()[1] >= 6  # the figure grew for the windows
    t = ev.trace.time_s
    assert ax.get_xlim() == pytest.approx((t[0], t[-1]))
    ts = ev.slips["trigger_time_s"]
    dt = float(np.median(np.diff(ts)))
    for z in fig.axes[1:]:
        t0, t1 = z.get_xlim()
        assert (t1 - t0) <= 8 * dt  # a few cycles each: the saw-tooth can be read
        assert 4 <= np.sum((ts >= t0) & (ts <= t1)) <= 8
        assert z.get_title(loc="left") in ("(a)", "(b)", "(c)")
    # the windows are shaded in the overview
    assert sum(1 for p in ax.patches if p.get_facecolor()[:3] != (1.0, 1.0, 1.0)) >= 3
    assert overlapping_tick_labels(fig) == []


@pytest.mark.parametrize("name", [LONG, SHORT])
def test_event_legend_is_legible_and_covers_no_frame(events, plt, name):
    ax = plot_events(events[name], ax=_as_analyze_does(plt))
    assert _legend_over_data(ax) == []
    assert overlapping_tick_labels(ax.figure) == []


def test_slip_marks_leave_the_frames_visible(events, plt):
    ax = plot_events(events[SHORT])
    lines = {ln.get_label(): ln for ln in ax.get_lines()}
    slips = next(ln for lab, ln in lines.items() if lab.startswith("slips"))
    assert slips.get_markerfacecolor() == "none"  # an open mark: the frame under it shows
    frames = lines["camera frames"]
    model = lines["staircase model"]
    assert frames.get_zorder() > model.get_zorder()  # the data drawn over the model line


def test_a_window_or_a_short_run_stays_one_panel(events, plt):
    ax = plot_events(events[SHORT])
    assert len(ax.figure.axes) == 1
    ax = plot_events(events[LONG], t_window=(2.0, 2.5))
    assert len(ax.figure.axes) == 1 and ax.get_xlim() == (2.0, 2.5)


# ----------------------------------------------------------------------------- Figs. 10-11
def test_covariance_gives_the_reported_standard_errors(analysis):
    fit = analysis.fit
    for name, f in fit.fits.items():
        names, cov = fit.covariance(name)
        assert names == [p for p in f.parameters if p not in f.at_bounds]
        np.testing.assert_allclose(np.sqrt(np.diag(cov)), [f.stderr[p] for p in names], rtol=1e-4)
    assert fit.fits["logarithmic"].at_bounds == ["t_c"]  # measured: held at 1 µs, the others free


def _bands(ax) -> list:
    return [c for c in ax.collections if isinstance(c, PolyCollection)]


def test_fig10_draws_a_band_per_law_around_its_curve(analysis, plt):
    fit = analysis.fit
    ax = plot_reduced_fit(fit, ax=_as_analyze_does(plt, (6, 4)))
    bands = _bands(ax)
    assert len(bands) == 3  # every law has a covariance here
    curves = [ln for ln in ax.get_lines() if ln.get_linestyle() != "None"]
    for band, curve in zip(bands, curves):
        x, y = curve.get_data()
        path = band.get_paths()[0]
        inside = path.contains_points(np.column_stack([x, y])[5:-5:10], radius=1e-9)
        assert inside.all()
    # the exponential's band at its data is narrow (its parameters are well determined)
    v = bands[0].get_paths()[0].vertices
    t_mid = float(np.median(fit.t_rest_s)) * 1e3
    near = np.abs(np.log(v[:, 0] / t_mid)) < 0.05
    assert np.ptp(v[near, 1]) < 0.02
    # the axis follows the data, not a band of an ill-determined law
    lo, hi = ax.get_ylim()
    assert hi - lo < 0.5


def test_fig10_says_the_logarithmic_law_sits_at_its_bound(analysis, plt):
    ax = plot_reduced_fit(analysis.fit, ax=_as_analyze_does(plt, (6, 4)))
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    log = next(t for t in texts if t.startswith("logarithmic"))
    assert "t_c stuck at its lower bound (1 µs)" in log and "straight line in ln t" in log
    assert any("best by AIC" in t for t in texts if t.startswith("exponential"))
    # the logistic's band is wide: measured mu_min = 0.38 ± 1.4, q0 = 0.44 ± 1.3
    assert "mu_min, q0: error > 100 %" in next(t for t in texts if t.startswith("logistic"))
    assert any("confidence band" in t for t in texts)
    assert _legend_over_data(ax) == []
    assert overlapping_tick_labels(ax.figure) == []


def test_fig11_bands_stay_positive_on_the_log_axis(analysis, plt):
    ax = plot_reduced_rates(analysis.fit, ax=_as_analyze_does(plt, (6, 4)))
    bands = _bands(ax)
    assert len(bands) == 3
    for b in bands:
        v = b.get_paths()[0].vertices
        assert np.all(v[:, 1] > 0)
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    assert any("t_c stuck at its lower bound" in t for t in texts)
    assert _legend_over_data(ax) == []
    assert overlapping_tick_labels(ax.figure) == []

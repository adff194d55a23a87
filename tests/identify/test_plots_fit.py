"""Figures of a fit: the model drawn as the staircase it is, a residual panel, zooms a
long run can be read in, an uncertainty band on the law, and model marks that do not
hide the data."""

import warnings

import numpy as np
import pytest

from identify import SimulationOptions, simulate
from identify.fitting.driver import FitOptions, fit
from identify.plots.base import pyplot
from identify.plots.fit import plot_residuals, plot_run_fit, plot_slip_lengths, plot_static_friction

V_STICK = 1e-5


@pytest.fixture(scope="module")
def fitted():
    """Two runs: a stiff spring with ~60 slips of a few steps each, a soft one with few."""
    runs = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i, (k, nb, fp) in enumerate([(20.3, 30, 100), (2.13, 5, 30)]):
            r = simulate("FOTAS", spring_constant_N_per_m=k, normal_load_uN=nb, step_frequency_Hz=fp,
                         travel_um=12, stick_speed_m_per_s=V_STICK, options=SimulationOptions(record=False))
            runs.append(r.sample(noise_nm=60, seed=10 + i, name=f"run{i}"))
    return fit(runs, options=FitOptions(fixed={"v_stick": V_STICK}))


@pytest.fixture
def close_figures():
    yield
    pyplot().close("all")


def test_staircase_agrees_with_the_model_at_the_frames_and_drops_only_at_triggers(fitted):
    for i, rd in enumerate(fitted.problem.runs):
        t, e = fitted.model_staircase(i)
        assert np.all(np.diff(t) >= 0)
        tf, ef, pof = fitted.model_elongation(i)
        # the staircase held from each of its points (steps-post) at every frame a plateau claims
        j = np.searchsorted(t, tf, side="right") - 1
        ok = pof >= 0
        np.testing.assert_allclose(e[j[ok]], ef[ok], rtol=0, atol=1e-12)
        de = np.diff(e)
        step = float(fitted.problem.model.step(fitted.problem.params(fitted.w[: fitted.problem.n_theta])))
        up = np.isclose(de, step, rtol=1e-9, atol=1e-15)
        flat = np.isclose(de, 0.0, atol=1e-15)  # the last level held to the last frame
        drops = de < 0
        assert np.all(up | flat | drops)
        assert drops.sum() == len(rd.trigger_steps)


def test_run_figure_draws_steps_residuals_and_zooms_on_single_slips(fitted, close_figures):
    rd = fitted.problem.runs[0]
    assert len(rd.trigger_steps) > 30  # a run whose overview alone is a band
    ax, axr, za, zb = plot_run_fit(fitted, 0)
    model = [ln for ln in ax.get_lines() if ln.get_label().startswith("fitted model")]
    assert model and model[0].get_drawstyle() == "steps-post"
    assert "data − model" in axr.get_ylabel()
    # residual points: the frames the plateaus claim, near zero against the noise
    res = axr.get_lines()[0].get_ydata()
    assert np.nanstd(res) < 3 * rd.sigma * 1e9
    t_trig = (np.asarray(rd.trigger_steps) + rd.events.step_phase) / rd.fp
    for z in (za, zb):
        lo, hi = z.get_xlim()
        assert hi - lo <= 24.0 / rd.fp + 1e-9  # steps wide enough to see
        assert 1 <= np.sum((t_trig >= lo) & (t_trig <= hi)) <= 3
        assert any(ln.get_drawstyle() == "steps-post" for ln in z.get_lines())
    assert za.get_xlim()[1] <= zb.get_xlim()[0] + 1e-9  # the two windows do not overlap
    leg = ax.get_legend()
    assert leg is not None and min(t.get_fontsize() for t in leg.get_texts()) >= 7


def test_run_with_one_slip_leaves_the_zooms_blank(fitted, close_figures):
    from identify.plots.fit import _zoom_windows

    assert _zoom_windows(np.array([1.0]), np.linspace(0, 2, 50), np.zeros(50), 100.0) == []


def test_static_friction_law_band_is_the_delta_method_on_the_covariance(fitted):
    prob = fitted.problem
    names = list(prob.theta.names)
    mu, band = fitted.static_friction_curve(np.array([1e3]))
    assert band is not None and band[0, 0] < mu[0] < band[1, 0]
    # at a long rest μs = μmax + A·ln(1 + v_stick/vc): its variance from the covariance
    P = prob.params(fitted.w[: prob.n_theta])
    c = float(np.log1p(P["v_stick"] / P["vc"]))
    g = np.zeros(len(names))
    g[names.index("mu_max")] = 1.0
    g[names.index("A")] = c
    half = 1.959963984540054 * np.sqrt(g @ fitted.covariance @ g)
    assert half > 0
    np.testing.assert_allclose((band[1, 0] - band[0, 0]) / 2, half, rtol=1e-3)


def test_static_friction_figure_shows_the_band_and_a_legible_legend(fitted, close_figures):
    from matplotlib.collections import PolyCollection

    ax = plot_static_friction(fitted)
    assert any(isinstance(c, PolyCollection) for c in ax.collections)  # the 95 % band
    assert "static friction coefficient" in ax.get_ylabel()
    leg = ax.get_legend()
    assert min(t.get_fontsize() for t in leg.get_texts()) >= 7
    assert any("95 %" in t.get_text() for t in leg.get_texts())


def test_slip_drop_figure_keeps_data_above_model_and_joins_no_runs(fitted, close_figures):
    ax, axd = plot_slip_lengths(fitted)
    model = [ln for ln in ax.get_lines() if ln.get_markerfacecolor() == "none"]
    assert len(model) == 2 and all(len(ln.get_xdata()) == 1 for ln in model)  # no line across runs
    data_z = [c.lines[0].get_zorder() for c in ax.containers]  # the data marks of the error bars
    assert data_z and min(data_z) > max(ln.get_zorder() for ln in model)
    assert ax.get_ylim()[0] == 0
    assert "data − model" in axd.get_ylabel() and len(axd.containers) == 2


def test_residual_figure_names_every_run(fitted, close_figures):
    axes = plot_residuals(fitted)
    fig = axes[0].figure
    texts = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
    for rd in fitted.problem.runs:
        assert any(f"k = {rd.k:g} N/m" in t and f"fp = {rd.fp:g} Hz" in t for t in texts)


def test_profile_figure_shows_units_interval_and_the_stderr_parabola(close_figures):
    from identify.fitting.result import ParameterEstimate, Profile
    from identify.plots.fit import plot_profile

    v = np.linspace(0.06, 0.07, 7)
    pr = Profile(name="tau", values=v, delta_chi2=((v - 0.065) / 0.002) ** 2, ci95=(0.0611, 0.0689), flat=False,
                 threshold=3.84)
    est = ParameterEstimate(name="tau", value=0.065, stderr=0.004, ci95=None, free=True, unit="s")
    ax = plot_profile(pr, estimate=est)
    assert ax.get_xlabel() == "tau (s)"
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert any("parabola" in t for t in labels) and any("[0.0611, 0.0689]" in t for t in labels)
    assert ax.get_ylim()[1] >= 3.84

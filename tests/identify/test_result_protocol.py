"""One result protocol: report(), to_dict()/from_dict() through strict JSON, save()/load()
and plot(ax=None), for the diagnosis, the profile and the regime map (the fit's own
round trip is tested with the fit)."""

import warnings

import numpy as np
import pytest

import identify
from identify import SimulationOptions, simulate
from identify.diagnosis.result import DiagnosisResult
from identify.fitting.estimates import Profile
from identify.plots.base import pyplot
from identify.simulation.regimes import RegimeMap, regime_map


@pytest.fixture(scope="module")
def small_fit():
    runs = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i, (k, nb, fp) in enumerate([(2.13, 5, 100), (20.3, 30, 30), (2.13, 10, 100)]):
            r = simulate("FOTAS", spring_constant_N_per_m=k, normal_load_uN=nb, step_frequency_Hz=fp, travel_um=10,
                         stick_speed_m_per_s=1e-5, options=SimulationOptions(record=False))
            runs.append(r.sample(noise_nm=90, seed=20 + i, name=f"r{i}"))
    return identify.fit(runs, options=identify.FitOptions(fixed={"v_stick": 1e-5}), progress=False)


@pytest.fixture
def close_figures():
    yield
    pyplot().close("all")


def _round_trip(result, cls, path, strict_json):
    result.save(path)
    strict_json(path)  # (no NaN or Infinity in the file)
    back = cls.load(path)
    assert back.to_dict() == result.to_dict()
    assert back.report() == result.report()
    return back


def test_diagnosis_reads_back_with_its_report_and_figure(small_fit, tmp_path, strict_json, close_figures):
    diag = identify.diagnose(None, baseline=small_fit, progress=False,
                             options=identify.DiagnosisOptions(effects=("drift",), workers=1))
    back = _round_trip(diag, DiagnosisResult, tmp_path / "d.json", strict_json)
    assert "gap (held out)" in back.report()  # (the current model's measurements came back too)
    assert back.plot().get_xlabel() == diag.plot().get_xlabel()
    assert back.baseline.parameters["mu_max"].value == diag.baseline.parameters["mu_max"].value


def test_profile_reads_back(small_fit, tmp_path, strict_json, close_figures):
    pr = small_fit.profile("tau", n_points=3, progress=False)
    back = _round_trip(pr, Profile, tmp_path / "p.json", strict_json)
    assert "Profile likelihood of tau" in back.report() and back.plot() is not None
    np.testing.assert_array_equal(back.values, pr.values)


def test_regime_map_reads_back_whole(tmp_path, strict_json, close_figures):
    m = regime_map("FOTAS", 2.13, [5, 20], [100], None, 1e-5, progress=False)
    back = _round_trip(m, RegimeMap, tmp_path / "m.json", strict_json)
    np.testing.assert_array_equal(back.regimes, m.regimes)
    np.testing.assert_allclose(back.mean_peak_elongation_um, m.mean_peak_elongation_um)
    assert back.plot() is not None and "Regime map" in back.report()


def test_fit_result_plot_draws_the_headline_figure(small_fit, close_figures):
    ax = small_fit.plot()
    assert "static friction" in ax.get_ylabel()
    with pytest.raises(ValueError, match="no fitted problem"):
        type(small_fit).from_dict(small_fit.to_dict()).plot()


def test_analysis_plot_draws_fig10(close_figures):
    from pathlib import Path

    res = identify.analyze([str(Path(__file__).resolve().parents[2] / "data" / "FOTAS")])
    ax = res.plot()
    assert "static friction" in ax.get_ylabel()
    assert res.to_dict() == res.to_json() and res.report().startswith("Analysis of")

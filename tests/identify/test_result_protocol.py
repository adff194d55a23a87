"""One result protocol: report(), to_dict()/from_dict() through strict JSON, save()/load()
and plot(ax=None), for the diagnosis, the profile, the regime map, the analysis and the
simulation (the fit's own round trip is tested with the fit); what a file does not keep
(an analysis's frames) is asked for with a clear error."""

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from matplotlib.axes import Axes

import identify
from identify import SimulationOptions, simulate
from identify.diagnosis.result import DiagnosisResult
from identify.fitting.estimates import Profile
from identify.plots.base import pyplot
from identify.simulation.regimes import RegimeMap, regime_map
from identify.simulation.result import SimulationResult
from identify.traces.analyze import AnalyzeResult, RunAnalysis
from identify.traces.io import load_traces

DATA = Path(__file__).resolve().parents[2] / "data" / "FOTAS"
RUNS = ("FOTAS_k2.13_Nb10uN_fp100Hz", "FOTAS_k20.3_Nb30uN_fp100Hz")


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
    on_disk = strict_json(path)  # (no NaN or Infinity in the file)
    assert on_disk == result.to_dict()
    back = cls.load(path)
    assert back.to_dict() == result.to_dict()
    assert cls.from_dict(result.to_dict()).to_dict() == result.to_dict()
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


# ----------------------------------------------------------------------------- analysis
@pytest.fixture(scope="module")
def analysis(tmp_path_factory):
    """Two runs, a file refused and a run whose extraction failed."""
    folder = tmp_path_factory.mktemp("runs")
    for name in RUNS:
        for ext in (".csv", ".json"):
            shutil.copy(DATA / (name + ext), folder)
    (folder / "bad.csv").write_text("a,b\n1,2\n", encoding="utf-8")
    res = identify.analyze(folder)
    failed = load_traces(DATA / (RUNS[0] + ".csv")).traces[0]
    res.runs.append(RunAnalysis(failed, None, False, "event extraction failed: ValueError: test"))
    return res


def test_analysis_reads_back_with_its_report_and_fig10(analysis, tmp_path, strict_json, close_figures):
    assert analysis.refused and analysis.fit is not None
    back = _round_trip(analysis, AnalyzeResult, tmp_path / "a.json", strict_json)
    assert "refused:" in back.report() and "extraction failed" in back.report()
    fit, fit2 = analysis.fit, back.fit
    assert fit2.best == fit.best and fit2.used == fit.used and fit2.source == fit.source
    np.testing.assert_array_equal(fit2.t_rest_s, fit.t_rest_s)
    np.testing.assert_array_equal(fit2.mu_s, fit.mu_s)
    assert fit2.fits.keys() == fit.fits.keys()
    for name, f in fit.fits.items():
        assert fit2.fits[name].parameters == f.parameters and fit2.fits[name].converged == f.converged
    assert [r.to_json() for r in fit2.runs] == [r.to_json() for r in fit.runs]
    ax = back.plot()
    assert "static friction" in ax.get_ylabel()
    assert len(ax.get_lines()) == len(analysis.plot().get_lines())
    assert [ra.regime for ra in back.runs] == [ra.regime for ra in analysis.runs]
    assert back.runs[-1].events is None and back.runs[0].read_back and not analysis.runs[0].read_back


def test_an_analysis_read_back_says_what_it_does_not_keep(analysis, tmp_path):
    back = AnalyzeResult.from_dict(analysis.to_dict())
    ra = back.runs[0]
    assert ra.trace.spring_constant == analysis.runs[0].trace.spring_constant and len(ra.trace) > 0
    with pytest.raises(AttributeError, match="read from JSON.*analyze"):
        ra.trace.time_s  # noqa: B018
    with pytest.raises(AttributeError, match="read from JSON"):
        ra.events.slips  # noqa: B018
    with pytest.raises(ValueError, match="read from JSON"):
        back.save_plots(tmp_path / "plots")
    assert not (tmp_path / "plots").exists()


def test_an_undetermined_law_fit_reads_back_as_nulls(tmp_path, strict_json):
    one = identify.analyze(DATA / (RUNS[0] + ".csv"))
    assert one.fit.best is None  # (one run for three parameters: NaN standard errors, R²)
    back = _round_trip(one, AnalyzeResult, tmp_path / "one.json", strict_json)
    assert np.isnan(back.fit.fits["exponential"].r2)


def test_an_analysis_without_runs_reads_back(tmp_path, strict_json):
    (tmp_path / "bad.csv").write_text("a,b\n1,2\n", encoding="utf-8")
    res = identify.analyze(tmp_path)
    assert res.fit is None and res.refused
    back = _round_trip(res, AnalyzeResult, tmp_path / "none.json", strict_json)
    assert back.fit is None and back.runs == []


# ----------------------------------------------------------------------------- simulation
@pytest.fixture(scope="module")
def run():
    return simulate("FOTAS", spring_constant_N_per_m=2.13, normal_load_uN=10, step_frequency_Hz=100, travel_um=8,
                    stick_speed_m_per_s=1e-5)


def test_simulation_reads_back_whole(run, tmp_path, strict_json, close_figures):
    assert len(run.slips) >= 2 and run.phases
    back = _round_trip(run, SimulationResult, tmp_path / "s.json", strict_json)
    assert back.regime == run.regime and back.coating == run.coating == "FOTAS"
    assert back.conditions == run.conditions and back.options == run.options
    assert back.model.law.name == run.model.law.name
    t = np.linspace(0, run.conditions.end_time, 777)
    for what in ("block_position", "elongation", "state_at", "velocity"):
        np.testing.assert_array_equal(getattr(back, what)(t), getattr(run, what)(t))
    tr, tr2 = run.sample(noise_nm=50, seed=3), back.sample(noise_nm=50, seed=3)
    np.testing.assert_array_equal(tr2.elongation, tr.elongation)
    assert "slips" in back.report() and "ms)" in back.report().splitlines()[1]


def test_simulation_plot(run, close_figures):
    axes = run.plot()
    assert len(axes) == 5 and axes[4].get_xlabel() == "time (ms)"
    back = SimulationResult.from_dict(json.loads(json.dumps(run.to_dict(), allow_nan=False)))
    assert len(back.plot()) == 5
    _, ax = pyplot().subplots()
    out = back.plot(ax=ax)
    assert isinstance(out, Axes) and out is ax and "elongation" in ax.get_ylabel()


@pytest.mark.parametrize("travel_um", [0.2, 6])
def test_simulation_without_phases_or_slips_reads_back(travel_um, tmp_path, strict_json):
    r = simulate("FOTAS", spring_constant_N_per_m=2.13, normal_load_uN=10, step_frequency_Hz=100,
                 travel_um=travel_um, options=SimulationOptions(record=False))
    back = _round_trip(r, SimulationResult, tmp_path / "s.json", strict_json)
    assert back.phases == [] and len(back.events) == len(r.events)
    assert back.events["step_index"].dtype == r.events["step_index"].dtype

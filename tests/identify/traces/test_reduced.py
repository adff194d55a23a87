"""The paper's reduced analysis: σ·√12 per run (MODEL.md "Reduced relations", Eq. 8) and
the Eq. 9 / Fig. 10 law comparison, checked on closed forms and simulated sweeps."""

import json
import math

import numpy as np
import pytest

from identify import simulate
from identify.model.laws import get_law
from identify.traces.analyze import analyze
from identify.traces.events import extract_events
from identify.traces.reduced import ReducedRun, fit_law_curve, reduced_fit, reduced_run

K = 2.13
STEP = 46e-9
FOTAS = dict(mu_max=0.796, mu_min=0.484, tau=0.0674, A=0.015, vc=1e-6)
V_STICK = 1e-5
# With the stick band the static threshold is F0(ψ, v_stick) = ψ + A·ln(1 + v_stick/vc)
# (params.py, v_stick): the saturated μs the reduced analysis sees.
MU_SAT = FOTAS["mu_max"] + FOTAS["A"] * math.log(1 + V_STICK / FOTAS["vc"])

# (Nb in µN, fp in Hz) at k = 2.13 N/m: stick-slip with rests from 0.1 s (≈ 1.5 τ) to 2 s.
# Shorter rests are not reachable in stick-slip with this model: at fp = 300 Hz and
# Nb = 5 µN (and wherever the rest would fall below ~1.5 τ) the run creeps or steps.
SWEEP = [
    (2, 10),
    (2, 30),
    (2, 60),
    (3, 10),
    (3, 30),
    (3, 60),
    (5, 10),
    (5, 30),
    (5, 100),
    (10, 100),
    (10, 200),
]


def _sim(nb, fp, travel=20):
    return simulate(
        "FOTAS",
        spring_constant_N_per_m=K,
        normal_load_uN=nb,
        step_frequency_Hz=fp,
        travel_um=travel,
        stick_speed_m_per_s=V_STICK,
    )


@pytest.fixture(scope="module")
def sweep_sims():
    return [_sim(nb, fp) for nb, fp in SWEEP]


@pytest.fixture(scope="module")
def run5():
    return _sim(5, 100, travel=30)


# ----------------------------------------------------------------------------- per run
def test_sqrt12_on_clean_sawtooth(run5):
    tr = run5.sample(noise_nm=0)
    r = reduced_run(tr, extract_events(tr))
    s = run5.slips
    mean_slip = s["slip_length_m"][1:].mean()
    assert r.slip_sqrt12_m == pytest.approx(mean_slip, rel=0.03)
    assert r.slip_sqrt12_corrected_m == pytest.approx(r.slip_sqrt12_m, rel=1e-6)
    assert r.mean_slip_m == pytest.approx(mean_slip, rel=1e-9)
    # Eq. 8: rest = δ̄/(fp·Δxp), against the trigger-to-trigger rests
    assert r.rest_time_sqrt12_s == pytest.approx(r.mean_rest_time_s, rel=0.03)
    # e_peak = ē + δ̄/2 sits half a step below the elongation after the trigger step
    k_over_nb = K / 5e-6
    assert r.mean_peak_elongation_m == pytest.approx(s["peak_elongation_m"][1:].mean(), rel=1e-9)
    assert r.mu_s_events == pytest.approx(k_over_nb * r.mean_peak_elongation_m)
    assert r.mu_s_events_mid == pytest.approx(k_over_nb * (r.mean_peak_elongation_m - STEP / 2))
    assert r.mu_s_sqrt12 == pytest.approx(r.mu_s_events_mid, abs=0.01)
    assert r.n_slips == len(s)
    assert r.frames_used < len(tr)  # loading ramp and last partial cycle left out


def test_noise_correction_of_sqrt12(run5):
    errs_raw, errs_c = [], []
    for seed in range(3):
        ev = extract_events(run5.sample(noise_nm=90, seed=seed))
        r = ev.reduced
        truth = run5.slips["slip_length_m"][1:].mean()
        assert r.std_elongation_m**2 == pytest.approx(r.slip_sqrt12_m**2 / 12)
        assert r.slip_sqrt12_corrected_m == pytest.approx(
            math.sqrt(12 * (r.std_elongation_m**2 - ev.noise_m**2))
        )
        errs_raw.append(r.slip_sqrt12_m / truth - 1)
        errs_c.append(r.slip_sqrt12_corrected_m / truth - 1)
    assert np.mean(errs_raw) > 0.04  # noise inflates σ·√12 by √(1 + 12σ²/δ²) ≈ 7 %
    assert abs(np.mean(errs_c)) < 0.03


def test_reduced_run_without_events_and_json(run5):
    tr = run5.sample(noise_nm=90, seed=2)
    r = reduced_run(tr, extract_events(tr))
    r2 = extract_events(tr).reduced
    assert r.to_json() == r2.to_json()
    d = json.loads(json.dumps(r.to_json()))
    assert d["regime"] == "stick-slip" and d["spring_constant_N_per_m"] == K
    assert r.usable
    t, mu = r.point("events")
    assert (t, mu) == (r.mean_rest_time_s, r.mu_s_events_mid)
    with pytest.raises(ValueError, match="source"):
        r.point("bogus")


# ----------------------------------------------------------------------------- law fits
@pytest.mark.parametrize(
    "law, theta",
    [
        ("exponential", [0.8, 0.5, 0.07]),
        ("logarithmic", [0.5, 0.03, 0.002]),
        ("logistic", [0.8, 0.5, 0.05, 0.05]),
    ],
)
def test_fit_law_curve_recovers_exact_curves(law, theta):
    t = np.logspace(-3, 1, 12)
    mu = get_law(law).static_curve(t, theta)
    f = fit_law_curve(law, t, mu)
    assert f.converged, f.message
    np.testing.assert_allclose(list(f.parameters.values()), theta, rtol=1e-4)
    assert f.r2 == pytest.approx(1.0, abs=1e-9)
    assert f.n == 12 and f.k == len(theta)


def test_aic_picks_the_generating_law():
    rng = np.random.default_rng(3)
    t = np.logspace(-2.5, 0.5, 15)
    for law, theta in (("exponential", [0.8, 0.5, 0.07]), ("logarithmic", [0.5, 0.03, 0.002])):
        mu = get_law(law).static_curve(t, theta) + rng.normal(0, 0.003, t.size)
        runs = [_fake_run(ti, mi) for ti, mi in zip(t, mu)]
        fit = reduced_fit(runs)
        assert fit.best == law
        f = fit.fits[law]
        for p, v in zip(f.parameters, theta):  # recovery within 4 standard errors
            assert abs(f.parameters[p] - v) < 4 * f.stderr[p] + 1e-9


def _fake_run(t_rest, mu_s, regime="stick-slip", nb=5e-6):
    nan = math.nan
    return ReducedRun(
        name=f"t{t_rest:.4g}",
        mean_elongation_m=nan,
        std_elongation_m=nan,
        slip_sqrt12_m=nan,
        slip_sqrt12_corrected_m=nan,
        peak_sqrt12_m=nan,
        mu_s_sqrt12=nan,
        rest_time_sqrt12_s=nan,
        peak_sqrt12_corrected_m=nan,
        mu_s_sqrt12_corrected=nan,
        rest_time_sqrt12_corrected_s=nan,
        mean_slip_m=nan,
        mean_peak_elongation_m=nan,
        mu_s_events=nan,
        mean_rest_time_s=t_rest,
        mu_s_events_mid=mu_s,
        n_slips=10,
        frames_used=100,
        noise_m=90e-9,
        spring_constant=K,
        normal_load=nb,
        step_frequency=100.0,
        step_size=STEP,
        coating="FOTAS",
        regime=regime,
    )


def test_too_few_runs_are_flagged_not_fatal():
    runs = [
        _fake_run(0.1, 0.75),
        _fake_run(0.5, 0.8),
        _fake_run(2.0, 0.82),
        _fake_run(0.01, 0.6, regime="unresolved"),
    ]
    fit = reduced_fit(runs)
    assert fit.used == [True, True, True, False]
    for f in fit.fits.values():  # 3 points, ≥ 3 parameters
        assert not f.converged and "undetermined" in f.message
        assert all(math.isnan(v) for v in f.stderr.values())
    assert fit.best is None
    assert "undetermined" in fit.report()
    json.dumps(fit.to_json())
    empty = reduced_fit([])
    assert empty.best is None and all(f.n == 0 for f in empty.fits.values())


def test_paper_fp_sweep_at_5uN_is_undetermined():
    """The brief's sweep (Nb = 5 µN, fp = 10, 30, 100, 300 Hz) gives only 3 stick-slip
    runs: at 300 Hz the block creeps (1-step slips of ~50 nm, rest ≈ 3 ms), and the
    two runs at 10 and 30 Hz rest ≫ τ. Three points cannot fix three parameters; the
    fit says so rather than inventing them."""
    runs = [
        extract_events(_sim(5, fp).sample(noise_nm=90, seed=1)).reduced for fp in (10, 30, 100, 300)
    ]
    assert [r.regime for r in runs] == ["stick-slip"] * 3 + ["unresolved"]
    fit = reduced_fit(runs)
    assert sum(fit.used) == 3
    assert not fit.fits["exponential"].converged
    assert fit.best is None


@pytest.mark.parametrize("seed", [1, 4])
def test_sweep_recovers_exponential_aging(sweep_sims, seed):
    runs = [extract_events(r.sample(noise_nm=90, seed=seed)).reduced for r in sweep_sims]
    assert all(r.regime == "stick-slip" for r in runs)
    for source in ("events", "sqrt12"):
        fit = reduced_fit(runs, source=source)
        assert fit.best == "exponential", fit.report()
        e = fit.fits["exponential"]
        assert e.converged and e.r2 > 0.7
        assert abs(e.parameters["mu_max"] - FOTAS["mu_max"]) < 0.05
        assert abs(e.parameters["mu_max"] - MU_SAT) < 0.02
        assert abs(e.parameters["mu_max"] - MU_SAT) < 3 * e.stderr["mu_max"] + 0.005
        assert e.parameters["tau"] == pytest.approx(FOTAS["tau"], rel=0.35)
        dA = fit.delta_aic()
        assert dA["logarithmic"] > 4
        # the logistic curve's tail is the exponential: same fit, one parameter more
        assert dA["logistic"] == pytest.approx(2.0, abs=0.5)


def test_reduced_fit_report_json_and_plots(sweep_sims):
    runs = [extract_events(r.sample(noise_nm=90, seed=1)).reduced for r in sweep_sims]
    fit = reduced_fit(runs)
    rep = fit.report()
    for law in ("exponential", "logarithmic", "logistic"):
        assert law in rep
    assert "<- best" in rep
    d = json.loads(json.dumps(fit.to_json()))
    assert d["best"] == "exponential" and d["fits"]["exponential"]["delta_aic"] == 0.0
    import matplotlib.pyplot as plt

    ax = fit.plot()
    assert ax.get_xscale() == "log" and len(ax.lines) == 4  # points + 3 curves
    plt.close(ax.figure)
    ax = fit.plot_rates()
    assert ax.get_yscale() == "log"
    plt.close(ax.figure)
    e = fit.fits["exponential"]
    t = np.array([0.05, 0.2])
    p = e.parameters
    exact = (p["mu_max"] - p["mu_min"]) / p["tau"] * np.exp(-t / p["tau"])
    np.testing.assert_allclose(e.rate(t), exact, rtol=1e-6)


# ----------------------------------------------------------------------------- analyze
def test_analyze_a_data_set(tmp_path, sweep_sims, monkeypatch):
    data = tmp_path / "data"
    for (nb, fp), r in zip(SWEEP[:6], sweep_sims[:6]):
        r.sample(noise_nm=90, seed=1, name=f"nb{nb}_fp{fp}").write(data / f"nb{nb}_fp{fp}")
    (data / "broken.csv").write_text("time_s,elongation_um\n0,1\n0,2\n")
    (data / "broken.json").write_text('{"format": "nanofrictor-trace/1"}')

    import importlib

    # the module, not the function of the same name that the package exports
    an = importlib.import_module("identify.traces.analyze")

    real = an.extract_events

    def flaky(trace, **kw):
        if trace.name == "nb3_fp10":
            raise RuntimeError("camera lost track")
        return real(trace, **kw)

    monkeypatch.setattr(an, "extract_events", flaky)
    res = analyze(data, plots_dir=tmp_path / "plots")
    assert len(res.runs) == 6
    assert [f for f, _ in res.refused] == [str(data / "broken.json")]
    bad = next(ra for ra in res.runs if ra.name == "nb3_fp10")
    assert bad.events is None and not bad.used and "camera lost track" in bad.reason
    assert sum(ra.used for ra in res.runs) == 5
    d = json.loads(json.dumps(res.to_json()))
    assert set(d) >= {"runs", "law_fits", "best_law", "refused"}
    run = d["runs"][0]
    assert set(run) >= {
        "name",
        "regime",
        "n_slips",
        "noise_nm",
        "step_phase",
        "reduced",
        "used",
        "reason",
    }
    assert d["refused"][0]["reason"]
    assert set(d["law_fits"]) == {"exponential", "logarithmic", "logistic"}
    rep = res.report()
    assert "extraction failed" in rep and "refused" in rep
    pngs = sorted(p.name for p in (tmp_path / "plots").glob("*.png"))
    assert "fig10_static_friction.png" in pngs and "fig11_aging_rates.png" in pngs
    assert sum(p.startswith("events_") for p in pngs) == 5

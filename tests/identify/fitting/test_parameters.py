"""Parameters declared lmfit-style (value, vary, min, max) become the fit's options."""

import warnings

import pytest

import identify
from identify import FitOptions, Parameters
from identify.model.params import ParameterError


def test_a_preset_varies_the_default_four_and_declares_nothing_else():
    p = Parameters.preset("FOTAS")
    assert [n for n, q in p.items() if q.vary] == ["mu_max", "mu_min", "tau", "A"]
    assert p.options() == dict(free=("mu_max", "mu_min", "tau", "A"), start={}, fixed={}, bounds={})
    assert p["tau"].value == pytest.approx(identify.parameter_set("FOTAS")["tau"])
    assert "tau " in str(p) and "(varies, bounds [" in str(p)


def test_set_gives_start_bounds_and_fixed_values_as_fit_options():
    p = Parameters.preset("OTS", vary=("mu_max", "tau"))
    p["tau"].set(value=0.05, min=1e-3, max=1.0)
    p["v_stick"].set(value=1e-5, vary=False)
    p["A"].set(vary=True, max=0.1)
    p.add("load_offset", 1e-7, min=-1e-6, max=1e-6)
    opts = p.options()
    assert set(opts["free"]) == {"mu_max", "tau", "A", "load_offset"}
    assert opts["start"] == {"tau": 0.05, "load_offset": 1e-7}
    assert opts["fixed"] == {"v_stick": 1e-5}
    assert opts["bounds"]["tau"] == (1e-3, 1.0) and opts["bounds"]["A"][1] == 0.1
    fo = FitOptions(**opts)  # (what fit(params=...) builds: FitOptions checks it too)
    assert fo.fixed == {"v_stick": 1e-5} and p.coating == "OTS"


def test_bad_declarations_are_refused_with_the_parameter_named():
    p = Parameters.preset()
    with pytest.raises(KeyError, match="no parameter 'taus'; these are mu_max"):
        p["taus"]
    with pytest.raises(ParameterError, match="tau: min = 1 must be below max = 0.1"):
        p["tau"].set(min=1.0, max=0.1)
    with pytest.raises(ParameterError, match="vary = 'yes' must be True or False"):
        p["tau"].set(vary="yes")
    with pytest.raises(ParameterError, match="vary: tauu not among"):
        Parameters.preset(vary=("tauu",))
    for name in list(p):
        p[name].vary = False
    with pytest.raises(ParameterError, match="no parameter varies"):
        p.options()
    with pytest.raises(TypeError, match="params must be identify.Parameters"):
        identify.fit([], params={"tau": 0.05})


def test_a_fit_takes_its_parameters_and_coating_from_them():
    """One short FOTAS run: the fit with ``params`` is the fit with the options they
    declare (same free set, fixed stick option, same χ²), its coating the preset's."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run = identify.simulate("FOTAS", spring_constant_N_per_m=20.3, normal_load_uN=30, step_frequency_Hz=100,
                                travel_um=8, stick_speed_m_per_s=1e-5).sample(noise_nm=90, seed=3, name="r")
        p = Parameters.preset("FOTAS", vary=("mu_max", "A"))
        p["v_stick"].set(value=1e-5, vary=False)
        a = identify.fit([run], params=p, options=FitOptions(threads=1, auto_starts=0), progress=False)
        b = identify.fit([run], coating="FOTAS", options=FitOptions(free=("mu_max", "A"), fixed={"v_stick": 1e-5},
                                                                    threads=1, auto_starts=0), progress=False)
    assert list(a.parameters) == list(b.parameters) and a.chi2 == pytest.approx(b.chi2, rel=1e-9)
    assert a.parameters["v_stick"].value == 1e-5 and not a.parameters["v_stick"].free


def test_a_prior_is_declared_on_a_parameter_and_reaches_the_options():
    p = Parameters.preset("FOTAS")
    p.add("drift_rate", 0.0, prior=5e-8)
    p["tau"].set(prior=0.5)
    assert p.options()["priors"] == {"tau": 0.5, "drift_rate": 5e-8}
    assert "prior sd 5e-08 m/s" in str(p)
    from identify.fitting.parameters import merged_options

    assert merged_options(FitOptions(), p).priors == {"tau": 0.5, "drift_rate": 5e-8}
    assert "priors" not in Parameters.preset("FOTAS").options()  # (a FitOptions' own priors then stay)
    kept = merged_options(FitOptions(free=("mu_max", "tau"), priors={"tau": 0.1}), Parameters.preset("FOTAS"))
    assert kept.priors == {"tau": 0.1}
    with pytest.raises(ParameterError, match="drift_rate: prior = -1 must be a standard deviation > 0, in m/s"):
        p["drift_rate"].set(prior=-1)

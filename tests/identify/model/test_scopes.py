"""Per-run and per-device parameters: their names, specs, and the candidates built on them."""

from types import SimpleNamespace

import pytest

from identify.model.effects import get_effect
from identify.model.params import ParameterError, spec
from identify.model.scopes import device_label, parse, resolve, run_scope_value, scoped


def _run(name, k, device="", kind="events"):
    return SimpleNamespace(name=name, k=k, device=device, kind=kind)


def test_names_round_trip_and_bad_names_say_the_rule():
    name = scoped("drift_rate", "run", "r1")
    assert name == "drift_rate@run:r1"
    assert parse(name) == ("drift_rate", "run", "r1")
    assert parse("mu_max") == ("mu_max", None, None)
    assert parse("drift_rate@run") == ("drift_rate", "run", None)  # one for every run
    with pytest.raises(ValueError, match="cannot take a per-run"):
        parse("mu_max@run:r1")
    with pytest.raises(ValueError, match="write a scoped parameter as"):
        parse("drift_rate@lab:r1")
    with pytest.raises(ValueError, match="write a scoped parameter as"):
        parse("drift_rate@run:")
    with pytest.raises(ValueError, match="without ','"):
        scoped("k_scale", "device", "a,b")


def test_a_scoped_name_has_its_base_parameters_unit_bounds_and_scale():
    s, b = spec("k_scale@device:k20.3"), spec("k_scale")
    assert (s.unit, s.lower, s.upper, s.scale, s.log) == (b.unit, b.lower, b.upper, b.scale, b.log)
    assert s.name == "k_scale@device:k20.3" and "device k20.3" in s.description
    with pytest.raises(ParameterError, match="cannot take a per-run"):
        spec("tau@run:r1")
    with pytest.raises(ParameterError, match="must lie in"):
        spec("k_scale@device:k20.3").check(50.0)


def test_a_run_value_wins_over_a_device_value_over_the_global_one():
    values = {"drift_rate": 1.0, "drift_rate@device:d": 2.0, "drift_rate@run:r1": 3.0, "mu_max": 0.7}
    assert run_scope_value(values, "drift_rate", "r1", "d") == 3.0
    assert run_scope_value(values, "drift_rate", "r2", "d") == 2.0
    assert run_scope_value(values, "drift_rate", "r2", "e") == 1.0
    seen = resolve(values, "r2", "d")
    assert seen == {"drift_rate": 2.0, "mu_max": 0.7}
    # a scoped value without its global one in the values: elsewhere the caller's default
    assert resolve({"k_scale@device:d": 1.2}, "r", "e") == {}
    assert resolve({"k_scale@device:d": 1.2}, "r", "d") == {"k_scale": 1.2}


def test_a_runs_device_is_its_trace_field_else_its_spring():
    assert device_label("chip3-a", 2.13) == "chip3-a"
    assert device_label(None, 2.13) == "k2.13"
    assert device_label("", 20.3) == "k20.3"


def test_per_run_drift_binds_one_rate_per_run_fitted_by_its_frames():
    runs = [_run("a", 2.13), _run("b", 2.13), _run("c", 20.3, kind="creep")]
    eff = get_effect("drift_per_run", runs)
    assert eff.parameters == ("drift_rate@run:a", "drift_rate@run:b")  # the creep run's level shows no drift
    assert eff.null_values({}) == {"drift_rate@run:a": 0.0, "drift_rate@run:b": 0.0}
    assert eff.bounds["drift_rate@run:a"] == get_effect("drift").bounds["drift_rate"]
    assert eff.applicable(("mu_max", "mu_min"), "exponential") is None
    # beside a global drift (and the global one beside per-run rates): the same residuals twice
    assert "another scope" in eff.applicable(("mu_max", "drift_rate"), "exponential")
    assert "another scope" in get_effect("drift").applicable(("mu_max", "drift_rate@run:a"), "exponential")
    # unbound, the library's entry is untouched
    assert get_effect("drift_per_run").parameters == ("drift_rate",)


def test_per_device_spring_constant_keeps_the_device_with_most_runs_as_reference():
    runs = [_run("a", 2.13), _run("b", 2.13), _run("c", 20.3), _run("d", 0.5, device="chip9")]
    eff = get_effect("spring_constant_per_device", runs)
    assert eff.reference_label == "k2.13"
    assert eff.parameters == ("k_scale@device:k20.3", "k_scale@device:chip9")
    assert eff.null_values({}) == {"k_scale@device:k20.3": 1.0, "k_scale@device:chip9": 1.0}
    assert eff.applicable(("mu_max",), "exponential") is None


def test_per_device_spring_constant_on_one_spring_is_confounded_never_fitted():
    eff = get_effect("spring_constant_per_device", [_run("a", 2.13), _run("b", 2.13)])
    assert eff.parameters == ()
    why = eff.applicable(("mu_max", "mu_min", "tau", "A"), "exponential")
    assert why is not None and "one device only (k2.13)" in why and "absorb" in why
    # a load offset per device has no reference, but one device's own offset is the
    # global one: the same refit twice, which would tie and name neither
    lo = get_effect("load_offset_per_device", [_run("a", 2.13), _run("b", 2.13)])
    assert lo.parameters == ("load_offset@device:k2.13",)
    assert "the same as the global candidate load_offset" in lo.applicable(("mu_max",), "exponential")
    one = get_effect("drift_per_run", [_run("a", 2.13), _run("b", 2.13, kind="creep")])
    assert "one run fitted by its frames only" in one.applicable(("mu_max",), "exponential")
    none = get_effect("drift_per_run", [_run("b", 2.13, kind="creep")])
    assert "no run fitted by its frames" in none.applicable(("mu_max",), "exponential")
    # names a list or a scoped name would misread are read with '_'
    odd = get_effect("drift_per_run", [_run("run@25C", 2.13), _run("a,b", 2.13)])
    assert odd.parameters == ("drift_rate@run:run_25C", "drift_rate@run:a_b")
    assert run_scope_value({"drift_rate": 0.0, "drift_rate@run:run_25C": 1.0}, "drift_rate", "run@25C", "d") == 1.0


def test_withheld_values_put_the_effect_where_the_candidate_can_see_it():
    runs = [("a", "k2.13"), ("b", "k2.13"), ("c", "k20.3")]
    k = get_effect("spring_constant_per_device").run_values(runs, 1.15)
    assert [v["k_scale"] for v in k] == [1.0, 1.0, 1.15]  # never on the reference
    tie = get_effect("spring_constant_per_device").run_values([("a", "kB"), ("b", "kA")], 1.15)
    assert [v["k_scale"] for v in tie] == [1.15, 1.0]  # kA, first by name, is the reference
    d = get_effect("drift_per_run").run_values(runs, 5e-8, seed=3)
    rates = [v["drift_rate"] for v in d]
    assert rates[0] > 0 > rates[1] and rates[2] > 0  # signs mixed
    assert all(2.5e-8 <= abs(r) <= 7.5e-8 for r in rates)
    assert d == get_effect("drift_per_run").run_values(runs, 5e-8, seed=3)  # seeded

import math

import numpy as np
import pytest

from identify.model.params import (
    PARAMETER_SETS,
    ParameterError,
    normal_load_from_voltage,
    parameter_set,
    spec,
    validate_parameters,
    voltage_for_normal_load,
)


@pytest.mark.parametrize("volts, load_uN", [(7.15, 0.98), (55.02, 60.8)])
def test_voltage_pairs_of_the_paper_within_2_percent(volts, load_uN):
    assert normal_load_from_voltage(volts) * 1e6 == pytest.approx(load_uN, rel=0.02)


def test_gap_closes_near_1_54_V():
    # Vb = 1.54 V "just closes the gap against 0.048 µN" (MODEL.md)
    assert voltage_for_normal_load(0.0) == pytest.approx(1.54, abs=0.02)
    with pytest.raises(ParameterError, match="block_voltage_V"):
        normal_load_from_voltage(1.0)


def test_voltage_round_trip():
    for nb in (1e-7, 5e-6, 4e-4):
        assert normal_load_from_voltage(voltage_for_normal_load(nb)) == pytest.approx(nb, rel=1e-12)


def test_table_II_presets():
    f, o = PARAMETER_SETS["FOTAS"], PARAMETER_SETS["OTS"]
    assert (f["mu_max"], f["mu_min"], f["tau"], f["A"]) == (0.796, 0.484, 0.0674, 0.015)
    assert (o["mu_max"], o["mu_min"], o["tau"], o["A"]) == (0.577, 0.404, 0.0845, 0.005)
    assert f["vc"] == o["vc"] == 1e-6 and f["dc"] == o["dc"] == 20e-9
    assert f["mb"] == 3.64e-10 and f["c"] == 3.57e-7 and f["step_size"] == 46e-9
    # effects carry their null values
    assert f["beta"] == 0 and f["k_scale"] == 1 and f["v_stick"] == 0


def test_air_damping_from_eq_7():
    # c = η·Ab/gb with η = 1.98e-5 Pa·s, Ab = 28 830 µm², gb = 1.6 µm
    assert 1.98e-5 * 28_830e-12 / 1.6e-6 == pytest.approx(spec("c").nominal, rel=0.01)


@pytest.mark.parametrize(
    "overrides, match",
    [
        ({"tau": float("nan")}, "tau"),
        ({"tau": -1.0}, "tau"),
        ({"mu_min": 0.9}, "mu_min = 0.9 must be smaller than mu_max"),
        ({"bogus": 1.0}, "unknown parameter 'bogus'"),
        ({"A": "x"}, "A: 'x' is not a number"),
    ],
)
def test_bad_parameters_name_the_parameter_and_rule(overrides, match):
    with pytest.raises(ParameterError, match=match):
        parameter_set("FOTAS", overrides)


def test_unknown_coating():
    with pytest.raises(ParameterError, match="coating 'PTFE' is not known"):
        parameter_set("PTFE")


def test_validate_accepts_the_presets():
    for name in PARAMETER_SETS:
        out = validate_parameters(PARAMETER_SETS[name])
        assert all(math.isfinite(v) for v in out.values())
        assert np.isclose(out["mu_0"], out["mu_min"])

"""Unit slips at the edges (issue: what users do wrong): a value outside what the platform
can do is refused where it enters, with the value, its unit, the range and the likely
slip named; a run outside on purpose says so and is accepted."""

import json
import shutil
from pathlib import Path

import pytest

import identify
from identify.cli import main as cli_main
from identify.model.params import ParameterError
from identify.model.plausible import PLATFORM_RANGES, platform_problem

DATA = Path(__file__).resolve().parents[3] / "data" / "FOTAS"
RUN = "FOTAS_k2.13_Nb10uN_fp100Hz"


@pytest.mark.parametrize("name, value, slip", [
    ("normal_load_uN", 3e-5, "newtons? (30 µN)"),
    ("normal_load_uN", 5000.0, None),
    ("spring_constant_N_per_m", 2130.0, "mN/m? (2.13 N/m)"),
    ("step_frequency_Hz", 0.1, "kHz? (100 Hz)"),
    ("step_size_nm", 4.6e-8, "metres? (46 nm)"),
])
def test_a_value_outside_the_platform_names_its_range_and_likely_slip(name, value, slip):
    problem = platform_problem(name, value)
    r = PLATFORM_RANGES[name]
    assert problem.startswith(f"{name} = {value:g} {r.unit}") and f"{r.lo:g} to {r.hi:g} {r.unit}" in problem
    if slip:
        assert f"did you give it in {slip}" in problem
    assert platform_problem(name, (r.lo * r.hi) ** 0.5) is None


def test_simulate_refuses_newtons_in_a_micronewton_field_unless_told():
    with pytest.raises(ParameterError, match=r"normal_load_uN = 3e-05 µN.*did you give it in newtons"):
        identify.simulate("FOTAS", spring_constant_N_per_m=2.13, normal_load_uN=3e-5, step_frequency_Hz=100,
                          travel_um=2)
    run = identify.simulate("FOTAS", spring_constant_N_per_m=2.13, normal_load_uN=600, step_frequency_Hz=100,
                            travel_um=2, check_platform=False)
    trace = run.sample(noise_nm=0, name="heavy")
    assert trace.metadata["outside_platform_ranges"] is True  # written so, read back without complaint


def _copy(tmp_path, **changes):
    for suffix in (".csv", ".json"):
        shutil.copy(DATA / f"{RUN}{suffix}", tmp_path / f"{RUN}{suffix}")
    meta_path = tmp_path / f"{RUN}.json"
    meta = json.loads(meta_path.read_text())
    meta.update(changes)
    meta_path.write_text(json.dumps(meta, indent=2))
    return tmp_path


def test_a_trace_in_newtons_is_refused_with_its_file_and_line(tmp_path):
    folder = _copy(tmp_path, normal_load_uN=1e-5)
    ts = identify.load_traces(folder)
    assert not ts.traces and len(ts.errors) == 1
    reason = str(ts.errors[0])
    assert f"{RUN}.json" in reason and "did you give it in newtons? (10 µN)" in reason


def test_a_trace_outside_on_purpose_is_read(tmp_path):
    folder = _copy(tmp_path, normal_load_uN=600, outside_platform_ranges=True)
    assert len(identify.load_traces(folder).traces) == 1
    with pytest.raises(identify.TraceFormatError, match="true or false"):
        identify.Trace.read(_copy(tmp_path, outside_platform_ranges="yes") / RUN)


def test_analyze_with_no_usable_run_exits_2_with_an_error_line(tmp_path, capsys):
    code = cli_main(["analyze", str(_copy(tmp_path, normal_load_uN=1e-5))])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: no run could be analysed")


@pytest.mark.parametrize("where, value, slip", [("tau", 67.4, "ms"), ("vc", 1.0, "µm/s"), ("dc", 20.0, "nm"),
                                                ("mu_max", 79.6, "per cent"), ("step_size", 46.0, "nm")])
def test_a_parameter_in_the_wrong_unit_is_refused_with_the_likely_slip(where, value, slip):
    with pytest.raises(ParameterError, match=rf"{where} = {value:g}.*did you give it in {slip}\?"):
        identify.FitOptions(start={where: value}) if where in ("tau", "mu_max") else \
            identify.FitOptions(fixed={where: value})


def test_a_parameter_outside_on_purpose_is_taken_when_told():
    assert identify.FitOptions(start={"tau": 67.4}, check_platform=False).start == {"tau": 67.4}
    with pytest.raises(ParameterError, match=r"params: tau = 67.4 s.*ms"):
        identify.simulate("FOTAS", spring_constant_N_per_m=2.13, normal_load_uN=5, step_frequency_Hz=100,
                          travel_um=1, params={"tau": 67.4})
    run = identify.simulate("FOTAS", spring_constant_N_per_m=2.13, normal_load_uN=5, step_frequency_Hz=100,
                            travel_um=1, params={"tau": 67.4}, check_platform=False)
    assert run.parameters["tau"] == 67.4
    # a fit may end near 0 in μmin or A: the plausible range checks their upper end only
    identify.FitOptions(start={"A": 1e-9, "mu_min": 1e-6})


def test_the_fit_command_refuses_a_slipped_unit_before_any_work(tmp_path, capsys):
    code = cli_main(["fit", str(DATA), "--fix", "v_stick=1e-5", "--start", "tau=67.4", "--json",
                     str(tmp_path / "fit.json")])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: start tau = 67.4 s") and "did you give it in ms" in err
    assert "[fit]" not in err  # (refused before loading anything)


def test_a_warning_repeated_at_every_slip_is_said_a_few_times_and_counted():
    from identify.messages import summarise

    msgs = [f"t = {0.01 * i:.6g} s: more than 100 reversals in one phase; phase cut" for i in range(435)]
    msgs.insert(5, "moving phase from t = 0.3 s failed: x")
    out = summarise(msgs)
    assert len(out) == 5 and out[3] == "... and 432 more like it" and out[4].startswith("moving phase")
    assert summarise(["a 1", "a 2"]) == ["a 1", "a 2"]

"""The result protocol of the design results: ``to_dict()``/``from_dict()`` round trip through
strict JSON, ``save()``/``load()``, the same ``report()`` and a working ``plot()`` after
loading; and the command line's ``--json`` read back with ``Class.load``.

Every result is built the cheapest real way: a tiny simulated or stubbed grid for the
operating ranges, two short candidate runs for the experiment plan (its Monte Carlo taken
from a written record, no fit run), one spring over a narrow range for the spring set.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
from matplotlib.axes import Axes
from matplotlib.figure import Figure

import design.ranges as dr
from design.cli import main
from design.experiment import Candidate, design_experiment
from design.experiment_plan import ExperimentPlan
from design.ranges import OperatingRanges, operating_ranges
from design.spring_coverage import SpringSet, paper_spring_set
from design.spring_set import design_spring_set
from design.spring_set_result import Attempt, SpringSetResult
from identify.simulation.regimes import RegimeMap

SMALL = [Candidate(2.13, 5, 100, 12.0), Candidate(20.3, 30, 30, 12.0)]


def _round_trip(result, tmp_path, strict_json, name="result.json"):
    """Save, check the file is strict JSON, load; the loaded result has the same dict,
    report and a plot. Returns the loaded result."""
    path = result.save(tmp_path / name)
    on_disk = strict_json(path)
    assert on_disk == result.to_dict()
    loaded = type(result).load(path)
    assert type(loaded) is type(result)
    assert loaded.to_dict() == result.to_dict()
    assert type(result).from_dict(result.to_dict()).to_dict() == result.to_dict()
    if hasattr(result, "report"):
        assert loaded.report() == result.report()
    if hasattr(result, "plot"):
        fig = Figure(figsize=(6.5, 5.0))
        ax = loaded.plot(ax=fig.add_subplot())
        assert isinstance(ax, Axes)
    return loaded


def _stub_regime_map(monkeypatch, regimes, mean_slip_um, n_slips):
    """The simulator grid replaced by fixed per-point results (rows: loads, cols: freqs)."""

    def fake(coating, k, loads, fps, travel_um=None, stick_speed_m_per_s=0.0, progress=None):
        shape = (len(loads), len(fps))
        return RegimeMap(
            coating=coating, spring_constant_N_per_m=k, stick_speed_m_per_s=stick_speed_m_per_s,
            travel_um=travel_um, normal_loads_uN=np.asarray(loads, float),
            step_frequencies_Hz=np.asarray(fps, float),
            regimes=np.asarray(regimes, str).reshape(shape),
            n_slips=np.asarray(n_slips, int).reshape(shape),
            mean_slip_um=np.asarray(mean_slip_um, float).reshape(shape),
            mean_peak_elongation_um=np.full(shape, np.nan), wall_time_s=np.zeros(shape),
            errors=["stub: one run failed"] if "error" in np.asarray(regimes).ravel() else [],
        )

    monkeypatch.setattr(dr, "regime_map", fake)


# ------------------------------------------------------------------ operating ranges
def test_operating_ranges_round_trip_simulated(tmp_path, strict_json):
    # 2 loads x 3 frequencies, 20 µm: stick-slip, creep, and 10 kHz not simulated (camera)
    r = operating_ranges(2.13, "FOTAS", stick_speed_m_per_s=0.0, loads_uN=[2.0, 5.0],
                         fps_Hz=[10.0, 1000.0, 10000.0], travel_um=20.0, progress=False)
    loaded = _round_trip(r, tmp_path, strict_json)
    assert np.array_equal(loaded.usable, r.usable)
    assert loaded.failed.tolist() == r.failed.tolist()
    assert loaded.regimes.tolist() == r.regimes.tolist()
    assert loaded.rules == r.rules


def test_operating_ranges_round_trip_every_rule(tmp_path, strict_json, monkeypatch):
    # one point per verdict, some failing several rules (outside Table I too: 1 µN < 1.92 µN)
    _stub_regime_map(monkeypatch,
                     regimes=["stick-slip", "creep", "stepping", "error", "stick-slip", "no-slip"],
                     mean_slip_um=[0.05, np.nan, 0.5, np.nan, 0.3, np.nan],
                     n_slips=[30, 0, 3, 0, 5, 0])
    r = operating_ranges(2.13, "FOTAS", loads_uN=[1.0, 5.0], fps_Hz=[10.0, 100.0, 1000.0, 10000.0],
                         progress=False)
    assert any(len(f) > 1 for f in r.failed.ravel())
    loaded = _round_trip(r, tmp_path, strict_json)
    assert loaded.failed.tolist() == r.failed.tolist()
    assert loaded.errors == r.errors
    assert np.array_equal(np.isnan(loaded.mean_slip_um), np.isnan(r.mean_slip_um))
    assert np.array_equal(loaded.n_slips, r.n_slips)


def test_cli_ranges_json_loads(tmp_path, monkeypatch, capsys, strict_json):
    _stub_regime_map(monkeypatch, regimes=["stick-slip", "creep"], mean_slip_um=[0.3, np.nan], n_slips=[40, 0])
    out = tmp_path / "ranges.json"
    assert main(["ranges", "--spring-constant", "2.13", "--loads-uN", "5", "--fp", "10", "100",
                 "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    strict_json(out)
    loaded = OperatingRanges.load(out)
    assert loaded.report() in printed
    assert loaded.to_dict() == json.loads(out.read_text(encoding="utf-8"))


# ------------------------------------------------------------------ experiment plan
@pytest.fixture(scope="module")
def plan() -> ExperimentPlan:
    return design_experiment(2, candidates=SMALL, reference=SMALL[::-1], progress=False)


def test_experiment_plan_round_trip(plan, tmp_path, strict_json):
    loaded = _round_trip(plan, tmp_path, strict_json)
    assert loaded.plan == plan.plan and loaded.reference_plan == plan.reference_plan
    assert [c for c, _ in loaded.candidates] == [c for c, _ in plan.candidates]


def test_experiment_plan_with_monte_carlo_round_trip(plan, tmp_path, strict_json):
    """A verified plan (the fits taken from a record: none run); the reference's fits
    carry no intervals, so its coverage is NaN: null in the file, NaN again when loaded."""
    from copy import deepcopy

    from design import verification as v

    verified = deepcopy(plan)
    context = v._record_context(verified, 90.0, v.STICK_SPEED, v.JITTER_LOAD)
    record = tmp_path / "mc.jsonl"
    rows = []
    for key in ("plan_stderr", "reference_stderr"):
        for seed in range(3):
            est = {n: verified.nominal[n] * (1 + 0.01 * (seed - 1)) for n in verified.free}
            row = dict(key=key, seed=seed, context=context[key], estimates=est)
            if key == "plan_stderr":
                row["ci95"] = {n: [0.9 * x, 1.1 * x] for n, x in verified.nominal.items()}
            rows.append(json.dumps(row))
    record.write_text("\n".join(rows) + "\n", encoding="utf-8")
    mc = v.verify_plans(verified, 3, seed=0, workers=1, record=record, progress=False,
                        stick_speed_m_per_s=v.STICK_SPEED)
    assert all(np.isnan(x) for x in mc["reference_coverage"].values())
    loaded = _round_trip(verified, tmp_path, strict_json)
    assert "Monte Carlo" in loaded.report()
    assert all(np.isnan(x) for x in loaded.monte_carlo["reference_coverage"].values())


def test_cli_experiment_json_loads(tmp_path, capsys, strict_json):
    out = tmp_path / "plan.json"
    assert main(["experiment", "--runs", "2", "--springs", "2.13", "--loads-uN", "5", "10", "--fp", "30", "100",
                 "--travel-um", "12", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    strict_json(out)
    loaded = ExperimentPlan.load(out)
    assert loaded.report() in printed
    assert loaded.to_dict() == json.loads(out.read_text(encoding="utf-8"))


# ------------------------------------------------------------------ spring sets
@pytest.fixture(scope="module")
def spring_result() -> SpringSetResult:
    return design_spring_set((1.0, 50.0), n_springs=1)


def test_spring_set_result_round_trip(spring_result, tmp_path, strict_json):
    loaded = _round_trip(spring_result, tmp_path, strict_json)
    assert loaded.spring_set == spring_result.spring_set
    assert loaded.reference == spring_result.reference
    assert loaded.attempts == spring_result.attempts
    # an n with no converged start has a -inf margin: null in the file, -inf when loaded
    failed_n = replace(spring_result, attempts=(Attempt(1, -math.inf, False),) + spring_result.attempts)
    again = _round_trip(failed_n, tmp_path, strict_json, name="failed_n.json")
    assert again.attempts == failed_n.attempts


def test_spring_set_round_trip(tmp_path, strict_json):
    # the paper's set over a range it does not cover: gaps, uncovered parts, its label
    s = paper_spring_set((0.05e-6, 400e-6), etch_bias_um=0.15)
    loaded = _round_trip(s, tmp_path, strict_json)
    assert loaded == s
    assert loaded.report_lines() == s.report_lines()
    assert SpringSet.from_dict(s.to_json()) == s


def test_cli_springs_json_loads(tmp_path, capsys, strict_json):
    out = tmp_path / "springs.json"
    assert main(["springs", "--load-range-uN", "1", "50", "--n-springs", "1", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    strict_json(out)
    loaded = SpringSetResult.load(out)
    assert loaded.report() in printed
    assert loaded.to_dict() == json.loads(out.read_text(encoding="utf-8"))

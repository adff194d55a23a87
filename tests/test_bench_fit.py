"""The calibration benchmark's statistics (tests/bench/bench_fit.py): the coverage's
range, and the table re-read from a record file without fitting."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent / "bench"))
import bench_fit  # noqa: E402


def test_coverage_range_is_clopper_pearson():
    # at k = n (and k = 0) the exact range has a closed form: (α/2)^(1/n)
    lo, hi = bench_fit.coverage_range(50, 50)
    assert hi == 1.0 and lo == pytest.approx(0.025 ** (1 / 50), rel=1e-9)
    lo, hi = bench_fit.coverage_range(0, 20)
    assert lo == 0.0 and hi == pytest.approx(1 - 0.025 ** (1 / 20), rel=1e-9)
    # 47 of 50: the band the calibration note quotes for A (83-99 %)
    lo, hi = bench_fit.coverage_range(47, 50)
    assert (round(100 * lo), round(100 * hi)) == (83, 99)


def _row(seed, covered: bool, context):
    truth = bench_fit._truth("FOTAS")
    row = dict(seed=seed, wall_s=1.0, success=True, iterations=5, status="Solve_Succeeded", reduced_chi2=1.0,
               start="given", context=context)
    for n in bench_fit.FREE:
        v = truth[n] * (1.001 if seed % 2 else 0.999)
        half = abs(v - truth[n]) * (3 if covered else 0.5)
        row[n] = dict(value=v, stderr=half / 1.96, ci95=[v - half, v + half])
    return row


def test_summary_of_a_record_groups_its_contexts(tmp_path, capsys):
    a = dict(coating="FOTAS", travel_um=20.0, jitter_load=0.05, fit_options="A")
    b = dict(a, fit_options="B")
    path = tmp_path / "cal.jsonl"
    rows = [_row(s, s != 3, a) for s in range(10)] + [_row(s, True, b) for s in range(4)]
    path.write_text("\n".join(json.dumps(r) for r in rows) + "\n{\"cut by a sto")
    out = bench_fit.summary_of_record(str(path))
    by = {c["context"]["fit_options"]: c["summary"] for c in out["contexts"]}
    assert by["A"]["mu_max"]["covered"] == 9 and by["A"]["mu_max"]["coverage"] == pytest.approx(0.9)
    assert by["B"]["tau"]["covered"] == 4
    assert by["A"]["A"]["coverage_range"] == pytest.approx(bench_fit.coverage_range(9, 10))
    printed = capsys.readouterr().out
    assert "9/10" in printed and "4/4" in printed


def test_summary_command(tmp_path, capsys):
    ctx = dict(coating="FOTAS", travel_um=20.0, jitter_load=0.0, fit_options="A")
    path = tmp_path / "cal.jsonl"
    path.write_text("\n".join(json.dumps(_row(s, True, ctx)) for s in range(3)) + "\n")
    out = tmp_path / "s.json"
    assert bench_fit.main(["summary", str(path), "--json", str(out)]) == 0
    assert "3/3" in capsys.readouterr().out
    assert json.loads(out.read_text())["contexts"][0]["summary"]["tau"]["covered"] == 3
    with pytest.raises(SystemExit) as e:
        bench_fit.main(["summary", str(tmp_path / "none.jsonl")])
    assert e.value.code == 2 and "no such file" in capsys.readouterr().err


def test_growth_fits_the_slope_and_gives_each_step():
    """The speed benchmark's growth: the slope of log(wall) on log(runs), and each step's
    own exponent (a size that costs more than its share shows there, not in the slope)."""
    rows = [dict(runs=2, wall_s=4.0), dict(runs=5, wall_s=40.0), dict(runs=10, wall_s=20.0),
            dict(runs=20, wall_s=40.0)]
    g = bench_fit.growth(rows)
    assert [s["runs"] for s in g["growth_steps"]] == [[2, 5], [5, 10], [10, 20]]
    assert g["growth_steps"][2]["exponent"] == pytest.approx(1.0)
    assert g["growth_steps"][1]["exponent"] == pytest.approx(-1.0)
    assert g["growth_steps"][0]["exponent"] == pytest.approx(np.log(10) / np.log(2.5))
    x, y = np.log([2, 5, 10, 20]), np.log([4.0, 40.0, 20.0, 40.0])
    assert g["growth_exponent"] == pytest.approx(np.polyfit(x, y, 1)[0])
    linear = bench_fit.growth([dict(runs=n, wall_s=3.0 * n) for n in (2, 10, 20)])
    assert linear["growth_exponent"] == pytest.approx(1.0)
    assert bench_fit.growth([dict(runs=10, wall_s=27.0)]) == {}


def test_a_clean_robustness_set_varies_more_than_the_noise():
    """A clean set: friction inside the issue's ranges, 6-8 runs that stick-slip under it,
    alternate initial contacts and frame phases, reproducible from its seed."""
    truth, traces = bench_fit._clean_set(1, 0)
    again, traces2 = bench_fit._clean_set(1, 0)
    assert truth == again and [t.name for t in traces] == [t.name for t in traces2]
    assert 0.5 <= truth["mu_max"] <= 0.9 and 0.3 <= truth["mu_min"] <= truth["mu_max"] - 0.08
    assert 0.02 <= truth["tau"] <= 0.3 and 0.003 <= truth["A"] <= 0.03
    assert 6 <= len(traces) <= 8
    np.testing.assert_array_equal(traces[0].elongation, traces2[0].elongation)


def test_a_robustness_row_that_failed_is_printed_as_such(capsys):
    bench_fit._robust_line(dict(set="clean 9", wall_s=1.0, error="no run could be used"))
    assert "failed: no run could be used" in capsys.readouterr().out


def test_a_robustness_record_resumes_without_fitting(tmp_path, capsys):
    """Sets a record file holds for the same seed and fit options are read back, not refitted:
    a stopped run of the benchmark resumes where it stopped."""
    from identify.fitting.driver import FitOptions

    context = dict(kind="robustness", seed=0, fit_options=repr(FitOptions(stick_speed="auto")))
    row = dict(set="clean 0", runs=7, wall_s=12.0, chi2=100.0, truth_chi2=100.5, reached=True,
               intervals_hold=dict(mu_max=True, mu_min=True, tau=True, A=True), ok=True, status="Solve_Succeeded")
    path = tmp_path / "rob.jsonl"
    path.write_text(json.dumps(dict(row, context=context)) + "\n" + '{"cut by a st')
    out = bench_fit.robustness(1, (), 0, record=str(path))
    assert out["clean_ok"] == 1 and out["rows"][0]["wall_s"] == 12.0
    assert "clean 0" in capsys.readouterr().out

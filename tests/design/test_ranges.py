"""Operating ranges per spring (issue 4, item 4) and ``python -m design ranges``.

The rule logic is checked against a stubbed regime map (no simulation); a tiny simulated
grid (2 loads x 2-3 frequencies, 20 µm travel, well under a second) checks the real path.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from matplotlib.figure import Figure

import design.ranges as dr
from design import OperatingRanges, operating_ranges
from design.cli import main
from identify.simulation.regimes import RegimeMap

TINY = {"loads_uN": [2.0, 5.0], "fps_Hz": [10.0, 1000.0, 10000.0], "travel_um": 20.0}


@pytest.fixture(scope="module")
def tiny() -> OperatingRanges:
    # FOTAS, k = 2.13 N/m, equations as written: stick-slip at 10 Hz, creep at 1 kHz
    # (README regime maps); 10 kHz needs 20 000 fps and is never simulated.
    return operating_ranges(2.13, "FOTAS", stick_speed_m_per_s=0.0, **TINY)


def stub_regime_map(monkeypatch, regimes, mean_slip_um, n_slips, calls=None):
    """Replace the simulator grid by fixed per-point results (rows: loads, cols: freqs)."""

    def fake(coating, k, loads, fps, travel_um=None, stick_speed_m_per_s=0.0, progress=None):
        if calls is not None:
            calls.append(np.asarray(fps, float).tolist())
        shape = (len(loads), len(fps))
        return RegimeMap(
            coating=coating, spring_constant_N_per_m=k, stick_speed_m_per_s=stick_speed_m_per_s,
            travel_um=travel_um, normal_loads_uN=np.asarray(loads, float),
            step_frequencies_Hz=np.asarray(fps, float),
            regimes=np.asarray(regimes, str).reshape(shape),
            n_slips=np.asarray(n_slips, int).reshape(shape),
            mean_slip_um=np.asarray(mean_slip_um, float).reshape(shape),
            mean_peak_elongation_um=np.full(shape, np.nan), wall_time_s=np.zeros(shape),
        )

    monkeypatch.setattr(dr, "regime_map", fake)


# ------------------------------------------------------------------ the simulated path
def test_table_i_range_of_2_13_N_per_m(tiny):
    lo, hi = tiny.normal_load_range_uN
    assert lo == pytest.approx(1.92, abs=0.005)  # MODEL.md: 1.92 to 237 µN
    assert hi == pytest.approx(237, abs=0.5)


def test_stick_slip_usable_and_creep_unusable_with_reason(tiny):
    j10, j1k = 0, 1
    for i in range(2):
        assert tiny.regimes[i, j10] == "stick-slip"
        assert tiny.usable[i, j10], tiny.reason(i, j10)
        assert tiny.regimes[i, j1k] == "creep"
        assert not tiny.usable[i, j1k]
        assert tiny.reason(i, j1k) == "creep"
        assert [r for r, _ in tiny.failed[i, j1k]] == ["regime"]
    assert tiny.usable_fp_ranges_Hz(0) == [(10.0, 10.0)]


def test_camera_rule_excludes_above_5_kHz(tiny):
    j = 2  # 10 kHz
    assert tiny.rules.max_step_frequency_Hz == 5000
    for i in range(2):
        assert tiny.regimes[i, j] == dr.NOT_SIMULATED
        assert tiny.reason(i, j) == "camera: 2 frames/step needs 20000 fps > 10000"
        assert tiny.n_slips[i, j] == 0


def test_json_keys_and_serialisable(tiny):
    d = json.loads(json.dumps(tiny.to_json()))
    for key in ("spring_constant_N_per_m", "coating", "normal_load_range_uN", "normal_loads_uN",
                "step_frequencies_Hz", "points", "loads", "usable_region", "rules",
                "stick_speed_m_per_s", "travel_um"):
        assert key in d
    assert d["spring_constant_N_per_m"] == 2.13 and d["coating"] == "FOTAS"
    assert d["normal_load_range_uN"] == pytest.approx([1.917, 236.67], rel=1e-3)
    assert len(d["points"]) == 6
    for p in d["points"]:
        assert set(p) >= {"normal_load_uN", "step_frequency_Hz", "regime", "usable", "reason"}
        assert (p["reason"] is None) == p["usable"]
    assert d["points"][2]["regime"] is None  # 10 kHz: not simulated
    assert d["loads"][1] == {"normal_load_uN": 5.0, "usable_fp_ranges_Hz": [[10.0, 10.0]]}
    assert d["usable_region"]["n_usable"] == 2


def test_report_and_plot(tiny, tmp_path):
    text = tiny.report()
    assert "Table I: Nb in [1.92, 237] µN" in text
    assert "Nb = 2 µN, fp = 1000 Hz: creep" in text
    fig = Figure()
    ax = tiny.plot(ax=fig.add_subplot())
    assert ax.get_xscale() == "log" and ax.get_yscale() == "log"
    out = tmp_path / "ranges.png"
    fig.savefig(out)
    assert out.stat().st_size > 1000


# ---------------------------------------------------------- rules on a stubbed grid
def test_each_failed_rule_is_named(monkeypatch):
    # loads: 1 µN (below Table I for 2.13 N/m), 10 µN; freqs 10, 30, 100 Hz
    stub_regime_map(
        monkeypatch,
        regimes=[["stick-slip", "stick-slip", "stick-slip"], ["stepping", "stick-slip", "no-slip"]],
        mean_slip_um=[[0.5, 0.5, 0.5], [0.05, 0.3, np.nan]],
        n_slips=[[40, 40, 40], [300, 12, 0]],
    )
    r = operating_ranges(2.13, loads_uN=[10, 1], fps_Hz=[100, 10, 30])
    assert r.normal_loads_uN.tolist() == [1, 10]  # the grid is sorted
    assert r.reason(0, 0) == "Table I: Nb = 1 µN outside 1.92-237 µN"
    assert r.reason(1, 0) == "stepping; slips 0.05 µm < 0.09 µm"
    assert r.reason(1, 1) == "only 12 slips in 100 µm"
    assert r.reason(1, 2) == "no slip in 100 µm"
    assert not r.usable.any()
    assert r.usable_region["normal_load_range_uN"] is None


def test_usable_fp_intervals_with_a_gap(monkeypatch):
    stub_regime_map(monkeypatch, regimes=[["stick-slip", "creep", "stick-slip", "stick-slip"]],
                    mean_slip_um=[[1.0] * 4], n_slips=[[50] * 4])
    r = operating_ranges(2.13, loads_uN=[5], fps_Hz=[10, 30, 100, 300])
    assert r.usable_fp_ranges_Hz(0) == [(10.0, 10.0), (100.0, 300.0)]
    assert "10 Hz, 100-300 Hz" in r.report()


def test_camera_only_grid_simulates_nothing(monkeypatch):
    calls = []
    stub_regime_map(monkeypatch, [], [], [], calls)
    r = operating_ranges(2.13, loads_uN=[5], fps_Hz=[6000, 20000])
    assert calls == []
    assert [r.reason(0, j) for j in range(2)] == [
        "camera: 2 frames/step needs 12000 fps > 10000",
        "camera: 2 frames/step needs 40000 fps > 10000",
    ]


def test_only_camera_ok_frequencies_are_simulated(monkeypatch):
    calls = []
    stub_regime_map(monkeypatch, [["stick-slip"]], [[1.0]], [[50]], calls)
    r = operating_ranges(2.13, loads_uN=[5], fps_Hz=[5000, 5001], frames_per_step=2)
    assert calls == [[5000.0]]  # fp·2 = 10 000 fps is allowed (closed limit)
    assert r.usable.tolist() == [[True, False]]


def test_default_grid(monkeypatch):
    calls = []
    stub_regime_map(monkeypatch, [["creep"] * 6] * 6, [[1.0] * 6] * 6, [[5] * 6] * 6, calls)
    r = operating_ranges(2.13)
    assert r.normal_loads_uN[[0, -1]] == pytest.approx([1.917, 236.67], rel=1e-3)
    assert len(r.normal_loads_uN) == 6
    assert calls == [[10.0, 30.0, 100.0, 300.0, 1000.0, 3000.0]]


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"spring_constant_N_per_m": 0.0}, "k = 0 N/m: the spring constant must be finite"),
        ({"spring_constant_N_per_m": float("nan")}, "k = nan N/m"),
        ({"spring_constant_N_per_m": 200.0}, "k < 100 N/m"),
        ({"spring_constant_N_per_m": 2.13, "coating": "PTFE"}, "coating 'PTFE' is not known"),
        ({"spring_constant_N_per_m": 2.13, "fps_Hz": [10, 0]}, "fp = 0 Hz: every value must be"),
        ({"spring_constant_N_per_m": 2.13, "loads_uN": [-1]}, "Nb = -1 µN"),
        ({"spring_constant_N_per_m": 2.13, "loads_uN": []}, "Nb: give at least one value"),
        ({"spring_constant_N_per_m": 2.13, "travel_um": 200}, "must be <= 100 µm"),
        ({"spring_constant_N_per_m": 2.13, "stick_speed_m_per_s": -1}, "v_stick = -1"),
        ({"spring_constant_N_per_m": 2.13, "min_slips": 0}, "min_slips = 0"),
        ({"spring_constant_N_per_m": 2.13, "frames_per_step": 0}, "frames_per_step = 0"),
    ],
)
def test_bad_input_raises_value_error(kwargs, match, monkeypatch):
    stub_regime_map(monkeypatch, [], [], [])  # must fail before any simulation
    with pytest.raises(ValueError, match=match.replace("(", r"\(").replace(".", r"\.")):
        operating_ranges(**kwargs)


# ------------------------------------------------------------------------------ CLI
def test_cli_writes_json_and_plot(tmp_path, capsys, strict_json):
    out, fig = tmp_path / "ranges.json", tmp_path / "ranges.png"
    argv = ["ranges", "--spring-constant", "2.13", "--coating", "FOTAS", "--loads-uN", "2", "5",
            "--fp", "10", "1000", "--travel-um", "20", "--json", str(out), "--plot", str(fig)]
    assert main(argv) == 0
    d = strict_json(out)
    assert d["normal_load_range_uN"] == pytest.approx([1.917, 236.67], rel=1e-3)
    assert [p["usable"] for p in d["points"]] == [True, False, True, False]
    assert fig.stat().st_size > 1000
    cap = capsys.readouterr()
    assert "[ranges] regime map: " in cap.err and "[4/4, " in cap.err  # progress on stderr, counted
    assert "Usable fp per load" in cap.out and f"wrote {out}" in cap.out


def test_cli_stick_speed_passes_through(monkeypatch, tmp_path):
    seen = {}

    def fake(*args, **kwargs):
        seen.update(kwargs)
        raise ValueError("stop here")

    monkeypatch.setattr(dr, "regime_map", fake)
    assert main(["ranges", "--spring-constant", "2.13", "--stick-speed", "1e-5"]) == 2
    assert seen["stick_speed_m_per_s"] == 1e-5


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("error: ") and "Traceback" not in err
    return lines[0]


@pytest.mark.parametrize(
    "extra, match",
    [
        (["--spring-constant", "0"], "k = 0 N/m: the spring constant must be finite and > 0"),
        (["--spring-constant", "-2"], "k = -2 N/m"),
        (["--spring-constant", "nan"], "k = nan N/m"),
        (["--spring-constant", "2.13", "--coating", "TEFLON"], "coating 'TEFLON' is not known"),
        (["--spring-constant", "2.13", "--fp", "10", "-5"], "fp = -5 Hz"),
        (["--spring-constant", "2.13", "--fp", "0"], "fp = 0 Hz"),
        (["--spring-constant", "2.13", "--plot", "x.jpg"], ".png"),
        (["--coating", "FOTAS"], "--spring-constant"),
    ],
)
def test_cli_bad_input_exit_2(extra, match, capsys):
    assert main(["ranges", *extra]) == 2
    assert match in one_error_line(capsys)

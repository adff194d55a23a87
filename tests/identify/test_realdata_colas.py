"""Real laboratory data: Colas et al. 2019, paper on paper pulled at constant speed through
a soft (168 N/m) and a stiff (1002 N/m) spring, imported from the upstream MATLAB files
and read for their regime and slip cycles (data/real/colas2019/README.md)."""

import json
from pathlib import Path

import numpy as np
import pytest

from identify.cli import main
from identify.traces.look import LookFormatError, read_mat

COLAS = Path(__file__).resolve().parents[2] / "data" / "real" / "colas2019"
WEIGHT_UN = 3.01e5  # m·g = 0.301 N
# what the data show (the force's share of time rising: a sawtooth or an oscillation)
REGIMES = {("168", "42"): "stick-slip", ("1002", "42"): "stick-slip", ("168", "1100"): "stick-slip",
           ("1002", "1100"): "inertial", ("168", "4300"): "inertial", ("1002", "4300"): "inertial"}


def _import(tmp_path, k, v):
    stem = tmp_path / "colas" / f"k{k}_v{v}"
    code = main(["import", str(COLAS / f"k{k}Nm_v{v}.mat"), "--time", "t", "--friction", "Fnorm",
                 "--stiffness-per-um", repr(float(k) / WEIGHT_UN), "--normal-load-uN", repr(WEIGHT_UN),
                 "--velocities", v, "--out", str(stem)])
    return code, stem


def test_the_six_runs_are_read_for_their_regimes(tmp_path, capsys):
    """Stick-slip at 42 µm/s on both springs and at 1100 µm/s on the soft one; inertial
    oscillation on the stiff one at 1100 and on both at 4300, as the data show. At
    42 µm/s each slip's drop matches what the drive loads back in a recurrence (a
    sawtooth), and the stiff spring's oscillation at 4300 µm/s has the slider's own
    period 2π·√(m/k) = 35 ms within 20 %."""
    for k, v in REGIMES:
        assert _import(tmp_path, k, v)[0] == 0
    capsys.readouterr()
    assert main(["analyze", str(tmp_path / "colas"), "--json", str(tmp_path / "cycles.json")]) == 0
    out = capsys.readouterr().out
    cycles = {c["name"]: c for c in json.loads((tmp_path / "cycles.json").read_text())["cycles"]}
    for (k, v), regime in REGIMES.items():
        assert cycles[f"k{k}_v{v}"]["regime"] == regime, (k, v, cycles[f"k{k}_v{v}"]["rising_fraction"])
    for k in ("168", "1002"):
        c = cycles[f"k{k}_v42"]
        assert c["mean_drop"] == pytest.approx(c["drive_rate"] * c["mean_period"], rel=0.2)
    assert cycles["k1002_v4300"]["mean_period"] == pytest.approx(2 * np.pi * np.sqrt(0.0307 / 1002), rel=0.2)
    assert "k168_v42: stick-slip" in out


def test_a_constant_drive_has_no_transient_to_fit(tmp_path, capsys):
    assert _import(tmp_path, "168", "4300")[0] == 0
    capsys.readouterr()
    assert main(["fit", str(tmp_path / "colas"), "--json", str(tmp_path / "f.json")]) == 2
    assert "one constant velocity, no transient to fit; 'analyze' reads" in capsys.readouterr().err


def test_matlab_files_read_as_columns(tmp_path):
    from scipy.io import savemat

    f = read_mat(COLAS / "k168Nm_v4300.mat")
    assert [c.name for c in f.channels] == ["t", "Fnorm"] and f.n_rows == 7521
    savemat(tmp_path / "bad.mat", dict(t=np.arange(5.0), F=np.arange(4.0)))
    with pytest.raises(LookFormatError, match="vectors of different lengths"):
        read_mat(tmp_path / "bad.mat")
    (tmp_path / "text.mat").write_text("not matlab")
    with pytest.raises(LookFormatError, match="not a MATLAB file"):
        read_mat(tmp_path / "text.mat")

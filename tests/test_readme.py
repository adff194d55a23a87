"""The README's script and command lines run as written (on a small data set, so the
suite stays fast): what researchers copy first must work."""

import re
import shlex
import warnings
from pathlib import Path

import pytest

import identify
from design.cli import main as design_main
from identify.cli import main as identify_main

README = Path(__file__).resolve().parent.parent / "README.md"


def _blocks(lang):
    return re.findall(rf"```{lang}\n(.*?)```", README.read_text(), flags=re.S)


@pytest.fixture(scope="module")
def small_data(tmp_path_factory):
    """Two FOTAS stick-slip runs, 15 µm, 90 nm: the README's data/FOTAS in miniature."""
    d = tmp_path_factory.mktemp("data") / "FOTAS"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i, (k, nb, fp) in enumerate([(2.13, 5, 100), (20.3, 30, 30)]):
            r = identify.simulate("FOTAS", spring_constant_N_per_m=k, normal_load_uN=nb,
                                  step_frequency_Hz=fp, travel_um=15, stick_speed_m_per_s=1e-5)
            r.sample(noise_nm=90, seed=i, name=f"run{i}").write(d / f"run{i}")
    return d


def test_first_lines_are_the_two_commands():
    lines = [ln.strip() for ln in README.read_text().splitlines()[:5] if ln.strip()]
    assert lines[1].endswith("python -m identify demo") and "pip install -e ." in lines[1]
    assert lines[2].endswith("python -m pytest") and '".[test]"' in lines[2]
    ci = (README.parent / ".ci" / "run").read_text()
    assert "python -m pytest" in ci


def test_readme_script_runs(small_data, tmp_path, monkeypatch):
    script = _blocks("python")[0]
    script = script.replace('"data/FOTAS"', repr(str(small_data)))
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    exec(compile(script, "README.md", "exec"), ns)
    res = ns["result"]
    assert res.n_runs == 2 and not res.profiles and "tau" in ns["profiled"].profiles
    assert (tmp_path / "out" / "k2.13_Nb5.csv").exists()
    assert any((tmp_path / "figures").glob("fit_*.png"))
    assert ns["diag"].verdict in ("adequate", "unexplained")
    assert (tmp_path / "diagnosis" / "gap_shrinkage.png").exists()


def test_readme_commands_run(small_data, tmp_path, monkeypatch):
    block = _blocks("bash")[0]
    monkeypatch.chdir(tmp_path)
    commands = [c for c in block.replace("\\\n", " ").splitlines() if c.strip()]
    assert len(commands) >= 6
    for cmd in commands:
        argv = shlex.split(re.sub(r"\[.*?\]", "", cmd), comments=True)  # optional flags in brackets
        argv = [str(small_data) if a == "data/FOTAS" else a for a in argv]
        assert argv[:2] == ["python", "-m"], cmd
        prog, args = argv[2], argv[3:]
        if prog == "identify" and args[0] == "regimes":
            args += ["--loads-uN", "5", "--fp", "100"]  # one cell, not the full map
        if prog == "identify" and args[0] == "bench":
            continue  # a benchmark, minutes long: run on demand (tests/bench)
        main = identify_main if prog == "identify" else design_main
        assert main(args) == 0, cmd
    assert (tmp_path / "fit.json").exists() and (tmp_path / "analysis.json").exists()
    assert (tmp_path / "springs.json").exists() and (tmp_path / "regimes.png").exists()
    assert (tmp_path / "plan.json").exists() and (tmp_path / "ranges.json").exists()
    assert (tmp_path / "diagnosis.json").exists() and (tmp_path / "diagnosis" / "misfit_by_feature.pdf").exists()


REPO = README.parent


def test_the_lab_data_script_and_commands_run(tmp_path, monkeypatch):
    """The laboratory section's commands (import, then fit) and its script, as written,
    from a folder where data/real is the repository's."""
    assert len(_blocks("python")) == 2 and len(_blocks("bash")) == 2
    monkeypatch.chdir(tmp_path)
    (tmp_path / "data").symlink_to(REPO / "data")
    block = _blocks("bash")[1]
    for cmd in [c for c in block.replace("\\\n", " ").splitlines() if c.strip()]:
        argv = shlex.split(cmd)
        assert argv[:3] == ["python", "-m", "identify"], cmd
        assert identify_main(argv[3:]) == 0, cmd
    assert (tmp_path / "p655_fit.json").exists() and any((tmp_path / "p655_figures").glob("*.png"))
    ns: dict = {}
    exec(compile(_blocks("python")[1], "README.md", "exec"), ns)
    assert ns["step"].success and abs(ns["step"]["a"].value - 0.00602) < 1e-4

"""Real laboratory data: the Penn State p655 velocity step (2.28 → 22.85 µm/s at 100 MPa)
imported from the raw look file with the lab's own recipe and fitted, against the lab's
published fits (data/real/p655/README.md)."""

import json
from pathlib import Path

import numpy as np
import pytest

from identify.cli import main

P655 = Path(__file__).resolve().parents[2] / "data" / "real" / "p655"
# 5 s either side of the step: ~11 µm of load point before it, ~114 µm (~17 Dc) after,
# ending before the recording's next change of rate (the lab's own fit rows do not
# match this file); how the estimates move with the window is measured in the slow test
WINDOW = "3847.35:3857.35"
PUBLISHED = {  # law, stiffness -> (value, standard error)
    ("aging", 1e-3): dict(mu0=(0.487786, 0.000043), a=(0.006043, 0.000113), b=(0.004279, 0.000109),
                          Dc=(6.505, 0.199)),
    ("slip", 1e-3): dict(mu0=(0.487805, 0.000041), a=(0.005823, 0.000098), b=(0.004094, 0.000094),
                         Dc=(12.817, 0.442)),
    ("slip", 1.6e-3): dict(mu0=(0.487596, 0.000026), a=(0.006005, 0.000053), b=(0.004230, 0.000051),
                           Dc=(17.745, 0.334)),
}


def _import(tmp_path, capsys, extra=()):
    stem = tmp_path / "p655" / "p655_vs"
    code = main(["import", str(P655 / "p655intact100l"), "--recipe", str(P655 / "p655_r-reduction.txt"),
                 "--stiffness-per-um", "1e-3", "--normal-load-uN", "2.5e11", "--window", WINDOW,
                 "--velocities", "2.28,22.85", "--load-point", "LP_disp", "--out", str(stem), *extra])
    return code, capsys.readouterr(), stem


def _fit(tmp_path, capsys, *args):
    out = tmp_path / f"fit{len(list(tmp_path.glob('fit*.json')))}.json"
    code = main(["fit", str(tmp_path / "p655"), "--json", str(out), *args])
    return code, capsys.readouterr(), json.loads(out.read_text())


def test_import_then_fit_gives_the_labs_aging_law_numbers(tmp_path, capsys, strict_json):
    """From the raw file, through the lab's recipe, the aging-law fit at the lab's
    stiffness 1e-3/µm: a and b within 2 of the lab's standard errors, a − b with the lab's
    sign, Dc within 15 %, the misfit within 3× the recording's scatter in steady sliding.
    (Measured: a 0.006047, b 0.004243, Dc 5.66 µm (−12.9 %), misfit 2.2× the scatter and
    4.1× the sample-to-sample noise.)"""
    code, out, stem = _import(tmp_path, capsys)
    assert code == 0, out.err
    assert "assumed: velocities taken as given (nominal): 2.28, 22.85 µm/s" in out.out
    assert "measured velocities 2.3" in out.out and "22.86" in out.out
    code, out, fit = _fit(tmp_path, capsys, "--law", "aging")
    assert code == 0, out.err
    assert out.out.startswith("Fit converged: Dieterich (aging) law, run p655_vs")
    ref = PUBLISHED[("aging", 1e-3)]
    p = {n: fit["parameters"][n]["value"] for n in ("mu0", "a", "b", "Dc")}
    for n in ("a", "b"):
        assert abs(p[n] - ref[n][0]) <= 2 * ref[n][1], (n, p[n], ref[n])
    assert (p["a"] - p["b"]) * (ref["a"][0] - ref["b"][0]) > 0
    assert p["Dc"] == pytest.approx(ref["Dc"][0], rel=0.15)
    assert fit["misfit_ratio"] <= 3.0
    strict_json(tmp_path / "fit0.json")


def test_import_refuses_what_it_cannot_do_in_one_line(tmp_path, capsys):
    code, out, stem = _import(tmp_path, capsys)
    assert code == 0
    code, out, _ = _import(tmp_path, capsys)
    assert code == 2 and "exists: give --overwrite" in out.err and "Traceback" not in out.err
    assert main(["import", str(P655 / "p655intact100l"), "--stiffness-per-um", "1e-3", "--window", "9:1",
                 "--out", str(tmp_path / "x")]) == 2
    assert "--window '9:1': expected START:END" in capsys.readouterr().err
    assert main(["import", str(P655 / "p655intact100l"), "--stiffness-per-um", "1e-3", "--friction", "mu",
                 "--load-point", "LP_disp", "--out", str(tmp_path / "y")]) == 2
    assert "no channel named 'mu'" in capsys.readouterr().err  # (no recipe: the raw file has bits only)
    assert main(["fit", str(tmp_path / "p655"), "--json", str(tmp_path / "f.json"), "--law", "exponential"]) == 2
    assert "rate-and-state laws aging or slip" in capsys.readouterr().err


def test_the_api_does_what_the_cli_does(tmp_path):
    """The README's script: read, reduce, import, fit, through the Python API."""
    from identify import TransientRun, apply_recipe, fit_transient, import_run, read_look

    look = apply_recipe(read_look(P655 / "p655intact100l"), P655 / "p655_r-reduction.txt")
    run = import_run(look, friction="mu", time="Time", load_point="LP_disp", stiffness_per_um=1e-3,
                     window_s=(3847.35, 3857.35), velocities_um_per_s=[2.28, 22.85]).trace
    res = fit_transient(TransientRun.from_trace(run), law="aging")
    assert res["a"].value == pytest.approx(0.00602, abs=1e-4) and res["Dc"].value == pytest.approx(5.6, abs=0.3)


@pytest.mark.slow
def test_the_slip_law_and_how_the_numbers_move_with_window_and_stiffness(tmp_path, capsys):
    """The slip law compared with the lab's the same way, at both stiffnesses the lab
    used; then the window moved (1-20 s before the step, 5-22.5 s after). Measured: slip
    at 1e-3 a 0.00598 (+1.6 σ), b 0.00421 (+1.2 σ), Dc 10.2 µm (−21 %); at 1.6e-3 a 0.00609
    (+1.6 σ), b 0.00418 (−1.0 σ), Dc 15.3 µm (−14 %); over the nine windows the aging
    law's a spans 0.0048-0.0063 and Dc 5.4-10.8 µm, wider than any one fit's interval."""
    code, out, _ = _import(tmp_path, capsys)
    assert code == 0
    for k in (1e-3, 1.6e-3):
        code, out, fit = _fit(tmp_path, capsys, "--law", "slip", "--stiffness-per-um", str(k))
        assert code == 0
        ref = PUBLISHED[("slip", k)]
        p = {n: fit["parameters"][n]["value"] for n in ("a", "b", "Dc")}
        for n in ("a", "b"):
            assert abs(p[n] - ref[n][0]) <= 2.5 * ref[n][1], (k, n, p[n], ref[n])
        assert p["Dc"] == pytest.approx(ref["Dc"][0], rel=0.25)
        assert fit["misfit_ratio"] <= 3.0
    from identify import TransientRun, apply_recipe, fit_transient, read_look
    from identify.model.rsf import VelocityDrive

    look = apply_recipe(read_look(P655 / "p655intact100l"), P655 / "p655_r-reduction.txt")
    t, mu = look["Time"].values, look["mu"].values
    a_values, dc_values = [], []
    for pre in (1.0, 5.0, 20.0):
        for post in (5.0, 10.0, 22.5):
            m = (t >= 3852.36 - pre) & (t <= 3852.36 + post)
            run = TransientRun("w", t[m], mu[m], VelocityDrive((t[m][0], 3852.36), (2.28, 22.85)), 1e-3)
            res = fit_transient(run, "aging", starts=2)
            a_values.append(res["a"].value)
            dc_values.append(res["Dc"].value)
    assert np.ptp(a_values) > 5e-4 and np.ptp(dc_values) > 3.0  # the window matters more than the noise

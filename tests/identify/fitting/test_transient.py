"""The rate-and-state transient of a velocity step: the model against its closed-form
limits, IDAS's derivatives against differences, and recovery of seeded truths."""

import numpy as np
import pytest

from identify.fitting.transient import TransientFitError, TransientRun, fit_transient
from identify.fitting.transient_result import TransientFitResult
from identify.model.rsf import VelocityDrive, simulate_rsf, transient_function

LAB = dict(mu0=0.4878, a=0.006, b=0.0043, Dc=6.5, k=1e-3)
DRIVE = VelocityDrive((0.0, 10.0), (2.28, 22.85))
TIMES = np.concatenate([np.arange(0, 10, 0.1), np.arange(10, 30, 0.01)])


@pytest.mark.parametrize("law", ["aging", "slip"])
def test_a_velocity_step_ends_at_the_steady_state_and_peaks_at_the_direct_effect(law):
    """Long after the step μ sits at μ0 + (a − b)·ln(V1/V0) (both laws); on a stiff
    machine the peak reaches the direct effect a·ln(V1/V0) before the state evolves; before
    the step μ stays at μ0."""
    r = np.log(22.85 / 2.28)
    t = np.concatenate([np.arange(0, 10, 0.5), np.arange(10, 60, 0.01)])
    mu = simulate_rsf(law, LAB, DRIVE, t)
    assert np.all(mu[t < 10] == pytest.approx(LAB["mu0"], abs=1e-12))
    assert mu[-1] == pytest.approx(LAB["mu0"] + (LAB["a"] - LAB["b"]) * r, abs=2e-6)
    stiff = simulate_rsf(law, dict(LAB, k=1.0), DRIVE, np.concatenate([[0.0], 10 + np.linspace(0, 0.02, 401)]))
    assert stiff.max() - LAB["mu0"] == pytest.approx(LAB["a"] * r, rel=0.03)


@pytest.mark.parametrize("law", ["aging", "slip"])
def test_the_jacobian_is_idas_sensitivities_and_agrees_with_differences(law):
    f = transient_function(law, DRIVE, TIMES)
    import casadi as ca

    th = ca.MX.sym("th", 5)
    J = np.asarray(ca.Function("j", [th], [ca.jacobian(f(th), th)])(list(LAB.values())))
    x = np.array(list(LAB.values()))
    for i in range(5):
        h = 1e-4 * abs(x[i])  # (far above the integrator's tolerance, truncation ~h²)
        e = np.zeros(5)
        e[i] = h
        fd = (np.asarray(f(x + e)).ravel() - np.asarray(f(x - e)).ravel()) / (2 * h)
        assert np.max(np.abs(fd - J[:, i])) <= 1e-3 * np.max(np.abs(J[:, i])), list(LAB)[i]


@pytest.mark.parametrize("law, truth, start", [
    ("aging", LAB, None),
    ("aging", dict(mu0=0.60, a=0.012, b=0.015, Dc=25.0, k=5e-4), dict(a=0.005, b=0.004, Dc=2.0)),
    ("slip", LAB, None),
    ("slip", dict(mu0=0.55, a=0.004, b=0.002, Dc=3.0, k=2e-3), dict(Dc=40.0)),
])
def test_seeded_truths_are_recovered_within_their_intervals(law, truth, start):
    """Noise 2e-4 (white, seeded); velocity-strengthening and -weakening truths, from the
    start the transient suggests and from a far one: each free parameter within 3 of its
    standard errors (which the white residuals make the right ones), misfit at the noise."""
    mu = simulate_rsf(law, truth, DRIVE, TIMES) + np.random.default_rng(4).normal(0, 2e-4, TIMES.size)
    res = fit_transient(TransientRun("syn", TIMES, mu, DRIVE, truth["k"]), law, start=start)
    assert res.success and res.misfit_white_ratio == pytest.approx(1.0, abs=0.1)
    for n in ("mu0", "a", "b", "Dc"):
        p = res[n]
        assert abs(p.value - truth[n]) < 3 * p.stderr_white, (n, p.value, truth[n], p.stderr_white)
    assert res.serial_inflation < 1.2 and res["k"].free is False


def test_stiffness_and_trend_can_be_fitted_too():
    truth = dict(LAB, k=1.5e-3)
    run_t = np.concatenate([np.arange(0, 10, 0.1), np.arange(10, 40, 0.01)])
    drive = VelocityDrive((0.0, 10.0), (2.28, 22.85))
    x = np.where(run_t < 10, 2.28 * (run_t - 10), 22.85 * (run_t - 10))
    mu = simulate_rsf("aging", truth, drive, run_t) + 2e-6 * x
    mu += np.random.default_rng(1).normal(0, 1e-4, run_t.size)
    res = fit_transient(TransientRun("syn", run_t, mu, drive, 1e-3), "aging", fixed=(), trend=True)
    assert res["k"].value == pytest.approx(1.5e-3, rel=0.05)
    assert res["c"].value == pytest.approx(2e-6, abs=3 * res["c"].stderr_white)


def test_a_window_and_the_result_protocol(tmp_path, strict_json):
    mu = simulate_rsf("aging", LAB, DRIVE, TIMES) + np.random.default_rng(0).normal(0, 2e-4, TIMES.size)
    run = TransientRun("syn", TIMES, mu, DRIVE, 1e-3).window(5.0, 20.0)
    assert run.time_s[0] >= 5.0 and run.time_s[-1] <= 20.0 and run.drive.times_s == (run.time_s[0], 10.0)
    res = fit_transient(run, "aging", starts=0)
    text = res.report()
    assert text.startswith("Fit converged: Dieterich (aging) law, run syn")
    for part in ("best found 1 of 1 starts", "a-b : +", "Dc  :", "µm", "sample-to-sample noise"):
        assert part in text
    path = res.save(tmp_path / "t.json")
    strict_json(path)
    back = TransientFitResult.load(path)
    assert back.to_dict() == res.to_dict() and back.report() == text
    import matplotlib

    matplotlib.use("Agg")
    axes = res.plot()
    assert axes[1].get_xlabel() == "load-point displacement (µm)"
    import matplotlib.pyplot as plt

    plt.close("all")


def test_what_cannot_be_fitted_is_refused_with_its_name():
    mu = simulate_rsf("aging", LAB, DRIVE, TIMES)
    run = TransientRun("syn", TIMES, mu, DRIVE, 1e-3)
    with pytest.raises(TransientFitError, match="law 'exponential' is not known; choose one of aging, slip"):
        fit_transient(run, "exponential")
    with pytest.raises(TransientFitError, match="unknown parameter\\(s\\) tau"):
        fit_transient(run, "aging", fixed=("tau",))
    flat = TransientRun("flat", TIMES[:50], mu[:50], VelocityDrive((0.0,), (2.28,)), 1e-3)
    with pytest.raises(TransientFitError, match="'flat': no velocity change in the window"):
        fit_transient(flat, "aging")
    with pytest.raises(TransientFitError, match="samples start at -1 s, before the drive's first time 0 s"):
        TransientRun("early", TIMES - 1, mu, DRIVE, 1e-3)
    with pytest.raises(TransientFitError, match="holds 0 samples"):
        run.window(100, 200)

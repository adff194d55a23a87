"""The sandwich's trigger meat: a run's slips share their phase error as far as the
spread of their trigger positions says (exchangeable correlation per run)."""

from types import SimpleNamespace

import numpy as np
import pytest

from identify.fitting.problem import Problem


def _fake(runs_of_slips, free_phase=False):
    """The attributes trigger_correlation and _exchangeable_meat read: slip trigger rows
    first (their runs), then n_other phase / first-start rows."""
    runs = np.asarray(runs_of_slips, int)
    ev_run = np.r_[runs[:1], runs]  # a first slip (no trigger row) ahead of the rest
    fake = SimpleNamespace(ev_run=ev_run, ev_next=np.arange(1, len(ev_run)), n_trig=len(runs),
                           opts=SimpleNamespace(free_phase=free_phase))
    fake.trigger_correlation = lambda r: Problem.trigger_correlation(fake, r)
    return fake


def test_phase_locked_runs_share_one_error():
    fake = _fake([0] * 5 + [1] * 4)
    r = np.r_[np.full(5, 0.7), np.full(4, -1.2), 0.0, 0.3]
    rho, sig2 = Problem.trigger_correlation(fake, r)
    assert rho == {0: 1.0, 1: 1.0} and sig2 == 1.0
    a = np.random.default_rng(0).normal(size=(len(r), 3))
    M = Problem._exchangeable_meat(fake, a, r)
    want = (np.outer(a[:5].sum(0), a[:5].sum(0)) + np.outer(a[5:9].sum(0), a[5:9].sum(0))
            + a[9:].T @ a[9:])
    np.testing.assert_allclose(M, want, rtol=1e-12)


def test_walking_phases_count_as_independent():
    # positions spread uniformly over the interval within each run: √12(s − ½) has unit
    # variance within the run, so nothing is shared
    rng = np.random.default_rng(1)
    s = rng.uniform(size=4000)
    r_slip = np.sqrt(12) * (s - 0.5)
    fake = _fake([0] * 2000 + [1] * 2000)
    rho, sig2 = Problem.trigger_correlation(fake, r_slip)
    assert rho[0] < 0.1 and rho[1] < 0.1 and sig2 == pytest.approx(1.0, abs=0.1)
    # half-locked: a shared position plus a within-run spread of half the variance
    shared = np.repeat(rng.uniform(size=2), 2000)
    mixed = np.sqrt(6) * (shared - 0.5) + np.sqrt(6) * (s - 0.5)
    rho, _ = Problem.trigger_correlation(fake, mixed)
    assert rho[0] == pytest.approx(0.5, abs=0.1) and rho[1] == pytest.approx(0.5, abs=0.1)


def test_misfit_beyond_the_uniform_scales_the_meat():
    # within-run variance 4 in every run: σ² = 4, ρ = 0, meat = 4·Σ a aᵀ
    rng = np.random.default_rng(2)
    r = 2.0 * rng.standard_normal(6000)
    r = np.concatenate([(x - x.mean()) / x.std(ddof=1) * 2.0 for x in np.split(r, 2)])
    fake = _fake([0] * 3000 + [1] * 3000)
    rho, sig2 = Problem.trigger_correlation(fake, r)
    assert sig2 == pytest.approx(4.0, rel=1e-9) and max(rho.values()) < 1e-9
    a = rng.normal(size=(6000, 2))
    np.testing.assert_allclose(Problem._exchangeable_meat(fake, a, r), 4.0 * a.T @ a, rtol=1e-9)


def test_runs_with_too_few_slips_are_taken_as_locked():
    fake = _fake([0, 0, 1, 1, 1])
    rho, _ = Problem.trigger_correlation(fake, np.array([1.5, -1.5, 0.2, -0.2, 0.0]))
    assert rho[0] == 1.0 and rho[1] < 1.0


def test_a_free_phase_takes_the_shared_error():
    # with free_phase the residuals are √12(s − φ): the shared part is the phase's, whose
    # own row counts it; the slips' rows must not count it again
    fake = _fake([0] * 5, free_phase=True)
    r = np.r_[np.full(5, 0.7), 0.0]
    rho, _ = Problem.trigger_correlation(fake, r)
    assert rho == {0: 0.0}
    a = np.random.default_rng(3).normal(size=(6, 2))
    np.testing.assert_allclose(Problem._exchangeable_meat(fake, a, r), a.T @ a, rtol=1e-12)


def test_a_nan_residual_is_not_hidden():
    fake = _fake([0] * 4 + [1] * 4)
    _, sig2 = Problem.trigger_correlation(fake, np.r_[np.nan, np.zeros(7)])
    assert np.isnan(sig2)

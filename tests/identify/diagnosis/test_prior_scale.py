"""The evidence's choice of a prior scale on a refit's linearisation
(:func:`identify.diagnosis.prior_scale.evidence_scale`), against the exact evidence of a
linear-Gaussian model, and the scale a refit's priors already have."""

import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy import optimize

from identify.diagnosis.candidates import _prior_scale_of
from identify.diagnosis.prior_scale import evidence_scale
from identify.model.effects import get_effect

UNIT = 1e-8  # physical value of one scaled unit (m): the fit's scaled variables are not SI


class _Update:
    """MacKay's update for coefficients with a common prior sd σ (m): σ² = Σ c²/γ."""

    def prior_scale_update(self, values, edf):
        return math.sqrt(sum(v * v for v in values.values()) / edf)


def _solved(M, y, own, s0, other_sd):
    """y = M·c + e (unit noise, c in scaled units), priors: sd s0 (m) on ``own``,
    ``other_sd`` (m) on the rest; the penalised solution a refit would end at, and the
    evaluation evidence_scale reads (data rows, then one prior row per parameter)."""
    n = M.shape[1]
    sd = np.where(np.isin(np.arange(n), own), s0, other_sd)
    Jp = np.diag(UNIT / sd)  # (a prior row is the parameter's SI value over its sd)
    B = M.T @ M + Jp.T @ Jp
    th = np.linalg.solve(B, M.T @ y)
    names = [f"c{i}" for i in range(n)]
    prob = SimpleNamespace(
        n_theta=n, residual_groups=lambda: {"priors": (M.shape[0], M.shape[0] + n)},
        information=lambda w, ev: B,
        theta=SimpleNamespace(names=names, from_scaled=lambda t: [UNIT * v for v in t]))
    return prob, th, (None, None, np.vstack([M, Jp])), [names[i] for i in own]


def _log_evidence(M, y, own, s, other_sd):
    n = M.shape[1]
    var = np.where(np.isin(np.arange(n), own), (s / UNIT) ** 2, (other_sd / UNIT) ** 2)
    S = np.eye(M.shape[0]) + (M * var) @ M.T
    sign, logdet = np.linalg.slogdet(S)
    return -0.5 * (y @ np.linalg.solve(S, y) + logdet)


@pytest.mark.parametrize("s0", [0.3 * UNIT, 2 * UNIT, 20 * UNIT])
def test_the_scale_is_where_the_exact_evidence_peaks_from_any_start(s0):
    """Coefficients seen through a mixing matrix, some with a prior of another effect
    (kept): the scale found is the evidence's maximum over the own prior's scale,
    wherever the refit's prior sat."""
    rng = np.random.default_rng(3)
    n, m = 40, 120
    M = rng.normal(size=(m, n)) / math.sqrt(n)
    own = list(range(30))
    c = np.r_[rng.normal(0, 3.0, 30), rng.normal(0, 0.5, 10)]
    y = M @ c + rng.normal(size=m)
    prob, th, ev, names = _solved(M, y, own, s0, 0.5 * UNIT)
    got = evidence_scale(prob, th, ev, _Update(), names, s0)
    best = optimize.minimize_scalar(lambda ls: -_log_evidence(M, y, own, math.exp(ls) * UNIT, 0.5 * UNIT),
                                    bounds=(-5, 5), method="bounded", options={"xatol": 1e-8})
    assert got == pytest.approx(math.exp(best.x) * UNIT, rel=1e-3)
    assert 1.5 * UNIT < got < 6 * UNIT  # (the truth, 3, within the spread 30 coefficients leave)


def test_a_refit_with_the_priors_a_rival_chose_starts_from_that_scale():
    """A candidate refitted beside a rival carries the scale the evidence chose for it,
    not its default: the rounds read it from the problem's priors."""
    runs = [SimpleNamespace(name=f"r{i}", kind="events", k=2.13, span_s=10.0 + i, device="") for i in range(3)]
    eff = get_effect("drift_walk", runs)
    chosen = eff.priors(3.7e-8)
    prob = SimpleNamespace(prior_sd=lambda: {**chosen, "topo_c1": 0.01})
    assert _prior_scale_of(prob, eff, list(chosen)) == pytest.approx(3.7e-8)
    assert _prior_scale_of(SimpleNamespace(prior_sd=dict), eff, []) == eff.roughness


def test_the_scale_is_written_with_its_unit():
    assert get_effect("drift_walk").prior_scale_text(2e-8) == "walk intensity σ_w = 20 nm/√s"
    assert get_effect("topography_field").prior_scale_text(0.02).startswith("roughness ρ = 0.02 (friction;")

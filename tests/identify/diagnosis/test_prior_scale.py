"""The evidence's choice of a prior scale on a refit's linearisation
(:func:`identify.diagnosis.prior_scale.evidence_scale`), against a case with a closed form."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from identify.diagnosis.prior_scale import evidence_scale


class _Shrunk:
    """N coefficients c_i ~ N(0, σ²), each seen once with unit noise: y_i = c_i + e_i."""

    def prior_scale_update(self, values, edf):  # MacKay: σ² = Σ c²/γ
        return math.sqrt(sum(v * v for v in values.values()) / edf)


def _solved_at(y, s0):
    """The penalised solution at prior scale s0, as a refit would leave it, and the
    evaluation evidence_scale reads (the prior rows' Jacobian: 1/s0 on the diagonal)."""
    n = y.size
    names = [f"c{i}" for i in range(n)]
    prob = SimpleNamespace(
        n_theta=n, residual_groups=lambda: {"priors": (n, 2 * n)},
        information=lambda w, ev: np.eye(n) + np.eye(n) / s0**2,  # (data and priors)
        theta=SimpleNamespace(names=names, from_scaled=lambda th: list(th)))
    jac = np.vstack([np.eye(n), np.eye(n) / s0])
    w = y * s0**2 / (1 + s0**2)
    return prob, w, (None, None, jac), names


@pytest.mark.parametrize("s0", [0.1, 1.0, 10.0])
def test_the_scale_is_the_evidences_maximum_from_any_start(s0):
    """The marginal of y_i is N(0, 1 + σ²): the evidence peaks at σ² = mean(y²) − 1,
    wherever the refit's prior sat."""
    rng = np.random.default_rng(3)
    y = rng.normal(0.0, math.sqrt(1 + 2.0**2), 400)
    prob, w, ev, names = _solved_at(y, s0)
    got = evidence_scale(prob, w, ev, _Shrunk(), names, s0)
    assert got == pytest.approx(math.sqrt(np.mean(y**2) - 1.0), rel=1e-3)
    assert 1.7 < got < 2.3  # (and the truth, 2, within the sampling spread of 400 draws)


def test_a_prior_on_another_effect_keeps_its_scale():
    """Parameters with priors of effects named before (not ``own``) keep their prior."""
    rng = np.random.default_rng(4)
    y = rng.normal(0.0, math.sqrt(1 + 2.0**2), 300)
    prob, w, ev, names = _solved_at(y, 1.0)
    own = names[:200]
    got = evidence_scale(prob, w, ev, _Shrunk(), own, 1.0)
    assert got == pytest.approx(math.sqrt(np.mean(y[:200] ** 2) - 1.0), rel=1e-3)


def test_the_scale_is_written_with_its_unit():
    from identify.model.effects import get_effect

    assert get_effect("drift_walk").prior_scale_text(2e-8) == "walk intensity σ_w = 20 nm/√s"
    assert get_effect("topography_field").prior_scale_text(0.02).startswith("roughness ρ = 0.02 (friction;")

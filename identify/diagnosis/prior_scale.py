"""A candidate's prior scale (a rough track's roughness, a random walk's intensity) as the
evidence chooses it, on the refit's linearisation.

MacKay's update (:meth:`identify.model.effects.Effect.prior_scale_update`) is a fixed-point
iteration: the scale from the coefficients the current scale gave and their effective
degrees of freedom. Each step of it needs the coefficients at the new scale. Taken one
refit per step it creeps: from a walk's start of 10 nm/√s, three quick runs walking at
20 nm/√s gave 10.9 after the first refit, a step below the 25 % the rounds stopped at, so
the refit kept the prior at half the truth. On the refit's linearisation the coefficients
at any scale are one linear solve away, so the iteration is run to its fixed point there,
and a refit is needed only to correct for the model's curvature.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["evidence_scale"]

MAX_STEPS = 500
STEP_RTOL = 1e-4


def evidence_scale(prob, w, evaluated, eff, own: list, scale: float) -> float:
    """The scale at which MacKay's update of ``eff`` stands still on the linearisation of
    ``prob`` at its penalised solution ``w`` (``evaluated``: its evaluation with the
    Jacobians), the candidate's penalised parameters ``own`` carrying priors at ``scale``
    (other priors, of effects named before, kept as they are).

    With B_d the reduced data information of the scaled parameters and Λ₀ the priors'
    at the solution θ₀, the reduced data gradient there is −Λ₀θ₀ (the penalised gradient
    vanishes), so under priors Λ the linearised solution is θ(Λ) = (B_d + Λ)⁻¹(B_d + Λ₀)θ₀,
    and the coefficients' effective degrees of freedom are Σ_own 1 − [(B_d + Λ)⁻¹Λ]ᵢᵢ,
    as :meth:`identify.fitting.problem.Problem.penalised_counts` counts them."""
    p0, p1 = prob.residual_groups()["priors"]
    n = prob.n_theta
    B = prob.information(w, evaluated)
    Jp = evaluated[2][p0:p1][:, :n]
    Jp = np.asarray(Jp.toarray() if hasattr(Jp, "toarray") else Jp)
    lam0 = np.diag(Jp.T @ Jp).copy()  # (each prior row is one parameter's: diagonal)
    Bd = B - np.diag(lam0)
    names = prob.theta.names
    idx = np.array([names.index(m) for m in own], int)
    th0 = np.asarray(w[:n], float)
    rhs = (Bd + np.diag(lam0)) @ th0
    s = float(scale)
    for _ in range(MAX_STEPS):
        lam = lam0.copy()
        lam[idx] *= (scale / s) ** 2
        A_inv = np.linalg.pinv(Bd + np.diag(lam), rcond=1e-12, hermitian=True)
        th = A_inv @ rhs
        edf = float(np.sum(1.0 - np.diag(A_inv)[idx] * lam[idx]))
        values = dict(zip(names, (float(v) for v in prob.theta.from_scaled(th))))
        new = float(eff.prior_scale_update({m: values[m] for m in own}, edf))
        if not (math.isfinite(new) and new > 0):
            return s
        done = abs(math.log(new / s)) < STEP_RTOL
        s = new
        if done:
            break
    return s

"""What a candidate refit's solution says: its parameters' estimates with robust standard
errors, how much of each candidate parameter the model's own can mimic, and how the runs
left out for their regime read at its values."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = ["parameter_estimates", "confounding", "regime_of_left_out"]


def parameter_estimates(prob, w, ev) -> dict:
    """value, stderr, 95 % interval of every free parameter (robust covariance)."""
    from identify.fitting.result import standard_errors

    tm = prob.theta
    th = w[: prob.n_theta]
    try:
        C = prob.covariance(w, robust=True, evaluated=ev)
    except Exception:
        C = np.full((prob.n_theta, prob.n_theta), np.nan)
    lo, hi = tm.from_scaled(tm.lo), tm.from_scaled(tm.hi)

    def bound(i):
        """'lower'/'upper' where the estimate sits on a bound (its value is the bound's,
        not the data's: a damping at −3e-7 N s/m is the least the model allows)."""
        tol = 1e-6 * max(1.0, abs(tm.lo[i]), abs(tm.hi[i]))
        return "lower" if th[i] - tm.lo[i] <= tol else "upper" if tm.hi[i] - th[i] <= tol else None

    return {n: dict(value=float(v), stderr=se, ci95=list(ci) if ci is not None else None, at_bound=bound(i),
                    bound=float(lo[i] if bound(i) == "lower" else hi[i]) if bound(i) else None)
            for i, (n, v, (se, _, ci)) in enumerate(zip(tm.names, tm.from_scaled(th), standard_errors(tm, th, C, 1.0)))}


def confounding(prob, w, ev, extra: Sequence[str], defining: Sequence[str] | None = None) -> dict:
    """How much of each candidate parameter the other free parameters can mimic.

    In the information metric (nuisances eliminated), R² of the candidate's direction
    regressed on the others' (1: exactly absorbed), and the others it leans on most;
    for the ``defining`` ones of ``extra`` only, when given (a nuisance freed beside the
    effect, as motion blur's clock shifts, is no evidence either way)."""
    names = prob.theta.names
    if not extra:
        return {}
    try:
        I = prob.information(w, evaluated=ev)
    except Exception as err:
        return {n: dict(r2=float("nan"), partners=[], note=str(err)) for n in extra}
    if not np.all(np.isfinite(I)):
        # (LAPACK would print "DLASCL parameter number 4 had an illegal value" and return NaN)
        return {n: dict(r2=float("nan"), partners=[], note="the information matrix is not finite at this solution")
                for n in extra}
    out = {}
    for n in extra:
        if n not in names or (defining is not None and n not in defining):
            continue
        c = names.index(n)
        others = [i for i in range(len(names)) if names[i] not in extra]
        Icc = I[c, c]
        if not others or Icc <= 0:
            # no information at all on it: as confounded as it gets (nothing to name)
            out[n] = dict(r2=0.0 if Icc > 0 else 1.0, partners=[], confounded=Icc <= 0)
            continue
        Ibb = I[np.ix_(others, others)]
        Ibc = I[others, c]
        coef = np.linalg.lstsq(Ibb, Ibc, rcond=1e-12)[0]
        r2 = float(np.clip(Ibc @ coef / Icc, 0.0, 1.0))
        corr = [(names[i], float(I[i, c] / math.sqrt(max(I[i, i] * Icc, 1e-300)))) for i in others]
        corr.sort(key=lambda t: -abs(t[1]))
        # the top partners always (R² can come from several weak ones)
        out[n] = dict(r2=r2, partners=[dict(parameter=a, score_correlation=b) for a, b in corr[:3]],
                      confounded=bool(r2 > 0.99))
    return out


def regime_of_left_out(task, values: dict) -> dict:
    """The runs left out for their regime, simulated at the refit's values
    (:func:`identify.fitting.regime_check.regime_check`), JSON-able; its error instead if the
    check itself fails (the refit's numbers stand)."""
    from identify.fitting.regime_check import regime_check
    from identify.model.laws import get_law
    from identify.model.symbolic import Model

    try:
        return regime_check(Model(get_law(task.law)), values, task.regime_runs).to_json()
    except Exception as err:
        return dict(error=f"{type(err).__name__}: {err}")

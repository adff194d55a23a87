"""The pieces of a :class:`identify.fitting.result.FitResult` computed from a solved
problem, which :func:`identify.fitting.result.build_result` puts together: the free
parameters' estimates and the flags of those the data cannot fix, the covariance in
natural units and the correlations, the fixed parameters, the run table, the solver's
record and the timing.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from identify.fitting.estimates import ParameterEstimate
from identify.fitting.intervals import standard_errors
from identify.fitting.solver_outcome import unconverged_flag
from identify.model.params import spec

__all__ = ["CONFOUNDED", "UNDETERMINED_REL", "free_estimates", "natural_covariance", "correlations",
           "flag_confounded", "add_fixed_estimates", "run_table", "solver_record", "timing_record"]

CONFOUNDED = 0.99  # |correlation| above which two parameters are reported as confounded
UNDETERMINED_REL = 1.0  # relative standard error above which a value is not a number to use


def free_estimates(prob, w, C, scale, best: dict, gap: dict | None, start: Mapping,
                   true_values: Mapping | None) -> dict:
    """The free parameters' estimates at ``w`` (value, standard error and 95 % interval
    from the covariance ``C`` × ``scale``), each flagged where the data cannot fix it (a
    parameter with a prior is not flagged for a wide interval: near its prior's zero it
    has the prior's spread, which is what the prior says, not a failure of the fit)."""
    tm = prob.theta
    priored = set(prob.prior_sd())
    th = w[: prob.n_theta]
    vals = tm.from_scaled(th)
    params: dict = {}
    for i, (n, (se, _, ci)) in enumerate(zip(tm.names, standard_errors(tm, th, C, scale))):
        params[n] = ParameterEstimate(
            name=n, value=float(vals[i]), stderr=se, ci95=ci, free=True, unit=spec(n).unit,
            init=float(start.get(n, np.nan)), flag=_flag(tm, th, i, se, vals[i], best, gap, n in priored),
            true=float(true_values[n]) if true_values and n in true_values else None,
        )
    return params


def _flag(tm, th, i: int, se, value, best: dict, gap: dict | None, priored: bool = False) -> str | None:
    """Why free parameter i's value is not a number to use (at a bound, undetermined, or
    where an unconverged solve stopped), or None."""
    rng = tm.hi[i] - tm.lo[i]
    if min(th[i] - tm.lo[i], tm.hi[i] - th[i]) < 1e-6 * max(rng, 1.0):
        return "at a bound: the data push it against its limit"
    if se is None or not np.isfinite(se):
        return "undetermined: no finite standard error (singular information)"
    if value != 0 and abs(se / value) > UNDETERMINED_REL and not priored:
        return f"undetermined: standard error {100 * abs(se / value):.0f} % of the value"
    if not best.get("success", True):
        # the covariance of a point the solver did not finish at is not an interval:
        # calibration seed 44 stopped in a degenerate basin (τ = 2.8e-5 s) with a τ
        # standard error of 3 % that missed the truth by 80000 of them
        return unconverged_flag(best.get("status"), gap)
    return None


def natural_covariance(prob, w, C, scale) -> np.ndarray:
    """The free parameters' covariance in natural units, from ``C`` × ``scale`` of the
    scaled ones."""
    d = prob.theta.jacobian_diag(w[: prob.n_theta])
    cov_nat = np.full((prob.n_theta, prob.n_theta), np.nan)
    for i in range(prob.n_theta):
        for j in range(prob.n_theta):
            cov_nat[i, j] = C[i, j] * scale * d[i] * d[j]
    return cov_nat


def correlations(names, cov_nat: np.ndarray) -> dict:
    """{a: {b: correlation}} of the parameters ``names`` from their covariance; None where
    a standard error is zero or not finite."""
    corr: dict = {}
    sd = np.sqrt(np.diag(cov_nat))
    for i, a in enumerate(names):
        corr[a] = {}
        for j, b in enumerate(names):
            c = cov_nat[i, j] / (sd[i] * sd[j]) if sd[i] > 0 and sd[j] > 0 and np.isfinite(sd[i] * sd[j]) else None
            corr[a][b] = float(np.clip(c, -1, 1)) if c is not None and np.isfinite(c) else None
    return corr


def flag_confounded(params: dict, corr: dict, names) -> None:
    """Flag, in ``params``, each parameter not flagged yet whose |correlation| with
    another exceeds :data:`CONFOUNDED`."""
    for a in names:
        partners = [b for b in names if b != a and corr[a][b] is not None and abs(corr[a][b]) > CONFOUNDED]
        if partners and params[a].flag is None:
            params[a].flag = f"confounded with {', '.join(partners)} (|correlation| > {CONFOUNDED})"


def add_fixed_estimates(params: dict, prob, true_values: Mapping | None) -> None:
    """The fixed parameters of the law (and any the user fixed) added to ``params``, for
    the record."""
    for n in prob.model.friction_names + tuple(k2 for k2 in prob.opts.fixed if k2 not in prob.model.friction_names):
        if n not in params and n in prob.values:
            params[n] = ParameterEstimate(name=n, value=float(prob.values[n]), stderr=None, ci95=None,
                                          free=False, unit=spec(n).unit,
                                          true=float(true_values[n]) if true_values and n in true_values else None)


def run_table(prob, params: dict, excluded: list) -> list:
    """One entry per run: used (slips, regime, noise, warnings, the model's stick-edge
    warning at the fitted values among them) or left out and why."""
    runs = []
    fitted = {**prob.values, **{n: p.value for n, p in params.items()}}
    for rd in prob.runs:
        ev = rd.events
        edge = rd.stick_edge(fitted)  # a model-side warning beside the event extraction's
        runs.append(dict(name=rd.name, used=True, reason=None, kind=rd.kind,
                         n_slips=int(len(rd.trigger_steps)) if rd.kind == "events" else 0,
                         regime=getattr(ev, "regime", "?"), noise_nm=rd.sigma * 1e9,
                         warnings=list(getattr(ev, "warnings", [])) + ([edge] if edge else [])))
    for name, why in excluded:
        runs.append(dict(name=name, used=False, reason=why, kind=None, n_slips=0, regime=None, noise_nm=None,
                         warnings=[]))
    return runs


def solver_record(prob, best: dict, wall_s: float, gap: dict | None) -> dict:
    """How the solve ended (status, iterations, the mode sequence's changes, restarts, the
    gap of an unconverged one), and by which solver."""
    return dict(status=best["status"], success=best["success"], iterations=best["iterations"],
                wall_time_s=float(wall_s), triggers_moved=int(best.get("triggers_moved", 0)),
                slips_inserted=int(best.get("slips_inserted", 0)),
                slips_removed=int(best.get("slips_removed", 0)),
                restarts=list(best.get("restarts", [])), solution_gap=gap,
                sequence_not_kept=best.get("sequence_not_kept"),
                **{k: best[k] for k in ("ipopt_status", "restoration_iterations", "handed_over") if k in best},
                method=("Gauss-Newton SQP (Gauss-Newton Hessian, l1-merit line search)"
                        if prob.opts.solver == "gauss-newton" else "Ipopt (Gauss-Newton Hessian)"),
                trigger=prob.opts.trigger)


def timing_record(prob, best: dict, results: list, wall_s: float) -> dict:
    """Where the fit's ``wall_s`` went: the arcs and their Jacobians (the problem's
    counter), the solves (the starts' and the best's), the set-up."""
    c = prob.counter
    solver_s = sum(x["wall_s"] for x in results) + (best["wall_s"] if not any(x is best for x in results) else 0.0)
    return dict(total_s=float(wall_s), arc_s=c["arc_s"], jac_s=c["jac_s"], arc_calls=c["arc_calls"],
                jac_calls=c["jac_calls"], solver_s=float(solver_s), setup_s=float(max(wall_s - solver_s, 0)))

"""Fit results: estimates with honest uncertainty, a readable report, JSON, profiles.

A parameter the data cannot fix is flagged (at a bound, standard error beyond 100 %,
confounded with another parameter, or a flat profile) and its number is shown as such,
never as a confident estimate.

:class:`FitResult` and :func:`build_result`, which makes one of a solved problem, live
here; the pieces are in modules of their own: one parameter's estimate and profile
(:mod:`identify.fitting.estimates`), standard errors and intervals
(:mod:`identify.fitting.intervals`), the flags and figures a result is built of
(:mod:`identify.fitting.result_build`), what the solver's end says of the values
(:mod:`identify.fitting.solver_outcome`), the text report
(:mod:`identify.fitting.result_report`) and the profile likelihood
(:mod:`identify.fitting.profile_likelihood`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from identify.fitting.creep_onset import creep_onsets
from identify.fitting.estimates import ParameterEstimate as ParameterEstimate
from identify.fitting.estimates import Profile as Profile
from identify.fitting.estimates import number_from_json
from identify.fitting.intervals import Z95 as Z95
from identify.fitting.intervals import covariance_and_scale
from identify.fitting.intervals import standard_errors as standard_errors
from identify.fitting.profile_likelihood import BETTER_TOL as BETTER_TOL
from identify.fitting.profile_likelihood import CHI2_95 as CHI2_95
from identify.fitting.profile_likelihood import MAX_EXTEND as MAX_EXTEND
from identify.fitting.profile_likelihood import REFINE_STEPS as REFINE_STEPS
from identify.fitting.profile_likelihood import profile as profile
from identify.fitting.result_build import CONFOUNDED as CONFOUNDED
from identify.fitting.result_build import UNDETERMINED_REL as UNDETERMINED_REL
from identify.fitting.result_build import (
    add_fixed_estimates,
    correlations,
    flag_confounded,
    free_estimates,
    natural_covariance,
    run_table,
    solver_record,
    timing_record,
)
from identify.fitting.result_report import fit_report
from identify.fitting.solver_outcome import NEAR_SOLUTION_FEAS_UM as NEAR_SOLUTION_FEAS_UM
from identify.fitting.solver_outcome import NEAR_SOLUTION_SE as NEAR_SOLUTION_SE
from identify.fitting.solver_outcome import SAME_SOLUTION_HALF_CHI2 as SAME_SOLUTION_HALF_CHI2
from identify.fitting.solver_outcome import best_found as best_found
from identify.fitting.solver_outcome import solution_gap

__all__ = ["ParameterEstimate", "FitResult", "Profile", "build_result", "profile"]

SUSPECT_REDCHI = 2.0  # reduced χ² above which a result is reported as not explained by the noise


@dataclass
class FitResult:
    """The outcome of :func:`identify.fit`."""

    parameters: dict
    correlation: dict
    covariance: np.ndarray | None
    chi2: float
    dof: int
    redchi: float
    aic: float
    bic: float
    cost: float
    law: str
    coating: str
    n_runs: int
    n_events: int
    n_observations: int
    nlp_size: dict
    solver: dict
    multistart: dict
    runs: list
    timing: dict
    start_source: str
    problem: Any = field(repr=False, default=None)
    w: np.ndarray | None = field(repr=False, default=None)
    profiles: dict = field(default_factory=dict)
    # runs left out for their regime (identify.fitting.regime_check.RegimeRun): the diagnosis
    # checks the fitted model against them
    regime_runs: list = field(repr=False, default_factory=list)
    # parameters fitted with Gaussian priors (FitOptions.priors, walk_intensity): how many,
    # their penalty (not in chi2) and the effective number of parameters they count as
    priors: dict = field(default_factory=dict)

    # ---------------------------------------------------------------- access
    @property
    def values(self) -> dict:
        return {n: p.value for n, p in self.parameters.items()}

    def __getitem__(self, name: str) -> ParameterEstimate:
        return self.parameters[name]

    @property
    def free(self) -> list:
        return [n for n, p in self.parameters.items() if p.free]

    @property
    def concerns(self) -> list:
        """Why this result is not one to use as it stands (empty: none found): the solver
        did not converge (and did not stop near its solution: :attr:`stopped_near`), the
        noise does not explain the misfit (reduced χ² above ``SUSPECT_REDCHI``), a free
        parameter sits at a bound, or the values contradict the model's physics (μmin ≥
        μmax). The report's first line and ``identify fit``'s exit status (3) say so."""
        out = []
        s = self.solver
        if not (s.get("success", True) or self.stopped_near):
            out.append(f"the solver did not converge ({s.get('status')})")
        if self.dof > 0 and np.isfinite(self.redchi) and self.redchi > SUSPECT_REDCHI:
            out.append(f"reduced chi-square {self.redchi:.3g}: the model does not explain the data to their noise")
        at_bound = [n for n, p in self.parameters.items() if p.free and (p.flag or "").startswith("at a bound")]
        if at_bound:
            out.append(f"{', '.join(at_bound)} at a bound of the search")
        v = self.values
        if "mu_min" in v and "mu_max" in v and v["mu_min"] >= v["mu_max"]:
            out.append(f"mu_min {v['mu_min']:.4g} >= mu_max {v['mu_max']:.4g}")
        return out

    @property
    def stopped_near(self) -> bool:
        """The solver did not converge but stopped near the solution its Gauss–Newton
        model predicts (within ``NEAR_SOLUTION_SE`` standard errors, continuity to
        ``NEAR_SOLUTION_FEAS_UM``): where a solution sits on an arc's kink, no line
        search gains, and an interval shifted by half its standard error at most is
        still one. Not a concern; the headline and the flags give the distance."""
        s = self.solver
        gap = s.get("solution_gap") or {}
        return not s.get("success", True) and bool(gap.get("near"))

    def headline(self) -> str:
        """One line: whether the fit is one to use, and if not, why."""
        if self.concerns:
            return "!! NOT A RESULT TO USE AS IT STANDS: " + "; ".join(self.concerns)
        if self.stopped_near:
            return (f"Fit stopped near its solution ({self.solver.get('status')}: within "
                    f"~{self.solver['solution_gap']['within_se']:.2g} standard errors of it), reduced chi-square "
                    f"{self.redchi:.4g}: the values below are estimates with calibrated intervals, shifted by that "
                    "much at most")
        return (f"Fit converged ({self.solver.get('status')}), reduced chi-square {self.redchi:.4g}: "
                "the values below are estimates with calibrated intervals")

    def uncertainty(self, covariance: str) -> dict:
        """Standard errors and 95 % intervals of the free parameters under another
        covariance than the fit's option (``robust``, ``cluster`` or ``model``, see
        :class:`FitOptions`): name -> {stderr, ci95}. The fit itself is unchanged."""
        self._needs_problem("uncertainty")
        prob, w = self.problem, self.w
        th = w[: prob.n_theta]
        C, scale = covariance_and_scale(prob, w, covariance, self.redchi)
        return {n: dict(stderr=se, ci95=list(ci) if ci else None)
                for n, (se, _, ci) in zip(prob.theta.names, standard_errors(prob.theta, th, C, scale))}

    # ---------------------------------------------------------------- text
    def report(self, show_correlations: float = 0.5) -> str:
        """The readable report (:func:`identify.fitting.result_report.fit_report`)."""
        return fit_report(self, show_correlations)

    def to_json(self) -> dict:
        return dict(
            parameters={n: p.to_json() for n, p in self.parameters.items()},
            correlation=self.correlation,
            cost=self.cost, chi2=self.chi2, dof=self.dof, redchi=self.redchi, aic=self.aic, bic=self.bic,
            law=self.law, coating=self.coating, n_runs=self.n_runs, n_events=self.n_events,
            n_observations=self.n_observations, nlp_size=self.nlp_size, solver=self.solver,
            multistart=self.multistart, runs=self.runs, timing=self.timing, start=self.start_source,
            profiles={n: p.to_json() for n, p in self.profiles.items()},
            priors=self.priors,
            concerns=self.concerns,
            covariance=None if self.covariance is None else np.asarray(self.covariance).tolist(),
        )

    to_dict = to_json

    @classmethod
    def from_dict(cls, d: dict) -> FitResult:
        """The result :meth:`to_dict` (or ``fit.json``) describes: everything its report,
        JSON and concerns show. It carries no problem, so what needs the fitted NLP
        (:meth:`profile`, :meth:`uncertainty`, :meth:`save_plots`) asks for a refit."""
        cov = d.get("covariance")
        return cls(
            parameters={n: ParameterEstimate.from_json(n, p) for n, p in d["parameters"].items()},
            correlation=d.get("correlation", {}),
            covariance=None if cov is None else np.array(cov, float),
            chi2=number_from_json(d["chi2"]), dof=int(d["dof"]), redchi=number_from_json(d["redchi"]),
            aic=number_from_json(d["aic"]), bic=number_from_json(d["bic"]), cost=number_from_json(d["cost"]),
            law=d["law"], coating=d["coating"], n_runs=int(d["n_runs"]),
            n_events=int(d["n_events"]), n_observations=int(d["n_observations"]), nlp_size=d.get("nlp_size", {}),
            solver=d.get("solver", {}), multistart=d.get("multistart", {}), runs=d.get("runs", []),
            timing=d.get("timing", {}), start_source=d.get("start", ""),
            profiles={n: Profile.from_json(p) for n, p in (d.get("profiles") or {}).items()},
            priors=d.get("priors") or {},
        )

    def save(self, path) -> Path:
        """Write :meth:`to_dict` as strict JSON (non-finite numbers as null)."""
        from identify.jsonio import write_json

        return write_json(path, self.to_dict())

    @classmethod
    def load(cls, path) -> FitResult:
        """A result saved by :meth:`save` (or ``identify fit --json``)."""
        import json

        with open(path, encoding="utf-8") as fh:
            return cls.from_dict(json.load(fh))

    def _needs_problem(self, what: str) -> None:
        if self.problem is None or self.w is None:
            raise ValueError(f"{what}: this result carries no fitted problem (read from JSON?): "
                             "fit the data again to compute it")

    # ---------------------------------------------------------------- more work
    def profile(self, name: str, n_points: int = 13, span: float = 4.0, progress=None) -> Profile:
        """Profile likelihood of ``name`` (a free parameter). The result is unchanged:
        :meth:`with_profiles` gives a result that carries the profile."""
        self._needs_problem("profile")
        return profile(self, name, n_points=n_points, span=span, progress=progress)

    def with_profiles(self, *profiles: Profile) -> FitResult:
        """A copy of this result carrying ``profiles``: each parameter keeps its
        calibrated ``ci95`` and gets the profile's interval as ``ci95_profile``; a side the
        profile leaves open is flagged (undetermined above, below, or both)."""
        params = {n: dataclasses.replace(p) for n, p in self.parameters.items()}
        for pr in profiles:
            p = params[pr.name]
            p.ci95_profile = pr.ci95
            und = pr.undetermined
            if pr.better:
                note = (f"the profile found a better fit at {pr.better[0]:.4g} (chi-square lower by "
                        f"{-pr.better[1]:.3g}): the fit's optimum is a local one")
                p.flag = note if not p.flag else f"{p.flag}; {note}"
            if und:
                note = ("undetermined: flat profile (the data do not fix it)" if und == "both" else
                        f"undetermined {und}: the profile stays below the 95% threshold "
                        f"{'up to' if und == 'above' else 'down to'} "
                        f"{pr.reach[1 if und == 'above' else 0]:.4g}")
                p.flag = note if not p.flag else f"{p.flag}; {note}"
        return dataclasses.replace(self, parameters=params,
                                   profiles={**self.profiles, **{pr.name: pr for pr in profiles}})

    def model_elongation(self, i_run: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The fitted model's elongation at the frames of run ``i_run`` (m), read from the
        solved problem's plateau nodes: (frame times s, model elongation m, plateau index
        of each frame, -1 where a frame belongs to none)."""
        from identify.fitting.rundata import plateaus_from_triggers

        ev, step, levels, offset = self._run_levels("model_elongation", i_run)
        pof = plateaus_from_triggers(ev, self.problem.runs[i_run].trigger_steps)
        e_model = np.full(len(ev.trace.time_s), np.nan)
        ok = (pof >= 0) & (pof < len(levels))
        e_model[ok] = step * ev.steps[ok] - levels[pof[ok]] + offset
        return ev.trace.time_s, e_model, pof

    def model_staircase(self, i_run: int) -> tuple[np.ndarray, np.ndarray]:
        """The fitted model's elongation of run ``i_run`` as the staircase it is, at every
        puller step rather than at the frames: (times s, elongation m), one point per
        step from the trace's start to its end, each level held until the next time (draw
        with ``drawstyle="steps-post"``). A slip drops the level at its trigger step; the
        slip itself (milliseconds) is drawn as the vertical edge there."""
        from identify.traces.events import step_counts

        ev, step, levels, offset = self._run_levels("model_staircase", i_run)
        tr = ev.trace
        fp, phi = tr.step_frequency, ev.step_phase
        t0, t1 = float(tr.time_s[0]), float(tr.time_s[-1])
        n0, n1 = (int(v) for v in step_counts(np.array([t0, t1]), fp, phi))
        n = np.arange(n0, n1 + 1)
        t = np.maximum((n + phi) / fp, t0)
        t = np.append(t, t1)  # the last level held to the last frame
        n = np.append(n, n1)
        idx = np.searchsorted(np.asarray(self.problem.runs[i_run].trigger_steps), n, side="right")
        e = step * n - levels[np.clip(idx, 0, len(levels) - 1)] + offset
        return t, e

    def static_friction_curve(self, rest_time_s) -> tuple[np.ndarray, np.ndarray | None]:
        """The fitted law's static friction coefficient after a rest of ``rest_time_s``
        from a rejuvenated contact, as a slip sees it (ψ plus the stick band
        A·ln(1 + v_stick/vc), zero without the stick option), and its 95 % pointwise band
        from the covariance by the delta method on the fit's own scale: (μs, (2, n)
        array of lower and upper bounds, or None where the fit has no covariance)."""
        self._needs_problem("static_friction_curve")
        prob, w = self.problem, self.w
        t = np.asarray(rest_time_s, float)

        def curve(th):
            P = prob.params(th)
            band = float(P["A"] * np.log1p(P["v_stick"] / P["vc"]))
            return prob.law.static_coefficient(prob.law.rest(prob.law.rejuvenated_state(P), t, P), P) + band

        th = np.asarray(w[: prob.n_theta], float)
        mu = curve(th)
        if self.covariance is None or not np.all(np.isfinite(self.covariance)):
            return mu, None
        d = self.problem.theta.jacobian_diag(th)
        C = np.asarray(self.covariance) / np.outer(d, d)  # back to the scaled parameters
        J = np.empty((len(t), len(th)))
        for i in range(len(th)):
            h = 1e-5 * max(1.0, abs(th[i]))
            up, dn = th.copy(), th.copy()
            up[i] += h
            dn[i] -= h
            J[:, i] = (curve(up) - curve(dn)) / (2 * h)
        half = Z95 * np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", J, C, J), 0.0))
        return mu, np.vstack([mu - half, mu + half])

    def _run_levels(self, what: str, i_run: int):
        """(events, fitted step m, plateau levels m, zero offset m) of run ``i_run``."""
        from identify.model.symbolic import LENGTH_UNIT

        self._needs_problem(what)
        prob, w = self.problem, self.w
        step = float(prob.model.step(prob.params(w[: prob.n_theta])))
        levels = w[prob.i_x + np.nonzero(prob.pl_run == i_run)[0]] * LENGTH_UNIT
        offset = float(w[prob.i_off + i_run] * LENGTH_UNIT) if prob.n_off else 0.0
        return prob.runs[i_run].events, step, levels, offset

    def plot(self, ax=None):
        """The fit's headline figure: every slip's static friction against its rest, with
        the fitted law and its 95 % band (:func:`identify.plots.fit.plot_static_friction`)."""
        from identify.plots.fit import plot_static_friction

        self._needs_problem("plot")
        return plot_static_friction(self, ax=ax)

    def save_plots(self, folder) -> list:
        from identify.plots.fit import save_fit_plots

        self._needs_problem("save_plots")
        return save_fit_plots(self, folder)


def build_result(prob, best: dict, results: list, excluded: list, start: Mapping, start_source: str,
                 coating: str, true_values: Mapping | None, wall_s: float) -> FitResult:
    """Statistics, covariance, flags and the run table of a solved :class:`Problem`."""
    w = best["w"]
    r = prob.residuals(w)
    n_obs = prob.n_observations()
    chi2, k, priors = _penalised_statistics(prob, w, r)
    dof = max(round(n_obs - k), 1) if priors else prob.dof()
    redchi = chi2 / dof
    C, scale = covariance_and_scale(prob, w, getattr(prob.opts, "covariance", "robust"), redchi)
    gap = solution_gap(prob, w) if not best.get("success", True) else None
    params = free_estimates(prob, w, C, scale, best, gap, start, true_values)
    cov_nat = natural_covariance(prob, w, C, scale)
    corr = correlations(prob.theta.names, cov_nat)
    flag_confounded(params, corr, prob.theta.names)
    add_fixed_estimates(params, prob, true_values)
    runs = run_table(prob, params, excluded)
    found = best_found([x["f"] for x in results])
    return FitResult(
        parameters=params, correlation=corr, covariance=cov_nat, chi2=chi2, dof=dof, redchi=redchi,
        aic=chi2 + 2 * k, bic=chi2 + k * math.log(max(n_obs, 1)), cost=float(best["f"]),
        law=prob.law.name, coating=coating, n_runs=len(prob.runs), n_events=prob.E,
        n_observations=n_obs,
        nlp_size=dict(variables=prob.n_w, constraints=prob.n_g, residuals=int(len(r)), drop_frames=int(prob.D)),
        solver=dict(solver_record(prob, best, wall_s, gap), creep_onsets=_creep_onsets(prob, w)),
        multistart=dict(starts=len(results), best_found=found, costs=[float(x["f"]) for x in results]),
        runs=runs,
        timing=timing_record(prob, best, results, wall_s),
        start_source=start_source, problem=prob, w=w, priors=priors,
    )


def _penalised_statistics(prob, w, r) -> tuple:
    """(χ², free dimensions, the priors' record) of a solved problem. With priors the χ²
    is the data's, their penalty apart, and the penalised parameters count by the
    effective degrees of freedom the penalty leaves them
    (:meth:`identify.fitting.problem.Problem.penalised_counts`), so that the reduced χ²,
    AIC and BIC measure the data's fit, as without priors."""
    sd = prob.prior_sd()
    if not sd:
        return float(r @ r) + prob.chi2_constant(), prob.n_effective(), {}
    prob.central_differences()  # (the effective count reads the information, as the covariance does)
    chi2, k = prob.penalised_counts(r, w)
    p0, p1 = prob.residual_groups()["priors"]
    walk = getattr(prob.opts, "walk_intensity", None)
    return chi2, k, dict(
        parameters=len(sd), penalty_chi2=float(r[p0:p1] @ r[p0:p1]),
        effective_parameters=float(len(sd) - (prob.n_effective() - k)),
        walk_intensity_m_per_sqrt_s=None if walk is None else float(walk))


def _creep_onsets(prob, w) -> list:
    """:func:`identify.fitting.creep_onset.creep_onsets` for the report: the slips at the
    model's kink, where an unconverged solve may have stopped and a converged one's ±
    describes one side of it ([] if it cannot be told)."""
    try:
        return creep_onsets(prob, w)
    except Exception:  # (the report stands without it)
        return []

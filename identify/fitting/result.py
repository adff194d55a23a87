"""Fit results: estimates with honest uncertainty, a readable report, JSON, profiles.

A parameter the data cannot fix is flagged (at a bound, standard error beyond 100 %,
confounded with another parameter, or a flat profile) and its number is shown as such,
never as a confident estimate.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from identify.fitting.convergence import message
from identify.model.params import SPECS
from identify.progress import Stage, reporter

__all__ = ["ParameterEstimate", "FitResult", "Profile", "build_result", "profile"]

CONFOUNDED = 0.99  # |correlation| above which two parameters are reported as confounded
UNDETERMINED_REL = 1.0  # relative standard error above which a value is not a number to use
NEAR_SOLUTION_SE = 0.5
"""A solve that stopped unconverged, at a point its Gauss–Newton model puts within this
many standard errors of that model's solution (½χ² within ½·this², continuity to
:data:`NEAR_SOLUTION_FEAS_UM`), has its values flagged with that distance rather than as
untrustworthy: an interval shifted by half its standard error at most is still one.
Measured (the 8-run model-made diagnosis benchmark's baseline, 420da57 on): it ends
``Line_Search_Failed`` at ½χ² 0.0207 from its Gauss–Newton solution (0.2 standard
errors), where the solver's own stall test asks 0.01."""
NEAR_SOLUTION_FEAS_UM = 1e-3  # 1 nm of continuity: 1/90 of the camera noise
Z95 = 1.959963984540054
CHI2_95 = 3.841458820694124  # 95 % quantile of χ² with 1 degree of freedom
SUSPECT_REDCHI = 2.0  # reduced χ² above which a result is reported as not explained by the noise
MAX_EXTEND = 6  # doublings of a profile's walk past its grid before a side is called open
REFINE_STEPS = 3  # bisections of the bracket where a profile crosses the 95 % threshold
# a profile point this much below the fit's χ² is a better fit (the solvers' own stall
# tolerance is 0.01 of ½χ², so 0.1 of χ² is beyond what stopping early explains)
BETTER_TOL = 0.1


def _num(x) -> float:
    """A JSON number back to a float (strict JSON writes a non-finite one as null)."""
    return float("nan") if x is None else float(x)


def _pair(x):
    """A JSON two-list back to the tuple it was (None stays None)."""
    return None if x is None else tuple(x)


@dataclass
class ParameterEstimate:
    """One parameter: value (SI) ± stderr, 95 % interval, whether it was free."""

    name: str
    value: float
    stderr: float | None
    ci95: tuple | None
    free: bool
    unit: str
    init: float | None = None
    flag: str | None = None
    true: float | None = None
    # the profile likelihood's 95 % interval, beside (never instead of) ``ci95``; a side
    # the profile never closes is None there (the parameter is undetermined that way)
    ci95_profile: tuple | None = None

    def to_json(self) -> dict:
        return dict(value=self.value, stderr=self.stderr,
                    ci95=list(self.ci95) if self.ci95 is not None else None,
                    ci95_profile=list(self.ci95_profile) if self.ci95_profile is not None else None,
                    free=self.free, unit=self.unit, init=self.init, flag=self.flag, true=self.true)

    @classmethod
    def from_json(cls, name: str, d: dict) -> ParameterEstimate:
        return cls(name=name, value=_num(d["value"]), stderr=d.get("stderr"),
                   ci95=_pair(d.get("ci95")), free=bool(d["free"]), unit=d.get("unit", "-"), init=d.get("init"),
                   flag=d.get("flag"), true=d.get("true"), ci95_profile=_pair(d.get("ci95_profile")))


@dataclass
class Profile:
    """Profile likelihood of one parameter: Δχ² against its value.

    ``values``, ``delta_chi2``: the points whose constrained fit converged (the only ones
    that count); ``failed``: the values where it did not. ``ci95``: (lower, upper), a
    side None where Δχ² never reaches the threshold (``open_below``, ``open_above``:
    the data do not bound the parameter that way over the range walked, ``reach``);
    None when both are open (``flat``)."""

    name: str
    values: np.ndarray
    delta_chi2: np.ndarray
    ci95: tuple | None
    flat: bool
    threshold: float
    open_below: bool = False
    open_above: bool = False
    failed: np.ndarray = field(default_factory=lambda: np.zeros(0))
    reach: tuple | None = None  # the farthest converged values walked, (below, above)
    # (value, Δχ² < 0) where a constrained fit beat the fit itself: the fit's optimum is
    # a local one, and ci95 is the interval about this better point
    better: tuple | None = None

    @property
    def undetermined(self) -> str | None:
        """'above', 'below', 'both' or None: where the profile leaves the parameter open."""
        if self.open_below and self.open_above:
            return "both"
        return "above" if self.open_above else "below" if self.open_below else None

    def interval_text(self, fmt: str = ".4g") -> str:
        """The interval with its open sides written out, e.g. ``[0.89, open)``."""
        if self.ci95 is None:
            return "no 95% bound on either side"
        lo = "(open" if self.ci95[0] is None else f"[{self.ci95[0]:{fmt}}"
        hi = "open)" if self.ci95[1] is None else f"{self.ci95[1]:{fmt}}]"
        return f"{lo}, {hi}"

    def to_json(self) -> dict:
        return dict(name=self.name, values=self.values.tolist(), delta_chi2=self.delta_chi2.tolist(),
                    ci95=list(self.ci95) if self.ci95 else None, flat=self.flat, threshold=self.threshold,
                    undetermined=self.undetermined, failed=np.asarray(self.failed).tolist(),
                    better=list(self.better) if self.better else None,
                    reach=list(self.reach) if self.reach else None)

    @classmethod
    def from_json(cls, d: dict) -> Profile:
        und = d.get("undetermined")
        return cls(name=d["name"], values=np.array(d["values"], float), delta_chi2=np.array(d["delta_chi2"], float),
                   ci95=_pair(d.get("ci95")), flat=bool(d["flat"]), threshold=float(d["threshold"]),
                   open_below=und in ("below", "both"), open_above=und in ("above", "both"),
                   failed=np.array(d.get("failed") or [], float), reach=_pair(d.get("reach")),
                   better=_pair(d.get("better")))

    def plot(self, ax=None):
        from identify.plots.fit import plot_profile

        return plot_profile(self, ax=ax)


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
        did not converge, the noise does not explain the misfit (reduced χ² above
        ``SUSPECT_REDCHI``), a free parameter sits at a bound, or the values contradict
        the model's physics (μmin ≥ μmax). The report's first line and ``identify fit``'s
        exit status (3) say so."""
        out = []
        s = self.solver
        if not s.get("success", True):
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

    def headline(self) -> str:
        """One line: whether the fit is one to use, and if not, why."""
        if self.concerns:
            return "!! NOT A RESULT TO USE AS IT STANDS: " + "; ".join(self.concerns)
        return (f"Fit converged ({self.solver.get('status')}), reduced chi-square {self.redchi:.4g}: "
                "the values below are estimates with calibrated intervals")

    def uncertainty(self, covariance: str) -> dict:
        """Standard errors and 95 % intervals of the free parameters under another
        covariance than the fit's option (``robust``, ``cluster`` or ``model``, see
        :class:`FitOptions`): name -> {stderr, ci95}. The fit itself is unchanged."""
        self._needs_problem("uncertainty")
        prob, w = self.problem, self.w
        th = w[: prob.n_theta]
        C, scale = _covariance(prob, w, covariance, self.redchi)
        return {n: dict(stderr=se, ci95=list(ci) if ci else None)
                for n, (se, _, ci) in zip(prob.theta.names, standard_errors(prob.theta, th, C, scale))}

    # ---------------------------------------------------------------- text
    def report(self, show_correlations: float = 0.5) -> str:
        s = self.solver
        lines = [
            self.headline(),
            "[[Fit Statistics]]",
            f"    model              = hybrid stick/slip, {self.law} aging law",
            f"    coating            = {self.coating} (fixed parameters from its preset)",
            f"    runs used          = {self.n_runs} ({self.n_events} slips)",
            f"    observations       = {self.n_observations} (plateau frames, triggers, creep means)"
            + (f"; {s['observations_detected']} in the detected sequence: the mode sequence the fit decided "
               f"changed which frames count (those taken while the block moved at a moved, inserted or "
               f"removed slip)" if s.get("observations_detected", self.n_observations) != self.n_observations
               else ""),
            f"    NLP                = {self.nlp_size['variables']} variables, {self.nlp_size['constraints']} "
            f"constraints, {self.nlp_size['residuals']} residuals (a plateau's frames enter through their "
            "mean; their scatter about it is a constant of the chi-square)",
            f"    solver             = {s['method']}: {s['status']} after {s['iterations']} "
            f"iterations, {s['wall_time_s']:.2f} s",
            f"    status             = {message(s['status'])}",
            *(["    Ipopt              = "
               + ("stopped at the fit's Gauss-Newton convergence test" if s["ipopt_status"] == "User_Requested_Stop"
                  else f"returned {s['ipopt_status']}")
               + f"; {s.get('restoration_iterations', 0)} restoration iteration(s)"]
              if s.get("ipopt_status") else []),
            *(["    triggers           = intervals (after the uniform encoding's fit); no trigger "
               "residuals in the chi-square or the covariance"] if s.get("trigger") == "interval" else []),
            *([f"    stick option       = {s['stick_option']}"] if s.get("stick_option") else []),
            f"    mode sequence      = {s.get('triggers_moved', 0)} trigger step(s) moved, "
            f"{s.get('slips_inserted', 0)} missed slip(s) inserted, "
            f"{s.get('slips_removed', 0)} spurious slip(s) removed by the fit",
            *([f"    stopped            = {_gap_text(s['solution_gap'])}"] if s.get("solution_gap") else []),
            *([f"    not kept           = the mode sequence the fit decided ({x['triggers_moved']} trigger(s) "
               f"moved, {x['slips_inserted']} inserted, {x['slips_removed']} removed): it ended at excess χ² "
               f"{x['excess_after']:.6g} against {x['excess_before']:.6g} on the sequence as detected"]
              if (x := s.get("sequence_not_kept")) else []),
            *([f"    arcs not finished  = {s['arcs_failed']} at trial points the solver rejected "
               f"(last: {s.get('arc_failure', '?')})"] if s.get("arcs_failed") else []),
            *[f"    after insertion    = {x['slips_inserted']} slip(s): solved afresh, ½χ² {x['fresh_half_chi2']:.6g}"
              + (f" ({x['fresh_suspect']}; from the warm point {x['warm_half_chi2']:.6g}, {x['kept']} kept)"
                 if x.get("warm_half_chi2") is not None else "")
              for x in s.get("restarts", [])],
            f"    chi-square         = {self.chi2:.6g}",
            f"    reduced chi-square = {self.redchi:.6g}  (dof = {self.dof})",
            f"    Akaike info crit   = {self.aic:.6g}",
            f"    Bayesian info crit = {self.bic:.6g}",
            f"    start              = {self.start_source}",
        ]
        ms = self.multistart
        if ms.get("starts", 1) > 1:
            lines.append(f"    multistart         = best value found {ms['best_found']} of {ms['starts']} times "
                         f"(½χ² within {SAME_SOLUTION_HALF_CHI2:g} of the best)"
                         + {True: "; the best point is unique among the spread starts",
                            False: "; NOT unique: another solution as good lies elsewhere (flagged below)"}
                         .get(ms.get("unique"), ""))
        lines.append("[[Variables]]")
        width = max(len(n) for n in self.parameters)
        for n, p in self.parameters.items():
            unit = p.unit if p.unit != "-" else ""
            if not p.free:
                lines.append(f"    {n + ':':<{width + 1}} {p.value:.6g} {unit} (fixed)")
                continue
            if p.stderr is not None and np.isfinite(p.stderr) and p.value != 0:
                rel = 100 * abs(p.stderr / p.value)
                txt = f"{p.value:.6g} +/- {p.stderr:.3g} ({rel:.2f}%)"
            else:
                txt = f"{p.value:.6g} +/- (not available)"
            ci = f" 95% [{p.ci95[0]:.4g}, {p.ci95[1]:.4g}]" if p.ci95 else ""
            init = f" (init = {p.init:.5g})" if p.init is not None else ""
            true = f" [true = {p.true:.6g}]" if p.true is not None else ""
            lines.append(f"    {n + ':':<{width + 1}} {txt} {unit}{ci}{init}{true}")
            if n in self.profiles:
                lines.append(f"    {'':<{width + 1}}   profile 95% {self.profiles[n].interval_text()}")
            if p.flag:
                lines.append(f"    {'':<{width + 1}} ! {p.flag}")
        corr = []
        names = list(self.correlation)
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                c = self.correlation[a][b]
                if c is not None and abs(c) > show_correlations:
                    corr.append((abs(c), f"    C({a}, {b}) = {c:+.4f}"))
        lines.append(f"[[Correlations]] (unreported correlations are < {show_correlations:.3f})")
        lines += [c[1] for c in sorted(corr, reverse=True)] or ["    (none)"]
        if self.profiles:
            lines.append("[[Profiles]]")
            for n, pr in self.profiles.items():
                und = {"both": " (flat: undetermined)", "above": " (undetermined above)",
                       "below": " (undetermined below)"}.get(pr.undetermined or "", "")
                bad = f"; {len(pr.failed)} point(s) not converged, left out" if len(pr.failed) else ""
                lines.append(f"    {n}: 95% {pr.interval_text()}{und}, {len(pr.values)} points{bad}")
                if pr.better:
                    lines.append(f"        ! a better fit lies at {n} = {pr.better[0]:.4g} (chi-square lower by "
                                 f"{-pr.better[1]:.3g}): the fit stopped in a local minimum; the interval is "
                                 f"about that point. Refit from there (start={{'{n}': {pr.better[0]:.4g}}})")
        lines.append("[[Runs]]")
        for r in self.runs:
            if r["used"]:
                lines.append(f"    {r['name']}: used, {r['n_slips']} slips, {r['regime']} ({r['kind']})")
                # what the event extraction saw (a wrong step size, backward jumps, ...)
                lines += [f"        warning: {w}" for w in r.get("warnings", [])]
            else:
                lines.append(f"    {r['name']}: LEFT OUT: {r['reason']}")
        t = self.timing
        lines.append("[[Timing]]")
        lines.append(f"    total {t['total_s']:.2f} s: arcs {t['arc_s']:.2f} s ({t['arc_calls']} batches), "
                     f"arc Jacobians {t['jac_s']:.2f} s ({t['jac_calls']}), solver linear algebra, "
                     f"assembly and the rest {max(t['total_s'] - t['arc_s'] - t['jac_s'], 0):.2f} s")
        if t.get("sequence_s"):
            lines.append(f"    of the total, deciding the mode sequence (moved triggers, missed slips, "
                         f"trials): {t['sequence_s']:.2f} s")
        return "\n".join(lines)

    def to_json(self) -> dict:
        return dict(
            parameters={n: p.to_json() for n, p in self.parameters.items()},
            correlation=self.correlation,
            cost=self.cost, chi2=self.chi2, dof=self.dof, redchi=self.redchi, aic=self.aic, bic=self.bic,
            law=self.law, coating=self.coating, n_runs=self.n_runs, n_events=self.n_events,
            n_observations=self.n_observations, nlp_size=self.nlp_size, solver=self.solver,
            multistart=self.multistart, runs=self.runs, timing=self.timing, start=self.start_source,
            profiles={n: p.to_json() for n, p in self.profiles.items()},
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
            chi2=_num(d["chi2"]), dof=int(d["dof"]), redchi=_num(d["redchi"]), aic=_num(d["aic"]),
            bic=_num(d["bic"]), cost=_num(d["cost"]), law=d["law"], coating=d["coating"], n_runs=int(d["n_runs"]),
            n_events=int(d["n_events"]), n_observations=int(d["n_observations"]), nlp_size=d.get("nlp_size", {}),
            solver=d.get("solver", {}), multistart=d.get("multistart", {}), runs=d.get("runs", []),
            timing=d.get("timing", {}), start_source=d.get("start", ""),
            profiles={n: Profile.from_json(p) for n, p in (d.get("profiles") or {}).items()},
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

    def save_plots(self, folder) -> list:
        from identify.plots.fit import save_fit_plots

        self._needs_problem("save_plots")
        return save_fit_plots(self, folder)


def _scaled_ci(theta, sigma, tm, i):
    lo, hi = theta - Z95 * sigma, theta + Z95 * sigma
    if tm.log[i]:
        return (float(tm.scale[i] * math.exp(lo)), float(tm.scale[i] * math.exp(hi)))
    return (float(tm.scale[i] * lo), float(tm.scale[i] * hi))


def _covariance(prob, w, mode: str, redchi: float):
    """(covariance of the scaled parameters, the factor it is used with): the sandwich
    carries its own scale; the model-based one is scaled by χ²_red (scale_covariance)."""
    C = prob.covariance(w, robust=mode)
    scale = (redchi if prob.opts.scale_covariance else 1.0) if mode == "model" else 1.0
    return C, scale


def standard_errors(tm, th, C, scale) -> list:
    """Per parameter (stderr in natural units or None, σ on the fit scale, 95 % interval)."""
    d = tm.jacobian_diag(th)
    out = []
    for i in range(len(tm.names)):
        var = C[i, i] * scale if np.isfinite(C[i, i]) else np.nan
        sig_th = math.sqrt(var) if var >= 0 and np.isfinite(var) else float("nan")
        se = abs(d[i]) * sig_th if np.isfinite(sig_th) else None
        try:
            ci = _scaled_ci(th[i], sig_th, tm, i) if se is not None else None
        except OverflowError:  # a log-scaled parameter the data do not determine at all
            ci = None
        out.append((se, sig_th, ci))
    return out


SAME_SOLUTION_HALF_CHI2 = 0.05
"""Starts whose ½χ² ends within this of the best count as having found it: the parameters
then within ~0.3 standard errors (√(2·0.05)), a difference the solver's own tolerances do
not resolve (its stall test asks 0.01; a fit that stopped 0.02 short is measured, above).
A relative tolerance (1e-6 of ½χ² before) put that line at 0.005 on an 8-run fit."""


def best_found(costs) -> int:
    """How many of the starts' final ½χ² (``costs``) are the best's, within
    :data:`SAME_SOLUTION_HALF_CHI2`."""
    finite = [float(f) for f in costs if np.isfinite(f)]
    if not finite:
        return 0
    best = min(finite)
    return sum(1 for f in finite if f - best <= SAME_SOLUTION_HALF_CHI2)


def _solution_gap(prob, w) -> dict | None:
    """:meth:`identify.fitting.gauss_newton.GaussNewtonSQP.solution_gap` at an unconverged solve's point, with
    the parameters' distance it implies (``within_se``); None when it cannot be computed."""
    try:
        gap = prob.solution_gap(w)
    except Exception:  # (the report stands without it)
        return None
    h = gap["half_chi2"]
    gap["within_se"] = math.sqrt(2.0 * h) if np.isfinite(h) else float("nan")
    gap["near"] = bool(gap["within_se"] <= NEAR_SOLUTION_SE and gap["continuity_um"] <= NEAR_SOLUTION_FEAS_UM)
    return gap


def _gap_text(gap: dict) -> str:
    if not np.isfinite(gap["half_chi2"]):
        return f"its Gauss–Newton model has no solution here (continuity {gap['continuity_um']:.1g} µm)"
    return (f"½χ² {gap['half_chi2']:.2g} away from the solution its Gauss–Newton step predicts (the parameters within "
            f"~{gap['within_se']:.2g} standard errors of it), continuity {gap['continuity_um']:.1g} µm")


def _unconverged_flag(status, gap: dict | None) -> str:
    """The flag of a parameter whose solve did not converge: how near it stopped, when
    that is known and near (:data:`NEAR_SOLUTION_SE`), else a warning not to trust it."""
    # (the numbers behind it are on the report's 'stopped' line)
    if gap is not None and gap["near"]:
        return (f"not converged ({status}): within ~{gap['within_se']:.2g} standard errors of the solution its "
                "Gauss–Newton step predicts")
    far = (f" (~{gap['within_se']:.2g} standard errors from the solution its Gauss–Newton step predicts)"
           if gap is not None and np.isfinite(gap["within_se"]) else "")
    return f"not converged ({status}): the value is where the solver stopped, its interval not to be trusted" + far


def build_result(prob, best: dict, results: list, excluded: list, start: Mapping, start_source: str,
                 coating: str, true_values: Mapping | None, wall_s: float) -> FitResult:
    """Statistics, covariance, flags and the run table of a solved :class:`Problem`."""
    w = best["w"]
    tm = prob.theta
    r = prob.residuals(w)
    chi2 = float(r @ r) + prob.chi2_constant()
    n_obs = prob.n_observations()
    k = prob.n_effective()
    dof = prob.dof()
    redchi = chi2 / dof
    C, scale = _covariance(prob, w, getattr(prob.opts, "covariance", "robust"), redchi)
    gap = _solution_gap(prob, w) if not best.get("success", True) else None
    th = w[: prob.n_theta]
    vals = tm.from_scaled(th)
    d = tm.jacobian_diag(th)
    params: dict = {}
    cov_nat = np.full((prob.n_theta, prob.n_theta), np.nan)
    for i, (n, (se, _, ci)) in enumerate(zip(tm.names, standard_errors(tm, th, C, scale))):
        flag = None
        rng = tm.hi[i] - tm.lo[i]
        if min(th[i] - tm.lo[i], tm.hi[i] - th[i]) < 1e-6 * max(rng, 1.0):
            flag = "at a bound: the data push it against its limit"
        elif se is None or not np.isfinite(se):
            flag = "undetermined: no finite standard error (singular information)"
        elif vals[i] != 0 and abs(se / vals[i]) > UNDETERMINED_REL:
            flag = f"undetermined: standard error {100 * abs(se / vals[i]):.0f} % of the value"
        elif not best.get("success", True):
            # the covariance of a point the solver did not finish at is not an interval:
            # calibration seed 44 stopped in a degenerate basin (τ = 2.8e-5 s) with a τ
            # standard error of 3 % that missed the truth by 80000 of them
            flag = _unconverged_flag(best.get("status"), gap)
        params[n] = ParameterEstimate(
            name=n, value=float(vals[i]), stderr=se, ci95=ci, free=True, unit=SPECS[n].unit,
            init=float(start.get(n, np.nan)), flag=flag,
            true=float(true_values[n]) if true_values and n in true_values else None,
        )
    for i in range(prob.n_theta):
        for j in range(prob.n_theta):
            cov_nat[i, j] = C[i, j] * scale * d[i] * d[j]
    corr: dict = {}
    sd = np.sqrt(np.diag(cov_nat))
    for i, a in enumerate(tm.names):
        corr[a] = {}
        for j, b in enumerate(tm.names):
            c = cov_nat[i, j] / (sd[i] * sd[j]) if sd[i] > 0 and sd[j] > 0 and np.isfinite(sd[i] * sd[j]) else None
            corr[a][b] = float(np.clip(c, -1, 1)) if c is not None and np.isfinite(c) else None
    for a in tm.names:
        partners = [b for b in tm.names if b != a and corr[a][b] is not None and abs(corr[a][b]) > CONFOUNDED]
        if partners and params[a].flag is None:
            params[a].flag = f"confounded with {', '.join(partners)} (|correlation| > {CONFOUNDED})"
    # the fixed parameters of the law (and any the user fixed), for the record
    for n in prob.model.friction_names + tuple(k2 for k2 in prob.opts.fixed if k2 not in prob.model.friction_names):
        if n not in params and n in prob.values:
            params[n] = ParameterEstimate(name=n, value=float(prob.values[n]), stderr=None, ci95=None,
                                          free=False, unit=SPECS[n].unit,
                                          true=float(true_values[n]) if true_values and n in true_values else None)
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
    found = best_found([x["f"] for x in results])
    c = prob.counter
    solver_s = sum(x["wall_s"] for x in results) + (best["wall_s"] if not any(x is best for x in results) else 0.0)
    return FitResult(
        parameters=params, correlation=corr, covariance=cov_nat, chi2=chi2, dof=dof, redchi=redchi,
        aic=chi2 + 2 * k, bic=chi2 + k * math.log(max(n_obs, 1)), cost=float(best["f"]),
        law=prob.law.name, coating=coating, n_runs=len(prob.runs), n_events=prob.E,
        n_observations=n_obs,
        nlp_size=dict(variables=prob.n_w, constraints=prob.n_g, residuals=int(len(r))),
        solver=dict(status=best["status"], success=best["success"], iterations=best["iterations"],
                    wall_time_s=float(wall_s), triggers_moved=int(best.get("triggers_moved", 0)),
                    slips_inserted=int(best.get("slips_inserted", 0)),
                    slips_removed=int(best.get("slips_removed", 0)),
                    restarts=list(best.get("restarts", [])), solution_gap=gap,
                    sequence_not_kept=best.get("sequence_not_kept"),
                    **{k: best[k] for k in ("ipopt_status", "restoration_iterations") if k in best},
                    method=("Gauss-Newton SQP (Gauss-Newton Hessian, l1-merit line search)"
                            if prob.opts.solver == "gauss-newton" else "Ipopt (Gauss-Newton Hessian)"),
                    trigger=prob.opts.trigger),
        multistart=dict(starts=len(results), best_found=found, costs=[float(x["f"]) for x in results]),
        runs=runs,
        timing=dict(total_s=float(wall_s), arc_s=c["arc_s"], jac_s=c["jac_s"], arc_calls=c["arc_calls"],
                    jac_calls=c["jac_calls"], solver_s=float(solver_s), setup_s=float(max(wall_s - solver_s, 0))),
        start_source=start_source, problem=prob, w=w,
    )


def profile(result: FitResult, name: str, n_points: int = 13, span: float = 4.0, progress=None) -> Profile:
    """Δχ² of the best fit with ``name`` held at each of ``n_points`` values.

    The grid covers ±``span`` standard errors on the parameter's fit scale (log for
    positive parameters), or, without a finite standard error, a factor e^±2 (log) or
    its bounds. Each point starts from the last converged solution before it, walking
    out from the optimum; a point whose constrained fit does not converge never counts
    (it is listed in ``failed``: its Δχ² is where a solver stopped, not the likelihood).
    Past the grid's edge without reaching the threshold, the walk goes on, doubling the
    distance, until it does, or reaches the bound, or (log scale) a decade, or
    ``MAX_EXTEND`` doublings. Where Δχ² crosses the threshold (3.84, × the reduced χ²
    when the covariance is scaled) between two points, the bracket is bisected
    ``REFINE_STEPS`` times before the crossing is interpolated. A side with no crossing
    is open: the data do not bound the parameter that way.

    ``progress`` (:mod:`identify.progress`): None draws a bar of the points with the time
    left on a terminal, False is silent, a callable gets each message.
    """
    progress = reporter(progress)
    prob = result.problem
    if prob is None or result.w is None:
        raise ValueError("profile: this result carries no problem (read from JSON?)")
    tm = prob.theta
    if name not in tm.names:
        raise ValueError(f"profile: {name!r} is not a free parameter ({', '.join(tm.names)})")
    i = tm.names.index(name)
    w_best = result.w
    th0 = w_best[i]
    p = result.parameters[name]
    d = tm.jacobian_diag(w_best[: prob.n_theta])[i]
    sig = (p.stderr / abs(d)) if p.stderr and np.isfinite(p.stderr) and d else None
    half = span * sig if sig else (2.0 if tm.log[i] else 0.5 * max(tm.hi[i] - tm.lo[i], 1e-6))
    lo, hi = max(th0 - half, tm.lo[i]), min(th0 + half, tm.hi[i])
    grid = np.linspace(lo, hi, n_points)
    # (a grid point within rounding of the optimum would be a second, identical point)
    grid = np.unique(np.concatenate([grid[np.abs(grid - th0) > 1e-6 * max(half, 1e-12)], [th0]]))
    chi2_min = result.chi2
    scale = result.redchi if prob.opts.scale_covariance else 1.0
    thr = CHI2_95 * max(scale, 1.0)
    out = {th0: 0.0}
    sols = {th0: w_best}
    failed: list = []
    count = [0]
    # the points to solve: the grid, then up to REFINE_STEPS bisections per side; a side
    # that crosses early skips the rest of its grid, one that does not cross adds points
    stage = Stage(progress, f"profile of {name}", len(grid) - 1 + 2 * REFINE_STEPS)

    def point(w, val, note):
        """Δχ² with the parameter held at ``val``, warm-started from ``w``; the solution,
        or None where the constrained fit did not converge."""
        w = w.copy()
        w[i] = val
        res = prob.solve(w, fixed={i: val})
        count[0] += 1
        stage.advance(note)
        rr = prob.residuals(res["w"])
        if not res.get("success") or not np.all(np.isfinite(rr)):
            failed.append(val)
            return None
        out[val] = float(rr @ rr + prob.chi2_constant() - chi2_min)
        sols[val] = res["w"]
        return res["w"]

    decade = math.log(10.0)
    def beyond(direction):
        return [v for v in out if direction * (v - th0) > 0]

    for direction in (+1, -1):
        side = grid[grid > th0] if direction > 0 else grid[grid < th0][::-1]
        w = w_best
        for k, val in enumerate(side):
            got = point(w, val, f"{name} held at {tm.scale[i] * (math.exp(val) if tm.log[i] else val):.4g}")
            w = got if got is not None else _nearest_out(sols, th0, val)
            if got is not None and out[val] >= thr:
                stage.total -= len(side) - k - 1  # (the points beyond add nothing to the interval)
                break
        val = side[-1] if len(side) else th0
        for _ in range(MAX_EXTEND):
            if any(out[v] >= thr for v in beyond(direction)):
                break
            far = max(beyond(direction) or [th0], key=lambda v: direction * (v - th0))
            if tm.log[i] and abs(far - th0) >= decade:
                break
            nxt = th0 + 2 * (val - th0) if val != th0 else th0 + direction * half
            nxt = min(max(nxt, tm.lo[i]), tm.hi[i])
            if nxt == val:
                break
            val = nxt
            stage.total += 1
            point(sols[far], val, f"extending to {val:.4g} (scaled)")
        # refine the bracket where Δχ² crosses the threshold
        for step in range(REFINE_STEPS):
            pts = sorted((v for v in out if direction * (v - th0) >= 0), key=lambda v: direction * (v - th0))
            br = next(((a, b) for a, b in zip(pts, pts[1:]) if out[a] < thr <= out[b]), None)
            if br is None:
                stage.total -= REFINE_STEPS - step
                break
            a, b = br
            point(sols[a], 0.5 * (a + b), f"refining the 95% crossing at {0.5 * (a + b):.4g} (scaled)")
    vals = np.array(sorted(out))
    dchi = np.array([out[v] for v in vals])
    nat = np.array(tm.scale[i] * (np.exp(vals) if tm.log[i] else vals))

    def crossing(seq_v, seq_d):
        for a in range(len(seq_d) - 1):
            if seq_d[a] < thr <= seq_d[a + 1]:
                f = (thr - seq_d[a]) / (seq_d[a + 1] - seq_d[a])
                return float(seq_v[a] + f * (seq_v[a + 1] - seq_v[a]))
        return None

    # a constrained fit better than the fit itself: the fit stopped in a local minimum.
    # The interval is then the one about the best point found, and the profile says so
    better = None
    j0 = int(np.argmin(np.abs(vals - th0)))
    if dchi.min() < -BETTER_TOL:
        j0 = int(np.argmin(dchi))
        better = (float(nat[j0]), float(dchi[j0]))
        dchi_ref = dchi - dchi[j0]
    else:
        dchi_ref = dchi
    up = crossing(nat[j0:], dchi_ref[j0:])
    down = crossing(nat[: j0 + 1][::-1], dchi_ref[: j0 + 1][::-1])
    flat = down is None and up is None
    ci = None if flat else (down, up)
    bad = np.array(sorted(tm.scale[i] * (np.exp(v) if tm.log[i] else v) for v in failed))
    return Profile(name=name, values=nat, delta_chi2=dchi, ci95=ci, flat=flat, threshold=thr,
                   open_below=down is None, open_above=up is None, failed=bad,
                   reach=(float(nat[0]), float(nat[-1])), better=better)


def _nearest_out(sols: dict, th0: float, val: float) -> np.ndarray:
    """The converged solution nearest ``val`` on its side of the optimum (the warm start
    after a point that failed)."""
    same = [v for v in sols if (v - th0) * (val - th0) >= 0]
    return sols[min(same, key=lambda v: abs(v - val))]

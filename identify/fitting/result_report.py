"""The text report of a fit (:meth:`identify.fitting.result.FitResult.report`): its
statistics and the solver's notes, the variables with their intervals and flags, the
correlations, profiles, runs and timing, one section per function.
"""

from __future__ import annotations

import numpy as np

from identify.fitting.convergence import message
from identify.fitting.creep_onset import onset_text
from identify.fitting.solver_outcome import SAME_SOLUTION_HALF_CHI2, gap_text

__all__ = ["fit_report"]


def fit_report(result, show_correlations: float = 0.5) -> str:
    """The report of ``result`` (a :class:`identify.fitting.result.FitResult`); correlations
    above ``show_correlations`` in magnitude are listed."""
    return "\n".join([*_statistics(result), *_variables(result), *_correlations(result, show_correlations),
                      *_profiles(result), *_runs(result), *_timing(result)])


def _statistics(result) -> list:
    """The headline and the fit's statistics: data, NLP, solver, χ², information criteria,
    start and multistart."""
    s = result.solver
    lines = [
        result.headline(),
        "[[Fit Statistics]]",
        f"    model              = hybrid stick/slip, {result.law} aging law",
        f"    coating            = {result.coating} (fixed parameters from its preset)",
        f"    runs used          = {result.n_runs} ({result.n_events} slips)",
        f"    observations       = {result.n_observations} (plateau frames, "
        + (f"{result.nlp_size['drop_frames']} frames around the slips one by one, "
           if result.nlp_size.get("drop_frames") else "")
        + "triggers, creep means)"
        + (f"; {s['observations_detected']} in the detected sequence: the mode sequence the fit decided "
           f"changed which frames count (those taken while the block moved at a moved, inserted or "
           f"removed slip)" if s.get("observations_detected", result.n_observations) != result.n_observations
           else ""),
        f"    NLP                = {result.nlp_size['variables']} variables, {result.nlp_size['constraints']} "
        f"constraints, {result.nlp_size['residuals']} residuals (a plateau's frames enter through their "
        "mean; their scatter about it is a constant of the chi-square)",
        f"    solver             = {s['method']}: {s['status']} after {s['iterations']} "
        f"iterations, {s['wall_time_s']:.2f} s",
        f"    status             = {message(s['status'])}",
        *_solver_notes(s),
        f"    chi-square         = {result.chi2:.6g}",
        *_prior_line(result.priors),
        f"    reduced chi-square = {result.redchi:.6g}  (dof = {result.dof})",
        f"    Akaike info crit   = {result.aic:.6g}",
        f"    Bayesian info crit = {result.bic:.6g}",
        f"    start              = {result.start_source}",
    ]
    ms = result.multistart
    if ms.get("starts", 1) > 1:
        lines.append(f"    multistart         = best value found {ms['best_found']} of {ms['starts']} times "
                     f"(½χ² within {SAME_SOLUTION_HALF_CHI2:g} of the best)"
                     + {True: "; the best point is unique among the spread starts",
                        False: "; NOT unique: another solution as good lies elsewhere (flagged below)"}
                     .get(ms.get("unique"), ""))
    return lines


def _prior_line(priors: dict) -> list:
    """What the priors did, where the fit had any: the chi-square above is the data's."""
    if not priors:
        return []
    walk = priors.get("walk_intensity_m_per_sqrt_s")
    why = (f"; the walk's modes at a Wiener process of {walk * 1e9:.4g} nm/√s" if walk else "")
    def num(key, fmt):  # (a number saved as null, non-finite, reads as such)
        v = priors.get(key)
        return "n/a" if v is None else format(v, fmt)

    return [f"    priors             = {priors['parameters']} parameter(s) with zero-mean Gaussian priors{why}: "
            f"penalty {num('penalty_chi2', '.4g')} (not in the chi-square), counted as "
            f"{num('effective_parameters', '.3g')} parameter(s) in dof, AIC and BIC"]


def _solver_notes(s: dict) -> list:
    """The lines on how the solver and the mode sequence ended, each only where it applies:
    Ipopt, interval triggers, the stick option, moved and inserted slips, where an
    unconverged solve stopped, a sequence not kept, arcs not finished, fresh restarts."""
    return [
        *(["    Ipopt              = "
           + ("stopped at the fit's Gauss-Newton convergence test" if s["ipopt_status"] == "User_Requested_Stop"
              else f"returned {s['ipopt_status']}")
           + f"; {s.get('restoration_iterations', 0)} restoration iteration(s)"
           + (f"; it ended {s['handed_over']} and the Gauss-Newton SQP went on from there"
              if s.get("handed_over") else "")]
          if s.get("ipopt_status") else []),
        *(["    triggers           = intervals (after the uniform encoding's fit); no trigger "
           "residuals in the chi-square or the covariance"] if s.get("trigger") == "interval" else []),
        *([f"    stick option       = {s['stick_option']}"] if s.get("stick_option") else []),
        f"    mode sequence      = {s.get('triggers_moved', 0)} trigger step(s) moved, "
        f"{s.get('slips_inserted', 0)} missed slip(s) inserted, "
        f"{s.get('slips_removed', 0)} spurious slip(s) removed by the fit",
        *([f"    stopped            = {gap_text(s['solution_gap'])}"
           + (f"; {onset_text(s['creep_onsets'])}" if s.get("creep_onsets") else "")] if s.get("solution_gap") else []),
        *([f"    kink               = {onset_text(s['creep_onsets'])}; the ± are this side's of it, a profile "
           "(result.profile(name)) sees both"] if s.get("creep_onsets") and not s.get("solution_gap") else []),
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
    ]


def _variables(result) -> list:
    """Each parameter: value ± standard error, 95 % interval, start, truth, profile
    interval and flag (a fixed one: its value)."""
    lines = ["[[Variables]]"]
    width = max(len(n) for n in result.parameters)
    for n, p in result.parameters.items():
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
        if n in result.profiles:
            lines.append(f"    {'':<{width + 1}}   profile 95% {result.profiles[n].interval_text()}")
        if p.flag:
            lines.append(f"    {'':<{width + 1}} ! {p.flag}")
    return lines


def _correlations(result, show_correlations: float) -> list:
    """The correlations above ``show_correlations`` in magnitude, largest first."""
    corr = []
    names = list(result.correlation)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            c = result.correlation[a][b]
            if c is not None and abs(c) > show_correlations:
                corr.append((abs(c), f"    C({a}, {b}) = {c:+.4f}"))
    return [f"[[Correlations]] (unreported correlations are < {show_correlations:.3f})",
            *([c[1] for c in sorted(corr, reverse=True)] or ["    (none)"])]


def _profiles(result) -> list:
    """Each profile's interval, its open sides and failed points, and a better fit it found."""
    lines = []
    if result.profiles:
        lines.append("[[Profiles]]")
        for n, pr in result.profiles.items():
            und = {"both": " (flat: undetermined)", "above": " (undetermined above)",
                   "below": " (undetermined below)"}.get(pr.undetermined or "", "")
            bad = f"; {len(pr.failed)} point(s) not converged, left out" if len(pr.failed) else ""
            lines.append(f"    {n}: 95% {pr.interval_text()}{und}, {len(pr.values)} points{bad}")
            if pr.better:
                # (not "fit again from there": measured on the small FOTAS fit, the solve from
                # the profile's better point of A ended in a pocket beside a kink of the χ²
                # surface, A 0.0231 ± 0.0005 against the truth 0.015, where the fit's 0.0143 ±
                # 0.0036 held it; the profile's interval spans the valley, the ± a pocket)
                lines.append(f"        ! a better fit lies at {n} = {pr.better[0]:.4g} (chi-square lower by "
                             f"{-pr.better[1]:.3g}): the fit stopped in a local minimum of a valley with kinks; "
                             "use the profile's interval, which is about that point (a fit solved from there "
                             "sits in another pocket of the valley, and its ± describes that pocket only)")
    return lines


def _runs(result) -> list:
    """Each run: used (slips, regime, the event extraction's warnings) or left out and why."""
    lines = ["[[Runs]]"]
    for r in result.runs:
        if r["used"]:
            lines.append(f"    {r['name']}: used, {r['n_slips']} slips, {r['regime']} ({r['kind']})")
            # what the event extraction saw (a wrong step size, backward jumps, ...)
            lines += [f"        warning: {w}" for w in r.get("warnings", [])]
        else:
            lines.append(f"    {r['name']}: LEFT OUT: {r['reason']}")
    return lines


def _timing(result) -> list:
    """Where the time went: arcs, their Jacobians, the rest, and deciding the mode sequence."""
    t = result.timing
    lines = ["[[Timing]]"]
    lines.append(f"    total {t['total_s']:.2f} s: arcs {t['arc_s']:.2f} s ({t['arc_calls']} batches), "
                 f"arc Jacobians {t['jac_s']:.2f} s ({t['jac_calls']}), solver linear algebra, "
                 f"assembly and the rest {max(t['total_s'] - t['arc_s'] - t['jac_s'], 0):.2f} s")
    if t.get("sequence_s"):
        lines.append(f"    of the total, deciding the mode sequence (moved triggers, missed slips, "
                     f"trials): {t['sequence_s']:.2f} s")
    return lines

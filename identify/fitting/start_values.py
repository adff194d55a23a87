"""Where a fit starts: the coating's preset or the reduced analysis's values, and starts spread
over each parameter's plausible range when a solution looks wrong."""

from __future__ import annotations

import logging

import numpy as np

from identify.fitting.options import FitOptions

log = logging.getLogger(__name__)


REDUCED_Z = 1.96  # a reduced-analysis value starts the fit only if its 95 % interval excludes 0
# ... and μmax alone, when the others are undetermined, if its standard error is below
# this: the static friction has saturated within the rests recorded
MU_MAX_SATURATED_SE = 0.02


def start_values(runs: list, law, preset: dict, opts: FitOptions) -> tuple[dict, str]:
    """Start from the reduced analysis where it can say something (DESIGN.md §2): its
    μmax, μmin and τ, when the Eq. 9 fit determines all three, else the preset; values
    the caller gives override either. Returns the start and where each value came from."""
    start = {n: preset[n] for n in opts.free}
    origin = {n: "preset" for n in start}
    ev_runs = [r.events for r in runs if r.kind == "events"]
    try:
        from identify.traces.reduced import reduced_fit

        red = [ev.reduced for ev in ev_runs if getattr(ev, "reduced", None) is not None]
        if len(red) >= 4 and law.name in ("exponential", "logistic"):
            fitted = reduced_fit(red, laws=(law.name,)).fits[law.name]
            names = [n for n in ("mu_max", "mu_min", "tau") if n in start and n in fitted.parameters]
            # measured on the two-condition plan's Monte Carlo: the Eq. 9 fit over two rest
            # times put μmin at 0.004-0.07 ± 0.2 in 4 of 20 repeats, and those fits ended
            # far from the truth. The three values are fitted together (τ and μmax moved
            # with that μmin), so one the fit cannot tell from zero discredits all three.
            vague = [n for n in names if not (np.isfinite(fitted.parameters[n])
                                              and np.isfinite(fitted.stderr.get(n, np.nan))
                                              and abs(fitted.parameters[n]) > REDUCED_Z * fitted.stderr[n])]
            if fitted.converged and names and not vague:
                for n in names:
                    start[n] = float(fitted.parameters[n])
                    origin[n] = "reduced analysis"
            elif fitted.converged and vague:
                log.info("reduced-analysis start not used: %s undetermined", ", ".join(vague))
                origin.update({n: f"preset ({', '.join(vague)} undetermined by the reduced analysis)"
                               for n in names})
                # μmax alone, where the saturated static friction pins it and τ alone is
                # undetermined: rests long against τ give μs ≈ μmax whatever τ is (the
                # issue's case: the reduced analysis put μs at 0.738 in every run, the
                # start took the preset's 0.796 because τ alone was undetermined). Not when
                # μmin is undetermined too: over two rest times μmax then moves with it
                # (the measured failure above: μmax 0.83 ± 0.0009 with μmin 0.004 ± 0.24)
                se = fitted.stderr.get("mu_max", np.nan)
                if vague == ["tau"] and "mu_max" in names and np.isfinite(se) and se < MU_MAX_SATURATED_SE:
                    start["mu_max"] = float(fitted.parameters["mu_max"])
                    origin["mu_max"] = f"reduced analysis (saturated μs; {', '.join(vague)} undetermined)"
    except Exception as err:  # the start is a convenience, never a reason to fail
        log.info("reduced-analysis start unavailable: %s", err)
    for n, v in opts.start.items():
        if n in start:
            start[n] = float(v)
            origin[n] = "given"
    if "mu_min" in start and "mu_max" in start and start["mu_min"] >= start["mu_max"]:
        start["mu_min"] = 0.9 * start["mu_max"]
        origin["mu_min"] = "0.9 mu_max (the start had mu_min >= mu_max)"
    groups: dict[str, list] = {}
    for n, o in origin.items():
        groups.setdefault(o, []).append(n)
    if len(groups) == 1:
        return start, next(iter(groups))
    return start, "; ".join(f"{o} for {', '.join(ns)}" for o, ns in groups.items())


AUTO_SEED = 20261127  # the spread starts' seed when the options give none (a fit repeats itself)


def tau_span(prob) -> tuple[float, float] | None:
    """The aging times the data's rests can tell apart, (s, s): a tenth of the shortest
    rest between slips to three times the longest (None without two slips in a run).
    Below it every slip starts fully aged, above it μs grows linearly with the rest and
    only μmax − ψ over τ counts: either way the χ² is flat in τ."""
    rests = np.concatenate([np.diff(r.trigger_steps) / r.fp for r in prob.runs
                            if r.trigger_steps is not None and len(r.trigger_steps) > 1] or [np.zeros(0)])
    rests = rests[rests > 0]
    return (0.1 * float(rests.min()), 3.0 * float(rests.max())) if rests.size else None


def spread_ranges(prob, w_ref: np.ndarray, preset: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The plausible range of each free parameter, scaled (lo, hi), inside the search
    bounds: around the suspect solution ``w_ref`` (a decade either side for log-scaled
    parameters, ±40 % for the others) and, so that a parameter collapsed onto a bound is
    not searched only there, around the coating's ``preset`` as well; a time constant
    (τ) also over :func:`tau_span`."""
    tm, k = prob.theta, prob.n_theta
    th0 = np.asarray(w_ref[:k], float)
    half = np.where(tm.log, np.log(10.0), 0.4 * np.maximum(np.abs(th0), 1e-3))
    lo, hi = th0 - half, th0 + half
    if preset:
        known = {n: preset[n] for n in tm.names if n in preset}
        if len(known) == k:
            thp = tm.to_scaled(known)
            half_p = np.where(tm.log, np.log(10.0), 0.4 * np.maximum(np.abs(thp), 1e-3))
            lo, hi = np.minimum(lo, thp - half_p), np.maximum(hi, thp + half_p)
    span = tau_span(prob)
    if span is not None and "tau" in tm.names:
        j = tm.names.index("tau")
        if tm.log[j]:
            lo[j] = min(lo[j], np.log(span[0] / tm.scale[j]))
            hi[j] = max(hi[j], np.log(span[1] / tm.scale[j]))
    return np.maximum(lo, tm.lo + 1e-9), np.minimum(hi, tm.hi - 1e-9)


def spread_starts(prob, w_ref: np.ndarray, n: int, rng, preset: dict | None = None) -> list:
    """``n`` starts spread over the plausible range of every free parameter
    (:func:`spread_ranges`) as a Latin hypercube: each parameter's range cut into ``n``
    strata, one start in each; the plateaus and triggers as in ``w_ref``, the arc starts
    synced to each start's parameters."""
    k = prob.n_theta
    out = []
    u = (rng.permuted(np.tile(np.arange(n), (k, 1)), axis=1).T + rng.random((n, k))) / n  # (n × k) in [0, 1)
    lo, hi = spread_ranges(prob, w_ref, preset)
    for row in u:
        w = np.array(w_ref, float)
        w[:k] = lo + row * (hi - lo)
        out.append(prob.sync_start_positions(w) if prob.E else w)
    return out

"""Full-model identification: event-based multiple shooting, joint over runs.

The data fix the mode sequence (:mod:`identify.traces.events`: plateaus separated by slips at
trigger steps); :mod:`identify.fitting.problem` builds the multiple-shooting NLP over all runs;
:mod:`identify.fitting.start` gets its start near the solution (the reduced analysis first,
DESIGN.md §2); this module reads the runs (:mod:`identify.fitting.rundata` prepares each for the
NLP), drives the solves, has the mode sequence decided with the fitted model
(:mod:`identify.fitting.mode_sequence`) and hands the solution to :mod:`identify.fitting.result`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import replace

import numpy as np

from identify import interrupts
from identify.fitting import best_so_far
from identify.fitting.mode_sequence.decide import decide_sequence
from identify.fitting.options import FitError, FitOptions
from identify.fitting.problem import Problem
from identify.fitting.rundata import RunData, make_run_data
from identify.fitting.scoped_options import check_scopes, every_scope, scoped_defaults
from identify.fitting.start_values import AUTO_SEED, spread_starts, start_values
from identify.fitting.suspect import (
    SAME_SOLUTION_TOL,
    at_bound,
    flag_rivals,
    improbable,
    suspect_reason,
    tau_beyond_rests,
)
from identify.model.laws import get_law
from identify.model.params import parameter_set
from identify.model.scopes import device_of, is_scoped, resolve
from identify.model.symbolic import Model
from identify.progress import Stage, reporter

__all__ = ["FitOptions", "fit", "FitError", "RunData", "prepare_runs", "decide_sequence"]



log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- data
def _decide_stick(runs_ev, model, values, opts, final_opts, say):
    """The stick option, when the caller did not give one (:mod:`identify.fitting.stick_choice`):
    with ``stick_speed='check'`` a fit the equations as written cannot make stops at once
    with what to do; with ``'auto'`` the option the data's regimes allow is taken and
    named. Returns (opts, final_opts, a note for the report or None)."""
    from identify.fitting.stick_choice import STICK_SPEED_AUTO as auto_speed
    from identify.fitting.stick_choice import stick_choice

    choice = stick_choice(runs_ev, model, values, options=(0.0, auto_speed) if opts.stick_speed == "auto" else (0.0,),
                          say=say)
    if not choice.mismatch(0.0):
        return opts, final_opts, ("as written (v_stick = 0): checked, the model stick-slips where the data do"
                                  if choice.n_stick_slip else None)
    if opts.stick_speed == "check":
        raise FitError(f"the model as written (v_stick = 0) creeps in {choice.text(0.0)}: it cannot fit their "
                       f"slips. Fit with the stick option (--fix v_stick={auto_speed:g}, or "
                       f"FitOptions(fixed={{'v_stick': {auto_speed:g}}})), or let the fit choose by the data's "
                       "regimes (--stick-speed auto); a trace does not say which the truth had")
    if choice.mismatch(auto_speed):
        raise FitError(f"neither stick option reproduces the data's regimes at the start values: as written the "
                       f"model creeps in {choice.text(0.0)}, with v_stick = {auto_speed:g} m/s in "
                       f"{choice.text(auto_speed)}. Give a start nearer the data (--start) or fix v_stick yourself")
    fixed = {**opts.fixed, "v_stick": auto_speed}
    note = (f"v_stick = {auto_speed:g} m/s, chosen by the data's regimes: as written the model creeps in "
            f"{choice.text(0.0)}; with the stick option in {len(choice.creeping[auto_speed])}")
    say(f"stick option: {note}")
    return replace(opts, fixed=fixed), replace(final_opts, fixed=fixed), note


def _check_left_out(result, model, prob, say) -> None:
    """The runs left out for their regime, simulated at the fitted values: their entry in
    ``result.runs`` gains ``model_regime`` and ``model_slip_um``, and their reason says
    when the fitted model stick-slips where the camera saw no saw-tooth (a gap between
    model and data that :func:`identify.diagnose` weighs). The fit stands if this fails."""
    from identify.fitting.regime_check import regime_check, slips_text

    if not result.regime_runs:
        return
    try:
        rc = regime_check(model, {**prob.values, **result.values}, result.regime_runs)
    except Exception as err:  # a check of runs not fitted never sinks the fit
        say(f"the runs left out for their regime could not be simulated at the fitted values: {err}")
        return
    by_name = {r["name"]: r for r in rc.runs}
    bad = set(rc.mismatched)
    for entry in result.runs:
        rec = by_name.get(entry["name"])
        if entry["used"] or rec is None:
            continue
        entry.update(model_regime=rec["model_regime"], model_slip_um=rec["model_slip_um"],
                     model_steady_slip_um=rec.get("model_steady_slip_um"))
        if entry["name"] in bad:
            entry["reason"] += (
                "; at the fitted values the model, sampled and read as the data were, stick-slips there "
                f"({slips_text(rec)}; the data's not resolvable): model and data part here (identify "
                "diagnose weighs it)")
    if bad:
        say(f"warning: the fitted model stick-slips in {len(bad)} run(s) left out without resolvable slips: "
            + ", ".join(sorted(bad)))


def prepare_runs(items, *, coating: str | None = None, noise_m: float | None = None):
    """Traces, RunEvents or paths -> (usable RunData list, excluded [(name, reason)], coating).

    Runs are left out, with their reason, when they break the format, have no usable
    conditions, belong to another coating, or show neither slips nor steady creep.
    """
    from identify.traces.events import RunEvents, extract_events
    from identify.traces.io import Trace, TraceFormatError, load_traces

    excluded: list[tuple[str, str]] = []
    traces: list = []
    path_like = [x for x in items if not isinstance(x, (Trace, RunEvents))]
    if path_like:
        ts = load_traces(path_like)
        traces.extend(ts.traces)
        for err in ts.errors:
            excluded.append((str(getattr(err, "path", "?")), str(err)))
    traces.extend(x for x in items if isinstance(x, (Trace, RunEvents)))
    coatings = [((t.trace if isinstance(t, RunEvents) else t).coating or "").upper() for t in traces]
    if coating is None:
        named = [c for c in coatings if c]
        coating = max(set(named), key=named.count) if named else "FOTAS"
    coating = coating.upper()
    runs: list[RunEvents] = []
    for item, c in zip(traces, coatings):
        tr = item.trace if isinstance(item, RunEvents) else item
        if c and c != coating:
            excluded.append((tr.name, f"coating {c} differs from the fit's {coating}"))
            continue
        try:
            ev = item if isinstance(item, RunEvents) else extract_events(tr, noise_m=noise_m)
        except (ValueError, TraceFormatError) as err:
            excluded.append((tr.name, f"event extraction failed: {err}"))
            continue
        runs.append(ev)
    return runs, excluded, coating


SEQUENCE_RECORDS = ("triggers_moved", "slips_inserted", "slips_removed", "restarts")
"""What a solution records of the mode sequence's decisions, carried to a later solve of it."""


def _interval_solve(prob, best: dict, opts, say):
    """``prob`` again with the triggers as intervals (``opts.trigger = "interval"``),
    solved from ``best``, the uniform encoding's solution: the same variables, every
    start position clipped into its interval, the arcs' horizons kept. Returns
    (problem, solution, note): a re-solve that fails or does not converge is not kept,
    and the note says so (the uniform problem and solution come back)."""
    from identify.fitting.problem import Problem

    say("triggers as intervals: solving again from the uniform encoding's solution")
    try:
        iprob = Problem(prob.runs, prob.model, prob.values, opts)
        iprob.ev_M = prob.ev_M.copy()
        iprob.counter = prob.counter  # the timing report covers every solve
        iprob.build()
        iprob.progress = prob.progress
        sol = iprob.solve(np.clip(best["w"], *iprob.bounds()))
    except Exception as err:  # (the uniform fit is finished: it is not lost to this)
        status = f"failed: {err}"
    else:
        if sol["success"]:
            sol.update({k: best[k] for k in SEQUENCE_RECORDS if k in best})
            sol["iterations"] += best["iterations"]
            return iprob, sol, " -> triggers as intervals"
        status = sol["status"]
    say(f"warning: the interval re-solve ended {status}; the uniform encoding's solution is kept")
    return prob, best, f" -> interval re-solve {status}, not kept (the uniform encoding's solution)"


def fit(data, *, coating: str | None = None, options: FitOptions | None = None, params=None,
        true_values: Mapping[str, float] | None = None, progress: Callable[[str], None] | bool | None = None):
    """Identify the friction parameters from recorded runs.

    Parameters
    ----------
    data : sequence of paths, Traces or RunEvents
        Files or folders of the trace format, loaded traces, or extracted events.
    coating : str, optional
        FOTAS or OTS: the preset for the parameters that are not free; runs of another
        coating are left out (default: the runs' majority coating).
    options : FitOptions
    params : identify.Parameters, optional
        The parameters declared lmfit-style (value, vary, min, max): they give the
        options' ``free``, ``start``, ``fixed`` and ``bounds``, and the coating when
        none is given.
    true_values : dict, optional
        Shown beside the estimates in the report (synthetic data).
    progress : callable, False or None
        Where the fit reports what it is doing (:mod:`identify.progress`): None draws a
        bar with the time left for its counted stages (solver starts) on a terminal and
        logs otherwise; False is silent; a callable gets each message.

    Returns
    -------
    FitResult

    Raises
    ------
    FitError
        When no run can be used or every solver start fails.
    identify.interrupts.Interrupted
        On Ctrl-C (a ``KeyboardInterrupt``): its ``saved`` holds the best point reached
        so far (parameters, χ², the solver's status), or None if no solve had begun.
    """
    from identify.fitting.parameters import merged_options

    options = merged_options(options, params)
    coating = coating or getattr(params, "coating", None)
    progress = reporter(progress)
    with interrupts.honoured(), best_so_far.watching() as seen:
        try:
            return _fit(data, coating=coating, options=options, true_values=true_values, progress=progress)
        except interrupts.Interrupted:
            raise
        except Exception as err:  # (an interrupt that landed inside C code comes out as another error)
            if not interrupts.caused_by_interrupt(err):
                raise
            raise _interrupted(seen) from err
        except KeyboardInterrupt as err:
            raise _interrupted(seen) from err


def _interrupted(seen) -> interrupts.Interrupted:
    """The interrupt with the best point the fit had reached (``seen``)."""
    saved = seen.saved()
    what = f"{saved['what']}, at chi-square {saved['chi2']:.6g}," if saved else "no solve had begun"
    return interrupts.Interrupted(what, saved)


def _fit(data, *, coating, options, true_values, progress):
    from identify.fitting.result import build_result

    final_opts = options or FitOptions()
    # the interval encoding is a last solve from the uniform encoding's solution, which
    # decides everything before it (see FitOptions.trigger)
    opts = replace(final_opts, trigger="uniform")
    say = progress or (lambda msg: None)
    wall0 = time.perf_counter()
    items = [data] if isinstance(data, (str, bytes)) or hasattr(data, "__fspath__") else list(data)
    say(f"loading {len(items)} input(s) and extracting events")
    runs_ev, excluded, coating = prepare_runs(items, coating=coating)
    law = get_law(opts.law)
    model = Model(law)
    preset = parameter_set(coating, {n: v for n, v in opts.fixed.items()})
    stick_note = None
    said = any("v_stick" in d for d in (opts.fixed, opts.start, opts.bounds)) or "v_stick" in opts.free
    if not said and opts.stick_speed != "off":
        opts, final_opts, stick_note = _decide_stick(runs_ev, model, {**preset, **opts.start}, opts, final_opts, say)
        preset = parameter_set(coating, {n: v for n, v in opts.fixed.items()})
    left = _LeftOut(excluded, say)
    run_data, stepping = _runs_to_fit(runs_ev, preset, opts, left, say)
    opts, final_opts = (every_scope(o, run_data) for o in (opts, final_opts))
    check_scopes(opts, run_data, left.excluded)
    preset = scoped_defaults(preset, opts)
    start, start_source = start_values(run_data, law, preset, opts)
    from identify.fitting.problem import MEASUREMENT

    values = {**model.defaults(preset), **{n: preset[n] for n in MEASUREMENT},
              **{n: v for n, v in preset.items() if is_scoped(n)}, **start}
    run_data = _creep_runs_checked(run_data, model, values, stepping, left)
    check_scopes(opts, run_data, left.excluded)  # (a run the creep check left out)
    prob = _problem(run_data, model, values, opts, left, say)
    n_obs = prob.n_observations()
    failed0 = prob.arcs.n_failed
    prob.progress = say
    start_given = dict(start)
    start, staged, starts, start_source = _starts(prob, start, start_source, opts, say)
    solves = _Solves(prob, say, loose=opts.multistart == 0)
    if prob.prior_sd():
        start_source += f" (each start solved first with the {len(prob.prior_sd())} parameter(s) with priors held)"
    stage = Stage(say, "solver starts", len(starts)) if len(starts) > 1 else None
    if stage is not None:
        stage.start(f"{len(starts)} starts ({opts.multistart} random)")
    for i, w in enumerate(starts):
        solves.solve_from(w, f"start {i + 1} of {len(starts)}", stage=stage)
    best = min(solves.results, key=lambda r: r["f"])
    source0 = start_source
    best, start, start_source = _second_opinion(solves, best, start, start_given, staged, start_source)
    if not np.isfinite(best["f"]):
        raise FitError("every solver start failed: " + "; ".join(r["status"] for r in solves.results))
    t_seq = time.perf_counter()
    prob, best = decide_sequence(prob, best, model, values, opts, say, fresh_start=start_given)
    t_seq = time.perf_counter() - t_seq
    solves.prob = prob  # (the problem now carries the decided sequence)
    if start_source == source0:  # (no second opinion yet: asked again, of the decided sequence)
        best, start, start_source = _second_opinion(solves, best, start, start_given, staged, start_source,
                                                    decided=True)
    decided_f = best["f"]
    best, start, start_source, rivals = _spread_if_suspect(solves, best, start, start_source, opts, preset, say)
    if best["f"] < decided_f - SAME_SOLUTION_TOL and opts.sequence_passes:
        # a better basin, found after the sequence was decided in the first one: the
        # sequence is decided again from it (see _decided_again)
        t0 = time.perf_counter()
        prob, best, start_source, rivals = _decided_again(solves, prob, best, model, values, opts, start_source,
                                                          rivals, say)
        t_seq += time.perf_counter() - t0
    if final_opts.trigger == "interval":
        prob, best, how = _interval_solve(prob, best, final_opts, say)
        start_source += how
    if best.get("shared"):
        say("the solution on the covariance's central differences")
        best = prob.accurate_differences(best)
    say("covariance")
    prob.progress = None  # the result keeps the problem; the caller's callback is not its business
    result = build_result(prob, best, solves.results, left.excluded, start, start_source, coating, true_values,
                          time.perf_counter() - wall0)
    result.timing["sequence_s"] = float(t_seq)
    flag_rivals(result, prob, best, rivals)
    result.regime_runs = left.regime_runs
    _check_left_out(result, model, prob, say)
    _solver_notes(result, prob, failed0, n_obs, stick_note)
    if opts.stick_speed == "auto" and stick_note and stick_note.startswith("as written"):
        return _stick_by_likelihood(result, data, coating, final_opts, true_values, progress, say)
    if stick_note and stick_note.startswith("as written"):
        _flag_stick_dependence(result)
    return result


class _LeftOut:
    """The runs a fit leaves out: (name, why) for the report, and those left out for their
    regime kept as evidence for the diagnosis (:class:`identify.fitting.regime_check.RegimeRun`)."""

    def __init__(self, excluded: list, say):
        self.excluded, self.regime_runs, self.say = excluded, [], say

    def for_regime(self, rd) -> None:
        from identify.fitting.regime_check import RegimeRun

        try:
            self.regime_runs.append(RegimeRun.of(rd))
        except Exception as err:  # (odd metadata): the run is left out all the same
            self.say(f"warning: {rd.name}: cannot be checked against the model later: {err}")


def _runs_to_fit(runs_ev, preset, opts, left: _LeftOut, say) -> tuple[list, dict]:
    """The runs' data for the NLP, and the runs that step between their slips under the
    stick option (name -> why); runs without slips are left out unless creep runs are used."""
    v_stick = float({**preset, **opts.start}.get("v_stick", 0.0))
    run_data, stepping = [], {}
    for ev in runs_ev:
        rd = make_run_data(ev, v_stick=v_stick, drops=opts.drop_frames)
        if rd.kind == "creep" and make_run_data(ev).kind == "events":
            stepping[rd.name] = (f"the block moves during its plateaus at {ev.creep_ratio:.2f} of the puller "
                                 f"speed: it steps between its slips, which the model under the stick option "
                                 f"(v_stick = {v_stick:.3g} m/s) makes only through releases its detected slips lack")
            say(f"{rd.name}: {stepping[rd.name]}; used only where the model creeps too")
        if rd.kind == "creep":
            if not opts.use_creep_runs:
                left.excluded.append((rd.name, stepping.get(rd.name,
                                                            f"no resolvable slips (data regime {ev.regime})")))
                left.for_regime(rd)
                continue
        if rd.kind == "events" and len(rd.trigger_steps) < 1:
            left.excluded.append((rd.name, "no slip detected"))
            continue
        run_data.append(rd)
    return run_data, stepping


def _creep_runs_checked(run_data, model, values, stepping, left: _LeftOut) -> list:
    """The runs kept: a creep run is used only where the model at the start creeps too."""
    if not any(r.kind == "creep" for r in run_data):
        return run_data
    from identify.fitting.regime_check import steps_of
    from identify.simulation.hybrid import RunConditions, SimulationOptions, simulate_run

    kept = []
    for r in run_data:
        if r.kind != "creep":
            kept.append(r)
            continue
        try:
            sim = simulate_run(model, resolve(values, r.name, device_of(r)),
                               RunConditions(r.k, r.Nb, r.fp, steps_of(r)),
                               SimulationOptions(record=False))
            if sim.regime == "creep":
                kept.append(r)
            else:
                why = f"{stepping[r.name]};" if r.name in stepping else "no resolvable slips and"
                left.excluded.append((r.name, f"{why} the model predicts {sim.regime}, not steady creep"))
                left.for_regime(r)
        except Exception as err:
            left.excluded.append((r.name, f"no resolvable slips; creep check failed: {err}"))
            left.for_regime(r)
    return kept


def _problem(run_data, model, values, opts, left: _LeftOut, say) -> Problem:
    """The NLP of the runs kept; a FitError where no run is left or the runs cannot fix
    the free parameters."""
    excluded, regime_runs = left.excluded, left.regime_runs
    if not run_data:
        # (a reason that already starts with the file's name, as a format error's does, is not prefixed again)
        raise FitError("no run could be used: " + "; ".join(why if str(why).startswith(str(n)) else f"{n}: {why}"
                                                            for n, why in excluded) if excluded
                       else "no run could be used", excluded, regime_runs=regime_runs, values=values)
    say(f"{len(run_data)} run(s) used, {len(excluded)} left out; building the NLP")
    for r in run_data:
        edge = r.stick_edge(values)
        if edge:
            say(f"warning: {r.name}: {edge}")
    prob = Problem(run_data, model, values, opts).build()
    n_obs, n_eff = prob.n_observations(), prob.n_effective()
    if n_obs < n_eff:
        # (creep runs alone give one mean each: a "fit" of four parameters to three of
        # them had put μmax at ± 0.03 %, measured on logistic-law data at Table II)
        used = [f"{r.name} ({'creep' if r.kind == 'creep' else f'{len(r.trigger_steps)} slip(s)'})" for r in run_data]
        out = ("; left out: " + "; ".join(f"{n}: {why}" for n, why in excluded)) if excluded else ""
        own = f" and {n_eff - prob.n_theta} of the runs' own" if n_eff > prob.n_theta else ""
        raise FitError(f"{n_obs} observation(s) for {n_eff} free dimension(s) ({', '.join(prob.theta.names)}{own}): "
                       f"the run(s) used cannot fix them: {', '.join(used)}{out}. Record runs "
                       "that stick-slip, or free fewer parameters", excluded, regime_runs=regime_runs,
                       values=values, used=[r.name for r in run_data], counts=(n_obs, n_eff))
    return prob


def _starts(prob, start: dict, start_source: str, opts, say):
    """(start, the staged start or None, the solver's starting points, where they came
    from): the staged start where it fits better than the one given, then ``multistart``
    random points about it."""
    staged = None
    start_given = dict(start)
    if opts.staged_start:
        from identify.fitting.start import staged_start, start_merit

        say("start: aging from the triggers, then the slip parameters from slip lengths")
        staged, stages = staged_start(prob, start, seed=opts.seed or 0)
        m_from = start_merit(prob, start)
        w_staged = prob.initial_w(staged)
        m_staged = start_merit(prob, staged, w_staged)
        log.info("staged start %s (χ² %.6g) from %s (χ² %.6g)", staged, m_staged, start_given, m_from)
        if m_staged <= m_from:
            start, w0 = staged, w_staged  # (made last: the arcs are sized as it left them; 0.3 s of 10 runs)
            start_source += " -> staged (triggers, slip lengths)"
        else:
            start_source += f" (staged start rejected: χ² {m_staged:.4g} > {m_from:.4g})"
    if start is not staged:
        w0 = prob.initial_w(start)
    starts = [w0]
    rng = np.random.default_rng(opts.seed)
    for _ in range(opts.multistart):
        w = w0.copy()
        w[: prob.n_theta] = np.clip(w0[: prob.n_theta] + np.where(prob.theta.log, rng.normal(0, 0.3, prob.n_theta),
                                    rng.normal(0, 0.3, prob.n_theta) * np.abs(w0[: prob.n_theta]) + 1e-3),
                                    prob.theta.lo + 1e-9, prob.theta.hi - 1e-9)
        starts.append(prob.sync_start_positions(w) if prob.E else w)
    return start, staged, starts, start_source


def _priored_held_first(prob, w0, say) -> tuple:
    """A start solved with every parameter that has a prior held at its start value (a
    walk's coefficients at their prior's zero), for the full solve to start from: (start,
    the held solve's iterations and wall time, or None where there are no priors or it
    did not converge, and the start is ``w0`` as it is).

    Why: from the preset, far from the data, the penalised coefficients take up the
    start's misfit and lead the friction parameters into another basin. Measured (three
    runs of another truth, μmin 0.45 and A 0.012, on fresh contacts, each with its own
    drift and a 15 nm/√s walk): from the preset, Ipopt ended `Solve_Succeeded` at μmin
    0.345 ± 0.009 and A 0.0215 ± 0.0009, a local optimum (its profile found μmin 0.416
    lower by Δχ² 5.8); with the walk held first it ended at μmin 0.424 ± 0.062, A 0.0142
    ± 0.0057, the truth inside every interval."""
    held = [prob.theta.names.index(n) for n in prob.prior_sd()]
    if not held:
        return w0, None
    say(f"  first with the {len(held)} parameter(s) with priors held at their start values")
    try:
        res = prob.solve(w0, fixed={i: float(w0[i]) for i in held}, loose=True)
    except Exception as err:  # (the full solve from the start as it was says what is wrong)
        log.info("the solve with the priored parameters held failed: %s", err)
        return w0, None
    if not res.get("success") or not np.all(np.isfinite(res["w"])):
        log.info("the solve with the priored parameters held ended %s: the full solve starts as it was",
                 res.get("status"))
        return w0, None
    return res["w"], dict(iterations=int(res["iterations"]), wall_s=float(res["wall_s"]))


class _Solves:
    """Every solve of a fit, in order (the report's multistart summary counts them).
    ``loose``: one start's solution only decides the mode sequence, which ends with a
    solve to the full tolerance; the values of several starts are compared, so each is
    solved fully."""

    def __init__(self, prob, say, loose: bool):
        self.prob, self.say, self.loose, self.results = prob, say, loose, []

    def solve_from(self, w, label: str, loose: bool | None = None, stage=None) -> dict:
        if stage is None:
            self.say(f"solving: {label}")
        try:
            w_from, held = _priored_held_first(self.prob, w, self.say)
            res = dict(self.prob.solve(w_from, loose=self.loose if loose is None else loose), start_w=w)
            if held is not None:  # (the held solve is part of this start's work)
                res.update(iterations=int(res["iterations"]) + held["iterations"],
                           wall_s=float(res["wall_s"]) + held["wall_s"], held_first=held)
            self.results.append(res)
        except Exception as err:
            self.results.append(dict(w=w, f=np.inf, status=f"failed: {err}", success=False, iterations=0,
                                     wall_s=0.0, start_w=w))
        if stage is not None:
            stage.advance(f"{label}: {self.results[-1]['status']}")
        return self.results[-1]


def _second_opinion(solves: _Solves, best, start, start_given, staged, start_source, decided: bool = False):
    """A suspect first solution solved again from the start not taken (staged or not),
    kept if better: (best, start, start_source). ``decided``: the mode sequence is decided
    (the solve is then a full one, on that sequence, and carries its records), and a
    solution the noise would exceed less than 1 % of the time (:func:`improbable`) is
    suspect too. That is asked only then: before it, missed slips and misplaced triggers
    raise the χ² of a solution in the right basin (the 10-run speed set: χ² 41793 against
    the limit 37719, 36032 once 7 slips were inserted), and the second solve from there
    cost 93 of the SQP's 120 s and 5 of Ipopt's 31, not kept.

    Why: the start's χ² does not say where a solve will end. Measured: from a staged start
    that looked better, 4 of 9 fits of a two-condition plan ended in a basin with τ → 0
    and A → 0 (reduced χ² 6, line search failed) while the truth fitted at 1.0; and on the
    5-run speed benchmark the staged start was rejected (χ² 1.6e11 against 3.9e6) and the
    solve from the unstaged one stalled at χ² 1.3e6."""
    prob = solves.prob
    other = None
    if start != start_given:
        other = (start_given, "the start before staging", "unstaged")
    elif staged is not None and staged != start_given:
        other = (staged, "the staged start it rejected", "staged")
    why = (suspect_reason(prob, best, near_ok=decided) or (improbable(prob, best) if decided else "")) \
        if other is not None else ""
    if why:
        again = solves.solve_from(prob.initial_w(other[0]), f"the fit looks wrong ({why}); again from {other[1]}",
                                  loose=False if decided else None)
        if decided:
            again.update({k: best[k] for k in SEQUENCE_RECORDS if k in best})
        better = again["f"] < best["f"]
        start_source += f" -> suspect, solved again from the {other[2]} start: " + (
            "kept" if better else "not better, not kept")
        if better:
            best, start = again, other[0]  # the report's init: where the kept solve began
    return best, start, start_source


def _decided_again(solves: _Solves, prob, best, model, values, opts, start_source, rivals, say):
    """The mode sequence decided again from ``best``, a solution in a better basin than the
    one the sequence was decided from (found by the second opinion or the spread starts,
    on the sequence the first decision left). (problem, solution, start_source, rivals):
    where the sequence changes, the rivals (solutions of the problem before, not
    comparable after) are dropped.

    Why: the sequence decided in a wrong basin chases its misfit. Measured on robustness
    clean set 12 with Ipopt: decided from the staged start's solution, 34 trigger moves
    ended at excess χ² 13535 against 2664 and were undone; the spread starts then found
    the right basin on the sequence as detected (χ² 5756.9), but the 31 moves the
    Gauss–Newton SQP had decided there (from its own first basin: χ² 5457.2, the
    truth-started fit's) were never tried from it."""
    say("the mode sequence decided again, from the better solution")
    prob2, best2 = decide_sequence(prob, dict(best), model, values, opts, say)
    # nothing changed: the solution stands as solved (measured: a load-offset baseline's
    # decision moved nothing on net, and its re-solve ran to the iteration limit at χ² 15812
    # against 12110). A change that ends worse is undone inside decide_sequence already (its
    # worse_sequence); what is left to refuse is a failed solve in place of a converged one.
    if not any(best2.get(k) for k in ("triggers_moved", "slips_inserted", "slips_removed")):
        return prob, best, start_source, rivals
    if best.get("success") and not best2.get("success"):
        return prob, best, start_source + " -> the mode sequence decided again from it: not kept", rivals
    solves.prob = prob2
    start_source += (f" -> the mode sequence decided again from it ({best2['triggers_moved']} trigger(s) moved, "
                     f"{best2['slips_inserted']} inserted, {best2['slips_removed']} removed)")
    return prob2, best2, start_source, []


def _spread_if_suspect(solves: _Solves, best, start, start_source, opts, preset, say):
    """Still suspect once the mode sequence is decided (a wrong trigger makes a misfit no
    start cures, and the sequence decision cures it first): a seeded multistart spread
    over the plausible range, so that the answer is the best of several basins rather than
    the first one reached. (best, start, start_source, rivals: the converged solutions of
    the final problem, for the uniqueness check)."""
    prob = solves.prob
    why = (suspect_reason(prob, best, near_ok=True) or at_bound(prob, best) or improbable(prob, best)
           or tau_beyond_rests(prob, best))
    if not (why and opts.auto_starts):
        return best, start, start_source, []
    auto = spread_starts(prob, best["w"], opts.auto_starts,
                         np.random.default_rng(opts.seed if opts.seed is not None else AUTO_SEED), preset)
    n_before = len(solves.results)
    stage = Stage(say, "spread starts", len(auto))
    stage.start(f"the fit looks wrong ({why}): {len(auto)} starts spread over the plausible ranges")
    for i, w in enumerate(auto):
        solves.solve_from(w, f"spread start {i + 1} of {len(auto)}", loose=False, stage=stage)
    tried = solves.results[n_before:]
    rivals = [r for r in tried if r.get("success") and np.isfinite(r["f"])]
    new_best = min(tried, key=lambda r: r["f"])
    kept = new_best["f"] < best["f"] - SAME_SOLUTION_TOL
    start_source += (f" -> suspect ({why}), {len(auto)} spread starts: "
                     + ("a better solution kept" if kept else "none better"))
    if kept:
        best = {**best, **{k: v for k, v in new_best.items() if k != "start_w"}}
        th = np.atleast_1d(prob.theta.from_scaled(new_best["start_w"][: prob.n_theta]))
        start = {n: float(v) for n, v in zip(prob.theta.names, th)}  # (the report's init)
    return best, start, start_source, rivals


def _solver_notes(result, prob, failed0: int, n_obs: int, stick_note) -> None:
    """What the report's solver section says beyond the solve itself: arcs the integrator
    could not finish at any tolerance (their trial points were rejected, which a solve that
    stalls or fails may owe to them), the detected sequence's observation count (fixing or
    freeing a parameter can move the decided sequence, and with it the frames that count),
    and the stick option taken."""
    n_failed = prob.arcs.n_failed - failed0
    result.solver["arcs_failed"] = int(n_failed)
    result.solver["observations_detected"] = int(n_obs)
    if stick_note:
        result.solver["stick_option"] = stick_note
    if n_failed and prob.arcs.last_failure is not None:
        result.solver["arc_failure"] = prob.arcs.last_failure[1]


def _flag_stick_dependence(result, other=None, kept_option: bool = False) -> None:
    """Where the fit kept the equations as written without being told (the data's
    regimes allow both), μmax depends on a choice the data do not make: with the stick
    option the static capacity carries the band A·ln(1 + v_stick/vc) on top of the aged
    state, so the same triggers put μmax that much lower. Its interval is conditional on
    the option, and μmax is flagged with both values (``other``: the fit with the option,
    when one was made; else the band computed at the estimates). ``kept_option``: the
    result is the fit with the option, ``other`` the fit as written."""
    from identify.fitting.stick_choice import STICK_SPEED_AUTO

    p, v = result.parameters.get("mu_max"), result.values
    if p is None or not p.free or "A" not in v or not v.get("vc"):
        return
    if other is not None and "mu_max" in other.parameters:
        alt = float(other["mu_max"].value)
    else:
        alt = float(p.value - v["A"] * np.log1p(STICK_SPEED_AUTO / v["vc"]))
    if not np.isfinite(alt) or abs(p.value - alt) <= (p.stderr or 0.0):
        return  # (within its own standard error: the choice does not matter here)
    written, option = (alt, p.value) if kept_option else (p.value, alt)
    text = (f"depends on the stick option, which a trace does not show: {written:.4g} as written, {option:.4g} "
            f"with v_stick = {STICK_SPEED_AUTO:g} m/s (fix v_stick to choose)")
    p.flag = f"{p.flag}; {text}" if p.flag else text
    result.solver["stick_alternative"] = (dict(v_stick_m_per_s=0.0, mu_max=alt) if kept_option
                                          else dict(v_stick_m_per_s=STICK_SPEED_AUTO, mu_max=alt))


STICK_DECISIVE = 10.0
"""Δχ² by which one stick option must fit better for the data to have chosen it (a
likelihood ratio of e⁵ ≈ 150); closer, μmax is flagged with both values."""


def _stick_by_likelihood(result, data, coating, final_opts, true_values, progress, say):
    """``stick_speed='auto'`` where the regimes did not tell (the model stick-slips as
    written where the data do): the fit with the stick option is made too, and the data
    choose by χ². An option that fits better by :data:`STICK_DECISIVE` is taken; within
    it, the lower χ² is kept and μmax, which means a different thing under each option,
    is flagged with both values. The report names both fits."""
    from identify.fitting.stick_choice import STICK_SPEED_AUTO

    say(f"stick option: the data's regimes allow both; fitting with v_stick = {STICK_SPEED_AUTO:g} m/s as well")
    try:
        other = fit(data, coating=coating, options=replace(final_opts, fixed={**final_opts.fixed,
                                                                                "v_stick": STICK_SPEED_AUTO}),
                    true_values=true_values, progress=progress or False)
    except FitError as err:
        result.solver["stick_option"] += f"; with v_stick = {STICK_SPEED_AUTO:g} m/s the fit failed: {err}"
        _flag_stick_dependence(result)
        return result
    # (with priors each fit's objective is its data's χ² and its penalty: compared whole)
    obj, obj_other = (x.chi2 + (x.priors or {}).get("penalty_chi2", 0.0) for x in (result, other))
    written = f"as written (v_stick = 0) chi-square {result.chi2:.6g}"
    if result.concerns:
        written += f" ({'; '.join(result.concerns)})"
    option = f"with v_stick = {STICK_SPEED_AUTO:g} m/s {other.chi2:.6g}"
    if other.concerns:
        option += f" ({'; '.join(other.concerns)})"
    decisive = abs(obj - obj_other) > STICK_DECISIVE
    if obj_other < obj:
        other.solver["stick_option"] = (f"v_stick = {STICK_SPEED_AUTO:g} m/s, chosen by the likelihood: {written}, "
                                        f"{option}")
        other.timing["total_s"] += result.timing["total_s"]
        if not decisive:
            _flag_stick_dependence(other, result, kept_option=True)
        return other
    result.solver["stick_option"] = f"as written (v_stick = 0), chosen by the likelihood: {written}, {option}"
    result.timing["total_s"] += other.timing["total_s"]
    if not decisive:
        _flag_stick_dependence(result, other)
    return result

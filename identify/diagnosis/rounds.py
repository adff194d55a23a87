"""Diagnose the sim-to-real gap: where it lies, which unmodelled effect causes it, how far
it shrinks once that effect is added — on runs the fit did not see (DESIGN.md §4).

1. The baseline is fitted (:func:`identify.fit`) and its misfit located feature by
   feature (:func:`identify.diagnosis.where.where`).
2. Every applicable candidate of the effect library (:mod:`identify.model.effects`) is refitted
   with its parameter(s) freed, warm-started from the current model
   (:func:`identify.diagnosis.candidates.run_candidate`, through a ``concurrent.futures`` Executor:
   local processes or a dask cluster), and scored by the likelihood ratio (p-value),
   ΔAIC and ΔBIC; alternative aging laws (not nested) by ΔAIC alone.
3. A candidate is named only when it is significant (p below α over the number of
   candidates, or ΔAIC < −10 for a law), the model's own parameters cannot mimic it (R²
   < 0.99 in the information metric, else ``confounded_with`` names them), no other
   candidate explains the same residuals as well (nearly parallel residual change and
   |ΔΔAIC| < 10: both are reported as confounded and neither is named), and it closes a
   real part of the gap on held-out runs (:func:`identify.diagnosis.scores.closes_gap`:
   of the µm gap, or — where that gap sits at the encoding's own floor — of the excess
   χ² with the likelihood gain kept held out; on all runs or on all but the one that
   argues most against it), and it stays significant refitted beside any better-fitting
   candidate the model's own parameters mimic
   (:func:`identify.diagnosis.selection.refit_beside`; else the two are reported as
   confounded). Forward selection adds it and tries the rest again.
4. Verdict: ``adequate`` when the final model's held-out gap is within ``gap_tolerance``
   (1.5×) of the noise floor, or when no feature is significant (Bonferroni over the
   features) and no nameable candidate is left significant; else ``unexplained`` (a gap
   no candidate closes, or one only confounded candidates do).

This module runs the rounds; the pieces live beside it: the options and the result
(:mod:`~identify.diagnosis.result`), the records of each refit and round
(:mod:`~identify.diagnosis.records`: frozen, each decision returns new ones), the refit
tasks (:mod:`~identify.diagnosis.tasks`), their scores (:mod:`~identify.diagnosis.scores`), which one is named
(:mod:`~identify.diagnosis.selection`), the mode sequence decided again
(:mod:`~identify.diagnosis.resequence`) and the runs left out for their regime
(:mod:`~identify.diagnosis.regime_notes`).
"""

from __future__ import annotations

import concurrent.futures as cf
import functools
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from identify import interrupts
from identify.diagnosis.candidates import run_candidate
from identify.diagnosis.drop_observations import with_drop_observations
from identify.diagnosis.heldout import folds_of
from identify.diagnosis.record import DiagnosisRecord, RecordedExecutor, inputs_digest
from identify.diagnosis.records import CandidateResult, Round
from identify.diagnosis.regime_notes import (
    REGIME_MISMATCH,
    SCREEN_AT_FINAL,
    final_screen,
    held_evidence,
    held_note,
    regime_check_notes,
    regime_mismatch,
    regime_notes,
    screen_note,
)
from identify.diagnosis.regime_screen import moved_text, own_screen, smallest_moves
from identify.diagnosis.resequence import rebuild_problem, resequence
from identify.diagnosis.result import DiagnosisOptions, DiagnosisResult
from identify.diagnosis.scores import MIN_CLOSED, closed_share, score_round
from identify.diagnosis.selection import at_noise, choose_named, own_text, put, refit_beside
from identify.diagnosis.tasks import candidate_tasks, expected_cost, rank_tasks
from identify.diagnosis.twins_final import recheck_twins
from identify.diagnosis.verdict import final_record
from identify.diagnosis.verdict import verdict as decide_verdict
from identify.diagnosis.where import where, with_regime
from identify.executors import make_executor
from identify.fitting.convergence import GIVE_UP_FEAS
from identify.fitting.driver import FitError, FitOptions, fit
from identify.model.effects import display, get_effect
from identify.progress import Stage, reporter

__all__ = ["DiagnosisOptions", "DiagnosisResult", "diagnose", "make_executor"]


log = logging.getLogger(__name__)


def diagnose(data, *, coating: str | None = None, fit_options: FitOptions | None = None,
             options: DiagnosisOptions | None = None, baseline=None, executor: cf.Executor | None = None,
             progress: Callable[[str], None] | bool | None = None) -> DiagnosisResult:
    """Diagnose the gap between a baseline model and the data.

    Parameters
    ----------
    data : paths, Traces or RunEvents
        As for :func:`identify.fit` (ignored when ``baseline`` is given).
    fit_options : FitOptions
        The baseline (e.g. ``fixed={"A": 0}`` for the paper's story).
    options : DiagnosisOptions
    baseline : FitResult, optional
        An existing baseline fit to diagnose (saves its fit).
    executor : concurrent.futures.Executor, optional
        Where the candidate refits run (default from ``options.workers`` / ``options.dask``).
    progress : callable, False or None
        Where it reports what it is doing (:mod:`identify.progress`): None draws a bar per
        round of refits with the time left on a terminal and logs otherwise; False is
        silent; a callable gets each message.

    Raises
    ------
    identify.interrupts.Interrupted
        On Ctrl-C: with ``options.record``, everything finished is in the record (its
        ``saved``: the record's path and the refits in it), and a diagnosis started again
        with ``resume=True`` goes on from there.
    """
    opts = options or DiagnosisOptions()
    progress = reporter(progress)
    record = None
    if opts.record:
        given = baseline.problem.opts if baseline is not None else (fit_options or FitOptions())
        inputs = inputs_digest(data if baseline is None else [], coating, given,
                               replace(opts, workers=1, dask=None, record=None, resume=False))
        record = DiagnosisRecord(opts.record, inputs, resume=opts.resume)
        if baseline is None:
            baseline = record.restored_baseline()
            if baseline is not None and progress is not None:
                progress(f"baseline fit from the record {record.path}")
    own, closer = (executor, None) if executor is not None else make_executor(opts.workers, opts.dask)
    if record is not None:
        own = RecordedExecutor(own, record)
    with interrupts.honoured():
        try:
            res = _diagnose(data, coating=coating, fit_options=fit_options, options=opts, baseline=baseline,
                            executor=own, progress=progress, record=record)
        except KeyboardInterrupt as err:
            if record is None:
                raise
            n = len(record.results)
            where = "the baseline fit and " if record.baseline is not None else ""
            raise interrupts.Interrupted(f"{where}{n} finished refit(s) in the record {record.path}",
                                         dict(record=str(record.path), refits=n,
                                              baseline=record.baseline is not None)) from err
        finally:
            if closer is not None:
                closer()
            if record is not None:
                record.close()
    if record is not None:
        res.timing["refits_from_record"] = record.resumed
    return res


def _diagnose(data, *, coating, fit_options, options, baseline, executor, progress, record) -> DiagnosisResult:
    opts = options
    fopts = fit_options or FitOptions()
    say = progress or (lambda m: None)
    t0 = time.perf_counter()
    given = baseline.problem.opts if baseline is not None else fopts
    if given.trigger != "uniform":
        # its features (the static friction at each slip), held-out steps and candidate
        # refits read the trigger residuals, which the interval encoding does not have
        raise ValueError(f"trigger = {given.trigger!r}: the diagnosis needs the uniform trigger encoding "
                         "(fit the baseline with trigger='uniform', the default)")
    if baseline is None:
        say("baseline fit")
        try:
            baseline = fit(data, coating=coating, options=fopts, progress=say)
            if record is not None:
                record.keep_baseline(baseline)
        except FitError as err:
            if not err.excluded or not all(REGIME_MISMATCH in why for _, why in err.excluded):
                raise
            return regime_mismatch(err, fopts, opts, t0, say, executor)
    st = _start_state(baseline, opts, executor, say)
    while _one_round(st):
        pass
    twins = recheck_twins(st)
    final_prob, final_w = rebuild_problem(st.current, st.runs, st.fopts, st.prob)
    regime_final = regime_check_notes(st.current["law"], st.current["values"], st.regime_runs, st.notes)
    # runs the final model puts in another regime than their data: whatever the held-out
    # gap of the runs it could fit, model and data part there (never `adequate`)
    screen, later, profile = [], [], None
    if regime_final is not None and regime_final.mismatched:
        screen, later, profile, named = _regime_left_out(st, regime_final)
        if named:
            final_prob, final_w = rebuild_problem(st.current, st.runs, st.fopts, st.prob)
            regime_final = regime_check_notes(st.current["law"], st.current["values"], st.regime_runs, st.notes)
    where_final = with_regime(where(final_prob, final_w) if st.effects else st.where0, regime_final)
    verdict, ratio = decide_verdict(st, where_final, regime_final)
    st.notes.extend(later)
    ok = bool(st.final_res is not None and st.final_res.ok)
    final = final_record(st, ok, ratio, profile)
    if not ok:
        verdict = "unexplained"
        status = st.final_res.status if st.final_res is not None and st.final_res.status is not None else "?"
        st.notes.append("the refits failed, so no gap could be measured: " + status)
    rounds = st.rounds
    return DiagnosisResult(
        verdict=verdict, effects=st.effects, where=st.where0, where_final=where_final,
        candidates=list(rounds[0].candidates) if rounds else [], rounds=rounds,
        baseline=baseline, final=final, confounded=st.confounded, options=opts,
        timing=dict(total_s=time.perf_counter() - t0, refits=st.n_refits,
                    baseline_fit_s=float(baseline.solver.get("wall_time_s", float("nan")))),
        notes=st.notes, final_problem=final_prob, final_w=final_w, regime_screen=screen, regime_profile=profile,
        twins_final=twins,
    )


@dataclass
class _State:
    """Where a diagnosis stands between its rounds: the current model (values, free
    parameters, law, solution) and runs, the rounds so far, the effects named, the groups
    found confounded, the last measurement of the final model, and the notes."""

    opts: DiagnosisOptions
    fopts: Any
    prob: Any  # the baseline's problem
    folds: list
    regime_runs: list
    where0: list
    current: dict
    runs: list
    threads: int
    executor: Any
    say: Any
    remaining: list
    notes: list = field(default_factory=list)
    rounds: list[Round] = field(default_factory=list)
    effects: list = field(default_factory=list)
    confounded: list = field(default_factory=list)
    final_res: CandidateResult | None = None
    n_refits: int = 0
    # candidates that fit better held at their realistic magnitude than refitted
    at_magnitude: dict = field(default_factory=dict)


def _start_state(baseline, opts: DiagnosisOptions, executor, say) -> _State:
    """The diagnosis's first state: the baseline as the current model, its misfit located."""
    from identify.model.params import parameter_set

    prob, w = baseline.problem, baseline.w
    where_prob = prob
    if "motion_blur" in opts.effects:
        # (the same observations for the blur candidate, its null and every other refit)
        prob, _ = with_drop_observations(prob, w)
    fopts = prob.opts
    runs = prob.runs
    folds = folds_of(len(runs), opts.folds, seed=opts.seed)
    # every parameter any candidate may free (another law's too), at the baseline's values
    values0 = {**parameter_set(baseline.coating), **prob.values, **baseline.values}
    # the runs the fit left out for their regime are evidence too (identify.fitting.regime_check)
    regime_runs = list(getattr(baseline, "regime_runs", None) or [])
    if regime_runs:
        say(f"simulating the {len(regime_runs)} run(s) left out for their regime under the baseline")
    notes: list = []
    where0 = with_regime(where(where_prob, w), regime_check_notes(prob.law.name, values0, regime_runs, notes))
    chi2_0, n_eff_0 = prob.penalised_counts(prob.residuals(w), w)
    current = dict(values=values0, free=tuple(prob.theta.names), law=prob.law.name,
                   w=w, ev_M=np.array(prob.ev_M), n_theta=prob.n_theta,
                   chi2=chi2_0, n_eff=n_eff_0, priors=prob.prior_sd())
    threads = 1 if (opts.workers > 1 or opts.dask) else max(int(fopts.threads), 1)
    return _State(opts=opts, fopts=fopts, prob=prob, folds=folds, regime_runs=regime_runs, where0=where0,
                  current=current, runs=runs, threads=threads, executor=executor, say=say,
                  remaining=list(opts.effects), notes=notes)


def _refits(st: _State, tasks) -> list:
    """Every task of a round through the executor, the most expensive first, each said as
    it finishes; a task that cannot be submitted or whose worker is lost fails alone."""
    stage = Stage(st.say, f"diagnosis round {len(st.rounds) + 1}", len(tasks))
    stage.start(f"{len(tasks) - 1} candidate refit(s) and the current model, {len(st.folds)} held-out fold(s) each")
    results = []
    futs = {}
    for t in sorted(tasks, key=expected_cost, reverse=True):
        try:
            futs[st.executor.submit(run_candidate, t)] = t
        except Exception as err:  # a broken pool or a lost cluster: the candidate fails
            results.append(CandidateResult(effect=t.effect, ok=False, status=f"failed: {err}", error=str(err)))
    for fut in cf.as_completed(futs):
        t = futs[fut]
        try:
            res = CandidateResult.from_dict(fut.result())  # (a record written by an earlier version: a dict)
        except Exception as err:  # a lost worker: the candidate fails, the rest goes on
            res = CandidateResult(effect=t.effect, ok=False, status=f"failed: {err}", error=str(err))
        stage.advance(f"{t.effect or 'current model'} ({res.status})")
        results.append(res)
    return results


def _one_round(st: _State) -> bool:
    """One round: the current model and every candidate left refitted, scored, and the
    one to name chosen and added. False when the diagnosis ends here."""
    opts, say = st.opts, st.say
    tasks, skipped = candidate_tasks(st.remaining, st.current, st.runs, st.fopts, st.folds, opts, st.threads,
                                     where_hint=st.where0, regime_runs=st.regime_runs, at_magnitude=st.at_magnitude)
    grouped = {e for g in st.confounded for e in g["effects"]}
    st.confounded.extend(dict(effects=[c.effect], confounded_with=list(c.confounded_with), closes=False,
                              why=c.reason.removeprefix("confounded: "))
                         for c in skipped if c.confounded_with and c.effect not in grouped)
    results = _refits(st, tasks)
    st.n_refits += len(tasks)
    base = next(r for r in results if r.effect is None)
    if not base.ok:
        st.notes.append(f"the current model could not be re-evaluated: {base.status}")
        st.rounds.append(Round(current=base, candidates=tuple(skipped)))
        if st.final_res is not None:  # the named candidate's numbers, on the sequence it was named on
            st.notes.append("the gaps after are the last named candidate's, on the mode sequence it was "
                            "named on")
        else:
            st.final_res = base
        return False
    st.final_res = base  # the current model, measured in this round
    n_cand = len([t for t in tasks if t.effect])
    scored = score_round(results, base, opts, n_cand, fold_names=[[st.runs[i].name for i in f] for f in st.folds])
    retry = None
    if opts.resequence is not False:
        retry = functools.partial(_own_sequence, base=base, current=st.current, runs=st.runs, fopts=st.fopts,
                                  prob0=st.prob, folds=st.folds, opts=opts, threads=st.threads,
                                  executor=st.executor, say=say)
    beside = functools.partial(refit_beside, scored=scored, base=base, current=st.current, runs=st.runs,
                               fopts=st.fopts, opts=opts, threads=st.threads, executor=st.executor,
                               where_hint=st.where0, n_cand=n_cand, say=say)
    chosen, groups, scored = choose_named(scored, base, beside, retry)
    scored = regime_notes(scored, base)
    st.confounded.extend(groups)
    st.n_refits += sum(len(c.beside or []) for c in scored)  # each check is a refit
    # each measurement on a candidate's own sequence, and of the current model's control
    st.n_refits += sum((c.own_sequence or {}).get("refits", 0) for c in scored)
    # the model measured on the chosen one's own mode sequence; none kept on the records
    adopted = next(c.own_model for c in scored if c.effect == chosen.effect) if chosen is not None else None
    scored = [c.but(own_model=None) if c.own_model is not None else c for c in scored]
    if chosen is None or len(st.effects) >= opts.max_effects:
        # (a round of the final model alone also ends here: it has no candidates)
        st.rounds.append(Round(current=base, candidates=tuple(sorted(scored, key=rank_tasks)) + tuple(skipped)))
        return False
    # (the chosen one as the round leaves it: with the notes added since it was chosen)
    chosen = next(c for c in scored if c.effect == chosen.effect).but(named=True)
    scored = put(scored, [chosen])
    st.rounds.append(Round(current=base, candidates=tuple(sorted(scored, key=rank_tasks)) + tuple(skipped),
                           chosen=chosen.effect))
    return _add_named(st, chosen, adopted, scored)


def _add_named(st: _State, chosen: CandidateResult, adopted: dict | None, scored: list) -> bool:
    """The chosen candidate (named) added to the current model, what the next round tries, and
    the mode sequence decided again under it. False when nothing is left to try."""
    opts = st.opts
    st.final_res = chosen  # the model with it, as measured in this round
    st.effects.append(chosen.effect)
    # the next round retries only what was significant in this one: adding an
    # effect explains part of the misfit, it does not create evidence elsewhere
    st.remaining = [c.effect for c in scored if c.significant and c.effect != chosen.effect]
    # ... and what fit better held at its realistic magnitude than its refit, which
    # ended near its null (evidence without an estimate), started there too.
    # Measured (the two-effect set, load offset and step size): in round 1 the step
    # size's refit stayed at 1 ± 0.013 while 1.05 fit better; not retried, round 2
    # named the topography (a ripple of 9.9 µm) in its place
    st.at_magnitude = {c.effect: c.at_magnitude for c in scored
                       if (c.at_magnitude or {}).get("better") and c.effect != chosen.effect}
    st.remaining += [e for e in st.at_magnitude if e not in st.remaining]
    eff = get_effect(chosen.effect, st.runs)
    if adopted:  # named on the mode sequence it decided: go on from there, as measured there
        st.current, st.runs, st.final_res = adopted["current"], adopted["runs"], adopted["measured"]
    else:
        st.current = dict(values=chosen.values, free=tuple(chosen.free), law=chosen.law,
                          w=chosen.w, ev_M=chosen.ev_M, n_theta=len(chosen.free), chi2=chosen.chi2,
                          n_eff=chosen.n_eff, bounds={**st.current.get("bounds", {}), **dict(eff.bounds)},
                          priors={**(st.current.get("priors") or {}), **(chosen.priors or {})})
    st.say(f"added {chosen.effect} ({', '.join(eff.parameters) or eff.law}); trying the rest again")
    if len(st.effects) >= opts.max_effects:
        st.remaining = []
    changed = False
    if not adopted and (opts.resequence is True or (opts.resequence == "auto" and not at_noise(chosen, opts))):
        try:
            st.current, st.runs, changed = resequence(st.current, st.runs, st.fopts, st.prob, st.say)
        except Exception as err:  # the named model stands with the baseline's sequence
            st.notes.append(f"deciding the mode sequence again with {chosen.effect} failed: "
                            f"{type(err).__name__}: {err}")
    if not st.remaining and not changed:
        # nothing left to try: the final model is this candidate's refit, already
        # measured on the same folds (a round of it alone refitted every held-out
        # fold again: 8 exact refits, ~10 min, on the drift data), and no candidate
        # is left for the verdict to judge
        st.rounds.append(Round(current=(st.final_res if adopted else chosen).but(effect=None, named=False)))
        return False
    return True


def _regime_left_out(st: _State, regime_final):
    """Runs the final model puts in another regime than their data: the candidates at the
    final values (a pointer), the check at each one's magnitude read on the runs left out,
    and where one makes them there, its profile on all runs, which may name it.
    (screen, notes for later, the profile, whether it named an effect)."""
    later = []
    screen = final_screen(st.current, st.regime_runs, st.effects, st.opts, st.say, st.executor)
    if len(screen) > 1:
        later.append(screen_note(screen[0], screen[1:], at=SCREEN_AT_FINAL))
    last = st.rounds[-1] if st.rounds else Round()
    held = held_evidence(last, st.effects, regime_final, st.current.get("chi2"))
    held_txt = held_note(held, len(st.regime_runs))
    if held_txt:
        later.append(held_txt)
    profile, changed = _profile_held(held, st.current, st.runs, st.fopts, st.opts, st.regime_runs, regime_final,
                                     st.executor, st.say, n_cand=len([c for c in last if c.effect]),
                                     confounded=st.confounded)
    if st.rounds:  # the last round's candidates with what was found of them here
        st.rounds[-1] = last.but(candidates=tuple(put(list(last.candidates), held + changed)))
    if profile is not None:
        later.append(profile["note"])
    named = bool(profile is not None and profile.get("named"))
    if named:
        eff = get_effect(profile["effect"])
        best = profile.pop("best")
        name = profile["parameter"]
        st.effects.append(profile["effect"])
        cur = st.current
        st.current = dict(values={**cur["values"], **best["values"]}, free=tuple(cur["free"]) + (name,),
                          law=cur["law"], w=best["w"], ev_M=best["ev_M"], n_theta=len(cur["free"]) + 1,
                          chi2=best["chi2"], n_eff=cur.get("n_eff"),
                          bounds={**cur.get("bounds", {}), **dict(eff.bounds)}, priors=cur.get("priors"))
    elif profile is not None:
        profile.pop("best", None)
    return screen, later, profile, named


def _profile_held(held: list, current: dict, runs: list, fopts, opts: DiagnosisOptions, regime_runs: list, check,
                  executor, say, n_cand: int, confounded: list) -> tuple:
    """Name a candidate on the runs left out for their regime, where only they show it.

    The one candidate whose check at its magnitude fits the runs fitted as well and makes
    the runs left out as the data's (:func:`held_evidence`) is profiled on every run
    (:func:`identify.diagnosis.regime_profile.regime_profile`). It is named where the profile's
    fall from the current model is significant (p below ``alpha`` over the round's
    candidates, and beyond its own 95 % interval), the runs left out come out as the
    data's at its best point, and no move of the current model's own parameters (one at
    a time, toward each bound: :func:`identify.diagnosis.regime_screen.own_screen`) makes every
    run, left out and fitted, as the data's — else it is confounded with those
    parameters. Several candidates that make the runs: confounded with each other, none
    profiled. Measured (withheld rejuvenation, dc = 1 µm): dc's 95 % interval between
    562 nm and 1.78 µm, joint χ² 2799.2 -> 2744.7 (p 1.6e-13), the left-out runs'
    largest-slip gap 231 nm -> 0, 0 held out; no own move makes all 8 runs. The diagnosis took
    410 s against 216 s before, both beside another slow test on two cores.

    Returns the profile's record with ``named``, ``significant``, ``own_moves`` and a
    ``note`` (``best`` too: the model to go on with), or None where nothing was profiled;
    and the candidates of ``held`` with what it found of them (confounded, named)."""
    from identify.diagnosis.regime_profile import regime_profile
    from identify.fitting.regime_check import RegimeRun

    yes = [c for c in held if c.held_regime["fits"] and c.held_regime["reproduces"]]
    if not yes:
        return None, []
    if len(yes) > 1:
        names = [c.effect for c in yes]
        why = ("each, held at its realistic magnitude and refitted, fits the runs fitted as well and makes the runs "
               "left out for their regime as the data's: these runs cannot tell them apart")
        confounded.append(dict(effects=names, confounded_with=[], closes=False, why=why))
        return (dict(effect=None, named=False, note=f"regime profile: not run, {' | '.join(names)}: {why}"),
                [c.but(confounded_with=[n for n in names if n != c.effect]) for c in yes])
    c = yes[0]
    eff = get_effect(c.effect, runs)
    if eff.law is not None or len(eff.parameters) != 1 or c.w_at_magnitude is None:
        return None, []
    tasks, _ = candidate_tasks([c.effect], current, runs, fopts, [], opts, 1, [], regime_runs=regime_runs)
    noise = {r.name: r.noise_m * 1e6 for r in regime_runs}
    am = c.at_magnitude
    try:
        prof = regime_profile(tasks[1], dict(value=am["value"], w=c.w_at_magnitude, ev_M=c.ev_M_at_magnitude),
                              current["chi2"], check.to_json(), noise, executor=executor, say=say,
                              continuity_um=GIVE_UP_FEAS)
    except Exception as err:  # the diagnosis stands without it
        say(f"regime profile failed: {type(err).__name__}: {err}")
        return dict(effect=c.effect, named=False, note=f"regime profile of {c.effect} failed: "
                                                       f"{type(err).__name__}: {err}"), []
    alpha_c = opts.alpha / max(n_cand, 1)
    prof["significant"] = bool(prof["p_value"] < alpha_c and prof.get("null_excluded"))
    own = []
    if prof["significant"] and prof["reproduces"]:
        # could the current model itself, one own parameter moved, make every run as the data's?
        everyone = list(regime_runs) + [RegimeRun.of(rd) for rd in runs]
        own = smallest_moves(own_screen(current["law"], current["free"], current["values"], everyone, say,
                                        executor=executor))
    prof["own_moves"] = [moved_text(r) for r in own]
    prof["named"] = bool(prof["significant"] and prof["reproduces"] and not own)
    if own:
        params = sorted({n for r in own for n in r["moved"]})
        c = c.but(confounded_with=params)
        confounded.append(dict(effects=[c.effect], confounded_with=params, closes=False,
                               why=(f"its profile on every run is significant, and the current model with "
                                    f"{' or '.join(prof['own_moves'])} makes every run as the data's too")))
    if prof["named"]:
        c = c.but(named=True, note="; ".join(x for x in (c.note, "named by its profile on every run (see the regime "
                                                                "profile)") if x))
    prof["note"] = _profile_note(prof, alpha_c)
    return prof, [c]


def _profile_note(prof: dict, alpha_c: float) -> str:
    """The profile's finding in a sentence (:func:`_profile_held`)."""
    n = prof["parameter"]
    if prof.get("error"):
        return f"regime profile of {prof['effect']} ({n}): {prof['error']}"
    lo, hi = prof["interval"]
    span = (f"between {display(n, lo) if lo is not None else '(open)'} and "
            f"{display(n, hi) if hi is not None else '(open)'}")
    head = (f"regime profile of {prof['effect']} ({n} held at points stepped from its realistic magnitude, the runs "
            f"fitted refitted at each, the runs left out read there): best {n} = {display(n, prof['value'])}, its "
            f"95 % interval {span} (the nearest points beyond it); joint χ² {prof['current_joint']:.1f} -> "
            f"{prof['current_joint'] - prof['delta_chi2']:.1f} (p = {prof['p_value']:.2g}); the runs left out: "
            f"largest-slip gap {prof['slip_gap_before_um'] * 1e3:.0f} nm -> {prof['slip_gap_after_um'] * 1e3:.0f} nm, "
            f"{prof['slip_gap_heldout_um'] * 1e3:.0f} nm held out (each predicted from the profile without it)")
    if prof["named"]:
        return (head + f". Named: significant (below {alpha_c:.2g}), the runs left out as the data's, and no move of "
                "the current model's own parameters makes every run so; the estimate is a grid point, the interval "
                "the data's")
    if prof["own_moves"]:
        return head + f". Not named: the current model with {' or '.join(prof['own_moves'])} makes every run too"
    if not prof["significant"]:
        return head + f". Not named: not significant (p ≥ {alpha_c:.2g}) or its interval holds the null"
    return head + ". Not named: at its best point the runs left out still part from the data"


def _own_sequence(c, base, current, runs, fopts, prob0, folds, opts, threads, executor, say):
    """The candidate ``c`` measured on the mode sequence it decides itself: its held-out
    gap there against the current model's on the current model's own sequence: ``c`` with
    its ``own_sequence`` (JSON-able; the new model and runs in its ``own_model`` for naming).

    Why: the current model's fit decided the sequence (moved triggers, inserted slips) to
    suit the current model; a candidate refitted on that sequence inherits the bends, and
    its held-out runs are predicted on them. Measured (logarithmic-law data, a baseline
    with the exponential law, at c43227d): the baseline's fit moved 112 triggers and
    inserted 15 slips; the law's refit removed 50 % of the excess χ² (ΔAIC −28 181) but
    closed only 28 % of the held-out gap (30 % needed), and nothing was named.

    Fair to both: the current model is given its sequence decided again from its own
    solution too, and measured there when that changes it (only once the candidate
    passes: decided once in its fit, it mostly stands)."""
    rec = dict(changed=False, refits=0)

    def measure(model, runs_):
        task = candidate_tasks([], model, runs_, fopts, folds, opts, threads, where_hint=[])[0][0]
        rec["refits"] += 1
        res = CandidateResult.from_dict(executor.submit(run_candidate, task).result())
        ho = res.heldout or {}
        if not res.ok or not np.isfinite(ho.get("gap_um", float("nan"))):
            raise RuntimeError(f"its held-out gap could not be measured ({res.status}"
                               f"{', ' + ho['error'] if ho.get('error') else ''})")
        return res

    try:
        eff = get_effect(c.effect, runs)
        cand = dict(values=dict(c.values), free=tuple(c.free), law=c.law, w=c.w, ev_M=c.ev_M,
                    n_theta=len(c.free), chi2=c.chi2, n_eff=c.n_eff,
                    bounds={**current.get("bounds", {}), **dict(eff.bounds)},
                    priors={**(current.get("priors") or {}), **(c.priors or {})})
        say(f"  {c.effect} explains {100 * c.explained_share:.0f} % of the excess χ² but closes "
            f"{100 * max(c.closed_fraction, 0):.0f} % of the held-out gap: measured on its own mode sequence")
        new, runs2, changed = resequence(cand, runs, fopts, prob0, say)
        if not changed:
            return c.but(own_sequence=rec)
        m = measure(new, runs2)
        noise = base.gap["noise_um"]
        before, after = float(base.heldout["gap_um"]), float(m.heldout["gap_um"])
        closed = closed_share(before, after, noise)
        ctrl = None
        if closed >= MIN_CLOSED:
            say("  and the current model on the sequence it decides again, for a fair comparison")
            model_c, runs_c, changed_c = resequence(current, runs, fopts, prob0, say)
            ctrl = dict(changed=bool(changed_c), **model_c.get("sequence_changes", {}))
            if changed_c:
                before = float(measure(model_c, runs_c).heldout["gap_um"])
                closed = closed_share(before, after, noise)
        # recorded only now: a comparison the control could not complete names nothing
        rec.update(changed=True, **new["sequence_changes"], heldout_gap_before_um=before, heldout_gap_after_um=after,
                   gap_after_um=float(m.gap["gap_um"]), chi2=float(m.chi2), closed_fraction=float(closed))
        if ctrl is not None:
            rec["current_resequenced"] = ctrl
        say(f"  {c.effect}: {own_text(rec)}")
        return c.but(own_sequence=rec, own_model=dict(current=new, runs=runs2, measured=m))
    except Exception as err:  # the candidate is judged on the current sequence, as before
        rec.update(changed=False, error=f"{type(err).__name__}: {err}")
        say(f"  {c.effect}: {own_text(rec)}")
        return c.but(own_sequence=rec, own_model=None)

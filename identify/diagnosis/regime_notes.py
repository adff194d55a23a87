"""The runs left out for their regime in a diagnosis: the regime screen's and profile's
evidence, turned into the notes and verdict lines the report gives."""

from __future__ import annotations

import concurrent.futures as cf
import math
import time
from collections.abc import Callable

import numpy as np
from scipy import stats

from identify.diagnosis.records import CandidateResult, Round
from identify.diagnosis.regime_screen import moved_text, own_screen, parting, regime_screen, smallest_moves
from identify.diagnosis.result import DiagnosisOptions, DiagnosisResult
from identify.fitting.convergence import GIVE_UP_FEAS
from identify.fitting.driver import FitOptions
from identify.model.effects import display

# ----------------------------------------------------------------------------- driver
# identify.fitting.driver's reason for a run without resolvable slips where the model makes them (a
# model that steps in slips below the noise agrees with such a run: that is no mismatch)
REGIME_MISMATCH = "the model predicts stick-slip"


def regime_mismatch(err, fopts: FitOptions, opts: DiagnosisOptions, t0: float,
                     say: Callable[[str], None], executor: cf.Executor | None = None) -> DiagnosisResult:
    """No run has a resolvable slip where the model, at the start parameters, stick-slips
    in every one, and the runs that creep as the model does, if any, are too few to fix
    the parameters (measured: logistic-law data, which never re-age after a slip; with
    the stick option as written, v_stick = 0, three of them creep: three means for four
    parameters): there is nothing to fit, and so no baseline to refine — a gap between
    the model and every run, which no candidate can be scored on by a refit. The verdict is ``unexplained``, with
    the regime named as where the misfit lives, and each candidate screened at its
    realistic magnitude against the runs' regime (:mod:`identify.diagnosis.regime_screen`): which
    of them could make such runs, said, not named. The screen runs on ``executor`` (or
    on one made from ``opts``, closed again here)."""
    from identify.diagnosis.where import Misfit, misfit_sigma

    excluded = err.excluded
    n = len(excluded)
    used = list(getattr(err, "used", []))
    current, screen, moves = None, [], []
    if err.regime_runs:
        say(f"no baseline: screening the candidates on the {len(err.regime_runs)} run(s) left out for their regime")
        # each candidate simulated in the diagnosis's workers, as its refits would be
        own = executor
        current, screen = regime_screen(opts.effects, fopts.law, fopts.free, err.values, err.regime_runs, say,
                                        executor=own)
        moves = own_screen(fopts.law, fopts.free, err.values, err.regime_runs, say, executor=own)
    rc = (current or {}).get("regime") or {}
    p = float(rc["p_value"]) if rc.get("df") else 0.0
    detail = (f"{n} of {n + len(used)} runs show no resolvable slip, where the model at the coating's preset "
              "stick-slips: " + "; ".join(f"{name}: {why}" for name, why in excluded))
    n_obs, n_eff = getattr(err, "counts", None) or (float("nan"),) * 2
    if used:
        detail += (f"; the other {len(used)} run(s) ({', '.join(used)}) creep as the model does: {n_obs} "
                   f"observation(s) for {n_eff} free dimension(s), too few to fit")
    if rc.get("df"):
        detail += (f"; read as the data were, {len(rc['mismatched'])} of {rc['df']} part from it "
                   f"(χ² {rc['chi2']:.1f}, df {rc['df']})")
        if not rc["mismatched"]:
            detail += (": no mismatch once read like the data, so the runs are unusable for a fit "
                       "rather than evidence against the model")
    where0 = [Misfit(feature="regime", misfit_sigma=misfit_sigma(p), p_value=p,
                     statistic=float(rc.get("chi2", n)), detail=detail)]
    nan = float("nan")
    why = ("no run shows a resolvable slip where the model stick-slips in every one" if not used else
           f"{n} run(s) show no resolvable slip where the model stick-slips, and the {len(used)} that creep as "
           f"the model does give {n_obs} observation(s) for {n_eff} free dimension(s)")
    notes = [f"no baseline could be fitted: {why}, so no candidate could be scored by a refit and the data carry "
             "no slip to compare the friction law with (record runs that stick-slip, or fit the creep levels from "
             "parameters under which the model creeps)"]
    reproducing = smallest_moves(moves)
    confounded = _screen_confounded(screen, reproducing)
    if screen:
        notes.append(screen_note(current, screen, reproducing))
    return DiagnosisResult(
        verdict="unexplained", effects=[], where=where0, where_final=where0, candidates=[], rounds=[],
        baseline=None, final=dict(law=None, free=[], values={}, gap_um=nan, heldout_gap_um=nan, noise_um=nan,
                                  heldout_gap_ratio=nan),
        confounded=confounded, options=opts,
        timing=dict(total_s=time.perf_counter() - t0, refits=0, baseline_fit_s=nan),
        notes=notes, regime_screen=([dict(current)] if current else []) + screen, regime_moves=moves,
    )


def _screen_confounded(screen: list, reproducing: list) -> list:
    """Candidates that make runs like the data's when the current model, with one of its
    own parameters moved, makes them too (:func:`identify.diagnosis.regime_screen.own_screen`): the
    runs cannot tell them apart, so each such candidate is confounded with those
    parameters (``confounded_with`` on its screen record) and a group says why."""
    if not reproducing:
        return []
    params = sorted({n for r in reproducing for n in r["moved"]})
    moved = " or ".join(moved_text(r) for r in reproducing)
    groups = []
    for r in screen:
        if r["reproduces_regime"]:
            r["confounded_with"] = list(params)
            groups.append(dict(effects=[r["effect"]], confounded_with=list(params), closes=False,
                               why=(f"makes runs like the data's, and so does the current model with {moved}: "
                                    "these runs cannot tell them apart")))
    return groups


SCREEN_AT_START = ("the fit's start values", "nothing was fitted (the start's friction, the library's magnitude), "
                   "so this says which candidate to fit, not that it is the cause")


def screen_note(current: dict, screen: list, reproducing: list = (), at: tuple = SCREEN_AT_START) -> str:
    """What the regime screen found, in a sentence: which candidates make runs like the
    data's, against the current model — a pointer, not a name — and whether the current
    model makes them too with one of its own parameters moved (``reproducing``:
    :func:`identify.diagnosis.regime_screen.smallest_moves`), which confounds those candidates.
    ``at``: (the values screened at, why what reproduces the runs is not named)."""
    def runs(r):
        part = parting(r)
        return f"{part} runs, χ² {r['regime']['chi2']:.1f}" if part else f"? ({r['error']})"

    yes = [r for r in screen if r["reproduces_regime"]]
    failed = [r["effect"] for r in screen if r.get("error")]
    others = [r for r in screen if not r["reproduces_regime"] and r.get("regime") and not r.get("error")]
    head = (f"regime screen ({at[0]}, each candidate at its realistic magnitude, the runs read "
            f"as the data were): the current model parts from {runs(current)}; ")
    tail = f"; not simulated in every run: {', '.join(failed)}" if failed else ""
    moved = " or ".join(moved_text(r) for r in reproducing)
    if not yes:
        own = (f". The current model itself makes runs like these with {moved}: fit their creep levels from there"
               if moved else "")
        return head + "no candidate reproduces the runs" + tail + own
    lo, hi = (min(r["mismatched"] for r in others), max(r["mismatched"] for r in others)) if others else (0, 0)
    span = f"{lo}-{hi}" if lo != hi else f"{lo}"
    left = f"; every other candidate parts from {span} run(s) (or from their largest slips)" if others else ""
    names = ", ".join(r["effect"] for r in yes)
    also = f", and so does the current model with {moved}" if moved else ""
    text = (head + names + " reproduce" + ("s" if len(yes) == 1 else "")
            + " them (no run parts, the largest slips agree)" + also + left + tail)
    if moved:
        params = ", ".join(sorted({n for r in reproducing for n in r["moved"]}))
        return (text + f". Confounded with {params}, not named: these runs cannot tell {names} from the current "
                "model at such values, and nothing was fitted")
    return text + f". Not named: {at[1]}"


SCREEN_AT_FINAL = ("the final model's values", "nothing is refitted here (the library's magnitude on the final "
                   "values), so this says which candidate to test, not that it is the cause; the check at each "
                   "candidate's magnitude, refitted, and a profile weigh it on every run")


def final_screen(current: dict, regime_runs: list, effects: list, opts: DiagnosisOptions, say,
                  executor=None) -> list:
    """The current model and each candidate not named, at its realistic magnitude on top
    of the final model's values, against the runs left out for their regime that the
    final model still parts from (:func:`identify.diagnosis.regime_screen.regime_screen`): which
    candidate would make them like the data's. A pointer, never a name: those runs are
    in no likelihood, and the fitted runs did not name it. The current model's own
    parameters are not moved here (the screen without a baseline does): the fitted runs
    fix them. Measured (withheld rejuvenation set, dc = 1 µm; 2 runs fitted at the noise,
    6 left out, 3 of them parting, χ² 54): rejuvenation alone makes all 6 (χ² 0, the
    largest slips agreeing), every other candidate parts from 2-4; ~15 s.
    Returns [current model's record, candidates' records...], or [] if the screen fails."""
    ids = [e for e in opts.effects if e not in effects]
    own = executor
    try:
        say(f"regime screen at the final model's values: {len(regime_runs)} run(s) left out for their regime")
        cur, screen = regime_screen(ids, current["law"], current["free"], current["values"], regime_runs, say,
                                    executor=own)
    except Exception as err:  # the screen is a pointer: the diagnosis stands without it
        say(f"regime screen failed: {type(err).__name__}: {err}")
        return []
    return [dict(cur)] + screen


def held_evidence(rnd: list, effects: list, check, current_chi2: float | None = None) -> list:
    """The candidates of the final round (``rnd``) whose check at the realistic magnitude
    (:func:`identify.diagnosis.magnitude_check.at_magnitude`: the effect held there, the model's own
    parameters refitted to the runs fitted) makes the runs left out for their regime as
    the data's while it fits the runs fitted as well, where the final model parts from
    them (``check``, its :class:`identify.fitting.regime_check.RegimeCheck`).

    Each candidate with such a check gets ``held_regime`` (a new record): the fitted runs' Δnll at the
    magnitude (``fits``: within the χ²₁ quantile of the current model and on continuity
    to :data:`identify.fitting.convergence.GIVE_UP_FEAS`), the left-out runs' regime χ² there against the
    final model's, and their sum, ``joint_delta_chi2`` = 2·Δnll + Δχ²_regime, with the
    p-value of its fall on one degree of freedom: the evidence of all the runs at one
    point, the library's magnitude. It names nothing: that point is not an estimate (the
    runs fitted cannot tell it from the null, the runs left out enter no likelihood).
    Δnll is against ``current_chi2`` (the current model's χ² at the values ``check`` read)
    where given. Measured (withheld rejuvenation, dc = 1 µm): held at 1 µm the 2 runs
    fitted give Δnll −0.12 and all 6 left out come out as the data's, χ² 54.3 -> 0 (joint
    Δχ² −54.5, p 1.6e-13); on top of the final values without the refit 1 µm kept the
    left-out runs too but shrank the fitted runs' largest slips (z 5.5, 7.8).

    Returns those (with their ``held_regime``) that fit and reproduce the runs first, then
    by joint Δχ²."""
    if check is None or not check.df:
        return []
    out = []
    for c in map(CandidateResult.from_dict, rnd):  # (records; dicts of their fields are read as records)
        am = c.at_magnitude or {}
        rc = am.get("regime") or {}
        dnll = am.get("delta_nll")
        if current_chi2 is not None and am.get("chi2") is not None:
            # against the current model's χ² at the values ``check`` read: the pairing the
            # joint needs (the round re-judges Δnll against its own re-solve of the current
            # model, which on the rejuvenation set ended at 2754.0, above its start's 2745.0)
            dnll = 0.5 * (float(am["chi2"]) - float(current_chi2))
        if (not c.effect or c.effect in effects or not c.ok or not rc.get("df")
                or dnll is None or not np.isfinite(dnll)):
            continue
        fits = bool(dnll <= am["needed_delta_nll"] and am.get("continuity_um", math.inf) <= GIVE_UP_FEAS)
        joint = 2.0 * dnll + float(rc["chi2"]) - float(check.chi2)
        out.append(c.but(held_regime=dict(
            parameter=am["parameter"], value=am["value"], delta_nll=float(dnll),
            needed_delta_nll=am["needed_delta_nll"], continuity_um=am.get("continuity_um"), fits=fits,
            reproduces=bool(rc.get("reproduces")), mismatched=len(rc.get("mismatched", [])), df=int(rc["df"]),
            chi2=float(rc["chi2"]), final_mismatched=len(check.mismatched), final_chi2=float(check.chi2),
            joint_delta_chi2=float(joint), p_value=float(stats.chi2.sf(-joint, 1)) if joint < 0 else 1.0)))
    out.sort(key=lambda c: (not (c.held_regime["fits"] and c.held_regime["reproduces"]),
                            c.held_regime["joint_delta_chi2"]))
    return out


def held_note(held: list, n_runs: int) -> str | None:
    """The sentence of :func:`held_evidence`: which candidates, held at their realistic
    magnitude and refitted, fit the runs fitted as well and make the runs left out as the
    data's — not named from there (one of them alone is profiled next,
    :func:`identify.diagnosis.rounds._profile_held`); None where none does (the report's regime screen lists each
    reading)."""
    yes = [c for c in held if c.held_regime["fits"] and c.held_regime["reproduces"]]
    if not yes:
        return None
    head = ("held at its realistic magnitude with the model's own parameters refitted to the runs fitted, "
            f"each candidate read on the {n_runs} run(s) left out for their regime: ")

    def one(c):
        h = c.held_regime
        return (f"{c.effect} at {h['parameter']} = {display(h['parameter'], h['value'])} fits them as well "
                f"(Δnll {h['delta_nll']:+.2f}, within {h['needed_delta_nll']:.1f}) and makes the runs left out as "
                f"the data's ({h['mismatched']} of {h['df']} parting, χ² {h['chi2']:.1f}, against the final model's "
                f"{h['final_mismatched']} of {h['df']}, χ² {h['final_chi2']:.1f}): joint Δχ² "
                f"{h['joint_delta_chi2']:.1f} (p = {h['p_value']:.2g})")

    names = ", ".join(c.effect for c in yes)
    tail = (f". Not named from here: {'its magnitude is' if len(yes) == 1 else 'their magnitudes are'} the "
            "library's, not estimated")
    tail += f"; nor can these runs tell {names} apart" if len(yes) > 1 else " (its profile follows)"
    return head + "; ".join(one(c) for c in yes) + tail


def regime_check_notes(law: str, values: dict, regime_runs: list, notes: list):
    """:func:`identify.fitting.regime_check.regime_check` under ``law`` at ``values``; None (and a
    note) if the check itself fails: the diagnosis goes on without it."""
    from identify.fitting.regime_check import regime_check
    from identify.model.laws import get_law
    from identify.model.symbolic import Model

    if not regime_runs:
        return None
    try:
        rc = regime_check(Model(get_law(law)), values, regime_runs)
    except Exception as err:
        rc, why = None, f"{type(err).__name__}: {err}"
    else:
        why = "; ".join(rc.errors) if not rc.df else None
    if why:  # (with_regime leaves out a check of no run: say why here)
        txt = f"the runs left out for their regime could not be simulated: {why}"
        if txt not in notes:
            notes.append(txt)
    return rc


def regime_notes(scored: list, base) -> list:
    """Say of each candidate whether it puts the left-out runs the current model misfits
    for their regime (``base.regime``) in the data's regime: the candidates, those it
    applies to with their ``regime_fixed``, ``regime_broken`` and note."""
    base = CandidateResult.from_dict(base)
    if "mismatched" not in (base.regime or {}):
        return list(scored)
    return [_regime_note(CandidateResult.from_dict(c), set(base.regime["mismatched"])) for c in scored]


def _regime_note(c, bad: set):
    """:func:`regime_notes` of one candidate (``bad``: the runs the current model misfits)."""
    rc = c.regime or {}
    if not c.ok or "mismatched" not in rc:
        return c
    fixed, broken = sorted(bad - set(rc["mismatched"])), sorted(set(rc["mismatched"]) - bad)
    c = c.but(regime_fixed=fixed, regime_broken=broken)
    said = []
    if fixed:
        said.append(f"under it {len(fixed)} of the {len(bad)} run(s) left out for their regime that the current "
                    "model stick-slips lose their resolvable slips, as in the data")
    elif bad:
        said.append(f"it leaves the {len(bad)} run(s) left out for their regime stick-slipping, unlike the data")
    if broken:  # evidence against it: the verdict's regime test will say so if it is named
        said.append(f"it stick-slips where the data and the current model do not: {', '.join(broken)}")
    if said:
        c = c.but(note="; ".join(([c.note] if c.note else []) + said))
    return c


def regime_left_note(check, rounds, effects) -> str:
    """The note of a final model that still puts left-out runs in another regime, with the
    candidates of the last round that had any, not named, under which none of them does."""
    rounds = [Round.of(r) for r in rounds]
    last = next((r for r in reversed(rounds) if any(c.effect for c in r)), [])
    fixers = [c.effect for c in last if c.effect and c.effect not in effects and c.ok
              and "mismatched" in (c.regime or {}) and not set(c.regime["mismatched"]) & set(check.mismatched)]
    txt = "regime: " + check.text()
    if fixers:
        one = len(fixers) == 1
        txt += (f"; under {', '.join(fixers)}, at {'its' if one else 'their'} refitted values, they do not stick-slip, "
                f"as in the data, but {'it' if one else 'none'} could {'not ' if one else ''}be named on the runs "
                f"fitted (see {'its' if one else 'their'} note{'' if one else 's'})")
    return txt

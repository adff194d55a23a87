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
   candidates, or ΔAIC < −10 for a law), the model's own parameters cannot mimic it
   (R² < 0.99 in the information metric, else ``confounded_with`` names them), no other
   candidate explains the same residuals as well (nearly parallel residual change and
   |ΔΔAIC| < 10: both are reported as confounded and neither is named), and it closes a
   real part of the gap on held-out runs (:func:`_closes`: of the µm gap, or — where
   that gap sits at the encoding's own floor — of the excess χ² with the likelihood gain
   kept held out; on all runs or on all but the one that argues most against it), and
   it stays significant refitted beside any better-fitting candidate the model's own
   parameters mimic (:func:`_beside`; else the two are reported as confounded).
   Forward selection adds it and tries the rest again.
4. Verdict: ``adequate`` when the final model's held-out gap is within ``gap_tolerance``
   (1.5×) of the noise floor, or when no feature is significant (Bonferroni over the
   features) and no nameable candidate is left significant; else ``unexplained`` (a gap
   no candidate closes, or one only confounded candidates do).
"""

from __future__ import annotations

import concurrent.futures as cf
import functools
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from identify import interrupts
from identify.diagnosis.candidates import (
    GAVE_UP,
    GIVE_UP_MARGIN,
    MAGNITUDE_MOVED_Z,
    STALLED,
    CandidateTask,
    run_candidate,
)
from identify.diagnosis.features import feature_values
from identify.diagnosis.heldout import folds_of
from identify.diagnosis.record import DiagnosisRecord, RecordedExecutor, inputs_digest
from identify.diagnosis.regime_screen import moved_text, own_screen, parting, regime_screen, smallest_moves
from identify.diagnosis.where import where, with_regime
from identify.executors import make_executor
from identify.fitting.convergence import GIVE_UP_FEAS, NOT_DIFFERENTIABLE
from identify.fitting.driver import FitError, FitOptions, fit
from identify.jsonio import write_json
from identify.model.effects import EFFECTS, display, get_effect
from identify.model.symbolic import LENGTH_UNIT
from identify.progress import Stage, reporter

__all__ = ["DiagnosisOptions", "DiagnosisResult", "diagnose", "make_executor"]

log = logging.getLogger(__name__)

LAW_DELTA_AIC = -10.0  # a non-nested law is preferred only with strong support
SAME_RESIDUALS = 0.9  # cosine of two candidates' residual changes above which they explain the same thing
TIE_AIC = 10.0
MAX_RIVALS = 2  # better-fitting candidates the model mimics that a named one is checked beside (_beside)
CONFOUNDED_R2 = 0.99
WALD_Z = 5.0  # a candidate determined this many stderr off its null is not called confounded
MIN_CLOSED = 0.3  # a named effect closes at least this share of the gap (see _closes)
HELDOUT_SHARE = 0.5  # ... and, judged by the likelihood, keeps this share of its gain held out
EXCESS_FLOOR = 3.0  # the excess χ² a share is taken of is at least this many of its chance σ
MIN_FOLDS_SET_ASIDE = 5  # one-run folds needed before one may be set aside (the rest must decide)


@dataclass(frozen=True)
class DiagnosisOptions:
    """How to diagnose.

    Parameters
    ----------
    effects : "all" or sequence of str
        Candidate ids (:data:`identify.model.effects.EFFECTS`).
    folds : "loo" or int
        Held-out runs: leave-one-run-out or k-fold (seeded).
    alpha : float
        Family-wise level of the tests (Bonferroni over candidates, and over features).
    max_effects : int
        Forward selection stops after this many.
    workers : int
        Local worker processes (1: in this process).
    dask : str or None
        Address of a dask.distributed scheduler (overrides ``workers``).
    seed : int
    gap_tolerance : float
        A model whose held-out gap (RMS feature misfit) is within this factor of the noise
        floor is ``adequate`` even when a feature test is formally significant: the
        trigger encoding itself leaves up to 1.24× on data made by the model (README).
    resequence : True, False or "auto"
        Once an effect is named, decide the mode sequence again with it
        (:func:`identify.fitting.driver.decide_sequence`): the baseline's sequence was decided by a
        model without the effect and may have been bent to absorb it (inserted slips,
        moved triggers), which the model with the effect then misfits. A new sequence is
        kept only if it lowers χ² (with the within-plateau sums). ``"auto"`` (default):
        only while the named model's held-out gap is above ``gap_tolerance`` times the
        noise, or could not be computed. Measured on the benchmark's topography set (λ = 4 µm; at 65a0b09, the
        candidate alone): named with a = 0.0255 ± 0.0002 (truth 0.03) and the held-out gap
        at 1.51× the noise, ``unexplained``; the sequence decided again moved 4 triggers in
        15 s, χ² 13842 -> 10730, a = 0.0295, λ = 3.997 µm, φ = 0.69 (truth 0.7), held-out gap
        1.08×, ``adequate``. Not always on: on the drift set (5e-8 m/s, at 51d9caf's
        parent, whose guard compared the compressed χ² alone) it moved 32 triggers and
        inserted a slip in 756 s, the χ² with the within-plateau sums rose 28207 -> 39541
        (the guard now rejects that); drift is now named with its held-out gap within the
        tolerance, where ``"auto"`` leaves the sequence alone.
    magnitude_check : bool
        Solve each candidate that is not significant again with its parameter held at
        its realistic magnitude (:func:`identify.diagnosis.candidates._at_magnitude`): where that
        fits as well, the data cannot exclude the effect, and the parameters that move to
        absorb it are reported as its partners (``confounded_with``). One more solve per
        such candidate, stopped as soon as the answer is known.
    record : path, optional
        A file that keeps the baseline fit and every refit as it finishes
        (:mod:`identify.diagnosis.record`), so that an interrupted diagnosis can resume.
    resume : bool
        Take the baseline and every refit the ``record`` holds instead of computing them
        again (the record must be for the same data and options: it says so if not).
    """

    effects: Any = "all"
    folds: Any = "loo"
    alpha: float = 0.01
    max_effects: int = 3
    workers: int = 1
    dask: str | None = None
    seed: int = 0
    max_iter: int = 20
    gap_tolerance: float = 1.5
    resequence: Any = "auto"
    magnitude_check: bool = True
    record: str | None = None
    resume: bool = False

    def __post_init__(self):
        ids = tuple(EFFECTS) if self.effects in ("all", None) else tuple(self.effects)
        for e in ids:
            get_effect(e)
        object.__setattr__(self, "effects", ids)
        if not 0 < self.alpha < 1:
            raise ValueError(f"alpha = {self.alpha!r}: must lie in (0, 1)")
        if int(self.workers) < 1:
            raise ValueError(f"workers = {self.workers!r}: must be a positive integer")
        if self.folds not in ("loo",) and not (isinstance(self.folds, int) and self.folds >= 2):
            raise ValueError(f"folds = {self.folds!r}: use 'loo' or an integer >= 2")
        if self.resequence not in (True, False, "auto"):
            raise ValueError(f"resequence = {self.resequence!r}: use True, False or 'auto'")
        if not isinstance(self.resequence, str):  # (1, np.True_: diagnose() tests ``is True``)
            object.__setattr__(self, "resequence", bool(self.resequence))


# ----------------------------------------------------------------------------- result
@dataclass
class DiagnosisResult:
    """The outcome of :func:`diagnose`."""

    verdict: str
    effects: list
    where: list  # Misfit, baseline
    where_final: list  # Misfit, final model
    candidates: list  # dicts, first round, best first
    rounds: list  # per round: list of candidate dicts
    baseline: Any  # FitResult
    final: dict  # values, free, law, gap, heldout gap
    confounded: list
    options: DiagnosisOptions
    timing: dict
    notes: list = field(default_factory=list)
    # no baseline (every run left out for its regime), or a final model that still parts
    # from runs left out for their regime: the current model, then each candidate at its
    # realistic magnitude, against the runs' regime (identify.diagnosis.regime_screen)
    regime_screen: list = field(default_factory=list)
    # ... and the current model with one of its own parameters moved (identify.diagnosis.regime_screen.own_screen)
    regime_moves: list = field(default_factory=list)
    # a candidate held at its magnitude that makes the runs left out as the data's,
    # profiled on every run (identify.diagnosis.regime_profile; _profile_held)
    regime_profile: dict | None = None
    final_problem: Any = field(repr=False, default=None)
    final_w: Any = field(repr=False, default=None)

    def not_converged(self) -> list:
        """Every candidate refit, in any round, that failed or ended without converging
        (its round, effect and status)."""
        done = ("Solve_Succeeded", STALLED, GAVE_UP)
        return [dict(round=k + 1, effect=c["effect"], status=str(c.get("status") or c.get("reason") or "failed"))
                for k, rnd in enumerate(self.rounds) for c in rnd
                if c.get("effect") and c.get("status") != "not applicable"
                and (not c.get("ok") or c.get("status") not in done)]

    def report(self) -> str:
        L = []
        L.append("[[Diagnosis]]")
        L.append(f"    verdict            = {self.verdict}")
        L.append(f"    effects added      = {', '.join(self.effects) if self.effects else '(none)'}")
        unconverged = self.not_converged()
        if unconverged:  # (the verdict stands on these refits too: the reader must see which ended short)
            L.append(f"    not converged      = {len(unconverged)} refit(s): " + "; ".join(
                f"{c['effect']} (round {c['round']}: {c['status']})" for c in unconverged))
        for grp in self.confounded:
            L.append(f"    confounded         = {' | '.join(grp['effects'])}: {grp['why']}")
        base = next((c for c in (self.rounds[0] if self.rounds else []) if c.get("effect") is None), None)
        if base and base.get("ok"):
            L.append(f"    gap (fitted runs)  = {base['gap']['gap_um'] * 1e3:.1f} nm before; noise floor "
                     f"{base['gap']['noise_um'] * 1e3:.1f} nm")
            ho = base["heldout"]
            why = (f" (not computed: {ho['error']})" if ho.get("error") else
                   f" ({ho['refitted_folds']} fold(s) refitted: the linear leave-out step did not hold)"
                   if ho.get("refitted_folds") else "")
            L.append(f"    gap (held out)     = {_cell(_nm(ho.get('gap_um')), '.1f')} nm before{why}")
        if "regime_slip_gap_heldout_um" in self.final:  # named by its profile on every run
            f = self.final
            L.append(f"    gap after          = {f['gap_um'] * 1e3:.1f} nm fitted; the runs left out for their "
                     f"regime, largest slips: {f['regime_slip_gap_before_um'] * 1e3:.0f} nm -> "
                     f"{f['regime_slip_gap_after_um'] * 1e3:.0f} nm, {f['regime_slip_gap_heldout_um'] * 1e3:.0f} nm "
                     "held out (each run predicted from the profile without it)")
        else:
            L.append(f"    gap after          = {self.final['gap_um'] * 1e3:.1f} nm fitted, "
                     f"{self.final['heldout_gap_um'] * 1e3:.1f} nm held out ({self.options.folds} folds)")
        L.append(f"    wall time          = {self.timing['total_s']:.1f} s ({self.timing['refits']} refits, "
                 f"{self.options.workers if not self.options.dask else 'dask'} worker(s))")
        L.append("[[Where (baseline), ranked]]")
        for m in self.where:
            L.append(f"    {m.feature:27s} {m.misfit_sigma:5.1f} σ  p = {m.p_value:.2g}  {m.detail}")
        if self.effects:
            L.append("[[Where (final model)]]")
            for m in self.where_final[:5]:
                L.append(f"    {m.feature:27s} {m.misfit_sigma:5.1f} σ  p = {m.p_value:.2g}  {m.detail}")
        for k, rnd in enumerate(self.rounds):
            L.append(f"[[Candidates, round {k + 1}]]" + (f" (after adding {', '.join(self.effects[:k])})" if k else ""))
            L.append(f"    {'effect':24s} {'Δnll':>9s} {'p':>9s} {'ΔAIC':>9s} {'ΔBIC':>9s} {'gap nm':>13s} "
                     f"{'held-out nm':>13s} {'Δnll h-o':>9s}  note")
            for c in rnd:
                if c.get("effect") is None:
                    continue
                if not c.get("ok"):
                    L.append(f"    {c['effect']:24s} {c.get('reason') or c.get('status')}")
                    continue
                p = c["p_value"]
                L.append(f"    {c['effect']:24s} {_cell(c['delta_nll'], '9.2f')} {_cell(p, '9.2g')} "
                         f"{_cell(c['delta_aic'], '9.1f')} {_cell(c['delta_bic'], '9.1f')} "
                         f"{_cell(_nm(c['gap_before_um']), '5.1f')}->{_cell(_nm(c['gap_after_um']), '<6.1f')} "
                         f"{_cell(_nm(c['heldout_gap_before_um']), '5.1f')}->"
                         f"{_cell(_nm(c['heldout_gap_after_um']), '<6.1f')} "
                         f"{_cell(c.get('heldout_delta_nll'), '9.2f')}  {c['note']}")
        if self.regime_screen:
            at = ("no baseline: the fit's start values" if self.baseline is None else
                  "the runs left out for their regime, at the final model's values")
            L.append(f"[[Regime screen]] ({at}, each candidate at its realistic magnitude)")
            L.append(f"    {'model':24s} {'runs parting':>13s} {'χ²':>9s}  note")
            for r in self.regime_screen:
                rc = r.get("regime") or {}
                name = r["effect"] or "(current model)"
                part = parting(r) or "-"
                note = "reproduces the regime" if r["reproduces_regime"] else (r.get("error") or "")
                if r.get("confounded_with"):
                    note += f"; confounded with {', '.join(r['confounded_with'])}"
                L.append(f"    {name:24s} {part:>13s} {rc.get('chi2', float('nan')):9.1f}  {note}")
            for r in smallest_moves(self.regime_moves):
                L.append(f"    {'(current model, moved)':24s} {parting(r):>13s} {r['regime']['chi2']:9.1f}  "
                         f"reproduces the regime with {moved_text(r)}")
            if self.regime_moves:
                L.append(f"    ({len(self.regime_moves)} move(s) of the current model's own parameters tried, one "
                         "at a time toward each bound)")
            last = self.rounds[-1] if self.rounds else []
            for c in [c for c in last if c.get("held_regime")]:
                h = c["held_regime"]
                fits = ("fits the runs fitted as well" if h["fits"] else "fits the runs fitted worse"
                        if h["delta_nll"] > h["needed_delta_nll"] else
                        f"stopped {(h['continuity_um'] or float('nan')) * 1e3:.1f} nm off continuity")
                L.append(f"    {c['effect'] + ', held':24s} {str(h['mismatched']) + ' of ' + str(h['df']):>13s} "
                         f"{h['chi2']:9.1f}  "
                         f"at {h['parameter']} = {display(h['parameter'], h['value'])}, refitted: {fits} "
                         f"(Δnll {h['delta_nll']:+.2f}); joint Δχ² {h['joint_delta_chi2']:.1f}")
        prof = self.regime_profile or {}
        if prof.get("points"):
            n = prof["parameter"]
            L.append(f"[[Regime profile]] ({prof['effect']}: {n} held, the runs fitted refitted, the runs left out "
                     f"read; current model: χ² {prof['current_chi2']:.1f} + {prof['current_regime_chi2']:.1f})")
            L.append(f"    {n:>12s} {'χ² fitted':>11s} {'χ² regime':>10s} {'joint':>10s}  status")
            for pt in prof["points"]:
                nan = float("nan")
                mark = "" if pt["used"] else " (not used: off continuity or not simulated)"
                L.append(f"    {display(n, pt['value']):>12s} {pt['chi2'] if pt['chi2'] is not None else nan:11.1f} "
                         f"{pt['regime_chi2'] if pt['regime_chi2'] is not None else nan:10.1f} "
                         f"{pt['joint'] if pt['joint'] is not None else nan:10.1f}  {pt['status']}{mark}")
        for n in self.notes:
            L.append(f"    note: {n}")
        return "\n".join(L)

    def to_json(self) -> dict:
        return dict(
            verdict=self.verdict, effects=list(self.effects), not_converged=self.not_converged(),
            where=[m.to_json() for m in self.where],
            where_final=[m.to_json() for m in self.where_final],
            candidates=[_cand_json(c) for c in self.candidates],
            rounds=[[_cand_json(c) for c in rnd if c.get("effect")] for rnd in self.rounds],
            confounded=self.confounded,
            final=self.final,
            baseline=self.baseline.to_json() if self.baseline is not None else None,
            options=dict(effects=list(self.options.effects), folds=self.options.folds, alpha=self.options.alpha,
                         workers=self.options.workers, dask=bool(self.options.dask),
                         gap_tolerance=self.options.gap_tolerance, resequence=self.options.resequence,
                         magnitude_check=self.options.magnitude_check),
            timing=self.timing, notes=self.notes, regime_screen=self.regime_screen, regime_moves=self.regime_moves,
            regime_profile=self.regime_profile,
        )

    def save_json(self, path) -> Path:
        """Strict JSON: non-finite numbers are written as null."""
        return write_json(path, self.to_json())

    def trigger_misfit_by_position(self) -> list:
        """Per model (the baseline, then the final model when an effect was added): (label,
        block position at each slip µm, static-friction misfit nm of elongation)."""
        panels = []
        if self.baseline is None:
            return panels
        models = [("baseline", self.baseline.problem, self.baseline.w)]
        if self.effects and self.final_problem is not None:
            models.append(("+ " + ", ".join(self.effects), self.final_problem, self.final_w))
        for label, prob, w in models:
            if not prob.n_trig:
                continue
            st = feature_values(prob, w, prob.residuals(w))["static_friction"]
            x_um = w[prob.i_x + prob.ev_prev[prob.ev_next]] * LENGTH_UNIT * 1e6
            panels.append((label, x_um, st.value_um * 1e3))
        return panels

    def trigger_misfit_by_run(self) -> list:
        """As :meth:`trigger_misfit_by_position`, with the run of each slip: per model a
        dict of ``label``, ``run`` (the run's name per slip), ``x_um``, ``misfit_nm`` and
        ``sigma_nm`` (the misfit's standard deviation per slip, nm of elongation: one
        puller step over √12, the resolution of a trigger)."""
        out = []
        if self.baseline is None:
            return out
        models = [("baseline", self.baseline.problem, self.baseline.w)]
        if self.effects and self.final_problem is not None:
            models.append(("+ " + ", ".join(self.effects), self.final_problem, self.final_w))
        for label, prob, w in models:
            if not prob.n_trig:
                continue
            st = feature_values(prob, w, prob.residuals(w))["static_friction"]
            x_um = w[prob.i_x + prob.ev_prev[prob.ev_next]] * LENGTH_UNIT * 1e6
            names = np.array([prob.runs[i].name for i in st.run])
            out.append(dict(label=label, run=names, x_um=x_um, misfit_nm=st.value_um * 1e3,
                            sigma_nm=st.sigma_um * 1e3))
        return out

    def save_plots(self, folder) -> list:
        from identify.plots.diagnosis import save_diagnosis_plots

        return save_diagnosis_plots(self, folder)


def _nm(um):
    """µm to nm, None kept."""
    return None if um is None else um * 1e3


def _cell(x, fmt: str) -> str:
    """A table cell: the number in ``fmt``, or a dash of the same width where there is
    none (not computed, or not a number), never 'nan'."""
    width = int("".join(ch for ch in fmt.lstrip("<>") if ch.isdigit() or ch == ".").split(".")[0] or 0)
    if x is None or not math.isfinite(float(x)):
        return f"{'–':{'<' if fmt.startswith('<') else '>'}{width}s}"
    return f"{x:{fmt}}"


_CAND_KEYS = ("effect", "parameters", "delta_nll", "p_value", "delta_aic", "delta_bic", "confounded_with",
              "gap_before_um", "gap_after_um", "heldout_gap_before_um", "heldout_gap_after_um", "significant",
              "named", "note", "ok", "status", "iterations", "wall_s", "law", "r2_with_model",
              "closed_fraction", "estimates", "rounds", "heldout_refitted_folds",
              "heldout_unverified_folds", "heldout_error", "heldout_delta_nll", "explained_share",
              "closes", "gap_sigma_before", "gap_sigma_after", "heldout_gap_sigma_before",
              "heldout_gap_sigma_after", "heldout_by_fold", "heldout_set_aside", "at_floor",
              "heldout_gap_ratio_before", "beside", "mimicked", "own_sequence", "wald_z", "undetermined",
              "at_magnitude", "regime", "regime_fixed", "regime_broken", "held_regime")


def _cand_json(c: dict) -> dict:
    return {k: c.get(k) for k in _CAND_KEYS}


# ----------------------------------------------------------------------------- driver
# identify.fitting.driver's reason for a run without resolvable slips where the model makes them (a
# model that steps in slips below the noise agrees with such a run: that is no mismatch)
REGIME_MISMATCH = "the model predicts stick-slip"


def _regime_mismatch(err, fopts: FitOptions, opts: DiagnosisOptions, t0: float,
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
        notes.append(_screen_note(current, screen, reproducing))
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


def _screen_note(current: dict, screen: list, reproducing: list = (), at: tuple = SCREEN_AT_START) -> str:
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
            return _regime_mismatch(err, fopts, opts, t0, say, executor)
    prob, w = baseline.problem, baseline.w
    fopts = prob.opts
    runs = prob.runs
    folds = folds_of(len(runs), opts.folds, seed=opts.seed)
    from identify.model.params import parameter_set

    # every parameter any candidate may free (another law's too), at the baseline's values
    values0 = {**parameter_set(baseline.coating), **prob.values, **baseline.values}
    # the runs the fit left out for their regime are evidence too (identify.fitting.regime_check)
    regime_runs = list(getattr(baseline, "regime_runs", None) or [])
    if regime_runs:
        say(f"simulating the {len(regime_runs)} run(s) left out for their regime under the baseline")
    notes: list = []
    where0 = with_regime(where(prob, w), _regime_check(prob.law.name, values0, regime_runs, notes))
    r0 = prob.residuals(w)
    current = dict(values=values0, free=tuple(prob.theta.names), law=prob.law.name,
                   w=w, ev_M=np.array(prob.ev_M), n_theta=prob.n_theta,
                   chi2=float(r0 @ r0) + prob.chi2_constant(), n_eff=prob.n_effective())
    own = executor
    threads = 1 if (opts.workers > 1 or opts.dask) else max(int(fopts.threads), 1)
    rounds, effects, confounded = [], [], []
    final_res = None
    n_refits = 0
    remaining = list(opts.effects)
    at_magnitude = {}  # candidates that fit better held at their realistic magnitude than refitted
    while True:
        tasks, skipped = _tasks(remaining, current, runs, fopts, folds, opts, threads, where_hint=where0,
                                regime_runs=regime_runs, at_magnitude=at_magnitude)
        stage = Stage(say, f"diagnosis round {len(rounds) + 1}", len(tasks))
        stage.start(f"{len(tasks) - 1} candidate refit(s) and the current model, {len(folds)} held-out fold(s) each")
        results = []
        futs = {}
        for t in sorted(tasks, key=_expected_cost, reverse=True):
            try:
                futs[own.submit(run_candidate, t)] = t
            except Exception as err:  # a broken pool or a lost cluster: the candidate fails
                results.append(dict(effect=t.effect, ok=False, status=f"failed: {err}", error=str(err)))
        for fut in cf.as_completed(futs):
            t = futs[fut]
            try:
                res = fut.result()
            except Exception as err:  # a lost worker: the candidate fails, the rest goes on
                res = dict(effect=t.effect, ok=False, status=f"failed: {err}", error=str(err))
            stage.advance(f"{t.effect or 'current model'} ({res.get('status')})")
            results.append(res)
        n_refits += len(tasks)
        base = next(r for r in results if r["effect"] is None)
        if not base.get("ok"):
            notes.append(f"the current model could not be re-evaluated: {base.get('status')}")
            rounds.append([base] + skipped)
            if final_res is not None:  # the named candidate's numbers, on the sequence it was named on
                notes.append("the gaps after are the last named candidate's, on the mode sequence it was "
                             "named on")
            else:
                final_res = base
            break
        final_res = base  # the current model, measured in this round
        scored = _score(results, base, opts, len([t for t in tasks if t.effect]),
                        fold_names=[[runs[i].name for i in f] for f in folds])
        rnd = [base] + sorted(scored, key=_rank) + skipped
        rounds.append(rnd)
        n_cand = len([t for t in tasks if t.effect])
        retry = None
        if opts.resequence is not False:
            retry = functools.partial(_own_sequence, base=base, current=current, runs=runs, fopts=fopts,
                                      prob0=prob, folds=folds, opts=opts, threads=threads, executor=own,
                                      say=say)
        beside = functools.partial(_beside, scored=scored, base=base, current=current, runs=runs, fopts=fopts,
                                   opts=opts, threads=threads, executor=own, where_hint=where0, n_cand=n_cand,
                                   say=say)
        chosen, groups = _choose(scored, base, beside, retry)
        _regime_notes(scored, base)
        confounded.extend(groups)
        n_refits += sum(len(c.get("beside", [])) for c in scored)  # each check is a refit
        # each measurement on a candidate's own sequence, and of the current model's control
        n_refits += sum(c.get("own_sequence", {}).get("refits", 0) for c in scored)
        adopted = chosen.pop("_own", None) if chosen is not None else None
        for c in scored:
            c.pop("_own", None)  # (the models of candidates not named)
        if chosen is None or len(effects) >= opts.max_effects:
            break  # (a round of the final model alone also ends here: it has no candidates)
        chosen["named"] = True
        final_res = chosen  # the model with it, as measured in this round
        effects.append(chosen["effect"])
        # the next round retries only what was significant in this one: adding an
        # effect explains part of the misfit, it does not create evidence elsewhere
        remaining = [c["effect"] for c in scored if c.get("significant") and c["effect"] != chosen["effect"]]
        # ... and what fit better held at its realistic magnitude than its refit, which
        # ended near its null (evidence without an estimate), started there too.
        # Measured (the two-effect set, load offset and step size): in round 1 the step
        # size's refit stayed at 1 ± 0.013 while 1.05 fit better; not retried, round 2
        # named the topography (a ripple of 9.9 µm) in its place
        at_magnitude = {c["effect"]: c["at_magnitude"] for c in scored
                        if (c.get("at_magnitude") or {}).get("better") and c["effect"] != chosen["effect"]}
        remaining += [e for e in at_magnitude if e not in remaining]
        eff = get_effect(chosen["effect"])
        if adopted:  # named on the mode sequence it decided: go on from there, as measured there
            current, runs, final_res = adopted["current"], adopted["runs"], adopted["measured"]
        else:
            current = dict(values=chosen["values"], free=tuple(chosen["free"]), law=chosen["law"],
                           w=chosen["w"], ev_M=chosen["ev_M"], n_theta=len(chosen["free"]), chi2=chosen["chi2"],
                           n_eff=chosen["n_eff"], bounds={**current.get("bounds", {}), **dict(eff.bounds)})
        say(f"added {chosen['effect']} ({', '.join(eff.parameters) or eff.law}); trying the rest again")
        if len(effects) >= opts.max_effects:
            remaining = []
        changed = False
        if not adopted and (opts.resequence is True or (opts.resequence == "auto" and not _at_noise(chosen, opts))):
            try:
                current, runs, changed = _resequence(current, runs, fopts, prob, say)
            except Exception as err:  # the named model stands with the baseline's sequence
                notes.append(f"deciding the mode sequence again with {chosen['effect']} failed: "
                             f"{type(err).__name__}: {err}")
        if not remaining and not changed:
            # nothing left to try: the final model is this candidate's refit, already
            # measured on the same folds (a round of it alone refitted every held-out
            # fold again: 8 exact refits, ~10 min, on the drift data), and no candidate
            # is left for the verdict to judge
            rounds.append([dict(final_res if adopted else chosen, effect=None, named=False)])
            break
    final_prob, final_w = _rebuild(current, runs, fopts, prob)
    regime_final = _regime_check(current["law"], current["values"], regime_runs, notes)
    # runs the final model puts in another regime than their data: whatever the held-out
    # gap of the runs it could fit, model and data part there (never `adequate`)
    regime_left = bool(regime_final is not None and regime_final.mismatched)
    screen, later, profile = [], [], None
    if regime_left:
        # the candidates at the final values (a pointer), the check at each one's magnitude
        # read on the runs left out, and where one makes them there, its profile on all runs
        own = executor
        screen = _final_screen(current, regime_runs, effects, opts, say, own)
        if len(screen) > 1:
            later.append(_screen_note(screen[0], screen[1:], at=SCREEN_AT_FINAL))
        held = _held_evidence(rounds[-1] if rounds else [], effects, regime_final, current.get("chi2"))
        held_txt = _held_note(held, len(regime_runs))
        if held_txt:
            later.append(held_txt)
        profile = _profile_held(held, current, runs, fopts, opts, regime_runs, regime_final, own, say,
                                n_cand=len([c for c in (rounds[-1] if rounds else []) if c.get("effect")]),
                                confounded=confounded)
        if profile is not None:
            later.append(profile["note"])
        if profile is not None and profile.get("named"):
            eff = get_effect(profile["effect"])
            best = profile.pop("best")
            name = profile["parameter"]
            effects.append(profile["effect"])
            current = dict(values={**current["values"], **best["values"]}, free=tuple(current["free"]) + (name,),
                           law=current["law"], w=best["w"], ev_M=best["ev_M"], n_theta=len(current["free"]) + 1,
                           chi2=best["chi2"], n_eff=current.get("n_eff"),
                           bounds={**current.get("bounds", {}), **dict(eff.bounds)})
            final_prob, final_w = _rebuild(current, runs, fopts, prob)
            regime_final = _regime_check(current["law"], current["values"], regime_runs, notes)
            regime_left = bool(regime_final is not None and regime_final.mismatched)
        elif profile is not None:
            profile.pop("best", None)
    where_final = with_regime(where(final_prob, final_w) if effects else where0, regime_final)
    n_feat = max(len(where_final), 1)
    misfit_left = [m for m in where_final if m.p_value < opts.alpha / n_feat]
    # significant candidates that would close a real part of the gap but could not be
    # named (no convergence, a confounded group): the gap is then not explained. One that
    # is formally significant but closes little is the encoding's own misfit, not evidence.
    # (the final round's record of the named model itself has effect None: not a candidate)
    # (nor is one whose estimate its own interval does not tell from the null: no evidence)
    still = [c for c in (rounds[-1] if rounds else []) if c.get("effect") is not None and c.get("significant")
             and not c.get("named") and c.get("effect") not in effects and not c.get("confounded_with")
             and not c.get("undetermined")
             and (c.get("closes") or c.get("heldout_error"))]
    grouped = {e for g in confounded if g.get("closes") for e in g["effects"]}
    ratio = _gap_ratio(final_res) if final_res and final_res.get("ok") else float("nan")
    within = _at_noise(final_res, opts) if final_res and final_res.get("ok") else False
    # within the tolerance there is no gap left for an unnamed candidate to explain
    if (within or (not misfit_left and not still and not grouped)) and not regime_left:
        verdict = "adequate"
        if misfit_left or still:
            notes.append(f"adequate: the held-out gap is {ratio:.2f}× the noise floor (tolerance "
                         f"{opts.gap_tolerance:g}×, the encoding's own error on model-made data), though "
                         + ", ".join([f"{m.feature} ({m.misfit_sigma:.1f} σ)" for m in misfit_left]
                                     + [f"candidate {c['effect']} ({_evidence(c)})" for c in still])
                         + " are significant")
    else:
        verdict = "unexplained"
        if misfit_left:
            notes.append(f"misfit left (held-out gap {ratio:.2f}× the noise floor) in: "
                         + ", ".join(f"{m.feature} ({m.misfit_sigma:.1f} σ)" for m in misfit_left))
        if still:
            notes.append("significant but not named: " + ", ".join(
                f"{c['effect']} ({c['note']})" for c in still))
        if grouped:
            notes.append("the gap is closed by candidates the data cannot tell apart: "
                         + "; ".join(" | ".join(g["effects"]) for g in confounded))
        if regime_left:
            notes.append(_regime_left_note(regime_final, rounds, effects))
    notes.extend(later)
    ok = bool(final_res and final_res.get("ok"))
    final = dict(law=current["law"], free=list(current["free"]),
                 values={n: current["values"][n] for n in current["free"]},
                 gap_um=final_res["gap"]["gap_um"] if ok else float("nan"),
                 heldout_gap_um=final_res["heldout"]["gap_um"] if ok else float("nan"),
                 noise_um=final_res["gap"]["noise_um"] if ok else float("nan"))
    final["heldout_gap_ratio"] = float(ratio)
    if profile is not None and profile.get("named"):
        # named by its profile: the runs fitted at its best point; held out, the runs left
        # out for their regime (the refits' held-out folds never had it)
        final.update(gap_um=profile["gap_after_um"], heldout_gap_um=float("nan"), heldout_gap_ratio=float("nan"),
                     regime_slip_gap_before_um=profile["slip_gap_before_um"],
                     regime_slip_gap_after_um=profile["slip_gap_after_um"],
                     regime_slip_gap_heldout_um=profile["slip_gap_heldout_um"])
    if not ok:
        verdict = "unexplained"
        notes.append("the refits failed, so no gap could be measured: " + (final_res or {}).get("status", "?"))
    return DiagnosisResult(
        verdict=verdict, effects=effects, where=where0, where_final=where_final,
        candidates=[c for c in rounds[0] if c.get("effect")] if rounds else [], rounds=rounds,
        baseline=baseline, final=final, confounded=confounded, options=opts,
        timing=dict(total_s=time.perf_counter() - t0, refits=n_refits,
                    baseline_fit_s=float(baseline.solver.get("wall_time_s", float("nan")))),
        notes=notes, final_problem=final_prob, final_w=final_w, regime_screen=screen, regime_profile=profile,
    )


SCREEN_AT_FINAL = ("the final model's values", "nothing is refitted here (the library's magnitude on the final "
                   "values), so this says which candidate to test, not that it is the cause; the check at each "
                   "candidate's magnitude, refitted, and a profile weigh it on every run")


def _final_screen(current: dict, regime_runs: list, effects: list, opts: DiagnosisOptions, say,
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


def _held_evidence(rnd: list, effects: list, check, current_chi2: float | None = None) -> list:
    """The candidates of the final round (``rnd``) whose check at the realistic magnitude
    (:func:`identify.diagnosis.candidates._at_magnitude`: the effect held there, the model's own
    parameters refitted to the runs fitted) makes the runs left out for their regime as
    the data's while it fits the runs fitted as well, where the final model parts from
    them (``check``, its :class:`identify.fitting.regime_check.RegimeCheck`).

    Each candidate with such a check gets ``held_regime``: the fitted runs' Δnll at the
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

    Returns those that fit and reproduce the runs first, then by joint Δχ²."""
    if check is None or not check.df:
        return []
    out = []
    for c in rnd:
        am = c.get("at_magnitude") or {}
        rc = am.get("regime") or {}
        dnll = am.get("delta_nll")
        if current_chi2 is not None and am.get("chi2") is not None:
            # against the current model's χ² at the values ``check`` read: the pairing the
            # joint needs (the round re-judges Δnll against its own re-solve of the current
            # model, which on the rejuvenation set ended at 2754.0, above its start's 2745.0)
            dnll = 0.5 * (float(am["chi2"]) - float(current_chi2))
        if (not c.get("effect") or c["effect"] in effects or not c.get("ok") or not rc.get("df")
                or dnll is None or not np.isfinite(dnll)):
            continue
        fits = bool(dnll <= am["needed_delta_nll"] and am.get("continuity_um", math.inf) <= GIVE_UP_FEAS)
        joint = 2.0 * dnll + float(rc["chi2"]) - float(check.chi2)
        c["held_regime"] = dict(
            parameter=am["parameter"], value=am["value"], delta_nll=float(dnll),
            needed_delta_nll=am["needed_delta_nll"], continuity_um=am.get("continuity_um"), fits=fits,
            reproduces=bool(rc.get("reproduces")), mismatched=len(rc.get("mismatched", [])), df=int(rc["df"]),
            chi2=float(rc["chi2"]), final_mismatched=len(check.mismatched), final_chi2=float(check.chi2),
            joint_delta_chi2=float(joint), p_value=float(stats.chi2.sf(-joint, 1)) if joint < 0 else 1.0)
        out.append(c)
    out.sort(key=lambda c: (not (c["held_regime"]["fits"] and c["held_regime"]["reproduces"]),
                            c["held_regime"]["joint_delta_chi2"]))
    return out


def _held_note(held: list, n_runs: int) -> str | None:
    """The sentence of :func:`_held_evidence`: which candidates, held at their realistic
    magnitude and refitted, fit the runs fitted as well and make the runs left out as the
    data's — not named from there (one of them alone is profiled next,
    :func:`_profile_held`); None where none does (the report's regime screen lists each
    reading)."""
    yes = [c for c in held if c["held_regime"]["fits"] and c["held_regime"]["reproduces"]]
    if not yes:
        return None
    head = ("held at its realistic magnitude with the model's own parameters refitted to the runs fitted, "
            f"each candidate read on the {n_runs} run(s) left out for their regime: ")

    def one(c):
        h = c["held_regime"]
        return (f"{c['effect']} at {h['parameter']} = {display(h['parameter'], h['value'])} fits them as well "
                f"(Δnll {h['delta_nll']:+.2f}, within {h['needed_delta_nll']:.1f}) and makes the runs left out as "
                f"the data's ({h['mismatched']} of {h['df']} parting, χ² {h['chi2']:.1f}, against the final model's "
                f"{h['final_mismatched']} of {h['df']}, χ² {h['final_chi2']:.1f}): joint Δχ² "
                f"{h['joint_delta_chi2']:.1f} (p = {h['p_value']:.2g})")

    names = ", ".join(c["effect"] for c in yes)
    tail = (f". Not named from here: {'its magnitude is' if len(yes) == 1 else 'their magnitudes are'} the "
            "library's, not estimated")
    tail += f"; nor can these runs tell {names} apart" if len(yes) > 1 else " (its profile follows)"
    return head + "; ".join(one(c) for c in yes) + tail


def _profile_held(held: list, current: dict, runs: list, fopts, opts: DiagnosisOptions, regime_runs: list, check,
                  executor, say, n_cand: int, confounded: list) -> dict | None:
    """Name a candidate on the runs left out for their regime, where only they show it.

    The one candidate whose check at its magnitude fits the runs fitted as well and makes
    the runs left out as the data's (:func:`_held_evidence`) is profiled on every run
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
    ``note`` (``best`` too: the model to go on with), or None where nothing was profiled."""
    from identify.diagnosis.regime_profile import regime_profile
    from identify.fitting.regime_check import RegimeRun

    yes = [c for c in held if c["held_regime"]["fits"] and c["held_regime"]["reproduces"]]
    if not yes:
        return None
    if len(yes) > 1:
        names = [c["effect"] for c in yes]
        for c in yes:
            c["confounded_with"] = [n for n in names if n != c["effect"]]
        why = ("each, held at its realistic magnitude and refitted, fits the runs fitted as well and makes the runs "
               "left out for their regime as the data's: these runs cannot tell them apart")
        confounded.append(dict(effects=names, confounded_with=[], closes=False, why=why))
        return dict(effect=None, named=False, note=f"regime profile: not run, {' | '.join(names)}: {why}")
    c = yes[0]
    eff = get_effect(c["effect"])
    if eff.law is not None or len(eff.parameters) != 1 or c.get("w_at_magnitude") is None:
        return None
    tasks, _ = _tasks([c["effect"]], current, runs, fopts, [], opts, 1, [], regime_runs=regime_runs)
    noise = {r.name: r.noise_m * 1e6 for r in regime_runs}
    am = c["at_magnitude"]
    try:
        prof = regime_profile(tasks[1], dict(value=am["value"], w=c["w_at_magnitude"], ev_M=c["ev_M_at_magnitude"]),
                              current["chi2"], check.to_json(), noise, executor=executor, say=say,
                              continuity_um=GIVE_UP_FEAS)
    except Exception as err:  # the diagnosis stands without it
        say(f"regime profile failed: {type(err).__name__}: {err}")
        return dict(effect=c["effect"], named=False, note=f"regime profile of {c['effect']} failed: "
                                                          f"{type(err).__name__}: {err}")
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
        c["confounded_with"] = params
        confounded.append(dict(effects=[c["effect"]], confounded_with=params, closes=False,
                               why=(f"its profile on every run is significant, and the current model with "
                                    f"{' or '.join(prof['own_moves'])} makes every run as the data's too")))
    if prof["named"]:
        c["named"] = True
        c["note"] = "; ".join(x for x in (c.get("note"), "named by its profile on every run (see the regime profile)")
                              if x)
    prof["note"] = _profile_note(prof, alpha_c)
    return prof


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


def _regime_check(law: str, values: dict, regime_runs: list, notes: list):
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


def _regime_notes(scored: list, base: dict) -> None:
    """Say of each candidate whether it puts the left-out runs the current model misfits
    for their regime (``base["regime"]``) in the data's regime."""
    if "mismatched" not in (base.get("regime") or {}):
        return
    bad = set(base["regime"]["mismatched"])
    for c in scored:
        rc = c.get("regime") or {}
        if not c.get("ok") or "mismatched" not in rc:
            continue
        fixed, broken = sorted(bad - set(rc["mismatched"])), sorted(set(rc["mismatched"]) - bad)
        c["regime_fixed"], c["regime_broken"] = fixed, broken
        said = []
        if fixed:
            said.append(f"under it {len(fixed)} of the {len(bad)} run(s) left out for their regime that the current "
                        "model stick-slips lose their resolvable slips, as in the data")
        elif bad:
            said.append(f"it leaves the {len(bad)} run(s) left out for their regime stick-slipping, unlike the data")
        if broken:  # evidence against it: the verdict's regime test will say so if it is named
            said.append(f"it stick-slips where the data and the current model do not: {', '.join(broken)}")
        if said:
            c["note"] = "; ".join(([c["note"]] if c.get("note") else []) + said)


def _regime_left_note(check, rounds, effects) -> str:
    """The note of a final model that still puts left-out runs in another regime, with the
    candidates of the last round that had any, not named, under which none of them does."""
    last = next((r for r in reversed(rounds) if any(c.get("effect") for c in r)), [])
    fixers = [c["effect"] for c in last if c.get("effect") and c.get("effect") not in effects and c.get("ok")
              and "mismatched" in (c.get("regime") or {})
              and not set(c["regime"]["mismatched"]) & set(check.mismatched)]
    txt = "regime: " + check.text()
    if fixers:
        one = len(fixers) == 1
        txt += (f"; under {', '.join(fixers)}, at {'its' if one else 'their'} refitted values, they do not stick-slip, "
                f"as in the data, but {'it' if one else 'none'} could {'not ' if one else ''}be named on the runs "
                f"fitted (see {'its' if one else 'their'} note{'' if one else 's'})")
    return txt


def _rank(c):
    return (0 if c.get("ok") else 1, c.get("delta_aic", math.inf) if c.get("ok") else 0)


def _tasks(ids, current, runs, fopts, folds, opts, threads, where_hint, regime_runs=(), at_magnitude=None):
    """Tasks for the current model itself and every applicable candidate; ``at_magnitude``:
    candidates that fit better held at their realistic magnitude last round (started
    there as well)."""
    tail = np.asarray(current["w"])[current["n_theta"]:]
    common = dict(runs=runs, values=current["values"], free=current["free"], w_tail=tail, ev_M=current["ev_M"],
                  options=fopts, folds=folds, max_iter=opts.max_iter, threads=threads,
                  null_chi2=current.get("chi2"), null_n_eff=current.get("n_eff"), screen_p=opts.alpha,
                  regime_runs=list(regime_runs))
    added = dict(current.get("bounds", {}))  # bounds of the effects already added
    tasks = [CandidateTask(effect=None, law=current["law"], bounds=added, **common)]
    skipped = []
    for eid in ids:
        eff = get_effect(eid)
        why = eff.applicable(tuple(current["free"]), current["law"])
        if why:
            skipped.append(dict(effect=eid, ok=False, reason=f"not applicable: {why}", status="not applicable",
                                parameters=list(eff.parameters), note=f"not applicable: {why}"))
            continue
        if eff.law is not None:
            from identify.model.laws import get_law

            old = get_law(current["law"]).parameters
            new = get_law(eff.law).parameters
            vals = dict(current["values"])
            tasks.append(CandidateTask(
                effect=eid, law=eff.law, extra=tuple(n for n in new if n not in old),
                replace_free=tuple(n for n in old if n not in new), bounds={**added, **dict(eff.bounds)},
                starts=[{}], staged=True, **{**common, "values": vals}))
            continue
        nulls = eff.null_values(current["values"])
        starts = _starts(eff, nulls, where_hint)
        m = (at_magnitude or {}).get(eid)
        if m and m.get("parameter") in eff.parameters:
            starts = starts + [{**nulls, m["parameter"]: float(m["value"])}]
        vals = {**current["values"], **nulls}
        tasks.append(CandidateTask(effect=eid, law=current["law"], extra=tuple(eff.parameters),
                                   bounds={**added, **dict(eff.bounds)}, starts=starts, nulls=nulls,
                                   magnitude=_magnitude(eff, nulls) if opts.magnitude_check else None,
                                   **{**common, "values": vals}))
    return tasks, skipped


def _expected_cost(task) -> int:
    """How long a refit is expected to take, in units of a one-start refit: the refits
    go to the workers longest first, so the last one to start is a short one (the
    makespan of a round is the longest worker's queue). A start is one solve; a law's
    refit starts afresh from the staged start, far from the current solution. Measured
    on the diagnosis speed benchmark (2026-11-24, two workers): submitted in library
    order, the topography (eight starts, 53 s) went eleventh of fourteen and the
    logistic law (32 s) third, the others took 1-21 s; the round took 125 s, and 122 and
    114 s in this order, the refits' sum 225 s over two workers (112 s each): the round
    is packed, its length their sum."""
    return len(task.starts or [{}]) + (2 if task.staged else 0)


def _magnitude(eff, nulls) -> tuple | None:
    """(parameter, realistic value) of a one-parameter candidate, for the check of
    :func:`identify.diagnosis.candidates._at_magnitude`; None where there is none to check (several
    parameters, as the topography's wavelength and phase, or a magnitude at the null)."""
    if len(eff.parameters) != 1 or not eff.magnitude or eff.magnitude[0] != eff.parameters[0]:
        return None
    name, value = eff.magnitude[0], float(eff.magnitude[1])
    return None if math.isclose(value, float(nulls[name]), rel_tol=1e-9, abs_tol=0.0) else (name, value)


def _starts(eff, nulls, where_hint) -> list:
    """Warm starts of a candidate's own parameters: the null, nudged off it where the
    Jacobian vanishes there, and for the topography the ripples the residuals show, each
    leading peak of their periodogram a basin of its own (``_basin``: the refit solves
    the best start of each basin and keeps the best end; :data:`identify.diagnosis.where.RIPPLE_PEAK_SHARE`)."""
    if eff.id == "topography":
        pos = next((m for m in where_hint if m.feature == "position"), None)
        extra = pos.extra if pos else {}
        peaks = extra.get("peaks") or [dict(wavelength_m=extra.get("wavelength_m", 5e-6),
                                            amplitude=extra.get("amplitude", 0.01), phase=extra.get("phase", 0.0))]
        # the residual ripple is a·sin(θ) + b·cos(θ) = amp·sin(θ + ph); the model's is the
        # capacity, whose sign the starts' own χ² decides
        return [dict(topo_amp=s * max(pk["amplitude"], 1e-3), topo_phase=pk["phase"],
                     topo_wavelength=pk["wavelength_m"], _basin=b)
                for b, pk in enumerate(peaks) for s in (1.0, -1.0)]
    if eff.id == "motion_blur":
        return [dict(exposure=1e-4), dict(exposure=2e-3)]  # no slope at T = 0
    if eff.id == "stick_threshold" and nulls.get("v_stick", 0.0) == 0.0:
        return [dict(v_stick=1e-6), dict(v_stick=1e-4)]
    return [dict(nulls)] + eff.nudges()


def _score(results, base, opts, n_cand, fold_names=None) -> list:
    """Likelihood ratio, ΔAIC, ΔBIC, confounding and gaps of every candidate against base."""
    out = []
    alpha_c = opts.alpha / max(n_cand, 1)
    r0 = base["r"]
    n_obs = base["n_obs"]
    for c in results:
        if c["effect"] is None:
            continue
        eff = get_effect(c["effect"])
        c["parameters"] = list(eff.parameters) if eff.nested else list(c.get("free", []))
        if not c.get("ok"):
            c["note"] = c.get("status", "failed")
            c["significant"] = False
            out.append(c)
            continue
        dk = c["n_eff"] - base["n_eff"]
        dnll = 0.5 * (base["chi2"] - c["chi2"])
        c["delta_nll"] = float(dnll)
        c["delta_aic"] = float(-2 * dnll + 2 * dk)
        c["delta_bic"] = float(-2 * dnll + dk * math.log(max(n_obs, 2)))
        if eff.nested and dk > 0:
            c["p_value"] = float(stats.chi2.sf(max(2 * dnll, 0.0), dk))
            sig = c["p_value"] < alpha_c and c["delta_bic"] < 0
        else:
            c["p_value"] = None
            sig = c["delta_aic"] < LAW_DELTA_AIC
        c["significant"] = bool(sig)
        c["gap_before_um"] = base["gap"]["gap_um"]
        c["gap_after_um"] = c["gap"]["gap_um"]
        c["heldout_gap_before_um"] = base["heldout"]["gap_um"]
        c["heldout_gap_after_um"] = c["heldout"]["gap_um"]
        # folds the linear leave-out step did not hold for (refitted), and why a held-out
        # gap is missing, if it is
        c["heldout_refitted_folds"] = c["heldout"].get("refitted_folds")
        c["heldout_unverified_folds"] = c["heldout"].get("unverified_folds")
        c["heldout_error"] = c["heldout"].get("error")
        c["heldout_delta_nll"] = _heldout_dnll(base["heldout"], c["heldout"])
        c["heldout_by_fold"], c["heldout_set_aside"] = _heldout_by_fold(base, c, fold_names)
        # the same gaps in noise units (1: at the noise)
        for key, before, after in (("gap_sigma", base["gap"], c["gap"]),
                                   ("heldout_gap_sigma", base["heldout"], c["heldout"])):
            c[key + "_before"], c[key + "_after"] = before.get("gap_sigma"), after.get("gap_sigma")
        conf = c.get("confounding") or {}
        r2 = max((v.get("r2", 0.0) for v in conf.values()), default=0.0)
        if any(v.get("confounded") for v in conf.values()):
            r2 = max(r2, 1.0)
        c["r2_with_model"] = float(r2) if np.isfinite(r2) else None
        partners = sorted({p["parameter"] for v in conf.values() for p in v.get("partners", [])})
        # confounded: the model's parameters can mimic it (R² > 0.99) and, with them free,
        # it is not determined away from its null (a strongly correlated but well-measured
        # parameter, like A against μmin, is not confounded)
        z = _wald(c, eff)
        c["wald_z"] = z
        if np.isfinite(r2) and r2 > CONFOUNDED_R2 and not z >= WALD_Z:
            # no partner listed: no information on it at all, so every model parameter is one
            c["confounded_with"] = partners or [n for n in base.get("free", []) if n not in eff.parameters]
            c["mimicked"] = True  # by the model's own parameters (not a tie with another candidate)
        else:
            c["confounded_with"] = []
            c["mimicked"] = False
        if dnll < -1e-6 * max(base["chi2"], 1.0):
            c["significant"] = False
            c["heldout_gap_after_um"] = c["gap_after_um"] = float("nan")
            c["worse"] = True
        c["dr"] = c["r"] - r0
        c["estimate_text"] = ", ".join(
            f"{n} = {_fmt(c['estimates'][n])}" for n in (eff.parameters if eff.nested else c.get("free", []))
            if n in c["estimates"])
        c["named"] = False
        c["closed_fraction"] = _closed_fraction(c)
        # the held-out gap at the encoding's floor (as the verdict's tolerance reads it)
        noise = base["gap"].get("noise_um", 0.0)
        c["heldout_gap_ratio_before"] = float(c["heldout_gap_before_um"] / noise) if noise > 0 else float("nan")
        c["at_floor"] = bool(c["heldout_gap_ratio_before"] <= opts.gap_tolerance)
        c["explained_share"] = _explained_share(c, base)
        c["closes"] = _closes(c)
        c["note"] = c["estimate_text"]
        stopped = (f"refit stopped after {c.get('iterations')} iterations in all: even {GIVE_UP_MARGIN:g}× the "
                   "gain its solver still promised could not make it significant; its Δnll is a lower "
                   "bound, the p-value an upper bound") if c.get("status") == GAVE_UP else ""
        if stopped:
            c["note"] += f" ({stopped})"
        if c["heldout_error"]:
            c["note"] += f" (no held-out gap: {c['heldout_error']})"
        elif c.get("heldout_unverified_folds"):
            c["note"] += (f" (held-out gap: {c['heldout_unverified_folds']} fold(s) from the linear "
                          "leave-out step, which the model did not confirm there; their refit failed)")
        if c.get("status") == NOT_DIFFERENTIABLE:
            c["note"] = ("the refit could not start: where it began, the last bit of a parameter moves the "
                         "residuals by more than their noise (the model is not differentiable there); no "
                         "evidence; the values at its start: " + c["estimate_text"])
        elif c.get("worse"):
            c["note"] = ("the refit ended worse than the current model (a local solution): no evidence; "
                         if not stopped else f"worse than the current model when its {stopped}: no evidence; "
                         ) + c["estimate_text"]
        m = c.get("at_magnitude")
        if m and not c["significant"]:
            if (m.get("absorbed") or m.get("better")) and np.isfinite(m.get("chi2", float("nan"))):
                # judged again against the best fit this round found: the current model
                # re-solved here, or the refit itself (the worker knew only last round's χ²)
                ref = min(base["chi2"], c["chi2"])
                m["delta_nll"] = 0.5 * (m["chi2"] - ref)
                if m["delta_nll"] > m["needed_delta_nll"]:
                    m.update(absorbed=False, better=False, partners=[], lower_bound=False)
                elif m["delta_nll"] < -m["needed_delta_nll"]:
                    m.update(absorbed=False, better=True, partners=[])
                elif m.get("better"):
                    # better only against the worker's reference: within the quantile of
                    # this round's best, so the check's own verdict (moves only: the
                    # standard errors there were not computed for a better fit)
                    for x in m.get("moved", []):
                        x["partner"] = bool(abs(x["z"]) >= MAGNITUDE_MOVED_Z)
                    m.update(absorbed=True, better=False,
                             partners=[x["parameter"] for x in m.get("moved", []) if x["partner"]])
            c["note"] += f" ({_magnitude_text(m)})"
            if m.get("absorbed") and m.get("partners") and not c["confounded_with"]:
                # not seen near its null, yet absorbed at its realistic size: the model's
                # own parameters stand in for it there (candidates._at_magnitude)
                c["confounded_with"] = list(m["partners"])
        out.append(c)
    return out


def _magnitude_text(m: dict) -> str:
    """What the check at the realistic magnitude (:func:`identify.diagnosis.candidates._at_magnitude`) found."""
    at = f"{m['parameter']} = {display(m['parameter'], m['value'])}"
    if m.get("absorbed") is None:
        return f"not settled at its realistic magnitude {at}: {m.get('error') or m.get('status')}"
    if m.get("better"):
        return (f"fits better at its realistic magnitude {at} than its refit (Δnll {m['delta_nll']:.1f}, beyond "
                f"−{m['needed_delta_nll']:.1f}): the refit ended in a local solution near its null, so there is "
                "evidence for it but no estimate: not named, and not shown absent either")
    if not m["absorbed"]:
        rel = "≥" if m.get("lower_bound") else "="
        return f"excluded at its realistic magnitude {at}: Δnll {rel} {m['delta_nll']:.1f} there"
    head = (f"not excluded at its realistic magnitude {at}, which fits as well (Δnll {m['delta_nll']:.1f}, "
            f"within {m['needed_delta_nll']:.1f})")
    moves = [x for x in m.get("moved", []) if x["parameter"] in m.get("partners", [])]
    if not moves:
        held = ("as the current model stands" if m.get("iterations", 0) <= 1
                else "with no parameter moving by its standard error")
        if not m.get("stderr_checked"):
            return head + f" {held} (the standard errors there could not be computed)"
        return head + f" {held} and none losing half its information: the data do not see it there"
    return (head + " with " + ", ".join(_moved_text(x) for x in moves)
            + ": were it there, these would be off or less certain than stated")


def _moved_text(x: dict) -> str:
    n = x["parameter"]
    out = f"{n} {display(n, x['value'])} -> {display(n, x['at_magnitude'])} ({x['z']:+.1f} σ"
    if x.get("undetermined"):
        out += f"; its standard error {display(n, x['stderr'])} -> undetermined"
    elif (x.get("wider") or 0.0) >= 1.2:
        out += f"; its standard error {display(n, x['stderr'])} -> {display(n, x['stderr_at_magnitude'])}"
    return out + ")"


def _heldout_dnll(before: dict, after: dict) -> float:
    """½ the fall of the held-out χ² (NaN unless both cover the same rows): the
    likelihood gain on runs the fit did not see, every row in its own noise units."""
    a, b = before.get("chi2"), after.get("chi2")
    if a is None or b is None or before.get("n_rows") != after.get("n_rows"):
        return float("nan")
    if before.get("unverified_folds") or after.get("unverified_folds"):
        return float("nan")  # a linear prediction the model contradicted is no comparison
    return float(0.5 * (a - b))


def _heldout_by_fold(base: dict, c: dict, fold_names=None):
    """The likelihood gain per fold, fitted and held out, and the run the naming rule may
    set aside: ([{runs, fitted_delta_nll, heldout_delta_nll}], set_aside or None).

    With leave-one-run-out and at least MIN_FOLDS_SET_ASIDE runs, the set-aside run is the
    one that argues most against the candidate (held-out gain less HELDOUT_SHARE of its
    fitted gain lowest), given with the sums over the other runs and the held-out µm gap
    before and after without it. :func:`_closes` accepts the likelihood test on all runs
    or on all but that one, so that one high-leverage run — which the candidate fits
    better, but cannot predict once it is left out — cannot veto an effect every other
    run confirms. A run the candidate fits worse contradicts it and is never set aside;
    both sums leave the run out, so a gain that lies in that one run (a run overfitted)
    gains nothing from it. Measured (drift at 5e-8 m/s, the withheld-effect benchmark's
    8 runs, at 7c7f030): the drift refit is right (4.94e-8 ± 0.03e-8 m/s) and keeps its
    gain held out on 7 runs (2.96e5 held out against 1.45e5 fitted); on the 2.13 N/m,
    20 µN, 300 Hz run its fitted χ² falls from 1.25e5 to 440 but its held-out χ² is 9.1e5,
    so the sum over all runs kept only 2.4e4 of 2.1e5."""
    ho_b, ho_c = base["heldout"], c["heldout"]
    keys = ("chi2_by_fold", "fitted_chi2_by_fold", "rows_by_fold")
    if (any(k not in ho_b or k not in ho_c for k in keys) or ho_b["rows_by_fold"] != ho_c["rows_by_fold"]
            or not np.isfinite(c.get("heldout_delta_nll", float("nan")))):
        return [], None
    h = 0.5 * (np.asarray(ho_b["chi2_by_fold"]) - np.asarray(ho_c["chi2_by_fold"]))
    g = 0.5 * (np.asarray(ho_b["fitted_chi2_by_fold"]) - np.asarray(ho_c["fitted_chi2_by_fold"]))
    names = fold_names
    if names is None or len(names) != len(h):
        names = [[f"fold {k}"] for k in range(len(h))]
    by_fold = [dict(runs=list(n), fitted_delta_nll=float(gi), heldout_delta_nll=float(hi))
               for n, gi, hi in zip(names, g, h)]
    if len(h) < MIN_FOLDS_SET_ASIDE or any(len(n) != 1 for n in names):
        return by_fold, None
    j = int(np.argmin(h - HELDOUT_SHARE * g))
    if g[j] < 0:  # a run fitted worse with the candidate argues against it in the fit too
        return by_fold, None
    keep = np.arange(len(h)) != j
    without = lambda ho, key: (ho.get(key) or [float("nan")] * len(h))[j]  # noqa: E731
    a = dict(runs=list(names[j]), fitted_delta_nll=float(g[j]), heldout_delta_nll=float(h[j]),
             fitted_delta_nll_kept=float(g[keep].sum()), heldout_delta_nll_kept=float(h[keep].sum()),
             heldout_gap_before_um=float(without(ho_b, "gap_um_without_fold")),
             heldout_gap_after_um=float(without(ho_c, "gap_um_without_fold")),
             noise_um=float(without(ho_b, "noise_um_without_fold")))
    a["closed_fraction"] = _closed_share(a["heldout_gap_before_um"], a["heldout_gap_after_um"], a["noise_um"])
    a["explained_share"] = _explained_share(dict(delta_nll=a["fitted_delta_nll_kept"]), base)
    return by_fold, a


def _wald(c, eff) -> float:
    """Largest |value − null|/stderr of the candidate's own parameters (0 if undetermined)."""
    if not eff.nested:
        return float("nan")
    z = 0.0
    nulls = c.get("nulls") or {}
    for n in eff.defining:
        e = c["estimates"].get(n)
        if not e or not e.get("stderr") or n not in nulls:
            continue
        z = max(z, abs(e["value"] - float(nulls[n])) / e["stderr"])
    return float(z)


def _fmt(e: dict) -> str:
    v, se = e["value"], e.get("stderr")
    if e.get("at_bound"):  # its value is the bound's, not the data's: no ± to give
        return f"{v:.4g} (at its {e['at_bound']} bound: the data push past what the model allows)"
    return f"{v:.4g} ± {se:.2g}" if se is not None else f"{v:.4g}"


def _closed_fraction(c) -> float:
    """Share of the held-out gap above the noise floor that the candidate closes."""
    return _closed_share(c["heldout_gap_before_um"], c["heldout_gap_after_um"], c.get("gap", {}).get("noise_um", 0.0))


def _closed_share(before_um: float, after_um: float, noise_um: float) -> float:
    if not (np.isfinite(before_um) and np.isfinite(after_um) and np.isfinite(noise_um)):
        return 0.0
    ex = lambda g: math.sqrt(max(g * g - noise_um * noise_um, 0.0))  # noqa: E731
    before, after = ex(before_um), ex(after_um)
    return (before - after) / before if before > 0 else 0.0


def _evidence(c) -> str:
    p = c.get("p_value")
    return f"p = {p:.2g}" if p is not None else f"ΔAIC = {c.get('delta_aic', float('nan')):.1f}"


def _explained_share(c, base) -> float:
    """Share of the current model's excess χ² (over its degrees of freedom) the candidate
    removes on the fitted runs. The excess is taken as at least EXCESS_FLOOR standard
    deviations of a χ² with those degrees of freedom: near an adequate model the excess is
    mostly chance, and a small significant gain would be a large share of it."""
    dof = max(base["n_obs"] - base["n_eff"], 1)
    excess = max(base["chi2"] - dof, EXCESS_FLOOR * math.sqrt(2 * dof))
    return float(2 * c["delta_nll"] / excess)


def _closes(c) -> bool:
    """Whether a candidate closes a real part of the gap, not only a formal one: at least
    MIN_CLOSED of the held-out µm gap above the noise; or, where that gap sits at the
    encoding's own floor (within ``gap_tolerance`` of the noise: ``c["at_floor"]``), at
    least MIN_CLOSED of the current model's excess χ² on the fitted runs with at least
    HELDOUT_SHARE of that likelihood gain kept on the held-out runs. Either on all runs,
    or on all but the one run that argues most against the candidate
    (:func:`_heldout_by_fold`). Measured (velocity strengthening at A = 0.0045 against a
    baseline fixing A = 0, the withheld-effect benchmark's 8 runs): p = 6e-54, Δnll 120
    fitted and 142 held out, yet the held-out µm gap went 20.5 → 21.2 nm (noise 15.0 nm):
    the µm gap pools the features by their size in µm and sat at the 1.2–1.4× the
    encoding leaves on model-made data, so the first test alone named nothing beside a
    10 σ post-slip misfit. Away from that floor the µm gap is the measure: on the
    out-of-library set (each run's load ±15 % off, at d6efe11) a load offset removed 37 %
    of the excess χ² and kept all of it held out, and was named, while the held-out gap
    (4.8× the noise) went 92.2 → 89.9 nm."""
    return _route(c) is not None


def _route(c):
    """How the candidate closes the gap (:func:`_closes`): "gap", "likelihood", "gap
    without one run", "likelihood without one run", or None."""
    if c.get("closed_fraction", 0.0) >= MIN_CLOSED:
        return "gap"
    own = c.get("own_sequence") or {}
    if own.get("changed") and not own.get("error") and own.get("closed_fraction", 0.0) >= MIN_CLOSED:
        return "gap on its own mode sequence"
    at_floor = c.get("at_floor", False)
    if at_floor and _likelihood_closes(c.get("explained_share", 0.0), c.get("heldout_delta_nll", float("nan")),
                                       c["delta_nll"]):
        return "likelihood"
    a = _set_aside_usable(c)
    if a and a.get("closed_fraction", 0.0) >= MIN_CLOSED:
        return "gap without one run"
    if a and at_floor and _likelihood_closes(a.get("explained_share", 0.0), a["heldout_delta_nll_kept"],
                                             a["fitted_delta_nll_kept"]):
        return "likelihood without one run"
    return None


def _likelihood_closes(share: float, heldout_dnll: float, fitted_dnll: float) -> bool:
    return bool(share >= MIN_CLOSED and np.isfinite(heldout_dnll) and heldout_dnll >= HELDOUT_SHARE * fitted_dnll)


def _set_aside_usable(c):
    """The run set aside (:func:`_heldout_by_fold`), if the rule may leave it out: the
    candidate gains on the other runs and its held-out Δnll over all runs is positive —
    the set-aside relaxes how much of the gain must be kept held out, never whether the
    held-out runs are predicted better in all (measured on the out-of-library set at
    d54fbfe: the spring nonlinearity kept 4611 of 7365 without the 10 Hz run, −4997 over
    all runs, and was named)."""
    a = c.get("heldout_set_aside")
    if a and a["fitted_delta_nll_kept"] > 0 and c.get("heldout_delta_nll", float("nan")) > 0:
        return a
    return None


def _select(scored, base, retry=None):
    """The candidate to add, and a confounded group when the best cannot be told apart.
    ``retry`` (:func:`_own_sequence`) measures a candidate that fits much better but does
    not close the gap on the current mode sequence on the sequence it decides itself
    (:func:`_worth_own_sequence`), before a weaker one is tried."""
    ok = [c for c in scored if c.get("ok") and c.get("significant")]
    for c in ok:
        if c["confounded_with"] and not c.get("confounded_beside"):
            c["note"] = (f"confounded with {', '.join(c['confounded_with'])} (R² = {c['r2_with_model']:.3f}): "
                         "the model's own parameters mimic it; " + c["estimate_text"])
    names = [c for c in ok if not c["confounded_with"]]
    if not names:
        return None, None
    names.sort(key=lambda c: c["delta_aic"])
    for k, best in enumerate(names):
        chosen, group = _try(best, names[k + 1:])
        if chosen is None and group is None and retry is not None and _worth_own_sequence(best):
            retry(best)  # records best["own_sequence"] and judges it again
            best["closes"] = _closes(best)
            chosen, group = _try(best, names[k + 1:])
        if chosen is not None or group is not None:
            return chosen, group
        if best.get("closes") and not _converged(best):
            # a better candidate that would close the gap could not be judged: naming a
            # weaker one risks the wrong name. Measured (spring nonlinearity at β = 3e8,
            # 3a37f1b): its refit closed 93 % of the held-out gap but ended
            # Line_Search_Failed, and a load offset closing 38 % was named in its place
            for c in names[k + 1:]:
                if c.get("closes"):
                    c["note"] = (f"not tried for a name: {best['effect']} fits better and would close the gap, "
                                 "but its refit did not converge; " + c["estimate_text"])
            return None, None
    return None, None


def _choose(scored, base, check, retry=None):
    """:func:`_select`, then ``check`` (:func:`_beside`) on its choice: a choice the check
    demotes (it returns the confounded group) gives way to the next :func:`_select` picks.
    The chosen candidate (or None) and every confounded group found on the way."""
    groups = []
    chosen, group = _select(scored, base, retry)
    while True:
        if group:
            groups.append(group)
        if chosen is None:
            return None, groups
        group = check(chosen)
        if group is None:
            return chosen, groups
        groups.append(group)
        chosen, group = _select(scored, base, retry)


def _gap_ratio(c) -> float:
    """A measured model's held-out gap over its noise floor (NaN when either is missing)."""
    noise = (c.get("gap") or {}).get("noise_um", float("nan"))
    return (c.get("heldout") or {}).get("gap_um", float("nan")) / noise if noise and noise > 0 else float("nan")


def _at_noise(c, opts) -> bool:
    """Whether a measured model's held-out gap is within the verdict's tolerance."""
    ratio = _gap_ratio(c)
    return bool(np.isfinite(ratio) and ratio <= opts.gap_tolerance)


def _rivals(chosen, scored) -> list:
    """Significant candidates that fit better than ``chosen`` but cannot be named because
    the model's own parameters mimic them (nested ones: the test below needs a p-value)."""
    out = [c for c in scored if c is not chosen and c.get("ok") and c.get("significant")
           and c.get("mimicked") and c.get("p_value") is not None
           and c["delta_aic"] < chosen["delta_aic"]]
    return sorted(out, key=lambda c: c["delta_aic"])[:MAX_RIVALS]


def _beside(chosen, scored, base, current, runs, fopts, opts, threads, executor, where_hint, n_cand, say):
    """``chosen`` refitted beside each better-fitting candidate the model mimics
    (:func:`_rivals`): None when it stays significant beside every one (it explains
    something of its own), else the confounded group it forms with the first it does
    not (and ``chosen`` is no longer nameable).

    Why: such a rival is significant, yet the baseline's parameters can absorb it, so
    forward selection never adds it and a weaker candidate that picks up part of the
    same residuals would be named in its place. Measured on the benchmark's data with
    velocity strengthening at 0.1× (A = 0.0015, baseline A = 0; at 8c17533): A was
    significant (ΔAIC −32.7) but confounded with μmax, μmin, τ, and a load offset of
    −40 ± 12 nN (ΔAIC −27.1; the data have none) was named; their residual changes were
    not parallel (cosine 0.57), so the tie rule of :func:`_try` did not apply."""
    eff = get_effect(chosen["effect"])
    if not eff.nested:
        return None  # another aging law is judged by ΔAIC against the current law, not nested
    own = {n: chosen["values"][n] for n in eff.parameters if n in chosen.get("values", {})}
    for rival in _rivals(chosen, scored):
        reff = get_effect(rival["effect"])
        nulls = eff.null_values(rival["values"])
        free = tuple(rival["free"])
        # one basin: its own estimates, the null or its nudges, and the leading ripple's
        # starts for the topography, whichever fits best at the start
        starts = [dict(own)] + [s for s in _starts(eff, nulls, where_hint) if not s.get("_basin")]
        task = CandidateTask(
            effect=chosen["effect"], runs=runs, law=rival["law"], values={**rival["values"], **nulls}, free=free,
            extra=tuple(n for n in eff.parameters if n not in free),
            bounds={**current.get("bounds", {}), **dict(reff.bounds), **dict(eff.bounds)},
            starts=starts, nulls=nulls, w_tail=np.asarray(rival["w"])[len(free):],
            ev_M=rival["ev_M"], options=fopts, folds=[], max_iter=opts.max_iter, threads=threads,
            null_chi2=rival["chi2"], null_n_eff=rival["n_eff"], screen_p=opts.alpha)
        say(f"  {chosen['effect']} refitted beside {rival['effect']} (which fits better but the model mimics)")
        try:
            res = executor.submit(run_candidate, task).result()
        except Exception as err:  # a lost worker: the check failed
            res = dict(ok=False, status=f"failed: {err}")
        check = dict(effect=rival["effect"], status=res.get("status"))
        if res.get("ok"):
            dnll = 0.5 * (rival["chi2"] - res["chi2"])
            dk = res["n_eff"] - rival["n_eff"]
            p = float(stats.chi2.sf(max(2 * dnll, 0.0), dk)) if dk > 0 else 1.0
            dbic = -2 * dnll + dk * math.log(max(base["n_obs"], 2))
            check.update(delta_nll=float(dnll), p_value=p,
                         significant=bool(p < opts.alpha / max(n_cand, 1) and dbic < 0))
        chosen.setdefault("beside", []).append(check)
        if "p_value" not in check:
            # no evidence either way: the candidate keeps the name its own tests give it
            chosen["note"] = (chosen.get("note", "")
                              + f" (not checked beside {rival['effect']}: the refit failed, {check['status']})")
            continue
        if check["significant"]:
            continue
        why = f"p = {check['p_value']:.2g}, Δnll {check['delta_nll']:.1f}, with both freed"
        chosen["confounded_with"] = [rival["effect"]]
        chosen["confounded_beside"] = rival["effect"]  # (not the model's parameters: _select's note)
        chosen["note"] = (f"significant alone, but not beside {rival['effect']}, which fits better and the model's "
                          f"own parameters mimic: {why}; " + chosen["estimate_text"])
        return dict(effects=[rival["effect"], chosen["effect"]], closes=bool(chosen.get("closes")),
                    why=(f"{chosen['effect']} explains nothing beyond {rival['effect']} ({why}), which the "
                         f"model's own parameters mimic ({', '.join(rival['confounded_with'])})"))
    return None


def _converged(c) -> bool:
    return str(c.get("status", "")).startswith(("Solve_Succeeded", STALLED))


def _undetermined(c) -> bool:
    """A nested candidate whose own 95 % interval holds its null for every parameter that
    defines it (or that has no interval at all): the likelihood ratio and the curvature at
    the estimate disagree, and a name would be a claim its interval does not make. The
    intervals are the fit's own (on the log scale for log-scaled parameters, such as dc).
    Measured (a load offset and a step size withheld together, at 5373b08): after both
    were named, rejuvenation gained Δnll 19.9 (p = 2.7e-10) with dc = 7.1 ± 8.0 nm, 95 %
    interval 0.8–64 nm around its null of 20 nm, and 'closed' 82 % of the held-out gap,
    1303 of its 1319 held-out likelihood units in one run whose fitted gain was −0.2: the
    current model's prediction of that run failed, and any refit mended it. Every effect
    named in the benchmarks lay at z ≥ 5.7 (:func:`_wald`)."""
    return _interval_text(c) is not None


def _interval_text(c):
    """Why ``c`` is undetermined (:func:`_undetermined`), or None when it is not."""
    if not c.get("effect"):
        return None
    eff = get_effect(c["effect"])
    if not eff.nested:
        return None  # another law: judged by ΔAIC, no null to exclude
    nulls, est = c.get("nulls") or {}, c.get("estimates") or {}
    held, missing = [], []
    for n in eff.defining:
        if n not in nulls:
            continue
        e = est.get(n) or {}
        ci = e.get("ci95")
        if ci is None and e.get("stderr") is not None and e.get("value") is not None:
            ci = [e["value"] - 1.96 * e["stderr"], e["value"] + 1.96 * e["stderr"]]  # (no interval given)
        if ci is None or not all(np.isfinite(ci)):
            missing.append(n)
        elif ci[0] <= float(nulls[n]) <= ci[1]:
            held.append(f"{n}: {ci[0]:.3g} to {ci[1]:.3g} holds the null {float(nulls[n]):.3g}")
        else:
            return None  # determined away from its null in at least one parameter
    if not held and not missing:
        return None
    return "; ".join(held + [f"{n} has no standard error" for n in missing])


def _worth_own_sequence(c) -> bool:
    """Whether a candidate that does not close the held-out gap on the current model's
    mode sequence is measured on the sequence it decides itself (:func:`_own_sequence`):
    a converged refit, away from the encoding's floor, that removes at least MIN_CLOSED
    of the current model's excess χ² on the fitted runs — it explains much of the misfit,
    yet predicts the held-out runs little better, the mark of a sequence bent to the
    current model."""
    return bool(_converged(c) and not c.get("closes") and not c.get("at_floor", False)
                and c.get("explained_share", 0.0) >= MIN_CLOSED and "own_sequence" not in c
                and not _undetermined(c))


def _own_text(own: dict) -> str:
    if own.get("error"):
        return f"deciding its own mode sequence failed: {own['error']}"
    if not own.get("changed"):
        return "its own mode sequence is the current model's"
    moved = (("from the detected one, " if own.get("from_detected") else "")
             + f"{own['triggers_moved']} trigger(s) moved, {own['slips_inserted']} slip(s) inserted, "
             f"{own['slips_removed']} removed")
    before = own["heldout_gap_before_um"]
    ctrl = own.get("current_resequenced")
    against = (f", against the current model's {before * 1e3:.1f} nm on the sequence it decides again "
               f"({ctrl['triggers_moved']} trigger(s) moved, {ctrl['slips_inserted']} inserted, "
               f"{ctrl['slips_removed']} removed)" if ctrl and ctrl.get("changed") else
               f", against {before * 1e3:.1f} nm" if np.isfinite(before) else "")
    return (f"on the mode sequence it decides ({moved}) it closes {100 * max(own['closed_fraction'], 0):.0f} %: "
            f"held-out gap {own['heldout_gap_after_um'] * 1e3:.1f} nm{against}")


def _own_sequence(c, base, current, runs, fopts, prob0, folds, opts, threads, executor, say):
    """The candidate ``c`` measured on the mode sequence it decides itself: its held-out
    gap there against the current model's on the current model's own sequence, in
    ``c["own_sequence"]`` (JSON-able; the new model and runs in ``c["_own"]`` for naming).

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
    c["own_sequence"] = rec

    def measure(model, runs_):
        task = _tasks([], model, runs_, fopts, folds, opts, threads, where_hint=[])[0][0]
        rec["refits"] += 1
        res = executor.submit(run_candidate, task).result()
        if not res.get("ok") or not np.isfinite((res.get("heldout") or {}).get("gap_um", float("nan"))):
            raise RuntimeError(f"its held-out gap could not be measured ({res.get('status')}"
                               f"{', ' + res['heldout']['error'] if (res.get('heldout') or {}).get('error') else ''})")
        return res

    try:
        eff = get_effect(c["effect"])
        cand = dict(values=dict(c["values"]), free=tuple(c["free"]), law=c["law"], w=c["w"], ev_M=c["ev_M"],
                    n_theta=len(c["free"]), chi2=c["chi2"], n_eff=c["n_eff"],
                    bounds={**current.get("bounds", {}), **dict(eff.bounds)})
        say(f"  {c['effect']} explains {100 * c['explained_share']:.0f} % of the excess χ² but closes "
            f"{100 * max(c['closed_fraction'], 0):.0f} % of the held-out gap: measured on its own mode sequence")
        new, runs2, changed = _resequence(cand, runs, fopts, prob0, say)
        if not changed:
            return
        m = measure(new, runs2)
        noise = base["gap"]["noise_um"]
        before, after = float(base["heldout"]["gap_um"]), float(m["heldout"]["gap_um"])
        closed = _closed_share(before, after, noise)
        ctrl = None
        if closed >= MIN_CLOSED:
            say("  and the current model on the sequence it decides again, for a fair comparison")
            model_c, runs_c, changed_c = _resequence(current, runs, fopts, prob0, say)
            ctrl = dict(changed=bool(changed_c), **model_c.get("sequence_changes", {}))
            if changed_c:
                before = float(measure(model_c, runs_c)["heldout"]["gap_um"])
                closed = _closed_share(before, after, noise)
        # recorded only now: a comparison the control could not complete names nothing
        rec.update(changed=True, **new["sequence_changes"], heldout_gap_before_um=before, heldout_gap_after_um=after,
                   gap_after_um=float(m["gap"]["gap_um"]), chi2=float(m["chi2"]), closed_fraction=float(closed))
        if ctrl is not None:
            rec["current_resequenced"] = ctrl
        c["_own"] = dict(current=new, runs=runs2, measured=m)
        say(f"  {c['effect']}: {_own_text(rec)}")
    except Exception as err:  # the candidate is judged on the current sequence, as before
        rec.update(changed=False, error=f"{type(err).__name__}: {err}")
        c.pop("_own", None)
        say(f"  {c['effect']}: {_own_text(rec)}")


def _try(best, others):
    """``best`` if it can be named; a confounded group if another explains the same; else None."""
    why = _interval_text(best)
    if why is not None:  # (before the ties: an undetermined candidate confounds nothing)
        best["undetermined"] = True
        best["note"] = (f"significant by the likelihood ratio, but its own 95 % interval does not exclude its null "
                        f"({why}): not determined, so not named; " + best["estimate_text"])
        return None, None
    ties = []
    for c in others:
        if _undetermined(c):
            continue
        a, b = best["dr"], c["dr"]
        cos = float(a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-300))
        if abs(c["delta_aic"] - best["delta_aic"]) < TIE_AIC and cos > SAME_RESIDUALS:
            ties.append((c, cos))
    if ties:
        grp = [best["effect"]] + [c["effect"] for c, _ in ties]
        for c in [best] + [t for t, _ in ties]:
            c["confounded_with"] = [e for e in grp if e != c["effect"]]
            c["note"] = "confounded with " + ", ".join(c["confounded_with"]) + "; " + c["estimate_text"]
        why = ("they change the residuals alike (cosine " + ", ".join(f"{cos:.2f}" for _, cos in ties)
               + ") and fit equally well (|ΔΔAIC| < 10)")
        closes = any(c.get("closes") for c in [best] + [t for t, _ in ties])
        return None, dict(effects=grp, why=why, closes=bool(closes))
    if not _converged(best):
        best["note"] = f"significant but its refit did not converge ({best['status']}); " + best["estimate_text"]
        return None, None
    a = _set_aside_usable(best)
    if not best.get("closes"):
        share, ho = best.get("explained_share", 0.0), best.get("heldout_delta_nll", float("nan"))
        um = f"closes {100 * max(best.get('closed_fraction', 0.0), 0):.0f} % of the held-out gap above the noise"
        if a:
            um += f" ({100 * max(a['closed_fraction'], 0):.0f} % without the run {', '.join(a['runs'])})"
        own = best.get("own_sequence")
        if own:
            um += f" ({_own_text(own)})"
        if not best.get("at_floor", False):
            why = (f"the likelihood test does not apply: the held-out gap is {best['heldout_gap_ratio_before']:.2g}× "
                   f"the noise, above the encoding's own floor (needs {100 * MIN_CLOSED:.0f} % of the gap)")
        else:
            why = (f"removes {100 * max(share, 0):.0f} % of the excess χ²" if share < MIN_CLOSED else
                   f"keeps {ho:.1f} of its Δnll {best['delta_nll']:.1f} on held-out runs" if np.isfinite(ho) else
                   "has no held-out Δnll")
            if a and share >= MIN_CLOSED:
                why += (f"; without the run {', '.join(a['runs'])} it removes "
                        f"{100 * max(a['explained_share'], 0):.0f} % and keeps {a['heldout_delta_nll_kept']:.1f} of "
                        f"{a['fitted_delta_nll_kept']:.1f}")
            why += (f" (needs {100 * MIN_CLOSED:.0f} % of either, the second with {100 * HELDOUT_SHARE:.0f} % of its "
                    "gain held out, on all runs or all but one)")
        best["note"] = f"significant, but {um}; {why}; " + best["estimate_text"]
        return None, None
    best["note"] = "added; " + best["estimate_text"]
    if _route(best) == "gap on its own mode sequence":
        best["note"] += (f" (closes {100 * max(best['closed_fraction'], 0):.0f} % of the held-out gap on the "
                         f"current model's mode sequence; {_own_text(best['own_sequence'])})")
    if _route(best) in ("gap without one run", "likelihood without one run"):
        # named on all runs but one: say which, and what the held-out figures are without it
        gaps = (f", held-out gap {a['heldout_gap_before_um'] * 1e3:.1f} -> {a['heldout_gap_after_um'] * 1e3:.1f} nm"
                if np.isfinite(a["heldout_gap_before_um"]) and np.isfinite(a["heldout_gap_after_um"]) else "")
        best["note"] += (f" (held out on every run but {', '.join(a['runs'])}, which it fits better but cannot "
                         f"predict once it is left out: held-out Δnll {a['heldout_delta_nll']:.1f} against "
                         f"{a['fitted_delta_nll']:.1f} fitted; on the others {a['heldout_delta_nll_kept']:.1f} held "
                         f"out against {a['fitted_delta_nll_kept']:.1f} fitted{gaps})")
    return best, None


def _resequence(current, runs, fopts, prob0, say):
    """The current model's mode sequence decided again (:func:`identify.fitting.driver.decide_sequence`),
    from its solution on the sequence it has, and from the sequence as detected when the
    fits have changed that: (current, runs, changed). The one with the lower excess χ² is
    taken, if it lowers the excess χ² (:func:`identify.fitting.driver.worse_sequence` with no
    slack); else unchanged. The runs then carry the new triggers and the next round
    measures the model with them (the named candidate's scores stand: they were its
    evidence against the model without it, on the same sequence).

    Why from the detected sequence too: the baseline's fit bends the sequence to absorb
    the effect it lacks, and a named model decided again from there can stay in that
    basin. Measured (logarithmic-law data, the law named at de5ae31): from the baseline's
    sequence (54 triggers moved, 7 slips inserted) the law's decided sequence ended at
    excess χ² 10 754 against 10 161 and was not kept (μ0 6 standard errors off); fitted
    from the detected sequence at the named values it converged at excess χ² −79
    (reduced χ² 0.992, μ0 0.4846 ± 0.0011 against the data's 0.484) in 32 s."""
    from identify.fitting.driver import decide_sequence, worse_sequence
    from identify.fitting.sequence import excess_chi2

    p, w = _rebuild(current, runs, fopts, prob0)
    r0 = p.residuals(w)
    f0 = 0.5 * float(r0 @ r0)
    say(f"deciding the mode sequence again with {', '.join(p.theta.names)} free")
    p.progress = say
    best = dict(w=np.asarray(w, float), f=f0, iterations=0, wall_s=0.0, success=True, status="named")
    values = dict(current["values"])
    tried = []
    try:
        tried.append((*decide_sequence(p, best, p.model, dict(values), p.opts, say), False))
    finally:
        p.progress = None
    detected = _as_detected(runs)
    if detected is not None:
        say("  and from the sequence as detected")
        try:
            tried.append((*_decided_from(detected, p, values, say), True))
        except Exception as err:  # (the sequence it has is still decided on)
            say(f"  from the sequence as detected: failed ({type(err).__name__}: {err})")

    def excess(p_, sol_):
        r_ = p_.residuals(sol_["w"])
        return excess_chi2(p_, r_) if np.all(np.isfinite(r_)) else float("inf")

    kept = []
    for p2, sol, from_det in tried:
        p2.progress = None
        differs = len(p2.runs) != len(runs) or any(
            not np.array_equal(a.trigger_steps, b.trigger_steps) for a, b in zip(p2.runs, runs))
        # (χ² above its expectation, comparable across sequences, must go down; a start off
        # continuity is no reference: the fit's own rule with no slack)
        if differs and worse_sequence(p, {"w": w}, p2, sol, slack=0.0) is None:
            kept.append((excess(p2, sol), p2, sol, from_det))
    if not kept:
        say("  the mode sequence stands")
        return dict(current, sequence_changes=dict(triggers_moved=0, slips_inserted=0, slips_removed=0)), runs, False
    _, p2, sol, from_det = min(kept, key=lambda t: t[0])
    r = p2.residuals(sol["w"])
    values.update(zip(p2.theta.names, (float(v) for v in p2.theta.from_scaled(sol["w"][: p2.n_theta]))))
    origin = "from the sequence as detected (the fits' changes undone), " if from_det else ""
    say(f"  {origin}{sol['triggers_moved']} trigger(s) moved, "
        f"{sol['slips_inserted']} slip(s) inserted, {sol['slips_removed']} removed: "
        f"χ² {2 * f0 + p.chi2_constant():.6g} -> {float(r @ r) + p2.chi2_constant():.6g}")
    changes = {k: int(sol[k]) for k in ("triggers_moved", "slips_inserted", "slips_removed")}
    new = dict(current, values=values, w=sol["w"], ev_M=np.array(p2.ev_M), n_theta=p2.n_theta,
               chi2=float(r @ r) + p2.chi2_constant(), n_eff=p2.n_effective(),
               sequence_changes=dict(changes, from_detected=bool(from_det)))
    return new, list(p2.runs), True


def _as_detected(runs):
    """The runs with the slips as their events were detected, or None when no fit has
    changed them (triggers moved, slips inserted or removed)."""
    from identify.fitting.rundata import make_run_data

    det = [make_run_data(r.events) if r.kind == "events" else r for r in runs]
    same = all(d is r or np.array_equal(d.trigger_steps, r.trigger_steps) for d, r in zip(det, runs))
    return None if same else det


def _decided_from(runs, p, values, say):
    """(problem, solution): the model of ``p`` at ``values`` solved on ``runs`` and its
    sequence decided from there, as a fit decides it."""
    from identify.fitting.driver import decide_sequence
    from identify.fitting.problem import Problem

    pd = Problem(runs, p.model, dict(values), p.opts)
    pd.progress = say
    pd.build()
    s0 = pd.solve(pd.initial_w(values), loose=True)
    try:
        return decide_sequence(pd, s0, pd.model, dict(values), pd.opts, say)
    finally:
        pd.progress = None


def _rebuild(current, runs, fopts, prob0):
    """The current model's NLP in this process (for the final 'where')."""
    from dataclasses import replace

    from identify.fitting.problem import Problem
    from identify.model.laws import get_law
    from identify.model.symbolic import Model

    same_runs = len(runs) == len(prob0.runs) and all(a is b for a, b in zip(runs, prob0.runs))
    if tuple(current["free"]) == tuple(prob0.theta.names) and current["law"] == prob0.law.name and same_runs:
        return prob0, current["w"]
    bounds = {**dict(fopts.bounds), **current.get("bounds", {})}
    opts = replace(fopts, free=tuple(current["free"]), law=current["law"], fixed={}, start={},
                   bounds={n: b for n, b in bounds.items() if n in current["free"]})
    p = Problem(runs, Model(get_law(current["law"])), dict(current["values"]), opts)
    if len(current["ev_M"]) == p.E:
        p.ev_M = np.array(current["ev_M"])
    return p.build(), np.asarray(current["w"])

"""The refit tasks of a round: which candidates apply, their starts and realistic magnitudes,
and the order that keeps the workers busy."""

from __future__ import annotations

import math

import numpy as np

from identify.diagnosis.candidates import CandidateTask
from identify.diagnosis.records import CandidateResult
from identify.model.effects import get_effect


def rank_tasks(c: CandidateResult):
    """The order of a round's candidates: refitted ones by ΔAIC, best first, then the rest."""
    if not c.ok:
        return (1, 0)
    return (0, math.inf if c.delta_aic is None else c.delta_aic)


def candidate_tasks(ids, current, runs, fopts, folds, opts, threads, where_hint, regime_runs=(), at_magnitude=None):
    """Tasks for the current model itself and every applicable candidate; ``at_magnitude``:
    candidates that fit better held at their realistic magnitude last round (started
    there as well)."""
    tail = np.asarray(current["w"])[current["n_theta"]:]
    common = dict(runs=runs, values=current["values"], free=current["free"], w_tail=tail, ev_M=current["ev_M"],
                  options=fopts, folds=folds, max_iter=opts.max_iter, threads=threads,
                  null_chi2=current.get("chi2"), null_n_eff=current.get("n_eff"), screen_p=opts.alpha,
                  regime_runs=list(regime_runs), priors=dict(current.get("priors") or {}))
    added = dict(current.get("bounds", {}))  # bounds of the effects already added
    tasks = [CandidateTask(effect=None, law=current["law"], bounds=added, **common)]
    skipped = []
    for eid in ids:
        eff = get_effect(eid, runs)
        why = eff.applicable(tuple(current["free"]), current["law"])
        if why and eff.confounded_reason():
            # (never named: the model's own parameters absorb it by construction)
            mimics = [n for n in current["free"] if n in ("mu_max", "mu_min", "A", "mu_0", "B")]
            skipped.append(CandidateResult(effect=eid, ok=False, reason=f"confounded: {why}",
                                           status="not applicable", parameters=list(eff.parameters),
                                           confounded_with=mimics, note=f"confounded: {why}"))
            continue
        if why:
            skipped.append(CandidateResult(effect=eid, ok=False, reason=f"not applicable: {why}",
                                           status="not applicable", parameters=list(eff.parameters),
                                           note=f"not applicable: {why}"))
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
        starts = candidate_starts(eff, nulls, where_hint)
        m = (at_magnitude or {}).get(eid)
        if m and m.get("parameter") in eff.parameters:
            starts = starts + [{**nulls, m["parameter"]: float(m["value"])}]
        vals = {**current["values"], **eff.fixed_values(), **nulls}
        tasks.append(CandidateTask(effect=eid, law=current["law"], extra=tuple(eff.parameters),
                                   bounds={**added, **dict(eff.bounds)}, starts=starts, nulls=nulls,
                                   magnitude=realistic_magnitude(eff, nulls) if opts.magnitude_check else None,
                                   **{**common, "values": vals, "priors": {**common["priors"], **eff.priors()}}))
    return tasks, skipped


def expected_cost(task) -> int:
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


def realistic_magnitude(eff, nulls) -> tuple | None:
    """(parameter, realistic value) of a one-parameter candidate, for the check of
    :func:`identify.diagnosis.magnitude_check.at_magnitude`; None where there is none to check (several
    parameters, as the topography's wavelength and phase, or a magnitude at the null)."""
    if len(eff.parameters) != 1 or not eff.magnitude or eff.magnitude[0] != eff.parameters[0]:
        return None
    name, value = eff.magnitude[0], float(eff.magnitude[1])
    return None if math.isclose(value, float(nulls[name]), rel_tol=1e-9, abs_tol=0.0) else (name, value)


def candidate_starts(eff, nulls, where_hint) -> list:
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

"""Each named per-run or per-device effect tested again against its nested twin in the
final model (a backward step of the forward selection).

A round decides between twins (:func:`identify.diagnosis.selection.nested_twins`) in
the model of that round, before the effects named later are in it. Measured on the
confusion row of a load offset beside each run's own drift (no random walk in the
data): round 1 named the walk over the drift per run, its 48 coefficients taking
part of the misfit of the load offset not yet modelled, which differs from run to run
through the load; round 2 then named the load offset. So once the rounds end, every
named effect with a twin that was not the last one named is refitted in the final
model with its twin in its place, and the twins are judged by the same test a round
uses: the richer one stays only where its extra values fit better beyond chance
(p < :data:`~identify.diagnosis.selection.TWIN_P` and a lower BIC), else the twin takes
its place, with its own refit as the final model (its held-out folds included).
"""

from __future__ import annotations

import numpy as np

from identify.diagnosis.candidates import CandidateTask, run_candidate
from identify.diagnosis.records import CandidateResult
from identify.diagnosis.selection import converged, twin_test
from identify.diagnosis.tasks import candidate_starts
from identify.model.effects import get_effect

__all__ = ["recheck_twins", "twin_task", "twin_test"]


def twin_task(st, k: int) -> CandidateTask | None:
    """The final model with its ``k``-th named effect replaced by that effect's nested
    twin, as a refit task (its held-out folds included), or None where there is no twin
    to test: no twin, the twin not among the candidates or already named."""
    sid = st.effects[k]
    s_eff = get_effect(sid, st.runs)
    gid = s_eff.global_twin
    if gid is None or gid in st.effects or gid not in st.opts.effects:
        return None
    g_eff = get_effect(gid, st.runs)
    cur = st.current
    own = set(s_eff.parameters)
    values = {**cur["values"], **s_eff.null_values(cur["values"]), **g_eff.fixed_values()}
    nulls = g_eff.null_values(values)
    # the twin starts from the named effect's own values where it has the same parameter
    # (a drift per run from the walk's rates), else from its null and its nudges
    warm = {n: float(cur["values"][n]) for n in g_eff.parameters if n in own and n in cur["values"]}
    starts = ([warm] if warm else []) + candidate_starts(g_eff, nulls, st.where0)
    return CandidateTask(
        effect=gid, runs=st.runs, law=cur["law"], values={**values, **nulls},
        free=tuple(n for n in cur["free"] if n not in own), extra=tuple(g_eff.parameters),
        bounds={**{n: b for n, b in cur.get("bounds", {}).items() if n not in own}, **dict(g_eff.bounds)},
        priors={**{n: sd for n, sd in (cur.get("priors") or {}).items() if n not in own}, **g_eff.priors()},
        starts=starts, nulls=nulls, w_tail=np.asarray(cur["w"])[cur["n_theta"]:], ev_M=cur["ev_M"],
        options=st.fopts, folds=st.folds, max_iter=st.opts.max_iter, threads=st.threads,
        regime_runs=list(st.regime_runs))


def recheck_twins(st) -> list:
    """Every named effect but the last, with a nested twin among the candidates, judged
    against it in the final model; where the twin wins it takes the effect's place in
    ``st`` (effects, current model, final measurement) and a note says so. The checks,
    one dict each (named, twin, the test's figures, the refit's status, the outcome)."""
    checks = []
    final = st.final_res
    if final is None or not final.ok or len(st.effects) < 2:
        return checks
    last = st.rounds[-1].current if st.rounds else None
    if last is not None and not last.ok:
        # the final numbers are a named candidate's, on a mode sequence decided before:
        # a refit on the current one would not compare like with like
        return checks
    if st.regime_runs and any(twin_task(st, k) is not None for k in range(len(st.effects) - 1)):
        # the runs left out for their regime are read next with the last round's refits,
        # made in the model as named; a twin in its place would leave them stale
        st.notes.append("the named per-run or per-device effects were not tested again against their twins in "
                        "the final model: runs were left out for their regime, and their screen reads the last "
                        "round's refits of the model as named")
        return checks
    k = 0
    while k < len(st.effects) - 1:  # (a twin that took a place is tested against its own twin)
        task = twin_task(st, k)
        if task is None:
            k += 1
            continue
        sid, gid = st.effects[k], task.effect
        st.say(f"{sid} tested again against {gid} in the final model (with "
               f"{', '.join(e for e in st.effects if e != sid)})")
        try:
            res = CandidateResult.from_dict(st.executor.submit(run_candidate, task).result())
        except Exception as err:  # a lost worker: no evidence, the named effect stays
            res = CandidateResult(effect=gid, ok=False, status=f"failed: {err}")
        st.n_refits += 1
        check = dict(named=sid, twin=gid, status=res.status)
        if not res.ok:
            check["outcome"] = "kept"
            st.notes.append(f"{sid} could not be tested again against {gid} in the final model: its refit "
                            f"failed ({res.status}); {sid} stays named")
            checks.append(check)
            k += 1
            continue
        test = twin_test(final, res, final.n_obs)
        check.update({n: v for n, v in test.items() if n != "text"}, twin_chi2=float(res.chi2),
                     named_chi2=float(final.chi2), outcome="kept" if test["keeps"] else "replaced")
        checks.append(check)
        if test["keeps"]:
            st.notes.append(f"{sid} tested again against {gid} in the final model: its extra values still fit "
                            f"better ({test['text']}); it stays named")
            k += 1
            continue
        if not converged(res):
            # (an unconverged twin would make a final model no round measured as such)
            check["outcome"] = "kept"
            st.notes.append(f"{sid} tested again against {gid} in the final model: the refit with {gid} did not "
                            f"converge ({res.status}), though its χ² says {sid}'s extra values add nothing "
                            f"({test['text']}); {sid} stays named")
            k += 1
            continue
        later = ", ".join(e for e in st.effects if e != sid)
        st.notes.append(f"{sid} replaced by {gid} in the final model: with {later} in the model, its values "
                        f"of their own add nothing beyond {gid}'s ({test['text']}). The final model and its "
                        f"gaps are {gid}'s refit" + (f"; {res.estimate_text}" if res.estimate_text else ""))
        _adopt(st, k, res)
        final = st.final_res
    return checks


def _adopt(st, k: int, res) -> None:
    """``res`` (the final model with the ``k``-th effect's twin in its place) as the final
    model."""
    eff = get_effect(res.effect, st.runs)
    old = set(get_effect(st.effects[k], st.runs).parameters)
    st.effects[k] = res.effect
    st.current = dict(values=res.values, free=tuple(res.free), law=res.law, w=res.w, ev_M=res.ev_M,
                      n_theta=len(res.free), chi2=res.chi2, n_eff=res.n_eff,
                      bounds={**{n: b for n, b in st.current.get("bounds", {}).items() if n not in old},
                              **dict(eff.bounds)},
                      priors=dict(res.priors or {}))
    st.final_res = res

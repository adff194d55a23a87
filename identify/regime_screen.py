"""Which candidate could make runs that show no stick-slip, when nothing can be fitted.

When every run is left out for its regime (no resolvable slips where the model at the
coating's preset stick-slips) there is no baseline, and so no refit to score a candidate
by. The runs are still evidence (:mod:`identify.regime_check`): each candidate, switched
on at its realistic magnitude (``Effect.magnitude``; an aging law with the preset's
static friction) on top of the preset, is simulated over every left-out run and read as
the data were. A candidate *reproduces the regime* when none of the runs is then a
mismatch.

This screens; it does not name. Nothing is fitted: the friction parameters are the
preset's, and the candidate's magnitude is the library's, not the data's. It says which
candidate to fit (or which runs to record), not that it is the cause, so the verdict
stays ``unexplained``. Measured (the withheld logistic-law set, Table II with dc = 20 nm:
every contact loses its seed in its first slip and never re-ages): the current model
mismatched 6 of 8 runs (χ² 1737), the logistic law none (χ² 0), every other candidate
2-7 (χ² ≥ 964).
"""

from __future__ import annotations

import concurrent.futures as cf
from typing import Callable, Sequence

from .effects import get_effect
from .executors import InProcess

__all__ = ["parting", "regime_screen", "screen_one"]


def regime_screen(ids: Sequence[str], law: str, free: Sequence[str], values: dict, regime_runs: Sequence,
                  progress: Callable[[str], None] | None = None, executor: cf.Executor | None = None
                  ) -> tuple[dict, list]:
    """The current model and each applicable candidate at its realistic magnitude,
    checked against ``regime_runs`` (:class:`identify.regime_check.RegimeRun`).

    ``values`` are those the runs' regime was judged at (the fit's start: the coating's
    preset, or the start given). Returns two things: the current model's record, and the
    candidates' records, those that reproduce the regime first, then by χ². A record
    holds ``effect``, ``law``, ``values`` (the parameters the candidate set), ``regime``
    (the check's JSON), ``mismatched`` (how many runs), ``reproduces_regime``, and
    ``error`` where it could not be simulated. ``executor``: where the candidates are
    simulated (the diagnosis's workers; each candidate is one task), else one after
    another in this process."""
    say = progress or (lambda m: None)
    todo = [None] + list(dict.fromkeys(eid for eid in ids if not get_effect(eid).applicable(tuple(free), law)))
    law_of = {eid: (get_effect(eid).law or law) if eid else law for eid in todo}
    args = [(eid, law, dict(values), list(regime_runs)) for eid in todo]
    recs = {}

    def failed(eid, err):
        return _record(eid, law_of[eid], error=f"{type(err).__name__}: {err}")

    say(f"regime screen: the current model and {len(todo) - 1} candidate(s) on {len(regime_runs)} run(s)")
    ex = executor if executor is not None else InProcess()

    def collect(fut, eid):
        try:
            recs[eid] = fut.result()
        except Exception as err:  # a lost worker: that candidate is not screened
            recs[eid] = failed(eid, err)
        say(f"regime screen: {len(recs)}/{len(todo)} done: {eid or 'current model'}")

    futs = {}
    for eid, a in zip(todo, args):
        try:
            fut = ex.submit(screen_one, *a)
        except Exception as err:  # a broken pool: that candidate is not screened
            recs[eid] = failed(eid, err)
            continue
        if fut.done():  # (in process: already run, said as it goes)
            collect(fut, eid)
        else:
            futs[fut] = eid
    for fut in cf.as_completed(futs):
        collect(fut, futs[fut])
    out = [recs[eid] for eid in todo[1:]]
    out.sort(key=lambda r: (not r["reproduces_regime"], r["regime"] is None,
                            (r["regime"] or {}).get("chi2", float("inf"))))
    return recs[None], out


def parting(r: dict) -> str | None:
    """'k of n' runs a screen record parts from, or None when it was not simulated."""
    rc = r.get("regime") or {}
    return f"{r['mismatched']} of {rc['df']}" if rc else None


def _record(effect, law, error=None) -> dict:
    return dict(effect=effect, law=law, values={}, regime=None, mismatched=None, reproduces_regime=False,
                error=error)


def screen_one(effect: str | None, law: str, values: dict, regime_runs: list) -> dict:
    """One record of :func:`regime_screen`: the current model (``effect`` None) or one
    candidate at its realistic magnitude, simulated over ``regime_runs`` (a picklable
    task: numbers in, numbers out)."""
    from .laws import get_law
    from .model import Model
    from .regime_check import regime_check

    eff = get_effect(effect) if effect else None
    law_e = (eff.law or law) if eff else law
    rec = _record(effect, law_e)
    try:
        set_values = eff.simulation_values(None, values) if eff else {}
        rec["values"] = dict(set_values)
        model = Model(get_law(law_e))
        merged = {**values, **set_values}
        # (the camera's parameters, drift and exposure, are not the model's: kept beside it)
        rc = regime_check(model, {**merged, **model.defaults(merged)}, regime_runs)
    except Exception as err:  # one candidate never sinks the screen
        rec["error"] = f"{type(err).__name__}: {err}"
        return rec
    rec.update(regime=rc.to_json(), mismatched=len(rc.mismatched),
               reproduces_regime=bool(not rc.mismatched and not rc.errors and rc.df > 0))
    if rc.errors:
        rec["error"] = "; ".join(rc.errors)
    return rec

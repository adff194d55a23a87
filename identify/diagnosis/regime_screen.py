"""Which candidate could make runs that show no stick-slip, when nothing can be fitted.

When every run is left out for its regime (no resolvable slips where the model at the
coating's preset stick-slips) there is no baseline, and so no refit to score a candidate
by. The runs are still evidence (:mod:`identify.fitting.regime_check`): each candidate, switched
on at its realistic magnitude (``Effect.magnitude``; an aging law with the preset's
static friction) on top of the preset, is simulated over every left-out run and read as
the data were. A candidate *reproduces the regime* when none of the runs is then a
mismatch and their largest slips agree with the data's
(:attr:`identify.fitting.regime_check.RegimeCheck.reproduces`).

The current model is screened the same way with one of its own free parameters moved at
a time (:func:`own_screen`). Where such a move makes runs like the data's too, a
candidate that makes them is confounded with that parameter: the runs cannot tell the
two apart.

This screens; it does not name. Nothing is fitted: the friction parameters are the
preset's, and the candidate's magnitude is the library's, not the data's. It says which
candidate to fit (or which runs to record), not that it is the cause, so the verdict
stays ``unexplained``. Measured (the withheld logistic-law set, Table II with dc = 20 nm:
every contact loses its seed in its first slip and never re-ages): the current model
mismatched 6 of 8 runs (χ² 1737), the logistic law none (χ² 0), every other candidate
2-7 (χ² ≥ 964); the exponential law with τ ≥ 67.4 s none: the logistic law is
confounded with τ there.
"""

from __future__ import annotations

import concurrent.futures as cf
import math
from collections.abc import Callable, Sequence

from identify.executors import InProcess
from identify.model.effects import get_effect
from identify.progress import Stage

__all__ = ["moved_text", "own_moves", "own_screen", "parting", "regime_screen", "screen_one", "smallest_moves"]


def regime_screen(ids: Sequence[str], law: str, free: Sequence[str], values: dict, regime_runs: Sequence,
                  progress: Callable[[str], None] | None = None, executor: cf.Executor | None = None
                  ) -> tuple[dict, list]:
    """The current model and each applicable candidate at its realistic magnitude,
    checked against ``regime_runs`` (:class:`identify.fitting.regime_check.RegimeRun`).

    ``values`` are those the runs' regime was judged at (the fit's start: the coating's
    preset, or the start given). Returns two things: the current model's record, and the
    candidates' records, those that reproduce the regime first, then by χ². A record
    holds ``effect``, ``law``, ``values`` (the parameters the candidate set), ``regime``
    (the check's JSON), ``mismatched`` (how many runs), ``reproduces_regime``, and
    ``error`` where it could not be simulated. ``executor``: where the candidates are
    simulated (the diagnosis's workers; each candidate is one task), else one after
    another in this process."""
    say = progress or (lambda m: None)
    # (a per-run or per-device candidate has no value to set on runs no fit has seen: at one
    # magnitude for every run it is its global candidate, screened already; a rough track
    # at its magnitude is one made-up track, not the runs')
    todo = [None] + list(dict.fromkeys(eid for eid in ids if get_effect(eid).scope is None
                                       and not get_effect(eid).priors()
                                       and not get_effect(eid).applicable(tuple(free), law)))
    law_of = {eid: (get_effect(eid).law or law) if eid else law for eid in todo}
    say(f"regime screen: the current model and {len(todo) - 1} candidate(s) on {len(regime_runs)} run(s)")
    recs = _run_all([(eid, (eid, law, dict(values), list(regime_runs))) for eid in todo],
                    lambda eid: eid or "current model", say, executor,
                    record=lambda eid, **kw: _record(eid, law_of[eid], **kw))
    out = [recs[eid] for eid in todo[1:]]
    out.sort(key=lambda r: (not r["reproduces_regime"], r["regime"] is None,
                            (r["regime"] or {}).get("chi2", float("inf"))))
    return recs[None], out


def own_screen(law: str, free: Sequence[str], values: dict, regime_runs: Sequence,
               progress: Callable[[str], None] | None = None, executor: cf.Executor | None = None) -> list:
    """The current model with one of its own free parameters moved (:func:`own_moves`),
    checked against ``regime_runs`` as :func:`regime_screen` checks the candidates: could
    the model's own parameters make such runs? A candidate that reproduces the runs is
    then told apart from the current model only by parameters the runs do not fix, and
    is confounded with them (:func:`smallest_moves`). Measured (the withheld logistic-law
    set, whose contacts never re-age after their first slip): the exponential law makes
    every run like the data's with τ ≥ 67.4 s, 1000× the preset, and no other moved
    parameter does — μmax ≤ 0.5 keeps their regime but loses their first slip.

    Returns one record per move (as :func:`regime_screen`'s, with ``moved``: name -> value,
    and ``start``: name -> the value it was moved from), in the order of :func:`own_moves`."""
    say = progress or (lambda m: None)
    moves = own_moves(free, values)
    if not moves:
        return []
    say(f"regime screen: the current model with {len(moves)} move(s) of its own parameters")
    keys = list(range(len(moves)))
    start = {i: {n: float(values[n]) for n in moves[i]} for i in keys}
    recs = _run_all([(i, (None, law, dict(values), list(regime_runs), moves[i])) for i in keys],
                    lambda i: moved_text({"moved": moves[i], "start": start[i]}, arrow=True),
                    say, executor, record=lambda i, **kw: {**_record(None, law, **kw), "moved": dict(moves[i])})
    for i in keys:
        recs[i]["start"] = start[i]
    return [recs[i] for i in keys]


MOVE_STEPS = 4
"""Steps each free parameter takes toward each of its bounds in :func:`own_moves`: decades
for a log-scaled parameter (at most ×10⁴, τ from its preset 67 ms to 674 s), quarters of
the way for the others."""


def own_moves(free: Sequence[str], values: dict) -> list[dict]:
    """One parameter moved at a time, {name: value}: each of ``free`` that has a value,
    toward its lower and its upper bound (:data:`identify.model.params.SPECS`) in
    :data:`MOVE_STEPS` steps, nearest first, the bound the last; a direction ends where
    the values break a rule between parameters (μmin < μmax)."""
    from identify.model.params import SPECS, ParameterError, validate_parameters

    def valid(name, x):
        try:
            validate_parameters({k: v for k, v in {**values, name: x}.items() if k in SPECS})
        except ParameterError:
            return False
        return True

    out = []
    for name in free:
        spec = SPECS.get(name)
        v = values.get(name)
        if spec is None or v is None or not math.isfinite(float(v)):
            continue
        v = float(v)
        for bound in (spec.lower, spec.upper):
            if bound == v or (spec.log and (v <= 0 or bound <= 0)):
                continue
            if spec.log:
                up = bound > v
                steps = [min(v * 10.0 ** j, bound) if up else max(v / 10.0 ** j, bound)
                         for j in range(1, MOVE_STEPS + 1)]
            else:
                steps = [v + (bound - v) * j / MOVE_STEPS for j in range(1, MOVE_STEPS + 1)]
            for x in dict.fromkeys(steps):
                if not valid(name, x):
                    break
                out.append({name: float(x)})
                if x == bound:
                    break
    return out


def smallest_moves(records: Sequence[dict]) -> list[dict]:
    """The own-parameter records (:func:`own_screen`) that reproduce the runs, the
    smallest move per parameter and direction: each is where the current model's own
    parameter, moved that far, makes runs like the data's. Each is returned as a copy
    with ``holds_beyond``: whether every farther move tried in that direction makes them
    too."""
    best, tried = {}, {}
    for r in records:
        (name, x), = r["moved"].items()
        v = r["start"][name]
        key = (name, x > v)
        tried.setdefault(key, []).append(r)
        if r.get("reproduces_regime") and (key not in best or abs(x - v) < abs(best[key]["moved"][name] - v)):
            best[key] = r
    out = []
    for key, r in best.items():
        (name, x), = r["moved"].items()
        v = r["start"][name]
        farther = [o for o in tried[key] if abs(o["moved"][name] - v) > abs(x - v)]
        out.append({**r, "holds_beyond": all(o.get("reproduces_regime") for o in farther)})
    return out


def moved_text(r: dict, arrow: bool = False) -> str:
    """A move record in words: 'tau ≥ 67.4 (1000× the start)' (or 'tau = 67.4' where a
    farther move did not reproduce the runs, :func:`smallest_moves`), or with ``arrow``
    'tau 0.0674 -> 67.4'."""
    (name, x), = r["moved"].items()
    v = r["start"][name]
    ratio = x / v if v > 0 else 0.0
    rel = f" ({ratio:.3g}× the start)" if 0 < ratio < 1000 else f" ({ratio:.0f}× the start)" if ratio else ""
    if arrow:
        return f"{name} {v:.4g} -> {x:.4g}{rel}"
    sign = ("≥" if x > v else "≤") if r.get("holds_beyond", True) else "="
    return f"{name} {sign} {x:.4g}{rel}"


def _run_all(tasks, label, say, executor, record) -> dict:
    """Each task (key, args of :func:`screen_one`) through ``executor`` (else in this
    process), each said as it is done; key -> record. A task that cannot be submitted, or
    whose worker is lost, is recorded with its error (``record(key, error=...)``): one
    never sinks the screen."""
    ex = executor if executor is not None else InProcess()
    recs, futs = {}, {}
    stage = Stage(say, "regime screen", len(tasks))

    def collect(fut, key):
        try:
            recs[key] = fut.result()
        except Exception as err:  # a lost worker: that task is not screened
            recs[key] = record(key, error=f"{type(err).__name__}: {err}")
        stage.advance(str(label(key)))

    for key, args in tasks:
        try:
            fut = ex.submit(screen_one, *args)
        except Exception as err:  # a broken pool: that task is not screened
            recs[key] = record(key, error=f"{type(err).__name__}: {err}")
            stage.advance(f"{label(key)}: not submitted")
            continue
        if fut.done():  # (in process: already run, said as it goes)
            collect(fut, key)
        else:
            futs[fut] = key
    for fut in cf.as_completed(futs):
        collect(fut, futs[fut])
    return recs


def parting(r: dict) -> str | None:
    """'k of n' runs a screen record parts from, or None when it was not simulated."""
    rc = r.get("regime") or {}
    return f"{r['mismatched']} of {rc['df']}" if rc else None


def _record(effect, law, error=None) -> dict:
    return dict(effect=effect, law=law, values={}, regime=None, mismatched=None, reproduces_regime=False,
                error=error)


def screen_one(effect: str | None, law: str, values: dict, regime_runs: list, moved: dict | None = None) -> dict:
    """One record of :func:`regime_screen`: the current model (``effect`` None) or one
    candidate at its realistic magnitude, simulated over ``regime_runs`` (a picklable
    task: numbers in, numbers out); ``moved``: the current model with these values of its
    own parameters instead (:func:`own_screen`)."""
    from identify.fitting.regime_check import regime_check
    from identify.model.laws import get_law
    from identify.model.symbolic import Model

    eff = get_effect(effect) if effect else None
    law_e = (eff.law or law) if eff else law
    rec = _record(effect, law_e)
    if moved:
        rec["moved"] = dict(moved)
        values = {**values, **moved}
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
               reproduces_regime=rc.reproduces)
    if rc.errors:
        rec["error"] = "; ".join(rc.errors)
    return rec

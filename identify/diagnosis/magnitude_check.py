"""The check of a candidate at its realistic magnitude: can the data tell it there from its refit?

The local tests (the refit's likelihood gain, its R² with the model's parameters at
the refit) see a neighbourhood of the null. An effect the data do not show there can
still be absorbed far from it: measured (damping of c_extra = 2e-5 N s/m, 56× the
air damping, on the withheld-effect benchmark's 8 runs): the baseline absorbs it with
A = 0.0236 ± 0.0035 (truth 0.015) at reduced χ² 0.9887; the damping refit sits at
c_extra = 0 ± 0.9e-6 N s/m with R² 0.009 against the model's parameters (so, locally,
"not confounded" and 23 standard errors from the truth); yet a fit with c_extra held
at the truth reaches reduced χ² 0.9889 with A 0.018: the slips of a damped block
barely depend on c, and A's slip shortening takes its place.

Held at 2e-5 from the baseline's point the χ² does not even change (Δnll −1.1):
simulated, slips shorten with c up to ~2e-5 N s/m at A = 0.015 and not beyond, and
not at all at A = 0.0236 — past that much damping (from A or c) a slip ends without
overshoot. So it is the standard errors that tell: with c held there the baseline's
A, μmax and μmin are confounded (A ± 0.0117 against ± 0.0035; at 2eb2dc5 ± 0.0268
against ± 0.0033). The reference is the baseline's own standard error, c held at the
refit's value, not the refit's with c free: on that set the refit's c_extra is
0 ± 5.3e-5 and its A ± 0.019, which made the ± 0.0268 look only 1.4× wider.

So the candidate is solved again with its parameter held at the realistic magnitude
(from the refit, same mode sequence), and its χ² compared with the refit's: within
the χ²₁ quantile at ``screen_p`` (6.6 at 0.01) the magnitude is not excluded, and
the parameters it moves or unpins (:data:`MAGNITUDE_WIDER`) are its partners (none:
the data do not see it there). The solve stops as soon as it is within that
quantile, or once even :data:`GIVE_UP_MARGIN` times what its step still promises
cannot bring it there (then its Δnll is a lower bound); away from continuity, where
that promise says less, only with :data:`MAGNITUDE_DECISIVE` times the quantile to
spare.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from identify.diagnosis.refit_readings import regime_of_left_out
from identify.diagnosis.refit_screen import GIVE_UP_AFTER, GIVE_UP_MARGIN
from identify.fitting.convergence import GAVE_UP

__all__ = ["at_magnitude", "MAGNITUDE_MAX_ITER", "MAGNITUDE_DECISIVE", "MAGNITUDE_MOVED_Z", "MAGNITUDE_WIDER"]

MAGNITUDE_MAX_ITER = 10
"""Iterations of the solve at the realistic magnitude. Measured (four bundled runs): a
2 µN load offset, 40 % of the smallest load, left the continuity 0.07–0.3 µm off for 20
iterations (Δnll ≈ 14 400, not a bound there), 27 s; it ends "not settled"."""
MAGNITUDE_DECISIVE = 100.0
"""Away from continuity (further than GIVE_UP_FEAS), where the early stop is not asked,
the check at the magnitude still stops once its χ² excess, less 2 × GIVE_UP_MARGIN × what
the step promises, exceeds this many times the quantile it is judged by: excluded, its
Δnll a lower bound. Measured on the 8-run diagnosis benchmark (model-made data, no
effect, 2026-11-25): held at 2 µN the load offset's solve wandered 0.06-0.14 µm off
continuity at ½χ² 38 000-41 500 (the refit's 175) for its 10 iterations, the spring
nonlinearity's at ~8400 with 3e-3-0.5 µm off, each ~8 s for "not settled"; past three
iterations both were 1000s of quantiles above, with promises of 0.01-3500."""
MAGNITUDE_MOVED_Z = 1.0
MAGNITUDE_WIDER = math.sqrt(2.0)
"""A parameter is named as the partner of an effect the data cannot exclude at its
realistic magnitude (:func:`at_magnitude`) when, with the effect held there, its
estimate moves by at least :data:`MAGNITUDE_MOVED_Z` of its standard errors, or its
standard error grows by :data:`MAGNITUDE_WIDER` or more — half its information or more
gone, a variance inflation of 2 — or it becomes undetermined: were the effect there, its
stated value or its stated uncertainty would not hold. Both are measured against what
the current model states: the standard errors with the effect's parameter held where
the refit has it (at its null, the current model's own), not the refit's, whose freed
parameter may already have unpinned them. (Measured, the damping set: A, μmin and μmax
1.68–1.71×, τ 1.02× at 3896163; 8.0–8.7× and 3.5× at 2eb2dc5, where against the refit's
own, c_extra free at 0 ± 5.3e-5, they were 1.40×, just short; motion blur on model-made
data: ≤ 1.01×.)"""


def at_magnitude(task, prob, w: np.ndarray, chi2: float, est: dict, evaluated=None) -> dict:
    """Whether the data can tell a candidate at its realistic magnitude (``task.magnitude``)
    from its refit at ``w`` (χ² ``chi2``, estimates ``est``): the module docstring says how."""
    name, value = task.magnitude
    names = prob.theta.names
    i = names.index(name)
    vals = _values_at(prob, w)
    target = float(prob.theta.to_scaled({**vals, name: float(value)})[i])
    if not prob.theta.lo[i] <= target <= prob.theta.hi[i]:
        return dict(parameter=name, value=float(value), absorbed=None,
                    error="the realistic magnitude lies outside the candidate's bounds")
    ref = min(chi2, task.null_chi2) if task.null_chi2 is not None else chi2
    need = float(stats.chi2.isf(task.screen_p, 1))
    const = prob.chi2_constant()
    horizons = np.array(prob.ev_M, copy=True)
    sol = _solve_held(task, prob, w, i, target, (ref, need, const))
    chi2_m = 2.0 * float(sol["f"]) + const
    dnll = 0.5 * (chi2_m - ref)
    # judged only at a point the solver vouches for: converged, or stopped by the rules
    # of _stops (``stop`` within GIVE_UP_FEAS of continuity, ``decisive`` anywhere, its point
    # then perhaps far off continuity: the Δnll a lower bound by a wide margin); else not settled
    settled = (bool(sol.get("success")) or sol["status"] == GAVE_UP) and np.isfinite(dnll)
    # held at the magnitude and fitting *better* than its own refit by more than the
    # quantile: no parameter of the model stands in for it there; the refit ended in a
    # local solution near its null (a start the solve never saw), which the report says
    better = bool(settled and 2 * dnll < -need)
    absorbed = bool(-need <= 2 * dnll <= need) if settled else None
    got = _values_at(prob, sol["w"])
    se_m, stated = _stderrs_held(prob, w, sol["w"], i, evaluated, horizons) if absorbed else ({}, {})
    moved = _moved(names, name, vals, got, est, stated, se_m, absorbed)
    partners = [m["parameter"] for m in moved if m["partner"]]
    out = dict(parameter=name, value=float(value), chi2=float(chi2_m), delta_nll=float(dnll),
               needed_delta_nll=0.5 * need, absorbed=absorbed, better=better, partners=partners,
               moved=moved[:max(4, len(partners))], stderr_checked=bool(se_m), status=sol["status"],
               iterations=int(sol["iterations"]), lower_bound=bool(sol["status"] == GAVE_UP and absorbed is False))
    if task.regime_runs:
        out.update(_left_out_at_held(task, prob, sol["w"], got))
    return out


def _values_at(prob, w: np.ndarray) -> dict:
    """Every free parameter's value at the solution ``w``, by name."""
    return dict(zip(prob.theta.names, (float(v) for v in prob.theta.from_scaled(w[: prob.n_theta]))))


def _stops(ref: float, need: float, const: float):
    """The held solve's two early stops: ``stop`` near continuity, once within the quantile
    ``need`` of ``ref`` or past it; ``decisive`` anywhere, only :data:`MAGNITUDE_DECISIVE`
    times past it (away from continuity a point that looks absorbed is no evidence)."""
    def stopper(beyond: float, within: bool):
        def stop(it: int, half_chi2: float, promised: float) -> bool:
            d = 2.0 * half_chi2 + const - ref
            if within and d <= need:
                return True
            return it > GIVE_UP_AFTER and d - 2.0 * GIVE_UP_MARGIN * max(promised, 0.0) > beyond
        return stop

    return stopper(need, within=True), stopper(MAGNITUDE_DECISIVE * need, within=False)


def _solve_held(task, prob, w: np.ndarray, i: int, target: float, judge: tuple) -> dict:
    """The refit solved again from ``w`` with parameter ``i`` held at ``target`` (same mode
    sequence), under :func:`_stops` and :data:`MAGNITUDE_MAX_ITER`; the problem's own stops
    and options are restored after. ``judge``: (ref, need, const) of :func:`_stops`."""
    ref, need, const = judge
    stop, decisive = _stops(ref, need, const)
    w0 = np.array(w, float)
    w0[i] = target
    give_up0, far0 = prob.give_up, getattr(prob, "give_up_far", None)
    try:
        # (the arcs may be resized: the refit's record has taken its own horizons already)
        if prob.E:
            w0 = prob.settle_arcs(w0)
        prob.give_up, prob.give_up_far = stop, decisive
        with prob.tuned(max_iter=min(prob.opts.max_iter, MAGNITUDE_MAX_ITER)):
            sol = prob.solve(w0, fixed={i: target})
            if (task.regime_runs and not sol.get("success") and sol["status"] != GAVE_UP
                    and np.isfinite(sol["f"]) and 2.0 * float(sol["f"]) + const - ref <= need):
                # the runs left out are read at this point (_left_out_at_held), which fits as
                # well so far: finished towards continuity, where its χ² is the model's.
                # Measured (rejuvenation held at 1 µm): 10 iterations left it 2.9 nm off continuity
                more = prob.solve(sol["w"], fixed={i: target})
                if np.isfinite(more["f"]):
                    sol = dict(more, iterations=int(sol["iterations"]) + int(more["iterations"]))
    finally:
        prob.give_up, prob.give_up_far = give_up0, far0
    return sol


def _stderrs_held(prob, w: np.ndarray, w_m: np.ndarray, i: int, evaluated, horizons: np.ndarray):
    """(standard errors with the effect held at its magnitude, at ``w_m``; the reference:
    those with it held where the refit has it, at ``w``: at its null the current model's own)."""
    se_m = _held_stderrs(prob, w_m, i)
    # (the refit's own evaluation at w, the solve since having moved the arcs' last
    # point; not when settling the arcs resized them: the reference and se_m must
    # come from one problem)
    same = evaluated is not None and np.array_equal(horizons, prob.ev_M)
    stated = _held_stderrs(prob, w, i, evaluated if same else None) if se_m else {}
    return se_m, stated


def _moved(names, name: str, vals: dict, got: dict, est: dict, stated: dict, se_m: dict, absorbed) -> list:
    """How far each other parameter moved with the effect held at its magnitude, in its
    standard errors, and whether it is a partner (:data:`MAGNITUDE_WIDER`); partners first."""
    moved = []
    for n in names:
        se_refit = (est.get(n) or {}).get("stderr")
        se = stated.get(n) or se_refit
        if n == name or not se or not np.isfinite(se) or se <= 0:
            continue
        m = dict(parameter=n, value=vals[n], at_magnitude=got[n], z=float((got[n] - vals[n]) / se), stderr=float(se),
                 stderr_refit=float(se_refit) if se_refit and np.isfinite(se_refit) else None,
                 # "held": the current model's (the effect held at the refit's value); "refit":
                 # that covariance failed or left this parameter undetermined
                 stderr_reference="held" if stated.get(n) else "refit")
        if se_m:
            s2 = se_m.get(n)
            ok = s2 is not None and np.isfinite(s2)
            m.update(stderr_at_magnitude=float(s2) if ok else None, wider=float(s2 / se) if ok else None,
                     undetermined=not ok)
        m["partner"] = bool(absorbed and (abs(m["z"]) >= MAGNITUDE_MOVED_Z or m.get("undetermined")
                                          or (m.get("wider") or 0.0) >= MAGNITUDE_WIDER))
        moved.append(m)
    moved.sort(key=lambda m: (not m["partner"], -_weight(m), m["parameter"]))
    return moved


def _weight(m: dict) -> float:
    """How far a parameter moved or widened, each criterion in units of its own threshold."""
    return math.inf if m.get("undetermined") else max(abs(m["z"]) / MAGNITUDE_MOVED_Z,
                                                      (m.get("wider") or 0.0) / MAGNITUDE_WIDER)


def _left_out_at_held(task, prob, w: np.ndarray, got: dict) -> dict:
    """The runs left out for their regime, read at the held values, with how far that point
    is from continuity and where a profile over the parameter would start."""
    # With its parameter at the magnitude and the model's own refitted to the runs fitted,
    # does the effect make them? (identify.diagnosis.regime_notes.held_evidence). Measured (withheld
    # rejuvenation, dc = 1 µm; 2 runs fitted, 6 left out): held at 1 µm the runs fitted give χ²
    # 2744.73 against the current model's 2744.97, and all 6 come out as the data's
    # (χ² 0, against 54.3 at the current values); on top of the current values without
    # the refit, 1 µm had shrunk the fitted runs' largest slips (z 5.5, 7.8).
    _, g = prob.evaluate(w)
    out = dict(continuity_um=float(np.abs(g).max()) if g.size else 0.0,
               regime=regime_of_left_out(task, {**task.values, **got}))
    # (where a profile over the parameter starts: identify.diagnosis.regime_profile; not JSON)
    out["_start"] = dict(w=np.array(w, float), ev_M=np.array(prob.ev_M))
    return out


def _held_stderrs(prob, w: np.ndarray, i: int, evaluated=None) -> dict:
    """Each parameter's robust standard error at w with parameter i held (known); {} when
    the covariance fails as a whole (it then says nothing of any one parameter).
    ``evaluated``: the central-difference evaluation at w, when there is one."""
    from identify.fitting.result import standard_errors

    try:
        C = prob.covariance(w, fixed_idx=[i], robust=True, evaluated=evaluated)
    except Exception:
        return {}
    errors = standard_errors(prob.theta, w[: prob.n_theta], C, 1.0)
    se = {n: x[0] for j, (n, x) in enumerate(zip(prob.theta.names, errors)) if j != i}
    return se if any(v is not None and np.isfinite(v) for v in se.values()) else {}

"""A candidate's parameter profiled on every run: the runs fitted by their likelihood, the
runs left out for their regime by how they read (:mod:`identify.fitting.regime_check`).

Where the final model parts from runs the fit left out for their regime, those runs are
evidence no refit sees: they enter no likelihood. Measured (the withheld rejuvenation
set, memory length dc = 1 µm against the baseline's 20 nm; 2 runs fitted, 6 left out):
the 2 runs fit at the noise with either dc — held at 1 µm and refitted they give χ²
2744.7 against the current model's 2745.0 — and only the
left-out runs tell the two apart (χ² 54.3 at the final values, 0 at 1 µm). A refit with
dc free ended in a local solution near its null (χ² 8108).

So the parameter is profiled: held at values stepped out from its realistic magnitude
(half-decades for a log-scaled parameter, half the distance to its null for the
others), the model's own parameters refitted to the runs fitted at each (warm-started
from the last), and every left-out run read at the refit's values. Each point gets the
joint

    C(v) = χ²_fitted(v) + Σ_runs d_j(v)²,   d_j = max(z_j, slip_z_j),

the run's distance from the data's in units of a slip's noise, the larger of its two
readings (:func:`identify.fitting.regime_check.regime_check`: model slips the data lack, and the
largest slips two-sided). The current model's is C₀ = χ²_fitted + Σ d_j² at its values.
The fall C₀ − min C is scored as a likelihood ratio on one degree of freedom; the 95 %
interval is the points within 3.84 of the minimum, bracketed by the first points beyond.
The own parameters follow the runs fitted at every point, not the joint (a refit of the
left-out runs' reading is not differentiable): along the profile they are what the runs
fitted make them.

Held out: each left-out run in turn is dropped from the sum, the profile's minimum taken
without it, and its largest slip predicted there (µm, floored as the check floors it).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from scipy import stats

from identify.diagnosis.features import feature_values, gap
from identify.diagnosis.refit_readings import regime_of_left_out
from identify.diagnosis.refit_screen import GIVE_UP_MARGIN
from identify.diagnosis.refit_solve import candidate_problem

__all__ = ["profile_chain", "regime_profile", "run_distances", "PROFILE_POINTS", "PROFILE_BEYOND"]

PROFILE_POINTS = 4
"""Points each direction of a profile takes at most (half-decades: ×100 either way)."""

PROFILE_BEYOND = 25.0
"""A direction stops once its joint χ² is this far above the best it has seen (5 σ on one
degree of freedom: well past the 95 % interval's 3.84)."""

PROFILE_MAX_ITER = 80
"""Iterations of each held refit (warm-started from the last point's solution)."""

CI_CHI2 = float(stats.chi2.isf(0.05, 1))  # 3.84


def run_distances(regime: dict) -> dict:
    """name -> d_j² of a regime check's JSON (the larger of the run's mismatch z and
    its two-sided slip_z, squared); runs that could not be simulated are left out."""
    out = {}
    for r in (regime or {}).get("runs", []):
        if r.get("error") or r.get("slip_z") is None:
            continue
        out[r["name"]] = max(float(r.get("z") or 0.0), float(r["slip_z"])) ** 2
    return out


def _slip_diffs_um(regime: dict, noise_um: dict) -> dict:
    """name -> the run's floored largest-slip difference, µm (slip_z·√2·σ̂)."""
    return {r["name"]: float(r["slip_z"]) * math.sqrt(2.0) * noise_um[r["name"]]
            for r in (regime or {}).get("runs", []) if r.get("slip_z") is not None and r["name"] in noise_um}


def profile_chain(task, start_value: float, direction: int, w0, ev_M, n_points: int = PROFILE_POINTS,
                  include_start: bool = False, beyond: float = PROFILE_BEYOND) -> list:
    """One direction of the profile (a picklable task): ``task`` is the candidate's
    :class:`identify.diagnosis.candidates.CandidateTask` (one parameter, ``task.extra``), held
    at values stepped from ``start_value`` (``direction`` +1 up, −1 down; the start
    itself too with ``include_start``), each solved from the last solution (``w0``,
    ``ev_M``: the check at the magnitude's). Returns one dict per point: ``value``,
    ``chi2`` (the runs fitted), ``status``, ``continuity_um``, ``values``, ``regime``
    (the left-out runs read there), ``joint`` (C), ``gap_um`` (the fitted runs'
    features), or ``error``."""
    (name,) = task.extra
    free = tuple(task.free) + (name,)
    prob = candidate_problem(task, free)
    prob.opts = replace(prob.opts, max_iter=PROFILE_MAX_ITER)
    if ev_M is not None and len(ev_M) == prob.E:
        prob.ev_M = np.array(ev_M)
    i = prob.theta.names.index(name)
    lo, hi = float(prob.theta.lo[i]), float(prob.theta.hi[i])
    log = bool(prob.theta.log[i])
    null = float(task.nulls.get(name, start_value))
    step = math.sqrt(10.0) if log else abs(start_value - null) / 2.0
    values = [start_value] if include_start else []
    v = start_value
    for _ in range(n_points if step > 0 else 0):
        v = v * step ** direction if log else v + direction * step
        values.append(v)
    w = np.array(w0, float)
    const = prob.chi2_constant()
    out, best = [], math.inf
    for v in values:
        rec = dict(value=float(v))
        try:
            vals = dict(zip(prob.theta.names, (float(x) for x in prob.theta.from_scaled(w[: prob.n_theta]))))
            target = float(prob.theta.to_scaled({**vals, name: v})[i])
            if not (lo <= target <= hi) or (log and v <= 0):
                break  # (past the bound: the direction ends)
            w[i] = target
            if prob.E:
                w = prob.settle_arcs(w)
            sol = prob.solve(w, fixed={i: target})
            if not np.isfinite(sol["f"]):
                raise ValueError(f"the held refit is not finite ({sol['status']})")
            r, g = prob.evaluate(sol["w"])
            got = dict(zip(prob.theta.names, (float(x) for x in prob.theta.from_scaled(sol["w"][: prob.n_theta]))))
            regime = regime_of_left_out(task, {**task.values, **got})
            chi2 = 2.0 * float(sol["f"]) + const
            joint = chi2 + sum(run_distances(regime).values())
            lower = chi2
            if not sol.get("success"):
                # how low its χ² could still go: what the Gauss–Newton model promises (to a
                # feasible point), GIVE_UP_MARGIN times over, as the candidates' refits judge
                half = prob.solution_gap(sol["w"])["half_chi2"]
                lower = chi2 - 2.0 * GIVE_UP_MARGIN * half if np.isfinite(half) else -math.inf
            rec.update(chi2=chi2, lower_chi2=float(lower), success=bool(sol.get("success")), status=sol["status"],
                       continuity_um=float(np.abs(g).max()) if g.size else 0.0,
                       values=got, regime=regime, joint=joint, gap_um=gap(feature_values(prob, sol["w"], r))["gap_um"],
                       log=log,
                       w=np.array(sol["w"]), ev_M=np.array(prob.ev_M))
            w = np.array(sol["w"])
        except Exception as err:  # the direction ends; the points so far stand
            rec["error"] = f"{type(err).__name__}: {err}"
            out.append(rec)
            break
        out.append(rec)
        best = min(best, joint)
        if joint > best + beyond:
            break
    return out


def _collect(futs, say) -> list:
    pts = []
    for f in futs:
        try:
            pts += f.result()
        except Exception as err:  # a lost worker: that direction is missing
            say(f"profile direction failed: {type(err).__name__}: {err}")
    return pts


def regime_profile(task, start: dict, current_chi2: float, final_regime: dict, noise_um: dict,
                   executor=None, say: Callable[[str], None] | None = None, continuity_um: float = 1e-3) -> dict:
    """The profile of ``task``'s parameter (module docstring) from the check at its
    magnitude (``start``: ``value``, ``w``, ``ev_M``), both directions on ``executor``
    (else here). ``current_chi2``/``final_regime``: the current model's χ² on the runs
    fitted and its regime check's JSON on the runs left out (C₀); ``noise_um``: run name
    -> σ̂ of the runs left out. A point is used where its held refit is on continuity to
    ``continuity_um`` and every left-out run was read there.

    Returns ``parameter``, ``value`` (the best point), ``inside`` (the lowest and highest
    points within 3.84 of the best), ``interval`` (lo, hi: the nearest points certainly
    beyond that on each side, between which the 95 % interval lies; None where a side
    has none: open), ``delta_chi2`` (C₀ − min C), ``p_value``, ``reproduces`` (the left-out runs at the
    best point), ``null_excluded`` (C₀ beyond the interval's 3.84), the gaps of
    the left-out runs' largest slips (µm: ``slip_gap_before_um`` at the current values,
    ``slip_gap_after_um`` at the best point, ``slip_gap_heldout_um`` each run predicted
    from the profile without it), ``gap_after_um`` (the runs fitted at the best point),
    ``points`` (value, chi2, regime χ², joint, status), and ``best`` (the best point's
    values, w, ev_M, chi2: the model to go on with; not JSON)."""
    (name,) = task.extra
    pts = _profile_points(task, start, executor, say or (lambda m: None), continuity_um)
    # the best point and those inside the interval: on continuity, the runs simulated
    used = [p for p in pts if "joint" in p and p["continuity_um"] <= continuity_um and (p["regime"] or {}).get("df")
            and not any(r.get("error") for r in p["regime"].get("runs", []))]  # (a run not read: no joint)
    for p in pts:
        p["used"] = any(p is q for q in used)
    base = sum(run_distances(final_regime).values())
    c0 = float(current_chi2) + base
    out = dict(effect=task.effect, parameter=name, null=task.nulls.get(name), points=_points_json(pts),
               current_joint=c0, current_chi2=float(current_chi2), current_regime_chi2=base)
    if not used:
        out.update(value=None, delta_chi2=float("nan"), p_value=float("nan"), reproduces=False, interval=None,
                   null_excluded=False,
                   error="no point of the profile could be used (none on continuity with its runs simulated)")
        return out
    best = min(used, key=lambda p: p["joint"])
    inside, interval = _interval(pts, used, best["joint"] + CI_CHI2)
    dc = c0 - best["joint"]
    # left-out runs' largest slips: before (current values), after (best), each held out
    d_before = _slip_diffs_um(final_regime, noise_um)
    d_after = _slip_diffs_um(best["regime"], noise_um)
    held = _slip_diffs_heldout_um(d_before, used, noise_um)
    rms = lambda d: float(np.sqrt(np.mean(np.square(list(d.values()))))) if d else float("nan")  # noqa: E731
    out.update(
        value=best["value"], inside=inside, interval=interval,
        delta_chi2=float(dc), p_value=float(stats.chi2.sf(dc, 1)) if dc > 0 else 1.0,
        reproduces=bool(best["regime"].get("reproduces")),
        # (the null is the current model, whose joint is C₀: outside the interval iff the fall exceeds 3.84)
        null_excluded=bool(dc > CI_CHI2),
        slip_gap_before_um=rms(d_before), slip_gap_after_um=rms(d_after), slip_gap_heldout_um=rms(held),
        gap_after_um=float(best["gap_um"]), chi2=float(best["chi2"]),
        best=dict(values=best["values"], w=best["w"], ev_M=best["ev_M"], chi2=float(best["chi2"]),
                  regime=best["regime"]))
    return out


def _profile_points(task, start: dict, executor, say: Callable[[str], None], continuity_um: float) -> list:
    """Every point of the profile, sorted by value: both directions from ``start`` on
    ``executor`` (else here), then one level of refinement around the best."""
    from identify.executors import InProcess

    (name,) = task.extra
    ex = executor if executor is not None else InProcess()
    say(f"profile of {task.effect} ({name}) on the runs fitted and the runs left out for their regime")
    futs = [ex.submit(profile_chain, task, float(start["value"]), +1, start["w"], start["ev_M"], PROFILE_POINTS, True),
            ex.submit(profile_chain, task, float(start["value"]), -1, start["w"], start["ev_M"], PROFILE_POINTS)]
    pts = _collect(futs, say)
    # one level of refinement: the point halfway (geometrically for a log-scaled
    # parameter) between the best and each neighbour, solved from the best's solution
    ok = [p for p in pts if "joint" in p and p["continuity_um"] <= continuity_um]
    if ok:
        b = min(ok, key=lambda p: p["joint"])
        log = b["log"]
        mids = []
        for side in (-1, 1):
            nb = [p for p in pts if (p["value"] - b["value"]) * side > 0]
            if nb:
                v = min(nb, key=lambda p: abs(p["value"] - b["value"]))["value"]
                mids.append(math.sqrt(v * b["value"]) if log else 0.5 * (v + b["value"]))
        say(f"profile of {task.effect}: refining around {name} = {b['value']:.4g}")
        pts += _collect([ex.submit(profile_chain, task, m, +1, b["w"], b["ev_M"], 0, True) for m in mids], say)
    pts.sort(key=lambda p: p["value"])
    return pts


def _points_json(pts: list) -> list:
    """The profile's points as the result reports them (value, χ² fitted and regime, joint,
    status, whether used)."""
    return [dict(value=p["value"], chi2=p.get("chi2"), lower_chi2=p.get("lower_chi2"),
                 regime_chi2=(p["joint"] - p["chi2"]) if "joint" in p else None, joint=p.get("joint"),
                 status=p.get("status") or p.get("error"), continuity_um=p.get("continuity_um"),
                 mismatched=len((p.get("regime") or {}).get("mismatched", [])), used=p["used"]) for p in pts]


def _interval(pts: list, used: list, edge: float):
    """((lowest, highest) used point within ``edge``, (lo, hi) the nearest points certainly
    beyond it on each side, None where a side has none: open)."""
    inside = [p for p in used if p["joint"] <= edge]

    def beyond(p):
        # outside the interval for certain: converged on continuity with its joint past
        # the edge, or its χ² past the edge however much lower it could still go (a
        # point still short of convergence only bounds the profile from above)
        if p["used"] and p["success"] and p["joint"] > edge:
            return True
        return "lower_chi2" in p and p["lower_chi2"] > edge

    lo_v, hi_v = min(p["value"] for p in inside), max(p["value"] for p in inside)
    # the interval's ends: the nearest points beyond it on each side, past any point
    # that is neither inside nor certainly beyond (None: open on that side)
    below = [p for p in pts if p["value"] < lo_v]
    above = [p for p in pts if p["value"] > hi_v]
    lo_b = next((p["value"] for p in reversed(below) if beyond(p)), None)
    hi_b = next((p["value"] for p in above if beyond(p)), None)
    return (lo_v, hi_v), (lo_b, hi_b)


def _slip_diffs_heldout_um(d_before: dict, used: list, noise_um: dict) -> dict:
    """Each left-out run's largest-slip difference (µm) at the profile's minimum without that
    run in the sum: the run predicted, not fitted."""
    held = {}
    for run in d_before:
        def without(p, run=run):
            return p["joint"] - run_distances(p["regime"]).get(run, 0.0)
        p_j = min(used, key=without)
        dj = _slip_diffs_um(p_j["regime"], noise_um).get(run)
        if dj is not None:
            held[run] = dj
    return held

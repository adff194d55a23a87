"""Start values for the full identification (DESIGN.md §2: reduced analysis first).

The multiple-shooting NLP converges in a handful of Gauss–Newton iterations near its
solution, but from a poor start its slip arcs enter regimes where they are not smooth
(slow creep-like slips, contact states above μmax, the stick band arming) or cannot be
integrated at all. Two small, robust least-squares problems, seeded by the given start,
put the parameters near the solution first:

aging (event-level Eq. 9)
    every detected slip but each run's first has a rest (its trigger step minus the
    previous one) after which the contact, rejuvenated by the previous slip, aged to a
    capacity inside the trigger step's force interval. Residual: √12·(position − ½),
    the uniform interval's; free: the aging law's parameters.
slip lengths
    with the aging fixed, the arcs started from each slip's trigger (data elongation,
    aged state) must reproduce the measured plateau differences. Free: the remaining
    parameters (μmin, A, ...). A subsample of slips keeps it cheap.

A weak pull towards the given start (one scale unit) keeps a parameter the data of a
stage cannot fix where it was, for the next stage or the full NLP to decide.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.optimize import least_squares

from identify.model.symbolic import LENGTH_UNIT

__all__ = ["staged_start", "start_merit"]

log = logging.getLogger(__name__)
_PRIOR_WEIGHT = 0.1  # residual per scaled unit away from the start


def _trigger_table(prob):
    """Per slip with a predecessor in its run: rest (s), force interval [lo, hi]/N
    relative quantities, data elongation at the trigger, run conditions."""
    x = prob.pl_x0  # data plateau levels, m
    keep = ~prob.ev_first
    e = np.nonzero(keep)[0]
    prev = e - 1
    rest = (prob.ev_step[e] - prob.ev_step[prev]) / prob.ev_fp[e]
    e0 = prob.ev_step[e] * prob.runs[0].step_nominal - x[prob.ev_prev[e]]
    return dict(ev=e, rest=rest, e0=e0, x_prev=x[prob.ev_prev[e]])


def _aging_residuals(prob, names, values, tab):
    model, law = prob.model, prob.law
    P = dict(values)
    step = model.step(P)
    ev = tab["ev"]
    Pev = prob.event_params(P, ev)
    e0 = step * prob.ev_step[ev] - tab["x_prev"]
    z0 = law.rejuvenated_state(P) + _seed(law, P)
    z = law.rest(z0, tab["rest"], P)
    z_before = law.rest(z0, np.maximum(tab["rest"] - 1 / prob.ev_fp[ev], 0), P)
    from identify.fitting.mode_sequence.triggers import trigger_residual

    return trigger_residual(prob.position(z, tab["x_prev"], e0, Pev, z_before=z_before))


def _slip_length_sigma(prob, ev) -> np.ndarray:
    """Noise of slips ``ev``'s measured lengths (µm): the difference of the mean levels
    of the plateaus before and after each."""
    prev = prob.ev_prev[ev]
    return prob.pl_sigma[prev] * np.sqrt(1 / np.maximum(prob.pl_n[prev], 1)
                                         + 1 / np.maximum(prob.pl_n[prev + 1], 1)) / LENGTH_UNIT


def _seed(law, P) -> float:
    # the logistic law never re-ages from exactly μmin: a slip leaves a trace of order
    # exp(−δ/dc); 1e-6 of the range is a generous stand-in for the start only
    return 1e-6 * (P.get("mu_max", 1.0) - P.get("mu_min", 0.0)) if law.name == "logistic" else 0.0


def _solve(fun, tm, idx, th0, th_start):
    """Bounded least squares over the scaled parameters ``idx`` with a weak prior."""
    lo, hi = tm.lo[idx], tm.hi[idx]
    x0 = np.clip(th0[idx], lo + 1e-9, hi - 1e-9)

    def res(v):
        r = fun(v)
        r = np.where(np.isfinite(r), r, 1e3)
        return np.r_[r, _PRIOR_WEIGHT * (v - th_start[idx])]

    sol = least_squares(res, x0, bounds=(lo, hi), method="trf", x_scale=1.0, diff_step=1e-6,
                        xtol=1e-10, ftol=1e-12, max_nfev=200)
    out = th0.copy()
    out[idx] = sol.x
    return out, sol


def staged_start(prob, start_values: dict, max_slips: int = 80, seed: int = 0) -> tuple[dict, dict]:
    """Improved start values for ``prob``'s free parameters (and a log of the stages)."""
    tm = prob.theta
    th_start = tm.to_scaled({n: start_values[n] for n in tm.names})
    th = th_start.copy()
    info = {}
    if not prob.E:
        return dict(zip(tm.names, tm.from_scaled(th))), info

    def values_of(theta):
        v = dict(prob.values)
        v.update(zip(tm.names, tm.from_scaled(theta)))
        return v

    # --- stage a: aging from the triggers
    aging = [i for i, n in enumerate(tm.names) if n in prob.law.parameters and n not in ("dc", "vc")]
    tab = _trigger_table(prob)
    if aging and len(tab["ev"]) >= len(aging) + 1:
        def fa(v):
            t = th.copy()
            t[aging] = v
            return _aging_residuals(prob, tm.names, values_of(t), tab)

        th, sol = _solve(fa, tm, np.array(aging), th, th_start)
        info["aging"] = dict(cost=float(sol.cost), nfev=int(sol.nfev), n=len(tab["ev"]),
                             values={tm.names[i]: float(tm.from_scaled(th)[i]) for i in aging})
    # --- stage b: the rest from slip lengths, aging held
    other = [i for i, n in enumerate(tm.names) if i not in aging]
    if other:
        rng = np.random.default_rng(seed)
        ev = tab["ev"] if len(tab["ev"]) else np.arange(prob.E)
        if len(ev) > max_slips:
            ev = np.sort(rng.choice(ev, max_slips, replace=False))
        x = prob.pl_x0
        dx_data = (x[prob.ev_prev[ev] + 1] - x[prob.ev_prev[ev]]) / LENGTH_UNIT
        sig = _slip_length_sigma(prob, ev)
        sub = dict(tab)
        pos = np.searchsorted(tab["ev"], ev)
        ok = (pos < len(tab["ev"])) & (tab["ev"][np.minimum(pos, len(tab["ev"]) - 1)] == ev)
        ev, dx_data, sig, pos = ev[ok], dx_data[ok], sig[ok], pos[ok]
        sub = dict(ev=ev, rest=tab["rest"][pos], e0=tab["e0"][pos], x_prev=tab["x_prev"][pos])
        arcs = prob.arcs

        def fb(v):
            t = th.copy()
            t[other] = v
            P = values_of(t)
            step = prob.model.step(P)
            e0 = step * prob.ev_step[ev] - sub["x_prev"]
            # each arc starts from its data trigger (capacity mid-interval): a valid
            # trigger whatever the parameters, unlike a state aged by the model
            Pev = prob.event_params(P, ev)
            z = prob.mid_state(sub["x_prev"], e0, Pev)
            A = arcs.inputs(sub["x_prev"], e0, z, Pev, prob.ev_k[ev], prob.ev_Nb[ev], prob.ev_fp[ev],
                            np.minimum(prob.ev_gap[ev], prob.opts.max_arc_steps))
            Y = arcs.evaluate(A, prob.opts.threads)
            return (Y[0] - dx_data) / sig

        if len(ev) >= len(other):
            th, sol = _solve(fb, tm, np.array(other), th, th_start)
            info["slips"] = dict(cost=float(sol.cost), nfev=int(sol.nfev), n=len(ev),
                                 values={tm.names[i]: float(tm.from_scaled(th)[i]) for i in other})
    out = dict(zip(tm.names, map(float, tm.from_scaled(th))))
    if "mu_min" in out and "mu_max" in out and out["mu_min"] >= out["mu_max"]:
        out["mu_min"] = 0.95 * out["mu_max"]
    return out, info


def start_merit(prob, start_values: dict, w: np.ndarray | None = None) -> float:
    """χ² of the full problem at a start: its residuals plus each slip's length misfit in
    units of its noise (the shooting constraints, which the start leaves violated; the
    plateaus sit at the frames). Lower is better; the staged start is kept only where it
    is lower than the start it came from (measured: with two conditions, each a locked
    phase, the aging stage put τ 8× too high, A at 0, and the fit ended in that basin).
    ``w``: the start's point, ``prob.initial_w(start_values)``, if already made."""
    w = prob.initial_w(start_values) if w is None else w
    r, g = prob.evaluate(w)
    if not prob.E:
        return float(r @ r)
    gl = np.asarray(g[: prob.E], float) / _slip_length_sigma(prob, np.arange(prob.E))
    m = float(r @ r + gl @ gl)
    return m if np.isfinite(m) else float("inf")

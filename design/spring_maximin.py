"""The maximin NLP of a spring set: one suspension assignment, solved by Ipopt.

For springs on a given assignment of suspensions, maximise the worst margin over the
log-widths (stage one), then, when an end margin is pinned at a hard limit, the worst of
the others (stage two); see :mod:`design.spring_set` for the margins and why each
subproblem is convex. :func:`maximin_starts` gives the starts, :func:`solve_assignment`
runs both stages from each.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import casadi as ca
import numpy as np

from . import constraints as tc
from .springs import Suspension

__all__ = ["COVER_TOL", "MaximinSolution", "admissible_widths", "maximin_starts", "solve_assignment"]

COVER_TOL = 1e-9
"""A margin >= -COVER_TOL counts as covering (Table I limits are closed)."""

_IPOPT_OPTS = {
    "ipopt.print_level": 0,
    "ipopt.sb": "yes",
    "print_time": False,
    "ipopt.tol": 1e-10,
    "ipopt.constr_viol_tol": 1e-11,
    "ipopt.max_iter": 200,
    "ipopt.bound_relax_factor": 0.0,
}


def admissible_widths(s: Suspension, b: float) -> tuple[float, float]:
    """Nominal-width interval (µm) of ``s`` whose realisations ``w ± 2b`` keep k in Table I."""
    c = s.coefficient
    lb = max(s.min_width_um, (tc.K_MIN.bound / c) ** (1 / 3) + 2 * b)
    ub = min(s.max_width_um, (tc.K_MAX.bound / c) ** (1 / 3) - 2 * b)
    return lb, ub


_LOG_LO_PER_K = math.log(tc.ELONGATION_RESOLUTION.bound / tc.MU_MIN.bound)  # ln(lo/k_stiff), ln m
_LOG_HI_PER_K = math.log(tc.PULLER_TRAVEL.bound / tc.MU_MAX.bound)  # ln(hi/k_soft), ln m


@functools.cache
def _maximin_solver(n: int) -> ca.Function:
    """Ipopt solver: maximise t s.t. m_j ≥ a_j·t + (1 − a_j)·floor_j, nominal k ordered.

    x = [u (n): ln(w/µm); t]; p = [ln c (n); 2b (µm); ln L_lo; ln L_hi; a (n+1); floor (n+1)].
    """
    u = ca.SX.sym("u", n)
    t = ca.SX.sym("t")
    log_c = ca.SX.sym("log_c", n)
    two_b = ca.SX.sym("two_b")
    log_lo_req = ca.SX.sym("log_lo_req")
    log_hi_req = ca.SX.sym("log_hi_req")
    active = ca.SX.sym("active", n + 1)
    floor = ca.SX.sym("floor", n + 1)
    w = ca.exp(u)
    log_lo = log_c + 3 * ca.log(w + two_b) + _LOG_LO_PER_K  # floor: stiffest realisation
    log_hi = log_c + 3 * ca.log(w - two_b) + _LOG_HI_PER_K  # ceiling: softest realisation
    inner = [log_hi[i] - log_lo[i + 1] for i in range(n - 1)]
    m = ca.vertcat(log_lo_req - log_lo[0], *inner, log_hi[n - 1] - log_hi_req)
    g = [m - active * t - (1 - active) * floor]
    if n > 1:
        log_k = log_c + 3 * u
        g.append(ca.vertcat(*[log_k[i + 1] - log_k[i] for i in range(n - 1)]))
    nlp = {
        "x": ca.vertcat(u, t),
        "p": ca.vertcat(log_c, two_b, log_lo_req, log_hi_req, active, floor),
        "f": -t,
        "g": ca.vertcat(*g),
    }
    return ca.nlpsol(f"spring_set_{n}", "ipopt", nlp, _IPOPT_OPTS)


def _margins_np(log_c, u, b, log_lo_req, log_hi_req) -> np.ndarray:
    """Margins m_0..m_n at log-widths ``u``: the NLP's constraints, evaluated in numpy."""
    w = np.exp(u)
    log_lo = log_c + 3 * np.log(w + 2 * b) + _LOG_LO_PER_K
    log_hi = log_c + 3 * np.log(w - 2 * b) + _LOG_HI_PER_K
    return np.concatenate(
        [[log_lo_req - log_lo[0]], log_hi[:-1] - log_lo[1:], [log_hi[-1] - log_hi_req]]
    )


@dataclass(frozen=True)
class MaximinSolution:
    """Widths found from one start for one suspension assignment, with both stages' values."""

    assignment: tuple[Suspension, ...]
    widths_um: tuple[float, ...]
    worst_margin: float  # min over all margins (stage one)
    balanced_margin: float  # min over the margins not pinned at a hard limit (stage two)
    start: int


def solve_assignment(
    assignment: tuple[Suspension, ...],
    b: float,
    load_range: tuple[float, float],
    starts: list[np.ndarray],
    counter: list[int],
) -> list[MaximinSolution]:
    """Both stages for one suspension assignment, from every start.

    Stage one maximises the worst of all margins. An end margin is *pinned* when even its
    own best value (spring 1 at its narrowest / spring n at its widest admissible width)
    does not exceed that optimum: it is then held at the stage-one value and stage two
    maximises the worst of the remaining margins, so a hard limit at one end does not
    leave the rest unbalanced (a lexicographic maximin).
    """
    n = len(assignment)
    solver = _maximin_solver(n)
    log_c = np.array([math.log(s.coefficient) for s in assignment])
    bounds = [admissible_widths(s, b) for s in assignment]
    lbu = np.log([lb for lb, _ in bounds])
    ubu = np.log([ub for _, ub in bounds])
    log_lo_req, log_hi_req = math.log(load_range[0]), math.log(load_range[1])
    lbx = np.concatenate([lbu, [-ca.inf]])
    ubx = np.concatenate([ubu, [ca.inf]])
    n_g = (n + 1) + (n - 1)
    lbg = np.zeros(n_g)
    ubg = np.full(n_g, ca.inf)
    head = [log_c, [2 * b, log_lo_req, log_hi_req]]
    # Best value each end margin can reach on its own.
    end_max = (
        _margins_np(log_c, lbu, b, log_lo_req, log_hi_req)[0],
        _margins_np(log_c, ubu, b, log_lo_req, log_hi_req)[-1],
    )
    out = []
    for si, u0 in enumerate(starts):
        u0 = np.clip(u0, lbu, ubu)
        m0 = _margins_np(log_c, u0, b, log_lo_req, log_hi_req)
        p = np.concatenate(head + [np.ones(n + 1), np.zeros(n + 1)])
        sol = solver(x0=np.concatenate([u0, [m0.min()]]), p=p, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
        counter[0] += 1
        u = np.clip(np.asarray(sol["x"]).ravel()[:n], lbu, ubu)
        m = _margins_np(log_c, u, b, log_lo_req, log_hi_req)
        t1 = float(m.min())
        free = np.ones(n + 1, dtype=bool)
        free[0] = end_max[0] > t1 + 1e-6
        free[-1] = end_max[1] > t1 + 1e-6
        if t1 >= -COVER_TOL and not free.all() and free.any():
            floor = np.where(free, 0.0, max(t1 - 1e-8, 0.0))
            p2 = np.concatenate(head + [free.astype(float), floor])
            sol2 = solver(x0=np.concatenate([u, [m[free].min()]]), p=p2, lbx=lbx, ubx=ubx,
                          lbg=lbg, ubg=ubg)
            counter[0] += 1
            u2 = np.clip(np.asarray(sol2["x"]).ravel()[:n], lbu, ubu)
            m2 = _margins_np(log_c, u2, b, log_lo_req, log_hi_req)
            if m2.min() >= min(t1, 0.0) - COVER_TOL and m2[free].min() >= m[free].min():
                u, m = u2, m2
        out.append(
            MaximinSolution(
                assignment,
                tuple(float(x) for x in np.exp(u)),
                float(m.min()),
                float(m[free].min()) if free.any() else float(m.min()),
                si,
            )
        )
    return out


def maximin_starts(
    assignment: tuple[Suspension, ...], b: float, load_range: tuple[float, float],
    n_starts: int, rng: np.random.Generator,
) -> list[np.ndarray]:
    """Geometric spacing of k across the range, then seeded random log-widths."""
    n = len(assignment)
    k_first = load_range[0] / math.exp(_LOG_LO_PER_K)
    k_last = load_range[1] / math.exp(_LOG_HI_PER_K)
    k = np.geomspace(k_first, k_last, n) if n > 1 else np.array([math.sqrt(k_first * k_last)])
    starts = [np.log([s.width_um(ki) for s, ki in zip(assignment, k)])]
    bounds = np.array([admissible_widths(s, b) for s in assignment])
    for _ in range(max(n_starts - 1, 0)):
        u = rng.uniform(np.log(bounds[:, 0]), np.log(bounds[:, 1]))
        log_k = np.log([s.coefficient for s in assignment]) + 3 * u
        starts.append(u[np.argsort(log_k)])
    return starts

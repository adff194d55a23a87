"""When a solve of the identification NLP has converged, and what its status says.

Both solvers (:mod:`identify.fitting.gauss_newton`, :mod:`identify.fitting.ipopt`) stop on
the same statistical test: at a point that satisfies the continuity constraints, the full
Gauss–Newton step would move ½χ² by less than a small share of one unit of the noise the
data claim. The derivation of each tolerance is in ``docs/engineering-notes.md``.
"""

from __future__ import annotations

from enum import Enum

import numpy as np
import scipy.sparse as sp

from identify.fitting import kkt

# The statistical test (units: ½χ², i.e. the noise the data claim; µm of slip for the
# continuity constraints). Converged: feasible to FEAS_TOL, and the full Gauss–Newton
# step would move ½χ² by less than STAT_TOL (the parameters by < 0.015 σ).
STAT_TOL = 1e-4
FEAS_TOL = 1e-6  # 1 pm: above the arcs' integration noise, far below a plateau's precision
# Stalled: STALL_ITERS accepted iterations in a row that gain less than STAT_TOL. Converged
# within tolerance (STALLED) if the linearised problem's solution lies within STALL_TOL of
# ½χ² (parameters within ~0.14 σ) and the constraints hold to STALL_FEAS.
STALL_ITERS = 4
STALL_TOL = 0.01
STALL_FEAS = 1e-4
GIVE_UP_FEAS = 1e-3  # (µm) a give_up callback is asked only this close to continuity
PROGRESS_EVERY_S = 30.0  # a solve that runs longer reports its iterations this often
# A solve that only decides the next mode sequence stops at these looser tolerances: a
# sequence decision needs ½χ² to within a fraction of the unit by which it judges.
LOOSE_STAT_TOL = 0.25
LOOSE_FEAS_TOL = 1e-4


class Status(str, Enum):
    """How a solve ended. The value is the string a result's ``solver["status"]`` holds
    (Ipopt's own names where they mean the same)."""

    SOLVE_SUCCEEDED = "Solve_Succeeded"
    STALLED_WITHIN_TOLERANCE = "Stalled_Within_Tolerance"
    STALLED = "Stalled"
    LINE_SEARCH_FAILED = "Line_Search_Failed"
    MAXIMUM_ITERATIONS_EXCEEDED = "Maximum_Iterations_Exceeded"
    SINGULAR_KKT = "Singular_KKT"
    NOT_DIFFERENTIABLE = "Not_Differentiable"
    STOPPED_CANNOT_MATTER = "Stopped_Cannot_Matter"
    STUCK = "Stuck"


MESSAGES = {
    Status.SOLVE_SUCCEEDED: "converged: the full step would move ½χ² by less than the statistical tolerance "
                            "at a point that satisfies the continuity constraints",
    Status.STALLED_WITHIN_TOLERANCE: "converged within tolerance: progress stalled where the linearised problem's "
                                     "solution lies within 0.01 of ½χ² (parameters within ~0.14 σ)",
    Status.STALLED: "stalled away from a solution: steps gain nothing, but the linearised problem still "
                    "promises more than the tolerance",
    Status.LINE_SEARCH_FAILED: "no step along the search direction lowers the merit function",
    Status.MAXIMUM_ITERATIONS_EXCEEDED: "the iteration limit was reached first",
    Status.SINGULAR_KKT: "the linearised problem has no unique solution (a direction the data and the "
                         "constraints do not fix)",
    Status.NOT_DIFFERENTIABLE: "at the start, the last bit of a parameter moves the residuals by more than their "
                               "noise: no linearisation holds there",
    Status.STOPPED_CANNOT_MATTER: "stopped by its caller: the solve could no longer change the decision it served",
    Status.STUCK: "Ipopt's iterates stopped gaining at continuity while the linearisation still promised more "
                  "(and no iterations were left for the Gauss-Newton SQP)",
}
"""What each :class:`Status` means, for reports."""

SUCCESS = frozenset({Status.SOLVE_SUCCEEDED.value, Status.STALLED_WITHIN_TOLERANCE.value})
STALLED = Status.STALLED_WITHIN_TOLERANCE.value
GAVE_UP = Status.STOPPED_CANNOT_MATTER.value  # a solve its give_up callback stopped
NOT_DIFFERENTIABLE = Status.NOT_DIFFERENTIABLE.value


def message(status: str) -> str:
    """The meaning of a solver status (:data:`MESSAGES`; Ipopt's own statuses as they are)."""
    try:
        return MESSAGES[Status(status)]
    except ValueError:
        return f"Ipopt returned {status}"


def kkt_solve(H, Jg, grad, g, free):
    """Solution (step on ``free``, then multipliers) of the linearised least-squares
    problem's KKT system; RuntimeError when it is singular (sparse LU)."""
    K = sp.bmat([[H[free][:, free], Jg[:, free].T], [Jg[:, free], None]], format="csc")
    return kkt.solve(K, np.r_[-grad[free], -g])


BOUND_NEAR = 1e-6
"""A variable within this share of its range of a bound is at it for :func:`bounded_step`:
an interior-point iterate never reaches a bound (Ipopt left A at 9e-8 of its range of 100),
and a step that pushed it outwards there promised a gain beyond the bound (measured: ½χ²
920 on a baseline fitted without its load offset, where no step along it gained)."""


def bounded_step(H, Jg, grad, g, w, lbx, ubx, fixed_mask):
    """The step of the linearised problem (Hessian ``H``) with the variables at a bound
    the step pushes outwards held there: (d, multipliers, indices of the free
    variables); d None when the KKT system is singular."""
    span = np.where(np.isfinite(ubx - lbx), ubx - lbx, 0.0)
    near = np.maximum(BOUND_NEAR * span, 1e-12)
    at_lo, at_hi = w <= lbx + near, w >= ubx - near
    hold = fixed_mask | (at_lo & (grad > 0)) | (at_hi & (grad < 0))
    d, lam, free = None, None, np.nonzero(~hold)[0]
    for _ in range(20):
        free = np.nonzero(~hold)[0]
        try:
            sol = kkt_solve(H, Jg, grad, g, free)
        except RuntimeError:
            return None, None, free
        d = np.zeros(len(w))
        d[free] = sol[: len(free)]
        lam = sol[len(free):]
        out = ((at_lo & (d < 0)) | (at_hi & (d > 0))) & ~hold
        if not out.any():
            break
        hold |= out
    return d, lam, free


def say_iteration(prob, it: int, chi2: float, feas: float, elapsed_s: float) -> None:
    """A long solve's progress line (either solver, every :data:`PROGRESS_EVERY_S`)."""
    prob.progress(f"  iteration {it} of at most {prob.opts.max_iter}: χ² {chi2:.6g}, "
                  f"constraint violation {feas:.2e}, {elapsed_s:.0f} s")

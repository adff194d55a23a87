"""What one Gauss–Newton SQP solve (:meth:`identify.fitting.gauss_newton.GaussNewtonSQP.solve_gn`)
hands from step to step: :class:`SolveState`, which lasts from one iteration to the next,
and :class:`Iteration`, what one iteration computes at its point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["SolveState", "Iteration"]


@dataclass
class SolveState:
    """The solve as it stands: the point reached, its bounds, the merit's weights, the
    damping, the counters of the stall rules and the arcs' differences in use."""

    w: np.ndarray  # the point reached
    r: np.ndarray  # its residuals and constraints (those of the last evaluation there)
    g: np.ndarray
    lbx: np.ndarray
    ubx: np.ndarray
    fixed_mask: np.ndarray  # variables held (equal bounds)
    t0: float  # time.perf_counter() at the start
    said: float  # when the progress was last reported
    flat_tol: float  # the fall of ½χ² that resets the flat-tail count
    may_share: bool  # the arcs' forward differences may be shared (SHARE_TOL)
    nu: float | np.ndarray = 1.0  # the merit's weight of each constraint
    lm: float = 0.0  # the Levenberg–Marquardt damping of the parameter block
    status: str = "Maximum_Iterations_Exceeded"
    success: bool = False
    it: int = 0
    stalled: int = 0  # consecutive iterations that gained < stat_tol of merit
    flat: int = 0  # iterations at feasible points since ½χ² last fell by flat_tol
    flat_ref: float | None = None
    refreshed: bool = False  # the Jacobian was taken again on other differences (the result's central)
    own_check: bool = False  # the step is on the arcs' own differences after a shared one failed
    trusted: bool = False  # shared steps trusted far out (SHARE_FEAS)


@dataclass
class Iteration:
    """One iteration: the linearisation at the point, the Gauss–Newton step and what the
    convergence tests and the line search made of it."""

    r0: np.ndarray  # residuals, constraints and ½χ²'s gradient at the point
    g0: np.ndarray
    grad: np.ndarray
    Jr: object  # the Jacobians (sparse) and the Gauss–Newton Hessian, damped once the step is computed
    Jg: object
    H: object
    d: np.ndarray | None = None  # the step (a second-order correction's after the line search)
    lam: np.ndarray | None = None  # the constraints' multipliers
    free: np.ndarray | None = None  # the variables the step moves
    feas0: float = 0.0  # the largest constraint violation at the point
    stat_tol: float = 0.0  # the problem's tolerances, as read at this iteration
    feas_tol: float = 0.0
    dr: np.ndarray | None = None  # Jᵣ·d
    moves: float = 0.0  # ½‖Jᵣd‖²: how far the full step moves the model's ½χ²
    a_max: float = 1.0  # the longest step within the bounds
    phi0: float = 0.0  # the merit at the point and its slope along the step
    dphi: float = 0.0
    d_gn: np.ndarray | None = None  # the step before any correction
    a: float = 0.0  # the step length the line search ended at
    accepted: bool = False
    r1: np.ndarray | None = None  # residuals, constraints and merit at the trial point taken
    g1: np.ndarray | None = None
    phi1: float = 0.0
    tried: int = 0  # trial points the line search evaluated
    shared: bool = False  # whether the step was on shared differences

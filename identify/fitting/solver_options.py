"""The solvers' options: when a solve has converged (:class:`StopOptions`, both solvers),
how the Gauss–Newton SQP searches (:class:`GaussNewtonOptions`), and what Ipopt is told
(:class:`IpoptOptions`). They are fields of :class:`identify.fitting.options.FitOptions`
(``stop``, ``gauss_newton``, ``ipopt``); the defaults are the module constants of
:mod:`identify.fitting.convergence` and :mod:`identify.fitting.gauss_newton`, whose comments
say why each is what it is.

Units: ½χ² (one unit is the noise the data claim) and µm of slip for the continuity
constraints.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields

from identify.fitting.convergence import (
    FEAS_TOL,
    GIVE_UP_FEAS,
    LOOSE_FEAS_TOL,
    LOOSE_STAT_TOL,
    STALL_FEAS,
    STALL_ITERS,
    STALL_TOL,
    STAT_TOL,
)
from identify.fitting.gauss_newton import (
    CENTRAL_RESOLVE_FEAS,
    FLAT_ITERS,
    FLAT_PROMISE,
    LADDER_REACH,
    LADDER_STEP,
    NEAR_SHARE,
    NEAR_TOL,
)

__all__ = ["StopOptions", "GaussNewtonOptions", "IpoptOptions", "IPOPT_OWN"]


def _check_fields(obj, positive=(), non_negative=(), counts=()) -> None:
    """A ``ValueError`` naming the field and the rule it broke."""
    cls = type(obj).__name__
    for name in positive:
        value = getattr(obj, name)
        if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
            raise ValueError(f"{cls}.{name} = {value!r}: must be a finite number > 0")
    for name in non_negative:
        value = getattr(obj, name)
        if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
            raise ValueError(f"{cls}.{name} = {value!r}: must be a finite number >= 0")
    for name in counts:
        value = getattr(obj, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{cls}.{name} = {value!r}: must be an integer >= 0")


@dataclass(frozen=True)
class StopOptions:
    """When a solve of the identification NLP has converged (both solvers).

    Parameters
    ----------
    stat_tol : float
        Converged when, feasible to ``feas_tol``, the full Gauss–Newton step would move
        ½χ² by less than this.
    feas_tol : float
        Continuity (µm of slip) a converged point holds.
    stall_iters : int
        Accepted iterations in a row gaining less than ``stat_tol`` that make a stall.
    stall_tol, stall_feas : float
        A stall is converged within tolerance when the linearised problem's solution is
        within ``stall_tol`` of ½χ² and continuity holds to ``stall_feas`` µm.
    loose_stat_tol, loose_feas_tol : float
        The same test for the solves that only decide the next mode sequence.
    give_up_feas : float
        A caller's early-stop callback (``Problem.give_up``) is asked only this close to
        continuity (µm).
    """

    stat_tol: float = STAT_TOL
    feas_tol: float = FEAS_TOL
    stall_iters: int = STALL_ITERS
    stall_tol: float = STALL_TOL
    stall_feas: float = STALL_FEAS
    loose_stat_tol: float = LOOSE_STAT_TOL
    loose_feas_tol: float = LOOSE_FEAS_TOL
    give_up_feas: float = GIVE_UP_FEAS

    def __post_init__(self):
        _check_fields(self, positive=("stat_tol", "feas_tol", "stall_tol", "stall_feas", "loose_stat_tol",
                                      "loose_feas_tol", "give_up_feas"), counts=("stall_iters",))
        if self.stall_iters < 1:
            raise ValueError(f"StopOptions.stall_iters = {self.stall_iters!r}: must be an integer >= 1")


@dataclass(frozen=True)
class GaussNewtonOptions:
    """How the Gauss–Newton SQP (``solver="gauss-newton"``) searches and when its own
    rules end a solve (besides :class:`StopOptions`).

    Parameters
    ----------
    near_tol : float
        Converged also when, feasible to ``StopOptions.stall_feas``, the undamped step
        would move the model by less than this much ½χ²; 0 turns the rule off.
    near_share : float
        ... but never where the step would remove this share of ½χ² itself.
    flat_iters : int
        Converged within tolerance after this many iterations in a row at feasible points
        that did not lower ½χ² by ``StopOptions.stall_tol``; 0 turns the rule off.
    flat_promise : float
        ... judged only on undamped steps promising less than this much ½χ².
    ladder_reach, ladder_step : float
        The damping ladder ends at once when the rest of it could change what the step
        promises by less than ``ladder_reach`` of the merit's slope and move the trial
        points by less than ``ladder_step`` of the step; 0 turns the rule off.
    central_resolve_feas : float
        A solve that stalls on forward differences is solved once more on central ones
        only if it ended within this violation of continuity (µm).
    """

    near_tol: float = NEAR_TOL
    near_share: float = NEAR_SHARE
    flat_iters: int = FLAT_ITERS
    flat_promise: float = FLAT_PROMISE
    ladder_reach: float = LADDER_REACH
    ladder_step: float = LADDER_STEP
    central_resolve_feas: float = CENTRAL_RESOLVE_FEAS

    def __post_init__(self):
        _check_fields(self, positive=("near_share", "flat_promise", "central_resolve_feas"),
                      non_negative=("near_tol", "ladder_reach", "ladder_step"), counts=("flat_iters",))


IPOPT_OWN = frozenset({"max_iter", "tol", "hessian_approximation", "output_file", "file_print_level",
                       "print_level", "sb"})
"""Ipopt options the toolkit sets itself: ``FitOptions.max_iter`` and ``tol``, the
Gauss–Newton Hessian, and the iteration log it reads for the restoration iterations."""

_MU_STRATEGIES = ("monotone", "adaptive")


@dataclass(frozen=True)
class IpoptOptions:
    """What Ipopt (``solver="ipopt"``) is told besides the iteration limit and tolerance of
    :class:`identify.fitting.options.FitOptions`.

    Parameters
    ----------
    mu_strategy : {"monotone", "adaptive"}
        Ipopt's barrier-parameter update (its own default: monotone).
    extra : dict
        Further Ipopt options by Ipopt's own names (``{"linear_solver": "mumps"}``),
        passed as given; Ipopt checks them when the solver is built. The options the
        toolkit sets itself (:data:`IPOPT_OWN`) are refused.
    """

    mu_strategy: str = "monotone"
    extra: Mapping[str, object] = field(default_factory=dict)

    def __post_init__(self):
        if self.mu_strategy not in _MU_STRATEGIES:
            raise ValueError(f"IpoptOptions.mu_strategy = {self.mu_strategy!r}: choose 'monotone' or 'adaptive'")
        clash = sorted(set(dict(self.extra)) & IPOPT_OWN)
        if clash:
            raise ValueError(f"IpoptOptions.extra sets {', '.join(clash)}, which the toolkit sets itself "
                             "(FitOptions.max_iter and tol, the Gauss–Newton Hessian, the iteration log)")
        object.__setattr__(self, "extra", dict(self.extra))

    def nlpsol_options(self) -> dict:
        """The options of Ipopt's own dictionary this object sets."""
        return {"mu_strategy": self.mu_strategy, **self.extra}


SOLVER_FIELDS = {cls: tuple(f.name for f in fields(cls)) for cls in (StopOptions, GaussNewtonOptions, IpoptOptions)}

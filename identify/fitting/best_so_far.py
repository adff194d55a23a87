"""What an interrupted fit hands back: the best point it reached.

Every solve of a fit (the first, each mode-sequence round's, the spread starts', the
stick option's second fit) reports here when it ends, and the solve in progress keeps
its last iterate on its problem (``Problem.last_iterate``). :func:`watching` holds one
record for the outermost fit of a call, so a fit that calls another (the stick option
decided by likelihood) keeps one best across both.
"""

from __future__ import annotations

import contextlib
from contextvars import ContextVar

import numpy as np

__all__ = ["BestSoFar", "solved", "solving", "watching"]

_CURRENT: ContextVar[BestSoFar | None] = ContextVar("best_so_far", default=None)


class BestSoFar:
    """The lowest-χ² finished solve so far, and the problem being solved now."""

    def __init__(self):
        self.best: dict | None = None
        self.problem = None
        self.solves = 0
        self.n_runs = 0  # the fit's problems cover the most runs; a trial re-solves one run alone

    def counts(self, problem) -> bool:
        """Whether a solve of ``problem`` is one of the fit's own (all its runs), whose χ²
        compare; a larger problem than any seen before starts the record again."""
        n = len(getattr(problem, "runs", ()))
        if n > self.n_runs:
            self.n_runs, self.best, self.solves = n, None, 0
        return n == self.n_runs

    def point(self, problem, w, half_chi2: float, violation: float | None, status: str) -> dict:
        th = np.atleast_1d(problem.theta.from_scaled(np.asarray(w[: problem.n_theta], float)))
        # (the frame-level χ² the report gives: the compressed plateaus' constant added)
        chi2 = 2.0 * float(half_chi2) + float(problem.chi2_constant())
        return dict(parameters={n: float(v) for n, v in zip(problem.theta.names, th)},
                    chi2=chi2, max_violation_um=None if violation is None else float(violation),
                    solver_status=status)

    def saved(self) -> dict | None:
        """The best finished solve's point; else, if a solve was under way, its last
        iterate (not converged: it says so); else None."""
        if self.best is not None:
            return dict(self.best, what=f"the best of {self.solves} finished solve(s)")
        p = self.problem
        if p is not None and getattr(p, "last_iterate", None) is not None:
            w, f, feas = p.last_iterate
            if np.isfinite(f):
                return dict(self.point(p, w, f, feas, "interrupted"),
                            what="the first solve's last iterate (not converged)")
        return None


def solving(problem) -> None:
    """A solve of ``problem`` begins (its iterates are what is left if nothing finishes)."""
    rec = _CURRENT.get()
    if rec is not None and rec.counts(problem):
        rec.problem = problem


def solved(problem, res: dict) -> None:
    """A solve of ``problem`` ended with ``res`` (the solver's dict)."""
    rec = _CURRENT.get()
    if rec is None or not np.isfinite(res.get("f", np.inf)) or not rec.counts(problem):
        return
    rec.solves += 1
    if rec.best is None or 2.0 * res["f"] + problem.chi2_constant() < rec.best["chi2"]:
        # (the violation as the solver reports it: evaluating the point again would integrate
        # every arc once more, in every solve)
        rec.best = rec.point(problem, res["w"], res["f"], res.get("max_violation"), str(res.get("status", "?")))


@contextlib.contextmanager
def watching():
    """The record of the outermost fit under way (a nested fit shares it)."""
    rec = _CURRENT.get()
    if rec is not None:
        yield rec
        return
    rec = BestSoFar()
    token = _CURRENT.set(rec)
    try:
        yield rec
    finally:
        _CURRENT.reset(token)

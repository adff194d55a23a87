"""Ipopt on the identification NLP (``FitOptions(solver="ipopt")``): the Gauss–Newton Hessian
through ``hess_lag``, stopped by the same statistical test as the SQP
(:mod:`identify.fitting.convergence`), its iteration log read for the restoration
iterations. :class:`IpoptSolver` is mixed into :class:`identify.fitting.problem.Problem`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import tempfile
import time
import weakref

import casadi as ca
import numpy as np

from identify import interrupts
from identify.fitting import convergence
from identify.fitting.convergence import GAVE_UP, STALLED, Status, bounded_step, say_iteration

log = logging.getLogger(__name__)

IPOPT_MAX_ITER = 100_000
WARM = {"mu_init": 1e-6, "warm_start_init_point": "yes"}  # Ipopt's options for a solve from continuity
WARM_FEAS = 1e-4  # (µm) a start this close to continuity is warm (LOOSE_FEAS_TOL's value, not its option)
# Stuck: this many iterations in a row without progress, where progress is halving the
# smallest constraint violation seen (while above FEAS_TOL) or lowering ½χ² by the
# statistical tolerance among iterates within twice it. Measured: after 11 slips were
# inserted into a calibration fit, Ipopt's full steps cycled with period 4 (|g| 2e-2,
# 1e-2, 5e-3, 6e-3 µm; ½χ² 159-186) for 100 iterations at μ = 0.1; on a baseline fitted
# without its load offset (before convergence.BOUND_NEAR) it sat at |g| ~5e-9 µm, ½χ²
# unchanged, to the iteration limit. The SQP, whose line search must lower its ℓ1 merit
# at every step, takes over (Problem.solve).
STUCK_ITERS = 15
STUCK = Status.STUCK.value


class _IpoptLog:
    """Ipopt's iteration log in a temporary file, read for what CasADi's stats leave out:
    which iterations were restoration ones (Ipopt marks their number with an ``r``).
    Ipopt appends every solve of one nlpsol to the file; each solve reads its part."""

    _ROW = re.compile(r"^\s*\d+(r?)\s+[-+0-9.]")

    def __init__(self):
        fd, self.path = tempfile.mkstemp(prefix="nanofrictor-ipopt-", suffix=".log")
        os.close(fd)
        weakref.finalize(self, _unlink, self.path)

    def mark(self) -> int:
        try:
            return os.path.getsize(self.path)
        except OSError:
            return 0

    def restoration_iterations(self, mark: int) -> int:
        try:
            with open(self.path, errors="replace") as fh:
                fh.seek(mark)
                text = fh.read()
        except OSError:
            return 0
        return sum(1 for line in text.splitlines() if (m := self._ROW.match(line)) and m.group(1))


def _unlink(path: str) -> None:
    with contextlib.suppress(OSError):
        os.unlink(path)


class _IpoptConvergence(ca.Callback):
    """Ipopt's iteration callback: stops the solve where the Gauss–Newton SQP would
    call it converged (:meth:`Problem.solve_gn`'s statistical test): at a point
    feasible to ``feas_tol`` µm whose full Gauss–Newton step would move the model's
    predictions by less than ``stat_tol`` in ½χ² (the parameters by < 0.015 σ).

    The test needs the arcs' Jacobian at the iterate, which Ipopt asks for next anyway
    (the arcs' callback remembers it), so it costs one KKT solve per iteration.

    It also stops a solve that cannot matter to its caller (the problem's ``give_up``
    near continuity, ``give_up_far`` elsewhere, asked as the SQP asks them, with the
    gain the full Gauss–Newton step promises), and at the problem's current
    ``opts.max_iter``: read per solve, so that ``Problem.tuned(max_iter=…)`` holds
    without building Ipopt again."""

    def __init__(self, problem):
        ca.Callback.__init__(self)
        self.problem = problem
        self.nx, self.ng = problem.n_w, problem.n_g
        self.converged = self.status = self.best = None
        self.since = self.it = 0
        self.lbx = self.ubx = self.stat_tol = self.feas_tol = None  # (each solve's: start)
        self.construct("ipopt_convergence", {})

    def start(self, lbx, ubx, stat_tol: float, feas_tol: float):
        self.lbx, self.ubx, self.stat_tol, self.feas_tol = lbx, ubx, stat_tol, feas_tol
        self.converged, self.status = None, None
        self.best, self.since = None, 0  # best ½χ² so far; iterations since it fell by stat_tol
        self.least_feas, self.ref_f, self.idle = np.inf, np.inf, 0  # (the stuck rule's record)
        self.it = -1  # (Ipopt calls back at its iteration 0, the start, too)
        self.t0 = self.said = time.perf_counter()

    def get_n_in(self):
        return ca.nlpsol_n_out()

    def get_n_out(self):
        return 1

    def get_name_in(self, i):
        return ca.nlpsol_out(i)

    def get_name_out(self, i):
        return "ret"

    def get_sparsity_in(self, i):
        n = ca.nlpsol_out(i)
        size = {"x": self.nx, "lam_x": self.nx, "g": self.ng, "lam_g": self.ng, "f": 1}.get(n, 0)
        return ca.Sparsity.dense(size, 1)

    def eval(self, arg):
        if interrupts.pending():
            return [1]  # (Ipopt stops, User_Requested_Stop; the solve's caller raises the interrupt)
        try:
            return self._eval(arg)
        except KeyboardInterrupt:
            interrupts.note()
            return [1]

    def _eval(self, arg):
        self.it += 1
        w = np.array(arg[0], float).ravel()
        if self.it >= self.problem.opts.max_iter:
            self.converged, self.status = w, Status.MAXIMUM_ITERATIONS_EXCEEDED.value
            return [1]
        try:
            r, g, Jr, Jg = self.problem.evaluate(w, jac=True)
        except RuntimeError:
            return [0]
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(g))):
            return [0]
        feas = float(np.abs(g).max()) if g.size else 0.0
        half_chi2 = 0.5 * float(r @ r)
        self.problem.last_iterate = (w, half_chi2, feas)
        if getattr(self.problem, "progress", None) is not None and time.perf_counter() - self.said >= \
                convergence.PROGRESS_EVERY_S:
            self.said = time.perf_counter()
            say_iteration(self.problem, self.it, 2.0 * half_chi2, feas, self.said - self.t0)
        idle = self._idle(feas, half_chi2)
        if self._stops(arg, w, r, g, Jr, Jg, feas, half_chi2):
            return [1]
        if idle >= STUCK_ITERS:
            log.debug("Ipopt iterate: %d iterations without progress at |g| %.2e: stuck", idle, feas)
            self.converged, self.status = w, STUCK
            return [1]
        return [0]

    def _stops(self, arg, w, r, g, Jr, Jg, feas: float, half_chi2: float) -> bool:
        """Whether the solve ends at this iterate: converged, stalled within tolerance, or
        stopped by the caller's give_up (then ``converged`` and ``status`` say so)."""
        stop = self.problem.opts.stop
        ask = self._give_up_callback(feas < stop.give_up_feas)
        if feas >= self.feas_tol and ask is None:
            log.debug("Ipopt iterate: |g| %.2e", feas)
            return False
        d, _, _ = bounded_step((Jr.T @ Jr).tocsc(), Jg, Jr.T @ r, g, w, self.lbx, self.ubx, self.lbx == self.ubx)
        if d is None or not np.all(np.isfinite(d)):
            return False
        dr = Jr @ d
        moves = 0.5 * float(dr @ dr)
        if ask is not None and ask(self.it, half_chi2, -float(r @ dr + 0.5 * dr @ dr)):
            self.converged, self.status = w, GAVE_UP
            return True
        if feas >= self.feas_tol:
            return False
        log.debug("Ipopt iterate: |g| %.2e, the Gauss-Newton step moves 1/2 chi2 by %.3g", feas, moves)
        f = float(np.asarray(arg[1]).ravel()[0])
        if self.best is None or f < self.best - self.stat_tol:
            self.best, self.since = f, 0
        else:
            self.since += 1
        if moves < self.stat_tol:
            self.converged, self.status = w, "Solve_Succeeded"
            return True
        if self.since >= stop.stall_iters and feas < stop.stall_feas and moves < stop.stall_tol:
            # the iterates no longer gain and the linearisation puts the solution within
            # the stall tolerance: the SQP's Stalled_Within_Tolerance (a step along the
            # model crosses one of the arcs' kinks, where no line search gains)
            self.converged, self.status = w, STALLED
            return True
        return False

    def _idle(self, feas: float, half_chi2: float) -> int:
        """Iterations in a row without progress (:data:`STUCK_ITERS`), this one counted."""
        if feas < 0.5 * self.least_feas and self.least_feas > self.feas_tol:
            self.ref_f, self.idle = half_chi2, 0
        elif feas <= 2.0 * max(self.least_feas, self.feas_tol) and half_chi2 < self.ref_f - self.stat_tol:
            self.ref_f, self.idle = half_chi2, 0
        else:
            self.idle += 1
        self.least_feas = min(self.least_feas, feas)
        return self.idle

    def _give_up_callback(self, near: bool):
        """The caller's early stop to ask at this iterate, as the SQP asks it: ``give_up``
        near continuity, ``give_up_far`` elsewhere (or where there is no ``give_up``)."""
        prob = self.problem
        give_up = getattr(prob, "give_up", None)
        return give_up if give_up is not None and near else getattr(prob, "give_up_far", None)


class IpoptSolver:
    """Ipopt on the problem (mixed into it): built by :meth:`_build_ipopt`, run by
    :meth:`solve_ipopt`."""

    def _build_ipopt(self, w, r, g, Jr, Jg, opts) -> None:
        """The nlpsol over the problem's symbolic residuals and constraints (the warm one,
        for solves that start at continuity, is built from the same NLP when first needed)."""
        p = ca.MX.sym("p", 0)
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", self.n_g)
        f = 0.5 * ca.dot(r, r)
        oracle = dict(
            # dense: CasADi hands Ipopt a user grad_f's nonzeros as they are, so structural
            # zeros (a variable no residual depends on) would shift the later entries and
            # leave the last ones as whatever was in Ipopt's buffer
            grad_f=ca.Function("grad_f", [w, p], [f, ca.densify(ca.mtimes(Jr.T, r))], ["x", "p"], ["f", "grad_f_x"]),
            jac_g=ca.Function("jac_g", [w, p], [g, Jg], ["x", "p"], ["g", "jac_g_x"]),
            hess_lag=ca.Function("hess_lag", [w, p, lam_f, lam_g], [ca.triu(lam_f * ca.mtimes(Jr.T, Jr))],
                                 ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"]),
        )
        self._ipopt_test = _IpoptConvergence(self)
        self._ipopt_log = _IpoptLog()
        own = opts.ipopt.nlpsol_options()
        ipopt = {"print_level": 0, "sb": "yes", "tol": opts.tol, "hessian_approximation": "exact",
                 # (the iteration limit is the convergence callback's, read at each solve;
                 # Ipopt's own only bounds a callback that never answers)
                 "max_iter": IPOPT_MAX_ITER, **own,
                 # (the iteration log, for the restoration iterations: CasADi's stats do
                 # not say which iterations were restoration ones)
                 "output_file": self._ipopt_log.path, "file_print_level": 5}
        common = dict(oracle, print_time=False, calc_lam_p=False, calc_multipliers=False, error_on_fail=False,
                      iteration_callback=self._ipopt_test,
                      # (a trial point where an arc cannot be integrated gives NaN, which Ipopt
                      # answers by a shorter step: not a warning for the user's terminal)
                      show_eval_warnings=False)
        nlp = {"x": w, "f": f, "g": g}
        self.ipopt = ca.nlpsol("identify", "ipopt", nlp, dict(common, ipopt=ipopt))
        # A solve that starts at continuity (a re-solve after a sequence change, on other
        # differences or encodings, a profile's or a held magnitude's point) starts with a
        # small barrier parameter: from Ipopt's default 0.1 the barrier held the iterates
        # off the interval encoding's bounds, ½χ² 0.01-0.02 above the solution, to the
        # iteration limit (noiseless test set; with 1e-6 and a warm-start point: 18 iterations)
        warm = {k: v for k, v in WARM.items() if k not in own}
        self._ipopt_warm = None
        self._ipopt_warm_build = lambda: ca.nlpsol("identify_warm", "ipopt", nlp, dict(common, ipopt={**ipopt, **warm}))

    def solve_ipopt(self, w0, fixed=None, loose: bool = False) -> dict:
        """Ipopt (interior point, filter line search) on the Gauss–Newton Hessian, stopped
        by the SQP's own statistical test (:class:`_IpoptConvergence`): its KKT
        tolerance is on the gradient, which the arcs' integration noise keeps from
        falling below ~1e-3 (measured: after reaching ½χ² to 1e-5 in 5 iterations, it
        spent 95 more at inf_du 8.6e-4 with the line search taking steps of 1e-12)."""
        lbx, ubx = self.bounds(fixed)
        test = self._ipopt_test
        stop = self.opts.stop
        test.start(lbx, ubx, stop.loose_stat_tol if loose else stop.stat_tol,
                   stop.loose_feas_tol if loose else stop.feas_tol)
        t0 = time.perf_counter()
        mark = self._ipopt_log.mark()
        x0 = np.clip(w0, lbx, ubx)
        solver = self.ipopt
        if self._violation(x0) < WARM_FEAS:
            if self._ipopt_warm is None:
                self._ipopt_warm = self._ipopt_warm_build()
            solver = self._ipopt_warm
        sol = solver(x0=x0, lbx=lbx, ubx=ubx, lbg=0, ubg=0)
        interrupts.check()  # (Ipopt stopped on the interrupt its callback saw)
        st = solver.stats()
        restoration = self._ipopt_log.restoration_iterations(mark)
        status = st.get("return_status", "?")
        w = np.array(sol["x"]).ravel()
        success = bool(st.get("success", False))
        if test.converged is not None:
            # Ipopt stops after the callback with its last accepted iterate: the point tested
            w, status = test.converged, test.status
            success = status in ("Solve_Succeeded", STALLED)
        f = 0.5 * float(np.sum(self.residuals(w) ** 2))
        return dict(w=w, f=f, status=status, success=success, iterations=int(st.get("iter_count", -1)),
                    wall_s=time.perf_counter() - t0, solver="ipopt", ipopt_status=st.get("return_status", "?"),
                    shared=self._cb_jac_shared(),
                    restoration_iterations=restoration, warm=solver is not self.ipopt,
                    **({"loose": True} if loose else {}))

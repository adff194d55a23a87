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
from identify.fitting.convergence import STALLED, bounded_step

log = logging.getLogger(__name__)


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
    (the arcs' callback remembers it), so it costs one KKT solve per iteration."""

    def __init__(self, problem):
        ca.Callback.__init__(self)
        self.problem = problem
        self.nx, self.ng = problem.n_w, problem.n_g
        self.converged = self.status = self.best = None
        self.since = 0
        self.lbx = self.ubx = self.stat_tol = self.feas_tol = None  # (each solve's: start)
        self.construct("ipopt_convergence", {})

    def start(self, lbx, ubx, stat_tol: float, feas_tol: float):
        self.lbx, self.ubx, self.stat_tol, self.feas_tol = lbx, ubx, stat_tol, feas_tol
        self.converged, self.status = None, None
        self.best, self.since = None, 0  # best ½χ² so far; iterations since it fell by stat_tol

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
        w = np.array(arg[0], float).ravel()
        try:
            r, g, Jr, Jg = self.problem.evaluate(w, jac=True)
        except RuntimeError:
            return [0]
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(g))):
            return [0]
        feas = float(np.abs(g).max()) if g.size else 0.0
        self.problem.last_iterate = (w, 0.5 * float(r @ r), feas)
        if feas >= self.feas_tol:
            log.debug("Ipopt iterate: |g| %.2e", feas)
            return [0]
        d, _, _ = bounded_step((Jr.T @ Jr).tocsc(), Jg, Jr.T @ r, g, w, self.lbx, self.ubx, self.lbx == self.ubx)
        if d is None or not np.all(np.isfinite(d)):
            return [0]
        dr = Jr @ d
        moves = 0.5 * float(dr @ dr)
        log.debug("Ipopt iterate: |g| %.2e, the Gauss-Newton step moves 1/2 chi2 by %.3g", feas, moves)
        f = float(np.asarray(arg[1]).ravel()[0])
        if self.best is None or f < self.best - self.stat_tol:
            self.best, self.since = f, 0
        else:
            self.since += 1
        if moves < self.stat_tol:
            self.converged, self.status = w, "Solve_Succeeded"
            return [1]
        stop = self.problem.opts.stop
        if self.since >= stop.stall_iters and feas < stop.stall_feas and moves < stop.stall_tol:
            # the iterates no longer gain and the linearisation puts the solution within
            # the stall tolerance: the SQP's Stalled_Within_Tolerance (a step along the
            # model crosses one of the arcs' kinks, where no line search gains)
            self.converged, self.status = w, STALLED
            return [1]
        return [0]


class IpoptSolver:
    """Ipopt on the problem (mixed into it): built by :meth:`_build_ipopt`, run by
    :meth:`solve_ipopt`."""

    def _build_ipopt(self, w, r, g, Jr, Jg, opts) -> None:
        """The nlpsol over the problem's symbolic residuals and constraints."""
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
        self.ipopt = ca.nlpsol("identify", "ipopt", {"x": w, "f": f, "g": g}, dict(
            oracle, print_time=False, calc_lam_p=False, calc_multipliers=False, error_on_fail=False,
            iteration_callback=self._ipopt_test,
            ipopt={"print_level": 0, "sb": "yes", "max_iter": opts.max_iter, "tol": opts.tol,
                   "hessian_approximation": "exact", **opts.ipopt.nlpsol_options(),
                   # (the iteration log, for the restoration iterations: CasADi's
                   # stats do not say which iterations were restoration ones)
                   "output_file": self._ipopt_log.path, "file_print_level": 5},
        ))

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
        sol = self.ipopt(x0=np.clip(w0, lbx, ubx), lbx=lbx, ubx=ubx, lbg=0, ubg=0)
        interrupts.check()  # (Ipopt stopped on the interrupt its callback saw)
        st = self.ipopt.stats()
        restoration = self._ipopt_log.restoration_iterations(mark)
        status = st.get("return_status", "?")
        w = np.array(sol["x"]).ravel()
        success = bool(st.get("success", False))
        if test.converged is not None:
            # Ipopt stops after the callback with its last accepted iterate: the point tested
            w, status, success = test.converged, test.status, True
        f = 0.5 * float(np.sum(self.residuals(w) ** 2))
        return dict(w=w, f=f, status=status, success=success, iterations=int(st.get("iter_count", -1)),
                    wall_s=time.perf_counter() - t0, solver="ipopt", ipopt_status=st.get("return_status", "?"),
                    restoration_iterations=restoration, **({"loose": True} if loose else {}))

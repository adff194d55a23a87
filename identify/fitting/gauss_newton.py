"""The constrained Gauss–Newton SQP (generalised Gauss–Newton, Bock's method) that solves
the identification NLP by default: :class:`GaussNewtonSQP`, mixed into
:class:`identify.fitting.problem.Problem`. Its iteration (:meth:`GaussNewtonSQP.solve_gn`)
is a sequence of named steps over a :class:`identify.fitting.gn_state.SolveState`; the
merit, line search and damping ladder are in :mod:`identify.fitting.gn_line_search`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping

import numpy as np
import scipy.sparse as sp

from identify.fitting import convergence
from identify.fitting.arcs import SOLVE_REL_STEP
from identify.fitting.convergence import (
    FEAS_TOL,
    GAVE_UP,
    NOT_DIFFERENTIABLE,
    STALL_FEAS,
    STALL_TOL,
    STALLED,
    bounded_step,
    kkt_solve,
    say_iteration,
)
from identify.fitting.gn_line_search import MAX_SOC as MAX_SOC
from identify.fitting.gn_line_search import MeritLineSearch
from identify.fitting.gn_state import Iteration, SolveState

log = logging.getLogger(__name__)


# The damping ladder (a Levenberg–Marquardt term on the parameter block, raised after each
# rejected step) ends at once when the rest of it could change what the step promises by
# less than LADDER_REACH of the merit's slope along it, and the trial points would move by
# less than LADDER_STEP of the step: a step the constraints drive comes back the same at
# every damping (GaussNewtonSQP._damping_reach).
LADDER_REACH = 0.02
LADDER_STEP = 0.1
# Converged within tolerance once FLAT_ITERS iterations in a row at feasible points have
# not lowered ½χ² by STALL_TOL, judged only on undamped steps promising less than
# FLAT_PROMISE: there the model's promises are the arcs' Jacobian noise, not gains.
FLAT_ITERS = 4
FLAT_PROMISE = 0.1
# Converged also when, feasible to STALL_FEAS, the undamped step would move the model by
# less than NEAR_TOL of ½χ² (the parameters by < 0.045 σ) and ½χ² by less than STALL_TOL;
# and STAT_TOL's test only when the step would move the model by less than NEAR_SHARE of
# ½χ² itself (data fitted far below their noise, e.g. noiseless ones, have no tail of
# Jacobian noise, and a step that removes much of what is left is progress).
NEAR_TOL = 1e-3
NEAR_SHARE = 0.1
# A solve that stalls or fails its line search on forward differences is solved once more
# on central ones only if it ended within this violation of continuity (µm): further out
# it is the constraints' curvature, not the differences, that stops it.
CENTRAL_RESOLVE_FEAS = 1e-2
_NEXT, _END = "next iteration", "end of the solve"  # what a step of solve_gn says the loop does next


class GaussNewtonSQP(MeritLineSearch):
    """The Gauss–Newton SQP of the identification NLP (mixed into the problem).

    Its tolerances are the problem's options (``opts.stop``, ``opts.gauss_newton``:
    :mod:`identify.fitting.solver_options`); a candidate refit of the diagnosis builds its
    problem with its own (:mod:`identify.diagnosis.refit_solve`) and changes them for a
    block of solves with :meth:`identify.fitting.problem.Problem.tuned`.
    """

    # the same kind of callback, asked wherever give_up is not (away from continuity, or
    # when there is no give_up): a stop only when decisive
    give_up_far = None
    # (w, ½χ², largest constraint violation µm) where the solve in progress stands: what an
    # interrupted fit can still hand back
    last_iterate = None
    # (w, options, solution_gap's answer) at the last point it was asked for
    _gap_memo = None
    _loose = False  # the solve in progress stops at LOOSE_STAT_TOL, LOOSE_FEAS_TOL (solve(loose=True))

    def accurate_differences(self, res: dict, fixed: Mapping[int, float] | None = None) -> dict:
        """A solution ``res`` of :meth:`solve` that ended on shared forward differences
        (``SHARE_TOL``) solved on from there on the covariance's differences (central, at
        the secant step, shared only within it: :meth:`central_differences`), so that it
        is a solution of the problem and not of the sharing's approximation of it
        (usually within tolerance at once: one Jacobian more, which the covariance then
        finds remembered). The fit's last step (:func:`identify.fitting.driver.fit`); the solves
        that only decide (mode-sequence trials, loose solves) stop on shared ones.
        Measured: the noiseless test fit's interval solve ended 8e-4 off in τ on shared
        differences (see also NEAR_SHARE), 5.7e-5 after this step on each arc's own
        forward differences, 6.4e-5 on these (4.4e-5 since the merit's weights per
        constraint); on the 10-run speed set this step took 0.4 s against 2.1 s, the
        estimates the same to every printed digit."""
        if not res.get("shared") or not np.isfinite(res["f"]):
            return res
        self.central_differences()
        try:
            more = (self._ipopt_then_sqp(res["w"], fixed, False) if self.opts.solver == "ipopt"
                    else self._solve_gn_resolved(res["w"], fixed))
        except Exception as err:  # the shared solution stands
            log.info("the solve on the covariance's differences after a shared one failed: %s", err)
            return res
        finally:
            self.jacobian_scheme(self.opts.arc_jacobian, SOLVE_REL_STEP)
        spent = dict(iterations=res["iterations"] + more["iterations"], wall_s=res["wall_s"] + more["wall_s"])
        # (the rest of res, the fit's records of the mode sequence, carried)
        return {**res, **more, **spent} if np.isfinite(more["f"]) and (more["success"] or more["f"] <= res["f"]) \
            else {**res, **spent}

    def _solve_gn_resolved(self, w0: np.ndarray, fixed: Mapping[int, float] | None) -> dict:
        """:meth:`solve_gn`, and once more on central differences after a forward-difference stall."""
        try:
            res = self.solve_gn(w0, fixed)
        finally:
            self.jacobian_scheme(self.opts.arc_jacobian, SOLVE_REL_STEP)  # (solve_gn may switch)
        forward_failed = res["status"] in ("Stalled", "Line_Search_Failed") and self.opts.arc_jacobian == "forward"
        if forward_failed and (feas := self._violation(res["w"])) >= self.opts.gauss_newton.central_resolve_feas:
            log.debug("%s at |g| %.2e µm: no central-difference solve after it (CENTRAL_RESOLVE_FEAS)",
                      res["status"], feas)
        elif forward_failed:
            # forward differences carry O(h) and noise/h errors that central ones halve
            # or cancel: a stall on them, or a line search that found no step along
            # them (a Jacobian row wrong to first order: measured, the step's actual
            # slip-length change missed the predicted one by 6.5e-6 µm at α = 0.01 and
            # 7e-4 at α = 1 on a creeping arc), gets one more solve on the accurate Jacobian
            # (in the one line-search failure measured, that solve ended there too); kept
            # also after a solve that switched to them itself, as calibrated at 208716e
            # (whether it gains anything there, where the damping and the merit's weight
            # start afresh, was not measured; with the parameters held it repeats work);
            # only near continuity, where the differences can matter (CENTRAL_RESOLVE_FEAS)
            self.jacobian_scheme("central", SOLVE_REL_STEP)
            try:
                more = self.solve_gn(res["w"], fixed)
            except Exception as err:  # the stalled solution stands
                log.info("central-difference solve after a stall failed: %s", err)
                more = dict(f=np.inf, success=False, iterations=0, wall_s=0.0)
            finally:
                self.jacobian_scheme(self.opts.arc_jacobian, SOLVE_REL_STEP)
            its, wall = res["iterations"] + more["iterations"], res["wall_s"] + more["wall_s"]
            if more["success"] or more["f"] <= res["f"]:
                res = more
            res["iterations"], res["wall_s"] = its, wall
        return res

    def _violation(self, w) -> float:
        """max |g| at w (µm; the arcs there are remembered, so this costs little); inf if
        it cannot be evaluated."""
        try:
            g = self.evaluate(w)[1]
        except Exception:  # (then no re-solve either: the solve's own result stands)
            return float("inf")
        return float(np.abs(g).max()) if g.size else 0.0

    def solve_gn(self, w0: np.ndarray, fixed: Mapping[int, float] | None = None) -> dict:
        """Constrained Gauss–Newton SQP (generalised Gauss–Newton, Bock's method).

        Each iteration solves the KKT system of the linearised problem
        min ½‖r + Jᵣd‖² s.t. g + J_g d = 0 (sparse LU), parameters at an active bound
        held there, then backtracks on the ℓ1 merit ½‖r‖² + Σᵢ νᵢ|gᵢ| (each constraint
        weighted by 1.1× the largest of its own multipliers so far), no further than where
        the step could gain less than ``STAT_TOL`` (below, the merit's change is the arcs'
        integration noise); a full step the merit rejects first gets second-order
        corrections (:meth:`_second_order_correction`). A Levenberg–Marquardt term on
        the parameter block is switched on only when the line search fails (flat
        directions) and decays after good steps.
        Converged when the relative parameter step, the constraint violation and the merit
        change are all below ``tol``, or when the full undamped step would move ½χ²'s
        quadratic model by less than ``STAT_TOL`` (½‖Jᵣd‖²) at a feasible point (a damped
        step that would is judged by the stall rule on the undamped one).
        A solve that gains less than ``STAT_TOL`` in ``STALL_ITERS`` accepted iterations
        in a row stops: ``Stalled_Within_Tolerance`` (a success) if the constraints hold
        to ``STALL_FEAS`` and the linearised problem's solution is within ``STALL_TOL``
        of ½χ² of the point reached (on the undamped step, if the last was damped), else
        ``Stalled``. A solve whose ½χ² has not fallen by ``STALL_TOL`` in ``FLAT_ITERS``
        iterations, accepted or rejected, at points feasible to ``feas_tol`` stops as
        ``Stalled_Within_Tolerance``. A solve whose line search finds no step even at
        the largest damping, or once no further damping could change the step (``ladder_reach``,
        :meth:`_damping_reach`), is judged the same way on its undamped step
        (``Stalled_Within_Tolerance``, else ``Line_Search_Failed``). A rejected step
        whose undamped Gauss–Newton step promises less than ``STALL_TOL`` at a point
        feasible to ``STALL_FEAS`` is judged so at once. A step from a point feasible to
        ``feas_tol`` on forward-difference arcs that the line search rejects is first
        computed again on central ones at the same point, which the rest of the solve
        keeps (the result's ``central``). Forward differences shared among nearly equal
        arcs (``SHARE_TOL``, among the arcs within ``SHARE_FEAS`` of continuity) come before:
        a full step on them that fails is computed again on each arc's own; if that step
        needs the line search as well, the sharing resumes, its failed full steps then
        backtracked like any other while the largest violation is at least ``SHARE_FEAS``
        (the result's ``shared``: whether its last Jacobian was shared).
        """
        st = self._gn_start(w0, fixed)
        for it in range(1, self.opts.max_iter + 1):
            st.it = it
            step = self._linearise(st)
            if step is None:  # (NOT_DIFFERENTIABLE)
                break
            then = self._gn_step(st, step)
            if then == _END:
                break
            if then == _NEXT:
                continue
            if self._ends_before_search(st, step):
                break
            self._merit(st, step)
            self._line_search(st, step)
            if self._retake_on_other_differences(st, step):
                continue
            if not step.accepted:
                if self._climb_damping(st, step):
                    break
                continue
            if self._take_step(st, step):
                break
        return dict(w=st.w, f=0.5 * float(st.r @ st.r), status=st.status, success=st.success, iterations=st.it,
                    wall_s=time.perf_counter() - st.t0, central=st.refreshed, shared=self._cb_jac_shared(),
                    max_violation=float(np.abs(st.g).max()) if st.g.size else 0.0)

    def _gn_start(self, w0: np.ndarray, fixed: Mapping[int, float] | None) -> SolveState:
        """The solve's start: ``w0`` clipped to the bounds (a fixed variable held by equal
        ones), evaluated there, the merit's weight 1 and no damping."""
        t0 = time.perf_counter()
        lbx, ubx = self.bounds(fixed)
        w = np.clip(np.asarray(w0, float), lbx, ubx)
        # (never looser than STALL_TOL: a candidate's stall_tol of a likelihood unit is for
        # its Δnll, and a named candidate's estimates come from where its refit ends)
        flat_tol = min(self.opts.stop.stall_tol, STALL_TOL)
        may_share = self._cb_jac_shared()
        r, g = self.evaluate(w)
        return SolveState(w=w, r=r, g=g, lbx=lbx, ubx=ubx, fixed_mask=lbx == ubx, t0=t0, said=t0, flat_tol=flat_tol,
                          may_share=may_share)

    def _linearise(self, st: SolveState) -> Iteration | None:
        """The residuals, constraints and their Jacobians at the point (the arcs' differences
        shared near continuity, where they may be); None where the last bit of a parameter
        moves the residuals by more than their noise at the start (NOT_DIFFERENTIABLE)."""
        n_th = self.n_theta
        self.last_iterate = (st.w, 0.5 * float(st.r @ st.r), float(np.abs(st.g).max()) if st.g.size else 0.0)
        if st.may_share:  # (SHARE_FEAS, per arc)
            self.jacobian_scheme("forward", SOLVE_REL_STEP, share=self.near_continuity(st.g))
        r, g, Jr, Jg = self.evaluate(st.w, jac=True)
        st.r, st.g = r, g
        step = Iteration(r0=r, g0=g, grad=Jr.T @ r, Jr=Jr, Jg=Jg, H=(Jr.T @ Jr).tocsc())
        rough = np.sqrt(step.H.diagonal()[:n_th]) * np.maximum(np.abs(st.w[:n_th]), 1.0) * np.finfo(float).eps
        rough[st.fixed_mask[:n_th]] = 0.0  # (a held parameter takes no step)
        if st.it == 1 and n_th and rough.max() > 1.0:
            # (NOT_DIFFERENTIABLE) the last bit of a parameter moves the residuals by
            # more than their noise: no linearisation holds here
            j = int(np.argmax(rough))
            log.debug("GN it 1: the last bit of %s moves the residuals by %.2g σ: %s", self.theta.names[j],
                      rough[j], NOT_DIFFERENTIABLE)
            st.status = NOT_DIFFERENTIABLE
            return None
        return step

    def _gn_step(self, st: SolveState, step: Iteration) -> str | None:
        """The Gauss–Newton step of the linearised problem, parameters at an active bound
        held, the Levenberg–Marquardt term on the parameter block when damped. A singular
        KKT system raises the damping instead: the next iteration, or the end past 1e8."""
        n_th = self.n_theta
        H = step.H
        if st.lm > 0:
            diagH = np.maximum(H.diagonal()[:n_th], 1e-12)
            H = H + sp.diags(np.r_[st.lm * diagH, np.zeros(self.n_w - n_th)])
        d, lam, free = bounded_step(H, step.Jg, step.grad, st.g, st.w, st.lbx, st.ubx, st.fixed_mask)
        if d is None or not np.all(np.isfinite(d)):
            st.lm = max(10 * st.lm, 1e-3)
            if st.lm > 1e8:
                st.status = "Singular_KKT"
                return _END
            return _NEXT
        step.H, step.d, step.lam, step.free = H, d, lam, free
        return None

    def _ends_before_search(self, st: SolveState, step: Iteration) -> bool:
        """Whether the solve ends at the point before its line search: converged at the
        step, flat for FLAT_ITERS iterations, or given up by its caller."""
        return self._converged_at_step(st, step) or self._flat_tail(st, step) or self._gave_up(st, step)

    def _converged_at_step(self, st: SolveState, step: Iteration) -> bool:
        """Whether the full step would move the model's ½χ² by less than the tolerance at a
        feasible point (tight, NEAR_TOL or loose); a damped step is judged as a stall."""
        # statistically converged: at a feasible point the full Gauss–Newton step
        # would move the model's predictions by ½‖Jᵣd‖² < stat_tol in ½χ² (the
        # parameters by < 0.015 σ in any direction). The relative-step test below can
        # wait for ever when finite-difference arc Jacobians are noisy. Not the step's
        # predicted gain −½∇f·d = ½‖Jᵣd‖² − ½λᵀg: at feasibility within the arcs'
        # integration noise (|g| ~ 0.1 pm, λ ~ 3e4 per µm of slip) its λᵀg term is that
        # noise times the multipliers, up to a few hundredths of ½χ², which no step
        # can remove. Measured on the 5-run speed benchmark: 566 → 435 s, the same
        # estimates (its first solve stopped at iteration 10, where the step moved the
        # model by 9e-6 of ½χ² and promised 2e-4, instead of 13).
        it, lm, g, d, grad, r0 = st.it, st.lm, st.g, step.d, step.grad, step.r0
        feas0 = float(np.abs(g).max()) if g.size else 0.0
        stat_tol, feas_tol = self.opts.stop.stat_tol, self.opts.stop.feas_tol
        dr = step.Jr @ d
        moves = 0.5 * float(dr @ dr)
        step.feas0, step.stat_tol, step.feas_tol, step.dr, step.moves = feas0, stat_tol, feas_tol, dr, moves
        log.debug("GN it %d: step moves 1/2 chi2 by %.3g, promises %.3g, |g| %.2e", it, moves,
                  -0.5 * float(grad @ d), feas0)
        # (min: a problem whose own stall tolerances are looser, a candidate refit's,
        # is not loosened further by this rule)
        # (none of these where the step would remove a good share of what is left of
        # ½χ² itself: NEAR_SHARE)
        gn, stop = self.opts.gauss_newton, self.opts.stop
        real = moves >= gn.near_share * 0.5 * float(r0 @ r0)
        near = (gn.near_tol > 0 and lm == 0 and feas0 < min(stop.stall_feas, STALL_FEAS) and not real
                and moves < max(gn.near_tol, stat_tol)
                and abs(float(grad @ d) + moves) < min(stop.stall_tol, STALL_TOL))
        # (and, as for NEAR_TOL, ½χ²'s own change along the step, restoring continuity
        # included, within the tolerance: moves alone leaves out λᵀg)
        loose = (self._loose and lm == 0 and feas0 < stop.loose_feas_tol and moves < stop.loose_stat_tol
                 and abs(float(grad @ d) + moves) < stop.loose_stat_tol)
        tight = feas0 < feas_tol and moves < stat_tol and not real
        if not (tight or near or loose):
            return False
        if loose and not near and not tight:
            log.debug("GN it %d: converged to the loose tolerances at |g| %.2e", it, feas0)
        elif not tight:
            log.debug("GN it %d: converged within NEAR_TOL at |g| %.2e", it, feas0)
        if lm > 0:
            # a damped step's prediction is short along the flat directions: the
            # damping grew because steps failed, so the solve has stopped gaining,
            # not converged; judged as a stall on the undamped step
            st.status, st.success = self._stalled_undamped(it, r0, step.Jr, step.Jg, grad, g, step.free, "Stalled")
        else:
            st.status, st.success = "Solve_Succeeded", True
        return True

    def _flat_tail(self, st: SolveState, step: Iteration) -> bool:
        """Whether ½χ² has not fallen by flat_tol for FLAT_ITERS iterations at feasible
        points, the last an undamped step promising less than FLAT_PROMISE (a stall within
        tolerance); the count starts again away from feasibility."""
        feas_tol = step.feas_tol
        gn = self.opts.gauss_newton
        if gn.flat_iters and step.feas0 < min(feas_tol, FEAS_TOL):
            # (FLAT_ITERS) every iteration counts here, accepted or rejected (a point
            # taken again on central differences too: its new Jacobian is a new try)
            f_now = 0.5 * float(step.r0 @ step.r0)
            if st.flat_ref is None or f_now < st.flat_ref - st.flat_tol:
                st.flat_ref, st.flat = f_now, 0
            else:
                st.flat += 1
                # ... and only on an undamped step that itself promises little: the
                # gain the linearisation still sees is then below FLAT_PROMISE
                if st.flat >= gn.flat_iters and st.lm == 0 and step.moves < gn.flat_promise:
                    log.debug("GN it %d: ½χ² %.8g within %.2g of %.8g for %d iterations at |g| < %.0e: %s",
                              st.it, f_now, st.flat_tol, st.flat_ref, st.flat, feas_tol, STALLED)
                    st.status, st.success = STALLED, True
                    return True
        else:
            st.flat, st.flat_ref = 0, None  # ("in a row": at feasible points only)
        return False

    def _gave_up(self, st: SolveState, step: Iteration) -> bool:
        """Whether the caller's give_up (near continuity; give_up_far elsewhere) stops the
        solve at an undamped step (GAVE_UP): the rest cannot matter to it."""
        near = step.feas0 < self.opts.stop.give_up_feas
        ask = self.give_up if self.give_up is not None and near else self.give_up_far
        r0, dr = step.r0, step.dr
        if st.lm == 0 and ask is not None and ask(st.it, 0.5 * float(r0 @ r0), -float(r0 @ dr + 0.5 * dr @ dr)):
            st.status = GAVE_UP
            return True
        return False

    def _retake_on_other_differences(self, st: SolveState, step: Iteration) -> bool:
        """Whether a step the line search rejected is computed again at the same point on
        other differences (shared ones: each arc's own; forward ones at a feasible point:
        central), which the rest of the solve keeps."""
        rejected = not step.accepted and step.tried
        if not (rejected and (step.shared or step.feas0 < step.feas_tol and self._cb_jac_forward())):
            return False
        # a step from a feasible point on forward differences that no line search
        # accepts: their O(h) error is first-order in the step. Measured in the
        # tail of the 10-run speed benchmark's first solve: the trial points'
        # constraint violation grew in proportion to α (0.8 pm at 1/16, 7 pm at 1;
        # the ℓ1 term then outweighs ½χ²'s gain), and the step on central
        # differences at the same point promised 0.0038, not 0.0157. The rest of
        # the solve takes central ones (the damping ladder on forward ones had
        # climbed for ten iterations). Away from feasibility the constraints'
        # curvature is the usual cause (the second-order correction's case): a
        # diagnosis test's load-offset refit, crawling at α ~0.02 with |g| ~1e-3 µm,
        # switched there and stalled 1e-3 µm off its constraints, not 3e-5.
        # Differences shared among nearly equal arcs (SHARE_TOL) err in the same way,
        # and more: a full step on them that fails, at any distance from continuity,
        # is taken again on each arc's own forward differences, for the rest of
        # the solve (measured: on noiseless data, from 10 % off, shared ones crawled
        # at α ~0.03 with the second-order correction failing, to the iteration limit)
        shared = step.shared
        log.debug("GN it %d rejected on %s forward differences: the arcs' Jacobian again, %s", st.it,
                  "shared" if shared else "the arcs' own", "unshared" if shared else "central")
        self.jacobian_scheme("forward" if shared else "central", SOLVE_REL_STEP, share=False)
        st.may_share, st.own_check = False, shared
        st.refreshed = True
        return True

    def _take_step(self, st: SolveState, step: Iteration) -> bool:
        """The accepted step taken (sharing resumed when the arcs' own differences needed
        the line search too, the damping decayed, the progress reported); whether the
        solve then ends (:meth:`_ends_after_step`)."""
        n_th = self.n_theta
        a, d = step.a, step.d
        step_th = float(np.max(np.abs(a * d[:n_th]))) if n_th else 0.0
        st.w, st.r, st.g = st.w + a * d, step.r1, step.g1
        if st.own_check:
            st.own_check = False
            if (a < step.a_max or st.lm > 0) and self.opts.share_arc_jacobian:
                # each arc's own differences needed the line search too: the
                # constraints' curvature, not the sharing, had stopped the full step
                st.may_share, st.trusted = True, True
                log.debug("GN it %d: on the arcs' own differences a step of %.2g: sharing again", st.it, a)
        lm_step, st.lm = st.lm, (st.lm / 10 if st.lm > 1e-3 else 0.0)
        feas = float(np.abs(st.g).max()) if st.g.size else 0.0
        log.debug("GN it %d: f %.8g |g| %.2e dθ %.2e α %.2g lm %.1e", st.it, 0.5 * st.r @ st.r, feas, step_th, a,
                  st.lm)
        self._report_progress(st, feas)
        return self._ends_after_step(st, step, step_th, feas, lm_step)

    def _report_progress(self, st: SolveState, feas: float) -> None:
        """The iteration, χ² and constraint violation to ``progress``, every
        PROGRESS_EVERY_S of a long solve."""
        if self.progress is not None and time.perf_counter() - st.said >= convergence.PROGRESS_EVERY_S:
            st.said = time.perf_counter()
            say_iteration(self, st.it, float(st.r @ st.r), feas, st.said - st.t0)

    def _ends_after_step(self, st: SolveState, step: Iteration, step_th: float, feas: float, lm_step: float) -> bool:
        """Whether the solve ends after a step taken: converged (relative step, violation
        and merit change below ``tol``), or stalled STALL_ITERS steps in a row (judged on
        the undamped step when the last was damped)."""
        opts = self.opts
        phi0, phi1 = step.phi0, step.phi1
        if step_th < opts.tol and feas < step.feas_tol and abs(phi0 - phi1) <= opts.tol * (1 + phi0):
            st.status, st.success = "Solve_Succeeded", True
            return True
        st.stalled = st.stalled + 1 if phi0 - phi1 < step.stat_tol else 0
        if st.stalled >= self.opts.stop.stall_iters:
            if lm_step > 0:  # judged on the undamped step, as a damped convergence is
                st.status, st.success = self._stalled_undamped(st.it, step.r0, step.Jr, step.Jg, step.grad, step.g0,
                                                               step.free, "Stalled")
            else:
                st.status, st.success = self._stalled(st.it, step.r0, step.Jr, step.d_gn, st.g, damped=False)
            return True
        return False

    def _stalled_undamped(self, it, r, Jr, Jg, grad, g, free, failed: str) -> tuple[str, bool]:
        """:meth:`_stalled` on the undamped Gauss–Newton step at the point reached;
        ``failed`` is the status when that does not hold either."""
        try:
            d0 = np.zeros(self.n_w)
            d0[free] = kkt_solve((Jr.T @ Jr).tocsc(), Jg, grad, g, free)[: len(free)]
        except RuntimeError:
            return failed, False
        status, success = self._stalled(it, r, Jr, d0, g, damped=False)
        return (status, True) if success else (failed, False)

    def solution_gap(self, w: np.ndarray) -> dict:
        """How far a point a solve stopped at lies from the solution its linearisation
        predicts, for the report of a solve that did not converge: ``half_chi2``, the ½χ²
        between here and the Gauss–Newton model's feasible stationary point (on central
        arc differences, as the covariance; the parameters then within about
        √(2·half_chi2) standard errors of it in any direction), and ``continuity_um``,
        the largest continuity violation here. ``half_chi2`` NaN where that model has no
        solution (a singular KKT system). Remembered for the last point and options asked:
        the fit's second opinion, its spread check and its result each ask at the same
        point, and each answer costs central differences of every arc."""
        w = np.asarray(w, float)
        memo = getattr(self, "_gap_memo", None)
        if memo is not None and memo[1] is self.opts and np.array_equal(memo[0], w):
            return dict(memo[2])
        gap = self._solution_gap(w)
        self._gap_memo = (w.copy(), self.opts, dict(gap))
        return gap

    def _solution_gap(self, w: np.ndarray) -> dict:
        self.central_differences()
        r, g, Jr, Jg = self.evaluate(w, jac=True)
        lbx, ubx = self.bounds()
        d, _, _ = bounded_step((Jr.T @ Jr).tocsc(), Jg, Jr.T @ r, g, np.asarray(w, float), lbx, ubx, lbx == ubx)
        feas = float(np.abs(g).max()) if g.size else 0.0
        if d is None or not np.all(np.isfinite(d)):
            return dict(half_chi2=float("nan"), continuity_um=feas)
        dr = Jr @ d
        return dict(half_chi2=abs(float(r @ dr + 0.5 * dr @ dr)), continuity_um=feas)

    def _stalled(self, it, r, Jr, d, g, damped: bool) -> tuple[str, bool]:
        """Status of a solve whose accepted steps no longer gain: the functions do not
        give what the linearisation predicts (finite-difference arc rows that are wrong
        where an arc sits on a kink or in its integration noise). Within tolerance
        if the constraints hold to ``STALL_FEAS`` and the Gauss–Newton model puts ½χ² at
        its feasible stationary point within ``STALL_TOL`` of its value here
        (½‖r + J d‖² − ½‖r‖² for the full step d); never when the step was damped, whose
        prediction is short along the flat directions."""
        dr = Jr @ d
        left = abs(float(r @ dr + 0.5 * dr @ dr))
        feas = float(np.abs(g).max()) if g.size else 0.0
        log.debug("GN it %d: stalled at |g| %.2e, 1/2 chi2 %.3g from the model's solution%s",
                  it, feas, left, " (damped step)" if damped else "")
        ok = not damped and feas < self.opts.stop.stall_feas and left < self.opts.stop.stall_tol
        return (STALLED, True) if ok else ("Stalled", False)

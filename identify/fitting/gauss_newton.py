"""The constrained Gauss–Newton SQP (generalised Gauss–Newton, Bock's method) that solves
the identification NLP by default: :class:`GaussNewtonSQP`, mixed into
:class:`identify.fitting.problem.Problem`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping

import numpy as np
import scipy.sparse as sp

from identify.fitting.arcs import SHARE_FEAS, SOLVE_REL_STEP
from identify.fitting.convergence import (
    FEAS_TOL,
    GAVE_UP,
    GIVE_UP_FEAS,
    LOOSE_FEAS_TOL,
    LOOSE_STAT_TOL,
    NOT_DIFFERENTIABLE,
    STALL_FEAS,
    STALL_ITERS,
    STALL_TOL,
    STALLED,
    STAT_TOL,
    bounded_step,
    kkt_solve,
)

log = logging.getLogger(__name__)


# The damping ladder (a Levenberg–Marquardt term on the parameter block, raised after each
# rejected step) ends at once when the rest of it could change what the step promises by
# less than LADDER_REACH of the merit's slope along it, and the trial points would move by
# less than LADDER_STEP of the step: a step the constraints drive comes back the same at
# every damping (GaussNewtonSQP._damping_reach).
LADDER_REACH = 0.02
LADDER_STEP = 0.1
MAX_SOC = 4  # second-order corrections tried for a rejected full step (as Ipopt's max_soc)
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
PROGRESS_EVERY_S = 30.0  # a solve that runs longer reports its iterations this often


def _l1(nu, g) -> float:
    """The ℓ1 merit's constraint term Σᵢ νᵢ|gᵢ| (ν one weight, or one per constraint)."""
    return float(np.sum(nu * np.abs(g)))


class GaussNewtonSQP:
    """The Gauss–Newton SQP of the identification NLP (mixed into the problem).

    Its tolerances are class attributes, from the module's constants; a candidate refit of
    the diagnosis overrides them on its problem instance
    (:mod:`identify.diagnosis.candidates`).
    """

    stat_tol, feas_tol = STAT_TOL, FEAS_TOL
    ladder_reach, ladder_step = LADDER_REACH, LADDER_STEP
    stall_tol, stall_feas = STALL_TOL, STALL_FEAS
    near_tol = NEAR_TOL
    give_up_feas = GIVE_UP_FEAS  # the give_up callback is asked only this close to continuity (µm)
    flat_iters = FLAT_ITERS  # (0: the rule off)
    # the same kind of callback, asked wherever give_up is not (away from continuity, or
    # when there is no give_up): a stop only when decisive
    give_up_far = None
    # (w, ½χ², largest constraint violation µm) where the solve in progress stands: what an
    # interrupted fit can still hand back
    last_iterate = None
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
            more = self._solve_gn_resolved(res["w"], fixed)
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
        if forward_failed and (feas := self._violation(res["w"])) >= CENTRAL_RESOLVE_FEAS:
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
        opts = self.opts
        t0 = time.perf_counter()
        lbx, ubx = self.bounds(fixed)
        w = np.clip(np.asarray(w0, float), lbx, ubx)
        fixed_mask = lbx == ubx
        n_th = self.n_theta
        nu, lm = 1.0, 0.0  # (nu: the merit's weight of each constraint, below)
        status, success, it = "Maximum_Iterations_Exceeded", False, 0
        said = t0
        stalled = 0  # consecutive iterations that gained < stat_tol of merit
        flat, flat_ref = 0, None  # iterations at feasible points since ½χ² last fell by flat_tol
        # (never looser than STALL_TOL: a candidate's stall_tol of a likelihood unit is for
        # its Δnll, and a named candidate's estimates come from where its refit ends)
        flat_tol = min(self.stall_tol, STALL_TOL)
        refreshed = False
        may_share = self._cb_jac_shared()
        own_check, trusted = False, False  # (shared steps trusted far out: see SHARE_FEAS)
        r, g = self.evaluate(w)
        for it in range(1, opts.max_iter + 1):
            self.last_iterate = (w, 0.5 * float(r @ r), float(np.abs(g).max()) if g.size else 0.0)
            if may_share:  # (SHARE_FEAS, per arc)
                self.jacobian_scheme("forward", SOLVE_REL_STEP, share=self.near_continuity(g))
            r, g, Jr, Jg = self.evaluate(w, jac=True)
            r0, g0, grad = r, g, Jr.T @ r
            H = (Jr.T @ Jr).tocsc()
            rough = np.sqrt(H.diagonal()[:n_th]) * np.maximum(np.abs(w[:n_th]), 1.0) * np.finfo(float).eps
            rough[fixed_mask[:n_th]] = 0.0  # (a held parameter takes no step)
            if it == 1 and n_th and rough.max() > 1.0:
                # (NOT_DIFFERENTIABLE) the last bit of a parameter moves the residuals by
                # more than their noise: no linearisation holds here
                j = int(np.argmax(rough))
                log.debug("GN it 1: the last bit of %s moves the residuals by %.2g σ: %s", self.theta.names[j],
                          rough[j], NOT_DIFFERENTIABLE)
                status = NOT_DIFFERENTIABLE
                break
            if lm > 0:
                diagH = np.maximum(H.diagonal()[:n_th], 1e-12)
                H = H + sp.diags(np.r_[lm * diagH, np.zeros(self.n_w - n_th)])
            d, lam, free = bounded_step(H, Jg, grad, g, w, lbx, ubx, fixed_mask)
            if d is None or not np.all(np.isfinite(d)):
                lm = max(10 * lm, 1e-3)
                if lm > 1e8:
                    status = "Singular_KKT"
                    break
                continue
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
            feas0 = float(np.abs(g).max()) if g.size else 0.0
            stat_tol, feas_tol = self.stat_tol, self.feas_tol
            dr = Jr @ d
            moves = 0.5 * float(dr @ dr)
            log.debug("GN it %d: step moves 1/2 chi2 by %.3g, promises %.3g, |g| %.2e", it, moves,
                      -0.5 * float(grad @ d), feas0)
            # (min: a problem whose own stall tolerances are looser, a candidate refit's,
            # is not loosened further by this rule)
            # (none of these where the step would remove a good share of what is left of
            # ½χ² itself: NEAR_SHARE)
            real = moves >= NEAR_SHARE * 0.5 * float(r0 @ r0)
            near = (self.near_tol > 0 and lm == 0 and feas0 < min(self.stall_feas, STALL_FEAS) and not real
                    and moves < max(self.near_tol, stat_tol)
                    and abs(float(grad @ d) + moves) < min(self.stall_tol, STALL_TOL))
            # (and, as for NEAR_TOL, ½χ²'s own change along the step, restoring continuity
            # included, within the tolerance: moves alone leaves out λᵀg)
            loose = (self._loose and lm == 0 and feas0 < LOOSE_FEAS_TOL and moves < LOOSE_STAT_TOL
                     and abs(float(grad @ d) + moves) < LOOSE_STAT_TOL)
            tight = feas0 < feas_tol and moves < stat_tol and not real
            if tight or near or loose:
                if loose and not near and not tight:
                    log.debug("GN it %d: converged to the loose tolerances at |g| %.2e", it, feas0)
                elif not tight:
                    log.debug("GN it %d: converged within NEAR_TOL at |g| %.2e", it, feas0)
                if lm > 0:
                    # a damped step's prediction is short along the flat directions: the
                    # damping grew because steps failed, so the solve has stopped gaining,
                    # not converged; judged as a stall on the undamped step
                    status, success = self._stalled_undamped(it, r0, Jr, Jg, grad, g, free, "Stalled")
                else:
                    status, success = "Solve_Succeeded", True
                break
            if self.flat_iters and feas0 < min(feas_tol, FEAS_TOL):
                # (FLAT_ITERS) every iteration counts here, accepted or rejected (a point
                # taken again on central differences too: its new Jacobian is a new try)
                f_now = 0.5 * float(r0 @ r0)
                if flat_ref is None or f_now < flat_ref - flat_tol:
                    flat_ref, flat = f_now, 0
                else:
                    flat += 1
                    # ... and only on an undamped step that itself promises little: the
                    # gain the linearisation still sees is then below FLAT_PROMISE
                    if flat >= self.flat_iters and lm == 0 and moves < FLAT_PROMISE:
                        log.debug("GN it %d: ½χ² %.8g within %.2g of %.8g for %d iterations at |g| < %.0e: %s",
                                  it, f_now, flat_tol, flat_ref, flat, feas_tol, STALLED)
                        status, success = STALLED, True
                        break
            else:
                flat, flat_ref = 0, None  # ("in a row": at feasible points only)
            ask = self.give_up if self.give_up is not None and feas0 < self.give_up_feas else self.give_up_far
            if lm == 0 and ask is not None and ask(it, 0.5 * float(r0 @ r0), -float(r0 @ dr + 0.5 * dr @ dr)):
                status = GAVE_UP
                break
            with np.errstate(divide="ignore", invalid="ignore"):
                a_max = float(min(1.0, np.min(np.where(d < 0, (lbx - w) / d, np.inf)),
                                  np.min(np.where(d > 0, (ubx - w) / d, np.inf))))
            # the ℓ1 merit weighs each constraint by its own multiplier (Powell's weights,
            # each never lowered), not all by the largest: a descent direction all the same
            # (ν_i ≥ |λ_i|). With one weight, the largest multiplier any constraint had held
            # every slip's continuity at that price. Measured on the 5-run speed set: ν 1.08e5
            # against a current max |λ| of 4.4e4, ν·|g|₁ ~20× ½χ², and the solve after the
            # inserted slips crawled at α 0.06-0.25 for five iterations (~2 s each) while the
            # full steps cut ½χ² by 1.6e3; per constraint, α = 1 from its fourth on
            if lam.size:
                nu = np.maximum(nu, 1.1 * np.abs(lam))
            pen = _l1(nu, g)
            phi0, dphi = 0.5 * r @ r + pen, grad @ d - pen
            a, accepted, d_gn = a_max, False, d  # (d_gn: the step before any correction)
            # backtracking stops where the step could gain less than stat_tol: steps that
            # short are the arcs' integration noise, not progress (measured on a stalled
            # 2-run fit: 21 of 38 accepted steps had α < 1e-6, dθ ~1e-9, and with the
            # rejected ones took 97 % of the line-search evaluations)
            tried = 0
            shared = self._cb_jac_shared()
            # (a shared step that fails is checked on each arc's own differences, unless
            # one such check showed the curvature far from continuity at work: SHARE_FEAS)
            check = shared and not (trusted and feas0 >= SHARE_FEAS)
            while a > 1e-10 and (dphi >= 0 or -a * dphi >= stat_tol):
                tried += 1
                r1, g1 = self.evaluate(w + a * d)
                phi1 = 0.5 * r1 @ r1 + _l1(nu, g1)
                if np.isfinite(phi1) and phi1 <= phi0 + 1e-4 * a * min(dphi, 0.0):
                    accepted = True
                    break
                if a == 1.0 and dphi < 0 and np.isfinite(phi1) and g.size:
                    soc = self._second_order_correction(w, d, g1, H, Jg, grad, free, lbx, ubx, nu,
                                                        phi0 + 1e-4 * dphi)
                    if soc is not None:
                        d, (r1, g1, phi1), accepted = soc[0], soc[1], True
                        break
                    if check:
                        break  # (the arcs' own differences first: below)
                a *= 0.5
            if not accepted and tried and (shared or feas0 < feas_tol and self._cb_jac_forward()):
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
                log.debug("GN it %d rejected on %s forward differences: the arcs' Jacobian again, %s", it,
                          "shared" if shared else "the arcs' own", "unshared" if shared else "central")
                self.jacobian_scheme("forward" if shared else "central", SOLVE_REL_STEP, share=False)
                may_share, own_check = False, shared
                refreshed = True
                continue
            if not accepted:
                if lm == 0 and feas0 < self.stall_feas and moves < self.stall_tol:
                    # the whole (undamped) step promises less than the stall tolerance: no rung
                    # of the damping ladder can gain more, and the stall rule would judge the
                    # point reached within tolerance after climbing it (measured: four rungs,
                    # ~20 s, for 1.5e-4 of ½χ² in the first solve above)
                    judged = self._stalled_undamped(it, r0, Jr, Jg, grad, g, free, "Line_Search_Failed")
                    if judged[1]:
                        status, success = judged
                        log.debug("GN it %d rejected within the stall tolerance: %s", it, status)
                        break
                reach, moves_step = self._damping_reach(d_gn, H, Jg, grad, g, free, Jr, dphi)
                log.debug("GN it %d rejected: phi %.6g dphi %.3g |d| %.3g nu %.3g lm %.1e reach %.2g, %.2g",
                          it, phi0, dphi, np.max(np.abs(d)), float(np.max(nu, initial=0.0)), lm, reach, moves_step)
                lm = max(10 * lm, 1e-3)
                if lm > 1e8 or (reach < self.ladder_reach and moves_step < self.ladder_step):
                    # no step gains along any damping (or none the rest of the ladder
                    # could give differs enough): judged like a stall, on the undamped
                    # step (a candidate's refit that cannot move further but whose Δnll
                    # is known to its tolerance has done its job)
                    status, success = self._stalled_undamped(it, r0, Jr, Jg, grad, g, free, "Line_Search_Failed")
                    break
                continue
            step_th = float(np.max(np.abs(a * d[:n_th]))) if n_th else 0.0
            w, r, g = w + a * d, r1, g1
            if own_check:
                own_check = False
                if (a < a_max or lm > 0) and self.opts.share_arc_jacobian:
                    # each arc's own differences needed the line search too: the
                    # constraints' curvature, not the sharing, had stopped the full step
                    may_share, trusted = True, True
                    log.debug("GN it %d: on the arcs' own differences a step of %.2g: sharing again", it, a)
            lm_step, lm = lm, (lm / 10 if lm > 1e-3 else 0.0)
            feas = float(np.abs(g).max()) if g.size else 0.0
            log.debug("GN it %d: f %.8g |g| %.2e dθ %.2e α %.2g lm %.1e", it, 0.5 * r @ r, feas, step_th, a, lm)
            if self.progress is not None and time.perf_counter() - said >= PROGRESS_EVERY_S:
                said = time.perf_counter()
                self.progress(f"  iteration {it} of at most {opts.max_iter}: χ² {float(r @ r):.6g}, "
                              f"constraint violation {feas:.2e}, {said - t0:.0f} s")
            if step_th < opts.tol and feas < feas_tol and abs(phi0 - phi1) <= opts.tol * (1 + phi0):
                status, success = "Solve_Succeeded", True
                break
            stalled = stalled + 1 if phi0 - phi1 < stat_tol else 0
            if stalled >= STALL_ITERS:
                if lm_step > 0:  # judged on the undamped step, as a damped convergence is
                    status, success = self._stalled_undamped(it, r0, Jr, Jg, grad, g0, free, "Stalled")
                else:
                    status, success = self._stalled(it, r0, Jr, d_gn, g, damped=False)
                break
        return dict(w=w, f=0.5 * float(r @ r), status=status, success=success, iterations=it,
                    wall_s=time.perf_counter() - t0, central=refreshed, shared=self._cb_jac_shared(),
                    max_violation=float(np.abs(g).max()) if g.size else 0.0)

    def _damping_reach(self, d, H, Jg, grad, g, free, Jr, dphi) -> tuple[float, float]:
        """How much the rest of the damping ladder could change a rejected step ``d``:
        (|m(d∞) − m(d)| / |∂φ|, max|d∞ − d| / max|d|), m the Gauss–Newton model of ½χ²'s
        change (∇f·x + ½‖Jᵣx‖²), d∞ the step with the parameter block held (the limit of
        infinite damping: the Levenberg–Marquardt term acts on the parameters alone; the
        states' part of the step, which the linearised constraints ask for, no damping
        removes), ∂φ the merit's directional derivative along ``d`` (the constraints'
        part of it is the same for every damping). The first says what the model would
        gain, the second how far the trial points would move (a parameter step along a
        flat direction changes the model little and the function perhaps much). (0, 0)
        when the parameters are held anyway (a run solved alone, a mode-sequence trial):
        every rung would give the same step."""
        n_th = self.n_theta
        states = free[free >= n_th]
        if len(states) == len(free):
            return 0.0, 0.0
        try:
            sol = kkt_solve(H, Jg, grad, g, states)
        except RuntimeError:
            return np.inf, np.inf
        d_inf = np.zeros(self.n_w)
        d_inf[states] = sol[: len(states)]

        def model(x):
            jx = Jr @ x
            return float(grad @ x) + 0.5 * float(jx @ jx)

        size = float(np.max(np.abs(d)))
        step = float(np.max(np.abs(d_inf - d))) / size if size > 0 else 0.0
        return (abs(model(d_inf) - model(d)) / abs(dphi) if dphi != 0 else np.inf), step

    def _second_order_correction(self, w, d, g1, H, Jg, grad, free, lbx, ubx, nu, target):
        """(step, (r, g, merit)) of a second-order correction of a full step ``d`` that
        the merit rejected, or None (Nocedal & Wright §18.3; Ipopt's SOC).

        The continuity constraints are nonlinear in the arcs' inputs: a full step the
        Gauss–Newton model predicts well for χ² can leave them violated to second order,
        and the ℓ1 merit then rejects it and every step down to α ~ 0.01 (the Maratos
        effect). Measured on the load-offset candidate of four short runs: χ² fell as
        predicted to 3 digits at α = 1, but |g| rose from 1e-6 to 1e-3…1e-2 µm, and the
        refit crawled at α ≈ 0.004…0.06 until it stalled. The correction solves the same
        KKT system with the constraints' residual at the trial point, c(w + d) − J_g·d,
        in place of c(w): the step then lands on the constraints to second order.
        Up to :data:`MAX_SOC` corrections, each from the last."""
        p, gp = d, g1
        for _ in range(MAX_SOC):
            try:
                sol = kkt_solve(H, Jg, grad, gp - Jg @ p, free)
            except RuntimeError:
                return None
            q = np.zeros(self.n_w)
            q[free] = sol[: len(free)]
            if not np.all(np.isfinite(q)):
                return None
            q = np.clip(w + q, lbx, ubx) - w  # (a correction may cross a bound the step touched)
            r1, g1 = self.evaluate(w + q)
            phi1 = 0.5 * r1 @ r1 + _l1(nu, g1)
            if not np.isfinite(phi1):
                return None
            if phi1 <= target:
                log.debug("   second-order correction accepted: |g| %.2e -> %.2e", float(np.abs(gp).max()),
                          float(np.abs(g1).max()))
                return q, (r1, g1, phi1)
            if np.abs(g1).sum() >= np.abs(gp).sum():  # the constraints are not converging
                log.debug("   second-order correction rejected: |g| %.2e -> %.2e", float(np.abs(gp).max()),
                          float(np.abs(g1).max()))
                return None
            p, gp = q, g1
        return None

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
        solution (a singular KKT system)."""
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
        ok = not damped and feas < self.stall_feas and left < self.stall_tol
        return (STALLED, True) if ok else ("Stalled", False)

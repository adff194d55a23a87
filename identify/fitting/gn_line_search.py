"""How the Gauss–Newton SQP takes its step: the ℓ1 merit and its weights, the backtracking
line search with second-order corrections of a rejected full step, and the damping ladder
climbed when no step is accepted. :class:`MeritLineSearch` is mixed into
:class:`identify.fitting.gauss_newton.GaussNewtonSQP`, whose :meth:`solve_gn` calls it.
"""

from __future__ import annotations

import logging

import numpy as np

from identify.fitting.arcs import SHARE_FEAS
from identify.fitting.convergence import kkt_solve
from identify.fitting.gn_state import Iteration, SolveState

__all__ = ["MAX_SOC", "MeritLineSearch"]

log = logging.getLogger(__name__)

MAX_SOC = 4  # second-order corrections tried for a rejected full step (as Ipopt's max_soc)


def _l1(nu, g) -> float:
    """The ℓ1 merit's constraint term Σᵢ νᵢ|gᵢ| (ν one weight, or one per constraint)."""
    return float(np.sum(nu * np.abs(g)))


class MeritLineSearch:
    """The merit, line search, second-order correction and damping ladder of the
    Gauss–Newton SQP (mixed into it; its stall tests and tolerances are the solver's)."""

    def _merit(self, st: SolveState, step: Iteration) -> None:
        """The longest step within the bounds, the merit's weights raised to the step's
        multipliers, and the merit at the point and its slope along the step."""
        d, w = step.d, st.w
        with np.errstate(divide="ignore", invalid="ignore"):
            step.a_max = float(min(1.0, np.min(np.where(d < 0, (st.lbx - w) / d, np.inf)),
                                   np.min(np.where(d > 0, (st.ubx - w) / d, np.inf))))
        # the ℓ1 merit weighs each constraint by its own multiplier (Powell's weights,
        # each never lowered), not all by the largest: a descent direction all the same
        # (ν_i ≥ |λ_i|). With one weight, the largest multiplier any constraint had held
        # every slip's continuity at that price. Measured on the 5-run speed set: ν 1.08e5
        # against a current max |λ| of 4.4e4, ν·|g|₁ ~20× ½χ², and the solve after the
        # inserted slips crawled at α 0.06-0.25 for five iterations (~2 s each) while the
        # full steps cut ½χ² by 1.6e3; per constraint, α = 1 from its fourth on
        if step.lam.size:
            st.nu = np.maximum(st.nu, 1.1 * np.abs(step.lam))
        pen = _l1(st.nu, st.g)
        step.phi0, step.dphi = 0.5 * st.r @ st.r + pen, step.grad @ d - pen

    def _line_search(self, st: SolveState, step: Iteration) -> None:
        """Backtracking on the merit from the longest step, a rejected full step first
        corrected to second order; it sets the step's ``accepted``, ``a``, ``d``, ``r1``,
        ``g1``, ``phi1``, ``tried`` and ``shared``."""
        w, d, a, phi0, dphi = st.w, step.d, step.a_max, step.phi0, step.dphi
        accepted, step.d_gn = False, d  # (d_gn: the step before any correction)
        r1 = g1 = phi1 = None
        # backtracking stops where the step could gain less than stat_tol: steps that
        # short are the arcs' integration noise, not progress (measured on a stalled
        # 2-run fit: 21 of 38 accepted steps had α < 1e-6, dθ ~1e-9, and with the
        # rejected ones took 97 % of the line-search evaluations)
        tried = 0
        shared = self._cb_jac_shared()
        # (a shared step that fails is checked on each arc's own differences, unless
        # one such check showed the curvature far from continuity at work: SHARE_FEAS)
        check = shared and not (st.trusted and step.feas0 >= SHARE_FEAS)
        while a > 1e-10 and (dphi >= 0 or -a * dphi >= step.stat_tol):
            tried += 1
            r1, g1 = self.evaluate(w + a * d)
            phi1 = 0.5 * r1 @ r1 + _l1(st.nu, g1)
            if np.isfinite(phi1) and phi1 <= phi0 + 1e-4 * a * min(dphi, 0.0):
                accepted = True
                break
            if a == 1.0 and dphi < 0 and np.isfinite(phi1) and st.g.size:
                soc = self._second_order_correction(w, d, g1, step.H, step.Jg, step.grad, step.free, st.lbx, st.ubx,
                                                    st.nu, phi0 + 1e-4 * dphi)
                if soc is not None:
                    d, (r1, g1, phi1), accepted = soc[0], soc[1], True
                    break
                if check:
                    break  # (the arcs' own differences first: GaussNewtonSQP._retake_on_other_differences)
            a *= 0.5
        step.d, step.a, step.accepted, step.tried, step.shared = d, a, accepted, tried, shared
        step.r1, step.g1, step.phi1 = r1, g1, phi1

    def _climb_damping(self, st: SolveState, step: Iteration) -> bool:
        """A step no line search accepted: judged at once when the undamped step promises
        less than the stall tolerance, else the damping raised a rung. Whether the solve
        ends (judged like a stall: at the ladder's top, or when no rung could change the step)."""
        it = st.it
        if st.lm == 0 and step.feas0 < self.opts.stop.stall_feas and step.moves < self.opts.stop.stall_tol:
            # the whole (undamped) step promises less than the stall tolerance: no rung
            # of the damping ladder can gain more, and the stall rule would judge the
            # point reached within tolerance after climbing it (measured: four rungs,
            # ~20 s, for 1.5e-4 of ½χ² in the first solve above)
            judged = self._stalled_undamped(it, step.r0, step.Jr, step.Jg, step.grad, st.g, step.free,
                                            "Line_Search_Failed")
            if judged[1]:
                st.status, st.success = judged
                log.debug("GN it %d rejected within the stall tolerance: %s", it, st.status)
                return True
        reach, moves_step = self._damping_reach(step.d_gn, step.H, step.Jg, step.grad, st.g, step.free, step.Jr,
                                                step.dphi)
        log.debug("GN it %d rejected: phi %.6g dphi %.3g |d| %.3g nu %.3g lm %.1e reach %.2g, %.2g",
                  it, step.phi0, step.dphi, np.max(np.abs(step.d)), float(np.max(st.nu, initial=0.0)), st.lm, reach,
                  moves_step)
        st.lm = max(10 * st.lm, 1e-3)
        gn = self.opts.gauss_newton
        if st.lm > 1e8 or (reach < gn.ladder_reach and moves_step < gn.ladder_step):
            # no step gains along any damping (or none the rest of the ladder
            # could give differs enough): judged like a stall, on the undamped
            # step (a candidate's refit that cannot move further but whose Δnll
            # is known to its tolerance has done its job)
            st.status, st.success = self._stalled_undamped(it, step.r0, step.Jr, step.Jg, step.grad, st.g, step.free,
                                                           "Line_Search_Failed")
            return True
        return False

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

"""The covariance of the estimates: the constrained Gauss–Newton information, and the
robust (sandwich), cluster (per run) and model-based forms of it. :class:`Covariance` is
mixed into :class:`identify.fitting.problem.Problem`.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable

import numpy as np
import scipy.sparse as sp

from identify.fitting import kkt

log = logging.getLogger(__name__)


COVARIANCE_REL_STEP = 1e-4  # secant step of the arc differences for the covariance (see central_differences)


# Arcs whose inputs agree to this relative distance share one arc's central differences
# for the covariance (identify.fitting.arcs.share_groups): at the secant step itself, so a group
# is no wider than the secant that smooths a kinked arc. Measured at the 10-run speed
# set's solution: 142 of 1093 arcs integrated, 2.8 s -> 0.4 s, and the standard errors
# (robust, cluster, model) within 0.17 % of those on each arc's own differences (at 1e-3:
# 61 arcs, within 0.2 %).
COVARIANCE_SHARE_TOL = 1e-4


SINGULAR_AMPLIFICATION = 1e12
"""The covariance's bread (the constrained Gauss–Newton system K) is taken as unable to fix
a parameter when its solution for that parameter's unit vector is this many times larger
than 1/max|K|: the direction then lies in K's numerical null space, where the solution is
rounding, and the sandwich's J·X does not even see it (it reported μmax ± 0.03 % from
three creep means, whose information has rank 1 in four parameters). Measured: the demo's
8-run fit, μmin and A correlated at −0.9994, reaches 1.5e3 over the variables (1.4e6 with
the constraints' multipliers, which are left out of the test)."""


def _information_solve(K, rhs: np.ndarray, n_primal: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """K·X = rhs for the covariance's bread, and per right-hand side (a parameter's unit
    vector) whether the information cannot fix it: where K is singular, a parameter is
    undetermined unless its unit vector lies in K's range (then the least-norm solution
    gives the variance of that estimable parameter), and wherever the solution's first
    ``n_primal`` rows (the variables; the rest are the constraints' multipliers) are of
    the size of rounding in K's null space (:data:`SINGULAR_AMPLIFICATION`)."""
    try:
        sol = kkt.solve(K, rhs)
        ok = np.all(np.isfinite(sol))
    except RuntimeError:
        ok = False
    norm_k = float(np.abs(K.data).max()) if K.nnz else 0.0
    undetermined = np.zeros(rhs.shape[1], bool)
    if not ok:
        Kd = K.toarray()
        if not np.all(np.isfinite(Kd)):
            return np.full(rhs.shape, np.nan), np.ones(rhs.shape[1], bool)
        sol = np.linalg.lstsq(Kd, rhs, rcond=1e-12)[0]
        resid = np.abs(Kd @ sol - rhs).max(axis=0)
        undetermined |= resid > 1e-6 * (norm_k * np.abs(sol).max(axis=0) + 1.0)
    with np.errstate(invalid="ignore", over="ignore"):
        amp = norm_k * np.abs(sol[:n_primal]).max(axis=0)
    undetermined |= ~np.isfinite(amp) | (amp > SINGULAR_AMPLIFICATION)
    return sol, undetermined


class Covariance:
    """The covariance of the problem's estimates (mixed into the problem)."""

    def information(self, w: np.ndarray, evaluated=None) -> np.ndarray:
        """Gauss–Newton information on the scaled free parameters, every other variable
        eliminated under the linearised constraints (a Schur complement). The parameters
        need not be determined (a singular complement is legitimate: a run alone, or a
        candidate effect the baseline's parameters absorb), so a tiny ridge ε makes the
        KKT matrix invertible and is subtracted again: (C_ε)⁻¹ − εI is the exact complement."""
        return self.information_parts(w, evaluated, meat=False)[0]

    def information_parts(self, w: np.ndarray, evaluated=None, meat: bool = True,
                          frame_scale: float | None = None):
        """(B, M) on the scaled free parameters, the nuisances eliminated: B the
        information of :meth:`information`, M the covariance of the reduced score under
        the robust covariance's error model (:meth:`covariance`: the frames independent,
        a run's triggers exchangeable). The estimator's covariance is B⁻¹MB⁻¹; for
        independent runs B and M both add up, so a plan's prediction is assembled from
        its runs'. σ² of the triggers is pooled over this problem's runs, and so is the
        frames' χ² scale unless ``frame_scale`` sets it (a design sets 1: its noise model
        is exact, and a creep run's one steady mean gives no χ² to scale by).
        ``meat=False``: (B, None)."""
        if evaluated is None:
            self.central_differences()
        r, g, Jr, Jg = evaluated if evaluated is not None else self.evaluate(w, jac=True)
        H = (Jr.T @ Jr).tocsc().toarray()
        Jg = Jg.toarray()
        n_th = self.n_theta
        lbx, ubx = self.bounds()
        keep = np.array([i for i in range(self.n_w) if i < n_th or lbx[i] < ubx[i]])
        H, Jg = H[np.ix_(keep, keep)], Jg[:, keep]
        eps = 1e-9 * max(np.abs(np.diag(H)[:n_th]).max(), 1.0)
        H[:n_th, :n_th] += eps * np.eye(n_th)
        m = Jg.shape[0]
        K = np.block([[H, Jg.T], [Jg, np.zeros((m, m))]]) if m else H
        rhs = np.zeros((K.shape[0], n_th))
        rhs[:n_th, :n_th] = np.eye(n_th)
        if not np.all(np.isfinite(K)):
            raise ValueError("the NLP Jacobian is not finite at this point")
        sol = np.linalg.solve(K, rhs)
        C = sol[:n_th, :n_th]
        C = 0.5 * (C + C.T)
        Cinv = np.linalg.inv(C)
        info = Cinv - eps * np.eye(n_th)
        info = 0.5 * (info + info.T)
        if not meat:
            return info, None
        # δθ = C_ε·u (u the reduced score): Cov(u) = C_ε⁻¹·Cov_ε(δθ)·C_ε⁻¹, exact for any ε
        X = np.zeros((self.n_w, n_th))
        X[keep] = sol[: len(keep)]
        V = self._sandwich_meat(r, Jr, X, "robust", frame_scale=frame_scale)
        M = Cinv @ V @ Cinv
        return info, 0.5 * (M + M.T)

    def central_differences(self):
        """Central arc differences with a secant step (``COVARIANCE_REL_STEP``) from now
        on, for the covariance and the information; :meth:`solve` goes back to the
        option's scheme.

        The hybrid arcs are only piecewise smooth: a slow slip whose speed grazes the
        stop threshold has a kink in its end state, and the solver likes to converge
        onto such a kink. Differences at 1e-6 across it then gave one arc's rows a
        derivative that moved the model-based standard error of μmin by 1.5× between two
        solutions 1e-3 σ apart; at 1e-5 … 3e-3 the covariance agreed to 1 % on both and
        everywhere between (smooth arcs change by O(h²) = 1e-8)."""
        return self.jacobian_scheme("central", COVARIANCE_REL_STEP, tol=COVARIANCE_SHARE_TOL)

    def trigger_correlation(self, r_trig: np.ndarray) -> tuple[dict, float]:
        """Per run, the correlation ρ of its slips' trigger errors, and their variance σ².

        A slip's trigger residual is √12·(s − ½), s its position in the trigger interval:
        uniform, so unit variance. A run whose slips recur at one phase shares one error
        (ρ = 1); one whose phase walks through the interval has nearly independent ones
        (ρ = 0). The spread of the residuals within a run tells which: ρ = 1 − v/σ², v its
        within-run variance. σ² is 1 unless the pooled within-run variance exceeds it (the
        uniform picture failing: then that). Runs with fewer than three trigger residuals
        (four slips: the first has none) get ρ = 1, the cautious end. With ``free_phase``
        each run's phase φ takes up the shared error (its own residual counts it), so the
        slips' residuals √12·(s − φ) keep only what varies within the run: ρ = 0.
        A non-finite residual gives σ² = NaN (an undetermined covariance, not a quiet 1).
        """
        runs = self.ev_run[self.ev_next]
        rs = np.asarray(r_trig[: self.n_trig], float)
        within, dof = 0.0, 0
        var = {}
        for c in np.unique(runs):
            x = rs[runs == c]
            if len(x) >= 3:
                var[int(c)] = float(np.var(x, ddof=1))
                within += var[int(c)] * (len(x) - 1)
                dof += len(x) - 1
        sig2 = (max(1.0, within / dof) if np.isfinite(within) else float("nan")) if dof else 1.0
        if self.opts.free_phase:
            return {int(c): 0.0 for c in np.unique(runs)}, sig2
        rho = {int(c): float(np.clip(1.0 - var[int(c)] / sig2, 0.0, 1.0)) if int(c) in var else 1.0
               for c in np.unique(runs)}
        return rho, sig2

    def _exchangeable_meat(self, A_t: np.ndarray, r_trig: np.ndarray) -> np.ndarray:
        """Σ_c σ²[(1 − ρ_c)·Σ a_i a_iᵀ + ρ_c·(Σ a_i)(Σ a_i)ᵀ] over each run's slip triggers
        (a_i the rows of Jₜ·X, in :meth:`trigger_runs` order), plus the other trigger-group
        rows (phases, first starts: one draw each) as independent unit-variance residuals."""
        rho, sig2 = self.trigger_correlation(r_trig)
        n = self.n_trig
        slip_runs = self.ev_run[self.ev_next]
        M = A_t[n:].T @ A_t[n:]
        for c, rc in rho.items():
            a = A_t[:n][slip_runs == c]
            tot = a.sum(axis=0)
            M = M + sig2 * ((1.0 - rc) * (a.T @ a) + rc * np.outer(tot, tot))
        return M

    def covariance(self, w: np.ndarray, fixed_idx: Iterable[int] = (), robust: bool | str = True,
                   evaluated=None) -> np.ndarray:
        """Covariance of the parameters and offsets at the solution w.

        Bread: the constrained Gauss–Newton system, the top-left block of
        [[JᵣᵀJᵣ, J_gᵀ], [J_g, 0]]⁻¹ (Z(ZᵀHZ)⁻¹Zᵀ, Z the null space of the constraints).
        ``robust=False`` (or ``"model"``): the model-based covariance, every residual
        independent with unit variance. Otherwise a sandwich whose meat keeps the
        model-based information of the frames (plateau levels and slopes, scaled by their
        reduced χ²) but not the triggers': slips of a run recur at nearly the same phase
        of the step interval, so their errors are largely one shared error rather than
        many independent ones.

        * ``True`` / ``"robust"`` (default): the trigger errors of a run exchangeable
          (:meth:`trigger_correlation`): unit variance (a uniform position, √12-scaled)
          with the correlation their spread within the run shows. It is the expected
          meat, not the realised one, and that matters with few runs: a run's shared
          error is largely absorbed by the parameters (as many as the runs, often), so
          the realised cluster sums run small and ``"cluster"`` put τ's standard error
          at 0.4 of the measured spread over redrawn loads.
        * ``"cluster"``: cluster-robust by run from the realised residuals (Liang–Zeger,
          with the c/(c − 1) small-sample factor): no assumption on the correlation, but
          only as many independent draws as runs.

        NaN where the information is singular (undetermined). ``evaluated``: the
        (r, g, Jr, Jg) of :meth:`evaluate` at w with :meth:`central_differences`, on this
        problem as built now (the same arc horizons ``ev_M``), when the caller has it (the
        arcs' Jacobian is most of the cost, and the arcs keep only their last point).
        """
        mode = {True: "robust", False: "model"}.get(robust, robust)
        if mode not in ("robust", "cluster", "model"):
            raise ValueError(f"covariance {robust!r}: choose 'robust', 'cluster' or 'model'")
        if evaluated is None:
            self.central_differences()
            r, g, Jr, Jg = self.evaluate(w, jac=True)
        else:
            r, g, Jr, Jg = evaluated
            if r.size != self.n_r or Jr.shape != (self.n_r, self.n_w) or Jg.shape != (self.n_g, self.n_w):
                raise ValueError(f"covariance: the evaluation given has {r.size} residuals and Jacobians "
                                 f"{Jr.shape}, {Jg.shape}; this problem has {self.n_r} residuals, "
                                 f"{self.n_g} constraints, {self.n_w} variables")
        H = (Jr.T @ Jr).tocsc()
        fixed_idx = set(fixed_idx)
        if not self.phases_free:
            fixed_idx |= set(range(self.i_phi, self.i_s))
        keep = np.setdiff1d(np.arange(self.n_w), sorted(fixed_idx))
        Hk, Jgk = H[keep][:, keep], Jg[:, keep]
        n, m = Hk.shape[0], Jgk.shape[0]
        K = sp.bmat([[Hk, Jgk.T], [Jgk, None]], format="csc")
        want = [i for i in range(self.n_theta + self.n_off) if i in set(keep)]
        cols = [int(np.searchsorted(keep, i)) for i in want]
        rhs = np.zeros((n + m, len(cols)))
        rhs[cols, np.arange(len(cols))] = 1.0
        sol, undetermined = _information_solve(K, rhs, n)
        X = np.zeros((self.n_w, len(cols)))
        X[keep] = sol[:n]
        if mode != "model":
            # (without triggers too: then the frames' χ² scale is what the sandwich adds)
            Cw = self._sandwich_meat(r, Jr, X, mode)
        else:
            Cw = sol[cols, :]
        Cw = np.array(Cw, float)
        Cw[undetermined, :] = np.nan  # (the sandwich's J·X does not see a direction the bread cannot fix)
        Cw[:, undetermined] = np.nan
        C = np.full((self.n_theta + self.n_off,) * 2, np.nan)
        for a_, i in enumerate(want):
            for b_, j in enumerate(want):
                C[i, j] = Cw[a_, b_]
        return C

    def _sandwich_meat(self, r, Jr, X, mode: str, frame_scale: float | None = None) -> np.ndarray:
        """Xᵀ·Cov(Jᵀr)·X: the frames (and creep means) independent, scaled by their
        reduced χ² when above 1 (or by ``frame_scale``); the triggers exchangeable within
        a run (``robust``) or cluster-robust from the realised residuals (``cluster``)."""
        grp = self.residual_groups()
        t0, t1 = grp["triggers"]
        ind = np.r_[np.arange(0, t0), np.arange(t1, len(r))]
        Ji = Jr[ind]
        ri = r[ind]
        # (the first slips' starts are fixed by their own rows in the trigger group, or,
        # with the interval encoding, by the frames)
        n_frames_fix = self.n_effective() - (len(self.ev_firsts) if self.n_s and not self.interval_triggers else 0)
        s2 = float(ri @ ri) / max(len(ri) - n_frames_fix, 1)
        A_ = np.asarray(Ji @ X)
        meat_part = (max(s2, 1.0) if frame_scale is None else frame_scale) * (A_.T @ A_)
        Jt = Jr[t0:t1]
        if t1 == t0:  # the interval encoding: no trigger residual to add
            return meat_part
        if mode == "cluster":
            runs = self.trigger_runs()
            scores = np.asarray(Jt.multiply(r[t0:t1][:, None]).tocsr().toarray())  # per-residual scores
            clusters = np.unique(runs)
            S = np.zeros((len(clusters), self.n_w))
            for ci, c in enumerate(clusters):
                S[ci] = scores[runs == c].sum(axis=0)
            B = S @ X
            nc = len(clusters)
            Cw = meat_part + (nc / max(nc - 1, 1)) * (B.T @ B)
        else:
            Cw = meat_part + self._exchangeable_meat(np.asarray(Jt @ X), r[t0:t1])
        return Cw

"""Held-out runs: how well a fit predicts runs it was not fitted to.

For each fold (a set of runs), the fit without them is one constrained Gauss–Newton step
from the full solution with the fold's residuals and continuity constraints dropped
(the approximate leave-out refit: the full solution's gradient is zero, so removing a
run moves the parameters by H₋F⁻¹·J_Fᵀr_F, to second order in the run's share of the
information). The held-out runs are then predicted with those parameters, their own
nuisances (first plateau position, offset) re-estimated from their own frames — as a new
run would be — by a second step with the shared parameters held. Both steps are sparse
KKT solves with the Jacobian the fit already has, so every fold of every candidate costs
milliseconds instead of a refit; :func:`exact_fold` does the refit, for checks.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .features import Layout

__all__ = ["folds_of", "heldout_residuals"]


def folds_of(n_runs: int, folds: "str | int" = "loo", seed: int = 0) -> list:
    """Run-index folds: ``"loo"`` (one run each) or an integer k (k-fold, seeded)."""
    if folds in ("loo", None):
        return [[i] for i in range(n_runs)]
    k = int(folds)
    if k < 2 or k > n_runs:
        raise ValueError(f"folds = {folds!r}: use 'loo' or an integer between 2 and the number of runs ({n_runs})")
    order = np.random.default_rng(seed).permutation(n_runs)
    return [sorted(order[i::k].tolist()) for i in range(k)]


def _kkt_solve(H, Jg, rhs_grad, g, free):
    """min ½dᵀHd + rhs_gradᵀd s.t. g + Jg d = 0 over the ``free`` variables (others 0)."""
    Hf = H[free][:, free]
    Jf = Jg[:, free]
    m = Jf.shape[0]
    # a tiny ridge keeps directions the kept residuals do not see (none should be left)
    ridge = 1e-10 * max(float(np.abs(Hf.diagonal()).max()) if Hf.shape[0] else 1.0, 1.0)
    Hf = Hf + sp.identity(Hf.shape[0], format="csc") * ridge
    K = sp.bmat([[Hf, Jf.T], [Jf, None]], format="csc") if m else Hf.tocsc()
    rhs = np.r_[-rhs_grad[free], -g] if m else -rhs_grad[free]
    try:
        sol = spla.splu(K).solve(rhs)
    except RuntimeError:  # exactly singular (a direction no kept row sees): least squares
        sol = np.linalg.lstsq(K.toarray(), rhs, rcond=1e-12)[0]
    d = np.zeros(H.shape[0])
    d[free] = sol[: len(free)]
    return d


def heldout_residuals(prob, w: np.ndarray, folds: Sequence, evaluated=None, hold: np.ndarray | None = None):
    """Predicted residuals of every run when it is held out (linearised; see module).

    Returns (r_heldout, theta_shift): the residual vector in which each run's rows come
    from the fit without its fold, and the scaled parameter shift per fold.
    """
    r, g, Jr, Jg = evaluated if evaluated is not None else prob.central_differences().evaluate(w, jac=True)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(Jr.data)) and np.all(np.isfinite(Jg.data))):
        raise ValueError("the residuals or their Jacobian are not finite at the solution")
    lay = Layout.of(prob)
    Jr = Jr.tocsr()
    Jg = Jg.tocsr()
    lbx, ubx = prob.bounds()
    # variables at an active bound stay there (as in the solver): a parameter at its null on
    # a bound (A = 0) must not step through it
    grad = Jr.T @ r
    active = ((w <= lbx + 1e-12) & (grad > 0)) | ((w >= ubx - 1e-12) & (grad < 0))
    fixed = (lbx == ubx) | active
    if hold is not None:
        fixed = fixed | hold
    n_th = prob.n_theta
    out = np.full_like(r, np.nan)
    shifts = []
    for fold in folds:
        fold = list(fold)
        in_rows = np.isin(lay.row_run, fold)
        in_cons = np.isin(lay.con_run, fold)
        in_vars = np.isin(lay.var_run, fold)
        # 1) the fit without the fold
        W = sp.diags((~in_rows).astype(float))
        Jk = W @ Jr
        H = (Jk.T @ Jk).tocsc()
        grad = Jk.T @ (r * ~in_rows)
        keep_c = np.nonzero(~in_cons)[0]
        free = np.nonzero(~fixed & ~in_vars)[0]
        d = _kkt_solve(H, Jg[keep_c], grad, g[keep_c], free)
        shifts.append(d[:n_th].copy())
        # 2) the fold's runs predicted: shared parameters held at the fold fit, the runs'
        #    own variables re-estimated from their own rows
        Wf = sp.diags(in_rows.astype(float))
        Jf = Wf @ Jr
        Hf = (Jf.T @ Jf).tocsc()
        dth = np.zeros(prob.n_w)
        dth[:n_th] = d[:n_th]
        rf = r * in_rows + Jf @ dth  # residuals after the parameter shift
        gf = g + Jg @ dth
        c_f = np.nonzero(in_cons)[0]
        free_f = np.nonzero(~fixed & in_vars)[0]
        if free_f.size:
            d2 = _kkt_solve(Hf, Jg[c_f], Jf.T @ rf, gf[c_f], free_f)
        else:
            d2 = np.zeros(prob.n_w)
        pred = rf + Jf @ d2
        out[in_rows] = pred[in_rows]
    return out, shifts

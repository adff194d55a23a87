"""Least-squares fits of one aging law's static curve μs(t_rest) (``static_curve``), as
the reduced analysis compares the laws across runs (:func:`identify.reduced_fit`).

:func:`fit_law_curve` fits one law by bounded least squares from several starts (times
and q0 on a log scale) and scores it by AIC and BIC; :class:`LawCurveFit` holds the
result, its standard errors and the parameters that ended on a bound.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from identify.jsonio import jsonable
from identify.model.laws import get_law

__all__ = ["LawCurveFit", "fit_law_curve"]

_MU_BOUNDS = (0.0, 3.0)
_TIME_BOUNDS = (1e-6, 1e3)  # s
_B_BOUNDS = (0.0, 3.0)


@dataclass
class LawCurveFit:
    """Least-squares fit of one law's static curve μs(t_rest) (``static_curve``).

    Attributes
    ----------
    law : str
    parameters, stderr : dict
        By ``law.curve_parameters`` (times in s); stderr NaN when undetermined.
    rss : float
        Residual sum of squares.
    n, k : int
        Data points and free parameters.
    aic, bic : float
        n·ln(RSS/n) + 2k and n·ln(RSS/n) + k·ln n.
    r2 : float
        1 − RSS/TSS.
    converged : bool
        The optimiser converged and the problem is determined (n ≥ k + 1).
    message : str
        Why not, when not.
    at_bounds : list of str
        Parameters that ended on a bound: held there for the standard errors of the
        others, their own stderr is NaN.
    """

    law: str
    parameters: dict
    stderr: dict
    rss: float
    n: int
    k: int
    aic: float
    bic: float
    r2: float
    converged: bool
    message: str = ""
    at_bounds: list = field(default_factory=list)

    def bound_side(self, name: str) -> str | None:
        """'lower' or 'upper': the bound parameter ``name`` sits at (None when it is not
        at one)."""
        if name not in self.at_bounds:
            return None
        lo, hi, _ = _param_bounds(name)
        v = self.parameters[name]
        return "lower" if abs(v - lo) <= abs(v - hi) else "upper"

    def predict(self, t_rest) -> np.ndarray:
        """μs at rest times ``t_rest`` (s)."""
        law = get_law(self.law)
        theta = [self.parameters[p] for p in law.curve_parameters]
        return law.static_curve(np.asarray(t_rest, float), theta)

    def rate(self, t_rest) -> np.ndarray:
        """dμs/dt_rest at ``t_rest`` (1/s), by complex step (exact to rounding, also
        where the curve has saturated)."""
        law = get_law(self.law)
        theta = [self.parameters[p] for p in law.curve_parameters]
        t = np.asarray(t_rest, float)
        h = 1e-20 * np.maximum(np.abs(t), 1e-12)
        return np.imag(law.static_curve(t + 1j * h, theta)) / h

    def to_json(self) -> dict:
        return jsonable(
            dict(
                law=self.law,
                parameters=self.parameters,
                stderr=self.stderr,
                rss=self.rss,
                n=self.n,
                k=self.k,
                aic=self.aic,
                bic=self.bic,
                r2=self.r2,
                converged=self.converged,
                message=self.message,
                at_bounds=self.at_bounds,
            )
        )


def _param_bounds(name: str) -> tuple[float, float, bool]:
    """(lower, upper, log) of a curve parameter."""
    if name in ("tau", "t_c"):
        return (*_TIME_BOUNDS, True)
    if name == "q0":
        return (1e-6, 1.0 - 1e-9, True)
    if name == "B":
        return (*_B_BOUNDS, False)
    return (*_MU_BOUNDS, False)


def _starts(law_name: str, t: np.ndarray, mu: np.ndarray) -> list[list[float]]:
    lo, hi = float(mu.min()), float(mu.max())
    span = max(hi - lo, 1e-3)
    tm = float(np.median(t))
    taus = [tm * f for f in (0.1, 0.3, 1.0, 3.0)]
    if law_name == "exponential":
        return [[hi + 0.05 * span, max(lo - 0.5 * span, 0.0), tau] for tau in taus]
    if law_name == "logistic":
        return [
            [hi + 0.05 * span, max(lo - 0.5 * span, 0.0), tau, q0]
            for tau in taus
            for q0 in (0.01, 0.1, 0.5)
        ]
    if law_name == "logarithmic":
        x = np.log(t)
        slope = float(np.polyfit(x, mu, 1)[0]) if np.ptp(x) > 0 else 0.01
        b0 = min(max(slope, 1e-3), 1.0)
        return [
            [max(lo - 0.1 * span, 0.0), b0, tc] for tc in (float(t.min()) * 0.1, float(t.min()), tm)
        ]
    raise ValueError(f"no starting values for law {law_name!r}")


def _failed_fit(law: str, names: list[str], n: int, message: str) -> LawCurveFit:
    nan = {p: math.nan for p in names}
    return LawCurveFit(
        law=law,
        parameters=dict(nan),
        stderr=dict(nan),
        rss=math.nan,
        n=n,
        k=len(names),
        aic=math.nan,
        bic=math.nan,
        r2=math.nan,
        converged=False,
        message=message,
    )


class _Scale:
    """The optimiser's coordinates u of the curve parameters θ: u = ln θ for times and
    q0, u = θ otherwise, with each parameter's bounds in u."""

    def __init__(self, names: list[str]):
        bnd = [_param_bounds(p) for p in names]
        self.is_log = np.array([b[2] for b in bnd])
        self.lo = np.array([math.log(b[0]) if b[2] else b[0] for b in bnd])
        self.hi = np.array([math.log(b[1]) if b[2] else b[1] for b in bnd])

    def natural(self, u: np.ndarray) -> np.ndarray:
        """θ at the coordinates ``u``."""
        return np.where(self.is_log, np.exp(u), u)

    def start(self, s0: list[float]) -> np.ndarray:
        """Coordinates of the start ``s0`` (natural parameters), just inside the bounds."""
        lo, hi = self.lo, self.hi
        u0 = np.array([math.log(v) if lg else v for v, lg in zip(s0, self.is_log)])
        return np.clip(u0, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))

    def at_bounds(self, names: list[str], u: np.ndarray) -> list[str]:
        """The parameters whose coordinate in ``u`` sits on (within 1e-7 of) a bound."""
        return [
            p
            for p, x, a, b in zip(names, u, self.lo, self.hi)
            if x <= a + 1e-7 * (b - a) or x >= b - 1e-7 * (b - a)
        ]


def _best_least_squares(law, t: np.ndarray, mu: np.ndarray, scale: _Scale, determined: bool):
    """The least-squares solution with the lowest cost over the law's starts (None when
    every start fails); an undetermined problem gets one start and a short budget."""
    from scipy.optimize import least_squares

    def resid(u):
        return law.static_curve(t, scale.natural(u)) - mu

    k = len(scale.is_log)
    best = None
    starts = _starts(law.name, t, mu)
    if not determined:  # the curve can pass through every point: one start is enough
        starts = starts[:1]
    for s0 in starts:
        try:
            res = least_squares(
                resid,
                scale.start(s0),
                bounds=(scale.lo, scale.hi),
                method="trf",
                x_scale="jac",
                xtol=1e-10,
                ftol=1e-10,
                gtol=1e-10,
                max_nfev=200 * k if determined else 50 * k,
            )
        except (ValueError, FloatingPointError):
            continue
        if not np.all(np.isfinite(res.fun)):
            continue
        if best is None or res.cost < best.cost:
            best = res
    return best


def _scores(rss: float, mu: np.ndarray, n: int, k: int) -> tuple[float, float, float]:
    """(R², AIC, BIC) of a fit with residual sum of squares ``rss`` to the points ``mu``."""
    tss = float(np.sum((mu - mu.mean()) ** 2))
    r2 = 1.0 - rss / tss if tss > 0 else math.nan
    rss_f = max(rss, 1e-300)
    aic = n * math.log(rss_f / n) + 2 * k
    bic = n * math.log(rss_f / n) + k * math.log(n)
    return r2, aic, bic


def _standard_errors(best, theta: np.ndarray, scale: _Scale, names: list[str], at_bounds: list[str],
                     rss: float, n: int) -> dict | None:
    """Standard errors s²·(JᵀJ)⁻¹ of the parameters not on a bound (bound ones are held
    there); empty when not finite, None when JᵀJ is singular."""
    # Jacobian in natural parameters: d/dθ = d/du · du/dθ, du/dθ = 1/θ on log scale
    J = best.jac / np.where(scale.is_log, theta, 1.0)[None, :]
    free = [i for i, p in enumerate(names) if p not in at_bounds]
    s2 = rss / (n - len(free))
    try:
        Jf = J[:, free]
        cov = s2 * np.linalg.inv(Jf.T @ Jf)
        se = np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        return None
    if np.all(np.isfinite(se)):
        return {names[i]: float(v) for i, v in zip(free, se)}
    return {}


def _joined(message: str, more: str) -> str:
    """``more`` appended to ``message`` with a '; ' between when both are given."""
    return (message + "; " if message else "") + more


def fit_law_curve(law_name: str, t_rest: np.ndarray, mu_s: np.ndarray) -> LawCurveFit:
    """Fit one law's ``static_curve`` to (t_rest, μs) by bounded least squares.

    Times and q0 are fitted on a log scale; several starts, the best kept. Standard
    errors from s²·(JᵀJ)⁻¹ with s² = RSS/(n − k), J the Jacobian in the natural
    parameters (a parameter that ends on a bound is held there: NaN stderr, k counts
    the others in s²; AIC and BIC count every parameter). With n < k + 1 points the
    fit is still attempted (when n ≥ 1) but reported as not converged, with NaN
    standard errors.
    """
    law = get_law(law_name)
    names = list(law.curve_parameters)
    t = np.asarray(t_rest, float)
    mu = np.asarray(mu_s, float)
    n, k = int(t.size), len(names)
    if n == 0:
        return _failed_fit(law.name, names, 0, "no data")
    scale = _Scale(names)
    determined = n >= k + 1
    best = _best_least_squares(law, t, mu, scale, determined)
    if best is None:
        return _failed_fit(law.name, names, n, "the optimiser failed from every start")
    theta = scale.natural(best.x)
    rss = float(np.dot(best.fun, best.fun))
    r2, aic, bic = _scores(rss, mu, n, k)
    at_bounds = scale.at_bounds(names, best.x)
    stderr = {p: math.nan for p in names}
    converged = bool(best.success)
    message = "" if best.success else f"optimiser: {best.message}"
    if not determined:
        converged = False
        message = f"undetermined: {n} run(s) for {k} parameters (need at least {k + 1})"
    else:
        se = _standard_errors(best, theta, scale, names, at_bounds, rss, n)
        if se is None:
            message = _joined(message, "singular JᵀJ: no standard errors")
        else:
            stderr.update(se)
    if at_bounds:
        message = _joined(message, f"at bound: {', '.join(at_bounds)}")
    return LawCurveFit(
        law=law.name,
        parameters={p: float(v) for p, v in zip(names, theta)},
        stderr=stderr,
        rss=rss,
        n=n,
        k=k,
        aic=aic,
        bic=bic,
        r2=r2,
        converged=converged,
        message=message,
        at_bounds=at_bounds,
    )

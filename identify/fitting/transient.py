"""Fitting rate-and-state parameters to the friction transients of continuously driven
runs (velocity steps), as friction labs do, with exact derivatives.

The model (:mod:`identify.model.rsf`) is integrated sample to sample by IDAS inside one
CasADi Function built per data set; the Jacobian of every sample's μ with respect to the
parameters comes from IDAS's forward sensitivities through that Function, never from
differences. The least-squares problem is small (≤ 5 parameters), so it is solved by a
trust-region Gauss-Newton (``scipy.optimize.least_squares``): the method labs use for
these fits (Levenberg-Marquardt), so that the numbers compare like with like.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import casadi as ca
import numpy as np
from scipy import optimize

from identify.fitting.transient_result import TransientFitResult, TransientParameter
from identify.model.rsf import RSF_LAWS, RSF_PARAMETERS, VelocityDrive, transient_function

__all__ = ["FIT_PARAMETERS", "TransientRun", "fit_transient", "TransientFitError", "noise_of", "steady_scatter"]


class TransientFitError(ValueError):
    """A transient fit that cannot be made as asked (no samples after a velocity change,
    a parameter that is not the law's); the message names the run or parameter."""


@dataclass
class TransientRun:
    """One continuously driven run: friction ``mu`` sampled at ``time_s`` under the load
    point ``drive``; ``stiffness_per_um`` the loading system's stiffness in friction per µm
    of load-point displacement (k/Nb)."""

    name: str
    time_s: np.ndarray
    mu: np.ndarray
    drive: VelocityDrive
    stiffness_per_um: float
    notes: dict = field(default_factory=dict)

    def __post_init__(self):
        self.time_s, self.mu = np.asarray(self.time_s, float), np.asarray(self.mu, float)
        if self.time_s.shape != self.mu.shape or self.time_s.ndim != 1 or self.time_s.size < 10:
            raise TransientFitError(f"run {self.name!r}: time_s and mu must be 1-D, of one length, >= 10 samples")
        if not (np.all(np.isfinite(self.time_s)) and np.all(np.isfinite(self.mu))):
            raise TransientFitError(f"run {self.name!r}: time_s and mu must be finite")
        if np.any(np.diff(self.time_s) <= 0):
            raise TransientFitError(f"run {self.name!r}: time_s must increase")
        if self.time_s[0] < self.drive.times_s[0]:
            raise TransientFitError(f"run {self.name!r}: samples start at {self.time_s[0]:g} s, before the drive's "
                                    f"first time {self.drive.times_s[0]:g} s")
        if not self.stiffness_per_um > 0:
            raise TransientFitError(f"run {self.name!r}: stiffness_per_um = {self.stiffness_per_um!r} must be > 0")

    @classmethod
    def from_trace(cls, trace, stiffness_per_um: float | None = None) -> TransientRun:
        """The run of a continuously driven trace: friction μ = k·e/Nb from its elongation,
        the stiffness k/Nb per µm (or ``stiffness_per_um``, which then also converts)."""
        drive = trace.drive
        if drive is None:
            raise TransientFitError(f"run {trace.name!r} has a stepper, not a continuous drive: fit it with "
                                    "identify.fit (the hybrid stick/slip model)")
        k_per_um = trace.spring_constant / (trace.normal_load * 1e6)  # (N/m = µN/µm) over µN
        k_fit = float(stiffness_per_um) if stiffness_per_um is not None else k_per_um
        mu = trace.elongation * 1e6 * k_per_um
        return cls(trace.name, trace.time_s, mu, drive, k_fit, dict(source=str(trace.path or trace.name)))

    def window(self, start_s: float | None = None, end_s: float | None = None) -> TransientRun:
        """The samples in [start_s, end_s]; the drive starts at the window (steady sliding
        at the velocity then in force is assumed there, as labs assume)."""
        lo = self.time_s[0] if start_s is None else start_s
        hi = self.time_s[-1] if end_s is None else end_s
        keep = (self.time_s >= lo) & (self.time_s <= hi)
        if keep.sum() < 10:
            raise TransientFitError(f"run {self.name!r}: the window [{lo:g}, {hi:g}] s holds {keep.sum()} samples")
        t0 = float(self.time_s[keep][0])
        times = [t0] + [t for t in self.drive.times_s if t0 < t <= hi]
        vels = list(self.drive.velocity_at(np.array(times)))
        return TransientRun(self.name, self.time_s[keep], self.mu[keep], VelocityDrive(tuple(times), tuple(vels)),
                            self.stiffness_per_um, dict(self.notes, window_s=[t0, float(self.time_s[keep][-1])]))


class _Evaluator:
    """μ at every sample of ``run`` and its Jacobian with respect to (mu0, a, b, Dc, k),
    as CasADi Functions built once per run and law."""

    def __init__(self, run: TransientRun, law: str):
        self.mu = transient_function(law, run.drive, run.time_s)
        theta = ca.MX.sym("theta", 5)
        self.jac = ca.Function("mu_jacobian", [theta], [ca.jacobian(self.mu(theta), theta)])

    def values(self, theta: np.ndarray) -> np.ndarray:
        return np.asarray(self.mu(theta)).ravel()

    def jacobian(self, theta: np.ndarray) -> np.ndarray:
        return np.asarray(self.jac(theta))


def _start_from_data(run: TransientRun) -> dict:
    """A start read off the transient: μ0 the pre-change mean; a from the peak (the direct
    effect a·ln(V1/V0), somewhat reduced by the finite stiffness); a − b from the level the
    run settles at; Dc from the slip over which the excess above that level decays by e."""
    t, mu, d = run.time_s, run.mu, run.drive
    if len(d.times_s) < 2:
        raise TransientFitError(f"run {run.name!r}: no velocity change in the window, nothing to fit a transient to")
    tc = d.times_s[1]
    pre = mu[t < tc]
    mu0 = float(np.mean(pre)) if pre.size else float(mu[0])
    end = d.times_s[2] if len(d.times_s) > 2 else t[-1] + 1
    post = (t >= tc) & (t < end)
    ln_r = np.log(d.velocities_um_per_s[1] / d.velocities_um_per_s[0])
    tail = mu[post][-max(5, post.sum() // 5):]
    ss = float(np.median(tail)) - mu0
    excess = mu[post] - mu0
    peak = float(excess.max() if ln_r > 0 else excess.min())
    a = max(abs(peak / ln_r) * 1.3, 1e-4)
    b = a - ss / ln_r
    v1 = d.velocities_um_per_s[1]
    ipk = int(np.argmax(excess) if ln_r > 0 else np.argmin(excess))
    rel = (excess[ipk:] - ss) / (peak - ss) if peak != ss else np.zeros(1)
    below = np.flatnonzero(rel < np.exp(-1))
    dc = float(v1 * (t[post][ipk + below[0]] - t[post][ipk])) if below.size else 10.0
    return dict(mu0=mu0, a=a, b=b, Dc=max(dc, 0.1), k=run.stiffness_per_um)


FIT_PARAMETERS = RSF_PARAMETERS + ("c",)
"""The law's parameters and c, a linear trend of friction with load-point displacement
from the first velocity change (1/µm; before it too), which labs fit beside the law
(xlook's ``qi`` has it) for the slow hardening or weakening of a sheared layer."""


def _scaling(start: Mapping, run: TransientRun):
    """(to_scaled, from_scaled, dθ/dx) between the fit's parameters and numbers near 1:
    μ0 as an offset from the start in 1e-3, a and b in 1e-3, Dc and k on a log scale (about
    1 µm and the run's stated stiffness), c in 1e-5 per µm."""
    ref_mu, ref_k = float(start["mu0"]), run.stiffness_per_um

    def to_scaled(p):
        return np.array([(p["mu0"] - ref_mu) / 1e-3, p["a"] / 1e-3, p["b"] / 1e-3, np.log(p["Dc"]),
                         np.log(p["k"] / ref_k), p["c"] / 1e-5])

    def from_scaled(x):
        return dict(mu0=ref_mu + 1e-3 * x[0], a=1e-3 * x[1], b=1e-3 * x[2], Dc=float(np.exp(x[3])),
                    k=ref_k * float(np.exp(x[4])), c=1e-5 * x[5])

    def dtheta_dx(x):
        p = from_scaled(x)
        return np.diag([1e-3, 1e-3, 1e-3, p["Dc"], p["k"], 1e-5])

    return to_scaled, from_scaled, dtheta_dx


def _search_bounds(run: TransientRun) -> tuple[np.ndarray, np.ndarray]:
    """Scaled bounds: a in (0, 0.2], |b| ≤ 0.2, Dc 1 nm to 1 cm, k within 1e-7..1 /µm,
    |c| ≤ 1e-3 /µm."""
    lk = np.log(run.stiffness_per_um)
    lo = np.array([-1e3, 1e-3, -200.0, np.log(1e-3), np.log(1e-7) - lk, -100.0])
    hi = np.array([1e3, 200.0, 200.0, np.log(1e4), -lk, 100.0])
    return lo, hi


def noise_of(mu: np.ndarray) -> float:
    """The recording's sample-to-sample noise (robust: the median absolute first
    difference, scaled to a standard deviation of white noise)."""
    d = np.diff(np.asarray(mu, float))
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0))


def steady_scatter(run: TransientRun) -> float:
    """The recording's scatter in steady sliding: the standard deviation about a straight
    line of the second half of the longest stretch at one load-point velocity (its first
    half may hold the transient). Unlike :func:`noise_of` it counts the slow fluctuations
    a sheared layer shows while nothing changes, which no friction law models."""
    t, d = run.time_s, run.drive
    edges = list(d.times_s) + [np.inf]
    best = None
    for a, b in zip(edges, edges[1:]):
        m = np.flatnonzero((t >= a) & (t < b))
        if best is None or m.size > best.size:
            best = m
    tail = best[best.size // 2:]
    if tail.size < 10:
        return float("nan")
    tt, y = t[tail], run.mu[tail]
    resid = y - np.polyval(np.polyfit(tt - tt.mean(), y, 1), tt - tt.mean())
    return float(np.sqrt(resid @ resid / (tail.size - 2)))


def fit_transient(run: TransientRun, law: str = "aging", *, fixed: Sequence[str] = ("k",), trend: bool = False,
                  start: Mapping[str, float] | None = None, starts: int = 4, seed: int = 0) -> TransientFitResult:
    """Fit μ0, a, b, Dc (and k unless ``fixed``) of the rate-and-state ``law`` ('aging' or
    'slip') to ``run``'s friction transient.

    Parameters
    ----------
    run : TransientRun
        The samples and the drive; window it first with :meth:`TransientRun.window`.
    law : {'aging', 'slip'}
    fixed : names of parameters held at their start (default: the stiffness, as labs
        state it from a calibration).
    trend : also fit c, a linear trend of friction with the load-point displacement from
        the first velocity change (otherwise c = 0).
    start : values to start from (default: read off the transient); Dc in µm, k and c in
        1/µm.
    starts : extra seeded starts spread over Dc (a decade either side) and a, b (±50 %),
        the best kept: the least-squares surface of these fits has more than one valley.
    seed : the spread starts' seed.
    """
    if law not in RSF_LAWS:
        raise TransientFitError(f"law {law!r} is not known; choose one of {', '.join(RSF_LAWS)}")
    bad = [n for n in list(fixed) + list(start or {}) if n not in FIT_PARAMETERS]
    if bad:
        raise TransientFitError(f"unknown parameter(s) {', '.join(bad)}; the fit's are {', '.join(FIT_PARAMETERS)}")
    fixed = set(fixed) | (set() if trend else {"c"})
    p0 = dict(_start_from_data(run), c=0.0, **{k: float(v) for k, v in (start or {}).items()})
    to_s, from_s, dth = _scaling(p0, run)
    ev = _Evaluator(run, law)
    dx = _displacement_from_change(run)
    free = [i for i, n in enumerate(FIT_PARAMETERS) if n not in fixed]
    x_all0 = to_s(p0)
    lo, hi = _search_bounds(run)

    def full(xf):
        x = x_all0.copy()
        x[free] = xf
        return x

    def theta(x):
        return np.array([from_s(x)[n] for n in RSF_PARAMETERS])

    def resid(xf):
        x = full(xf)
        r = ev.values(theta(x)) + from_s(x)["c"] * dx - run.mu
        return np.where(np.isfinite(r), r, 1.0)

    def jac(xf):
        x = full(xf)
        J = np.column_stack([ev.jacobian(theta(x)), dx])
        return (J @ dth(x))[:, free]

    sols = _solve_from_starts(resid, jac, x_all0, free, lo, hi, starts, seed)
    if not sols:
        raise TransientFitError(f"run {run.name!r}: no start could be integrated")
    best = min(sols, key=lambda s: s.cost)
    n_best = sum(abs(s.cost - best.cost) <= 1e-6 * max(best.cost, 1e-30) + 1e-12 for s in sols)
    x = full(best.x)
    J = jac(best.x) @ np.diag(1.0 / np.diag(dth(x))[free])  # d mu / d(parameter)
    return _result(run, law, from_s(x), free, J, best.fun, best, n_best, len(sols), p0)


def _solve_from_starts(resid, jac, x_all0, free, lo, hi, starts: int, seed: int) -> list:
    """Trust-region Gauss-Newton solves from the given start and ``starts`` seeded others
    (a, b ×0.5-1.5, Dc a decade either side); a start whose integration fails is skipped."""
    rng = np.random.default_rng(seed)
    tries = [x_all0[free]]
    for _ in range(starts):
        x = x_all0.copy()
        x[1:3] = x[1:3] * rng.uniform(0.5, 1.5, 2)
        x[3] = x[3] + rng.uniform(-np.log(10), np.log(10))
        tries.append(x[free])
    sols = []
    for x in tries:
        x = np.clip(x, lo[free] + 1e-9, hi[free] - 1e-9)
        try:
            sols.append(optimize.least_squares(resid, x, jac=jac, bounds=(lo[free], hi[free]), method="trf",
                                               x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-10, max_nfev=200))
        except (RuntimeError, ValueError):  # an integration that failed at a far start
            continue
    return sols


def _displacement_from_change(run: TransientRun) -> np.ndarray:
    """Load-point displacement (µm) from its position at the drive's first velocity
    change (negative before it), as xlook's linear term takes it."""
    d = run.drive
    x = d.displacement_um(run.time_s)
    return x - (d.displacement_um(np.array([d.times_s[1]]))[0] if len(d.times_s) > 1 else 0.0)


def _result(run, law, values, free, J, r, best, n_best, n_solves, p0) -> TransientFitResult:
    """The result: each parameter's estimate with the standard error of the Gauss-Newton
    covariance s²·(JᵀJ)⁻¹ (s² = RSS/dof, as labs compute it) and with the one widened for
    the residuals' serial correlation (what the interval uses, see
    :func:`_serial_inflation`)."""
    n, k = len(r), len(free)
    dof = max(n - k, 1)
    rss = float(r @ r)
    s2 = rss / dof
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.full((k, k), np.nan)
    infl = _serial_inflation(r)
    params = {}
    j = 0
    for i, name in enumerate(FIT_PARAMETERS):
        if i in free:
            se = float(np.sqrt(cov[j, j])) if cov[j, j] >= 0 else float("nan")
            params[name] = TransientParameter(name, float(values[name]), se, se * infl, True, float(p0[name]))
            j += 1
        else:
            params[name] = TransientParameter(name, float(values[name]), None, None, False, float(p0[name]))
    sd = np.sqrt(np.diag(cov))
    corr = cov / np.outer(sd, sd) if np.all(sd > 0) else np.full_like(cov, np.nan)
    names = [FIT_PARAMETERS[i] for i in free]
    return TransientFitResult(
        run=run.name, law=law, parameters=params, n_samples=n, rms=float(np.sqrt(rss / n)),
        noise=noise_of(run.mu), scatter=steady_scatter(run), serial_inflation=infl, status=str(best.message),
        success=bool(best.success),
        nfev=int(best.nfev), best_of=(n_best, n_solves),
        correlations={f"{a},{b}": float(corr[i, j]) for i, a in enumerate(names) for j, b in enumerate(names) if i < j},
        reference_velocity_um_per_s=float(run.drive.velocities_um_per_s[0]), drive=run.drive.to_dict(),
        window_s=[float(run.time_s[0]), float(run.time_s[-1])], time_s=run.time_s, mu=run.mu, model=run.mu + r)


def _serial_inflation(r: np.ndarray) -> float:
    """How much wider than white noise's the standard errors are when the residuals are
    serially correlated: sqrt((1 + ρ)/(1 − ρ)) with ρ their lag-1 autocorrelation (an AR(1)
    residual's variance of a mean), 1 when ρ ≤ 0."""
    r = np.asarray(r, float) - np.mean(r)
    den = float(r @ r)
    rho = float(r[1:] @ r[:-1]) / den if den > 0 else 0.0
    rho = min(max(rho, 0.0), 0.999)
    return float(np.sqrt((1 + rho) / (1 - rho)))

"""The profile likelihood of one free parameter: Δχ² of the best fit with the parameter
held at values walked out from the optimum, and the 95 % interval where it crosses the
threshold (:func:`profile`, giving a :class:`identify.fitting.estimates.Profile`).
"""

from __future__ import annotations

import math

import numpy as np

from identify.fitting.estimates import Profile
from identify.progress import Stage, reporter

__all__ = ["CHI2_95", "MAX_EXTEND", "REFINE_STEPS", "BETTER_TOL", "profile"]

CHI2_95 = 3.841458820694124  # 95 % quantile of χ² with 1 degree of freedom
MAX_EXTEND = 6  # doublings of a profile's walk past its grid before a side is called open
REFINE_STEPS = 3  # bisections of the bracket where a profile crosses the 95 % threshold
# a profile point this much below the fit's χ² is a better fit (the solvers' own stall
# tolerance is 0.01 of ½χ², so 0.1 of χ² is beyond what stopping early explains)
BETTER_TOL = 0.1
_DECADE = math.log(10.0)  # how far (log scale) a profile's walk extends past its grid at most


def profile(result, name: str, n_points: int = 13, span: float = 4.0, progress=None) -> Profile:
    """Δχ² of the best fit (a :class:`identify.fitting.result.FitResult`) with ``name``
    held at each of ``n_points`` values.

    The grid covers ±``span`` standard errors on the parameter's fit scale (log for
    positive parameters), or, without a finite standard error, a factor e^±2 (log) or
    its bounds. Each point starts from the last converged solution before it, walking
    out from the optimum; a point whose constrained fit does not converge never counts
    (it is listed in ``failed``: its Δχ² is where a solver stopped, not the likelihood).
    Past the grid's edge without reaching the threshold, the walk goes on, doubling the
    distance, until it does, or reaches the bound, or (log scale) a decade, or
    ``MAX_EXTEND`` doublings. Where Δχ² crosses the threshold (3.84, × the reduced χ²
    when the covariance is scaled) between two points, the bracket is bisected
    ``REFINE_STEPS`` times before the crossing is interpolated. A side with no crossing
    is open: the data do not bound the parameter that way.

    ``progress`` (:mod:`identify.progress`): None draws a bar of the points with the time
    left on a terminal, False is silent, a callable gets each message.
    """
    progress = reporter(progress)
    prob = result.problem
    if prob is None or result.w is None:
        raise ValueError("profile: this result carries no problem (read from JSON?)")
    tm = prob.theta
    if name not in tm.names:
        raise ValueError(f"profile: {name!r} is not a free parameter ({', '.join(tm.names)})")
    i = tm.names.index(name)
    half, grid = _grid(result, i, n_points, span)
    scale = result.redchi if prob.opts.scale_covariance else 1.0
    # the points to solve: the grid, then up to REFINE_STEPS bisections per side; a side
    # that crosses early skips the rest of its grid, one that does not cross adds points
    stage = Stage(progress, f"profile of {name}", len(grid) - 1 + 2 * REFINE_STEPS)
    # (a profile walks the objective the fit minimised: with priors, their penalty too)
    chi2_min = result.chi2 + (result.priors or {}).get("penalty_chi2", 0.0)
    walk = _Walk(prob, i, name, result.w, chi2_min, CHI2_95 * max(scale, 1.0), half, stage)
    for direction in (+1, -1):
        side = grid[grid > walk.th0] if direction > 0 else grid[grid < walk.th0][::-1]
        walk.along_grid(side)
        walk.extend(direction, side[-1] if len(side) else walk.th0)
        walk.refine(direction)
    return walk.to_profile()


def _grid(result, i: int, n_points: int, span: float) -> tuple:
    """(half-width, grid) of parameter i's profile on its fit scale: ±``span`` standard
    errors about the optimum, or without one a factor e^±2 (log) or half its bounds."""
    prob, w_best = result.problem, result.w
    tm = prob.theta
    th0 = w_best[i]
    p = result.parameters[tm.names[i]]
    d = tm.jacobian_diag(w_best[: prob.n_theta])[i]
    sig = (p.stderr / abs(d)) if p.stderr and np.isfinite(p.stderr) and d else None
    half = span * sig if sig else (2.0 if tm.log[i] else 0.5 * max(tm.hi[i] - tm.lo[i], 1e-6))
    lo, hi = max(th0 - half, tm.lo[i]), min(th0 + half, tm.hi[i])
    grid = np.linspace(lo, hi, n_points)
    # (a grid point within rounding of the optimum would be a second, identical point)
    grid = np.unique(np.concatenate([grid[np.abs(grid - th0) > 1e-6 * max(half, 1e-12)], [th0]]))
    return half, grid


class _Walk:
    """The constrained fits of one profile, walked out from the optimum ``th0`` (scaled):
    Δχ² by held value (``out``), their solutions (``sols``), the values that failed."""

    def __init__(self, prob, i: int, name: str, w_best, chi2_min: float, thr: float, half: float, stage):
        self.prob, self.i, self.name, self.tm = prob, i, name, prob.theta
        self.th0, self.w_best = w_best[i], w_best
        self.chi2_min, self.thr, self.half, self.stage = chi2_min, thr, half, stage
        self.out = {self.th0: 0.0}
        self.sols = {self.th0: w_best}
        self.failed: list = []

    def point(self, w, val, note):
        """Δχ² with the parameter held at ``val``, warm-started from ``w``; the solution,
        or None where the constrained fit did not converge."""
        prob, i = self.prob, self.i
        w = w.copy()
        w[i] = val
        res = prob.solve(w, fixed={i: val})
        self.stage.advance(note)
        rr = prob.residuals(res["w"])
        if not res.get("success") or not np.all(np.isfinite(rr)):
            self.failed.append(val)
            return None
        self.out[val] = float(rr @ rr + prob.chi2_constant() - self.chi2_min)
        self.sols[val] = res["w"]
        return res["w"]

    def along_grid(self, side) -> None:
        """The grid's points on one side, out from the optimum, each warm-started from the
        last converged one; the walk stops at the first point past the threshold."""
        tm, i, th0 = self.tm, self.i, self.th0
        w = self.w_best
        for k, val in enumerate(side):
            got = self.point(w, val, f"{self.name} held at {tm.scale[i] * (math.exp(val) if tm.log[i] else val):.4g}")
            w = got if got is not None else _nearest_out(self.sols, th0, val)
            if got is not None and self.out[val] >= self.thr:
                self.stage.total -= len(side) - k - 1  # (the points beyond add nothing to the interval)
                break

    def beyond(self, direction) -> list:
        """The values walked on one side of the optimum (+1 above, -1 below)."""
        return [v for v in self.out if direction * (v - self.th0) > 0]

    def extend(self, direction, val) -> None:
        """Past the grid's edge ``val`` while Δχ² stays below the threshold: the distance
        doubled each time, up to the bound, a decade (log scale) or ``MAX_EXTEND`` times."""
        tm, i, th0 = self.tm, self.i, self.th0
        for _ in range(MAX_EXTEND):
            if any(self.out[v] >= self.thr for v in self.beyond(direction)):
                break
            far = max(self.beyond(direction) or [th0], key=lambda v: direction * (v - th0))
            if tm.log[i] and abs(far - th0) >= _DECADE:
                break
            nxt = th0 + 2 * (val - th0) if val != th0 else th0 + direction * self.half
            nxt = min(max(nxt, tm.lo[i]), tm.hi[i])
            if nxt == val:
                break
            val = nxt
            self.stage.total += 1
            self.point(self.sols[far], val, f"extending to {val:.4g} (scaled)")

    def refine(self, direction) -> None:
        """The bracket where Δχ² crosses the threshold on one side, bisected up to
        ``REFINE_STEPS`` times."""
        out, thr, th0 = self.out, self.thr, self.th0
        for step in range(REFINE_STEPS):
            pts = sorted((v for v in out if direction * (v - th0) >= 0), key=lambda v: direction * (v - th0))
            br = next(((a, b) for a, b in zip(pts, pts[1:]) if out[a] < thr <= out[b]), None)
            if br is None:
                self.stage.total -= REFINE_STEPS - step
                break
            a, b = br
            self.point(self.sols[a], 0.5 * (a + b), f"refining the 95% crossing at {0.5 * (a + b):.4g} (scaled)")

    def to_profile(self) -> Profile:
        """The :class:`Profile` of the points walked, in natural units, its interval about
        the optimum, or about a better point a constrained fit found."""
        tm, i, th0, thr = self.tm, self.i, self.th0, self.thr
        out = self.out
        vals = np.array(sorted(out))
        dchi = np.array([out[v] for v in vals])
        nat = np.array(tm.scale[i] * (np.exp(vals) if tm.log[i] else vals))
        # a constrained fit better than the fit itself: the fit stopped in a local minimum.
        # The interval is then the one about the best point found, and the profile says so
        better = None
        j0 = int(np.argmin(np.abs(vals - th0)))
        if dchi.min() < -BETTER_TOL:
            j0 = int(np.argmin(dchi))
            better = (float(nat[j0]), float(dchi[j0]))
            dchi_ref = dchi - dchi[j0]
        else:
            dchi_ref = dchi
        up = _crossing(thr, nat[j0:], dchi_ref[j0:])
        down = _crossing(thr, nat[: j0 + 1][::-1], dchi_ref[: j0 + 1][::-1])
        flat = down is None and up is None
        ci = None if flat else (down, up)
        bad = np.array(sorted(tm.scale[i] * (np.exp(v) if tm.log[i] else v) for v in self.failed))
        return Profile(name=self.name, values=nat, delta_chi2=dchi, ci95=ci, flat=flat, threshold=thr,
                       open_below=down is None, open_above=up is None, failed=bad,
                       reach=(float(nat[0]), float(nat[-1])), better=better)


def _crossing(thr: float, seq_v, seq_d):
    """Where Δχ² ``seq_d`` first rises through ``thr`` along ``seq_v``, interpolated; None
    where it never does."""
    for a in range(len(seq_d) - 1):
        if seq_d[a] < thr <= seq_d[a + 1]:
            f = (thr - seq_d[a]) / (seq_d[a + 1] - seq_d[a])
            return float(seq_v[a] + f * (seq_v[a + 1] - seq_v[a]))
    return None


def _nearest_out(sols: dict, th0: float, val: float) -> np.ndarray:
    """The converged solution nearest ``val`` on its side of the optimum (the warm start
    after a point that failed)."""
    same = [v for v in sols if (v - th0) * (val - th0) >= 0]
    return sols[min(same, key=lambda v: abs(v - val))]

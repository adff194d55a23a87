"""Spring-set design: the fewest springs that cover a normal-load range, robust to etch bias.

Problem
-------
Given a requested normal-load range [L_lo, L_hi] (inside Table I's [10 nN, 452 µN]), find
the fewest springs such that every load in the range is an allowed operating point of at
least one spring, for every μ in [0.1, 0.9] and every realisation of the etch bias, and
among those sets the one with the largest worst margin (below).

Robustness to the etch bias
---------------------------
Spring i has nominal effective width w_i on suspension s_i (k = c_i·w³, Eq. (1) of
:mod:`design.springs`). Its realised width lies in [w_i − 2b, w_i + 2b] (edge-bias error in
[−b, +b] per edge), so k_i ∈ [k_soft,i, k_stiff,i]. The allowed range of the spring is the one
valid for *every* realisation (:func:`design.constraints.robust_load_range`): the floor from
the stiffest k, the ceiling from the softest,

    lo_i = k_stiff,i · 90 nm / 0.1,        hi_i = k_soft,i · 100 µm / 0.9,

and the k rows of Table I must hold at both realisations (k_soft,i ≥ 0.01 N/m,
k_stiff,i ≤ 100 N/m). The bias is treated independently per spring, which is conservative
if it is in fact common to the chip; it makes each spring's range valid whatever the bias
turns out to be, so an experimenter can pick the spring for a load without knowing it.

Margins (the measure both the design and the paper's set are judged by)
-----------------------------------------------------------------------
With the springs ordered by nominal k, and lo_i, hi_i the elongation window above (not
clipped to Table I's load limits — the requested range already lies inside them):

    m_0 = ln(L_lo / lo_1)                     low end: how far spring 1 reaches below L_lo
    m_i = ln(hi_i / lo_{i+1}),  i = 1..n−1     overlap of neighbouring springs
    m_n = ln(hi_n / L_hi)                     high end: how far spring n reaches above L_hi

The set covers the range iff every m_j ≥ 0 (a negative m_i is a gap of ratio e^{−m_i}).
The **worst margin** is min_j m_j; a margin m means every range boundary survives a further
relative stiffness error of e^m − 1 (beyond the etch-bias model). The **worst overlap
margin** is min over the neighbour overlaps m_1..m_{n−1} only.

Optimisation
------------
For n = 1, 2, ... (up to ``max_springs``): for each assignment of the candidate suspensions
to the springs (springs on a more compliant suspension are the softer ones, so there are
C(n+S−1, S−1) assignments), maximise t subject to m_j ≥ t over the log-widths
u_i = ln(w_i / 1 µm) (all decision variables are O(1)) and nominal k ordered, with width
bounds from the process intersected with the k rows of Table I at the worst-case bias. Each
m_j is concave in u (ln(e^u − 2b) is concave, ln(e^u + 2b) convex), so every subproblem is
convex and Ipopt finds its global optimum; we still start it from a geometric spacing of
k plus seeded random starts and report how often the best value was reached. The first n
whose best worst margin is ≥ 0 is the answer (so n − 1 springs cannot cover the range).
When an end margin is pinned (it cannot exceed the stage-one optimum even on its own, e.g.
a requested floor at the lowest load the process can resolve), a second stage holds it
there and maximises the worst of the other margins (a lexicographic maximin), so a hard
limit at one end does not leave the rest unbalanced. The chosen set is then checked point
by point against every row of Table I at both bias extremes (:meth:`SpringSet.verify`); a
set that fails the check is not accepted.
"""

from __future__ import annotations

import functools
import itertools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import casadi as ca
import numpy as np

from . import constraints as tc
from .springs import (
    ETCH_BIAS_UM,
    LONG_SUSPENSION,
    PAPER_SPRING_CONSTANTS,
    PAPER_SUSPENSION,
    SpringDesign,
    Suspension,
    paper_springs,
)

__all__ = [
    "DEFAULT_SUSPENSIONS",
    "MAX_SPRINGS",
    "InfeasibleDesignError",
    "SpringSet",
    "Attempt",
    "SpringSetResult",
    "design_spring_set",
    "coverable_load_range",
    "paper_spring_set",
]

log = logging.getLogger(__name__)

DEFAULT_SUSPENSIONS: tuple[Suspension, ...] = (PAPER_SUSPENSION, LONG_SUSPENSION)
"""Candidate suspensions of the optimiser: the paper's 189 µm beam and the 390 µm beam."""
MAX_SPRINGS = 8
"""Largest number of springs the optimiser tries."""

_COVER_TOL = 1e-9  # a margin >= -_COVER_TOL counts as covering (Table I limits are closed)
_IPOPT_OPTS = {
    "ipopt.print_level": 0,
    "ipopt.sb": "yes",
    "print_time": False,
    "ipopt.tol": 1e-10,
    "ipopt.constr_viol_tol": 1e-11,
    "ipopt.max_iter": 200,
    "ipopt.bound_relax_factor": 0.0,
}


class InfeasibleDesignError(ValueError):
    """No spring set meets the request; the message says which limit stops it."""


def _uN(x: float) -> float:
    return x * 1e6


def _fmt_range_uN(lo: float, hi: float) -> str:
    return f"{_uN(lo):.4g}-{_uN(hi):.4g} µN"


def _validate_load_range_uN(load_range_uN) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in load_range_uN)
    except (TypeError, ValueError):
        raise ValueError(
            f"load_range_uN = {load_range_uN!r}: must be two numbers (low, high) in µN"
        ) from None
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo <= 0 or hi <= lo:
        raise ValueError(
            f"load_range_uN = ({lo:g}, {hi:g}): must satisfy 0 < low < high (µN)"
        )
    return lo * 1e-6, hi * 1e-6


# --------------------------------------------------------------------------------------
# A spring set and its measures
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SpringSet:
    """Springs judged against a requested load range at an etch-bias uncertainty.

    Parameters
    ----------
    springs : sequence of SpringDesign
        The springs; stored sorted by nominal k.
    load_range : (float, float)
        Requested normal-load range (N).
    etch_bias_um : float
        Uncertainty b of the edge bias per edge (µm); realised widths ``w ± 2b``.
    label : str
        Name for reports and legends.
    """

    springs: tuple[SpringDesign, ...]
    load_range: tuple[float, float]
    etch_bias_um: float = ETCH_BIAS_UM
    label: str = ""

    def __post_init__(self) -> None:
        springs = tuple(self.springs)
        if not springs or not all(isinstance(s, SpringDesign) for s in springs):
            raise ValueError("SpringSet.springs: must be a non-empty sequence of SpringDesign")
        object.__setattr__(self, "springs", tuple(sorted(springs, key=lambda s: s.spring_constant)))
        lo, hi = (float(v) for v in self.load_range)
        if not (0 < lo < hi) or not math.isfinite(hi):
            raise ValueError(
                f"SpringSet.load_range = {self.load_range!r}: must be 0 < low < high (N)"
            )
        object.__setattr__(self, "load_range", (lo, hi))
        b = float(self.etch_bias_um)
        if not math.isfinite(b) or b < 0:
            raise ValueError(f"SpringSet.etch_bias_um = {self.etch_bias_um!r}: must be >= 0")
        object.__setattr__(self, "etch_bias_um", b)
        for s in springs:
            s.spring_constant_range(b)  # raises if a realisation has no width

    # -- per spring -------------------------------------------------------------------
    @property
    def n(self) -> int:
        return len(self.springs)

    @property
    def spring_constants(self) -> np.ndarray:
        """Nominal k (N/m)."""
        return np.array([s.spring_constant for s in self.springs])

    @property
    def spring_constant_ranges(self) -> tuple[np.ndarray, np.ndarray]:
        """(k_soft, k_stiff) arrays (N/m) at the realised widths ``w ∓ 2b``."""
        pairs = [s.spring_constant_range(self.etch_bias_um) for s in self.springs]
        return np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])

    @property
    def windows(self) -> tuple[np.ndarray, np.ndarray]:
        """Elongation windows (N): loads with 90 nm ≤ e ≤ 100 µm for all μ and realisations."""
        return tc.elongation_window(*self.spring_constant_ranges)

    @property
    def load_ranges(self) -> tuple[np.ndarray, np.ndarray]:
        """Allowed Nb ranges (N) under every row of Table I at the worst-case bias (NaN: none)."""
        lo, hi = tc.robust_load_range(*self.spring_constant_ranges)
        return np.atleast_1d(lo), np.atleast_1d(hi)

    # -- set measures -----------------------------------------------------------------
    @property
    def margins(self) -> np.ndarray:
        """m_0..m_n (natural-log ratios), see the module docstring."""
        lo, hi = self.windows
        L_lo, L_hi = self.load_range
        return np.concatenate(
            [[math.log(L_lo / lo[0])], np.log(hi[:-1] / lo[1:]), [math.log(hi[-1] / L_hi)]]
        )

    @property
    def margin_labels(self) -> list[str]:
        return ["low end"] + [f"{i}|{i + 1}" for i in range(1, self.n)] + ["high end"]

    @property
    def worst_margin(self) -> float:
        """min over all margins (ends and overlaps); ≥ 0 iff the set covers the range."""
        return float(np.min(self.margins))

    @property
    def worst_overlap_margin(self) -> float | None:
        """min over the neighbour overlaps m_1..m_{n−1}; None for a single spring."""
        return float(np.min(self.margins[1:-1])) if self.n > 1 else None

    @property
    def covered_load_range(self) -> tuple[float, float]:
        """(lowest floor, highest ceiling) of the springs' allowed ranges (N); see :attr:`gaps`."""
        lo, hi = self.load_ranges
        ok = np.isfinite(lo)
        if not ok.any():
            return (math.nan, math.nan)
        return float(lo[ok].min()), float(hi[ok].max())

    def _union(self) -> list[tuple[float, float]]:
        lo, hi = self.load_ranges
        ivs = sorted((a, b) for a, b in zip(lo, hi) if np.isfinite(a))
        out: list[list[float]] = []
        for a, b in ivs:
            if out and a <= out[-1][1] * (1 + tc.RTOL):
                out[-1][1] = max(out[-1][1], b)
            else:
                out.append([a, b])
        return [(a, b) for a, b in out]

    @property
    def gaps(self) -> list[tuple[float, float]]:
        """Loads (N) between the lowest floor and highest ceiling that no spring allows."""
        u = self._union()
        return [(u[i][1], u[i + 1][0]) for i in range(len(u) - 1)]

    @property
    def uncovered(self) -> list[tuple[float, float]]:
        """Parts (N) of the requested range that no spring allows (ends included)."""
        L_lo, L_hi = self.load_range
        out, x = [], L_lo
        for a, b in self._union():
            if b <= x:
                continue
            if a > x * (1 + tc.RTOL):
                out.append((x, min(a, L_hi)))
            x = max(x, b)
            if x >= L_hi:
                break
        if x < L_hi * (1 - tc.RTOL):
            out.append((x, L_hi))
        return [(a, b) for a, b in out if b > a * (1 + tc.RTOL)]

    @property
    def covers(self) -> bool:
        """True when every requested load is allowed by some spring at the worst-case bias."""
        return not self.uncovered

    def verify(self, n_loads: int = 400, n_mu: int = 9) -> list[str]:
        """Check the set point by point against every row of Table I; return the failures.

        On ``n_loads`` log-spaced loads in the requested range (plus every range end), for
        every spring whose reported allowed range contains the load, evaluate every
        constraint of :data:`design.constraints.TABLE_I` at both bias extremes (k_soft and
        k_stiff) and ``n_mu`` values of μ in [0.1, 0.9]. Independent of the margins.

        Returns
        -------
        list of str
            Empty when the set covers the range; otherwise one message per failure
            (uncovered load, or the first violated rule with its point).
        """
        lo, hi = self.load_ranges
        ks, kt = self.spring_constant_ranges
        L_lo, L_hi = self.load_range
        ends = np.concatenate([lo[np.isfinite(lo)], hi[np.isfinite(hi)]])
        loads = np.concatenate([np.geomspace(L_lo, L_hi, n_loads), ends])
        loads = np.unique(loads[(loads >= L_lo) & (loads <= L_hi)])
        mus = np.linspace(tc.MU_MIN.bound, tc.MU_MAX.bound, n_mu)
        failures: list[str] = []
        for nb in loads:
            inside = np.flatnonzero(
                np.isfinite(lo) & (lo <= nb * (1 + tc.RTOL)) & (nb <= hi * (1 + tc.RTOL))
            )
            if inside.size == 0:
                failures.append(f"Nb = {tc.format_load(nb)} is allowed by no spring")
                continue
            for i in inside:
                k = np.array([ks[i], kt[i]])[:, None]
                v = tc.check(nb, k, mus[None, :])
                if v:
                    failures.append(
                        f"spring {i + 1} (w = {self.springs[i].width_um:.4g} µm): {v[0].message}"
                    )
        return failures

    # -- output -----------------------------------------------------------------------
    def spring_json(self) -> list[dict]:
        ks, kt = self.spring_constant_ranges
        lo, hi = self.load_ranges
        return [
            {
                "width_um": s.width_um,
                "drawn_width_um": s.drawn_width_um,
                "spring_constant_N_per_m": s.spring_constant,
                "spring_constant_range_N_per_m": [float(ks[i]), float(kt[i])],
                "normal_load_range_uN": (
                    [_uN(lo[i]), _uN(hi[i])] if np.isfinite(lo[i]) else None
                ),
                "suspension": s.suspension.to_json(),
            }
            for i, s in enumerate(self.springs)
        ]

    def to_json(self) -> dict:
        """Springs, coverage and margins as a JSON-ready dict (loads in µN)."""
        c_lo, c_hi = self.covered_load_range
        wom = self.worst_overlap_margin
        return {
            "springs": self.spring_json(),
            "covered_load_range_uN": [_uN(c_lo), _uN(c_hi)] if math.isfinite(c_lo) else None,
            "covers_load_range": self.covers,
            "worst_margin": self.worst_margin,
            "worst_overlap_margin": wom,
            "margins": [
                {"between": lab, "value": float(m)}
                for lab, m in zip(self.margin_labels, self.margins)
            ],
            "gaps_uN": [[_uN(a), _uN(b)] for a, b in self.gaps],
            "uncovered_uN": [[_uN(a), _uN(b)] for a, b in self.uncovered],
        }

    def report_lines(self) -> list[str]:
        ks, kt = self.spring_constant_ranges
        lo, hi = self.load_ranges
        lines = [
            f"  {'#':>2}  {'suspension':<16} {'w (µm)':>7} {'drawn':>7} {'k (N/m)':>9} "
            f"{'k range (N/m)':>17}  {'allowed Nb (µN)':>18}"
        ]
        for i, s in enumerate(self.springs):
            rng = f"{_uN(lo[i]):.4g}-{_uN(hi[i]):.4g}" if np.isfinite(lo[i]) else "none"
            lines.append(
                f"  {i + 1:>2}  {s.suspension.name + f' ({s.suspension.length_um:g} µm)':<16} "
                f"{s.width_um:7.3f} {s.drawn_width_um:7.3f} {s.spring_constant:9.4g} "
                f"{f'{ks[i]:.3g}-{kt[i]:.3g}':>17}  {rng:>18}"
            )
        lines.append(
            "  margins ln(ratio): "
            + ", ".join(f"{lab} {m:+.3f}" for lab, m in zip(self.margin_labels, self.margins))
        )
        worst = int(np.argmin(self.margins))
        wom = self.worst_overlap_margin
        lines.append(
            f"  worst margin {self.worst_margin:+.3f} ({self.margin_labels[worst]})"
            + (f"; worst overlap {wom:+.3f}" if wom is not None else "")
        )
        c_lo, c_hi = self.covered_load_range
        cov = f"  allowed loads span {_fmt_range_uN(c_lo, c_hi)}"
        if self.gaps:
            cov += "; gaps " + ", ".join(_fmt_range_uN(a, b) for a, b in self.gaps)
        lines.append(cov)
        if self.uncovered:
            lines.append(
                "  does NOT cover "
                + ", ".join(_fmt_range_uN(a, b) for a, b in self.uncovered)
                + " of the requested range"
            )
        else:
            lines.append(f"  covers the requested {_fmt_range_uN(*self.load_range)}")
        return lines


def paper_spring_set(
    load_range: tuple[float, float], etch_bias_um: float = ETCH_BIAS_UM
) -> SpringSet:
    """The paper's four springs (0.028, 0.24, 2.13, 20.3 N/m) as a :class:`SpringSet`.

    Parameters
    ----------
    load_range : (float, float)
        Requested range (N) to judge them against.
    etch_bias_um : float
        Etch-bias uncertainty per edge (µm).
    """
    return SpringSet(paper_springs(), load_range, etch_bias_um, label="paper (Table I, Fig. 3)")


# --------------------------------------------------------------------------------------
# Limits of what any set can cover
# --------------------------------------------------------------------------------------
def _admissible_widths(s: Suspension, b: float) -> tuple[float, float]:
    """Nominal-width interval (µm) of ``s`` whose realisations ``w ± 2b`` keep k in Table I."""
    c = s.coefficient
    lb = max(s.min_width_um, (tc.K_MIN.bound / c) ** (1 / 3) + 2 * b)
    ub = min(s.max_width_um, (tc.K_MAX.bound / c) ** (1 / 3) - 2 * b)
    return lb, ub


def coverable_load_range(
    suspensions: Sequence[Suspension] = DEFAULT_SUSPENSIONS, etch_bias_um: float = ETCH_BIAS_UM
) -> tuple[tuple[float, float], tuple[str, str]]:
    """Lowest and highest load (N) any allowed spring can cover at the worst-case bias.

    The floor of a spring grows with its width, so the lowest reachable load is the floor of
    the narrowest admissible width on the most compliant suspension (admissible: inside the
    process bounds with k_soft ≥ 0.01 N/m and k_stiff ≤ 100 N/m); the highest is the
    ceiling of the widest admissible width on the stiffest. Both are clipped to Table I.

    Returns
    -------
    ((low, high), (why_low, why_high))
        Loads in N and a phrase for each saying which spring sets it.
    """
    b = float(etch_bias_um)
    best_lo, why_lo, best_hi, why_hi = math.inf, "", 0.0, ""
    for s in suspensions:
        lb, ub = _admissible_widths(s, b)
        if lb > ub:
            continue
        k_soft_lb, k_stiff_lb = s.spring_constant_range(lb, b)
        lo, _ = tc.elongation_window(k_soft_lb, k_stiff_lb)
        lo = max(float(lo), tc.LOAD_MIN.bound)
        if lo < best_lo:
            best_lo = lo
            why_lo = (
                f"w = {lb:.3g} µm on the {s.name} suspension ({s.length_um:g} µm), "
                f"k = {k_soft_lb:.3g}-{k_stiff_lb:.3g} N/m"
            )
        k_soft_ub, k_stiff_ub = s.spring_constant_range(ub, b)
        _, hi = tc.elongation_window(k_soft_ub, k_stiff_ub)
        hi = min(float(hi), tc.LOAD_MAX.bound)
        if hi > best_hi:
            best_hi = hi
            why_hi = (
                f"w = {ub:.3g} µm on the {s.name} suspension ({s.length_um:g} µm), "
                f"k = {k_soft_ub:.3g}-{k_stiff_ub:.3g} N/m"
            )
    if not why_lo:
        raise InfeasibleDesignError(
            "no suspension admits a width whose realisations keep 0.01 < k < 100 N/m"
        )
    return (best_lo, best_hi), (why_lo, why_hi)


# --------------------------------------------------------------------------------------
# The NLP (one per number of springs, cached)
# --------------------------------------------------------------------------------------
_LOG_LO_PER_K = math.log(tc.ELONGATION_RESOLUTION.bound / tc.MU_MIN.bound)  # ln(lo/k_stiff), ln m
_LOG_HI_PER_K = math.log(tc.PULLER_TRAVEL.bound / tc.MU_MAX.bound)  # ln(hi/k_soft), ln m


@functools.cache
def _maximin_solver(n: int) -> ca.Function:
    """Ipopt solver: maximise t s.t. m_j ≥ a_j·t + (1 − a_j)·floor_j, nominal k ordered.

    x = [u (n): ln(w/µm); t]; p = [ln c (n); 2b (µm); ln L_lo; ln L_hi; a (n+1); floor (n+1)].
    """
    u = ca.SX.sym("u", n)
    t = ca.SX.sym("t")
    log_c = ca.SX.sym("log_c", n)
    two_b = ca.SX.sym("two_b")
    log_lo_req = ca.SX.sym("log_lo_req")
    log_hi_req = ca.SX.sym("log_hi_req")
    active = ca.SX.sym("active", n + 1)
    floor = ca.SX.sym("floor", n + 1)
    w = ca.exp(u)
    log_lo = log_c + 3 * ca.log(w + two_b) + _LOG_LO_PER_K  # floor: stiffest realisation
    log_hi = log_c + 3 * ca.log(w - two_b) + _LOG_HI_PER_K  # ceiling: softest realisation
    inner = [log_hi[i] - log_lo[i + 1] for i in range(n - 1)]
    m = ca.vertcat(log_lo_req - log_lo[0], *inner, log_hi[n - 1] - log_hi_req)
    g = [m - active * t - (1 - active) * floor]
    if n > 1:
        log_k = log_c + 3 * u
        g.append(ca.vertcat(*[log_k[i + 1] - log_k[i] for i in range(n - 1)]))
    nlp = {
        "x": ca.vertcat(u, t),
        "p": ca.vertcat(log_c, two_b, log_lo_req, log_hi_req, active, floor),
        "f": -t,
        "g": ca.vertcat(*g),
    }
    return ca.nlpsol(f"spring_set_{n}", "ipopt", nlp, _IPOPT_OPTS)


def _margins_np(log_c, u, b, log_lo_req, log_hi_req) -> np.ndarray:
    w = np.exp(u)
    log_lo = log_c + 3 * np.log(w + 2 * b) + _LOG_LO_PER_K
    log_hi = log_c + 3 * np.log(w - 2 * b) + _LOG_HI_PER_K
    return np.concatenate(
        [[log_lo_req - log_lo[0]], log_hi[:-1] - log_lo[1:], [log_hi[-1] - log_hi_req]]
    )


@dataclass(frozen=True)
class _Candidate:
    assignment: tuple[Suspension, ...]
    widths_um: tuple[float, ...]
    worst_margin: float  # min over all margins (stage one)
    balanced_margin: float  # min over the margins not pinned at a hard limit (stage two)
    start: int


def _solve_assignment(
    assignment: tuple[Suspension, ...],
    b: float,
    load_range: tuple[float, float],
    starts: list[np.ndarray],
    counter: list[int],
) -> list[_Candidate]:
    """Both stages for one suspension assignment, from every start.

    Stage one maximises the worst of all margins. An end margin is *pinned* when even its
    own best value (spring 1 at its narrowest / spring n at its widest admissible width)
    does not exceed that optimum: it is then held at the stage-one value and stage two
    maximises the worst of the remaining margins, so a hard limit at one end does not
    leave the rest unbalanced (a lexicographic maximin).
    """
    n = len(assignment)
    solver = _maximin_solver(n)
    log_c = np.array([math.log(s.coefficient) for s in assignment])
    bounds = [_admissible_widths(s, b) for s in assignment]
    lbu = np.log([lb for lb, _ in bounds])
    ubu = np.log([ub for _, ub in bounds])
    log_lo_req, log_hi_req = math.log(load_range[0]), math.log(load_range[1])
    lbx = np.concatenate([lbu, [-ca.inf]])
    ubx = np.concatenate([ubu, [ca.inf]])
    n_g = (n + 1) + (n - 1)
    lbg = np.zeros(n_g)
    ubg = np.full(n_g, ca.inf)
    head = [log_c, [2 * b, log_lo_req, log_hi_req]]
    # Best value each end margin can reach on its own.
    end_max = (
        _margins_np(log_c, lbu, b, log_lo_req, log_hi_req)[0],
        _margins_np(log_c, ubu, b, log_lo_req, log_hi_req)[-1],
    )
    out = []
    for si, u0 in enumerate(starts):
        u0 = np.clip(u0, lbu, ubu)
        m0 = _margins_np(log_c, u0, b, log_lo_req, log_hi_req)
        p = np.concatenate(head + [np.ones(n + 1), np.zeros(n + 1)])
        sol = solver(x0=np.concatenate([u0, [m0.min()]]), p=p, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
        counter[0] += 1
        u = np.clip(np.asarray(sol["x"]).ravel()[:n], lbu, ubu)
        m = _margins_np(log_c, u, b, log_lo_req, log_hi_req)
        t1 = float(m.min())
        free = np.ones(n + 1, dtype=bool)
        free[0] = end_max[0] > t1 + 1e-6
        free[-1] = end_max[1] > t1 + 1e-6
        if t1 >= -_COVER_TOL and not free.all() and free.any():
            floor = np.where(free, 0.0, max(t1 - 1e-8, 0.0))
            p2 = np.concatenate(head + [free.astype(float), floor])
            sol2 = solver(x0=np.concatenate([u, [m[free].min()]]), p=p2, lbx=lbx, ubx=ubx,
                          lbg=lbg, ubg=ubg)
            counter[0] += 1
            u2 = np.clip(np.asarray(sol2["x"]).ravel()[:n], lbu, ubu)
            m2 = _margins_np(log_c, u2, b, log_lo_req, log_hi_req)
            if m2.min() >= min(t1, 0.0) - _COVER_TOL and m2[free].min() >= m[free].min():
                u, m = u2, m2
        out.append(
            _Candidate(
                assignment,
                tuple(float(x) for x in np.exp(u)),
                float(m.min()),
                float(m[free].min()) if free.any() else float(m.min()),
                si,
            )
        )
    return out


def _starts(
    assignment: tuple[Suspension, ...], b: float, load_range: tuple[float, float],
    n_starts: int, rng: np.random.Generator,
) -> list[np.ndarray]:
    """Geometric spacing of k across the range, then seeded random log-widths."""
    n = len(assignment)
    k_first = load_range[0] / math.exp(_LOG_LO_PER_K)
    k_last = load_range[1] / math.exp(_LOG_HI_PER_K)
    k = np.geomspace(k_first, k_last, n) if n > 1 else np.array([math.sqrt(k_first * k_last)])
    starts = [np.log([s.width_um(ki) for s, ki in zip(assignment, k)])]
    bounds = np.array([_admissible_widths(s, b) for s in assignment])
    for _ in range(max(n_starts - 1, 0)):
        u = rng.uniform(np.log(bounds[:, 0]), np.log(bounds[:, 1]))
        log_k = np.log([s.coefficient for s in assignment]) + 3 * u
        starts.append(u[np.argsort(log_k)])
    return starts


# --------------------------------------------------------------------------------------
# Result
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Attempt:
    """Best worst margin found with ``n`` springs (over assignments and starts)."""

    n: int
    worst_margin: float
    covers: bool


@dataclass(frozen=True)
class SpringSetResult:
    """An optimised spring set, the paper's set under the same measures, and the evidence.

    Attributes
    ----------
    spring_set : SpringSet
        The design (fewest springs, largest worst margin).
    reference : SpringSet
        The paper's four springs judged against the same range and bias.
    requested_load_range_uN : (float, float) or None
        What the caller asked for (None: Table I's range, clipped to what is reachable).
    attempts : tuple of Attempt
        One per n tried: the best worst margin (negative: n springs cannot cover).
    notes : tuple of str
        Decisions the caller should know about (e.g. a clipped default range).
    n_solves : int
        Ipopt solves run.
    n_starts : int
        Starts per suspension assignment.
    n_best_found : int
        Starts (over all assignments) whose result matched the best worst margin.
    """

    spring_set: SpringSet
    reference: SpringSet
    requested_load_range_uN: tuple[float, float] | None
    attempts: tuple[Attempt, ...]
    notes: tuple[str, ...] = ()
    n_solves: int = 0
    n_starts: int = 1
    n_best_found: int = 1

    @property
    def springs(self) -> tuple[SpringDesign, ...]:
        return self.spring_set.springs

    @property
    def load_range(self) -> tuple[float, float]:
        """Designed load range (N)."""
        return self.spring_set.load_range

    @property
    def etch_bias_um(self) -> float:
        return self.spring_set.etch_bias_um

    @property
    def worst_margin(self) -> float:
        return self.spring_set.worst_margin

    def report(self) -> str:
        """Readable text: the design, why n is the fewest, and the paper's set beside it."""
        s = self.spring_set
        lines = [
            f"Spring set covering Nb = {_fmt_range_uN(*s.load_range)} for every μ in "
            f"[{tc.MU_MIN.bound:g}, {tc.MU_MAX.bound:g}], etch bias ±{s.etch_bias_um:g} µm "
            "per edge (worst case per spring)",
        ]
        lines += [f"note: {n}" for n in self.notes]
        fewer = [a for a in self.attempts if a.n < s.n]
        why = "; ".join(
            f"{a.n} spring{'s' if a.n > 1 else ''}: best worst margin {a.worst_margin:+.3f}"
            for a in fewer
        )
        head = f"{s.n} spring{'s' if s.n > 1 else ''}"
        if why:
            head += f" (fewer cannot cover: {why})"
        elif s.n > 1:
            head += " (number fixed by the caller)"
        lines.append(head)
        lines += s.report_lines()
        lines.append(
            "Paper's springs (" + ", ".join(f"{k:g}" for k in PAPER_SPRING_CONSTANTS)
            + " N/m; 0.028 N/m on the long suspension) under the same measures:"
        )
        lines += self.reference.report_lines()
        lines.append(
            "margins: low end ln(L_lo/lo_1), i|i+1 ln(hi_i/lo_i+1), high end ln(hi_n/L_hi); "
            "lo from k_stiff·90 nm/0.1, hi from k_soft·100 µm/0.9"
        )
        lines.append(
            f"solver: Ipopt, {self.n_solves} solves, {self.n_starts} starts per suspension "
            f"assignment; best worst margin reached {self.n_best_found} times"
        )
        return "\n".join(lines)

    def to_json(self) -> dict:
        """JSON-ready dict; loads in µN, widths in µm, spring constants in N/m."""
        d = self.spring_set.to_json()
        d.update(
            {
                "n_springs": self.spring_set.n,
                "reference": self.reference.to_json(),
                "etch_bias_um": self.etch_bias_um,
                "load_range_uN": [_uN(x) for x in self.load_range],
                "requested_load_range_uN": (
                    list(self.requested_load_range_uN) if self.requested_load_range_uN else None
                ),
                "attempts": [
                    {"n_springs": a.n, "worst_margin": a.worst_margin, "covers": a.covers}
                    for a in self.attempts
                ],
                "notes": list(self.notes),
                "margin_definition": (
                    "natural-log ratios: low end ln(L_lo/lo_1), overlap i|i+1 ln(hi_i/lo_{i+1}), "
                    "high end ln(hi_n/L_hi); lo_i = k_stiff·90 nm/0.1, hi_i = k_soft·100 µm/0.9 "
                    "at realised widths w ± 2·etch_bias"
                ),
            }
        )
        return d

    def plot(self, ax=None):
        """Fig. 3: the Table I region in the k–Nb plane with this set and the paper's."""
        from .plots import plot_design

        return plot_design(self, ax=ax)


# --------------------------------------------------------------------------------------
# Entry point
# --------------------------------------------------------------------------------------
def _round_sig(x: float, sig: int, up: bool) -> float:
    e = math.floor(math.log10(abs(x))) - sig + 1
    f = (math.ceil if up else math.floor)(x / 10.0**e)
    return f * 10.0**e


def design_spring_set(
    load_range_uN: tuple[float, float] | None = None,
    *,
    n_springs: int | None = None,
    etch_bias_um: float = ETCH_BIAS_UM,
    suspensions: Sequence[Suspension] = DEFAULT_SUSPENSIONS,
    max_springs: int = MAX_SPRINGS,
    n_starts: int = 2,
    seed: int = 0,
) -> SpringSetResult:
    """Fewest springs covering a normal-load range for every μ, robust to the etch bias.

    Parameters
    ----------
    load_range_uN : (float, float), optional
        Requested normal-load range (µN), inside Table I's [0.01, 452] µN. Default: Table
        I's range, with its low end raised to the lowest load any allowed spring can resolve
        at the worst-case bias (10 nN itself needs k ≤ 0.0111 N/m at the stiffest and
        ≥ 0.01 N/m at the softest realisation, i.e. a width ≥ 11 µm at b = 0.1 µm). The
        clipping is stated in :attr:`SpringSetResult.notes`. An explicit range is never
        clipped.
    n_springs : int, optional
        Fix the number of springs instead of searching for the fewest.
    etch_bias_um : float
        Uncertainty b of the edge bias per edge (µm), ≥ 0; realised widths are ``w ± 2b``.
    suspensions : sequence of Suspension
        Candidate suspensions; each spring is made on one of them (the default offers the
        paper's 189 µm beam and the 390 µm beam of the softest spring). Their process width
        bounds apply to the nominal effective widths.
    max_springs : int
        Largest n tried when ``n_springs`` is None.
    n_starts : int
        Ipopt starts per suspension assignment (first: geometric spacing of k).
    seed : int
        Seed of the random starts.

    Returns
    -------
    SpringSetResult

    Raises
    ------
    InfeasibleDesignError (a ValueError)
        When no set of up to ``max_springs`` (or exactly ``n_springs``) springs covers the
        range; the message names the limit (Table I's load bounds, the reachable loads at
        this bias and these widths, or the best margin found).
    ValueError
        On malformed arguments.
    """
    b = float(etch_bias_um)
    if not math.isfinite(b) or b < 0:
        raise ValueError(f"etch_bias_um = {etch_bias_um!r}: must be a finite number >= 0 µm")
    suspensions = tuple(suspensions)
    if not suspensions or not all(isinstance(s, Suspension) for s in suspensions):
        raise ValueError("suspensions: must be a non-empty sequence of Suspension")
    for s in suspensions:
        if s.min_width_um <= 2 * b:
            raise ValueError(
                f"etch_bias_um = {b:g} µm: suspension {s.name!r} allows widths down to "
                f"{s.min_width_um:g} µm, which must exceed 2·etch_bias_um = {2 * b:g} µm"
            )
    for name, v, lo in (("max_springs", max_springs, 1), ("n_starts", n_starts, 1)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
            raise ValueError(f"{name} = {v!r}: must be an integer >= {lo}")
    if n_springs is not None and (
        isinstance(n_springs, bool) or not isinstance(n_springs, (int, np.integer)) or n_springs < 1
    ):
        raise ValueError(f"n_springs = {n_springs!r}: must be an integer >= 1")
    # Suspensions ordered from the most compliant: softer springs use earlier ones.
    suspensions = tuple(sorted(suspensions, key=lambda s: s.coefficient, reverse=False))

    table_lo, table_hi = tc.LOAD_MIN.bound, tc.LOAD_MAX.bound
    table_txt = f"Table I allows Nb in [{tc.format_load(table_lo)}, {tc.format_load(table_hi)}]"
    up_to = f"{n_springs}" if n_springs is not None else f"up to {max_springs}"
    (reach_lo, reach_hi), (why_lo, why_hi) = coverable_load_range(suspensions, b)
    notes: list[str] = []
    if load_range_uN is None:
        requested = None
        lo, hi = table_lo, table_hi
        if reach_lo > lo * (1 + tc.RTOL):
            lo = _round_sig(reach_lo * 1.001, 3, up=True)
            notes.append(
                f"Table I's floor of {tc.format_load(table_lo)} cannot be reached at ±{b:g} µm "
                f"etch bias with widths >= the process minimum; the lowest load any allowed "
                f"spring resolves for every μ is {tc.format_load(reach_lo)} ({why_lo}); "
                f"designing from {tc.format_load(lo)}"
            )
        if reach_hi < hi * (1 - tc.RTOL):
            hi = _round_sig(reach_hi * 0.999, 3, up=False)
            notes.append(
                f"Table I's ceiling of {tc.format_load(table_hi)} cannot be reached; the highest "
                f"load any allowed spring covers is {tc.format_load(reach_hi)} ({why_hi})"
            )
    else:
        lo, hi = _validate_load_range_uN(load_range_uN)
        requested = (_uN(lo), _uN(hi))
        what = f"no set of {up_to} springs covers {_fmt_range_uN(lo, hi)}"
        if lo < table_lo * (1 - tc.RTOL) or hi > table_hi * (1 + tc.RTOL):
            raise InfeasibleDesignError(f"{what}: {table_txt}")
        if lo < reach_lo * (1 - tc.RTOL):
            raise InfeasibleDesignError(
                f"{what}: at ±{b:g} µm etch bias the lowest load any allowed spring resolves "
                f"for every μ in [0.1, 0.9] is {tc.format_load(reach_lo)} ({why_lo}); {table_txt}"
            )
        if hi > reach_hi * (1 + tc.RTOL):
            raise InfeasibleDesignError(
                f"{what}: at ±{b:g} µm etch bias the highest load any allowed spring covers "
                f"for every μ in [0.1, 0.9] is {tc.format_load(reach_hi)} ({why_hi}); {table_txt}"
            )
    load_range = (lo, hi)

    rng = np.random.default_rng(seed)
    counter = [0]
    attempts: list[Attempt] = []
    chosen: SpringSet | None = None
    n_best_found = 0
    ns = [int(n_springs)] if n_springs is not None else list(range(1, max_springs + 1))
    for n in ns:
        cands: list[_Candidate] = []
        for idx in itertools.combinations_with_replacement(range(len(suspensions)), n):
            assignment = tuple(suspensions[i] for i in idx)
            bounds = [_admissible_widths(s, b) for s in assignment]
            if any(lb > ub for lb, ub in bounds):
                continue
            starts = _starts(assignment, b, load_range, n_starts, rng)
            cands += _solve_assignment(assignment, b, load_range, starts, counter)
        if not cands:
            attempts.append(Attempt(n, -math.inf, False))
            continue
        best_t = max(c.worst_margin for c in cands)
        covers = best_t >= -_COVER_TOL
        log.info("n = %d springs: best worst margin %.4g over %d runs", n, best_t, len(cands))
        if covers:
            # Among candidates within 1e-6 of the best worst margin, take the best balanced.
            tied = [c for c in cands if c.worst_margin >= best_t - 1e-6]
            best = max(tied, key=lambda c: (c.balanced_margin, c.worst_margin))
            n_best_found = sum(c.balanced_margin >= best.balanced_margin - 1e-6 for c in tied)
            trial = SpringSet(
                tuple(SpringDesign(w, s) for w, s in zip(best.widths_um, best.assignment)),
                load_range, b, label="optimised",
            )
            failures = trial.verify()
            if failures:  # should not happen: margins and the pointwise check disagree
                log.warning("n = %d: optimum fails the pointwise check: %s", n, failures[0])
                covers = False
            else:
                chosen = trial
        attempts.append(Attempt(n, best_t, covers))
        if chosen is not None:
            break
    if chosen is None:
        best = max(attempts, key=lambda a: a.worst_margin)
        raise InfeasibleDesignError(
            f"no set of {up_to} springs covers {_fmt_range_uN(lo, hi)} at ±{b:g} µm etch bias: "
            f"the best {best.n}-spring set has worst margin {best.worst_margin:.3g} (< 0, a gap "
            f"of ratio {math.exp(-best.worst_margin):.3g}); {table_txt}"
        )
    return SpringSetResult(
        spring_set=chosen,
        reference=paper_spring_set(load_range, b),
        requested_load_range_uN=requested,
        attempts=tuple(attempts),
        notes=tuple(notes),
        n_solves=counter[0],
        n_starts=n_starts,
        n_best_found=n_best_found,
    )

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

Layout: the set's measures, pointwise check, JSON and report lines are
:class:`~design.spring_coverage.SpringSet` (:mod:`design.spring_coverage`); the NLP of one
suspension assignment is :mod:`design.spring_maximin`; the result and its report are
:mod:`design.spring_set_result`. Their public names are importable from here.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Sequence

import numpy as np

from . import constraints as tc
from .spring_coverage import SpringSet, format_load_range_uN, paper_spring_set, to_uN
from .spring_maximin import COVER_TOL, MaximinSolution, admissible_widths, maximin_starts, solve_assignment
from .spring_set_result import Attempt, SpringSetResult
from .springs import ETCH_BIAS_UM, LONG_SUSPENSION, PAPER_SUSPENSION, SpringDesign, Suspension

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


class InfeasibleDesignError(ValueError):
    """No spring set meets the request; the message says which limit stops it."""


def _validate_load_range_uN(load_range_uN) -> tuple[float, float]:
    """The requested (low, high) in µN as loads in N; refused unless 0 < low < high."""
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
        lb, ub = admissible_widths(s, b)
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
    b = _checked_etch_bias(etch_bias_um)
    suspensions = _checked_suspensions(suspensions, b)
    _check_counts(n_springs, max_springs, n_starts)
    up_to = f"{n_springs}" if n_springs is not None else f"up to {max_springs}"
    load_range, requested, notes = _load_range_to_design(load_range_uN, suspensions, b, up_to)
    counter = [0]
    ns = [int(n_springs)] if n_springs is not None else list(range(1, max_springs + 1))
    attempts, chosen, n_best_found = _fewest_springs(
        ns, suspensions, b, load_range, n_starts, np.random.default_rng(seed), counter
    )
    if chosen is None:
        raise _no_cover_error(attempts, up_to, load_range, b)
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


# --------------------------------------------------------------------------------------
# Steps of design_spring_set: the arguments, the load range, the search over n
# --------------------------------------------------------------------------------------
def _checked_etch_bias(etch_bias_um) -> float:
    """The etch bias b (µm) as a float; refused unless finite and >= 0."""
    b = float(etch_bias_um)
    if not math.isfinite(b) or b < 0:
        raise ValueError(f"etch_bias_um = {etch_bias_um!r}: must be a finite number >= 0 µm")
    return b


def _checked_suspensions(suspensions: Sequence[Suspension], b: float) -> tuple[Suspension, ...]:
    """The candidate suspensions ordered from the most compliant (softer springs use earlier
    ones); refused when empty or when the bias can etch their narrowest beam away."""
    suspensions = tuple(suspensions)
    if not suspensions or not all(isinstance(s, Suspension) for s in suspensions):
        raise ValueError("suspensions: must be a non-empty sequence of Suspension")
    for s in suspensions:
        if s.min_width_um <= 2 * b:
            raise ValueError(
                f"etch_bias_um = {b:g} µm: suspension {s.name!r} allows widths down to "
                f"{s.min_width_um:g} µm, which must exceed 2·etch_bias_um = {2 * b:g} µm"
            )
    return tuple(sorted(suspensions, key=lambda s: s.coefficient, reverse=False))


def _check_counts(n_springs, max_springs, n_starts) -> None:
    """Refuse a spring count, largest count or start count that is not an integer >= 1."""
    for name, v, lo in (("max_springs", max_springs, 1), ("n_starts", n_starts, 1)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
            raise ValueError(f"{name} = {v!r}: must be an integer >= {lo}")
    if n_springs is not None and (
        isinstance(n_springs, bool) or not isinstance(n_springs, (int, np.integer)) or n_springs < 1
    ):
        raise ValueError(f"n_springs = {n_springs!r}: must be an integer >= 1")


def _table_i_loads() -> str:
    """Table I's load bounds, as every infeasibility message ends."""
    return (
        f"Table I allows Nb in [{tc.format_load(tc.LOAD_MIN.bound)}, "
        f"{tc.format_load(tc.LOAD_MAX.bound)}]"
    )


def _load_range_to_design(
    load_range_uN, suspensions: tuple[Suspension, ...], b: float, up_to: str
) -> tuple[tuple[float, float], tuple[float, float] | None, list[str]]:
    """(load range in N, the caller's request in µN or None, notes): Table I's range clipped
    to what any allowed spring reaches, or the caller's range checked against both."""
    reach, why = coverable_load_range(suspensions, b)
    if load_range_uN is None:
        load_range, notes = _default_load_range(reach, why, b)
        return load_range, None, notes
    lo, hi = _validate_load_range_uN(load_range_uN)
    _check_requested_range(lo, hi, reach, why, b, up_to)
    return (lo, hi), (to_uN(lo), to_uN(hi)), []


def _default_load_range(
    reach: tuple[float, float], why: tuple[str, str], b: float
) -> tuple[tuple[float, float], list[str]]:
    """Table I's load range (N) with each end the springs cannot reach at this bias moved
    inside, rounded to 3 digits; a note for each end moved."""
    (reach_lo, reach_hi), (why_lo, why_hi) = reach, why
    table_lo, table_hi = tc.LOAD_MIN.bound, tc.LOAD_MAX.bound
    lo, hi = table_lo, table_hi
    notes: list[str] = []
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
    return (lo, hi), notes


def _round_sig(x: float, sig: int, up: bool) -> float:
    """``x`` rounded up or down to ``sig`` significant digits (a clipped range end stays reachable)."""
    e = math.floor(math.log10(abs(x))) - sig + 1
    f = (math.ceil if up else math.floor)(x / 10.0**e)
    return f * 10.0**e


def _check_requested_range(
    lo: float, hi: float, reach: tuple[float, float], why: tuple[str, str], b: float, up_to: str
) -> None:
    """Refuse a requested range (N) outside Table I or beyond the loads any allowed spring
    reaches at this bias (an explicit range is never clipped)."""
    (reach_lo, reach_hi), (why_lo, why_hi) = reach, why
    table_txt = _table_i_loads()
    what = f"no set of {up_to} springs covers {format_load_range_uN(lo, hi)}"
    if lo < tc.LOAD_MIN.bound * (1 - tc.RTOL) or hi > tc.LOAD_MAX.bound * (1 + tc.RTOL):
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


def _fewest_springs(
    ns: list[int], suspensions: tuple[Suspension, ...], b: float, load_range: tuple[float, float],
    n_starts: int, rng: np.random.Generator, counter: list[int],
) -> tuple[list[Attempt], SpringSet | None, int]:
    """Try each n in turn and stop at the first whose best set covers the range and passes
    the pointwise check: (one attempt per n tried, that set or None, starts that reached it)."""
    attempts: list[Attempt] = []
    for n in ns:
        cands = _assignment_solutions(n, suspensions, b, load_range, n_starts, rng, counter)
        if not cands:
            attempts.append(Attempt(n, -math.inf, False))
            continue
        best_t = max(c.worst_margin for c in cands)
        covers = best_t >= -COVER_TOL
        log.info("n = %d springs: best worst margin %.4g over %d runs", n, best_t, len(cands))
        chosen, n_best_found = _verified_best(cands, best_t, n, load_range, b) if covers else (None, 0)
        attempts.append(Attempt(n, best_t, chosen is not None))
        if chosen is not None:
            return attempts, chosen, n_best_found
    return attempts, None, 0


def _assignment_solutions(
    n: int, suspensions: tuple[Suspension, ...], b: float, load_range: tuple[float, float],
    n_starts: int, rng: np.random.Generator, counter: list[int],
) -> list[MaximinSolution]:
    """Every start's solution for every admissible assignment of the suspensions to n
    springs (softer springs on the more compliant suspensions)."""
    cands: list[MaximinSolution] = []
    for idx in itertools.combinations_with_replacement(range(len(suspensions)), n):
        assignment = tuple(suspensions[i] for i in idx)
        bounds = [admissible_widths(s, b) for s in assignment]
        if any(lb > ub for lb, ub in bounds):
            continue
        starts = maximin_starts(assignment, b, load_range, n_starts, rng)
        cands += solve_assignment(assignment, b, load_range, starts, counter)
    return cands


def _verified_best(
    cands: list[MaximinSolution], best_t: float, n: int, load_range: tuple[float, float], b: float
) -> tuple[SpringSet | None, int]:
    """The best balanced set among the solutions within 1e-6 of the best worst margin, or
    None when it fails the pointwise check; and how many starts reached it."""
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
        return None, n_best_found
    return trial, n_best_found


def _no_cover_error(
    attempts: list[Attempt], up_to: str, load_range: tuple[float, float], b: float
) -> InfeasibleDesignError:
    """The error when no n tried covers the range: the best attempt and the gap it leaves."""
    best = max(attempts, key=lambda a: a.worst_margin)
    return InfeasibleDesignError(
        f"no set of {up_to} springs covers {format_load_range_uN(*load_range)} at ±{b:g} µm etch bias: "
        f"the best {best.n}-spring set has worst margin {best.worst_margin:.3g} (< 0, a gap "
        f"of ratio {math.exp(-best.worst_margin):.3g}); {_table_i_loads()}"
    )

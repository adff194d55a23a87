"""Optimal experiment design: which (k, Nb, fp) runs make the friction parameters
well determined.

The information of a run is taken from the identification's own NLP
(:class:`identify.fitting.problem.Problem`), so the design optimises exactly what the fit will use:
the run is simulated at the nominal parameters without noise, its events extracted, the
NLP built with the camera noise model (``noise_nm``, 90 nm) as the frame standard
deviation, the per-run nuisances (plateau positions) solved with the friction parameters
held at their nominal values, and then

    I_run = Schur complement of the Gauss–Newton matrix JᵀJ on the friction parameters,
            the nuisances eliminated under the shooting constraints.

Nuisances belong to one run, so the information of a plan is the sum of its runs' (plus
a prior, for sequential design). Criteria, on the relative parameters θ/θ_nominal so that
A and E do not depend on units: D (max log det I), A (min trace I⁻¹), E (max λ_min I).
A plan of N runs (replicates allowed) is found by exhaustive enumeration when the number
of plans is small, else by a greedy build followed by Fedorov exchange until no swap
improves the criterion.

Layout: the runs to choose from are :mod:`design.candidates`, the information of one run
:mod:`design.information`, the plan found and its report :mod:`design.experiment_plan`,
and its Monte Carlo check :mod:`design.verification`; their public names are importable
from here.
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from identify.progress import Stage, reporter

from .candidates import PAPER_FPS_HZ as PAPER_FPS_HZ
from .candidates import PAPER_LOADS_UN as PAPER_LOADS_UN
from .candidates import Candidate, default_candidates, paper_plan
from .experiment_plan import ExperimentPlan
from .information import DEFAULT_FREE, STICK_SPEED, run_information, run_information_parts, run_problem
from .verification import JITTER_LOAD as JITTER_LOAD
from .verification import verify_plans

__all__ = ["Candidate", "CRITERIA", "ExperimentPlan", "run_information", "run_information_parts", "run_problem",
           "design_experiment", "paper_plan", "prior_from_fit", "verify_plans"]

CRITERIA = ("D", "A", "E")


# ----------------------------------------------------------------------------- criteria
def _criterion(I_rel: np.ndarray, name: str) -> float:
    """Larger is better for every criterion (A is negated).

    D and A need a positive definite information: a plan that leaves a direction
    undetermined scores −inf. (Measured: a near-singular matrix with a rounding-size
    negative eigenvalue gave −trace(inverse) = +1.5e16, and the A criterion chose that
    plan, whose standard errors are NaN; slogdet's sign misses an even count of them.)"""
    if name not in CRITERIA:
        raise ValueError(f"criterion {name!r}: choose one of {', '.join(CRITERIA)}")
    lam = np.linalg.eigvalsh(0.5 * (I_rel + I_rel.T))
    if name == "E":
        return float(lam[0])
    if not (np.all(np.isfinite(lam)) and lam[0] > 1e-12 * max(lam[-1], 0.0)):
        return -np.inf
    if name == "D":
        return float(np.sum(np.log(lam)))
    return -float(np.sum(1.0 / lam))


def _effective(B: np.ndarray, M: np.ndarray) -> np.ndarray:
    """B·M⁻¹·B: the inverse of the sandwich covariance B⁻¹MB⁻¹ (what the criteria and the
    predicted standard errors are taken of). M's pseudo-inverse: a direction in which the
    score does not vary (a plan that does not inform it) carries no information, rather
    than a huge one from a near-singular solve."""
    if not np.all(np.isfinite(M)) or not np.any(M):
        return np.zeros_like(B)
    E = B @ np.linalg.pinv(M, rcond=1e-12, hermitian=True) @ B
    return 0.5 * (E + E.T)


def _stderr(I_nat: np.ndarray) -> np.ndarray:
    """Standard errors from an information matrix; NaN where it leaves a parameter undetermined."""
    try:
        C = np.linalg.inv(I_nat)
        d = np.diag(C)
        return np.where(d > 0, np.sqrt(np.abs(d)), np.nan)
    except np.linalg.LinAlgError:
        return np.full(len(I_nat), np.nan)


# ----------------------------------------------------------------------------- plans
def design_experiment(n_runs: int, coating: str = "FOTAS", *, springs: Sequence[float] = (2.13, 20.3),
                      candidates: Sequence[Candidate] | None = None, criterion: str = "D",
                      free: Sequence[str] = DEFAULT_FREE, prior_information: np.ndarray | None = None,
                      noise_nm: float = 90.0, stick_speed_m_per_s: float = STICK_SPEED, travel_um: float = 30.0,
                      max_enumerate: int = 20000, reference: Sequence[Candidate] | None = None,
                      progress: Callable[[str], None] | bool | None = None) -> ExperimentPlan:
    """Choose ``n_runs`` runs from the candidate grid that optimise ``criterion``.

    ``progress`` (:mod:`identify.progress`): None draws a bar of the candidates'
    simulations with the time left on a terminal, False is silent, a callable gets each
    message."""
    from identify.model.params import parameter_set

    if criterion not in CRITERIA:
        raise ValueError(f"criterion {criterion!r}: choose one of {', '.join(CRITERIA)}")
    if int(n_runs) < 1:
        raise ValueError(f"runs = {n_runs!r}: must be a positive integer")
    free = tuple(free)
    nominal = {n: float(parameter_set(coating)[n]) for n in free}
    scale = np.array([abs(nominal[n]) for n in free])
    say = reporter(progress) or (lambda msg: None)
    cands = list(candidates) if candidates is not None else default_candidates(springs, travel_um)
    ref = list(reference) if reference is not None else paper_plan(n_runs, travel_um)
    infos = _information_of_runs(cands, ref, coating, free, noise_nm, stick_speed_m_per_s, say)
    I0 = np.zeros((len(free),) * 2) if prior_information is None else np.asarray(prior_information, float)
    usable = [c for c in cands if infos[c][2].get("used")]
    if not usable:
        raise ValueError("no candidate run carries information (all creep-free of slips or failed)")
    mats = [infos[c][:2] for c in usable]
    score = _PlanScore(mats, I0, scale, criterion)
    best, best_v, enumeration = _search_plans(score, len(usable), n_runs, max_enumerate)
    plan = [usable[i] for i in sorted(best)]
    B_ref = I0 + sum(infos[c][0] for c in ref)
    I_ref = _effective(B_ref, I0 + sum(infos[c][1] for c in ref))
    B_plan = I0 + sum(mats[i][0] for i in best)
    se = dict(zip(free, _stderr(score.effective(best)).tolist()))
    se_ref = dict(zip(free, _stderr(I_ref).tolist()))
    return ExperimentPlan(
        reference_note=_reference_note(ref, infos, se_ref, free), stick_speed_m_per_s=stick_speed_m_per_s,
        coating=coating, criterion=criterion, free=free, nominal=nominal, plan=plan, predicted_stderr=se,
        criterion_value=float(best_v), reference_plan=ref, reference_stderr=se_ref,
        reference_criterion_value=float(_criterion(score.relative(I_ref), criterion)),
        fisher_stderr=dict(zip(free, _stderr(B_plan).tolist())),
        reference_fisher_stderr=dict(zip(free, _stderr(B_ref).tolist())),
        candidates=[(c, dict(infos[c][2])) for c in cands],
        enumeration=enumeration,
        prior_used=prior_information is not None,
    )


def _information_of_runs(cands: list, ref: list, coating: str, free: tuple, noise_nm: float,
                         stick_speed_m_per_s: float, say: Callable[[str], None]) -> dict:
    """Candidate -> (B, M, summary) for every candidate (progress reported) and every
    reference run, each distinct run simulated once."""
    infos: dict = {}
    stage = Stage(say, "information of the candidates", len(cands))
    for c in cands:
        if c not in infos:
            infos[c] = _run_information_or_reason(c, coating, free, noise_nm, stick_speed_m_per_s)
        stage.advance(c.label())
    for c in ref:
        if c not in infos:
            infos[c] = _run_information_or_reason(c, coating, free, noise_nm, stick_speed_m_per_s)
    return infos


def _run_information_or_reason(c: Candidate, coating: str, free: tuple, noise_nm: float,
                               stick_speed_m_per_s: float) -> tuple:
    """(B, M, summary) of one run: its information and its score covariance; a run that
    fails to simulate carries none, with the error as its reason, rather than stopping the design."""
    try:
        B, M, s = run_information_parts(c, coating, free=free, noise_nm=noise_nm,
                                        stick_speed_m_per_s=stick_speed_m_per_s)
    except Exception as err:  # one candidate that fails to simulate is dropped, not fatal
        B = M = np.zeros((len(free),) * 2)
        s = dict(used=False, reason=f"{type(err).__name__}: {err}")
    return (B, M, s)


class _PlanScore:
    """The criterion of a plan given as indices into the usable runs' (B, M) pairs, a prior
    added; the plan search only ever asks this."""

    def __init__(self, mats: list, prior: np.ndarray, scale: np.ndarray, criterion: str):
        self.mats, self.prior, self.scale, self.criterion = mats, prior, scale, criterion

    def effective(self, idx, extra=0.0) -> np.ndarray:
        """Effective information of the runs ``idx`` (natural units); a prior (a fit's
        covariance inverted) counts as efficient information: B = M."""
        B = self.prior + extra + sum(self.mats[i][0] for i in idx)
        M = self.prior + extra + sum(self.mats[i][1] for i in idx)
        return _effective(B, M)

    def relative(self, I: np.ndarray) -> np.ndarray:
        """Information on θ/θ_nominal, which the criteria are taken of."""
        return I * np.outer(self.scale, self.scale)

    def value(self, idx, extra=0.0) -> float:
        """The criterion of the runs ``idx`` (larger is better)."""
        return _criterion(self.relative(self.effective(idx, extra)), self.criterion)


def _search_plans(score: _PlanScore, n_usable: int, n_runs: int,
                  max_enumerate: int) -> tuple[list[int], float, dict]:
    """(best plan as indices, its criterion, how it was found): every plan when there are
    at most ``max_enumerate``, else a greedy build improved by exchange."""
    n_plans = math.comb(n_usable + n_runs - 1, n_runs)
    if n_plans <= max_enumerate:
        best, best_v, evaluated = _enumerate_plans(score, n_usable, n_runs)
        method = "exhaustive enumeration"
    else:
        best, best_v, evaluated = _greedy_and_exchange(score, n_usable, n_runs)
        method = "greedy + Fedorov exchange"
    return best, best_v, dict(method=method, plans_evaluated=evaluated, plans_possible=n_plans,
                              best_value_enumerated=float(best_v) if method.startswith("exhaustive") else None)


def _enumerate_plans(score: _PlanScore, n_usable: int, n_runs: int) -> tuple[list[int] | None, float, int]:
    """The best of every plan of ``n_runs`` runs (replicates allowed): (indices, value, plans evaluated)."""
    best, best_v, evaluated = None, -np.inf, 0
    for idx in itertools.combinations_with_replacement(range(n_usable), n_runs):
        v = score.value(idx)
        evaluated += 1
        if v > best_v:
            best, best_v = list(idx), v
    return best, best_v, evaluated


def _greedy_and_exchange(score: _PlanScore, n_usable: int, n_runs: int) -> tuple[list[int], float, int]:
    """Greedy build (each run the one that adds most), then Fedorov exchange until no single
    swap improves the criterion: (indices, value, plans evaluated)."""
    # a tiny ridge so that the first picks compare
    ridge = 1e-9 * np.eye(len(score.scale))
    best: list[int] = []
    evaluated = 0
    for _ in range(n_runs):
        gains = [score.value(best + [j], ridge) for j in range(n_usable)]
        evaluated += len(gains)
        best.append(int(np.argmax(gains)))
    best_v = score.value(best)
    improved = True
    while improved:
        improved = False
        for pos in range(n_runs):
            for j in range(n_usable):
                trial = best.copy()
                trial[pos] = j
                v = score.value(trial)
                evaluated += 1
                if v > best_v + 1e-12:
                    best, best_v, improved = trial, v, True
    return best, best_v, evaluated


def _reference_note(ref, infos, se_ref, free) -> str:
    """Why the reference plan's standard errors are undefined ('' when they are not)."""
    missing = [n for n in free if not np.isfinite(se_ref.get(n, np.nan))]
    if not missing:
        return ""
    unused = [f"{c.label()}: {infos[c][2].get('reason')}" for c in ref if not infos[c][2].get("used")]
    used = len(ref) - len(unused)
    why = (f"{used} of its {len(ref)} run(s) carry information, too little to fix {', '.join(missing)}"
           if used else f"none of its {len(ref)} run(s) carries information")
    return why + (" (" + "; ".join(unused) + ")" if unused else "") + \
        "; give more runs (--runs) or a longer travel (--travel-um)"


# ----------------------------------------------------------------------------- prior
def prior_from_fit(path: str | Path, coating: str, free: Sequence[str] = DEFAULT_FREE) -> np.ndarray:
    """Information already in hand, from a fit's JSON (``python -m identify fit --json``):
    the inverse of its covariance (standard errors and correlation) on ``free``."""
    p = Path(path)
    try:
        js = json.loads(p.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"--prior {p}: not a readable fit JSON ({err})") from None
    if str(js.get("coating", "")).upper() != coating.upper():
        raise ValueError(f"--prior {p}: a fit of coating {js.get('coating')!r}, not {coating}; "
                         "information from another coating does not carry over")
    pars = js.get("parameters", {})
    missing = [n for n in free if n not in pars or not pars[n].get("free") or pars[n].get("stderr") is None]
    if missing:
        raise ValueError(f"--prior {p}: no free estimate with a standard error for {', '.join(missing)}")
    se = np.array([pars[n]["stderr"] for n in free], float)
    corr = js.get("correlation", {})
    R = np.eye(len(free))
    for i, a in enumerate(free):
        for j, b in enumerate(free):
            if i != j:
                v = (corr.get(a, {}) or {}).get(b) if isinstance(corr.get(a), dict) else None
                R[i, j] = 0.0 if v is None else float(v)
    return np.linalg.inv(np.outer(se, se) * R)

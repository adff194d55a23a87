"""The diagnosis's records: a candidate's refit and its scores, and a round.

Both are frozen: a decision (:mod:`~identify.diagnosis.scores`, :mod:`~identify.diagnosis.selection`,
:mod:`~identify.diagnosis.regime_notes`) returns a new record (:meth:`CandidateResult.but`) rather
than writing into the one it was given. :meth:`CandidateResult.to_dict` and :meth:`Round.to_json`
give the shape the diagnosis's JSON has (:meth:`identify.diagnosis.result.DiagnosisResult.to_json`),
and ``from_dict``/``from_json`` read it back.

A field left at None is one the record does not have (a failed refit has no χ², a
candidate not applicable no scores), as a key missing from the JSON reads as null. For
code written against the dicts these records replace, a record also answers
``c["key"]``, ``c.get("key", default)`` and ``"key" in c`` (read only).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

__all__ = ["CANDIDATE_KEYS", "CandidateResult", "Round"]

CANDIDATE_KEYS = ("effect", "parameters", "delta_nll", "p_value", "delta_aic", "delta_bic", "confounded_with",
                  "gap_before_um", "gap_after_um", "heldout_gap_before_um", "heldout_gap_after_um", "significant",
                  "named", "note", "ok", "status", "iterations", "wall_s", "law", "r2_with_model",
                  "closed_fraction", "estimates", "rounds", "heldout_refitted_folds",
                  "heldout_unverified_folds", "heldout_error", "heldout_delta_nll", "explained_share",
                  "closes", "gap_sigma_before", "gap_sigma_after", "heldout_gap_sigma_before",
                  "heldout_gap_sigma_after", "heldout_by_fold", "heldout_set_aside", "at_floor",
                  "heldout_gap_ratio_before", "beside", "mimicked", "own_sequence", "wald_z", "undetermined",
                  "at_magnitude", "regime", "regime_fixed", "regime_broken", "held_regime", "time_by_run",
                  "prior_scale")
"""A candidate's fields in the diagnosis's JSON, in their order there."""


@dataclass(frozen=True, eq=False)
class CandidateResult:
    """One refit of a round and what the diagnosis decided of it: the current model
    itself (``effect`` None) or a candidate effect freed beside it.

    The refit's numbers (:func:`identify.diagnosis.candidates.run_candidate`) come first,
    then the scores of :func:`identify.diagnosis.scores.score_round` and the decisions of
    :mod:`identify.diagnosis.selection`. Records compare by identity (they hold arrays)."""

    # ---- the refit
    effect: str | None = None
    ok: bool | None = None
    status: str | None = None
    error: str | None = None
    reason: str | None = None  # why a candidate was not refitted (not applicable)
    iterations: int | None = None
    rounds: list | None = None  # the solver's rounds
    wall_s: float | None = None
    chi2: float | None = None
    n_obs: int | None = None
    n_eff: float | None = None  # free dimensions; a prior's parameters by their effective count
    free: list | None = None
    priors: dict | None = None  # the priors' standard deviations (a rough track's, as the data chose them)
    prior_scale: float | None = None  # their scale as the evidence chose it (roughness, walk intensity)
    law: str | None = None
    values: dict | None = None
    estimates: dict | None = None
    confounding: dict | None = None
    nulls: dict | None = None
    r: Any = None  # residuals (not in the JSON)
    w: Any = None  # solution (not in the JSON)
    ev_M: Any = None
    gap: dict | None = None  # fitted gap (identify.diagnosis.features.gap)
    heldout: dict | None = None  # held-out gap, and by fold
    regime: dict | None = None  # the runs left out for their regime, read under the refit
    # the current model's: each run's own trend of its plateau levels in time (chi2, df, p;
    # identify.diagnosis.where.run_trends), the signature a drift per run must show
    time_by_run: dict | None = None
    at_magnitude: dict | None = None  # the check at the realistic magnitude (magnitude_check)
    w_at_magnitude: Any = None
    ev_M_at_magnitude: Any = None
    # ---- its scores (identify.diagnosis.scores)
    parameters: list | None = None
    note: str | None = None
    significant: bool | None = None
    delta_nll: float | None = None
    p_value: float | None = None
    delta_aic: float | None = None
    delta_bic: float | None = None
    gap_before_um: float | None = None
    gap_after_um: float | None = None
    heldout_gap_before_um: float | None = None
    heldout_gap_after_um: float | None = None
    heldout_refitted_folds: int | None = None
    heldout_unverified_folds: int | None = None
    heldout_error: str | None = None
    heldout_delta_nll: float | None = None
    heldout_by_fold: list | None = None
    heldout_set_aside: dict | None = None
    gap_sigma_before: float | None = None
    gap_sigma_after: float | None = None
    heldout_gap_sigma_before: float | None = None
    heldout_gap_sigma_after: float | None = None
    r2_with_model: float | None = None
    wald_z: float | None = None
    confounded_with: list | None = None
    mimicked: bool | None = None
    worse: bool | None = None  # the refit ended worse than the current model
    dr: Any = None  # the change of the residuals (not in the JSON)
    estimate_text: str | None = None
    closed_fraction: float | None = None
    heldout_gap_ratio_before: float | None = None
    at_floor: bool | None = None
    explained_share: float | None = None
    closes: bool | None = None
    # ---- the decisions (identify.diagnosis.selection, regime_notes, rounds)
    named: bool | None = None
    undetermined: bool | None = None
    confounded_beside: str | None = None
    beside: list | None = None
    own_sequence: dict | None = None
    own_model: dict | None = None  # the model measured on its own mode sequence (not in the JSON)
    regime_fixed: list | None = None
    regime_broken: list | None = None
    held_regime: dict | None = None

    def but(self, **changes) -> CandidateResult:
        """This record with ``changes``."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """The candidate as the diagnosis's JSON gives it (every key, null where none)."""
        return {k: getattr(self, k) for k in CANDIDATE_KEYS}

    @classmethod
    def from_dict(cls, d) -> CandidateResult:
        """A record from its JSON (:meth:`to_dict`) or from any dict of its fields (keys it
        does not have are ignored); a record is returned as it is."""
        if isinstance(d, cls):
            return d
        d = dict(d)
        if "_own" in d:
            d["own_model"] = d.pop("_own")
        return cls(**{k: v for k, v in d.items() if k in _FIELDS})

    # (read-only access as the dicts these records replace had it)
    def __getitem__(self, key: str):
        if key not in _FIELDS:
            raise KeyError(key)
        return getattr(self, key)

    def get(self, key: str, default=None):
        v = getattr(self, key, None) if key in _FIELDS else None
        return default if v is None else v

    def __contains__(self, key) -> bool:
        return key in _FIELDS and getattr(self, key) is not None


_FIELDS = frozenset(f.name for f in dataclasses.fields(CandidateResult))


@dataclass(frozen=True)
class Round:
    """One round of the diagnosis: the current model measured (``current``, effect None;
    None when read from a JSON without it), its candidates — the scored ones best first,
    then those not refitted — and the one named (``chosen``, its effect; None if none).

    Iterating gives the current model first, then the candidates (as the rounds were
    lists)."""

    current: CandidateResult | None = None
    candidates: tuple = ()
    chosen: str | None = None

    def __iter__(self) -> Iterator[CandidateResult]:
        if self.current is not None:
            yield self.current
        yield from self.candidates

    def __len__(self) -> int:
        return len(self.candidates) + (self.current is not None)

    def __getitem__(self, i):
        return list(self)[i]

    def __bool__(self) -> bool:
        return len(self) > 0

    def but(self, **changes) -> Round:
        return dataclasses.replace(self, **changes)

    def replaced(self, new: CandidateResult) -> Round:
        """The round with the candidate of ``new``'s effect replaced by ``new``."""
        return self.but(candidates=tuple(new if c.effect == new.effect else c for c in self.candidates))

    def to_json(self) -> list:
        """The round's candidates as the JSON's ``rounds`` lists them (the current model
        is in its ``current_model``: :meth:`current_json`)."""
        return [c.to_dict() for c in self.candidates if c.effect]

    def current_json(self) -> dict | None:
        """The current model's measurement as the JSON's ``current_model`` gives it."""
        c = self.current
        return None if c is None else {**c.to_dict(), "gap": c.gap, "heldout": c.heldout}

    @classmethod
    def from_json(cls, candidates: list, current: dict | None = None) -> Round:
        """A round from the JSON's ``rounds`` entry and ``current_model`` entry."""
        cands = tuple(CandidateResult.from_dict(c) for c in candidates)
        return cls(current=None if current is None else CandidateResult.from_dict(current), candidates=cands,
                   chosen=next((c.effect for c in cands if c.named), None))

    @classmethod
    def of(cls, records, chosen: str | None = None) -> Round:
        """A round from a list of records or dicts, the current model's first (a round
        given as it is)."""
        if isinstance(records, cls):
            return records
        cs = [CandidateResult.from_dict(c) for c in records]
        current = cs[0] if cs and cs[0].effect is None else None
        return cls(current=current, candidates=tuple(cs[1:] if current is not None else cs), chosen=chosen)

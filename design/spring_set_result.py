"""The result of a spring-set design: the set, the paper's set beside it, and the evidence.

:class:`SpringSetResult` is what :func:`design.spring_set.design_spring_set` returns; it
writes the readable report and the JSON of ``python -m design springs``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from identify.jsonio import SavedResult

from . import constraints as tc
from .spring_coverage import SpringSet, format_load_range_uN, to_uN
from .springs import PAPER_SPRING_CONSTANTS, SpringDesign

__all__ = ["Attempt", "SpringSetResult"]


@dataclass(frozen=True)
class Attempt:
    """Best worst margin found with ``n`` springs (over assignments and starts)."""

    n: int
    worst_margin: float
    covers: bool


@dataclass(frozen=True)
class SpringSetResult(SavedResult):
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
            f"Spring set covering Nb = {format_load_range_uN(*s.load_range)} for every μ in "
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
                "load_range_uN": [to_uN(x) for x in self.load_range],
                "requested_load_range_uN": (
                    list(self.requested_load_range_uN) if self.requested_load_range_uN else None
                ),
                "attempts": [
                    {"n_springs": a.n, "worst_margin": a.worst_margin, "covers": a.covers}
                    for a in self.attempts
                ],
                "notes": list(self.notes),
                "n_solves": self.n_solves,
                "n_starts": self.n_starts,
                "n_best_found": self.n_best_found,
                "margin_definition": (
                    "natural-log ratios: low end ln(L_lo/lo_1), overlap i|i+1 ln(hi_i/lo_{i+1}), "
                    "high end ln(hi_n/L_hi); lo_i = k_stiff·90 nm/0.1, hi_i = k_soft·100 µm/0.9 "
                    "at realised widths w ± 2·etch_bias"
                ),
            }
        )
        return d

    @classmethod
    def from_dict(cls, d: dict) -> SpringSetResult:
        """The result back from :meth:`to_json` (or :meth:`to_dict`, a saved file or the
        ``--json`` of ``python -m design springs``)."""
        req = d.get("requested_load_range_uN")
        return cls(
            spring_set=SpringSet.from_dict(d),
            reference=SpringSet.from_dict(d["reference"]),
            requested_load_range_uN=tuple(req) if req else None,
            # (a null margin: no start converged with that many springs, -inf in the result)
            attempts=tuple(Attempt(a["n_springs"], -math.inf if a["worst_margin"] is None else a["worst_margin"],
                                   a["covers"]) for a in d["attempts"]),
            notes=tuple(d.get("notes") or ()),
            n_solves=d.get("n_solves", 0),
            n_starts=d.get("n_starts", 1),
            n_best_found=d.get("n_best_found", 1),
        )

    def plot(self, ax=None):
        """Fig. 3: the Table I region in the k–Nb plane with this set and the paper's."""
        from .plots import plot_design

        return plot_design(self, ax=ax)

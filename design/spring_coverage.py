"""A spring set judged against a requested load range, at an etch-bias uncertainty.

:class:`SpringSet` holds the measures :func:`design.spring_set.design_spring_set` optimises
and reports (margins, coverage, gaps; defined in :mod:`design.spring_set`), the pointwise
check against every row of Table I, and the set's JSON and report lines.
:func:`paper_spring_set` judges the paper's four springs by the same measures.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from identify.jsonio import SavedResult

from . import constraints as tc
from .springs import ETCH_BIAS_UM, SpringDesign, Suspension, paper_springs

__all__ = ["SpringSet", "paper_spring_set", "to_uN", "format_load_range_uN"]


def to_uN(x: float) -> float:
    """A load in N as µN (the unit of every load in the reports and JSON)."""
    return x * 1e6


def format_load_range_uN(lo: float, hi: float) -> str:
    """``lo-hi µN`` at four significant digits, for reports and messages (loads in N)."""
    return f"{to_uN(lo):.4g}-{to_uN(hi):.4g} µN"


@dataclass(frozen=True)
class SpringSet(SavedResult):
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
        """m_0..m_n (natural-log ratios), see :mod:`design.spring_set`."""
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
                    [to_uN(lo[i]), to_uN(hi[i])] if np.isfinite(lo[i]) else None
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
            "covered_load_range_uN": [to_uN(c_lo), to_uN(c_hi)] if math.isfinite(c_lo) else None,
            "covers_load_range": self.covers,
            "worst_margin": self.worst_margin,
            "worst_overlap_margin": wom,
            "margins": [
                {"between": lab, "value": float(m)}
                for lab, m in zip(self.margin_labels, self.margins)
            ],
            "gaps_uN": [[to_uN(a), to_uN(b)] for a, b in self.gaps],
            "uncovered_uN": [[to_uN(a), to_uN(b)] for a, b in self.uncovered],
            "load_range_N": list(self.load_range),
            "etch_bias_um": self.etch_bias_um,
            "label": self.label,
        }

    @classmethod
    def from_dict(cls, d: dict) -> SpringSet:
        """The set back from :meth:`to_json`: the springs (width and suspension), the
        requested range (N) and the etch bias; every measure follows from them."""
        springs = [SpringDesign(s["width_um"], Suspension.from_json(s["suspension"])) for s in d["springs"]]
        load_range = d.get("load_range_N") or [x * 1e-6 for x in d["load_range_uN"]]
        return cls(springs, tuple(load_range), d.get("etch_bias_um", ETCH_BIAS_UM), d.get("label", ""))

    def report_lines(self) -> list[str]:
        ks, kt = self.spring_constant_ranges
        lo, hi = self.load_ranges
        lines = [
            f"  {'#':>2}  {'suspension':<16} {'w (µm)':>7} {'drawn':>7} {'k (N/m)':>9} "
            f"{'k range (N/m)':>17}  {'allowed Nb (µN)':>18}"
        ]
        for i, s in enumerate(self.springs):
            rng = f"{to_uN(lo[i]):.4g}-{to_uN(hi[i]):.4g}" if np.isfinite(lo[i]) else "none"
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
        cov = f"  allowed loads span {format_load_range_uN(c_lo, c_hi)}"
        if self.gaps:
            cov += "; gaps " + ", ".join(format_load_range_uN(a, b) for a, b in self.gaps)
        lines.append(cov)
        if self.uncovered:
            lines.append(
                "  does NOT cover "
                + ", ".join(format_load_range_uN(a, b) for a, b in self.uncovered)
                + " of the requested range"
            )
        else:
            lines.append(f"  covers the requested {format_load_range_uN(*self.load_range)}")
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

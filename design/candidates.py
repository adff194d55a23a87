"""The runs an experiment plan chooses from: a :class:`Candidate` (k, Nb, fp, travel), the
default grid inside Table I, and the paper's conditions as the reference plan."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["Candidate", "PAPER_FPS_HZ", "PAPER_LOADS_UN", "default_candidates", "paper_plan"]

PAPER_LOADS_UN = (0.98, 8.0, 18.1)
PAPER_FPS_HZ = (10.0, 100.0, 500.0, 1000.0)


@dataclass(frozen=True)
class Candidate:
    """One run a plan may contain."""

    spring_constant_N_per_m: float
    normal_load_uN: float
    step_frequency_Hz: float
    travel_um: float = 30.0

    def to_json(self) -> dict:
        return dict(spring_constant_N_per_m=self.spring_constant_N_per_m, normal_load_uN=self.normal_load_uN,
                    step_frequency_Hz=self.step_frequency_Hz, travel_um=self.travel_um)

    def label(self) -> str:
        return f"k={self.spring_constant_N_per_m:g} Nb={self.normal_load_uN:g}µN fp={self.step_frequency_Hz:g}Hz"


def paper_plan(n_runs: int, travel_um: float = 30.0) -> list:
    """The paper's conditions (k = 2.13 N/m, Nb ∈ {0.98, 8, 18.1} µN, fp ∈ {10, 100, 500,
    1000} Hz: 12 runs) cut or repeated to ``n_runs``, spread evenly over the 12."""
    grid = [Candidate(2.13, nb, fp, travel_um) for nb in PAPER_LOADS_UN for fp in PAPER_FPS_HZ]
    idx = np.floor(np.arange(n_runs) * len(grid) / n_runs).astype(int) if n_runs <= len(grid) \
        else np.arange(n_runs) % len(grid)
    return [grid[i] for i in idx]


def default_candidates(springs: Sequence[float], travel_um: float = 30.0,
                       loads_uN: Sequence[float] | None = None,
                       fps_Hz: Sequence[float] = (10.0, 30.0, 100.0, 300.0, 1000.0)) -> list:
    """(k, Nb, fp) grid inside Table I for each spring, camera at ≤ 5000 Hz."""
    from .constraints import allowed_load_range

    out = []
    for k in springs:
        lo, hi = (float(np.asarray(v).ravel()[0]) * 1e6 for v in allowed_load_range(k))
        loads = loads_uN if loads_uN is not None else np.geomspace(lo, min(hi, 60.0), 4)
        for nb in loads:
            if lo * (1 - 1e-9) <= nb <= hi * (1 + 1e-9):
                out += [Candidate(float(k), float(np.round(nb, 3)), float(fp), travel_um)
                        for fp in fps_Hz if fp <= 5000]
    return out

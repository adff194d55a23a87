"""The free parameters as the NLP's decision variables: :class:`ThetaMap`, scaled (log
for positive parameters, else value/scale) with bounds."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from identify.model.params import spec

__all__ = ["ThetaMap"]


@dataclass
class ThetaMap:
    """Free parameters <-> scaled decision variables (log or linear)."""

    names: tuple
    scale: np.ndarray
    log: np.ndarray
    lo: np.ndarray  # scaled bounds
    hi: np.ndarray

    @classmethod
    def build(cls, names, bounds: Mapping[str, tuple]):
        scale, logs, lo, hi = [], [], [], []
        for n in names:
            s = spec(n)
            b = bounds.get(n, (s.lower, s.upper))
            scale.append(s.scale)
            use_log = s.log and b[0] > 0
            logs.append(use_log)
            if use_log:
                lo.append(math.log(b[0] / s.scale))
                hi.append(math.log(b[1] / s.scale))
            else:
                lo.append(b[0] / s.scale)
                hi.append(b[1] / s.scale)
        return cls(tuple(names), np.array(scale), np.array(logs, bool), np.array(lo), np.array(hi))

    def to_scaled(self, values: Mapping[str, float]) -> np.ndarray:
        v = np.array([values[n] for n in self.names], float)
        return np.where(self.log, np.log(np.maximum(v, 1e-300) / self.scale), v / self.scale)

    def from_scaled(self, th, ops=np):
        return [self.scale[i] * ops.exp(th[i]) if self.log[i] else self.scale[i] * th[i]
                for i in range(len(self.names))]

    def jacobian_diag(self, th: np.ndarray) -> np.ndarray:
        """d value / d scaled, per parameter."""
        vals = np.array(self.from_scaled(th))
        return np.where(self.log, vals, self.scale)

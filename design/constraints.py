"""Table I of the paper as named constraint objects.

An operating point (k, Nb) of a spring is allowed when, for every friction coefficient μ in
[0.1, 0.9], the spring elongation at slip ``e = μ·Nb/k`` stays measurable and within the
puller's travel (MODEL.md, "Springs and the design constraints (Table I, Fig. 3)"):

==================  ==========================================================
constraint          why
==================  ==========================================================
e > 90 nm           displacement resolution (pixel/10 at 0.88 µm/pixel)
e < 100 µm          nanotractor travel
Nb > 10 nN          block stays flat in contact
Nb < 452 µN         block voltage limit of the equipment
μ > 0.1, μ < 0.9    expected friction range (conservative)
k > 0.01 N/m        practical
k < 100 N/m         beam nonlinearity
==================  ==========================================================

The paper writes strict inequalities; here a point on a boundary passes (the limits are
closed, up to a relative tolerance of 1e-9), so that k = 2.13 N/m covers exactly
[k·90 nm/0.1, k·100 µm/0.9] = [1.92, 237] µN as the paper states.

Every function is vectorised over arrays of (Nb, k, μ) in SI units (N, N/m, –). The bounds
below are the only place these numbers are written.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = [
    "Sense",
    "Constraint",
    "Violation",
    "ConstraintViolation",
    "ELONGATION_RESOLUTION",
    "PULLER_TRAVEL",
    "LOAD_MIN",
    "LOAD_MAX",
    "MU_MIN",
    "MU_MAX",
    "K_MIN",
    "K_MAX",
    "TABLE_I",
    "check",
    "require",
    "satisfied",
    "allowed_load_range",
    "robust_load_range",
    "elongation_window",
    "format_load",
]

RTOL = 1e-9
"""Relative tolerance at which a point on a Table I boundary still passes."""


class Sense(enum.Enum):
    """Direction of a one-sided bound."""

    GREATER = ">"
    LESS = "<"


_QUANTITIES: dict[str, Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]] = {
    "e": lambda nb, k, mu: mu * nb / k,
    "Nb": lambda nb, k, mu: nb,
    "μ": lambda nb, k, mu: mu,
    "k": lambda nb, k, mu: k,
}


def format_load(normal_load: float) -> str:
    """A normal load (N) for messages: ``"10 nN"`` below 1 µN, else ``"452 µN"``."""
    if abs(normal_load) < 1e-6:
        return f"{normal_load * 1e9:.3g} nN"
    return f"{normal_load * 1e6:.3g} µN"


@dataclass(frozen=True)
class Constraint:
    """One row of Table I: a one-sided bound on e, Nb, μ or k.

    Parameters
    ----------
    name : str
        Human name, e.g. ``"e < 100 µm"``.
    quantity : str
        ``"e"`` (elongation μ·Nb/k, m), ``"Nb"`` (N), ``"μ"`` (–) or ``"k"`` (N/m).
    sense : Sense
        ``GREATER``: quantity must be >= bound; ``LESS``: <= bound (closed limits).
    bound : float
        The bound in SI units.
    unit : str
        SI unit of the quantity.
    display_unit : str
        Unit for messages; ``display_factor`` converts SI to it.
    display_factor : float
    reason : str
        Why the constraint exists (Table I).
    """

    name: str
    quantity: str
    sense: Sense
    bound: float
    unit: str
    display_unit: str
    display_factor: float
    reason: str

    def __post_init__(self) -> None:
        if self.quantity not in _QUANTITIES:
            raise ValueError(
                f"Constraint.quantity = {self.quantity!r}: must be one of {sorted(_QUANTITIES)}"
            )
        if not isinstance(self.sense, Sense):
            raise ValueError(f"Constraint.sense = {self.sense!r}: must be a Sense ('>' or '<')")
        if not np.isfinite(self.bound) or self.bound <= 0:
            raise ValueError(f"Constraint.bound = {self.bound!r}: must be a finite number > 0")

    def value(
        self, normal_load: npt.ArrayLike, spring_constant: npt.ArrayLike, mu: npt.ArrayLike
    ) -> np.ndarray:
        """The constrained quantity (SI) at broadcast arrays of Nb (N), k (N/m), μ (–)."""
        nb, k, m = np.broadcast_arrays(
            np.asarray(normal_load, float),
            np.asarray(spring_constant, float),
            np.asarray(mu, float),
        )
        return _QUANTITIES[self.quantity](nb, k, m)

    def satisfied(
        self, normal_load: npt.ArrayLike, spring_constant: npt.ArrayLike, mu: npt.ArrayLike
    ) -> np.ndarray:
        """Boolean array: True where the constraint holds (boundary included)."""
        v = self.value(normal_load, spring_constant, mu)
        if self.sense is Sense.GREATER:
            return v >= self.bound * (1 - RTOL)
        return v <= self.bound * (1 + RTOL)

    def slack(
        self, normal_load: npt.ArrayLike, spring_constant: npt.ArrayLike, mu: npt.ArrayLike
    ) -> np.ndarray:
        """Log-ratio distance to the bound, positive when satisfied: ln(v/bound) or ln(bound/v)."""
        v = self.value(normal_load, spring_constant, mu)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.log(v / self.bound)
        return r if self.sense is Sense.GREATER else -r

    def violations(
        self, normal_load: npt.ArrayLike, spring_constant: npt.ArrayLike, mu: npt.ArrayLike
    ) -> list[Violation]:
        """One :class:`Violation` per broadcast point where the constraint fails."""
        nb, k, m = np.broadcast_arrays(
            np.asarray(normal_load, float),
            np.asarray(spring_constant, float),
            np.asarray(mu, float),
        )
        nb, k, m = nb.ravel(), k.ravel(), m.ravel()
        v = self.value(nb, k, m)
        bad = np.flatnonzero(~self.satisfied(nb, k, m))
        return [Violation(self, float(nb[i]), float(k[i]), float(m[i]), float(v[i])) for i in bad]

    def display(self, value: float) -> str:
        return f"{value * self.display_factor:.3g} {self.display_unit}".rstrip()


@dataclass(frozen=True)
class Violation:
    """A constraint failing at one point (SI values)."""

    constraint: Constraint
    normal_load: float
    spring_constant: float
    mu: float
    value: float

    @property
    def message(self) -> str:
        """E.g. ``e < 100 µm violated at Nb = 300 µN, k = 2.13 N/m, μ = 0.9 (e = 127 µm)``."""
        c = self.constraint
        point = (
            f"Nb = {format_load(self.normal_load)}, k = {self.spring_constant:.3g} N/m, "
            f"μ = {self.mu:.3g}"
        )
        extra = f" ({c.quantity} = {c.display(self.value)})" if c.quantity == "e" else ""
        return f"{c.name} violated at {point}{extra}"

    def __str__(self) -> str:
        return self.message


class ConstraintViolation(ValueError):
    """An operating point breaks Table I; the message names the rule and the point."""

    def __init__(self, violations: Sequence[Violation]):
        self.violations = tuple(violations)
        msg = self.violations[0].message
        if len(self.violations) > 1:
            msg += f" (and {len(self.violations) - 1} more violations)"
        super().__init__(msg)


def _c(name, quantity, sense, bound, unit, display_unit, display_factor, reason) -> Constraint:
    return Constraint(
        name, quantity, Sense(sense), bound, unit, display_unit, display_factor, reason
    )


ELONGATION_RESOLUTION = _c("e > 90 nm", "e", ">", 90e-9, "m", "nm", 1e9,
                           "displacement resolution (pixel/10 at 0.88 µm/pixel)")
PULLER_TRAVEL = _c("e < 100 µm", "e", "<", 100e-6, "m", "µm", 1e6, "nanotractor travel")
LOAD_MIN = _c("Nb > 10 nN", "Nb", ">", 10e-9, "N", "µN", 1e6, "block stays flat in contact")
LOAD_MAX = _c("Nb < 452 µN", "Nb", "<", 452e-6, "N", "µN", 1e6,
              "block voltage limit of the equipment")
MU_MIN = _c("μ > 0.1", "μ", ">", 0.1, "-", "", 1.0, "expected friction range (conservative)")
MU_MAX = _c("μ < 0.9", "μ", "<", 0.9, "-", "", 1.0, "expected friction range (conservative)")
K_MIN = _c("k > 0.01 N/m", "k", ">", 0.01, "N/m", "N/m", 1.0, "practical")
K_MAX = _c("k < 100 N/m", "k", "<", 100.0, "N/m", "N/m", 1.0, "beam nonlinearity")

TABLE_I: tuple[Constraint, ...] = (
    ELONGATION_RESOLUTION, PULLER_TRAVEL, LOAD_MIN, LOAD_MAX, MU_MIN, MU_MAX, K_MIN, K_MAX,
)
"""Table I of the paper, one :class:`Constraint` per bound."""


def check(
    normal_load: npt.ArrayLike,
    spring_constant: npt.ArrayLike,
    mu: npt.ArrayLike,
    constraints: Iterable[Constraint] = TABLE_I
) -> list[Violation]:
    """Every violation of ``constraints`` at broadcast arrays of Nb (N), k (N/m), μ (–).

    Returns
    -------
    list of Violation
        Empty when every point satisfies every constraint; ordered by constraint, then point.
    """
    out: list[Violation] = []
    for c in constraints:
        out.extend(c.violations(normal_load, spring_constant, mu))
    return out


def satisfied(
    normal_load: npt.ArrayLike,
    spring_constant: npt.ArrayLike,
    mu: npt.ArrayLike,
    constraints: Iterable[Constraint] = TABLE_I,
) -> np.ndarray:
    """Boolean array: True where every constraint holds."""
    ok = None
    for c in constraints:
        s = c.satisfied(normal_load, spring_constant, mu)
        ok = s if ok is None else ok & s
    return ok


def require(
    normal_load: npt.ArrayLike,
    spring_constant: npt.ArrayLike,
    mu: npt.ArrayLike,
    constraints: Iterable[Constraint] = TABLE_I,
) -> None:
    """Raise :class:`ConstraintViolation` (a ValueError) if any point breaks a constraint."""
    v = check(normal_load, spring_constant, mu, constraints)
    if v:
        raise ConstraintViolation(v)


def elongation_window(
    k_soft: npt.ArrayLike, k_stiff: npt.ArrayLike
) -> tuple[np.ndarray, np.ndarray]:
    """Loads (N) at which e stays in [90 nm, 100 µm] for every μ in [0.1, 0.9].

    For a spring whose realised stiffness lies in [k_soft, k_stiff] (N/m): the floor is set
    by the stiffest realisation at the lowest μ, ``k_stiff·90 nm/0.1``, the ceiling by the
    softest at the highest μ, ``k_soft·100 µm/0.9``. Neither the Nb nor the k rows of
    Table I are applied (see :func:`robust_load_range`).
    """
    k_soft = np.asarray(k_soft, float)
    k_stiff = np.asarray(k_stiff, float)
    lo = k_stiff * ELONGATION_RESOLUTION.bound / MU_MIN.bound
    hi = k_soft * PULLER_TRAVEL.bound / MU_MAX.bound
    return lo, hi


def robust_load_range(
    k_soft: npt.ArrayLike, k_stiff: npt.ArrayLike
) -> tuple[np.ndarray, np.ndarray]:
    """Allowed Nb range (N) of a spring whose realised k lies in [k_soft, k_stiff] (N/m).

    ``[k_stiff·90 nm/0.1, k_soft·100 µm/0.9] ∩ [10 nN, 452 µN]``, i.e. the loads at which
    every row of Table I holds for every μ in [0.1, 0.9] and every realisation of k. NaN
    (both ends) where the range is empty or k breaks 0.01 < k < 100 N/m.
    """
    lo, hi = elongation_window(k_soft, k_stiff)
    lo = np.maximum(lo, LOAD_MIN.bound)
    hi = np.minimum(hi, LOAD_MAX.bound)
    ks, kt = np.broadcast_arrays(np.asarray(k_soft, float), np.asarray(k_stiff, float))
    bad = (
        ~K_MIN.satisfied(0.0, ks, 0.5) | ~K_MAX.satisfied(0.0, kt, 0.5) | (lo > hi * (1 + RTOL))
    )
    lo = np.where(bad, np.nan, lo)
    hi = np.where(bad, np.nan, hi)
    if lo.ndim == 0:
        return float(lo), float(hi)
    return lo, hi


def allowed_load_range(spring_constant: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Allowed Nb range (N) of a spring constant k (N/m), Table I.

    ``[k·90 nm/0.1, k·100 µm/0.9] ∩ [10 nN, 452 µN]``; e.g. k = 2.13 N/m gives
    1.92–237 µN (MODEL.md). NaN where empty or k is outside [0.01, 100] N/m.
    """
    return robust_load_range(spring_constant, spring_constant)

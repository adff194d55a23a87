"""Spring model of the nanofrictor: the folded fixed-guided beam suspension.

The lateral spring that connects the puller to the friction block is a folded suspension of
fixed-guided beams (MODEL.md, "Springs and the design constraints"). For one effective
fixed-guided beam of width w, length l and thickness t,

    k = E·t·(w/l)³ · n_parallel / n_series                                   (1)

(a fixed-guided beam has k = 12·E·I/l³ with I = t·w³/12). With polysilicon E = 164 GPa,
l = 189 µm, t = 2.25 µm and n_parallel = n_series = 1 this reproduces the paper's springs:
w = 1.64, 3.39, 7.23 µm give 0.241, 2.13, 20.7 N/m (paper: 0.24, 2.13, 20.3 N/m).

Widths
------
Every function here takes the **effective** width, i.e. the width after the etch has
removed the edge bias: ``w_eff = w_drawn − 2·etch_bias`` (the paper's widths 1.64–7.23 µm
are already effective widths, with a bias of 0.1 µm per edge). :func:`effective_width_um`
and :func:`drawn_width_um` convert. The etch bias is also uncertain: the design code
assumes the realised width lies in ``w_eff ± 2·b`` with b = ``etch_bias_um`` (worst case
over a per-edge bias error in [−b, +b]); :meth:`Suspension.spring_constant_range` gives the
softest and stiffest realisation.

The softest spring
------------------
The paper's softest spring, 0.028 N/m, cannot be made from the 189 µm beam: even the
narrowest width the process allows (1.5 µm, below) gives 0.18 N/m. The paper only says it
uses "a longer or more-folded suspension". We provide :data:`LONG_SUSPENSION`, the same beam
2.06× longer (l = 390 µm), which gives 0.0274 N/m at w = 1.64 µm and 0.028 N/m at 1.65 µm.
Equivalent alternatives are ``Suspension(n_series=8)`` (8 folds of the 189 µm beam in
series: 0.0301 N/m at 1.64 µm) or any geometry with the same (n_series/n_parallel)·l³.

Process bounds (our choice, documented here once)
--------------------------------------------------
Effective widths between ``MIN_WIDTH_UM`` = 1.5 µm (just below the paper's narrowest,
1.64 µm, and comfortably above SUMMiT V's ~1 µm minimum line after a 2×0.1 µm edge loss)
and ``MAX_WIDTH_UM`` = 10 µm (wider beams on a 2.25 µm thick layer stop behaving as slender
beams and need release holes). These bound the *nominal* effective width; the realised
widths ``w ± 2b`` may lie slightly outside.

All constants cite ``shared/MODEL.md``. Units: widths, lengths and thicknesses in µm at
this edge (``width_um``), Young's modulus in Pa, spring constants in N/m (SI).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "YOUNGS_MODULUS_POLYSILICON",
    "BEAM_LENGTH_UM",
    "BEAM_THICKNESS_UM",
    "ETCH_BIAS_UM",
    "MIN_WIDTH_UM",
    "MAX_WIDTH_UM",
    "LONG_BEAM_LENGTH_UM",
    "PAPER_SPRING_CONSTANTS",
    "PAPER_WIDTHS_UM",
    "Suspension",
    "SpringDesign",
    "PAPER_SUSPENSION",
    "LONG_SUSPENSION",
    "spring_constant",
    "width_for_spring_constant",
    "effective_width_um",
    "drawn_width_um",
    "paper_springs",
]

ArrayLike = float | np.ndarray

# --- Constants (MODEL.md, "Springs and the design constraints (Table I, Fig. 3)") --------
YOUNGS_MODULUS_POLYSILICON = 164e9
"""Young's modulus of polysilicon E (Pa); MODEL.md."""
BEAM_LENGTH_UM = 189.0
"""Length l of the paper's fixed-guided beams (µm)."""
BEAM_THICKNESS_UM = 2.25
"""Thickness t of the structural polysilicon (µm)."""
ETCH_BIAS_UM = 0.1
"""Edge bias per edge (µm): effective width = drawn width − 2·bias. Also the default
half-width of its uncertainty in the robust design."""
MIN_WIDTH_UM = 1.5
"""Narrowest effective beam width the design may use (µm); our process choice."""
MAX_WIDTH_UM = 10.0
"""Widest effective beam width the design may use (µm); our process choice."""
LONG_BEAM_LENGTH_UM = 390.0
"""Beam length of :data:`LONG_SUSPENSION` (µm), chosen so that w ≈ 1.64 µm gives the
paper's softest spring, 0.028 N/m (the paper gives no geometry for it)."""

PAPER_SPRING_CONSTANTS = (0.028, 0.24, 2.13, 20.3)
"""The paper's four spring constants (N/m)."""
PAPER_WIDTHS_UM = (None, 1.64, 3.39, 7.23)
"""The paper's effective widths (µm) for those springs on the 189 µm beam; the 0.028 N/m
spring's geometry is not given."""

_UM = 1e-6


def _positive_finite(name: str, value: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: {value!r} is not a number") from None
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{name} = {value!r}: must be a finite number > 0")
    return v


@dataclass(frozen=True)
class Suspension:
    """A folded fixed-guided-beam suspension and the process that makes it.

    Parameters
    ----------
    length_um : float
        Beam length l (µm). Default 189 µm, the paper's.
    thickness_um : float
        Structural layer thickness t (µm). Default 2.25 µm.
    youngs_modulus : float
        Young's modulus E (Pa). Default 164 GPa (polysilicon).
    n_parallel, n_series : int
        Multiplier of Eq. (1): number of effective beams in parallel and in series.
        Defaults 1 and 1: the single effective beam of MODEL.md.
    min_width_um, max_width_um : float
        Process bounds on the nominal effective width (µm). Defaults 1.5 and 10 µm.
    etch_bias_um : float
        Edge bias per edge (µm), default 0.1 µm: drawn = effective + 2·bias. The design
        code also uses it as the default uncertainty of the bias (realised width
        ``w ± 2·bias``), so ``min_width_um`` must exceed ``2·etch_bias_um``.
    name : str
        Label used in reports.

    Raises
    ------
    ValueError
        On construction, naming the field and the rule it breaks.
    """

    length_um: float = BEAM_LENGTH_UM
    thickness_um: float = BEAM_THICKNESS_UM
    youngs_modulus: float = YOUNGS_MODULUS_POLYSILICON
    n_parallel: int = 1
    n_series: int = 1
    min_width_um: float = MIN_WIDTH_UM
    max_width_um: float = MAX_WIDTH_UM
    etch_bias_um: float = ETCH_BIAS_UM
    name: str = "paper"

    def __post_init__(self) -> None:
        for f in ("length_um", "thickness_um", "youngs_modulus", "min_width_um", "max_width_um"):
            object.__setattr__(self, f, _positive_finite(f"Suspension.{f}", getattr(self, f)))
        for f in ("n_parallel", "n_series"):
            v = getattr(self, f)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"Suspension.{f} = {v!r}: must be an integer >= 1")
            object.__setattr__(self, f, int(v))
        try:
            bias = float(self.etch_bias_um)
        except (TypeError, ValueError):
            raise ValueError(
                f"Suspension.etch_bias_um: {self.etch_bias_um!r} is not a number"
            ) from None
        if not math.isfinite(bias) or bias < 0:
            raise ValueError(
                f"Suspension.etch_bias_um = {self.etch_bias_um!r}: must be a finite number >= 0"
            )
        object.__setattr__(self, "etch_bias_um", bias)
        if self.min_width_um >= self.max_width_um:
            raise ValueError(
                f"Suspension.min_width_um = {self.min_width_um:g} µm: must be < max_width_um "
                f"= {self.max_width_um:g} µm"
            )
        if self.min_width_um <= 2 * bias:
            raise ValueError(
                f"Suspension.min_width_um = {self.min_width_um:g} µm: must exceed "
                f"2·etch_bias_um = {2 * bias:g} µm (the thinnest realisation must have a width)"
            )
        if not isinstance(self.name, str):
            raise ValueError(f"Suspension.name = {self.name!r}: must be a string")

    # -- Eq. (1) -------------------------------------------------------------------------
    @property
    def coefficient(self) -> float:
        """k / w³ in N/m per µm³ (w the effective width in µm); Eq. (1)."""
        return (
            self.youngs_modulus
            * self.thickness_um * _UM
            * (_UM / (self.length_um * _UM)) ** 3
            * self.n_parallel / self.n_series
        )

    def spring_constant(self, width_um: ArrayLike) -> ArrayLike:
        """Lateral spring constant k (N/m) for an effective width (µm), Eq. (1).

        Parameters
        ----------
        width_um : float or array
            Effective beam width w (µm), > 0. Process bounds are not enforced here
            (see :meth:`check_width`).

        Returns
        -------
        float or ndarray
            k in N/m.
        """
        w = np.asarray(width_um, dtype=float)
        if np.any(~np.isfinite(w)) or np.any(w <= 0):
            raise ValueError(f"width_um = {width_um!r}: every width must be a finite number > 0 µm")
        k = self.coefficient * w**3
        return float(k) if k.ndim == 0 else k

    def width_um(self, spring_constant: ArrayLike) -> ArrayLike:
        """Effective width w (µm) that gives spring constant k (N/m): inverse of Eq. (1)."""
        k = np.asarray(spring_constant, dtype=float)
        if np.any(~np.isfinite(k)) or np.any(k <= 0):
            raise ValueError(
                f"spring_constant = {spring_constant!r}: every value must be a finite number "
                "> 0 N/m"
            )
        w = np.cbrt(k / self.coefficient)
        return float(w) if w.ndim == 0 else w

    def spring_constant_range(
        self, width_um: ArrayLike, etch_bias_um: float | None = None
    ) -> tuple[ArrayLike, ArrayLike]:
        """Softest and stiffest realisation of a nominal effective width.

        Parameters
        ----------
        width_um : float or array
            Nominal effective width w (µm).
        etch_bias_um : float, optional
            Uncertainty b of the edge bias per edge (µm); default: this suspension's
            ``etch_bias_um``. The realised width lies in ``[w − 2b, w + 2b]``.

        Returns
        -------
        (k_soft, k_stiff) : floats or arrays
            Spring constants (N/m) at ``w − 2b`` and ``w + 2b``.
        """
        b = self.etch_bias_um if etch_bias_um is None else float(etch_bias_um)
        if not math.isfinite(b) or b < 0:
            raise ValueError(f"etch_bias_um = {etch_bias_um!r}: must be a finite number >= 0")
        w = np.asarray(width_um, dtype=float)
        if np.any(w - 2 * b <= 0):
            raise ValueError(
                f"width_um = {width_um!r}: must exceed 2·etch_bias_um = {2 * b:g} µm "
                "(the thinnest realisation must have a width)"
            )
        return self.spring_constant(w - 2 * b), self.spring_constant(w + 2 * b)

    def check_width(self, width_um: float) -> float:
        """Return ``width_um`` as float or raise ValueError if outside the process bounds."""
        w = _positive_finite("width_um", width_um)
        if not (self.min_width_um <= w <= self.max_width_um):
            raise ValueError(
                f"width_um = {w:g} µm: must lie in the process bounds "
                f"[{self.min_width_um:g}, {self.max_width_um:g}] µm of suspension {self.name!r}"
            )
        return w

    def describe(self) -> str:
        """One-line description, e.g. ``paper (l = 189 µm, t = 2.25 µm, 1 parallel/1 series)``."""
        return (
            f"{self.name} (l = {self.length_um:g} µm, t = {self.thickness_um:g} µm, "
            f"{self.n_parallel} parallel/{self.n_series} series)"
        )

    def to_json(self) -> dict:
        return {
            "name": self.name,
            "length_um": self.length_um,
            "thickness_um": self.thickness_um,
            "youngs_modulus_Pa": self.youngs_modulus,
            "n_parallel": self.n_parallel,
            "n_series": self.n_series,
            "width_bounds_um": [self.min_width_um, self.max_width_um],
            "etch_bias_um": self.etch_bias_um,
        }

    @classmethod
    def from_json(cls, d: dict) -> Suspension:
        """The suspension back from :meth:`to_json` (default etch bias when it is absent)."""
        lo, hi = d["width_bounds_um"]
        return cls(length_um=d["length_um"], thickness_um=d["thickness_um"], youngs_modulus=d["youngs_modulus_Pa"],
                   n_parallel=d["n_parallel"], n_series=d["n_series"], min_width_um=lo, max_width_um=hi,
                   etch_bias_um=d.get("etch_bias_um", ETCH_BIAS_UM), name=d["name"])


PAPER_SUSPENSION = Suspension()
"""The paper's suspension: l = 189 µm, t = 2.25 µm, E = 164 GPa (springs 0.24–20.3 N/m)."""
LONG_SUSPENSION = Suspension(length_um=LONG_BEAM_LENGTH_UM, name="long")
"""A 390 µm beam for the softest springs (0.028 N/m at w = 1.65 µm); our assumption."""


@dataclass(frozen=True)
class SpringDesign:
    """One spring: a nominal effective width on a suspension.

    Parameters
    ----------
    width_um : float
        Nominal effective width w (µm), within the suspension's process bounds.
    suspension : Suspension
        The suspension it is made on.
    """

    width_um: float
    suspension: Suspension = PAPER_SUSPENSION

    def __post_init__(self) -> None:
        if not isinstance(self.suspension, Suspension):
            raise ValueError(f"SpringDesign.suspension = {self.suspension!r}: must be a Suspension")
        object.__setattr__(self, "width_um", self.suspension.check_width(self.width_um))

    @property
    def spring_constant(self) -> float:
        """Nominal spring constant k (N/m)."""
        return self.suspension.spring_constant(self.width_um)

    @property
    def drawn_width_um(self) -> float:
        """Width to draw on the mask (µm): ``width_um + 2·etch_bias_um``."""
        return drawn_width_um(self.width_um, self.suspension.etch_bias_um)

    def spring_constant_range(self, etch_bias_um: float | None = None) -> tuple[float, float]:
        """(k_soft, k_stiff) in N/m at the realised widths ``w ∓ 2b``."""
        return self.suspension.spring_constant_range(self.width_um, etch_bias_um)


def spring_constant(width_um: ArrayLike, suspension: Suspension = PAPER_SUSPENSION) -> ArrayLike:
    """Spring constant k (N/m) of an effective width (µm) on a suspension; Eq. (1).

    Parameters
    ----------
    width_um : float or array
        Effective (after etch bias) beam width (µm).
    suspension : Suspension
        Default: the paper's 189 µm beam.
    """
    return suspension.spring_constant(width_um)


def width_for_spring_constant(
    spring_constant: ArrayLike, suspension: Suspension = PAPER_SUSPENSION
) -> ArrayLike:
    """Effective width (µm) giving spring constant k (N/m) on a suspension; inverse of Eq. (1)."""
    return suspension.width_um(spring_constant)


def effective_width_um(drawn_width_um: ArrayLike, etch_bias_um: float = ETCH_BIAS_UM) -> ArrayLike:
    """Effective width (µm) of a drawn width (µm): ``drawn − 2·etch_bias_um``."""
    w = np.asarray(drawn_width_um, dtype=float) - 2.0 * float(etch_bias_um)
    if np.any(~np.isfinite(w)) or np.any(w <= 0):
        raise ValueError(
            f"drawn_width_um = {drawn_width_um!r}: must exceed 2·etch_bias_um = "
            f"{2 * float(etch_bias_um):g} µm"
        )
    return float(w) if w.ndim == 0 else w


def drawn_width_um(effective_width_um: ArrayLike, etch_bias_um: float = ETCH_BIAS_UM) -> ArrayLike:
    """Drawn (mask) width (µm) of an effective width (µm): ``effective + 2·etch_bias_um``."""
    w = np.asarray(effective_width_um, dtype=float)
    if np.any(~np.isfinite(w)) or np.any(w <= 0):
        raise ValueError(f"effective_width_um = {effective_width_um!r}: must be finite and > 0 µm")
    d = w + 2.0 * float(etch_bias_um)
    return float(d) if d.ndim == 0 else d


def paper_springs(
    paper_suspension: Suspension = PAPER_SUSPENSION, soft_suspension: Suspension = LONG_SUSPENSION
) -> tuple[SpringDesign, ...]:
    """The paper's four springs, with nominal k = 0.028, 0.24, 2.13, 20.3 N/m.

    The 0.028 N/m spring is placed on ``soft_suspension`` (the paper gives no geometry), the
    others on ``paper_suspension``; widths are the inverse of Eq. (1) for the paper's spring
    constants (1.65 µm on the long beam; 1.638, 3.390, 7.19 µm — the paper states 1.64, 3.39,
    7.23 µm).
    """
    suspensions = (soft_suspension,) + (paper_suspension,) * 3
    return tuple(
        SpringDesign(s.width_um(k), s) for k, s in zip(PAPER_SPRING_CONSTANTS, suspensions)
    )

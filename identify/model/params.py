"""The one parameter table of nanofrictor.

Every physical number of the platform lives here: a :class:`ParamSpec` per symbol
(name, unit, nominal value, bounds, scale, whether it is best handled on a log scale),
the named friction sets of the paper's Table II (FOTAS, OTS) and the platform
constants (block mass, air damping, puller step, electrostatic geometry).

Values are SI inside the toolkit; names at the edges carry their units
(``normal_load_uN``). Source: ``shared/MODEL.md`` (the restored equations and
Table II of the paper), equation numbers are the paper's.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from identify.model.errors import ParameterError
from identify.model.plausible import PARAMETER_RANGES

__all__ = [
    "ParamSpec",
    "SPECS",
    "TOPO_MODES",
    "topo_field_names",
    "WALK_MODES",
    "walk_names",
    "walk_mode",
    "walk_prior_sd",
    "EXPOSURE_ALIGNMENTS",
    "exposure_align",
    "CONDITION_SPECS",
    "PARAMETER_SETS",
    "EPS_AIR",
    "ELECTROSTATIC",
    "spec",
    "parameter_set",
    "validate_parameters",
    "normal_load_from_voltage",
    "voltage_for_normal_load",
    "ParameterError",
]


@dataclass(frozen=True)
class ParamSpec:
    """One model parameter.

    Attributes
    ----------
    name : str
        Identifier used everywhere (``mu_max``, ``tau``, ...).
    unit : str
        SI unit of the value ("-" for dimensionless).
    nominal : float
        Default value (FOTAS for friction parameters, the platform's value otherwise).
    lower, upper : float
        Physically admissible bounds (inclusive); fits are bounded by these.
    scale : float
        Typical magnitude; optimisers see ``value / scale`` (or ``log(value/scale)``).
    log : bool
        Whether the parameter is positive and best estimated on a log scale.
    kind : str
        ``friction``, ``platform``, ``effect`` (model extension with a null value) or
        ``measurement``.
    description : str
        What it is, with the paper's symbol and equation.
    display_unit, display_factor : str, float
        Unit for reports and plots and the factor SI -> display.
    """

    name: str
    unit: str
    nominal: float
    lower: float
    upper: float
    scale: float
    log: bool = False
    kind: str = "friction"
    description: str = ""
    display_unit: str = ""
    display_factor: float = 1.0

    def check(self, value: float, where: str = "") -> float:
        """Return ``value`` as float or raise :class:`ParameterError` naming the rule."""
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise ParameterError(f"{where}{self.name}: {value!r} is not a number") from None
        if not math.isfinite(v):
            raise ParameterError(f"{where}{self.name} = {v}: must be a finite number")
        if v < self.lower or v > self.upper:
            r = PARAMETER_RANGES.get(self.name)
            hint = r.hint(v) if r is not None else ""
            raise ParameterError(
                f"{where}{self.name} = {v:g} {self.unit}: must lie in "
                f"[{self.lower:g}, {self.upper:g}] {self.unit}" + (f": {hint}" if hint else "")
            )
        if self.log and v <= 0:
            raise ParameterError(f"{where}{self.name} = {v:g}: must be > 0")
        return v

    def to_display(self, value: float) -> float:
        return value * self.display_factor

    @property
    def shown_unit(self) -> str:
        return self.display_unit or self.unit


def _s(*args, **kw) -> ParamSpec:
    return ParamSpec(*args, **kw)


# Friction-law parameters (Eqs. 18-19 and the alternative laws of Fig. 11).
# Nominal values are FOTAS, Table II; mu_0 and B (logarithmic law) have no value in the
# paper: their nominal values are illustrative (mu_0 = mu_min of FOTAS, B such that the
# static coefficient reaches FOTAS's mu_max after 1 s of rest).
_FRICTION = [
    _s("mu_max", "-", 0.796, 0.0, 3.0, 0.5, description="saturated static friction coefficient μmax (Eq. 10)"),
    _s("mu_min", "-", 0.484, 0.0, 3.0, 0.5, description="fully rejuvenated friction coefficient μmin (Eq. 15)"),
    _s("tau", "s", 0.0674, 1e-6, 1e3, 0.1, log=True, description="aging time constant τ (Eq. 10)",
       display_unit="ms", display_factor=1e3),
    _s("A", "-", 0.015, 0.0, 1.0, 0.01, description="velocity-strengthening coefficient A (Eq. 18)"),
    _s("vc", "m/s", 1e-6, 1e-12, 1.0, 1e-6, log=True, description="velocity normalisation vc (Eq. 18)",
       display_unit="µm/s", display_factor=1e6),
    _s("dc", "m", 2e-8, 1e-12, 1e-5, 2e-8, log=True, description="memory length dc (Eq. 15)",
       display_unit="nm", display_factor=1e9),
    _s("mu_0", "-", 0.484, 0.0, 3.0, 0.5,
       description="logarithmic law: friction coefficient at zero contact age μ0 (Eq. 1)"),
    _s("B", "-", 0.0794, 0.0, 1.0, 0.05,
       description="logarithmic law: aging coefficient B (Eq. 1)"),
]

# Platform constants (MODEL.md: symbols, Eqs. 5-7).
_PLATFORM = [
    _s("mb", "kg", 3.64e-10, 1e-14, 1e-6, 3.64e-10, log=True, kind="platform",
       description="effective block mass mb", display_unit="ng", display_factor=1e12),
    _s("c", "N s/m", 3.57e-7, 0.0, 1e-2, 3.57e-7, kind="platform",
       description="air (Couette) damping c = η·Ab/gb (Eq. 7)", display_unit="µN s/m", display_factor=1e6),
    _s("step_size", "m", 46e-9, 1e-10, 1e-5, 46e-9, log=True, kind="platform",
       description="puller step Δxp", display_unit="nm", display_factor=1e9),
]

# Model extensions with a null value that gives back the paper's model. The simulator
# always carries them, so one compiled model serves every candidate of the diagnosis.
TOPO_MODES = 8
"""Modes of the rough track's Fourier series (:class:`identify.model.effects.TopographyField`):
wavelengths down to L/8, a few µm on a track of tens of µm, longer than a slip."""

_EFFECTS = [
    _s("v_stick", "m/s", 0.0, 0.0, 1.0, 1e-4, kind="effect",
       description="stick threshold (Karnopp band): a block slower than this is held while the "
       "spring force is within F0(ψ, v_stick); 0 = the equations as written",
       display_unit="µm/s", display_factor=1e6),
    _s("c_extra", "N s/m", 0.0, -1e-3, 1e-2, 1e-6, kind="effect",
       description="extra viscous damping added to c", display_unit="µN s/m", display_factor=1e6),
    _s("beta", "1/m^2", 0.0, -1e12, 1e12, 1e8, kind="effect",
       description="spring nonlinearity: F = k·e·(1 + β·e²)", display_unit="1/µm²", display_factor=1e-12),
    _s("k_scale", "-", 1.0, 0.1, 10.0, 1.0, kind="effect",
       description="true spring constant / nominal"),
    _s("load_offset", "N", 0.0, -1e-3, 1e-3, 1e-6, kind="effect",
       description="adhesion-like extra normal force Fa (Eq. 6)", display_unit="µN", display_factor=1e6),
    _s("load_scale", "-", 1.0, 0.1, 10.0, 1.0, kind="effect",
       description="true normal load / nominal"),
    _s("step_scale", "-", 1.0, 0.1, 10.0, 1.0, kind="effect",
       description="true puller step / nominal"),
    _s("topo_amp", "-", 0.0, -1.0, 1.0, 0.01, kind="effect",
       description="topography: amplitude of a friction-coefficient ripple along the track"),
    _s("topo_wavelength", "m", 5e-6, 1e-8, 1e-3, 5e-6, log=True, kind="effect",
       description="topography: wavelength of the ripple", display_unit="µm", display_factor=1e6),
    _s("topo_phase", "rad", 0.0, -1e3, 1e3, 1.0, kind="effect",
       description="topography: phase of the ripple at x = 0"),
    _s("topo_length", "m", 5e-5, 1e-7, 1e-2, 5e-5, log=True, kind="effect",
       description="rough track: the period L of its Fourier series (longer than the track travelled, "
       "so the series need not repeat on it)", display_unit="µm", display_factor=1e6),
    *(_s(f"topo_{part}{j}", "-", 0.0, -1.0, 1.0, 0.01, kind="effect",
         description=f"rough track: {'cosine' if part == 'c' else 'sine'} coefficient of mode {j}, "
         f"wavelength L/{j}")
      for j in range(1, TOPO_MODES + 1) for part in ("c", "s")),
]

WALK_MODES = 6
"""Modes of a run's random walk of the camera's zero (:class:`identify.model.effects.DriftWalk`):
the Karhunen–Loève series of a Wiener process on the run, √2·sin((m − ½)π·t/T); the sixth
mode's prior variance is 1/121 of the first's, so the ones left out hold ~3 % of the walk's
variance."""

# Measurement-side parameters (they change what the camera reports, not the motion).
_MEASUREMENT = [
    _s("e_offset", "m", 0.0, -1e-4, 1e-4, 1e-7, kind="measurement",
       description="elongation zero offset of the camera", display_unit="µm", display_factor=1e6),
    _s("drift_rate", "m/s", 0.0, -1e-3, 1e-3, 1e-8, kind="measurement",
       description="slow drift of the measured elongation", display_unit="µm/s", display_factor=1e6),
    _s("exposure", "s", 0.0, 0.0, 1.0, 1e-3, kind="measurement",
       description="exposure time: each frame averages e over it (motion blur)",
       display_unit="ms", display_factor=1e3),
    _s("clock_shift", "s", 0.0, -1.0, 1.0, 1e-4, kind="measurement",
       description="how much later the puller's steps fall than the step phase estimated from the "
       "frames says (a blurred exposure moves that estimate)", display_unit="ms", display_factor=1e3),
    _s("exposure_align", "-", 0.5, 0.0, 1.0, 0.5, kind="measurement",
       description="share of the exposure before the frame's timestamp: 0 starts at it, 0.5 centred "
       "on it, 1 ends at it (EXPOSURE_ALIGNMENTS)"),
    *(_s(f"walk_{m}", "m", 0.0, -1e-4, 1e-4, 1e-8, kind="measurement",
         description=f"random walk of the camera's zero: coefficient of mode {m} of its series over the "
         f"run, √2·sin(({m} − ½)π·t/T)", display_unit="nm", display_factor=1e9)
      for m in range(1, WALK_MODES + 1)),
]


EXPOSURE_ALIGNMENTS = {"start": 0.0, "centre": 0.5, "center": 0.5, "end": 1.0}
"""Where the exposure window sits on a frame's timestamp, by name, as ``exposure_align``."""


def exposure_align(value) -> float:
    """``exposure_align`` from a name of :data:`EXPOSURE_ALIGNMENTS` or a share in [0, 1]."""
    if isinstance(value, str):
        key = value.strip().lower()
        if key not in EXPOSURE_ALIGNMENTS:
            raise ParameterError(f"exposure alignment {value!r}: must be one of start, centre, end "
                                 "(or a share of the exposure before the timestamp, 0 to 1)")
        return EXPOSURE_ALIGNMENTS[key]
    a = float(value)
    if not (0.0 <= a <= 1.0):
        raise ParameterError(f"exposure_align = {value!r}: must lie in [0, 1] (0 start, 0.5 centre, 1 end)")
    return a

def walk_names() -> tuple:
    """A run's random-walk coefficients, mode by mode: walk_1, walk_2, ..."""
    return tuple(f"walk_{m}" for m in range(1, WALK_MODES + 1))


def walk_mode(name: str) -> int | None:
    """The mode m of a walk coefficient (``walk_3`` or ``walk_3@run:r1`` -> 3), else None."""
    base = name.partition("@")[0]
    return int(base[5:]) if base in walk_names() else None


def walk_prior_sd(intensity: float, mode: int, span_s: float) -> float:
    """The standard deviation of mode ``mode``'s coefficient of a Wiener process of
    ``intensity`` (m/√s) over a run of ``span_s`` seconds: σ_w·√T/((m − ½)π), the
    Karhunen–Loève series' (the coefficients are independent with these spreads)."""
    return float(intensity) * math.sqrt(float(span_s)) / ((mode - 0.5) * math.pi)


def topo_field_names() -> tuple:
    """The rough track's coefficients, mode by mode: topo_c1, topo_s1, topo_c2, ..."""
    return tuple(f"topo_{part}{j}" for j in range(1, TOPO_MODES + 1) for part in ("c", "s"))


SPECS: dict[str, ParamSpec] = {p.name: p for p in _FRICTION + _PLATFORM + _EFFECTS + _MEASUREMENT}

# Conditions of a run (not estimated by default; SI).
CONDITION_SPECS: dict[str, ParamSpec] = {
    p.name: p
    for p in [
        _s("k", "N/m", 2.13, 1e-4, 1e4, 1.0, log=True, kind="condition",
           description="lateral spring constant k (1 N/m = 1 µN/µm)", display_unit="N/m"),
        _s("Nb", "N", 5e-6, 1e-10, 1e-2, 1e-6, log=True, kind="condition",
           description="normal load Nb", display_unit="µN", display_factor=1e6),
        _s("fp", "Hz", 100.0, 1e-3, 1e7, 100.0, log=True, kind="condition",
           description="puller step frequency fp", display_unit="Hz"),
    ]
}

# Table II of the paper (exponential-law fit), with the platform constants.
_TABLE_II = {
    "FOTAS": dict(mu_max=0.796, mu_min=0.484, tau=0.0674, A=0.015, vc=1e-6, dc=20e-9),
    "OTS": dict(mu_max=0.577, mu_min=0.404, tau=0.0845, A=0.005, vc=1e-6, dc=20e-9),
}
PARAMETER_SETS: dict[str, dict[str, float]] = {
    name: {**{n: s.nominal for n, s in SPECS.items()}, **vals, "mu_0": vals["mu_min"]}
    for name, vals in _TABLE_II.items()
}
"""Named parameter sets: Table II (FOTAS, OTS) plus platform constants and null effects."""

# Electrostatic normal-load model (Eqs. 5-6).
EPS_AIR = 8.854e-12 * 1.00059  # F/m
ELECTROSTATIC = dict(
    plate_area=14_700e-12,  # m², the four effective plates
    gap=1.6e-6,  # m, block gap gb with the feet in contact
    kz=0.030,  # N/m, vertical spring (kz·gb = 0.048 µN)
    # Effective ε·A is ~0.79 × the parallel-plate value: least squares over the paper's
    # pairs (7.15 V -> 0.98 µN, 55.02 V -> 60.8 µN) gives 0.790; see tests/identify/test_params.py.
    calibration=0.790,
    adhesion=0.0,  # N, Fa; the paper finds none
)


def spec(name: str) -> ParamSpec:
    """The spec of a parameter or condition, with a clear error for unknown names."""
    if name in SPECS:
        return SPECS[name]
    if name in CONDITION_SPECS:
        return CONDITION_SPECS[name]
    if "@" in name:  # a per-run or per-device value (identify.model.scopes)
        from identify.model.scopes import parse, scoped_spec

        try:
            base = parse(name)[0]
        except ValueError as err:
            raise ParameterError(str(err)) from None
        return scoped_spec(name, SPECS[base])
    raise ParameterError(
        f"unknown parameter {name!r}; known: {', '.join(sorted(SPECS))}"
    )


def parameter_set(coating: str = "FOTAS", overrides: Mapping[str, float] | None = None) -> dict[str, float]:
    """Table II parameters for ``coating`` (FOTAS or OTS), with ``overrides`` applied.

    Raises
    ------
    ParameterError
        For an unknown coating, an unknown parameter name or a value outside its bounds,
        or ``mu_min >= mu_max``.
    """
    key = coating.upper() if isinstance(coating, str) else coating
    if key not in PARAMETER_SETS:
        raise ParameterError(
            f"coating {coating!r} is not known; choose one of {', '.join(PARAMETER_SETS)}"
        )
    values = dict(PARAMETER_SETS[key])
    for name, value in (overrides or {}).items():
        values[name] = spec(name).check(value)
    return validate_parameters(values)


def validate_parameters(values: Mapping[str, float], where: str = "") -> dict[str, float]:
    """Check every value against its spec and the cross-parameter rules."""
    out = {}
    for name, value in values.items():
        out[name] = spec(name).check(value, where)
    if "mu_max" in out and "mu_min" in out and out["mu_min"] >= out["mu_max"]:
        raise ParameterError(
            f"{where}mu_min = {out['mu_min']:g} must be smaller than mu_max = {out['mu_max']:g}"
        )
    return out


def normal_load_from_voltage(
    voltage_V: float | Iterable[float],
    calibration: float | None = None,
    adhesion_N: float | None = None,
):
    """Normal load Nb (N) from the block voltage Vb (V), Eqs. 5-6.

    ``Nb = cal·ε_air·A_plate·Vb²/(2·gb²) − kz·gb + Fa``; the block weight is neglected
    (about 3 % gap change, MODEL.md). ``calibration`` defaults to the factor that
    reproduces the paper's voltage/load pairs.
    """
    import numpy as np

    g = ELECTROSTATIC
    cal = g["calibration"] if calibration is None else calibration
    fa = g["adhesion"] if adhesion_N is None else adhesion_N
    v = np.asarray(voltage_V, dtype=float)
    if not np.all(np.isfinite(v)):
        raise ParameterError(f"block_voltage_V = {voltage_V!r}: must be a finite number")
    fe = cal * EPS_AIR * g["plate_area"] * v**2 / (2 * g["gap"] ** 2)
    nb = fe - g["kz"] * g["gap"] + fa
    if np.any(nb <= 0):
        raise ParameterError(
            f"block_voltage_V = {voltage_V!r}: too low to close the gap "
            f"(needs Vb > {voltage_for_normal_load(0.0, cal, fa):.2f} V for any normal load)"
        )
    return float(nb) if nb.ndim == 0 else nb


def voltage_for_normal_load(normal_load_N: float, calibration: float | None = None,
                            adhesion_N: float | None = None) -> float:
    """Inverse of :func:`normal_load_from_voltage`: the Vb (V) giving ``normal_load_N``."""
    g = ELECTROSTATIC
    cal = g["calibration"] if calibration is None else calibration
    fa = g["adhesion"] if adhesion_N is None else adhesion_N
    fe = normal_load_N + g["kz"] * g["gap"] - fa
    return math.sqrt(max(fe, 0.0) * 2 * g["gap"] ** 2 / (cal * EPS_AIR * g["plate_area"]))

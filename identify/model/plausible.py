"""What the platform can do: the range of each run condition, checked where a value
enters the toolkit (a trace's metadata, ``simulate``), so that a value typed in the wrong
unit is caught with the likely slip named rather than fitted in silence.

The ranges are the platform's (``docs/model.md``, Table I and the camera): the normal
load up to the block voltage limit of 452 µN, down to what the electrostatic actuator
resolves; springs of 0.01-100 N/m; step frequencies of 1 Hz-10 kHz; puller steps of
1-1000 nm; a block of 1e-13-1e-7 kg. A run outside them on purpose is accepted when
told so: ``"outside_platform_ranges": true`` in its metadata, ``check_platform=False``
in :func:`identify.simulate` and :class:`identify.FitOptions`.

Model parameters typed by a user (a fit's fixed and start values, a simulation's
overrides) are checked the same way against the range a MEMS contact on this platform
can plausibly have (:data:`PARAMETER_RANGES`, in SI): narrower than the bounds a fit may
search, so that ``tau = 67.4`` (milliseconds typed for seconds) is caught, while the
fit's own iterates are never judged by it.
"""

from __future__ import annotations

import math

from identify.model.errors import ParameterError

__all__ = ["PARAMETER_RANGES", "PLATFORM_RANGES", "PlatformRange", "check_parameters", "parameter_problem",
           "platform_problem"]


class PlatformRange:
    """The admissible range of one condition, in the unit of its field."""

    def __init__(self, lo: float, hi: float, unit: str, why: str, units: dict[float, str]):
        self.lo, self.hi, self.unit, self.why = lo, hi, unit, why
        self.units = units  # factor -> the unit a value that factor off was likely given in

    def outside(self, name: str, value: float, what: str, override: str) -> str | None:
        """The message for ``name`` = ``value`` outside the range ('what' it is outside
        of, and how to override), with the likely slip; None when inside or not a
        positive number (that is another rule's business)."""
        if not math.isfinite(value) or value <= 0 or self.lo <= value <= self.hi:
            return None
        hint = self.hint(value)
        return (f"{name} = {value:g} {self.unit} lies outside {what}, {self.lo:g} to {self.hi:g} {self.unit} "
                f"({self.why})" + (f": {hint}" if hint else "") + f"; {override}")

    def hint(self, value: float) -> str:
        """The likely unit slip of a value outside the range ('' if none fits)."""
        for factor, name in self.units.items():
            if self.lo <= value * factor <= self.hi:
                return f"did you give it in {name}? ({value * factor:.4g} {self.unit})"
        return ""


PLATFORM_RANGES = {
    "normal_load_uN": PlatformRange(
        0.01, 452.0, "µN", "the block voltage limits Nb to 452 µN (Table I)",
        {1e6: "newtons", 1e3: "mN", 1e-3: "nN"}),
    "spring_constant_N_per_m": PlatformRange(
        0.01, 100.0, "N/m", "Table I: 0.01 N/m < k < 100 N/m",
        {1e-6: "µN/m", 1e-3: "mN/m", 1e3: "kN/m"}),
    "step_frequency_Hz": PlatformRange(
        1.0, 1e4, "Hz", "the puller steps at 10 Hz to 10 kHz",
        {1e3: "kHz", 1e-3: "mHz"}),
    "step_size_nm": PlatformRange(
        1.0, 1000.0, "nm", "the puller's step is 46 nm",
        {1e9: "metres", 1e3: "µm", 1e-3: "pm"}),
    "block_mass_kg": PlatformRange(
        1e-13, 1e-7, "kg", "the friction block's mass is 3.6e-10 kg",
        {1e-3: "grams", 1e-6: "milligrams", 1e-9: "micrograms"}),
}


def platform_problem(name: str, value: float) -> str | None:
    """Why ``value`` of the condition ``name`` (a key of :data:`PLATFORM_RANGES`, in its
    field's unit) lies outside what the platform can do, with the likely unit slip; None
    when it lies inside or ``name`` has no range (a value that is not a positive number is
    left to the rule that it must be one)."""
    r = PLATFORM_RANGES.get(name)
    return None if r is None else r.outside(
        name, value, "what the platform can do",
        "a run outside on purpose says so (\"outside_platform_ranges\": true in its metadata; "
        "check_platform=False in simulate, --outside-platform-ranges on the command line)")


PARAMETER_RANGES = {
    "mu_max": PlatformRange(0.05, 2.0, "-", "friction coefficients of MEMS contacts lie between ~0.05 and 2",
                            {0.01: "per cent"}),
    "mu_min": PlatformRange(0.0, 2.0, "-", "friction coefficients of MEMS contacts lie between ~0.05 and 2",
                            {0.01: "per cent"}),
    "mu_0": PlatformRange(0.0, 2.0, "-", "friction coefficients of MEMS contacts lie between ~0.05 and 2",
                          {0.01: "per cent"}),
    "B": PlatformRange(0.0, 0.5, "-", "the logarithmic law's aging coefficient is a few per cent of μ",
                       {0.01: "per cent"}),
    "tau": PlatformRange(1e-6, 30.0, "s", "aging times up to tens of seconds; Table II: 67-85 ms",
                         {1e-3: "ms", 1e-6: "µs"}),
    "A": PlatformRange(0.0, 0.3, "-", "the rate term is a small share of μ; Table II: 0.005-0.015",
                       {0.01: "per cent"}),
    "vc": PlatformRange(1e-10, 1e-3, "m/s", "Table II: 1 µm/s", {1e-6: "µm/s", 1e-9: "nm/s", 1e-3: "mm/s"}),
    "dc": PlatformRange(1e-10, 1e-6, "m", "Table II: 20 nm", {1e-9: "nm", 1e-6: "µm"}),
    "mb": PlatformRange(1e-13, 1e-7, "kg", "the friction block's mass is 3.6e-10 kg", {1e-12: "ng", 1e-9: "µg"}),
    "c": PlatformRange(1e-10, 1e-4, "N s/m", "the air damping is 3.57e-7 N s/m", {1e-6: "µN s/m"}),
    "step_size": PlatformRange(1e-9, 1e-6, "m", "the puller's step is 46 nm", {1e-9: "nm"}),
    "v_stick": PlatformRange(1e-9, 1e-3, "m/s", "a stick threshold near the puller's speed, µm/s",
                             {1e-6: "µm/s", 1e-3: "mm/s"}),
    "exposure": PlatformRange(1e-7, 0.1, "s", "a high-speed camera's exposure is µs to ms", {1e-3: "ms", 1e-6: "µs"}),
}
"""The plausible range of each model parameter a user may type (SI units): values
outside are refused at the edges, with the likely unit slip. Parameters whose null is 0
(effects, offsets) are checked only when positive; those without an entry are not. A
lower end of 0 checks the upper end only: a fit may well end at μmin or A near 0."""


def parameter_problem(name: str, value: float) -> str | None:
    """Why the model parameter ``name`` = ``value`` (SI) lies outside what a contact on this
    platform can plausibly have, with the likely unit slip; None when it lies inside, is
    not positive (a null effect, or the bounds' business) or ``name`` has no range."""
    r = PARAMETER_RANGES.get(name)
    return None if r is None else r.outside(
        name, value, "the plausible range", "a value outside on purpose: check_platform=False "
        "(--outside-platform-ranges)")


def check_parameters(values, where: str = "") -> None:
    """Raise ``ParameterError`` naming every implausible value of ``values`` ({name: SI
    value}); ``where`` says where they came from ('fixed ', 'start ')."""
    problems = [p for n, v in dict(values).items() if (p := parameter_problem(n, float(v))) is not None]
    if problems:
        raise ParameterError(where + ("; ".join(problems)))

"""What the platform can do: the range of each run condition, checked where a value
enters the toolkit (a trace's metadata, ``simulate``), so that a value typed in the wrong
unit is caught with the likely slip named rather than fitted in silence.

The ranges are the platform's (``docs/model.md``, Table I and the camera): the normal
load up to the block voltage limit of 452 µN, down to what the electrostatic actuator
resolves; springs of 0.01-100 N/m; step frequencies of 1 Hz-10 kHz; puller steps of
1-1000 nm; a block of 1e-13-1e-7 kg. A run outside them on purpose is accepted when
told so: ``"outside_platform_ranges": true`` in its metadata, ``check_platform=False``
in :func:`identify.simulate`.
"""

from __future__ import annotations

import math

__all__ = ["PLATFORM_RANGES", "PlatformRange", "platform_problem"]


class PlatformRange:
    """The admissible range of one condition, in the unit of its field."""

    def __init__(self, lo: float, hi: float, unit: str, why: str, units: dict[float, str]):
        self.lo, self.hi, self.unit, self.why = lo, hi, unit, why
        self.units = units  # factor -> the unit a value that factor off was likely given in

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
    if r is None or not math.isfinite(value) or value <= 0 or r.lo <= value <= r.hi:
        return None
    hint = r.hint(value)
    return (f"{name} = {value:g} {r.unit} lies outside what the platform can do, {r.lo:g} to {r.hi:g} {r.unit} "
            f"({r.why})" + (f": {hint}" if hint else "")
            + "; a run outside on purpose says so (\"outside_platform_ranges\": true in its metadata, "
            "check_platform=False in simulate)")

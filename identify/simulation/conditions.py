"""The inputs of a simulated run: its conditions (spring, load, steps), how its moving
phases are integrated (:mod:`identify.simulation.hybrid`), and the checks and unit
conversions that turn the front end's arguments (:func:`identify.simulation.hybrid.simulate`)
into them."""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass

from identify.model.params import ParameterError, normal_load_from_voltage
from identify.model.plausible import check_parameters, platform_problem

__all__ = ["RunConditions", "SimulationOptions", "MAX_TRAVEL_M"]

MAX_TRAVEL_M = 100e-6  # nanotractor travel (Table I)


@dataclass(frozen=True)
class RunConditions:
    """The conditions of one run, SI.

    Parameters
    ----------
    spring_constant : float
        k, N/m.
    normal_load : float
        Nb, N.
    step_frequency : float
        fp, Hz.
    n_steps : int
        Number of puller steps (travel = n_steps·Δxp).
    first_step_time : float, optional
        Time of the first step, s (default 1/fp: steps at t = n/fp, n ≥ 1).
    initial_elongation : float
        e at t = 0, m (default 0: spring relaxed).
    initial_state : float or None
        Contact state at t = 0 (None: fully aged, ψ = μmax for the exponential law).
    """

    spring_constant: float
    normal_load: float
    step_frequency: float
    n_steps: int
    first_step_time: float | None = None
    initial_elongation: float = 0.0
    initial_state: float | None = None

    def __post_init__(self):
        for name, value, rule in (
            ("spring_constant_N_per_m", self.spring_constant, "must be > 0"),
            ("normal_load", self.normal_load, "must be > 0"),
            ("step_frequency_Hz", self.step_frequency, "must be > 0"),
        ):
            v = float(value)
            if not math.isfinite(v) or v <= 0:
                raise ParameterError(f"{name} = {value!r}: {rule} and finite")
        if int(self.n_steps) != self.n_steps or self.n_steps < 1:
            raise ParameterError(f"n_steps = {self.n_steps!r}: must be a positive integer (travel > 0)")
        if not math.isfinite(float(self.initial_elongation)):
            raise ParameterError(f"initial_elongation = {self.initial_elongation!r}: must be finite")

    @property
    def t_first(self) -> float:
        return 1.0 / self.step_frequency if self.first_step_time is None else float(self.first_step_time)

    @property
    def end_time(self) -> float:
        """The run ends one step period after its last step."""
        return self.t_first + self.n_steps / self.step_frequency


@dataclass(frozen=True)
class SimulationOptions:
    """How moving phases are integrated.

    Parameters
    ----------
    integrator : {"idas", "rosenbrock"}
        Engine for moving phases (module docstring).
    reltol, abstol : float or None
        Integrator tolerances (abstol in the scaled units: µm, mm/s). Defaults per
        engine: rosenbrock 1e-5/1e-6 (slip lengths within 1e-3 nm of a 1e-10 reference),
        idas 1e-8/1e-10 (looser IDAS tolerances mis-time the creep nucleation).
    record : bool
        Keep the fine trajectory of every moving phase (for plots and frame sampling
        inside slips); False keeps only the events.
    max_phase_steps : int
        A moving phase that crosses more puller steps than this is cut short and the run
        stopped with a warning (protects against runaway cost).
    """

    integrator: str = "rosenbrock"
    reltol: float | None = None
    abstol: float | None = None
    record: bool = True
    max_phase_steps: int = 1_000_000

    def __post_init__(self):
        if self.integrator not in ("idas", "rosenbrock"):
            raise ValueError(
                f"integrator = {self.integrator!r}: choose 'idas' or 'rosenbrock'"
            )
        defaults = {"rosenbrock": (1e-5, 1e-6), "idas": (1e-8, 1e-10)}[self.integrator]
        for name, default in zip(("reltol", "abstol"), defaults):
            v = getattr(self, name)
            if v is None:
                object.__setattr__(self, name, default)
                continue
            if not (v > 0 and math.isfinite(v)):
                raise ValueError(f"{name} = {v!r}: must be a positive number")


# ----------------------------------------------------------------------------- from the front end
def normal_load_N(normal_load_uN: float | None, block_voltage_V: float | None) -> float:
    """Nb, N, from exactly one of the normal load (µN) or the block voltage (V, through
    Eqs. 5-6)."""
    if (normal_load_uN is None) == (block_voltage_V is None):
        raise ParameterError("give exactly one of normal_load_uN or block_voltage_V")
    if normal_load_uN is not None:
        nb = float(normal_load_uN)
        if not math.isfinite(nb) or nb <= 0:
            raise ParameterError(f"normal_load_uN = {normal_load_uN!r}: must be > 0 and finite")
        return nb * 1e-6
    return normal_load_from_voltage(block_voltage_V)


def check_platform_conditions(Nb: float, spring_constant_N_per_m: float, step_frequency_Hz: float) -> None:
    """Refuse a load, spring or step frequency outside what the platform can do
    (:data:`identify.model.plausible.PLATFORM_RANGES`)."""
    for name, value in (("normal_load_uN", Nb * 1e6), ("spring_constant_N_per_m", spring_constant_N_per_m),
                        ("step_frequency_Hz", step_frequency_Hz)):
        if (problem := platform_problem(name, float(value))) is not None:
            raise ParameterError(problem)


def parameter_overrides(params: Mapping[str, float] | None, stick_speed_m_per_s: float | None,
                         check_platform: bool) -> dict:
    """The parameter overrides: ``params`` and the stick threshold (``v_stick``), refused
    when implausible for a contact on the platform if ``check_platform``."""
    overrides = dict(params or {})
    if stick_speed_m_per_s is not None:
        overrides["v_stick"] = stick_speed_m_per_s
    if check_platform:
        check_parameters(overrides, "params: ")
    return overrides


def step_count(travel_um: float | None, n_steps: int | None, step: float) -> int:
    """The number of puller steps: ``n_steps``, or the travel (µm) rounded to whole steps
    of ``step`` (m), with a warning past the nanotractor's range."""
    if (travel_um is None) == (n_steps is None):
        raise ParameterError("give exactly one of travel_um or n_steps")
    if travel_um is None:
        return n_steps
    tr = float(travel_um)
    if not math.isfinite(tr) or tr <= 0:
        raise ParameterError(f"travel_um = {travel_um!r}: must be > 0 and finite")
    if tr * 1e-6 > MAX_TRAVEL_M * (1 + 1e-9):
        warnings.warn(
            f"travel_um = {tr:g} exceeds the nanotractor's {MAX_TRAVEL_M * 1e6:g} µm range",
            stacklevel=3,  # the caller of simulate
        )
    return max(1, int(round(tr * 1e-6 / step)))

"""Regime maps: which (Nb, fp) give stick-slip, stepping or creep for a spring.

Each grid point is one simulated run (:func:`identify.simulate`); the regime is the
run's :func:`identify.simulation.hybrid.classify` label. Used for the README's maps (equations as
written and with the stick-threshold option) and by ``design`` for operating ranges.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from identify.jsonio import SavedResult
from identify.progress import Stage, reporter
from identify.simulation.hybrid import SimulationOptions, simulate

__all__ = ["RegimeMap", "regime_map"]

log = logging.getLogger(__name__)


@dataclass
class RegimeMap(SavedResult):
    """Regimes over a (normal load, step frequency) grid for one spring.

    Attributes
    ----------
    normal_loads_uN, step_frequencies_Hz : ndarray
        Grid axes.
    regimes : ndarray of str, shape (n_loads, n_freqs)
    mean_slip_um, mean_peak_elongation_um, n_slips, wall_time_s : ndarray
        Per-run numbers (NaN where there was no slip).
    """

    coating: str
    spring_constant_N_per_m: float
    stick_speed_m_per_s: float
    travel_um: float | None
    normal_loads_uN: np.ndarray
    step_frequencies_Hz: np.ndarray
    regimes: np.ndarray
    n_slips: np.ndarray
    mean_slip_um: np.ndarray
    mean_peak_elongation_um: np.ndarray
    wall_time_s: np.ndarray
    errors: list = field(default_factory=list)

    def to_json(self) -> dict:
        return dict(
            coating=self.coating,
            spring_constant_N_per_m=self.spring_constant_N_per_m,
            stick_speed_m_per_s=self.stick_speed_m_per_s,
            travel_um=self.travel_um,
            normal_loads_uN=self.normal_loads_uN.tolist(),
            step_frequencies_Hz=self.step_frequencies_Hz.tolist(),
            regimes=self.regimes.tolist(),
            n_slips=self.n_slips.tolist(),
            mean_slip_um=np.where(np.isfinite(self.mean_slip_um), self.mean_slip_um, None).tolist(),
            mean_peak_elongation_um=np.where(np.isfinite(self.mean_peak_elongation_um),
                                             self.mean_peak_elongation_um, None).tolist(),
            wall_time_s=np.asarray(self.wall_time_s, float).tolist(),
            errors=list(self.errors),
        )

    @classmethod
    def from_dict(cls, d: dict) -> RegimeMap:
        """A map read back from :meth:`to_dict` (or ``identify regimes --json``)."""
        loads, fps = np.asarray(d["normal_loads_uN"], float), np.asarray(d["step_frequencies_Hz"], float)
        shape = (len(loads), len(fps))

        def grid(key, dtype=float):  # (null -> NaN; older files lack the keys written later)
            v = d.get(key)
            if v is None:
                return np.full(shape, np.nan)
            return np.array([[np.nan if x is None else x for x in row] for row in v], dtype).reshape(shape)

        return cls(coating=d["coating"], spring_constant_N_per_m=float(d["spring_constant_N_per_m"]),
                   stick_speed_m_per_s=float(d["stick_speed_m_per_s"]), travel_um=d.get("travel_um"),
                   normal_loads_uN=loads, step_frequencies_Hz=fps,
                   regimes=np.array(d["regimes"], dtype=object).astype(str).reshape(shape),
                   n_slips=np.array(d["n_slips"], int).reshape(shape), mean_slip_um=grid("mean_slip_um"),
                   mean_peak_elongation_um=grid("mean_peak_elongation_um"), wall_time_s=grid("wall_time_s"),
                   errors=list(d.get("errors", [])))

    def report(self) -> str:
        """The map as text (:meth:`table`) with the runs that could not be simulated."""
        head = (f"Regime map: {self.coating}, k = {self.spring_constant_N_per_m:g} N/m, "
                f"stick option {self.stick_speed_m_per_s:g} m/s")
        return "\n".join([head, self.table(), *(f"error: {e}" for e in self.errors)])

    def table(self) -> str:
        """The map as text: rows Nb, columns fp, one letter per regime."""
        code = {"stick-slip": "S", "stepping": "t", "creep": "C", "no-slip": "-", "error": "!"}
        head = "Nb \\ fp (Hz) " + " ".join(f"{f:>6g}" for f in self.step_frequencies_Hz)
        rows = [head]
        for i, nb in enumerate(self.normal_loads_uN):
            rows.append(f"{nb:>9.3g} µN  " + " ".join(f"{code.get(r, '?'):>6}" for r in self.regimes[i]))
        rows.append("S stick-slip, t stepping, C creep, - no slip within the travel")
        return "\n".join(rows)

    def plot(self, ax=None):
        from identify.plots.base import plot_regime_map

        return plot_regime_map(self, ax=ax)


def regime_map(
    coating: str = "FOTAS",
    spring_constant_N_per_m: float = 2.13,
    normal_loads_uN: Sequence[float] = (1, 2, 5, 10, 20, 30, 60),
    step_frequencies_Hz: Sequence[float] = (10, 30, 100, 300, 1000, 3000, 10000),
    travel_um: float | None = None,
    stick_speed_m_per_s: float = 0.0,
    law: str = "exponential",
    params: dict | None = None,
    progress: Callable[[str], None] | bool | None = None,
) -> RegimeMap:
    """Simulate every (Nb, fp) of the grid and classify it.

    ``progress`` (:mod:`identify.progress`): None draws a bar of the runs with the time
    left on a terminal, False is silent, a callable gets each message (with ``done``
    and ``total``).

    ``travel_um`` None gives each load enough travel for the first loading to μmax plus
    a few slips: max(20 µm, 3·μmax·Nb/k), at most the nanotractor's 100 µm. A failed
    run is marked ``error`` (and listed) rather than stopping the map.
    """
    from identify.model.params import parameter_set

    mu_top = parameter_set(coating, params or {}).get("mu_max", 0.8)
    loads = np.asarray(normal_loads_uN, float)
    freqs = np.asarray(step_frequencies_Hz, float)
    shape = (len(loads), len(freqs))
    regimes = np.full(shape, "", dtype=object)
    n = np.zeros(shape, int)
    slip = np.full(shape, np.nan)
    peak = np.full(shape, np.nan)
    wall = np.zeros(shape)
    errors = []
    stage = Stage(reporter(progress), "regime map", loads.size * freqs.size)
    for i, nb in enumerate(loads):
        for j, fp in enumerate(freqs):
            try:
                tr = travel_um if travel_um else min(100.0, max(20.0, 3 * mu_top * nb / spring_constant_N_per_m))
                r = simulate(
                    coating, spring_constant_N_per_m=spring_constant_N_per_m, normal_load_uN=nb,
                    step_frequency_Hz=fp, travel_um=tr, law=law, params=params,
                    stick_speed_m_per_s=stick_speed_m_per_s, options=SimulationOptions(record=False),
                )
                regimes[i, j] = r.regime
                sl = r.slips
                n[i, j] = len(sl)
                if len(sl):
                    slip[i, j] = np.mean(sl["slip_length_m"]) * 1e6
                    peak[i, j] = np.mean(sl["peak_elongation_m"]) * 1e6
                wall[i, j] = r.wall_time_s
            except Exception as err:  # one bad point never sinks the map
                regimes[i, j] = "error"
                errors.append(f"Nb = {nb:g} µN, fp = {fp:g} Hz: {err}")
                log.warning(errors[-1])
            stage.advance(f"Nb = {nb:g} µN, fp = {fp:g} Hz: {regimes[i, j]}")
    return RegimeMap(
        coating=coating, spring_constant_N_per_m=spring_constant_N_per_m,
        stick_speed_m_per_s=stick_speed_m_per_s, travel_um=travel_um,
        normal_loads_uN=loads, step_frequencies_Hz=freqs, regimes=regimes.astype(str),
        n_slips=n, mean_slip_um=slip, mean_peak_elongation_um=peak, wall_time_s=wall, errors=errors,
    )


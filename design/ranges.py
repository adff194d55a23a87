"""Operating ranges of one spring: where in (Nb, fp) a run is worth recording.

A grid point (Nb, fp) is *usable* when every rule below holds (issue 4, item 4):

==============  =======================================================================
rule            test
==============  =======================================================================
``table_i``     Nb inside the spring's Table I range (:func:`allowed_load_range`)
``camera``      ``frames_per_step·fp <= max_frame_rate`` (2 frames per step, 10 000 fps)
``regime``      the simulated run is clean stick-slip (not creep, stepping or no slip)
``slip_length`` mean slip length >= ``min_slip`` (90 nm, the camera's resolution)
``slip_count``  at least ``min_slips`` slips fit in the puller travel
==============  =======================================================================

The camera rule depends on fp only, so those points are excluded before simulating. The
regimes come from :func:`identify.simulation.regimes.regime_map`: one simulated run per point over the
whole travel, so the slip count is counted, not extrapolated.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from identify.fitting.stick_choice import STICK_SPEED_AUTO
from identify.jsonio import SavedResult
from identify.model.params import parameter_set
from identify.simulation.regimes import regime_map

from . import constraints as tc

__all__ = ["DEFAULT_STEP_FREQUENCIES_HZ", "OperatingRanges", "UsabilityRules", "operating_ranges"]

DEFAULT_STEP_FREQUENCIES_HZ = (10.0, 30.0, 100.0, 300.0, 1000.0, 3000.0)
DEFAULT_N_LOADS = 6
NOT_SIMULATED = "not simulated"

_REGIME_CODES = {"stick-slip": "S", "stepping": "t", "creep": "C", "no-slip": "-",
                 "error": "!", NOT_SIMULATED: "c"}
_RULE_CODES = {"table_i": "T", "camera": "c", "slip_length": "r", "slip_count": "n"}


def _positive(name: str, value: float, unit: str = "", what: str = "") -> float:
    v = float(value)
    if not math.isfinite(v) or v <= 0:
        u = f" {unit}" if unit else ""
        raise ValueError(f"{name} = {v:g}{u}: {what or 'must be'} finite and > 0")
    return v


@dataclass(frozen=True)
class UsabilityRules:
    """The measurement rules a usable run must pass (besides Table I and the regime).

    Parameters
    ----------
    min_slip_m : float
        Smallest mean slip length the camera resolves, m (90 nm noise, MODEL.md).
    min_slips : int
        Slips needed within the travel.
    max_frame_rate_Hz : float
        Camera's maximum frame rate, frames/s.
    frames_per_step : float
        Frames wanted per puller step.
    """

    min_slip_m: float = 90e-9
    min_slips: int = 20
    max_frame_rate_Hz: float = 10_000.0
    frames_per_step: float = 2.0

    def __post_init__(self) -> None:
        _positive("min_slip_m", self.min_slip_m)
        _positive("max_frame_rate_Hz", self.max_frame_rate_Hz)
        _positive("frames_per_step", self.frames_per_step)
        if int(self.min_slips) != self.min_slips or self.min_slips < 1:
            raise ValueError(f"min_slips = {self.min_slips!r}: must be a positive integer")

    @property
    def max_step_frequency_Hz(self) -> float:
        """Highest fp the camera can follow at ``frames_per_step`` frames per step."""
        return self.max_frame_rate_Hz / self.frames_per_step


@dataclass
class OperatingRanges(SavedResult):
    """Usable (Nb, fp) points of one spring, and why every other point is not.

    Attributes
    ----------
    coating : str
    spring_constant_N_per_m : float
    stick_speed_m_per_s : float
        The stick option (0: equations as written).
    travel_um : float
        Puller travel the slip count refers to, µm.
    rules : UsabilityRules
    normal_load_range_uN : (float, float)
        Table I range of the spring, µN.
    normal_loads_uN, step_frequencies_Hz : ndarray
        Grid axes, ascending.
    regimes : ndarray of str, shape (n_loads, n_freqs)
        ``stick-slip``, ``stepping``, ``creep``, ``no-slip``, ``error`` or ``not simulated``.
    failed : ndarray of tuple, shape (n_loads, n_freqs)
        Per point, the failed rules as ``(rule, message)`` pairs; empty when usable.
    mean_slip_um : ndarray
        Mean simulated slip length, µm (NaN where not simulated or without slips).
    n_slips : ndarray of int
        Slips in the simulated run over ``travel_um`` (0 where not simulated).
    errors : list of str
        Simulation failures (those points are marked ``error``).
    """

    coating: str
    spring_constant_N_per_m: float
    stick_speed_m_per_s: float
    travel_um: float
    rules: UsabilityRules
    normal_load_range_uN: tuple[float, float]
    normal_loads_uN: np.ndarray
    step_frequencies_Hz: np.ndarray
    regimes: np.ndarray
    failed: np.ndarray
    mean_slip_um: np.ndarray
    n_slips: np.ndarray
    errors: list = field(default_factory=list)

    @property
    def usable(self) -> np.ndarray:
        """Boolean array (n_loads, n_freqs): True where every rule holds."""
        return np.vectorize(lambda f: not f, otypes=[bool])(self.failed)

    def reason(self, i: int, j: int) -> str:
        """Why point (i, j) is unusable ('' when usable), e.g. ``creep; only 3 slips in 100 µm``."""
        return "; ".join(msg for _, msg in self.failed[i, j])

    def usable_fp_ranges_Hz(self, i: int) -> list[tuple[float, float]]:
        """Usable fp intervals at load i: runs of neighbouring usable grid frequencies, Hz."""
        out: list[tuple[float, float]] = []
        prev = False
        for f, ok in zip(self.step_frequencies_Hz, self.usable[i]):
            if ok and prev:
                out[-1] = (out[-1][0], float(f))
            elif ok:
                out.append((float(f), float(f)))
            prev = bool(ok)
        return out

    @property
    def usable_region(self) -> dict:
        """Overall usable region: Nb and fp spans (None when empty) and the point count."""
        ok = self.usable
        rows, cols = np.nonzero(ok)
        return {
            "normal_load_range_uN": _span(self.normal_loads_uN[rows]),
            "step_frequency_range_Hz": _span(self.step_frequencies_Hz[cols]),
            "n_usable": int(ok.sum()),
            "n_points": int(ok.size),
        }

    def _code(self, i: int, j: int) -> str:
        if not self.failed[i, j]:
            return "ok"
        rule = self.failed[i, j][0][0]
        if rule == "regime" or rule == "camera":
            return _REGIME_CODES.get(self.regimes[i, j], "?")
        return _RULE_CODES.get(rule, "?")

    def report(self) -> str:
        """Readable text: the rules, the grid as codes, usable fp per load, each exclusion."""
        r = self.rules
        lo, hi = self.normal_load_range_uN
        opt = ("equations as written" if not self.stick_speed_m_per_s
               else f"stick option {self.stick_speed_m_per_s:g} m/s")
        lines = [
            f"Operating ranges: {self.coating}, k = {self.spring_constant_N_per_m:g} N/m ({opt})",
            f"Table I: Nb in [{lo:.3g}, {hi:.3g}] µN",
            (f"rules: clean stick-slip; mean slip >= {r.min_slip_m * 1e6:g} µm; "
             f">= {r.min_slips} slips in {self.travel_um:g} µm; {r.frames_per_step:g} frames/step"
             f" <= {r.max_frame_rate_Hz:g} fps (fp <= {r.max_step_frequency_Hz:g} Hz)"),
            "",
            "  Nb (µN) \\ fp (Hz) " + " ".join(f"{f:>6g}" for f in self.step_frequencies_Hz),
        ]
        for i, nb in enumerate(self.normal_loads_uN):
            codes = " ".join(f"{self._code(i, j):>6}" for j in range(len(self.step_frequencies_Hz)))
            lines.append(f"  {nb:>17.3g} {codes}")
        lines += [
            ("  ok usable; C creep, t stepping, - no slip, ! simulation error, "
             "c camera too slow, r slips too short, n too few slips, T outside Table I"),
            "",
            "Usable fp per load:",
        ]
        for i, nb in enumerate(self.normal_loads_uN):
            rng = ", ".join(f"{a:g} Hz" if a == b else f"{a:g}-{b:g} Hz"
                            for a, b in self.usable_fp_ranges_Hz(i))
            lines.append(f"  Nb = {nb:.3g} µN: {rng or 'none'}")
        reg = self.usable_region
        if reg["n_usable"]:
            (a, b), (c, d) = reg["normal_load_range_uN"], reg["step_frequency_range_Hz"]
            nb = f"{a:.3g}" if a == b else f"{a:.3g}-{b:.3g}"
            fp = f"{c:g}" if c == d else f"{c:g}-{d:g}"
            lines.append(f"Usable points span Nb {nb} µN, fp {fp} Hz "
                         f"({reg['n_usable']} of {reg['n_points']} points)")
        else:
            lines.append(f"Usable points: none of the {reg['n_points']} points")
        lines += ["", "Excluded points:"]
        for i, nb in enumerate(self.normal_loads_uN):
            for j, fp in enumerate(self.step_frequencies_Hz):
                if self.failed[i, j]:
                    lines.append(f"  Nb = {nb:.3g} µN, fp = {fp:g} Hz: {self.reason(i, j)}")
        lines += [f"error: {e}" for e in self.errors]
        return "\n".join(lines)

    def to_json(self) -> dict:
        """JSON-ready dict: Table I range, rules, grid, per-point verdicts, per-load fp ranges."""
        def num(x: float):
            return float(x) if np.isfinite(x) else None

        points = [
            {
                "normal_load_uN": float(nb),
                "step_frequency_Hz": float(fp),
                "regime": None if self.regimes[i, j] == NOT_SIMULATED else str(self.regimes[i, j]),
                "usable": not self.failed[i, j],
                "reason": self.reason(i, j) or None,
                "failed_rules": [rule for rule, _ in self.failed[i, j]],
                "failed_messages": [msg for _, msg in self.failed[i, j]],
                "mean_slip_um": num(self.mean_slip_um[i, j]),
                "n_slips": int(self.n_slips[i, j]) if self.regimes[i, j] != NOT_SIMULATED else None,
            }
            for i, nb in enumerate(self.normal_loads_uN)
            for j, fp in enumerate(self.step_frequencies_Hz)
        ]
        return {
            "spring_constant_N_per_m": self.spring_constant_N_per_m,
            "coating": self.coating,
            "stick_speed_m_per_s": self.stick_speed_m_per_s,
            "travel_um": self.travel_um,
            "normal_load_range_uN": [float(x) for x in self.normal_load_range_uN],
            "rules": {
                "min_slip_um": self.rules.min_slip_m * 1e6,
                "min_slip_m": self.rules.min_slip_m,
                "min_slips": int(self.rules.min_slips),
                "max_frame_rate_Hz": self.rules.max_frame_rate_Hz,
                "frames_per_step": self.rules.frames_per_step,
                "max_step_frequency_Hz": self.rules.max_step_frequency_Hz,
            },
            "normal_loads_uN": self.normal_loads_uN.tolist(),
            "step_frequencies_Hz": self.step_frequencies_Hz.tolist(),
            "points": points,
            "loads": [
                {"normal_load_uN": float(nb),
                 "usable_fp_ranges_Hz": [list(r) for r in self.usable_fp_ranges_Hz(i)]}
                for i, nb in enumerate(self.normal_loads_uN)
            ],
            "usable_region": self.usable_region,
            "errors": list(self.errors),
        }

    @classmethod
    def from_dict(cls, d: dict) -> OperatingRanges:
        """The ranges back from :meth:`to_json` (or :meth:`to_dict`, a saved file): the
        per-point verdicts with their messages, the grid and the rules."""
        loads = np.asarray(d["normal_loads_uN"], float)
        fps = np.asarray(d["step_frequencies_Hz"], float)
        shape = (loads.size, fps.size)
        points = d["points"]
        if len(points) != loads.size * fps.size:
            raise ValueError(f"OperatingRanges: {len(points)} points for a {shape[0]} x {shape[1]} grid")
        failed = np.empty(len(points), dtype=object)
        for n, p in enumerate(points):
            rules = list(p.get("failed_rules") or ())
            msgs = list(p.get("failed_messages") or ())
            if len(msgs) != len(rules):  # (a file written before the messages were kept)
                msgs = (p.get("reason") or "").split("; ")
                msgs = msgs if len(msgs) == len(rules) else rules
            failed[n] = tuple(zip(rules, msgs))
        r = d["rules"]
        min_slip_m = r["min_slip_m"] if r.get("min_slip_m") is not None else r["min_slip_um"] * 1e-6
        return cls(
            coating=d["coating"],
            spring_constant_N_per_m=float(d["spring_constant_N_per_m"]),
            stick_speed_m_per_s=float(d["stick_speed_m_per_s"]),
            travel_um=float(d["travel_um"]),
            rules=UsabilityRules(min_slip_m, int(r["min_slips"]), r["max_frame_rate_Hz"], r["frames_per_step"]),
            normal_load_range_uN=tuple(float(x) for x in d["normal_load_range_uN"]),
            normal_loads_uN=loads,
            step_frequencies_Hz=fps,
            regimes=np.array([NOT_SIMULATED if p["regime"] is None else p["regime"] for p in points],
                             dtype=str).reshape(shape),
            failed=failed.reshape(shape),
            mean_slip_um=np.array([np.nan if p["mean_slip_um"] is None else p["mean_slip_um"] for p in points],
                                  float).reshape(shape),
            n_slips=np.array([p["n_slips"] or 0 for p in points], int).reshape(shape),
            errors=list(d.get("errors") or ()),
        )

    def plot(self, ax=None):
        """Regime map over (Nb, fp) with the excluded points hatched and Table I's Nb limits."""
        from .plots import plot_operating_ranges

        return plot_operating_ranges(self, ax=ax)


def _span(v: np.ndarray) -> list[float] | None:
    return [float(v.min()), float(v.max())] if v.size else None


def _grid(values, default, name: str, unit: str) -> np.ndarray:
    v = np.asarray(default if values is None else values, float).ravel()
    if not v.size:
        raise ValueError(f"{name}: give at least one value")
    for x in v:
        _positive(name, x, unit, "every value must be")
    return np.unique(v)


def operating_ranges(
    spring_constant_N_per_m: float,
    coating: str = "FOTAS",
    *,
    loads_uN: Sequence[float] | None = None,
    fps_Hz: Sequence[float] | None = None,
    travel_um: float = 100.0,
    stick_speed_m_per_s: float = STICK_SPEED_AUTO,
    min_slip_m: float = 90e-9,
    min_slips: int = 20,
    max_frame_rate_Hz: float = 10_000.0,
    frames_per_step: float = 2.0,
    progress: Callable[[str], None] | bool | None = None,
) -> OperatingRanges:
    """Simulate a (Nb, fp) grid for one spring and mark where runs are usable.

    Parameters
    ----------
    spring_constant_N_per_m : float
        k, N/m; must lie in Table I's [0.01, 100] N/m.
    coating : str
        Table II preset, ``FOTAS`` or ``OTS``.
    loads_uN : sequence of float, optional
        Normal loads Nb, µN (default: 6 log-spaced over the Table I range).
    fps_Hz : sequence of float, optional
        Step frequencies fp, Hz (default 10, 30, 100, 300, 1000, 3000).
    travel_um : float
        Puller travel in which ``min_slips`` must fit, µm (at most Table I's 100 µm).
    stick_speed_m_per_s : float
        Stick option ``v_stick``, m/s; 0 keeps the equations as written. The default is
        the one ``design experiment`` plans with and ``identify fit --stick-speed auto``
        takes (1e-5), so that the two design commands call each condition alike.
    min_slip_m, min_slips, max_frame_rate_Hz, frames_per_step
        See :class:`UsabilityRules`.
    progress : callable, False or None
        Where the simulations are reported (:mod:`identify.progress`): None draws a bar
        with the time left on a terminal, False is silent, a callable gets each message.

    Returns
    -------
    OperatingRanges

    Raises
    ------
    ValueError
        For a non-positive or non-finite k, load, fp or travel, a k outside Table I, an
        unknown coating or a bad rule value; the message names the parameter and the rule.
    """
    k = _checked_spring_constant(spring_constant_N_per_m)
    v_stick = _checked_stick_speed(coating, stick_speed_m_per_s)
    rules = UsabilityRules(min_slip_m, min_slips, max_frame_rate_Hz, frames_per_step)
    travel = _checked_travel(travel_um)

    lo, hi = (float(x) * 1e6 for x in tc.allowed_load_range(k))
    loads = _grid(loads_uN, np.geomspace(lo, hi, DEFAULT_N_LOADS), "Nb", "µN")
    fps = _grid(fps_Hz, DEFAULT_STEP_FREQUENCIES_HZ, "fp", "Hz")
    # The camera rule needs no simulation: those frequencies are never run.
    camera_ok = fps * rules.frames_per_step <= rules.max_frame_rate_Hz * (1 + 1e-12)
    regimes, slip, count, errors = _simulate_grid(coating, k, loads, fps, camera_ok, travel, v_stick, progress)
    failed = np.empty(regimes.shape, dtype=object)
    for i, nb in enumerate(loads):
        for j, fp in enumerate(fps):
            failed[i, j] = _point_failures(nb, fp, (lo, hi), camera_ok[j], regimes[i, j], slip[i, j],
                                           count[i, j], rules, travel)

    return OperatingRanges(
        coating=coating.upper(), spring_constant_N_per_m=k, stick_speed_m_per_s=v_stick,
        travel_um=travel, rules=rules, normal_load_range_uN=(lo, hi), normal_loads_uN=loads,
        step_frequencies_Hz=fps, regimes=regimes.astype(str), failed=failed, mean_slip_um=slip,
        n_slips=count, errors=errors,
    )


def _checked_spring_constant(spring_constant_N_per_m: float) -> float:
    """k (N/m) as a float; refused unless positive, finite and inside Table I's k rows."""
    k = _positive("k", spring_constant_N_per_m, "N/m", "the spring constant must be")
    if not (tc.K_MIN.satisfied(0.0, k, 0.5) and tc.K_MAX.satisfied(0.0, k, 0.5)):
        raise ValueError(
            f"k = {k:g} N/m: Table I allows {tc.K_MIN.name} "
            f"({tc.K_MIN.reason}) and {tc.K_MAX.name} ({tc.K_MAX.reason})"
        )
    return k


def _checked_stick_speed(coating: str, stick_speed_m_per_s: float) -> float:
    """The stick speed as a float, checked with the coating before any simulation: inside
    the grid a bad value would fail every run alone."""
    v_stick = float(stick_speed_m_per_s)
    if not math.isfinite(v_stick):
        raise ValueError(f"stick_speed_m_per_s = {stick_speed_m_per_s!r}: must be finite")
    parameter_set(coating, {"v_stick": v_stick})
    return v_stick


def _checked_travel(travel_um: float) -> float:
    """The puller travel (µm) as a float; refused unless positive and within Table I's travel."""
    travel = _positive("travel_um", travel_um, "µm", "the travel must be")
    if travel * 1e-6 > tc.PULLER_TRAVEL.bound * (1 + tc.RTOL):
        raise ValueError(
            f"travel_um = {travel:g} µm: must be <= "
            f"{tc.PULLER_TRAVEL.bound * 1e6:g} µm ({tc.PULLER_TRAVEL.reason})"
        )
    return travel


def _simulate_grid(coating: str, k: float, loads: np.ndarray, fps: np.ndarray, camera_ok: np.ndarray,
                   travel: float, v_stick: float, progress) -> tuple[np.ndarray, np.ndarray, np.ndarray, list]:
    """Regimes, mean slips (µm), slip counts and simulation errors over the grid: one run per
    point whose fp the camera can follow; the others stay ``not simulated``."""
    shape = (loads.size, fps.size)
    regimes = np.full(shape, NOT_SIMULATED, dtype=object)
    slip = np.full(shape, np.nan)
    count = np.zeros(shape, int)
    errors: list[str] = []
    if camera_ok.any():
        # Each run covers the whole travel, so the slip count is counted, not extrapolated:
        # a short run scaled up gave 19.7 slips against 20 simulated over 100 µm at
        # Nb = 34.5 µN, k = 2.13 N/m - right at the threshold - while the whole default
        # grid costs ~10 s.
        m = regime_map(coating, k, loads, fps[camera_ok], travel_um=travel,
                       stick_speed_m_per_s=v_stick, progress=progress)
        regimes[:, camera_ok] = m.regimes
        slip[:, camera_ok] = m.mean_slip_um
        count[:, camera_ok] = m.n_slips
        errors += m.errors
    return regimes, slip, count, errors


def _point_failures(nb: float, fp: float, table_range_uN: tuple[float, float], camera_ok: bool, regime: str,
                    slip_um: float, n_slips: int, rules: UsabilityRules, travel: float) -> tuple:
    """The rules grid point (Nb, fp) fails, as (rule, message) pairs; empty when usable. A
    point the camera cannot follow was not simulated, so only Table I is judged beside it."""
    lo, hi = table_range_uN
    f: list[tuple[str, str]] = []
    if not (lo * (1 - tc.RTOL) <= nb <= hi * (1 + tc.RTOL)):
        f.append(("table_i", f"Table I: Nb = {nb:.3g} µN outside {lo:.3g}-{hi:.3g} µN"))
    if not camera_ok:
        f.append(("camera", (f"camera: {rules.frames_per_step:g} frames/step needs "
                             f"{fp * rules.frames_per_step:g} fps > "
                             f"{rules.max_frame_rate_Hz:g}")))
        return tuple(f)
    if regime != "stick-slip":
        what = {"no-slip": f"no slip in {travel:g} µm",
                "error": "simulation failed (see errors)"}.get(regime, regime)
        f.append(("regime", what))
    # A creep run's "slips" are long creeping phases: length and count say nothing.
    if regime in ("stick-slip", "stepping"):
        if slip_um * 1e-6 < rules.min_slip_m:
            f.append(("slip_length",
                      f"slips {slip_um:.3g} µm < {rules.min_slip_m * 1e6:g} µm"))
        if n_slips < rules.min_slips:
            f.append(("slip_count",
                      f"only {n_slips} slip{'' if n_slips == 1 else 's'} in {travel:g} µm"))
    return tuple(f)

"""What a simulated run gives: its slip events, its regime and its trajectories.

:class:`SimulationResult` answers the block and puller positions, elongation, contact
state and speed at any time, samples the run as a camera would (:meth:`SimulationResult.sample`)
and reports it; :func:`classify` names the run's regime from its events. The integration
that produces it is in :mod:`identify.simulation.hybrid`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from identify.jsonio import SavedResult
from identify.messages import summarise
from identify.model.params import ParameterError
from identify.model.symbolic import Model
from identify.simulation.conditions import RunConditions, SimulationOptions

__all__ = ["EventTable", "MovingPhase", "SimulationResult", "classify", "REGIMES", "MIN_SLIP_STEPS"]

REGIMES = ("stick-slip", "stepping", "creep", "no-slip")
MIN_SLIP_STEPS = 0.1  # a moving phase is a slip when it moves at least this many steps


_EVENT_COLUMNS = (
    ("time_s", "trigger time (the step instant)"),
    ("step_index", "index n of the triggering step (1 = first)"),
    ("peak_elongation_m", "elongation just after the triggering step"),
    ("slip_length_m", "block displacement over the moving phase"),
    ("peak_speed_m_per_s", "largest |ẋ| in the phase"),
    ("rest_time_s", "rest before the trigger (from the previous stop, or t = 0)"),
    ("duration_s", "from trigger to stop"),
    ("state_before", "contact state at the trigger"),
    ("state_after", "contact state at the stop"),
    ("steps_crossed", "puller steps applied while moving"),
    ("reversals", "stops the block could not hold (it went on)"),
    ("stop_elongation_m", "elongation at the stop"),
)


@dataclass
class EventTable:
    """Slip events of a run, one array per column (see ``EventTable.columns``)."""

    data: dict[str, np.ndarray]
    columns = _EVENT_COLUMNS

    def __len__(self) -> int:
        return len(self.data["time_s"])

    def __getitem__(self, name: str) -> np.ndarray:
        return self.data[name]

    def to_dict(self) -> dict[str, list]:
        return {k: v.tolist() for k, v in self.data.items()}

    def select(self, mask) -> EventTable:
        return EventTable({k: v[mask] for k, v in self.data.items()})

    @classmethod
    def from_rows(cls, rows: list[dict]) -> EventTable:
        return cls({name: np.array([r[name] for r in rows], dtype=_dtype(name)) for name, _ in _EVENT_COLUMNS})

    @classmethod
    def from_dict(cls, d: Mapping[str, list]) -> EventTable:
        """The table :meth:`to_dict` gives (null read back as NaN)."""
        return cls({name: np.array(d.get(name, []), dtype=_dtype(name)) for name, _ in _EVENT_COLUMNS})


def _dtype(column: str) -> type:
    return int if column in ("step_index", "steps_crossed", "reversals") else float


@dataclass
class MovingPhase:
    """The fine trajectory of one moving phase (scaled back to SI)."""

    t: np.ndarray  # s
    x: np.ndarray  # m
    v: np.ndarray  # m/s
    state: np.ndarray


@dataclass
class SimulationResult(SavedResult):
    """One simulated run: events, regime, trajectories, and a camera sampler.

    ``to_dict()`` holds the CLI's summary and all it takes to rebuild the run (law,
    parameters, conditions, options, events, stops and recorded phases), so a result
    read back by :meth:`from_dict` or :meth:`load` answers, samples, reports and plots
    as the one written.

    Attributes
    ----------
    model : Model
    parameters : dict
        The parameter values used (SI).
    conditions : RunConditions
    events : EventTable
    regime : str
        ``stick-slip``, ``stepping``, ``creep`` or ``no-slip`` (see :func:`classify`).
    phases : list of MovingPhase
        Fine trajectory of every moving phase (empty unless ``record``).
    stops : ndarray, shape (n, 4)
        (time, x, state, elongation) at every stop, and at t = 0.
    wall_time_s : float
    integrator_calls : int
    warnings : list of str
    """

    model: Model
    parameters: dict
    conditions: RunConditions
    events: EventTable
    regime: str
    phases: list
    stops: np.ndarray
    wall_time_s: float
    integrator_calls: int
    options: SimulationOptions
    completed: bool = True
    warnings: list = field(default_factory=list)
    coating: str | None = None

    # ------------------------------------------------------------- derived numbers
    @property
    def slips(self) -> EventTable:
        """The moving phases that moved the block at least a tenth of a puller step.

        ``events`` also holds creep nucleations that failed (the block moved picometres to
        nanometres and stopped again as its contact aged); no camera can see those.
        """
        ev = self.events
        if not len(ev):
            return ev
        return ev.select(np.abs(ev["slip_length_m"]) >= MIN_SLIP_STEPS * self.step)

    @property
    def step(self) -> float:
        return self.model.step(self._P)

    @property
    def _P(self) -> dict:
        return {**self.parameters, "k": self.conditions.spring_constant, "Nb": self.conditions.normal_load}

    def puller_position(self, t) -> np.ndarray:
        """xp(t), m: Δxp times the number of steps taken by t."""
        c = self.conditions
        n = np.floor((np.asarray(t, float) - c.t_first) * c.step_frequency + 1 + 1e-9)
        return np.clip(n, 0, c.n_steps) * self.step

    def block_position(self, t) -> np.ndarray:
        """x(t), m (linear between recorded points inside moving phases)."""
        tt, xx = self._x_table()
        return np.interp(np.asarray(t, float), tt, xx)

    def elongation(self, t) -> np.ndarray:
        """e(t) = xp(t) − x(t), m."""
        return self.puller_position(t) - self.block_position(t)

    def _x_table(self):
        if getattr(self, "_xt", None) is None:
            pts_t = [self.stops[:, 0]]
            pts_x = [self.stops[:, 1]]
            for ph in self.phases:
                pts_t.append(ph.t)
                pts_x.append(ph.x)
            ev = self.events
            if len(ev):  # phase starts (block at rest until the trigger)
                idx = np.searchsorted(self.stops[:, 0], ev["time_s"], side="right") - 1
                pts_t.append(ev["time_s"])
                pts_x.append(self.stops[np.clip(idx, 0, None), 1])
            tt = np.concatenate(pts_t)
            xx = np.concatenate(pts_x)
            order = np.argsort(tt, kind="stable")
            tt, xx = tt[order], xx[order]
            end = self.conditions.end_time
            tt = np.append(tt, max(end, tt[-1]))
            xx = np.append(xx, xx[-1])
            self._xt = (tt, xx)
        return self._xt

    def state_at(self, t) -> np.ndarray:
        """Contact state at times ``t`` (closed form at rest, recorded while moving)."""
        t = np.asarray(t, float)
        law = self.model.law
        P = self._P
        stop_t = self.stops[:, 0]
        i = np.clip(np.searchsorted(stop_t, t, side="right") - 1, 0, len(stop_t) - 1)
        out = law.rest(self.stops[i, 2], np.maximum(t - stop_t[i], 0.0), P)
        # inside a moving phase: recorded values
        for ph in self.phases:
            m = (t >= ph.t[0]) & (t <= ph.t[-1])
            if m.any():
                out = np.where(m, np.interp(t, ph.t, ph.state), out)
        return out

    def velocity(self, t) -> np.ndarray:
        t = np.asarray(t, float)
        out = np.zeros_like(t)
        for ph in self.phases:
            m = (t >= ph.t[0]) & (t <= ph.t[-1])
            if m.any():
                out = np.where(m, np.interp(t, ph.t, ph.v), out)
        return out

    # ------------------------------------------------------------- camera
    def sample(
        self,
        frame_rate_Hz: float | None = None,
        frame_phase: float = 0.5,
        noise_nm: float = 0.0,
        seed: int | None = None,
        exposure_s: float | None = None,
        exposure_align: float | str | None = None,
        drift_rate_m_per_s: float | None = None,
        offset_m: float | None = None,
        drift_walk_m_per_sqrt_s: float = 0.0,
        name: str = "run",
        metadata: Mapping[str, Any] | None = None,
        times_s: np.ndarray | None = None,
    ):
        """The camera's trace of this run (:class:`identify.traces.io.Trace`).

        Frames are at ``t_j = (j + frame_phase)/frame_rate`` (default 2 frames per step
        period, each in the middle of its half period), or at ``times_s`` (s, the run's
        clock: steps at n/fp; times at or past the run's end are dropped), e.g. a
        recorded trace's own frames. Measurement effects default to
        the run's parameters (``exposure``, ``exposure_align``, ``drift_rate``, ``e_offset``);
        ``exposure_align`` places the exposure on the timestamp: "start", "centre" (the
        default), "end", or the share of it before the timestamp. Gaussian noise
        of ``noise_nm`` (standard deviation, nm) is drawn from ``seed``; a random walk of
        the camera's zero, ``drift_walk_m_per_sqrt_s`` (its standard deviation grows as
        √t), from a stream of its own of the same seed (the noise stays as without it).
        """
        from identify.traces.io import Trace

        c = self.conditions
        fr = 2.0 * c.step_frequency if frame_rate_Hz is None else float(frame_rate_Hz)
        if not (fr > 0 and math.isfinite(fr)):
            raise ParameterError(f"frame_rate_Hz = {frame_rate_Hz!r}: must be > 0")
        if not (0.0 <= frame_phase < 1.0):
            raise ParameterError(f"frame_phase = {frame_phase!r}: must lie in [0, 1)")
        if noise_nm < 0 or not math.isfinite(noise_nm):
            raise ParameterError(f"noise_nm = {noise_nm!r}: must be >= 0")
        if times_s is not None:
            t = np.asarray(times_s, float).ravel()
            if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
                raise ParameterError("times_s: must be finite and strictly increasing")
            t = t[(t >= 0) & (t < c.end_time)]
            if t.size < 2:
                raise ParameterError(f"times_s: fewer than 2 frames within the run (0 to {c.end_time:.6g} s)")
        else:
            n = int(math.floor(c.end_time * fr - frame_phase)) + 1
            t = (np.arange(n) + frame_phase) / fr
            t = t[t < c.end_time]
        P = self.parameters
        exposure = P.get("exposure", 0.0) if exposure_s is None else exposure_s
        drift = P.get("drift_rate", 0.0) if drift_rate_m_per_s is None else drift_rate_m_per_s
        offset = P.get("e_offset", 0.0) if offset_m is None else offset_m
        if exposure > 0:
            from identify.model.params import exposure_align as _align

            a = _align(P.get("exposure_align", 0.5) if exposure_align is None else exposure_align)
            # (256 sub-frames: a window straddling a slip reads the share of it on each side to
            # 1/512, 10 nm on a 5 µm slip, well below a camera's noise)
            sub = (np.arange(256) + 0.5) / 256 - a
            e = self.elongation(t[:, None] + exposure * sub[None, :]).mean(axis=1)
        else:
            e = self.elongation(t)
        e = e + offset + drift * t
        if drift_walk_m_per_sqrt_s:
            if drift_walk_m_per_sqrt_s < 0 or not math.isfinite(drift_walk_m_per_sqrt_s):
                raise ParameterError(f"drift_walk_m_per_sqrt_s = {drift_walk_m_per_sqrt_s!r}: must be >= 0")
            dt = np.diff(t, prepend=0.0)
            walk = np.random.default_rng([0 if seed is None else int(seed), 1]).normal(0.0, 1.0, size=t.shape)
            e = e + np.cumsum(walk * np.sqrt(dt)) * drift_walk_m_per_sqrt_s
        if noise_nm > 0:
            rng = np.random.default_rng(seed)
            e = e + rng.normal(0.0, noise_nm * 1e-9, size=e.shape)
        meta = dict(metadata or {})
        meta.setdefault("frame_rate_Hz", fr)
        return Trace.from_simulation(self, t, e, name=name, extra=meta)

    # ------------------------------------------------------------- reporting
    def summary(self) -> dict:
        """The JSON summary of the CLI (SI values, units in the keys)."""
        ev = self.slips
        slips = ev["slip_length_m"] if len(ev) else np.array([])
        return dict(
            n_slips=int(len(ev)),
            n_moving_phases=int(len(self.events)),
            regime=self.regime,
            completed=self.completed,
            slip_lengths_um=(slips * 1e6).round(6).tolist(),
            peak_elongations_um=(ev["peak_elongation_m"] * 1e6).round(6).tolist() if len(ev) else [],
            peak_slip_speed_m_per_s=float(ev["peak_speed_m_per_s"].max()) if len(ev) else 0.0,
            peak_slip_speeds_m_per_s=ev["peak_speed_m_per_s"].tolist() if len(ev) else [],
            mean_slip_length_um=float(slips.mean() * 1e6) if len(ev) else None,
            mean_peak_elongation_um=float(ev["peak_elongation_m"].mean() * 1e6) if len(ev) else None,
            rest_times_s=ev["rest_time_s"].tolist() if len(ev) else [],
            mean_rest_time_s=float(ev["rest_time_s"][1:].mean()) if len(ev) > 1 else None,
            states_after=ev["state_after"].tolist() if len(ev) else [],
            moving_fraction=self.moving_fraction,
            spring_constant_N_per_m=self.conditions.spring_constant,
            normal_load_uN=self.conditions.normal_load * 1e6,
            step_frequency_Hz=self.conditions.step_frequency,
            travel_um=self.conditions.n_steps * self.step * 1e6,
            law=self.model.law.name,
            parameters=dict(self.parameters),
            integrator=self.options.integrator,
            integrator_calls=self.integrator_calls,
            wall_time_s=self.wall_time_s,
            warnings=list(self.warnings),
        )

    @property
    def moving_fraction(self) -> float:
        """Share of the time after the first trigger that the block spends moving."""
        ev = self.events
        if not len(ev):
            return 0.0
        span = self.conditions.end_time - ev["time_s"][0]
        return float(np.clip(ev["duration_s"].sum() / span, 0.0, 1.0)) if span > 0 else 0.0

    def report(self) -> str:
        s = self.summary()
        c = self.conditions
        lines = [
            f"Simulation ({self.model.law.name} law, {self.options.integrator})",
            f"  k = {c.spring_constant:g} N/m, Nb = {c.normal_load * 1e6:g} µN, fp = {c.step_frequency:g} Hz, "
            f"travel = {s['travel_um']:.2f} µm ({c.n_steps} steps over {c.end_time * 1e3:.4g} ms)",
            f"  regime: {self.regime}; {s['n_slips']} slips; moving {100 * s['moving_fraction']:.1f} % of the time",
        ]
        if s["n_slips"]:
            sl = np.array(s["slip_lengths_um"])
            lines += [
                f"  slip length  {sl.mean():.4f} µm (min {sl.min():.4f}, max {sl.max():.4f})",
                f"  peak elongation {np.mean(s['peak_elongations_um']):.4f} µm",
                f"  peak slip speed {s['peak_slip_speed_m_per_s'] * 100:.3f} cm/s",
            ]
            if s["mean_rest_time_s"] is not None:
                lines.append(f"  mean rest time {s['mean_rest_time_s'] * 1e3:.3f} ms")
        lines.append(f"  wall time {self.wall_time_s:.3f} s, {self.integrator_calls} integrator calls")
        lines += [f"  warning: {w}" for w in summarise(self.warnings)]
        return "\n".join(lines)

    def to_json(self) -> dict:
        """:meth:`summary` with what :meth:`from_dict` rebuilds the run from: the events,
        conditions, options, coating, stops and recorded moving phases."""
        d = self.summary()
        d["events"] = self.events.to_dict()
        d["coating"] = self.coating
        d["conditions"] = dataclasses.asdict(self.conditions)
        d["options"] = dataclasses.asdict(self.options)
        d["stops"] = np.asarray(self.stops, float).tolist()
        d["phases"] = [{k: np.asarray(getattr(ph, k), float).tolist() for k in ("t", "x", "v", "state")}
                       for ph in self.phases]
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SimulationResult:
        """The run :meth:`to_dict` describes (a null number is read back as NaN). The model
        is rebuilt from its law's name (:class:`identify.model.symbolic.Model`)."""

        def arr(x):
            return np.array(x, dtype=float)

        return cls(
            model=Model(d["law"]),
            parameters={n: math.nan if v is None else float(v) for n, v in d["parameters"].items()},
            conditions=RunConditions(**d["conditions"]),
            events=EventTable.from_dict(d["events"]),
            regime=d["regime"],
            phases=[MovingPhase(arr(p["t"]), arr(p["x"]), arr(p["v"]), arr(p["state"])) for p in d.get("phases", [])],
            stops=arr(d["stops"]).reshape(-1, 4),
            wall_time_s=float(d["wall_time_s"]),
            integrator_calls=int(d["integrator_calls"]),
            options=SimulationOptions(**d["options"]),
            completed=bool(d.get("completed", True)),
            warnings=list(d.get("warnings", [])),
            coating=d.get("coating"),
        )

    def plot(self, ax=None, t_window: tuple[float, float] | None = None, n_slips: int = 4):
        """The run's figure, the paper's Fig. 13 (:func:`identify.plots.base.plot_simulation`):
        positions, velocity, elongation, contact state and forces over a few slips.

        ``ax`` None (a new figure) or a sequence of 5 Axes: the five panels, and those
        axes are returned. One Axes: the spring elongation alone (panel (c)), returned.
        """
        from matplotlib.axes import Axes

        from identify.plots.base import plot_simulation, plot_simulation_elongation

        if not isinstance(ax, Axes):
            return plot_simulation(self, axes=ax, t_window=t_window, n_slips=n_slips)
        return plot_simulation_elongation(self, ax, t_window=t_window, n_slips=n_slips)


def classify(events: EventTable, step: float, moving_fraction: float) -> str:
    """The run's regime.

    ``creep`` when the block is moving more than half the time after its first slip;
    else ``stepping`` when the median slip (phases moving at least 0.1 step) is shorter
    than two puller steps (the block follows the puller step by step); else
    ``stick-slip``; ``no-slip`` without slips.
    """
    if moving_fraction > 0.5:
        return "creep"
    slips = np.abs(events["slip_length_m"]) if len(events) else np.array([])
    slips = slips[slips >= MIN_SLIP_STEPS * step]
    if not slips.size:
        return "no-slip"
    if np.median(slips) < 2 * step:
        return "stepping"
    return "stick-slip"

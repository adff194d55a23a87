"""Hybrid stick/slip simulation of one nanofrictor run.

The loop runs over *moving phases*, not over puller steps or samples:

stick
    The block is at rest; its contact state ages in closed form (Eq. 11 for the
    exponential law) and the spring force changes only at puller steps, so a slip can
    only start at a step: the first one after which |F_s(e)| exceeds the static
    capacity ψ·N. That step is found by one vectorised search over the coming steps.
moving
    From the trigger step the slip-mode equations (Eqs. 18–20, :mod:`identify.model.symbolic`)
    are integrated, across further puller steps if the motion lasts (creep), until the
    block stops: v returns to 0 and the spring cannot overcome the static capacity (else
    it goes on, reversing if need be), or, with the stick-threshold option, its speed
    falls back below ``v_stick`` after having exceeded it.

Two engines integrate moving phases, from the same symbolic model:

``idas`` (default)
    IDAS on adaptive sub-intervals (each sized from the current speed and acceleration
    so it ends just after a predicted stop); the stop is bracketed on the sub-interval's
    output grid, located by cubic Hermite interpolation and polished by a short
    integration to it. CasADi 3.8's own event support fails with IDAS on this problem.
``rosenbrock``
    CasADi's Rosenbrock plugin with the model's zero indicators and freezing transition:
    it stops exactly at the event and costs nothing after it; used by the identification
    because its sensitivities include the event times.
"""

from __future__ import annotations

import logging
import math
import time as _time
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from identify.messages import summarise
from identify.model.laws import get_law
from identify.model.params import ParameterError, normal_load_from_voltage, parameter_set, validate_parameters
from identify.model.plausible import check_parameters, platform_problem
from identify.model.symbolic import LENGTH_UNIT, N_STATES, SPEED_UNIT, TIME_UNIT, Model, slip_integrator, slip_rhs

__all__ = [
    "RunConditions",
    "SimulationOptions",
    "SimulationResult",
    "EventTable",
    "simulate",
    "simulate_run",
    "REGIMES",
    "MAX_TRAVEL_M",
]

log = logging.getLogger(__name__)

MAX_TRAVEL_M = 100e-6  # nanotractor travel (Table I)
REGIMES = ("stick-slip", "stepping", "creep", "no-slip")
MIN_SLIP_STEPS = 0.1  # a moving phase is a slip when it moves at least this many steps
_CHUNK_POINTS = 16  # output points per IDAS sub-interval
_HOLD_SLACK = 1e-6  # relative force tolerance of the hold test at a located stop


# ----------------------------------------------------------------------------- inputs
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


# ----------------------------------------------------------------------------- outputs
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
        data = {}
        for name, _ in _EVENT_COLUMNS:
            dtype = int if name in ("step_index", "steps_crossed", "reversals") else float
            data[name] = np.array([r[name] for r in rows], dtype=dtype)
        return cls(data)


@dataclass
class _Phase:
    t: np.ndarray  # s
    x: np.ndarray  # m
    v: np.ndarray  # m/s
    state: np.ndarray


@dataclass
class SimulationResult:
    """One simulated run: events, regime, trajectories, and a camera sampler.

    Attributes
    ----------
    model : Model
    parameters : dict
        The parameter values used (SI).
    conditions : RunConditions
    events : EventTable
    regime : str
        ``stick-slip``, ``stepping``, ``creep`` or ``no-slip`` (see :func:`classify`).
    phases : list
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
        drift_rate_m_per_s: float | None = None,
        offset_m: float | None = None,
        name: str = "run",
        metadata: Mapping[str, Any] | None = None,
        times_s: np.ndarray | None = None,
    ):
        """The camera's trace of this run (:class:`identify.traces.io.Trace`).

        Frames are at ``t_j = (j + frame_phase)/frame_rate`` (default 2 frames per step
        period, each in the middle of its half period), or at ``times_s`` (s, the run's
        clock: steps at n/fp; times at or past the run's end are dropped), e.g. a
        recorded trace's own frames. Measurement effects default to
        the run's parameters (``exposure``, ``drift_rate``, ``e_offset``). Gaussian noise
        of ``noise_nm`` (standard deviation, nm) is drawn from ``seed``.
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
            sub = (np.arange(16) + 0.5) / 16 - 0.5
            e = self.elongation(t[:, None] + exposure * sub[None, :]).mean(axis=1)
        else:
            e = self.elongation(t)
        e = e + offset + drift * t
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
            f"travel = {s['travel_um']:.2f} µm ({c.n_steps} steps)",
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
        d = self.summary()
        d["events"] = self.events.to_dict()
        return d


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


# ----------------------------------------------------------------------------- engine
def _parabolic_peak(y: np.ndarray) -> float:
    """Maximum of equally spaced samples, refined by the parabola through the top three."""
    i = int(np.argmax(y))
    if 0 < i < len(y) - 1:
        a, b, c = y[i - 1], y[i], y[i + 1]
        den = a - 2 * b + c
        if den < 0:
            return float(b - 0.125 * (a - c) ** 2 / den)
    return float(y[i])


def _interval_grid(K: int) -> np.ndarray:
    """Normalised output points inside one step interval: half geometric (slips start
    at the trigger, so the start needs resolution), half uniform; the last is 1."""
    geo = np.geomspace(1e-6, 1.0, K // 2, endpoint=False)
    uni = np.linspace(0.0, 1.0, K - K // 2 + 1)[1:]
    return np.unique(np.concatenate([geo, uni]))


_GRID = _interval_grid(_CHUNK_POINTS * 2)


def _grid_of(M: int, grid: np.ndarray = _GRID) -> np.ndarray:
    """Output points of a window of M step intervals, normalised to (0, 1]."""
    return ((np.arange(M)[:, None] + grid[None, :]) / M).ravel()


class _Runner:
    """State of one simulation; methods integrate stick and moving phases."""

    def __init__(self, model: Model, values: dict, cond: RunConditions, opts: SimulationOptions):
        self.model = model
        self.law = model.law
        self.opts = opts
        self.c = cond
        self.P = {**values, "k": cond.spring_constant, "Nb": cond.normal_load}
        self.fp = cond.step_frequency
        self.dx = model.step(self.P)
        self.base_p = model.pack(values, cond.spring_constant, cond.normal_load, 1.0, 1.0)
        self.N = model.normal_load(self.P)
        kmb = math.sqrt(self.P["k"] * self.P["k_scale"] * self.P["mb"])
        self.t_inertial = math.pi * self.P["mb"] / kmb  # π·sqrt(mb/k), half period
        self.v_fast = 0.005 * self.N / kmb  # speeds above this are inertial slips
        self.v_stick = float(self.P["v_stick"])
        self.sc = self.law.state_scale
        self.calls = 0
        self.warnings: list[str] = []
        self.phases: list[_Phase] = []
        self._cache: dict = {}
        self.rhs = slip_rhs(model)

    # -- helpers
    def step_time(self, n: int) -> float:
        return self.c.t_first + (n - 1) / self.fp

    def p(self, direction: float, duration_s: float) -> np.ndarray:
        p = self.base_p.copy()
        p[-2] = direction
        p[-1] = duration_s / TIME_UNIT
        return p

    def spring(self, e):
        return self.model.spring_force(e, self.P)

    def capacity(self, state, x):
        return self.model.hold_coefficient(state, x, self.P) * self.N

    def integrator(self, plugin: str, M: int, grid: np.ndarray | None = None, calc_ic: bool = True):
        key = (plugin, M, None if grid is None else len(grid), calc_ic)
        if key not in self._cache:
            g = tuple(_grid_of(M) if grid is None else grid)
            # No control groups: CasADi 3.8's rosenbrock "control_group_size" failed or
            # diverged on creep tails; one control column per output restarts the
            # stepper at each output, which costs little.
            self._cache[key] = slip_integrator(
                self.model, plugin, g, None, self.opts.reltol, self.opts.abstol, calc_ic=calc_ic
            )
        return self._cache[key]

    # -- stick: vectorised trigger search
    def next_trigger(self, t_s: float, x: float, z_s: float, n_done: int) -> int | None:
        """First step after n_done whose spring force exceeds the aged capacity."""
        start, chunk = n_done + 1, 256
        while start <= self.c.n_steps:
            n = np.arange(start, min(start + chunk, self.c.n_steps + 1))
            tn = self.c.t_first + (n - 1) / self.fp
            e = n * self.dx - x
            z = self.law.rest(z_s, tn - t_s, self.P)
            over = np.abs(self.spring(e)) > self.capacity(z, x)
            if over.any():
                return int(n[np.argmax(over)])
            start += chunk
            chunk *= 2
        return None

    def _steps_until(self, n_done: int, t: float) -> int:
        """How many steps after step n_done have happened by time t."""
        if n_done >= self.c.n_steps:
            return 0
        k = int(math.floor((t - self.step_time(n_done + 1)) * self.fp + 1e-9)) + 1
        return int(min(max(k, 0), self.c.n_steps - n_done))

    # -- moving phase
    def move(self, t0: float, x0: float, z0: float, n_done: int, direction: float):
        """Integrate from rest at t0 until the block is held again.

        Windows of whole step intervals (1, 2, 4, ... up to 64 while the block keeps
        moving) are integrated in one call each, the puller position a control. The
        stop is read from the frozen state (rosenbrock) or bracketed on the outputs and
        located (idas). Returns (t, x, state, n_done, info).
        """
        plugin = self.opts.integrator
        s = direction
        X = np.zeros(N_STATES)
        X[0], X[2], X[3] = x0 / LENGTH_UNIT, z0 / self.sc, 1.0
        X[4] = 1.0 if self.v_stick <= 0 else 0.0
        t = t0
        rec_t, rec_X = [t0], [X.copy()]
        reversals, steps_crossed, M = 0, 0, 1
        end = self.c.end_time
        while True:
            if t >= end - 1e-12 / self.fp:
                return self._finish(t, X, n_done, s, rec_t, rec_X, reversals, steps_crossed, held=False)
            aligned = abs(t - self.step_time(n_done)) <= 1e-9 / self.fp
            if aligned:
                M_eff = max(1, min(M, self.c.n_steps - n_done + 1))
                H = M_eff / self.fp
                ts = t + H * _grid_of(M_eff)
                xp = (n_done + np.arange(M_eff)) * self.dx / LENGTH_UNIT
                F = self.integrator(plugin, M_eff)
            else:  # restart between steps: up to the next step
                M_eff = 1
                t_next = self.step_time(n_done + 1) if n_done < self.c.n_steps else end
                H = t_next - t
                ts = t + H * _GRID
                xp = np.array([n_done * self.dx / LENGTH_UNIT])
                F = self.integrator(plugin, 1)
            K = len(_GRID)
            u = np.repeat(xp, K)[None, :]
            try:
                out = np.array(F(x0=X, p=self.p(s, H), u=u)["xf"])
            except RuntimeError:
                if plugin != "idas":
                    raise
                # IDACalcIC occasionally fails in a creep tail; the state is a valid
                # initial condition of the ODE as it is, so retry without it
                F = self.integrator(plugin, M_eff if aligned else 1, None, calc_ic=False)
                out = np.array(F(x0=X, p=self.p(s, H), u=u)["xf"])
            self.calls += 1
            if not np.all(np.isfinite(out)):
                raise FloatingPointError(f"integration failed at t = {t:.6g} s")
            xp_out = np.repeat(xp, K)
            stop = self._find_stop(t, X, ts, out, s, xp_out)
            if stop is None:
                self._record(rec_t, rec_X, ts, out)
                t, X = ts[-1], out[:, -1].copy()
                k_in = self._steps_until(n_done, t + 1e-9 / self.fp)
                n_done += k_in
                steps_crossed += k_in
                t = self.step_time(n_done) if k_in and n_done < self.c.n_steps + 1 else t
                M = min(2 * M, 64)
                if steps_crossed > self.opts.max_phase_steps:
                    self.warnings.append(
                        f"t = {t:.6g} s: a moving phase crossed more than "
                        f"{self.opts.max_phase_steps} steps; run stopped"
                    )
                    return self._finish(t, X, n_done, s, rec_t, rec_X, reversals, steps_crossed, held=False)
                continue
            j, t_stop, X_stop, threshold = stop
            self._record(rec_t, rec_X, ts[:j], out[:, :j])
            X = X_stop.copy()
            X[1], X[3] = 0.0, 1.0
            t = t_stop
            rec_t.append(t)
            rec_X.append(X.copy())
            k_in = self._steps_until(n_done, t)
            n_done += k_in
            steps_crossed += k_in
            x, z = X[0] * LENGTH_UNIT, X[2] * self.sc
            go_on = 0.0 if threshold else self.stop_outcome(n_done * self.dx - x, z, x, s)
            if go_on == 0.0:
                return self._finish(t, X, n_done, s, rec_t, rec_X, reversals, steps_crossed, held=True)
            s = go_on
            reversals += 1
            X[4] = 1.0 if self.v_stick <= 0 else 0.0
            M = 1
            if reversals > 100:
                self.warnings.append(f"t = {t:.6g} s: more than 100 reversals in one phase; phase cut")
                return self._finish(t, X, n_done, s, rec_t, rec_X, reversals, steps_crossed, held=True)

    def _record(self, rec_t, rec_X, ts, out):
        if len(ts):
            rec_t.extend(np.asarray(ts).tolist())
            rec_X.extend(np.asarray(out).T)

    def _find_stop(self, t, X, ts, out, s, xp_out):
        """(index of the first output past the stop, t_stop, X_stop, threshold) or None."""
        if self.opts.integrator == "rosenbrock":
            frozen = np.nonzero(out[3] < 0.5)[0]
            if not frozen.size:
                return None
            j = int(frozen[0])
            Xs = out[:, j].copy()
            t_stop = ts[j] - Xs[5] * TIME_UNIT
            Xs[2], Xs[5] = Xs[6], 0.0
            return j, t_stop, Xs, bool(self.v_stick > 0 and Xs[4] > 0.5)
        # idas: bracket on the outputs, then locate
        sv = s * out[1] * SPEED_UNIT
        idx = np.arange(len(sv))
        armed = X[4] > 0.5
        arm_j = -1
        if not armed:
            hit = np.nonzero(sv >= self.v_stick)[0]
            if hit.size:
                armed, arm_j = True, int(hit[0])
                out[4, arm_j:] = 1.0
        below = (idx > arm_j) & (sv < self.v_stick) if (armed and self.v_stick > 0) else idx < 0
        stop = np.nonzero(below | (sv <= 0))[0]
        if not stop.size:
            return None
        j = int(stop[0])
        thr = self.v_stick if below[j] else 0.0
        Xa = X if j == 0 else out[:, j - 1]
        ta = t if j == 0 else ts[j - 1]
        t_stop, Xs = self._locate(ta, Xa, ts[j], out[:, j], s, thr, float(xp_out[j]))
        return j, t_stop, Xs, thr > 0

    def _locate(self, ta, Xa, tb, Xb, s, thr, xp_um):
        """The stop between ta and tb (g = s·v − thr changes sign there), IDAS engine.

        The bracket is narrowed with a 16-point sub-grid until g falls smoothly across
        it, then Illinois regula falsi integrates forward from the last point before
        the stop (each a short call). Creep tails end with v decaying slowly, so the
        search also ends once the bracket no longer moves the block (1 pm).
        """
        p0 = self.p(s, TIME_UNIT)
        sub = np.linspace(0.0, 1.0, 17)[1:]
        F_sub = self.integrator("idas", 1, sub)
        F_one = self.integrator("idas", 1, np.array([1.0]))

        def g_and_slope(X):
            d = np.array(self.rhs(X, xp_um, p0))[:, 0]
            return s * X[1] * SPEED_UNIT - thr, s * d[1] * SPEED_UNIT / TIME_UNIT

        ga, da = g_and_slope(Xa)
        for _ in range(4):
            gb, db = g_and_slope(Xb)
            drop = ga - gb
            if (tb - ta) * max(-da, -db, 0.0) <= 4 * drop + 1e-30:
                break
            out = np.array(F_sub(x0=Xa, p=self.p(s, tb - ta), u=xp_um)["xf"])
            self.calls += 1
            ts = ta + (tb - ta) * sub
            gs = s * out[1] * SPEED_UNIT - thr
            j = int(np.nonzero(gs <= 0)[0][0])
            if j:
                ta, Xa = ts[j - 1], out[:, j - 1]
                ga, da = g_and_slope(Xa)
            tb, Xb = ts[j], out[:, j]
        tol = 1e-9 + 1e-7 * abs(ga)
        t_lo, X_lo, g_lo = ta, Xa, ga
        t_hi, X_hi, g_hi = tb, Xb, g_and_slope(Xb)[0]
        w_lo, w_hi = g_lo, g_hi  # interpolation weights (Illinois halves them), not values
        side = 0
        for _ in range(40):
            if g_lo <= tol:
                return t_lo, X_lo
            if g_hi >= -tol or abs(X_hi[0] - X_lo[0]) * LENGTH_UNIT < 1e-13:
                return t_hi, X_hi
            theta = w_lo / (w_lo - w_hi)
            dt = (t_hi - t_lo) * min(max(theta, 1e-6), 1 - 1e-6)
            X = np.array(F_one(x0=X_lo, p=self.p(s, dt), u=xp_um)["xf"]).ravel()
            self.calls += 1
            g = g_and_slope(X)[0]
            if g > 0:
                t_lo, X_lo, g_lo, w_lo = t_lo + dt, X, g, g
                if side == 1:
                    w_hi *= 0.5
                side = 1
            else:
                t_hi, X_hi, g_hi, w_hi = t_lo + dt, X, g, g
                if side == -1:
                    w_lo *= 0.5
                side = -1
        return t_hi, X_hi

    def stop_outcome(self, e: float, z: float, x: float, s: float) -> float:
        """At a located stop: 0 if the block is held, else the direction it goes on in.

        A block that decelerated to v = 0⁺ in direction s has s·F_s ≤ capacity up to
        the integration error, so only a spring pulling it back past the capacity
        (r ≥ 3 in the paper's Appendix) sends it on, reversed.
        """
        f = s * self.spring(e)
        cap = self.capacity(z, x)
        if f < -cap * (1 + _HOLD_SLACK):
            return -s
        if f > cap * (1 + 1e-3) + 1e-3 * self.N * self.P["A"]:
            return s  # not decelerating at all: cannot happen in exact arithmetic
        return 0.0

    def _replay(self, rec_t, rec_X, s_of):
        """Re-integrate the recorded interval with the largest displacement on a fine grid.

        Outputs are coarse (32 per step interval) and a 40 µs slip falls between two of
        them; the replay resolves it for the trajectory and (idas) for the peak speed.
        """
        if len(rec_t) < 2:
            return None
        tt = np.asarray(rec_t)
        XX = np.asarray(rec_X).reshape(len(rec_t), -1)
        i = int(np.argmax(np.abs(np.diff(XX[:, 0]))))
        dt = tt[i + 1] - tt[i]
        if dt <= 0:
            return None
        fine = self.integrator(self.opts.integrator, 1, np.linspace(0.0, 1.0, 129)[1:])
        xp_um = float(self.dx * (self.c.n_steps if tt[i] >= self.step_time(self.c.n_steps)
                                 else max(0, math.floor((tt[i] - self.c.t_first) * self.fp + 1e-9) + 1))
                      ) / LENGTH_UNIT
        X0 = XX[i].copy()
        X0[3] = 1.0
        rep = np.array(fine(x0=X0, p=self.p(s_of, dt), u=xp_um)["xf"])
        self.calls += 1
        keep = rep[3] > 0.5  # rosenbrock: up to the freeze
        return i, tt[i] + dt * np.linspace(0.0, 1.0, 129)[1:][keep], rep[:, keep]

    def _finish(self, t, X, n_done, s, rec_t, rec_X, reversals, steps_crossed, held):
        if self.opts.record or self.opts.integrator == "idas":
            rep = self._replay(rec_t, rec_X, s)
            if rep is not None:
                i, rt, rX = rep
                if rX.size:
                    X[7] = max(X[7], _parabolic_peak(np.abs(rX[1])))
                    rec_t[i + 1:i + 1] = rt.tolist()
                    rec_X[i + 1:i + 1] = list(rX.T)
        if self.opts.integrator == "idas" and rec_X:
            X[7] = max(X[7], float(np.max(np.abs(np.asarray(rec_X).reshape(len(rec_t), -1)[:, 1]))))
        if self.opts.record and rec_t:
            arr = np.array(rec_X).reshape(len(rec_t), -1)
            self.phases.append(
                _Phase(np.array(rec_t), arr[:, 0] * LENGTH_UNIT, arr[:, 1] * SPEED_UNIT, arr[:, 2] * self.sc)
            )
        info = dict(vmax=float(X[7]) * SPEED_UNIT, reversals=reversals, steps_crossed=steps_crossed, held=held)
        return t, X[0] * LENGTH_UNIT, X[2] * self.sc, n_done, info


def simulate_run(
    model: Model,
    values: Mapping[str, float],
    conditions: RunConditions,
    options: SimulationOptions | None = None,
) -> SimulationResult:
    """Simulate one run (SI throughout). See :func:`simulate` for the friendly front end."""
    opts = options or SimulationOptions()
    wall0 = _time.perf_counter()
    values = validate_parameters(model.defaults(values))
    r = _Runner(model, values, conditions, opts)
    law = model.law
    P = r.P
    x = -float(conditions.initial_elongation)
    z = law.aged_state(P) if conditions.initial_state is None else float(conditions.initial_state)
    t, n_done = 0.0, 0
    stops = [(0.0, x, z, -x)]
    rows = []
    move = r.move
    completed = True
    while True:
        if not rows and np.abs(r.spring(-x)) > r.capacity(z, x):
            n, t_trig, z_trig = 0, 0.0, z  # a block that cannot be held at t = 0 moves at once
        else:
            n = r.next_trigger(t, x, z, n_done)
            if n is None:
                break
            t_trig = r.step_time(n)
            z_trig = law.rest(z, t_trig - t, P)
            n_done = n
        e_trig = n_done * r.dx - x
        direction = float(np.sign(r.spring(e_trig))) or 1.0
        rest = t_trig - t
        try:
            t_stop, x_stop, z_stop, n_done, info = move(t_trig, x, float(z_trig), n_done, direction)
        except (RuntimeError, FloatingPointError) as err:  # keep what was computed
            r.warnings.append(f"moving phase from t = {t_trig:.6g} s failed: {err}")
            completed = False
            break
        rows.append(dict(
            time_s=t_trig, step_index=n, peak_elongation_m=e_trig, slip_length_m=x_stop - x,
            peak_speed_m_per_s=info["vmax"], rest_time_s=rest, duration_s=t_stop - t_trig,
            state_before=float(law.static_coefficient(z_trig, P)),
            state_after=float(law.static_coefficient(z_stop, P)),
            steps_crossed=info["steps_crossed"], reversals=info["reversals"],
            stop_elongation_m=n_done * r.dx - x_stop,
        ))
        t, x, z = t_stop, x_stop, z_stop
        stops.append((t, x, z, n_done * r.dx - x))
        if not info["held"]:
            break
    events = EventTable.from_rows(rows) if rows else EventTable.from_rows([])
    res = SimulationResult(
        model=model, parameters=values, conditions=conditions, events=events, regime="",
        phases=r.phases, stops=np.array(stops, float), wall_time_s=0.0,
        integrator_calls=r.calls, options=opts, completed=completed, warnings=r.warnings,
    )
    res.regime = classify(events, r.dx, res.moving_fraction)
    res.wall_time_s = _time.perf_counter() - wall0
    for w in summarise(r.warnings):
        log.warning(w)
    return res


def simulate(
    coating: str = "FOTAS",
    *,
    spring_constant_N_per_m: float,
    step_frequency_Hz: float,
    travel_um: float | None = None,
    n_steps: int | None = None,
    normal_load_uN: float | None = None,
    block_voltage_V: float | None = None,
    law: str = "exponential",
    params: Mapping[str, float] | None = None,
    stick_speed_m_per_s: float | None = None,
    initial_elongation_um: float = 0.0,
    initial_state: float | None = None,
    first_step_time_s: float | None = None,
    options: SimulationOptions | None = None,
    check_platform: bool = True,
) -> SimulationResult:
    """Simulate one run of the platform.

    Parameters
    ----------
    coating : str
        Parameter preset from Table II, ``FOTAS`` or ``OTS``.
    spring_constant_N_per_m : float
        k, N/m (= µN/µm).
    step_frequency_Hz : float
        fp, Hz.
    travel_um, n_steps : float, int
        Puller travel in µm (rounded to whole steps) or the number of steps.
    normal_load_uN, block_voltage_V : float
        Exactly one: the normal load Nb in µN, or the block voltage Vb in V (the load then
        comes from Eqs. 5-6 and their calibration).
    law : str
        Aging law: ``exponential`` (paper), ``logarithmic`` or ``logistic``.
    params : dict
        Overrides of any model parameter, SI (``{"tau": 0.05}``).
    stick_speed_m_per_s : float, optional
        The stick-threshold option (parameter ``v_stick``): a block that has slid faster
        than this is held once it is slower again. None/0 keeps the equations as written.
    initial_elongation_um, initial_state : float
        Start: spring elongation (µm) and contact state (default fully aged).
    first_step_time_s : float, optional
        Time of the first step (default 1/fp).
    options : SimulationOptions
    check_platform : bool
        Refuse conditions outside what the platform can do
        (:data:`identify.model.plausible.PLATFORM_RANGES`) and parameters outside what a
        contact on it can plausibly have (``PARAMETER_RANGES``), naming the likely unit
        slip; False simulates them anyway.

    Returns
    -------
    SimulationResult
    """
    if (normal_load_uN is None) == (block_voltage_V is None):
        raise ParameterError("give exactly one of normal_load_uN or block_voltage_V")
    if normal_load_uN is not None:
        nb = float(normal_load_uN)
        if not math.isfinite(nb) or nb <= 0:
            raise ParameterError(f"normal_load_uN = {normal_load_uN!r}: must be > 0 and finite")
        Nb = nb * 1e-6
    else:
        Nb = normal_load_from_voltage(block_voltage_V)
    if check_platform:
        for name, value in (("normal_load_uN", Nb * 1e6), ("spring_constant_N_per_m", spring_constant_N_per_m),
                            ("step_frequency_Hz", step_frequency_Hz)):
            if (problem := platform_problem(name, float(value))) is not None:
                raise ParameterError(problem)
    overrides = dict(params or {})
    if stick_speed_m_per_s is not None:
        overrides["v_stick"] = stick_speed_m_per_s
    if check_platform:
        check_parameters(overrides, "params: ")
    model = Model(get_law(law))
    values = parameter_set(coating, overrides)
    step = values["step_size"] * values["step_scale"]
    if (travel_um is None) == (n_steps is None):
        raise ParameterError("give exactly one of travel_um or n_steps")
    if travel_um is not None:
        tr = float(travel_um)
        if not math.isfinite(tr) or tr <= 0:
            raise ParameterError(f"travel_um = {travel_um!r}: must be > 0 and finite")
        if tr * 1e-6 > MAX_TRAVEL_M * (1 + 1e-9):
            warnings.warn(
                f"travel_um = {tr:g} exceeds the nanotractor's {MAX_TRAVEL_M * 1e6:g} µm range",
                stacklevel=2,
            )
        n_steps = max(1, int(round(tr * 1e-6 / step)))
    cond = RunConditions(
        spring_constant=float(spring_constant_N_per_m), normal_load=Nb,
        step_frequency=float(step_frequency_Hz), n_steps=int(n_steps),
        first_step_time=first_step_time_s, initial_elongation=float(initial_elongation_um) * 1e-6,
        initial_state=initial_state,
    )
    res = simulate_run(model, values, cond, options)
    res.coating = coating.upper()
    return res

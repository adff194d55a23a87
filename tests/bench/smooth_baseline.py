"""The paper's route: one smooth ODE through every puller step (benchmark baseline only).

The paper integrates a single ODE in (x, ẋ, ψ) with the stick made smooth: the
friction force is

    F_fric = μ(ψ, |ẋ|)·N·tanh(ẋ/v_reg),   μ = ψ + μ_topo(x) + A·ln(1 + |ẋ|/vc)   (Eq. 18)
    mb·ẍ   = F_s(xp − x) − F_fric − c·ẋ                                        (Eq. 20)
    dψ/dt  = (μmax − ψ)/τ − (ψ − μmin)·|ẋ|/dc                                   (Eq. 19)

with a regularisation speed v_reg (1e-8 m/s by default). At rest the tanh acts as a
dashpot of coefficient μ·N/v_reg (~400 N·s/m at Nb = 5 µN), so a "stuck" block creeps at
v ≈ v_reg·artanh(F_s/(μ·N)) instead of standing still, and the problem is extremely
stiff (fast eigenvalue ~ μ·N/(v_reg·mb) ~ 1e12 1/s). This module exists only so that
the simulator benchmark (``bench_simulator.py``) can measure the hybrid simulator (:mod:`identify.simulation.hybrid`)
against it; nothing else in the toolkit uses it (DESIGN.md §1).

Integration
    The puller position xp(t) = Δxp·(number of steps taken by t) is discontinuous, so
    the ODE is integrated step interval by step interval: :func:`scipy.integrate.solve_ivp`
    is restarted at every step with the new xp, from the state at the end of the previous
    interval. Within an interval the block position is integrated relative to its value at
    the interval start (u = x − x_ref), so the relative tolerance acts on the displacement,
    not on the absolute position (up to 100 µm). The analytic Jacobian is passed to Radau,
    BDF and LSODA (the exponential law; checked against finite differences in the tests).
    LSODA now and then gives up on an interval ("repeated convergence failures", seen
    with 4.6 nm steps); such an interval is retried with a 10x and 100x smaller first
    step, then with Radau, and counted in ``n_retries``.

Tolerances (defaults, documented choices)
    rtol = 1e-6; atol = (1e-12 m, 1e-10 m/s, 1e-8) for (u, ẋ, ψ): 1 pm is 1e-5 of the
    camera's 90 nm resolution and 1e-6 of a micrometre slip; 1e-10 m/s is 1 % of v_reg,
    so the stick creep speed (a few v_reg) is resolved; ψ ~ 0.5 to 1e-8. ``first_step``
    is 1e-8 s (a fraction of the 1 µs rejuvenation time dc/|ẋ| of a fast slip: a slip is
    triggered at a step instant, so each interval must start with a step short enough to
    see it); ``max_step`` is the interval length.

Slip events (the same quantities as the hybrid's EventTable)
    A slip is an episode where |ẋ| exceeds the detection speed ``v_detect`` (default
    100·v_reg = 1e-6 m/s = vc). Justification: in a stick the smoothed block creeps at
    v_reg·artanh(F_s/(μN)), which stays below ~10·v_reg until the force is within 1e-8 of
    the capacity (artanh(1 − 2e-9) ≈ 10), so 100·v_reg never fires in a stick; the hybrid
    counts the whole moving phase — creep nucleation at v ~ vc, the fast slip, the creep
    tail, and steady creep with the puller (4.6 µm/s at fp = 100 Hz) — as one event, and
    a threshold at vc keeps those phases together, where 1e-5 m/s would split a creep run
    into its fast bursts. An episode ends at the first solver point with |ẋ| ≤ v_detect.
    Slip length = x at the end − x at the last point before the episode; peak elongation
    = xp − x at that last point (after the triggering step, as in the hybrid); peak speed
    = the largest |ẋ| at the solver's points (they are dense inside a slip).

Budget
    ``max_wall_s`` bounds the wall time: the RHS checks the clock and the run stops,
    marked ``finished = False`` with the time and travel reached (DESIGN.md: at
    v_reg = 1e-10 m/s a 20 µm run did not finish in 9 minutes).
"""

from __future__ import annotations

import math
import time as _time
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.integrate import solve_ivp

from identify.model.laws import Exponential
from identify.model.params import ParameterError, parameter_set
from identify.model.symbolic import Model
from identify.simulation.hybrid import RunConditions, classify

__all__ = [
    "SmoothOptions",
    "SmoothEvents",
    "SmoothResult",
    "SmoothODE",
    "simulate_smooth",
    "simulate_smooth_run",
    "V_REG",
]

V_REG = 1e-8  # m/s, the paper-route regularisation speed of the benchmark (issue item 7)


class _OutOfTime(Exception):
    """Raised inside the RHS when the wall-time budget is spent."""


@dataclass(frozen=True)
class SmoothOptions:
    """Settings of the smooth (regularised-stick) route.

    Parameters
    ----------
    method : str
        ``Radau``, ``LSODA`` or ``BDF`` (scipy's implicit / switching methods; the
        explicit ones cannot take this problem).
    v_reg : float
        Regularisation speed of the tanh stick, m/s.
    v_detect : float or None
        Slip detection speed, m/s (None: 100·v_reg; module docstring).
    rtol : float
        Relative tolerance.
    atol : tuple of 3 floats
        Absolute tolerances of (u in m, ẋ in m/s, ψ).
    first_step : float
        First step of every interval, s (capped at the interval length).
    max_wall_s : float or None
        Wall-time budget; the run stops, unfinished, once it is spent.
    jacobian : bool
        Pass the analytic Jacobian (True) or let scipy difference it.
    """

    method: str = "Radau"
    v_reg: float = V_REG
    v_detect: float | None = None
    rtol: float = 1e-6
    atol: tuple = (1e-12, 1e-10, 1e-8)
    first_step: float = 1e-8
    max_wall_s: float | None = None
    jacobian: bool = True

    def __post_init__(self):
        if self.method not in ("Radau", "LSODA", "BDF"):
            raise ValueError(f"method = {self.method!r}: choose 'Radau', 'LSODA' or 'BDF'")
        for name in ("v_reg", "rtol", "first_step"):
            v = getattr(self, name)
            if not (v > 0 and math.isfinite(v)):
                raise ValueError(f"{name} = {v!r}: must be a positive number")
        if self.v_detect is not None and not (self.v_detect > 0):
            raise ValueError(f"v_detect = {self.v_detect!r}: must be > 0")
        if len(self.atol) != 3 or not all(a > 0 for a in self.atol):
            raise ValueError(f"atol = {self.atol!r}: three positive numbers (u, v, psi)")
        if self.max_wall_s is not None and not (self.max_wall_s > 0):
            raise ValueError(f"max_wall_s = {self.max_wall_s!r}: must be > 0 or None")

    @property
    def detect_speed(self) -> float:
        return 100.0 * self.v_reg if self.v_detect is None else float(self.v_detect)


@dataclass
class SmoothEvents:
    """Slip episodes of a smooth run, one array per column (SI)."""

    data: dict

    columns = ("time_s", "peak_elongation_m", "slip_length_m", "peak_speed_m_per_s", "duration_s")

    def __len__(self) -> int:
        return len(self.data["time_s"])

    def __getitem__(self, name: str) -> np.ndarray:
        return self.data[name]

    @classmethod
    def from_rows(cls, rows: list) -> SmoothEvents:
        return cls({c: np.array([r[c] for r in rows], float) for c in cls.columns})


@dataclass
class SmoothResult:
    """One run of the smooth route.

    Attributes
    ----------
    events : SmoothEvents
    finished : bool
        False when the wall-time budget stopped the run (or the solver failed).
    t_reached, travel_reached_m : float
        How far the run got (time, puller travel).
    n_rhs, n_jac, n_lu, n_solver_steps, n_intervals : int
        Work counters summed over the solve_ivp calls (n_rhs counts every RHS call,
        including those of scipy's finite differences when ``jacobian`` is False).
    wall_time_s : float
    regime : str
        As :func:`identify.simulation.hybrid.classify` on the episodes.
    message : str
        Why the run stopped early, if it did.
    n_retries : int
        Step intervals the solver failed on and that were retried (smaller first step,
        then Radau).
    """

    conditions: RunConditions
    options: SmoothOptions
    events: SmoothEvents
    finished: bool
    t_reached: float
    travel_reached_m: float
    n_rhs: int
    n_jac: int
    n_lu: int
    n_solver_steps: int
    n_intervals: int
    wall_time_s: float
    moving_fraction: float
    regime: str
    step: float
    message: str = ""
    n_retries: int = 0
    trajectory: dict | None = field(default=None, repr=False)

    def summary(self) -> dict:
        ev = self.events
        n = len(ev)
        return dict(
            method=self.options.method,
            v_reg_m_per_s=self.options.v_reg,
            v_detect_m_per_s=self.options.detect_speed,
            finished=self.finished,
            message=self.message,
            n_slips=int(n),
            regime=self.regime,
            mean_slip_length_um=float(ev["slip_length_m"].mean() * 1e6) if n else None,
            mean_peak_elongation_um=float(ev["peak_elongation_m"].mean() * 1e6) if n else None,
            peak_slip_speed_m_per_s=float(ev["peak_speed_m_per_s"].max()) if n else 0.0,
            moving_fraction=self.moving_fraction,
            t_reached_s=self.t_reached,
            travel_reached_um=self.travel_reached_m * 1e6,
            n_rhs=self.n_rhs,
            n_jac=self.n_jac,
            n_lu=self.n_lu,
            n_solver_steps=self.n_solver_steps,
            n_intervals=self.n_intervals,
            n_retries=self.n_retries,
            wall_time_s=self.wall_time_s,
        )


class SmoothODE:
    """RHS and Jacobian of the regularised single ODE, from the model's physics methods.

    State y = (u, v, ψ), u = x − x_ref (m), v = ẋ (m/s). ``xp`` and ``x_ref`` are set
    per step interval. Only the exponential law (the paper's) is supported.
    """

    def __init__(self, model: Model, P: Mapping[str, float], v_reg: float):
        if not isinstance(model.law, Exponential):
            raise ParameterError(
                f"the smooth baseline is written for the exponential law, not {model.law.name!r}"
            )
        self.model = model
        self.law = model.law
        self.P = dict(P)
        self.v_reg = float(v_reg)
        self.N = float(model.normal_load(self.P))
        self.c = float(model.damping(self.P))
        self.mb = float(self.P["mb"])
        self.xp = 0.0
        self.x_ref = 0.0
        self.n_rhs = 0
        self.deadline = math.inf

    # -- physics pieces (the model's methods; math as the scalar backend)
    def friction(self, x, v, psi):
        """μ(ψ, |v|, x)·N·tanh(v/v_reg), N."""
        mu = self.model.friction_coefficient(psi, abs(v), x, self.P, ops=math)
        return mu * self.N * math.tanh(v / self.v_reg)

    def rhs(self, t, y):
        self.n_rhs += 1
        if self.n_rhs & 63 == 0 and _time.perf_counter() > self.deadline:
            raise _OutOfTime
        u, v, psi = float(y[0]), float(y[1]), float(y[2])
        x = self.x_ref + u
        fs = self.model.spring_force(self.xp - x, self.P, ops=math)
        acc = (fs - self.friction(x, v, psi) - self.c * v) / self.mb
        return np.array([v, acc, self.law.rate(psi, abs(v), self.P, ops=math)])

    def jac(self, t, y):
        """Analytic Jacobian d(rhs)/dy (exponential law, every model effect)."""
        P = self.P
        u, v, psi = float(y[0]), float(y[1]), float(y[2])
        x = self.x_ref + u
        e = self.xp - x
        speed = abs(v)
        sgn = (v > 0) - (v < 0)
        th = math.tanh(v / self.v_reg)
        mu = self.model.friction_coefficient(psi, speed, x, P, ops=math)
        # dF_s/de for F_s = s_k·k·e·(1 + β·e²); dμ_topo/dx for a·sin(2πx/λ + φ)
        dfs = P["k_scale"] * P["k"] * (1 + 3 * P["beta"] * e * e)
        w = 2 * math.pi / P["topo_wavelength"]
        dtopo = P["topo_amp"] * w * math.cos(w * x + P["topo_phase"])
        dmu_dv = P["A"] * sgn / (P["vc"] + speed)
        N, mb = self.N, self.mb
        J = np.empty((3, 3))
        J[0] = (0.0, 1.0, 0.0)
        J[1, 0] = (-dfs - N * th * dtopo) / mb
        J[1, 1] = (-N * (dmu_dv * th + mu * (1 - th * th) / self.v_reg) - self.c) / mb
        J[1, 2] = -N * th / mb
        J[2, 0] = 0.0
        J[2, 1] = -(psi - P["mu_min"]) * sgn / P["dc"]
        J[2, 2] = -1.0 / P["tau"] - speed / P["dc"]
        return J


class _EpisodeTracker:
    """Turns the solver's points into slip episodes (module docstring)."""

    def __init__(self, v_detect: float):
        self.vd = v_detect
        self.rows: list = []
        self.open: dict | None = None
        self.last = None  # (t, x, e) of the last point below the threshold
        self.moving_time = 0.0

    def feed(self, t, x, v, xp):
        fast = np.abs(v) > self.vd
        i = 0
        n = len(t)
        while i < n:
            if self.open is None:
                j = np.argmax(fast[i:]) + i if fast[i:].any() else n
                if j > i:
                    self.last = (t[j - 1], x[j - 1], xp - x[j - 1])
                if j >= n:
                    return
                t0, x0, e0 = self.last if self.last is not None else (t[j], x[j], xp - x[j])
                self.open = dict(time_s=t0, x0=x0, peak_elongation_m=e0, vmax=0.0)
                i = j
            else:
                slow = ~fast[i:]
                j = np.argmax(slow) + i if slow.any() else n
                seg = np.abs(v[i:j])
                if seg.size:
                    self.open["vmax"] = max(self.open["vmax"], float(seg.max()))
                if j >= n:
                    self.open["x_last"], self.open["t_last"] = x[n - 1], t[n - 1]
                    return
                self._close(t[j], x[j])
                i = j

    def _close(self, t_end, x_end):
        o = self.open
        self.rows.append(
            dict(
                time_s=o["time_s"],
                peak_elongation_m=o["peak_elongation_m"],
                slip_length_m=x_end - o["x0"],
                peak_speed_m_per_s=o["vmax"],
                duration_s=t_end - o["time_s"],
            )
        )
        self.moving_time += t_end - o["time_s"]
        self.open = None
        self.last = None

    def finish(self, finished: bool):
        """Close an episode still open at the end of a finished run (the hybrid does too)."""
        if self.open is not None and finished and "x_last" in self.open:
            self._close(self.open["t_last"], self.open["x_last"])
        return SmoothEvents.from_rows(self.rows)


def simulate_smooth_run(
    model: Model,
    values: Mapping[str, float],
    conditions: RunConditions,
    options: SmoothOptions | None = None,
    keep_trajectory: bool = False,
) -> SmoothResult:
    """Integrate one run with the regularised single ODE (SI throughout).

    Same conditions and conventions as :func:`identify.simulation.hybrid.simulate_run`:
    steps at t_n = t_first + (n − 1)/fp, the run ends one step period after the last
    step, the block starts at x = −e0 with the state fully aged unless given.
    """
    opts = options or SmoothOptions()
    wall0 = _time.perf_counter()
    c = conditions
    vals = model.defaults(values)
    P = {**vals, "k": c.spring_constant, "Nb": c.normal_load}
    ode = SmoothODE(model, P, opts.v_reg)
    if opts.max_wall_s is not None:
        ode.deadline = wall0 + float(opts.max_wall_s)
    dx = float(model.step(P))
    fp = c.step_frequency
    atol = np.asarray(opts.atol, float)
    # interval boundaries: 0, t_1, ..., t_n, end
    bounds = np.concatenate([[0.0], c.t_first + np.arange(c.n_steps) / fp, [c.end_time]])
    x = -float(c.initial_elongation)
    psi = model.law.aged_state(P) if c.initial_state is None else float(c.initial_state)
    v = 0.0
    tracker = _EpisodeTracker(opts.detect_speed)
    n_jac = n_lu = n_steps = n_retries = 0
    finished, message = True, ""
    t_reached, n_done = 0.0, 0
    traj: dict | None = dict(t=[], x=[], v=[], psi=[], xp=[]) if keep_trajectory else None
    jac = ode.jac if opts.jacobian else None
    for i in range(len(bounds) - 1):
        t0, t1 = float(bounds[i]), float(bounds[i + 1])
        if t1 <= t0:
            continue
        ode.xp = i * dx if i <= c.n_steps else c.n_steps * dx
        ode.x_ref = x
        y0 = np.array([0.0, v, psi])
        h0 = min(opts.first_step, 0.5 * (t1 - t0))
        # LSODA occasionally gives up on an interval ("repeated convergence failures"):
        # retry with a 10x and 100x smaller first step, then with Radau (counted in n_retries)
        attempts = [(opts.method, h0), (opts.method, h0 / 10), (opts.method, h0 / 100)]
        if opts.method != "Radau":
            attempts.append(("Radau", h0))
        sol = None
        try:
            for meth, h in attempts:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", UserWarning)
                    sol = solve_ivp(
                        ode.rhs,
                        (t0, t1),
                        y0,
                        method=meth,
                        jac=jac,
                        rtol=opts.rtol,
                        atol=atol,
                        first_step=h,
                        max_step=t1 - t0,
                    )
                n_jac += int(sol.njev)
                n_lu += int(sol.nlu)
                if sol.status >= 0:
                    break
                n_retries += 1
        except _OutOfTime:
            finished = False
            message = f"did not finish in {opts.max_wall_s:g} s (reached t = {t_reached:.4g} s)"
            break
        n_steps += max(len(sol.t) - 1, 0)
        if sol.status < 0:
            finished = False
            message = f"solver failed at t = {t0:.6g} s: {sol.message}"
            break
        xs = x + sol.y[0]
        tracker.feed(sol.t, xs, sol.y[1], ode.xp)
        if traj is not None:
            traj["t"].append(sol.t)
            traj["x"].append(xs)
            traj["v"].append(sol.y[1])
            traj["psi"].append(sol.y[2])
            traj["xp"].append(np.full(len(sol.t), ode.xp))
        x, v, psi = float(xs[-1]), float(sol.y[1, -1]), float(sol.y[2, -1])
        t_reached, n_done = t1, min(i, c.n_steps)
    events = tracker.finish(finished)
    span_start = events["time_s"][0] if len(events) else t_reached
    span = t_reached - span_start
    moving = tracker.moving_time
    if tracker.open and "t_last" in tracker.open and not finished:  # episode cut by the budget
        moving += tracker.open["t_last"] - tracker.open["time_s"]
    moving_fraction = float(np.clip(moving / span, 0.0, 1.0)) if span > 0 else 0.0
    res = SmoothResult(
        conditions=c,
        options=opts,
        events=events,
        finished=finished,
        t_reached=t_reached,
        travel_reached_m=n_done * dx,
        n_rhs=ode.n_rhs,
        n_jac=n_jac,
        n_lu=n_lu,
        n_solver_steps=n_steps,
        n_intervals=i + (1 if finished else 0),
        wall_time_s=_time.perf_counter() - wall0,
        moving_fraction=moving_fraction,
        regime=classify(events, dx, moving_fraction),
        step=dx,
        message=message,
        n_retries=n_retries,
    )
    if traj is not None:
        res.trajectory = {k: np.concatenate(v) if v else np.array([]) for k, v in traj.items()}
    return res


def simulate_smooth(
    coating: str = "FOTAS",
    *,
    spring_constant_N_per_m: float,
    step_frequency_Hz: float,
    normal_load_uN: float,
    travel_um: float | None = None,
    n_steps: int | None = None,
    params: Mapping[str, float] | None = None,
    options: SmoothOptions | None = None,
    method: str | None = None,
    max_wall_s: float | None = None,
    keep_trajectory: bool = False,
) -> SmoothResult:
    """Front end mirroring :func:`identify.simulate` (exponential law only).

    ``method`` and ``max_wall_s``, when given, override those of ``options``.
    """
    opts = options or SmoothOptions()
    if method is not None or max_wall_s is not None:
        kw = dict(opts.__dict__)
        if method is not None:
            kw["method"] = method
        if max_wall_s is not None:
            kw["max_wall_s"] = max_wall_s
        opts = SmoothOptions(**kw)
    values = parameter_set(coating, params)
    model = Model()
    step = values["step_size"] * values["step_scale"]
    if (travel_um is None) == (n_steps is None):
        raise ParameterError("give exactly one of travel_um or n_steps")
    if travel_um is not None:
        if not (travel_um > 0 and math.isfinite(travel_um)):
            raise ParameterError(f"travel_um = {travel_um!r}: must be > 0 and finite")
        n_steps = max(1, int(round(travel_um * 1e-6 / step)))
    cond = RunConditions(
        spring_constant=float(spring_constant_N_per_m),
        normal_load=float(normal_load_uN) * 1e-6,
        step_frequency=float(step_frequency_Hz),
        n_steps=int(n_steps),
    )
    return simulate_smooth_run(model, values, cond, opts, keep_trajectory)

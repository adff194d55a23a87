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

The run's inputs are in :mod:`identify.simulation.conditions`; what it gives (events,
regime, trajectories, camera sampling, report) in :mod:`identify.simulation.result`.
"""

from __future__ import annotations

import logging
import math
import time as _time
from collections.abc import Mapping

import numpy as np

from identify.messages import summarise
from identify.model.laws import get_law
from identify.model.params import parameter_set, validate_parameters
from identify.model.symbolic import LENGTH_UNIT, N_STATES, SPEED_UNIT, TIME_UNIT, Model, slip_integrator, slip_rhs
from identify.simulation.conditions import (
    MAX_TRAVEL_M,
    RunConditions,
    SimulationOptions,
    check_platform_conditions,
    normal_load_N,
    parameter_overrides,
    step_count,
)

# (``X as X``: names of the parts split out of this module stay importable from it)
from identify.simulation.result import MIN_SLIP_STEPS as MIN_SLIP_STEPS
from identify.simulation.result import REGIMES, EventTable, MovingPhase, SimulationResult, classify

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

_CHUNK_POINTS = 16  # output points per IDAS sub-interval
_HOLD_SLACK = 1e-6  # relative force tolerance of the hold test at a located stop


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
        self.phases: list[MovingPhase] = []
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
        s = direction
        X = self._rest_state(x0, z0)
        t = t0
        rec_t, rec_X = [t0], [X.copy()]
        reversals, steps_crossed, M = 0, 0, 1
        end = self.c.end_time
        while True:
            if t >= end - 1e-12 / self.fp:
                return self._finish(t, X, n_done, s, rec_t, rec_X, reversals, steps_crossed, held=False)
            M_eff, H, ts, xp = self._window(t, n_done, M)
            out = self._integrate(t, X, s, M_eff, H, xp)
            stop = self._find_stop(t, X, ts, out, s, np.repeat(xp, len(_GRID)))
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

    def _rest_state(self, x0: float, z0: float) -> np.ndarray:
        """The scaled state of a block at rest at x0 with contact state z0; the stick
        threshold is armed from the start only when there is none (v_stick ≤ 0)."""
        X = np.zeros(N_STATES)
        X[0], X[2], X[3] = x0 / LENGTH_UNIT, z0 / self.sc, 1.0
        X[4] = 1.0 if self.v_stick <= 0 else 0.0
        return X

    def _window(self, t: float, n_done: int, M: int):
        """The next integration window from t: (step intervals M_eff, duration H, output
        times, puller position per interval in µm). From a step it spans up to M whole
        step intervals; from between two steps (after a stop) it ends at the next step."""
        if abs(t - self.step_time(n_done)) <= 1e-9 / self.fp:
            M_eff = max(1, min(M, self.c.n_steps - n_done + 1))
            H = M_eff / self.fp
            ts = t + H * _grid_of(M_eff)
            xp = (n_done + np.arange(M_eff)) * self.dx / LENGTH_UNIT
        else:
            M_eff = 1
            t_next = self.step_time(n_done + 1) if n_done < self.c.n_steps else self.c.end_time
            H = t_next - t
            ts = t + H * _GRID
            xp = np.array([n_done * self.dx / LENGTH_UNIT])
        return M_eff, H, ts, xp

    def _integrate(self, t: float, X: np.ndarray, s: float, M_eff: int, H: float, xp: np.ndarray) -> np.ndarray:
        """The outputs of one window integrated from X, the puller position a control per
        step interval; raises FloatingPointError if they are not finite.

        IDACalcIC occasionally fails in a creep tail; the state is a valid initial
        condition of the ODE as it is, so IDAS then retries without it.
        """
        plugin = self.opts.integrator
        F = self.integrator(plugin, M_eff)
        u = np.repeat(xp, len(_GRID))[None, :]
        try:
            out = np.array(F(x0=X, p=self.p(s, H), u=u)["xf"])
        except RuntimeError:
            if plugin != "idas":
                raise
            F = self.integrator(plugin, M_eff, None, calc_ic=False)
            out = np.array(F(x0=X, p=self.p(s, H), u=u)["xf"])
        self.calls += 1
        if not np.all(np.isfinite(out)):
            raise FloatingPointError(f"integration failed at t = {t:.6g} s")
        return out

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
                MovingPhase(np.array(rec_t), arr[:, 0] * LENGTH_UNIT, arr[:, 1] * SPEED_UNIT, arr[:, 2] * self.sc)
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
    Nb = normal_load_N(normal_load_uN, block_voltage_V)
    if check_platform:
        check_platform_conditions(Nb, spring_constant_N_per_m, step_frequency_Hz)
    overrides = parameter_overrides(params, stick_speed_m_per_s, check_platform)
    model = Model(get_law(law))
    values = parameter_set(coating, overrides)
    n_steps = step_count(travel_um, n_steps, values["step_size"] * values["step_scale"])
    cond = RunConditions(
        spring_constant=float(spring_constant_N_per_m), normal_load=Nb,
        step_frequency=float(step_frequency_Hz), n_steps=int(n_steps),
        first_step_time=first_step_time_s, initial_elongation=float(initial_elongation_um) * 1e-6,
        initial_state=initial_state,
    )
    res = simulate_run(model, values, cond, options)
    res.coating = coating.upper()
    return res


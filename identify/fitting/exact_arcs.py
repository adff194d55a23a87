"""Exact derivatives of the slip arcs: IDAS on the symbolic slip model, the stop time
refined by a CasADi rootfinder (DESIGN.md §2).

An arc (:mod:`identify.fitting.arcs`) starts at a trigger step with the block at rest and ends
where the block stops. The event-located simulation (the Rosenbrock arc) tells where
the stop is: its time T*, the step interval j it falls in (or that the block still
moves at the arc's horizon) and whether the stick threshold was armed. Here the same
slip is integrated again with IDAS, forward sensitivities under error control:

* j whole step intervals at fixed times, the puller advanced by one step at each node
  (never ``floor(fp·t)`` inside the ODE: its derivative is zero and the integrator would
  not see the jump);
* then the last, partial interval of length τ, τ* the root of v(τ) − v_stop found by a
  Newton ``rootfinder`` seeded with the simulated stop. CasADi differentiates through τ*
  by the implicit function theorem, so the slip length and the contact state carry the
  stop time's dependence on every input, exactly up to the integrator's tolerance;
* after the stop the contact ages in closed form (the law's ``rest``) to the horizon.

An arc whose end is a knife edge (:func:`grazing_flags`) has outputs that jump with its
inputs: no method gives it a derivative. Such arcs still get the derivative of the
branch they are on, and are flagged, so that the mode-sequence decision (not the
solver's linearisation) deals with them.

One Function per structure (whole intervals j, still moving or stopped, the inputs
differentiated) is built once and mapped over every arc that shares it.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass

import casadi as ca
import numpy as np

from identify.fitting.creep_onset import creep_onset_mask
from identify.model.compiled import held_stderr
from identify.model.symbolic import LENGTH_UNIT, SPEED_UNIT, TIME_UNIT, Model, slip_dae

__all__ = ["EXACT_ABSTOL", "EXACT_RELTOL", "GRAZING_REASONS", "ExactArcs", "exact_arcs", "grazing_flags"]

log = logging.getLogger(__name__)

# IDAS tolerances: relative, and absolute per state (x µm, v mm/s, scaled contact state).
# The slip length's dependence on the start of the slip is a small difference of large
# terms (the creep nucleation's timing moves with the start, the stop time takes most of
# it back), so the sensitivities need tolerances well below what the values need
# (docs/engineering-notes.md, "Exact arc derivatives", has the convergence measured).
# IDAS is given the smallest as one scalar: with per-state tolerances (abstolv) its
# forward sensitivities stopped at t = 0 ("initial ewt component = 0.0 illegal").
EXACT_RELTOL = 1e-10
EXACT_ABSTOL = (1e-10, 1e-10, 1e-10)
# The stop-time Newton: converged when its step is below ROOT_STEP (ms) or the speed's
# miss below ROOT_MISS of the slip's peak speed. The integrator's own noise in v decides
# the last digits: measured at IDAS 1e-10, the miss wanders at 1e-7 to 5e-7 mm/s on a
# 28 mm/s slip and the step at 1e-9 to 5e-9 ms, whatever the iterations; CVODES's noise is
# ten times that. Started from the event-located stop it needs 1-5 iterations; an arc
# not converged in ROOT_MAX_ITER (or whose stop would move before the slip's start)
# counts as failed. The derivative terms a miss leaves are proportional to it (see
# ExactArcs._build): at 1e-6 of the peak speed, below the integration error.
ROOT_STEP = 1e-9
ROOT_MISS = 1e-6
ROOT_MAX_ITER = 8
# What makes an arc grazing (fractions): its stop within GRAZE_NODE of a step period of
# a step node (a block that nearly stopped is pushed on, or not, by the next step); its
# peak speed within GRAZE_ARM of the stick threshold (armed or not); the spring force at
# the stop within GRAZE_HOLD of what friction can hold there (stays, or slips again).
GRAZE_NODE = 1e-3
GRAZE_ARM = 0.02
GRAZE_HOLD = 1e-3
# And (bit 3, where the arcs can be integrated again) the speed's dip after the
# deceleration near the stick threshold: :mod:`identify.fitting.creep_onset`.
GRAZING_REASONS = ("stop at a step node", "peak speed at the stick threshold", "force at the holding limit",
                   "stop at a creep tail's onset")


@dataclass(frozen=True)
class _Structure:
    whole: int  # whole step intervals before the last one
    stopped: bool  # False: still moving at the horizon (no stop to find)
    rows: tuple  # the inputs differentiated


class ExactArcs:
    """Exact arc Jacobians for one model (see the module docstring).

    Parameters
    ----------
    model : Model
        The friction model (the same one the event-located arcs integrate).
    input_names : tuple of str
        The arcs' inputs, in :class:`identify.fitting.arcs.ArcFunctions` order.
    reltol : float
        IDAS relative tolerance.
    abstol : tuple of float
        IDAS absolute tolerances per state (x µm, v mm/s, scaled contact state).
    """

    def __init__(self, model: Model, input_names: tuple, reltol: float = EXACT_RELTOL,
                 abstol: tuple = EXACT_ABSTOL):
        self.model, self.law = model, model.law
        self.input_names = tuple(input_names)
        self.n_in = len(self.input_names)
        self.index = {n: i for i, n in enumerate(self.input_names)}
        self.param_names = tuple(self.input_names[3:-4])
        self.reltol, self.abstol = float(reltol), tuple(float(a) for a in abstol)
        self._functions: dict = {}
        self.n_failed = 0  # arcs whose IDAS integration or stop refinement failed

    # ---------------------------------------------------------------- symbolic
    def _segment(self, plugin: str) -> ca.Function:
        """(X0, xp_um, p) -> X at the end of one segment of the slip ODE (x, v, state),
        the segment's length the last entry of p (ms), integrated by ``plugin``
        (built once per plugin and kept)."""
        key = ("segment", plugin)
        if key not in self._functions:
            self._functions[key] = self._build_segment(plugin)
        return self._functions[key]

    def _build_segment(self, plugin: str) -> ca.Function:
        ode, x3, u, p = _forward_slip_ode(self.model)
        opts = dict(reltol=self.reltol, abstol=min(self.abstol), max_num_steps=200_000)
        if plugin == "idas":
            opts.update(fsens_err_con=True, calc_ic=True, disable_internal_warnings=True)
        integ = ca.integrator(f"slip_{plugin}", plugin, dict(x=x3, u=u, p=p, ode=ode), 0.0, 1.0, opts)
        X0, xp, pp = ca.MX.sym("X0", 3), ca.MX.sym("xp"), ca.MX.sym("p", p.numel())
        return ca.Function("segment", [X0, xp, pp], [integ(x0=X0, u=xp, p=pp)["xf"]],
                           ["X0", "xp_um", "p"], ["Xf"])

    @functools.cached_property
    def _rhs(self) -> ca.Function:
        """(X, xp_um, p) -> dX/dt per ms (the segment ODE with a duration of 1 ms)."""
        ode, x3, u, p = _forward_slip_ode(self.model)
        return ca.Function("slip_rhs", [x3, u, p], [ode])

    def _build(self, s: _Structure, plugin: str) -> tuple[ca.Function, ca.Function]:
        """Two Functions of one structure, both (a_var, a, τ, v_stop) -> ...:

        * ``step``: the Newton step on the stop time, (v_stop − v(τ)) / v̇(τ) (ms), and
          v(τ) − v_stop (mm/s), values only, for refining τ to the root;
        * ``arc``: y = [slip µm, state at horizon, stop ms] and dy[:2]/da_var at a root τ.

        At the root, the stop time's derivative is the implicit function theorem's,
        dτ*/da = −(∂v/∂a) / v̇, and the state's is ∂X/∂a + Ẋ·dτ*/da. Both come out of
        differentiating one Newton step X(τ) + Ẋ·(v_stop − v(τ))/v̇ taken from the root
        with τ held: the terms the step adds beyond these are multiplied by the
        residual, zero there. So each arc needs a single integration with forward
        sensitivities (the rootfinder's implicit derivative re-integrates the
        sensitivities at every Newton iteration)."""
        ix, law, seg = self.index, self.law, self._segment(plugin)
        a_all = ca.MX.sym("a", self.n_in)
        a_var = ca.MX.sym("a_var", len(s.rows))
        sel = np.zeros((self.n_in, len(s.rows)))
        sel[list(s.rows), range(len(s.rows))] = 1.0
        keep = np.ones(self.n_in)
        keep[list(s.rows)] = 0.0
        a = a_all * ca.DM(keep) + ca.mtimes(ca.DM(sel), a_var)
        n_m = len(self.param_names)
        pm = a[3 : 3 + n_m]
        k, nb, fp, M = a[ix["k"]], a[ix["Nb"]], a[ix["fp"]], a[ix["M"]]
        step_um = a[ix["step_size"]] * a[ix["step_scale"]] / LENGTH_UNIT
        period_ms = 1 / fp / TIME_UNIT

        def pv(duration_ms):
            return ca.vertcat(pm, k, nb, 1.0, duration_ms)

        X = ca.vertcat(a[0], 0, a[2] / law.state_scale)
        u0 = a[0] + a[1]
        if s.whole:
            chain = seg.mapaccum("whole", s.whole)
            nodes = u0 + step_um * ca.DM(np.arange(s.whole)).T
            X = chain(X, nodes, ca.repmat(pv(period_ms), 1, s.whole))
        tau, v_stop = ca.MX.sym("tau"), ca.MX.sym("v_stop")
        u_last = u0 + s.whole * step_um
        if s.stopped:
            Xr = seg(X, u_last, pv(tau))
            rate = self._rhs(Xr, u_last, pv(1.0))
            miss = Xr[1] - v_stop
            dtau = -miss / rate[1]
            Xe = Xr + rate * dtau
            stop_ms = s.whole * period_ms + tau + dtau
        else:
            Xe, dtau, miss = X, ca.MX(0), ca.MX(0)
            stop_ms = s.whole * period_ms
        rest_s = (M * period_ms - stop_ms) * TIME_UNIT
        P = {n: pm[i] for i, n in enumerate(self.param_names)}
        z_end = law.rest(Xe[2] * law.state_scale, rest_s, P, ops=ca) if s.stopped else Xe[2] * law.state_scale
        y = ca.vertcat(Xe[0] - a[0], z_end, stop_ms)
        # forward mode, one direction per input: two outputs against several inputs
        # would otherwise go to adjoint sensitivities (a backward integration)
        J = ca.jtimes(y[:2], a_var, ca.DM.eye(len(s.rows)))
        ins, names = [a_var, a_all, tau, v_stop], ["a_var", "a", "tau", "v_stop"]
        return (ca.Function("stop_step", ins, [dtau, miss], names, ["dtau", "miss"]),
                ca.Function("arc_exact", ins, [y, J], names, ["y", "dy_da"]))

    def function(self, whole: int, stopped: bool, rows: tuple, plugin: str = "idas") -> tuple[ca.Function, ca.Function]:
        """The cached (stop step, arc) Functions of one arc structure."""
        s = _Structure(int(whole), bool(stopped), tuple(int(r) for r in rows))
        f = self._functions.get((s, plugin))
        if f is None:
            f = self._functions[(s, plugin)] = self._build(s, plugin)
        return f

    # ---------------------------------------------------------------- numeric
    def structure(self, A: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per arc, from its event-located simulation ``Y``: whole step intervals before
        the stop, whether it stopped, and its stop speed (mm/s)."""
        ix = self.index
        period_ms = 1 / A[ix["fp"]] / TIME_UNIT
        stopped = Y[4] < 0.5
        whole = np.where(stopped, np.floor(Y[2] / period_ms), A[ix["M"]])
        whole = np.clip(np.nan_to_num(whole, nan=0.0), 0, A[ix["M"]]).astype(int)
        v_stick = A[ix["v_stick"]]
        armed = (v_stick > 0) & (Y[3] > v_stick)
        v_stop = np.where(armed, v_stick / SPEED_UNIT, 0.0)
        return whole, stopped, v_stop

    def _stop_times(self, step: ca.Function, args: tuple, peak_mm_s: np.ndarray,
                    threads: int) -> tuple[np.ndarray, np.ndarray]:
        """Newton on the stop time of each arc of one structure, from the event-located
        stop; returns (τ, converged). Values only: one integration per iteration."""
        n = args[2].size
        tau = np.array(args[2], float)
        done = np.zeros(n, bool)
        live = np.ones(n, bool)
        for _ in range(ROOT_MAX_ITER):
            cols = np.nonzero(live & ~done)[0]
            if not cols.size:
                break
            sub = tuple(x[:, cols] if np.ndim(x) > 1 else x[cols] for x in (args[0], args[1], tau, args[3]))
            peak = peak_mm_s[cols]
            try:
                dtau, miss = (np.array(o).ravel() for o in _mapped(step, cols.size, threads)(*sub))
            except RuntimeError:
                dtau, miss = np.full(cols.size, np.nan), np.full(cols.size, np.nan)
                for j in range(cols.size):
                    try:
                        dtau[j], miss[j] = (float(o) for o in step(*(x[:, j] if np.ndim(x) > 1 else x[j] for x in sub)))
                    except RuntimeError:
                        pass
            bad = ~np.isfinite(dtau) | (tau[cols] + dtau < 0)
            live[cols[bad]] = False
            good = cols[~bad]
            tau[good] += dtau[~bad]
            done[good] = (np.abs(dtau[~bad]) < ROOT_STEP) | (np.abs(miss[~bad]) < ROOT_MISS * peak[~bad])
        return tau, done & live

    def jacobian(self, A: np.ndarray, Y: np.ndarray, rows,
                 threads: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Exact d(slip, state at horizon)/d(inputs ``rows``) of every arc (columns of A),
        seeded by its event-located outputs ``Y`` (5 × n, :meth:`ArcFunctions.evaluate`).

        Returns (y, J, ok): y (3 × n: slip µm, state at horizon, stop ms, from the IDAS
        integration), J (2 × n_in × n, zero in the rows not asked for) and, per arc,
        whether the integration and the stop refinement succeeded (else y and J are NaN
        there).

        IDAS integrates every arc; an arc it cannot start is integrated by CVODES, the
        same BDF method for explicit ODEs (measured: IDAS's consistent-initial-condition
        search, IDACalcIC, failed on 28 of ~1100 arcs of the 10-run speed set, slips
        from a fully aged contact whose initial acceleration is ~2·10⁴ in scaled units;
        CVODES needs no initial derivative)."""
        rows = tuple(int(r) for r in rows)
        n = A.shape[1]
        y = np.full((3, n), np.nan)
        J = np.zeros((2, self.n_in, n))
        ok = np.zeros(n, bool)
        if not n:
            return y, J, ok
        finite = np.all(np.isfinite(A), axis=0) & np.all(np.isfinite(Y[:5]), axis=0)
        todo = np.nonzero(finite)[0]
        for plugin in ("idas", "cvodes"):
            if not todo.size:
                break
            with _held_stderr(plugin):
                yy, jj, done = self._pass(A[:, todo], Y[:, todo], rows, threads, plugin)
            y[:, todo[done]], J[:, :, todo[done]], ok[todo[done]] = yy[:, done], jj[:, :, done], True
            todo = todo[~done]
        self.n_failed += int(todo.size)
        J[:, :, ~ok] = np.nan
        return y, J, ok

    def _pass(self, A: np.ndarray, Y: np.ndarray, rows: tuple, threads: int, plugin: str):
        """:meth:`jacobian` of arcs with finite inputs, by one integrator plugin."""
        n = A.shape[1]
        y = np.full((3, n), np.nan)
        J = np.zeros((2, self.n_in, n))
        ok = np.zeros(n, bool)
        whole, stopped, v_stop = self.structure(A, Y)
        keys = np.stack([whole, stopped.astype(int)])
        for key in np.unique(keys, axis=1).T:
            cols = np.nonzero((whole == key[0]) & (stopped == bool(key[1])))[0]
            step, f = self.function(int(key[0]), bool(key[1]), rows, plugin)
            period_ms = 1 / A[self.index["fp"], cols] / TIME_UNIT
            tau0 = Y[2, cols] - key[0] * period_ms if key[1] else np.zeros(cols.size)
            args = (A[list(rows)][:, cols], A[:, cols], tau0, v_stop[cols])
            if key[1]:
                tau, conv = self._stop_times(step, args, np.abs(Y[3, cols]) / SPEED_UNIT, threads)
            else:
                tau, conv = tau0, np.ones(cols.size, bool)
            cols, args = cols[conv], (args[0][:, conv], args[1][:, conv], tau[conv], args[3][conv])
            if not cols.size:
                continue
            try:
                yy, jj = _mapped(f, cols.size, threads)(*args)
                yy, jj = np.array(yy), np.array(jj)
                done = np.ones(cols.size, bool)
            except RuntimeError:
                # one arc the integrator cannot do must not sink the others
                yy, jj = np.full((3, cols.size), np.nan), np.full((2, len(rows) * cols.size), np.nan)
                done = np.zeros(cols.size, bool)
                for c in range(cols.size):
                    try:
                        y1, j1 = f(*(x[:, c] if np.ndim(x) > 1 else x[c] for x in args))
                        yy[:, c] = np.array(y1).ravel()
                        jj[:, c * len(rows):(c + 1) * len(rows)] = np.array(j1)
                        done[c] = True
                    except RuntimeError:
                        pass
            y[:, cols] = yy
            # (the map puts each arc's 2 × rows block side by side)
            J[:, np.array(rows)[:, None], cols[None, :]] = jj.reshape(2, cols.size, len(rows)).transpose(0, 2, 1)
            finite_jac = np.all(np.isfinite(jj.reshape(2, cols.size, -1)), axis=(0, 2))
            ok[cols] = done & np.all(np.isfinite(yy), axis=0) & finite_jac
        return y, J, ok


def _held_stderr(what: str):
    """Keep what SUNDIALS and CasADi print when an integration fails (the solver's
    message and every input of each Function it failed in, tens of lines per arc) off
    the user's terminal: the arc is integrated again or counted as failed, and the
    message goes to the debug log."""

    def then(text: str) -> None:
        if text.strip():
            log.debug("%s: %s", what, text.strip().splitlines()[0])

    return held_stderr(then)


def _mapped(f: ca.Function, n: int, threads: int) -> ca.Function:
    return f.map(n, "thread", threads) if threads > 1 else f.map(n)


def grazing_flags(model: Model, A: np.ndarray, Y: np.ndarray, index: dict, arcs=None) -> np.ndarray:
    """Per arc, a bit mask of :data:`GRAZING_REASONS` (0: not grazing).

    Bit 0: the stop lies within ``GRAZE_NODE`` of a step period of a step node after
    the trigger. Bit 1: under the stick option, the peak speed lies within ``GRAZE_ARM``
    of the threshold (arming is a yes/no decision). Bit 2: at the stop the spring force
    lies within ``GRAZE_HOLD`` of what the contact can hold (the block stays or slips on).
    Bit 3, with ``arcs`` (the :class:`identify.fitting.arcs.ArcFunctions` of ``A``) to
    integrate them again: the stop changes branch with the stick threshold moved by
    :data:`identify.fitting.creep_onset.CREEP_MARGIN` (a creep tail's onset)."""
    n = A.shape[1]
    flags = np.zeros(n, int)
    if not n:
        return flags
    ix = index
    fp = A[ix["fp"]]
    period_ms = 1 / fp / TIME_UNIT
    stopped = Y[4] < 0.5
    with np.errstate(invalid="ignore", divide="ignore"):
        phase = Y[2] / period_ms
        near_node = stopped & (phase > 0.5) & (np.abs(phase - np.round(phase)) < GRAZE_NODE)
        v_stick = A[ix["v_stick"]]
        near_arm = (v_stick > 0) & (np.abs(Y[3] / np.where(v_stick > 0, v_stick, 1.0) - 1) < GRAZE_ARM)
        P = {n_: A[ix[n_]] for n_ in ix if n_ not in ("x0_um", "e0_um", "state0", "fp", "M")}
        step_m = A[ix["step_size"]] * A[ix["step_scale"]]
        x_stop_m = (A[0] + Y[0]) * LENGTH_UNIT
        xp_m = (A[0] + A[1]) * LENGTH_UNIT + step_m * np.floor(phase)
        force = model.spring_force(xp_m - x_stop_m, P)
        # the state at the stop: the end state aged back is not available; the capacity
        # at the horizon bounds it from above (aging only raises it), so use the end state
        state_stop = Y[1]
        cap = model.hold_coefficient(state_stop, x_stop_m, P) * model.normal_load(P)
        near_hold = stopped & (np.abs(np.abs(force) / cap - 1) < GRAZE_HOLD)
    flags |= near_node.astype(int)
    flags |= near_arm.astype(int) << 1
    flags |= near_hold.astype(int) << 2
    if arcs is not None:
        flags |= creep_onset_mask(arcs, A, Y).astype(int) << 3
    return flags


def _forward_slip_ode(model: Model):
    """The slip ODE of :func:`identify.model.symbolic.slip_dae` for a block sliding forward
    (direction +1, speed = v), time-scaled to [0, 1] over the ``duration`` parameter.

    The same equations as the simulator's while v ≥ 0, which holds on an arc up to its
    stop. Written with v instead of |v| and sgn(v) so that their derivative at v = 0,
    where every slip starts, is the one-sided one (1/vc for the rate term) rather than
    the 0 that automatic differentiation gives |v| there: with it, IDAS's Newton matrix
    and the sensitivity equations miss the rate term's stiffness at the start of a slip
    and fail there at tight tolerances."""
    d = slip_dae(model)
    p, u = d["p"], d["u"]
    P = {n: p[i] for i, n in enumerate(d["names"])}
    law = model.law
    x3 = ca.SX.sym("X", 3)
    x = x3[0] * LENGTH_UNIT
    v = x3[1] * SPEED_UNIT
    state = x3[2] * law.state_scale
    e = u * LENGTH_UNIT - x
    N = model.normal_load(P)
    static = model.static_coefficient(state, x, P, ops=ca)
    rate = P["A"] * ca.log1p(v / P["vc"])
    force = model.spring_force(e, P, ops=ca) - (static + rate) * N - model.damping(P) * v
    T = P["duration"] * TIME_UNIT
    ode = T * ca.vertcat(v / LENGTH_UNIT, force / P["mb"] / SPEED_UNIT,
                         law.rate(state, v, P, ops=ca) / law.state_scale)
    return ode, x3, u, p


@functools.cache
def exact_arcs(model: Model, input_names: tuple, reltol: float = EXACT_RELTOL,
               abstol: tuple = EXACT_ABSTOL) -> ExactArcs:
    """Cached :class:`ExactArcs` for ``model``."""
    return ExactArcs(model, input_names, reltol, abstol)

"""The identification NLP: event-based multiple shooting over all runs.

Decision variables
    θ, the free model parameters (scaled: log for positive ones, else value/scale); per
    run optionally an elongation offset; per plateau p the block position x_p (µm); per
    run the phase its slips recur at (fixed at ½ unless ``free_phase``); per slip e the
    position s_e in its trigger interval that its arc starts from (``arc_start="aged"``).
Constraints (continuity of the hybrid trajectory)
    x_{p+1} = x_p + δ_e: slip e's length from its arc (:mod:`identify.fitting.arcs`, the
    symbolic slip model integrated event-aware over the steps it spans);
    s_e = where the previous arc's end state, aged in closed form over the rest, puts
    the capacity in slip e's interval (every slip but a run's first).
Residuals (σ-normalised: the noise model is stated and the covariance follows from it)
    * plateau frames: e_j = Δx·n_j − x_p + offset + noise(σ_run), compressed exactly into
      each plateau's mean (√n·(ē − Δx·n̄ + x − offset)/σ) and the run's pooled
      within-plateau staircase slope (√S_nn·(Δx − Δx̂)/σ); the objective equals the
      frame-level χ² up to a constant;
    * triggers: the contact left by the previous slip's arc, aged in closed form over
      the rest, must put the capacity inside the trigger step's spring-force interval
      [F_s(e − Δx), F_s(e)] (the slip happened at this step, not the one before). The
      position within is uniform: residual √12·(position − φ_run), smooth in the
      parameters where the trigger rule itself is discrete (:func:`trigger_residual`);
      a run's first slip, whose contact comes from the unobserved initial state, gets
      the uniform's √12·(s_e − ½). With ``trigger="interval"`` none of these: the
      position is bounded to [0, 1] instead (the flat likelihood the uniform stands in
      for, consistent as the noise vanishes; :class:`identify.fitting.driver.FitOptions`);
    * creep runs (no resolvable slips): their steady elongation against the steady
      friction at the pull speed.

Arc starts. With ``arc_start="aged"`` (default) an arc starts from the state the
previous arc left, aged over the rest, as in the simulator: at the true parameters the
slip lengths then match a noiseless trace to 0.001-0.007 nm (measured). The start
position passes through :func:`below_top`, so an arc always starts with the force above
the capacity and slips (a state aged above the force would not: a cliff in the
objective). ``arc_start="mid"`` starts every arc mid-interval, valid for any parameters
but off by 0.06-0.35 nm of slip length at the truth (measured; ~|∂δ/∂ψ0|·Δψ/2): far
below a plateau's ~15 nm precision at 90 nm noise, ~10 σ on a noiseless trace.

Derivatives: the residuals and constraints are explicit in w and the arc outputs Y; the
arcs' Jacobians (central differences of the compiled arc) are chain-ruled in a sparse
block-diagonal product. The Gauss–Newton Hessian is JᵣᵀJᵣ.

Where the parts live: the expressions and Functions in :mod:`identify.fitting.nlp_expressions`,
the arcs inside them in :mod:`identify.fitting.arc_callback`, the scaled parameters in
:mod:`identify.fitting.theta_map`; the solvers, the covariance and the trigger refinement
are mixed in from their own modules. :class:`Problem` holds the layout, the trigger
geometry, the numerics and the statistics.
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Mapping, Sequence

import casadi as ca
import numpy as np
import scipy.sparse as sp

from identify import interrupts
from identify.fitting import best_so_far
from identify.fitting.arcs import SHARE_FEAS, SHARE_TOL, SOLVE_REL_STEP, arc_functions
from identify.fitting.convergence import GAVE_UP, Status
from identify.fitting.covariance import Covariance
from identify.fitting.gauss_newton import GaussNewtonSQP
from identify.fitting.ipopt import IpoptSolver
from identify.fitting.mode_sequence.triggers import TriggerRefinement, below_top
from identify.fitting.nlp_expressions import NLPExpressions
from identify.fitting.theta_map import ThetaMap as ThetaMap
from identify.model.params import SPECS, walk_names
from identify.model.scopes import device_of, is_scoped, parse, run_scope_value
from identify.model.symbolic import LENGTH_UNIT, Model

__all__ = ["Problem", "ThetaMap", "MEASUREMENT"]

MEASUREMENT = ("drift_rate", "exposure", "exposure_align", "clock_shift") + walk_names()
"""Camera-side parameters the residuals model (the zero offset is ``free_offset``)."""

log = logging.getLogger(__name__)


# Exact arc Jacobians (identify.fitting.exact_arcs) are shared among arcs whose inputs agree to
# this relative distance: an exact Jacobian costs ~10 forward differences
EXACT_SHARE_TOL = 1e-4


def _same_mask(a, b) -> bool:
    return (a is None and b is None) or (a is not None and b is not None and np.array_equal(a, b))


def _to_csc(M, n_cols: int) -> sp.csc_matrix:
    M = ca.DM(M)
    r, c = M.sparsity().get_triplet()
    return sp.csc_matrix((np.array(M.nonzeros()), (r, c)), shape=(M.size1(), n_cols))


class Problem(GaussNewtonSQP, IpoptSolver, Covariance, TriggerRefinement, NLPExpressions):
    """The NLP over all usable runs for one set of free parameters.

    Fixing a free parameter (profiles) is done with equal bounds, so the same NLP
    serves the fit, the multistart and the profile likelihoods.
    """

    def __init__(self, runs: Sequence, model: Model, values: dict, opts):
        self.runs = list(runs)
        self.model, self.law, self.opts = model, model.law, opts
        self.values = dict(values)
        self.theta = ThetaMap.build(opts.free, dict(opts.bounds))
        self.arcs = arc_functions(model, opts.arc_reltol, opts.arc_abstol)
        self.counter = dict(arc_s=0.0, jac_s=0.0, arc_calls=0, jac_calls=0)
        self.progress = None  # callable(str): the solver's iterations, for long solves
        # callable(iteration, ½χ², ½χ² the Gauss–Newton step promises) -> bool: stop the
        # solve (status GAVE_UP) when it says the rest cannot matter (identify.diagnosis.candidates)
        self.give_up = None
        self._layout()

    @property
    def interval_triggers(self) -> bool:
        """Triggers as the step's force interval (bounds on the start positions), no
        trigger residuals (``FitOptions.trigger = "interval"``)."""
        return self.opts.trigger == "interval"

    @property
    def phases_free(self) -> bool:
        """The runs' trigger phases are variables (``free_phase``; never with the interval,
        where nothing refers to them)."""
        return bool(self.opts.free_phase) and not self.interval_triggers

    # ---------------------------------------------------------------- layout
    def _layout(self):
        ev_runs = [r for r in self.runs if r.kind == "events"]
        self.creep_runs = [r for r in self.runs if r.kind == "creep"]
        n_th = len(self.theta.names)
        n_off = len(self.runs) if self.opts.free_offset else 0
        P = sum(len(r.plateau_n) for r in ev_runs)
        E = sum(len(r.trigger_steps) for r in ev_runs)
        self.n_theta, self.n_off, self.P, self.E = n_th, n_off, P, E
        self.i_off, self.i_x = n_th, n_th + n_off
        self.i_phi = self.i_x + P  # per events run: the phase its slips recur at
        self.i_s = self.i_phi + len(ev_runs)  # per slip: its arc's start position
        idx = {id(r): i for i, r in enumerate(self.runs)}
        pl = dict(run=[], n=[], e=[], s=[], x0=[], t=[])
        ev = dict(run=[], prev=[], step=[], first=[], gap=[])
        dr = {k: [] for k in ("run", "ev", "e", "t", "steps", "phase", "dt", "moving")}
        p0 = 0
        for r in ev_runs:
            ri = idx[id(r)]
            Pr, Er = len(r.plateau_n), len(r.trigger_steps)
            if r.drops and r.drop_e is not None and r.drop_e.size:
                e0 = len(ev["run"])  # the run's first slip, globally
                dr["run"].append(np.full(r.drop_e.size, ri))
                dr["ev"].append(e0 + r.drop_slip)
                for k, v in (("e", r.drop_e), ("t", r.drop_t), ("steps", r.drop_steps), ("phase", r.drop_phase),
                             ("dt", r.drop_dt), ("moving", r.drop_moving)):
                    dr[k].append(np.asarray(v, float))
            pl["run"] += [ri] * Pr
            pl["n"].append(r.plateau_n)
            pl["e"].append(r.plateau_mean_e)
            pl["s"].append(r.plateau_mean_steps)
            pl["x0"].append(r.plateau_level0)
            pl["t"].append(r.plateau_mean_t if r.plateau_mean_t is not None else r.plateau_mean_s / r.fp)
            for i in range(Er):
                ev["run"].append(ri)
                ev["prev"].append(p0 + i)
                ev["step"].append(int(r.trigger_steps[i]))
                ev["first"].append(i == 0)
                ev["gap"].append(int(r.trigger_steps[i + 1] - r.trigger_steps[i]) if i + 1 < Er else 10**9)
            p0 += Pr
        cat = lambda v: np.concatenate(v) if v else np.zeros(0)  # noqa: E731
        self.pl_run = np.array(pl["run"], int)
        self.pl_n, self.pl_mean_e, self.pl_mean_s, self.pl_x0, self.pl_mean_t = (
            cat(pl[k]) for k in ("n", "e", "s", "x0", "t"))
        self.ev_run = np.array(ev["run"], int)
        self.ev_prev = np.array(ev["prev"], int)
        self.ev_step = np.array(ev["step"], float)
        self.ev_first = np.array(ev["first"], bool)
        self.ev_gap = np.array(ev["gap"], int)
        self.ev_M = np.minimum(np.ones(E, int), self.ev_gap)
        rr = self.runs
        self.ev_k = np.array([rr[i].k for i in self.ev_run])
        self.ev_Nb = np.array([rr[i].Nb for i in self.ev_run])
        self.ev_fp = np.array([rr[i].fp for i in self.ev_run])
        self.pl_sigma = np.array([rr[i].sigma for i in self.pl_run])
        # each run's span, the random walk's series is over (1 s where a run has no frames' time)
        self.run_span = np.array([r.span_s if np.isfinite(r.span_s) and r.span_s > 0 else 1.0 for r in rr])
        # frames around the slips, each an observation (RunData.drops)
        self.dr_run = cat(dr["run"]).astype(int)
        self.dr_ev = cat(dr["ev"]).astype(int)
        self.dr_e, self.dr_t, self.dr_steps, self.dr_phase, self.dr_dt, self.dr_moving = (
            cat(dr[k]) for k in ("e", "t", "steps", "phase", "dt", "moving"))
        self.dr_sigma = np.array([rr[i].sigma for i in self.dr_run])
        self.dr_fp = np.array([rr[i].fp for i in self.dr_run])
        self.D = int(self.dr_run.size)
        self.ev_next = np.nonzero(~self.ev_first)[0]  # slips with a predecessor in their run
        self.n_trig = len(self.ev_next)
        self.ev_firsts = np.nonzero(self.ev_first)[0]  # each run's first slip
        self.n_s = E if self.opts.arc_start == "aged" else 0
        self.n_w = self.i_s + self.n_s
        ev_run_ids = sorted(set(self.ev_run.tolist()))
        self.phase_of_run = {ri: k for k, ri in enumerate(ev_run_ids)}
        self.n_phase = len(ev_run_ids)

    # ---------------------------------------------------------------- physics helpers
    def params(self, th) -> dict:
        """Model and measurement parameter values (numbers or MX), the free ones from
        scaled ``th``; per-run and per-device values under their scoped names
        (:mod:`identify.model.scopes`: :meth:`run_params`, :meth:`event_params` apply them)."""
        P = {n: self.values.get(n, SPECS[n].nominal) for n in self.model.parameter_names + MEASUREMENT}
        P.update({n: v for n, v in self.values.items() if is_scoped(n)})
        ops = ca if isinstance(th, ca.MX) else np
        P.update(zip(self.theta.names, self.theta.from_scaled(th, ops=ops)))
        return P

    @property
    def scoped_bases(self) -> tuple:
        """The parameters that take a per-run or per-device value in this problem."""
        names = list(self.theta.names) + [n for n in self.values if is_scoped(n)]
        return tuple(sorted({parse(n)[0] for n in names if is_scoped(n)}))

    def run_device(self, ri: int) -> str:
        return device_of(self.runs[ri])

    def per_run(self, P: Mapping, base: str):
        """``base``'s value in each run (a list, numbers or MX), its scoped values applied."""
        return [run_scope_value(P, base, self.runs[i].name, self.run_device(i)) for i in range(len(self.runs))]

    def per_run_column(self, P: Mapping, base: str, rows: np.ndarray):
        """``base``'s value for each of ``rows`` (run indices) as a CasADi column."""
        col = ca.vertcat(*[v if isinstance(v, ca.MX) else ca.MX(v) for v in self.per_run(P, base)])
        return ca.reshape(col[np.asarray(rows, int).tolist()], -1, 1)

    def run_params(self, P: Mapping, ri: int) -> dict:
        """P as run ``ri`` sees it: its conditions (k, Nb) and its scoped values."""
        out = dict(P, k=self.runs[ri].k, Nb=self.runs[ri].Nb)
        for base in self.scoped_bases:
            out[base] = run_scope_value(P, base, self.runs[ri].name, self.run_device(ri))
        return out

    def event_params(self, P: Mapping, ev=None, ops=np) -> dict:
        """P for the slips ``ev`` (indices, default all): their runs' conditions and scoped
        values as vectors (columns of DM/MX with ``ops=casadi``)."""
        ev = np.arange(self.E) if ev is None else np.asarray(ev, int)
        runs = self.ev_run[ev]
        if ops is ca:
            out = dict(P, k=ca.DM(self.ev_k[ev]), Nb=ca.DM(self.ev_Nb[ev]))
        else:
            out = dict(P, k=self.ev_k[ev], Nb=self.ev_Nb[ev])
        for base in self.scoped_bases:
            if ops is ca:
                out[base] = self.per_run_column(P, base, runs)
            else:
                out[base] = np.array([float(v) for v in self.per_run(P, base)])[runs]
        return out

    def interval(self, x_prev_m, e0, P, ops=np):
        """Spring-force interval of the trigger step, [F_s(e0 − Δx), F_s(e0)] (N)."""
        step = self.model.step(P)
        return self.model.spring_force(e0 - step, P, ops=ops), self.model.spring_force(e0, P, ops=ops)

    def start_state(self, s, x_prev_m, e0, P, ops=np):
        """The contact state whose capacity sits at position s of the trigger interval
        [F_s(e0 − Δx), F_s(e0)], s kept below the top (:func:`below_top`) so that the
        arc starts with the spring force above the capacity: it slips."""
        f_lo, f_hi = self.interval(x_prev_m, e0, P, ops)
        band = P["A"] * ops.log(1 + P["v_stick"] / P["vc"])
        cap = f_lo + below_top(s, ops) * (f_hi - f_lo)
        mu = cap / self.model.normal_load(P) - band - self.model.topography(x_prev_m, P, ops)
        return self.law.state_from_coefficient(mu, P, ops)

    def start_positions(self, w):
        """Each arc's start position in its trigger interval (column, MX or array): the
        shooting variables, or the middle for every slip with ``arc_start="mid"``."""
        if self.n_s:
            return w[self.i_s : self.i_s + self.n_s]
        return ca.DM.ones(self.E, 1) * 0.5 if isinstance(w, ca.MX) else np.full(self.E, 0.5)

    def sync_start_positions(self, w: np.ndarray, passes: int = 2, keep: float = 0.0) -> np.ndarray:
        """w with every start position set to where the previous arc's end puts it (a
        consistent point for the shooting constraints; the end state barely depends on
        the start, the slip rejuvenating the contact, so two passes suffice). A start
        within ``keep`` of that target stays (its arc, integrated before, is not again)."""
        w = np.array(w, float)
        if not self.n_s or not self.n_trig:
            return w
        idx = self.i_s + self.ev_next
        for _ in range(passes):
            Y = self.arcs.evaluate(np.array(self._arc_inputs(w)), self.opts.threads)
            t = np.array(self._s_target_fun(w, Y[:2])).ravel()
            move = np.isfinite(t) & ~(np.abs(t - w[idx]) <= keep)  # an arc that failed keeps its start
            w[idx] = np.where(move, t, w[idx])
        return w

    def settle_arcs(self, w: np.ndarray, keep: float = 0.0) -> np.ndarray:
        """Arcs sized from w's starts, the starts synced to them, and the arcs sized again
        from the synced starts (a lower start slips further and may need a longer
        horizon), synced again if that changed a horizon (``keep``: see
        :meth:`sync_start_positions`)."""
        self.size_arcs(w)
        w = self.sync_start_positions(w, keep=keep)
        M = self.ev_M.copy()
        self.size_arcs(w)
        return self.sync_start_positions(w, keep=keep) if not np.array_equal(M, self.ev_M) else w

    def mid_state(self, x_prev_m, e0, P, ops=np):
        """The contact state whose capacity sits in the middle of the trigger interval."""
        return self.start_state(0.5, x_prev_m, e0, P, ops)

    def position(self, z, x_prev_m, e0, P, ops=np, z_before=None):
        """Where state z puts the capacity inside the trigger's admissible interval (0 .. 1).

        The slip happened at this step and not at the one before: cap(tₙ) < F_s(eₙ) and
        cap(tₙ₋₁) ≥ F_s(eₙ − Δx). The contact ages during the step, by
        Δ = cap(tₙ) − cap(tₙ₋₁) (``z_before``: the state one step earlier), so cap(tₙ)
        lies in [F_s(eₙ − Δx) + Δ, F_s(eₙ)] — a large correction where the contact ages
        fast (rests near τ at high step frequency: measured up to 65 % of the interval).
        """
        f_lo, f_hi = self.interval(x_prev_m, e0, P, ops)
        N = self.model.normal_load(P)
        cap = self.model.hold_coefficient(z, x_prev_m, P, ops) * N
        if z_before is not None:
            gain = (self.model.hold_coefficient(z, x_prev_m, P, ops)
                    - self.model.hold_coefficient(z_before, x_prev_m, P, ops)) * N
            width = f_hi - f_lo
            # keep a sliver of the interval when the aging outruns a whole step
            f_lo = f_lo + (ops.fmin(gain, 0.9 * width) if ops is ca else np.minimum(gain, 0.9 * width))
        return (cap - f_lo) / (f_hi - f_lo)


    # ---------------------------------------------------------------- numerics
    def evaluate(self, w, jac: bool = False):
        """(r, g) or (r, g, Jr, Jg) at w; an arc that cannot be integrated at a trial point
        gives non-finite values (the point is rejected, the fit goes on)."""
        interrupts.check()
        try:
            r = np.array(self._r_fun(w)).ravel()
            g = np.array(self._g_fun(w)).ravel()
            if not jac:
                return r, g
            return r, g, _to_csc(self._jr_fun(w), self.n_w), _to_csc(self._jg_fun(w), self.n_w)
        except RuntimeError:
            interrupts.check()  # (an interrupt inside the arcs' callback comes out as a RuntimeError)
            raise

    def residuals(self, w) -> np.ndarray:
        return self.evaluate(w)[0]

    def arc_inputs(self, w: np.ndarray) -> np.ndarray:
        """The arcs' input matrix at w (n_in × E, :class:`identify.fitting.arcs.ArcFunctions` order)."""
        if not self.E:
            return np.zeros((self.arcs.n_in, 0))
        return np.array(self._arc_inputs(w))

    def arc_outputs(self, w: np.ndarray) -> np.ndarray:
        if not self.E:
            return np.zeros((5, 0))
        return self.arcs.evaluate(np.array(self._arc_inputs(w)), self.opts.threads)

    def initial_w(self, theta_values: Mapping[str, float]) -> np.ndarray:
        """Parameters from ``theta_values``; plateau positions from the frames."""
        w = np.zeros(self.n_w)
        th = self.theta.to_scaled(theta_values)
        w[: self.n_theta] = np.clip(th, self.theta.lo + 1e-9, self.theta.hi - 1e-9)
        w[self.i_x : self.i_x + self.P] = self.pl_x0 / LENGTH_UNIT
        w[self.i_phi : self.i_phi + self.n_phase] = 0.5
        w[self.i_s : self.i_s + self.n_s] = 0.5
        if self.E:
            w = self.settle_arcs(w)  # sized first from the mid-interval starts: they always slip
        return w

    def size_arcs(self, w: np.ndarray) -> int:
        """Grow each arc's span (doubling, up to the next trigger) until its block stops;
        returns how many still move at their horizon."""
        cap = np.minimum(self.ev_gap, self.opts.max_arc_steps)
        at_end = self.arc_outputs(w)[4] > 0.5
        for _ in range(12):
            moving = at_end & (self.ev_M < cap)
            if not moving.any():
                break
            self.ev_M = np.where(moving, np.minimum(2 * self.ev_M, cap), self.ev_M)
            self.build()
            at_end = self.arc_outputs(w)[4] > 0.5
        # (the count is of the arcs as they are now: no evaluation more than the loop's, which
        # matters for a mode-sequence trial, whose set-up sizes the arcs twice)
        return int(at_end.sum())

    def bounds(self, fixed: Mapping[int, float] | None = None):
        lbx = np.full(self.n_w, -np.inf)
        ubx = np.full(self.n_w, np.inf)
        lbx[: self.n_theta], ubx[: self.n_theta] = self.theta.lo, self.theta.hi
        if not self.phases_free:
            # slips recur at the middle of the step interval on average (uniform phase)
            lbx[self.i_phi : self.i_s] = ubx[self.i_phi : self.i_s] = 0.5
        else:
            # a run's common phase lies inside the trigger interval: the interval
            # constraint itself, for what all its slips share
            lbx[self.i_phi : self.i_s], ubx[self.i_phi : self.i_s] = 0.0, 1.0
        if self.interval_triggers:
            # the slip happened at this step: the capacity inside the step's force
            # interval (the plain one: the aging during the step, which position()
            # subtracts from the lower end, would make the bound depend on the parameters)
            lbx[self.i_s : self.i_s + self.n_s], ubx[self.i_s : self.i_s + self.n_s] = 0.0, 1.0
        for i, v in (fixed or {}).items():
            lbx[i] = ubx[i] = v
        return lbx, ubx

    # ---------------------------------------------------------------- solvers
    @contextlib.contextmanager
    def tuned(self, **changes):
        """The problem's options changed for the solves inside the ``with`` block
        (:meth:`identify.fitting.options.FitOptions.evolve`: ``prob.tuned(stall_tol=1.0)``),
        restored after it. Ipopt's own options are taken when its solver is built, so
        changing them here has no effect on a built problem."""
        before = self.opts
        self.opts = before.evolve(**changes)
        try:
            yield self
        finally:
            self.opts = before

    def solve(self, w0: np.ndarray, fixed: Mapping[int, float] | None = None, loose: bool = False) -> dict:
        """Solve from ``w0`` (the Gauss–Newton SQP, or Ipopt). ``loose``: to the
        tolerances a mode-sequence decision needs (``LOOSE_STAT_TOL``, ``LOOSE_FEAS_TOL``),
        for a solution that only decides the next sequence; the result says ``loose``."""
        best_so_far.solving(self)
        res = self._solve(w0, fixed, loose)
        best_so_far.solved(self, res)
        return res

    def _solve(self, w0, fixed, loose):
        self.jacobian_scheme(self.opts.arc_jacobian, SOLVE_REL_STEP)
        if self.opts.solver == "ipopt":
            return self._ipopt_then_sqp(w0, fixed, loose)
        return self._solve_sqp(w0, fixed, loose)

    def _ipopt_then_sqp(self, w0, fixed, loose):
        """Ipopt; where it ends neither converged nor stopped by its caller (stuck, or one of
        its own failures) with iterations left, the SQP goes on from the better of its end
        and its start for the iterations left; its ℓ1-merit line search must lower the merit
        at every step. Measured: after 11 inserted slips (calibration seed 14) Ipopt's full
        steps cycled with period 4, and the SQP converged from there; the fit's last solve on
        central differences (seed 12) ended stuck, and the SQP converged from there."""
        res = self.solve_ipopt(w0, fixed, loose)
        left = self.opts.max_iter - int(res["iterations"])
        if res["success"] or res["status"] in (GAVE_UP, Status.MAXIMUM_ITERATIONS_EXCEEDED.value) or left <= 0:
            return res
        start = res["w"] if np.isfinite(res["f"]) and res["f"] <= self._half_chi2(w0) else w0
        log.info("Ipopt ended %s after %d iterations: the Gauss-Newton SQP goes on (%d iterations left)",
                 res["status"], res["iterations"], left)
        try:
            with self.tuned(max_iter=left):
                more = self._solve_sqp(start, fixed, loose)
        except Exception as err:  # (Ipopt's point stands)
            log.info("the SQP after Ipopt failed: %s", err)
            return res
        ipopt_record = {k: res[k] for k in ("ipopt_status", "restoration_iterations", "warm") if k in res}
        return dict(more, **ipopt_record, iterations=int(res["iterations"]) + int(more["iterations"]),
                    wall_s=res["wall_s"] + more["wall_s"], solver="ipopt", handed_over=res["status"])

    def _half_chi2(self, w) -> float:
        try:
            r = self.residuals(w)
        except Exception:
            return float("inf")
        return 0.5 * float(r @ r) if np.all(np.isfinite(r)) else float("inf")

    def _solve_sqp(self, w0, fixed, loose):
        if not loose:
            return self._solve_gn_resolved(w0, fixed)
        # (only the convergence test: the line search's and the stall rule's tolerances
        # stay, else a solve still far off stalls on small gains, measured at ½χ² 69.9
        # against 16.5 on two short runs)
        self._loose = True
        try:
            return dict(self._solve_gn_resolved(w0, fixed), loose=True)
        finally:
            self._loose = False


    def near_continuity(self, g: np.ndarray) -> np.ndarray:
        """Per arc: whether every constraint its inputs or outputs enter is within
        ``SHARE_FEAS`` of continuity at a point whose constraints are ``g`` (its own slip,
        the previous slip's, which ends on the plateau it starts from, and the start
        positions its end state and its start take part in).

        Why per arc: one slip far off continuity had kept every slip on its own
        differences. Measured on the 10-run speed set, after the first iteration of a
        solve from a staged start 95-97 % of the arcs were within 10 nm while the
        largest violation stayed at 0.02-0.08 µm for two or three iterations more, each
        ~2.4 s on the arcs' own differences against ~0.4 s shared."""
        E = self.E
        a = np.abs(np.asarray(g, float).ravel())
        near = np.ones(E, bool)
        if not a.size or not E or a.max() < SHARE_FEAS:
            return near
        loc = a[:E].copy()
        nx = self.ev_next
        # (a constraint that could not be evaluated is NaN: its arcs are not near, no warning)
        with np.errstate(invalid="ignore"):
            np.maximum.at(loc, nx, a[nx - 1])
            if a.size >= E + nx.size and self.n_s:
                gs = a[E:E + nx.size]
                np.maximum.at(loc, nx, gs)
                np.maximum.at(loc, nx - 1, gs)
            return loc < SHARE_FEAS

    def _cb_jac_shared(self) -> bool:
        """Whether the arcs' Jacobian is by forward differences shared among nearly equal
        arcs now (``SHARE_TOL``; the covariance's shared central ones are not the solver's)."""
        cb = getattr(self, "_cb_jac", None)
        return cb is not None and cb.share is not None and cb.scheme == "forward"

    def _cb_jac_forward(self) -> bool:
        """Whether the arcs' Jacobian is by forward differences now."""
        cb = getattr(self, "_cb_jac", None)
        return cb is not None and cb.scheme == "forward"


    def moving_times(self, w: np.ndarray) -> dict:
        """Per run, how long each slip's block moves after its trigger step (s)."""
        Y = self.arc_outputs(w)
        out: dict = {}
        for e in range(self.E):
            out.setdefault(int(self.ev_run[e]), []).append(Y[2, e] * 1e-3)
        return {k: np.array(v) for k, v in out.items()}

    def slip_ramps(self, w: np.ndarray) -> dict:
        """Per run, the time over which each slip covers its length (s): a half sine of
        its peak speed covers it in (π/2)·slip/peak, which ignores the slow approach to
        the stop speed the moving time includes (measured: 2 ms of moving time for slips
        done in ~0.1 ms on a 20.3 N/m spring, which a ramp over the moving time misreads
        in the frames around the slips)."""
        Y = self.arc_outputs(w)
        out: dict = {}
        for e in range(self.E):
            slip, stop, peak = Y[0, e] * 1e-6, Y[2, e] * 1e-3, Y[3, e]
            d = 0.5 * math.pi * abs(slip) / peak if peak > 0 else stop
            out.setdefault(int(self.ev_run[e]), []).append(min(d, stop))
        return {k: np.array(v) for k, v in out.items()}

    # ---------------------------------------------------------------- statistics
    def chi2_constant(self) -> float:
        """χ² of the frames that the compressed residuals leave out (within plateaus)."""
        return float(sum(r.s_res / r.sigma**2 for r in self.runs if r.kind == "events"))

    def n_observations(self) -> int:
        """Frames, slip triggers and one phase pseudo-observation per run, creep means
        (with the interval encoding the triggers are bounds, not observations)."""
        per_slip = 0 if self.interval_triggers else 1
        return int(sum(r.plateau_n.sum() + per_slip * len(r.trigger_steps) if r.kind == "events" else 1
                       for r in self.runs)) + self.D

    def dof(self) -> int:
        """Degrees of freedom of the χ²: observations less free dimensions (at least 1)."""
        return max(self.n_observations() - self.n_effective(), 1)

    def n_effective(self) -> int:
        """Free dimensions: parameters, offsets, and per events run its first plateau,
        its trigger phase (free_phase) and its first slip's start (arc_start="aged"); the
        other plateaus and starts follow from the constraints."""
        per_run = 1 + self.phases_free
        first_starts = len(self.ev_firsts) if self.n_s else 0
        return self.n_theta + self.n_off + per_run * sum(1 for r in self.runs if r.kind == "events") + first_starts

    def residual_groups(self) -> dict:
        """Index ranges of the residual vector: plateaus, slopes, triggers, creep, the
        frames around the slips (``drops``, with ``FitOptions.drop_frames``), priors."""
        n_slope = sum(1 for r in self.runs if r.kind == "events" and r.s_nn > 0)
        p = self.P
        t0 = p + n_slope
        # phase rows exist with any slip; then the first slips' start positions
        t1 = t0 if self.interval_triggers else \
            t0 + self.n_trig + (self.n_phase if self.E else 0) + (len(self.ev_firsts) if self.n_s else 0)
        t2 = t1 + len(self.creep_runs)
        t3 = t2 + self.D
        return dict(plateaus=(0, p), slopes=(p, t0), triggers=(t0, t1),
                    creep=(t1, t2), drops=(t2, t3), priors=(t3, t3 + len(self.prior_sd())))

    def prior_sd(self) -> dict:
        """The priors' standard deviations (SI) of the free parameters that have one
        (:attr:`identify.fitting.options.FitOptions.priors`), in the order of their rows."""
        pri = dict(self.opts.priors)
        return {n: float(pri[n]) for n in self.theta.names if n in pri}

    def penalised_counts(self, r: np.ndarray, w: np.ndarray | None = None, evaluated=None) -> tuple:
        """(χ² of the data, free dimensions) of residual vector ``r`` (at ``w``): the
        priors' rows taken out of the χ², and the penalised parameters counted by the
        effective degrees of freedom their penalty leaves them (the trace of the hat
        matrix), tr(B⁻¹·B_data) over the parameters, B the information with the priors,
        so that a likelihood-ratio test or AIC compares like with like (a penalised
        spline's usual count). Without priors: (χ² + the plateaus' constant,
        :meth:`n_effective`)."""
        p0, p1 = self.residual_groups()["priors"]
        r = np.asarray(r, float)
        chi2 = float(r[:p0] @ r[:p0]) + float(r[p1:] @ r[p1:]) + self.chi2_constant()
        if p1 == p0:
            return chi2, float(self.n_effective())
        if evaluated is None:
            evaluated = self.evaluate(w, jac=True)
        B = self.information(w, evaluated)
        Jp = evaluated[2][p0:p1][:, : self.n_theta]
        Jp = np.asarray(Jp.toarray() if hasattr(Jp, "toarray") else Jp)
        lam = Jp.T @ Jp
        shrink = float(np.trace(np.linalg.pinv(B, rcond=1e-12, hermitian=True) @ lam))
        return chi2, float(self.n_effective()) - min(max(shrink, 0.0), float(p1 - p0))

    def trigger_runs(self) -> np.ndarray:
        """Run index of each trigger residual (slips, then one phase residual per run)."""
        if not self.E or self.interval_triggers:
            return np.zeros(0, int)
        phase_runs = sorted(self.phase_of_run, key=self.phase_of_run.get)
        first = self.ev_run[self.ev_firsts] if self.n_s else np.zeros(0, int)
        return np.r_[self.ev_run[self.ev_next], np.array(phase_runs, int), first]


    def jacobian_scheme(self, scheme: str, rel_step: float | None = None, share=True, tol: float | None = None):
        """Finite differences of the arcs from now on: ``forward`` or ``central``, with
        relative step ``rel_step`` (None: the arcs' default, 1e-6; :meth:`solve` uses
        ``SOLVE_REL_STEP``). They are shared among arcs whose inputs agree to ``tol``
        (default: ``SHARE_TOL`` for forward ones; central ones, asked for their
        accuracy, only with a ``tol``) if ``share`` (True, or a bool per arc: the arcs
        that may; the others keep their own) and the option ``share_arc_jacobian`` say
        so."""
        cb = getattr(self, "_cb_jac", None)
        may = None
        if isinstance(share, np.ndarray):
            may, share = share, bool(share.any())
        if tol is None and scheme == "forward":
            tol = SHARE_TOL
        elif tol is None and scheme == "exact":
            tol = EXACT_SHARE_TOL
        if not (share and self.opts.share_arc_jacobian):
            tol = None
        own = None if tol is None or may is None or may.all() else ~may
        if cb is not None and ((cb.scheme, cb.rel_step, cb.share) != (scheme, rel_step, tol)
                               or not _same_mask(cb.own, own)):
            cb.scheme, cb.rel_step, cb.share, cb.own = scheme, rel_step, tol, own
            cb.forget()
            if own is not None:
                log.debug("arc differences shared among the %d of %d arcs near continuity",
                          int(own.size - own.sum()), own.size)
        return self

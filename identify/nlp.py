"""The identification NLP: event-based multiple shooting over all runs.

Decision variables
    θ, the free model parameters (scaled: log for positive ones, else value/scale); per
    run optionally an elongation offset; per plateau p the block position x_p (µm); per
    run the phase its slips recur at (fixed at ½ unless ``free_phase``); per slip e the
    position s_e in its trigger interval that its arc starts from (``arc_start="aged"``).
Constraints (continuity of the hybrid trajectory)
    x_{p+1} = x_p + δ_e: slip e's length from its arc (:mod:`identify.arcs`, the
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
      for, consistent as the noise vanishes; :class:`identify.fit.FitOptions`);
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
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
import tempfile
import time
import weakref
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import casadi as ca
import numpy as np
import scipy.sparse as sp

from . import kkt
from .arcs import ArcFunctions, arc_functions, share_groups
from .exact_arcs import exact_arcs
from .model import LENGTH_UNIT, Model
from .params import SPECS

__all__ = ["Problem", "ThetaMap", "MEASUREMENT"]

MEASUREMENT = ("drift_rate", "exposure")
"""Camera-side parameters the residuals model (the zero offset is ``free_offset``)."""

log = logging.getLogger(__name__)


STAT_TOL = 1e-4  # ½χ² the Gauss–Newton model may still promise at convergence
# constraint violation at convergence (µm of slip length): 1 pm, 0.02 σ of a noiseless
# trace's print precision, and above the arcs' own integration noise (reltol 1e-6 of a
# ~0.5 µm slip: the adaptive steps make the slip length jump by ~0.5 pm between nearby
# inputs, which held the solver at |g| ≈ 2e-7 for twenty iterations at 1e-7)
FEAS_TOL = 1e-6
PROGRESS_EVERY_S = 30.0  # a solve that runs longer reports its iterations this often
# a solve that gains less than stat_tol of merit in STALL_ITERS accepted iterations in
# a row (rejected ones, which raise the damping, neither count nor reset) has stalled
# (measured: 100 iterations at alpha ~1e-4, |g| stuck at 1 nm on one slip whose arc
# Jacobian was wrong in sign). It is converged within tolerance (STALLED) if the
# Gauss-Newton model puts its solution within STALL_TOL of 1/2 chi2 (parameters within
# ~0.14 standard errors: 1/2 chi2 changes by 1/2 over one) and its constraints hold to
# STALL_FEAS, 0.1 nm of slip length (1e-4 of a slip, ~1e-2 of a plateau's precision at
# 90 nm; measured, a solve converged in all but name stalled at |g| = 1.9 pm, the arcs'
# integration noise, above FEAS_TOL); else it stops as "Stalled"
STALL_ITERS = 4
# the damping ladder ends at once (judged as at its end) when the rest of it could change
# what a rejected step promises by less than this share of the merit's slope along it
# (Problem._damping_reach): the Levenberg–Marquardt term acts on the parameter block
# only, and a step the constraints drive (an arc on a kink asking its states to move)
# comes back all but the same at every damping. Measured on the 8-run diagnosis
# baseline: twelve ladders climbed to lm = 1e8, none accepted, ~25 s of its 63; their
# first rungs' reach 0.005-0.022, below 0.02 by lm = 0.1. The smallest reach seen before
# an accepted rung: 0.099 (a load-offset refit on four short runs, lm = 10 -> 100); on
# the 10-run speed benchmark every rung's 0.11-0.46.
LADDER_REACH = 0.02
# ... and only when the trial points would move by less than this share of the step: a
# parameter step along a flat direction changes the model little and the function perhaps
# much (the baseline's ladders above: 0.022-0.042 on the rungs where they end)
LADDER_STEP = 0.1
MAX_SOC = 4  # second-order corrections tried for a rejected full step (Ipopt's max_soc)
STALL_TOL = 0.01
# A solve also ends, converged within tolerance (STALLED), once FLAT_ITERS iterations in a
# row, accepted or rejected, at points feasible to FEAS_TOL have not brought ½χ² down by
# STALL_TOL from where it stood at the first of them: ½χ² is then known to STALL_TOL.
# Why: there the Gauss–Newton model's promises are the arcs' Jacobian noise, not gains.
# Measured on the 5-run speed benchmark (2026-11-25, its log): the fresh solve after
# inserting 7 slips reached ½χ² 1122.5341 at iteration 17 (|g| 4e-8 µm), then spent
# iterations 18-33 (~100 s of a 234 s fit) on steps that promised 0.01-0.09 and gave
# nothing: accepted ones moved ½χ² by ±0.016, the central Jacobian's steps were rejected
# rung after rung, and it ended at 1122.5338 (the stall rule's "within tolerance"). The
# rejections count: each rung of the damping ladder there cost ~5 s of line search.
FLAT_ITERS = 4
# ... and it fires only on an undamped step whose own move of the model, ½‖Jᵣd‖², is below
# this (10 × STALL_TOL; the tail above: 0.003-0.09), so a step that still promises much
# and fails its line search is left to the damping ladder and the stall judgement
FLAT_PROMISE = 0.1
STALL_FEAS = 1e-4
# Converged also (without waiting on the stall rule) when, at a point feasible to
# STALL_FEAS, the undamped step would move the model's predictions by less than NEAR_TOL
# of ½χ² (the parameters by < 0.045 standard errors in any direction) and change ½χ²
# itself by less than STALL_TOL (the value, restoring continuity included, as exact as
# a likelihood ratio needs). Why: with FEAS_TOL alone the solve went on while the
# continuity fell from 6e-6 to 8e-8 µm, the forward-difference Jacobian's noise moving
# the model by ~0.016 and back each iteration. Measured on the 10-run speed benchmark
# (its log, 2026-11-24): its first solve met this at iteration 12 and went on to 14 (a
# central-difference Jacobian included, ~23 s); the solve after moving three triggers met
# it at 4 and went on to 7 (~12 s).
NEAR_TOL = 1e-3
# ... and STAT_TOL's test too (not the loose one: it only decides a mode sequence) only
# when the step would move the model by less than this share of ½χ² itself. The
# tolerances are statistical, in units of the noise the data claim. Data fitted far
# below their noise (noiseless ones: ½χ² ~1e-4) have no tail of Jacobian noise, and a
# step that would remove much of what is left is real progress. Measured: with the
# arcs' differences shared (SHARE_TOL), the noiseless test fit's interval solve stopped
# at ½χ² 2.9e-4 on a step promising 2.9e-4, τ 2.2e-4 off; with this rule, 7e-5 off
# (test_noiseless_data_recover_every_parameter_to_1e4). A noisy fit's ½χ² is ~n/2,
# hundreds, where the rule never binds.
NEAR_SHARE = 0.1
STALLED = "Stalled_Within_Tolerance"
GAVE_UP = "Stopped_Cannot_Matter"  # status of a solve its give_up callback stopped
# status of a solve that starts where a free parameter's last bit (its scaled value, at
# least 1, times machine epsilon) moves the residuals by more than one noise unit: the model is
# not numerically differentiable there, and no step from a linearisation can be trusted.
# Measured on the diagnosis benchmark's logistic-law refit from the exponential baseline
# (2026-11-25): ∂(½χ²)/∂μmin = -4.5e22, the Gauss–Newton diagonal 8e39 against 1e7-3e8
# for the other parameters (the logistic rest's derivative at a contact whose seed a
# slip wiped grows as e^(t/τ)); its 13 rejected rungs took 20 s for no step.
NOT_DIFFERENTIABLE = "Not_Differentiable"
GIVE_UP_FEAS = 1e-3  # (µm) the ½χ² of a point further from feasible says little
# difference step of the arcs while the solver iterates. The arcs' integration noise
# (~0.2 pm of slip length, adaptive steps) makes 1e-6 too small: measured, one arc's
# d(slip)/d(state0) came out +0.14 against -0.082 (-0.081 at 1e-4, -0.082 at 1e-3),
# and the solve sat at |g| = 1 nm on that slip for 100 iterations. Three two-run data
# sets of 2000 steps (forward differences, the stall rule): 1e-6 ended at worse points
# in two (chi2/2 191 against 95.8; mu_min -9.8 % against -0.05 %); 1e-5 and 1e-4 at the
# same estimates in all three; on the 15 um pair of the tests 1e-5 stalled at chi2/2
# 16.45 from both starts, 1e-4 converged to 15.15.
SOLVE_REL_STEP = 1e-4
# While the solver iterates on forward differences, arcs whose inputs agree to this
# relative distance share one arc's differences (identify.arcs.share_groups): a run's
# slips repeat nearly one cycle, so most of the 6 integrations per slip and iteration
# were spent on derivatives already known to within the differences' own error.
SHARE_TOL = 1e-3
# ... only among arcs whose constraints are within this violation of continuity (µm;
# Problem.near_continuity): further out the arcs' inputs are not yet one cycle, and the
# steps are long and ill-conditioned enough that the shared differences change where
# they lead. Measured with the whole problem's largest violation as the gate: from
# |g| < 0.1 µm, a noiseless fit from 10 % off went to another basin (the test
# test_noiseless_data_recover_every_parameter_to_1e4), and a diagnosis test's baseline
# (load offset withheld) crawled at |g| ~0.02 µm to the iteration limit, where each
# arc's own differences had not; at 1e-2 µm both end as they did.
SHARE_FEAS = 1e-2
# A full step on shared differences that fails is taken again on each arc's own, which the
# rest of the solve keeps, unless that step too needs the line search (or damping): then
# the constraints' curvature stopped it, not the sharing, and the solve shares again, its
# shared steps from then on backtracked like any other while the largest violation is at
# least SHARE_FEAS (nearer, a failed full step is checked again). Measured on
# the 5-run speed set: its first solve failed a shared full step at |g| ~0.1 µm and the
# own-differences step after it took α = 0.25; the solve then spent 5 more iterations,
# and the solve after the inserted slips 11, on each arc's own differences (~1.5 s each
# against ~0.5 s shared) while |g| stayed above 0.02 µm. Sharing again without trusting
# failed the next shared step each time: four own-differences checks in a row, each
# backtracked to α 0.06-0.12 as the shared steps would have been.
# A solve that stalls or fails its line search on forward differences is solved once more
# on central ones (Problem.solve) only if it ended within this violation of continuity
# (µm). Forward differences err by a small share of each Jacobian row (95th percentile
# 6e-3 relative, measured), so further out the linearised constraints are off by a
# small share of a violation the step is asked to remove, and it is the constraints'
# curvature, not the differences, that stops the line search. Measured on the 8-run
# diagnosis benchmark's logistic-law refit (2026-11-25): from its staged start (½χ² 5.8e8,
# |g| 0.23 µm) the forward solve climbed the damping ladder to the top in 13 rejected
# iterations, and the central solve after it did the same in 13 more: 26 s for one point.
CENTRAL_RESOLVE_FEAS = 1e-2
# A solve whose solution only decides the next mode sequence (the fit's first solve,
# each round's after moving triggers or inserting slips: identify.fit.decide_sequence)
# stops once its step would move the model by less than LOOSE_STAT_TOL of ½χ² at a point
# feasible to LOOSE_FEAS_TOL µm (0.1 nm, ~1e-3 of the camera noise): ½χ² is then known to
# ~0.1-0.3 (measured: 0.07 between |g| 2e-4 and 6e-6 µm on each arc's own differences;
# on shared ones, SHARE_TOL, the steps moved ½χ² by 0.05-0.22 to and fro for five
# iterations, ~5.5 s of the 10-run fit, at 0.05), against sequence decisions that need a
# change of 1. The sequence settled, the solution is solved to the full tolerances.
# Why: each full solve ended with 4-6 iterations that took the continuity from ~1e-5 to
# 1e-7 µm while the forward-difference Jacobian's noise moved the parameters by ~0.1 σ
# to and fro (docs/engineering-notes.md, chord iterations), ~2.5 s each on the 10-run
# speed benchmark, where the first two solves' results are replaced anyway.
LOOSE_STAT_TOL = 0.25
LOOSE_FEAS_TOL = 1e-4
COVARIANCE_REL_STEP = 1e-4  # secant step of the arc differences for the covariance (see central_differences)
# Arcs whose inputs agree to this relative distance share one arc's central differences
# for the covariance (identify.arcs.share_groups): at the secant step itself, so a group
# is no wider than the secant that smooths a kinked arc. Measured at the 10-run speed
# set's solution: 142 of 1093 arcs integrated, 2.8 s -> 0.4 s, and the standard errors
# (robust, cluster, model) within 0.17 % of those on each arc's own differences (at 1e-3:
# 61 arcs, within 0.2 %).
COVARIANCE_SHARE_TOL = 1e-4
# Exact arc Jacobians (identify.exact_arcs) are shared among arcs whose inputs agree to
# this relative distance: an exact Jacobian costs ~10 forward differences
EXACT_SHARE_TOL = 1e-4


@dataclass
class ThetaMap:
    """Free parameters <-> scaled decision variables (log or linear)."""

    names: tuple
    scale: np.ndarray
    log: np.ndarray
    lo: np.ndarray  # scaled bounds
    hi: np.ndarray

    @classmethod
    def build(cls, names, bounds: Mapping[str, tuple]):
        scale, logs, lo, hi = [], [], [], []
        for n in names:
            s = SPECS[n]
            b = bounds.get(n, (s.lower, s.upper))
            scale.append(s.scale)
            use_log = s.log and b[0] > 0
            logs.append(use_log)
            if use_log:
                lo.append(math.log(b[0] / s.scale))
                hi.append(math.log(b[1] / s.scale))
            else:
                lo.append(b[0] / s.scale)
                hi.append(b[1] / s.scale)
        return cls(tuple(names), np.array(scale), np.array(logs, bool), np.array(lo), np.array(hi))

    def to_scaled(self, values: Mapping[str, float]) -> np.ndarray:
        v = np.array([values[n] for n in self.names], float)
        return np.where(self.log, np.log(np.maximum(v, 1e-300) / self.scale), v / self.scale)

    def from_scaled(self, th, ops=np):
        return [self.scale[i] * ops.exp(th[i]) if self.log[i] else self.scale[i] * th[i]
                for i in range(len(self.names))]

    def jacobian_diag(self, th: np.ndarray) -> np.ndarray:
        """d value / d scaled, per parameter."""
        vals = np.array(self.from_scaled(th))
        return np.where(self.log, vals, self.scale)


class _ArcCallback(ca.Callback):
    """Arc values (5 × E) or Jacobians (2 × n_in·E) for all slips, memoised on the input
    matrix: the solver asks for them at the same point from several Functions."""

    def __init__(self, name: str, arcs: ArcFunctions, n_events: int, threads: int, jac: bool,
                 counter: dict, rows=None, scheme: str = "central", jac_callback=None):
        ca.Callback.__init__(self)
        self.jac_callback = jac_callback  # (values only) the Jacobian callback: see has_jacobian
        self.arcs, self.E, self.threads, self.jac = arcs, n_events, threads, jac
        self.counter, self.rows, self.scheme, self.rel_step, self.share = counter, rows, scheme, None, None
        self.own = None  # with ``share``: arcs that keep their own differences (bool per arc)
        self._key: bytes | None = None
        self._val = None
        self.construct(name, {})

    def get_n_in(self):
        return 1

    def get_n_out(self):
        return 1

    def get_sparsity_in(self, i):
        return ca.Sparsity.dense(self.arcs.n_in, self.E)

    def get_sparsity_out(self, i):
        return ca.Sparsity.dense(2, self.arcs.n_in * self.E) if self.jac else ca.Sparsity.dense(5, self.E)

    def _exact(self, A: np.ndarray) -> np.ndarray:
        """Exact arc Jacobians (:mod:`identify.exact_arcs`), in the layout of
        :meth:`ArcFunctions.evaluate_jacobian`; an arc the exact route cannot do (its
        IDAS run or stop refinement failed) takes its central differences instead."""
        arcs = self.arcs
        rows = list(range(arcs.n_in)) if self.rows is None else list(self.rows)
        Y = arcs.evaluate(A, self.threads)  # (remembered: the solver asked for the values first)
        n = A.shape[1]
        reps, inverse = np.arange(n), None
        if self.share is not None and n > 1:
            reps, inverse = share_groups(A, Y, rows, arcs.typical, self.share, own=self.own)
        B, YB = A[:, reps], Y[:, reps]
        _, J, ok = exact_arcs(arcs.model, arcs.input_names).jacobian(B, YB, rows, self.threads)
        if not ok.all():
            _, Jfd = arcs.evaluate_jacobian(B[:, ~ok], self.threads, rows=rows, scheme="central",
                                            rel_step=SOLVE_REL_STEP)
            J[:, :, ~ok] = Jfd.reshape(2, int((~ok).sum()), arcs.n_in).transpose(0, 2, 1)
        if inverse is not None:
            J = J[:, :, inverse]
        return J.transpose(0, 2, 1).reshape(2, n * arcs.n_in)

    def has_jacobian(self):
        # the values' Jacobian is the Jacobian callback's, laid out per output entry:
        # solvers that differentiate the NLP themselves (Ipopt's Lagrangian gradient)
        # see the same arc derivatives as the explicit Jr, Jg
        return not self.jac and getattr(self, "jac_callback", None) is not None

    def get_jacobian(self, name, inames, onames, opts):
        E, n_in = self.E, self.arcs.n_in
        A = ca.MX.sym("A", n_in, E)
        out = ca.MX.sym("Y", 5, E)
        JA = ca.MX(_blockdiag_sparsity(2, n_in, E), ca.vec(self.jac_callback(A)))  # (2E × n_in·E)
        # rows 2e + r of JA are entries 5e + r of vec(Y)
        rows = (5 * np.arange(E)[:, None] + np.arange(2)[None, :]).ravel()
        S = ca.DM(ca.Sparsity.triplet(5 * E, 2 * E, rows.tolist(), list(range(2 * E))), 1.0)
        return ca.Function(name, [A, out], [ca.mtimes(S, JA)], inames, onames, opts)

    def eval(self, arg):
        A = np.array(arg[0])
        key = A.tobytes()
        if key != self._key:
            t0 = time.perf_counter()
            if self.jac and self.scheme == "exact":
                self._val = self._exact(A)
                self.counter["jac_s"] += time.perf_counter() - t0
                self.counter["jac_calls"] += 1
            elif self.jac:
                self._val = self.arcs.evaluate_jacobian(A, self.threads, rows=self.rows, scheme=self.scheme,
                                                        rel_step=self.rel_step, share=self.share,
                                                        own=self.own)[1]
                self.counter["jac_s"] += time.perf_counter() - t0
                self.counter["jac_calls"] += 1
            else:
                self._val = self.arcs.evaluate(A, self.threads)
                self.counter["arc_s"] += time.perf_counter() - t0
                self.counter["arc_calls"] += 1
            self._key = key
        return [self._val]


def trigger_residual(s, phase=0.5):
    """Residual of a trigger at position s ∈ [0, 1] of its admissible interval.

    The position is uniform over the interval. But slips of a run recur at nearly the
    same phase of the step interval (a deterministic cycle locks it), so their errors
    are one shared error, not many independent ones: a Gaussian surrogate √12·(s − ½)
    per slip pulled every trigger to mid-interval and put μmax 9σ low on synthetic data.
    The NLP therefore gives each run a phase φ (a random effect): √12·(s − φ) per slip —
    what varies within the run, e.g. with the rest — and √12·(φ − ½) once per run.
    (Measured alternatives: exact interval constraints stalled the solver and gave a
    useless Gauss–Newton covariance; flat-bottomed residuals diverged.)
    """
    return math.sqrt(12) * (s - phase)


START_SCALE_UM = 1e-3  # slip length per unit of start position (measured: 0.35 nm for 0.3)
START_MARGIN = 0.02  # fraction of the trigger interval an arc's start keeps below its top


def below_top(s, ops=np, eps: float = START_MARGIN):
    """s itself up to 1 − 2ε, then bent (C¹) to stay below 1 − ε.

    An arc started from a capacity at or above the spring force would not slip (a cliff
    in the objective), yet a true trigger can lie anywhere in [0, 1]: the start is exact
    for every position up to 1 − 2ε, and off by less than ε of the interval above.
    """
    u = (1 - s) / eps
    if ops is ca:
        g = 1 + ca.fmin(ca.fmax(u, 0), 2) ** 2 / 4 + ca.fmax(u - 2, 0)
    else:
        g = 1 + np.clip(u, 0, 2) ** 2 / 4 + np.maximum(u - 2, 0)
    return 1 - eps * g


def _l1(nu, g) -> float:
    """The ℓ1 merit's constraint term Σᵢ νᵢ|gᵢ| (ν one weight, or one per constraint)."""
    return float(np.sum(nu * np.abs(g)))


def _same_mask(a, b) -> bool:
    return (a is None and b is None) or (a is not None and b is not None and np.array_equal(a, b))


def _kkt_solve(H, Jg, grad, g, free):
    """Solution (step on ``free``, then multipliers) of the linearised least-squares
    problem's KKT system; RuntimeError when it is singular (sparse LU)."""
    K = sp.bmat([[H[free][:, free], Jg[:, free].T], [Jg[:, free], None]], format="csc")
    return kkt.solve(K, np.r_[-grad[free], -g])


class _IpoptLog:
    """Ipopt's iteration log in a temporary file, read for what CasADi's stats leave out:
    which iterations were restoration ones (Ipopt marks their number with an ``r``).
    Ipopt appends every solve of one nlpsol to the file; each solve reads its part."""

    _ROW = re.compile(r"^\s*\d+(r?)\s+[-+0-9.]")

    def __init__(self):
        fd, self.path = tempfile.mkstemp(prefix="nanofrictor-ipopt-", suffix=".log")
        os.close(fd)
        weakref.finalize(self, _unlink, self.path)

    def mark(self) -> int:
        try:
            return os.path.getsize(self.path)
        except OSError:
            return 0

    def restoration_iterations(self, mark: int) -> int:
        try:
            with open(self.path, errors="replace") as fh:
                fh.seek(mark)
                text = fh.read()
        except OSError:
            return 0
        return sum(1 for line in text.splitlines() if (m := self._ROW.match(line)) and m.group(1))


def _unlink(path: str) -> None:
    with contextlib.suppress(OSError):
        os.unlink(path)


class _IpoptConvergence(ca.Callback):
    """Ipopt's iteration callback: stops the solve where the Gauss–Newton SQP would
    call it converged (:meth:`Problem.solve_gn`'s statistical test): at a point
    feasible to ``feas_tol`` µm whose full Gauss–Newton step would move the model's
    predictions by less than ``stat_tol`` in ½χ² (the parameters by < 0.015 σ).

    The test needs the arcs' Jacobian at the iterate, which Ipopt asks for next anyway
    (the arcs' callback remembers it), so it costs one KKT solve per iteration."""

    def __init__(self, problem: Problem):
        ca.Callback.__init__(self)
        self.problem = problem
        self.nx, self.ng = problem.n_w, problem.n_g
        self.converged = self.status = self.best = None
        self.since = 0
        self.lbx = self.ubx = None
        self.stat_tol, self.feas_tol = STAT_TOL, FEAS_TOL
        self.construct("ipopt_convergence", {})

    def start(self, lbx, ubx, stat_tol: float, feas_tol: float):
        self.lbx, self.ubx, self.stat_tol, self.feas_tol = lbx, ubx, stat_tol, feas_tol
        self.converged, self.status = None, None
        self.best, self.since = None, 0  # best ½χ² so far; iterations since it fell by stat_tol

    def get_n_in(self):
        return ca.nlpsol_n_out()

    def get_n_out(self):
        return 1

    def get_name_in(self, i):
        return ca.nlpsol_out(i)

    def get_name_out(self, i):
        return "ret"

    def get_sparsity_in(self, i):
        n = ca.nlpsol_out(i)
        size = {"x": self.nx, "lam_x": self.nx, "g": self.ng, "lam_g": self.ng, "f": 1}.get(n, 0)
        return ca.Sparsity.dense(size, 1)

    def eval(self, arg):
        w = np.array(arg[0], float).ravel()
        try:
            r, g, Jr, Jg = self.problem.evaluate(w, jac=True)
        except RuntimeError:
            return [0]
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(g))):
            return [0]
        feas = float(np.abs(g).max()) if g.size else 0.0
        if feas >= self.feas_tol:
            log.debug("Ipopt iterate: |g| %.2e", feas)
            return [0]
        d, _, _ = _bounded_step((Jr.T @ Jr).tocsc(), Jg, Jr.T @ r, g, w, self.lbx, self.ubx, self.lbx == self.ubx)
        if d is None or not np.all(np.isfinite(d)):
            return [0]
        dr = Jr @ d
        moves = 0.5 * float(dr @ dr)
        log.debug("Ipopt iterate: |g| %.2e, the Gauss-Newton step moves 1/2 chi2 by %.3g", feas, moves)
        f = float(np.asarray(arg[1]).ravel()[0])
        if self.best is None or f < self.best - self.stat_tol:
            self.best, self.since = f, 0
        else:
            self.since += 1
        if moves < self.stat_tol:
            self.converged, self.status = w, "Solve_Succeeded"
            return [1]
        if self.since >= STALL_ITERS and feas < self.problem.stall_feas and moves < self.problem.stall_tol:
            # the iterates no longer gain and the linearisation puts the solution within
            # the stall tolerance: the SQP's Stalled_Within_Tolerance (a step along the
            # model crosses one of the arcs' kinks, where no line search gains)
            self.converged, self.status = w, STALLED
            return [1]
        return [0]


def _bounded_step(H, Jg, grad, g, w, lbx, ubx, fixed_mask):
    """The step of the linearised problem (Hessian ``H``) with the variables at a bound
    the step pushes outwards held there: (d, multipliers, indices of the free
    variables); d None when the KKT system is singular."""
    at_lo, at_hi = w <= lbx + 1e-12, w >= ubx - 1e-12
    hold = fixed_mask | (at_lo & (grad > 0)) | (at_hi & (grad < 0))
    d, lam, free = None, None, np.nonzero(~hold)[0]
    for _ in range(20):
        free = np.nonzero(~hold)[0]
        try:
            sol = _kkt_solve(H, Jg, grad, g, free)
        except RuntimeError:
            return None, None, free
        d = np.zeros(len(w))
        d[free] = sol[: len(free)]
        lam = sol[len(free):]
        out = ((at_lo & (d < 0)) | (at_hi & (d > 0))) & ~hold
        if not out.any():
            break
        hold |= out
    return d, lam, free


def _blockdiag_sparsity(rows: int, cols: int, E: int) -> ca.Sparsity:
    """E dense rows × cols blocks on the diagonal (column-major nonzeros = vec of the
    rows × cols·E matrix of the blocks side by side)."""
    r = np.tile(np.arange(rows), cols * E) + np.repeat(np.arange(E), rows * cols) * rows
    c = np.repeat(np.arange(cols * E), rows)
    return ca.Sparsity.triplet(rows * E, cols * E, r.tolist(), c.tolist())


def _to_csc(M, n_cols: int) -> sp.csc_matrix:
    M = ca.DM(M)
    r, c = M.sparsity().get_triplet()
    return sp.csc_matrix((np.array(M.nonzeros()), (r, c)), shape=(M.size1(), n_cols))


SINGULAR_AMPLIFICATION = 1e12
"""The covariance's bread (the constrained Gauss–Newton system K) is taken as unable to fix
a parameter when its solution for that parameter's unit vector is this many times larger
than 1/max|K|: the direction then lies in K's numerical null space, where the solution is
rounding, and the sandwich's J·X does not even see it (it reported μmax ± 0.03 % from
three creep means, whose information has rank 1 in four parameters). Measured: the demo's
8-run fit, μmin and A correlated at −0.9994, reaches 1.5e3 over the variables (1.4e6 with
the constraints' multipliers, which are left out of the test)."""


def _information_solve(K, rhs: np.ndarray, n_primal: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """K·X = rhs for the covariance's bread, and per right-hand side (a parameter's unit
    vector) whether the information cannot fix it: where K is singular, a parameter is
    undetermined unless its unit vector lies in K's range (then the least-norm solution
    gives the variance of that estimable parameter), and wherever the solution's first
    ``n_primal`` rows (the variables; the rest are the constraints' multipliers) are of
    the size of rounding in K's null space (:data:`SINGULAR_AMPLIFICATION`)."""
    try:
        sol = kkt.solve(K, rhs)
        ok = np.all(np.isfinite(sol))
    except RuntimeError:
        ok = False
    norm_k = float(np.abs(K.data).max()) if K.nnz else 0.0
    undetermined = np.zeros(rhs.shape[1], bool)
    if not ok:
        Kd = K.toarray()
        if not np.all(np.isfinite(Kd)):
            return np.full(rhs.shape, np.nan), np.ones(rhs.shape[1], bool)
        sol = np.linalg.lstsq(Kd, rhs, rcond=1e-12)[0]
        resid = np.abs(Kd @ sol - rhs).max(axis=0)
        undetermined |= resid > 1e-6 * (norm_k * np.abs(sol).max(axis=0) + 1.0)
    with np.errstate(invalid="ignore", over="ignore"):
        amp = norm_k * np.abs(sol[:n_primal]).max(axis=0)
    undetermined |= ~np.isfinite(amp) | (amp > SINGULAR_AMPLIFICATION)
    return sol, undetermined


class Problem:
    """The NLP over all usable runs for one set of free parameters.

    Fixing a free parameter (profiles) is done with equal bounds, so the same NLP
    serves the fit, the multistart and the profile likelihoods.
    """

    # the solver's tolerances (module constants, above); a candidate refit of the
    # diagnosis overrides them on its instance (identify.candidates)
    stat_tol, feas_tol = STAT_TOL, FEAS_TOL
    ladder_reach, ladder_step = LADDER_REACH, LADDER_STEP
    stall_tol, stall_feas = STALL_TOL, STALL_FEAS
    near_tol = NEAR_TOL
    give_up_feas = GIVE_UP_FEAS  # the give_up callback is asked only this close to continuity (µm)
    flat_iters = FLAT_ITERS  # (0: the rule off)
    # the same kind of callback, asked wherever give_up is not (away from continuity, or
    # when there is no give_up) (identify.candidates._at_magnitude: a stop only when decisive)
    give_up_far = None
    _loose = False  # the solve in progress stops at LOOSE_STAT_TOL, LOOSE_FEAS_TOL (solve(loose=True))

    def __init__(self, runs: Sequence, model: Model, values: dict, opts):
        self.runs = list(runs)
        self.model, self.law, self.opts = model, model.law, opts
        self.values = dict(values)
        self.theta = ThetaMap.build(opts.free, dict(opts.bounds))
        self.arcs = arc_functions(model, opts.arc_reltol, opts.arc_abstol)
        self.counter = dict(arc_s=0.0, jac_s=0.0, arc_calls=0, jac_calls=0)
        self.progress = None  # callable(str): the solver's iterations, for long solves
        # callable(iteration, ½χ², ½χ² the Gauss–Newton step promises) -> bool: stop the
        # solve (status GAVE_UP) when it says the rest cannot matter (identify.candidates)
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
        p0 = 0
        for r in ev_runs:
            ri = idx[id(r)]
            Pr, Er = len(r.plateau_n), len(r.trigger_steps)
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
        scaled ``th``."""
        P = {n: self.values.get(n, SPECS[n].nominal) for n in self.model.parameter_names + MEASUREMENT}
        ops = ca if isinstance(th, ca.MX) else np
        P.update(zip(self.theta.names, self.theta.from_scaled(th, ops=ops)))
        return P

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

    def _camera_terms(self, P, step):
        """What the camera adds to each plateau's mean elongation (m).

        Drift: + drift_rate·t̄_p (t̄_p the plateau's mean frame time).
        Motion blur: a frame at step phase u (fraction of the step interval since the
        last step) averaging e over an exposure T centred on it reads, with h = T·fp/2
        (T·fp ≤ 1),  e(t) + Δx·[max(0, u + h − 1) − max(0, h − u)]/(2h): a part of the
        next step when the window reaches it, minus a part of the current one when the
        window starts before it. Frames placed symmetrically in the step interval (the
        usual two frames per step at u = ¼, ¾) cancel in the plateau mean: the blur then
        shows only in frames taken during a slip, which the plateaus leave out.
        """
        out = ca.DM.zeros(self.P, 1)
        if "drift_rate" in self.theta.names or self.values.get("drift_rate", 0.0) != 0.0:
            out = out + P["drift_rate"] * ca.DM(self.pl_mean_t)
        if "exposure" in self.theta.names or self.values.get("exposure", 0.0) != 0.0:
            rows = []
            for r in self.runs:
                if r.kind != "events":
                    continue
                u = ca.DM(r.frame_phases).T  # 1 × U
                h = P["exposure"] * r.fp / 2
                b = (ca.fmax(0, u + h - 1) - ca.fmax(0, h - u)) / (2 * h + 1e-30)
                counts = ca.DM(r.phase_counts)  # plateaus × U
                rows.append(ca.mtimes(counts, b.T) / ca.DM(np.maximum(r.plateau_n, 1)))
            out = out + step * ca.vertcat(*rows)
        return out

    # ---------------------------------------------------------------- symbolic NLP
    def _symbolic(self, w, Y):
        """Arc inputs A(w), residuals r(w, Y), constraints g(w, Y); Y = (slip, end state)."""
        th = w[: self.n_theta]
        P = self.params(th)
        E = self.E
        x_um = w[self.i_x : self.i_x + self.P]
        step = self.model.step(P)
        res = []
        if self.P:
            off = w[self.i_off + self.pl_run] if self.n_off else 0.0
            model_e = step * ca.DM(self.pl_mean_s) - x_um * LENGTH_UNIT + off * LENGTH_UNIT
            model_e = model_e + self._camera_terms(P, step)
            res.append(ca.sqrt(ca.DM(self.pl_n)) * (ca.DM(self.pl_mean_e) - model_e) / ca.DM(self.pl_sigma))
        drift = P["drift_rate"]
        for r in self.runs:
            if r.kind == "events" and r.s_nn > 0:
                # a drift adds drift/fp per step to the staircase slope
                res.append(math.sqrt(r.s_nn) * (step + drift / r.fp - r.slope_hat) / r.sigma)
        A, g = None, ca.MX(0, 1)
        if E:
            x_prev = x_um[self.ev_prev] * LENGTH_UNIT
            e0 = step * ca.DM(self.ev_step) - x_prev
            Pev = dict(P, k=ca.DM(self.ev_k), Nb=ca.DM(self.ev_Nb))
            z0 = self.start_state(self.start_positions(w), x_prev, e0, Pev, ops=ca)
            rows = [(x_prev / LENGTH_UNIT).T, (e0 / LENGTH_UNIT).T, z0.T]
            for n in self.arcs.param_names:
                v = P[n]
                rows.append(ca.repmat(v if isinstance(v, ca.MX) else ca.MX(v), 1, E))
            rows += [ca.DM(self.ev_k).T, ca.DM(self.ev_Nb).T, ca.DM(self.ev_fp).T, ca.DM(self.ev_M).T]
            A = ca.vertcat(*rows)
            # triggers: the previous arc's end state aged over the rest, in this interval
            nx = self.ev_next
            pv = nx - 1
            rest = (self.ev_step[nx] - self.ev_step[pv] - self.ev_M[pv]) / self.ev_fp[pv]
            z_aged = self.law.rest(Y[1, pv].T, ca.DM(rest), P, ops=ca)
            z_before = self.law.rest(Y[1, pv].T, ca.DM(np.maximum(rest - 1 / self.ev_fp[nx], 0)), P, ops=ca)
            Pn = dict(P, k=ca.DM(self.ev_k[nx]), Nb=ca.DM(self.ev_Nb[nx]))
            s_pos = self.position(z_aged, x_prev[nx], e0[nx], Pn, ops=ca, z_before=z_before)
            if not self.interval_triggers:
                phi = w[self.i_phi : self.i_phi + self.n_phase]
                k_of = np.array([self.phase_of_run[int(ri)] for ri in self.ev_run[nx]], int)
                # (a 1x1 MX indexed by a list comes back as a row: force a column)
                res.append(math.sqrt(12) * (s_pos - ca.reshape(phi[k_of.tolist()], -1, 1)))
                res.append(math.sqrt(12) * (phi - 0.5))
            g = x_um[self.ev_prev + 1] - x_um[self.ev_prev] - Y[0, :].T
            if self.n_s:
                # shooting: each arc starts where the previous arc's end, aged over the
                # rest, puts the capacity in the (plain) trigger interval; a run's first
                # slip from an unobserved initial contact, uniform over the interval
                self._s_target = self.position(z_aged, x_prev[nx], e0[nx], Pn, ops=ca)
                s_all = w[self.i_s : self.i_s + self.n_s]
                # (scaled to µm of slip length, so that the feasibility tolerance means
                # the same as for the slip lengths; a 1x1 MX indexed by a list comes back
                # as a row: force columns)
                s_next = ca.reshape(s_all[self.ev_next.tolist()], -1, 1)
                g = ca.vertcat(g, START_SCALE_UM * (s_next - ca.reshape(self._s_target, -1, 1)))
                if not self.interval_triggers:
                    res.append(math.sqrt(12) * (ca.reshape(s_all[self.ev_firsts.tolist()], -1, 1) - 0.5))
        for r in self.creep_runs:
            Pr = dict(P, k=r.k, Nb=r.Nb)
            vp = r.fp * step
            zss = self.law.steady_state(vp, Pr, ops=ca)
            mu = self.law.static_coefficient(zss, Pr, ops=ca) + P["A"] * ca.log(1 + vp / P["vc"])
            f = self.model.spring_force(r.steady_mean_e, Pr, ops=ca)
            res.append((f - mu * self.model.normal_load(Pr)) / (r.k * r.steady_se))
        return A, ca.vertcat(*res), g

    def build(self):
        """Residual, constraint and derivative Functions (and Ipopt, when chosen)."""
        opts = self.opts
        E = self.E
        w = ca.MX.sym("w", self.n_w)
        Ysym = ca.MX.sym("Y", 2, max(E, 1))
        A, rY, gY = self._symbolic(w, Ysym)
        R_w = ca.jacobian(rY, w)
        if self.n_s:
            self._s_target_fun = ca.Function("s_target", [w, Ysym], [self._s_target])
        if E:
            ix = self.arcs.index
            # the block position matters to an arc only through the topography ripple:
            # without it, two fewer integrations per arc and Jacobian
            topo = "topo_amp" in self.theta.names or self.values.get("topo_amp", 0.0) != 0.0
            rows = ([ix["x0_um"]] if topo else []) + [ix["e0_um"], ix["state0"]] \
                + [ix[n] for n in self.theta.names if n in ix]
            self._cb_jac = _ArcCallback("arc_jacs", self.arcs, E, opts.threads, True, self.counter, rows,
                                        scheme=opts.arc_jacobian)
            self._cb_val = _ArcCallback("arcs", self.arcs, E, opts.threads, False, self.counter,
                                        jac_callback=self._cb_jac)
            Y = self._cb_val(A)[:2, :]
            JA = ca.MX(_blockdiag_sparsity(2, self.arcs.n_in, E), ca.vec(self._cb_jac(A)))
            dY_dw = ca.mtimes(JA, ca.jacobian(ca.vec(A), w))
            r = ca.substitute(rY, Ysym, Y)
            g = ca.substitute(gY, Ysym, Y)
            Jr = ca.substitute(R_w + ca.mtimes(ca.jacobian(rY, ca.vec(Ysym)), dY_dw), Ysym, Y)
            Jg = ca.substitute(ca.jacobian(gY, w) + ca.mtimes(ca.jacobian(gY, ca.vec(Ysym)), dY_dw), Ysym, Y)
            self._arc_inputs = ca.Function("arc_inputs", [w], [A])
        else:
            r, g, Jr, Jg = rY, gY, R_w, ca.MX(0, self.n_w)
            self._arc_inputs = None
        self._r_fun = ca.Function("r", [w], [r])
        self._g_fun = ca.Function("g", [w], [g])
        self._jr_fun = ca.Function("Jr", [w], [Jr])
        self._jg_fun = ca.Function("Jg", [w], [Jg])
        self.n_g = int(g.numel())
        self.n_r = int(r.numel())
        if opts.solver == "ipopt":
            p = ca.MX.sym("p", 0)
            lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", self.n_g)
            f = 0.5 * ca.dot(r, r)
            oracle = dict(
                grad_f=ca.Function("grad_f", [w, p], [f, ca.mtimes(Jr.T, r)], ["x", "p"], ["f", "grad_f_x"]),
                jac_g=ca.Function("jac_g", [w, p], [g, Jg], ["x", "p"], ["g", "jac_g_x"]),
                hess_lag=ca.Function("hess_lag", [w, p, lam_f, lam_g], [ca.triu(lam_f * ca.mtimes(Jr.T, Jr))],
                                     ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"]),
            )
            self._ipopt_test = _IpoptConvergence(self)
            self._ipopt_log = _IpoptLog()
            self.ipopt = ca.nlpsol("identify", "ipopt", {"x": w, "f": f, "g": g}, dict(
                oracle, print_time=False, calc_lam_p=False, calc_multipliers=False, error_on_fail=False,
                iteration_callback=self._ipopt_test,
                ipopt={"print_level": 0, "sb": "yes", "max_iter": opts.max_iter, "tol": opts.tol,
                       "hessian_approximation": "exact",
                       # (the iteration log, for the restoration iterations: CasADi's
                       # stats do not say which iterations were restoration ones)
                       "output_file": self._ipopt_log.path, "file_print_level": 5},
            ))
        return self

    # ---------------------------------------------------------------- numerics
    def evaluate(self, w, jac: bool = False):
        """(r, g) or (r, g, Jr, Jg) at w; an arc that cannot be integrated at a trial point
        gives non-finite values (the point is rejected, the fit goes on)."""
        r = np.array(self._r_fun(w)).ravel()
        g = np.array(self._g_fun(w)).ravel()
        if not jac:
            return r, g
        return r, g, _to_csc(self._jr_fun(w), self.n_w), _to_csc(self._jg_fun(w), self.n_w)

    def residuals(self, w) -> np.ndarray:
        return self.evaluate(w)[0]

    def arc_inputs(self, w: np.ndarray) -> np.ndarray:
        """The arcs' input matrix at w (n_in × E, :class:`identify.arcs.ArcFunctions` order)."""
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
    def solve(self, w0: np.ndarray, fixed: Mapping[int, float] | None = None, loose: bool = False) -> dict:
        """Solve from ``w0`` (the Gauss–Newton SQP, or Ipopt). ``loose``: to the
        tolerances a mode-sequence decision needs (``LOOSE_STAT_TOL``, ``LOOSE_FEAS_TOL``),
        for a solution that only decides the next sequence; the result says ``loose``."""
        self.jacobian_scheme(self.opts.arc_jacobian, SOLVE_REL_STEP)
        if self.opts.solver == "ipopt":
            return self.solve_ipopt(w0, fixed, loose)
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

    def accurate_differences(self, res: dict, fixed: Mapping[int, float] | None = None) -> dict:
        """A solution ``res`` of :meth:`solve` that ended on shared forward differences
        (``SHARE_TOL``) solved on from there on the covariance's differences (central, at
        the secant step, shared only within it: :meth:`central_differences`), so that it
        is a solution of the problem and not of the sharing's approximation of it
        (usually within tolerance at once: one Jacobian more, which the covariance then
        finds remembered). The fit's last step (:func:`identify.fit.fit`); the solves
        that only decide (mode-sequence trials, loose solves) stop on shared ones.
        Measured: the noiseless test fit's interval solve ended 8e-4 off in τ on shared
        differences (see also NEAR_SHARE), 5.7e-5 after this step on each arc's own
        forward differences, 6.4e-5 on these (4.4e-5 since the merit's weights per
        constraint); on the 10-run speed set this step took 0.4 s against 2.1 s, the
        estimates the same to every printed digit."""
        if not res.get("shared") or not np.isfinite(res["f"]):
            return res
        self.central_differences()
        try:
            more = self._solve_gn_resolved(res["w"], fixed)
        except Exception as err:  # the shared solution stands
            log.info("the solve on the covariance's differences after a shared one failed: %s", err)
            return res
        finally:
            self.jacobian_scheme(self.opts.arc_jacobian, SOLVE_REL_STEP)
        spent = dict(iterations=res["iterations"] + more["iterations"], wall_s=res["wall_s"] + more["wall_s"])
        # (the rest of res, the fit's records of the mode sequence, carried)
        return {**res, **more, **spent} if np.isfinite(more["f"]) and (more["success"] or more["f"] <= res["f"]) \
            else {**res, **spent}

    def _solve_gn_resolved(self, w0: np.ndarray, fixed: Mapping[int, float] | None) -> dict:
        """:meth:`solve_gn`, and once more on central differences after a forward-difference stall."""
        try:
            res = self.solve_gn(w0, fixed)
        finally:
            self.jacobian_scheme(self.opts.arc_jacobian, SOLVE_REL_STEP)  # (solve_gn may switch)
        forward_failed = res["status"] in ("Stalled", "Line_Search_Failed") and self.opts.arc_jacobian == "forward"
        if forward_failed and (feas := self._violation(res["w"])) >= CENTRAL_RESOLVE_FEAS:
            log.debug("%s at |g| %.2e µm: no central-difference solve after it (CENTRAL_RESOLVE_FEAS)",
                      res["status"], feas)
        elif forward_failed:
            # forward differences carry O(h) and noise/h errors that central ones halve
            # or cancel: a stall on them, or a line search that found no step along
            # them (a Jacobian row wrong to first order: measured, the step's actual
            # slip-length change missed the predicted one by 6.5e-6 µm at α = 0.01 and
            # 7e-4 at α = 1 on a creeping arc), gets one more solve on the accurate Jacobian
            # (in the one line-search failure measured, that solve ended there too); kept
            # also after a solve that switched to them itself, as calibrated at 208716e
            # (whether it gains anything there, where the damping and the merit's weight
            # start afresh, was not measured; with the parameters held it repeats work);
            # only near continuity, where the differences can matter (CENTRAL_RESOLVE_FEAS)
            self.jacobian_scheme("central", SOLVE_REL_STEP)
            try:
                more = self.solve_gn(res["w"], fixed)
            except Exception as err:  # the stalled solution stands
                log.info("central-difference solve after a stall failed: %s", err)
                more = dict(f=np.inf, success=False, iterations=0, wall_s=0.0)
            finally:
                self.jacobian_scheme(self.opts.arc_jacobian, SOLVE_REL_STEP)
            its, wall = res["iterations"] + more["iterations"], res["wall_s"] + more["wall_s"]
            if more["success"] or more["f"] <= res["f"]:
                res = more
            res["iterations"], res["wall_s"] = its, wall
        return res

    def _violation(self, w) -> float:
        """max |g| at w (µm; the arcs there are remembered, so this costs little); inf if
        it cannot be evaluated."""
        try:
            g = self.evaluate(w)[1]
        except Exception:  # (then no re-solve either: the solve's own result stands)
            return float("inf")
        return float(np.abs(g).max()) if g.size else 0.0

    def solve_ipopt(self, w0, fixed=None, loose: bool = False) -> dict:
        """Ipopt (interior point, filter line search) on the Gauss–Newton Hessian, stopped
        by the SQP's own statistical test (:class:`_IpoptConvergence`): its KKT
        tolerance is on the gradient, which the arcs' integration noise keeps from
        falling below ~1e-3 (measured: after reaching ½χ² to 1e-5 in 5 iterations, it
        spent 95 more at inf_du 8.6e-4 with the line search taking steps of 1e-12)."""
        lbx, ubx = self.bounds(fixed)
        test = self._ipopt_test
        test.start(lbx, ubx, LOOSE_STAT_TOL if loose else self.stat_tol,
                   LOOSE_FEAS_TOL if loose else self.feas_tol)
        t0 = time.perf_counter()
        mark = self._ipopt_log.mark()
        sol = self.ipopt(x0=np.clip(w0, lbx, ubx), lbx=lbx, ubx=ubx, lbg=0, ubg=0)
        st = self.ipopt.stats()
        restoration = self._ipopt_log.restoration_iterations(mark)
        status = st.get("return_status", "?")
        w = np.array(sol["x"]).ravel()
        success = bool(st.get("success", False))
        if test.converged is not None:
            # Ipopt stops after the callback with its last accepted iterate: the point tested
            w, status, success = test.converged, test.status, True
        f = 0.5 * float(np.sum(self.residuals(w) ** 2))
        return dict(w=w, f=f, status=status, success=success, iterations=int(st.get("iter_count", -1)),
                    wall_s=time.perf_counter() - t0, solver="ipopt", ipopt_status=st.get("return_status", "?"),
                    restoration_iterations=restoration, **({"loose": True} if loose else {}))

    def solve_gn(self, w0: np.ndarray, fixed: Mapping[int, float] | None = None) -> dict:
        """Constrained Gauss–Newton SQP (generalised Gauss–Newton, Bock's method).

        Each iteration solves the KKT system of the linearised problem
        min ½‖r + Jᵣd‖² s.t. g + J_g d = 0 (sparse LU), parameters at an active bound
        held there, then backtracks on the ℓ1 merit ½‖r‖² + Σᵢ νᵢ|gᵢ| (each constraint
        weighted by 1.1× the largest of its own multipliers so far), no further than where
        the step could gain less than ``STAT_TOL`` (below, the merit's change is the arcs'
        integration noise); a full step the merit rejects first gets second-order
        corrections (:meth:`_second_order_correction`). A Levenberg–Marquardt term on
        the parameter block is switched on only when the line search fails (flat
        directions) and decays after good steps.
        Converged when the relative parameter step, the constraint violation and the merit
        change are all below ``tol``, or when the full undamped step would move ½χ²'s
        quadratic model by less than ``STAT_TOL`` (½‖Jᵣd‖²) at a feasible point (a damped
        step that would is judged by the stall rule on the undamped one).
        A solve that gains less than ``STAT_TOL`` in ``STALL_ITERS`` accepted iterations
        in a row stops: ``Stalled_Within_Tolerance`` (a success) if the constraints hold
        to ``STALL_FEAS`` and the linearised problem's solution is within ``STALL_TOL``
        of ½χ² of the point reached (on the undamped step, if the last was damped), else
        ``Stalled``. A solve whose ½χ² has not fallen by ``STALL_TOL`` in ``FLAT_ITERS``
        iterations, accepted or rejected, at points feasible to ``feas_tol`` stops as
        ``Stalled_Within_Tolerance``. A solve whose line search finds no step even at
        the largest damping, or once no further damping could change the step (``ladder_reach``,
        :meth:`_damping_reach`), is judged the same way on its undamped step
        (``Stalled_Within_Tolerance``, else ``Line_Search_Failed``). A rejected step
        whose undamped Gauss–Newton step promises less than ``STALL_TOL`` at a point
        feasible to ``STALL_FEAS`` is judged so at once. A step from a point feasible to
        ``feas_tol`` on forward-difference arcs that the line search rejects is first
        computed again on central ones at the same point, which the rest of the solve
        keeps (the result's ``central``). Forward differences shared among nearly equal
        arcs (``SHARE_TOL``, among the arcs within ``SHARE_FEAS`` of continuity) come before:
        a full step on them that fails is computed again on each arc's own; if that step
        needs the line search as well, the sharing resumes, its failed full steps then
        backtracked like any other while the largest violation is at least ``SHARE_FEAS``
        (the result's ``shared``: whether its last Jacobian was shared).
        """
        opts = self.opts
        t0 = time.perf_counter()
        lbx, ubx = self.bounds(fixed)
        w = np.clip(np.asarray(w0, float), lbx, ubx)
        fixed_mask = lbx == ubx
        n_th = self.n_theta
        nu, lm = 1.0, 0.0  # (nu: the merit's weight of each constraint, below)
        status, success, it = "Maximum_Iterations_Exceeded", False, 0
        said = t0
        stalled = 0  # consecutive iterations that gained < stat_tol of merit
        flat, flat_ref = 0, None  # iterations at feasible points since ½χ² last fell by flat_tol
        # (never looser than STALL_TOL: a candidate's stall_tol of a likelihood unit is for
        # its Δnll, and a named candidate's estimates come from where its refit ends)
        flat_tol = min(self.stall_tol, STALL_TOL)
        refreshed = False
        may_share = self._cb_jac_shared()
        own_check, trusted = False, False  # (shared steps trusted far out: see SHARE_FEAS)
        r, g = self.evaluate(w)
        for it in range(1, opts.max_iter + 1):
            if may_share:  # (SHARE_FEAS, per arc)
                self.jacobian_scheme("forward", SOLVE_REL_STEP, share=self.near_continuity(g))
            r, g, Jr, Jg = self.evaluate(w, jac=True)
            r0, g0, grad = r, g, Jr.T @ r
            H = (Jr.T @ Jr).tocsc()
            rough = np.sqrt(H.diagonal()[:n_th]) * np.maximum(np.abs(w[:n_th]), 1.0) * np.finfo(float).eps
            rough[fixed_mask[:n_th]] = 0.0  # (a held parameter takes no step)
            if it == 1 and n_th and rough.max() > 1.0:
                # (NOT_DIFFERENTIABLE) the last bit of a parameter moves the residuals by
                # more than their noise: no linearisation holds here
                j = int(np.argmax(rough))
                log.debug("GN it 1: the last bit of %s moves the residuals by %.2g σ: %s", self.theta.names[j],
                          rough[j], NOT_DIFFERENTIABLE)
                status = NOT_DIFFERENTIABLE
                break
            if lm > 0:
                diagH = np.maximum(H.diagonal()[:n_th], 1e-12)
                H = H + sp.diags(np.r_[lm * diagH, np.zeros(self.n_w - n_th)])
            d, lam, free = _bounded_step(H, Jg, grad, g, w, lbx, ubx, fixed_mask)
            if d is None or not np.all(np.isfinite(d)):
                lm = max(10 * lm, 1e-3)
                if lm > 1e8:
                    status = "Singular_KKT"
                    break
                continue
            # statistically converged: at a feasible point the full Gauss–Newton step
            # would move the model's predictions by ½‖Jᵣd‖² < stat_tol in ½χ² (the
            # parameters by < 0.015 σ in any direction). The relative-step test below can
            # wait for ever when finite-difference arc Jacobians are noisy. Not the step's
            # predicted gain −½∇f·d = ½‖Jᵣd‖² − ½λᵀg: at feasibility within the arcs'
            # integration noise (|g| ~ 0.1 pm, λ ~ 3e4 per µm of slip) its λᵀg term is that
            # noise times the multipliers, up to a few hundredths of ½χ², which no step
            # can remove. Measured on the 5-run speed benchmark: 566 → 435 s, the same
            # estimates (its first solve stopped at iteration 10, where the step moved the
            # model by 9e-6 of ½χ² and promised 2e-4, instead of 13).
            feas0 = float(np.abs(g).max()) if g.size else 0.0
            stat_tol, feas_tol = self.stat_tol, self.feas_tol
            dr = Jr @ d
            moves = 0.5 * float(dr @ dr)
            log.debug("GN it %d: step moves 1/2 chi2 by %.3g, promises %.3g, |g| %.2e", it, moves,
                      -0.5 * float(grad @ d), feas0)
            # (min: a problem whose own stall tolerances are looser, a candidate refit's,
            # is not loosened further by this rule)
            # (none of these where the step would remove a good share of what is left of
            # ½χ² itself: NEAR_SHARE)
            real = moves >= NEAR_SHARE * 0.5 * float(r0 @ r0)
            near = (self.near_tol > 0 and lm == 0 and feas0 < min(self.stall_feas, STALL_FEAS) and not real
                    and moves < max(self.near_tol, stat_tol)
                    and abs(float(grad @ d) + moves) < min(self.stall_tol, STALL_TOL))
            # (and, as for NEAR_TOL, ½χ²'s own change along the step, restoring continuity
            # included, within the tolerance: moves alone leaves out λᵀg)
            loose = (self._loose and lm == 0 and feas0 < LOOSE_FEAS_TOL and moves < LOOSE_STAT_TOL
                     and abs(float(grad @ d) + moves) < LOOSE_STAT_TOL)
            tight = feas0 < feas_tol and moves < stat_tol and not real
            if tight or near or loose:
                if loose and not near and not tight:
                    log.debug("GN it %d: converged to the loose tolerances at |g| %.2e", it, feas0)
                elif not tight:
                    log.debug("GN it %d: converged within NEAR_TOL at |g| %.2e", it, feas0)
                if lm > 0:
                    # a damped step's prediction is short along the flat directions: the
                    # damping grew because steps failed, so the solve has stopped gaining,
                    # not converged; judged as a stall on the undamped step
                    status, success = self._stalled_undamped(it, r0, Jr, Jg, grad, g, free, "Stalled")
                else:
                    status, success = "Solve_Succeeded", True
                break
            if self.flat_iters and feas0 < min(feas_tol, FEAS_TOL):
                # (FLAT_ITERS) every iteration counts here, accepted or rejected (a point
                # taken again on central differences too: its new Jacobian is a new try)
                f_now = 0.5 * float(r0 @ r0)
                if flat_ref is None or f_now < flat_ref - flat_tol:
                    flat_ref, flat = f_now, 0
                else:
                    flat += 1
                    # ... and only on an undamped step that itself promises little: the
                    # gain the linearisation still sees is then below FLAT_PROMISE
                    if flat >= self.flat_iters and lm == 0 and moves < FLAT_PROMISE:
                        log.debug("GN it %d: ½χ² %.8g within %.2g of %.8g for %d iterations at |g| < %.0e: %s",
                                  it, f_now, flat_tol, flat_ref, flat, feas_tol, STALLED)
                        status, success = STALLED, True
                        break
            else:
                flat, flat_ref = 0, None  # ("in a row": at feasible points only)
            ask = self.give_up if self.give_up is not None and feas0 < self.give_up_feas else self.give_up_far
            if lm == 0 and ask is not None and ask(it, 0.5 * float(r0 @ r0), -float(r0 @ dr + 0.5 * dr @ dr)):
                status = GAVE_UP
                break
            with np.errstate(divide="ignore", invalid="ignore"):
                a_max = float(min(1.0, np.min(np.where(d < 0, (lbx - w) / d, np.inf)),
                                  np.min(np.where(d > 0, (ubx - w) / d, np.inf))))
            # the ℓ1 merit weighs each constraint by its own multiplier (Powell's weights,
            # each never lowered), not all by the largest: a descent direction all the same
            # (ν_i ≥ |λ_i|). With one weight, the largest multiplier any constraint had held
            # every slip's continuity at that price. Measured on the 5-run speed set: ν 1.08e5
            # against a current max |λ| of 4.4e4, ν·|g|₁ ~20× ½χ², and the solve after the
            # inserted slips crawled at α 0.06-0.25 for five iterations (~2 s each) while the
            # full steps cut ½χ² by 1.6e3; per constraint, α = 1 from its fourth on
            if lam.size:
                nu = np.maximum(nu, 1.1 * np.abs(lam))
            pen = _l1(nu, g)
            phi0, dphi = 0.5 * r @ r + pen, grad @ d - pen
            a, accepted, d_gn = a_max, False, d  # (d_gn: the step before any correction)
            # backtracking stops where the step could gain less than stat_tol: steps that
            # short are the arcs' integration noise, not progress (measured on a stalled
            # 2-run fit: 21 of 38 accepted steps had α < 1e-6, dθ ~1e-9, and with the
            # rejected ones took 97 % of the line-search evaluations)
            tried = 0
            shared = self._cb_jac_shared()
            # (a shared step that fails is checked on each arc's own differences, unless
            # one such check showed the curvature far from continuity at work: SHARE_FEAS)
            check = shared and not (trusted and feas0 >= SHARE_FEAS)
            while a > 1e-10 and (dphi >= 0 or -a * dphi >= stat_tol):
                tried += 1
                r1, g1 = self.evaluate(w + a * d)
                phi1 = 0.5 * r1 @ r1 + _l1(nu, g1)
                if np.isfinite(phi1) and phi1 <= phi0 + 1e-4 * a * min(dphi, 0.0):
                    accepted = True
                    break
                if a == 1.0 and dphi < 0 and np.isfinite(phi1) and g.size:
                    soc = self._second_order_correction(w, d, g1, H, Jg, grad, free, lbx, ubx, nu,
                                                        phi0 + 1e-4 * dphi)
                    if soc is not None:
                        d, (r1, g1, phi1), accepted = soc[0], soc[1], True
                        break
                    if check:
                        break  # (the arcs' own differences first: below)
                a *= 0.5
            if not accepted and tried and (shared or feas0 < feas_tol and self._cb_jac_forward()):
                # a step from a feasible point on forward differences that no line search
                # accepts: their O(h) error is first-order in the step. Measured in the
                # tail of the 10-run speed benchmark's first solve: the trial points'
                # constraint violation grew in proportion to α (0.8 pm at 1/16, 7 pm at 1;
                # the ℓ1 term then outweighs ½χ²'s gain), and the step on central
                # differences at the same point promised 0.0038, not 0.0157. The rest of
                # the solve takes central ones (the damping ladder on forward ones had
                # climbed for ten iterations). Away from feasibility the constraints'
                # curvature is the usual cause (the second-order correction's case): a
                # diagnosis test's load-offset refit, crawling at α ~0.02 with |g| ~1e-3 µm,
                # switched there and stalled 1e-3 µm off its constraints, not 3e-5.
                # Differences shared among nearly equal arcs (SHARE_TOL) err in the same way,
                # and more: a full step on them that fails, at any distance from continuity,
                # is taken again on each arc's own forward differences, for the rest of
                # the solve (measured: on noiseless data, from 10 % off, shared ones crawled
                # at α ~0.03 with the second-order correction failing, to the iteration limit)
                log.debug("GN it %d rejected on %s forward differences: the arcs' Jacobian again, %s", it,
                          "shared" if shared else "the arcs' own", "unshared" if shared else "central")
                self.jacobian_scheme("forward" if shared else "central", SOLVE_REL_STEP, share=False)
                may_share, own_check = False, shared
                refreshed = True
                continue
            if not accepted:
                if lm == 0 and feas0 < self.stall_feas and moves < self.stall_tol:
                    # the whole (undamped) step promises less than the stall tolerance: no rung
                    # of the damping ladder can gain more, and the stall rule would judge the
                    # point reached within tolerance after climbing it (measured: four rungs,
                    # ~20 s, for 1.5e-4 of ½χ² in the first solve above)
                    judged = self._stalled_undamped(it, r0, Jr, Jg, grad, g, free, "Line_Search_Failed")
                    if judged[1]:
                        status, success = judged
                        log.debug("GN it %d rejected within the stall tolerance: %s", it, status)
                        break
                reach, moves_step = self._damping_reach(d_gn, H, Jg, grad, g, free, Jr, dphi)
                log.debug("GN it %d rejected: phi %.6g dphi %.3g |d| %.3g nu %.3g lm %.1e reach %.2g, %.2g",
                          it, phi0, dphi, np.max(np.abs(d)), float(np.max(nu, initial=0.0)), lm, reach, moves_step)
                lm = max(10 * lm, 1e-3)
                if lm > 1e8 or (reach < self.ladder_reach and moves_step < self.ladder_step):
                    # no step gains along any damping (or none the rest of the ladder
                    # could give differs enough): judged like a stall, on the undamped
                    # step (a candidate's refit that cannot move further but whose Δnll
                    # is known to its tolerance has done its job)
                    status, success = self._stalled_undamped(it, r0, Jr, Jg, grad, g, free, "Line_Search_Failed")
                    break
                continue
            step_th = float(np.max(np.abs(a * d[:n_th]))) if n_th else 0.0
            w, r, g = w + a * d, r1, g1
            if own_check:
                own_check = False
                if (a < a_max or lm > 0) and self.opts.share_arc_jacobian:
                    # each arc's own differences needed the line search too: the
                    # constraints' curvature, not the sharing, had stopped the full step
                    may_share, trusted = True, True
                    log.debug("GN it %d: on the arcs' own differences a step of %.2g: sharing again", it, a)
            lm_step, lm = lm, (lm / 10 if lm > 1e-3 else 0.0)
            feas = float(np.abs(g).max()) if g.size else 0.0
            log.debug("GN it %d: f %.8g |g| %.2e dθ %.2e α %.2g lm %.1e", it, 0.5 * r @ r, feas, step_th, a, lm)
            if self.progress is not None and time.perf_counter() - said >= PROGRESS_EVERY_S:
                said = time.perf_counter()
                self.progress(f"  iteration {it} of at most {opts.max_iter}: χ² {float(r @ r):.6g}, "
                              f"constraint violation {feas:.2e}, {said - t0:.0f} s")
            if step_th < opts.tol and feas < feas_tol and abs(phi0 - phi1) <= opts.tol * (1 + phi0):
                status, success = "Solve_Succeeded", True
                break
            stalled = stalled + 1 if phi0 - phi1 < stat_tol else 0
            if stalled >= STALL_ITERS:
                if lm_step > 0:  # judged on the undamped step, as a damped convergence is
                    status, success = self._stalled_undamped(it, r0, Jr, Jg, grad, g0, free, "Stalled")
                else:
                    status, success = self._stalled(it, r0, Jr, d_gn, g, damped=False)
                break
        return dict(w=w, f=0.5 * float(r @ r), status=status, success=success, iterations=it,
                    wall_s=time.perf_counter() - t0, central=refreshed, shared=self._cb_jac_shared())

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

    def _damping_reach(self, d, H, Jg, grad, g, free, Jr, dphi) -> tuple[float, float]:
        """How much the rest of the damping ladder could change a rejected step ``d``:
        (|m(d∞) − m(d)| / |∂φ|, max|d∞ − d| / max|d|), m the Gauss–Newton model of ½χ²'s
        change (∇f·x + ½‖Jᵣx‖²), d∞ the step with the parameter block held (the limit of
        infinite damping: the Levenberg–Marquardt term acts on the parameters alone; the
        states' part of the step, which the linearised constraints ask for, no damping
        removes), ∂φ the merit's directional derivative along ``d`` (the constraints'
        part of it is the same for every damping). The first says what the model would
        gain, the second how far the trial points would move (a parameter step along a
        flat direction changes the model little and the function perhaps much). (0, 0)
        when the parameters are held anyway (a run solved alone, a mode-sequence trial):
        every rung would give the same step."""
        n_th = self.n_theta
        states = free[free >= n_th]
        if len(states) == len(free):
            return 0.0, 0.0
        try:
            sol = _kkt_solve(H, Jg, grad, g, states)
        except RuntimeError:
            return np.inf, np.inf
        d_inf = np.zeros(self.n_w)
        d_inf[states] = sol[: len(states)]

        def model(x):
            jx = Jr @ x
            return float(grad @ x) + 0.5 * float(jx @ jx)

        size = float(np.max(np.abs(d)))
        step = float(np.max(np.abs(d_inf - d))) / size if size > 0 else 0.0
        return (abs(model(d_inf) - model(d)) / abs(dphi) if dphi != 0 else np.inf), step

    def _second_order_correction(self, w, d, g1, H, Jg, grad, free, lbx, ubx, nu, target):
        """(step, (r, g, merit)) of a second-order correction of a full step ``d`` that
        the merit rejected, or None (Nocedal & Wright §18.3; Ipopt's SOC).

        The continuity constraints are nonlinear in the arcs' inputs: a full step the
        Gauss–Newton model predicts well for χ² can leave them violated to second order,
        and the ℓ1 merit then rejects it and every step down to α ~ 0.01 (the Maratos
        effect). Measured on the load-offset candidate of four short runs: χ² fell as
        predicted to 3 digits at α = 1, but |g| rose from 1e-6 to 1e-3…1e-2 µm, and the
        refit crawled at α ≈ 0.004…0.06 until it stalled. The correction solves the same
        KKT system with the constraints' residual at the trial point, c(w + d) − J_g·d,
        in place of c(w): the step then lands on the constraints to second order.
        Up to :data:`MAX_SOC` corrections, each from the last."""
        p, gp = d, g1
        for _ in range(MAX_SOC):
            try:
                sol = _kkt_solve(H, Jg, grad, gp - Jg @ p, free)
            except RuntimeError:
                return None
            q = np.zeros(self.n_w)
            q[free] = sol[: len(free)]
            if not np.all(np.isfinite(q)):
                return None
            q = np.clip(w + q, lbx, ubx) - w  # (a correction may cross a bound the step touched)
            r1, g1 = self.evaluate(w + q)
            phi1 = 0.5 * r1 @ r1 + _l1(nu, g1)
            if not np.isfinite(phi1):
                return None
            if phi1 <= target:
                log.debug("   second-order correction accepted: |g| %.2e -> %.2e", float(np.abs(gp).max()),
                          float(np.abs(g1).max()))
                return q, (r1, g1, phi1)
            if np.abs(g1).sum() >= np.abs(gp).sum():  # the constraints are not converging
                log.debug("   second-order correction rejected: |g| %.2e -> %.2e", float(np.abs(gp).max()),
                          float(np.abs(g1).max()))
                return None
            p, gp = q, g1
        return None

    def _stalled_undamped(self, it, r, Jr, Jg, grad, g, free, failed: str) -> tuple[str, bool]:
        """:meth:`_stalled` on the undamped Gauss–Newton step at the point reached;
        ``failed`` is the status when that does not hold either."""
        try:
            d0 = np.zeros(self.n_w)
            d0[free] = _kkt_solve((Jr.T @ Jr).tocsc(), Jg, grad, g, free)[: len(free)]
        except RuntimeError:
            return failed, False
        status, success = self._stalled(it, r, Jr, d0, g, damped=False)
        return (status, True) if success else (failed, False)

    def solution_gap(self, w: np.ndarray) -> dict:
        """How far a point a solve stopped at lies from the solution its linearisation
        predicts, for the report of a solve that did not converge: ``half_chi2``, the ½χ²
        between here and the Gauss–Newton model's feasible stationary point (on central
        arc differences, as the covariance; the parameters then within about
        √(2·half_chi2) standard errors of it in any direction), and ``continuity_um``,
        the largest continuity violation here. ``half_chi2`` NaN where that model has no
        solution (a singular KKT system)."""
        self.central_differences()
        r, g, Jr, Jg = self.evaluate(w, jac=True)
        lbx, ubx = self.bounds()
        d, _, _ = _bounded_step((Jr.T @ Jr).tocsc(), Jg, Jr.T @ r, g, np.asarray(w, float), lbx, ubx, lbx == ubx)
        feas = float(np.abs(g).max()) if g.size else 0.0
        if d is None or not np.all(np.isfinite(d)):
            return dict(half_chi2=float("nan"), continuity_um=feas)
        dr = Jr @ d
        return dict(half_chi2=abs(float(r @ dr + 0.5 * dr @ dr)), continuity_um=feas)

    def _stalled(self, it, r, Jr, d, g, damped: bool) -> tuple[str, bool]:
        """Status of a solve whose accepted steps no longer gain: the functions do not
        give what the linearisation predicts (finite-difference arc rows that are wrong
        where an arc sits on a kink or in its integration noise). Within tolerance
        if the constraints hold to ``STALL_FEAS`` and the Gauss–Newton model puts ½χ² at
        its feasible stationary point within ``STALL_TOL`` of its value here
        (½‖r + J d‖² − ½‖r‖² for the full step d); never when the step was damped, whose
        prediction is short along the flat directions."""
        dr = Jr @ d
        left = abs(float(r @ dr + 0.5 * dr @ dr))
        feas = float(np.abs(g).max()) if g.size else 0.0
        log.debug("GN it %d: stalled at |g| %.2e, 1/2 chi2 %.3g from the model's solution%s",
                  it, feas, left, " (damped step)" if damped else "")
        ok = not damped and feas < self.stall_feas and left < self.stall_tol
        return (STALLED, True) if ok else ("Stalled", False)

    # ---------------------------------------------------------------- mode sequence
    def refine_triggers(self, w: np.ndarray, shifts=(-2, -1, 1, 2), min_gain: float = 1.0):
        """Slips the model places a step or two from their detected trigger.

        At a few σ of slip length the step at which a plateau ends is uncertain in the
        frames; the fit says which step fits. Per slip and shift, with everything else
        held, the χ² change is scored: frames changing plateau (at the fitted levels),
        the slip's own trigger residual, its arc's length against the plateau difference,
        and the next slip's trigger (its contact aged from the shifted arc over the
        shorter rest). Returns ({run index: trigger steps}, slips moved).
        """
        if not self.E:
            return {}, 0
        P = self.params(w[: self.n_theta])
        step = float(self.model.step(P))
        law = self.law
        x = w[self.i_x : self.i_x + self.P] * LENGTH_UNIT
        off = lambda e: (w[self.i_off + self.ev_run[e]] * LENGTH_UNIT) if self.n_off else 0.0  # noqa: E731
        A0 = np.array(self._arc_inputs(w))
        Y0 = self.arcs.evaluate(A0, self.opts.threads)
        S = len(shifts)
        E = self.E
        phi_all = w[self.i_phi : self.i_phi + self.n_phase]
        phase = np.array([phi_all[self.phase_of_run[int(ri)]] for ri in self.ev_run])
        ev = np.repeat(np.arange(E), S)
        sh = np.tile(np.array(shifts, float), E)
        n_new = self.ev_step[ev] + sh
        prev = self.ev_prev[ev]
        e0 = step * n_new - x[prev]
        Pe = dict(P, k=self.ev_k[ev], Nb=self.ev_Nb[ev])
        first = self.ev_first[ev]
        pv = np.maximum(ev - 1, 0)
        rest = (n_new - self.ev_step[pv] - self.ev_M[pv]) / self.ev_fp[pv]
        A = np.repeat(A0, S, axis=1)
        A[1] = e0 / LENGTH_UNIT
        s_start = np.asarray(self.start_positions(w), float)[ev]
        if self.n_s:  # the shifted arc starts from the previous end aged over the changed rest
            aged = self.position(law.rest(Y0[1, pv], np.maximum(rest, 0), P), x[prev], e0, Pe)
            s_start = np.where(first, s_start, aged)
        A[2] = self.start_state(s_start, x[prev], e0, Pe)

        # own trigger: the previous arc's end aged over the changed rest
        def pos(z_end, rest_s, fp, xp, e, Pp):
            return self.position(law.rest(z_end, np.maximum(rest_s, 0), P), xp, e, Pp,
                                 z_before=law.rest(z_end, np.maximum(rest_s - 1 / fp, 0), P))

        s_own = pos(Y0[1, pv], rest, self.ev_fp[ev], x[prev], e0, Pe)
        own_new = np.where(first, 0.0, trigger_residual(s_own, phase[ev]) ** 2)
        valid = first | ((s_own > 0) & (s_own < 1))  # the capacity must be exceeded at n_new only
        nx = np.minimum(ev + 1, E - 1)
        has_next = (ev + 1 < E) & ~self.ev_first[nx]
        # (the triggers kept in order within their run)
        lo_ok = np.where(first, 1, self.ev_step[pv] + 1)
        hi_ok = np.where(has_next, self.ev_step[nx] - 1, np.inf)
        ok = valid & (n_new >= lo_ok) & (n_new <= hi_ok)
        # only the shifts that can be taken are integrated (measured on the 10-run speed
        # set: 77 and 71 of the 4348 and 4376 shifted arcs, where all had been, 1.5 s a call)
        Yc = np.full((Y0.shape[0], len(ev)), np.nan)
        if ok.any():
            Yc[:, ok] = self.arcs.evaluate(A[:, ok], self.opts.threads)
        e0_old = step * self.ev_step[ev] - x[prev]
        rest_old = (self.ev_step[ev] - self.ev_step[pv] - self.ev_M[pv]) / self.ev_fp[pv]
        s_old = pos(Y0[1, pv], rest_old, self.ev_fp[ev], x[prev], e0_old, Pe)
        own_now = np.where(first, 0.0, trigger_residual(s_old, phase[ev]) ** 2)
        # the next slip's trigger, aged from the shifted arc
        e0n = step * self.ev_step[nx] - x[self.ev_prev[nx]]
        Pn = dict(P, k=self.ev_k[nx], Nb=self.ev_Nb[nx])
        rest_n_new = (self.ev_step[nx] - n_new - self.ev_M[ev]) / self.ev_fp[ev]
        rest_n_old = (self.ev_step[nx] - self.ev_step[ev] - self.ev_M[ev]) / self.ev_fp[ev]
        sn_new = pos(Yc[1], rest_n_new, self.ev_fp[nx], x[self.ev_prev[nx]], e0n, Pn)
        sn_old = pos(Y0[1, ev], rest_n_old, self.ev_fp[nx], x[self.ev_prev[nx]], e0n, Pn)
        next_new = np.where(has_next, trigger_residual(sn_new, phase[nx]) ** 2, 0.0)
        next_now = np.where(has_next, trigger_residual(sn_old, phase[nx]) ** 2, 0.0)
        # the arc's slip against the plateau difference
        sig = self.pl_sigma[prev] * np.sqrt(1 / np.maximum(self.pl_n[prev], 1) + 1 / np.maximum(self.pl_n[prev + 1], 1))
        dx = x[prev + 1] - x[prev]
        slip_new = ((Yc[0] * LENGTH_UNIT - dx) / sig) ** 2
        slip_now = ((Y0[0, ev] * LENGTH_UNIT - dx) / sig) ** 2
        # frames that change plateau, at the fitted levels
        frames = np.zeros(len(ev))
        for c in range(len(ev)):
            e = ev[c]
            run = self.runs[self.ev_run[e]]
            evr = run.events
            lo_n, hi_n = sorted((self.ev_step[e], n_new[c]))
            sel = (evr.steps >= lo_n) & (evr.steps < hi_n)
            if not sel.any():
                continue
            ee = evr.trace.elongation[sel] - off(e)
            before = ((ee - (step * evr.steps[sel] - x[prev[c]])) ** 2).sum()
            after = ((ee - (step * evr.steps[sel] - x[prev[c] + 1])) ** 2).sum()
            frames[c] = ((before - after) if n_new[c] > self.ev_step[e] else (after - before)) / run.sigma**2
        gain = (own_now + next_now + slip_now) - (own_new + next_new + slip_new + frames)
        ok &= np.isfinite(gain)
        gain = np.where(ok, gain, -np.inf).reshape(E, S)
        best = np.argmax(gain, axis=1)
        moved = gain[np.arange(E), best] > min_gain
        new_steps = self.ev_step.copy()
        new_steps[moved] += np.array(shifts)[best[moved]]
        # two neighbours moved towards each other can meet: keep the less certain one
        for _ in range(E):
            clash = np.nonzero((np.diff(new_steps) <= 0) & (self.ev_run[1:] == self.ev_run[:-1]))[0]
            if not clash.size:
                break
            for i in clash:
                j = min((p for p in (i, i + 1) if moved[p]), key=lambda p: gain[p, best[p]])
                moved[j] = False
                new_steps[j] = self.ev_step[j]
        changes = {}
        for ri in np.unique(self.ev_run[moved]):
            sel = self.ev_run == ri
            changes[int(ri)] = np.sort(new_steps[sel]).astype(int)
        return changes, int(moved.sum())

    def moving_times(self, w: np.ndarray) -> dict:
        """Per run, how long each slip's block moves after its trigger step (s)."""
        Y = self.arc_outputs(w)
        out: dict = {}
        for e in range(self.E):
            out.setdefault(int(self.ev_run[e]), []).append(Y[2, e] * 1e-3)
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
                       for r in self.runs))

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
        """Index ranges of the residual vector: plateaus, slopes, triggers, creep."""
        n_slope = sum(1 for r in self.runs if r.kind == "events" and r.s_nn > 0)
        p = self.P
        t0 = p + n_slope
        # phase rows exist with any slip; then the first slips' start positions
        t1 = t0 if self.interval_triggers else \
            t0 + self.n_trig + (self.n_phase if self.E else 0) + (len(self.ev_firsts) if self.n_s else 0)
        return dict(plateaus=(0, p), slopes=(p, t0), triggers=(t0, t1),
                    creep=(t1, t1 + len(self.creep_runs)))

    def trigger_runs(self) -> np.ndarray:
        """Run index of each trigger residual (slips, then one phase residual per run)."""
        if not self.E or self.interval_triggers:
            return np.zeros(0, int)
        phase_runs = sorted(self.phase_of_run, key=self.phase_of_run.get)
        first = self.ev_run[self.ev_firsts] if self.n_s else np.zeros(0, int)
        return np.r_[self.ev_run[self.ev_next], np.array(phase_runs, int), first]

    def information(self, w: np.ndarray, evaluated=None) -> np.ndarray:
        """Gauss–Newton information on the scaled free parameters, every other variable
        eliminated under the linearised constraints (a Schur complement). The parameters
        need not be determined (a singular complement is legitimate: a run alone, or a
        candidate effect the baseline's parameters absorb), so a tiny ridge ε makes the
        KKT matrix invertible and is subtracted again: (C_ε)⁻¹ − εI is the exact complement."""
        return self.information_parts(w, evaluated, meat=False)[0]

    def information_parts(self, w: np.ndarray, evaluated=None, meat: bool = True,
                          frame_scale: float | None = None):
        """(B, M) on the scaled free parameters, the nuisances eliminated: B the
        information of :meth:`information`, M the covariance of the reduced score under
        the robust covariance's error model (:meth:`covariance`: the frames independent,
        a run's triggers exchangeable). The estimator's covariance is B⁻¹MB⁻¹; for
        independent runs B and M both add up, so a plan's prediction is assembled from
        its runs'. σ² of the triggers is pooled over this problem's runs, and so is the
        frames' χ² scale unless ``frame_scale`` sets it (a design sets 1: its noise model
        is exact, and a creep run's one steady mean gives no χ² to scale by).
        ``meat=False``: (B, None)."""
        if evaluated is None:
            self.central_differences()
        r, g, Jr, Jg = evaluated if evaluated is not None else self.evaluate(w, jac=True)
        H = (Jr.T @ Jr).tocsc().toarray()
        Jg = Jg.toarray()
        n_th = self.n_theta
        lbx, ubx = self.bounds()
        keep = np.array([i for i in range(self.n_w) if i < n_th or lbx[i] < ubx[i]])
        H, Jg = H[np.ix_(keep, keep)], Jg[:, keep]
        eps = 1e-9 * max(np.abs(np.diag(H)[:n_th]).max(), 1.0)
        H[:n_th, :n_th] += eps * np.eye(n_th)
        m = Jg.shape[0]
        K = np.block([[H, Jg.T], [Jg, np.zeros((m, m))]]) if m else H
        rhs = np.zeros((K.shape[0], n_th))
        rhs[:n_th, :n_th] = np.eye(n_th)
        if not np.all(np.isfinite(K)):
            raise ValueError("the NLP Jacobian is not finite at this point")
        sol = np.linalg.solve(K, rhs)
        C = sol[:n_th, :n_th]
        C = 0.5 * (C + C.T)
        Cinv = np.linalg.inv(C)
        info = Cinv - eps * np.eye(n_th)
        info = 0.5 * (info + info.T)
        if not meat:
            return info, None
        # δθ = C_ε·u (u the reduced score): Cov(u) = C_ε⁻¹·Cov_ε(δθ)·C_ε⁻¹, exact for any ε
        X = np.zeros((self.n_w, n_th))
        X[keep] = sol[: len(keep)]
        V = self._sandwich_meat(r, Jr, X, "robust", frame_scale=frame_scale)
        M = Cinv @ V @ Cinv
        return info, 0.5 * (M + M.T)

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
            cb.scheme, cb.rel_step, cb.share, cb.own, cb._key = scheme, rel_step, tol, own, None
            if own is not None:
                log.debug("arc differences shared among the %d of %d arcs near continuity",
                          int(own.size - own.sum()), own.size)
        return self

    def central_differences(self):
        """Central arc differences with a secant step (``COVARIANCE_REL_STEP``) from now
        on, for the covariance and the information; :meth:`solve` goes back to the
        option's scheme.

        The hybrid arcs are only piecewise smooth: a slow slip whose speed grazes the
        stop threshold has a kink in its end state, and the solver likes to converge
        onto such a kink. Differences at 1e-6 across it then gave one arc's rows a
        derivative that moved the model-based standard error of μmin by 1.5× between two
        solutions 1e-3 σ apart; at 1e-5 … 3e-3 the covariance agreed to 1 % on both and
        everywhere between (smooth arcs change by O(h²) = 1e-8)."""
        return self.jacobian_scheme("central", COVARIANCE_REL_STEP, tol=COVARIANCE_SHARE_TOL)

    def trigger_correlation(self, r_trig: np.ndarray) -> tuple[dict, float]:
        """Per run, the correlation ρ of its slips' trigger errors, and their variance σ².

        A slip's trigger residual is √12·(s − ½), s its position in the trigger interval:
        uniform, so unit variance. A run whose slips recur at one phase shares one error
        (ρ = 1); one whose phase walks through the interval has nearly independent ones
        (ρ = 0). The spread of the residuals within a run tells which: ρ = 1 − v/σ², v its
        within-run variance. σ² is 1 unless the pooled within-run variance exceeds it (the
        uniform picture failing: then that). Runs with fewer than three trigger residuals
        (four slips: the first has none) get ρ = 1, the cautious end. With ``free_phase``
        each run's phase φ takes up the shared error (its own residual counts it), so the
        slips' residuals √12·(s − φ) keep only what varies within the run: ρ = 0.
        A non-finite residual gives σ² = NaN (an undetermined covariance, not a quiet 1).
        """
        runs = self.ev_run[self.ev_next]
        rs = np.asarray(r_trig[: self.n_trig], float)
        within, dof = 0.0, 0
        var = {}
        for c in np.unique(runs):
            x = rs[runs == c]
            if len(x) >= 3:
                var[int(c)] = float(np.var(x, ddof=1))
                within += var[int(c)] * (len(x) - 1)
                dof += len(x) - 1
        sig2 = (max(1.0, within / dof) if np.isfinite(within) else float("nan")) if dof else 1.0
        if self.opts.free_phase:
            return {int(c): 0.0 for c in np.unique(runs)}, sig2
        rho = {int(c): float(np.clip(1.0 - var[int(c)] / sig2, 0.0, 1.0)) if int(c) in var else 1.0
               for c in np.unique(runs)}
        return rho, sig2

    def _exchangeable_meat(self, A_t: np.ndarray, r_trig: np.ndarray) -> np.ndarray:
        """Σ_c σ²[(1 − ρ_c)·Σ a_i a_iᵀ + ρ_c·(Σ a_i)(Σ a_i)ᵀ] over each run's slip triggers
        (a_i the rows of Jₜ·X, in :meth:`trigger_runs` order), plus the other trigger-group
        rows (phases, first starts: one draw each) as independent unit-variance residuals."""
        rho, sig2 = self.trigger_correlation(r_trig)
        n = self.n_trig
        slip_runs = self.ev_run[self.ev_next]
        M = A_t[n:].T @ A_t[n:]
        for c, rc in rho.items():
            a = A_t[:n][slip_runs == c]
            tot = a.sum(axis=0)
            M = M + sig2 * ((1.0 - rc) * (a.T @ a) + rc * np.outer(tot, tot))
        return M

    def covariance(self, w: np.ndarray, fixed_idx: Iterable[int] = (), robust: bool | str = True,
                   evaluated=None) -> np.ndarray:
        """Covariance of the parameters and offsets at the solution w.

        Bread: the constrained Gauss–Newton system, the top-left block of
        [[JᵣᵀJᵣ, J_gᵀ], [J_g, 0]]⁻¹ (Z(ZᵀHZ)⁻¹Zᵀ, Z the null space of the constraints).
        ``robust=False`` (or ``"model"``): the model-based covariance, every residual
        independent with unit variance. Otherwise a sandwich whose meat keeps the
        model-based information of the frames (plateau levels and slopes, scaled by their
        reduced χ²) but not the triggers': slips of a run recur at nearly the same phase
        of the step interval, so their errors are largely one shared error rather than
        many independent ones.

        * ``True`` / ``"robust"`` (default): the trigger errors of a run exchangeable
          (:meth:`trigger_correlation`): unit variance (a uniform position, √12-scaled)
          with the correlation their spread within the run shows. It is the expected
          meat, not the realised one, and that matters with few runs: a run's shared
          error is largely absorbed by the parameters (as many as the runs, often), so
          the realised cluster sums run small and ``"cluster"`` put τ's standard error
          at 0.4 of the measured spread over redrawn loads.
        * ``"cluster"``: cluster-robust by run from the realised residuals (Liang–Zeger,
          with the c/(c − 1) small-sample factor): no assumption on the correlation, but
          only as many independent draws as runs.

        NaN where the information is singular (undetermined). ``evaluated``: the
        (r, g, Jr, Jg) of :meth:`evaluate` at w with :meth:`central_differences`, on this
        problem as built now (the same arc horizons ``ev_M``), when the caller has it (the
        arcs' Jacobian is most of the cost, and the arcs keep only their last point).
        """
        mode = {True: "robust", False: "model"}.get(robust, robust)
        if mode not in ("robust", "cluster", "model"):
            raise ValueError(f"covariance {robust!r}: choose 'robust', 'cluster' or 'model'")
        if evaluated is None:
            self.central_differences()
            r, g, Jr, Jg = self.evaluate(w, jac=True)
        else:
            r, g, Jr, Jg = evaluated
            if r.size != self.n_r or Jr.shape != (self.n_r, self.n_w) or Jg.shape != (self.n_g, self.n_w):
                raise ValueError(f"covariance: the evaluation given has {r.size} residuals and Jacobians "
                                 f"{Jr.shape}, {Jg.shape}; this problem has {self.n_r} residuals, "
                                 f"{self.n_g} constraints, {self.n_w} variables")
        H = (Jr.T @ Jr).tocsc()
        fixed_idx = set(fixed_idx)
        if not self.phases_free:
            fixed_idx |= set(range(self.i_phi, self.i_s))
        keep = np.setdiff1d(np.arange(self.n_w), sorted(fixed_idx))
        Hk, Jgk = H[keep][:, keep], Jg[:, keep]
        n, m = Hk.shape[0], Jgk.shape[0]
        K = sp.bmat([[Hk, Jgk.T], [Jgk, None]], format="csc")
        want = [i for i in range(self.n_theta + self.n_off) if i in set(keep)]
        cols = [int(np.searchsorted(keep, i)) for i in want]
        rhs = np.zeros((n + m, len(cols)))
        rhs[cols, np.arange(len(cols))] = 1.0
        sol, undetermined = _information_solve(K, rhs, n)
        X = np.zeros((self.n_w, len(cols)))
        X[keep] = sol[:n]
        if mode != "model":
            # (without triggers too: then the frames' χ² scale is what the sandwich adds)
            Cw = self._sandwich_meat(r, Jr, X, mode)
        else:
            Cw = sol[cols, :]
        Cw = np.array(Cw, float)
        Cw[undetermined, :] = np.nan  # (the sandwich's J·X does not see a direction the bread cannot fix)
        Cw[:, undetermined] = np.nan
        C = np.full((self.n_theta + self.n_off,) * 2, np.nan)
        for a_, i in enumerate(want):
            for b_, j in enumerate(want):
                C[i, j] = Cw[a_, b_]
        return C

    def _sandwich_meat(self, r, Jr, X, mode: str, frame_scale: float | None = None) -> np.ndarray:
        """Xᵀ·Cov(Jᵀr)·X: the frames (and creep means) independent, scaled by their
        reduced χ² when above 1 (or by ``frame_scale``); the triggers exchangeable within
        a run (``robust``) or cluster-robust from the realised residuals (``cluster``)."""
        grp = self.residual_groups()
        t0, t1 = grp["triggers"]
        ind = np.r_[np.arange(0, t0), np.arange(t1, len(r))]
        Ji = Jr[ind]
        ri = r[ind]
        # (the first slips' starts are fixed by their own rows in the trigger group, or,
        # with the interval encoding, by the frames)
        n_frames_fix = self.n_effective() - (len(self.ev_firsts) if self.n_s and not self.interval_triggers else 0)
        s2 = float(ri @ ri) / max(len(ri) - n_frames_fix, 1)
        A_ = np.asarray(Ji @ X)
        meat_part = (max(s2, 1.0) if frame_scale is None else frame_scale) * (A_.T @ A_)
        Jt = Jr[t0:t1]
        if t1 == t0:  # the interval encoding: no trigger residual to add
            return meat_part
        if mode == "cluster":
            runs = self.trigger_runs()
            scores = np.asarray(Jt.multiply(r[t0:t1][:, None]).tocsr().toarray())  # per-residual scores
            clusters = np.unique(runs)
            S = np.zeros((len(clusters), self.n_w))
            for ci, c in enumerate(clusters):
                S[ci] = scores[runs == c].sum(axis=0)
            B = S @ X
            nc = len(clusters)
            Cw = meat_part + (nc / max(nc - 1, 1)) * (B.T @ B)
        else:
            Cw = meat_part + self._exchangeable_meat(np.asarray(Jt @ X), r[t0:t1])
        return Cw

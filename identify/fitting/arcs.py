"""Slip arcs for identification: one event-aware integration per detected slip.

An arc starts at a trigger step with the block at rest (position x0, elongation e0,
contact state z0) and integrates the slip model (:func:`identify.model.symbolic.arc_dae`) over M
step intervals with CasADi's Rosenbrock plugin: the zero-crossing event freezes the
block at its stop, after which only the contact ages. Its outputs at the horizon are the
slip length and the contact state, so the next stick phase continues in closed form; the
stop time never becomes a decision variable (DESIGN.md §2), yet the sensitivities
include the event time.

Two Functions, independent of the data, compiled once per model and tolerance and cached
on disk (:mod:`identify.model.compiled`):

``arc(a) -> y``
    a = [x0 (µm), e0 (µm), z0, model parameters..., k, Nb, fp, M] (one column per arc),
    y = [slip length (µm), state at the horizon, stop time after the trigger (ms),
    peak speed (m/s), still moving at the horizon (1/0)].
Derivatives come from finite differences of the compiled arc (forward while the solver
iterates, central for the covariance), for the inputs that vary in the fit only, all
perturbations of all arcs in one batched call. CasADi's Rosenbrock
sensitivities (forward and adjoint alike) are exact for fast slips but were measured
wrong by 1-280 % where a slow, creep-like slip ends at a stop event (they differentiate
the discrete scheme; the computed arc is smooth there: differences with steps of 1e-4
and 1e-6 agree to 5 digits).
"""

from __future__ import annotations

import functools

import casadi as ca
import numpy as np

from identify import interrupts
from identify.model.compiled import compiled
from identify.model.params import SPECS
from identify.model.symbolic import LENGTH_UNIT, SPEED_UNIT, TIME_UNIT, Model, arc_dae, transition

__all__ = ["ArcFunctions", "arc_functions", "ARC_OUTPUTS", "N_ARC_JAC_OUTPUTS"]

ARC_OUTPUTS = ("slip_um", "state_end", "stop_ms", "peak_speed_m_per_s", "moving_at_end")
N_ARC_JAC_OUTPUTS = 2  # slip length and state at the horizon enter the NLP
_TAPE_STEPS = 20_000  # bound of the adjoint tape (steps per arc); a slip takes a few hundred
# Tolerances of the arcs (scaled states: µm, mm/s, ms). The relative tolerance decides
# how smooth an arc is in its inputs: at reltol 1e-6 the position at a fast slip's stop
# event is interpolated inside one long adaptive step, and which step holds the stop
# depends on the inputs. Measured on the 2-run speed benchmark at its stalled point, one
# arc's slip length jumped by 0.14 nm between inputs 4e-5 apart (97 of 274 arcs jumped by
# > 0.1 pm along e0 there, 14 at the true parameters); a jump J over a difference step h
# puts J/h in the Jacobian, and that solve spent 60 iterations and 104 s "Stalled" at the
# optimum. At 1e-7 that fit converges in 9 iterations (reltol 1e-8: 2.3x per arc, no
# further gain). The absolute tolerance barely matters for the slip lengths but sets
# the cost: measured on those 274 arcs at the truth against a reference at 1e-10/1e-13,
#   reltol/abstol   ms per arc   max |slip error|   largest 2nd difference of the slip
#   1e-6 / 1e-9        0.46          4.7 pm               4.4 pm (102 arcs > 0.1 pm)
#   1e-7 / 1e-9        0.67-0.79     0.08 pm              0.02 pm
#   1e-7 / 1e-6        0.32          0.11 pm              0.08 pm
# (2nd differences over 21 points 2e-5 apart, relative, along e0, x0, state0, μmin, τ).
# An abstol of 1e-9 mm/s had the integrator resolve the stiff layer |v| < vc at the start
# and end of every slip to 1e-6 of vc. Looser ones (1e-8, 1e-6) first had a diagnosis
# test's load-offset refit crawl at α ~0.01 to its limit: measured at 1e-6, χ² fell as
# predicted to 3 digits at α = 1 while the continuity constraints' violation rose from
# 1e-6 to 1e-2 µm (the Maratos effect); the solver's second-order correction
# (identify.fitting.problem.Problem._second_order_correction) is what let the tolerance go.
ARC_RELTOL = 1e-7
ARC_ABSTOL = 1e-6
# An arc at abstol 1e-6 that cannot be finished, or ends where no slip can (beyond
# ``_SLIP_BOUND`` times the spring's elongation plus the puller's travel over the arc:
# a frictionless spring released from rest moves the block by twice that), is integrated
# again at this tolerance. Measured on the 5-run speed benchmark at μmin 0.484, A 0.02 (a
# start 33 % off in A): two of its 27 arcs at k 2.13 N/m, 20 µN, 300 Hz ended in NaN and
# in a slip of 0.55 m; at 1e-9 both gave 5.5 µm like their neighbours, and the start's χ²
# came out finite instead of infinite (the staged start it made was thrown away for that).
STRICT_ABSTOL = 1e-9
_SLIP_BOUND = 4.0
# Arcs already integrated are remembered by their exact inputs (an arc is a pure function
# of its input column). A mode-sequence trial changes one run's triggers, and setting up
# its problem integrates every arc five times (sizing, syncing the starts, the frames
# that moved), most of them at inputs integrated before; the whole problem rebuilt for a
# kept change repeats every other run's arcs. Bounded: ~0.5 kB per arc, so at most
# ~50 MB; the memory is emptied when full.
MEMO_MAX = 100_000


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
# relative distance share one arc's differences (identify.fitting.arcs.share_groups): a run's
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


class ArcFunctions:
    """The compiled arc and arc-Jacobian Functions of one model (see module docstring)."""

    def __init__(self, model: Model, reltol: float = ARC_RELTOL, abstol: float = ARC_ABSTOL):
        self.model = model
        self.reltol, self.abstol = reltol, abstol
        d = arc_dae(model)
        self.param_names = d["names"][: len(model.parameter_names)]
        self.input_names = ("x0_um", "e0_um", "state0", *self.param_names, "k", "Nb", "fp", "M")
        self.n_in = len(self.input_names)
        self.index = {n: i for i, n in enumerate(self.input_names)}
        self.arc = compiled(lambda o: self._build(False, o), tag="arc")
        self.n_retried = 0  # arcs integrated again at STRICT_ABSTOL
        self.n_integrated = 0  # arcs integrated (not taken from the memory)
        self._memo: dict = {}  # input column (bytes) -> outputs (see MEMO_MAX)
        # arcs that could not be integrated even at STRICT_ABSTOL (NaN outputs, the trial
        # point rejected): how many, and the last one's (inputs, message); a fit reports
        # its own share (identify.fitting.driver)
        self.n_failed = 0
        self.last_failure: tuple | None = None
        self.typical = np.ones(self.n_in)  # perturbation scale per input
        for j, n in enumerate(self.param_names):
            from identify.model.params import SPECS

            self.typical[3 + j] = SPECS[n].scale

    def _integrator(self, tape: bool) -> ca.Function:
        d = arc_dae(self.model)
        dae = {k: d[k] for k in ("x", "u", "t", "p", "ode", "zero")}
        opts = dict(reltol=self.reltol, abstol=self.abstol, max_num_steps=200_000,
                    transition=transition(self.model, 1), max_events=2_000, event_tol=1e-12)
        if tape:
            opts["max_tape_steps"] = _TAPE_STEPS
        return ca.integrator("arc_int", "rosenbrock", dae, 0.0, [1.0], opts)

    def _build(self, jac: bool, fopts: dict) -> ca.Function:
        law = self.model.law
        a = ca.MX.sym("a", self.n_in)
        ix = self.index
        n_m = len(self.param_names)
        pm = a[3 : 3 + n_m]
        k, nb, fp, M = a[ix["k"]], a[ix["Nb"]], a[ix["fp"]], a[ix["M"]]
        duration_ms = M / fp / TIME_UNIT
        p = ca.vertcat(pm, k, nb, 1.0, duration_ms, fp)
        v_stick = pm[self.param_names.index("v_stick")]
        x0 = ca.vertcat(a[0], 0, a[2] / law.state_scale, 1, ca.if_else(v_stick > 0, 0, 1), 0, 0, 0)
        xf = self._integrator(jac)(x0=x0, p=p, u=a[0] + a[1])["xf"]
        moving = xf[3]
        # after the stop the frozen-time clock runs: stop time = horizon − frozen time
        stop_ms = ca.if_else(moving > 0.5, duration_ms, duration_ms - xf[5])
        y = ca.vertcat(xf[0] - a[0], xf[2] * law.state_scale, stop_ms, xf[7] * SPEED_UNIT, moving)
        if not jac:
            return ca.Function("arc", [a], [y], ["a"], ["y"], fopts)
        J = ca.jacobian(y[:N_ARC_JAC_OUTPUTS], a)
        return ca.Function("arc_jac", [a], [y, J], ["a"], ["y", "dy_da"], fopts)

    # ---------------------------------------------------------------- numeric helpers
    def inputs(self, x0_m, e0_m, state0, values: dict, k, Nb, fp, M) -> np.ndarray:
        """Stack arc inputs (SI arguments, broadcast) into the n_in × n matrix."""
        n = int(np.broadcast(np.asarray(x0_m), np.asarray(e0_m), np.asarray(state0),
                             np.asarray(k), np.asarray(Nb), np.asarray(fp), np.asarray(M)).size)
        A = np.empty((self.n_in, n))
        A[0] = np.asarray(x0_m, float) / LENGTH_UNIT
        A[1] = np.asarray(e0_m, float) / LENGTH_UNIT
        A[2] = state0
        for j, name in enumerate(self.param_names):
            # (a per-run value comes as one number per arc: identify.model.scopes)
            A[3 + j] = values[name] if name in values else SPECS[name].nominal
        A[self.index["k"]] = k
        A[self.index["Nb"]] = Nb
        A[self.index["fp"]] = fp
        A[self.index["M"]] = M
        return A

    def evaluate(self, A: np.ndarray, threads: int = 1) -> np.ndarray:
        """Outputs of every arc (columns of A). An arc the integrator cannot finish, or
        that ends where no slip can, is integrated again at ``STRICT_ABSTOL``; one that
        still fails (extreme trial parameters) gives NaN instead of failing the batch.
        Arcs integrated before at the same inputs are not integrated again (``MEMO_MAX``)."""
        A = np.ascontiguousarray(A, dtype=float)
        n = A.shape[1]
        # one bytes key per column, made in C (a view of the columns as opaque records)
        keys = np.ascontiguousarray(A.T).view(np.dtype((np.void, 8 * A.shape[0]))).ravel().tolist()
        memo = self._memo
        found = [memo.get(k) for k in keys]
        # (a loop over arcs, not samples: ~1 µs each against ~0.4 ms per integration)
        todo: dict = {}  # key -> first column needing it (a batch can repeat a column)
        for j, (k, y) in enumerate(zip(keys, found)):
            if y is None and k not in todo:
                todo[k] = j
        if todo:
            cols = list(todo.values())
            new = self._integrate(A[:, cols], threads)
            if len(memo) + len(cols) > MEMO_MAX:
                memo.clear()
            fresh = {}
            for c, k in enumerate(todo):
                fresh[k] = memo[k] = new[:, c].copy()
            found = [y if y is not None else fresh[k] for k, y in zip(keys, found)]
        return np.stack(found, axis=1) if n else np.zeros((len(ARC_OUTPUTS), 0))

    def forget(self):
        """Empty the memory of integrated arcs."""
        self._memo.clear()

    def _integrate(self, A: np.ndarray, threads: int) -> np.ndarray:
        """:meth:`evaluate` without the memory."""
        self.n_integrated += A.shape[1]
        out = self._run(self.arc, A, threads, record=self.abstol <= STRICT_ABSTOL)
        bad = ~self.plausible(A, out)
        if bad.any() and self.abstol > STRICT_ABSTOL:
            strict = arc_functions(self.model, self.reltol, STRICT_ABSTOL)
            self.n_retried += int(bad.sum())
            out[:, bad] = self._run(strict.arc, A[:, bad], 1, record=True)
        return out

    def plausible(self, A: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Per arc: finite, and a slip no longer than ``_SLIP_BOUND`` × (|e0| + the
        puller's travel over the arc) + 1 µm."""
        ix = self.index
        step_um = A[ix["step_size"]] * A[ix["step_scale"]] / LENGTH_UNIT
        bound = _SLIP_BOUND * (np.abs(A[ix["e0_um"]]) + np.abs(A[ix["M"]] * step_um)) + 1.0
        with np.errstate(invalid="ignore"):
            return np.all(np.isfinite(out), axis=0) & (np.abs(out[0]) <= bound)

    def _run(self, f: ca.Function, A: np.ndarray, threads: int, record: bool) -> np.ndarray:
        try:
            return np.array(_mapped(f, A.shape[1], threads)(A))
        except RuntimeError:
            interrupts.check()  # (CasADi hands an interrupt on as a RuntimeError)
            out = np.full((len(ARC_OUTPUTS), A.shape[1]), np.nan)
            for j in range(A.shape[1]):
                interrupts.check()
                try:
                    out[:, j] = np.array(f(A[:, j])).ravel()
                except RuntimeError as err:
                    if record:
                        self.n_failed += 1
                        self.last_failure = (A[:, j].copy(), str(err).strip().splitlines()[-1])
            return out

    def evaluate_jacobian(self, A: np.ndarray, threads: int = 1, rows=None, rel_step: float | None = None,
                          scheme: str = "central", share: float | None = None,
                          own: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Outputs and d(slip, state at horizon)/d(inputs) by finite differences.

        ``rows``: the inputs that vary (others get zero columns). ``scheme``:
        ``central`` (two integrations per input, default step 1e-6 relative) or
        ``forward`` (one): measured against central differences on 90 arcs, median
        relative error 1e-5 to 1e-7 per input, 95th percentile ≤ 6e-3 — enough for
        Gauss–Newton steps at 1.6× less integration, not for the covariance. The
        default step is at the arcs' integration noise for some arcs (a wrong sign was
        measured); the solver passes 1e-4 (``identify.fitting.arcs.SOLVE_REL_STEP``).
        ``share``: arcs whose inputs agree to this relative distance take one
        representative's differences (:func:`share_groups`); None, every arc its own.
        ``own`` (bool per arc): arcs that keep their own differences even so.
        Returns y (5 × n) and J (2 × n_in·n), arc e's block in columns
        e·n_in … (e+1)·n_in − 1.
        """
        if scheme not in ("central", "forward"):
            raise ValueError(f"scheme = {scheme!r}: choose 'central' or 'forward'")
        n = A.shape[1]
        rows = list(range(self.n_in)) if rows is None else list(rows)
        rel_step = 1e-6 if rel_step is None else rel_step
        full_n, inverse = n, None
        if share is not None and n > 1:
            y_all = self.evaluate(A, threads)  # (remembered: the solver asked for the values first)
            reps, inverse = share_groups(A, y_all, rows, self.typical, share, own=own)
            if reps.size < n:
                A = A[:, reps]
                n = A.shape[1]
            else:
                inverse = None
        h = rel_step * np.maximum(np.abs(A[rows]), self.typical[rows, None])  # (r, n)
        signs = (1.0, -1.0) if scheme == "central" else (1.0,)
        blocks = [A]
        for k, i in enumerate(rows):
            for sgn in signs:
                B = A.copy()
                B[i] += sgn * h[k]
                blocks.append(B)
        Y = self.evaluate(np.hstack(blocks), threads)
        y = Y[:, :n]
        J = np.zeros((N_ARC_JAC_OUTPUTS, self.n_in, n))
        m = len(signs)
        for k, i in enumerate(rows):
            yp = Y[:N_ARC_JAC_OUTPUTS, (1 + m * k) * n:(2 + m * k) * n]
            if scheme == "central":
                ym = Y[:N_ARC_JAC_OUTPUTS, (2 + m * k) * n:(3 + m * k) * n]
                J[:, i, :] = (yp - ym) / (2 * h[k])
            else:
                J[:, i, :] = (yp - y[:N_ARC_JAC_OUTPUTS]) / h[k]
        if inverse is not None:
            y, J, n = y_all, J[:, :, inverse], full_n
        return y, J.transpose(0, 2, 1).reshape(N_ARC_JAC_OUTPUTS, n * self.n_in)


# the inputs that differ from arc to arc (the rest are the run's conditions and the
# shared parameters); the block position counts only where the arcs depend on it
_PER_ARC = ("x0_um", "e0_um", "state0")


def share_groups(A: np.ndarray, y: np.ndarray, rows, typical: np.ndarray, tol: float,
                 own: np.ndarray | None = None):
    """Arcs that may share one arc's finite differences: (representatives, inverse), with
    arc j's group represented by column ``reps[inverse[j]]``.

    Same group: the same inputs apart from the per-arc ones (x0 counts only when it is
    among the ``rows`` differenced: without the topography no arc depends on it), those
    in the same cell of a grid ``tol`` × their scale (the larger of the arcs' mean
    magnitude and ``typical``) wide, and the same end (stopped or still moving, ``y[4]``).
    Arcs where ``own`` (bool per arc) is set, and arcs that failed, are groups of one.

    Why: the slips of one run repeat nearly the same cycle, so their inputs, and their
    derivatives, nearly agree. Measured on the 2-run speed set (274 arcs): at the fitted
    point the inputs of a run's slips agree to 0.2 %, and at ``tol`` 1e-3 (the solver's
    ``SHARE_TOL``) eight arcs' differences stood for all 274, each within 0.11 % of the
    arc's own — below the 0.6 % (95th percentile) forward differences already err by;
    at the start (continuity still far off) 85 of 274, median 0.02 %, 95th percentile
    4.6 %, largest 19 % (hence ``identify.fitting.arcs.SHARE_FEAS``)."""
    n = A.shape[1]
    per_arc = [i for i in range(len(_PER_ARC)) if i > 0 or i in set(rows)]
    other = list(range(len(_PER_ARC), A.shape[0]))
    with np.errstate(invalid="ignore"):
        size = np.abs(A[per_arc]).mean(axis=1, where=np.isfinite(A[per_arc]))
        scale = np.fmax(size, typical[per_arc])[:, None]
        cells = np.floor(A[per_arc] / (tol * scale))
    key = np.vstack([A[other], cells, np.nan_to_num(y[4:5], nan=-1.0)])
    alone = ~np.all(np.isfinite(key), axis=0)  # (an arc that failed keeps its own differences)
    if own is not None:
        alone |= np.asarray(own, bool)
    if alone.any():
        key = np.nan_to_num(key, nan=0.0, posinf=0.0, neginf=0.0)
        key = np.vstack([key, np.where(alone, np.arange(n), -1)])
    _, reps, inverse = np.unique(key.T, axis=0, return_index=True, return_inverse=True)
    return reps, inverse.ravel()


@functools.lru_cache(maxsize=64)
def _mapped(f: ca.Function, n: int, threads: int) -> ca.Function:
    return f.map(n, "thread", threads) if threads > 1 else f.map(n)


@functools.cache
def arc_functions(model: Model, reltol: float = ARC_RELTOL, abstol: float = ARC_ABSTOL) -> ArcFunctions:
    """Cached :class:`ArcFunctions` for ``model``."""
    return ArcFunctions(model, reltol, abstol)

"""Slip triggers: the residual that places a slip's contact in its trigger step's interval,
the start position an arc keeps below the interval's top, and the refinement of the
trigger steps from the residuals (:class:`TriggerRefinement`, mixed into
:class:`identify.fitting.problem.Problem`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import casadi as ca
import numpy as np

from identify.model.symbolic import LENGTH_UNIT

log = logging.getLogger(__name__)


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


@dataclass
class _Shifts:
    """Every slip's trigger shifted by each of ``shifts`` (one column per slip and shift,
    ``ev`` the slip of each): where it then starts, and its arc's inputs (``A``), at the
    solution w (``P``, ``step``, plateau levels ``x``, arcs' outputs ``Y0`` there)."""

    P: dict
    step: float
    x: np.ndarray
    off: object  # slip -> its run's zero offset (m)
    Y0: np.ndarray
    phase: np.ndarray  # per slip, its run's trigger phase
    ev: np.ndarray
    n_new: np.ndarray  # the shifted trigger step
    prev: np.ndarray  # the plateau before the slip
    e0: np.ndarray
    Pe: dict
    first: np.ndarray  # a run's first slip (no trigger residual)
    pv: np.ndarray  # the slip before
    rest: np.ndarray  # the rest from the slip before to the shifted trigger (s)
    A: np.ndarray
    nx: np.ndarray  # the slip after
    has_next: np.ndarray  # whether there is one in the run


class TriggerRefinement:
    """Moving a slip's trigger to the step its residuals point at (mixed into the problem)."""

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
        c = self._shifted(w, shifts)
        own_new, ok = self._own_trigger(c)
        # only the shifts that can be taken are integrated (measured on the 10-run speed
        # set: 77 and 71 of the 4348 and 4376 shifted arcs, where all had been, 1.5 s a call)
        Yc = np.full((c.Y0.shape[0], len(c.ev)), np.nan)
        if ok.any():
            Yc[:, ok] = self.arcs.evaluate(c.A[:, ok], self.opts.threads)
        own_now = self._own_trigger_now(c)
        next_new, next_now = self._next_trigger(c, Yc)
        slip_new, slip_now = self._slip_length(c, Yc)
        frames = self._frames_moved(c)
        gain = (own_now + next_now + slip_now) - (own_new + next_new + slip_new + frames)
        ok &= np.isfinite(gain)
        gain = np.where(ok, gain, -np.inf).reshape(self.E, len(shifts))
        return self._take_shifts(gain, shifts, min_gain)

    def _shifted(self, w: np.ndarray, shifts) -> _Shifts:
        """The shifted triggers at w and their arcs' inputs: each shifted arc starts from the
        previous end aged over the changed rest (the middle with ``arc_start="mid"``)."""
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
        Pe = self.event_params(P, ev)
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
        nx = np.minimum(ev + 1, E - 1)
        has_next = (ev + 1 < E) & ~self.ev_first[nx]
        return _Shifts(P=P, step=step, x=x, off=off, Y0=Y0, phase=phase, ev=ev, n_new=n_new, prev=prev, e0=e0,
                       Pe=Pe, first=first, pv=pv, rest=rest, A=A, nx=nx, has_next=has_next)

    def _aged_position(self, P, z_end, rest_s, fp, xp, e, Pp):
        """Where an arc's end state ``z_end``, aged over ``rest_s``, puts the capacity in a
        trigger interval (:meth:`position`, with the aging during the step)."""
        law = self.law
        return self.position(law.rest(z_end, np.maximum(rest_s, 0), P), xp, e, Pp,
                             z_before=law.rest(z_end, np.maximum(rest_s - 1 / fp, 0), P))

    def _own_trigger(self, c: _Shifts):
        """(own trigger residual², which shifts can be taken) per shift: the previous arc's
        end aged over the changed rest must exceed the capacity at the new step only, and
        the triggers stay in order within their run."""
        s_own = self._aged_position(c.P, c.Y0[1, c.pv], c.rest, self.ev_fp[c.ev], c.x[c.prev], c.e0, c.Pe)
        own_new = np.where(c.first, 0.0, trigger_residual(s_own, c.phase[c.ev]) ** 2)
        valid = c.first | ((s_own > 0) & (s_own < 1))  # the capacity must be exceeded at n_new only
        # (the triggers kept in order within their run)
        lo_ok = np.where(c.first, 1, self.ev_step[c.pv] + 1)
        hi_ok = np.where(c.has_next, self.ev_step[c.nx] - 1, np.inf)
        return own_new, valid & (c.n_new >= lo_ok) & (c.n_new <= hi_ok)

    def _own_trigger_now(self, c: _Shifts) -> np.ndarray:
        """The slip's own trigger residual² at its step now (per shift, to compare)."""
        e0_old = c.step * self.ev_step[c.ev] - c.x[c.prev]
        rest_old = (self.ev_step[c.ev] - self.ev_step[c.pv] - self.ev_M[c.pv]) / self.ev_fp[c.pv]
        s_old = self._aged_position(c.P, c.Y0[1, c.pv], rest_old, self.ev_fp[c.ev], c.x[c.prev], e0_old, c.Pe)
        return np.where(c.first, 0.0, trigger_residual(s_old, c.phase[c.ev]) ** 2)

    def _next_trigger(self, c: _Shifts, Yc: np.ndarray):
        """The next slip's trigger residual², its contact aged from the shifted arc (``Yc``)
        over the changed rest, and from the arc now."""
        nx = c.nx
        e0n = c.step * self.ev_step[nx] - c.x[self.ev_prev[nx]]
        Pn = self.event_params(c.P, nx)
        rest_n_new = (self.ev_step[nx] - c.n_new - self.ev_M[c.ev]) / self.ev_fp[c.ev]
        rest_n_old = (self.ev_step[nx] - self.ev_step[c.ev] - self.ev_M[c.ev]) / self.ev_fp[c.ev]
        sn_new = self._aged_position(c.P, Yc[1], rest_n_new, self.ev_fp[nx], c.x[self.ev_prev[nx]], e0n, Pn)
        sn_old = self._aged_position(c.P, c.Y0[1, c.ev], rest_n_old, self.ev_fp[nx], c.x[self.ev_prev[nx]], e0n, Pn)
        next_new = np.where(c.has_next, trigger_residual(sn_new, c.phase[nx]) ** 2, 0.0)
        next_now = np.where(c.has_next, trigger_residual(sn_old, c.phase[nx]) ** 2, 0.0)
        return next_new, next_now

    def _slip_length(self, c: _Shifts, Yc: np.ndarray):
        """The arc's slip against the plateau difference, χ² of the shifted arc and of the
        arc now."""
        prev = c.prev
        sig = self.pl_sigma[prev] * np.sqrt(1 / np.maximum(self.pl_n[prev], 1) + 1 / np.maximum(self.pl_n[prev + 1], 1))
        dx = c.x[prev + 1] - c.x[prev]
        return ((Yc[0] * LENGTH_UNIT - dx) / sig) ** 2, ((c.Y0[0, c.ev] * LENGTH_UNIT - dx) / sig) ** 2

    def _frames_moved(self, c: _Shifts) -> np.ndarray:
        """The χ² change of the frames that change plateau with the shift, at the fitted levels."""
        ev, n_new, prev, x, step = c.ev, c.n_new, c.prev, c.x, c.step
        frames = np.zeros(len(ev))
        for k in range(len(ev)):
            e = ev[k]
            run = self.runs[self.ev_run[e]]
            evr = run.events
            lo_n, hi_n = sorted((self.ev_step[e], n_new[k]))
            sel = (evr.steps >= lo_n) & (evr.steps < hi_n)
            if not sel.any():
                continue
            ee = evr.trace.elongation[sel] - c.off(e)
            before = ((ee - (step * evr.steps[sel] - x[prev[k]])) ** 2).sum()
            after = ((ee - (step * evr.steps[sel] - x[prev[k] + 1])) ** 2).sum()
            frames[k] = ((before - after) if n_new[k] > self.ev_step[e] else (after - before)) / run.sigma**2
        return frames

    def _take_shifts(self, gain: np.ndarray, shifts, min_gain: float):
        """Each slip's best shift (gain: slips × shifts) where it gains more than ``min_gain``;
        of two neighbours moved to meet, the less certain stays. ({run: steps}, slips moved)."""
        E = self.E
        best = np.argmax(gain, axis=1)
        moved = gain[np.arange(E), best] > min_gain
        new_steps = self.ev_step.copy()
        new_steps[moved] += np.array(shifts)[best[moved]]
        # two neighbours moved towards each other can meet: the one that gains less goes
        # back, one clash at a time (a slip in two clashes may already be back when the
        # second is looked at; and a clash of two slips neither of which moved was there
        # before, in the detected sequence, and is not this refinement's to undo)
        for _ in range(E):
            clash = np.nonzero((np.diff(new_steps) <= 0) & (self.ev_run[1:] == self.ev_run[:-1]))[0]
            clash = [i for i in clash if moved[i] or moved[i + 1]]
            if not clash:
                break
            i = clash[0]
            j = min((p for p in (i, i + 1) if moved[p]), key=lambda p: gain[p, best[p]])
            moved[j] = False
            new_steps[j] = self.ev_step[j]
        changes = {}
        for ri in np.unique(self.ev_run[moved]):
            sel = self.ev_run == ri
            changes[int(ri)] = np.sort(new_steps[sel]).astype(int)
        return changes, int(moved.sum())

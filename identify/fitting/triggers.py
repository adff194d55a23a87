"""Slip triggers: the residual that places a slip's contact in its trigger step's interval,
the start position an arc keeps below the interval's top, and the refinement of the
trigger steps from the residuals (:class:`TriggerRefinement`, mixed into
:class:`identify.fitting.problem.Problem`).
"""

from __future__ import annotations

import logging
import math

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

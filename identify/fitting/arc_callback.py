"""The arcs inside the CasADi NLP: :class:`ArcCallback` gives the slips' arc values, or
their Jacobians, for all slips at once, memoised on the input matrix."""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from identify import interrupts
from identify.fitting.arcs import SOLVE_REL_STEP, ArcFunctions, share_groups
from identify.fitting.exact_arcs import exact_arcs

__all__ = ["ArcCallback", "blockdiag_sparsity"]


class ArcCallback(ca.Callback):
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
        """Exact arc Jacobians (:mod:`identify.fitting.exact_arcs`), in the layout of
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
        JA = ca.MX(blockdiag_sparsity(2, n_in, E), ca.vec(self.jac_callback(A)))  # (2E × n_in·E)
        # rows 2e + r of JA are entries 5e + r of vec(Y)
        rows = (5 * np.arange(E)[:, None] + np.arange(2)[None, :]).ravel()
        S = ca.DM(ca.Sparsity.triplet(5 * E, 2 * E, rows.tolist(), list(range(2 * E))), 1.0)
        return ca.Function(name, [A, out], [ca.mtimes(S, JA)], inames, onames, opts)

    def eval(self, arg):
        try:
            return self._eval(arg)
        except KeyboardInterrupt:
            interrupts.note()  # (CasADi hands it on as a RuntimeError: see identify.interrupts)
            raise

    def _eval(self, arg):
        interrupts.check()
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

    def forget(self) -> None:
        """Forget the remembered value (the scheme of the differences changed)."""
        self._key = None


def blockdiag_sparsity(rows: int, cols: int, E: int) -> ca.Sparsity:
    """E dense rows × cols blocks on the diagonal (column-major nonzeros = vec of the
    rows × cols·E matrix of the blocks side by side)."""
    r = np.tile(np.arange(rows), cols * E) + np.repeat(np.arange(E), rows * cols) * rows
    c = np.repeat(np.arange(cols * E), rows)
    return ca.Sparsity.triplet(rows * E, cols * E, r.tolist(), c.tolist())

"""Sparse linear systems with a few dense rows and columns: the KKT systems of the fit.

The multiple-shooting KKT matrix is banded run by run (plateau levels, slips and start
positions in sequence), but for the shared parameters, whose rows and columns touch
every slip. SuperLU on the whole matrix picks pivots in those dense rows and fills in:
measured on the 10-run speed set's KKT matrix (4352 square, 58 028 nonzeros), 4.9
million nonzeros in L + U and 0.22 s per factorisation, for each Gauss–Newton step,
second-order correction and covariance. :func:`solve` factorises the matrix without
its dense rows and columns (43 512 nonzeros in L + U, 4.5 ms there) and closes the
system with their small dense Schur complement; the residual is the same (5e-10
against 6e-10). It falls back to the whole matrix whenever that route does not give a
clean answer, so a singular system is reported as it was (RuntimeError).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = ["solve"]

# a column is dense with more nonzeros than DENSE_FACTOR times the median and than
# DENSE_MIN; the route is taken for at most MAX_DENSE of them (the complement is dense)
DENSE_FACTOR = 10.0
DENSE_MIN = 50
MAX_DENSE = 64
# the eliminated solution is kept when its residual is within this share of the
# system's scale (‖K‖·‖x‖ + ‖b‖, max norms); else the whole matrix is factorised
BACKWARD_TOL = 1e-10


def dense_columns(K: sp.spmatrix) -> np.ndarray:
    """Indices of the columns of ``K`` (CSC) that count as dense (see DENSE_FACTOR)."""
    counts = np.diff(K.indptr)
    if counts.size == 0:
        return np.zeros(0, int)
    return np.flatnonzero(counts > max(DENSE_MIN, DENSE_FACTOR * float(np.median(counts))))


def solve(K: sp.spmatrix, b: np.ndarray) -> np.ndarray:
    """x with K·x = b (b a vector or a matrix of right-hand sides), K square and sparse.
    RuntimeError when K is singular (as ``scipy.sparse.linalg.splu``)."""
    K = sp.csc_matrix(K)
    b = np.asarray(b, float)
    dense = dense_columns(K)
    if 0 < dense.size <= MAX_DENSE and dense.size < K.shape[0]:
        x = _eliminated(K, b, dense)
        if x is not None:
            return x
    return spla.splu(K).solve(b)


def _eliminated(K: sp.csc_matrix, b: np.ndarray, dense: np.ndarray) -> np.ndarray | None:
    """The solution with the ``dense`` rows and columns eliminated last, or None when
    the sparse part is singular or the result is not clean."""
    n = K.shape[0]
    rest = np.setdiff1d(np.arange(n), dense)
    B = b.reshape(n, -1)
    k = B.shape[1]
    K_rows = K[rest]
    S = K_rows[:, rest].tocsc()
    U = K_rows[:, dense].toarray()  # (rest, dense)
    K_dense = K[dense]
    V = K_dense[:, rest].toarray()  # (dense, rest)
    D = K_dense[:, dense].toarray()
    try:
        X = spla.splu(S).solve(np.column_stack([B[rest], U]))
        xs, Y = X[:, :k], X[:, k:]
        # (a singular sparse part gives inf/NaN here: judged below, not warned of)
        with np.errstate(invalid="ignore", over="ignore"):
            xd = np.linalg.solve(D - V @ Y, B[dense] - V @ xs)
    except (RuntimeError, np.linalg.LinAlgError):
        return None
    x = np.empty((n, k))
    x[dense] = xd
    with np.errstate(invalid="ignore", over="ignore"):
        x[rest] = xs - Y @ xd
    if not np.all(np.isfinite(x)):
        return None
    with np.errstate(over="ignore", invalid="ignore"):  # (a near-singular system: the whole matrix decides)
        scale = abs(K).max() * np.abs(x).max() + np.abs(B).max()
        resid = np.abs(K @ x - B).max()
    if not (np.isfinite(scale) and resid <= BACKWARD_TOL * scale):
        return None
    return x.reshape(b.shape)

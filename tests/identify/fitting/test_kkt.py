"""Sparse systems with a few dense rows and columns (identify.fitting.kkt)."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from identify.fitting import kkt


def _bordered_kkt(n=400, m=300, n_dense=4, seed=0):
    """A KKT matrix like the fit's: H banded with n_dense parameters touching everything,
    constraints chaining neighbouring variables and every parameter."""
    rng = np.random.default_rng(seed)
    Jr = sp.lil_matrix((2 * n, n))
    for i in range(2 * n):
        j = (i // 2) % (n - n_dense) + n_dense
        Jr[i, j] = rng.normal()
        Jr[i, min(j + 1, n - 1)] = rng.normal()
        Jr[i, :n_dense] = rng.normal(size=n_dense)
    H = (Jr.T @ Jr).tocsc()
    Jg = sp.lil_matrix((m, n))
    for i in range(m):
        j = i + n_dense
        Jg[i, j], Jg[i, j + 1] = 1.0, -1.0
        Jg[i, :n_dense] = 0.1 * rng.normal(size=n_dense)
    K = sp.bmat([[H, Jg.T.tocsc()], [Jg.tocsc(), None]], format="csc")
    return K, rng.normal(size=n + m)


def test_the_dense_rows_are_eliminated_last_with_the_same_solution():
    K, b = _bordered_kkt()
    np.testing.assert_array_equal(kkt.dense_columns(K), np.arange(4))
    ref = spla.splu(K).solve(b)
    x = kkt.solve(K, b)
    np.testing.assert_allclose(x, ref, rtol=0, atol=1e-9 * np.abs(ref).max())
    # several right-hand sides at once (the covariance's)
    X = kkt.solve(K, np.column_stack([b, -2 * b]))
    assert X.shape == (K.shape[0], 2)
    np.testing.assert_allclose(X[:, 1], -2 * ref, rtol=0, atol=1e-9 * np.abs(ref).max())


def test_the_elimination_fills_in_far_less_than_the_whole_matrix():
    """Why the route exists: SuperLU's pivots in the dense rows fill the factors in."""
    K, _ = _bordered_kkt(n=800, m=600)
    dense = kkt.dense_columns(K)
    rest = np.setdiff1d(np.arange(K.shape[0]), dense)
    whole = spla.splu(K)
    part = spla.splu(K[rest][:, rest].tocsc())
    assert part.L.nnz + part.U.nnz < 0.1 * (whole.L.nnz + whole.U.nnz)  # (measured: 88x less)


def test_a_singular_sparse_part_falls_back_to_the_whole_matrix():
    """A variable seen only through the dense rows: the sparse part is singular, the
    whole matrix is not."""
    K = sp.lil_matrix(np.diag([4.0, 3.0, 2.0, 5.0] + [1.0] * 60))
    K[5, 5] = 0.0  # the sixth variable couples to the dense ones only
    for j in range(4):
        K[j, 4:] = 0.5
        K[4:, j] = 0.5
    K = K.tocsc()
    b = np.arange(K.shape[0], dtype=float)
    assert 5 not in set(kkt.dense_columns(K).tolist())
    np.testing.assert_allclose(kkt.solve(K, b), np.linalg.solve(K.toarray(), b), rtol=1e-9, atol=1e-9)


def test_a_singular_system_is_reported_as_splu_reports_it():
    K, b = _bordered_kkt()
    K = K.tolil()
    K[10, :] = 0.0
    K[:, 10] = 0.0
    with pytest.raises(RuntimeError):
        kkt.solve(K.tocsc(), b)


def test_a_matrix_without_dense_columns_is_solved_whole():
    K = sp.diags([1.0, 2.0, 3.0]).tocsc()
    assert kkt.dense_columns(K).size == 0
    np.testing.assert_allclose(kkt.solve(K, np.ones(3)), [1.0, 0.5, 1 / 3])


def test_a_solution_too_large_to_check_is_left_to_the_whole_matrix():
    """An elimination whose residual check overflows (measured in a diagnosis refit: a
    near-singular step) is not taken: the whole matrix decides, without a warning."""
    import warnings

    K, b = _bordered_kkt()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert kkt._eliminated(K, 1e304 * b, kkt.dense_columns(K)) is None  # (x ~1e307, ‖K‖ 835)
        assert kkt._eliminated(K, b, kkt.dense_columns(K)) is not None


def test_a_variable_an_interior_point_left_next_to_its_bound_is_held_there():
    """bounded_step holds a variable the step pushes outwards at a bound it sits within
    BOUND_NEAR of its range of (an interior-point iterate never reaches the bound): its
    step is zero and the others' gain is the one the bound allows. Before, A left 9e-8 off
    its bound (range 100) was stepped to -5.7, a gain of 920 in ½χ² no step could take."""
    from identify.fitting.convergence import BOUND_NEAR, bounded_step

    # min ½|r|², r = (x0 - 1, x1 + 1): the unconstrained step takes x1 to -1, below its bound 0
    H = sp.identity(2, format="csc")
    Jg = sp.csr_matrix((0, 2))
    lbx, ubx = np.array([-10.0, 0.0]), np.array([10.0, 100.0])
    for x1, held in ((9e-8, True), (0.3 * BOUND_NEAR * 100, True), (3 * BOUND_NEAR * 100, False)):
        w = np.array([0.0, x1])
        grad = np.array([w[0] - 1.0, w[1] + 1.0])  # (H = I: Jrᵀr)
        d, _, free = bounded_step(H, Jg, grad, np.zeros(0), w, lbx, ubx, np.zeros(2, bool))
        assert d[0] == pytest.approx(1.0)
        assert bool(d[1] == 0.0 and 1 not in free) is held, (x1, d)
    # a variable at its bound the step moves inwards is free
    w = np.array([0.0, 9e-8])
    d, _, free = bounded_step(H, Jg, np.array([-1.0, -1.0]), np.zeros(0), w, lbx, ubx, np.zeros(2, bool))
    assert 1 in free and d[1] == pytest.approx(1.0)

"""Constraint sets: the one-sided form (dense and sparse alike), stacking per subsystem, the excess."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from dmpc.core.qp_status import SOLVED, QPStatus
from dmpc.core.system import LinearSet, stack_sets

INF = np.inf
TWO_SIDED = LinearSet(np.array([[1.0, 2.0], [0.0, 1.0], [1.0, -1.0]]), np.array([-1.0, -INF, -INF]),
                      np.array([3.0, 2.0, INF]))


def test_one_sided_keeps_the_finite_sides_row_by_row_upper_first():
    G, g = TWO_SIDED.one_sided()
    np.testing.assert_array_equal(G, [[1.0, 2.0], [-1.0, -2.0], [0.0, 1.0]])
    np.testing.assert_array_equal(g, [3.0, 1.0, 2.0])
    for x in (np.array([0.5, 0.7]), np.array([0.5, 2.5]), np.array([-3.0, 0.0])):
        Hx = TWO_SIDED.H @ x
        assert np.all(G @ x <= g) == bool(np.all((Hx <= TWO_SIDED.upper) & (Hx >= TWO_SIDED.lower)))


def test_one_sided_of_a_sparse_set_is_the_same_sparse_matrix():
    G, g = TWO_SIDED.one_sided()
    Gs, gs = LinearSet(sp.csr_matrix(TWO_SIDED.H), TWO_SIDED.lower, TWO_SIDED.upper).one_sided()
    assert sp.issparse(Gs)
    np.testing.assert_array_equal(Gs.toarray(), G)
    np.testing.assert_array_equal(gs, g)


def test_a_set_without_finite_sides_has_no_rows():
    G, g = LinearSet(np.eye(2), np.full(2, -INF), np.full(2, INF)).one_sided()
    assert G.shape == (0, 2) and g.shape == (0,)


def test_stacking_is_block_diagonal_dense_or_sparse_and_skips_missing_sets():
    box = LinearSet.box([-1.0], [1.0])
    stacked = stack_sets([TWO_SIDED, None, box], [2, 3, 1])
    assert stacked.H.shape == (4, 6)
    np.testing.assert_array_equal(stacked.H[:3, :2], TWO_SIDED.H)
    np.testing.assert_array_equal(stacked.H[3], [0, 0, 0, 0, 0, 1.0])
    np.testing.assert_array_equal(stacked.upper, [3.0, 2.0, INF, 1.0])
    sparse = stack_sets([TWO_SIDED, None, box], [2, 3, 1], sparse=True)
    assert sp.issparse(sparse.H)
    np.testing.assert_array_equal(sparse.H.toarray(), stacked.H)
    assert stack_sets([None, None], [2, 1]) is None


def test_excess_per_row_with_and_without_tolerance():
    values = np.array([[0.0, 0.0], [3.0, 1.0], [0.0, 3.0]])
    excess = TWO_SIDED.excess(values)
    np.testing.assert_allclose(excess, [-1.0, 2.0, 3.0])
    widened = TWO_SIDED.excess(values, tolerance=1e-3)
    np.testing.assert_allclose(widened, excess - [1e-3, 3e-3, 3e-3])  # each bound moved by 1e-3 * max(1, |bound|)
    assert TWO_SIDED.largest_excess(values, tolerance=1e-3) == pytest.approx(3.0 - 3e-3)
    assert TWO_SIDED.excess(np.zeros((0, 2))).shape == (0,) and TWO_SIDED.largest_excess(np.zeros((0, 2))) == -INF


def test_excess_of_infinite_and_missing_values():
    box = LinearSet.box([-1.0, -INF], [1.0, INF])
    excess = box.excess(np.array([[0.0, INF], [INF, 0.0], [np.nan, 0.0]]))
    assert excess[0] == -1.0  # an infinite value against an infinite bound does not count
    assert excess[1] == INF and np.isnan(excess[2])


def test_the_solved_statuses_are_the_feasible_ones():
    assert SOLVED == {s.value for s in QPStatus if s.feasible}
    assert {"solved", "solved_inaccurate"} == SOLVED

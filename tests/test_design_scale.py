"""The offline design at scale: the same terminal set, sigma and gains as the plain methods give.

- X^f with redundancy decided on each row's neighbourhood (dmpc.offline.redundancy) equals X^f
  from one LP over the whole set per test, row for row;
- LMI (11) built block by block for Clarabel (dmpc.offline.lmi_conic) has the optimum of the
  cvxpy formulation;
- the spectral radius from ARPACK (large systems) equals the one from all eigenvalues.
"""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from dmpc.offline.gains import CLARABEL_SETTINGS, DENSE_EIGENVALUES, _lmi_problem, _solve_quietly, spectral_radius
from dmpc.offline.lmi_conic import solve_lmi
from dmpc.offline.redundancy import SparseRows
from dmpc.offline.terminal_set import maximal_admissible_set
from dmpc.scenario import build_system, load_scenario
from tests.helpers.reference import K_PAPER

CHAIN = "scenarios/chain.yaml"


def chain(M: int):
    return build_system(load_scenario(CHAIN, {"family.M": M}))


@pytest.mark.parametrize("M, gains", [(6, "paper"), (12, "paper"), (10, "lmi")])
def test_local_redundancy_gives_the_plain_terminal_set(M, gains):
    system = chain(M)
    if gains == "paper":
        K = [K_PAPER[3]] * M  # some of its rows are redundant: the removal pass drops them
    else:
        from dmpc.offline.gains import lmi_gains
        K = lmi_gains(system).K
    local = maximal_admissible_set(system, K, local=True)
    plain = maximal_admissible_set(system, K, local=False)
    assert (local.rows, local.t_star) == (plain.rows, plain.t_star)
    np.testing.assert_allclose(local.omega, plain.omega, rtol=0, atol=1e-12)
    for alpha in (np.zeros(system.n), np.random.default_rng(M).uniform(-0.2, 0.2, system.n)):
        assert local.sigma(alpha) == pytest.approx(plain.sigma(alpha), abs=1e-12)


def test_paper_terminal_set_is_unchanged():
    """The paper's figures: 22 rows, t* = 2, sigma(0) = 1.3454 (docs/algorithm.md)."""
    system = build_system(load_scenario("scenarios/paper.yaml"))
    for local in (True, False):
        t = maximal_admissible_set(system, K_PAPER, local=local)
        assert (t.rows, t.t_star) == (22, 2)
        assert t.sigma(np.zeros(8)) == pytest.approx(1.3454, abs=1e-4)


def test_irredundant_drops_implied_rows_in_order():
    """Scaled copies and a row implied by two others go; the first of two equal rows stays."""
    rows = np.array([[1.0, 0, 0, 0], [0.5, 0, 0, 0], [0, 1.0, 0, 0], [0, 0.5, 0, 0], [0.5, 0.5, 0, 0],
                     [-1.0, 0, 0, 0], [0, -1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 1.0, 0], [0, 0, -1.0, 0],
                     [0, 0, 0, 1.0], [0, 0, 0, -1.0], [0, 0, 0.3, 0.3]])
    for local in (True, False):
        kept = SparseRows(sp.csr_matrix(rows), local=local).irredundant()
        assert list(kept) == [0, 2, 5, 6, 8, 9, 10, 11]


def test_lmi_built_for_clarabel_has_the_cvxpy_optimum():
    system = chain(4)
    scaling = [np.ones(s.n) for s in system.subsystems]
    sol = solve_lmi(system, scaling, "logdet", 1e-4, CLARABEL_SETTINGS)
    problem, Xs, Ys = _lmi_problem(system, scaling, "logdet", 1e-4)
    assert _solve_quietly(problem, "test", **CLARABEL_SETTINGS)
    assert sol.status == "optimal"
    ours = sum(np.linalg.slogdet(X)[1] for X in sol.X)
    theirs = sum(np.linalg.slogdet(X.value)[1] for X in Xs)
    assert ours == pytest.approx(theirs, rel=1e-7)
    for X, Y, Xc, Yc in zip(sol.X, sol.Y, Xs, Ys):
        np.testing.assert_allclose(Y @ np.linalg.inv(X), Yc.value @ np.linalg.inv(Xc.value), atol=1e-5)


def test_lmi_feasibility_and_scaling():
    system = chain(3)
    scaled = solve_lmi(system, [np.array([2.0, 0.5])] * 3, "feasibility", 0.0, CLARABEL_SETTINGS)
    assert scaled.status in ("optimal", "optimal_inaccurate")
    assert all(np.linalg.eigvalsh(X).min() > 0 for X in scaled.X)


def test_spectral_radius_of_a_large_sparse_matrix():
    n = DENSE_EIGENVALUES + 100
    rng = np.random.default_rng(3)
    M = sp.random(n, n, density=4.0 / n, random_state=rng).toarray() * 0.3 + np.diag(rng.uniform(-0.9, 0.9, n))
    assert spectral_radius(M) == pytest.approx(float(np.max(np.abs(np.linalg.eigvals(M)))), abs=1e-10)

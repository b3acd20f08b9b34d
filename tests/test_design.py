"""Offline design (docs/algorithm.md, "Offline design", and the offline side of "What is and is not guaranteed").

The paper's example (docs/algorithm.md, "The paper's example, corrected") is checked against its reference figures and
against independent computations: the global matrices are written out by hand in
``tests/helpers/reference.py`` and every set property is an LP solved here with scipy.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from dmpc.offline import DesignError
from dmpc.offline.tubes import RevisionBound, robust_tightening
from dmpc.scenario import build_system, load_scenario
from dmpc.setup import prepare
from tests.helpers.reference import (
    A_II,
    A_IJ,
    B_II,
    CHAIN,
    K_PAPER,
    P_PAPER,
    PAPER,
    PAPER_LMI,
    Q_I,
    R_I,
    U_BAR,
    block_diag,
    chain_matrices,
    cube_vertices,
    lp_max,
    sigma_lp,
)

N_SUBSYSTEMS = 4


@pytest.fixture(scope="module")
def paper():
    return prepare(load_scenario(PAPER))


@pytest.fixture(scope="module")
def paper_closed_loop():
    """A + BK of the paper's example, built by hand from the printed (K_2-fixed) gains."""
    A, B = chain_matrices(N_SUBSYSTEMS)
    return A + B @ block_diag(K_PAPER)


def lyapunov_margin(A, B, K, P, Q, R) -> float:
    AK = A + B @ K
    lhs = AK.T @ P @ AK - P + Q + K.T @ R @ K
    return float(np.max(np.linalg.eigvalsh((lhs + lhs.T) / 2)))


# ---------------------------------------------------------------- the paper's example, given gains

def test_paper_system_matches_the_hand_built_matrices(paper):
    A, B = chain_matrices(N_SUBSYSTEMS)
    np.testing.assert_array_equal(paper.system.A, A)
    np.testing.assert_array_equal(paper.system.B, B)
    for i in range(N_SUBSYSTEMS):
        np.testing.assert_array_equal(paper.design.gains.K[i], K_PAPER[i])
        np.testing.assert_allclose(paper.design.gains.P[i], P_PAPER[i], rtol=0, atol=1e-15)


def test_paper_reference_figures(paper):
    d = paper.design
    assert d.terminal.rows == 22
    assert d.terminal.omega.shape == (22, 8)
    assert d.terminal.t_star == 2
    assert d.sigma0 == pytest.approx(1.3454, abs=1e-3)
    assert d.gains.rho == pytest.approx(0.697, abs=1e-3)
    assert d.gains.lyapunov_margin == pytest.approx(-0.350, abs=1e-3)


def test_paper_rho_and_margin_independently(paper, paper_closed_loop):
    """rho(A+BK) and the (10) margin recomputed from the hand-built matrices."""
    A, B = chain_matrices(N_SUBSYSTEMS)
    K, P = block_diag(K_PAPER), block_diag(P_PAPER)
    Q, R = block_diag([Q_I] * 4), block_diag([R_I] * 4)
    rho = float(np.max(np.abs(np.linalg.eigvals(paper_closed_loop))))
    margin = lyapunov_margin(A, B, K, P, Q, R)
    assert rho == pytest.approx(0.697, abs=1e-3)
    assert margin == pytest.approx(-0.350, abs=1e-3)
    assert paper.design.gains.rho == pytest.approx(rho, abs=1e-12)
    assert paper.design.gains.lyapunov_margin == pytest.approx(margin, abs=1e-9)


def test_omega_is_positively_invariant(paper, paper_closed_loop):
    """For every row l: max Omega_l A_K x over X^f <= 1 (+1e-7)."""
    omega = paper.design.terminal.omega
    ones = np.ones(omega.shape[0])
    for l in range(omega.shape[0]):
        assert lp_max(omega[l] @ paper_closed_loop, omega, ones) <= 1.0 + 1e-7, f"row {l}"


def test_terminal_gain_respects_the_input_bound_on_xf(paper):
    """|K_i x| <= 2.5 on X^f (one LP per sign and input row), and the bound is attained."""
    omega = paper.design.terminal.omega
    ones = np.ones(omega.shape[0])
    K = block_diag(K_PAPER)
    best = 0.0
    for r in range(K.shape[0]):
        for sign in (1.0, -1.0):
            value = lp_max(sign * K[r], omega, ones)
            assert value <= U_BAR + 1e-7, f"input row {r}, sign {sign}"
            best = max(best, value)
    # X^f is the *maximal* admissible set, so some input constraint is active on it
    assert best == pytest.approx(U_BAR, abs=1e-6)


def test_omega_is_the_maximal_admissible_set(paper, paper_closed_loop):
    """X^f contains every x with |K A_K^t x| <= 2.5 for t = 0..12, and has no redundant rows.

    Together with invariance and admissibility this pins X^f down as the maximal admissible set.
    """
    omega = paper.design.terminal.omega
    K = block_diag(K_PAPER)
    rows, power = [], np.eye(8)
    for _ in range(13):
        rows.append(K @ power)
        power = paper_closed_loop @ power
    G = np.vstack(rows)
    G = np.vstack([G, -G]) / U_BAR
    ones = np.ones(G.shape[0])
    for l in range(omega.shape[0]):
        assert lp_max(omega[l], G, ones) <= 1.0 + 1e-7, f"row {l} cuts off admissible states"
    # no redundant row: relaxing row l lets Omega_l x exceed 1 over the other rows
    for l in range(omega.shape[0]):
        others = np.delete(omega, l, axis=0)
        cap = np.vstack([others, omega[l]])
        value = lp_max(omega[l], cap, np.append(np.ones(others.shape[0]), 2.0))
        assert value > 1.0 + 1e-7, f"row {l} is redundant"


alphas = st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=8, max_size=8).map(np.array)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(direction=alphas, depth=st.floats(0.0, 0.98))
@example(direction=np.array([0.0, 0.0, 0.0, 0.03125, 0.0, 0.0, 0.0, 1.0]), depth=1e-6)  # needs a tight LP tolerance
def test_sigma_equals_the_lp_and_the_cube_fits(paper, direction, depth):
    """sigma(alpha) = the LP optimum; the 256 cube vertices are inside X^f; a larger cube is not."""
    terminal = paper.design.terminal
    omega = terminal.omega
    scale = float(np.max(omega @ direction))
    alpha = direction * (depth / scale) if scale > 1e-9 else np.zeros(8)
    assert np.all(omega @ alpha <= 1.0)
    sigma = terminal.sigma(alpha)
    assert sigma == pytest.approx(sigma_lp(omega, alpha), abs=1e-9)
    vertices = cube_vertices(alpha, sigma)
    assert vertices.shape == (256, 8)
    assert np.all(vertices @ omega.T <= 1.0 + 1e-9)
    bigger = cube_vertices(alpha, sigma * (1 + 1e-6) + 1e-9)
    assert np.any(bigger @ omega.T > 1.0)


def test_sigma_at_zero_is_the_smallest_inverse_row_norm(paper):
    omega = paper.design.terminal.omega
    assert paper.design.sigma0 == pytest.approx(1.0 / np.max(np.abs(omega).sum(axis=1)), rel=1e-12)
    assert paper.design.sigma0 == pytest.approx(sigma_lp(omega, np.zeros(8)), abs=1e-9)


# ---------------------------------------------------------------- LMI gains

@pytest.fixture(scope="module", params=["paper-lmi", "chain-8"])
def lmi(request):
    if request.param == "paper-lmi":
        prepared = prepare(load_scenario(PAPER_LMI))
        M = 4
    else:
        prepared = prepare(load_scenario(CHAIN, {"family.M": 8}))
        M = 8
    return prepared, M


def test_lmi_gains_are_stable_and_satisfy_10(lmi):
    prepared, M = lmi
    g = prepared.design.gains
    assert g.method == "lmi"
    A, B = chain_matrices(M)
    np.testing.assert_array_equal(prepared.system.A, A)
    K, P = block_diag(g.K), block_diag(g.P)
    Q, R = block_diag([Q_I] * M), block_diag([R_I] * M)
    # block-diagonal structure of the design itself
    assert K.shape == (M, 2 * M) and P.shape == (2 * M, 2 * M)
    rho = float(np.max(np.abs(np.linalg.eigvals(A + B @ K))))
    assert rho < 1.0
    assert g.rho == pytest.approx(rho, abs=1e-10)
    p_eigs = np.linalg.eigvalsh(P)
    assert np.min(p_eigs) > 0
    margin = lyapunov_margin(A, B, K, P, Q, R)
    assert margin <= 1e-6 * np.max(p_eigs)
    # the log-det optimum sits on the boundary of (10)
    assert abs(margin) <= 1e-3 * np.max(p_eigs)


def test_lmi_terminal_set_is_invariant(lmi):
    prepared, M = lmi
    A, B = chain_matrices(M)
    AK = A + B @ block_diag(prepared.design.gains.K)
    omega = prepared.design.terminal.omega
    ones = np.ones(omega.shape[0])
    for l in range(omega.shape[0]):
        assert lp_max(omega[l] @ AK, omega, ones) <= 1.0 + 1e-7, f"row {l}"


def test_lqr_on_the_paper_is_rejected_naming_10():
    with pytest.raises(DesignError, match=r"\(10\)"):
        prepare(load_scenario(PAPER, {"design.gains": "lqr"}))


def test_lqr_rejection_is_right():
    """Independently: per-subsystem DARE gains violate (10) on the coupled paper system."""
    import scipy.linalg as sla
    Pi = sla.solve_discrete_are(A_II, B_II, Q_I, R_I)
    Ki = -np.linalg.solve(R_I + B_II.T @ Pi @ B_II, B_II.T @ Pi @ A_II)
    A, B = chain_matrices(4)
    margin = lyapunov_margin(A, B, block_diag([Ki] * 4), block_diag([Pi] * 4), np.eye(8), 0.01 * np.eye(4))
    assert margin > 1e-3


# ---------------------------------------------------------------- negative cases

@pytest.mark.parametrize("K2, expected_rho22", [
    ([[0.7452, 1.113]], 3.42),    # as printed in the paper: both minus signs lost
    ([[0.7452, -1.113]], 1.793),  # only the first minus sign lost
])
def test_printed_k2_is_rejected_as_unstable(K2, expected_rho22):
    K2 = np.array(K2)
    rho22 = float(np.max(np.abs(np.linalg.eigvals(A_II + B_II @ K2))))
    assert rho22 == pytest.approx(expected_rho22, abs=5e-3)  # independently: it destabilises its own subsystem
    with pytest.raises(DesignError, match=r"unstable.*spectral radius") as info:
        prepare(load_scenario(PAPER, {"subsystems.1.K": K2.tolist()}))
    assert f"{rho22:.4g}" in str(info.value)


def test_input_coupling_equal_to_bii_is_rejected_as_unstable():
    overrides = {f"couplings.{c}.B": [[1.0], [1.0]] for c in range(6)}
    scenario = load_scenario(PAPER, overrides)
    system = build_system(scenario)
    A, B = chain_matrices(4)
    for i in range(4):
        for j in (i - 1, i + 1):
            if 0 <= j < 4:
                B[2 * i:2 * i + 2, j] = B_II[:, 0]
    np.testing.assert_array_equal(system.B, B)
    rho = float(np.max(np.abs(np.linalg.eigvals(A + B @ block_diag(K_PAPER)))))
    assert rho > 1.0
    with pytest.raises(DesignError, match="unstable") as info:
        prepare(scenario)
    assert f"{rho:.4g}" in str(info.value)


PAPER_LITERAL_TUBE = {
    "options.tube": "robust",
    **{f"subsystems.{i}.revision_bound": {"state": [2.8, 2.8], "input": [2.5]} for i in range(4)},
}


def test_paper_literal_tube_is_an_empty_set_error():
    with pytest.raises(DesignError, match="empty"):
        prepare(load_scenario(PAPER, PAPER_LITERAL_TUBE))


def test_paper_literal_tube_empties_u2_at_t1():
    """By hand: h_E(1)(K_2^T) = sum_j 2.8 * ||A_2j^T K_2^T||_1 = 2.910 > 2.5, so U_2 is empty at t = 1."""
    scenario = load_scenario(PAPER, PAPER_LITERAL_TUBE)
    system = build_system(scenario)
    margin = 2 * 2.8 * np.abs(A_IJ.T @ K_PAPER[1][0]).sum()
    assert margin == pytest.approx(2.9103, abs=1e-3)
    bounds = {i: RevisionBound(np.array([2.8, 2.8]), np.array([2.5])) for i in range(4)}
    with pytest.raises(DesignError, match=r"empty at t = 1"):
        robust_tightening(system, 1, K_PAPER[1], 10, bounds)


def test_robust_tightening_margins_by_hand():
    """Small revision bounds: the margins equal the support-function sums computed here."""
    system = build_system(load_scenario(PAPER))
    xbar, ubar = np.array([0.01, 0.02]), np.array([0.03])
    bounds = {i: RevisionBound(xbar, ubar) for i in range(4)}
    i, N = 1, 4  # subsystem 2 has neighbours 1 and 3
    Gamma = A_II + B_II @ K_PAPER[i]

    def h_E(t, d):
        total = 0.0
        for s in range(t):
            ds = np.linalg.matrix_power(Gamma, s).T @ d
            total += 2 * (xbar @ np.abs(A_IJ.T @ ds))  # two neighbours, B_ij = 0
        return total

    tight = robust_tightening(system, i, K_PAPER[i], N, bounds)
    expected_u = np.array([[h_E(t, K_PAPER[i][0])] for t in range(N)])
    np.testing.assert_allclose(tight.input_margin, expected_u, atol=1e-14)
    np.testing.assert_allclose(tight.terminal_margin, [h_E(N, e) for e in np.eye(2)], atol=1e-14)
    assert tight.input_margin[0, 0] == 0.0
    assert tight.state_margin.shape == (N + 1, 0)


def test_beta0_above_sigma_is_rejected():
    with pytest.raises(DesignError, match="beta0"):
        prepare(load_scenario(PAPER, {"terminal.beta0": 1.35}))


def test_beta0_above_sigma_of_a_shifted_alpha0_is_rejected():
    """alpha_1(0) = [0.5, 0.5] lowers sigma below 0.95; beta0 = 0.95 must be rejected, 0.9 accepted."""
    prepared = prepare(load_scenario(PAPER, {"terminal.alpha0": {"1": [0.5, 0.5]}, "terminal.beta0": 0.9}))
    alpha = np.zeros(8)
    alpha[:2] = 0.5
    sigma = sigma_lp(prepared.design.terminal.omega, alpha)
    assert 0.9 < sigma < 0.95
    assert prepared.design.sigma0 == pytest.approx(sigma, abs=1e-9)
    with pytest.raises(DesignError, match="sigma"):
        prepare(load_scenario(PAPER, {"terminal.alpha0": {"1": [0.5, 0.5]}, "terminal.beta0": 0.95}))

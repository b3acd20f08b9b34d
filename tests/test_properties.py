"""Online properties (docs/algorithm.md, "What is and is not guaranteed") on closed-loop runs, and the paper's
reference figures.

Each scenario is designed and simulated once per module (in-process run). The checks use the
recorded steps and recompute everything they assert from the hand-built global matrices of
``tests/helpers/reference.py`` and from the design's Omega (sigma via an explicit formula here),
never from the package's own helper functions.

Shifted candidate (what ``test_shifted_candidate_is_feasible`` checks): for agent i at step k+1,
    v~(t) = v_i*(k+1+t | k) for t = 0..N-2,  v~(N-1) = K_i eta_i(k)      (K tail)
    z~(0) = x_i(k+1) (measured),  z~(t+1) = A_ii z~(t) + B_ii v~(t) + c_i(t)
with the coupling feed-forward c_i recomputed at k+1 from the neighbours' *final plans of step k*
shifted by one (Assumption 1: zhat_j(0) = x_j(k+1), zhat_j(t) = z_j*(k+1+t | k)). We check that
v~ is in U_i and that ||z~(N) - alpha_i(k+1)||_inf <= beta(k+1) + 1e-6: this is feasibility for
QP_i at k+1. z~(N) is not alpha_i(k+1) exactly: alpha(k+1) = (A+BK) eta(k) is the global K tail,
while z~ is driven by the neighbours' plans of step k, which differ from what agent i assumed
when it planned at k (their revisions). The largest such deviation is recorded as a property.
We also check that the QP's optimum at k+1 is no worse than the candidate's cost.
"""
from __future__ import annotations

import numpy as np
import pytest

from dmpc.records.run_folder import trajectory_arrays
from dmpc.runtime.inprocess import simulate
from dmpc.scenario import load_scenario
from dmpc.setup import prepare
from tests.helpers.reference import (
    A_II,
    A_IJ,
    B_II,
    CHAIN,
    PAPER,
    U_BAR,
    block_diag,
    chain_matrices,
    chain_x0,
    cube_vertices,
)

N = 10


class Run:
    def __init__(self, path, overrides, M):
        self.prepared = prepare(load_scenario(path, overrides))
        self.records = []
        simulate(self.prepared, self.records.append)
        self.arrays = trajectory_arrays(self.prepared.system, self.records)
        self.M = M
        self.A, self.B = chain_matrices(M)
        self.K = [np.asarray(k) for k in self.prepared.design.gains.K]
        self.P = [np.asarray(p) for p in self.prepared.design.gains.P]
        self.AK = self.A + self.B @ block_diag(self.K)
        self.omega = self.prepared.design.terminal.omega

    def sigma(self, alpha):
        norms = np.abs(self.omega).sum(axis=1)
        return float(np.min((1.0 - self.omega @ alpha) / norms))

    def part(self, x, i):
        return x[2 * i:2 * i + 2]

    def neighbours(self, i):
        return [j for j in (i - 1, i + 1) if 0 <= j < self.M]


@pytest.fixture(scope="module")
def paper():
    return Run(PAPER, {}, 4)


@pytest.fixture(scope="module")
def chain():
    return Run(CHAIN, {"family.M": 8}, 8)


@pytest.fixture(scope="module", params=["paper", "chain"])
def run(request):
    return request.getfixturevalue(request.param)


def stage_cost(x, u):
    return float(x @ x + 0.01 * u @ u)  # Q = I, R = 0.01 I in both scenarios


def plan_cost(z, v, P):
    return float(sum(z[t] @ z[t] + 0.01 * v[t] @ v[t] for t in range(N)) + z[N] @ P @ z[N])


def shifted_feedforward(run, i, k_plus_1):
    """c_i(t), t = 0..N-1, at step k+1 from the neighbours' final plans of step k (shift 1)."""
    prev, now = run.records[k_plus_1 - 1], run.records[k_plus_1]
    c = np.zeros((N, 2))
    for j in run.neighbours(i):
        zj = prev.plans_z[j]
        zhat = np.vstack([run.part(now.x, j), zj[2:N + 1]])  # t = 0..N-1
        assert zhat.shape == (N, 2)
        c += zhat @ A_IJ.T  # B_ij = 0
    return c


# ---------------------------------------------------------------- the paper's reference figures

def test_paper_reference_figures(paper):
    a = paper.arrays
    np.testing.assert_allclose(a["J"][:4], [102.05, 54.48, 21.60, 8.36], atol=0.05)
    np.testing.assert_allclose(a["S"][:3], [20.50, 14.68, 6.26], atol=0.01)
    np.testing.assert_allclose(a["u"][0], [-2.5, -2.5, 0.489, -0.472], atol=1e-3)
    np.testing.assert_allclose(a["x"][1], [3.293, 1.606, 2.008, 1.397, 1.068, -1.711, -1.283, 2.755], atol=1e-3)
    assert a["beta"][0] == 0.5
    assert a["beta"][1] == pytest.approx(1.3413, abs=1e-4)


def test_state_trajectory_follows_the_plant(run):
    """x(0) is the scenario's, and x(k+1) = A x(k) + B u(k) with the hand-built A, B."""
    a = run.arrays
    np.testing.assert_array_equal(a["x"][0], chain_x0(run.M))
    for k in range(len(run.records)):
        np.testing.assert_allclose(a["x"][k + 1], run.A @ a["x"][k] + run.B @ a["u"][k], atol=1e-12)


def test_S_is_the_neighbour_weighted_norm(run):
    a = run.arrays
    for k in range(a["x"].shape[0]):
        S = sum(run.part(a["x"][k], i) @ run.part(a["x"][k], i) / (1 + len(run.neighbours(i))) for i in range(run.M))
        assert a["S"][k] == pytest.approx(S, rel=1e-12, abs=1e-15)


# ---------------------------------------------------------------- section 6 online properties

def test_every_qp_feasible_no_fallback(run):
    for rec in run.records:
        assert rec.status == ["solved"] * run.M, (rec.k, rec.status)
        assert not any(rec.fallback), rec.k


def test_k0_iterates_to_a_fixed_point(paper):
    rec = paper.records[0]
    assert rec.rounds > 1
    assert rec.max_change < 1e-9


def test_beta_at_most_sigma_alpha(run):
    a = run.arrays
    assert a["beta"][0] == pytest.approx(0.5)
    for k in range(a["beta"].size):
        sigma = run.sigma(a["alpha"][k])
        assert a["beta"][k] <= sigma + 1e-9, k
        if k > 0:  # beta(k) = sigma(alpha(k)) after the first step
            assert a["beta"][k] == pytest.approx(sigma, abs=1e-9)


def test_terminal_cube_inside_xf_at_every_step(paper):
    """All 256 vertices of the cube ||x - alpha(k)||_inf <= beta(k) satisfy Omega x <= 1."""
    a = paper.arrays
    for k in range(a["beta"].size):
        vertices = cube_vertices(a["alpha"][k], a["beta"][k])
        assert vertices.shape == (256, 8)
        assert np.max(vertices @ paper.omega.T) <= 1.0 + 1e-9, k


def test_chain_terminal_cube_inside_xf_at_every_step(chain):
    """2^16 vertices per step are many: check, per row of Omega, the vertex alpha + beta sign(Omega_l)
    that maximises that row over the cube, plus 512 random vertices."""
    a = chain.arrays
    rng = np.random.default_rng(1)
    for k in range(a["beta"].size):
        alpha, beta = a["alpha"][k], a["beta"][k]
        worst = alpha[None, :] + beta * np.where(chain.omega >= 0, 1.0, -1.0)
        random = alpha[None, :] + beta * rng.choice([-1.0, 1.0], size=(512, alpha.size))
        assert np.max(np.vstack([worst, random]) @ chain.omega.T) <= 1.0 + 1e-9, k


def test_alpha_update_is_the_global_k_tail(run):
    """alpha(k+1) = (A+BK) eta(k), eta = the final plans' z[N]; alpha(0) = 0."""
    a = run.arrays
    np.testing.assert_array_equal(a["alpha"][0], np.zeros(2 * run.M))
    for k, rec in enumerate(run.records):
        eta = np.concatenate([z[N] for z in rec.plans_z])
        np.testing.assert_allclose(a["alpha"][k + 1], run.AK @ eta, atol=1e-12)


def test_plans_respect_their_constraints(run):
    """Every applied plan: z[0] = x(k), u = v[0], |v| <= 2.5, terminal box around alpha_i(k) of radius beta(k)."""
    a = run.arrays
    for k, rec in enumerate(run.records):
        for i in range(run.M):
            z, v = rec.plans_z[i], rec.plans_v[i]
            assert z.shape == (N + 1, 2) and v.shape == (N, 1)
            np.testing.assert_array_equal(z[0], run.part(a["x"][k], i))
            np.testing.assert_array_equal(a["u"][k][i:i + 1], v[0])
            assert np.max(np.abs(v)) <= U_BAR + 1e-7
            assert np.max(np.abs(z[N] - run.part(a["alpha"][k], i))) <= a["beta"][k] + 1e-6, (k, i)


def test_inputs_within_bounds(run):
    assert np.max(np.abs(run.arrays["u"])) <= U_BAR + 1e-7


def test_paper_saturates_in_the_first_steps(paper):
    assert np.max(np.abs(paper.arrays["u"][0])) == pytest.approx(U_BAR, abs=1e-6)


def test_recorded_costs_are_the_plans_costs(run):
    for rec in run.records:
        for i in range(run.M):
            cost = plan_cost(rec.plans_z[i], rec.plans_v[i], run.P[i])
            assert rec.J_agents[i] == pytest.approx(cost, rel=1e-6, abs=1e-9)
        assert rec.J == pytest.approx(sum(rec.J_agents), rel=1e-12)


def test_first_prediction_step_is_exact(run):
    """With measured neighbour states and B_ij = 0: x_i(k+1) = z_i*(k+1|k)."""
    a = run.arrays
    for k, rec in enumerate(run.records):
        for i in range(run.M):
            np.testing.assert_allclose(rec.plans_z[i][1], run.part(a["x"][k + 1], i), atol=1e-6)


def test_plans_use_the_shifted_feedforward(run):
    """From k = 1 (p = 1): z_i*(t+1) = A_ii z_i*(t) + B_ii v_i*(t) + c_i(t), c_i from the shifted plans of k-1.

    At k = 0 the same holds with the step's own final plans (Jacobi fixed point).
    """
    for k, rec in enumerate(run.records):
        for i in range(run.M):
            if k == 0:
                c = np.zeros((N, 2))
                for j in run.neighbours(i):
                    c += rec.plans_z[j][:N] @ A_IJ.T
            else:
                c = shifted_feedforward(run, i, k)
            z, v = rec.plans_z[i], rec.plans_v[i]
            for t in range(N):
                np.testing.assert_allclose(z[t + 1], A_II @ z[t] + B_II @ v[t] + c[t], atol=1e-6,
                                           err_msg=f"k={k} i={i} t={t}")


def test_shifted_candidate_is_feasible(run, record_property):
    """The explicit shifted candidate is feasible for QP_i at k+1 (see the module docstring)."""
    a = run.arrays
    worst_deviation = 0.0
    for k1 in range(1, len(run.records)):
        prev, now = run.records[k1 - 1], run.records[k1]
        for i in range(run.M):
            z_prev, v_prev = prev.plans_z[i], prev.plans_v[i]
            v_c = np.vstack([v_prev[1:], run.K[i] @ z_prev[N]])
            c = shifted_feedforward(run, i, k1)
            z_c = [run.part(a["x"][k1], i)]
            for t in range(N):
                z_c.append(A_II @ z_c[-1] + B_II @ v_c[t] + c[t])
            z_c = np.array(z_c)
            assert np.max(np.abs(v_c)) <= U_BAR + 1e-7, (k1, i)
            deviation = np.max(np.abs(z_c[N] - run.part(a["alpha"][k1], i)))
            worst_deviation = max(worst_deviation, deviation)
            assert deviation <= a["beta"][k1] + 1e-6, (k1, i, deviation, a["beta"][k1])
            # the QP's optimum at k+1 is no worse than this feasible point
            assert now.J_agents[i] <= plan_cost(z_c, v_c, run.P[i]) + 1e-6, (k1, i)
    record_property("candidate_terminal_deviation_max", float(worst_deviation))


def test_paper_cost_non_increasing(paper):
    J = paper.arrays["J"]
    assert np.all(np.diff(J) <= 1e-9), np.diff(J)


def test_paper_S_decreasing(paper):
    S = paper.arrays["S"]
    assert np.all(np.diff(S[:20]) < 0)


def test_paper_converges(paper):
    assert len(paper.records) == 30
    assert np.max(np.abs(paper.arrays["x"][30])) < 1e-5


def test_paper_theorem3_decrease(paper):
    a = paper.arrays
    for k in range(len(paper.records) - 1):
        l_k = stage_cost(a["x"][k], a["u"][k])
        assert a["J"][k + 1] <= a["J"][k] - l_k + 1e-6, k


def test_chain_theorem3_margin_recorded(chain, record_property):
    """Not a guarantee on the chain (docs/algorithm.md, "What is and is not guaranteed"): only recorded."""
    a = chain.arrays
    margins = [a["J"][k] - stage_cost(a["x"][k], a["u"][k]) - a["J"][k + 1] for k in range(len(chain.records) - 1)]
    assert np.all(np.isfinite(margins))
    record_property("chain8_theorem3_margin_min", float(np.min(margins)))
    record_property("chain8_theorem3_margins", [float(m) for m in margins])
    record_property("chain8_J_non_increasing", bool(np.all(np.diff(a["J"]) <= 1e-9)))
    print(f"chain M=8: smallest Theorem-3 margin {np.min(margins):.3g}")

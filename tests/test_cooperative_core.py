"""The pure core of ``tv-box-coop`` (Stewart, Venkat, Rawlings & Wright, "Cooperative distributed
model predictive control", Syst. Control Lett. 59, 2010): the input reach, agent i's cooperative QP,
the combination of the proposals, the shifted iterate, and the closed loop they make.

What is asserted is recomputed here or in ``tests/helpers/cooperative.py`` (global matrices from
the raw blocks, trajectories and costs by loops, every constraint row from the raw sets, the
restricted problem in cvxpy/Clarabel, the start's feasibility by an LP), never with
``GlobalModel.excess``, ``GlobalModel.cost`` or ``GlobalModel.simulate``.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from dmpc.api.scenarios import load_scenario
from dmpc.cooperative.agent_qp import CooperativeQP
from dmpc.cooperative.iterate import GlobalModel, Iterate, combine
from dmpc.cooperative.reach import input_reach
from dmpc.cooperative.rounds import CooperativeRounds
from dmpc.core.errors import DesignError
from dmpc.core.qp_status import QPStatus
from dmpc.core.system import CoupledSystem, Coupling, LinearSet, Subsystem
from dmpc.scenario.load import ScenarioError
from dmpc.setup import prepare
from dmpc.tracking.targets import Target
from tests.helpers.cooperative import (
    centrally_feasible,
    dense_block_diag,
    global_AB,
    largest_violation,
    offsets,
    part_costs,
    plan_cost,
    random_system,
    random_weights,
    restricted_optimum,
    simulate,
    steady_target,
    terminal_box_around,
    with_sets_around,
)
from tests.helpers.reference import A_II, A_IJ, B_II, Q_I, R_I

FEASIBLE = 1e-7
"""Largest absolute excess over any constraint row accepted as feasible."""

seeds = st.integers(0, 2**32 - 1)
factors = st.floats(0.5, 2.5)


def subsystem(name: str, A=A_II, B=B_II) -> Subsystem:
    return Subsystem(name=name, A=np.asarray(A, float), B=np.asarray(B, float), Q=Q_I, R=R_I, x0=np.zeros(2),
                     input_set=LinearSet.box([-2.5], [2.5]))


def chain(M: int) -> CoupledSystem:
    """The paper's chain: B_ij = 0, A_ij between neighbours."""
    couplings = [Coupling(target=i, source=j, A=A_IJ, B=np.zeros((2, 1)))
                 for i in range(M) for j in (i - 1, i + 1) if 0 <= j < M]
    return CoupledSystem(subsystems=tuple(subsystem(f"c{i}") for i in range(M)), couplings=tuple(couplings))


def response_reach(system: CoupledSystem, horizon: int) -> tuple[tuple[int, ...], ...]:
    """Brute force: j is reached by agent i iff block (j, i) of A^t B is nonzero for some t < N."""
    A, B = global_AB(system)
    xs, us = offsets(system)
    power = B.copy()
    hit = np.zeros((system.M, system.M), dtype=bool)
    for _ in range(horizon):
        for j in range(system.M):
            for i in range(system.M):
                hit[j, i] |= bool(np.any(np.abs(power[xs[j], us[i]]) > 1e-13))
        power = A @ power
    return tuple(tuple(int(j) for j in np.flatnonzero(hit[:, i])) for i in range(system.M))


# ================================================================ 1. input_reach

@pytest.mark.parametrize("horizon, expected", [
    (1, ((0,), (1,), (2,), (3,), (4,))),
    (2, ((0, 1), (0, 1, 2), (1, 2, 3), (2, 3, 4), (3, 4))),
    (3, ((0, 1, 2), (0, 1, 2, 3), (0, 1, 2, 3, 4), (1, 2, 3, 4), (2, 3, 4))),
    (5, tuple(tuple(range(5)) for _ in range(5))),
])
def test_chain_reach_grows_one_hop_per_step(horizon, expected):
    system = chain(5)
    assert input_reach(system, horizon) == expected
    assert response_reach(system, horizon) == expected


def test_input_coupling_reaches_the_neighbour_at_once():
    """B_12 != 0 and A_12 = 0: agent 2's inputs move subsystem 1 within one step; agent 1's never move 2."""
    system = CoupledSystem(subsystems=(subsystem("a"), subsystem("b")),
                           couplings=(Coupling(target=0, source=1, A=np.zeros((2, 2)), B=np.array([[0.7], [0.0]])),))
    for horizon in (1, 2, 4):
        assert input_reach(system, horizon) == ((0,), (0, 1))
        assert response_reach(system, horizon) == ((0,), (0, 1))


def test_agent_without_own_input_reaches_only_through_couplings():
    """B_ii = 0, B_ji != 0: agent i's reach starts at j, not at i; it reaches i only through A_ij."""
    subs = (subsystem("a", B=np.zeros((2, 1))), subsystem("b"), subsystem("c"))
    couplings = (Coupling(target=1, source=0, A=np.zeros((2, 2)), B=np.array([[0.0], [1.0]])),
                 Coupling(target=0, source=1, A=A_IJ, B=np.zeros((2, 1))),
                 Coupling(target=2, source=1, A=A_IJ, B=np.zeros((2, 1))))
    system = CoupledSystem(subsystems=subs, couplings=couplings)
    assert input_reach(system, 1) == ((1,), (1,), (2,))
    assert input_reach(system, 2) == ((0, 1, 2), (0, 1, 2), (2,))
    for horizon in (1, 2, 3):
        assert input_reach(system, horizon) == response_reach(system, horizon)


def test_agent_without_any_effective_input_reaches_nothing():
    subs = (subsystem("a", B=np.zeros((2, 1))), subsystem("b"))
    system = CoupledSystem(subsystems=subs, couplings=(Coupling(target=1, source=0, A=A_IJ, B=np.zeros((2, 1))),))
    assert input_reach(system, 3) == ((), (1,))


def random_structure(rng: np.random.Generator, M: int, dense: bool) -> CoupledSystem:
    """Random block structure (A_jj, B_jj, A_jl, B_jl each present or not) with random entries;
    ``dense``: a present block has every entry nonzero (no structural cancellation in A^t B)."""
    def block(shape, present):
        if not present:
            return np.zeros(shape)
        values = rng.uniform(0.3, 1.0, shape) * rng.choice([-1.0, 1.0], shape)
        if not dense:
            values *= rng.random(shape) < 0.5
        return values

    subs = tuple(Subsystem(name=f"r{j}", A=block((2, 2), rng.random() < 0.8), B=block((2, 1), rng.random() < 0.7),
                           Q=Q_I, R=R_I, x0=np.zeros(2), input_set=LinearSet.box([-1.0], [1.0])) for j in range(M))
    couplings = []
    for j in range(M):
        for source in range(M):
            if j != source and rng.random() < 0.4:
                couplings.append(Coupling(target=j, source=source, A=block((2, 2), rng.random() < 0.6),
                                          B=block((2, 1), rng.random() < 0.3)))
    return CoupledSystem(subsystems=subs, couplings=tuple(couplings))


@settings(max_examples=60, deadline=None)
@given(seed=seeds, M=st.integers(2, 6), horizon=st.integers(1, 6))
def test_reach_is_the_response_pattern(seed, M, horizon):
    """With dense blocks, input_reach is exactly the block pattern of [B, AB, ..., A^(N-1) B]."""
    system = random_structure(np.random.default_rng(seed), M, dense=True)
    assert input_reach(system, horizon) == response_reach(system, horizon)


@settings(max_examples=60, deadline=None)
@given(seed=seeds, M=st.integers(2, 6), horizon=st.integers(1, 6))
def test_reach_covers_the_response_with_sparse_blocks(seed, M, horizon):
    """With sparse blocks (structural cancellation possible) the reach may be larger, never smaller."""
    system = random_structure(np.random.default_rng(seed), M, dense=False)
    for reach, response in zip(input_reach(system, horizon), response_reach(system, horizon)):
        assert set(response) <= set(reach)


# ================================================================ random feasible iterates

class Case:
    """A random coupled system, sets around a random iterate (deviation coordinates around a
    steady target), a terminal box the iterate meets, and K, P."""

    def __init__(self, seed: int, M: int, horizon: int, factor: float, target: bool, decoupled: bool = False,
                 no_own_input: bool = False) -> None:
        rng = np.random.default_rng(seed)
        self.N = horizon
        raw = random_system(rng, M, factor, decoupled=decoupled, no_own_input=0 if no_own_input else None)
        self.K, self.P = random_weights(rng, M)
        self.x_s, self.u_s = steady_target(rng, raw, 0.5 if target else 0.0)
        self.A, self.B = global_AB(raw)
        self.v = rng.uniform(-1.0, 1.0, (horizon, raw.M))
        self.z = simulate(self.A, self.B, rng.normal(size=2 * M), self.v)
        self.system = with_sets_around(rng, raw, self.z, self.v, self.x_s, self.u_s)
        self.alpha, self.beta = terminal_box_around(rng, self.z[-1])
        self.Q = dense_block_diag([s.Q for s in self.system.subsystems])
        self.R = dense_block_diag([s.R for s in self.system.subsystems])
        self.P_all = dense_block_diag(self.P)
        self.xs, self.us = offsets(self.system)
        self.reach = input_reach(self.system, horizon)
        assert self.violation(self.z, self.v) <= 0.0

    def violation(self, z, v) -> float:
        return largest_violation(self.system, z, v, self.x_s, self.u_s, self.alpha, self.beta)

    def cost(self, z, v) -> float:
        return plan_cost(z, v, self.Q, self.R, self.P_all)

    def model(self) -> GlobalModel:
        return GlobalModel(self.system, self.K, self.P, self.N)

    def agent(self, i: int) -> CooperativeQP:
        return CooperativeQP(self.system, self.P, self.N, i, self.reach[i])

    def propose(self, qp: CooperativeQP, z, v):
        i = qp.index
        return qp.solve(z[:, qp.states], v[:, self.us[i]], self.x_s[qp.states], self.u_s[self.us[i]],
                        self.alpha[qp.states], self.beta)

    def proposals(self) -> dict[int, np.ndarray]:
        out = {}
        for i in range(self.system.M):
            if not self.reach[i]:
                continue
            sol = self.propose(self.agent(i), self.z, self.v)
            assert sol.status.feasible, (i, sol.status)  # the iterate's own inputs are a feasible point
            out[i] = sol.v
        return out


cases = dict(seed=seeds, M=st.integers(2, 3), horizon=st.integers(2, 5), factor=factors, target=st.booleans())


# ================================================================ 2. CooperativeQP

@settings(max_examples=30, deadline=None)
# found by this test: OSQP's polish with 3 refinement steps left dynamics residuals of 5e-8, and the
# proposal's own states missed a terminal row by 3.7e-7 (fixed: COOPERATIVE_SETTINGS)
@example(seed=33244, M=3, horizon=5, factor=2.125, target=False, no_own_input=False)
# found by this test: agent 1's QP (P_i eigenvalues below 6, a random feasible iterate) stops at
# OSQP's 10 000-iteration cap ("max_iter"; it needs 17 760): the agent has no proposal
@example(seed=3, M=3, horizon=4, factor=2.5, target=False, no_own_input=False)
@given(no_own_input=st.booleans(), **cases)
def test_agent_qp_is_the_restricted_centralised_problem(seed, M, horizon, factor, target, no_own_input):
    """Agent i's proposal is the minimiser of the centralised problem over v_i, the other agents'
    inputs at the iterate (cvxpy, Clarabel); its cost is the global cost less the parts v_i cannot
    move; c(t) is what the rest of the iterate feeds into R; the iterate's own v_i bounds the optimum."""
    case = Case(seed, M, horizon, factor, target, no_own_input=no_own_input)
    system, z, v = case.system, case.z, case.v
    assert case.reach == response_reach(system, horizon)
    state_costs, input_costs = part_costs(system, case.P, z, v)
    for i in range(M):
        if not case.reach[i]:
            continue
        qp = case.agent(i)
        R = list(case.reach[i])
        rows_R = np.concatenate([np.arange(case.xs[j].start, case.xs[j].stop) for j in R])
        np.testing.assert_array_equal(qp.states, rows_R)
        sol = case.propose(qp, z, v)
        assert sol.status.feasible, sol.status
        w_ref, V_ref = restricted_optimum(system, case.P, z, v, i, case.x_s, case.u_s, case.alpha, case.beta)
        scale = 1.0 + np.abs(w_ref).max()
        np.testing.assert_allclose(sol.v, w_ref, atol=2e-5 * scale)

        v_new = v.copy()
        v_new[:, case.us[i]] = sol.v
        z_new = simulate(case.A, case.B, z[0], v_new)
        V_new = case.cost(z_new, v_new)
        assert abs(V_new - V_ref) <= 1e-6 * (1.0 + abs(V_ref)), (V_new, V_ref)
        assert case.violation(z_new, v_new) <= FEASIBLE
        # the QP's states are R's under the proposal; the others' do not move
        np.testing.assert_allclose(sol.z, z_new[:, rows_R], atol=1e-8 * (1.0 + np.abs(z_new).max()))
        outside = np.setdiff1d(np.arange(system.n), rows_R)
        np.testing.assert_allclose(z_new[:, outside], z[:, outside], atol=1e-12)
        # its cost is the global cost less the parts v_i cannot move
        constant = sum(state_costs[j] for j in range(M) if j not in R) + sum(
            input_costs[j] for j in range(M) if j != i)
        assert sol.cost == pytest.approx(V_new - constant, rel=1e-7, abs=1e-9)

        # c(t): what the other agents' inputs and the subsystems outside R feed into R at the iterate
        others = np.setdiff1d(np.arange(system.m), np.arange(system.m)[case.us[i]])
        expected = (z[:-1, outside] @ case.A[np.ix_(rows_R, outside)].T
                    + v[:, others] @ case.B[np.ix_(rows_R, others)].T)
        np.testing.assert_allclose(qp.coupling(z[:, rows_R], v[:, case.us[i]]), expected,
                                   atol=1e-10 * (1.0 + np.abs(z).max()))
        # the iterate's own inputs are feasible for the QP: its optimum is no worse than their cost
        at_iterate = sum(state_costs[j] for j in R) + input_costs[i]
        assert sol.cost <= at_iterate + 1e-9 * (1.0 + at_iterate)


# ================================================================ 3. combine

def weighted(case: Case, proposals: dict[int, np.ndarray], s: float) -> tuple[np.ndarray, np.ndarray]:
    """The iterate with every agent's inputs moved by s toward its proposal, states simulated."""
    v = case.v.copy()
    for i, w in proposals.items():
        v[:, case.us[i]] += s * (w - case.v[:, case.us[i]])
    return simulate(case.A, case.B, case.z[0], v), v


@settings(max_examples=30, deadline=None)
@given(**cases)
def test_combine_keeps_feasibility_and_lowers_the_cost(seed, M, horizon, factor, target):
    """(a) feasible, (b) no worse than the iterate and the 1/M combination, (c) "equal" is the 1/M
    combination, (e) the states are the inputs' response; and "line" is the best feasible weight."""
    case = Case(seed, M, horizon, factor, target)
    proposals = case.proposals()
    model = case.model()
    V0 = case.cost(case.z, case.v)
    z_eq, v_eq = weighted(case, proposals, 1.0 / M)
    V_eq = case.cost(z_eq, v_eq)
    results = {}
    for rule in ("line", "equal"):
        done = combine(model, Iterate(case.z.copy(), case.v.copy()), proposals, case.x_s, case.u_s, case.alpha,
                       case.beta, rule)
        z, v = done.iterate.z, done.iterate.v
        results[rule] = done
        # (a) every row of the centralised problem
        assert case.violation(z, v) <= FEASIBLE, rule
        # (e) the states are the model's response to the inputs
        np.testing.assert_allclose(z, simulate(case.A, case.B, case.z[0], v), rtol=1e-9, atol=1e-10)
        # (b) no worse than the iterate, nor than the equal-weight combination
        V = case.cost(z, v)
        assert V <= V0 + 1e-9 * max(1.0, V0)
        assert V <= V_eq + 1e-9 * max(1.0, V_eq)
        assert done.cost_before == pytest.approx(V0, rel=1e-10)
        assert done.cost_after == pytest.approx(V, rel=1e-10)
        # every agent moved by the same weight s in [1/M, 1]
        assert 1.0 / M - 1e-12 <= done.step <= 1.0
        _, v_s = weighted(case, proposals, done.step)
        np.testing.assert_allclose(v, v_s, rtol=1e-12, atol=1e-12)
    # (c) "equal" is the 1/M combination
    assert results["equal"].step == 1.0 / M
    np.testing.assert_allclose(results["equal"].iterate.v, v_eq, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(results["equal"].iterate.z, z_eq, rtol=1e-10, atol=1e-12)
    # "line": no feasible weight in [1/M, 1] does better
    V_line = results["line"].cost_after
    for s in np.linspace(1.0 / M, 1.0, 41):
        z_s, v_s = weighted(case, proposals, s)
        if case.violation(z_s, v_s) <= 0.0:
            assert V_line <= case.cost(z_s, v_s) + 1e-9 * max(1.0, V_line), s


@settings(max_examples=15, deadline=None)
@given(**cases)
def test_combine_takes_whole_proposals_of_decoupled_agents(seed, M, horizon, factor, target):
    """(d) No couplings: the agents' problems are independent, so the line step is 1."""
    case = Case(seed, M, horizon, factor, target, decoupled=True)
    assert case.reach == tuple((i,) for i in range(M))
    proposals = case.proposals()
    done = combine(case.model(), Iterate(case.z, case.v), proposals, case.x_s, case.u_s, case.alpha, case.beta,
                   "line")
    assert done.step == pytest.approx(1.0, abs=1e-6)
    for i, w in proposals.items():
        np.testing.assert_allclose(done.iterate.v[:, case.us[i]], w, atol=1e-6 * (1.0 + np.abs(w).max()))
    assert case.violation(done.iterate.z, done.iterate.v) <= FEASIBLE


@pytest.mark.parametrize("rule", ["line", "equal"])
def test_combine_keeps_the_iterate_rather_than_raise_its_cost(rule):
    """Proposals worse than the iterate (a QP solved only to its solver's accuracy near the
    optimum): the iterate stays, step 0."""
    case = Case(11, 3, 4, 1.5, True)
    V0 = case.cost(case.z, case.v)
    # a small move of every agent's inputs that raises the cost (first order) and keeps every row
    worse = {}
    for i in range(3):
        bump = np.zeros_like(case.v)
        bump[:, case.us[i]] = 1e-3
        up = case.cost(simulate(case.A, case.B, case.z[0], case.v + bump), case.v + bump)
        down = case.cost(simulate(case.A, case.B, case.z[0], case.v - bump), case.v - bump)
        worse[i] = case.v[:, case.us[i]] + (1e-3 if up > down else -1e-3)
        assert max(up, down) > V0
    z_w, v_w = weighted(case, worse, 1.0 / 3)
    assert case.violation(z_w, v_w) <= 0.0 and case.cost(z_w, v_w) > V0
    done = combine(case.model(), Iterate(case.z, case.v), worse, case.x_s, case.u_s, case.alpha, case.beta, rule)
    assert done.step == 0.0 and done.cost_after == done.cost_before
    np.testing.assert_array_equal(done.iterate.v, case.v)
    np.testing.assert_array_equal(done.iterate.z, case.z)


def test_combine_without_moves_keeps_the_iterate():
    case = Case(7, 3, 4, 1.5, True)
    done = combine(case.model(), Iterate(case.z, case.v), {i: case.v[:, case.us[i]] for i in range(3)},
                   case.x_s, case.u_s, case.alpha, case.beta)
    assert done.step == 0.0 and done.change == 0.0
    np.testing.assert_array_equal(done.iterate.v, case.v)


# ================================================================ 4. the shifted iterate

@settings(max_examples=20, deadline=None)
@given(**cases)
def test_shifted_iterate_under_the_model(seed, M, horizon, factor, target):
    case = Case(seed, M, horizon, factor, target)
    model = case.model()
    K = dense_block_diag(case.K)
    z, v = case.z, case.v
    shifted = model.shifted(Iterate(z, v), z[1].copy())
    np.testing.assert_allclose(shifted.v, np.vstack([v[1:], K @ z[-1]]), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(shifted.z, np.vstack([z[1:], (case.A + case.B @ K) @ z[-1]]),
                               rtol=1e-10, atol=1e-10 * (1.0 + np.abs(z).max()))
    # from a measured state off the plan: the same inputs, the states simulated from it
    x = z[1] + np.random.default_rng(seed).normal(size=z.shape[1])
    moved = model.shifted(Iterate(z, v), x)
    np.testing.assert_allclose(moved.v, shifted.v, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(moved.z, simulate(case.A, case.B, x, moved.v), rtol=1e-10, atol=1e-10)


# ================================================================ 5. the closed loop

def scenario_mapping(rng: np.random.Generator, M: int, factor: float, horizon: int, steps: int) -> dict:
    """M subsystems (n_i = 2, m_i = 1) in a chain, coupled through A_ij and through B_ij of norm
    ``factor`` |B_jj| (as large as the subsystem's own input and larger)."""
    subs, couplings = [], []
    for i in range(M):
        A = rng.uniform(-0.4, 0.4, (2, 2)) + np.diag(rng.uniform(0.7, 1.1, 2))
        b = rng.uniform(0.3, 1.0, 2) * rng.choice([-1.0, 1.0], 2)
        u = rng.uniform(1.0, 3.0)
        x = rng.uniform(3.0, 6.0)
        subs.append(dict(name=f"s{i}", A=A, B=b[:, None], Q=np.eye(2), R=[[rng.uniform(0.05, 1.0)]],
                         input=dict(lower=[-u], upper=[u]), state=dict(lower=[-x, -x], upper=[x, x]),
                         x0=rng.uniform(-1.5, 1.5, 2)))
    for i in range(M):
        for j in (i - 1, i + 1):
            if 0 <= j < M:
                Bij = rng.normal(size=(2, 1))
                Bij *= factor * np.linalg.norm(subs[j]["B"]) / np.linalg.norm(Bij)
                couplings.append(dict(target=f"s{i}", source=f"s{j}", A=rng.uniform(-0.15, 0.15, (2, 2)), B=Bij))
    return dict(name="coop-random", subsystems=subs, couplings=couplings, horizon=horizon, steps=steps,
                options=dict(method="tv-box-coop"))


STEPS = 40


@pytest.mark.slow  # about 25 s, most of it in the designs' terminal sets
@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.filter_too_much, HealthCheck.too_slow])
# found by this test: at k = 0, from the centralised plan, agent 2's QP stops at OSQP's iteration
# cap as "solved_inaccurate", its proposal misses a terminal row by 1.8e-6, and the combined
# iterate misses it by 6.0e-7 (P_i up to 6.5e5: a badly conditioned design)
@example(seed=75, M=3, factor=2.2095758978529947, horizon=7, rounds=3, rule="line")
# found by this test: the centralised QP of the first iterate needed more than OSQP's default
# 10 000 iterations, and unpolished proposals raised the cost of that (optimal) iterate (both fixed
# in dmpc/cooperative); still open: the unpolished proposals ("solved", rows missed by 1.1e-7) make
# the combined iterate miss a row by 1.0e-7 to 1.3e-7 in the k = 0 rounds
@example(seed=24, M=3, factor=0.6353565247232662, horizon=7, rounds=2, rule="equal")
@given(seed=seeds, M=st.integers(2, 3), factor=factors, horizon=st.integers(4, 7), rounds=st.integers(1, 3),
       rule=st.sampled_from(["line", "equal"]))
def test_closed_loop_on_random_input_coupled_systems(seed, M, factor, horizon, rounds, rule):
    """The loop the coordinator runs, on the model: the first iterate, Jacobi rounds of every
    agent's CooperativeQP combined, the first inputs applied, the terminal box moved to
    alpha = (A+BK) eta, beta = sigma(alpha), the iterate shifted. On systems whose neighbours'
    inputs drive a subsystem as much as its own and more (B_ij of norm 0.5 to 2.5 |B_jj|), with a
    design and a centrally feasible start: every iterate meets every row of the centralised
    problem, the cost never rises over a round, the shifted iterate's cost is the last one's less
    the stage cost (the Lyapunov inequality (10)), and the state converges."""
    rng = np.random.default_rng(seed)
    try:
        prepared = prepare(load_scenario(scenario_mapping(rng, M, factor, horizon, STEPS)))
    except (DesignError, ScenarioError):
        assume(False)
    system, design = prepared.system, prepared.design
    N = design.horizon
    A, B = global_AB(system)
    K = dense_block_diag([np.asarray(k) for k in design.gains.K])
    P_blocks = [np.asarray(p) for p in design.gains.P]
    P = dense_block_diag(P_blocks)
    Q = dense_block_diag([s.Q for s in system.subsystems])
    R = dense_block_diag([s.R for s in system.subsystems])
    us = offsets(system)[1]
    AK = A + B @ K
    omega = np.asarray(design.terminal.omega)
    norms = np.abs(omega).sum(axis=1)

    def sigma(alpha):
        return float(np.min((1.0 - omega @ alpha) / norms))

    # (10): (A+BK)'P(A+BK) - P + Q + K'RK <= 0, to the design's tolerance
    lyapunov = float(np.linalg.eigvalsh(AK.T @ P @ AK - P + Q + K.T @ R @ K).max())
    assert lyapunov <= 1e-6 * float(np.linalg.eigvalsh(P).max())
    lyapunov = max(lyapunov, 0.0)

    x = system.x0.copy()
    alpha, beta = np.asarray(design.alpha0, float).copy(), float(design.beta0)
    assert beta <= sigma(alpha) + 1e-12
    assume(centrally_feasible(system, x, N, alpha, beta))

    zero_x, zero_u = np.zeros(system.n), np.zeros(system.m)
    target = Target.origin(system.n, system.m)
    reach = input_reach(system, N)
    agents = [CooperativeQP(system, P_blocks, N, i, reach[i]) for i in range(system.M)]
    coop = CooperativeRounds(system, list(design.gains.K), P_blocks, P, N, rule)

    def violation(it):
        return largest_violation(system, it.z, it.v, zero_x, zero_u, alpha, beta)

    def cost(it):
        return plan_cost(it.z, it.v, Q, R, P)

    first = coop.first(x, target, alpha, beta, (np.eye(system.n), alpha - beta, alpha + beta))
    assert violation(first.iterate) <= FEASIBLE, first.note
    it = first.iterate
    x_norm0 = float(np.abs(x).max())
    unsolved = []
    for k in range(STEPS):
        assert violation(it) <= FEASIBLE, (k, "the shifted iterate")
        np.testing.assert_allclose(it.z, simulate(A, B, x, it.v), rtol=1e-9, atol=1e-9)
        for r in range(3 * rounds if k == 0 else rounds):
            proposals = {}
            for i, qp in enumerate(agents):
                R_i = qp.states
                sol = qp.solve(it.z[:, R_i], it.v[:, us[i]], zero_x[R_i], zero_u[us[i]], alpha[R_i], beta)
                # the iterate's own inputs are a feasible point: no certificate of infeasibility
                assert sol.status not in (QPStatus.INFEASIBLE, QPStatus.UNBOUNDED), (k, r, i, sol.status)
                if sol.status.feasible:
                    proposals[i] = sol.v
                else:  # the solver stopped (iteration cap): the agent keeps its inputs, as the coordinator does
                    unsolved.append((k, r, i, sol.status))
            before = cost(it)
            it = coop.combine(it, proposals, target, alpha, beta).iterate
            after = cost(it)
            assert violation(it) <= FEASIBLE, (k, r, unsolved)
            assert after <= before + 1e-9 * max(1.0, before), (k, r, before, after)
        u = it.v[0].copy()
        stage = float(x @ Q @ x + u @ R @ u)
        last, eta = cost(it), it.z[-1].copy()
        x = A @ x + B @ u
        alpha = AK @ eta
        beta = sigma(alpha)
        assert beta >= -1e-12  # alpha(k+1) = (A+BK) eta stays in X^f
        it = coop.next_step(it, x, target)
        # the shifted iterate: feasible, and its cost at most the last one's less the stage cost
        tolerance = lyapunov * float(eta @ eta) + 1e-9 * max(1.0, last)
        assert cost(it) <= last - stage + tolerance, (k, cost(it), last, stage)
    assert violation(it) <= FEASIBLE, "the last shifted iterate"
    assert float(np.abs(x).max()) <= 0.05 * x_norm0, (x, unsolved)

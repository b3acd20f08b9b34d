"""Steady-state targets, the scaled terminal set around them and the reference governor
(docs/algorithm.md, "Setpoints"), checked against independent computations (cvxpy, scipy LPs,
explicit loops)."""
from __future__ import annotations

import cvxpy as cp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dmpc.core.system import CoupledSystem, Coupling, LinearSet, Subsystem
from dmpc.scenario import load_scenario
from dmpc.setup import prepare
from dmpc.tracking.governor import RESERVE, ReferenceGovernor
from dmpc.tracking.schedule import Schedule, SetpointEntry
from dmpc.tracking.targets import DEFAULT_MARGIN, MARGIN_ROOM, Request, TargetError, TargetSpace
from tests.helpers.reference import PAPER, ROOT, U_BAR, chain_matrices

MARGIN = DEFAULT_MARGIN


@pytest.fixture(scope="module")
def paper():
    return prepare(load_scenario(PAPER))


@pytest.fixture(scope="module")
def space(paper):
    return TargetSpace(paper.system)


@pytest.fixture(scope="module")
def governor(paper, space):
    A, B = chain_matrices(4)
    K = np.zeros((4, 8))
    for i, k in enumerate(paper.design.gains.K):
        K[i, 2 * i:2 * i + 2] = k
    return ReferenceGovernor(space, paper.design.terminal, A + B @ K, K), A + B @ K, K


def request(n: int, m: int, x: dict | None = None, u: dict | None = None) -> Request:
    r = Request.free(n, m)
    xs, us = r.x.copy(), r.u.copy()
    for c, value in (x or {}).items():
        xs[c] = value
    for c, value in (u or {}).items():
        us[c] = value
    return Request(xs, us)


# ---------------------------------------------------------------- the paper's example

def test_no_request_is_the_origin(space):
    t = space.target(Request.free(8, 4))
    assert t.is_origin and t.scale == 1.0 and t.reachable


def test_a_requested_component_is_met_by_a_steady_state(space):
    A, B = chain_matrices(4)
    t = space.target(request(8, 4, {0: 1.0}))
    assert t.reachable
    assert t.x[0] == pytest.approx(1.0, abs=1e-9)
    assert np.abs(A @ t.x + B @ t.u - t.x).max() < 1e-9
    assert np.abs(t.u).max() <= (1 - MARGIN) * U_BAR + 1e-9
    # the terminal set around it: lambda = 1 - the largest |u_i| / 2.5 (no state bounds)
    assert t.scale == pytest.approx(1 - np.abs(t.u).max() / U_BAR, abs=1e-12)


def test_free_components_are_the_nearest_to_the_origin_in_the_cost_weights(space):
    A, B = chain_matrices(4)
    x, u = cp.Variable(8), cp.Variable(4)
    problem = cp.Problem(cp.Minimize(cp.sum_squares(x) + 0.01 * cp.sum_squares(u)),
                         [x == A @ x + B @ u, x[0] == 1.0, cp.abs(u) <= (1 - MARGIN) * U_BAR])
    problem.solve(solver=cp.CLARABEL)
    t = space.target(request(8, 4, {0: 1.0}))
    assert np.allclose(t.x, x.value, atol=1e-6) and np.allclose(t.u, u.value, atol=1e-6)


def test_the_reachable_range_is_the_steady_gain_times_the_inputs(space):
    """x_s = (I - A)^-1 B u_s: x_11 reaches at most sum_j |G_1j| 2.5 (1 - margin) (22.4 without margin)."""
    A, B = chain_matrices(4)
    G = np.linalg.solve(np.eye(8) - A, B)
    top = float(np.abs(G[0]).sum()) * U_BAR
    assert top == pytest.approx(22.4, abs=0.05)
    inside = space.target(request(8, 4, {0: 0.9 * (1 - MARGIN) * top}))
    assert inside.reachable
    beyond = space.target(request(8, 4, {0: 60.0}))
    assert not beyond.reachable
    assert beyond.x[0] == pytest.approx((1 - MARGIN - MARGIN_ROOM) * top, rel=1e-7)
    assert beyond.gap_x[0] == pytest.approx((1 - MARGIN - MARGIN_ROOM) * top - 60.0, rel=1e-7)
    assert np.isnan(beyond.gap_x[1:]).all()


def test_an_input_target_is_met(space):
    t = space.target(request(8, 4, u={1: 0.5}))
    assert t.reachable and t.u[1] == pytest.approx(0.5, abs=1e-9)


def test_a_request_no_steady_state_can_meet_is_the_nearest_one_not_an_error():
    """A cart's velocity is zero at every steady state: asking 0.5 gives the nearest target (v = 0)
    with its gap, whatever the solver makes of the infeasible exact problem."""
    system = prepare(load_scenario(ROOT / "scenarios" / "carts.yaml")).system
    space = TargetSpace(system)
    t = space.target(request(system.n, system.m, {1: 0.5}))
    assert not t.reachable
    assert abs(t.x[1]) < 1e-9 and t.gap_x[1] == pytest.approx(-0.5, abs=1e-9)
    assert np.abs(system.A @ t.x + system.B @ t.u - t.x).max() < 1e-9


def test_bad_requests_are_refused(space):
    with pytest.raises(TargetError, match="8 state and 4 input"):
        space.target(Request(np.zeros(7), np.full(4, np.nan)))
    with pytest.raises(TargetError, match="infinite"):
        space.target(request(8, 4, {0: np.inf}))


def test_the_scaled_terminal_set_is_invariant_and_admissible_around_the_target(paper, space, governor):
    """Corners of sigma-cubes inside lambda X^f: x_s + y stays admissible under u_s + K y, and A_K y
    stays in lambda X^f (the property the governor's condition rests on)."""
    _, AK, K = governor
    omega = paper.design.terminal.omega
    norms = np.abs(omega).sum(axis=1)
    rng = np.random.default_rng(1)
    for value in (1.0, -0.5, 15.0):
        t = space.target(request(8, 4, {0: value}))
        for _ in range(20):
            direction = rng.normal(size=8)
            alpha = direction / np.max(omega @ direction) * t.scale * rng.uniform(0, 0.9)
            radius = float(np.min((t.scale - omega @ alpha) / norms))
            assert radius >= 0
            for sign in rng.choice([-1.0, 1.0], size=(16, 8)):
                y = alpha + radius * sign
                assert np.max(omega @ y) <= t.scale + 1e-9
                assert np.abs(t.u + K @ y).max() <= U_BAR + 1e-9
                assert np.max(omega @ (AK @ y)) <= t.scale + 1e-9


def test_the_governor_takes_the_whole_way_when_the_candidates_allow_it(space, governor):
    gov, _, _ = governor
    here = space.target(request(8, 4, {0: 1.0}))
    there = space.target(request(8, 4, {0: -0.5}))
    step = gov.step(here.x.copy(), here, there)
    assert step.theta == 1.0 and step.target is there


def test_the_governor_takes_the_largest_safe_fraction_of_a_big_jump(space, governor):
    gov, _, _ = governor
    here = space.target(request(8, 4, {0: 1.0}))
    there = space.target(request(8, 4, {0: 18.0}))
    eta = here.x.copy()  # the plans end at the applied target: settled
    assert gov.slack(eta, there) < 0  # the plain jump leaves the candidates infeasible
    step = gov.step(eta, here, there)
    assert 0 < step.theta < 1
    # as far as the candidates stay feasible with the reserve: a box of RESERVE times the full one
    reserve = RESERVE * here.scale * gov.terminal.sigma(np.zeros(8))
    assert min(gov.slacks(eta, here)[1], gov.slacks(eta, here)[0]) > reserve > 0
    tail, box = gov.slacks(eta, step.target)
    assert tail >= 0 and box >= reserve - 1e-12
    further = here.towards(there, step.theta + 1e-6, space)
    tail, box = gov.slacks(eta, further)
    assert tail < 0 or box < reserve
    assert np.abs(step.target.x - (here.x + step.theta * (there.x - here.x))).max() < 1e-12


def test_the_governor_keeps_a_target_whose_candidates_already_fail(space, governor):
    gov, _, _ = governor
    here = space.target(request(8, 4, {0: 1.0}))
    there = space.target(request(8, 4, {0: 2.0}))
    far = here.x + 50.0
    assert gov.step(far, here, there).theta == 0.0


# ---------------------------------------------------------------- random coupled systems

@st.composite
def coupled_systems(draw):
    M = draw(st.integers(2, 4))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    subs, couplings = [], []
    for i in range(M):
        n, m = int(rng.integers(1, 3)), 1
        A = rng.normal(scale=0.6, size=(n, n))
        B = rng.normal(size=(n, m))
        ubar = rng.uniform(0.5, 3.0, size=m)
        xbar = rng.uniform(1.0, 10.0, size=n)
        state_set = LinearSet.box(-xbar, xbar) if rng.uniform() < 0.5 else None
        subs.append(Subsystem(str(i + 1), A, B, np.eye(n) * rng.uniform(0.5, 2), np.eye(m) * 0.1, np.zeros(n),
                              LinearSet.box(-ubar * rng.uniform(0.5, 1), ubar), state_set))
    for i in range(M - 1):
        couplings.append(Coupling(i + 1, i, rng.normal(scale=0.1, size=(subs[i + 1].n, subs[i].n)),
                                  np.zeros((subs[i + 1].n, subs[i].m))))
    return CoupledSystem(tuple(subs), tuple(couplings))


def independent_nearest(system: CoupledSystem, wanted_x: np.ndarray, margin: float):
    """The nearest admissible steady state to the requested components, by cvxpy: value of the objective."""
    n, m = system.n, system.m
    x, u = cp.Variable(n), cp.Variable(m)
    cons = [x == system.A @ x + system.B @ u]
    for i, s in enumerate(system.subsystems):
        U = s.input_set
        cons += [u[system.us(i)] <= (1 - margin) * U.upper, u[system.us(i)] >= (1 - margin) * U.lower]
        if s.state_set is not None:
            cons += [x[system.xs(i)] <= (1 - margin) * s.state_set.upper,
                     x[system.xs(i)] >= (1 - margin) * s.state_set.lower]
    pinned = ~np.isnan(wanted_x)
    weights = np.diag(system.Q)[pinned]
    objective = cp.sum(cp.multiply(weights, cp.square(x[pinned] - wanted_x[pinned])))
    problem = cp.Problem(cp.Minimize(objective), cons)
    problem.solve(solver=cp.CLARABEL)
    return problem.value


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(system=coupled_systems(), data=st.data())
def test_targets_of_random_systems_are_admissible_steady_states(system, data):
    space = TargetSpace(system)
    n, m = system.n, system.m
    component = data.draw(st.integers(0, n - 1))
    value = data.draw(st.floats(-20, 20))
    wanted = np.full(n, np.nan)
    wanted[component] = value
    t = space.target(Request(wanted, np.full(m, np.nan)))
    scale = np.abs(np.concatenate([system.A, system.B], axis=1)).max() + 1
    assert np.abs(system.A @ t.x + system.B @ t.u - t.x).max() <= 1e-7 * scale * (1 + np.abs(t.x).max())
    assert space.gauge(t.x, t.u) <= 1 - MARGIN + 1e-7
    assert t.scale >= MARGIN - 1e-7
    best = independent_nearest(system, wanted, MARGIN + MARGIN_ROOM)  # the margin the targets keep
    achieved = float(np.diag(system.Q)[component] * (t.x[component] - value) ** 2)
    assert achieved <= best + 1e-6 * (1 + best)
    if t.reachable:
        assert t.x[component] == pytest.approx(value, abs=1e-7 * (1 + abs(value)))
    else:
        assert best > 1e-10
        assert t.gap_x[component] == pytest.approx(t.x[component] - value, abs=1e-9)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(system=coupled_systems(), theta=st.floats(0.0, 1.0), data=st.data())
def test_steady_states_in_between_are_steady_and_inside(system, theta, data):
    space = TargetSpace(system)
    n, m = system.n, system.m
    ends = []
    for _ in range(2):
        wanted = np.full(n, np.nan)
        wanted[data.draw(st.integers(0, n - 1))] = data.draw(st.floats(-5, 5))
        ends.append(space.target(Request(wanted, np.full(m, np.nan))))
    mid = ends[0].towards(ends[1], theta, space)
    assert np.abs(system.A @ mid.x + system.B @ mid.u - mid.x).max() <= 1e-7 * (1 + np.abs(mid.x).max())
    assert mid.scale >= min(ends[0].scale, ends[1].scale) - 1e-9  # lambda is concave along the way


# ---------------------------------------------------------------- schedules

def test_the_latest_entry_at_or_before_k_holds_per_subsystem(paper):
    system = paper.system
    nan = np.nan
    schedule = Schedule(system, [SetpointEntry(0, 0, np.array([1.0, nan]), np.array([nan])),
                                 SetpointEntry(40, 0, np.array([-0.5, nan]), np.array([nan])),
                                 SetpointEntry(10, 2, np.array([nan, 0.3]), np.array([0.1]))])
    assert schedule.change_steps() == [0, 10, 40]
    r5, r10, r40 = schedule.request(5), schedule.request(10), schedule.request(40)
    assert r5.x[0] == 1.0 and np.isnan(r5.x[1:]).all() and np.isnan(r5.u).all()
    assert r10.x[5] == 0.3 and r10.u[2] == 0.1 and r10.x[0] == 1.0
    assert r40.x[0] == -0.5 and r40.x[5] == 0.3
    later = schedule.with_entry(SetpointEntry(20, 0, np.array([0.2, nan]), np.array([nan]), "operator"))
    assert later.request(25).x[0] == 0.2 and later.request(40).x[0] == -0.5
    assert Schedule(system).request(3).is_free

"""The event trigger's pieces, each against an independent computation.

- :func:`dmpc.core.trajectories.kept_plan` against the construction written out (shift, the
  correction Gamma^t e, the K tail, the end plus Gamma^N e), and :func:`kept_around` against the same
  construction done in deviation coordinates around a target;
- :meth:`dmpc.core.mpc_qp.MpcQP.violations`: about 0 for a solved plan, and each kind of row it
  checks found broken by the amount it is broken by;
- :class:`dmpc.core.unconstrained.UnconstrainedBound` against a dense KKT solve of the same
  equality-constrained QP, and below OSQP's constrained optimum;
- :class:`dmpc.agents.trigger.KeepRule`: every reason in a situation built for it, a keep otherwise;
- the wire format of ``Kept``, ``PlanMessage.reason`` and ``Release.kept``.

The agent is the paper's subsystem 1 (docs/algorithm.md, "The paper's example, corrected"), the
printed K_1 and P_1.
"""
from __future__ import annotations

import msgpack
import numpy as np
import pytest
import scipy.linalg as sla

from dmpc.agents.local_qp import LocalQP
from dmpc.agents.trigger import CHANGED, CONSTRAINTS, COST, LIMIT, NO_PLAN, PREDICTION, REASONS, KeepRule
from dmpc.bus.codec import DecodeError, decode, encode
from dmpc.bus.messages import Kept, PlanMessage, Release, messages_equal
from dmpc.core.mpc_qp import MpcQP, StageRows, plan_cost
from dmpc.core.system import LinearSet, Subsystem
from dmpc.core.trajectories import OperatingPoint, Plan, kept_around, kept_plan
from dmpc.core.unconstrained import UnconstrainedBound
from dmpc.offline.tubes import Tightening
from tests.helpers.reference import A_II, B_II, K_PAPER, P_PAPER, Q_I, R_I

N = 10
K_1, P_1 = K_PAPER[0], P_PAPER[0]
GAMMA_1 = A_II + B_II @ K_1


def explicit_kept(z: np.ndarray, v: np.ndarray, x_now: np.ndarray, end: np.ndarray, Gamma: np.ndarray,
                  K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The kept plan written out term by term (agents/trigger.py's docstring): with
    e = x_now - z(1), z'(t) = z(t+1) + Gamma^t e and v'(t) = v(t+1) + K Gamma^t e for t < N - 1,
    v'(N-1) = K z'(N-1), z'(N) = end + Gamma^N e; z'(0) = x_now."""
    Nh = v.shape[0]
    e = x_now - z[1]
    power = [np.linalg.matrix_power(Gamma, t) for t in range(Nh + 1)]
    zk = np.array([z[t + 1] + power[t] @ e for t in range(Nh)] + [end + power[Nh] @ e])
    vk = np.array([v[t + 1] + K @ power[t] @ e for t in range(Nh - 1)] + [K @ zk[Nh - 1]])
    zk[0] = x_now
    return zk, vk


def random_plan(rng, k: int, Nh: int, n: int, m: int) -> Plan:
    return Plan(k, 0, rng.normal(size=(Nh + 1, n)), rng.normal(size=(Nh, m)))


# ---------------------------------------------------------------- kept_plan, kept_around

@pytest.mark.parametrize("seed", range(6))
def test_kept_plan_is_the_shifted_plan_corrected_by_gamma_and_ended_at_the_centre(seed):
    rng = np.random.default_rng(seed)
    n, m, Nh = int(rng.integers(1, 4)), int(rng.integers(1, 3)), int(rng.integers(2, 9))
    plan = random_plan(rng, 6, Nh, n, m)
    Gamma, K = 0.5 * rng.normal(size=(n, n)), rng.normal(size=(m, n))
    x_now = plan.z[1] + rng.normal(scale=0.3, size=n)
    end = rng.normal(size=n)
    kept = kept_plan(plan, 7, x_now, end, Gamma, K)
    z, v = explicit_kept(plan.z, plan.v, x_now, end, Gamma, K)
    assert (kept.k, kept.round) == (7, 0)
    assert kept.z.shape == plan.z.shape and kept.v.shape == plan.v.shape
    assert np.array_equal(kept.z[0], x_now)  # exactly the measured state, not z(1) + e
    # matrix powers here, repeated products there: equal up to rounding
    np.testing.assert_allclose(kept.z, z, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(kept.v, v, rtol=1e-12, atol=1e-12)
    # the plan given is not changed
    assert kept.z is not plan.z and kept.v is not plan.v


def test_kept_plan_without_a_prediction_error_is_the_plain_shift():
    plan = random_plan(np.random.default_rng(1), 3, N, 2, 1)
    end = np.array([0.25, -0.5])
    kept = kept_plan(plan, 4, plan.z[1].copy(), end, GAMMA_1, K_1)
    assert np.array_equal(kept.z[:N], plan.z[1:]) and np.array_equal(kept.z[N], end)
    assert np.array_equal(kept.v[:N - 1], plan.v[1:]) and np.array_equal(kept.v[N - 1], K_1 @ plan.z[N])


def test_the_correction_keeps_the_dynamics_with_the_shifted_feedforward():
    """Why the kept plan is a feasible point: a plan that meets z(t+1) = A z + B v + c(t) at step
    k - 1, shifted and corrected by Gamma, meets the same dynamics with c shifted by one step, for
    any prediction error, when its end is A z(N) + B K z(N) + c(N-1) of the new feed-forward."""
    rng = np.random.default_rng(4)
    x_prev = np.array([1.5, -1.0])
    c_prev = rng.normal(scale=0.2, size=(N, 2))
    v_prev = rng.normal(size=(N, 1))
    z_prev = np.empty((N + 1, 2))
    z_prev[0] = x_prev
    for t in range(N):
        z_prev[t + 1] = A_II @ z_prev[t] + B_II @ v_prev[t] + c_prev[t]
    c_new = np.vstack([c_prev[1:], rng.normal(scale=0.2, size=(1, 2))])
    end = GAMMA_1 @ z_prev[N] + c_new[N - 1]
    e = np.array([0.03, -0.02])
    kept = kept_plan(Plan(2, 0, z_prev, v_prev), 3, z_prev[1] + e, end, GAMMA_1, K_1)
    residual = kept.z[1:] - (kept.z[:-1] @ A_II.T + kept.v @ B_II.T + c_new)
    assert np.max(np.abs(residual)) < 1e-13  # measured 1.4e-14 (A is unstable: the entries grow)


@pytest.mark.parametrize("seed", range(4))
def test_kept_around_a_target_is_kept_plan_in_deviation_coordinates(seed):
    rng = np.random.default_rng(10 + seed)
    n, m = 2, 1
    plan = random_plan(rng, 4, N, n, m)
    x_s, u_s = rng.normal(size=n), rng.normal(size=m)
    x_now = plan.z[1] + rng.normal(scale=0.1, size=n)
    end = rng.normal(size=n)  # relative to the target, as alpha_i(k) is
    kept = kept_around(plan, 5, x_now, end, GAMMA_1, K_1, (x_s, u_s))
    dz, dv = explicit_kept(plan.z - x_s, plan.v - u_s, x_now - x_s, end, GAMMA_1, K_1)
    np.testing.assert_allclose(kept.z, dz + x_s, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(kept.v, dv + u_s, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(kept.z[0], x_now, rtol=0, atol=1e-14)
    # the tail is K applied in deviation coordinates, not to the plant's state
    np.testing.assert_allclose(kept.v[N - 1] - u_s, K_1 @ (kept.z[N - 1] - x_s), atol=1e-12)
    assert np.max(np.abs(kept.v[N - 1] - K_1 @ kept.z[N - 1])) > 1e-3
    # no target (the origin): kept_plan itself, bit for bit
    origin = OperatingPoint.origin(n, m)
    plain, direct = kept_around(plan, 5, x_now, end, GAMMA_1, K_1, origin), kept_plan(plan, 5, x_now, end, GAMMA_1, K_1)
    assert np.array_equal(plain.z, direct.z) and np.array_equal(plain.v, direct.v)


# ---------------------------------------------------------------- MpcQP.violations

def mpc_qp(input_bound: float = 2.5, state_bound: float | None = None) -> MpcQP:
    inputs = StageRows(np.eye(1), np.full((N, 1), -input_bound), np.full((N, 1), input_bound))
    states = None
    if state_bound is not None:
        states = StageRows(np.eye(2), np.full((N, 2), -state_bound), np.full((N, 2), state_bound))
    return MpcQP(A_II, B_II, Q_I, R_I, P_1, N, inputs, states, np.eye(2))


def rollout(x: np.ndarray, v: np.ndarray, c: np.ndarray) -> np.ndarray:
    z = [x]
    for t in range(v.shape[0]):
        z.append(A_II @ z[-1] + B_II @ v[t] + c[t])
    return np.array(z)


X_START = np.array([2.794, 2.5])  # the paper's x_1(0): the input saturates in the first steps


@pytest.fixture
def solved():
    """A solved QP with active input rows: (qp, x, c, terminal lower, upper, solution)."""
    qp = mpc_qp(state_bound=4.0)
    c = np.random.default_rng(2).uniform(-0.3, 0.3, (N, 2))
    lower, upper = np.full(2, -1.0), np.full(2, 1.0)
    sol = qp.solve(X_START, c, lower, upper)
    assert sol.status.feasible and sol.polished
    assert np.isclose(np.max(np.abs(sol.v)), 2.5, atol=1e-6)  # an input row is active
    return qp, X_START, c, lower, upper, sol


def test_a_solved_plan_violates_nothing(solved):
    qp, x, c, lower, upper, sol = solved
    dynamics, rows = qp.violations(x, c, lower, upper, sol.z, sol.v)
    assert dynamics < 1e-12  # polished: measured 1.0e-15
    assert rows < 1e-9  # measured 0: every row met


def test_a_changed_feedforward_is_a_dynamics_residual(solved):
    qp, x, c, lower, upper, sol = solved
    changed = c.copy()
    changed[3, 1] += 1e-3
    dynamics, rows = qp.violations(x, changed, lower, upper, sol.z, sol.v)
    assert dynamics == pytest.approx(1e-3, rel=1e-6)  # |c| < 1: relative to 1
    assert rows < 1e-9
    big = c.copy()
    big[5, 0] = 4.0
    dynamics, _ = qp.violations(x, big, lower, upper, sol.z, sol.v)
    assert dynamics == pytest.approx(abs(4.0 - c[5, 0]) / 4.0, rel=1e-6)  # relative to |c| = 4
    # another measured state: the first dynamics row
    dynamics, _ = qp.violations(x + np.array([0.0, 0.02]), c, lower, upper, sol.z, sol.v)
    assert dynamics == pytest.approx(0.02 / 2.52, rel=1e-6)


def test_an_input_beyond_its_bound_is_a_row_excess():
    qp = mpc_qp(input_bound=2.5)
    c = np.zeros((N, 2))
    v = np.full((N, 1), 0.1)
    v[2] = 2.5 + 0.25  # the only row broken
    z = rollout(np.array([0.1, 0.1]), v, c)
    dynamics, rows = qp.violations(z[0], c, np.full(2, -1e3), np.full(2, 1e3), z, v)
    assert dynamics < 1e-12
    assert rows == pytest.approx(0.25 / 2.5, rel=1e-9)  # relative to |bound| = 2.5
    v[2] = -2.5 - 0.5
    z = rollout(np.array([0.1, 0.1]), v, c)
    assert qp.violations(z[0], c, np.full(2, -1e3), np.full(2, 1e3), z, v)[1] == pytest.approx(0.2, rel=1e-9)


def test_a_state_beyond_its_bound_is_a_row_excess():
    qp = mpc_qp(input_bound=100.0, state_bound=0.5)
    c = np.zeros((N, 2))
    v = np.zeros((N, 1))
    v[0] = 0.3  # z(1) = A 0 + B 0.3 = [0.3, 0.3]; then grows: A is unstable
    z = rollout(np.zeros(2), v, c)
    dynamics, rows = qp.violations(z[0], c, np.full(2, -1e9), np.full(2, 1e9), z, v)
    excess = float(np.max(np.abs(z[1:])) - 0.5)
    assert dynamics < 1e-12 and excess > 0.1
    assert rows == pytest.approx(excess, rel=1e-9)  # relative to max(1, 0.5) = 1


def test_a_terminal_state_outside_the_box_is_a_row_excess(solved):
    qp, x, c, _, _, sol = solved
    end = sol.z[N]
    lower, upper = end - 1.0, end.copy()
    upper[1] = end[1] - 0.01  # z(N) 0.01 above the box on its second coordinate
    dynamics, rows = qp.violations(x, c, lower, upper, sol.z, sol.v)
    assert dynamics < 1e-12
    assert rows == pytest.approx(0.01 / max(1.0, abs(upper[1])), rel=1e-6)
    # the box given is the one checked: a box that holds z(N) gives no excess
    assert qp.violations(x, c, end - 0.01, end + 0.01, sol.z, sol.v)[1] < 1e-9


def test_violations_follow_the_offset_of_a_target():
    """With a setpoint target the stage rows move (U - u_s): the check uses the moved rows."""
    qp = mpc_qp(input_bound=2.5)
    c = np.zeros((N, 2))
    v = np.full((N, 1), 1.8)
    z = rollout(np.zeros(2), v, c)
    wide = (np.full(2, -1e9), np.full(2, 1e9))
    assert qp.violations(z[0], c, *wide, z, v)[1] == 0.0
    qp.set_offset(np.zeros(2), np.array([1.0]))  # |v + 1| <= 2.5: v <= 1.5
    assert qp.violations(z[0], c, *wide, z, v)[1] == pytest.approx(0.3 / 1.5, rel=1e-9)
    qp.set_offset(np.zeros(2), np.zeros(1))  # the origin
    assert qp.violations(z[0], c, *wide, z, v)[1] == 0.0


# ---------------------------------------------------------------- UnconstrainedBound

def kkt_optimum(A, B, Q, R, P, Nh, x, c) -> float:
    """min sum z'Qz + v'Rv + z(N)'P z(N) s.t. z(0) = x, z(t+1) = A z(t) + B v(t) + c(t), by one
    dense solve of its KKT system in w = [z(0..N), v(0..N-1)]."""
    n, m = B.shape
    nz, nv = (Nh + 1) * n, Nh * m
    H = sla.block_diag(*([Q] * Nh + [P] + [R] * Nh))
    E = np.zeros(((Nh + 1) * n, nz + nv))
    f = np.zeros((Nh + 1) * n)
    E[:n, :n] = np.eye(n)
    f[:n] = x
    for t in range(Nh):
        rows = slice((t + 1) * n, (t + 2) * n)
        E[rows, (t + 1) * n:(t + 2) * n] = np.eye(n)
        E[rows, t * n:(t + 1) * n] = -A
        E[rows, nz + t * m:nz + (t + 1) * m] = -B
        f[rows] = c[t]
    kkt = np.block([[2 * H, E.T], [E, np.zeros((E.shape[0], E.shape[0]))]])
    w = np.linalg.solve(kkt, np.concatenate([np.zeros(nz + nv), f]))[:nz + nv]
    return float(w @ H @ w)


def random_weights(rng, n, m):
    G = rng.normal(size=(n, n))
    Q = G @ G.T + 0.1 * np.eye(n)
    G = rng.normal(size=(m, m))
    R = G @ G.T + 0.05 * np.eye(m)
    G = rng.normal(size=(n, n))
    return Q, R, G @ G.T + np.eye(n)


@pytest.mark.parametrize("seed", range(12))
def test_unconstrained_bound_is_the_kkt_optimum_and_below_the_constrained_one(seed):
    rng = np.random.default_rng(100 + seed)
    n, m, Nh = int(rng.integers(1, 4)), int(rng.integers(1, 3)), int(rng.integers(2, 9))
    A, B = rng.normal(scale=0.7, size=(n, n)), rng.normal(size=(n, m))
    Q, R, P = random_weights(rng, n, m)
    x, c = rng.normal(size=n), rng.normal(scale=0.3, size=(Nh, n))
    bound = UnconstrainedBound(A, B, Q, R, P, Nh)
    reference = kkt_optimum(A, B, Q, R, P, Nh, x, c)
    assert bound.cost(x, c) == pytest.approx(reference, rel=1e-9, abs=1e-10)
    assert bound.cost(x, None) == pytest.approx(kkt_optimum(A, B, Q, R, P, Nh, x, np.zeros((Nh, n))), rel=1e-9,
                                                abs=1e-10)
    # OSQP with input boxes tight enough to bind: never below the bound
    ubar = 0.3
    qp = MpcQP(A, B, Q, R, P, Nh, StageRows(np.eye(m), np.full((Nh, m), -ubar), np.full((Nh, m), ubar)), None,
               np.eye(n))
    sol = qp.solve(x, c, np.full(n, -1e6), np.full(n, 1e6))
    assert sol.status.feasible
    assert bound.cost(x, c) <= sol.cost + 1e-7 * max(1.0, sol.cost)
    # and equal to it when the boxes do not bind
    loose = MpcQP(A, B, Q, R, P, Nh, StageRows(np.eye(m), np.full((Nh, m), -1e4), np.full((Nh, m), 1e4)), None,
                  np.eye(n)).solve(x, c, np.full(n, -1e6), np.full(n, 1e6))
    assert loose.status.feasible
    assert bound.cost(x, c) == pytest.approx(loose.cost, rel=1e-6, abs=1e-8)


def test_unconstrained_bound_is_strictly_below_where_the_inputs_saturate(solved):
    qp, x, c, lower, upper, sol = solved
    bound = UnconstrainedBound(A_II, B_II, Q_I, R_I, P_1, N)
    assert bound.cost(x, c) < sol.cost - 1.0  # measured 19.6 against 33.3: U binds


# ---------------------------------------------------------------- KeepRule

def rule_qp(input_bound: float = 2.5, state_bound: float | None = None) -> LocalQP:
    sub = Subsystem(name="1", A=A_II, B=B_II, Q=Q_I, R=R_I, x0=np.zeros(2),
                    input_set=LinearSet.box([-input_bound], [input_bound]),
                    state_set=None if state_bound is None else LinearSet.box([-state_bound] * 2, [state_bound] * 2))
    return LocalQP(sub, P_1, N, Tightening.none(2, 1, 0 if state_bound is None else 2, N))


def keep_rule(qp: LocalQP | None = None, threshold: float = 1e-6, cost: float = 1e3,
              max_keep: int | None = None) -> KeepRule:
    return KeepRule(qp or rule_qp(), UnconstrainedBound(A_II, B_II, Q_I, R_I, P_1, N), Q_I, R_I, P_1, GAMMA_1, K_1,
                    threshold, cost, max_keep)


class Step:
    """Agent 1's plan of step k - 1 = 4 and step k = 5 as the protocol gives it: the measured state
    its plan predicted (plus ``error``), the feed-forward shifted by one step with a new last entry,
    and the centre where the dynamics take the plan's end (what alpha_1(k) is when every agent
    keeps)."""

    def __init__(self, error=(0.0, 0.0)) -> None:
        rng = np.random.default_rng(7)
        self.c_prev = rng.uniform(-0.2, 0.2, (N, 2))
        sol = rule_qp().solve(np.array([1.2, -0.9]), self.c_prev, np.zeros(2), 1.0)
        assert sol.status.feasible
        self.previous = Plan(4, 0, sol.z, sol.v)
        self.k = 5
        self.c = np.vstack([self.c_prev[1:], [[0.05, -0.03]]])
        self.centre = GAMMA_1 @ sol.z[N] + self.c[N - 1]
        self.x = sol.z[1] + np.asarray(error)
        self.size = 1.0

    def decide(self, rule: KeepRule, **changes):
        args = dict(k=self.k, x=self.x, coupling=self.c, centre=self.centre, size=self.size, previous=self.previous,
                    kept_so_far=0)
        args.update(changes)
        return rule.decide(**args)


def test_keeps_the_shifted_plan_when_every_test_passes():
    step = Step()
    decision = step.decide(keep_rule())
    assert decision.keep and decision.reason == ""
    expected = kept_plan(step.previous, step.k, step.x, step.centre, GAMMA_1, K_1)
    assert np.array_equal(decision.plan.z, expected.z) and np.array_equal(decision.plan.v, expected.v)
    assert decision.cost == plan_cost(expected.z, expected.v, Q_I, R_I, P_1)
    # the kept plan is a feasible point of the step's QP (its own check, independently of the rule)
    dynamics, rows = rule_qp().violations(step.x, step.c, step.centre, step.size, expected.z, expected.v)
    assert dynamics < 1e-12 and rows == 0.0


def test_no_plan_to_keep():
    step = Step()
    assert step.decide(keep_rule(), previous=None).reason == NO_PLAN
    older = Plan(3, 0, step.previous.z, step.previous.v)  # a plan of step k - 2 (a fallback at k - 1)
    assert step.decide(keep_rule(), previous=older).reason == NO_PLAN
    assert step.decide(keep_rule(), k=0, previous=None).reason == NO_PLAN


def test_the_limit_of_consecutive_keeps():
    step = Step()
    rule = keep_rule(max_keep=3)
    assert step.decide(rule, kept_so_far=2).keep
    assert step.decide(rule, kept_so_far=3).reason == LIMIT
    assert step.decide(keep_rule(max_keep=None), kept_so_far=10**6).keep


def test_a_prediction_error_above_the_threshold():
    step = Step(error=(0.0, 2e-3))
    assert step.decide(keep_rule(threshold=1e-3)).reason == PREDICTION
    # below the threshold the corrected plan is kept: it still meets the dynamics
    assert step.decide(keep_rule(threshold=2.001e-3)).keep
    assert Step(error=(-9e-4, 5e-4)).decide(keep_rule(threshold=1e-3)).keep


def test_a_changed_neighbour_feedforward():
    step = Step()
    c = step.c.copy()
    c[4, 0] += 1e-5  # a neighbour's plan moved: 100 times the rule's tolerance
    assert step.decide(keep_rule(), coupling=c).reason == CHANGED
    c[4, 0] = step.c[4, 0] + 5e-8  # below its tolerance (1e-7): the solver's own accuracy
    assert step.decide(keep_rule(), coupling=c).keep
    # a centre that is not where the dynamics take the plan's end breaks its last dynamics row
    assert step.decide(keep_rule(), centre=step.centre + np.array([1e-4, 0.0])).reason == CHANGED


def test_a_broken_terminal_box():
    step = Step(error=(0.05, -0.05))
    reach = np.max(np.abs(np.linalg.matrix_power(GAMMA_1, N) @ np.array([0.05, -0.05])))
    assert reach > 1e-4  # |Gamma^N e|: where the kept plan ends off the centre
    rule = keep_rule(threshold=0.1)
    assert step.decide(rule, size=0.5 * reach).reason == CONSTRAINTS
    assert step.decide(rule, size=1.01 * reach).keep


def test_broken_input_and_state_rows():
    step = Step()
    kept = kept_plan(step.previous, step.k, step.x, step.centre, GAMMA_1, K_1)
    largest_v, largest_z = float(np.max(np.abs(kept.v))), float(np.max(np.abs(kept.z[1:])))
    assert step.decide(keep_rule(rule_qp(input_bound=0.9 * largest_v))).reason == CONSTRAINTS
    assert step.decide(keep_rule(rule_qp(input_bound=1.01 * largest_v))).keep
    assert step.decide(keep_rule(rule_qp(state_bound=0.9 * largest_z))).reason == CONSTRAINTS
    assert step.decide(keep_rule(rule_qp(state_bound=1.01 * largest_z))).keep


def test_keeping_that_gives_up_more_than_the_cost_threshold():
    step = Step()
    kept = kept_plan(step.previous, step.k, step.x, step.centre, GAMMA_1, K_1)
    gap = plan_cost(kept.z, kept.v, Q_I, R_I, P_1) - UnconstrainedBound(A_II, B_II, Q_I, R_I, P_1, N).cost(step.x,
                                                                                                         step.c)
    assert gap > 1e-3  # measured 7.2e-3: the shifted plan is not the optimum of the new QP
    assert step.decide(keep_rule(cost=gap * (1 - 1e-6))).reason == COST
    assert step.decide(keep_rule(cost=gap * (1 + 1e-6))).keep


def test_the_first_failed_test_is_the_reason():
    """Prediction before the rows, the limit before the prediction, the dynamics before the cost."""
    step = Step(error=(0.3, 0.0))
    c = step.c.copy()
    c[0, 0] += 1.0
    assert step.decide(keep_rule(threshold=0.1, max_keep=1), kept_so_far=1, coupling=c).reason == LIMIT
    assert step.decide(keep_rule(threshold=0.1, cost=0.0), coupling=c).reason == PREDICTION
    assert step.decide(keep_rule(threshold=1.0, cost=0.0), coupling=c, size=0.0).reason == CHANGED
    assert step.decide(keep_rule(threshold=1.0, cost=0.0), size=0.0).reason == CONSTRAINTS
    assert step.decide(keep_rule(threshold=1.0, cost=0.0)).reason == COST
    assert {NO_PLAN, LIMIT, PREDICTION, CHANGED, CONSTRAINTS, COST} < set(REASONS)


# ---------------------------------------------------------------- the wire

def test_kept_round_trips():
    msg = Kept(run="r1", k=17, round=0, sender="agent-3", sent_at=12.5)
    raw = encode(msg)
    back = decode(raw)
    assert isinstance(back, Kept) and back == msg
    body = msgpack.unpackb(raw, raw=False)
    assert body["type"] == "kept" and "z" not in body and "v" not in body
    assert len(raw) < 100  # a notice, not a plan


@pytest.mark.parametrize("reason", ["", *REASONS])
def test_plan_reason_round_trips_and_is_left_out_when_empty(reason):
    msg = PlanMessage(run="r", k=3, round=0, sender="2", status="solved", z=np.arange(6.0).reshape(3, 2),
                      v=np.ones((2, 1)), cost=1.5, solve_time=1e-4, qp_iterations=5, reason=reason)
    raw = encode(msg)
    back = decode(raw)
    assert messages_equal(back, msg) and back.reason == reason
    assert ("reason" in msgpack.unpackb(raw, raw=False)) == bool(reason)


@pytest.mark.parametrize("kept", [(), ("1",), ("1", "3")])
def test_release_kept_round_trips_and_is_left_out_when_empty(kept):
    msg = Release(run="r", k=4, round=0, x=np.zeros(6), centres=np.zeros(6), sizes=np.ones(3),
                  assumed=np.array([[3, 0], [3, 0], [3, 0]]), kept=kept)
    raw = encode(msg)
    back = decode(raw)
    assert messages_equal(back, msg) and back.kept == kept
    assert ("kept" in msgpack.unpackb(raw, raw=False)) == bool(kept)


@pytest.mark.parametrize("message, mutate, match", [
    (PlanMessage(run="r", k=1, round=0, sender="1", status="solved", z=np.zeros((2, 2)), v=np.zeros((1, 1)),
                 cost=1.0, solve_time=0.0, qp_iterations=1, reason="cost"), lambda b: b.update(reason=""), "reason"),
    (PlanMessage(run="r", k=1, round=0, sender="1", status="solved", z=np.zeros((2, 2)), v=np.zeros((1, 1)),
                 cost=1.0, solve_time=0.0, qp_iterations=1, reason="cost"), lambda b: b.update(reason=3), "reason"),
    (Release(run="r", k=1, round=0, x=np.zeros(2), centres=np.zeros(2), sizes=np.ones(2),
             assumed=np.array([[0, 0], [0, 0]]), kept=("1",)), lambda b: b.update(kept=[]), "kept"),
    (Release(run="r", k=1, round=0, x=np.zeros(2), centres=np.zeros(2), sizes=np.ones(2),
             assumed=np.array([[0, 0], [0, 0]]), kept=("1",)), lambda b: b.update(kept=["1", "2", "3"]), "kept"),
    (Kept(run="r", k=1, round=0, sender="1"), lambda b: b.update(k=-1), "k"),
    (Kept(run="r", k=1, round=0, sender="1"), lambda b: b.update(sender=""), "sender"),
    (Kept(run="r", k=1, round=0, sender="1"), lambda b: b.pop("sent_at"), "missing"),
    (Kept(run="r", k=1, round=0, sender="1"), lambda b: b.update(z=[]), "unexpected"),
])
def test_trigger_fields_defects_named(message, mutate, match):
    body = msgpack.unpackb(encode(message), raw=False)
    mutate(body)
    with pytest.raises(DecodeError, match=match):
        decode(msgpack.packb(body, use_bin_type=True))

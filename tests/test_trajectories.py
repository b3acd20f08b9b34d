"""dmpc.core.trajectories on small integer examples, with the expected values written out by hand.

Plan made at k' = 5 with N = 3: z = [1,2],[3,4],[5,6],[7,8]; v = 10, 20, 30.
Local terminal dynamics Gamma = [[0,1],[2,0]], K = [1, 2] (chosen for exact integer arithmetic,
not as A + BK of a real system): the tail is Gamma [7,8] = [8,14], Gamma [8,14] = [14,16],
Gamma [14,16] = [16,28]; K [7,8] = 23, K [8,14] = 36, K [14,16] = 46.
"""
from __future__ import annotations

import numpy as np
import pytest

from dmpc.core.trajectories import (
    Plan,
    assumed_trajectory,
    candidate_plan,
    continued,
    coupling_feedforward,
    k_rollout,
    shifted_input,
)

GAMMA = np.array([[0.0, 1.0], [2.0, 0.0]])
K = np.array([[1.0, 2.0]])
N = 3
X_NOW = np.array([-1.0, 1.0])


@pytest.fixture
def plan():
    return Plan(k=5, round=2, z=np.array([[1.0, 2], [3, 4], [5, 6], [7, 8]]), v=np.array([[10.0], [20], [30]]))


# ---------------------------------------------------------------- continued

def test_continued_within_the_horizon(plan):
    z, v = continued(plan, 3, GAMMA, K)
    np.testing.assert_array_equal(z, plan.z)
    np.testing.assert_array_equal(v, plan.v)
    z, v = continued(plan, 2, GAMMA, K)
    np.testing.assert_array_equal(z, plan.z[:3])
    np.testing.assert_array_equal(v, plan.v[:2])


def test_continued_beyond_the_horizon(plan):
    z, v = continued(plan, 6, GAMMA, K)
    np.testing.assert_array_equal(z, [[1, 2], [3, 4], [5, 6], [7, 8], [8, 14], [14, 16], [16, 28]])
    np.testing.assert_array_equal(v, [[10], [20], [30], [23], [36], [46]])
    assert z.shape == (7, 2) and v.shape == (6, 1)


def test_continued_beyond_the_horizon_does_not_alias_the_plan(plan):
    z0, v0 = plan.z.copy(), plan.v.copy()
    z, v = continued(plan, 5, GAMMA, K)
    z[:] = 0
    v[:] = 0
    np.testing.assert_array_equal(plan.z, z0)
    np.testing.assert_array_equal(plan.v, v0)


# ---------------------------------------------------------------- assumed trajectories

def test_assumed_shift_0(plan):
    zhat, vhat = assumed_trajectory(plan, 5, X_NOW, N, GAMMA, K)
    np.testing.assert_array_equal(zhat, [[-1, 1], [3, 4], [5, 6]])
    np.testing.assert_array_equal(vhat, [[10], [20], [30]])


def test_assumed_shift_1_is_assumption_1(plan):
    """zhat(0) = x measured, zhat(t) = z*(t+1), vhat(t) = v*(t+1), vhat(N-1) = K eta."""
    zhat, vhat = assumed_trajectory(plan, 6, X_NOW, N, GAMMA, K)
    np.testing.assert_array_equal(zhat, [[-1, 1], [5, 6], [7, 8]])
    np.testing.assert_array_equal(vhat, [[20], [30], [23]])
    np.testing.assert_array_equal(vhat[-1], K @ plan.z[N])


def test_assumed_shift_3(plan):
    zhat, vhat = assumed_trajectory(plan, 8, X_NOW, N, GAMMA, K)
    np.testing.assert_array_equal(zhat, [[-1, 1], [8, 14], [14, 16]])
    np.testing.assert_array_equal(vhat, [[23], [36], [46]])
    assert zhat.shape == (N, 2) and vhat.shape == (N, 1)


def test_assumed_states_are_a_copy(plan):
    z0 = plan.z.copy()
    for k in (5, 6, 8):
        zhat, _ = assumed_trajectory(plan, k, X_NOW, N, GAMMA, K)
        zhat[:] = 99
    np.testing.assert_array_equal(plan.z, z0)


def test_assumed_inputs_are_a_copy(plan):
    for k in (5, 6, 8):
        _, vhat = assumed_trajectory(plan, k, X_NOW, N, GAMMA, K)
        vhat[:] = 99
    np.testing.assert_array_equal(plan.v, [[10], [20], [30]])


def test_assumed_without_a_plan_is_the_k_rollout():
    zhat, vhat = assumed_trajectory(None, 7, X_NOW, N, GAMMA, K)
    np.testing.assert_array_equal(zhat, [[-1, 1], [1, -2], [-2, 2]])
    np.testing.assert_array_equal(vhat, [[1], [-3], [2]])


def test_candidate_without_a_plan_is_the_k_rollout_over_the_horizon():
    z, v = candidate_plan(None, 7, X_NOW, N, GAMMA, K)
    np.testing.assert_array_equal(z, [[-1, 1], [1, -2], [-2, 2], [2, -4]])
    np.testing.assert_array_equal(v, [[1], [-3], [2]])


@pytest.mark.parametrize("k", [5, 6, 8])
def test_candidate_is_the_plan_shifted_to_k_and_continued(plan, k):
    z, v = candidate_plan(plan, k, None, N, GAMMA, K)
    shift = k - plan.k
    z_full, v_full = continued(plan, shift + N, GAMMA, K)
    assert z.shape == (N + 1, 2) and v.shape == (N, 1)
    np.testing.assert_array_equal(z, z_full[shift:])
    np.testing.assert_array_equal(v, v_full[shift:])
    if k == 6:  # plan row 1 on: z(1..3), then Gamma z(3) = (8, 14); v(1..2), then K z(3) = 23
        np.testing.assert_array_equal(z, [[3, 4], [5, 6], [7, 8], [8, 14]])
        np.testing.assert_array_equal(v, [[20], [30], [23]])


def test_k_rollout():
    z, v = k_rollout(np.array([1.0, 0.0]), 4, GAMMA, K)
    np.testing.assert_array_equal(z, [[1, 0], [0, 2], [2, 0], [0, 4]])
    np.testing.assert_array_equal(v, [[1], [4], [2], [8]])
    z, v = k_rollout(np.array([3.0, 4.0]), 1, GAMMA, K)
    np.testing.assert_array_equal(z, [[3, 4]])
    np.testing.assert_array_equal(v, [[11]])


# ---------------------------------------------------------------- fallback input

@pytest.mark.parametrize("k, expected", [(5, 6.0), (6, 10.0), (7, 14.0), (8, 1.0), (9, 1.0)])
def test_shifted_input_literal(plan, k, expected):
    # k=5: 10 + K([-1,1]-[1,2]) = 6;  k=6: 20 + K([-1,1]-[3,4]) = 10;  k=7: 30 + K([-1,1]-[5,6]) = 14
    # k=8: 23 + K([-1,1]-[7,8]) = 1;  k=9: 36 + K([-1,1]-[8,14]) = 1
    np.testing.assert_array_equal(shifted_input(plan, k, X_NOW, GAMMA, K), [expected])


@pytest.mark.parametrize("shift", [0, 1, 2, 3, 4, 6])
def test_shifted_input_is_v_plus_K_error(plan, shift):
    z, v = [list(plan.z), list(plan.v)]
    while len(z) <= shift + 1:
        z.append(GAMMA @ z[-1])
    while len(v) <= shift:
        v.append(K @ z[len(v)])
    x = np.array([0.5, -2.0])
    np.testing.assert_allclose(shifted_input(plan, plan.k + shift, x, GAMMA, K), v[shift] + K @ (x - z[shift]),
                               rtol=0, atol=1e-12)


def test_shifted_input_on_the_plan_is_the_planned_input(plan):
    for s in range(N):
        np.testing.assert_array_equal(shifted_input(plan, plan.k + s, plan.z[s], GAMMA, K), plan.v[s])


def test_shifted_input_without_a_plan_is_Kx():
    np.testing.assert_array_equal(shifted_input(None, 3, X_NOW, GAMMA, K), [1.0])


# ---------------------------------------------------------------- coupling feed-forward

def test_coupling_feedforward_sums_the_neighbours():
    # neighbour a: n_j = 2, m_j = 1; neighbour b: n_j = 1, m_j = 2; receiver n_i = 2
    A_a = np.array([[1.0, 0.0], [0.0, 2.0]])
    B_a = np.array([[0.0], [1.0]])
    A_b = np.array([[3.0], [0.0]])
    B_b = np.array([[1.0, 1.0], [0.0, -1.0]])
    za = np.array([[1.0, 1.0], [2.0, 0.0], [0.0, 1.0]])
    va = np.array([[5.0], [0.0], [-1.0]])
    zb = np.array([[1.0], [0.0], [2.0]])
    vb = np.array([[1.0, 2.0], [0.0, 0.0], [1.0, -1.0]])
    c = coupling_feedforward([A_a, A_b], [B_a, B_b], [(za, va), (zb, vb)], N, 2)
    # t=0: A_a[1,1] = [1,2], B_a 5 = [0,5], A_b 1 = [3,0], B_b [1,2] = [3,-2]  -> [7, 5]
    # t=1: A_a[2,0] = [2,0], B_a 0 = 0,   A_b 0 = 0,     B_b 0 = 0          -> [2, 0]
    # t=2: A_a[0,1] = [0,2], B_a -1 = [0,-1], A_b 2 = [6,0], B_b [1,-1] = [0,1] -> [6, 2]
    np.testing.assert_array_equal(c, [[7, 5], [2, 0], [6, 2]])


def test_coupling_feedforward_without_neighbours_is_zero():
    c = coupling_feedforward([], [], [], N, 2)
    np.testing.assert_array_equal(c, np.zeros((N, 2)))


def test_coupling_feedforward_is_linear_in_the_assumptions():
    rng = np.random.default_rng(3)
    A, B = rng.normal(size=(2, 2)), rng.normal(size=(2, 1))
    z1, v1 = rng.normal(size=(N, 2)), rng.normal(size=(N, 1))
    z2, v2 = rng.normal(size=(N, 2)), rng.normal(size=(N, 1))
    both = coupling_feedforward([A, A], [B, B], [(z1, v1), (z2, v2)], N, 2)
    summed = coupling_feedforward([A], [B], [(z1 + z2, v1 + v2)], N, 2)
    np.testing.assert_allclose(both, summed, atol=1e-12)
    for t in range(N):
        np.testing.assert_allclose(both[t], A @ (z1[t] + z2[t]) + B @ (v1[t] + v2[t]), atol=1e-12)


def test_the_usual_one_step_shift_equals_the_continuation_exactly():
    """assumed_trajectory and candidate_plan take a shortcut for a plan of the step before; it
    must give the continuation's numbers bit for bit (run and simulate must agree to 1e-9)."""
    rng = np.random.default_rng(7)
    plan = Plan(4, 2, rng.normal(size=(N + 1, 2)), rng.normal(size=(N, 1)))
    z, v = continued(plan, N + 1, GAMMA, K)
    zhat, vhat = assumed_trajectory(plan, 5, X_NOW, N, GAMMA, K)
    expected = z[1:N + 1].copy()
    expected[0] = X_NOW
    assert np.array_equal(zhat, expected) and np.array_equal(vhat, v[1:N + 1])
    zc, vc = candidate_plan(plan, 5, None, N, GAMMA, K)
    assert np.array_equal(zc, z[1:]) and np.array_equal(vc, v[1:])

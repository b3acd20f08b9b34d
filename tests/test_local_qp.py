"""QP_i (docs/algorithm.md, "Online step k, agent i", item 3) against the same QP written independently in cvxpy
and solved by Clarabel.

The cvxpy problems are parametrised (x, c, alpha, beta) and built once per variant. The
hypothesis comparisons use a fresh LocalQP per example (the QP itself); reusing one LocalQP
over a sequence of instances (OSQP warm start, only bounds updated) is tested separately:
over feasible instances it must give the fresh answers, and over a sequence that contains
infeasible instances its verdicts must still be right.
"""
from __future__ import annotations

import cvxpy as cp
import numpy as np
import pytest
import scipy.linalg as sla
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from scipy.optimize import linprog

from dmpc.agents.local_qp import LocalQP, QPStatus
from dmpc.core.system import LinearSet, Subsystem
from dmpc.offline.tubes import Tightening
from tests.helpers.reference import A_II, B_II, P_PAPER, Q_I, R_I

N = 10


def paper_subsystem(state_set=None, input_set=None, B=B_II) -> Subsystem:
    return Subsystem(name="1", A=A_II, B=B, Q=Q_I, R=R_I if B.shape[1] == 1 else 0.01 * np.eye(B.shape[1]),
                     x0=np.zeros(2), input_set=input_set or LinearSet.box([-2.5], [2.5]), state_set=state_set)


class Variant:
    """A subsystem, its LocalQP and the independent cvxpy formulation of the same QP."""

    def __init__(self, sub: Subsystem, P: np.ndarray, tightening: Tightening) -> None:
        self.sub, self.P, self.tight = sub, P, tightening
        self.qp = LocalQP(sub, P, N, tightening)  # reused (warm-started) instance
        n, m = sub.n, sub.m
        self.x, self.alpha = cp.Parameter(n), cp.Parameter(n)
        self.c = cp.Parameter((N, n))
        self.beta = cp.Parameter()
        self.z, self.v = cp.Variable((N + 1, n)), cp.Variable((N, m))
        z, v = self.z, self.v
        cons = [z[0] == self.x]
        cost = 0
        for t in range(N):
            cons.append(z[t + 1] == sub.A @ z[t] + sub.B @ v[t] + self.c[t])
            H = sub.input_set.H
            hi = sub.input_set.upper - tightening.input_margin[t]
            lo = sub.input_set.lower + tightening.input_margin[t]
            fin_hi, fin_lo = np.isfinite(hi), np.isfinite(lo)
            if fin_hi.any():
                cons.append(H[fin_hi] @ v[t] <= hi[fin_hi])
            if fin_lo.any():
                cons.append(H[fin_lo] @ v[t] >= lo[fin_lo])
            cost += cp.quad_form(z[t], sub.Q) + cp.quad_form(v[t], sub.R)
        if sub.state_set is not None:
            H = sub.state_set.H
            for t in range(1, N + 1):
                hi = sub.state_set.upper - tightening.state_margin[t]
                lo = sub.state_set.lower + tightening.state_margin[t]
                cons += [H @ z[t] <= hi, H @ z[t] >= lo]
        radius = self.beta - tightening.terminal_margin
        cons += [z[N] - self.alpha <= radius, self.alpha - z[N] <= radius]
        cost += cp.quad_form(z[N], P)
        self.problem = cp.Problem(cp.Minimize(cost), cons)

    def reference(self, x, c, alpha, beta):
        self.x.value, self.c.value, self.alpha.value, self.beta.value = x, c, alpha, beta
        self.problem.solve(solver=cp.CLARABEL, tol_gap_abs=1e-11, tol_gap_rel=1e-11, tol_feas=1e-11)
        return self.problem.status

    def terminal_violation(self, x, c, alpha, beta) -> float:
        """Smallest s >= -inf such that the QP is feasible with the terminal box radius beta + s (an LP).

        The QP is feasible iff s <= 0; |s| tiny means a borderline instance.
        """
        sub, tight = self.sub, self.tight
        n, m = sub.n, sub.m
        # variables: v (N*m), s ; z is an affine function of v
        Phi = [np.zeros((n, N * m))]
        const = [np.asarray(x, float)]
        for t in range(N):
            Bt = np.zeros((n, N * m))
            Bt[:, t * m:(t + 1) * m] = sub.B
            Phi.append(sub.A @ Phi[-1] + Bt)
            const.append(sub.A @ const[-1] + c[t])
        rows, rhs = [], []
        for t in range(N):
            H = sub.input_set.H
            hi = sub.input_set.upper - tight.input_margin[t]
            lo = sub.input_set.lower + tight.input_margin[t]
            sel = np.zeros((H.shape[0], N * m))
            sel[:, t * m:(t + 1) * m] = H
            for r in range(H.shape[0]):
                if np.isfinite(hi[r]):
                    rows.append(np.append(sel[r], 0.0)); rhs.append(hi[r])
                if np.isfinite(lo[r]):
                    rows.append(np.append(-sel[r], 0.0)); rhs.append(-lo[r])
        if sub.state_set is not None:
            H = sub.state_set.H
            for t in range(1, N + 1):
                hi = sub.state_set.upper - tight.state_margin[t]
                lo = sub.state_set.lower + tight.state_margin[t]
                for r in range(H.shape[0]):
                    rows.append(np.append(H[r] @ Phi[t], 0.0)); rhs.append(hi[r] - H[r] @ const[t])
                    rows.append(np.append(-H[r] @ Phi[t], 0.0)); rhs.append(-lo[r] + H[r] @ const[t])
        radius = beta - tight.terminal_margin
        for r in range(n):
            rows.append(np.append(Phi[N][r], -1.0)); rhs.append(alpha[r] + radius[r] - const[N][r])
            rows.append(np.append(-Phi[N][r], -1.0)); rhs.append(-alpha[r] + radius[r] + const[N][r])
        obj = np.zeros(N * m + 1)
        obj[-1] = 1.0
        res = linprog(obj, A_ub=np.array(rows), b_ub=np.array(rhs), bounds=[(None, None)] * (N * m) + [(-50, None)],
                      method="highs")
        if res.status != 0:  # the input/state constraints alone are infeasible
            return np.inf
        return float(res.x[-1])


@pytest.fixture(scope="module")
def box_variant():
    return Variant(paper_subsystem(), P_PAPER[0], Tightening.none(2, 1, 0, N))


@pytest.fixture(scope="module")
def polytope_variant():
    """|x| <= 4, a non-box input polytope (-2.2 <= u <= 2.5, 0.5 u <= 1.1) and nonzero tightening margins."""
    state = LinearSet.box([-4.0, -4.0], [4.0, 4.0])
    inputs = LinearSet.polytope([[1.0], [-1.0], [0.5]], [2.5, 2.2, 1.1])
    assert not inputs.is_box
    tight = Tightening(input_margin=np.linspace(0.0, 0.3, N)[:, None] * np.ones((1, 3)),
                       state_margin=np.linspace(0.0, 0.5, N + 1)[:, None] * np.ones((1, 2)),
                       terminal_margin=np.array([0.05, 0.1]))
    return Variant(paper_subsystem(state_set=state, input_set=inputs), P_PAPER[1], tight)


@pytest.fixture(scope="module")
def two_input_variant():
    """Two inputs with a diamond |u1| + |u2| <= 3 (a genuinely 2-D polytope)."""
    B = np.array([[1.0, 0.0], [1.0, 0.5]])
    inputs = LinearSet.polytope([[1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]], [3.0] * 4)
    state = LinearSet.box([-4.0, -4.0], [4.0, 4.0])
    return Variant(paper_subsystem(state_set=state, input_set=inputs, B=B), P_PAPER[2], Tightening.none(2, 4, 2, N))


def vec(n, lo, hi):
    return st.lists(st.floats(lo, hi, allow_nan=False), min_size=n, max_size=n).map(np.array)


# ranges chosen so that both feasible and infeasible instances are common (see test_both_verdicts_occur)
instances = dict(x=vec(2, -7.0, 7.0), c=vec(2 * N, -0.5, 0.5).map(lambda a: a.reshape(N, 2)),
                 alpha=vec(2, -1.5, 1.5), beta=st.floats(0.2, 1.5))


def compare(variant: Variant, x, c, alpha, beta) -> None:
    sol = LocalQP(variant.sub, variant.P, N, variant.tight).solve(x, c, alpha, beta)
    ref = variant.reference(x, c, alpha, beta)
    if ref in (cp.INFEASIBLE, cp.INFEASIBLE_INACCURATE) or sol.status == QPStatus.INFEASIBLE:
        s = variant.terminal_violation(x, c, alpha, beta)
        assume(abs(s) > 1e-5)  # borderline instances: either verdict is acceptable
        if s > 0:
            assert ref in (cp.INFEASIBLE, cp.INFEASIBLE_INACCURATE)
            assert sol.status == QPStatus.INFEASIBLE, f"LP says infeasible by {s:.3g}, LocalQP {sol.status}"
            assert not sol.status.feasible
            assert np.all(np.isnan(sol.z)) and np.all(np.isnan(sol.v)) and np.isnan(sol.cost)
            return
    assert ref == cp.OPTIMAL, ref
    assert sol.status == QPStatus.SOLVED, sol.status
    assert sol.status.feasible
    J = variant.problem.value
    assert sol.cost == pytest.approx(J, abs=1e-5 * max(1.0, abs(J)))
    np.testing.assert_allclose(sol.v[0], variant.v.value[0], atol=1e-5)
    np.testing.assert_allclose(sol.z, variant.z.value, atol=1e-4)
    np.testing.assert_allclose(sol.v, variant.v.value, atol=1e-4)
    np.testing.assert_array_equal(sol.z[0], x)
    # the plan is a consistent trajectory of the dynamics with the feed-forward
    sub = variant.sub
    for t in range(N):
        np.testing.assert_allclose(sol.z[t + 1], sub.A @ sol.z[t] + sub.B @ sol.v[t] + c[t], atol=1e-6)
    # and its reported cost is the cost of that plan (OSQP's objective: equal to solver accuracy)
    cost = sum(sol.z[t] @ sub.Q @ sol.z[t] + sol.v[t] @ sub.R @ sol.v[t] for t in range(N)) + \
        sol.z[N] @ variant.P @ sol.z[N]
    assert sol.cost == pytest.approx(cost, rel=1e-7, abs=1e-9)


SETTINGS = dict(deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                         HealthCheck.filter_too_much])


@settings(max_examples=300, **SETTINGS)
@given(**instances)
def test_box_variant_matches_cvxpy(box_variant, x, c, alpha, beta):
    compare(box_variant, x, c, alpha, beta)


@settings(max_examples=300, **SETTINGS)
@given(**instances)
def test_polytope_variant_matches_cvxpy(polytope_variant, x, c, alpha, beta):
    compare(polytope_variant, x, c, alpha, beta)


@settings(max_examples=100, **SETTINGS)
@given(**instances)
def test_two_input_polytope_matches_cvxpy(two_input_variant, x, c, alpha, beta):
    compare(two_input_variant, x, c, alpha, beta)


def test_both_verdicts_occur(box_variant, polytope_variant):
    """The random instances above do contain feasible and infeasible ones (sanity of the generator)."""
    rng = np.random.default_rng(0)
    for variant in (box_variant, polytope_variant):
        seen = set()
        for _ in range(100):
            x = rng.uniform(-7, 7, 2)
            c = rng.uniform(-0.5, 0.5, (N, 2))
            alpha, beta = rng.uniform(-1.5, 1.5, 2), rng.uniform(0.2, 1.5)
            seen.add(variant.qp.solve(x, c, alpha, beta).status)
        assert {QPStatus.SOLVED, QPStatus.INFEASIBLE} <= seen


def random_instance(rng, scale=1.0):
    return (rng.uniform(-7, 7, 2) * scale, rng.uniform(-0.5, 0.5, (N, 2)) * scale, rng.uniform(-1.5, 1.5, 2) * scale,
            rng.uniform(0.2, 1.5))


def test_reused_instance_matches_fresh_solves_on_feasible_instances(polytope_variant):
    """One LocalQP over 80 feasible instances in a row (warm starts) gives the fresh answers."""
    v = polytope_variant
    qp = LocalQP(v.sub, v.P, N, v.tight)
    rng = np.random.default_rng(7)
    done = 0
    while done < 80:
        inst = random_instance(rng, 0.5)
        if v.terminal_violation(*inst) > -1e-3:
            continue
        reused = qp.solve(*inst)
        fresh = LocalQP(v.sub, v.P, N, v.tight).solve(*inst)
        assert reused.status is QPStatus.SOLVED and fresh.status is QPStatus.SOLVED
        np.testing.assert_allclose(reused.z, fresh.z, atol=1e-5)
        np.testing.assert_allclose(reused.v, fresh.v, atol=1e-5)
        done += 1


def test_reused_instance_verdicts_after_infeasible_solves(polytope_variant):
    v = polytope_variant
    qp = LocalQP(v.sub, v.P, N, v.tight)
    hopeless = (np.array([-6.0, 0.0]), np.zeros((N, 2)), np.array([-0.85, 0.0]), 0.87)  # z(1) cannot reach |x| <= 4
    rng = np.random.default_rng(0)
    wrong = []
    for trial in range(40):
        for inst in (random_instance(rng), hopeless):
            margin = v.terminal_violation(*inst)
            status = qp.solve(*inst).status
            if margin < -1e-3 and status is not QPStatus.SOLVED:
                wrong.append((trial, "feasible", status.value))
            if margin > 1e-3 and status is not QPStatus.INFEASIBLE:
                wrong.append((trial, "infeasible", status.value))
    assert wrong == []


def test_fresh_instance_detects_the_hopeless_instance(polytope_variant):
    v = polytope_variant
    hopeless = (np.array([-6.0, 0.0]), np.zeros((N, 2)), np.array([-0.85, 0.0]), 0.87)
    assert v.terminal_violation(*hopeless) == np.inf
    assert LocalQP(v.sub, v.P, N, v.tight).solve(*hopeless).status is QPStatus.INFEASIBLE


# ---------------------------------------------------------------- known answers

def test_unconstrained_single_agent_is_lqr():
    """Huge bounds, huge terminal box, no coupling, P = DARE solution: the MPC is exactly LQR."""
    P = sla.solve_discrete_are(A_II, B_II, Q_I, R_I)
    K = -np.linalg.solve(R_I + B_II.T @ P @ B_II, B_II.T @ P @ A_II)
    sub = paper_subsystem(input_set=LinearSet.box([-1e4], [1e4]))
    qp = LocalQP(sub, P, N, Tightening.none(2, 1, 0, N))
    for x in ([2.794, 2.5], [-2.8, 2.5], [0.3, -0.1], [10.0, -20.0]):
        x = np.array(x)
        sol = qp.solve(x, np.zeros((N, 2)), np.zeros(2), 1e4)
        assert sol.status == QPStatus.SOLVED
        scale = max(1.0, np.abs(x).max())
        np.testing.assert_allclose(sol.v[0], K @ x, atol=1e-6 * scale)
        z = x.copy()
        for t in range(N):  # the whole plan is the LQR closed loop
            np.testing.assert_allclose(sol.v[t], K @ z, atol=1e-5 * scale)
            z = (A_II + B_II @ K) @ z
        assert sol.cost == pytest.approx(x @ P @ x, rel=1e-6)  # the LQR value function


def test_infeasible_instance_maps_to_infeasible():
    sub = paper_subsystem()
    qp = LocalQP(sub, P_PAPER[0], N, Tightening.none(2, 1, 0, N))
    ok = qp.solve(np.array([2.794, 2.5]), np.zeros((N, 2)), np.zeros(2), 0.5)
    assert ok.status is QPStatus.SOLVED and ok.status.feasible
    bad = qp.solve(np.array([2.794, 2.5]), np.zeros((N, 2)), np.array([100.0, 100.0]), 1e-3)
    assert bad.status is QPStatus.INFEASIBLE
    assert not bad.status.feasible
    assert np.all(np.isnan(bad.z)) and np.all(np.isnan(bad.v)) and np.isnan(bad.cost)
    # and the instance is usable again afterwards
    again = qp.solve(np.array([2.794, 2.5]), np.zeros((N, 2)), np.zeros(2), 0.5)
    assert again.status is QPStatus.SOLVED
    assert again.cost == pytest.approx(ok.cost, rel=1e-7)


def test_later_solves_do_not_modify_earlier_solutions():
    qp = LocalQP(paper_subsystem(), P_PAPER[0], N, Tightening.none(2, 1, 0, N))
    first = qp.solve(np.array([2.794, 2.5]), np.zeros((N, 2)), np.zeros(2), 0.5)
    z, v = first.z.copy(), first.v.copy()
    qp.solve(np.array([-1.0, 1.0]), np.full((N, 2), 0.1), np.array([0.2, -0.2]), 0.3)
    np.testing.assert_array_equal(first.z, z)
    np.testing.assert_array_equal(first.v, v)


def test_iteration_limit_maps_to_max_iter():
    sub = paper_subsystem()
    qp = LocalQP(sub, P_PAPER[0], N, Tightening.none(2, 1, 0, N),
                 settings={"max_iter": 1, "polishing": False, "check_termination": 1})
    sol = qp.solve(np.array([2.794, 2.5]), np.zeros((N, 2)), np.zeros(2), 0.5)
    assert sol.status is QPStatus.MAX_ITER
    assert not sol.status.feasible


def test_status_values_are_the_wire_strings():
    assert QPStatus.SOLVED.value == "solved"
    assert QPStatus.INACCURATE.value == "solved_inaccurate"
    assert {s for s in QPStatus if s.feasible} == {QPStatus.SOLVED, QPStatus.INACCURATE}


def test_terminal_box_emptied_by_tightening_is_infeasible():
    sub = paper_subsystem()
    tight = Tightening(np.zeros((N, 1)), np.zeros((N + 1, 0)), np.array([0.3, 0.3]))
    qp = LocalQP(sub, P_PAPER[0], N, tight)
    first = qp.solve(np.array([2.794, 2.5]), np.zeros((N, 2)), np.zeros(2), 0.5)
    assert first.status is QPStatus.SOLVED
    # beta(k) below the terminal margin: the tightened terminal box is empty
    sol = qp.solve(np.array([1.0, -1.0]), np.zeros((N, 2)), np.zeros(2), 0.2)
    assert sol.status is QPStatus.INFEASIBLE

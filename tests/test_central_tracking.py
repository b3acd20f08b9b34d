"""The ``centralized`` method with setpoints (dmpc.runtime.central_loop; docs/methods.md,
"`centralized`"): the same targets and reference governor as the distributed methods, the central
QP in deviation coordinates around the target applied with the terminal set lambda X^f, and the
records' tracking. Checked against the hand-built matrices of tests/helpers/reference.py and an
independent cvxpy problem, and against ``tv-box`` on the same schedule."""
from __future__ import annotations

import json

import cvxpy as cp
import numpy as np
import pytest

import dmpc
from dmpc.core.central_qp import CentralQP
from dmpc.scenario import load_scenario
from dmpc.setup import prepare
from dmpc.tracking.targets import Request, TargetSpace
from tests.helpers.reference import P_PAPER, PAPER, Q_I, R_I, U_BAR, block_diag, chain_matrices

A, B = chain_matrices(4)
NAMES = ("1", "2", "3", "4")
SCHEDULE = [{"at": 0, "subsystem": "1", "x": [1.0, None]}, {"at": 40, "subsystem": "1", "x": [-0.5, None]}]
"""x_11 = 1.0 from k = 0, -0.5 from k = 40 (as tests/test_setpoints.py)."""
STEPS = 80
COST_TOLERANCE = 1e-6
"""centralized's closed-loop cost may exceed tv-box's by this much, relative (solver accuracy)."""


def stacked(result, field):
    return np.hstack([getattr(result, field)[name] for name in NAMES])


def closed_loop_cost_around(result, field):
    """sum_k ||x(k) - x_s(k)||_Q^2 + ||u(k) - u_s(k)||_R^2 around the recorded targets ``field``,
    from the hand-built weights."""
    x, u = result.stacked_x()[:-1], result.stacked_u()
    dx, du = x - stacked(result, field), u - stacked(result, f"{field}_u")
    Q, R = np.kron(np.eye(4), Q_I), np.kron(np.eye(4), R_I)
    return float(np.einsum("ki,ij,kj->", dx, Q, dx) + np.einsum("ki,ij,kj->", du, R, du))


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The schedule with centralized (its run folder kept) and with tv-box."""
    folder = tmp_path_factory.mktemp("central") / "run"
    scenario = dmpc.load_scenario(PAPER, steps=STEPS, setpoints=SCHEDULE)
    return {"centralized": dmpc.simulate(scenario, method="centralized", out=folder),
            "tv-box": dmpc.simulate(scenario, method="tv-box")}


def test_centralized_reaches_the_targets_with_every_qp_solved_and_the_bounds_held(runs):
    result = runs["centralized"]
    s = result.summary
    assert result.verdict == "ok", s["failures"]
    assert s["method"] == "centralized"
    assert s["feasible"] and s["qp_failed"] == 0 and s["fallbacks"] == 0
    assert np.abs(result.stacked_u()).max() <= U_BAR + 1e-7
    x11 = result.x["1"][:, 0]
    assert abs(x11[40] - 1.0) < 1e-4 and abs(x11[STEPS] + 0.5) < 1e-4
    x = result.stacked_x()
    assert np.abs(x[-1] - stacked(result, "target")[-1]).max() < 1e-6
    tracked = s["tracking"]["components"]
    assert [(c["subsystem"], c["component"], c["asked"]) for c in tracked] == [("1", "x1", -0.5)]
    assert abs(tracked[0]["error"]) < 1e-4
    assert not [w for w in s["warnings"] if w["kind"] in ("not-converged", "setpoint-unreachable")]
    # the cost decreases while the applied target stays (the decrease of Theorem 3 around it)
    targets = np.hstack([stacked(result, "target"), stacked(result, "target_u")])
    steady = np.all(targets[1:] == targets[:-1], axis=1)
    assert np.all(np.diff(result.J)[steady] <= 1e-6) and s["J_non_increasing"]


def test_centralized_costs_at_most_what_tv_box_costs_on_the_schedule(runs, record_property):
    central, box = (runs[m].summary["closed_loop_cost"] for m in ("centralized", "tv-box"))
    # both apply the same targets here (no governor step after k = 0), so the costs compare
    assert np.array_equal(stacked(runs["centralized"], "target"), stacked(runs["tv-box"], "target"))
    assert central == pytest.approx(closed_loop_cost_around(runs["centralized"], "target"), rel=1e-12)
    record_property("tv_box_over_centralized_with_setpoints", float(box / central))
    print(f"closed-loop cost with setpoints: centralized {central:.6f}, tv-box {box:.6f}, ratio {box / central:.6f}")
    assert central <= box * (1.0 + COST_TOLERANCE)


def test_the_records_carry_the_tracking_as_the_distributed_ones_do(runs):
    central, box = runs["centralized"], runs["tv-box"]
    for field in ("setpoint", "reference", "target", "setpoint_u", "reference_u", "target_u"):
        np.testing.assert_array_equal(stacked(central, field), stacked(box, field), err_msg=field)
    assert np.array_equal(central.governor, box.governor)
    lines = [json.loads(line) for line in (central.folder / "steps.jsonl").read_text().splitlines()]
    assert all(set(line) >= {"setpoint", "reference", "target", "governor"} for line in lines)
    assert lines[40]["setpoint"][0] == -0.5 and lines[39]["setpoint"][0] == 1.0
    # the plans recorded are the plant's coordinates: they start at x(k)
    for name in NAMES:
        plans = np.load(central.folder / "trajectory.npz")[f"plan_z_{name}"]
        np.testing.assert_allclose(plans[:, 0], central.x[name][:-1], atol=1e-12)


def test_a_large_jump_goes_through_the_governor_without_an_infeasible_qp():
    """x_11 = 1.0, then 18.0 from k = 40: the shifted central plan would be infeasible for the
    request itself; the governor moves the applied target in steps that keep it feasible."""
    jump = [{"at": 0, "subsystem": "1", "x": [1.0, None]}, {"at": 40, "subsystem": "1", "x": [18.0, None]}]
    scenario = dmpc.load_scenario(PAPER, steps=110, setpoints=jump)
    result = dmpc.simulate(scenario, method="centralized")
    s = result.summary
    assert result.verdict == "ok" and s["qp_failed"] == 0 and s["fallbacks"] == 0
    moved = np.flatnonzero(result.governor[1:] < 1.0) + 1
    assert moved.size >= 2 and moved.min() == 40
    applied = result.target["1"][:, 0]
    assert np.all(np.diff(applied[40:]) >= -1e-12) and applied[-1] == pytest.approx(18.0, abs=1e-9)
    assert abs(result.x["1"][-1, 0] - 18.0) < 1e-4
    assert np.abs(result.stacked_u()).max() <= U_BAR + 1e-7
    # tv-box's governor holds the target back longer: around the references (the request's target,
    # the same for both) the centralised loop costs less, around each one's applied targets more
    box = dmpc.simulate(scenario, method="tv-box")
    assert len(result.summary["tracking"]["governor_steps"]) < len(box.summary["tracking"]["governor_steps"])
    assert closed_loop_cost_around(result, "reference") < closed_loop_cost_around(box, "reference")


def test_without_setpoints_the_records_carry_no_tracking(tmp_path):
    """A run without setpoints works around the origin as before: no tracking in the records."""
    result = dmpc.simulate(PAPER, method="centralized", steps=3, out=tmp_path / "run")
    first = json.loads((tmp_path / "run" / "steps.jsonl").read_text().splitlines()[0])
    assert "target" not in first and "setpoint" not in np.load(tmp_path / "run" / "trajectory.npz").files
    assert result.verdict == "ok"


# --------------------------------------------------------------------------- the QP around a target
def test_the_qp_around_a_target_is_the_deviation_problem_with_lambda_xf():
    """CentralQP.solve_around against the same problem written here in cvxpy (Clarabel): deviation
    coordinates around a steady state of the hand-built system, U - u_s, and Omega dz(N) <= lambda."""
    prepared = prepare(load_scenario(PAPER))
    omega, N = prepared.design.terminal.omega, prepared.design.horizon
    space = TargetSpace(prepared.system)
    target = space.target(Request(np.array([1.5] + [np.nan] * 7), np.full(4, np.nan)))
    assert np.abs(A @ target.x + B @ target.u - target.x).max() < 1e-12 and 0.0 < target.scale < 1.0
    qp = CentralQP(prepared.system, prepared.design.gains.P_global(), N, terminal="omega", omega=omega)
    x0 = target.x + np.array([0.3, -0.2, 0.1, 0.0, -0.1, 0.2, 0.0, 0.1])
    sol = qp.solve_around(x0, target.x, target.u, target.scale)
    assert sol.status.feasible
    z, v = cp.Variable((N + 1, 8)), cp.Variable((N, 4))
    Q, R, P = np.kron(np.eye(4), Q_I), np.kron(np.eye(4), R_I), block_diag(P_PAPER)
    cost = sum(cp.quad_form(z[t], Q) + cp.quad_form(v[t], R) for t in range(N)) + cp.quad_form(z[N], P)
    cons = [z[0] == x0 - target.x, v <= U_BAR - target.u, v >= -U_BAR - target.u, omega @ z[N] <= target.scale]
    cons += [z[t + 1] == A @ z[t] + B @ v[t] for t in range(N)]
    problem = cp.Problem(cp.Minimize(cost), cons)
    problem.solve(solver=cp.CLARABEL, tol_gap_abs=1e-10, tol_gap_rel=1e-10, tol_feas=1e-10)
    assert problem.status == cp.OPTIMAL
    np.testing.assert_allclose(sol.v, v.value, atol=1e-5)
    assert sol.cost == pytest.approx(problem.value, rel=1e-6)
    # and back at the origin, the rows are the origin's again
    again = qp.solve(x0 - target.x)
    plain = CentralQP(prepared.system, prepared.design.gains.P_global(), N, terminal="omega", omega=omega)
    np.testing.assert_allclose(again.v, plain.solve(x0 - target.x).v, atol=1e-7)

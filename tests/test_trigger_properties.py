"""Every kept plan is a feasible point of the QP its agent would have solved (``trigger: event``).

Random small coupled systems (2 to 4 subsystems of 1 or 2 states and 1 input, input boxes, state
boxes on some, couplings along a chain, input couplings B_ij on some) are designed by dmpc's own
pipeline (``gains: lmi`` or ``lqr``, ``horizon: auto``, ``beta0: auto``; systems it refuses are
assumed away) and run in-process with the event trigger. For every plan kept at step k by agent i
the test rebuilds QP_i of step k itself, from the scenario's matrices and the recorded plans only
(nothing of agents/trigger.py or dmpc.core.trajectories), following docs/algorithm.md section 3:

- the neighbours' assumed trajectories: their plans of step k - 1 shifted, zhat_j(0) = x_j(k),
  zhat_j(t) = z_j(t+1 | k-1), vhat_j(t) = v_j(t+1 | k-1), vhat_j(N-1) = K_j z_j(N | k-1);
- c_i(t) = sum_j A_ij zhat_j(t) + B_ij vhat_j(t);

and checks z(0) = x_i(k), z(t+1) = A_ii z(t) + B_ii v(t) + c_i(t), v(t) in U_i, z(t) in X_i
(t = 1..N) and |z(N) - alpha_i(k)| <= beta(k), each to 1e-6. Every run ends without failure.

The cost is held to what docs/algorithm.md promises for kept plans ("The cost: Theorem 3"): at a
step k at which every agent keeps, the plans are the candidate of Theorem 3's proof and
J(k) <= J(k-1) - l(x(k-1), u(k-1)), checked to 1e-9 max(1, J(0)) (measured over 600 random
systems: at most 2e-10 above, with prediction errors e up to 7e-8 within trigger_threshold).
A step at which some agent solves is not held to a decrease: with neighbours revising their plans
at the same step the docs guarantee none ("What is and is not guaranteed"), whatever the trigger,
and random systems break it. Example: three in those 600 raise J by 36 to 81 without a fallback,
and one, whose Jacobi iteration at k = 0 never converges (a plan change of 0.73 at round 200 as at
round 2000), raises J from 285.5 to 441.7 at k = 3 with trigger_cost 1e-6: no agent ever keeps
there, and the run is the one of ``trigger: always`` to the last bit.
"""
from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from scipy.linalg import block_diag

from dmpc.core.errors import DesignError
from dmpc.records.run_folder import trajectory_arrays
from dmpc.runtime.inprocess import simulate
from dmpc.scenario import validate_scenario
from dmpc.setup import prepare

TOL = 1e-6
STEPS = 20


def matrix(draw, rows: int, cols: int, low: float, high: float) -> np.ndarray:
    values = draw(st.lists(st.floats(low, high, allow_nan=False, allow_infinity=False),
                           min_size=rows * cols, max_size=rows * cols))
    # model data to 6 decimals: entries such as 1e-300 beside 1 only test the LP solver's scaling
    return np.round(np.array(values, dtype=float), 6).reshape(rows, cols)


@st.composite
def coupled_systems(draw) -> dict:
    """A scenario mapping of a random chain of small subsystems with the event trigger."""
    M = draw(st.integers(2, 4))
    subsystems, sizes = [], []
    for i in range(M):
        n = draw(st.integers(1, 2))
        B = matrix(draw, n, 1, 0.2, 1.0) * np.array(draw(st.lists(st.sampled_from([-1.0, 1.0]), min_size=n,
                                                                     max_size=n)))[:, None]
        ubar = draw(st.floats(0.5, 2.0))
        sub = {"name": str(i + 1), "A": (np.eye(n) + matrix(draw, n, n, -0.3, 0.3)).tolist(), "B": B.tolist(),
               "Q": np.eye(n).tolist(), "R": [[0.1]], "input": {"lower": [-ubar], "upper": [ubar]},
               "x0": matrix(draw, n, 1, -3.0, 3.0)[:, 0].tolist()}
        if draw(st.booleans()):
            xbar = draw(st.floats(3.5, 6.0))  # x0 inside
            sub["state"] = {"lower": [-xbar] * n, "upper": [xbar] * n}
        subsystems.append(sub)
        sizes.append(n)
    couplings, strength = [], draw(st.sampled_from([0.02, 0.1]))
    for i in range(M - 1):
        for target, source in ((i, i + 1), (i + 1, i)):
            coupling = {"target": str(target + 1), "source": str(source + 1),
                        "A": matrix(draw, sizes[target], sizes[source], -strength, strength).tolist()}
            if draw(st.booleans()):
                coupling["B"] = matrix(draw, sizes[target], 1, -strength / 2, strength / 2).tolist()
            couplings.append(coupling)
    return {"name": "random", "subsystems": subsystems, "couplings": couplings, "steps": STEPS, "horizon": "auto",
            "design": {"gains": draw(st.sampled_from(["lmi", "lqr"]))},
            "options": {"trigger": "event", "trigger_cost": draw(st.sampled_from([1e-6, 1e-2, 1e3]))}}


def blocks(scenario: dict) -> tuple[dict[int, list[tuple[int, np.ndarray, np.ndarray]]], list[dict]]:
    """Per target i: its sources (j, A_ij, B_ij), from the scenario mapping (B_ij zeros if not given)."""
    subs = scenario["subsystems"]
    index = {s["name"]: i for i, s in enumerate(subs)}
    sources: dict[int, list] = {i: [] for i in range(len(subs))}
    for c in scenario["couplings"]:
        i, j = index[c["target"]], index[c["source"]]
        A = np.array(c["A"], float)
        B = np.array(c["B"], float) if "B" in c else np.zeros((A.shape[0], 1))
        sources[i].append((j, A, B))
    return sources, subs


def check_kept_plan(i: int, k: int, arrays: dict, scenario: dict, K: list[np.ndarray], N: int) -> None:
    """Agent i's kept plan of step k against QP_i of step k, built here."""
    sources, subs = blocks(scenario)
    sizes = [len(s["x0"]) for s in subs]
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    part = [slice(int(offsets[j]), int(offsets[j + 1])) for j in range(len(subs))]
    name = subs[i]["name"]
    z, v = arrays[f"plan_z_{name}"][k], arrays[f"plan_v_{name}"][k]
    x = arrays["x"][k]
    assert np.array_equal(z[0], x[part[i]]), (i, k)  # the measured state itself
    c = np.zeros((N, sizes[i]))
    for j, A_ij, B_ij in sources[i]:
        zj, vj = arrays[f"plan_z_{subs[j]['name']}"][k - 1], arrays[f"plan_v_{subs[j]['name']}"][k - 1]
        zhat = np.vstack([x[part[j]], zj[2:N + 1]])
        vhat = np.vstack([vj[1:N], K[j] @ zj[N]])
        c += zhat @ A_ij.T + vhat @ B_ij.T
    A, B = np.array(subs[i]["A"]), np.array(subs[i]["B"])
    residual = z[1:] - (z[:-1] @ A.T + v @ B.T + c)
    assert np.max(np.abs(residual)) <= TOL, (i, k, residual)
    U = subs[i]["input"]
    assert np.all(v >= np.array(U["lower"]) - TOL) and np.all(v <= np.array(U["upper"]) + TOL), (i, k)
    if "state" in subs[i]:
        X = subs[i]["state"]
        assert np.all(z[1:] >= np.array(X["lower"]) - TOL) and np.all(z[1:] <= np.array(X["upper"]) + TOL), (i, k)
    assert np.max(np.abs(z[N] - arrays["alpha"][k][part[i]])) <= arrays["beta"][k] + TOL, (i, k)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(scenario=coupled_systems())
def kept_plans_checked(scenario: dict, tally: list[tuple[float, int, int]]) -> None:
    """Run one system; check each of its kept plans and the cost at each step every agent kept; add
    (trigger_cost, plans checked, steps every agent kept) to ``tally``."""
    try:
        prepared = prepare(validate_scenario(scenario))
    except DesignError:
        assume(False)  # no design for it (unstable or non-decreasing coupled loop, infeasible start)
    records: list = []
    run = simulate(prepared, records.append)
    assert run.coordinator.failure == ""
    arrays = trajectory_arrays(prepared.system, records)
    K = [np.asarray(k, float) for k in prepared.design.gains.K]
    N = prepared.design.horizon
    kept, fallback = arrays["kept"], arrays["fallback"]
    # Theorem 3 with kept plans: where every agent keeps, J(k) is the candidate's cost
    J, x, u = np.asarray(arrays["J"], float), arrays["x"], arrays["u"]
    Q = block_diag(*[np.array(s["Q"], float) for s in scenario["subsystems"]])
    R = block_diag(*[np.array(s["R"], float) for s in scenario["subsystems"]])
    all_kept = [k for k in range(1, STEPS) if kept[k].all()]
    for k in all_kept:
        stage = float(x[k - 1] @ Q @ x[k - 1] + u[k - 1] @ R @ u[k - 1])
        assert J[k] <= J[k - 1] - stage + 1e-9 * max(1.0, float(J[0])), (k, J[k], J[k - 1], stage)
    assert kept.shape == (STEPS, len(scenario["subsystems"])) and not kept[0].any()  # nothing to keep at k = 0
    checked = 0
    for k, i in zip(*np.nonzero(kept)):
        assert not fallback[k, i]
        if fallback[k - 1].any():
            continue  # a plan of k - 1 was a fallback: what the agents assume of it is shifted further
        check_kept_plan(int(i), int(k), arrays, scenario, K, N)
        checked += 1
    cost = scenario["options"]["trigger_cost"]
    if cost >= 1e3 and arrays["rounds"][0] < 200:
        # the k = 0 plans agree (Jacobi converged): the shifted plans hold at k = 1 and are kept from then on
        assert checked > 0
    tally.append((cost, checked, len(all_kept)))


def test_every_kept_plan_is_feasible_for_its_qp():
    tally: list[tuple[float, int, int]] = []
    kept_plans_checked(tally=tally)
    # not vacuous: most examples keep plans (measured: every one with trigger_cost 1e3, and about
    # two in three of the others; where a neighbour re-solves every step its plan keeps changing
    # the feed-forward, and the agents solve for "changed"); and the cost is checked somewhere
    # (measured: three examples in four have steps at which every agent keeps)
    assert sum(checked > 0 for _, checked, _ in tally) > len(tally) / 2, tally
    assert any(all_kept > 0 for _, _, all_kept in tally), tally

"""``tv-box-coop`` through the coordinator on random input-coupled systems (the guarantees of
docs/algorithm.md, "Cooperative DMPC", "What is guaranteed").

Hypothesis draws systems of 2 or 3 subsystems (n_i = 2, m_i = 1) in which every subsystem's input
drives every other subsystem's states with B_ij as large as B_jj and larger (|B_ij| = factor
|B_jj|, factor in [0.5, 2.5]), plus small state couplings; input and state boxes; LMI gains.
A system whose design fails (no block-diagonal K and P meet (10), or the start check fails) is
discarded (``assume``), and so is one whose start is not centrally feasible (an LP over the
centralised rows, tests/helpers/cooperative.py). The rest is run with ``dmpc.simulate`` (agents,
coordinator and plant in this process), with 1 or 3 rounds per step, and must show, in nominal
conditions:

- no fallback, every QP ``solved``, at every step;
- every recorded iterate (the last of each step) a feasible point of the centralised problem:
  a trajectory of the model from x(k), inputs in U, states in X (t = 1..N), z(N) in the step's
  terminal box; every applied input in U and every state in X;
- J(k) the global cost of that iterate, and J(k+1) <= J(k) - l(x(k), u(k)) at every step;
- ||x|| converging to the target (the origin).

Everything is recomputed from the mapping's numbers (and the design's P_i for the cost), not
from the run's summary. The pure core (reach, QPs, combination) is tests/test_cooperative_core.py.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

import dmpc
from tests.helpers.closed_loop import (
    SOLVED,
    bound_excess,
    cost_decrease,
    cost_weights,
    dense_block_diag,
    designed,
    fallback_steps,
    plan_cost,
    read_steps,
    recorded_iterates,
    scenario_bounds,
    statuses,
)
from tests.helpers.cooperative import centrally_feasible

STEPS = 60
HORIZON = 10
U_BOUND = 1.0
X_BOUND = 4.0
FEASIBLE = 1e-7
"""Largest excess of an iterate over a row (absolute; the bounds are O(1))."""
DECREASE_TOLERANCE = 1e-8
CONVERGED = 0.1
"""||x(K)||_inf at most this times ||x(0)||_inf after STEPS steps."""


def random_mapping(seed: int, M: int, factor: float, iterations: int) -> dict:
    """A scenario mapping: M subsystems (n_i = 2, m_i = 1), each B_ij (i != j) a random direction
    of norm ``factor`` |B_jj|, A_ij entries up to 0.1; |u_i| <= U_BOUND, |x_i| <= X_BOUND, x0 in
    [-1, 1]^2."""
    rng = np.random.default_rng(seed)
    subsystems, own_B = [], []
    for i in range(M):
        A = rng.uniform(-0.3, 0.3, (2, 2)) + np.diag(rng.uniform(0.7, 1.08, 2))
        B = (rng.uniform(0.3, 1.0, 2) * rng.choice([-1.0, 1.0], 2))[:, None]
        L = rng.normal(size=(2, 2))
        subsystems.append(dict(name=f"s{i}", A=A.tolist(), B=B.tolist(), Q=(L @ L.T + 0.5 * np.eye(2)).tolist(),
                               R=[[float(rng.uniform(0.05, 1.0))]],
                               input=dict(lower=[-U_BOUND], upper=[U_BOUND]),
                               state=dict(lower=[-X_BOUND] * 2, upper=[X_BOUND] * 2),
                               x0=rng.uniform(-1.0, 1.0, 2).tolist()))
        own_B.append(B)
    couplings = []
    for i in range(M):
        for j in range(M):
            if i != j:
                B_ij = rng.normal(size=(2, 1))
                B_ij *= factor * np.linalg.norm(own_B[j]) / np.linalg.norm(B_ij)
                couplings.append(dict(target=f"s{i}", source=f"s{j}", A=rng.uniform(-0.1, 0.1, (2, 2)).tolist(),
                                      B=B_ij.tolist()))
    return dict(name=f"random-coop-{seed}", subsystems=subsystems, couplings=couplings, horizon=HORIZON,
                steps=STEPS, design=dict(gains="lmi"),
                options=dict(method="tv-box-coop", iterations=iterations))


def global_model(mapping: dict) -> tuple[np.ndarray, np.ndarray]:
    """Global A and B assembled by hand from the mapping's blocks (discrete time)."""
    names = [s["name"] for s in mapping["subsystems"]]
    M = len(names)
    A, B = np.zeros((2 * M, 2 * M)), np.zeros((2 * M, M))
    for i, s in enumerate(mapping["subsystems"]):
        A[2 * i:2 * i + 2, 2 * i:2 * i + 2] = s["A"]
        B[2 * i:2 * i + 2, i:i + 1] = s["B"]
    for c in mapping["couplings"]:
        i, j = names.index(c["target"]), names.index(c["source"])
        A[2 * i:2 * i + 2, 2 * j:2 * j + 2] += c["A"]
        B[2 * i:2 * i + 2, j:j + 1] += c["B"]
    return A, B


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(seed=st.integers(0, 2**32 - 1), M=st.sampled_from([2, 3]), factor=st.floats(0.5, 2.5),
       iterations=st.sampled_from([1, 3]))
@example(seed=16, M=2, factor=2.34, iterations=1)  # its k = 0 iterate is the centralised QP's plan (see the report)
def test_random_input_coupled_systems_keep_the_guarantees(tmp_path_factory, seed, M, factor, iterations):
    mapping = random_mapping(seed, M, factor, iterations)
    scenario = dmpc.load_scenario(mapping)
    prepared = designed(scenario)
    assume(prepared is not None)
    design = prepared.design
    x0 = np.concatenate([s["x0"] for s in mapping["subsystems"]])
    assume(centrally_feasible(prepared.system, x0, design.horizon, np.asarray(design.alpha0, float),
                              float(design.beta0)))

    out = tmp_path_factory.mktemp("coop-random") / "run"
    result = dmpc.simulate(scenario, out=out)
    steps = read_steps(out)
    summary = result.summary

    # no fallback, every QP solved
    assert summary["fallbacks"] == 0 and summary["qp_failed"] == 0, (summary["failures"], summary.get("notes"))
    assert fallback_steps(steps) == [] and statuses(steps) == {SOLVED}
    assert result.verdict == "ok", summary["failures"]

    # every applied input and every state within the mapping's boxes
    x_excess, u_excess = bound_excess(result, scenario_bounds(scenario))
    assert x_excess <= FEASIBLE and u_excess <= FEASIBLE

    # every recorded iterate: a model trajectory from x(k), feasible for the centralised rows, costing J(k)
    A, B = global_model(mapping)
    Q, R = cost_weights(scenario)
    P = dense_block_diag([np.asarray(p, float) for p in design.gains.P])
    z_all, v_all = recorded_iterates(out, result.names)
    x, alpha = result.stacked_x(), np.hstack([result.alpha[name] for name in result.names])
    for k in range(result.steps):
        z, v = z_all[k], v_all[k]
        assert np.array_equal(z[0], x[k])
        assert np.abs(z[1:] - z[:-1] @ A.T - v @ B.T).max() <= 1e-9 * (1 + np.abs(z).max())
        assert np.abs(v).max() <= U_BOUND + FEASIBLE, (k, np.abs(v).max())
        assert np.abs(z[1:]).max() <= X_BOUND + FEASIBLE, (k, np.abs(z[1:]).max())
        assert np.abs(z[-1] - alpha[k]).max() <= result.beta[k] + FEASIBLE, (k, np.abs(z[-1] - alpha[k]).max(),
                                                                            result.beta[k])
        V = plan_cost(z, v, Q, R, P)
        assert abs(result.J[k] - V) <= 1e-9 * max(1.0, V), (k, result.J[k], V)
        assert np.array_equal(result.stacked_u()[k], v[0])

    # the global cost decreases by at least the stage cost, at every step (no setpoints: the target stays)
    decrease = cost_decrease(result, Q, R)
    assert decrease.moved.size == 0 and decrease.steps.size == result.steps - 1
    J = np.asarray(result.J)
    worst = int(np.argmax(decrease.margin))
    assert np.all(decrease.margin <= DECREASE_TOLERANCE * np.maximum(1.0, J[decrease.steps])), \
        (worst, decrease.margin[worst])

    # convergence to the origin
    norms = np.abs(x).max(axis=1)
    assert norms[-1] <= CONVERGED * norms[0], (norms[0], norms[-1])


PANIC = dict(seed=257, M=2, factor=1.8981968723745577, iterations=3)
"""A system drawn above whose LMI design makes Clarabel 0.10.0 panic ("Eigval error: Eigen(1)",
psdtrianglecone.rs) inside dmpc/offline/lmi_conic.py's solve."""


def test_a_solver_panic_in_the_lmi_design_is_a_design_error():
    """A design that fails says so (DesignError, one line from the command), whatever the solver
    does: a Rust panic reaches Python as pyo3's PanicException, a BaseException that neither
    ``except Exception`` nor the CLI's error handling catches (``dmpc design`` prints a traceback)."""
    scenario = dmpc.load_scenario(random_mapping(**PANIC))
    with pytest.raises(dmpc.DesignError):
        dmpc.design(scenario)

"""The control methods (dmpc.methods) on the paper's example: feasibility, optimality against
the centralised reference, the ellipsoid geometry, the fixed box, and tv-box unchanged.

The centralised QP is checked against the same problem written here in cvxpy and solved by
Clarabel; the ellipsoid's containment in X^f is checked on the vertices of the product of the
polytopes actually imposed.
"""
from __future__ import annotations

import cvxpy as cp
import numpy as np
import pytest

from dmpc.coordinator.barrier import Coordinator
from dmpc.core.central_qp import CentralQP
from dmpc.evaluation.compare import compare
from dmpc.methods import (
    CAPABILITIES,
    METHOD_NAMES,
    METHODS,
    CapabilityError,
    lacks,
    method_spec,
    methods_with,
    require,
    terminal_policy,
)
from dmpc.methods.inscribed import inscribed_rows, polytope_vertices, unit_ball_polytope
from dmpc.methods.levels import containment, dual_norms, fit_levels, level_increments, static_level
from dmpc.methods.policy import BoxPolicy, EllipsoidPolicy
from dmpc.methods.terminal_rows import InscribedTerminal
from dmpc.plant.dynamics import Plant
from dmpc.prepared import design_digest
from dmpc.prepared.bundle import load_bundle, write_bundle
from dmpc.records.session import RunRecorder
from dmpc.runtime.direct import DirectLoop
from dmpc.runtime.inprocess import record_run, simulate
from dmpc.scenario import load_scenario
from dmpc.setup import prepare
from tests.helpers.reference import P_PAPER, PAPER, Q_I, R_I, U_BAR, block_diag, chain_matrices, chain_x0

DISTRIBUTED = [m for m in METHOD_NAMES if method_spec(m).distributed]


@pytest.fixture(scope="module")
def paper():
    return prepare(load_scenario(PAPER))


@pytest.fixture(scope="module")
def paper_n3():
    return prepare(load_scenario(PAPER, {"horizon": 3, "design.check_start": False}))


@pytest.fixture(scope="module")
def comparison(tmp_path_factory):
    """Every method on the paper's example, as ``dmpc compare`` runs them."""
    out = tmp_path_factory.mktemp("compare")
    return out, compare(load_scenario(PAPER), out, list(METHOD_NAMES), show_progress=False)


# --------------------------------------------------------------------------- the paper's example
def test_every_method_is_feasible_on_the_paper(comparison):
    _, data = comparison
    assert list(data["methods"]) == list(METHOD_NAMES)
    for method, entry in data["methods"].items():
        assert entry["feasible"] and entry["fallbacks"] == 0, method
        assert entry["steps_to_1e-3"] is not None, method


def test_centralised_cost_is_at_most_every_distributed_cost(comparison, record_property):
    _, data = comparison
    central = data["methods"]["centralized"]["closed_loop_cost"]
    for method in DISTRIBUTED:
        assert central <= data["methods"][method]["closed_loop_cost"] + 1e-9, method
    ratio = data["methods"]["tv-box"]["closed_loop_cost"] / central
    record_property("tv_box_over_centralized", float(ratio))
    print(f"closed-loop cost tv-box / centralized = {ratio:.5f}")
    assert 1.0 <= ratio < 1.01


def test_centralised_cost_is_at_most_distributed_with_active_terminal_sets(paper_n3):
    """At N = 3 the terminal sets are active (at N = 10 they are not, and the methods coincide)."""
    costs = {}
    for method in ("tv-box", "fixed-box", "ellipsoid", "centralized"):
        recs = _records(paper_n3, method)
        costs[method] = sum(r.x @ paper_n3.system.Q @ r.x + r.u @ paper_n3.system.R @ r.u for r in recs)
    assert len({round(c, 6) for c in costs.values()}) > 1
    assert all(costs["centralized"] <= c + 1e-9 for c in costs.values())


def _records(prepared, method, steps=30, x0=None):
    if method_spec(method).distributed:
        loop = DirectLoop(prepared.system, prepared.design, prepared.protocol, method)
    else:
        from dmpc.runtime.central_loop import CentralLoop

        loop = CentralLoop(prepared.system, prepared.design)
    recs = []
    loop.run(steps, recs.append, x0=x0)
    return recs


# --------------------------------------------------------------------------- centralised vs cvxpy
def _cvxpy_first_input(x0, N, omega):
    """Problem (9) with Omega z(N) <= 1, written from the paper's matrices; Clarabel."""
    A, B = chain_matrices(4)
    n, m = B.shape
    Q, R, P = np.kron(np.eye(4), Q_I), np.kron(np.eye(4), R_I), block_diag(P_PAPER)
    z, v = cp.Variable((N + 1, n)), cp.Variable((N, m))
    cost = sum(cp.quad_form(z[t], Q) + cp.quad_form(v[t], R) for t in range(N)) + cp.quad_form(z[N], P)
    cons = [z[0] == x0, cp.abs(v) <= U_BAR, omega @ z[N] <= 1]
    cons += [z[t + 1] == A @ z[t] + B @ v[t] for t in range(N)]
    prob = cp.Problem(cp.Minimize(cost), cons)
    prob.solve(solver=cp.CLARABEL, tol_gap_abs=1e-10, tol_gap_rel=1e-10, tol_feas=1e-10)
    assert prob.status == cp.OPTIMAL
    return v.value[0], prob.value


@pytest.mark.parametrize("N", [10, 3])
def test_centralised_first_input_matches_cvxpy_clarabel(paper, N):
    omega = paper.design.terminal.omega
    qp = CentralQP(paper.system, paper.design.gains.P_global(), N, terminal="omega", omega=omega)
    rng = np.random.default_rng(1)
    states = [chain_x0(4)] + [rng.uniform(-2.0, 2.0, 8) for _ in range(3)]
    for x0 in states:
        sol = qp.solve(x0)
        assert sol.status.feasible
        u_ref, cost_ref = _cvxpy_first_input(x0, N, omega)
        np.testing.assert_allclose(sol.v[0], u_ref, atol=1e-5)
        assert abs(sol.cost - cost_ref) <= 1e-5 * max(1.0, cost_ref)


def test_centralised_run_applies_the_qp_first_input(comparison, paper):
    out, _ = comparison
    u = np.load(out / "centralized" / "trajectory.npz")["u"]
    u_ref, _ = _cvxpy_first_input(chain_x0(4), paper.design.horizon, paper.design.terminal.omega)
    np.testing.assert_allclose(u[0], u_ref, atol=1e-5)


# --------------------------------------------------------------------------- ellipsoid geometry
@pytest.mark.parametrize("n", [1, 2, 3, 4, 7])
def test_unit_ball_polytope_is_inside_the_ball_and_touches_it(n):
    G, h = unit_ball_polytope(n)
    V = polytope_vertices(G, h)
    norms = np.linalg.norm(V, axis=1)
    assert norms.max() <= 1 + 1e-9
    assert norms.max() >= 1 - 1e-9  # as large as it can be scaled


def test_polygon_covers_most_of_the_disc():
    G, h = unit_ball_polytope(2, 16)
    np.testing.assert_allclose(h, np.cos(np.pi / 16))
    V = polytope_vertices(G, h)
    np.testing.assert_allclose(np.linalg.norm(V, axis=1), 1.0, atol=1e-12)
    assert len(V) == 16


@pytest.mark.parametrize("i", range(4))
def test_inscribed_polygon_is_inside_each_paper_ellipse(i):
    P = P_PAPER[i]
    T, h = inscribed_rows(P)
    for r in (0.3, 1.0, 11.3):
        V = polytope_vertices(T, np.sqrt(r) * h)
        levels = np.einsum("vj,jk,vk->v", V, P, V)
        assert levels.max() <= r * (1 + 1e-9)
        assert levels.max() >= r * (1 - 1e-9)


def test_inscribed_polytope_inside_a_three_dimensional_ellipsoid():
    rng = np.random.default_rng(3)
    M = rng.normal(size=(3, 3))
    P = M @ M.T + 0.5 * np.eye(3)
    T, h = inscribed_rows(P)
    V = polytope_vertices(T, 2.0 * h)
    assert np.einsum("vj,jk,vk->v", V, P, V).max() <= 4.0 * (1 + 1e-9)


def test_static_level_puts_the_product_of_polytopes_inside_xf(paper):
    system, omega = paper.system, paper.design.terminal.omega
    policy = terminal_policy("ellipsoid", system, paper.design)
    r = policy.level0
    corners = []
    for i in range(system.M):
        term = policy.agent_terminal(i)
        corners.append(polytope_vertices(term.T, term.bounds(np.zeros(2), r)[1]))
    grids = np.meshgrid(*[np.arange(len(c)) for c in corners], indexing="ij")
    X = np.hstack([corners[i][grids[i].ravel()] for i in range(system.M)])
    worst = float(np.max(X @ omega.T))
    assert X.shape == (16 ** 4, 8)
    assert worst <= 1 + 1e-9


def test_static_level_puts_the_product_of_ellipsoids_inside_xf_and_is_tight(paper):
    system, omega, P = paper.system, paper.design.terminal.omega, paper.design.gains.P
    r = static_level(omega, system, P)
    theta = np.linspace(0, 2 * np.pi, 20001)
    circle = np.vstack([np.cos(theta), np.sin(theta)])
    support = np.zeros(omega.shape[0])
    for i in range(system.M):
        L = np.linalg.cholesky(P[i])
        boundary = np.sqrt(r) * np.linalg.solve(L.T, circle)  # z' P z = r
        assert np.allclose(np.einsum("jv,jk,kv->v", boundary, P[i], boundary), r)
        support += np.max(omega[:, system.xs(i)] @ boundary, axis=1)
    assert support.max() <= 1 + 1e-9
    assert support.max() >= 1 - 1e-6  # the largest such common level


def test_adaptive_increments_split_the_lyapunov_inequality(paper):
    system, g = paper.system, paper.design.gains
    Gammas = level_increments(system, g.K, g.P)
    AK = system.A + system.B @ g.K_global()
    lhs10 = AK.T @ g.P_global() @ AK - g.P_global() + system.Q + g.K_global().T @ system.R @ g.K_global()
    np.testing.assert_allclose(sum(Gammas), lhs10, atol=1e-12)
    assert np.linalg.eigvalsh(sum(Gammas)).max() <= 1e-9
    for i, G in enumerate(Gammas):  # only the blocks of N_i
        outside = [j for j in range(system.M) if j not in system.neighbours[i]]
        for j in outside:
            assert np.all(G[system.xs(j)] == 0) and np.all(G[:, system.xs(j)] == 0)


def test_fit_levels_keeps_the_product_inside_xf(paper):
    system, omega, P = paper.system, paper.design.terminal.omega, paper.design.gains.P
    norms = dual_norms(omega, system, P)
    r0 = static_level(omega, system, P)
    grown = np.array([3.0 * r0, 0.1 * r0, r0, r0])
    fitted, scaled = fit_levels(grown, norms)
    assert scaled and containment(fitted, norms) <= 1 + 1e-12
    same, scaled = fit_levels(np.full(4, r0), norms)
    assert not scaled and np.array_equal(same, np.full(4, r0))


def test_inscribed_terminal_tightens_each_row_by_its_support_over_the_error_box():
    T, h = inscribed_rows(P_PAPER[0])
    margin = np.array([0.01, 0.02])
    lo, hi = InscribedTerminal(T, h, margin).bounds(np.zeros(2), 4.0)
    np.testing.assert_allclose(hi, 2.0 * h - np.abs(T) @ margin)
    assert np.all(np.isneginf(lo))


# --------------------------------------------------------------------------- records of the methods
def test_fixed_box_keeps_alpha_zero_and_beta_constant(comparison):
    out, _ = comparison
    t = np.load(out / "fixed-box" / "trajectory.npz")
    assert np.all(t["alpha"] == 0.0)
    assert np.all(t["beta"] == 0.5)


def test_fixed_box_holds_its_box_where_tv_box_moves(paper_n3):
    recs = _records(paper_n3, "fixed-box", steps=8)
    assert all(np.all(r.alpha_next == 0) and r.beta_next == 0.5 for r in recs)
    moving = _records(paper_n3, "tv-box", steps=8)
    assert any(r.beta_next != 0.5 for r in moving)


def test_ellipsoid_runs_record_their_levels(comparison, paper):
    out, _ = comparison
    r0 = static_level(paper.design.terminal.omega, paper.system, paper.design.gains.P)
    static = np.load(out / "ellipsoid" / "trajectory.npz")
    assert static["r"].shape == (31, 4) and np.all(static["r"] == r0)
    assert np.all(static["alpha"] == 0) and np.all(np.isnan(static["beta"]))
    adaptive = np.load(out / "ellipsoid-adaptive" / "trajectory.npz")
    assert adaptive["r"].shape == (31, 4) and not np.all(adaptive["r"] == r0)
    norms = dual_norms(paper.design.terminal.omega, paper.system, paper.design.gains.P)
    assert max(containment(r, norms) for r in adaptive["r"]) <= 1 + 1e-9
    assert "r" not in np.load(out / "tv-box" / "trajectory.npz").files


def test_adaptive_levels_follow_the_increments(paper_n3):
    policy = terminal_policy("ellipsoid-adaptive", paper_n3.system, paper_n3.design)
    recs = _records(paper_n3, "ellipsoid-adaptive", steps=6)
    for rec in recs:
        eta = np.concatenate([z[-1] for z in rec.plans_z])
        raw = rec.r + np.array([eta @ G @ eta for G in policy._gamma])
        expected, _ = fit_levels(raw, policy._norms)
        np.testing.assert_allclose(rec.r_next, expected, rtol=1e-12)
        for i, z in enumerate(rec.plans_z):  # the plans end inside their ellipses
            assert z[-1] @ paper_n3.design.gains.P[i] @ z[-1] <= rec.r[i] * (1 + 1e-6)


def test_summary_names_the_method(comparison):
    import json

    out, data = comparison
    for method in data["methods"]:
        assert json.loads((out / method / "summary.json").read_text())["method"] == method


def test_tv_box_opt_chooses_beta0_as_sigma_of_alpha0(paper_n3):
    recs = _records(paper_n3, "tv-box-opt", steps=2)
    alpha0, beta0 = recs[0].alpha, recs[0].beta
    assert beta0 == pytest.approx(paper_n3.design.terminal.sigma(alpha0))
    assert beta0 >= paper_n3.design.beta0 - 1e-6
    assert "chosen by the centralised QP" in recs[0].note


# --------------------------------------------------------------------------- tv-box unchanged
def test_tv_box_default_policy_is_bit_identical_to_the_explicit_one(paper, tmp_path):
    """The coordinator without a policy, compare's tv-box run and simulate give the same bits."""
    ref = []
    simulate(paper, ref.append)
    direct = _records(paper, "tv-box")
    for a, b in zip(ref, direct):
        assert np.array_equal(a.u, b.u) and np.array_equal(a.x_next, b.x_next)
        assert np.array_equal(a.alpha_next, b.alpha_next) and a.beta_next == b.beta_next
    with RunRecorder(tmp_path / "run", paper, show_progress=False) as recorder:
        record_run(paper, recorder)
    x = np.load(tmp_path / "run" / "trajectory.npz")["x"]
    assert np.array_equal(x, np.vstack([r.x for r in ref] + [ref[-1].x_next]))


def test_default_coordinator_uses_the_paper_box(paper):
    coord = Coordinator(paper.system, paper.design, Plant(paper.system), paper.protocol, "r")
    assert coord.policy.name == "tv-box"
    np.testing.assert_array_equal(coord.alpha, np.zeros(8))
    assert coord.beta == 0.5


def test_tv_box_digest_leaves_the_method_out_and_other_methods_differ(paper, tmp_path):
    assert paper.digest == design_digest(paper.design) == design_digest(paper.design, "tv-box")
    assert len({design_digest(paper.design, m) for m in METHOD_NAMES}) == len(METHOD_NAMES)
    write_bundle(paper, tmp_path / "run.json")  # Omega through a file keeps the digest
    assert load_bundle(tmp_path / "run.json").digest == paper.digest


# --------------------------------------------------------------------------- runtimes agree
def test_direct_loop_equals_the_bus_run(paper_n3):
    for method in ("ellipsoid-adaptive", "tv-box-opt"):
        prepared = prepare(load_scenario(PAPER, {"horizon": 3, "design.check_start": False, "options.method": method}))
        bus = []
        simulate(prepared, bus.append)
        direct = _records(prepared, method)
        assert len(bus) == len(direct) == 30
        for a, b in zip(bus, direct):
            assert np.array_equal(a.u, b.u) and np.array_equal(a.x_next, b.x_next), method


def test_run_bundle_carries_the_method(tmp_path):
    prepared = prepare(load_scenario(PAPER, {"options.method": "ellipsoid-adaptive"}))
    write_bundle(prepared, tmp_path / "run.json")
    loaded = load_bundle(tmp_path / "run.json")
    assert loaded.method == "ellipsoid-adaptive" and loaded.digest == prepared.digest


def test_centralized_has_no_terminal_policy(paper):
    with pytest.raises(CapabilityError, match="method 'centralized' runs no agents .*: it has no terminal policy"):
        terminal_policy("centralized", paper.system, paper.design)
    with pytest.raises(ValueError, match="unknown method"):
        terminal_policy("box", paper.system, paper.design)


# --------------------------------------------------------------------------- what each method can do
CAN = {  # distributed, tracks setpoints, supports the event trigger, cooperative
    "tv-box": (True, True, True, False),
    "tv-box-opt": (True, True, True, False),
    "tv-box-coop": (True, True, False, True),
    "fixed-box": (True, False, False, False),
    "ellipsoid": (True, False, False, False),
    "ellipsoid-adaptive": (True, False, False, False),
    "centralized": (False, True, False, False),
}


def test_each_spec_records_what_its_method_can_do():
    assert tuple(CAN) == METHOD_NAMES == tuple(METHODS)
    for name, flags in CAN.items():
        spec = method_spec(name)
        assert tuple(getattr(spec, c) for c in CAPABILITIES) == flags, name
        for capability, has in zip(CAPABILITIES, flags):
            assert (lacks(name, capability) is None) == has == (name in methods_with(capability)), (name, capability)
    assert methods_with("tracks_setpoints") == ("tv-box", "tv-box-opt", "tv-box-coop", "centralized")
    assert methods_with("supports_trigger") == ("tv-box", "tv-box-opt")


def test_a_capability_error_names_the_method_and_the_capability():
    error = lacks("ellipsoid", "tracks_setpoints")
    assert isinstance(error, CapabilityError) and isinstance(error, ValueError)
    assert (error.method, error.capability) == ("ellipsoid", "tracks_setpoints")
    assert str(error) == ("method 'ellipsoid' does not track setpoints (methods that do: tv-box, tv-box-opt, "
                          "tv-box-coop, centralized)")
    assert str(lacks("tv-box-coop", "supports_trigger", "a kept plan is not an iterate")) == (
        "method 'tv-box-coop' does not work with the event trigger (methods that do: tv-box, tv-box-opt): "
        "a kept plan is not an iterate")
    assert str(lacks("tv-box", "cooperative")) == "method 'tv-box' is not cooperative (methods that do: tv-box-coop)"
    assert "method 'centralized' runs no agents" in str(lacks(method_spec("centralized"), "distributed"))
    assert require("centralized", "tracks_setpoints") is method_spec("centralized")
    with pytest.raises(CapabilityError, match="method 'fixed-box' does not track setpoints"):
        require("fixed-box", "tracks_setpoints")
    with pytest.raises(ValueError, match="unknown method 'boxes'"):
        lacks("boxes", "distributed")
    with pytest.raises(ValueError, match="unknown capability 'fast'"):
        lacks("tv-box", "fast")  # type: ignore[arg-type]  # a capability that does not exist


@pytest.mark.parametrize("name, kind, moving, optimised", [
    ("tv-box", BoxPolicy, True, False), ("tv-box-opt", BoxPolicy, True, True), ("tv-box-coop", BoxPolicy, True, False),
    ("fixed-box", BoxPolicy, False, False), ("ellipsoid", EllipsoidPolicy, False, False),
    ("ellipsoid-adaptive", EllipsoidPolicy, True, False),
])
def test_the_terminal_policy_is_built_from_the_spec(paper, name, kind, moving, optimised):
    policy = terminal_policy(name, paper.system, paper.design)
    assert type(policy) is kind and policy.name == name
    if kind is BoxPolicy:
        assert policy.time_varying == moving and (policy._optimizer is not None) == optimised
    else:
        assert policy.adaptive == moving


def test_the_core_holds_no_lists_of_method_names():
    import dmpc.core.steps as steps

    lists = [name for name, value in vars(steps).items()
             if isinstance(value, tuple) and value and set(value) <= set(METHOD_NAMES) and name != "METHOD_NAMES"]
    assert lists == []


def test_ellipsoid_policy_polygon_sides_are_configurable(paper):
    policy = EllipsoidPolicy(paper.system, paper.design, "ellipsoid", adaptive=False, facets=8)
    assert policy.agent_terminal(0).T.shape == (8, 2)


def test_method_names_defaults_and_the_scenario_agree():
    """One list of methods, one default, and run.json keeps the scenario's names of the Jacobi rounds."""
    from typing import get_args

    from dmpc.core.steps import COUPLINGS, MODES, ProtocolOptions
    from dmpc.methods import DEFAULT_METHOD, METHOD_NAMES, METHODS, Method
    from dmpc.scenario.schema import OptionsSpec

    assert METHOD_NAMES == get_args(Method) == tuple(METHODS) and DEFAULT_METHOD == "tv-box"
    fields = OptionsSpec.model_fields
    assert get_args(fields["method"].annotation) == METHOD_NAMES and fields["method"].default == DEFAULT_METHOD
    assert get_args(fields["mode"].annotation) == MODES and get_args(fields["coupling"].annotation) == COUPLINGS
    options = ProtocolOptions(steps=5, rounds=3, tolerance=1e-6, initial_rounds=7, initial_tolerance=1e-8)
    assert options.to_json() == {"steps": 5, "iterations": 3, "tolerance": 1e-6, "initial_iterations": 7,
                                 "initial_tolerance": 1e-8}
    assert ProtocolOptions.from_json(options.to_json()) == options
    equal = ProtocolOptions(steps=5, cooperative_step="equal")
    assert equal.to_json()["cooperative_step"] == "equal" and ProtocolOptions.from_json(equal.to_json()) == equal

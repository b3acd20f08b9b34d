"""The input-coupling check (dmpc.offline.input_coupling, docs/algorithm.md, "Input coupling"):
hand-checkable cases, the closed loop against the method itself, and what dmpc design and
dmpc validate say on the shipped scenarios."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

import dmpc
from dmpc.core.system import CoupledSystem, Coupling, LinearSet, Subsystem
from dmpc.core.unconstrained import UnconstrainedBound
from dmpc.offline.input_coupling import (
    agent_response,
    closed_loop,
    closed_loop_radius,
    input_coupling,
    input_drives,
    jacobi_radius,
    perron_bound,
    response_map,
)
from dmpc.scenario import build_system, load_scenario, validate_scenario
from dmpc.setup import prepare
from dmpc.setup.coupling_check import design_coupling, local_lqr, non_cooperative, scenario_coupling
from tests.helpers.cli import call

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"
FOURTANK = SCENARIOS / "fourtank.yaml"


def scalar_pair(a: float, b: float, beta: float, q: float = 1.0, r: float = 1.0, coupling_a: float = 0.0):
    """Two scalar subsystems x_i+ = a x_i + b u_i + coupling_a x_j + beta u_j."""
    subs = tuple(Subsystem(name, np.array([[a]]), np.array([[b]]), np.array([[q]]), np.array([[r]]), np.zeros(1),
                           LinearSet.box([-1.0], [1.0])) for name in ("1", "2"))
    couplings = tuple(Coupling(i, 1 - i, np.array([[coupling_a]]), np.array([[beta]])) for i in (0, 1))
    return CoupledSystem(subs, couplings)


def swapped_fourtank() -> dict:
    """scenarios/fourtank.yaml with the pumps swapped: subsystem a (tanks 1, 3) takes pump b, which
    feeds its tanks most, and b (tanks 2, 4) takes pump a."""
    data = yaml.safe_load(FOURTANK.read_text())
    a, b = data["subsystems"]
    to_a, to_b = data["couplings"]
    a["B"], to_a["B"] = to_a["B"], a["B"]
    b["B"], to_b["B"] = to_b["B"], b["B"]
    a["input"], b["input"] = b["input"], a["input"]
    a["inputs"], b["inputs"] = b["inputs"], a["inputs"]
    return data


# --- hand-checkable cases --------------------------------------------------------------------------

def test_two_scalar_agents_with_n_1():
    """N = 1: agent i minimises p z(1)^2 + r v^2 with z(1) = a x + b v + beta vhat_j, so
    v = -p b (a x + beta vhat_j) / (p b^2 + r): a Jacobi round is [[0, t], [t, 0]] with
    t = -p b beta / (p b^2 + r), spectral radius |t|."""
    a, b, beta, p, r = 0.9, 1.0, 2.0, 1.0, 0.5
    system = scalar_pair(a, b, beta, r=r)
    P = [np.array([[p]])] * 2
    radius, kind, dim = jacobi_radius(system, P, 1)
    assert kind == "exact" and dim == 2
    assert radius == pytest.approx(p * b * beta / (p * b * b + r), rel=1e-12)  # 4/3: diverges
    ic = input_coupling(system, [np.zeros((1, 1))] * 2, P, 1)
    assert ic.diverges and ic.likely_to_fail
    drive = input_drives(system)
    assert [(d.source, d.target) for d in drive] == [(1, 0), (0, 1)]
    assert drive[0].ratio == pytest.approx(beta / b)  # one step: |B_ji| / |B_ii|
    assert drive[0].steady_ratio == pytest.approx(beta / b)  # (I - A)^-1 B with A = a I: the same ratio
    weak = input_coupling(scalar_pair(a, b, 0.2, r=r), [np.zeros((1, 1))] * 2, P, 1)
    assert weak.radius == pytest.approx(p * b * 0.2 / (p * b * b + r)) and not weak.diverges


def test_the_weights_make_the_ratio_unit_free():
    """States of subsystem 2 in mm instead of m: B_21 and Q_2 change, the ratio does not."""
    base = scalar_pair(0.9, 1.0, 0.5)
    s1, s2 = base.subsystems
    scaled = CoupledSystem((s1, Subsystem("2", s2.A, 1e3 * s2.B, 1e-6 * s2.Q, s2.R, s2.x0, s2.input_set)),
                           (Coupling(0, 1, np.zeros((1, 1)), np.array([[0.5]])),
                            Coupling(1, 0, np.zeros((1, 1)), np.array([[0.5e3]]))))
    for d0, d1 in zip(input_drives(base), input_drives(scaled)):
        assert d1.ratio == pytest.approx(d0.ratio, rel=1e-12)
        assert d1.steady_ratio == pytest.approx(d0.steady_ratio, rel=1e-9)


def test_the_closed_loop_with_n_1_by_hand():
    """N = 1, one round: s = (x1, x2, z1(1), v1(0), z2(1), v2(0)) of the step before. Agent i's
    feed-forward is beta vhat_j(0) = beta K_j z_j(1 | k-1) (the shifted plan's K tail) plus
    A_ij x_j; v_i = -p b (a x_i + c_i) / (p b^2 + r), z_i = a x_i + b v_i + c_i, and the plant
    applies x_i+ = a x_i + b v_i + coupling_a x_j + beta v_j."""
    a, b, beta, p, r, kappa, ca = 0.8, 1.0, 0.7, 2.0, 0.3, -0.4, 0.1
    system = scalar_pair(a, b, beta, r=r, coupling_a=ca)
    L = closed_loop(system, [np.array([[kappa]])] * 2, [np.array([[p]])] * 2, 1)
    g = p * b / (p * b * b + r)
    # rows of v_i and z_i over s = (x1, x2, z1, v1, z2, v2)
    v1 = np.array([-g * a, -g * ca, 0, 0, -g * beta * kappa, 0])
    v2 = np.array([-g * ca, -g * a, -g * beta * kappa, 0, 0, 0])
    z1 = np.array([a, ca, 0, 0, beta * kappa, 0]) + b * v1
    z2 = np.array([ca, a, beta * kappa, 0, 0, 0]) + b * v2
    x1 = np.array([a, ca, 0, 0, 0, 0]) + b * v1 + beta * v2
    x2 = np.array([ca, a, 0, 0, 0, 0]) + b * v2 + beta * v1
    np.testing.assert_allclose(L, np.vstack([x1, x2, z1, v1, z2, v2]), atol=1e-15)


def test_the_agent_response_is_the_unconstrained_optimum():
    """The plan of agent_response costs the unconstrained optimum of dmpc.core.unconstrained, and
    moving any input raises the cost."""
    rng = np.random.default_rng(7)
    n, m, N = 3, 2, 6
    A, B = rng.normal(size=(n, n)) * 0.5, rng.normal(size=(n, m))
    Q, R = np.diag([1.0, 2.0, 0.5]), np.diag([0.1, 0.3])
    P = 3.0 * np.eye(n)
    r = agent_response(A, B, Q, R, P, N)
    bound = UnconstrainedBound(A, B, Q, R, P, N)
    x, c = rng.normal(size=n), rng.normal(size=(N, n))

    def cost(v: np.ndarray) -> float:
        z, total = x, 0.0
        for t in range(N):
            total += z @ Q @ z + v[t] @ R @ v[t]
            z = A @ z + B @ v[t] + c[t]
        return total + z @ P @ z

    v = (r.Vx @ x + r.Vc @ c.ravel()).reshape(N, m)
    z = (r.Zx @ x + r.Zc @ c.ravel()).reshape(N, n)
    assert cost(v) == pytest.approx(bound.cost(x, c), rel=1e-9)
    assert z[0] == pytest.approx(A @ x + B @ v[0] + c[0])
    for _ in range(5):
        assert cost(v + 1e-3 * rng.normal(size=v.shape)) > cost(v)
    assert response_map(A, B, Q, R, P, N).shape == ((N - 1) * n + N * m, N * n)


def test_the_perron_bound_is_an_upper_bound_and_tight():
    rng = np.random.default_rng(11)
    for M in (2, 10, 80):
        C = np.abs(rng.normal(size=(M, M))) * (rng.random((M, M)) < 0.3) + np.diag(np.ones(M - 1), 1)
        C[-1, 0] = 0.5  # irreducible: a cycle through every index
        radius = max(abs(np.linalg.eigvals(C)))
        assert radius - 1e-12 <= perron_bound(C) <= radius * (1 + 1e-6)
    chain = np.diag(np.ones(9), 1) + np.diag(np.ones(9), -1)  # periodic: eigenvalues +-rho
    assert perron_bound(chain) == pytest.approx(2 * np.cos(np.pi / 11), rel=1e-6)
    assert perron_bound(np.zeros((3, 3))) == 0.0


def test_the_block_norm_bound_is_never_below_the_radius():
    system = build_system(load_scenario(FOURTANK))
    K, P = local_lqr(system)
    exact, kind, _ = jacobi_radius(system, P, 8)
    bound, bound_kind, _ = jacobi_radius(system, P, 8, dense_limit=0)
    assert kind == "exact" and bound_kind == "bound" and bound >= exact
    assert closed_loop_radius(system, K, P, 8, dense_limit=10) is None


# --- the closed loop is the method's --------------------------------------------------------------

def nash_plans(system, K, P, N, x0, rounds=300):
    """The k = 0 plans of the method: Jacobi rounds from the K-rollouts to convergence (numeric)."""
    subs = system.subsystems
    resp = [agent_response(s.A, s.B, s.Q, s.R, P[i], N) for i, s in enumerate(subs)]
    xs = [x0[system.xs(i)] for i in range(system.M)]
    plans = []
    for i, s in enumerate(subs):  # K-rollouts: z(t) = Gamma^t x, v(t) = K z(t)
        G = s.A + s.B @ K[i]
        z = [xs[i]]
        for _ in range(N):
            z.append(G @ z[-1])
        plans.append((np.array(z[1:]), np.array([K[i] @ zt for zt in z[:N]])))
    for _ in range(rounds):
        new = []
        for i, s in enumerate(subs):
            c = np.zeros((N, s.n))
            for cp in system.couplings:
                if cp.target != i:
                    continue
                zj, vj = plans[cp.source]
                zhat = np.vstack([xs[cp.source], zj[:N - 1]])
                c += zhat @ cp.A.T + vj @ cp.B.T
            new.append(((resp[i].Zx @ xs[i] + resp[i].Zc @ c.ravel()).reshape(N, s.n),
                        (resp[i].Vx @ xs[i] + resp[i].Vc @ c.ravel()).reshape(N, s.m)))
        plans = new
    return plans


@pytest.mark.parametrize("path, rounds", [("fourtank.yaml", 1), ("fourtank_own.yaml", 1), ("fourtank.yaml", 2)])
def test_the_closed_loop_matrix_is_the_method_without_active_constraints(path, rounds):
    """dmpc.simulate of tv-box from a small start, with no constraint active and the linear plant,
    follows s(k+1) = L s(k) from its first plans: the derivation is the method, and on the
    benchmark's partition its loop is unstable (the deviation grows)."""
    steps = 25
    data = yaml.safe_load((SCENARIOS / path).read_text())
    data.update(setpoints=[], steps=steps, plant={"model": "nominal"})
    data["subsystems"][0]["x0"], data["subsystems"][1]["x0"] = [0.004, -0.002], [-0.003, 0.002]
    data.setdefault("options", {})["method"] = "tv-box"  # the files' method is tv-box-coop
    data["options"]["iterations"] = rounds
    data["options"]["tolerance"] = 1e-300  # every round runs
    scenario = validate_scenario(data)
    result = dmpc.simulate(scenario)
    assert result.verdict == "ok"
    prepared = prepare(scenario)
    system, gains, N = prepared.system, prepared.design.gains, prepared.design.horizon
    x = result.stacked_x()
    plans = nash_plans(system, gains.K, gains.P, N, x[0])
    u0 = np.concatenate([v[0] for _, v in plans])
    np.testing.assert_allclose(result.stacked_u()[0], u0, atol=1e-8)
    s = np.concatenate([x[1]] + [np.concatenate([z.ravel(), v.ravel()]) for z, v in plans])
    L = closed_loop(system, gains.K, gains.P, N, rounds)
    for k in range(1, steps + 1):
        np.testing.assert_allclose(x[k], s[:system.n], atol=1e-8, err_msg=f"k = {k}")
        s = L @ s
    radius = max(abs(np.linalg.eigvals(L)))
    if path == "fourtank.yaml":
        assert radius > 1.0
    else:
        assert radius < 1.0


# --- the shipped scenarios -------------------------------------------------------------------------

def test_the_benchmark_partition_is_likely_to_fail():
    ic = design_coupling(prepare(load_scenario(FOURTANK)))
    assert ic.input_coupled and ic.likely_to_fail and ic.unstable
    strongest = ic.strongest
    assert (strongest.source, strongest.target) == (0, 1)  # pump a drives tanks 2 and 4 more than 1 and 3
    # pump a: 0.7 of its flow into tank 4, 0.3 into tank 1 (scaled alike by the discretisation of
    # each subsystem's own tanks, whose first entries differ)
    assert strongest.ratio > 2.0 and strongest.steady_ratio > 1.0
    assert ic.loop_radius > 1.0 and ic.radius < 1.0  # the rounds converge; their equilibrium does not stabilise
    data = ic.to_json(["a", "b"])
    assert data["likely_to_fail"] is True and data["pairs"][1]["source"] == "a"
    json.dumps(data)


@pytest.mark.parametrize("data", [lambda: swapped_fourtank(), lambda: yaml.safe_load((SCENARIOS / "fourtank_own.yaml").read_text())],
                         ids=["pumps-swapped", "fourtank_own"])
def test_pumps_feeding_their_own_tanks_are_not_flagged(data):
    scenario = validate_scenario(data())
    ic = design_coupling(prepare(scenario))
    assert ic.input_coupled and not ic.likely_to_fail
    assert ic.strongest.ratio < 1.0 and ic.loop_radius < 1.0 and ic.radius < 1.0
    assert not scenario_coupling(scenario).likely_to_fail


@pytest.mark.parametrize("name", ["paper", "chain"])
def test_no_input_coupling_no_warning(name):
    prepared = prepare(load_scenario(SCENARIOS / f"{name}.yaml"))
    ic = design_coupling(prepared)
    assert not ic.input_coupled and not ic.likely_to_fail
    assert ic.radius < 1.0 and ic.loop_radius < 1.0
    assert scenario_coupling(prepared.scenario) is None  # validate has nothing to check


def test_the_rooms_are_not_flagged():
    scenario = load_scenario(SCENARIOS / "rooms.yaml")
    assert scenario_coupling(scenario) is None
    system = build_system(scenario)
    K, P = local_lqr(system)
    ic = input_coupling(system, K, P, 42)
    assert not ic.input_coupled and not ic.likely_to_fail and ic.loop_radius < 1.0


def test_the_methods_the_check_applies_to():
    assert non_cooperative("tv-box") and non_cooperative("tv-box-opt") and non_cooperative("ellipsoid")
    assert not non_cooperative("centralized") and not non_cooperative("tv-box-coop")
    assert not non_cooperative("no-such-method")


# --- what the command line says --------------------------------------------------------------------

def test_validate_warns_on_the_benchmark_in_one_line(monkeypatch, capsys):
    code, out, err = call(monkeypatch, capsys, "validate", str(FOURTANK), "--set", "options.method=tv-box")
    assert code == 0 and "valid" in out
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("warning: subsystem a's inputs drive b more than a")
    assert "--method tv-box-coop" in lines[0] and "unstable" in lines[0]
    assert "tv-box's closed loop" in lines[0]
    assert lines[0].endswith("use the cooperative method (options.method: tv-box-coop, or --method tv-box-coop)")


def test_validate_warns_on_the_benchmark_only_for_a_non_cooperative_method(monkeypatch, capsys):
    """The file's method is tv-box-coop: no warning; with tv-box, the one line naming tv-box-coop."""
    assert load_scenario(FOURTANK).options.method == "tv-box-coop"
    code, out, err = call(monkeypatch, capsys, "validate", str(FOURTANK))
    assert code == 0 and "valid" in out and err == ""
    code, out, err = call(monkeypatch, capsys, "validate", str(FOURTANK), "--set", "options.method=tv-box")
    assert code == 0 and "valid" in out
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("warning: ") and "tv-box-coop" in lines[0]


@pytest.mark.parametrize("name, args", [("paper", ()), ("chain", ()), ("rooms", ()),
                                        ("fourtank_own", ("--set", "options.method=tv-box"))])
def test_validate_is_quiet_elsewhere(monkeypatch, capsys, name, args):
    """fourtank_own with tv-box (its file's method, tv-box-coop, is never warned about)."""
    code, out, err = call(monkeypatch, capsys, "validate", str(SCENARIOS / f"{name}.yaml"), *args)
    assert code == 0 and "valid" in out and err == ""


def test_design_reports_and_writes_the_figures(monkeypatch, capsys):
    code, out, err = call(monkeypatch, capsys, "design", str(FOURTANK), "--json", "--set", "options.method=tv-box")
    assert code == 0
    data = json.loads(out)["input_coupling"]
    assert data["likely_to_fail"] is True and data["horizon"] == 20 and data["loop_radius"] > 1.0
    assert err.startswith("warning: ") and "tv-box-coop" in err and len(err.strip().splitlines()) == 1
    code, out, err = call(monkeypatch, capsys, "design", str(FOURTANK), "--json")  # the file's tv-box-coop
    assert code == 0 and json.loads(out)["input_coupling"] == data and err == ""
    code, out, err = call(monkeypatch, capsys, "design", str(FOURTANK), "--set", "options.method=centralized")
    assert code == 0 and "input coupling" in out and err == ""  # centralized is not at risk


def test_design_is_quiet_on_the_paper(monkeypatch, capsys):
    code, out, err = call(monkeypatch, capsys, "design", str(SCENARIOS / "paper.yaml"))
    assert code == 0 and "none (B_ij = 0)" in out and err == ""

"""The quadruple-tank benchmark: its equilibrium, its linearisation, the nonlinear plant
(``plant.model: fourtank``) and the shipped scenarios built from them (docs/fourtank.md).

The shipped files' plant is their linear model; the tests of the nonlinear tanks give
``plant.model: fourtank`` (and, for fourtank_own, its valve splits) explicitly, as the files'
comments do (``--set plant.model=fourtank``)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.integrate import solve_ivp

import dmpc
from dmpc.plant.fourtank import (
    LEVELS,
    PUMPS,
    SECONDS_PER_HOUR,
    FourTank,
    FourTankPlant,
    equilibrium,
    integrate,
    linearisation,
    outflows,
    rates,
)
from dmpc.scenario import (
    Scenario,
    ScenarioError,
    build_system,
    discrete_model,
    load_scenario,
    parse_override,
    validate_scenario,
)
from dmpc.scenario.schema import FourTankSpec
from dmpc.setup import prepare

ROOT = Path(__file__).resolve().parents[1]
FOURTANK = ROOT / "scenarios" / "fourtank.yaml"
OWN = ROOT / "scenarios" / "fourtank_own.yaml"

# The benchmark's ranges (Alvarado et al. 2011): flows in m^3/h, levels in m.
Q_MAX = np.array([3.26, 4.0])
LEVEL_LOW = np.array([0.2, 0.2, 0.2, 0.2])
LEVEL_HIGH = np.array([1.36, 1.36, 1.30, 1.30])
OWN_FLOOR = 0.05  # scenarios/fourtank_own.yaml lowers the floor of tanks 3 and 4 to this

# The nonlinear tanks of each file as its comments give them (the files' own plant is the linear model).
NONLINEAR = {FOURTANK: {"plant.model": "fourtank"},
             OWN: {"plant.model": "fourtank", "plant.fourtank.gamma": [0.7, 0.6]}}


def nonlinear(path: Path) -> Scenario:
    """The scenario file with the nonlinear tanks it linearises as its plant."""
    return load_scenario(path, NONLINEAR[path])


def tanks_of(path: Path) -> tuple[FourTank, np.ndarray]:
    """The FourTank and q0 of a scenario file's nonlinear tanks (its plant section with NONLINEAR)."""
    spec = nonlinear(path).plant.fourtank or FourTankSpec()
    return FourTank(area=spec.area, outlets=tuple(spec.outlets), gamma=tuple(spec.gamma), g=spec.g), np.array(spec.q0)


def positions(path: Path) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """(subsystem index, position) of h1..h4 and of qa, qb in a scenario file."""
    subs = load_scenario(path).resolved_subsystems()
    where_x = {label.name: (i, c) for i, s in enumerate(subs) for c, label in enumerate(s.states)}
    where_u = {label.name: (i, c) for i, s in enumerate(subs) for c, label in enumerate(s.inputs)}
    return [where_x[n] for n in LEVELS], [where_u[n] for n in PUMPS]


# --- the equations ---------------------------------------------------------------------------------

@pytest.mark.parametrize("gamma, q0", [((0.3, 0.4), (1.63, 2.0)), ((0.7, 0.6), (1.63, 2.0)), ((0.5, 0.2), (3.0, 0.5))])
def test_the_equilibrium_is_at_rest(gamma, q0):
    tanks = FourTank(gamma=gamma)
    h0 = equilibrium(tanks, np.array(q0))
    assert np.all(h0 > 0)
    scale = np.max(np.abs(np.array(q0))) / SECONDS_PER_HOUR / tanks.area
    np.testing.assert_allclose(rates(tanks, h0, np.array(q0)), 0.0, atol=1e-13 * scale)
    # the water pumped in leaves through the two lower tanks
    out = outflows(tanks, h0)
    assert out[0] + out[1] == pytest.approx(sum(q0) / SECONDS_PER_HOUR, rel=1e-13)


def test_the_benchmark_operating_point_lies_inside_its_bounds():
    tanks, q0 = tanks_of(FOURTANK)
    h0 = equilibrium(tanks, q0)
    assert np.all(LEVEL_LOW < h0) and np.all(h0 < LEVEL_HIGH)
    assert np.all(0 < q0) and np.all(q0 < Q_MAX)


def test_the_rates_conserve_water():
    """What tank 3 (4) loses, tank 1 (2) gains: the volume changes by what the pumps deliver less
    what the lower tanks let out."""
    tanks = FourTank()
    rng = np.random.default_rng(3)
    for _ in range(20):
        h, q = rng.uniform(0.0, 1.4, 4), rng.uniform(0.0, 4.0, 2)
        out = outflows(tanks, h)
        assert tanks.area * rates(tanks, h, q).sum() == pytest.approx(q.sum() / SECONDS_PER_HOUR - out[0] - out[1],
                                                                     rel=1e-12, abs=1e-18)


@pytest.mark.parametrize("gamma", [(0.3, 0.4), (0.7, 0.6)])
def test_the_linearisation_is_the_jacobian_of_the_rates(gamma):
    tanks = FourTank(gamma=gamma)
    q0 = np.array([1.63, 2.0])
    h0 = equilibrium(tanks, q0)
    A, B = linearisation(tanks, h0)
    step_h, step_q = 1e-6, 1e-4
    A_fd = np.column_stack([(rates(tanks, h0 + step_h * e, q0) - rates(tanks, h0 - step_h * e, q0)) / (2 * step_h)
                            for e in np.eye(4)])
    B_fd = np.column_stack([(rates(tanks, h0, q0 + step_q * e) - rates(tanks, h0, q0 - step_q * e)) / (2 * step_q)
                            for e in np.eye(2)])
    np.testing.assert_allclose(A, A_fd, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(B, B_fd, rtol=1e-9, atol=1e-15)
    # where each pump's water goes, and that tanks 3 and 4 drain into 1 and 2
    assert np.count_nonzero(A) == 6 and A[0, 2] == -A[2, 2] and A[1, 3] == -A[3, 3]
    assert np.allclose(B.sum(axis=0) * SECONDS_PER_HOUR * tanks.area, 1.0)


# --- the nonlinear plant ---------------------------------------------------------------------------

def test_rk4_agrees_with_an_adaptive_integrator():
    tanks = FourTank()
    h, q = np.array([0.9, 0.3, 0.5, 1.1]), np.array([0.5, 3.5])
    reference = solve_ivp(lambda t, y: rates(tanks, y, q), (0.0, 5.0), h, method="DOP853", rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(integrate(tanks, h, q, 5.0), reference.y[:, -1], rtol=0, atol=1e-10)


def test_the_plant_at_its_operating_point_stays_there():
    tanks, q0 = tanks_of(FOURTANK)
    plant = FourTankPlant(tanks, q0, 5.0, (0, 2, 1, 3), (0, 1))
    x = np.zeros(4)
    for k in range(200):
        x = plant(x, np.zeros(2), k)
    assert np.max(np.abs(x)) < 1e-14


def test_the_plant_conserves_water_over_a_step():
    """S * (sum of the level changes) = pumped volume - volume let out by tanks 1 and 2, the latter
    integrated alongside by an adaptive integrator."""
    tanks, q0 = tanks_of(FOURTANK)
    plant = FourTankPlant(tanks, q0, 5.0, (0, 1, 2, 3), (0, 1))
    h0 = equilibrium(tanks, q0)
    x, u = np.array([0.2, -0.1, 0.05, 0.3]), np.array([1.0, -1.5])
    x_next = plant(x, u, 0)
    q = q0 + u

    def with_outflow(t, y):
        out = outflows(tanks, y[:4])
        return np.append(rates(tanks, y[:4], q), out[0] + out[1])

    ref = solve_ivp(with_outflow, (0.0, 5.0), np.append(h0 + x, 0.0), method="DOP853", rtol=1e-12, atol=1e-14)
    let_out = ref.y[4, -1]
    assert tanks.area * (x_next - x).sum() == pytest.approx(q.sum() / SECONDS_PER_HOUR * 5.0 - let_out, rel=1e-8)


def test_levels_never_go_negative():
    """Pumps off and nearly empty tanks: each tank empties in finite time and stays at 0."""
    tanks, q0 = tanks_of(FOURTANK)
    plant = FourTankPlant(tanks, q0, 5.0, (0, 1, 2, 3), (0, 1))
    h0 = plant.h0
    x = np.array([0.002, 0.001, 0.003, 0.0]) - h0  # levels 2, 1, 3 and 0 mm
    for k in range(100):
        x = plant(x, -q0, k)  # q = 0
        assert np.all(h0 + x >= 0.0)
    np.testing.assert_array_equal(h0 + x, 0.0)
    below = plant(np.full(4, -5.0), np.zeros(2), 0)  # a start below empty counts as empty
    assert np.all(h0 + below >= 0.0)


@pytest.mark.parametrize("path", [FOURTANK, OWN], ids=["fourtank", "fourtank_own"])
def test_the_discrete_model_is_the_nonlinear_step_linearised(path):
    """The controllers' discrete matrices against a finite-difference Jacobian of the plant
    function over one period: the whole chain (equilibrium, linearisation, units, partition,
    discretisation) checked end to end."""
    prepared = prepare(nonlinear(path))
    system, f = prepared.system, prepared.plant.function
    assert prepared.plant.model == "fourtank" and f is not None
    eps_x, eps_u = 1e-6, 1e-4
    A_fd = np.column_stack([(f(eps_x * e, np.zeros(system.m), 0) - f(-eps_x * e, np.zeros(system.m), 0)) / (2 * eps_x)
                            for e in np.eye(system.n)])
    B_fd = np.column_stack([(f(np.zeros(system.n), eps_u * e, 0) - f(np.zeros(system.n), -eps_u * e, 0)) / (2 * eps_u)
                            for e in np.eye(system.m)])
    np.testing.assert_allclose(system.A, A_fd, rtol=0, atol=1e-8)
    np.testing.assert_allclose(system.B, B_fd, rtol=0, atol=1e-9)


# --- the scenario files ----------------------------------------------------------------------------

@pytest.mark.parametrize("path, floors", [(FOURTANK, LEVEL_LOW), (OWN, np.array([0.2, 0.2, OWN_FLOOR, OWN_FLOOR]))],
                         ids=["fourtank", "fourtank_own"])
def test_the_scenario_is_the_linearisation_at_the_exact_equilibrium(path, floors):
    """The continuous-time matrices, the bounds and the units of the file, from the equations."""
    scn = nonlinear(path)
    assert scn.time == "continuous" and scn.dt == 5.0 and scn.plant.model == "fourtank"
    tanks, q0 = tanks_of(path)
    h0 = equilibrium(tanks, q0)
    A, B = linearisation(tanks, h0)
    x_at, u_at = positions(path)
    subs = scn.resolved_subsystems()
    assert [s.name for s in subs] == ["a", "b"]
    assert x_at == [(0, 0), (1, 0), (0, 1), (1, 1)] and u_at == [(0, 0), (1, 0)]  # a = tanks 1, 3 and pump a
    couplings = {(c.target, c.source): c for c in scn.couplings}
    tank_of = {sub: [t for t, (i, _) in enumerate(x_at) if i == sub] for sub in (0, 1)}
    for i, s in enumerate(subs):
        rows = tank_of[i]
        np.testing.assert_allclose(s.A, A[np.ix_(rows, rows)], rtol=1e-10, atol=1e-16)
        np.testing.assert_allclose(s.B, B[np.ix_(rows, [i])], rtol=1e-10, atol=1e-16)
        np.testing.assert_allclose(s.state.lower, floors[rows] - h0[rows], rtol=1e-10)
        np.testing.assert_allclose(s.state.upper, LEVEL_HIGH[rows] - h0[rows], rtol=1e-10)
        np.testing.assert_allclose(s.input.lower, [-q0[i]], rtol=1e-12)
        np.testing.assert_allclose(s.input.upper, [Q_MAX[i] - q0[i]], rtol=1e-12)
        assert [label.unit for label in s.states] == ["m", "m"] and s.inputs[0].unit == "m^3/h"
        j = 1 - i
        c = couplings[(s.name, subs[j].name)]
        np.testing.assert_array_equal(c.A, 0.0)  # the partition couples through the pumps only
        np.testing.assert_allclose(c.B, B[np.ix_(rows, [j])], rtol=1e-10, atol=1e-16)
        assert c.A is not None
        np.testing.assert_allclose(A[np.ix_(rows, tank_of[j])], 0.0)


def test_local_zoh_is_exact_for_this_partition():
    model = discrete_model(load_scenario(FOURTANK))
    assert model.model_error == 0.0
    np.testing.assert_allclose(model.system.A, model.A_exact, atol=1e-15)
    np.testing.assert_allclose(model.system.B, model.B_exact, atol=1e-15)


def test_the_benchmark_setpoints_and_variant():
    scn, own = load_scenario(FOURTANK), load_scenario(OWN)
    asked = [(s.at, s.subsystem, s.x) for s in scn.setpoints]
    assert asked == [(0, "a", {"h1": 0.15}), (0, "b", {"h2": 0.15}), (1500, "a", {"h1": 0.0}), (1500, "b", {"h2": 0.0})]
    assert [(s.at, s.subsystem, s.x) for s in own.setpoints] == asked
    # the files' plant is their linear model, their method the cooperative one
    assert scn.plant.model == own.plant.model == "nominal" and scn.plant.fourtank is None and own.plant.fourtank is None
    assert scn.options.method == own.options.method == "tv-box-coop"
    # their nonlinear tanks: the benchmark's, and the variant's valve splits, as the files' comments give them
    assert "--set plant.model=fourtank" in FOURTANK.read_text()
    assert "--set plant.model=fourtank --set plant.fourtank.gamma=[0.7,0.6]" in OWN.read_text()
    documented = dict(parse_override(text) for text in ("plant.model=fourtank", "plant.fourtank.gamma=[0.7,0.6]"))
    assert documented == NONLINEAR[OWN] and {"plant.model": documented["plant.model"]} == NONLINEAR[FOURTANK]
    assert nonlinear(FOURTANK).plant.fourtank is None and nonlinear(OWN).plant.fourtank.gamma == [0.7, 0.6]
    assert FourTankSpec().gamma == list(FourTank().gamma) and FourTankSpec().outlets == list(FourTank().outlets)
    assert FourTankSpec().area == FourTank().area and FourTankSpec().g == FourTank().g
    assert scn.steps * scn.dt >= 2 * 1500  # each segment 25 min


def test_the_plant_finds_the_tanks_by_name_in_any_order():
    """Subsystems in the other order: the same physics through the names."""
    data = yaml.safe_load(FOURTANK.read_text())
    data["subsystems"].reverse()
    swapped = prepare(validate_scenario(data, NONLINEAR[FOURTANK])).plant.function
    straight = prepare(nonlinear(FOURTANK)).plant.function
    x, u = np.array([0.1, -0.05, 0.02, 0.2]), np.array([0.5, -0.3])  # a: h1, h3; b: h2, h4
    out = straight(x, u, 0)
    np.testing.assert_array_equal(swapped(x[[2, 3, 0, 1]], u[[1, 0]], 0), out[[2, 3, 0, 1]])


@pytest.mark.parametrize("change, field, words", [
    ({"subsystems.0.states": [{"name": "x1"}, {"name": "h3"}]}, "plant.model", "missing: h1"),
    ({"plant": {"model": "nominal", "fourtank": {}}}, "plant.fourtank", "only read when model is 'fourtank'"),
    ({"plant": {"model": "fourtank", "fourtank": {"gamma": [0.3, 1.0]}}}, "plant.fourtank.gamma[1]", "(0, 1)"),
    ({"plant": {"model": "fourtank", "fourtank": {"outlets": [1e-4, 1e-4, 1e-4]}}}, "plant.fourtank.outlets",
     "4 entries"),
    ({"dt": None}, "dt", "required"),
])
def test_plant_model_fourtank_errors_name_the_field(change, field, words):
    data = yaml.safe_load(FOURTANK.read_text())
    data["plant"] = {"model": "fourtank"}  # the nonlinear tanks; the cases below change or replace it
    for key, value in change.items():
        if key == "subsystems.0.states":
            data["subsystems"][0]["states"] = value
        else:
            data[key] = value
    with pytest.raises(ScenarioError) as err:
        validate_scenario(data)
    assert str(err.value).startswith(field) and words in str(err.value), str(err.value)


def test_the_nonlinear_plant_runs_and_says_so():
    scenario = dmpc.load_scenario(FOURTANK, steps=12, **{"options.method": "centralized", "plant.model": "fourtank"})
    result = dmpc.simulate(scenario)
    assert result.summary["plant"]["model"] == "fourtank"
    assert result.summary["plant"]["function"] == "dmpc.plant.fourtank:FourTankPlant"
    assert np.all(np.isfinite(result.stacked_x()))
    assert build_system(scenario).n == 4


def test_the_example_script_prints_the_benchmark():
    done = subprocess.run([sys.executable, str(ROOT / "examples" / "fourtank.py"), "--steps", "20"], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert "partition a = (h1, h3; qa), b = (h2, h4; qb)" in out
    assert "warning: subsystem a's inputs drive b more than a" in out and "tv-box-coop" in out
    assert "centralized  verdict ok" in out and "tv-box-coop  verdict ok, fallbacks 0" in out
    assert "closed loop on the nonlinear tanks" in out


def test_the_example_script_runs_the_variant_on_its_own_tanks():
    done = subprocess.run([sys.executable, str(ROOT / "examples" / "fourtank.py"), "--own", "--steps", "5"], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "splits gamma_a, gamma_b = (0.7, 0.6)" in done.stdout

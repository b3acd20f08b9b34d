"""A constant disturbance step written in the scenario (``plant.disturbance: {kind: step, at,
input, state}``, docs/scenarios.md): its schema, the w(k) it makes, and the shipped example
scenarios/paper-input-disturbance.yaml with and without estimation (docs/algorithm.md,
"Offset-free tracking").

The expected w(k) is recomputed from the scenario's own numbers (B_ii, the couplings' B_ij, the
offsets), and the plant's update is checked against the run's records: x(k+1) - A x(k) - B u(k)
is the recorded w(k).

Figures measured when these tests were written (paper-input-disturbance.yaml, 120 steps):

    with estimation       ||x(120)||_inf = 1.8e-7, u(119) = -d_u to 2e-7, d^ = d_u to 3e-9; 0.9 s
    without estimation    x1 settles 0.54, 0.58, 0.30, 0.59 off in subsystems 1-4 (||x||_inf 0.59)
    dmpc.run (40 steps)   the trajectory and w of dmpc.simulate, bit for bit; 4 s
"""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml

import dmpc
from dmpc.api.result import Result
from dmpc.scenario import ScenarioError, build_system, discrete_model, setpoint_entries, validate_scenario
from dmpc.setup.plant import disturbance_start, plant_setup
from tests.helpers.closed_loop import SOLVED, bound_excess, fallback_steps, read_steps, scenario_bounds, statuses

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "scenarios" / "paper-input-disturbance.yaml"
CARTS = ROOT / "scenarios" / "carts-continuous.yaml"

OFFSET_FRACTION = 1e-4
"""With estimation, the states at the end within this fraction of the offset the disturbance
leaves without estimation."""
BOUND_TOLERANCE = 1e-7
"""An input may pass its bound by this much (the QP's accuracy)."""


def two_carts(**disturbance) -> dict:
    """Two subsystems (n_i = 2, m_i = 1), each input also driving the other (B_ij != 0), with
    ``plant.disturbance`` the given fields."""
    sub = {"A": [[1.0, 0.1], [0.0, 1.0]], "B": [[0.0], [0.1]], "Q": [[1.0, 0.0], [0.0, 1.0]], "R": [[0.1]],
           "input": {"lower": [-1.0], "upper": [1.0]}, "x0": [0.1, 0.0]}
    return {"name": "two", "subsystems": [dict(copy.deepcopy(sub), name="a"), dict(copy.deepcopy(sub), name="b")],
            "couplings": [{"target": "a", "source": "b", "A": [[0.0, 0.0], [0.02, 0.0]], "B": [[0.0], [0.04]]},
                          {"target": "b", "source": "a", "A": [[0.0, 0.0], [0.03, 0.0]], "B": [[0.01], [0.05]]}],
            "horizon": 5, "steps": 12, "plant": {"disturbance": disturbance}}


def refused(data: dict, field: str, *words: str) -> None:
    with pytest.raises(ScenarioError) as caught:
        validate_scenario(data)
    assert caught.value.field == field, str(caught.value)
    for word in words:
        assert word in str(caught.value), str(caught.value)


# ------------------------------------------------------------------------------------- the schema
@pytest.mark.parametrize("fields, field, words", [
    ({"input": {"a": [0.1]}}, "plant.disturbance.at", ["required when kind is 'step'"]),
    ({"at": 3}, "plant.disturbance.input", ["'input'", "'state'"]),
    ({"at": 3, "input": {}, "state": {}}, "plant.disturbance.input", ["'input'", "'state'"]),
    ({"at": -1, "input": {"a": [0.1]}}, "plant.disturbance.at", [">= 0"]),
    ({"at": 3, "input": {"c": [0.1]}}, "plant.disturbance.input.c", ["unknown subsystem 'c'"]),
    ({"at": 3, "state": {"z": [0.1, 0.0]}}, "plant.disturbance.state.z", ["unknown subsystem 'z'"]),
    ({"at": 3, "input": {"a": [0.1, 0.2]}}, "plant.disturbance.input.a", ["m = 1 inputs of subsystem 'a'", "2"]),
    ({"at": 3, "state": {"b": [0.1]}}, "plant.disturbance.state.b", ["n = 2 states of subsystem 'b'", "1"]),
    ({"at": 3, "input": {"a": [float("nan")]}}, "plant.disturbance.input.a[0]", []),
    ({"at": 3, "input": {"a": [0.1]}, "bound": {"a": [0.1, 0.1]}}, "plant.disturbance.bound",
     ["only read when kind is 'uniform'"]),
])
def test_a_step_is_refused_with_the_field_named(fields, field, words):
    refused(two_carts(kind="step", **fields), field, *words)


@pytest.mark.parametrize("field, value", [("at", 3), ("input", {"a": [0.1]}), ("state", {"a": [0.1, 0.0]})])
def test_the_fields_of_a_step_are_refused_with_another_kind(field, value):
    refused(two_carts(kind="uniform", bound={"a": [0.1, 0.1]}, **{field: value}), f"plant.disturbance.{field}",
            "only read when kind is 'step'")


def test_at_counts_steps_without_dt_and_seconds_with_it_as_for_setpoints():
    data = two_carts(kind="step", at=2.5, input={"a": [0.1]})
    scn = validate_scenario(data)
    with pytest.raises(ScenarioError) as caught:
        plant_setup(scn, build_system(scn), scn.steps)
    assert caught.value.field == "plant.disturbance.at" and "whole step" in str(caught.value)
    for at, dt in ((0.3, 0.1), (0.25, 0.1), (1.0, 0.5), (0.0, 0.2)):  # 0.3 / 0.1 = 2.9999999999999996: step 3
        scn = validate_scenario(dict(data, dt=dt, plant={"disturbance": {"kind": "step", "at": at, "input": {"a": [0.1]}}},
                                 setpoints=[{"at": at, "subsystem": "a", "x": [0.0, None]}]))
        assert disturbance_start(scn) == setpoint_entries(scn)[0].at == int(np.ceil(round(at / dt, 9)))


# ---------------------------------------------------------------------------------------- w(k)
def coupled_B(data: dict) -> np.ndarray:
    """The global B (n, m) from the scenario mapping: B_ii on the diagonal, the couplings' B_ij."""
    names = [s["name"] for s in data["subsystems"]]
    n = [len(s["A"]) for s in data["subsystems"]]
    m = [len(s["B"][0]) for s in data["subsystems"]]
    rows, cols = np.cumsum([0] + n), np.cumsum([0] + m)
    B = np.zeros((rows[-1], cols[-1]))
    for i, s in enumerate(data["subsystems"]):
        B[rows[i]:rows[i + 1], cols[i]:cols[i + 1]] = s["B"]
    for c in data["couplings"]:
        i, j = names.index(c["target"]), names.index(c["source"])
        B[rows[i]:rows[i + 1], cols[j]:cols[j + 1]] += c["B"]
    return B


def test_w_is_B_times_the_input_offset_plus_the_state_offset_from_at_on():
    data = two_carts(kind="step", at=4, input={"b": [0.5]}, state={"a": [0.0, -0.02]})
    scn = validate_scenario(data)
    setup = plant_setup(scn, build_system(scn), scn.steps)
    expected = coupled_B(data) @ np.array([0.0, 0.5]) + np.array([0.0, -0.02, 0.0, 0.0])
    assert expected[1] != -0.02 and expected[3] != 0  # b's input reaches a through B_ab, and b itself
    assert setup.disturbance is not None and setup.disturbance.shape == (scn.steps, 4)
    assert not np.any(setup.disturbance[:4])
    np.testing.assert_array_equal(setup.disturbance[4:], np.tile(expected, (scn.steps - 4, 1)))
    assert setup.disturbance_kind == "step"
    np.testing.assert_array_equal(setup.disturbance_bound, np.abs(expected))  # the tube's W (tube: robust)


def test_with_the_exact_plant_the_input_offset_enters_through_its_own_B():
    scn = dmpc.load_scenario(CARTS, steps=5, plant={"model": "exact", "disturbance": {"kind": "step", "at": 0.2,
                                                                                      "input": {"2": [0.4]}}})
    system = build_system(scn)
    w = plant_setup(scn, system, scn.steps).disturbance
    B_exact = discrete_model(scn).B_exact
    d_u = np.array([0.0, 0.4, 0.0])
    assert w is not None and not np.any(w[:2])  # 0.2 s at dt = 0.1 s: from step 2
    np.testing.assert_array_equal(w[2:], np.tile(B_exact @ d_u, (3, 1)))
    assert np.abs(B_exact @ d_u - system.B @ d_u).max() > 1e-6  # not the controllers' model's


# ------------------------------------------------------------------------------ the shipped example
@pytest.fixture(scope="module")
def example_runs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("disturbance-step")
    with_estimation = dmpc.simulate(dmpc.load_scenario(EXAMPLE), out=folder / "estimation")
    without = dmpc.simulate(dmpc.load_scenario(EXAMPLE, estimation=None), out=folder / "plain")
    return with_estimation, without


def example_offset() -> tuple[dict, np.ndarray]:
    """The example's mapping and its input offset d_u stacked (m,), from the file."""
    data = yaml.safe_load(EXAMPLE.read_text())
    d = data["plant"]["disturbance"]
    return data, np.concatenate([d["input"].get(s["name"], [0.0]) for s in data["subsystems"]])


def assert_plant_adds_w(result: Result, data: dict, start: int) -> None:
    """x(k+1) - A x(k) - B u(k) is the recorded w(k) (A, B from the file), and w(k) = B d_u from
    ``start`` on, zeros before."""
    names = [s["name"] for s in data["subsystems"]]
    n = len(data["subsystems"][0]["A"])
    A = np.zeros((n * len(names),) * 2)
    for i, s in enumerate(data["subsystems"]):
        A[i * n:(i + 1) * n, i * n:(i + 1) * n] = s["A"]
    for c in data["couplings"]:
        i, j = names.index(c["target"]), names.index(c["source"])
        A[i * n:(i + 1) * n, j * n:(j + 1) * n] += c["A"]
    B = coupled_B(data)
    x, u = result.stacked_x(), result.stacked_u()
    w = np.concatenate([result.w[name] for name in result.names], axis=1)
    np.testing.assert_allclose(x[1:] - x[:-1] @ A.T - u @ B.T, w, rtol=0, atol=1e-12)
    _, d_u = example_offset()
    assert not np.any(w[:start])
    np.testing.assert_array_equal(w[start:], np.tile(B @ d_u, (len(w) - start, 1)))


def test_the_example_returns_to_the_origin_with_estimation(example_runs):
    result, without = example_runs
    data, d_u = example_offset()
    start = data["plant"]["disturbance"]["at"]
    assert result.verdict == "ok", result.summary["failures"]
    assert result.summary["warnings"] == [], result.summary["warnings"]
    assert result.summary["fallbacks"] == 0 and result.summary["qp_failed"] == 0 and result.summary["feasible"]
    steps = read_steps(result.folder)
    assert fallback_steps(steps) == [] and statuses(steps) == {SOLVED} and len(steps) == data["steps"]
    x_excess, u_excess = bound_excess(result, scenario_bounds(dmpc.load_scenario(EXAMPLE)))
    assert x_excess <= BOUND_TOLERANCE and u_excess <= BOUND_TOLERANCE
    assert_plant_adds_w(result, data, start)
    effect = np.abs(without.stacked_x()[-1]).max()  # what the disturbance leaves without estimation
    assert effect >= 0.1
    assert np.abs(result.stacked_x()[-1]).max() <= OFFSET_FRACTION * effect
    # the observer found the offset, and the inputs cancel it
    d_hat = np.concatenate([result.d_hat[name][-1] for name in result.names])
    np.testing.assert_allclose(d_hat, d_u, rtol=0, atol=1e-6)
    np.testing.assert_allclose(result.stacked_u()[-1], -d_u, rtol=0, atol=1e-6)


def test_without_estimation_the_example_settles_off_and_the_summary_says_so(example_runs):
    _, result = example_runs
    data, _ = example_offset()
    assert result.verdict == "ok" and result.summary["fallbacks"] == 0
    assert_plant_adds_w(result, data, data["plant"]["disturbance"]["at"])
    x = result.stacked_x()
    assert np.abs(x[-1] - x[-2]).max() <= 1e-9  # settled
    offsets = {w["subsystem"]: w["amount"] for w in result.summary["warnings"] if w["kind"] == "offset"}
    assert sorted(offsets) == list(result.names)
    for name in result.names:  # x1 is requested at 0 in every subsystem
        assert offsets[name] == pytest.approx(abs(result.x[name][-1, 0]), abs=1e-9)
        assert offsets[name] >= 0.1
    assert any(w["kind"] == "not-converged" for w in result.summary["warnings"])


@pytest.mark.e2e
def test_the_plant_process_of_dmpc_run_applies_the_same_step(tmp_path):
    """Over Zenoh, one process per agent: the plant process builds w from the run folder's
    scenario and gives the in-process run's trajectory, bit for bit, with w in the record."""
    scenario = dmpc.load_scenario(EXAMPLE, steps=40)
    simulated = dmpc.simulate(scenario, out=tmp_path / "sim")
    ran = dmpc.run(scenario, out=tmp_path / "run")
    assert ran.verdict == "ok"
    np.testing.assert_array_equal(ran.stacked_x(), simulated.stacked_x())
    np.testing.assert_array_equal(ran.stacked_u(), simulated.stacked_u())
    w = np.load(tmp_path / "run" / "disturbance.npy")
    np.testing.assert_array_equal(w, np.load(tmp_path / "sim" / "disturbance.npy"))
    assert w.shape == (40, 8) and not np.any(w[:30]) and np.all(w[30:] == w[30])
    assert_plant_adds_w(ran, yaml.safe_load(EXAMPLE.read_text()), 30)

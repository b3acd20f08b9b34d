"""A plant outside that reports measured outputs y_i in place of states (docs/protocol.md, "The plant's side"),
on the in-memory bus: the controllers see what they see when dmpc measures y = C x itself, and the
records hold, for those subsystems, the estimate that agrees with the measurements."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dmpc.agents.process import agent_node
from dmpc.bus.codec import DecodeError, decode, encode
from dmpc.bus.memory import MemoryBus
from dmpc.bus.messages import State
from dmpc.coordinator.process import run_coordinator
from dmpc.plant.models import make_plant
from dmpc.plant.role import PlantRole
from dmpc.plant.state_inbox import StateInbox
from dmpc.records.session import RunRecorder
from dmpc.runtime.inprocess import simulate
from dmpc.scenario import load_scenario
from dmpc.setup import prepare
from tests.helpers.cli import call, one_error_line

ROOT = Path(__file__).resolve().parents[1]
RUN = "outputs"
STEPS = 80


def _prepared(name: str):
    return prepare(load_scenario(ROOT / "scenarios" / f"{name}.yaml", {"steps": STEPS}))


def _outside(prepared, folder: Path, sensors: bool):
    """The run with dmpc's plant as an outside plant that reports outputs (per subsystem with ``sensors``)."""
    bus = MemoryBus()
    for name in prepared.names:
        agent_node(prepared, name, bus, RUN).announce()
    roles = [PlantRole(bus, make_plant(prepared), prepared.system, RUN, sensors=[name], outputs=True)
             for name in prepared.names] if sensors else \
        [PlantRole(bus, make_plant(prepared), prepared.system, RUN, outputs=True)]
    for role in roles:
        role.announce()
    with RunRecorder(folder, prepared, show_progress=False) as recorder:
        outcome = run_coordinator(prepared, recorder, bus, RUN, startup_timeout=10.0, external_plant=True,
                                  plant_timeout=5.0)
    assert outcome.code == 0, outcome.message
    return outcome.summary, np.load(folder / "trajectory.npz")


@pytest.mark.parametrize("sensors", [False, True])
def test_outputs_in_place_of_states_steer_the_run_as_measured_outputs_do(tmp_path, sensors):
    prepared = _prepared("fourtank-levels")
    reference = []
    simulate(prepared, reference.append)
    summary, arrays = _outside(prepared, tmp_path / "run", sensors)
    assert summary["outputs_reported"] == ["a", "b"]
    u = np.array([rec.u for rec in reference])
    x_hat = np.array([rec.estimate.x_hat for rec in reference])
    # the same measurements, so the same estimates and inputs, bit for bit
    assert np.array_equal(arrays["u"], u) and np.array_equal(arrays["x_hat"], x_hat)
    true_x = np.array([rec.x for rec in reference] + [reference[-1].x_next])
    measured = [0, 2]  # h1 of a, h2 of b: the rows of C
    assert np.array_equal(arrays["x"][:, measured], true_x[:, measured])  # the records' outputs are the measurements
    unmeasured = [1, 3]
    np.testing.assert_array_equal(arrays["x"][:-1, unmeasured], x_hat[:, unmeasured])  # the estimate, elsewhere
    assert summary["verdict"] == "ok"


def test_outputs_in_the_plants_units_with_an_operating_point(tmp_path):
    prepared = _prepared("fourtank-absolute")
    reference = []
    simulate(prepared, reference.append)
    summary, arrays = _outside(prepared, tmp_path / "run", sensors=False)
    u_op = prepared.system.input_offset
    u = np.array([rec.u for rec in reference]) + u_op
    np.testing.assert_allclose(arrays["u"], u, rtol=0, atol=1e-9)  # the wire's x_op + x - x_op rounds
    assert 0.6 < arrays["x"][0, 0] < 0.7  # levels in m
    assert summary["verdict"] == "ok"


def test_the_inbox_takes_outputs_only_in_a_run_with_estimation():
    prepared = _prepared("fourtank-levels")
    inbox = StateInbox(prepared.system, outputs=True)
    inbox.expect(0)
    msg = State(run=RUN, k=0, sender="plant", x={"a": np.zeros(2)}, y={"b": np.array([0.1])})
    assert inbox.problem("plant", msg) is None
    measured = inbox.take(msg)
    assert measured is not None
    assert np.array_equal(measured.x[:2], [0.0, 0.0]) and np.isnan(measured.x[2:]).all()
    assert list(measured.y) == ["b"] and measured.y["b"].tolist() == [0.1]
    strict = StateInbox(prepared.system)
    strict.expect(0)
    assert strict.problem("plant", msg) == ("outputs (y) in a run without estimation: this run needs every "
                                            "subsystem's state x")
    inbox.expect(1)
    wrong = State(run=RUN, k=1, sender="sensor-a", x={}, y={"a": np.zeros(2)})
    assert inbox.problem("sensor-a", wrong) == "the outputs of subsystem a have shape (2,), expected (1,)"
    other = State(run=RUN, k=1, sender="sensor-a", x={}, y={"b": np.zeros(1)})
    assert inbox.problem("sensor-a", other) == "a sensor of a sent the outputs of b"


def test_the_wire_leaves_y_out_when_empty_and_refuses_a_subsystem_in_both():
    plain = State(run=RUN, k=3, sender="plant", x={"a": np.ones(2)})
    assert decode(encode(plain)).y == {}
    assert b"\xa1y" not in encode(plain)  # no y field at all: what a reader of version 3 always read
    both = State(run=RUN, k=3, sender="plant", x={"a": np.ones(2)}, y={"a": np.ones(1)})
    with pytest.raises(DecodeError, match="subsystem 'a' is in both x and y"):
        decode(encode(both))
    only = State(run=RUN, k=3, sender="plant", x={}, y={"a": np.ones(1)})
    assert decode(encode(only)).y["a"].tolist() == [1.0]


@pytest.mark.parametrize(("argv", "words"), [
    (["plant", "scenarios/paper.yaml", "--coordinator", "external", "--outputs", "--run-id", "x"],
     "--outputs: the scenario has no 'estimation'"),
    (["plant", "scenarios/paper.yaml", "--outputs", "--out", "OUT"], "--outputs: only with --coordinator external"),
])
def test_outputs_from_dmpc_plant_need_estimation_and_an_outside_coordinator(monkeypatch, capsys, tmp_path, argv,
                                                                           words):
    argv = [str(tmp_path / "run") if a == "OUT" else a for a in argv]
    code, _, err = call(monkeypatch, capsys, *argv)
    assert code == 2 and words in one_error_line(err), err

"""The coordinator and the plant as two roles on one in-memory bus, and protocol versions.

The end-to-end versions (real processes, an outside plant that is not dmpc) are in
tests/test_e2e_outside_plant.py.
"""
from __future__ import annotations

import msgpack
import numpy as np
import pytest

from dmpc.agents.controller import AgentController
from dmpc.agents.node import AgentNode
from dmpc.agents.process import Changes, serve
from dmpc.bus import keys
from dmpc.bus.codec import encode
from dmpc.bus.memory import MemoryBus
from dmpc.bus.messages import PROTOCOL_VERSION, Release, State
from dmpc.coordinator.barrier import Coordinator
from dmpc.coordinator.process import run_coordinator
from dmpc.plant.dynamics import Plant
from dmpc.plant.role import PlantRole
from dmpc.records.session import RunRecorder
from dmpc.records.tables import print_summary
from dmpc.runtime.inprocess import simulate
from dmpc.scenario import load_scenario
from dmpc.setup import prepare
from tests.helpers.cli import call, one_error_line
from tests.helpers.reference import PAPER

RUN = "roles"


@pytest.fixture(scope="module")
def paper():
    return prepare(load_scenario(PAPER, {"steps": 8}))


def agents_on(bus: MemoryBus, prepared) -> list[AgentNode]:
    nodes = []
    for i in range(prepared.system.M):
        controller = AgentController(prepared.system, prepared.design, i)
        node = AgentNode(bus, controller, prepared.names, RUN, prepared.digest, scenario=prepared.name)
        node.announce()
        nodes.append(node)
    return nodes


def with_version(payload: bytes, version: int) -> bytes:
    """``payload`` as a sender of another protocol version would have written it."""
    body = msgpack.unpackb(payload, raw=False)
    body["protocol"] = version
    return msgpack.packb(body, use_bin_type=True)


def test_a_coordinator_without_a_plant_asks_for_the_state_and_continues_from_it(paper):
    coordinator = Coordinator(paper.system, paper.design, None, paper.protocol, RUN)
    with pytest.raises(ValueError, match="measured x"):
        coordinator.start()
    actions = coordinator.start(paper.system.x0)
    assert actions and coordinator.k == 0
    assert coordinator.on_state(1, paper.system.x0) == []  # nothing awaited yet


@pytest.mark.parametrize("sensors", [None, "each"])
def test_split_roles_on_one_bus_give_the_trajectory_of_simulate(tmp_path, paper, sensors):
    reference = []
    simulate(paper, reference.append)
    bus = MemoryBus()
    agents_on(bus, paper)
    names = paper.names if sensors == "each" else None
    plants = [PlantRole(bus, Plant(paper.system), paper.system, RUN, sensors=[name]) for name in names] if names \
        else [PlantRole(bus, Plant(paper.system), paper.system, RUN)]
    for plant in plants:
        plant.announce()
    with RunRecorder(tmp_path / "run", paper, show_progress=False) as recorder:
        outcome = run_coordinator(paper, recorder, bus, RUN, startup_timeout=10.0, external_plant=True, plant_timeout=5.0)
    assert outcome.code == 0, outcome.message
    assert outcome.summary["plant"] == {"model": "outside"}
    with np.load(tmp_path / "run" / "trajectory.npz") as arrays:
        x = arrays["x"]
    expected = np.array([rec.x for rec in reference] + [reference[-1].x_next])
    assert x.shape == expected.shape and np.array_equal(x, expected)
    assert all(plant.k == paper.protocol.steps and plant.stopped for plant in plants)


def test_a_state_of_the_wrong_shape_is_dropped_and_the_run_stops_naming_the_sensor(tmp_path, paper):
    bus = MemoryBus()
    agents_on(bus, paper)
    honest = [PlantRole(bus, Plant(paper.system), paper.system, RUN, sensors=[name]) for name in paper.names[:3]]
    for plant in honest:
        plant.announce()
    bad = keys.sensor_role(paper.names[3])
    bus.declare_alive(keys.alive(RUN, bad))
    wrong = encode(State(run=RUN, k=0, sender=bad, x={paper.names[3]: np.zeros(5)}))
    bus.call_later(0.5, lambda: bus.publish(keys.state(RUN, bad), wrong))  # once the coordinator listens
    with RunRecorder(tmp_path / "run", paper, show_progress=False) as recorder:
        outcome = run_coordinator(paper, recorder, bus, RUN, startup_timeout=3.0, external_plant=True)
    assert outcome.code == 1
    assert "the plant sent no state for step 0 within 3 s (missing: subsystems 4)" in outcome.message
    assert "sensor-4: alive; last state dropped: the state of subsystem 4 has shape (5,), expected (2,)" \
        in outcome.message
    assert outcome.summary["rejected"].get("sensor-4") == 1


def test_a_state_dropped_once_and_sent_again_leaves_the_run_ok_and_says_so_on_the_console(tmp_path, paper, capsys):
    """x(3) first arrives with a NaN in subsystem 2; the coordinator drops it, repeats the inputs,
    and the plant's answer to the repeat completes the step. The summary counts the drop by its
    whole reason, and the printed summary has one line about it."""
    bus = MemoryBus()
    agents_on(bus, paper)
    PlantRole(bus, Plant(paper.system), paper.system, RUN).announce()
    real_publish, spoilt = bus.publish, []

    def publish(key, payload):
        body = msgpack.unpackb(payload, raw=False)
        if key == keys.state(RUN, keys.PLANT_ROLE) and body["k"] == 3 and not spoilt:
            body["x"]["2"]["data"] = np.array([np.nan, 0.0], "<f8").tobytes()
            spoilt.append(key)
            payload = msgpack.packb(body, use_bin_type=True)
        real_publish(key, payload)

    bus.publish = publish
    with RunRecorder(tmp_path / "run", paper, show_progress=False) as recorder:
        outcome = run_coordinator(paper, recorder, bus, RUN, startup_timeout=10.0, external_plant=True, plant_timeout=5.0)
    assert spoilt and outcome.code == 0, outcome.message
    summary = outcome.summary
    assert summary["verdict"] == "ok" and summary["steps"] == paper.protocol.steps
    assert summary["rejected"] == {"plant": 1}
    assert summary["rejected_reasons"] == {"x[2]: non-finite values": 1}
    capsys.readouterr()
    print_summary(summary, tmp_path / "run")
    lines = [line for line in capsys.readouterr().out.splitlines() if "dropped by the coordinator" in line]
    assert len(lines) == 1 and "1 from plant (x[2]: non-finite values)" in lines[0], lines


def test_an_agent_of_another_protocol_version_is_named_with_both_versions(tmp_path, paper):
    bus = MemoryBus()
    agents_on(bus, paper)
    # agent 4's Ready goes out as an agent of protocol version 2 would write it
    real_publish = bus.publish
    bus.publish = lambda key, payload: real_publish(
        key, with_version(payload, 2) if key == keys.ready(RUN, "4") else payload)
    with RunRecorder(tmp_path / "run", paper, show_progress=False) as recorder:
        outcome = run_coordinator(paper, recorder, bus, RUN, startup_timeout=3.0)
    assert outcome.code == 1
    assert f"agent 4 speaks protocol version 2; this coordinator speaks protocol version {PROTOCOL_VERSION}" \
        in outcome.message
    assert "agents 4 not ready within 3 s" in outcome.message


def test_an_agent_names_a_coordinator_of_another_protocol_version(paper):
    bus = MemoryBus()
    node = agents_on(bus, paper)[0]
    bus.declare_alive(keys.alive(RUN, keys.COORDINATOR_ROLE))
    release = Release(run=RUN, k=0, round=0, x=paper.system.x0, centres=np.zeros(paper.system.n),
                      sizes=np.ones(paper.system.M), assumed=np.full((paper.system.M, 2), -1))
    bus.publish(keys.release(RUN), with_version(encode(release), 4))
    ends: dict = {}
    serve({node.name: node}, bus, RUN, 2.0, Changes(), ends)
    code, message = ends[node.name]
    assert code == 1
    assert ("the coordinator speaks protocol version 4; this process speaks protocol version "
            f"{PROTOCOL_VERSION}") in message


@pytest.mark.parametrize("argv, words", [
    (["coordinator", PAPER, "--out", "x", "--plant", "outside"], "--plant: expected internal or external"),
    (["coordinator", PAPER, "--out", "x", "--plant", "external", "--model", "m:f"], "the plant is outside"),
    (["plant", PAPER], "--out: a run folder is needed when this process hosts the coordinator"),
    (["plant", PAPER, "--out", "x", "--sensor", "1"], "--sensor: only with --coordinator external"),
    (["plant", PAPER, "--coordinator", "external", "--out", "x"], "the plant alone writes no run folder"),
    (["plant", PAPER, "--coordinator", "external", "--sensor", "9"], "--sensor: no subsystem '9'"),
    (["plant", PAPER, "--coordinator", "external", "--sensor", "1", "--sensor", "1"], "named twice"),
    (["run", PAPER, "--plant", "elsewhere"], "--plant: expected internal or external"),
])
def test_role_flags_that_do_not_fit_are_refused_with_one_line(monkeypatch, capsys, tmp_path, argv, words):
    monkeypatch.chdir(tmp_path)
    code, _, err = call(monkeypatch, capsys, *map(str, argv))
    assert code == 2 and words in one_error_line(err), err
    assert not (tmp_path / "x").exists()

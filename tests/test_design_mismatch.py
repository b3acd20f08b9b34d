"""A design that differs between the plant and an agent is named on both sides (in-memory bus).

The end-to-end version, with real processes over Zenoh, is in tests/test_e2e_runtime.py.
"""
from __future__ import annotations

import pytest

from dmpc.agents.controller import AgentController
from dmpc.agents.node import AgentNode
from dmpc.agents.process import Changes, serve
from dmpc.bus import keys
from dmpc.bus.codec import MAX_REASON, decode, encode
from dmpc.bus.memory import MemoryBus
from dmpc.bus.messages import Ready, design_claim
from dmpc.coordinator.barrier import Coordinator
from dmpc.coordinator.node import CoordinatorNode
from dmpc.coordinator.process import run_coordinator
from dmpc.plant.dynamics import Plant
from dmpc.records.session import RunRecorder
from dmpc.scenario import load_scenario
from dmpc.setup import prepare
from tests.helpers.reference import PAPER

RUN = "mismatch"


@pytest.fixture(scope="module")
def paper():
    return prepare(load_scenario(PAPER))


@pytest.fixture(scope="module")
def paper_n12():
    return prepare(load_scenario(PAPER, {"horizon": 12}))


def agent_node(bus: MemoryBus, prepared, i: int) -> AgentNode:
    controller = AgentController(prepared.system, prepared.design, i)
    node = AgentNode(bus, controller, prepared.names, RUN, prepared.digest, scenario=prepared.name)
    node.announce()
    return node


def serve_alone(node: AgentNode, bus: MemoryBus) -> tuple[int, str]:
    ends: dict = {}
    serve({node.name: node}, bus, RUN, 5.0, Changes(), ends)
    return ends[node.name]


def test_plant_and_agent_name_the_differing_design(tmp_path, paper, paper_n12):
    assert paper.digest != paper_n12.digest
    bus = MemoryBus()
    agents = [agent_node(bus, paper, i) for i in range(3)] + [agent_node(bus, paper_n12, 3)]
    with RunRecorder(tmp_path / "run", paper, show_progress=False) as recorder:
        outcome = run_coordinator(paper, recorder, bus, RUN, startup_timeout=5.0)
    assert outcome.code == 1
    assert outcome.message.startswith("plant: a design differs from this plant's: ")
    assert f"agent 4 uses design {paper_n12.digest} (scenario 'paper', horizon 12)" in outcome.message
    assert f"this plant uses design {paper.digest} (scenario 'paper', horizon 10)" in outcome.message
    assert "agents 4 not ready within 5 s" in outcome.message
    assert set(outcome.summary["rejected"]) == {"4"}
    assert outcome.summary["rejected_reasons"].keys() == {"design"}
    assert [a.design_refused for a in agents] == [False, False, False, True]
    code, message = serve_alone(agents[3], bus)
    assert code == 1
    assert message.startswith(f"agent 4: its design differs from the coordinator's: this agent uses design "
                              f"{paper_n12.digest} (scenario 'paper', horizon 12)")
    code, message = serve_alone(agents[0], bus)
    assert code == 1 and "its design differs" not in message and "the coordinator stopped the run" in message


def test_a_forged_ready_with_another_design_does_not_stop_the_run(paper):
    """Anyone on the bus can send one: the plant counts it and starts once the real agents are ready."""
    bus = MemoryBus()
    coordinator = Coordinator(paper.system, paper.design, Plant(paper.system), paper.protocol, RUN)
    plant = CoordinatorNode(bus, coordinator, paper.digest, lambda record: None, scenario=paper.name)
    plant.announce()
    forged = Ready(run=RUN, sender="2", design_digest="0123456789abcdef", scenario="x\x1b[2J", horizon=3)
    bus.publish(keys.ready(RUN, "2"), encode(forged))
    bus.run(lambda: False, timeout=0.1)
    assert plant.mismatched.keys() == {"2"} and not plant.finished
    assert plant.design_mismatch(["2"]).startswith(
        "a design differs from this plant's: agent 2 uses design 0123456789abcdef (scenario 'x?[2J', horizon 3); "
        f"this plant uses design {paper.digest} (scenario 'paper', horizon 10)")
    assert plant.design_mismatch(["1", "3"]) == ""
    agents = [agent_node(bus, paper, i) for i in range(4)]
    assert bus.run(lambda: plant.started, timeout=5.0)
    assert plant.failure == "" and plant.mismatched == {}
    assert plant.rejected == {"2": 1}
    assert not any(a.design_refused for a in agents)


def test_several_differing_designs_are_bounded(paper):
    bus = MemoryBus()
    coordinator = Coordinator(paper.system, paper.design, Plant(paper.system), paper.protocol, RUN)
    plant = CoordinatorNode(bus, coordinator, paper.digest, lambda record: None)
    for name in paper.names:
        plant.mismatched[name] = Ready(run=RUN, sender=name, design_digest="f" * 64, scenario="s" * 64, horizon=99)
    text = plant.design_mismatch(paper.names)
    assert text.startswith("4 designs differ from this plant's: agent 1 uses design ")
    assert "agent 3 uses design" in text and "agent 4 uses design" not in text and "and 1 more" in text
    assert f"this plant uses design {paper.digest} (horizon 10)" in text
    stops = []
    bus.subscribe(keys.control(RUN), lambda key, payload: stops.append(decode(payload)))
    plant.fail(f"plant: {text}; " + "agents not ready " * 100)
    bus.run(lambda: bool(stops), timeout=1.0)
    assert len(stops[0].reason) == MAX_REASON and design_claim("1", "f" * 64) in stops[0].reason

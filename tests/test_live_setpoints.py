"""Setpoints changed while a run goes on (docs/protocol.md, "Setpoints while a run goes on"): the
coordinator's checks (``Coordinator.on_setpoint``), where a request lands in the schedule and the
records, and the node's handling of requests on the in-memory bus. The request's side (values,
names) is tested here too; over Zenoh, tests/test_e2e_live_setpoints.py."""
from __future__ import annotations

import math

import numpy as np
import pytest

import dmpc
from dmpc.agents.process import agent_node
from dmpc.bus import keys
from dmpc.bus.codec import decode, encode
from dmpc.bus.memory import MemoryBus
from dmpc.bus.messages import Setpoint, SetpointAnswer, State
from dmpc.coordinator.process import coordinator_node
from dmpc.plant.dynamics import Plant
from dmpc.plant.role import PlantRole
from dmpc.runtime.inprocess import build_run
from dmpc.runtime.setpoints import SetpointInputError, components, scenario_subsystem, send_setpoint
from dmpc.scenario import load_scenario
from dmpc.security.rejects import UNKNOWN
from dmpc.setup import prepare
from tests.helpers.reference import PAPER

RUN = "live"
FREE = np.full(2, math.nan)


def prepared_paper(steps: int = 30, **fields):
    return prepare(load_scenario(PAPER, {"steps": steps, **fields}))


@pytest.fixture(scope="module")
def paper():
    return prepared_paper()


def request(x=(1.0, math.nan), u=(), subsystem="1", run=RUN, sender="ops", id_=7) -> Setpoint:
    return Setpoint(run=run, sender=sender, id=id_, subsystem=subsystem, x=np.array(x, dtype=float),
                    u=np.array(u, dtype=float))


def run_until(run, k: int) -> None:
    """Step the in-memory run until the coordinator works on step k."""
    assert run.bus.run(until=lambda: run.coordinator.coordinator.k >= k)


# ------------------------------------------------------------------------------ the coordinator
def test_a_request_holds_from_the_next_step_and_the_records_show_it(paper):
    records = []
    run = build_run(paper, records.append, run_id=RUN)
    run_until(run, 5)
    coordinator = run.coordinator.coordinator
    answer = coordinator.on_setpoint(request(id_=11))
    assert answer == SetpointAnswer(run=RUN, id=11, subsystem="1", accepted=True, k=6, reason="")
    run.bus.run(until=lambda: run.coordinator.finished)
    assert [entry.at for entry in coordinator.tracker.schedule.entries] == [6]
    assert coordinator.tracker.schedule.entries[0].source == "ops"
    assert records[5].note == "setpoint from ops (id 11): subsystem 1 x = [1, free], u free from step 6"
    assert all("setpoint" not in rec.note for i, rec in enumerate(records) if i != 5)
    requested = np.array([rec.tracking.request.x for rec in records])
    assert np.isnan(requested[:6]).all()
    assert (requested[6:, 0] == 1.0).all() and np.isnan(requested[6:, 1:]).all()


def test_a_second_request_of_the_same_step_holds_and_an_empty_one_frees_the_subsystem(paper):
    records = []
    run = build_run(paper, records.append, run_id=RUN)
    run_until(run, 3)
    coordinator = run.coordinator.coordinator
    assert coordinator.on_setpoint(request(x=(1.0, math.nan))).k == 4
    assert coordinator.on_setpoint(request(x=(0.5, math.nan), id_=8)).k == 4
    run_until(run, 8)
    assert coordinator.on_setpoint(request(x=(), u=(), id_=9)).k == 9
    run.bus.run(until=lambda: run.coordinator.finished)
    x11 = np.array([rec.tracking.request.x[0] for rec in records])
    assert (x11[4:9] == 0.5).all() and np.isnan(x11[9:]).all()
    assert "x free, u free from step 9" in records[8].note


@pytest.mark.parametrize("msg, reason", [
    (request(run="other"), "wrong run id 'other' (this run is 'live')"),
    (request(subsystem="9"), "unknown subsystem '9' (known: 1, 2, 3, 4)"),
    (request(x=(1.0,)), "x: expected 2 entries (n_i = 2 states of subsystem '1') or none, got 1"),
    (request(u=(1.0, 2.0)), "u: expected 1 entries (m_i = 1 inputs of subsystem '1') or none, got 2"),
    (request(u=(3.0,)), "u[0]: the target 3 of subsystem '1' is outside U_i [-2.5, 2.5]"),
    (request(u=(-2.6,)), "u[0]: the target -2.6 of subsystem '1' is outside U_i [-2.5, 2.5]"),
    (request(x=(math.inf, 0.0)), "x[0]: expected a finite number up to 1e+12 in size, or NaN for a free one"),
    (request(x=(0.0, 1e13)), "x[1]: expected a finite number up to 1e+12 in size"),
    (Setpoint(run=RUN, sender="ops", id=1, subsystem="1", x=object(), u=np.zeros(0)), "malformed: TypeError"),
])
def test_a_request_that_cannot_be_taken_is_refused_and_changes_nothing(paper, msg, reason):
    records = []
    run = build_run(paper, records.append, run_id=RUN)
    run_until(run, 2)
    coordinator = run.coordinator.coordinator
    answer = coordinator.on_setpoint(msg)
    assert not answer.accepted and answer.k == -1 and answer.reason.startswith(reason)
    assert answer.id == msg.id and answer.run == RUN
    assert not coordinator.tracker.schedule and not coordinator.tracker.active
    run.bus.run(until=lambda: run.coordinator.finished)
    assert all(not rec.note for rec in records[1:])


def test_a_value_outside_a_box_of_states_is_refused_in_the_scenarios_words():
    boxed = prepared_paper(steps=5, **{"subsystems.0.state": {"lower": [-5, -5], "upper": [5, 5]}})
    run = build_run(boxed, lambda rec: None, run_id=RUN)
    answer = run.coordinator.coordinator.on_setpoint(request(x=(math.nan, 6.0)))
    assert answer.reason == "x[1]: the target 6 of subsystem '1' is outside X_i [-5, 5]"
    assert run.coordinator.coordinator.on_setpoint(request(x=(4.5, math.nan))).accepted


def test_a_method_without_setpoints_a_finished_run_and_a_decided_last_step_refuse():
    fixed = build_run(prepared_paper(steps=5, **{"options.method": "fixed-box"}), lambda rec: None, run_id=RUN)
    assert fixed.coordinator.coordinator.on_setpoint(request()).reason == (
        "method 'fixed-box' does not track setpoints (methods that do: tv-box, tv-box-opt, tv-box-coop, centralized)")
    run = build_run(prepared_paper(steps=5), lambda rec: None, run_id=RUN)
    run_until(run, 4)  # the last step: its successor's target is decided at its end, and no step uses it
    assert run.coordinator.coordinator.on_setpoint(request()).reason == (
        "too late: the run's last step (4) is already decided")
    run.bus.run(until=lambda: run.coordinator.finished)
    assert run.coordinator.coordinator.on_setpoint(request()).reason == "the run is finished"


def test_before_the_run_starts_a_request_holds_from_step_1(paper):
    run = build_run(paper, lambda rec: None, run_id=RUN)
    assert run.coordinator.coordinator.on_setpoint(request()).k == 1


def test_while_a_plant_outside_measures_a_request_holds_a_step_later_and_is_noted_in_the_decided_step(paper):
    bus, records = MemoryBus(), []
    for name in paper.names:
        agent_node(paper, name, bus, RUN).announce()
    PlantRole(bus, Plant(paper.system), paper.system, RUN).announce()
    node = coordinator_node(paper, bus, RUN, records.append, None, plant_timeout=5.0)
    node.announce()
    coordinator = node.coordinator
    assert bus.run(until=lambda: coordinator.k == 3 and coordinator._pending is not None, timeout=30)
    assert coordinator.on_setpoint(request()).k == 5
    assert bus.run(until=lambda: node.finished, timeout=60)
    assert records[3].note == "setpoint from ops (id 7): subsystem 1 x = [1, free], u free from step 5"
    requested = np.array([rec.tracking.request.x[0] for rec in records])
    assert np.isnan(requested[:5]).all() and (requested[5:] == 1.0).all()


# ------------------------------------------------------------------------------ the node
class Operator:
    """A supervisory program on the in-memory bus: sends requests, keeps the answers."""

    def __init__(self, bus: MemoryBus, sender: str = "ops") -> None:
        self.bus, self.sender, self.answers = bus, sender, []
        bus.subscribe(keys.setpoint_answer(RUN, sender), lambda key, payload: self.answers.append(decode(payload)))

    def send(self, msg: Setpoint | bytes, key: str | None = None) -> None:
        self.bus.publish(key or keys.setpoint(RUN, self.sender), msg if isinstance(msg, bytes) else encode(msg))


def test_the_node_answers_each_request_and_the_state_follows(caplog):
    prepared = prepared_paper(steps=60)
    records = []
    run = build_run(prepared, records.append, run_id=RUN)
    operator = Operator(run.bus)
    run_until(run, 10)
    operator.send(request(id_=1))
    operator.send(request(u=(9.0,), id_=2))
    run.bus.run(until=lambda: run.coordinator.finished)
    assert [(a.id, a.accepted, a.k) for a in operator.answers] == [(1, True, 11), (2, False, -1)]
    assert operator.answers[1].reason == "u[0]: the target 9 of subsystem '1' is outside U_i [-2.5, 2.5]"
    assert abs(records[-1].x_next[0] - 1.0) < 1e-3
    assert not any(rec.fallback[i] for rec in records for i in range(4))
    assert run.coordinator.rejected == {}
    logged = [r.getMessage() for r in caplog.records if "setpoint request" in r.getMessage()]
    assert logged == ["coordinator: setpoint request 1 from ops for subsystem 1 accepted from step 11",
                      "coordinator: setpoint request 2 from ops for subsystem 1 refused: u[0]: the target 9 of "
                      "subsystem '1' is outside U_i [-2.5, 2.5]"]


def test_bad_payloads_are_counted_and_never_answered(paper):
    run = build_run(paper, lambda rec: None, run_id=RUN)
    operator = Operator(run.bus)
    run_until(run, 2)
    operator.send(b"\x92\x01")  # not a message
    operator.send(request(sender="someone-else"))  # the sender is not its key's
    operator.send(request(sender="bad name"), key=keys.setpoint(RUN, "bad name"))  # not a key chunk
    operator.send(encode(State(run=RUN, k=0, sender="ops", x={"1": np.zeros(2)})))  # another message on the key
    run.bus.run(until=lambda: run.coordinator.finished)
    assert operator.answers == []
    assert run.coordinator.rejected == {UNKNOWN: 4}
    assert not run.coordinator.coordinator.tracker.schedule


def test_a_request_sent_as_a_query_is_answered_by_its_reply_and_a_dropped_one_ends_without(paper):
    run = build_run(paper, lambda rec: None, run_id=RUN)
    published = Operator(run.bus)  # hears what is published on setpoint-answer/ops: nothing, for queries
    run_until(run, 4)
    replies: list = []
    run.bus.ask(keys.setpoint(RUN, "ops"), encode(request(id_=21)), replies.append)
    run.bus.ask(keys.setpoint(RUN, "ops"), encode(request(sender="someone-else", id_=22)), replies.append)
    run.bus.ask(keys.setpoint(RUN, "ops"), b"\x92\x01", replies.append)
    run.bus.run(until=lambda: len(replies) == 3)
    assert decode(replies[0]) == SetpointAnswer(run=RUN, id=21, subsystem="1", accepted=True, k=5, reason="")
    assert replies[1:] == [None, None]  # dropped (and counted): the query ends without a reply
    assert run.coordinator.rejected == {UNKNOWN: 2}
    run.bus.run(until=lambda: run.coordinator.finished)
    assert published.answers == []


# ------------------------------------------------------------------------------ the request's side
def test_components_by_position_and_by_name():
    scenario = dmpc.load_scenario({"name": "two", "subsystems": [
        {"name": "room", "A": [[0.9, 0.0], [0.0, 0.8]], "B": [[0.1], [0.2]], "Q": [[1, 0], [0, 1]], "R": [[1]],
         "input": {"lower": [-1], "upper": [1]}, "x0": [0.1, 0.0],
         "states": [{"name": "Ta"}, {"name": "Tw"}], "inputs": [{"name": "heat"}]}]})
    spec = scenario_subsystem(scenario, "room")
    assert np.array_equal(components([1.0, None], "x", "x", "room"), [1.0, math.nan], equal_nan=True)
    assert components(None, "x", "x", "room").shape == (0,)
    assert np.array_equal(components({"Tw": 1.5}, "x", "x", "room", spec), [math.nan, 1.5], equal_nan=True)
    assert np.array_equal(components({"heat": 0.5}, "u", "u", "room", spec), [0.5])
    with pytest.raises(SetpointInputError, match="subsystem 'room' has no state 'Tx' \\(it has Ta, Tw\\)"):
        components({"Tx": 1.0}, "x", "--x", "room", spec)
    with pytest.raises(SetpointInputError, match="--x: states by name need the scenario"):
        components({"Ta": 1.0}, "x", "--x", "room")
    with pytest.raises(SetpointInputError, match="x: expected 2 entries \\(n_i = 2 states of subsystem 'room'\\), got 3"):
        components([1, 2, 3], "x", "x", "room", spec)
    with pytest.raises(SetpointInputError, match=r"x\[1\]: expected a finite number"):
        components([1, math.inf], "x", "x", "room")
    with pytest.raises(SetpointInputError, match=r"x\[0\]: expected a number or None"):
        components(["warm"], "x", "x", "room")
    with pytest.raises(SetpointInputError, match="no subsystem 'kitchen' in scenario 'two' \\(subsystems: room\\)"):
        scenario_subsystem(scenario, "kitchen")
    paper = scenario_subsystem(load_scenario(PAPER), "1")
    with pytest.raises(SetpointInputError, match="names need the subsystem's 'states' \\(subsystem '1' names none\\)"):
        components({"x1": 1.0}, "x", "x", "1", paper)


@pytest.mark.parametrize("kwargs, match", [
    ({"connect": "tcp/127.0.0.1"}, "bad Zenoh endpoint"),
    ({"connect": []}, "connect: the coordinator's endpoint is needed"),
    ({"run_id": "a/b"}, "run id 'a/b' must be"),
    ({"sender": ""}, "sender name '' must be"),
    ({"subsystem": ""}, "subsystem: expected a subsystem's name"),
    ({"tls_dir": "/nonexistent-dir"}, "--tls /nonexistent-dir: no such directory"),
    ({"timeout": 0}, "timeout: expected a positive number"),
])
def test_a_request_that_cannot_be_sent_fails_before_connecting(kwargs, match):
    args = {"connect": "tcp/127.0.0.1:7447", "run_id": RUN, "subsystem": "1", "sender": "ops", **kwargs}
    with pytest.raises(SetpointInputError, match=match):
        send_setpoint(args.pop("connect"), args.pop("run_id"), args.pop("subsystem"), FREE, np.zeros(0), **args)


def test_the_python_function_says_when_nothing_answers_and_refuses_what_cannot_be_sent():
    import zenoh

    from dmpc.bus.session import free_tcp_port, session_config

    port = free_tcp_port()
    with pytest.raises(dmpc.SetpointUnanswered, match="no answer from the coordinator of run nobody: cannot open"):
        dmpc.setpoint(f"tcp/127.0.0.1:{port}", "nobody", "1", x=[1.0, None], timeout=0.3)
    with zenoh.open(session_config(listen=[f"tcp/127.0.0.1:{port}"])):
        with pytest.raises(dmpc.SetpointUnanswered, match=f"^not authorised or no run listening: no answer from the "
                                                          f"coordinator of run nobody at tcp/127.0.0.1:{port} within 0.3 s "):
            dmpc.setpoint(f"tcp/127.0.0.1:{port}", "nobody", "1", x=[1.0, None], timeout=0.3)
    with pytest.raises(ValueError, match="connect: tls/127.0.0.1:1 is a TLS endpoint: give the certificate directory"):
        dmpc.setpoint("tls/127.0.0.1:1", "nobody", "1", x=[1.0, None])
    with pytest.raises(ValueError, match="x: states by name need the scenario"):
        dmpc.setpoint(f"tcp/127.0.0.1:{port}", "nobody", "1", x={"x1": 1.0})
    with pytest.raises(dmpc.DmpcError, match="no subsystem '7' in scenario 'paper'"):
        dmpc.setpoint(f"tcp/127.0.0.1:{port}", "nobody", "7", x=[1.0, None], scenario=PAPER)
    assert issubclass(dmpc.SetpointUnanswered, TimeoutError) and issubclass(dmpc.SetpointRefused, dmpc.SetpointError)

"""A live setpoint's targets are computed beside the run, never on a step's path (docs/protocol.md,
"Setpoints while a run goes on"): the tracker computes the schedule's targets when it is built and
names the targets a new request needs; the coordinator's node has them computed by its worker and
takes the request at the first step boundary after they are known; over Zenoh, a target solve that
does not end holds up no step. Nothing here is timed: the tests wait for events."""
from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from dmpc.agents.process import agent_node
from dmpc.bus import keys
from dmpc.bus.codec import decode, encode
from dmpc.bus.messages import Setpoint
from dmpc.bus.session import free_tcp_port, session_config
from dmpc.bus.zenoh_bus import ZenohBus
from dmpc.coordinator.process import coordinator_node
from dmpc.methods import terminal_policy
from dmpc.plant.models import make_plant
from dmpc.runtime.inprocess import build_run
from dmpc.scenario import load_scenario
from dmpc.setup import prepare
from dmpc.tracking.schedule import SetpointEntry
from dmpc.tracking.targets import Request, TargetSpace
from dmpc.tracking.tracker import Tracker
from tests.helpers.reference import PAPER

RUN = "beside"
FREE = np.full(2, math.nan)


@pytest.fixture(scope="module")
def paper():
    return prepare(load_scenario(PAPER, {"steps": 40}))


def request(x=(1.0, math.nan), u=(), subsystem="1", sender="ops", id_=7) -> Setpoint:
    return Setpoint(run=RUN, sender=sender, id=id_, subsystem=subsystem, x=np.array(x, dtype=float),
                    u=np.array(u, dtype=float))


def tracker_of(prepared, entries=()) -> Tracker:
    policy = terminal_policy(prepared.method, prepared.system, prepared.design)
    return Tracker(prepared.system, prepared.design.terminal, policy.closed_loop, prepared.design.gains.K_global(),
                   tuple(entries))


def counted_targets(monkeypatch) -> list[Request]:
    """Every request whose target TargetSpace computes from now on (a QP: one that asks for something)."""
    seen: list[Request] = []
    original = TargetSpace.target

    def target(space, request):
        if not request.is_free:
            seen.append(request)
        return original(space, request)

    monkeypatch.setattr(TargetSpace, "target", target)
    return seen


# ------------------------------------------------------------------------------ the tracker (pure)
def test_the_schedules_targets_are_computed_when_the_tracker_is_built(paper, monkeypatch):
    seen = counted_targets(monkeypatch)
    entries = (SetpointEntry(5, 0, np.array([1.0, np.nan]), np.array([np.nan])),
               SetpointEntry(12, 2, np.array([0.5, np.nan]), np.array([np.nan])),
               SetpointEntry(20, 0, FREE.copy(), np.array([np.nan])))
    tracker = tracker_of(paper, entries)
    assert len(seen) == 3  # {1}, {1, 3}, {3}: step 0 asks for nothing
    assert tracker.unknown() == []
    eta = np.zeros(paper.system.n)
    for k in range(30):
        tracker.step(k)
        tracker.advance(k + 1, eta)
    assert len(seen) == 3  # no step computed a target


def test_unknown_names_what_a_new_entry_makes_from_its_step_on_and_learn_keeps_it(paper, monkeypatch):
    later = SetpointEntry(20, 2, np.array([0.5, np.nan]), np.array([np.nan]))
    tracker = tracker_of(paper, [later])
    new = SetpointEntry(8, 0, np.array([1.0, np.nan]), np.array([np.nan]))
    unknown = tracker.unknown([new])
    x11 = [r.x[0] for r in unknown]
    x31 = [r.x[4] for r in unknown]
    assert x11 == [1.0, 1.0] and math.isnan(x31[0]) and x31[1] == 0.5  # at 8: {1}; at 20: {1, 3}
    assert len(tracker.unknown([SetpointEntry(25, 0, np.array([1.0, np.nan]), np.array([np.nan]))])) == 1
    tracker.learn((r, tracker.space.target(r)) for r in unknown)
    assert tracker.unknown([new]) == []
    seen = counted_targets(monkeypatch)
    tracker.add(new)
    eta = np.zeros(paper.system.n)
    for k in range(30):
        tracker.step(k)
        tracker.advance(k + 1, eta)
    assert seen == []


# ------------------------------------------------------------------------------ the node's queue
class HeldWorker:
    """A target worker that computes a batch only when the test says so (on the bus's thread)."""

    def __init__(self, space: TargetSpace) -> None:
        self.space = space
        self.jobs: list = []
        self.closed = False

    def submit(self, requests, done) -> None:
        self.jobs.append((requests, done))

    def finish(self) -> None:
        requests, done = self.jobs.pop(0)
        done([(r, self.space.target(r)) for r in requests], "")

    def close(self) -> None:
        self.closed = True


class Operator:
    def __init__(self, bus, sender: str = "ops") -> None:
        self.bus, self.sender, self.answers = bus, sender, []
        bus.subscribe(keys.setpoint_answer(RUN, sender), lambda key, payload: self.answers.append(decode(payload)))

    def send(self, msg: Setpoint) -> None:
        self.bus.publish(keys.setpoint(RUN, self.sender), encode(msg))


def held_run(prepared):
    records: list = []
    run = build_run(prepared, records.append, run_id=RUN)
    worker = HeldWorker(run.coordinator.coordinator.tracker.space)
    run.coordinator.targets = worker  # the in-memory bus has none: this one waits for the test
    return run, worker, records, Operator(run.bus)


def test_requests_wait_for_their_targets_and_are_taken_in_order_at_the_boundary_after(paper):
    run, worker, records, operator = held_run(paper)
    coordinator = run.coordinator.coordinator
    run.bus.run(until=lambda: coordinator.k >= 5)
    operator.send(request(id_=1))
    operator.send(request(x=(0.5, math.nan), subsystem="3", id_=2))
    operator.send(request(x=(), u=(9.0,), id_=3))  # refused at once, whatever waits
    run.bus.run(until=lambda: coordinator.k >= 9)
    assert [(a.id, a.accepted, a.k) for a in operator.answers] == [(3, False, -1)]
    assert len(worker.jobs) == 1  # request 1's target; request 2 waits behind it
    assert not coordinator.tracker.schedule  # nothing taken while the targets are unknown
    taken_at: list[int] = []

    def finish() -> None:
        taken_at.append(coordinator.k + 1)  # the first step whose target is not decided yet
        worker.finish()

    run.bus.call_later(0.0, finish)
    run.bus.run(until=lambda: len(operator.answers) == 2)
    assert len(worker.jobs) == 1  # request 2's targets: {1, 3}, now that request 1 is in the schedule
    assert [r.x[[0, 4]].tolist() for r in worker.jobs[0][0]] == [[1.0, 0.5]]
    run.bus.run(until=lambda: coordinator.k >= taken_at[0] + 3)
    run.bus.call_later(0.0, finish)
    run.bus.run(until=lambda: run.coordinator.finished)
    K1, K2 = taken_at
    assert K1 >= 10 and K2 >= K1 + 3
    assert [(a.id, a.accepted, a.k) for a in operator.answers[1:]] == [(1, True, K1), (2, True, K2)]
    assert records[K1 - 1].note == f"setpoint from ops (id 1): subsystem 1 x = [1, free], u free from step {K1}"
    assert records[K2 - 1].note == f"setpoint from ops (id 2): subsystem 3 x = [0.5, free], u free from step {K2}"
    requested = np.array([rec.tracking.request.x for rec in records])
    assert np.isnan(requested[:K1]).all() and (requested[K1:, 0] == 1.0).all()
    assert np.isnan(requested[:K2, 4]).all() and (requested[K2:, 4] == 0.5).all()
    assert worker.jobs == [] and worker.closed


def test_a_request_whose_targets_are_known_is_taken_at_once_and_later_ones_wait_behind_a_batch(paper):
    run, worker, records, operator = held_run(paper)
    coordinator = run.coordinator.coordinator
    run.bus.run(until=lambda: coordinator.k >= 3)
    operator.send(request(x=(), id_=1))  # asks for nothing: the origin, no target to compute
    run.bus.run(until=lambda: bool(operator.answers))
    assert operator.answers[0].accepted and worker.jobs == []
    operator.send(request(id_=2))
    operator.send(request(x=(), id_=3))  # would need nothing, but arrived after 2: it waits behind it
    run.bus.run(until=lambda: coordinator.k >= 8)
    assert [a.id for a in operator.answers] == [1]
    run.bus.call_later(0.0, worker.finish)
    run.bus.run(until=lambda: len(operator.answers) == 3)
    assert [(a.id, a.accepted) for a in operator.answers] == [(1, True), (2, True), (3, True)]
    assert operator.answers[1].k == operator.answers[2].k  # taken at the same boundary, in their order


def test_requests_still_waiting_when_the_run_ends_are_refused(paper):
    run, worker, records, operator = held_run(prepare(load_scenario(PAPER, {"steps": 12})))
    coordinator = run.coordinator.coordinator
    run.bus.run(until=lambda: coordinator.k >= 5)
    operator.send(request(id_=4))
    run.bus.run(until=lambda: run.coordinator.finished)
    run.bus.run(until=lambda: bool(operator.answers))  # sent as the run stops
    assert [(a.id, a.accepted, a.k, a.reason) for a in operator.answers] == [(4, False, -1, "the run is finished")]
    assert not coordinator.tracker.schedule and worker.closed


# ------------------------------------------------------------------------------ over Zenoh
def test_over_zenoh_a_target_solve_that_does_not_end_holds_up_no_step(monkeypatch):
    """The target's solve is blocked until three more steps have completed: computed on the step's
    path, it would hold up the very steps it waits for. The request is then taken at the boundary
    after its target is known, the answer says which step, and the records agree."""
    prepared = prepare(load_scenario(PAPER, {"steps": 400}))
    gate = threading.Event()
    solved_on: list[int] = []
    original = TargetSpace.target

    def blocked_target(space, request):
        if request.is_free:  # the origin: no QP
            return original(space, request)
        solved_on.append(threading.get_ident())
        assert gate.wait(60), "the steps stopped while the target was computed"
        return original(space, request)

    monkeypatch.setattr(TargetSpace, "target", blocked_target)
    records: list = []
    sent: list[int] = []
    taken: list = []

    def on_step(record) -> None:
        records.append(record)
        if record.k == 5:
            bus.publish(keys.setpoint(RUN, "ops"), encode(request(id_=9)))
            sent.append(record.k)
        if sent and record.k >= sent[0] + 3:
            gate.set()

    bus = ZenohBus(session_config(listen=[f"tcp/127.0.0.1:{free_tcp_port()}"]), open_timeout=10, shared=True)
    try:
        bus.subscribe(keys.setpoint_answer(RUN, "ops"), lambda key, payload: taken.append(decode(payload)))
        node = coordinator_node(prepared, bus, RUN, on_step, make_plant(prepared))
        assert node.targets is not None  # a Zenoh bus: targets beside the run
        agents = [agent_node(prepared, name, bus, RUN) for name in prepared.names]
        node.announce()
        for agent in agents:
            agent.announce()
        assert bus.run(until=lambda: bool(taken) or node.finished, timeout=120)
    finally:
        bus.close()
    assert solved_on and threading.get_ident() not in solved_on  # never on the run's thread
    answer = taken[0]
    assert answer.accepted and answer.k >= sent[0] + 5  # the steps 6, 7 and 8 completed meanwhile
    assert "setpoint from ops (id 9)" in records[answer.k - 1].note
    assert all("setpoint" not in rec.note for rec in records[:answer.k - 1])
    assert not any(f for rec in records for f in rec.fallback)

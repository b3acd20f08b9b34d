"""Fuzzing the coordinator and the agent and plant nodes with hostile message sequences.

Random bytes, truncated messages, wrong types, NaN and infinities, wrong shapes, stale and
future steps and rounds, unknown senders, senders that do not match their key, duplicates
with other content, deadlines and lost agents, in any order. No exception may escape, and the
QP and the plant are wrapped so that every call is checked: they only ever see validated data.

Valid messages carry values of at most ``VALID`` in size; everything invalid carries values of
at least ``BAD`` (or NaN/inf), so any invalid value that slipped through would show.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dmpc.agents.controller import AgentController
from dmpc.agents.node import AgentNode
from dmpc.bus import keys
from dmpc.bus.codec import DecodeError, decode, encode
from dmpc.bus.memory import MemoryBus
from dmpc.bus.messages import COORDINATOR, PlanMessage, Ready, Release, Stop
from dmpc.coordinator.barrier import Coordinator, StepCompleted
from dmpc.coordinator.node import CoordinatorNode
from dmpc.core.mpc_qp import QPStatus
from dmpc.core.steps import ProtocolOptions
from dmpc.core.trajectories import Plan
from dmpc.plant.dynamics import Plant
from dmpc.scenario import load_scenario
from dmpc.security.rejects import UNKNOWN
from dmpc.setup import prepare

RUN = "fz"
NAMES = ["1", "2", "3", "4"]
VALID = 2.0  # |u| <= 2.5 in the paper: a valid plan's input is inside U
BAD = 50.0
EVENTS = 40
FUZZ = settings(max_examples=50, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

PLAN_FAULTS = ["valid", "valid", "valid", "again", "stale_k", "future_k", "stale_it", "future_it", "wrong_run",
               "short_z", "wide_v", "nan", "inf", "huge", "unknown_status", "infeasible", "unknown_sender",
               "sender_mismatch", "bytes", "truncated"]


@pytest.fixture(scope="module")
def prepared():
    return prepare(load_scenario("scenarios/paper.yaml"))


def values(draw, shape, bad: bool = False) -> np.ndarray:
    if bad:
        return np.full(shape, draw(st.sampled_from([BAD, -3 * BAD, 1e13, np.nan, np.inf])))
    seed = draw(st.integers(0, 2**32 - 1))
    return np.random.default_rng(seed).uniform(-VALID, VALID, size=shape)


def plan_payload(draw, prepared, name: str, k: int, it: int, fault: str, key_name: str | None = None,
                 store_window: bool = False) -> tuple[str, bytes]:
    """A plan message of agent ``name`` for (k, it) with one ``fault``; returns (key, payload).

    ``store_window``: the receiver keeps plans of other steps and rounds (an agent does, for
    late and lost neighbours); a plan of another (k, round) near the current step is then a
    legitimate message, not an invalid one, and carries valid values. Far out of the window
    it is invalid and carries bad values.
    """
    N = prepared.design.horizon
    sub = prepared.system.subsystems[NAMES.index(name)]
    bad = fault not in ("valid", "infeasible")  # "again": a second copy with other (bad) content
    if store_window and fault in ("stale_k", "future_k", "stale_it", "future_it"):
        bad = False
    z, v = values(draw, (N + 1, sub.n), bad), values(draw, (N, sub.m), bad)
    fields = dict(run=RUN, k=k, round=it, sender=name, status="solved", z=z, v=v, cost=1.0, solve_time=0.001,
                  qp_iterations=10, sent_at=0.0)
    if fault == "stale_k":
        fields["k"] = max(0, k - draw(st.integers(1, 3))) if k > 0 else k + 10**6
    elif fault == "future_k":
        fields["k"] = k + draw(st.sampled_from([1, 2, 10**6, 2**53]))
    elif fault == "stale_it":
        fields["round"] = it - 1 if it > 0 else it + 500
    elif fault == "future_it":
        fields["round"] = it + draw(st.integers(1, 5000))
    elif fault == "wrong_run":
        fields["run"] = "other"
    elif fault == "short_z":
        fields["z"] = z[:-1]
    elif fault == "wide_v":
        fields["v"] = np.full((N, sub.m + 1), BAD)
    elif fault == "nan":
        fields["z"] = z.copy()
        fields["z"][draw(st.integers(0, N)), 0] = np.nan
    elif fault == "inf":
        fields["cost"] = float("inf")
    elif fault == "huge":
        fields["v"] = np.full(v.shape, 1e13)
    elif fault == "unknown_status":
        fields["status"] = draw(st.sampled_from(["SOLVED", "ok", "solved "]))
    elif fault == "infeasible":
        fields.update(status=QPStatus.INFEASIBLE.value, z=np.full(z.shape, np.nan), v=np.full(v.shape, np.nan),
                      cost=float("nan"))
    elif fault == "unknown_sender":
        fields["sender"] = key_name = draw(st.sampled_from(["9", "plant", "x" * 64]))
    elif fault == "sender_mismatch":
        fields["sender"] = draw(st.sampled_from([n for n in NAMES if n != name]))
    if store_window and fault in ("stale_k", "future_k") and abs(fields["k"] - k) > 2:
        fields["z"], fields["v"] = values(draw, z.shape, True), values(draw, v.shape, True)
    payload = encode(PlanMessage(**fields))
    if fault == "bytes":
        payload = draw(st.binary(max_size=200))
    elif fault == "truncated":
        payload = payload[:draw(st.integers(0, len(payload) - 1))]
    return keys.plan(RUN, key_name or name), payload


# ---------------------------------------------------------------------------- coordinator


class GuardedPlant:
    """Checks every input applied to the plant: right shape, finite, inside U_i."""

    def __init__(self, plant: Plant, system) -> None:
        self.plant, self.system = plant, system
        self.violations: list[str] = []
        self.steps = 0

    def __getattr__(self, name):
        return getattr(self.plant, name)

    def step(self, u):
        u = np.asarray(u)
        if u.shape != (self.system.m,) or not np.isfinite(u).all():
            self.violations.append(f"plant input {u!r}")
        else:
            for i, part in enumerate(self.system.split_input(u)):
                if not self.system.subsystems[i].input_set.contains(part, tol=1e-6):
                    self.violations.append(f"input of {NAMES[i]} outside U: {part}")
        self.steps += 1
        return self.plant.step(u)


def guarded_coordinator(prepared, steps: int = 6) -> tuple[Coordinator, GuardedPlant]:
    plant = GuardedPlant(Plant(prepared.system), prepared.system)
    options = ProtocolOptions(steps=steps, rounds=2, initial_rounds=3)
    return Coordinator(prepared.system, prepared.design, plant, options, RUN), plant


@FUZZ
@given(st.data())
def test_coordinator_survives_hostile_plans(prepared, data):
    coord, plant = guarded_coordinator(prepared)
    records = []
    reasons = set()  # why the coordinator dropped plans

    def handle(actions):
        for action in actions:
            if isinstance(action, StepCompleted):
                records.append(action.record)

    handle(coord.start())
    for _ in range(EVENTS):
        if coord.finished:
            break
        kind = data.draw(st.sampled_from(["plan"] * 6 + ["deadline", "lost", "back"]))
        if kind == "plan":
            name = data.draw(st.sampled_from(NAMES))
            # the key of a message (its true sender) is the nodes' business: see the node tests
            fault = data.draw(st.sampled_from([f for f in PLAN_FAULTS if f not in ("bytes", "truncated", "sender_mismatch")]))
            if fault == "again" and not coord.has_plan(name):
                fault = "valid"
            _, payload = plan_payload(data.draw, prepared, name, coord.k, coord.round, fault)
            try:
                msg = decode(payload)
            except DecodeError:
                msg = _unchecked_plan(payload)  # what the codec refuses goes to the barrier's own checks
            actions, reason = coord.on_plan(msg)
            handle(actions)
            if reason is not None:
                reasons.add(reason)
        elif kind == "deadline":
            k, it = coord.k + data.draw(st.integers(-1, 1)), coord.round + data.draw(st.integers(-1, 1))
            handle(coord.on_deadline(k, it))
        elif kind == "lost":
            handle(coord.on_agent_lost(data.draw(st.sampled_from(NAMES + ["9"]))))
        else:
            coord.on_agent_back(data.draw(st.sampled_from(NAMES + ["9"])))
    assert plant.violations == []
    assert plant.steps == len(records)
    for rec in records:
        for arr in (rec.x_next, rec.alpha_next, rec.u):
            assert np.isfinite(arr).all()
        assert np.isfinite(rec.beta_next)
    assert reasons <= {"wrong run", "unknown sender", "stale", "future", "wrong shape", "unknown status",
                                   "non-finite plan", "out of range"}


def _unchecked_plan(payload: bytes) -> PlanMessage:
    """A PlanMessage as a buggy decoder would pass it on (NaN/inf kept), to test the barrier's own checks."""
    import msgpack

    b = msgpack.unpackb(payload, raw=False)
    arr = lambda d: np.frombuffer(d["data"], dtype="<f8").reshape(d["shape"])
    return PlanMessage(run=b["run"], k=b["k"], round=b["iteration"], sender=b["sender"], status=b["status"],
                       z=arr(b["z"]), v=arr(b["v"]), cost=b["cost"], solve_time=b["solve_time"],
                       qp_iterations=b["qp_iterations"], sent_at=b["sent_at"])


def _step_with_plans_outside_U(prepared) -> tuple[Coordinator, GuardedPlant]:
    """One step in which every agent answers every round with inputs BAD, outside U."""
    coord, plant = guarded_coordinator(prepared, steps=1)
    coord.start()
    N = prepared.design.horizon
    while not coord.finished:  # the same plans every round: converged after the second
        for name in NAMES:
            sub = prepared.system.subsystems[NAMES.index(name)]
            coord.on_plan(PlanMessage(run=RUN, k=0, round=coord.round, sender=name, status="solved",
                                      z=np.zeros((N + 1, sub.n)), v=np.full((N, sub.m), BAD), cost=0.0,
                                      solve_time=0.0, qp_iterations=1))
    return coord, plant


def test_plans_outside_U_never_reach_the_plant(prepared):
    coord, plant = _step_with_plans_outside_U(prepared)
    assert plant.steps == 1 and plant.violations == []
    assert set(coord.inputs_refused) == set(NAMES)


def test_coordinator_guard_catches_an_invalid_input(prepared, monkeypatch):
    """The guard is not a tautology: a plan outside U that the coordinator accepts shows up."""
    monkeypatch.setattr("dmpc.coordinator.barrier.input_excess", lambda input_set, v: -np.inf)
    coord, plant = _step_with_plans_outside_U(prepared)
    assert plant.steps == 1 and coord.inputs_refused == {}
    assert any("outside U" in v for v in plant.violations)


# ---------------------------------------------------------------------------- agent node


class GuardedController:
    """The real controller, with every solve's inputs checked first."""

    def __init__(self, controller: AgentController, prepared) -> None:
        self.controller = controller
        self.prepared = prepared
        self.violations: list[str] = []
        self.calls: list[tuple[int, dict]] = []

    def __getattr__(self, name):
        return getattr(self.controller, name)

    def answer(self, *args, **kwargs):
        """The controller's own answer, with its solve going through the check below."""
        return AgentController.answer(self, *args, **kwargs)

    def solve(self, k, states, alpha, beta, plans):
        c, system, N = self.controller, self.prepared.system, self.prepared.design.horizon
        group = set(system.neighbours[c.index])
        problems = []
        if type(k) is not int or k < 0:
            problems.append(f"k={k!r}")
        if set(states) != group:
            problems.append(f"states of {sorted(states)}")
        for j, x in states.items():
            if x.shape != (system.subsystems[j].n,) or not np.all(np.abs(x) <= VALID):
                problems.append(f"state {j}: {x}")
        if alpha.shape != (c.n,) or not np.all(np.abs(alpha) <= VALID):
            problems.append(f"alpha {alpha}")
        if not 0 <= beta <= VALID:
            problems.append(f"beta {beta}")
        if set(plans) != set(c.neighbours):
            problems.append(f"plans of {sorted(plans)}")
        for j, plan in plans.items():
            if plan is None:
                continue
            sub = system.subsystems[j]
            if (not isinstance(plan, Plan) or plan.z.shape != (N + 1, sub.n) or plan.v.shape != (N, sub.m)
                    or not np.all(np.abs(plan.z) <= VALID) or not np.all(np.abs(plan.v) <= VALID)):
                problems.append(f"plan of {j}")
        self.violations.extend(problems)
        self.calls.append((k, states))
        return self.controller.solve(k, states, alpha, beta, plans)


def release_payload(draw, prepared, name: str, k: int, it: int, fault: str) -> tuple[str, bytes]:
    """A release of (k, it) with one ``fault``, as agent ``name`` receives it; returns (key, payload)."""
    system = prepared.system
    M, n = system.M, system.n
    x = values(draw, (n,))
    if fault == "nan":
        x[draw(st.integers(0, n - 1))] = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    assumed = np.full((M, 2), -1, dtype=np.int64)
    if not (k == 0 and it == 0):
        for j in range(M):
            assumed[j] = draw(st.sampled_from([(-1, -1), (k, it - 1) if it > 0 else (k - 1, 0), (max(k - 1, 0), 0)]))
    fields = dict(run=RUN, k=k, round=it, x=x, centres=values(draw, (n,)),
                  sizes=np.full(M, draw(st.floats(0, VALID))), assumed=assumed)
    i = NAMES.index(name)
    others = [NAMES[j] for j in system.neighbours[i] if j != i]
    if fault == "wrong_sender":
        fields["sender"] = "1"
    elif fault == "wrong_run":
        fields["run"] = "other"
    elif fault == "wrong_shape":
        fields["x"], fields["centres"] = np.full(n + 1, BAD), np.full(n + 1, BAD)
    elif fault == "wrong_count":
        fields["sizes"], fields["assumed"] = np.full(M + 1, BAD), np.zeros((M + 1, 2), dtype=np.int64)
    elif fault == "future_far":
        fields["k"] = k + 10**6
    elif fault == "future_ref":
        assumed[[NAMES.index(o) for o in others]] = (k + 1, 0)
    elif fault == "skipped":
        fields["skipped"] = (name,)
    elif fault == "bad_provided":
        fields["provided"] = {others[0]: (np.full((3, 2), BAD), np.full((2, 1), BAD))}
    elif fault == "unknown_provided":
        N = prepared.design.horizon
        fields["provided"] = {"9": (np.full((N + 1, 2), BAD), np.full((N, 1), BAD))}
    elif fault == "huge_size":
        fields["sizes"] = np.full(M, np.inf)
    payload = encode(Release(**fields))
    if fault == "truncated":
        payload = payload[:draw(st.integers(0, len(payload) - 1))]
    elif fault == "bytes":
        payload = draw(st.binary(max_size=200))
    return keys.release(RUN), payload


RELEASE_FAULTS = ["valid", "valid", "valid", "again", "nan", "wrong_sender", "wrong_run", "wrong_shape",
                  "wrong_count", "future_far", "future_ref", "skipped", "bad_provided", "unknown_provided",
                  "huge_size", "truncated", "bytes"]


@FUZZ
@given(st.data())
def test_agent_node_survives_hostile_messages(prepared, data):
    name = "2"
    controller = GuardedController(AgentController(prepared.system, prepared.design, NAMES.index(name)), prepared)
    bus = MemoryBus()
    sent = []
    bus.subscribe(keys.plan(RUN, name), lambda key, payload: sent.append(payload))
    node = AgentNode(bus, controller, NAMES, RUN, "digest", plan_wait=data.draw(st.sampled_from([None, 0.5])))
    bus.declare_alive(keys.alive(RUN, keys.COORDINATOR_ROLE))
    node.announce()
    bus.run(lambda: False, timeout=0.1)
    k, it = 0, 0
    history: list[tuple[str, bytes]] = []
    for _ in range(EVENTS):
        kind = data.draw(st.sampled_from(["release"] * 3 + ["plan"] * 3 + ["again", "stop", "garbage", "alive"]))
        if kind == "release":
            if data.draw(st.booleans()):
                k, it = (k, it + 1) if data.draw(st.booleans()) else (k + 1, 0)
            fault = data.draw(st.sampled_from(RELEASE_FAULTS))
            if fault == "again" and history:
                key, payload = data.draw(st.sampled_from(history))
            else:
                key, payload = release_payload(data.draw, prepared, name, k, it, "valid" if fault == "again" else fault)
        elif kind == "plan":
            other = data.draw(st.sampled_from(["1", "3"]))
            pk, pit = max(0, k + data.draw(st.integers(-2, 1))), data.draw(st.integers(0, 2))
            fault = data.draw(st.sampled_from(PLAN_FAULTS))
            if fault == "again" and (pk, pit) not in node.plans[other]:
                fault = "valid"
            key, payload = plan_payload(data.draw, prepared, other, pk, pit, fault, store_window=True)
        elif kind == "again" and history:
            key, payload = data.draw(st.sampled_from(history))
        elif kind == "stop":
            stop = Stop(run=data.draw(st.sampled_from([RUN, "other"])), k=data.draw(st.sampled_from([0, k, 10**6])),
                        reason="finished", sender=data.draw(st.sampled_from([COORDINATOR, "1", "2"])))
            key, payload = keys.control(RUN), encode(stop)
        elif kind == "alive":
            role = data.draw(st.sampled_from([keys.COORDINATOR_ROLE, "agent-1", "agent-3", "agent-x" * 9]))
            (bus.declare_alive if data.draw(st.booleans()) else bus.drop_alive)(keys.alive(RUN, role))
            bus.run(lambda: False, timeout=0.1)
            continue
        else:
            key = data.draw(st.sampled_from([keys.release(RUN), keys.plan(RUN, "1"), keys.plan(RUN, "3"),
                                             keys.control(RUN)]))
            payload = data.draw(st.binary(max_size=300))
        history.append((key, payload))
        bus.publish(key, payload)
        bus.run(lambda: False, timeout=1.0)  # deliveries and the plan-wait timer; any exception escapes here
    assert controller.violations == []
    assert set(node.rejected) <= {COORDINATOR, "1", "3"}
    assert len(node.peers_alive) <= 3
    # every plan sent is decodable, and no (k, round) is answered twice
    answered = [(m.k, m.round) for m in map(decode, sent)]
    assert answered == sorted(set(answered))
    assert len(controller.calls) == len(sent)


def test_agent_guard_catches_an_invalid_release(prepared):
    """The guard is not a tautology: a release with out-of-bounds states that reaches the QP shows up."""
    controller = GuardedController(AgentController(prepared.system, prepared.design, 1), prepared)
    states = {j: np.full(2, BAD) for j in (0, 1, 2)}
    controller.solve(0, states, np.zeros(2), 1.0, {0: None, 2: None})
    assert controller.violations


# ---------------------------------------------------------------------------- plant node


@FUZZ
@given(st.data())
def test_plant_node_survives_hostile_messages(prepared, data):
    coord, plant = guarded_coordinator(prepared, steps=4)
    bus = MemoryBus()
    records = []
    deadline = data.draw(st.sampled_from([None, 0.5]))
    node = CoordinatorNode(bus, coord, "digest", records.append, deadline=deadline)
    node.announce()
    for name in NAMES:
        bus.declare_alive(keys.alive(RUN, keys.agent_role(name)))
    # hostile readies first: wrong digest, wrong run, unknown agents, a sender that is not its key
    for run, sender, key_name, digest in [(RUN, "1", "1", "other"), ("other", "1", "1", "digest"),
                                          (RUN, "9", "9", "digest"), (RUN, "2", "1", "digest")]:
        bus.publish(keys.ready(RUN, key_name), encode(Ready(run=run, sender=sender, design_digest=digest)))
    bus.publish(keys.ready(RUN, "x" * 60), data.draw(st.binary(max_size=100)))
    bus.run(lambda: False, timeout=0.1)
    assert not node.started and node.failure == ""
    for name in NAMES:
        bus.publish(keys.ready(RUN, name), encode(Ready(run=RUN, sender=name, design_digest="digest")))
    bus.run(lambda: node.started, timeout=1.0)
    assert node.started
    history: list[tuple[str, bytes]] = []
    for _ in range(EVENTS):
        if node.finished:
            break
        kind = data.draw(st.sampled_from(["plan"] * 6 + ["again", "ready", "alive", "garbage"]))
        if kind == "plan":
            name = data.draw(st.sampled_from(NAMES))
            fault = data.draw(st.sampled_from(PLAN_FAULTS))
            if fault == "again" and not coord.has_plan(name):
                fault = "valid"
            key, payload = plan_payload(data.draw, prepared, name, coord.k, coord.round, fault)
        elif kind == "again" and history:
            key, payload = data.draw(st.sampled_from(history))
        elif kind == "ready":
            name = data.draw(st.sampled_from(NAMES + ["7"]))
            key = keys.ready(RUN, name)
            payload = encode(Ready(run=RUN, sender=name, design_digest=data.draw(st.sampled_from(["digest", "x"]))))
        elif kind == "alive":
            role = keys.agent_role(data.draw(st.sampled_from(NAMES + ["7"])))
            (bus.declare_alive if data.draw(st.booleans()) else bus.drop_alive)(keys.alive(RUN, role))
            bus.run(lambda: False, timeout=0.1)
            continue
        else:
            key = data.draw(st.sampled_from([keys.plan(RUN, "1"), keys.plan(RUN, "zz"), keys.ready(RUN, "3")]))
            payload = data.draw(st.binary(max_size=300))
        history.append((key, payload))
        bus.publish(key, payload)
        bus.run(lambda: False, timeout=1.0)
    assert plant.violations == []
    assert node.failure == ""
    assert set(node.rejected) <= set(NAMES) | {UNKNOWN}
    assert len(records) == plant.steps

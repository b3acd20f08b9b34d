"""The Coordinator state machine (coordinator/barrier.py) without any bus.

Plans are PlanMessage objects built here from AgentController solves (dmpc.agents.controller),
driven by the coordinator's own Release actions. Expected inputs, fallbacks and plant updates
are recomputed by hand from the paper's matrices (tests/helpers/reference.py).
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from dmpc.agents.controller import AgentController
from dmpc.bus.messages import PlanMessage
from dmpc.coordinator.barrier import (
    ApplyInputs,
    Coordinator,
    PlanRefused,
    RoundOpened,
    RunFinished,
    SendRelease,
    StepCompleted,
    input_excess,
)
from dmpc.core.steps import ProtocolOptions
from dmpc.core.system import LinearSet
from dmpc.core.trajectories import Plan
from dmpc.plant.dynamics import Plant
from dmpc.scenario import load_scenario
from dmpc.setup import prepare
from tests.helpers.reference import A_II, B_II, K_PAPER, PAPER, U_BAR, block_diag, chain_matrices

RUN = "test-run"
N = 10
NAMES = ["1", "2", "3", "4"]
A_GLOBAL, B_GLOBAL = chain_matrices(4)
AK = A_GLOBAL + B_GLOBAL @ block_diag(K_PAPER)


@pytest.fixture(scope="module")
def prepared():
    return prepare(load_scenario(PAPER))


@pytest.fixture(scope="module")
def controllers(prepared):
    return [AgentController(prepared.system, prepared.design, i) for i in range(4)]


def agent_view(release, system, name: str) -> SimpleNamespace:
    """Agent ``name``'s part of a broadcast release: its neighbourhood's states by name, its centre
    and size, its neighbours' references (None for a K-rollout) and provided plans."""
    i = NAMES.index(name)
    others = [NAMES[j] for j in system.neighbours[i] if j != i]
    return SimpleNamespace(
        k=release.k, round=release.round,
        states={NAMES[j]: release.x[system.xs(j)] for j in system.neighbours[i]},
        alpha=release.centres[system.xs(i)], beta=float(release.sizes[i]),
        assumed={o: release.reference(NAMES.index(o)) for o in others},
        provided={o: release.provided[o] for o in others if o in release.provided})


class Driver:
    """Plays the agents' part: answers the coordinator's releases with controller solves."""

    def __init__(self, prepared, controllers, options: ProtocolOptions) -> None:
        self.system = prepared.system
        self.coord = Coordinator(prepared.system, prepared.design, Plant(prepared.system), options, RUN)
        self.controllers = controllers
        self.archive: dict[tuple[str, int, int], Plan] = {}
        self.releases = {}  # name -> its part of the latest release
        self.records = []
        self.rejected: dict[str, int] = {}  # the coordinator's reasons for the plans it dropped
        self.finished = False
        self.handle(self.coord.start())

    def handle(self, actions) -> list:
        for action in actions:
            if isinstance(action, SendRelease):
                for name in NAMES:
                    if name not in action.release.skipped:
                        self.releases[name] = agent_view(action.release, self.system, name)
            elif isinstance(action, StepCompleted):
                self.records.append(action.record)
            elif isinstance(action, RunFinished):
                self.finished = True
            else:
                assert isinstance(action, (RoundOpened, PlanRefused))  # a host only logs a refusal
        return actions

    def message(self, name: str, alpha=None, beta=None, **changes) -> PlanMessage:
        """The plan of agent ``name`` for its latest release (optionally with another terminal box)."""
        rel = self.releases[name]
        i = NAMES.index(name)
        plans = {}
        for other, ref in rel.assumed.items():
            j = NAMES.index(other)
            if ref is None:
                plans[j] = None
            elif other in rel.provided:
                plans[j] = Plan(ref[0], ref[1], *rel.provided[other])
            else:
                plans[j] = self.archive[(other, *ref)]
        states = {NAMES.index(n): x for n, x in rel.states.items()}
        sol = self.controllers[i].solve(rel.k, states, rel.alpha if alpha is None else alpha,
                                        rel.beta if beta is None else beta, plans)
        fields = dict(run=RUN, k=rel.k, round=rel.round, sender=name, status=sol.status.value, z=sol.z,
                      v=sol.v, cost=sol.cost, solve_time=sol.solve_time, qp_iterations=int(sol.iterations))
        fields.update(changes)
        return PlanMessage(**fields)

    def deliver(self, msg: PlanMessage) -> list:
        if msg.status in ("solved", "solved_inaccurate"):
            self.archive[(msg.sender, msg.k, msg.round)] = Plan(msg.k, msg.round, msg.z, msg.v)
        return self.handle(self.offer(msg))

    def offer(self, msg: PlanMessage) -> list:
        """The coordinator's actions for ``msg``; the reason it gives for dropping it is tallied."""
        actions, reason = self.coord.on_plan(msg)
        if reason is not None:
            self.rejected[reason] = self.rejected.get(reason, 0) + 1
        return actions

    def round(self, names=NAMES) -> list:
        """Every named agent answers the open round (all solved before any is delivered)."""
        msgs = [self.message(n) for n in names]
        actions = []
        for m in msgs:
            actions += self.deliver(m)
        return actions

    def step(self, names=NAMES):
        """Answer rounds until the current step completes; returns its record."""
        done = len(self.records)
        while len(self.records) == done:
            before = (self.coord.k, self.coord.round)
            self.round(names)
            assert (self.coord.k, self.coord.round) != before or len(self.records) > done, "round did not close"
        return self.records[-1]


def options(**kw) -> ProtocolOptions:
    return ProtocolOptions(**{"steps": 8, **kw})


def part(x, i):
    return x[2 * i:2 * i + 2]


def shifted_projected(plan: Plan, k: int, x_i: np.ndarray, i: int) -> np.ndarray:
    """clip(v*(k|k') + K_i (x_i - z*(k|k')), +-2.5) with the local K tail beyond the plan's horizon."""
    z, v = list(plan.z), list(plan.v)
    Gamma = A_II + B_II @ K_PAPER[i]
    while len(z) < k - plan.k + 1:
        z.append(Gamma @ z[-1])
    while len(v) < k - plan.k + 1:
        v.append(K_PAPER[i] @ z[len(v)])
    s = k - plan.k
    return np.clip(v[s] + K_PAPER[i] @ (x_i - z[s]), -U_BAR, U_BAR)


def check_plant_update(rec) -> None:
    np.testing.assert_allclose(rec.x_next, A_GLOBAL @ rec.x + B_GLOBAL @ rec.u, atol=1e-12)


def sigma(prepared, alpha) -> float:
    omega = prepared.design.terminal.omega
    return float(np.min((1 - omega @ alpha) / np.abs(omega).sum(axis=1)))


# ---------------------------------------------------------------- complete steps

def test_full_first_step_reproduces_the_paper(prepared, controllers):
    d = Driver(prepared, controllers, options())
    first = d.releases["2"]
    assert (first.k, first.round) == (0, 0)
    assert set(first.states) == {"1", "2", "3"}
    np.testing.assert_array_equal(first.states["2"], [2.08, 2.2])
    assert first.assumed == {"1": None, "3": None}
    np.testing.assert_array_equal(first.alpha, np.zeros(2))
    assert first.beta == 0.5
    rec = d.step()
    assert rec.k == 0 and rec.rounds > 1 and rec.max_change < 1e-9
    assert rec.fallback == [False] * 4 and rec.status == ["solved"] * 4
    np.testing.assert_allclose(rec.u, [-2.5, -2.5, 0.489, -0.472], atol=1e-3)
    np.testing.assert_allclose(rec.x_next, [3.293, 1.606, 2.008, 1.397, 1.068, -1.711, -1.283, 2.755], atol=1e-3)
    check_plant_update(rec)
    eta = np.concatenate([z[N] for z in rec.plans_z])
    np.testing.assert_allclose(rec.alpha_next, AK @ eta, atol=1e-12)
    assert rec.beta_next == pytest.approx(sigma(prepared, rec.alpha_next), abs=1e-12)
    assert rec.beta_next == pytest.approx(1.3413, abs=1e-4)
    assert rec.J == pytest.approx(102.05, abs=0.05)
    # the release of step 1 carries the new state, box and references to the final k = 0 plans
    rel = d.releases["2"]
    assert (rel.k, rel.round) == (1, 0)
    np.testing.assert_array_equal(rel.states["2"], part(rec.x_next, 1))
    np.testing.assert_array_equal(rel.alpha, part(rec.alpha_next, 1))
    assert rel.beta == rec.beta_next
    assert rel.assumed == {"1": (0, rec.rounds - 1), "3": (0, rec.rounds - 1)}


def test_single_round_step_records(prepared, controllers):
    d = Driver(prepared, controllers, options(initial_rounds=1))
    msgs = [d.message(n) for n in NAMES]
    for m in msgs[:-1]:
        assert d.deliver(m) == []  # the round waits for everybody
    d.deliver(msgs[-1])
    rec = d.records[-1]
    assert rec.rounds == 1
    np.testing.assert_array_equal(rec.u, np.concatenate([m.v[0] for m in msgs]))
    check_plant_update(rec)
    assert rec.J == pytest.approx(sum(m.cost for m in msgs))
    x = rec.x
    assert rec.S == pytest.approx(sum(part(x, i) @ part(x, i) / n for i, n in enumerate([2, 3, 3, 2])))


def test_run_finishes_after_the_last_step(prepared, controllers):
    d = Driver(prepared, controllers, options(steps=3))
    for _ in range(3):
        d.step()
    assert d.finished and d.coord.finished
    assert [r.k for r in d.records] == [0, 1, 2]
    assert d.offer(d.message("1")) == []


# ---------------------------------------------------------------- rejected messages

@pytest.fixture
def at_step_1(prepared, controllers):
    d = Driver(prepared, controllers, options())
    d.step()
    assert (d.coord.k, d.coord.round) == (1, 0)
    return d


def test_duplicate_plan_is_ignored(at_step_1):
    d = at_step_1
    m = d.message("1")
    assert d.deliver(m) == []
    assert d.deliver(m) == []
    assert d.coord.duplicates == 1
    other = d.message("1", alpha=np.array([0.3, 0.3]))  # a different plan from the same sender
    assert d.deliver(other) == []
    assert d.coord.duplicates == 2
    d.round(["2", "3", "4"])
    rec = d.records[-1]
    np.testing.assert_array_equal(rec.plans_z[0], m.z)  # the first one counts
    assert d.rejected == {}


@pytest.mark.parametrize("k_shift, it, reason", [(1, 0, "future"), (0, 1, "future"), (-1, 0, "stale")])
def test_wrong_step_or_round_is_rejected(at_step_1, k_shift, it, reason):
    d = at_step_1
    m = d.message("1", k=1 + k_shift, round=it)
    assert d.deliver(m) == []
    assert d.rejected == {reason: 1}
    d.round()  # the round is unaffected and completes with the proper plans
    assert d.records[-1].k == 1 and d.records[-1].fallback == [False] * 4


def test_unknown_sender_wrong_shape_wrong_run_non_finite(at_step_1):
    d = at_step_1
    good = d.message("1")
    bad_z = good.z.copy()
    bad_z[3, 0] = np.nan
    cases = [
        (d.message("1", sender="9"), "unknown sender"),
        (d.message("1", z=good.z[:N]), "wrong shape"),
        (d.message("1", v=np.zeros((N, 2))), "wrong shape"),
        (d.message("1", run="other"), "wrong run"),
        (d.message("1", z=bad_z), "non-finite plan"),
    ]
    for msg, _ in cases:
        assert d.offer(msg) == []
    assert d.rejected == {"unknown sender": 1, "wrong shape": 2, "wrong run": 1, "non-finite plan": 1}
    assert d.coord.duplicates == 0
    d.round()
    assert d.records[-1].fallback == [False] * 4


# ---------------------------------------------------------------- fallbacks

def test_deadline_with_one_agent_missing(prepared, at_step_1):
    d = at_step_1
    last = d.records[-1]
    plan_2 = Plan(0, last.rounds - 1, last.plans_z[1], last.plans_v[1])
    assert d.coord.on_deadline(0, 0) == []  # an old deadline does nothing
    assert d.coord.on_deadline(1, 1) == []
    d.round(["1", "3", "4"])
    assert len(d.records) == 1
    late = d.message("2")
    d.handle(d.coord.on_deadline(1, 0))
    rec = d.records[-1]
    assert rec.k == 1
    assert rec.fallback == [False, True, False, False]
    assert rec.status[1] == "missed" and rec.fallback_reason[1] == "missed"
    x2 = part(rec.x, 1)
    expected = shifted_projected(plan_2, 1, x2, 1)
    np.testing.assert_allclose(rec.u[1:2], expected, atol=1e-12)
    assert abs(rec.u[1]) <= U_BAR
    check_plant_update(rec)
    # the recorded plan of the missing agent is its previous plan shifted by one
    np.testing.assert_allclose(rec.plans_z[1][:N], plan_2.z[1:], atol=1e-12)
    np.testing.assert_allclose(rec.plans_v[1][:N - 1], plan_2.v[1:], atol=1e-12)
    assert rec.beta_next == pytest.approx(sigma(prepared, rec.alpha_next), abs=1e-12)
    # a plan arriving after the deadline is stale
    assert d.deliver(late) == []
    assert d.rejected == {"stale": 1}
    # the neighbours keep assuming the last plan of agent 2 (shifted again)
    assert d.releases["1"].assumed["2"] == (0, last.rounds - 1)
    # and a second miss shifts that plan twice
    d.round(["1", "3", "4"])
    d.handle(d.coord.on_deadline(2, 0))
    rec2 = d.records[-1]
    assert rec2.k == 2 and rec2.fallback == [False, True, False, False]
    np.testing.assert_allclose(rec2.u[1:2], shifted_projected(plan_2, 2, part(rec2.x, 1), 1), atol=1e-12)
    check_plant_update(rec2)


def test_deadline_at_k0_without_any_plan_uses_projected_Kx(prepared, controllers):
    d = Driver(prepared, controllers, options())
    d.round(["2", "3", "4"])
    d.handle(d.coord.on_deadline(0, 0))
    rec = d.records[-1]
    assert rec.k == 0 and rec.rounds == 1
    assert rec.fallback == [True, False, False, False]
    raw = K_PAPER[0] @ np.array([2.794, 2.5])
    assert raw[0] < -U_BAR  # K_1 x_1(0) alone exceeds the bound
    np.testing.assert_allclose(rec.u[0:1], np.clip(raw, -U_BAR, U_BAR), atol=1e-12)
    check_plant_update(rec)


def test_infeasible_status_triggers_the_fallback(at_step_1):
    d = at_step_1
    last = d.records[-1]
    plan_3 = Plan(0, last.rounds - 1, last.plans_z[2], last.plans_v[2])
    bad = d.message("3", alpha=np.array([50.0, 50.0]), beta=1e-3)
    assert bad.status == "infeasible"
    assert np.all(np.isnan(bad.z))
    msgs = [d.message(n) for n in ("1", "2", "4")] + [bad]
    for m in msgs:
        d.deliver(m)
    rec = d.records[-1]
    assert rec.k == 1
    assert rec.fallback == [False, False, True, False]
    assert rec.status[2] == "infeasible"
    assert "infeasible" in rec.fallback_reason[2]
    np.testing.assert_allclose(rec.u[2:3], shifted_projected(plan_3, 1, part(rec.x, 2), 2), atol=1e-12)
    assert np.all(np.isfinite(rec.u)) and np.max(np.abs(rec.u)) <= U_BAR + 1e-7
    check_plant_update(rec)


def test_agent_lost_and_back(at_step_1):
    d = at_step_1
    assert d.coord.on_agent_lost("nobody") == []
    d.round(["1", "2", "3"])
    assert len(d.records) == 1
    d.handle(d.coord.on_agent_lost("4"))
    rec = d.records[-1]
    assert rec.k == 1 and rec.fallback == [False, False, False, True]
    assert abs(rec.u[3]) <= U_BAR
    # while lost, the next step does not wait for it
    d.round(["1", "2", "3"])
    assert d.records[-1].k == 2 and d.records[-1].fallback == [False, False, False, True]
    # back: the round already open (k = 3) still counts it as missed, the next one waits for it
    d.coord.on_agent_back("4")
    d.round(["1", "2", "3"])
    assert d.records[-1].k == 3 and d.records[-1].fallback == [False, False, False, True]
    d.round(["1", "2", "3"])
    assert d.records[-1].k == 3  # k = 4 waits for agent 4
    d.round(["4"])
    assert d.records[-1].k == 4 and d.records[-1].fallback == [False] * 4
    check_plant_update(d.records[-1])


# ---------------------------------------------------------------- inputs outside U_i

def test_plan_with_an_input_outside_U_i_is_refused_and_its_fallback_applied(at_step_1):
    d = at_step_1
    last = d.records[-1]
    plan_2 = Plan(0, last.rounds - 1, last.plans_z[1], last.plans_v[1])
    good = d.message("2")
    v = good.v.copy()
    v[4, 0] = 3 * U_BAR  # a later input: the whole plan must lie in U_i, not only v(k)
    bad = d.message("2", v=v)
    assert d.coord.check(bad) is None  # well-formed: not dropped, so the round does not wait for it
    for m in [d.message(n) for n in ("1", "3", "4")] + [bad]:
        d.deliver(m)
    rec = d.records[-1]
    assert rec.k == 1
    assert d.coord.inputs_refused == {"2": 1} and d.rejected == {}
    assert rec.fallback == [False, True, False, False]
    assert rec.status[1] == "solved" and rec.fallback_reason[1] == "input outside U_i"
    np.testing.assert_allclose(rec.u[1:2], shifted_projected(plan_2, 1, part(rec.x, 1), 1), atol=1e-12)
    assert np.max(np.abs(rec.u)) <= U_BAR
    check_plant_update(rec)
    # its neighbours keep building on its last accepted plan
    assert d.releases["1"].assumed["2"] == (0, last.rounds - 1)
    d.round()
    assert d.records[-1].fallback == [False] * 4 and d.coord.inputs_refused == {"2": 1}


def test_a_refused_plan_is_an_action_that_names_the_agent_the_round_and_the_excess(at_step_1):
    """The host learns of a refusal from the coordinator's actions, first of them, once per plan."""
    d = at_step_1
    v = d.message("3").v.copy()
    v[2, 0] = U_BAR + 0.25
    actions = d.offer(d.message("3", v=v))
    assert actions == [PlanRefused("3", 1, 0, pytest.approx(0.25 - 1e-6 * U_BAR), 1)]
    d.round(["1", "2", "4"])
    v = d.message("3").v.copy()
    v[0, 0] = -U_BAR - 1.0
    actions = d.offer(d.message("3", v=v))
    assert isinstance(actions[0], PlanRefused) and actions[0].count == 2 and actions[0].k == 2
    assert not any(isinstance(a, PlanRefused) for a in d.offer(d.message("1")))


@pytest.mark.parametrize("excess, refused", [(0.5e-6 * U_BAR, False), (2e-6 * U_BAR, True), (-1e-3, False)])
def test_input_tolerance_is_relative_to_the_bound(at_step_1, excess, refused):
    d = at_step_1
    msg = d.message("1")
    v = msg.v.copy()
    v[0, 0] = -(U_BAR + excess)
    d.deliver(d.message("1", v=v))
    d.round(["2", "3", "4"])
    rec = d.records[-1]
    assert rec.fallback[0] is refused
    assert d.coord.inputs_refused == ({"1": 1} if refused else {})
    if not refused:
        assert rec.u[0] == -(U_BAR + excess)  # within the tolerance the plan is applied as sent


def test_input_excess_on_a_polytope_with_one_sided_rows():
    lin = LinearSet(np.array([[1.0, 1.0], [1.0, -1.0]]), np.array([-np.inf, -1.0]), np.array([2.0, np.inf]))
    inside = np.array([[1.0, 0.5], [0.0, 0.0]])
    assert input_excess(lin, inside) < 0
    assert input_excess(lin, np.array([[1.5, 1.0]])) == pytest.approx(0.5 - 2e-6)
    assert input_excess(lin, np.array([[0.0, 2.0]])) == pytest.approx(1.0 - 1e-6)
    assert input_excess(lin, np.zeros((0, 2))) == -np.inf


class OutsideDriver(Driver):
    """A Driver whose coordinator has a plant outside: steps end with ApplyInputs."""

    def __init__(self, prepared, controllers, options: ProtocolOptions) -> None:
        self.system = prepared.system
        self.coord = Coordinator(prepared.system, prepared.design, None, options, RUN)
        self.controllers = controllers
        self.archive, self.releases, self.records, self.rejected = {}, {}, [], {}
        self.finished = False
        self.applied: list[ApplyInputs] = []
        self.handle(self.coord.start(prepared.system.x0))

    def handle(self, actions) -> list:
        self.applied += [a for a in actions if isinstance(a, ApplyInputs)]
        return super().handle([a for a in actions if not isinstance(a, ApplyInputs)])


def test_a_round_closed_while_the_plant_outside_measures_is_not_closed_again(prepared, controllers):
    """Between ApplyInputs and the state, a deadline of the closed round or a lost agent must not
    decide the step again; the record (built after the state) is the simulated plant's."""
    options = ProtocolOptions(steps=3, initial_rounds=1)
    simulated = Driver(prepared, controllers, options)
    simulated.round()
    outside = OutsideDriver(prepared, controllers, options)
    outside.round()
    assert len(outside.applied) == 1 and outside.applied[0].k == 0
    assert outside.coord.on_deadline(0, 0) == [] and outside.coord.on_agent_lost("2") == []
    assert len(outside.applied) == 1
    outside.handle(outside.coord.on_state(1, Plant(prepared.system).step(outside.applied[0].u)))
    ours, theirs = outside.records[0], simulated.records[0]
    assert np.array_equal(ours.u, theirs.u) and np.array_equal(ours.x_next, theirs.x_next)
    assert ours.max_change == theirs.max_change and ours.J == theirs.J and ours.S == theirs.S

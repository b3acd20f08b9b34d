"""The step barrier and coordinator: a pure state machine (no bus; time only from the host's clock).

Per step k it releases round 0 to every agent, collects their plans, runs further Jacobi rounds
while the plans still move (k = 0: to convergence), then finalises the step: inputs (with the
fallback of docs/algorithm.md, "Online step k, agent i", item 7, for missing, infeasible or
refused plans), alpha(k+1) = (A+BK) eta, beta(k+1) = sigma(alpha(k+1)) (or another method's
terminal update, dmpc.methods.policy), the plant update and the step record.

Inputs are method calls (``start``, ``on_plan``, ``on_deadline``, ``on_agent_lost``,
``on_agent_back``, ``step_opened``); outputs are lists of actions for the hosting process to carry
out. The coordinator is the one place that accepts or rejects a plan: ``on_plan`` says why it
dropped one, and answers a plan whose inputs leave U_i with :class:`PlanRefused`. The host's clock, if given, only times the records (plan latency, step time).
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial

import numpy as np

from dmpc.bus.messages import Kept, PlanMessage, Release, Setpoint, SetpointAnswer
from dmpc.core.central_qp import CentralQP
from dmpc.core.mpc_qp import plan_cost
from dmpc.core.qp_status import KEPT, PLANNED, SOLVED, QPStatus
from dmpc.core.steps import NO_SEED, SETPOINT_METHODS, ProtocolOptions, StepRecord
from dmpc.core.system import CoupledSystem, LinearSet, project_onto
from dmpc.core.trajectories import Plan, candidate_plan, kept_around, relative_to, shifted_input
from dmpc.methods import DEFAULT_METHOD, terminal_policy
from dmpc.methods.policy import TerminalPolicy, TerminalState
from dmpc.offline import ControllerDesign
from dmpc.plant.dynamics import Plant
from dmpc.security.rejects import MAX_MAGNITUDE, STALE, clearly_in_range, magnitude
from dmpc.tracking.schedule import SetpointEntry
from dmpc.tracking.targets import Target
from dmpc.tracking.tracker import Tracker, TrackingStep

KNOWN_STATUSES = frozenset(s.value for s in QPStatus)
NO_PLAN_TO_KEEP = "kept without a plan of the previous step"
# A solved plan may leave U_i by this much times max(1, |bound|): OSQP solves to about 1e-7,
# so an honest plan stays well inside, and anything beyond is refused.
INPUT_TOLERANCE = 1e-6
INPUT_REFUSED = "input outside U_i"


def input_excess(input_set: LinearSet, v: np.ndarray) -> float:
    """How far the inputs ``v`` (one per row, shape (N, m_i)) leave ``input_set`` beyond
    ``INPUT_TOLERANCE``; > 0 means refused. Infinite bounds never bind."""
    return input_set.largest_excess(v, INPUT_TOLERANCE)


@dataclass(frozen=True)
class SendRelease:
    release: Release


@dataclass(frozen=True)
class RoundOpened:
    """Round ``round`` of step ``k`` was released; the host arms its deadline (if any) for it."""

    k: int
    round: int


class StepCompleted:
    """A step is complete; its record is built when first read.

    The next step's release is decided without what only the record needs (the round's plan
    change when no decision rests on it, the spread, the cost sum): the host sends the release
    first and reads ``record`` afterwards, off the step's path. Everything the record is made
    of is fixed when the step completes, so when it is read does not change it.
    """

    __slots__ = ("_build", "_record")

    def __init__(self, build: Callable[[], StepRecord]) -> None:
        self._build = build
        self._record: StepRecord | None = None

    @property
    def record(self) -> StepRecord:
        if self._record is None:
            self._record, self._build = self._build(), None
        return self._record


@dataclass(frozen=True)
class ApplyInputs:
    """The step's inputs are decided: the host has the plant apply u(k) (shape (m,)) and answers
    with :meth:`Coordinator.on_state` (only with an outside plant)."""

    k: int
    u: np.ndarray


@dataclass(frozen=True)
class PlanRefused:
    """The plan of agent ``name`` for step ``k``, round ``round``, leaves U_i by ``excess``
    (beyond ``INPUT_TOLERANCE``): it stands as the agent's answer, its fallback applies, and it
    is the agent's ``count``-th refusal of the run."""

    name: str
    k: int
    round: int
    excess: float
    count: int


@dataclass(frozen=True)
class RunFinished:
    reason: str


@dataclass(frozen=True)
class _AgentStep:
    """One agent's part of a step record: its input u_i (m_i,), terminal state eta_i (n_i,),
    cost, what its plan said, and the plan the step recorded for it, z (N+1, n_i), v (N, m_i)."""

    u: np.ndarray
    eta: np.ndarray
    J: float
    status: str
    fallback: bool
    reason: str
    solve_time: float
    qp_iterations: int
    latency: float
    z: np.ndarray
    v: np.ndarray
    solved_because: str = ""


@dataclass(frozen=True)
class _PendingStep:
    """What a completed step's record is made of, fixed when the step closes: the state x(k) (n,),
    inputs u (m,), terminal sets before and after, rounds, each agent's part, note, and the last
    round's plan change (measured when the record is built)."""

    k: int
    x: np.ndarray
    u: np.ndarray
    alpha: np.ndarray
    beta: float
    rounds: int
    agents: list[_AgentStep]
    note: str
    r: np.ndarray | None
    terminal: TerminalState
    max_change: Callable[[], float]
    tracking: TrackingStep | None = None
    target: Target | None = None  # the target of the next step (with a tracker)
    triggered: bool = False  # an event trigger: the record says why each agent solved

    def record(self, x_next: np.ndarray, step_time: float, system: CoupledSystem) -> StepRecord:
        agents, nxt = self.agents, self.terminal
        J_agents = [a.J for a in agents]
        return StepRecord(
            k=self.k, x=self.x, u=self.u, alpha=self.alpha, beta=self.beta, alpha_next=nxt.alpha, beta_next=nxt.beta,
            J=float(np.sum(J_agents)), J_agents=J_agents, S=system.spread(self.x), rounds=self.rounds,
            max_change=self.max_change(), status=[a.status for a in agents], fallback=[a.fallback for a in agents],
            fallback_reason=[a.reason for a in agents], solve_time=[a.solve_time for a in agents],
            qp_iterations=[a.qp_iterations for a in agents], plans_z=[a.z for a in agents],
            plans_v=[a.v for a in agents], latency=[a.latency for a in agents], note=self.note, r=self.r,
            r_next=nxt.r, x_next=x_next, step_time=step_time, tracking=self.tracking,
            solve_reason=[a.solved_because for a in agents] if self.triggered else None)


class Coordinator:
    """The barrier for one run.

    Parameters
    ----------
    system : CoupledSystem
    design : ControllerDesign
    plant : Plant or None
        The simulated plant, stepped in place; None for a plant outside (hardware, another
        program): then :meth:`start` takes the measured x(0), each step ends with
        :class:`ApplyInputs`, and the host answers with :meth:`on_state`.
    options : ProtocolOptions
    run_id : str
    policy : TerminalPolicy, optional
        The method's terminal sets: what each agent is released and how the terminal
        parameters move (the paper's time-varying boxes by default).
    clock : callable () -> float, optional
        The host's clock in seconds, read when a plan is accepted, when the host opens a step
        (:meth:`step_opened`) and when a step completes: the records' latency and step time.
        Without one both are NaN.
    tracker : Tracker, optional
        The setpoint targets (docs/algorithm.md, "Setpoints"): each step's controllers work in
        deviation coordinates around the target it applies. None: the origin throughout.
    triggered : bool
        The agents have an event trigger: they may answer with :class:`Kept` (:meth:`on_kept`),
        and the records say why each agent solved.
    """

    def __init__(self, system: CoupledSystem, design: ControllerDesign, plant: Plant | None, options: ProtocolOptions,
                 run_id: str, policy: TerminalPolicy | None = None, clock: Callable[[], float] | None = None,
                 tracker: Tracker | None = None, triggered: bool = False) -> None:
        self.system = system
        self.design = design
        self.plant = plant
        self.options = options
        self.run_id = run_id
        self.names = [s.name for s in system.subsystems]
        self.index = {name: i for i, name in enumerate(self.names)}
        self.N = design.horizon
        K = design.gains.K
        self._K = K
        self._gamma = [s.A + s.B @ K[i] for i, s in enumerate(system.subsystems)]
        if policy is None:
            policy = terminal_policy(DEFAULT_METHOD, system, design)
        self.policy = policy
        self._clock = clock
        self._x = np.array(system.x0, dtype=float)  # the measured state, with a plant outside (until start)
        self._pending: _PendingStep | None = None  # a step whose next state is awaited
        self.terminal = policy.initial(self.x)
        self.k = 0
        self.round = 0
        self.finished = False
        self.last_plan: list[Plan | None] = [None] * system.M
        self._round: dict[int, PlanMessage] = {}
        self._missed: set[int] = set()
        self._lost: set[int] = set()
        self._step_latest: dict[int, Plan] = {}
        self._prev_round: dict[int, Plan] = {}
        self._round_status: dict[int, PlanMessage] = {}
        self._received_at: dict[int, float] = {}  # per agent: when its plan in _round_status was accepted
        self._solve_reason: dict[int, str] = {}  # per agent: why it solved in round 0 of the open step (a trigger)
        self._opened_at = math.nan
        self.duplicates = 0
        self.inputs_refused: dict[str, int] = {}
        self._refused: dict[int, PlanMessage] = {}  # per agent: its last plan refused (kept until replaced)
        # the centralised QP's plans seeded at k = 0: no agent published them, so every release
        # that refers to one carries it (its agent may keep it for many rounds, even steps)
        self._seeded: dict[int, Plan] = {}
        self._note = self.terminal.note
        self.tracker = tracker
        self._target: Target | None = None  # the open step's target, None at the origin
        self.triggered = triggered
        self._kept_last: tuple[str, ...] = ()  # the agents that kept their plan at the step before

    @property
    def alpha(self) -> np.ndarray:
        """The terminal box centres alpha(k), shape (n,) (zeros for the ellipsoid methods)."""
        return self.terminal.alpha

    @property
    def beta(self) -> float:
        """The terminal box radius beta(k) (NaN for the ellipsoid methods)."""
        return self.terminal.beta

    # ------------------------------------------------------------------ inputs
    @property
    def x(self) -> np.ndarray:
        """The measured state x(k), shape (n,)."""
        return self.plant.x if self.plant is not None else self._x

    def start(self, x0: np.ndarray | None = None) -> list:
        """Actions that release step 0, round 0.

        ``x0`` (shape (n,)): the state x(0) measured by a plant outside (required then; ignored
        with a simulated plant). The terminal sets start from it.
        """
        if self.plant is None:
            if x0 is None:
                raise ValueError("a coordinator with a plant outside starts from the measured x(0)")
            self._x = np.array(x0, dtype=float)
            self.terminal = self.policy.initial(self._x)
            self._note = self.terminal.note
        return self._release_round()

    def on_state(self, k: int, x: np.ndarray) -> list:
        """The plant outside measured x(k) (shape (n,)) after the inputs of step k - 1: the step
        is complete. Returns its actions; none for a state that was not awaited."""
        if self._pending is None or k != self.k + 1:
            return []
        pending, self._pending = self._pending, None
        self._x = np.array(x, dtype=float)
        return self._complete_step(pending, self._x)

    def on_plan(self, msg: PlanMessage) -> tuple[list, str | None]:
        """A plan arrived: accept it, or drop it and say why.

        Returns
        -------
        (actions, reason)
            The actions it triggers (possibly none), and why it was dropped: None when it was
            accepted or ignored as a copy (a second plan of an agent for the open round; the
            first one counts, and ``duplicates`` counts the others), else the reason (see
            :meth:`check`; ``malformed: <error>`` for a message the checks cannot even read).
        """
        try:
            problem = self.check(msg)
        except Exception as exc:  # noqa: BLE001 - a malformed message must not stop the run
            problem = f"malformed: {type(exc).__name__}"
        if problem is not None:
            return [], problem
        if self.finished:
            return [], None
        i = self.index[msg.sender]
        if i in self._round or i in self._missed:
            self.duplicates += 1
            return [], None
        self._round[i] = msg
        self._received_at[i] = self._now()
        excess = input_excess(self.system.subsystems[i].input_set, msg.v) if msg.status in SOLVED else 0.0
        refused = [self._refuse(i, msg, excess)] if excess > 0 else []
        return refused + self._maybe_close_round(), None

    def on_kept(self, msg: Kept) -> tuple[list, str | None]:
        """Agent ``msg.sender`` kept its shifted plan (an event trigger): the plan is rebuilt here
        from the agent's last plan, x_i(k) and alpha_i(k), and stands as the agent's answer, or the
        notice is dropped and the reason said (as for :meth:`on_plan`)."""
        problem = self._kept_problem(msg)
        if problem is not None:
            return [], problem
        if self.finished:
            return [], None
        i = self.index[msg.sender]
        if i in self._round or i in self._missed:
            self.duplicates += 1
            return [], None
        last = self.last_plan[i]
        assert last is not None  # checked above
        x_i = self.x[self.system.xs(i)]
        offset = self._around(self._target, i, last, x_i)[2]
        centre = self.alpha[self.system.xs(i)]
        kept = kept_around(last, self.k, x_i, centre, self._gamma[i], self._K[i], offset)
        around = kept if offset is None else relative_to(kept, *offset)
        assert around is not None
        sub = self.system.subsystems[i]
        cost = plan_cost(around.z, around.v, sub.Q, sub.R, self.design.gains.P[i])
        self._round[i] = PlanMessage(run=msg.run, k=msg.k, round=msg.round, sender=msg.sender, status=KEPT, z=kept.z,
                                     v=kept.v, cost=cost, solve_time=0.0, qp_iterations=0, sent_at=msg.sent_at)
        self._received_at[i] = self._now()
        return self._maybe_close_round(), None

    def _kept_problem(self, msg: Kept) -> str | None:
        """None if the notice belongs to the open round of an agent with a plan of the step
        before; else the reason."""
        if msg.run != self.run_id:
            return "wrong run"
        i = self.index.get(msg.sender)
        if i is None:
            return "unknown sender"
        if (msg.k, msg.round) != (self.k, self.round):
            return STALE if (msg.k, msg.round) < (self.k, self.round) else "future"
        last = self.last_plan[i]
        if not self.triggered or self.round != 0 or last is None or last.k != self.k - 1:
            return NO_PLAN_TO_KEEP
        return None

    def step_opened(self) -> None:
        """The host has begun the open step (sent its release, or opened it with every agent
        lost): the step's time runs from now."""
        self._opened_at = self._now()

    def _now(self) -> float:
        return self._clock() if self._clock is not None else math.nan

    def _refuse(self, i: int, msg: PlanMessage, excess: float) -> PlanRefused:
        """Agent i's plan leaves U_i: it stands as the agent's answer for the round, but its
        fallback applies (as for an infeasible QP), and the refusal is counted."""
        self._refused[i] = msg
        count = self.inputs_refused[msg.sender] = self.inputs_refused.get(msg.sender, 0) + 1
        return PlanRefused(msg.sender, msg.k, msg.round, excess, count)

    def _usable(self, i: int, msg: PlanMessage | None) -> bool:
        """True if ``msg`` is a solved (or kept) plan of agent i that was not refused."""
        return msg is not None and msg.status in PLANNED and self._refused.get(i) is not msg

    def _fallback_reason(self, i: int, msg: PlanMessage | None) -> str:
        if msg is None:
            return "lost" if i in self._lost else "missed"
        return INPUT_REFUSED if self._refused.get(i) is msg else f"qp {msg.status}"

    def on_deadline(self, k: int, r: int) -> list:
        """The deadline of round ``r`` of step ``k`` passed: whoever has not delivered missed it."""
        if self.finished or (k, r) != (self.k, self.round):
            return []
        for i in range(self.system.M):
            if i not in self._round:
                self._missed.add(i)
        return self._maybe_close_round()

    def on_agent_lost(self, name: str) -> list:
        """Liveliness of agent ``name`` disappeared: stop waiting for it and stop releasing to it.

        Its fallback applies from the open round on; the step record notes the loss.
        """
        i = self.index.get(name)
        if i is None or self.finished:
            return []
        if i not in self._lost:
            self._add_note(f"agent {name} lost")
        self._lost.add(i)
        if i not in self._round:
            self._missed.add(i)
        return self._maybe_close_round()

    def on_agent_back(self, name: str) -> bool:
        """Agent ``name`` is ready again: it is released to and waited for from the next round on.

        Returns True if it had been lost (the step record then notes its return).
        """
        i = self.index.get(name)
        if i is None or i not in self._lost or self.finished:
            return False
        self._lost.discard(i)
        self._add_note(f"agent {name} back")
        return True

    def _add_note(self, text: str) -> None:
        self._note = f"{self._note}; {text}" if self._note else text

    # ------------------------------------------------------------------ setpoints
    def on_setpoint(self, msg: Setpoint) -> SetpointAnswer:
        """A setpoint request of a supervisory program: take it from the first step whose target
        is not decided yet, or refuse it and say why.

        Accepted, it joins the tracker's schedule from that step (NaN where free; an empty x or u
        leaves every component free) and the record of the step it arrived in notes it. Refused,
        nothing changes.

        Returns
        -------
        SetpointAnswer
            Accepted with ``k`` the first step the request holds at, or refused (``k`` = -1) with
            the reason.
        """
        try:
            problem = self._setpoint_problem(msg)
        except Exception as exc:  # noqa: BLE001 - a malformed message must not stop the run
            problem = f"malformed: {type(exc).__name__}"
        if problem is not None:
            return SetpointAnswer(self.run_id, msg.id, msg.subsystem, False, -1, problem)
        assert self.tracker is not None  # checked by _setpoint_problem
        i, at = self.index[msg.subsystem], self._first_undecided()
        sub = self.system.subsystems[i]
        x, u = _request_part(msg.x, sub.n), _request_part(msg.u, sub.m)
        self.tracker.add(SetpointEntry(at=at, index=i, x=x, u=u, source=msg.sender))
        self._note_setpoint(f"setpoint from {msg.sender} (id {msg.id}): subsystem {msg.subsystem} "
                            f"{_components_text('x', x)}, {_components_text('u', u)} from step {at}")
        return SetpointAnswer(self.run_id, msg.id, msg.subsystem, True, at)

    def _first_undecided(self) -> int:
        """The first step whose target is not decided yet: k + 1, or k + 2 while step k is
        decided and its next state awaited from a plant outside."""
        return self.k + (2 if self._pending is not None else 1)

    def _setpoint_problem(self, msg: Setpoint) -> str | None:
        """Why the request cannot be taken, or None."""
        if msg.run != self.run_id:
            return f"wrong run id '{msg.run}' (this run is '{self.run_id}')"
        if self.tracker is None:
            return f"this run's method does not track setpoints (only {' and '.join(SETPOINT_METHODS)} do)"
        if self.finished:
            return "the run is finished"
        at = self._first_undecided()
        if at >= self.options.steps:
            return f"too late: the run's last step ({self.options.steps - 1}) is already decided"
        i = self.index.get(msg.subsystem)
        if i is None:
            shown = ", ".join(self.names[:8]) + (", ..." if len(self.names) > 8 else "")
            return f"unknown subsystem '{msg.subsystem}' (known: {shown})"
        sub = self.system.subsystems[i]
        return (_component_problem(np.asarray(msg.x, dtype=float), "x", sub.n, sub.state_set, msg.subsystem)
                or _component_problem(np.asarray(msg.u, dtype=float), "u", sub.m, sub.input_set, msg.subsystem))

    def _note_setpoint(self, text: str) -> None:
        """Note ``text`` in the record of the step the request arrived in (the decided step while
        its state is awaited)."""
        if self._pending is None:
            self._add_note(text)
        else:
            note = self._pending.note
            self._pending = replace(self._pending, note=f"{note}; {text}" if note else text)

    # ------------------------------------------------------------------ checks
    def check(self, msg: PlanMessage) -> str | None:
        """None if the plan belongs to the open round and has the right shapes; else the reason."""
        if msg.run != self.run_id:
            return "wrong run"
        i = self.index.get(msg.sender)
        if i is None:
            return "unknown sender"
        if (msg.k, msg.round) != (self.k, self.round):
            return STALE if (msg.k, msg.round) < (self.k, self.round) else "future"
        sub = self.system.subsystems[i]
        if msg.z.shape != (self.N + 1, sub.n) or msg.v.shape != (self.N, sub.m):
            return "wrong shape"
        if msg.status not in KNOWN_STATUSES:
            return "unknown status"
        if msg.status in SOLVED and not clearly_in_range(msg.z, msg.v, msg.cost):
            size = magnitude(msg.z, msg.v, msg.cost)
            if not math.isfinite(size):
                return "non-finite plan"
            if size > MAX_MAGNITUDE:
                return "out of range"
        return None

    def has_plan(self, name: str) -> bool:
        """True if agent ``name``'s plan for the open round is in (or the agent was marked missed)."""
        i = self.index.get(name)
        return i is not None and (i in self._round or i in self._missed)

    # ------------------------------------------------------------------ rounds
    def _release_round(self) -> list:
        self._round = {}
        self._missed = set(self._lost)
        actions: list = []
        M = self.system.M
        if len(self._lost) < M:
            assumed = np.full((M, 2), -1, dtype=np.int64)
            for j in range(M):
                ref = self._reference(j)
                if ref is not None:
                    assumed[j] = (ref.k, ref.round)
            centres, sizes = self.policy.release_all(self.terminal)
            # lost agents are skipped: their plans would not be used, and the first release after
            # their Ready tells them they are back
            release = Release(run=self.run_id, k=self.k, round=self.round, x=self.x.copy(),
                              centres=centres, sizes=sizes, assumed=assumed,
                              skipped=tuple(self.names[i] for i in sorted(self._lost)),
                              provided=self._provided_plans(),
                              target=None if self._target is None else (self._target.x, self._target.u),
                              kept=self._kept_last if self.round == 0 else ())
            actions.append(SendRelease(release))
        actions.append(RoundOpened(self.k, self.round))
        actions.extend(self._maybe_close_round())
        return actions

    def _provided_plans(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """The seeded plans the next release refers to, by agent name: (z, v)."""
        return {self.names[j]: (plan.z, plan.v) for j, plan in self._seeded.items() if self._reference(j) is plan}

    def _reference(self, j: int) -> Plan | None:
        """The plan of agent j its neighbours build their assumption from."""
        if self.round > 0 and j in self._step_latest:
            return self._step_latest[j]
        return self.last_plan[j]

    def _maybe_close_round(self) -> list:
        if self._pending is not None:
            return []  # the step is decided: its inputs are with the plant outside, its state awaited
        if len(self._round) + len(self._missed) < self.system.M or (
                self._missed and len(self._round) + len(self._missed - self._round.keys()) < self.system.M):
            return []
        self._prev_round = dict(self._step_latest)
        for i, msg in self._round.items():
            self._round_status[i] = msg
            if self.round == 0:  # the trigger decides in round 0; later rounds of the step (k = 0) only refine
                self._solve_reason[i] = msg.reason
            if self._usable(i, msg):
                self._step_latest[i] = Plan(msg.k, msg.round, msg.z, msg.v)
        infeasible = [self.names[i] for i, msg in self._round.items() if msg.status not in PLANNED]
        if self.k == 0 and self.round == 0 and infeasible and not self._missed:
            self._seed_from_centralized(infeasible)
        rounds_allowed = self.options.initial_rounds if self.k == 0 else self.options.rounds
        tol = self.options.initial_tolerance if self.k == 0 else self.options.tolerance
        another = self.round + 1 < rounds_allowed and not self._missed
        change = self._round_change() if another and self.round > 0 else None  # round 0 never converges
        if another and not (change is not None and change < tol):
            self.round += 1
            return self._release_round()
        if change is None:  # only the record needs it: measured after the next release is out
            return self._finalise_step(self._change_later())
        return self._finalise_step(lambda: change)

    def _seed_from_centralized(self, infeasible: list[str]) -> None:
        """Replace the first round's plans by the centralised QP's plan
        (docs/algorithm.md, "Online step k, agent i", item 4)."""
        T, lower, upper = self.policy.joint_terminal(self.terminal)
        qp = CentralQP(self.system, self.design.gains.P_global(), self.N, terminal="rows", rows=T)
        sol = qp.solve_rows(self.x, lower, upper)
        if not sol.status.feasible:
            self._add_note(f"k=0: round 0 infeasible for agents {', '.join(infeasible)}; {NO_SEED}"
                           f"{_seed_failure(sol.status)}{_start_check_finding(self.design.start, self.N)}")
            return
        for i in range(self.system.M):
            plan = Plan(0, 0, sol.z[:, self.system.xs(i)], sol.v[:, self.system.us(i)])
            self._step_latest[i] = plan
            self._seeded[i] = plan
        self._add_note(f"k=0: round 0 infeasible from decoupled rollouts for agents {', '.join(infeasible)}; "
                       "started from the centralised QP's plan")

    def _round_change(self) -> float:
        """Largest change of this round's plans: max over agents of max |z - z_ref|, |v - v_ref|.

        Round 0 compares each plan with what the neighbours assumed of it: the agent's candidate,
        its last plan shifted to step k and continued with K_i (at k = 0, or without any plan,
        the decoupled K-rollout from x_i(k)), with the measured x_i(k) as first state. Later
        rounds compare with the agent's plan of the previous round; inf if it has none there
        (its QP was infeasible), so the rounds go on. Agents without a plan in this round do not
        count (0 if none has one).
        """
        return self._change_later()()

    def _change_later(self) -> Callable[[], float]:
        """:meth:`_round_change` of the round closing now, to be measured later: what it reads is
        taken now (the plans are never changed once received; the last plans and the state are
        replaced when the step completes)."""
        k, r, latest, prev_round, target = self.k, self.round, self._step_latest, self._prev_round, self._target
        x_parts = self.system.split_state(self.x.copy()) if r == 0 else None
        last = list(self.last_plan) if r == 0 else None

        def change() -> float:
            top = 0.0
            for i, plan in latest.items():
                if r == 0:
                    last_i, x_i, offset = self._around(target, i, last[i], x_parts[i])
                    z_ref, v_ref = candidate_plan(last_i, k, x_i, self.N, self._gamma[i], self._K[i])
                    z_ref[0] = x_i
                    if offset is not None:
                        z_ref, v_ref = z_ref + offset[0], v_ref + offset[1]
                else:
                    prev = prev_round.get(i)
                    if prev is None:
                        return float("inf")
                    z_ref, v_ref = prev.z, prev.v
                top = max(top, float(np.abs(plan.z - z_ref).max()), float(np.abs(plan.v - v_ref).max()))
            return top

        return change

    # ------------------------------------------------------------------ step end
    def _finalise_step(self, max_change: Callable[[], float]) -> list:
        """Close the step: every agent's input and terminal state decide the next terminal sets and
        (with a simulated plant) x(k+1). ``max_change`` gives the last round's plan change."""
        system = self.system
        x = self.x.copy()
        x_parts = system.split_state(x)
        agents = [self._agent_step(i, x_parts[i]) for i in range(system.M)]
        u = np.concatenate([a.u for a in agents])
        eta = np.concatenate([a.eta for a in agents])
        tracking = target = None
        if self.tracker is not None and self.tracker.active:
            tracking = self.tracker.step(self.k)
            target = self.tracker.advance(self.k + 1, eta)
        elif self.tracker is not None:
            tracking = self.tracker.idle
        if target is None or target.is_origin:
            nxt = self.policy.update(self.terminal, eta)
        else:  # the next step's terminal set is around its target (docs/algorithm.md, "Setpoints")
            nxt = self.policy.update(self.terminal, eta - target.x, target.scale)
        pending = _PendingStep(k=self.k, x=x, u=u, alpha=self.alpha.copy(), beta=self.beta, rounds=self.round + 1,
                               agents=agents, note="; ".join(t for t in (self._note, nxt.note) if t), r=self.terminal.r,
                               terminal=nxt, max_change=max_change, tracking=tracking, target=target,
                               triggered=self.triggered)
        if self.plant is None:
            self._pending = pending
            return [ApplyInputs(self.k, u)]
        return self._complete_step(pending, self.plant.step(u))

    def _complete_step(self, pending: _PendingStep, x_next: np.ndarray) -> list:
        """The step's record with x(k+1) (shape (n,)), then the next step's release (or the end)."""
        nxt = pending.terminal
        actions: list = [StepCompleted(partial(pending.record, x_next.copy(), self._now() - self._opened_at, self.system))]
        self.terminal = nxt
        self._target = None if pending.target is None or pending.target.is_origin else pending.target
        self._kept_last = tuple(self.names[i] for i, a in enumerate(pending.agents) if a.status == KEPT)
        self.k += 1
        self.round = 0
        self._step_latest = {}
        self._prev_round = {}
        self._round_status = {}
        self._solve_reason = {}
        self._received_at = {}
        self._note = ""
        if self.k >= self.options.steps:
            self.finished = True
            actions.append(RunFinished("finished"))
            return actions
        actions.extend(self._release_round())
        return actions

    def _agent_step(self, i: int, x_i: np.ndarray) -> _AgentStep:
        """Agent i's part of the step: its plan of the step, or its fallback (the shifted
        candidate of its last plan, input projected onto U_i), with what the record says of it.

        The plan of the step becomes the agent's last plan."""
        msg = self._round_status.get(i)
        plan = self._step_latest.get(i)
        reason = self._solve_reason.get(i, "")
        if msg is None:
            status, solve_time, qp_iterations, latency = "missed", math.nan, 0, math.nan
        else:
            status, solve_time, qp_iterations = msg.status, msg.solve_time, msg.qp_iterations
            latency = self._received_at.get(i, math.nan) - msg.sent_at
        if plan is not None:
            self.last_plan[i] = plan
            usable = self._usable(i, msg)
            J = float(msg.cost) if usable else self._candidate_cost(i, self._around(self._target, i, plan, x_i)[0])
            return _AgentStep(u=plan.v[0], eta=plan.z[-1], J=J, status=status, fallback=False, reason="",
                              solve_time=solve_time, qp_iterations=qp_iterations, latency=latency, z=plan.z,
                              v=plan.v, solved_because=reason)
        sub = self.system.subsystems[i]
        last, x_i, offset = self._around(self._target, i, self.last_plan[i], x_i)
        u_c = shifted_input(last, self.k, x_i, self._gamma[i], self._K[i])
        z_c, v_c = candidate_plan(last, self.k, x_i, self.N, self._gamma[i], self._K[i])
        eta = self.policy.fallback_terminal(self.terminal, i, z_c[-1])
        if offset is not None:
            u_c, z_c, v_c, eta = u_c + offset[1], z_c + offset[0], v_c + offset[1], eta + offset[0]
        return _AgentStep(u=project_onto(sub.input_set, u_c), eta=eta,
                          J=self._candidate_cost(i, last) if last is not None else math.nan, status=status,
                          fallback=True, reason=self._fallback_reason(i, msg), solve_time=solve_time,
                          qp_iterations=qp_iterations, latency=latency, z=z_c, v=v_c, solved_because=reason)

    def _around(self, target: Target | None, i: int, plan: Plan | None,
                x_i: np.ndarray) -> tuple[Plan | None, np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        """Agent i's plan and state x_i (n_i,) in deviation coordinates around ``target`` (unchanged
        without one), and the offsets (x_s_i, u_s_i) that take them back (None without one)."""
        if target is None:
            return plan, x_i, None
        x_s, u_s = target.x[self.system.xs(i)], target.u[self.system.us(i)]
        return relative_to(plan, x_s, u_s), x_i - x_s, (x_s, u_s)

    def _candidate_cost(self, i: int, plan: Plan) -> float:
        sub = self.system.subsystems[i]
        z, v = candidate_plan(plan, self.k, None, self.N, self._gamma[i], self._K[i])
        return plan_cost(z, v, sub.Q, sub.R, self.design.gains.P[i])


def _request_part(values: np.ndarray, size: int) -> np.ndarray:
    """A subsystem's requested components (size,), NaN where free: ``values`` or, empty, all free."""
    values = np.asarray(values, dtype=float)
    return np.full(size, np.nan) if values.size == 0 else values.copy()


def _component_problem(values: np.ndarray, kind: str, size: int, bounds: LinearSet | None, name: str) -> str | None:
    """Why the requested states (``kind`` x) or inputs (u) of subsystem ``name`` cannot be taken, or
    None: ``size`` entries or none, NaN or finite, inside a box X_i or U_i (a polytope's are left to
    the target, which keeps inside it)."""
    if values.ndim != 1 or values.size not in (0, size):
        what = f"n_i = {size} states" if kind == "x" else f"m_i = {size} inputs"
        return f"{kind}: expected {size} entries ({what} of subsystem '{name}') or none, got {values.size}"
    for c, value in enumerate(values):
        if math.isnan(value):
            continue
        if not abs(value) <= MAX_MAGNITUDE:
            return f"{kind}[{c}]: expected a finite number up to {MAX_MAGNITUDE:g} in size, or NaN for a free one"
        if bounds is not None and bounds.is_box and not bounds.lower[c] <= value <= bounds.upper[c]:
            return (f"{kind}[{c}]: the target {value:g} of subsystem '{name}' is outside "
                    f"{'X_i' if kind == 'x' else 'U_i'} [{bounds.lower[c]:g}, {bounds.upper[c]:g}]")
    return None


def _components_text(kind: str, values: np.ndarray) -> str:
    """``x = [1, free]``, or ``x free`` when nothing is requested."""
    if np.isnan(values).all():
        return f"{kind} free"
    return f"{kind} = [{', '.join('free' if math.isnan(v) else f'{v:g}' for v in values)}]"


def _seed_failure(status: QPStatus) -> str:
    """Why the centralised QP gave no seed, in words."""
    if status is QPStatus.INFEASIBLE:
        return "OSQP reported the centralised QP infeasible"
    if status is QPStatus.MAX_ITER:
        return "OSQP stopped at its iteration cap on the centralised QP (max_iter) without a plan"
    return f"the centralised QP ended with status {status.value}"


def _start_check_finding(start: dict | None, horizon: int) -> str:
    """What the design's start check found of x(0) (``Design.start``), as the rest of the seed note."""
    start = start or {}
    if start.get("centrally_feasible") is True or start.get("horizon") == "auto":
        return (f", although the start check (an LP) found x(0) feasible for the centralised problem at N = "
                f"{horizon}: x(0) is near the edge of what N = {horizon} allows; a longer horizon "
                "(horizon: auto) gives the plans room")
    if "centrally_feasible" in start:
        return "; the start check could not decide whether x(0) is feasible for the centralised problem"
    return "; the start was not checked (design.check_start: false)"

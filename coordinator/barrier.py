"""The step barrier and coordinator: a pure state machine (no bus; time only from the host's clock).

Per step k it releases round 0 to every agent, collects their plans, runs further Jacobi rounds
while the plans still move (k = 0: to convergence), then finalises the step: inputs (with the
fallback of docs/algorithm.md, "Online step k, agent i", item 7, for missing, infeasible or
refused plans), alpha(k+1) = (A+BK) eta, beta(k+1) = sigma(alpha(k+1)) (or another method's
terminal update, dmpc.methods.policy), the plant update and the step record.

Inputs are method calls (``start``, ``on_plan``, ``on_kept``, ``on_deadline``, ``on_agent_lost``,
``on_agent_back``, ``on_setpoint``, ``on_state``, ``step_opened``; ``setpoint_needs`` and ``learn_targets``
let the host compute a request's targets beside the run first); outputs are lists of actions
(:mod:`dmpc.coordinator.actions`, importable from here too) for the hosting process to carry out.
The coordinator is the one place that accepts or rejects a plan: ``on_plan`` says why it dropped
one, and answers a plan whose inputs leave U_i with :class:`PlanRefused`. The host's clock, if
given, only times the records (plan latency, step time).

:class:`Coordinator` wires together the parts, each in its own module of this package:

- :class:`~dmpc.coordinator.open_step.OpenStep`: the open step's state, made new for every step;
- :class:`~dmpc.coordinator.round_barrier.RoundBarrier`: who answered the open round, who missed
  it, who is lost, and when the round closes;
- :class:`~dmpc.coordinator.guard.AnswerGuard`: the checks a plan and a kept notice share;
- :class:`~dmpc.coordinator.combiner.RoundCombiner`: what a closed round adds to the step and
  whether another round follows (:class:`~dmpc.coordinator.combiner.JacobiRounds`);
- :class:`~dmpc.coordinator.step_close.StepCloser`: each agent's part of the step, its
  fallback, and the record;
- :class:`~dmpc.coordinator.setpoint_intake.SetpointIntake`: setpoint requests and the tracker;
- :class:`~dmpc.coordinator.candidates.Candidates` and
  :class:`~dmpc.coordinator.refusals.InputRefusals`: the agents' terminal controllers, and the
  plans refused for inputs outside U_i.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import replace
from functools import partial

import numpy as np

from dmpc.bus.messages import Kept, PlanMessage, Release, Setpoint, SetpointAnswer
from dmpc.cooperative.iterate import DEFAULT_STEP_RULE, StepRule
from dmpc.coordinator.actions import (
    Action,
    ApplyInputs,
    PlanRefused,
    RoundOpened,
    RunFinished,
    SendRelease,
    StepCompleted,
)
from dmpc.coordinator.candidates import Candidates
from dmpc.coordinator.combiner import AnotherRound, ClosedRound, JacobiRounds, RoundCombiner
from dmpc.coordinator.cooperative_rounds import CooperativeCombiner
from dmpc.coordinator.estimation import Estimate, Estimation
from dmpc.coordinator.guard import AnswerGuard
from dmpc.coordinator.open_step import OpenStep
from dmpc.coordinator.refusals import INPUT_REFUSED, INPUT_TOLERANCE, InputRefusals
from dmpc.coordinator.round_barrier import RoundBarrier
from dmpc.coordinator.setpoint_intake import SetpointIntake
from dmpc.coordinator.step_close import PendingStep, StepCloser
from dmpc.core.qp_status import KEPT, SOLVED
from dmpc.core.steps import ProtocolOptions
from dmpc.core.system import CoupledSystem, LinearSet
from dmpc.core.trajectories import Plan
from dmpc.methods import DEFAULT_METHOD, terminal_policy
from dmpc.methods.policy import TerminalPolicy
from dmpc.offline import ControllerDesign
from dmpc.plant.dynamics import Plant
from dmpc.tracking.targets import Request, Target
from dmpc.tracking.tracker import Tracker

__all__ = ["INPUT_REFUSED", "INPUT_TOLERANCE", "Action", "ApplyInputs", "Coordinator", "PlanRefused", "RoundOpened",
           "RunFinished", "SendRelease", "StepCompleted", "input_excess"]


def input_excess(input_set: LinearSet, v: np.ndarray) -> float:
    """How far the inputs ``v`` (one per row, shape (N, m_i)) leave ``input_set`` beyond
    ``INPUT_TOLERANCE``; > 0 means refused. Infinite bounds never bind."""
    return input_set.largest_excess(v, INPUT_TOLERANCE)


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
    cooperative : bool
        The method is cooperative (``tv-box-coop``): each round releases the iterate of the whole
        system and combines the agents' proposals into the next
        (:class:`~dmpc.coordinator.cooperative_rounds.CooperativeCombiner`).
    cooperative_step : {"line", "equal"}
        How a cooperative round's proposals combine (``options.cooperative_step``).
    estimation : Estimation, optional
        With the scenario's ``estimation``: the plant's outputs y = C x (+ noise) update the
        observer at every step, and the controllers work from its estimate x^ instead of x; the
        disturbance estimate moves the setpoint targets (docs/algorithm.md, "Offset-free tracking").

    Attributes
    ----------
    terminal : TerminalState
        The open step's terminal sets.
    last_plan : list of Plan or None
        Per agent: its plan of the last step it had one (None before its first).
    finished : bool
        The run is over.
    outputs_reported : set of str
        The subsystems whose outputs a plant outside reported in place of their states (the
        records hold their estimates, :meth:`Estimation.recorded
        <dmpc.coordinator.estimation.Estimation.recorded>`).
    """

    def __init__(self, system: CoupledSystem, design: ControllerDesign, plant: Plant | None, options: ProtocolOptions,
                 run_id: str, policy: TerminalPolicy | None = None, clock: Callable[[], float] | None = None,
                 tracker: Tracker | None = None, triggered: bool = False, cooperative: bool = False,
                 cooperative_step: StepRule = DEFAULT_STEP_RULE, estimation: Estimation | None = None) -> None:
        self.system = system
        self.design = design
        self.plant = plant
        self.options = options
        self.run_id = run_id
        self.names = [s.name for s in system.subsystems]
        self.index = {name: i for i, name in enumerate(self.names)}
        self.N = design.horizon
        self.policy = policy if policy is not None else terminal_policy(DEFAULT_METHOD, system, design)
        self.triggered = triggered
        self._clock = clock
        self._x = np.array(system.x0, dtype=float)  # the measured state, with a plant outside (until start)
        self._estimation = estimation
        self._estimate: Estimate | None = None  # the open step's, with estimation
        self._outputs: dict[str, np.ndarray] = {}  # the outputs a plant outside reported of the step, in place of states
        self.outputs_reported: set[str] = set()  # the subsystems it ever did so for
        self.terminal = self.policy.initial(self.x)
        self.finished = False
        self.last_plan: list[Plan | None] = [None] * system.M
        self._opened_at = math.nan  # when the host last opened a step (step_opened), on its clock
        self._pending: PendingStep | None = None  # a step whose next state is awaited from a plant outside
        self._setpoints = SetpointIntake(system, run_id, options.steps, tracker, self.policy.name)
        self._step = OpenStep(k=0, target=self._setpoints.origin, note=self.terminal.note)
        self._barrier = RoundBarrier(system.M)
        self._guard = AnswerGuard(system, run_id, design.horizon)
        self._refusals = InputRefusals()
        candidates = Candidates(system, design)
        self._candidates = candidates
        self._combiner: RoundCombiner = (
            CooperativeCombiner(system, design, self.policy, options, self._refusals, cooperative_step)
            if cooperative else JacobiRounds(system, design, self.policy, options, candidates, self._refusals))
        self._closer = StepCloser(system, candidates, self.policy, self._refusals, self._setpoints, triggered)

    # ------------------------------------------------------------------ what it holds
    @property
    def k(self) -> int:
        """The open step."""
        return self._step.k

    @property
    def round(self) -> int:
        """The open step's open round."""
        return self._step.round

    @property
    def x(self) -> np.ndarray:
        """The state x(k) the controllers work from, shape (n,): the measured state, or with
        estimation the estimate x^(k)."""
        if self._estimate is not None:
            return self._estimate.x_hat
        return self.measured

    @property
    def measured(self) -> np.ndarray:
        """The plant's state x(k) as the simulated plant has it or the plant outside reported it, shape (n,)."""
        return self.plant.x if self.plant is not None else self._x

    @property
    def alpha(self) -> np.ndarray:
        """The terminal box centres alpha(k), shape (n,) (zeros for the ellipsoid methods)."""
        return self.terminal.alpha

    @property
    def beta(self) -> float:
        """The terminal box radius beta(k) (NaN for the ellipsoid methods)."""
        return self.terminal.beta

    @property
    def tracker(self) -> Tracker | None:
        """The setpoint targets (None: the origin throughout)."""
        return self._setpoints.tracker

    @property
    def duplicates(self) -> int:
        """Answers ignored as copies (a second answer of an agent for the open round)."""
        return self._guard.duplicates

    @property
    def inputs_refused(self) -> dict[str, int]:
        """Plans refused for inputs outside U_i, per agent name."""
        return self._refusals.counts

    # ------------------------------------------------------------------ inputs
    @property
    def estimates(self) -> bool:
        """The controllers work from an estimate (the scenario's ``estimation``): a plant outside may
        report a subsystem's outputs in place of its state."""
        return self._estimation is not None

    def start(self, x0: np.ndarray | None = None, outputs: Mapping[str, np.ndarray] | None = None) -> list[Action]:
        """Actions that release step 0, round 0.

        ``x0`` (shape (n,)): the state x(0) measured by a plant outside (required then; ignored
        with a simulated plant), NaN in the subsystems whose ``outputs`` y_i(0) (p_i,) it reported
        instead (with estimation only). The terminal sets start from it (with estimation: from
        the estimate).
        """
        if self.plant is None:
            if x0 is None:
                raise ValueError("a coordinator with a plant outside starts from the measured x(0)")
            self._x = np.array(x0, dtype=float)
            if self._estimation is None:
                self.terminal = self.policy.initial(self._x)
                self._step.note = self.terminal.note
        self._outputs = dict(outputs or {})
        self.outputs_reported.update(self._outputs)
        if self._estimation is not None:
            self._estimate = self._estimation.update(0, None, self._estimation.measure(0, self.measured, self._outputs))
            self._x = self._estimation.recorded(self._x, self._estimate)
            self.terminal = self.policy.initial(self.x)
            self._step.note = self.terminal.note
        self._combiner.step_started(self._step, self.x, self.terminal)
        return self._release_round()

    def on_state(self, k: int, x: np.ndarray, outputs: Mapping[str, np.ndarray] | None = None) -> list[Action]:
        """The plant outside measured x(k) (shape (n,); NaN in the subsystems whose ``outputs`` y_i(k)
        it reported instead, as :meth:`start` takes them) after the inputs of step k - 1: the step
        is complete. Returns its actions; none for a state that was not awaited."""
        if self._pending is None or k != self.k + 1:
            return []
        pending, self._pending = self._pending, None
        self._x = np.array(x, dtype=float)
        self._outputs = dict(outputs or {})
        self.outputs_reported.update(self._outputs)
        return self._complete_step(pending, self._x)

    def on_plan(self, msg: PlanMessage) -> tuple[list[Action], str | None]:
        """A plan ``msg`` arrived: accept it, or drop it and say why.

        Returns
        -------
        (actions, reason)
            The actions it triggers (possibly none), and why it was dropped: None when it was
            accepted or ignored as a copy (a second plan of an agent for the open round; the
            first one counts, and ``duplicates`` counts the others), else the reason (see
            :meth:`check`; ``malformed: <error>`` for a message the checks cannot even read).
        """
        i, problem = self._guard.admit(msg, lambda: self.check(msg), self.finished, self._barrier)
        if i is None:
            return [], problem
        self._barrier.accept(i, msg)
        self._step.received_at[i] = self._now()
        excess = input_excess(self.system.subsystems[i].input_set, msg.v) if msg.status in SOLVED else 0.0
        refused: list[Action] = [self._refusals.refuse(i, msg, excess)] if excess > 0 else []
        return refused + self._close_round_if_due(), None

    def on_kept(self, msg: Kept) -> tuple[list[Action], str | None]:
        """Agent ``msg.sender`` kept its shifted plan (an event trigger): the plan is rebuilt here
        from the agent's last plan, x_i(k) and alpha_i(k), and stands as the agent's answer, or the
        notice is dropped and the reason said (as for :meth:`on_plan`)."""
        problem = partial(self._guard.kept_problem, msg, self.k, self.round, self.triggered, self.last_plan)
        i, reason = self._guard.admit(msg, problem, self.finished, self._barrier)
        if i is None:
            return [], reason
        last = self.last_plan[i]
        assert last is not None  # checked by kept_problem
        own = self.system.xs(i)
        point = self._step.point.subsystem(self.system, i)
        kept = self._candidates.kept(i, last, self.k, self.x[own], self.alpha[own], point)
        cost = self._candidates.cost(i, point.plan_around(kept))
        self._barrier.accept(i, PlanMessage(run=msg.run, k=msg.k, round=msg.round, sender=msg.sender, status=KEPT,
                                            z=kept.z, v=kept.v, cost=cost, solve_time=0.0, qp_iterations=0,
                                            sent_at=msg.sent_at))
        self._step.received_at[i] = self._now()
        return self._close_round_if_due(), None

    def check(self, msg: PlanMessage) -> str | None:
        """None if the plan ``msg`` belongs to the open round and has the right shapes; else the reason."""
        return self._guard.plan_problem(msg, self.k, self.round)

    def has_plan(self, name: str) -> bool:
        """True if agent ``name``'s plan for the open round is in (or the agent was marked missed)."""
        i = self.index.get(name)
        return i is not None and self._barrier.has_answered(i)

    def step_opened(self) -> None:
        """The host has begun the open step (sent its release, or opened it with every agent
        lost): the step's time runs from now."""
        self._opened_at = self._now()

    def on_deadline(self, k: int, r: int) -> list[Action]:
        """The deadline of round ``r`` of step ``k`` passed: whoever has not delivered missed it."""
        if self.finished or (k, r) != (self.k, self.round):
            return []
        self._barrier.deadline_passed()
        return self._close_round_if_due()

    def on_agent_lost(self, name: str) -> list[Action]:
        """Liveliness of agent ``name`` disappeared: stop waiting for it and stop releasing to it.

        Its fallback applies from the open round on; the step record notes the loss.
        """
        i = self.index.get(name)
        if i is None or self.finished:
            return []
        if self._barrier.lose(i):
            self._step.add_note(f"agent {name} lost")
        return self._close_round_if_due()

    def on_agent_back(self, name: str) -> bool:
        """Agent ``name`` is ready again: it is released to and waited for from the next round on.

        Returns True if it had been lost (the step record then notes its return).
        """
        i = self.index.get(name)
        if i is None or self.finished or not self._barrier.come_back(i):
            return False
        self._step.add_note(f"agent {name} back")
        return True

    def on_setpoint(self, msg: Setpoint) -> SetpointAnswer:
        """A setpoint request ``msg`` of a supervisory program: take it from the first step whose target
        is not decided yet (k + 1, or k + 2 while step k's state is awaited from a plant outside),
        or refuse it and say why (:meth:`SetpointIntake.answer
        <dmpc.coordinator.setpoint_intake.SetpointIntake.answer>`). Accepted, the record of the
        step it arrived in notes it (the decided step while its state is awaited)."""
        answer, note = self._setpoints.answer(msg, self._first_undecided(), self.finished)
        if note and self._pending is not None:
            old = self._pending.note
            self._pending = replace(self._pending, note=f"{old}; {note}" if old else note)
        elif note:
            self._step.add_note(note)
        return answer

    def _first_undecided(self) -> int:
        """The first step whose target is not decided yet: k + 1, or k + 2 while step k's state is
        awaited from a plant outside."""
        return self.k + (2 if self._pending is not None else 1)

    def setpoint_needs(self, msgs: Sequence[Setpoint]) -> tuple[list[SetpointAnswer | None], list[Request]]:
        """What :meth:`on_setpoint` would need to take the requests ``msgs`` now, in their order: the
        refusal of each that is refused, and the requests whose targets are to be computed first,
        beside the run (:meth:`SetpointIntake.needs <dmpc.coordinator.setpoint_intake.SetpointIntake.needs>`).
        No requests: they can be taken now, and no step will wait for a target."""
        return self._setpoints.needs(msgs, self._first_undecided(), self.finished)

    def setpoint_refusal(self, msg: Setpoint) -> SetpointAnswer | None:
        """The answer that refuses the request ``msg`` now, or None if :meth:`on_setpoint` would take it."""
        return self._setpoints.refusal(msg, self._first_undecided(), self.finished)

    def learn_targets(self, known: Iterable[tuple[Request, Target]]) -> None:
        """Keep the targets ``known`` (request, its target) computed beside the run, for
        :meth:`on_setpoint` and the steps after it."""
        self._setpoints.learn(known)

    # ------------------------------------------------------------------ rounds
    def _now(self) -> float:
        return self._clock() if self._clock is not None else math.nan

    def _release_round(self) -> list[Action]:
        """Open the step's round: release it to every agent not lost (none if all are)."""
        self._barrier.open()
        actions: list[Action] = []
        if not self._barrier.all_lost:
            step = self._step
            plans = self._combiner.released_plans(step, self.last_plan)
            centres, sizes = self.policy.release_all(self.terminal)
            # lost agents are skipped: their plans would not be used, and the first release after
            # their Ready tells them they are back
            actions.append(SendRelease(Release(
                run=self.run_id, k=step.k, round=step.round, x=self.x.copy(), centres=centres, sizes=sizes,
                assumed=plans.assumed, skipped=self._barrier.skipped(self.names), provided=plans.provided,
                target=step.released_target, kept=step.kept_last if step.round == 0 else (), iterate=plans.iterate)))
        actions.append(RoundOpened(self.k, self.round))
        actions.extend(self._close_round_if_due())
        return actions

    def _close_round_if_due(self) -> list[Action]:
        """Once every agent has answered the open round or will not, the round combiner decides:
        another round, or the step's close. Nothing while a decided step awaits its state."""
        if self._pending is not None or not self._barrier.closed:
            return []
        closed = ClosedRound(self._barrier.answers, self._barrier.missed, self.x, self.terminal, self.last_plan)
        outcome = self._combiner.close_round(self._step, closed)
        if isinstance(outcome, AnotherRound):
            self._step.round += 1
            return self._release_round()
        return self._finalise_step(outcome.max_change)

    # ------------------------------------------------------------------ step end
    def _finalise_step(self, max_change: Callable[[], float]) -> list[Action]:
        """Close the step: every agent's input and terminal state decide the next terminal sets and
        (with a simulated plant) x(k+1). ``max_change`` gives the last round's plan change."""
        estimate = self._estimate
        pending = self._closer.close(self._step, self.x.copy(), self.terminal, self.last_plan, self._barrier.lost,
                                     max_change, self._combiner.agent_steps(self._step, self._barrier.lost),
                                     None if estimate is None else estimate.d_hat)
        if estimate is not None:  # the record holds the plant's state, and what the controllers saw of it
            pending = replace(pending, x=self.measured.copy(), estimate=estimate)
        for i, part in enumerate(pending.agents):
            if part.plan is not None:
                self.last_plan[i] = part.plan
        if self.plant is None:
            self._pending = pending
            return [ApplyInputs(self.k, pending.u)]
        return self._complete_step(pending, self.plant.step(pending.u))

    def _complete_step(self, pending: PendingStep, x_next: np.ndarray) -> list[Action]:
        """The step's record with x(k+1) (shape (n,)), then the next step's release (or the end)."""
        if self._estimation is not None:
            # the estimate of step k + 1 comes before the record: a state a plant outside did not report
            # (only its outputs) is recorded as the estimate that agrees with them
            self._estimate = self._estimation.update(pending.k + 1, pending.u,
                                                     self._estimation.measure(pending.k + 1, x_next, self._outputs))
            x_next = self._estimation.recorded(x_next, self._estimate)
            if self.plant is None:
                self._x = x_next
        actions: list[Action] = [StepCompleted(partial(pending.record, x_next.copy(), self._now() - self._opened_at,
                                                       self.system))]
        self.terminal = pending.terminal
        kept = tuple(self.names[i] for i, part in enumerate(pending.agents) if part.status == KEPT)
        self._step = OpenStep(k=pending.k + 1, target=pending.target, kept_last=kept)
        if self._step.k >= self.options.steps:
            self.finished = True
            actions.append(RunFinished("finished"))
            return actions
        self._combiner.step_started(self._step, self.x, self.terminal)
        actions.extend(self._release_round())
        return actions

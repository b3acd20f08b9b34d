"""The round combiner of the cooperative method ``tv-box-coop`` (docs/algorithm.md, "Cooperative DMPC").

The step holds one iterate of the whole system (:class:`dmpc.cooperative.rounds.CooperativeRounds`).
Every release carries it; every agent answers with its proposal, its own inputs over the horizon;
a closed round combines the usable proposals into the next iterate, so every iterate stays a
feasible point of the centralised problem and its cost never rises. An agent without a usable
proposal (missed, lost, its QP failed, its inputs refused) keeps its inputs at the iterate. Rounds
go on while rounds are left, nobody missed and the iterate still moves by the tolerance or more.

The step's plans are the last iterate's parts; the next step starts from that iterate shifted,
with the terminal controller at its tail, from the measured state.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from dmpc.cooperative.iterate import Iterate, StepRule
from dmpc.cooperative.rounds import CooperativeRounds
from dmpc.coordinator.combiner import AnotherRound, ClosedRound, FinishStep, ReleasedPlans, RoundOutcome
from dmpc.coordinator.open_step import OpenStep
from dmpc.coordinator.refusals import INPUT_REFUSED, InputRefusals
from dmpc.coordinator.step_close import AgentStep
from dmpc.core.steps import ProtocolOptions
from dmpc.core.system import CoupledSystem
from dmpc.core.trajectories import Plan
from dmpc.methods.policy import TerminalPolicy, TerminalState
from dmpc.offline import ControllerDesign


class CooperativeCombiner:
    """Cooperative rounds: the agents' proposals combined into one iterate per round.

    Parameters
    ----------
    system : CoupledSystem
    design : ControllerDesign
    policy : TerminalPolicy
        The time-varying boxes (the joint terminal rows of the first iterate's centralised QP).
    options : ProtocolOptions
        Rounds and tolerances.
    refusals : InputRefusals
        Which answers were refused (not usable as proposals).
    rule : {"line", "equal"}
        How a round's proposals combine (:func:`dmpc.cooperative.iterate.combine`).
    """

    def __init__(self, system: CoupledSystem, design: ControllerDesign, policy: TerminalPolicy,
                 options: ProtocolOptions, refusals: InputRefusals, rule: StepRule = "line") -> None:
        self.system = system
        self.policy = policy
        self.options = options
        self.refusals = refusals
        self.rounds = CooperativeRounds(system, design.gains.K, design.gains.P, design.gains.P_global(),
                                        design.horizon, rule)
        self.iterate: Iterate | None = None  # the open step's, plant coordinates

    def step_started(self, step: OpenStep, x: np.ndarray, terminal: TerminalState) -> None:
        """The open step begins at the measured x (n,): its first iterate is the last step's shifted,
        or at k = 0 the terminal controller's rollout or the centralised QP's plan (noted)."""
        if self.iterate is not None and step.k > 0:
            self.iterate = self.rounds.next_step(self.iterate, x, step.target)
            return
        first = self.rounds.first(x, step.target, terminal.alpha, terminal.beta, self.policy.joint_terminal(terminal))
        self.iterate = first.iterate
        if first.note:
            step.add_note(first.note)

    def released_plans(self, step: OpenStep, last_plan: Sequence[Plan | None]) -> ReleasedPlans:
        """No neighbour plan is named (every row (-1, -1)): the release carries the iterate.

        Parameters
        ----------
        step : OpenStep
            The open step (its iterate is this combiner's, set by :meth:`step_started`).
        last_plan : sequence of Plan or None
            Per agent, its last plan: unused, as no release of the method names one.
        """
        assert self.iterate is not None, "step_started opens every step"
        return ReleasedPlans(np.full((self.system.M, 2), -1, dtype=np.int64),
                             iterate=(self.iterate.z, self.iterate.v))

    def close_round(self, step: OpenStep, closed: ClosedRound) -> RoundOutcome:
        """Combine the round's usable proposals into the next iterate; another round while rounds
        are left, nobody missed this one and the iterate moved by the tolerance or more.

        Parameters
        ----------
        step : OpenStep
            The open step: it takes the round's answers (as proposals, none of them the step's
            plan), and its step, round and target decide the rounds allowed, the tolerance and the
            coordinates.
        closed : ClosedRound
            The closed round: its answers (each usable one's v (N, m_i) a proposal), who missed it
            and the step's terminal box.
        """
        assert self.iterate is not None, "step_started opens every step"
        step.take_round(closed.answers, lambda i, msg: False)  # the answers are proposals, not the step's plans
        proposals = {i: msg.v for i, msg in closed.answers.items() if self.refusals.usable(i, msg)}
        done = self.rounds.combine(self.iterate, proposals, step.target, closed.terminal.alpha, closed.terminal.beta)
        self.iterate = done.iterate
        first = step.k == 0
        rounds_allowed = self.options.initial_rounds if first else self.options.rounds
        tolerance = self.options.initial_tolerance if first else self.options.tolerance
        change = done.change
        if step.round + 1 < rounds_allowed and not closed.missed and not change < tolerance:
            return AnotherRound()
        return FinishStep(lambda: change)

    def agent_steps(self, step: OpenStep, lost: set[int]) -> list[AgentStep]:
        """Every agent's part of the step from the last iterate: its inputs, states, terminal state and
        its subsystem's part of the cost. An agent whose last answer was not a usable proposal kept
        its inputs at the iterate: recorded as a fallback, with the reason.

        Parameters
        ----------
        step : OpenStep
            The closing step, with each agent's last answer.
        lost : set of int
            The agents lost now: one without an answer is recorded as ``lost`` rather than ``missed``.
        """
        assert self.iterate is not None, "step_started opens every step"
        parts = self.rounds.parts(self.iterate, step.target)
        agents = []
        for i, part in enumerate(parts):
            msg = step.answers.get(i)
            plan = Plan(step.k, step.round, part.z, part.v)
            if msg is None:
                status, solve_time, iterations, reason = "missed", math.nan, 0, "lost" if i in lost else "missed"
            else:
                status, solve_time, iterations = msg.status, msg.solve_time, msg.qp_iterations
                reason = "" if self.refusals.usable(i, msg) else (
                    INPUT_REFUSED if self.refusals.refused(i, msg) else f"qp {msg.status}")
            agents.append(AgentStep(u=part.u, eta=part.eta, J=part.cost, status=status, fallback=bool(reason),
                                    reason=reason, solve_time=solve_time, qp_iterations=iterations,
                                    latency=step.latency(i), z=part.z, v=part.v, plan=plan))
        return agents

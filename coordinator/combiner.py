"""How a closed round becomes the step's plans, and whether another round follows.

This is the one place where the coordinator decides between another round of the step and the
step's close. A :class:`RoundCombiner` takes the answers of a round whose barrier closed into the
open step (:class:`~dmpc.coordinator.open_step.OpenStep`) and says :class:`AnotherRound` or
:class:`FinishStep`; it also says which plans the next release names (:class:`ReleasedPlans`).
The coordinator does what it says, and nothing else of it depends on how the answers combine.

:class:`JacobiRounds` is the combiner of every method today (docs/algorithm.md, "Online step k,
agent i"): each agent's answer is its plan of the step; rounds go on while the plans move
(k = 0: up to ``initial_rounds`` and ``initial_tolerance``, later ``rounds`` and ``tolerance``),
and a round 0 at k = 0 with infeasible agents is seeded from the centralised QP. A method whose
coordinator combines the agents' proposals into one iterate would be another combiner: it takes
the proposals into the step in its ``close_round``, and releases the iterate through
:meth:`RoundCombiner.released_plans`.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence, Set
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from dmpc.bus.messages import PlanMessage
from dmpc.coordinator.candidates import Candidates
from dmpc.coordinator.open_step import OpenStep
from dmpc.coordinator.refusals import InputRefusals
from dmpc.coordinator.step_close import AgentStep
from dmpc.core.central_qp import CentralQP
from dmpc.core.qp_status import PLANNED, QPStatus
from dmpc.core.steps import NO_SEED, ProtocolOptions
from dmpc.core.system import CoupledSystem
from dmpc.core.trajectories import Plan
from dmpc.methods.policy import TerminalPolicy, TerminalState
from dmpc.offline import ControllerDesign


@dataclass(frozen=True)
class ClosedRound:
    """A round whose barrier closed, as the combiner sees it.

    Attributes
    ----------
    answers : mapping i -> PlanMessage
        The round's answers (a kept plan as a message of status ``kept``).
    missed : set of int
        The agents without an answer in it (deadline, lost).
    x : ndarray, shape (n,)
        The measured state x(k).
    terminal : TerminalState
        The step's terminal sets.
    last_plan : sequence of Plan or None
        Per agent: its last plan, of a step before (None if it never had one).
    """

    answers: Mapping[int, PlanMessage]
    missed: Set[int]
    x: np.ndarray
    terminal: TerminalState
    last_plan: Sequence[Plan | None]


@dataclass(frozen=True)
class AnotherRound:
    """Release the next round of the open step."""


@dataclass(frozen=True)
class FinishStep:
    """Close the open step with the plans it holds; ``max_change`` gives the last round's plan
    change for the record (measured when the record is built, or already known)."""

    max_change: Callable[[], float]


RoundOutcome = AnotherRound | FinishStep


@dataclass(frozen=True)
class ReleasedPlans:
    """What a release says of the plans the agents build on.

    Attributes
    ----------
    assumed : ndarray of int64, shape (M, 2)
        Row j: the plan (k', round') of agent j that its neighbours build its assumed trajectory
        from; (-1, -1) for none (a K-rollout).
    provided : dict name -> (z, v)
        Plans the coordinator supplies itself, which no agent published.
    iterate : (ndarray (N+1, n), ndarray (N, m)) or None
        The cooperative iterate the agents propose against (``tv-box-coop``); None otherwise.
    """

    assumed: np.ndarray
    provided: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    iterate: tuple[np.ndarray, np.ndarray] | None = None


class RoundCombiner(Protocol):
    """How the rounds of a step combine: what a closed round adds to the step, whether another
    round follows, which plans each release names, and the agents' parts of the closed step."""

    def step_started(self, step: OpenStep, x: np.ndarray, terminal: TerminalState) -> None:
        """The open step ``step`` begins at the measured x (n,) with the terminal sets ``terminal``."""
        ...

    def agent_steps(self, step: OpenStep, lost: set[int]) -> list[AgentStep] | None:
        """The agents' parts of the closing ``step`` (``lost``: the agents lost now), or None for
        the step closer's own (each agent's plan of the step, or its fallback)."""
        ...

    def close_round(self, step: OpenStep, closed: ClosedRound) -> RoundOutcome:
        """Take the closed round into ``step`` and decide: another round, or the step's close."""
        ...

    def released_plans(self, step: OpenStep, last_plan: Sequence[Plan | None]) -> ReleasedPlans:
        """The plans the release of ``step``'s open round names, given each agent's plan of a step before
        (``last_plan``, None where it never had one)."""
        ...


class JacobiRounds:
    """Jacobi rounds: each agent's answer is its plan, and rounds go on while the plans move.

    Parameters
    ----------
    system : CoupledSystem
    design : ControllerDesign
    policy : TerminalPolicy
        Gives the joint terminal rows of the centralised seed.
    options : ProtocolOptions
        Rounds and tolerances.
    candidates : Candidates
        The shifted candidates round 0's plans are compared with.
    refusals : InputRefusals
        Which answers were refused (not usable as plans).

    Attributes
    ----------
    seeded : dict i -> Plan
        The centralised QP's plans seeded at k = 0: no agent published them, so every release
        that refers to one carries it (its agent may keep it for many rounds, even steps).
    """

    def __init__(self, system: CoupledSystem, design: ControllerDesign, policy: TerminalPolicy,
                 options: ProtocolOptions, candidates: Candidates, refusals: InputRefusals) -> None:
        self.system = system
        self.design = design
        self.policy = policy
        self.options = options
        self.candidates = candidates
        self.refusals = refusals
        self.names = [s.name for s in system.subsystems]
        self.seeded: dict[int, Plan] = {}

    def step_started(self, step: OpenStep, x: np.ndarray, terminal: TerminalState) -> None:
        """Nothing to prepare: the agents build on their plans (``step``, ``x`` and ``terminal`` unused)."""

    def agent_steps(self, step: OpenStep, lost: set[int]) -> list[AgentStep] | None:
        """None: each agent's part is its plan of the ``step`` or its fallback (``lost`` unused)."""
        return None

    def close_round(self, step: OpenStep, closed: ClosedRound) -> RoundOutcome:
        """The ``closed`` round's usable answers become the agents' plans of the step; another round follows
        while rounds are left, nobody missed this one and the plans still moved by the tolerance
        or more (round 0 never converges)."""
        step.take_round(closed.answers, self.refusals.usable)
        infeasible = [self.names[i] for i, msg in closed.answers.items() if msg.status not in PLANNED]
        if step.k == 0 and step.round == 0 and infeasible and not closed.missed:
            self._seed_from_centralized(step, closed, infeasible)
        first = step.k == 0
        rounds_allowed = self.options.initial_rounds if first else self.options.rounds
        tolerance = self.options.initial_tolerance if first else self.options.tolerance
        another = step.round + 1 < rounds_allowed and not closed.missed
        change = self._change_later(step, closed)() if another and step.round > 0 else None
        if another and not (change is not None and change < tolerance):
            return AnotherRound()
        if change is None:  # only the record needs it: measured after the next release is out
            return FinishStep(self._change_later(step, closed))
        return FinishStep(lambda: change)

    def released_plans(self, step: OpenStep, last_plan: Sequence[Plan | None]) -> ReleasedPlans:
        """Each agent's reference in the open round of ``step`` (:meth:`OpenStep.reference`, from
        ``last_plan``, each agent's plan of a step before), and the seeded plans among them."""
        assumed = np.full((self.system.M, 2), -1, dtype=np.int64)
        references = [step.reference(j, last_plan) for j in range(self.system.M)]
        for j, ref in enumerate(references):
            if ref is not None:
                assumed[j] = (ref.k, ref.round)
        provided = {self.names[j]: (plan.z, plan.v) for j, plan in self.seeded.items() if references[j] is plan}
        return ReleasedPlans(assumed, provided)

    def _seed_from_centralized(self, step: OpenStep, closed: ClosedRound, infeasible: list[str]) -> None:
        """Replace the first round's plans by the centralised QP's plan
        (docs/algorithm.md, "Online step k, agent i", item 4)."""
        T, lower, upper = self.policy.joint_terminal(closed.terminal)
        qp = CentralQP(self.system, self.design.gains.P_global(), self.design.horizon, terminal="rows", rows=T)
        sol = qp.solve_rows(closed.x, lower, upper)
        if not sol.status.feasible:
            step.add_note(f"k=0: round 0 infeasible for agents {', '.join(infeasible)}; {NO_SEED}"
                          f"{_seed_failure(sol.status)}{_start_check_finding(self.design.start, self.design.horizon)}")
            return
        for i in range(self.system.M):
            plan = Plan(0, 0, sol.z[:, self.system.xs(i)], sol.v[:, self.system.us(i)])
            step.latest[i] = plan
            self.seeded[i] = plan
        step.add_note(f"k=0: round 0 infeasible from decoupled rollouts for agents {', '.join(infeasible)}; "
                      "started from the centralised QP's plan")

    def _change_later(self, step: OpenStep, closed: ClosedRound) -> Callable[[], float]:
        """The largest change of the closing round's plans, to be measured later: max over agents of
        max |z - z_ref|, |v - v_ref|.

        Round 0 compares each plan with what the neighbours assumed of it: the agent's candidate,
        its last plan shifted to step k and continued with K_i (at k = 0, or without any plan,
        the decoupled K-rollout from x_i(k)), with the measured x_i(k) as first state, both taken
        around the step's operating point. Later rounds compare with the agent's plan of the
        previous round; inf if it has none there (its QP was infeasible), so the rounds go on.
        Agents without a plan in this round do not count (0 if none has one).

        What it reads is taken now: the plans are never changed once received, and the step's
        state is replaced by the next step's.
        """
        k, r, latest, previous, point = step.k, step.round, step.latest, step.previous_round, step.point
        x_parts = self.system.split_state(closed.x.copy()) if r == 0 else []
        last = list(closed.last_plan) if r == 0 else []
        system, candidates = self.system, self.candidates

        def change() -> float:
            top = 0.0
            for i, plan in latest.items():
                if r == 0:
                    part = point.subsystem(system, i)
                    x_i = part.state_around(x_parts[i])
                    z_ref, v_ref = candidates.candidate(i, part.plan_around(last[i]), k, x_i)
                    z_ref[0] = x_i
                    z_ref, v_ref = part.trajectory_back(z_ref, v_ref)
                else:
                    prev = previous.get(i)
                    if prev is None:
                        return float("inf")
                    z_ref, v_ref = prev.z, prev.v
                top = max(top, float(np.abs(plan.z - z_ref).max()), float(np.abs(plan.v - v_ref).max()))
            return top

        return change


def _seed_failure(status: QPStatus) -> str:
    """Why the centralised QP gave no seed, in words."""
    if status is QPStatus.INFEASIBLE:
        return "OSQP reported the centralised QP infeasible"
    if status is QPStatus.MAX_ITER:
        return "OSQP stopped at its iteration cap on the centralised QP (max_iter) without a plan"
    return f"the centralised QP ended with status {status.value}"


def _start_check_finding(start: dict[str, object] | None, horizon: int) -> str:
    """What the design's start check found of x(0) (``Design.start``), as the rest of the seed note."""
    start = start or {}
    if start.get("centrally_feasible") is True or start.get("horizon") == "auto":
        return (f", although the start check (an LP) found x(0) feasible for the centralised problem at N = "
                f"{horizon}: x(0) is near the edge of what N = {horizon} allows; a longer horizon "
                "(horizon: auto) gives the plans room")
    if "centrally_feasible" in start:
        return "; the start check could not decide whether x(0) is feasible for the centralised problem"
    return "; the start was not checked (design.check_start: false)"

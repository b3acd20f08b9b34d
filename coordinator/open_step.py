"""The step the coordinator works on: everything it holds of it, made new for every step.

Nothing here outlives its step: when a step completes, the coordinator builds the next step's
:class:`OpenStep` from what the closed one decided (its target, the agents that kept their plan),
and the closed one is only read by the record it left (:class:`~dmpc.coordinator.step_close.PendingStep`).
"""
from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from dmpc.bus.messages import PlanMessage
from dmpc.core.trajectories import OperatingPoint, Plan
from dmpc.tracking.targets import Target


@dataclass(eq=False)
class OpenStep:
    """Step ``k`` while its rounds run.

    Attributes
    ----------
    k : int
    target : Target
        The setpoint target the step is controlled around: x_s (n,), u_s (m,), the scale of its
        terminal set; the origin without setpoints.
    kept_last : tuple of str
        The agents that kept their plan at step k - 1 (an event trigger): round 0's release names them.
    note : str
        What the step's record notes so far (``; ``-separated).
    round : int
        The Jacobi round open now.
    latest : dict i -> Plan
        Per agent: its plan of the step so far, the latest one it delivered that was usable (a
        solved or kept plan, not refused), or the centralised seed at k = 0.
    previous_round : dict i -> Plan
        ``latest`` as it was before the last round closed (what that round's plans are compared with).
    answers : dict i -> PlanMessage
        Per agent: its last answer of the step (a kept plan as a message of status ``kept``).
    received_at : dict i -> float
        Per agent: when its answer in ``answers`` was accepted, on the host's clock.
    solve_reason : dict i -> str
        Per agent: why it solved in round 0 (an event trigger; "" without one).
    point : OperatingPoint
        (x_s, u_s) of ``target``: the one operating point the step's plans move around.
    """

    k: int
    target: Target
    kept_last: tuple[str, ...] = ()
    note: str = ""
    round: int = 0
    latest: dict[int, Plan] = field(default_factory=dict)
    previous_round: dict[int, Plan] = field(default_factory=dict)
    answers: dict[int, PlanMessage] = field(default_factory=dict)
    received_at: dict[int, float] = field(default_factory=dict)
    solve_reason: dict[int, str] = field(default_factory=dict)
    point: OperatingPoint = field(init=False)

    def __post_init__(self) -> None:
        self.point = OperatingPoint(self.target.x, self.target.u)

    @property
    def released_target(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The target as a release carries it: (x_s, u_s), or None at the origin, which the wire
        leaves out (:class:`~dmpc.bus.messages.Release`)."""
        return None if self.target.is_origin else (self.target.x, self.target.u)

    def add_note(self, text: str) -> None:
        """Add ``text`` to what the step's record notes."""
        self.note = f"{self.note}; {text}" if self.note else text

    def reference(self, j: int, last_plan: Sequence[Plan | None]) -> Plan | None:
        """The plan of agent j its neighbours build their assumption from in the open round: its
        plan of this step after round 0, else its last plan (``last_plan[j]``; None: a K-rollout)."""
        if self.round > 0 and j in self.latest:
            return self.latest[j]
        return last_plan[j]

    def take_round(self, answers: Mapping[int, PlanMessage], usable: Callable[[int, PlanMessage], bool]) -> None:
        """The answers of the round that closed (agent i -> its message) become the agents' answers
        of the step, and each ``usable`` one its plan of the step."""
        self.previous_round = dict(self.latest)
        for i, msg in answers.items():
            self.answers[i] = msg
            if self.round == 0:  # the trigger decides in round 0; later rounds of the step (k = 0) only refine
                self.solve_reason[i] = msg.reason
            if usable(i, msg):
                self.latest[i] = Plan(msg.k, msg.round, msg.z, msg.v)

    def latency(self, i: int) -> float:
        """Seconds from agent i publishing its answer to the host accepting it (NaN without one)."""
        msg = self.answers.get(i)
        return math.nan if msg is None else self.received_at.get(i, math.nan) - msg.sent_at

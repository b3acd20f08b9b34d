"""Plans whose inputs leave U_i: refused, though they stand as their agent's answer.

An agent's solved plan is checked against its input set U_i when it arrives
(:func:`~dmpc.coordinator.barrier.input_excess`); a plan beyond the tolerance is the agent's answer
for the round (the barrier does not wait for another), but its fallback applies, as for an
infeasible QP (docs/faults.md; docs/security.md).
"""
from __future__ import annotations

from dmpc.bus.messages import PlanMessage
from dmpc.coordinator.actions import PlanRefused
from dmpc.core.qp_status import PLANNED

# A solved plan may leave U_i by this much times max(1, |bound|): OSQP solves to about 1e-7,
# so an honest plan stays well inside, and anything beyond is refused.
INPUT_TOLERANCE = 1e-6
INPUT_REFUSED = "input outside U_i"


class InputRefusals:
    """The plans refused in a run, and how many per agent.

    Attributes
    ----------
    counts : dict name -> int
        Plans refused per agent name, for the run (``inputs_refused`` of ``summary.json``).
    """

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}
        self._last: dict[int, PlanMessage] = {}  # per agent: its last plan refused (kept until replaced)

    def refuse(self, i: int, msg: PlanMessage, excess: float) -> PlanRefused:
        """Agent i's plan ``msg`` leaves U_i by ``excess``: note it and count it."""
        self._last[i] = msg
        count = self.counts[msg.sender] = self.counts.get(msg.sender, 0) + 1
        return PlanRefused(msg.sender, msg.k, msg.round, excess, count)

    def refused(self, i: int, msg: PlanMessage) -> bool:
        """True if ``msg`` is agent i's plan refused last."""
        return self._last.get(i) is msg

    def usable(self, i: int, msg: PlanMessage | None) -> bool:
        """True if ``msg`` is a solved (or kept) plan of agent i that was not refused."""
        return msg is not None and msg.status in PLANNED and not self.refused(i, msg)

"""The outcome of a QP solve in the project's own terms, and which outcomes give a plan.

Plans carry the status as its string value on the wire, so :data:`SOLVED` holds strings. Kept
apart from :mod:`dmpc.core.mpc_qp` so that code which only reads statuses (the codec, the records)
does not import the solver.
"""
from __future__ import annotations

import enum


class QPStatus(str, enum.Enum):
    """Solver outcome in the project's own terms."""

    SOLVED = "solved"
    INACCURATE = "solved_inaccurate"
    INFEASIBLE = "infeasible"
    UNBOUNDED = "unbounded"
    MAX_ITER = "max_iter"
    ERROR = "error"

    @property
    def feasible(self) -> bool:
        return self.value in SOLVED


SOLVED = frozenset({QPStatus.SOLVED.value, QPStatus.INACCURATE.value})
"""The statuses, as plans carry them, of a solve that produced a plan."""

KEPT = "kept"
"""The status of an agent's answer when its event trigger kept its shifted plan: a plan, no solve."""

PLANNED = SOLVED | {KEPT}
"""The statuses of an answer that gives the step a plan of the agent's own."""

"""The one guard of an agent's answer: a plan message (:meth:`Coordinator.on_plan`) and a kept
notice (:meth:`Coordinator.on_kept`) pass the same checks, in the same order.

1. what it must be to be read at all: the run, a known sender, the open step and round (an older
   one is ``stale``, a later one ``future``), then what its kind needs (a plan's shapes, status and
   range; a kept notice's plan of the step before);
2. the run still going on (after its end an answer is ignored, not dropped);
3. the agent's first answer of the round (a copy is ignored and counted in ``duplicates``).
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence

from dmpc.bus.messages import Kept, PlanMessage
from dmpc.coordinator.round_barrier import RoundBarrier
from dmpc.core.qp_status import SOLVED, QPStatus
from dmpc.core.system import CoupledSystem
from dmpc.core.trajectories import Plan
from dmpc.security.rejects import MAX_MAGNITUDE, STALE, clearly_in_range, magnitude

KNOWN_STATUSES = frozenset(s.value for s in QPStatus)
NO_PLAN_TO_KEEP = "kept without a plan of the previous step"


class AnswerGuard:
    """The checks of the agents' answers in one run.

    Parameters
    ----------
    system : CoupledSystem
        Names the agents (its subsystems, in order) and their sizes n_i, m_i.
    run_id : str
    horizon : int
        N: a plan has z of shape (N + 1, n_i) and v of shape (N, m_i).

    Attributes
    ----------
    duplicates : int
        Answers ignored as copies (a second answer of an agent for the open round).
    """

    def __init__(self, system: CoupledSystem, run_id: str, horizon: int) -> None:
        self.system = system
        self.run_id = run_id
        self.N = horizon
        self.index = {s.name: i for i, s in enumerate(system.subsystems)}
        self.duplicates = 0

    def admit(self, msg: PlanMessage | Kept, problem: Callable[[], str | None], finished: bool,
              barrier: RoundBarrier) -> tuple[int | None, str | None]:
        """Whether the answer ``msg`` counts for the open round.

        Parameters
        ----------
        msg : PlanMessage or Kept
        problem : callable () -> str or None
            Its checks (:meth:`plan_problem` or :meth:`kept_problem`): why it is dropped, or None.
        finished : bool
            The run is over.
        barrier : RoundBarrier
            Who answered the open round already.

        Returns
        -------
        (i, reason)
            ``(i, None)``: agent i's answer, to be taken. ``(None, reason)``: dropped, and why
            (``malformed: <error>`` for a message the checks cannot even read). ``(None, None)``:
            ignored (the run is over, or a copy: counted in ``duplicates``).
        """
        try:
            reason = problem()
        except Exception as exc:  # noqa: BLE001 - a malformed message must not stop the run
            reason = f"malformed: {type(exc).__name__}"
        if reason is not None:
            return None, reason
        if finished:
            return None, None
        i = self.index[msg.sender]
        if barrier.has_answered(i):
            self.duplicates += 1
            return None, None
        return i, None

    def sender_problem(self, msg: PlanMessage | Kept, k: int, round: int) -> str | None:
        """None if the answer is of this run, from a known agent, for step ``k``, round ``round``;
        else the reason (``wrong run``, ``unknown sender``, ``stale`` or ``future``).

        Parameters
        ----------
        msg : PlanMessage or Kept
            The answer, whose ``run``, ``sender``, ``k`` and ``round`` are checked.
        k, round : int
            The open step and round.
        """
        if msg.run != self.run_id:
            return "wrong run"
        if msg.sender not in self.index:
            return "unknown sender"
        if (msg.k, msg.round) != (k, round):
            return STALE if (msg.k, msg.round) < (k, round) else "future"
        return None

    def plan_problem(self, msg: PlanMessage, k: int, round: int) -> str | None:
        """None if the plan belongs to the open round (step ``k``, round ``round``) and has the
        right shapes, a known status and numbers in range; else the reason.

        Parameters
        ----------
        msg : PlanMessage
            The plan: its sender as :meth:`sender_problem` checks it, then z (N + 1, n_i),
            v (N, m_i), its status and, when solved, the magnitude of z, v and its cost.
        k, round : int
            The open step and round.
        """
        problem = self.sender_problem(msg, k, round)
        if problem is not None:
            return problem
        sub = self.system.subsystems[self.index[msg.sender]]
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

    def kept_problem(self, msg: Kept, k: int, round: int, triggered: bool,
                     last_plan: Sequence[Plan | None]) -> str | None:
        """None if the notice belongs to the open round 0 of a run with an event trigger, from an
        agent whose last plan (``last_plan[i]``) is of step k - 1; else the reason.

        Parameters
        ----------
        msg : Kept
            The kept notice, its sender checked as :meth:`sender_problem` does.
        k, round : int
            The open step and round.
        triggered : bool
            The agents have an event trigger (without one, no notice is taken).
        last_plan : sequence of Plan or None
            Per agent, its last plan (None if it never had one).
        """
        problem = self.sender_problem(msg, k, round)
        if problem is not None:
            return problem
        last = last_plan[self.index[msg.sender]]
        if not triggered or round != 0 or last is None or last.k != k - 1:
            return NO_PLAN_TO_KEEP
        return None

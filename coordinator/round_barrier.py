"""The barrier of one round: who answered, who will not, and when the round closes.

A round is released to every agent that is not lost; it closes once every agent has answered or
will not: it missed the round's deadline, or its liveliness went (lost). A lost agent is skipped
from every release until it is back, and counts as having missed each round meanwhile.
"""
from __future__ import annotations

from collections.abc import Sequence

from dmpc.bus.messages import PlanMessage


class RoundBarrier:
    """Who answered the open round, who missed it, who is lost.

    Parameters
    ----------
    M : int
        The number of agents (indexed 0..M-1 in the scenario's order).

    Attributes
    ----------
    answers : dict i -> PlanMessage
        The answers accepted in the open round (a kept plan as a message of status ``kept``).
    missed : set of int
        The agents that will not answer the open round: its deadline passed, or they are lost.
    lost : set of int
        The agents whose liveliness went: not released to, not waited for, until they are back.
    """

    def __init__(self, M: int) -> None:
        self.M = M
        self.answers: dict[int, PlanMessage] = {}
        self.missed: set[int] = set()
        self.lost: set[int] = set()

    def open(self) -> None:
        """A new round: nobody has answered, and the lost agents have missed it already."""
        self.answers = {}
        self.missed = set(self.lost)

    def has_answered(self, i: int) -> bool:
        """True if agent i's answer of the open round is in, or it was marked as missing it."""
        return i in self.answers or i in self.missed

    def accept(self, i: int, msg: PlanMessage) -> None:
        """Take agent i's answer of the open round.

        Parameters
        ----------
        i : int
            The agent's index.
        msg : PlanMessage
            Its answer, already checked (a kept plan as a message of status ``kept``); it replaces
            one taken before in the round.
        """
        self.answers[i] = msg

    def deadline_passed(self) -> None:
        """The open round's deadline passed: whoever has not answered missed it."""
        self.missed.update(i for i in range(self.M) if i not in self.answers)

    def lose(self, i: int) -> bool:
        """Agent i is lost: it misses the open round unless it has answered. True if it was not lost before."""
        newly = i not in self.lost
        self.lost.add(i)
        if i not in self.answers:
            self.missed.add(i)
        return newly

    def come_back(self, i: int) -> bool:
        """Agent i is ready again: released to and waited for from the next round on. True if it was lost."""
        if i not in self.lost:
            return False
        self.lost.discard(i)
        return True

    @property
    def all_lost(self) -> bool:
        """True when every agent is lost (a round is then opened without a release)."""
        return len(self.lost) >= self.M

    @property
    def closed(self) -> bool:
        """True once every agent has answered the open round or will not."""
        answered, missed = len(self.answers), self.missed
        if answered + len(missed) < self.M:
            return False
        return not (missed and answered + len(missed - self.answers.keys()) < self.M)

    def skipped(self, names: Sequence[str]) -> tuple[str, ...]:
        """The names of the lost agents, in index order: a release skips them."""
        return tuple(names[i] for i in sorted(self.lost))

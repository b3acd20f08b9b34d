"""What the coordinator asks its host to do: the actions its methods return.

The coordinator (:class:`dmpc.coordinator.barrier.Coordinator`) never touches the bus, the plant
outside or the records; each of its methods returns a list of these, in the order the host
carries them out (coordinator/node.py over a bus, dmpc/runtime/direct.py by function calls).
They are importable from :mod:`dmpc.coordinator.barrier` too.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dmpc.bus.messages import Release
from dmpc.core.steps import StepRecord


@dataclass(frozen=True)
class SendRelease:
    """Send ``release`` to every agent (one broadcast)."""

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

    Parameters
    ----------
    build : callable () -> StepRecord
        Builds the record; called once, on the first read.
    """

    __slots__ = ("_build", "_record")

    def __init__(self, build: Callable[[], StepRecord]) -> None:
        self._build: Callable[[], StepRecord] | None = build
        self._record: StepRecord | None = None

    @property
    def record(self) -> StepRecord:
        """The step's record (built on the first read)."""
        if self._record is None:
            assert self._build is not None  # dropped only once the record is built
            self._record, self._build = self._build(), None
        return self._record


@dataclass(frozen=True)
class ApplyInputs:
    """The step's inputs are decided: the host has the plant apply u(k) (shape (m,)) and answers
    with :meth:`Coordinator.on_state <dmpc.coordinator.barrier.Coordinator.on_state>` (only with
    an outside plant)."""

    k: int
    u: np.ndarray


@dataclass(frozen=True)
class PlanRefused:
    """The plan of agent ``name`` for step ``k``, round ``round``, leaves U_i by ``excess``
    (beyond :data:`~dmpc.coordinator.refusals.INPUT_TOLERANCE`): it stands as the agent's answer,
    its fallback applies, and it is the agent's ``count``-th refusal of the run."""

    name: str
    k: int
    round: int
    excess: float
    count: int


@dataclass(frozen=True)
class RunFinished:
    """The run is over (``reason``: ``finished``): the host stops the agents."""

    reason: str


Action = SendRelease | RoundOpened | StepCompleted | ApplyInputs | PlanRefused | RunFinished
"""Anything a coordinator method returns for its host to carry out."""

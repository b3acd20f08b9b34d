"""A distributed run without a bus: the coordinator's releases answered by direct solves.

The same Coordinator and AgentControllers as ``dmpc simulate``, wired together by function
calls instead of messages: no codec, no event loop, no clock (the records' latency and step
time are NaN). Each agent answers a release through the same AgentController.answer as over a
bus. The agents' QPs are set up once and reused for every run, so many runs from different
initial states (the region of attraction) cost only their solves. Fault-free runs only: every
plan arrives.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from dmpc.agents.controller import AgentController
from dmpc.agents.cooperative import CooperativeController
from dmpc.bus.messages import Kept, PlanMessage, Release
from dmpc.coordinator.barrier import Coordinator, SendRelease, StepCompleted
from dmpc.core.steps import Coupling, ProtocolOptions, StepRecord
from dmpc.core.system import CoupledSystem
from dmpc.core.trajectories import Plan
from dmpc.methods import Method, method_spec, terminal_policy
from dmpc.offline import ControllerDesign
from dmpc.plant.dynamics import Plant

RUN_ID = "direct"


class DirectLoop:
    """The distributed closed loop of one method, set up once.

    Parameters
    ----------
    system : CoupledSystem
    design : ControllerDesign
    protocol : ProtocolOptions
    method : str
        A distributed method of :mod:`dmpc.methods`.
    coupling : {"feedforward", "nominal"}
    """

    def __init__(self, system: CoupledSystem, design: ControllerDesign, protocol: ProtocolOptions, method: Method,
                 coupling: Coupling = "feedforward") -> None:
        self.system = system
        self.design = design
        self.protocol = protocol
        self.policy = terminal_policy(method, system, design)
        self.cooperative = method_spec(method).cooperative
        self.controllers: list[AgentController] | list[CooperativeController] = (
            [CooperativeController(system, design, i) for i in range(system.M)] if self.cooperative else
            [AgentController(system, design, i, coupling=coupling, method=method) for i in range(system.M)])
        self.names = [s.name for s in system.subsystems]

    def run(self, steps: int, on_step: Callable[[StepRecord], None], x0: np.ndarray | None = None,
            stop: Callable[[StepRecord], bool] | None = None) -> int:
        """Run from x0 (the scenario's by default) for at most ``steps`` steps, ``on_step`` called with
        each step's record; returns the steps done.

        ``stop(record)`` returning True ends the run after that step.
        """
        options: ProtocolOptions = replace(self.protocol, steps=steps)
        coordinator = Coordinator(self.system, self.design, Plant(self.system, x0), options, RUN_ID,
                                  policy=self.policy, cooperative=self.cooperative,
                                  cooperative_step=options.cooperative_step)
        archive: dict[tuple[int, int, int], Plan] = {}
        pending = deque(coordinator.start())
        done = 0
        while pending:
            action = pending.popleft()
            if isinstance(action, SendRelease):
                skipped = set(action.release.skipped)
                for i, name in enumerate(self.names):
                    if name not in skipped:
                        actions, _ = coordinator.on_plan(self._answer(i, action.release, archive))
                        pending.extend(actions)
            elif isinstance(action, StepCompleted):
                on_step(action.record)
                done += 1
                if stop is not None and stop(action.record):
                    break
        return done

    def _answer(self, i: int, release: Release, archive: dict[tuple[int, int, int], Plan]) -> PlanMessage:
        """Agent i's plan for the release (what AgentNode does over the bus)."""
        plans: dict[int, Plan | None] = {}
        for j in self.controllers[i].neighbours:
            ref = release.reference(j)
            if ref is None:
                plans[j] = None
            elif self.names[j] in release.provided:
                plans[j] = Plan(ref[0], ref[1], *release.provided[self.names[j]])
            else:
                plans[j] = archive[(j, *ref)]
        msg = self.controllers[i].answer(release, plans, RUN_ID)
        if isinstance(msg, Kept):  # only with an event trigger, which this loop's controllers are built without
            raise RuntimeError(f"agent {self.names[i]} kept its plan at k = {release.k}: the direct loop runs "
                               "without the event trigger (it has no kept plans to rebuild)")
        archive[(i, release.k, release.round)] = Plan(release.k, release.round, msg.z, msg.v)
        return msg

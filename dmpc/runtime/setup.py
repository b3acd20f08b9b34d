"""From a validated scenario to everything a run needs (system, design, protocol settings)."""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

import numpy as np

from dmpc.design import Design, RevisionBound, design_system
from dmpc.plant.barrier import ProtocolOptions
from dmpc.scenario import Scenario, alpha0_vector, build_system, given_gains
from dmpc.system import CoupledSystem


@dataclass(frozen=True)
class Prepared:
    """A scenario ready to run.

    Attributes
    ----------
    scenario : Scenario
    system : CoupledSystem
    design : Design
    digest : str
        Short hash of the design; every process of a run must agree on it.
    protocol : ProtocolOptions
    mode : str
    dt : float
    deadline : float or None
    """

    scenario: Scenario
    system: CoupledSystem
    design: Design
    digest: str
    protocol: ProtocolOptions
    mode: str
    dt: float
    deadline: float | None

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.system.subsystems]

    @property
    def plan_wait(self) -> float | None:
        """How long an agent waits for a referenced neighbour plan (half the deadline)."""
        return None if self.deadline is None else 0.5 * self.deadline


def design_for(scenario: Scenario, system: CoupledSystem) -> Design:
    """Run the offline design the scenario asks for (DesignError on failure)."""
    given = given_gains(scenario) if scenario.design.gains == "given" else None
    bounds = {}
    for i, spec in enumerate(scenario.resolved_subsystems()):
        if spec.revision_bound is not None:
            bounds[i] = RevisionBound(np.asarray(spec.revision_bound.state, float),
                                      np.asarray(spec.revision_bound.input, float))
    return design_system(system, gains=scenario.design.gains, horizon=scenario.horizon,
                         alpha0=alpha0_vector(scenario, system), beta0=scenario.terminal.beta0, given=given,
                         tube=scenario.options.tube, revision_bounds=bounds)


def design_digest(design: Design) -> str:
    text = json.dumps(design.to_json(), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def prepare(scenario: Scenario, steps: int | None = None) -> Prepared:
    """Build the system and run the design; ``steps`` overrides the scenario's."""
    system = build_system(scenario)
    design = design_for(scenario, system)
    opts = scenario.options
    protocol = ProtocolOptions(steps=steps or scenario.steps, iterations=opts.iterations, tolerance=opts.tolerance,
                               initial_iterations=opts.initial_iterations, initial_tolerance=opts.initial_tolerance)
    deadline = opts.deadline
    if deadline is None and opts.mode == "realtime":
        deadline = opts.dt
    return Prepared(scenario=scenario, system=system, design=design, digest=design_digest(design),
                    protocol=protocol, mode=opts.mode, dt=opts.dt, deadline=deadline)

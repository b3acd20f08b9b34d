"""From a validated scenario to everything a run needs (system, design, protocol settings)."""
from __future__ import annotations

from typing import TYPE_CHECKING

import hashlib
import json
from dataclasses import dataclass

from dmpc.bus.faults import FaultPlan, LinkFault
from dmpc.design import Design, design_from_json, design_system
from dmpc.plant.barrier import ProtocolOptions
from dmpc.system import CoupledSystem

if TYPE_CHECKING:  # the scenario package needs pydantic, which agent processes can do without
    from dmpc.scenario import Scenario


@dataclass(frozen=True)
class Prepared:
    """A scenario ready to run.

    Attributes
    ----------
    scenario : Scenario or None
        None when loaded from a run bundle (dmpc.runtime.bundle).
    system : CoupledSystem
    design : Design
    digest : str
        Short hash of the design; every process of a run must agree on it.
    protocol : ProtocolOptions
    mode : str
    dt : float
    deadline : float or None
    faults : FaultPlan
    name : str
        The scenario's name.
    coupling : str
        ``feedforward`` or ``nominal``.
    method : str
        The control method (:mod:`dmpc.methods`), ``tv-box`` by default.
    """

    scenario: "Scenario | None"
    system: CoupledSystem
    design: Design
    digest: str
    protocol: ProtocolOptions
    mode: str
    dt: float
    deadline: float | None
    faults: FaultPlan = FaultPlan()
    name: str = "scenario"
    coupling: str = "feedforward"
    method: str = "tv-box"

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.system.subsystems]

    def design_json(self) -> dict:
        """The content of ``design.json`` (the design plus its digest)."""
        data = self.design.to_json()
        data["digest"] = self.digest
        return data

    @property
    def plan_wait(self) -> float | None:
        """How long an agent waits for a referenced neighbour plan (half the deadline)."""
        return None if self.deadline is None else 0.5 * self.deadline


def design_for(scenario: Scenario, system: CoupledSystem, design_data: dict | None = None) -> Design:
    """Run the offline design the scenario asks for, or rebuild it from ``design.json`` content."""
    from dmpc.scenario import alpha0_vector, given_gains, revision_bounds

    kwargs = dict(horizon=scenario.horizon, alpha0=alpha0_vector(scenario, system), beta0=scenario.terminal.beta0,
                  tube=scenario.options.tube, revision_bounds=revision_bounds(scenario))
    if design_data is not None:
        return design_from_json(system, design_data, **kwargs)
    given = given_gains(scenario) if scenario.design.gains == "given" else None
    return design_system(system, gains=scenario.design.gains, given=given, **kwargs)


def design_digest(design: Design, method: str = "tv-box") -> str:
    """Short hash of the design, and of the method unless it is the default ``tv-box``."""
    data = design.to_json()
    if method != "tv-box":
        data["method"] = method
    text = json.dumps(data, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def prepare(scenario: Scenario, steps: int | None = None, design_data: dict | None = None) -> Prepared:
    """Build the system and the design; ``steps`` overrides the scenario's; ``design_data``
    (``design.json`` content) skips the offline solves."""
    from dmpc.scenario import build_system

    system = build_system(scenario)
    design = design_for(scenario, system, design_data)
    opts = scenario.options
    protocol = ProtocolOptions(steps=steps or scenario.steps, iterations=opts.iterations, tolerance=opts.tolerance,
                               initial_iterations=opts.initial_iterations, initial_tolerance=opts.initial_tolerance)
    deadline = opts.deadline
    if deadline is None and opts.mode == "realtime":
        deadline = opts.dt
    lossy = scenario.faults.loss > 0 or any(link.loss > 0 for link in scenario.faults.links)
    if lossy and deadline is None:
        from dmpc.scenario import ScenarioError

        raise ScenarioError("faults.loss: lost messages need a deadline in lockstep mode, or the run would wait "
                            "for them forever: set options.deadline (--deadline S) or options.mode: realtime",
                            field="faults.loss")
    return Prepared(scenario=scenario, system=system, design=design, digest=design_digest(design, opts.method),
                    protocol=protocol, mode=opts.mode, dt=opts.dt, deadline=deadline, faults=fault_plan(scenario),
                    name=scenario.name, coupling=opts.coupling, method=opts.method)


def fault_plan(scenario: Scenario) -> FaultPlan:
    """The scenario's ``faults`` section as a FaultPlan seeded by the scenario's seed."""
    f = scenario.faults
    links = tuple((l.source, l.target, LinkFault(l.delay_ms, l.jitter_ms, l.loss)) for l in f.links)
    return FaultPlan(default=LinkFault(f.delay_ms, f.jitter_ms, f.loss), links=links, seed=scenario.seed)

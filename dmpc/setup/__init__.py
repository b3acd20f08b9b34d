"""From a validated scenario to everything a run needs (system, design, protocol settings)."""
from __future__ import annotations

from typing import Final

from dmpc.bus.faults import FaultPlan, LinkFault
from dmpc.core.steps import ProtocolOptions, TriggerOptions
from dmpc.core.system import CoupledSystem
from dmpc.offline import ControllerDesign, DesignError, design_from_json, design_gains
from dmpc.offline.horizon import StartCheck, auto_beta0
from dmpc.prepared import Prepared, design_digest
from dmpc.scenario import (
    OptionsSpec,
    Scenario,
    alpha0_vector,
    build_system,
    discrete_model,
    given_gains,
    revision_bounds,
    setpoint_entries,
)
from dmpc.scenario.schema import per_subsystem
from dmpc.setup.estimation import design_estimation
from dmpc.setup.plant import disturbance_bounds, plant_setup
from dmpc.setup.start import MethodStart

AUTO: Final = "auto"


def design_for(scenario: Scenario, system: CoupledSystem, design_data: dict | None = None,
               protocol: ProtocolOptions | None = None, disturbances: dict | None = None) -> ControllerDesign:
    """Run the offline design the scenario asks for on ``system``, or rebuild it from ``design.json``
    content; the start is checked with the coordinator's settings ``protocol`` (the scenario's by
    default).

    Resolves ``terminal.beta0: auto`` and ``horizon: auto`` and checks the start
    (:mod:`dmpc.offline.horizon`); a design read from ``design_data`` keeps the horizon and beta0
    it was made with. ``disturbances`` (per subsystem index, the bound (n_i,) of an additive plant
    disturbance) widen the tube of ``options.tube: robust``.
    """
    alpha0 = alpha0_vector(scenario, system)
    bounds = revision_bounds(scenario)
    tube = scenario.options.tube
    if design_data is not None:
        horizon = scenario.horizon if scenario.horizon != AUTO else int(design_data.get("horizon", 0) or 0)
        beta0 = scenario.terminal.beta0 if scenario.terminal.beta0 != AUTO else float(design_data.get("beta0", 0))
        if horizon < 1:
            raise DesignError("design file: no horizon in it, and the scenario's horizon is auto")
        return design_from_json(system, design_data, horizon=horizon, alpha0=alpha0, beta0=beta0, tube=tube,
                                revision_bounds=bounds, disturbance_bounds=disturbances)
    given = given_gains(scenario) if scenario.design.gains == "given" else None
    gains, terminal = design_gains(system, scenario.design.gains, given)
    beta0 = auto_beta0(terminal, alpha0) if scenario.terminal.beta0 == AUTO else scenario.terminal.beta0
    start = MethodStart(system, scenario.options.method, scenario.options.coupling,
                        protocol or protocol_options(scenario))
    check = StartCheck(system, gains, terminal, alpha0=alpha0, beta0=beta0, tube=tube, start=start,
                       revision_bounds=bounds, disturbance_bounds=disturbances)
    if scenario.horizon == AUTO:
        design = check.auto(check_start=scenario.design.check_start)
    elif scenario.design.check_start:
        design = check.checked(scenario.horizon)
    else:
        design = check.design(scenario.horizon)
    if scenario.terminal.beta0 == AUTO:
        design = design.with_start({**(design.start or {}), "beta0": "auto"})
    return design


def protocol_options(scenario: Scenario, steps: int | None = None) -> ProtocolOptions:
    """The coordinator's settings from the ``scenario``'s options, for ``steps`` steps (None: the
    scenario's)."""
    opts = scenario.options
    return ProtocolOptions(steps=steps or scenario.steps, rounds=opts.iterations, tolerance=opts.tolerance,
                           initial_rounds=opts.initial_iterations, initial_tolerance=opts.initial_tolerance,
                           cooperative_step=opts.cooperative_step)


def prepare(scenario: Scenario, steps: int | None = None, design_data: dict | None = None) -> Prepared:
    """Build the system and the design; ``steps`` overrides the scenario's; ``design_data``
    (``design.json`` content) skips the offline solves (the estimator of ``estimation`` is designed
    again: it is quick, and deterministic)."""
    system = build_system(scenario)
    estimator = design_estimation(scenario, system)  # first: a detectability error is quicker to find than the design
    protocol = protocol_options(scenario, steps)
    plant = plant_setup(scenario, system, protocol.steps)
    design = design_for(scenario, system, design_data, protocol, disturbance_bounds(plant, system))
    opts = scenario.options
    deadline = opts.deadline
    if deadline is None and opts.mode == "realtime":
        deadline = opts.dt
    trigger = trigger_options(scenario)
    digest = design_digest(design, opts.method, trigger, estimator)
    return Prepared(scenario=scenario, system=system, design=design, digest=digest,
                    protocol=protocol, mode=opts.mode, dt=opts.dt, deadline=deadline, faults=fault_plan(scenario),
                    name=scenario.name, coupling=opts.coupling, method=opts.method, plant=plant,
                    model=_model_report(scenario), setpoints=setpoint_entries(scenario),
                    setpoint_margin=opts.setpoint_margin, trigger=trigger, estimator=estimator)


def trigger_options(scenario: Scenario) -> TriggerOptions:
    """The scenario's event trigger, its thresholds one per subsystem."""
    opts = scenario.options
    names = [s.name for s in scenario.resolved_subsystems()]
    fields = OptionsSpec.model_fields
    return TriggerOptions(mode=opts.trigger,
                          threshold=per_subsystem(opts.trigger_threshold, names, fields["trigger_threshold"].default),
                          cost=per_subsystem(opts.trigger_cost, names, fields["trigger_cost"].default),
                          max_keep=opts.trigger_max_keep)


def _model_report(scenario: Scenario) -> dict | None:
    """The discretisation of a continuous-time scenario, for design.json (None in discrete time)."""
    if scenario.time != "continuous":
        return None

    return discrete_model(scenario).to_json()


def fault_plan(scenario: Scenario) -> FaultPlan:
    """The scenario's ``faults`` section as a FaultPlan seeded by the scenario's seed."""
    f = scenario.faults
    links = tuple((l.source, l.target, LinkFault(l.delay_ms, l.jitter_ms, l.loss)) for l in f.links)
    return FaultPlan(default=LinkFault(f.delay_ms, f.jitter_ms, f.loss), links=links, seed=scenario.seed)

"""Scenario files: schema, safe loading with overrides, and building the coupled system."""
from dmpc.scenario.build import (
    alpha0_vector,
    build_system,
    discrete_model,
    given_gains,
    revision_bounds,
    setpoint_entries,
)
from dmpc.scenario.load import (
    ScenarioError,
    dump_resolved,
    load_scenario,
    parse_override,
    scenario_json_schema,
    validate_scenario,
)
from dmpc.scenario.schema import (
    BoxSpec,
    ChainFamily,
    CouplingSpec,
    DesignSpec,
    FamilyCouplingSpec,
    FaultsSpec,
    LinkFaultSpec,
    OptionsSpec,
    PolytopeSpec,
    RevisionBoundSpec,
    Scenario,
    SetpointSpec,
    SubsystemSpec,
    SubsystemTemplate,
    TerminalSpec,
)

__all__ = [
    "BoxSpec", "ChainFamily", "CouplingSpec", "DesignSpec", "FamilyCouplingSpec", "FaultsSpec",
    "LinkFaultSpec", "OptionsSpec", "PolytopeSpec", "RevisionBoundSpec", "Scenario", "ScenarioError", "SetpointSpec",
    "SubsystemSpec", "SubsystemTemplate", "TerminalSpec", "alpha0_vector", "build_system", "discrete_model",
    "dump_resolved", "given_gains", "load_scenario", "parse_override", "revision_bounds",
    "scenario_json_schema", "setpoint_entries", "validate_scenario",
]

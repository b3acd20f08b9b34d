"""Distributed MPC with time-varying terminal sets for coupled linear systems.

From Python::

    import dmpc

    scenario = dmpc.load_scenario("scenarios/paper.yaml", steps=20)
    design = dmpc.design(scenario)              # gains, X^f, sigma, horizon, checks
    result = dmpc.simulate(scenario)            # in this process
    result = dmpc.run(scenario)                 # plant + one process per agent over Zenoh
    result.x["1"], result.u["1"], result.t, result.verdict
    figures = result.plot()
    again = dmpc.load_run("runs/paper-...")

The names below are the public API (:mod:`dmpc.api`); the subpackages (``dmpc.scenario``,
``dmpc.runtime``, ...) are the layers under it. They are loaded on first use, so that importing
a part of the numerical core does not import the rest.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

# The offline design package is imported first: afterwards the attribute ``dmpc.design`` is the
# function below, while ``from dmpc.design import ...`` still reaches the package (imports read
# sys.modules, not this attribute).
import dmpc.design as _design_package  # noqa: F401

if TYPE_CHECKING:  # the names loaded lazily below, for type checkers and editors
    from dmpc.api import RunError, ScenarioLike, load_run, load_scenario, run, simulate
    from dmpc.offline_design import Design
    from dmpc.plant.models import PlantModelError
    from dmpc.result import Result
    from dmpc.scenario import Scenario, ScenarioError

__all__ = ["Design", "PlantModelError", "Result", "RunError", "Scenario", "ScenarioError", "design", "load_run",
           "load_scenario", "run", "simulate"]

_LAZY = {"load_scenario": "dmpc.api", "simulate": "dmpc.api", "run": "dmpc.api", "load_run": "dmpc.api",
         "RunError": "dmpc.api", "Design": "dmpc.offline_design", "Result": "dmpc.result",
         "PlantModelError": "dmpc.plant.models", "Scenario": "dmpc.scenario", "ScenarioError": "dmpc.scenario"}


def design(scenario: "ScenarioLike") -> "Design":
    """The offline design of a scenario (:func:`dmpc.api.design`): gains, terminal set, sigma,
    horizon and checks, the same as ``dmpc design --json``."""
    from dmpc.api import design as offline_design  # start-up time: `import dmpc` loads the API on first use

    return offline_design(scenario)


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'dmpc' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))

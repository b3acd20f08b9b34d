"""Distributed MPC with time-varying terminal sets for coupled linear systems.

From Python::

    import dmpc

    scenario = dmpc.load_scenario("scenarios/paper.yaml", steps=20)
    design = dmpc.design(scenario)              # gains, X^f, sigma, horizon, checks
    result = dmpc.simulate(scenario)            # in this process
    result = dmpc.run(scenario)                 # plant + one process per agent over Zenoh
    dmpc.setpoint("tcp/127.0.0.1:7447", run_id, "1", x=[1.0, None])  # a running run's setpoint
    result.x["1"], result.u["1"], result.t, result.verdict
    figures = result.plot()
    again = dmpc.load_run("runs/paper-...")

The names below are the public API (:mod:`dmpc.api`); every error it raises on purpose is a
``dmpc.DmpcError``. The subpackages (``dmpc.scenario``, ``dmpc.runtime``, ...) are the layers under
it (the offline design is ``dmpc.offline``: ``dmpc.design`` is the function). They are loaded on first use, so that importing
a part of the numerical core does not import the rest.
"""
from __future__ import annotations

import sys as _sys


def _interrupts_end_the_command_while_it_imports() -> None:
    """If this interpreter runs the ``dmpc`` command (its script, or ``python -m dmpc.cli``),
    SIGINT and SIGTERM end it with ``error: interrupted`` and exit code 130 until the command
    sets its own handlers (:func:`dmpc.terminal.signals.sigterm_as_interrupt`).

    The command's imports take most of a second, in which Python would print a KeyboardInterrupt
    traceback, or die of SIGTERM without a word; nothing has been started yet, so the process
    ends at once. Written here with the standard library only, and first: importing any part of
    dmpc runs this file, and must load no other dmpc module (tests/test_pure_core.py).
    """
    argv = list(getattr(_sys, "orig_argv", []))
    as_module = "-m" in argv[:-1] and argv[argv.index("-m") + 1] == "dmpc.cli"
    as_script = bool(_sys.argv) and _sys.argv[0].replace("\\", "/").rsplit("/", 1)[-1] == "dmpc"
    if not (as_module or as_script):
        return
    import os
    import signal

    def end(signum, frame):
        os.write(2, b"error: interrupted\n")
        os._exit(130)  # dmpc.terminal.exit_codes.EXIT_INTERRUPTED, not imported (see above)

    signal.signal(signal.SIGTERM, end)
    signal.signal(signal.SIGINT, end)


_interrupts_end_the_command_while_it_imports()
del _interrupts_end_the_command_while_it_imports, _sys

from typing import TYPE_CHECKING  # noqa: E402

if TYPE_CHECKING:  # the names loaded lazily below, for type checkers and editors
    from dmpc.api import RunError, ScenarioLike, load_run, load_scenario, run, simulate
    from dmpc.api.result import Result
    from dmpc.api.setpoints import LiveRun, SetpointError, SetpointRefused, SetpointUnanswered, setpoint
    from dmpc.core.errors import DesignError, DmpcError
    from dmpc.offline.record import Design
    from dmpc.plant.models import PlantModelError
    from dmpc.scenario import Scenario, ScenarioError

__all__ = ["Design", "DesignError", "DmpcError", "LiveRun", "PlantModelError", "Result", "RunError", "Scenario",
           "ScenarioError", "SetpointError", "SetpointRefused", "SetpointUnanswered", "design", "load_run",
           "load_scenario", "run", "setpoint", "simulate"]

_LAZY = {"load_scenario": "dmpc.api", "simulate": "dmpc.api", "run": "dmpc.api", "load_run": "dmpc.api",
         "RunError": "dmpc.api", "setpoint": "dmpc.api", "LiveRun": "dmpc.api", "SetpointError": "dmpc.api",
         "SetpointRefused": "dmpc.api", "SetpointUnanswered": "dmpc.api", "Design": "dmpc.offline.record", "Result": "dmpc.api.result",
         "DmpcError": "dmpc.core.errors", "DesignError": "dmpc.core.errors",
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

"""The numerical core imports neither Zenoh nor anything that does I/O (README, "Layout").

The core is what computes: the model and its sets, the discretisation, the offline design, the
terminal policies of the methods, the QPs, the trajectories, an agent's controller, the plant's
dynamics and the coordinator's state machine, with the plain data they exchange (the messages
as dataclasses, their keys, the checks of a received state). Everything that talks to the
outside, such as the nodes, the buses, the processes, the records, the scenario files, the CLI
and the live view, is built around it.

Two checks:

* **Loaded** (a fresh interpreter, ``sys.modules`` after importing every core module): the core
  loads no dmpc module outside itself, and none of the modules in ``NEVER_LOADED``, whoever
  would import them (numpy, scipy and OSQP load none of them).
* **Imported** (the source of every core module, imports inside functions included): no import
  of an I/O module (``IO_MODULES``) and no third-party package other than the numerical
  libraries. numpy, scipy and OSQP themselves load ``socket``, ``subprocess``, ``threading``
  and others when imported (for their test and build utilities), so for those modules
  ``sys.modules`` cannot tell who needed them: the source can.
"""
from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.test_layering import modules_of, package_dirs

ROOT = Path(__file__).resolve().parents[1]

CORE_PACKAGES = {"dmpc.core": ROOT / "dmpc" / "core", "dmpc.offline": ROOT / "dmpc" / "offline",
                 "dmpc.methods": ROOT / "dmpc" / "methods", "dmpc.tracking": ROOT / "dmpc" / "tracking",
                 "dmpc.cooperative": ROOT / "dmpc" / "cooperative", "dmpc.estimation": ROOT / "dmpc" / "estimation"}
"""Every module of these packages is core: the model, its sets, projections, the discretisation, the
QPs and their statuses, the trajectories, the protocol options and the record of one step
(dmpc.core), the offline design and its record (dmpc.offline), the methods' terminal policies,
the setpoint targets and the reference governor (dmpc.tracking), the cooperative iterate and the
agents' cooperative QPs (dmpc.cooperative), the disturbance models, the observer and the offset-free
targets (dmpc.estimation)."""
CORE_MODULES = {
    "dmpc.agents": ROOT / "agents" / "__init__.py",
    "dmpc.agents.local_qp": ROOT / "agents" / "local_qp.py",
    "dmpc.agents.controller": ROOT / "agents" / "controller.py",
    "dmpc.agents.trigger": ROOT / "agents" / "trigger.py",  # keep the shifted plan or solve
    "dmpc.agents.cooperative": ROOT / "agents" / "cooperative.py",  # a cooperative agent's proposal
    "dmpc.plant": ROOT / "plant" / "__init__.py",
    "dmpc.coordinator": ROOT / "coordinator" / "__init__.py",
    "dmpc.coordinator.barrier": ROOT / "coordinator" / "barrier.py",  # the coordinator's state machine
    # ... and its parts
    **{f"dmpc.coordinator.{part}": ROOT / "coordinator" / f"{part}.py" for part in (
        "actions", "candidates", "combiner", "cooperative_rounds", "estimation", "guard", "open_step", "refusals",
        "round_barrier", "setpoint_intake", "step_close")},
    "dmpc.plant.dynamics": ROOT / "plant" / "dynamics.py",
    "dmpc.plant.disturbance": ROOT / "plant" / "disturbance.py",
    "dmpc.plant.state_inbox": ROOT / "plant" / "state_inbox.py",  # the coordinator's checks of a state
    "dmpc.bus": ROOT / "bus" / "__init__.py",
    "dmpc.bus.messages": ROOT / "bus" / "messages.py",  # the messages as dataclasses (no codec)
    "dmpc.bus.keys": ROOT / "bus" / "keys.py",  # key expressions and role names, as strings
    "dmpc.security": ROOT / "dmpc" / "security" / "__init__.py",
    "dmpc.security.rejects": ROOT / "dmpc" / "security" / "rejects.py",  # range checks of received numbers
}

IO_MODULES = {
    # the bus and the network
    "zenoh", "socket", "ssl", "select", "selectors", "asyncio", "http", "urllib", "socketserver",
    # the wire format: the core works on decoded messages, the codec is the bus's
    "msgpack",
    # processes, signals and the threads that wait on them: the nodes own time and concurrency,
    # the core runs in its caller's thread
    "subprocess", "multiprocessing", "signal", "threading", "concurrent", "queue",
    # files: scenarios are read by dmpc.scenario, records written by dmpc.records
    "os", "io", "pathlib", "shutil", "tempfile", "glob", "fcntl", "mmap", "sqlite3", "yaml", "orjson",
    # the machine's processes
    "psutil",
}
"""Modules that do I/O. ``logging`` is not among them: the core reports through log records and
the application chooses where they go. Neither is ``time``: the QP reads a clock to time its
solve."""

ENTRY = "dmpc"
"""The package itself: importing any core module runs its ``__init__``, so it is loaded with the
core and counts in the check of what is loaded. Its source is not checked like a core module's:
its names are the public API (``dmpc.simulate``, ``dmpc.run``, ...), which reach the outer layers
on first use, by design."""

NUMERICAL = {"numpy", "scipy", "osqp", "cvxpy", "clarabel"}
"""The third-party packages the core may import."""

NEVER_LOADED = {"zenoh", "msgpack", "asyncio", "multiprocessing", "ssl", "http", "urllib.request", "socketserver",
                "yaml", "orjson", "psutil", "pydantic", "rich", "typer", "click", "matplotlib", "bokeh",
                "cryptography"}
"""Modules that nothing the core loads may load: the I/O modules that the numerical libraries do
not load themselves, and the packages of the outer layers (scenario files, records, CLI, figures,
live view, certificates)."""

PROBE = """
import importlib, json, sys
for name in sys.argv[1:]:
    importlib.import_module(name)
print(json.dumps(sorted(sys.modules)))
"""


def core_modules() -> dict[str, Path]:
    """Module name -> file of every core module."""
    modules = dict(CORE_MODULES)
    for package, folder in CORE_PACKAGES.items():
        for path in sorted(folder.glob("*.py")):
            modules[package if path.stem == "__init__" else f"{package}.{path.stem}"] = path
    return modules


def loaded_after_importing(names: list[str]) -> set[str]:
    """``sys.modules`` of a fresh interpreter after importing ``names``."""
    result = subprocess.run([sys.executable, "-c", PROBE, *names], cwd=ROOT, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    return set(json.loads(result.stdout))


def loading_violations(loaded: set[str], core: set[str]) -> list[str]:
    """dmpc modules outside the core, and modules of ``NEVER_LOADED``, among ``loaded``."""
    outside = sorted(m for m in loaded if (m == ENTRY or m.startswith(ENTRY + ".")) and m not in core | {ENTRY})
    never = sorted(m for m in loaded if m in NEVER_LOADED or m.split(".")[0] in NEVER_LOADED)
    return [f"{m}: a dmpc module outside the core" for m in outside] + [f"{m}: loaded" for m in never]


def import_violations(module: str, path: Path, source: str, core: set[str]) -> list[str]:
    """Imports in ``source`` (the text of ``module``, whose file is ``path``; anywhere in it) of
    I/O modules, of third-party packages other than the numerical libraries, and of dmpc modules
    outside the core."""
    found = []
    every_module = set(modules_of(package_dirs()))
    package = module if path.stem == "__init__" else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            # ``from package import module`` reaches the module; ``from module import name`` the module
            names = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in every_module else base
                     for alias in node.names]
        else:
            continue
        for name in names:
            top = name.split(".")[0]
            if top == "dmpc":
                if name not in core:
                    found.append(f"{module}:{node.lineno} imports {name}, outside the core")
            elif top in IO_MODULES:
                found.append(f"{module}:{node.lineno} imports {name}, which does I/O")
            elif top not in sys.stdlib_module_names and top != "__future__" and top not in NUMERICAL:
                found.append(f"{module}:{node.lineno} imports {name}, a package other than {sorted(NUMERICAL)}")
    return list(dict.fromkeys(found))


# ---------------------------------------------------------------------------- the core as it is
def test_the_core_list_names_existing_files():
    missing = [f"{name}: {path}" for name, path in core_modules().items() if not path.is_file()]
    assert missing == []


def test_importing_the_core_in_a_fresh_interpreter_loads_no_io_and_nothing_outside_it():
    core = core_modules()
    loaded = loaded_after_importing(sorted(core))
    assert set(core) <= loaded  # the probe did import them
    found = loading_violations(loaded, set(core))
    assert found == [], "\n".join(found)


def test_no_core_module_imports_io_or_a_non_numerical_package():
    core = core_modules()
    found = [line for name, path in core.items()
             for line in import_violations(name, path, path.read_text(), set(core))]
    assert found == [], "\n".join(found)


# ---------------------------------------------------------------------------- the checks can fail
BARRIER = ROOT / "coordinator" / "barrier.py"


def test_a_node_module_loads_zenoh_and_is_caught():
    """The Zenoh bus beside the core: the fresh interpreter shows zenoh and the bus's modules."""
    core = core_modules()
    loaded = loaded_after_importing(["dmpc.coordinator.barrier", "dmpc.bus.zenoh_bus"])
    found = loading_violations(loaded, set(core))
    assert "dmpc.bus.zenoh_bus: a dmpc module outside the core" in found
    assert "dmpc.bus.session: a dmpc module outside the core" in found and "zenoh: loaded" in found


@pytest.mark.parametrize("source, words", [
    ("import socket\n", "imports socket, which does I/O"),
    ("def f():\n    from subprocess import run\n", "imports subprocess, which does I/O"),
    ("from pathlib import Path\n", "imports pathlib, which does I/O"),
    ("import zenoh\n", "imports zenoh, which does I/O"),
    ("import matplotlib.pyplot as plt\n", "imports matplotlib.pyplot, a package other than"),
    ("from dmpc.records.session import RunRecorder\n", "imports dmpc.records.session, outside the core"),
    ("from dmpc.bus import codec\n", "imports dmpc.bus.codec, outside the core"),
    ("from .. import setup\n", "imports dmpc.setup, outside the core"),
])
def test_an_io_import_in_a_core_module_is_caught(source, words):
    core = set(core_modules())
    found = import_violations("dmpc.coordinator.barrier", BARRIER, source, core)
    assert len(found) == 1 and words in found[0], found
    assert found[0].startswith("dmpc.coordinator.barrier:")


def test_numerical_and_core_imports_pass():
    core = set(core_modules())
    source = ("import numpy as np\nimport scipy.sparse as sp\nfrom dmpc.core.system import CoupledSystem\n"
              "from dmpc.bus.messages import Release\nimport logging, math\n"
              "def f():\n    import osqp\n    from ..plant.dynamics import Plant\n")
    assert import_violations("dmpc.coordinator.barrier", BARRIER, source, core) == []

"""What the plant simulates: the controllers' model, the exact discretisation, a built-in nonlinear
model (the quadruple tank), or the user's function, plus an additive disturbance (scenario field
``plant``, and ``--model`` / ``plant=``).

A user's plant function is never named in a scenario file (a scenario must not run code): it
comes from the command line (``dmpc plant --model module:function``) or from Python
(``dmpc.simulate(..., plant=f)``), and is added to a prepared run with :func:`with_plant_function`.
"""
from __future__ import annotations

import importlib
import importlib.util
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from dmpc.core.system import CoupledSystem
from dmpc.plant.disturbance import DisturbanceSequence, gaussian_sequence, step_sequence, uniform_sequence
from dmpc.plant.fourtank import FourTank, FourTankPlant
from dmpc.prepared import PlantFunction, PlantSetup, Prepared
from dmpc.scenario import Scenario, ScenarioError, discrete_model
from dmpc.scenario.build import SETPOINT_TIME_TOLERANCE
from dmpc.scenario.schema import FourTankSpec, fourtank_positions
from dmpc.setup.estimation import measurement_noise


def plant_setup(scenario: Scenario, system: CoupledSystem, steps: int) -> PlantSetup:
    """The scenario's ``plant`` section (the model, the disturbance, the measurement noise) for a run
    of ``system`` of ``steps`` steps.

    Parameters
    ----------
    scenario : Scenario
        The validated scenario; its ``plant`` section is read.
    system : CoupledSystem
        The controllers' model built from ``scenario``: the global state order of w(k), and the
        B through which a ``step`` disturbance's input offsets enter (unless the plant is
        ``exact``, whose own B they enter through).
    steps : int
        The run's length: w(k) has this many rows.

    Returns
    -------
    PlantSetup

    Raises
    ------
    ScenarioError
        A disturbance file that cannot be read or does not fit (rows < steps, columns != n); a
        ``step`` at a fractional step in a scenario without dt.
    """
    spec = scenario.plant
    A = B = None
    function, function_name = None, ""
    if spec.model == "exact":
        model = discrete_model(scenario)
        A, B = model.A_exact, model.B_exact
    elif spec.model == "fourtank":
        function, function_name = fourtank_plant(scenario), FOURTANK_NAME
    w, kind, bound = None, "", None
    if spec.disturbance is not None:
        kind = spec.disturbance.kind
        w = _disturbance(scenario, system, steps, system.B if B is None else B)
        if kind == "uniform":
            bound = _per_state(system, spec.disturbance.bound)
        elif kind in ("file", "step"):
            bound = DisturbanceSequence(w).bound()
    return PlantSetup(model=spec.model, A=A, B=B, disturbance=w, disturbance_kind=kind, disturbance_bound=bound,
                      function=function, function_name=function_name,
                      measurement_noise=measurement_noise(scenario, system))


FOURTANK_NAME = "dmpc.plant.fourtank:FourTankPlant"
"""How the built-in quadruple-tank plant is named in ``summary.json`` and messages."""


def fourtank_plant(scenario: Scenario) -> FourTankPlant:
    """The nonlinear quadruple-tank plant of ``plant.model: fourtank`` (:mod:`dmpc.plant.fourtank`):
    the tanks of ``plant.fourtank`` (the benchmark's when omitted), integrated over the scenario's
    dt, on the states named h1..h4 and the inputs named qa, qb wherever the subsystems put them."""
    spec = scenario.plant.fourtank or FourTankSpec()
    states, inputs = fourtank_positions(scenario)
    tanks = FourTank(area=spec.area, outlets=(spec.outlets[0], spec.outlets[1], spec.outlets[2], spec.outlets[3]),
                     gamma=(spec.gamma[0], spec.gamma[1]), g=spec.g)
    assert scenario.dt is not None  # checked by the schema for model: fourtank
    # with operating points the plant function is given the levels and flows themselves (FunctionPlant):
    # its own operating point is then no flow and empty tanks, the zeros of those units
    q0 = np.zeros(2) if any(s.operating_point is not None for s in scenario.resolved_subsystems()) else np.array(spec.q0)
    return FourTankPlant(tanks, q0, scenario.dt, tuple(states), tuple(inputs), spec.substeps)


def _per_state(system: CoupledSystem, by_name: dict[str, list[float]] | None, inputs: bool = False) -> np.ndarray:
    """A global (n,) vector from per-subsystem entries (with ``inputs``, a global (m,) one), zeros for
    subsystems not listed."""
    out = np.zeros(system.m if inputs else system.n)
    for i, s in enumerate(system.subsystems):
        if by_name and s.name in by_name:
            out[system.us(i) if inputs else system.xs(i)] = by_name[s.name]
    return out


def _disturbance(scenario: Scenario, system: CoupledSystem, steps: int, B: np.ndarray) -> np.ndarray:
    spec = scenario.plant.disturbance
    assert spec is not None  # called for a plant with a disturbance
    seed = scenario.seed if spec.seed is None else spec.seed
    if spec.kind == "uniform":
        return uniform_sequence(_per_state(system, spec.bound), steps, seed)
    if spec.kind == "gaussian":
        return gaussian_sequence(_per_state(system, spec.std), steps, seed)
    if spec.kind == "step":
        offset = B @ _per_state(system, spec.input, inputs=True) + _per_state(system, spec.state)
        return step_sequence(offset, disturbance_start(scenario), steps)
    assert spec.file is not None  # kind "file" comes with its file (the schema)
    return read_disturbance(Path(spec.file), system.n, steps)


def disturbance_start(scenario: Scenario) -> int:
    """The first step k whose update x(k+1) a ``step`` disturbance of ``scenario`` is added to:
    ``at`` itself without dt, else the first step at or after the time ``at`` (k = ceil(at / dt)), as
    for the ``at`` of setpoints.

    Parameters
    ----------
    scenario : Scenario
        A scenario whose ``plant.disturbance`` has kind ``step``.

    Returns
    -------
    int

    Raises
    ------
    ScenarioError
        ``at`` is not a whole step and the scenario has no dt.
    """
    spec = scenario.plant.disturbance
    assert spec is not None and spec.at is not None  # kind "step" comes with its at (the schema)
    field = "plant.disturbance.at"
    if scenario.dt is None:
        if spec.at != int(spec.at):
            raise ScenarioError(f"{field}: expected a whole step, got {spec.at:g} (the scenario has no dt, so 'at' "
                                "counts steps)", field=field)
        return int(spec.at)
    return max(int(math.ceil(spec.at / scenario.dt - SETPOINT_TIME_TOLERANCE)), 0)


def read_disturbance(path: Path, n: int, steps: int) -> np.ndarray:
    """Rows 0..steps-1 of the ``.npy`` or ``.csv`` file ``path`` of w(k), shape (rows, n).

    Raises
    ------
    ScenarioError
        Unreadable, not 2-D numbers, fewer than ``steps`` rows, or not ``n`` columns.
    """
    field = "plant.disturbance.file"
    try:
        if path.suffix == ".npy":
            w = np.load(path, allow_pickle=False)
        elif path.suffix == ".csv":
            w = np.loadtxt(path, delimiter=",", ndmin=2)
        else:
            raise ScenarioError(f"{field}: expected a .npy or .csv file, got {path}", field=field)
    except (OSError, ValueError) as exc:
        raise ScenarioError(f"{field}: cannot read {path} ({exc})", field=field) from None
    w = np.asarray(w, dtype=float)
    if w.ndim == 1 and n == 1:
        w = w[:, None]
    if w.ndim != 2 or w.shape[1] != n:
        raise ScenarioError(f"{field}: {path} has shape {w.shape}; expected one row per step and n = {n} columns",
                            field=field)
    if w.shape[0] < steps:
        raise ScenarioError(f"{field}: {path} has {w.shape[0]} rows; the run needs {steps} (one per step)",
                            field=field)
    if not np.isfinite(w[:steps]).all():
        raise ScenarioError(f"{field}: {path} holds NaN or infinite values", field=field)
    return w[:steps].copy()


def disturbance_bounds(setup: PlantSetup, system: CoupledSystem) -> dict[int, np.ndarray] | None:
    """Per subsystem index of ``system``, the bound (n_i,) of the bounded disturbance of the plant
    ``setup`` for the tube (``tube: robust``).

    A uniform disturbance is bounded by its box, a file by its largest |w| per state over the
    run; a Gaussian one is unbounded and gives None (the tube cannot cover it).
    """
    bound = setup.disturbance_bound
    if bound is None:
        return None
    return {i: bound[system.xs(i)] for i in range(system.M)}


def with_plant_function(prepared: Prepared, function: PlantFunction, name: str = "") -> Prepared:
    """``prepared`` whose plant is ``function`` (x, u, k) -> x_next, named ``name`` in the records (the
    disturbance is kept)."""
    if not callable(function):
        raise TypeError(f"the plant must be a function (x, u, k) -> x_next, got {type(function).__name__}")
    name = name or function_reference(function, strict=False)
    return replace(prepared, plant=replace(prepared.plant, model="function", function=function, function_name=name))


def function_reference(function: PlantFunction, strict: bool = True) -> str:
    """How another process finds ``function``: ``module:qualname``, or ``/path/file.py:qualname``
    for a top-level module (found from any folder).

    Raises
    ------
    ValueError
        (``strict``) The function cannot be imported by name: defined in ``__main__`` (a script
        or notebook), inside another function, or a lambda.
    """
    module = getattr(function, "__module__", None)
    qualname = str(getattr(function, "__qualname__", None) or getattr(type(function), "__qualname__", ""))
    if not strict:
        return f"{module}:{qualname}" if module else qualname
    if not module or module == "__main__" or "<" in qualname:
        raise ValueError(f"the plant function {qualname or function!r} cannot be imported by another process "
                         f"(defined in {module or 'no module'}{', inside a function' if '<' in qualname else ''}): "
                         "put it at the top level of a module of its own (e.g. plants.py) and import it from there; "
                         "dmpc.simulate takes any function")
    file = getattr(sys.modules.get(module), "__file__", None)
    if "." not in module and file:
        return f"{Path(file).resolve()}:{qualname}"
    return f"{module}:{qualname}"


def load_plant_function(reference: str) -> tuple[PlantFunction, str]:
    """Import ``module:function`` or ``path/to/file.py:function`` (``--model``).

    Returns
    -------
    (function, reference)

    Raises
    ------
    ValueError
        A malformed reference, a module or file that cannot be imported (the import error is
        chained), or a name that is missing or not callable.
    """
    target, sep, qualname = reference.rpartition(":")
    if not sep or not target or not qualname:
        raise ValueError(f"--model {reference}: expected module:function or path/to/file.py:function")
    try:
        if target.endswith(".py") or "/" in target:
            module = _module_from_file(Path(target))
        else:
            module = importlib.import_module(target)
    except Exception as exc:
        raise ValueError(f"--model {reference}: cannot import {target} ({type(exc).__name__}: {exc})") from exc
    obj = module
    for part in qualname.split("."):
        if not hasattr(obj, part):
            raise ValueError(f"--model {reference}: {target} has no {qualname}")
        obj = getattr(obj, part)
    if not callable(obj):
        raise ValueError(f"--model {reference}: {qualname} is not a function (x, u, k) -> x_next")
    return obj, reference


def _module_from_file(path: Path):
    if not path.is_file():
        raise FileNotFoundError(f"no file {path}")
    path = path.resolve()
    name = f"dmpc_user_plant_{path.stem}"
    if name in sys.modules and getattr(sys.modules[name], "__file__", None) == str(path):
        return sys.modules[name]
    if str(path.parent) not in sys.path:
        sys.path.append(str(path.parent))  # its own imports of neighbouring modules
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:  # a file Python cannot load as a module (e.g. not .py)
        raise ImportError(f"{path} is not a Python module")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module

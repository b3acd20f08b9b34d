"""A scenario from what a Python user has at hand: a file, a mapping (with python-control models)
or a Scenario, with overrides (``dmpc.load_scenario``)."""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Union

from dmpc.scenario import Scenario, validate_scenario
from dmpc.scenario import load_scenario as load_file
from dmpc.scenario.state_space import from_state_spaces

ScenarioLike = Union[str, Path, Mapping, Scenario]


def load_scenario(source: ScenarioLike, /, **overrides) -> "Scenario":
    """A validated scenario from a YAML file, a mapping (numpy arrays allowed) or a Scenario.

    In a mapping, a subsystem, a coupling or a family's subsystem or coupling may give a
    python-control model, ``system=control.ss(...)``, in place of A and B: its labels name the
    states and inputs, and its time base sets ``time`` and ``dt``
    (:mod:`dmpc.scenario.state_space`).

    Parameters
    ----------
    source : str, Path, mapping or Scenario
    **overrides
        Fields to change, as ``--set`` does: ``steps=10``, ``horizon=5``; a nested field with
        ``__`` (``options__method="centralized"``) or a dotted key (``**{"family.M": 16}``).

    Returns
    -------
    Scenario

    Raises
    ------
    dmpc.scenario.ScenarioError
        One line naming the field at fault.
    """
    pairs = {key.replace("__", "."): value for key, value in overrides.items()}
    if isinstance(source, Scenario):
        if not pairs:
            return source
        data = source.model_dump(mode="python")
        return validate_scenario({k: v for k, v in data.items() if v is not None}, pairs, source=source.name)
    if isinstance(source, Mapping):
        return validate_scenario(from_state_spaces(source), pairs)
    return load_file(source, pairs)

"""python-control models in a scenario given as a mapping (the Python API).

Where a scenario mapping takes A and B (a subsystem, a coupling, a family's subsystem or its
coupling), ``system=`` may give a python-control ``StateSpace`` instead (``control.ss``,
``control.c2d``). Its A and B become the entry's, its state and input labels the names of the
states and inputs (unless they are python-control's defaults ``x[i]``, ``u[i]``, or the entry
names them itself), and its time base the scenario's:

- ``dt = 0`` (continuous time): ``time: continuous``, discretised with the scenario's ``dt``;
- ``dt > 0`` (discrete time): ``time: discrete`` and ``dt`` set to it;
- ``dt = True`` (discrete, period not given): ``time: discrete``.

Every system of one scenario must have the same time base. A subsystem's C is its measurement
matrix when the scenario has ``estimation`` (unless the entry gives ``C`` itself, and left out when
it is the identity), with its output labels as the names of the outputs (unless they are
python-control's defaults ``y[i]``, or the entry gives ``outputs``); without ``estimation`` dmpc
measures the whole state and C is not used. A non-zero D is refused rather than dropped.
python-control itself is never imported: the objects are recognised by their type's module and
attributes, so dmpc and its agents run without it.
"""
from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any, Literal

import numpy as np

from dmpc.scenario.load import ScenarioError

SYSTEM = "system"
"""The key of an entry that takes a python-control model in place of A and B."""
_DEFAULT_LABEL = {"states": re.compile(r"x\[\d+\]"), "inputs": re.compile(r"u\[\d+\]"),
                  "outputs": re.compile(r"y\[\d+\]")}


def from_state_spaces(data: Mapping) -> dict:
    """``data`` with every ``system`` entry replaced by its A, B and labels, and ``time`` and ``dt``
    set from the systems' time base.

    Parameters
    ----------
    data : mapping
        A scenario mapping (not modified). Entries without ``system`` are left as they are.

    Returns
    -------
    dict
        A shallow copy in which the changed entries are new dicts.

    Raises
    ------
    ScenarioError
        A ``system`` that is not a python-control StateSpace, given with A or B, with a non-zero
        D, or whose time base differs from another system's or from the scenario's ``time``/``dt``.
    """
    out = dict(data)
    bases: list[tuple[str, TimeBase]] = []  # (path, dt) of every system, in the order found
    measured = out.get("estimation") is not None  # C is used only with an observer
    for path, entry, labelled, put in _entries(out):
        if isinstance(entry, Mapping) and SYSTEM in entry:
            put(_expanded(entry, path, labelled, bases, measured))
    if bases:
        _set_time_base(out, bases)
    return out


def _entries(data: dict):
    """(path, entry, takes labels, setter) for every place of ``data`` that takes A and B."""
    def setter(container, key):
        def put(value):
            container[key] = value
        return put

    for list_key, labelled in (("subsystems", True), ("couplings", False)):
        items = data.get(list_key)
        if isinstance(items, (list, tuple)):
            items = data[list_key] = list(items)
            for i, entry in enumerate(items):
                yield f"{list_key}[{i}]", entry, labelled, setter(items, i)
    family = data.get("family")
    if isinstance(family, Mapping):
        family = data["family"] = dict(family)
        for key, labelled in (("subsystem", True), ("coupling", False)):
            if key in family:
                yield f"family.{key}", family[key], labelled, setter(family, key)


def is_state_space(value: object) -> bool:
    """True for a python-control StateSpace ``value`` (recognised without importing python-control)."""
    kind = type(value)
    return kind.__module__.split(".")[0] == "control" and all(hasattr(value, a) for a in ("A", "B", "C", "D", "dt"))


def _expanded(entry: Mapping, path: str, labelled: bool, bases: list[tuple[str, TimeBase]],
              measured: bool = False) -> dict:
    """``entry`` with its ``system`` replaced by A, B (and labels; and C with its output labels when
    ``measured``, for a subsystem); its time base appended to ``bases``."""
    where = f"{path}.{SYSTEM}"
    sys = entry[SYSTEM]
    if not is_state_space(sys):
        kind = type(sys)
        hint = "; a transfer function becomes one with control.ss(...)" if kind.__name__ == "TransferFunction" else ""
        raise ScenarioError(f"{where}: expected a python-control StateSpace (control.ss, control.c2d), got "
                            f"{kind.__module__}.{kind.__name__}{hint}", field=where)
    given = [key for key in ("A", "B") if key in entry]
    if given:
        raise ScenarioError(f"{where}: give either a system or {' and '.join(given)}, not both "
                            f"({path}.{given[0]} is also given)", field=where)
    D = np.asarray(sys.D, dtype=float)
    if D.size and np.any(D != 0):
        raise ScenarioError(f"{where}: D is not zero (largest |D| entry {np.abs(D).max():g}): dmpc's model is "
                            "x(k+1) = A x + B u with outputs y = C x (the whole state without 'estimation'), so D is "
                            "not used, and a feedthrough would be lost; pass control.ss(sys.A, sys.B, sys.C, 0) if "
                            "the feedthrough does not matter here", field=where)
    out = {key: value for key, value in entry.items() if key != SYSTEM}
    out["A"], out["B"] = np.asarray(sys.A, dtype=float), np.asarray(sys.B, dtype=float)
    if labelled:
        for key, labels in (("states", getattr(sys, "state_labels", None)), ("inputs", getattr(sys, "input_labels", None))):
            names = list(labels or [])
            if key not in out and names and not all(_DEFAULT_LABEL[key].fullmatch(n) for n in names):
                out[key] = [{"name": str(n)} for n in names]
        if measured:
            _measurements(sys, out)
    bases.append((where, _time_base(sys.dt, where)))
    return out


def _measurements(sys: Any, out: dict) -> None:
    """Put the system's C (unless the identity) and its output labels (unless python-control's
    defaults) into the subsystem entry ``out``, where the entry does not give them itself."""
    C = np.asarray(sys.C, dtype=float)
    identity = C.shape == (out["A"].shape[0],) * 2 and np.array_equal(C, np.eye(C.shape[0]))
    if "C" not in out and not identity:
        out["C"] = C
    names = list(getattr(sys, "output_labels", None) or [])
    if "outputs" not in out and names and not all(_DEFAULT_LABEL["outputs"].fullmatch(n) for n in names):
        out["outputs"] = [{"name": str(n)} for n in names]


TimeBase = float | Literal[True]
"""A system's time base: 0.0 (continuous), True (discrete, period not given) or the period in seconds."""


def _time_base(dt: Any, where: str) -> TimeBase:
    """0.0 (continuous), True (discrete, period not given) or the period in seconds, from a system's
    ``dt`` (whatever the object holds; a value float() refuses raises here)."""
    if dt is True:
        return True
    if dt is None or isinstance(dt, bool):
        raise ScenarioError(f"{where}: its time base is not set (dt = {dt}); give dt = 0 for continuous time or "
                            "the sampling period in seconds", field=where)
    value = float(dt)
    if not np.isfinite(value) or value < 0:
        raise ScenarioError(f"{where}: dt = {value:g} is not a time base (0 or a period > 0)", field=where)
    return value


def _is_continuous(dt: TimeBase) -> bool:
    return dt is not True and dt == 0.0


def _conflict(a: TimeBase, b: TimeBase) -> bool:
    """True unless the time bases ``a`` and ``b`` can belong to one scenario (True fits any period)."""
    if _is_continuous(a) != _is_continuous(b):
        return True
    if a is True or b is True:
        return False
    return not _close(a, b)


def _describe(dt: TimeBase) -> str:
    if dt is True:
        return "discrete-time (dt = True)"
    return "continuous-time (dt = 0)" if dt == 0 else f"discrete-time with dt = {dt:g} s"


def _set_time_base(data: dict, bases: list[tuple[str, TimeBase]]) -> None:
    first_path, first = bases[0]
    for path, dt in bases[1:]:
        if _conflict(first, dt):
            raise ScenarioError(f"{path}: {_describe(dt)}, but {first_path} is {_describe(first)}: every system "
                                "of a scenario needs the same time base (control.c2d(sys, dt) discretises one)",
                                field=path)
    periods = [dt for _, dt in bases if dt is not True]
    continuous = _is_continuous(first)
    time = data.get("time")
    if continuous:
        if time not in (None, "continuous"):
            raise ScenarioError(f"time: {time!r}, but {first_path} is continuous-time (dt = 0); leave time out or "
                                "give a discrete-time system (control.c2d)", field="time")
        if data.get("dt") is None:
            raise ScenarioError(f"dt: required: {first_path} is continuous-time (dt = 0), so the scenario needs the "
                                "sampling period to discretise it with", field="dt")
        data["time"] = "continuous"
        return
    if time not in (None, "discrete"):
        raise ScenarioError(f"time: {time!r}, but {first_path} is {_describe(first)}; leave time out or give a "
                            "continuous-time system", field="time")
    if periods:
        period = periods[0]
        given = data.get("dt")
        if given is not None and not _close(given, period):
            raise ScenarioError(f"dt: {given!r} differs from the sampling period of {first_path} ({period:g} s)",
                                field="dt")
        if given is None:
            data["dt"] = period


def _close(a: Any, b: float) -> bool:
    """Whether ``a`` (any value: one float() refuses is not close) equals the period ``b``."""
    try:
        return abs(float(a) - b) <= 1e-12 * max(1.0, abs(b))
    except (TypeError, ValueError):
        return False  # not a number: the schema says so

"""From a validated :class:`~dmpc.scenario.schema.Scenario` to the numerical objects of ``dmpc.core.system``.

Subsystems are indexed 0..M-1 in file order (a family: "1".."M" -> 0..M-1).
"""
from __future__ import annotations

import dataclasses
import math
from typing import overload

import numpy as np

from dmpc.core.system import CoupledSystem, Coupling, LinearSet, Subsystem
from dmpc.offline.tubes import RevisionBound
from dmpc.scenario.load import ScenarioError
from dmpc.scenario.schema import (
    BoxSpec,
    PolytopeSpec,
    Scenario,
    SubsystemSpec,
    SubsystemTemplate,
    setpoint_values,
    state_margin,
)
from dmpc.tracking.schedule import SetpointEntry

SETPOINT_TIME_TOLERANCE = 1e-9
"""A setpoint time within this many steps after a step's time takes effect at that step (rounding of t / dt)."""

__all__ = ["alpha0_vector", "build_system", "discrete_model", "given_gains", "revision_bounds"]


def _array(rows: list) -> np.ndarray:
    return np.array(rows, dtype=float)


def _symmetric(rows: list) -> np.ndarray:
    """The symmetric part (the schema allows asymmetry up to a 1e-9 relative tolerance)."""
    a = _array(rows)
    return (a + a.T) / 2


@overload
def _linear_set(spec: BoxSpec | PolytopeSpec, around: np.ndarray | None = None) -> LinearSet: ...


@overload
def _linear_set(spec: BoxSpec | PolytopeSpec | None, around: np.ndarray | None = None) -> LinearSet | None: ...


def _linear_set(spec: BoxSpec | PolytopeSpec | None, around: np.ndarray | None = None) -> LinearSet | None:
    """The set of ``spec``; with ``around`` (d,), the set of v - around for v in it (the set in
    deviations from an operating point)."""
    if spec is None:
        return None
    if isinstance(spec, BoxSpec):
        if around is None:
            return LinearSet.box(spec.lower, spec.upper)
        return LinearSet.box(np.asarray(spec.lower, float) - around, np.asarray(spec.upper, float) - around)
    if around is None:
        return LinearSet.polytope(spec.H, spec.h)
    H = np.atleast_2d(np.asarray(spec.H, float))
    return LinearSet.polytope(H, np.asarray(spec.h, float) - H @ around)


def operating_point(s: SubsystemTemplate) -> tuple[np.ndarray, np.ndarray] | None:
    """The subsystem's operating point (x_op (n_i,), u_op (m_i,)) in the plant's units, or None."""
    op = s.operating_point
    return None if op is None else (_array(op.x), _array(op.inputs(s.m)))


def build_system(scn: Scenario) -> CoupledSystem:
    """The coupled system of a scenario: the controllers' discrete-time model.

    Parameters
    ----------
    scn : Scenario

    Returns
    -------
    CoupledSystem
        Subsystems in file order with ``name`` = the user's id and ``C`` None where the file's C is
        omitted or the identity; couplings with 0-based indices
        (B = zeros where the file omits it); ``scn.graph`` as extra edges. With
        ``time: continuous``, the matrices discretised with ``dt`` (:func:`discrete_model`).
    """
    if scn.time == "continuous":
        return discrete_model(scn).system
    return _system_as_written(scn)


def discrete_model(scn: Scenario):
    """The discretisation of the ``time: continuous`` scenario ``scn``
    (:class:`dmpc.core.discretisation.DiscreteModel`).

    Raises
    ------
    ScenarioError
        The scenario is in discrete time, or ``exact-zoh`` spreads entries outside the coupling
        graph above ``discretisation.tolerance`` without ``truncate``.
    """
    from dmpc.core.discretisation import FillInRefused, discretise  # lazy: scipy.linalg only when needed

    if scn.time != "continuous":
        raise ScenarioError("time: the scenario is in discrete time; nothing to discretise", field="time")
    d, dt = scn.discretisation, scn.dt
    assert dt is not None  # the schema asks for dt in continuous time
    try:
        return discretise(_system_as_written(scn), dt, d.method, d.truncate, d.tolerance)
    except FillInRefused as exc:
        raise ScenarioError(f"discretisation: {exc}", field="discretisation.truncate") from None


def _system_as_written(scn: Scenario) -> CoupledSystem:
    specs = scn.resolved_subsystems()
    index = {s.name: i for i, s in enumerate(specs)}
    margin = None if scn.estimation is None else scn.estimation.margin
    subsystems = tuple(_with_margin(_subsystem(s), state_margin(margin, s)) for s in specs)
    couplings = []
    for c in scn.resolved_couplings():
        t, s = index[c.target], index[c.source]
        B = _array(c.B) if c.B is not None else np.zeros((subsystems[t].n, subsystems[s].m))
        couplings.append(Coupling(target=t, source=s, A=_array(c.A), B=B))
    edges = tuple((min(index[a], index[b]), max(index[a], index[b])) for a, b in scn.graph)
    return CoupledSystem(subsystems=subsystems, couplings=tuple(couplings), edges=edges)


def _subsystem(s: SubsystemSpec) -> Subsystem:
    """The subsystem ``s`` in the model's coordinates: x0 and the sets in deviations from its operating
    point when it gives one."""
    C = None if s.C is None or s.measures_state else _array(s.C)  # the identity as None: today's runs, bit for bit
    op = operating_point(s)
    if op is None:
        return Subsystem(name=s.name, A=_array(s.A), B=_array(s.B), Q=_symmetric(s.Q), R=_symmetric(s.R),
                         x0=_array(s.x0), input_set=_linear_set(s.input), state_set=_linear_set(s.state), C=C)
    x_op, u_op = op
    return Subsystem(name=s.name, A=_array(s.A), B=_array(s.B), Q=_symmetric(s.Q), R=_symmetric(s.R),
                     x0=_array(s.x0) - x_op, input_set=_linear_set(s.input, u_op),
                     state_set=_linear_set(s.state, x_op), C=C, x_op=x_op, u_op=u_op)


def _with_margin(sub: Subsystem, margin: list[float] | None) -> Subsystem:
    """``sub`` whose controllers keep ``margin`` (n_i,) from its state bounds for the estimation error
    (``estimation.margin``); ``sub`` itself without one (or a margin of zeros)."""
    if margin is None or not any(margin) or sub.state_set is None:
        return sub
    e = _array(margin)
    shrink = np.abs(np.asarray(sub.state_set.H, dtype=float)) @ e
    tightened = LinearSet(sub.state_set.H, sub.state_set.lower + shrink, sub.state_set.upper - shrink)
    return dataclasses.replace(sub, state_set=tightened, state_margin=e)


def given_gains(scn: Scenario) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The K_i (m_i x n_i) and P_i (n_i x n_i, symmetrised) of the scenario ``scn``, in subsystem order.

    Raises
    ------
    ScenarioError
        If ``design.gains`` is not ``'given'``.
    """
    if scn.design.gains != "given":
        raise ScenarioError(f"design.gains: is '{scn.design.gains}', gains are read from the scenario "
                            "only when it is 'given'", field="design.gains")
    K, P = [], []
    for i, s in enumerate(scn.resolved_subsystems()):
        if s.K is None or s.P is None:  # the schema asks for both with design.gains: given
            raise ScenarioError(f"{scn.subsystem_path(i)}: K and P are required when design.gains is 'given'",
                                field=scn.subsystem_path(i))
        K.append(_array(s.K))
        P.append(_symmetric(s.P))
    return K, P


def alpha0_vector(scn: Scenario, system: CoupledSystem) -> np.ndarray:
    """The global alpha(0): ``terminal.alpha0`` stacked in subsystem order, zeros where absent.

    Parameters
    ----------
    scn : Scenario
    system : CoupledSystem
        ``build_system(scn)`` (only its names and offsets are used).

    Returns
    -------
    ndarray, shape (n,)
    """
    alpha = np.zeros(system.n)
    given = dict(scn.terminal.alpha0 or {})
    for i, sub in enumerate(system.subsystems):
        if sub.name in given:
            alpha[system.xs(i)] = given.pop(sub.name)
    if given:
        name = next(iter(given))
        raise ScenarioError(f"terminal.alpha0.{name}: subsystem '{name}' is not in the system",
                            field=f"terminal.alpha0.{name}")
    return alpha


def revision_bounds(scn: Scenario) -> dict:
    """``{index: dmpc.offline.tubes.RevisionBound}`` for the subsystems of ``scn`` that declare one."""
    return {i: RevisionBound(state=_array(s.revision_bound.state), input=_array(s.revision_bound.input))
            for i, s in enumerate(scn.resolved_subsystems()) if s.revision_bound is not None}


def setpoint_entries(scenario: Scenario) -> tuple[SetpointEntry, ...]:
    """The scenario's setpoint schedule as entries on step indices (``at`` in seconds turned into
    the first step at or after that time when the scenario has dt), NaN for free components.

    Without ``estimation`` the outputs are the states (C is the identity), so a request of ``y`` is
    one of ``x`` and every entry has ``y`` None. With it, the requests are on the outputs: every entry
    has ``y`` (p_i,), a requested state becomes a request of the output that measures it alone (the
    schema refuses the others), and ``x`` is all NaN.
    """
    subs = scenario.resolved_subsystems()
    index = {s.name: i for i, s in enumerate(subs)}
    entries = []
    for e, spec in enumerate(scenario.setpoints):
        i = index[spec.subsystem]
        sub = subs[i]
        path = f"setpoints[{e}]"
        k = int(spec.at) if scenario.dt is None else int(math.ceil(spec.at / scenario.dt - SETPOINT_TIME_TOLERANCE))
        op = operating_point(sub)
        x_op, u_op = op if op is not None else (np.zeros(sub.n), np.zeros(sub.m))
        x = _nan_free(setpoint_values(spec, sub, "x", path)) - x_op
        u = _nan_free(setpoint_values(spec, sub, "u", path)) - u_op
        y = None
        if spec.y is not None or scenario.estimation is not None:
            y_op = x_op if sub.C is None else _array(sub.C) @ x_op
            requested = _nan_free(setpoint_values(spec, sub, "y", path)) - y_op
            if scenario.estimation is None:  # C is the identity: outputs r are the states r
                x = np.where(np.isnan(requested), x, requested)
            else:
                y = requested
                for r, j in sub.state_rows().items():  # the output that measures state j alone (rows are independent)
                    if not np.isnan(x[j]):
                        y[r] = x[j]
                x = np.full(sub.n, np.nan)
        entries.append(SetpointEntry(max(k, 0), i, x, u, y=y))
    return tuple(entries)


def _nan_free(values: list[float | None]) -> np.ndarray:
    """The components of a request as floats, NaN where free (None)."""
    return np.array([np.nan if v is None else v for v in values], float)

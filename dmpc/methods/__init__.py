"""The control methods dmpc can run on one scenario, for comparison.

| method | terminal set of agent i | how it moves |
|---|---|---|
| ``tv-box`` | box ||z_i(N) - alpha_i|| <= beta | alpha(k+1) = (A+BK) eta, beta = sigma(alpha) (the paper) |
| ``tv-box-opt`` | the same | the same, with alpha(0), beta(0) chosen by optimisation at k = 0 |
| ``fixed-box`` | the same box | alpha, beta keep their values at k = 0 |
| ``ellipsoid`` | z_i(N)' P_i z_i(N) <= r | static common level r |
| ``ellipsoid-adaptive`` | z_i(N)' P_i z_i(N) <= r_i | r_i(k+1) = r_i(k) + eta' Gamma_i eta |
| ``centralized`` | one QP over the whole system, Omega z(N) <= 1 | none: the optimality reference |

Only the terminal rows and their update differ (:mod:`dmpc.methods.policy`); everything else is
the same code.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dmpc.core.steps import DEFAULT_METHOD as DEFAULT_METHOD  # the names live with the other run options
from dmpc.core.steps import METHOD_NAMES, Method
from dmpc.core.system import CoupledSystem, LinearSet
from dmpc.methods.policy import BoxPolicy, EllipsoidPolicy, TerminalPolicy
from dmpc.offline import ControllerDesign


@dataclass(frozen=True)
class MethodSpec:
    """One method: its name, a one-line description, and whether agents run it."""

    name: Method
    description: str
    distributed: bool = True


METHODS: dict[str, MethodSpec] = {m.name: m for m in (
    MethodSpec("tv-box", "time-varying terminal boxes: alpha(k+1) = (A+BK) eta, beta(k+1) = sigma(alpha(k+1))"),
    MethodSpec("tv-box-opt", "tv-box with alpha(0), beta(0) = sigma(alpha(0)) chosen by the centralised QP at k = 0"),
    MethodSpec("fixed-box", "terminal boxes held at alpha(0), beta(0) (no update)"),
    MethodSpec("ellipsoid", "terminal ellipsoids z_i' P_i z_i <= r at the static common level (inscribed polytopes)"),
    MethodSpec("ellipsoid-adaptive", "terminal ellipsoids with levels r_i(k+1) = r_i(k) + eta' Gamma_i eta"),
    MethodSpec("centralized", "one QP over the whole system with Omega z(N) <= 1: the optimality reference",
               distributed=False),
)}
assert METHOD_NAMES == tuple(METHODS), "every method has a spec, in the same order"


def method_spec(name: str) -> MethodSpec:
    """The method called ``name``; ValueError listing the methods if there is none."""
    try:
        return METHODS[name]
    except KeyError:
        raise ValueError(f"unknown method {name!r} (expected one of: {', '.join(METHODS)})") from None


def terminal_policy(name: str, system: CoupledSystem, design: ControllerDesign) -> TerminalPolicy:
    """The :class:`~dmpc.methods.policy.TerminalPolicy` of a distributed method.

    Raises
    ------
    ValueError
        For an unknown method, or for ``centralized``, which has no agents.
    """
    spec = method_spec(name)
    if not spec.distributed:
        raise ValueError(f"method {name!r} runs no agents and has no terminal policy")
    if name in ("tv-box", "fixed-box"):
        return BoxPolicy(system, design, name, time_varying=name == "tv-box")
    if name == "tv-box-opt":
        from dmpc.methods.initial import BoxOptimizer  # start-up time: only the tv-box-opt method uses it

        return BoxPolicy(system, design, name, time_varying=True, optimizer=BoxOptimizer(system, design))
    return EllipsoidPolicy(system, design, name, adaptive=name == "ellipsoid-adaptive")


def initial_terminal_set(name: str, system: CoupledSystem, design: ControllerDesign) -> LinearSet:
    """The method's terminal constraint at k = 0 on the global state (rows on z(N), dimension n).

    The box methods impose the box around alpha0; ``tv-box-opt`` and ``centralized`` may use all
    of X^f; the ellipsoid methods their inscribed polytopes.
    """
    if name in ("tv-box-opt", "centralized"):
        omega = design.terminal.omega
        return LinearSet.polytope(omega, np.ones(omega.shape[0]))
    policy = terminal_policy(name, system, design)
    T, lower, upper = policy.joint_terminal(policy.initial(system.x0))
    return LinearSet(T, lower, upper)

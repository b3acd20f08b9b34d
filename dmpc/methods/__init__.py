"""The control methods dmpc can run on one scenario, for comparison.

| method | terminal set of agent i | how it moves |
|---|---|---|
| ``tv-box`` | box ||z_i(N) - alpha_i|| <= beta | alpha(k+1) = (A+BK) eta, beta = sigma(alpha) (the paper) |
| ``tv-box-opt`` | the same | the same, with alpha(0), beta(0) chosen by optimisation at k = 0 |
| ``tv-box-coop`` | the same | the same; each agent minimises the cost of every subsystem its inputs reach |
| ``fixed-box`` | the same box | alpha, beta keep their values at k = 0 |
| ``ellipsoid`` | z_i(N)' P_i z_i(N) <= r | static common level r |
| ``ellipsoid-adaptive`` | z_i(N)' P_i z_i(N) <= r_i | r_i(k+1) = r_i(k) + eta' Gamma_i eta |
| ``centralized`` | one QP over the whole system, Omega z(N) <= 1 | none: the optimality reference |

Only the terminal rows and their update differ (:mod:`dmpc.methods.policy`); everything else is
the same code. What each method can do (run agents, track setpoints, work with the event trigger,
cooperate) is recorded on its :class:`MethodSpec`, and every check of it goes through
:func:`lacks` (or :func:`require`), whose error names the method and what it cannot do.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

from dmpc.core.errors import InputError
from dmpc.core.steps import DEFAULT_METHOD as DEFAULT_METHOD  # the names live with the other run options
from dmpc.core.steps import METHOD_NAMES, Method
from dmpc.core.system import CoupledSystem, LinearSet
from dmpc.methods.policy import BoxPolicy, EllipsoidPolicy, TerminalPolicy
from dmpc.offline import ControllerDesign

Capability = Literal["distributed", "tracks_setpoints", "supports_trigger", "cooperative"]
"""What a method may or may not do: a boolean field of :class:`MethodSpec` each."""
CAPABILITIES: tuple[Capability, ...] = get_args(Capability)

TerminalKind = Literal["box", "ellipsoid", "omega"]
"""The shape of a method's terminal set: a box per agent around alpha_i, an ellipsoid per agent
(imposed through an inscribed polytope), or X^f itself on the whole state (one central QP)."""

_LACKING: dict[Capability, str] = {
    "distributed": "runs no agents",
    "tracks_setpoints": "does not track setpoints",
    "supports_trigger": "does not work with the event trigger",
    "cooperative": "is not cooperative",
}
"""Per capability, what a method that lacks it does not do, in words."""


@dataclass(frozen=True)
class MethodSpec:
    """One method: its name, a one-line description, its terminal set and what it can do.

    Attributes
    ----------
    name : str
    description : str
    terminal : {"box", "ellipsoid", "omega"}
        The shape of its terminal set (:data:`TerminalKind`).
    moving : bool
        The terminal set moves at every step: the boxes with alpha(k+1) = (A+BK) eta and
        beta(k+1) = sigma(alpha(k+1)), the ellipsoids with their adaptive levels. False keeps the
        values of k = 0.
    optimised_start : bool
        alpha(0), beta(0) are chosen by the centralised QP from x(0) (the box methods; its k = 0
        terminal constraint is then X^f shrunk by beta_min, on all of X^f).
    distributed : bool
        Agents run it (False: one QP over the whole system, no agents, no bus).
    tracks_setpoints : bool
        It tracks the scenario's setpoints (and live setpoint requests) with the reference governor.
    supports_trigger : bool
        Its agents can run with the event trigger (``options.trigger: event``).
    cooperative : bool
        Each agent minimises the cost of every subsystem its inputs reach, not only its own.
    """

    name: Method
    description: str
    terminal: TerminalKind
    moving: bool = True
    optimised_start: bool = False
    distributed: bool = True
    tracks_setpoints: bool = False
    supports_trigger: bool = False
    cooperative: bool = False


METHODS: dict[str, MethodSpec] = {m.name: m for m in (
    MethodSpec("tv-box", "time-varying terminal boxes: alpha(k+1) = (A+BK) eta, beta(k+1) = sigma(alpha(k+1))",
               "box", tracks_setpoints=True, supports_trigger=True),
    MethodSpec("tv-box-opt", "tv-box with alpha(0), beta(0) = sigma(alpha(0)) chosen by the centralised QP at k = 0",
               "box", optimised_start=True, tracks_setpoints=True, supports_trigger=True),
    MethodSpec("tv-box-coop", "cooperative DMPC (Stewart et al. 2010): each agent minimises the cost of every "
                              "subsystem its inputs reach, rounds combined so every iterate stays feasible; "
                              "time-varying terminal boxes",
               "box", tracks_setpoints=True, cooperative=True),
    MethodSpec("fixed-box", "terminal boxes held at alpha(0), beta(0) (no update)", "box", moving=False),
    MethodSpec("ellipsoid", "terminal ellipsoids z_i' P_i z_i <= r at the static common level (inscribed polytopes)",
               "ellipsoid", moving=False),
    MethodSpec("ellipsoid-adaptive", "terminal ellipsoids with levels r_i(k+1) = r_i(k) + eta' Gamma_i eta",
               "ellipsoid"),
    MethodSpec("centralized", "one QP over the whole system with Omega z(N) <= 1: the optimality reference "
                              "(with setpoints, around the target: Omega (z(N) - x_s) <= lambda)",
               "omega", moving=False, distributed=False, tracks_setpoints=True),
)}
assert METHOD_NAMES == tuple(METHODS), "every method has a spec, in the same order"


def method_spec(name: str) -> MethodSpec:
    """The method called ``name``; ValueError listing the methods if there is none."""
    try:
        return METHODS[name]
    except KeyError:
        raise ValueError(f"unknown method {name!r} (expected one of: {', '.join(METHODS)})") from None


# ----------------------------------------------------------------------------- capabilities
def methods_with(capability: Capability) -> tuple[Method, ...]:
    """The methods that have ``capability``, in the order of :data:`METHODS`."""
    return tuple(spec.name for spec in METHODS.values() if getattr(spec, capability))


class CapabilityError(InputError, ValueError):
    """A method asked to do what it cannot; the message names the method, the capability it lacks
    and the methods that have it, e.g. "method 'ellipsoid' does not track setpoints (methods that
    do: tv-box, tv-box-opt, tv-box-coop, centralized)". An :class:`~dmpc.core.errors.InputError`
    (the method was chosen), and a ValueError as the checks of a method's name raise.

    Parameters
    ----------
    method : str
    capability : str
        One of :data:`CAPABILITIES`.
    consequence : str
        What the caller cannot do for it, appended after a colon ("" for nothing).
    """

    def __init__(self, method: str, capability: Capability, consequence: str = "") -> None:
        self.method = method
        self.capability = capability
        having = methods_with(capability)
        others = f"methods that do: {', '.join(having)}" if having else "no method does"
        tail = f": {consequence}" if consequence else ""
        super().__init__(f"method '{method}' {_LACKING[capability]} ({others}){tail}")


def lacks(method: str | MethodSpec, capability: Capability, consequence: str = "") -> CapabilityError | None:
    """None when ``method`` (a name or a spec) has ``capability``; else the error that says so,
    followed by ``consequence`` if given (what the caller cannot do for it).

    The one check of a method's capabilities: :func:`require` raises what it returns, and a
    caller that reports rather than raises (a skipped run, a refused request) takes its text.

    Raises
    ------
    ValueError
        For an unknown method name, or an unknown capability.
    """
    spec = method if isinstance(method, MethodSpec) else method_spec(method)
    if capability not in _LACKING:
        raise ValueError(f"unknown capability {capability!r} (expected one of: {', '.join(CAPABILITIES)})")
    return None if getattr(spec, capability) else CapabilityError(spec.name, capability, consequence)


def require(method: str | MethodSpec, capability: Capability, consequence: str = "") -> MethodSpec:
    """The spec of ``method``; :class:`CapabilityError` if it lacks ``capability`` (:func:`lacks`,
    with ``consequence``)."""
    error = lacks(method, capability, consequence)
    if error is not None:
        raise error
    return method if isinstance(method, MethodSpec) else method_spec(method)


# ----------------------------------------------------------------------------- terminal sets
def terminal_policy(name: str, system: CoupledSystem, design: ControllerDesign) -> TerminalPolicy:
    """The :class:`~dmpc.methods.policy.TerminalPolicy` of the distributed method ``name`` on
    ``system`` with ``design``, built from its spec (its terminal kind, whether the set moves,
    whether alpha(0) is optimised).

    Raises
    ------
    ValueError
        For an unknown method, or for one that runs no agents (:class:`CapabilityError`, e.g.
        ``centralized``: it has no terminal policy).
    """
    spec = require(name, "distributed", "it has no terminal policy")
    if spec.terminal == "box":
        if spec.optimised_start:
            from dmpc.methods.initial import BoxOptimizer  # start-up time: only where alpha(0) is optimised

            return BoxPolicy(system, design, name, time_varying=spec.moving, optimizer=BoxOptimizer(system, design))
        return BoxPolicy(system, design, name, time_varying=spec.moving)
    return EllipsoidPolicy(system, design, name, adaptive=spec.moving)


def initial_terminal_set(name: str, system: CoupledSystem, design: ControllerDesign) -> LinearSet:
    """The terminal constraint at k = 0 of the method ``name`` on the global state of ``system``
    (rows on z(N), dimension n), with ``design``.

    The box methods impose the box around alpha0; a method that optimises alpha(0)
    (``tv-box-opt``) and one whose terminal set is X^f (``centralized``) may use all of X^f; the
    ellipsoid methods their inscribed polytopes.
    """
    spec = method_spec(name)
    if spec.terminal == "omega" or spec.optimised_start:
        omega = design.terminal.omega
        return LinearSet.polytope(omega, np.ones(omega.shape[0]))
    policy = terminal_policy(name, system, design)
    T, lower, upper = policy.joint_terminal(policy.initial(system.x0))
    return LinearSet(T, lower, upper)

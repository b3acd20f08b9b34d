"""The messages of the step protocol (typed, immutable).

- ``Release`` coordinator -> every agent (one broadcast): step k, Jacobi round, the measured
  state, each agent's terminal centre and size and, per agent, which of its plans its neighbours
  build their assumed trajectory from.
- ``PlanMessage`` agent i -> neighbours and coordinator: the solved plan of (k, round).
- ``Kept`` agent i -> coordinator: with an event trigger, the agent kept its shifted plan at step k
  (no solve, no plan message; everyone rebuilds the kept plan from what they hold).
- ``Ready`` agent -> coordinator: the agent is set up (with the digest of its design).
- ``Stop`` coordinator -> everyone: the run is over (finished, aborted, failed).
- ``Inputs`` coordinator -> plant: the inputs u(k) to apply.
- ``State`` plant (or one subsystem's sensor) -> coordinator: the measured state x(k).
- ``Setpoint`` a supervisory program -> coordinator: a new setpoint of one subsystem while the run
  goes on.
- ``SetpointAnswer`` coordinator -> that program: accepted from step k, or refused and why.

Agents are named by the scenario's subsystem names; the coordinator is ``"coordinator"``, a plant
that reports the whole state ``"plant"``, and one that reports subsystem I alone ``"sensor-I"``.
Every message carries ``PROTOCOL_VERSION`` (docs/protocol.md).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from dmpc.bus.keys import COORDINATOR_ROLE

PROTOCOL_VERSION = 3
COORDINATOR = COORDINATOR_ROLE
# After the coordinator's liveliness goes, agents and a plant wait this long for it to come back
# before exiting. A link that broke (or a process hung past the lease and resumed) reconnects
# within it: at once, or at Zenoh's first connect retry one second later. A crashed coordinator
# never comes back: its liveliness goes at once (a hung one's after the lease).
COORDINATOR_GRACE = 1.5


@dataclass(frozen=True)
class Release:
    """Step k, Jacobi round ``round`` (``iteration`` on the wire), released to every agent at once.

    One message per round for the whole run: each agent reads its own part (the states of N_i,
    its centre and size, its neighbours' references). Agents are indexed in the scenario's order.

    Attributes
    ----------
    x : ndarray, shape (n,)
        The measured state x(k) of every subsystem.
    centres : ndarray, shape (n,)
        The terminal centres released, agent i's on its own coordinates (alpha_i(k) for the box
        methods, zeros for the ellipsoid ones).
    sizes : ndarray, shape (M,)
        The terminal size released to each agent (beta(k) for the box methods, the level r_i(k)
        for the ellipsoid ones).
    assumed : ndarray of int64, shape (M, 2)
        Row j: the plan (k', round') of agent j that its neighbours build its assumed trajectory
        from; ``(-1, -1)`` means none, the decoupled K-rollout from x_j(k).
    skipped : tuple of str
        Agents not released this round (lost ones): they ignore it.
    provided : dict name -> (z, v)
        Plans supplied by the coordinator itself (the centralised seed at k = 0); they stand for
        the plans named in ``assumed``. Usually empty.
    target : (ndarray (n,), ndarray (m,)) or None
        The setpoint target (x_s, u_s) of the whole system the step is controlled around. The
        origin (no setpoint) is a target like any other, zeros, but travels as None: left out on
        the wire, as before targets existed, and read back as the origin by whoever receives it
        (:meth:`dmpc.agents.controller.AgentController.operating_point`). A sender leaves it out
        exactly when the target is the origin; zeros written out mean the same.
    kept : tuple of str
        The agents that kept their plan at step k - 1 (an event trigger): the plans ``assumed``
        names for them are their plans of step k - 2 kept (:func:`dmpc.core.trajectories.kept_plan`
        with the state and centre of release k - 1). Left out on the wire when empty.
    iterate : (ndarray (N+1, n), ndarray (N, m)) or None
        The cooperative method's iterate of the round (``tv-box-coop``; docs/algorithm.md,
        "Cooperative DMPC"): every subsystem's planned states z and inputs v, in the plant's
        coordinates, z[0] = x. Each agent proposes its own inputs against it. None (left out on
        the wire) for the other methods.
    """

    run: str
    k: int
    round: int
    x: np.ndarray
    centres: np.ndarray
    sizes: np.ndarray
    assumed: np.ndarray
    sender: str = COORDINATOR
    skipped: tuple[str, ...] = ()
    provided: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    target: tuple[np.ndarray, np.ndarray] | None = None
    kept: tuple[str, ...] = ()
    iterate: tuple[np.ndarray, np.ndarray] | None = None

    @cached_property
    def kept_set(self) -> frozenset[str]:
        """``kept`` as a set, made once per message: the agents of a process share one decoded
        release, and each looks up its few neighbours in it."""
        return frozenset(self.kept)

    def reference(self, j: int) -> tuple[int, int] | None:
        """The plan (k', round') agent j's assumed trajectory is built from, or None (K-rollout)."""
        k, r = self.assumed[j]
        return None if k < 0 else (int(k), int(r))


@dataclass(frozen=True)
class PlanMessage:
    """Agent ``sender``'s plan for step k, Jacobi round ``round`` (``iteration`` on the wire).

    Attributes
    ----------
    run : str
        The run id (every key starts with ``dmpc/<run>/``): a message of another run is dropped.
    k : int
        The step of the release the plan answers.
    round : int
        Its Jacobi round.
    sender : str
        The agent's subsystem name (the key's last chunk).
    status : str
        A QPStatus value.
    z : ndarray, shape (N + 1, n_i)
    v : ndarray, shape (N, m_i)
        Both all-NaN when the QP was not solved.
    cost : float
        J_i of the plan (NaN when not solved).
    solve_time : float
        Seconds in the solver.
    qp_iterations : int
        The solver's iteration count.
    sent_at : float
        Sender's clock when published (latency measurement only).
    reason : str
        With an event trigger, why the agent solved rather than kept its plan
        (:data:`dmpc.agents.trigger.REASONS`); "" without one (left out on the wire).
    """

    run: str
    k: int
    round: int
    sender: str
    status: str
    z: np.ndarray
    v: np.ndarray
    cost: float
    solve_time: float
    qp_iterations: int
    sent_at: float = 0.0
    reason: str = ""


@dataclass(frozen=True)
class Kept:
    """Agent ``sender`` kept its shifted plan at step k, round ``round`` (an event trigger): the
    coordinator rebuilds the plan from the agent's last one, x(k) and alpha(k).

    Attributes
    ----------
    run : str
        The run id (every key starts with ``dmpc/<run>/``): a message of another run is dropped.
    k, round : int
        The step and round of the release it answers (round 0: an agent keeps only there).
    sender : str
        The agent's subsystem name (the key's last chunk).
    sent_at : float
        Sender's clock when published (latency measurement only).
    """

    run: str
    k: int
    round: int
    sender: str
    sent_at: float = 0.0


@dataclass(frozen=True)
class Ready:
    """Agent ``sender`` is set up and subscribed; ``design_digest`` identifies its design.

    ``scenario`` (its scenario's name) and ``horizon`` (N) only help to say how a design
    differs from the plant's; a sender may leave them out ("" and 0: unknown).

    Attributes
    ----------
    run : str
        The run id (every key starts with ``dmpc/<run>/``): a message of another run is dropped.
    sender : str
        The agent's subsystem name.
    design_digest : str
        The digest of the agent's design; the coordinator starts only with agents whose digest
        equals its own.
    pid : int
        The agent's process id (for the records; 0 when not given).
    scenario : str
        The agent's scenario's name ("" when not given).
    horizon : int
        The agent's horizon N (0 when not given).
    """

    run: str
    sender: str
    design_digest: str
    pid: int = 0
    scenario: str = ""
    horizon: int = 0


@dataclass(frozen=True)
class Stop:
    """The run is over at step k; ``reason`` is ``finished``, ``aborted`` or ``failed: ...``.

    Attributes
    ----------
    run : str
        The run id (every key starts with ``dmpc/<run>/``): a message of another run is dropped.
    k : int
        The step at which the run stopped.
    reason : str
        ``finished``, ``aborted``, or ``failed: ...`` with the reason.
    sender : str
        Who stops the run: the coordinator.
    """

    run: str
    k: int
    reason: str
    sender: str = COORDINATOR


@dataclass(frozen=True)
class Inputs:
    """The inputs to apply at step k, one entry per subsystem.

    Attributes
    ----------
    run : str
        The run id (every key starts with ``dmpc/<run>/``): a message of another run is dropped.
    k : int
        The step whose inputs these are.
    u : dict name -> ndarray, shape (m_i,)
        Subsystem i's input u_i(k), for every subsystem in the scenario's order.
    sender : str
        Who decided them: the coordinator.
    """

    run: str
    k: int
    u: dict[str, np.ndarray]
    sender: str = COORDINATOR


@dataclass(frozen=True)
class State:
    """The measured state x(k) of some or all subsystems, or their measured outputs y(k), from ``sender``.

    A plant that measures everything sends one ``State`` per step with every subsystem; a
    sensor of subsystem I (``sender`` = ``"sensor-I"``) sends its own entry only.

    Attributes
    ----------
    run : str
        The run id (every key starts with ``dmpc/<run>/``): a message of another run is dropped.
    k : int
        The step whose state this is: x(0) at the start, x(k + 1) after the inputs of step k.
    sender : str
        ``"plant"``, or ``"sensor-<name>"`` (the key's last chunk).
    x : dict name -> ndarray, shape (n_i,)
        Subsystem i's measured state x_i(k).
    y : dict name -> ndarray, shape (p_i,)
        Subsystem i's measured outputs y_i(k), in place of its state (a run with estimation only);
        optional on the wire, left out when empty. A subsystem is in ``x`` or in ``y``, not both.
    """

    run: str
    k: int
    sender: str
    x: dict[str, np.ndarray]
    y: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass(frozen=True)
class Setpoint:
    """Request ``id`` of ``sender``: subsystem ``subsystem`` asks for ``x`` and ``u`` from the first
    step whose target the coordinator has not decided yet.

    Attributes
    ----------
    run : str
        The run id (every key starts with ``dmpc/<run>/``): a message of another run is dropped.
    sender : str
        Who asks (the key's last chunk); the answer goes to ``setpoint-answer/<sender>``.
    id : int
        Chosen by the sender, echoed in the answer.
    subsystem : str
        The subsystem's name.
    x : ndarray, shape (n_i,) or (0,)
        The requested states, NaN where free; empty: every state free.
    u : ndarray, shape (m_i,) or (0,)
        The requested inputs, the same way.
    """

    run: str
    sender: str
    id: int
    subsystem: str
    x: np.ndarray
    u: np.ndarray


@dataclass(frozen=True)
class SetpointAnswer:
    """The coordinator's answer to request ``id``: ``accepted`` from step ``k`` on, or refused
    (``k`` = -1) for ``reason``.

    Attributes
    ----------
    run : str
        The run id (every key starts with ``dmpc/<run>/``): a message of another run is dropped.
    id : int
        The request's ``id``.
    subsystem : str
        The request's ``subsystem``.
    accepted : bool
        True: the request joins the setpoint schedule.
    k : int
        Accepted: the first step the request holds at. Refused: -1.
    reason : str
        Why it was refused; "" when accepted.
    """

    run: str
    id: int
    subsystem: str
    accepted: bool
    k: int
    reason: str = ""


Message = Release | PlanMessage | Kept | Ready | Stop | Inputs | State | Setpoint | SetpointAnswer

MESSAGE_TYPES: dict[str, type] = {"release": Release, "plan": PlanMessage, "kept": Kept, "ready": Ready, "stop": Stop,
                                  "inputs": Inputs, "state": State, "setpoint": Setpoint,
                                  "setpoint-answer": SetpointAnswer}
TYPE_NAMES: dict[type, str] = {v: k for k, v in MESSAGE_TYPES.items()}


def design_claim(name: str, digest: str) -> str:
    """The words with which the coordinator's ``Stop`` reason names agent ``name``'s differing design.

    An agent that finds them with its own name and digest knows that the coordinator refused its design.
    """
    return f"agent {name} uses design {digest}"


def messages_equal(a: Message, b: Message) -> bool:
    """Equality that compares arrays by value (NaN equal to NaN).

    Parameters
    ----------
    a, b : Message
        The two messages: equal when of the same class and every field equal, arrays in shape,
        dtype and value, inside tuples, lists and maps too.
    """
    if type(a) is not type(b):
        return False
    for name in a.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if not _values_equal(x, y):
            return False
    return True


def _values_equal(x, y) -> bool:
    if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
        return (isinstance(x, np.ndarray) and isinstance(y, np.ndarray) and x.shape == y.shape
                and x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True))
    if isinstance(x, (tuple, list)):
        return isinstance(y, (tuple, list)) and len(x) == len(y) and all(_values_equal(a, b) for a, b in zip(x, y))
    if isinstance(x, dict):
        return isinstance(y, dict) and x.keys() == y.keys() and all(_values_equal(x[k], y[k]) for k in x)
    if isinstance(x, float) and isinstance(y, float) and np.isnan(x) and np.isnan(y):
        return True
    return x == y


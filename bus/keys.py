"""Every key expression of the protocol, built in one place.

``dmpc/<run>/release``          coordinator -> every agent (one broadcast per round)
``dmpc/<run>/plan/<agent>``     agent -> neighbours, coordinator
``dmpc/<run>/ready/<agent>``    agent -> coordinator
``dmpc/<run>/control``          coordinator -> all (Stop)
``dmpc/<run>/inputs``           coordinator -> plant (the inputs of step k)
``dmpc/<run>/state/<source>``   plant or sensor -> coordinator (``plant`` or ``sensor-<name>``)
``dmpc/<run>/alive/<role>``     liveliness tokens (``coordinator``, ``plant``, ``sensor-<name>``,
                                ``agent-<name>``)
``dmpc/<run>/telemetry/<kind>`` coordinator -> observers (``step``, ``meta``, ``end``; best effort)
``dmpc/<run>/setpoint/<sender>``        a supervisory program -> coordinator (a setpoint request)
``dmpc/<run>/setpoint-answer/<sender>`` coordinator -> that program (the answer)

docs/protocol.md describes each of them.
"""
from __future__ import annotations

import re

ROOT = "dmpc"
_SAFE = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


def check_chunk(text: str, what: str) -> str:
    """Return ``text`` if it is safe as one key chunk; ValueError otherwise, naming it as ``what`` (e.g. "run id")."""
    if not _SAFE.match(text):
        raise ValueError(f"{what} {text!r} must be 1-64 characters from A-Z a-z 0-9 _ . -")
    return text


def release(run: str) -> str:
    """The releases of run ``run`` (coordinator -> every agent)."""
    return f"{ROOT}/{run}/release"


def plan(run: str, agent: str) -> str:
    """The plans of agent ``agent`` in run ``run`` (agent -> neighbours, coordinator)."""
    return f"{ROOT}/{run}/plan/{agent}"


def kept(run: str, agent: str) -> str:
    """The Kept notices of agent ``agent`` in run ``run`` (an event trigger kept its plan)."""
    return f"{ROOT}/{run}/kept/{agent}"


def ready(run: str, agent: str) -> str:
    """The Ready messages of agent ``agent`` in run ``run``."""
    return f"{ROOT}/{run}/ready/{agent}"


def control(run: str) -> str:
    """The control messages (Stop) of run ``run``."""
    return f"{ROOT}/{run}/control"


def alive(run: str, role: str) -> str:
    """The liveliness token of role ``role`` in run ``run``."""
    return f"{ROOT}/{run}/alive/{role}"


def inputs(run: str) -> str:
    """The inputs of each step of run ``run`` (coordinator -> plant)."""
    return f"{ROOT}/{run}/inputs"


def state(run: str, source: str) -> str:
    """The states sent by ``source`` (``plant`` or ``sensor-<name>``) in run ``run``."""
    return f"{ROOT}/{run}/state/{source}"


def state_prefix(run: str) -> str:
    """Every source's states in run ``run``."""
    return f"{ROOT}/{run}/state/*"


def telemetry(run: str, kind: str) -> str:
    """The telemetry of kind ``kind`` (``step``, ``meta``, ``end``) of run ``run``."""
    return f"{ROOT}/{run}/telemetry/{kind}"


def telemetry_prefix(run: str) -> str:
    """Every kind of telemetry of run ``run``."""
    return f"{ROOT}/{run}/telemetry/*"


def setpoint(run: str, sender: str) -> str:
    """The setpoint requests of program ``sender`` in run ``run``."""
    return f"{ROOT}/{run}/setpoint/{sender}"


def setpoint_prefix(run: str) -> str:
    """Every program's setpoint requests in run ``run``."""
    return f"{ROOT}/{run}/setpoint/*"


def setpoint_answer(run: str, sender: str) -> str:
    """The coordinator's answers to program ``sender``'s setpoint requests in run ``run``."""
    return f"{ROOT}/{run}/setpoint-answer/{sender}"


COORDINATOR_ROLE = "coordinator"
PLANT_ROLE = "plant"
AGENT_PREFIX = "agent-"
SENSOR_PREFIX = "sensor-"
OPERATOR_ROLE = "operator"
"""The certificate of a supervisory program that may change setpoints (it holds no token)."""


def agent_role(agent: str) -> str:
    """The role of the agent of subsystem ``agent``."""
    return f"{AGENT_PREFIX}{agent}"


def sensor_role(subsystem: str) -> str:
    """The role of a plant process that measures subsystem ``subsystem`` alone."""
    return f"{SENSOR_PREFIX}{subsystem}"


def state_sources(subsystems) -> list[str]:
    """The roles that may send states: the plant, then each subsystem's sensor (in the order of the
    names in ``subsystems``)."""
    return [PLANT_ROLE] + [sensor_role(name) for name in subsystems]


def subsystem_of(role: str, prefix: str) -> str | None:
    """The subsystem name in ``role`` = ``prefix<name>`` (``prefix``: ``AGENT_PREFIX`` or ``SENSOR_PREFIX``),
    or None."""
    return role[len(prefix):] if role.startswith(prefix) and len(role) > len(prefix) else None


def alive_prefix(run: str) -> str:
    """Every role's liveliness token in run ``run``."""
    return f"{ROOT}/{run}/alive/*"


def last_chunk(key: str) -> str:
    """The last chunk of ``key`` (after its last ``/``)."""
    return key.rsplit("/", 1)[-1]

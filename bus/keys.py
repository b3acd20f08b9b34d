"""Every key expression of the protocol, built in one place.

``dmpc/<run>/release``          plant -> every agent (one broadcast per round)
``dmpc/<run>/plan/<agent>``     agent -> neighbours, plant
``dmpc/<run>/ready/<agent>``    agent -> plant
``dmpc/<run>/control``          plant -> all (Stop)
``dmpc/<run>/alive/<role>``     liveliness tokens (``plant`` or ``agent-<name>``)
``dmpc/<run>/telemetry/<kind>`` plant -> observers (``step``, ``meta``, ``end``; best effort)
"""
from __future__ import annotations

import re

ROOT = "dmpc"
_SAFE = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


def check_chunk(text: str, what: str) -> str:
    """Return ``text`` if it is safe as one key chunk; ValueError otherwise."""
    if not _SAFE.match(text):
        raise ValueError(f"{what} {text!r} must be 1-64 characters from A-Z a-z 0-9 _ . -")
    return text


def release(run: str) -> str:
    return f"{ROOT}/{run}/release"


def plan(run: str, agent: str) -> str:
    return f"{ROOT}/{run}/plan/{agent}"


def ready(run: str, agent: str) -> str:
    return f"{ROOT}/{run}/ready/{agent}"


def control(run: str) -> str:
    return f"{ROOT}/{run}/control"


def alive(run: str, role: str) -> str:
    return f"{ROOT}/{run}/alive/{role}"


def telemetry(run: str, kind: str) -> str:
    return f"{ROOT}/{run}/telemetry/{kind}"


def telemetry_prefix(run: str) -> str:
    return f"{ROOT}/{run}/telemetry/*"


def agent_role(agent: str) -> str:
    return f"agent-{agent}"


def alive_prefix(run: str) -> str:
    return f"{ROOT}/{run}/alive/*"


def last_chunk(key: str) -> str:
    return key.rsplit("/", 1)[-1]

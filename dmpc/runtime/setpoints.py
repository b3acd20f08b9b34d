"""A supervisory program's side of a setpoint request: its components, and one request sent over
Zenoh with its answer awaited (docs/protocol.md, "Setpoints while a run goes on").

The command line (``dmpc setpoint``) and the Python API (``dmpc.setpoint``) both come here. A
request names a subsystem's components by position; names (a subsystem's ``states`` and
``inputs`` labels) are turned into positions here, from the scenario the caller gives, since the
wire carries positions only.
"""
from __future__ import annotations

import math
import secrets
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from dmpc.bus import keys
from dmpc.bus.codec import MAX_NAME, DecodeError, decode, encode
from dmpc.bus.messages import Setpoint, SetpointAnswer
from dmpc.bus.session import session_config
from dmpc.bus.zenoh_bus import ZenohBus
from dmpc.core.errors import InputError
from dmpc.security.files import node_security

DEFAULT_TIMEOUT = 5.0
"""Seconds a request waits for its answer, connecting included."""


class SetpointInputError(InputError, ValueError):
    """A request that cannot be sent as given (a value, a name, an endpoint, a certificate)."""


def components(given, kind: str, what: str, subsystem: str, spec=None) -> np.ndarray:
    """A subsystem's requested states (``kind`` "x") or inputs ("u") as they travel.

    Parameters
    ----------
    given : None, sequence of float or None, or mapping name -> float or None
        None: every component free. A sequence: one value per component, None (or NaN) for a
        free one. A mapping: by the names of the subsystem's states or inputs (needs ``spec``).
    kind : {"x", "u"}
    what : str
        How the caller names the argument in messages (``--x``, ``x``).
    subsystem : str
    spec : SubsystemSpec, optional
        The subsystem in the scenario: its sizes and names. Without it, a sequence is sent as it
        is (the coordinator checks its length).

    Returns
    -------
    ndarray, shape (n_i,) or (m_i,), or (0,) for None
        NaN where free.

    Raises
    ------
    SetpointInputError
        A value that is not a number or None, an infinite one, the wrong number of entries, or a
        name the subsystem does not have (or names without ``spec``).
    """
    if given is None:
        return np.empty(0)
    if isinstance(given, Mapping):
        values = _by_name(given, kind, what, subsystem, spec)
    else:
        values = [_value(v, f"{what}[{c}]") for c, v in enumerate(_sequence(given, what))]
    if spec is not None:
        size = spec.n if kind == "x" else spec.m
        if len(values) != size:
            unit = f"n_i = {size} states" if kind == "x" else f"m_i = {size} inputs"
            raise SetpointInputError(f"{what}: expected {size} entries ({unit} of subsystem '{subsystem}'), "
                                     f"got {len(values)}")
    return np.array(values, dtype=float)


def _sequence(given, what: str) -> list:
    if isinstance(given, (str, bytes)) or not isinstance(given, (Sequence, np.ndarray)):
        raise SetpointInputError(f"{what}: expected a list of numbers and None, or a map name -> number, "
                                 f"got {type(given).__name__}")
    return list(np.asarray(given, dtype=object).ravel()) if isinstance(given, np.ndarray) else list(given)


def _value(value, where: str) -> float:
    """A component: a finite number, or NaN for None (free)."""
    if value is None:
        return math.nan
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise SetpointInputError(f"{where}: expected a number or None (free), got {value!r:.40}") from None
    if math.isinf(number):
        raise SetpointInputError(f"{where}: expected a finite number or None (free), got {number}")
    return number


def _by_name(given: Mapping, kind: str, what: str, subsystem: str, spec) -> list[float]:
    """The values of a mapping name -> value, in the subsystem's order (NaN for the others)."""
    noun = "state" if kind == "x" else "input"
    if spec is None:
        raise SetpointInputError(f"{what}: {noun}s by name need the scenario that names them; give the scenario, "
                                 "or the values by position")
    labels = spec.states if kind == "x" else spec.inputs
    if not labels:
        raise SetpointInputError(f"{what}: names need the subsystem's '{noun}s' (subsystem '{subsystem}' names "
                                 "none): give the values by position")
    names = [label.name for label in labels]
    for key in given:
        if key not in names:
            raise SetpointInputError(f"{what}: subsystem '{subsystem}' has no {noun} '{key}' (it has "
                                     f"{', '.join(names)})")
    return [_value(given.get(name), f"{what}.{name}") for name in names]


def scenario_subsystem(scenario, subsystem: str):
    """The subsystem named ``subsystem`` of a Scenario (its sizes and labels).

    Raises
    ------
    SetpointInputError
        The scenario has no such subsystem.
    """
    found = {spec.name: spec for spec in scenario.resolved_subsystems()}
    if subsystem not in found:
        names = list(found)
        shown = ", ".join(names[:8]) + (", ..." if len(names) > 8 else "")
        raise SetpointInputError(f"subsystem: no subsystem '{subsystem}' in scenario '{scenario.name}' "
                                 f"(subsystems: {shown})")
    return found[subsystem]


def send_setpoint(connect: str | Sequence[str], run_id: str, subsystem: str, x: np.ndarray, u: np.ndarray, *,
                  sender: str, tls_dir: str | Path | None = None, timeout: float = DEFAULT_TIMEOUT,
                  request_id: int | None = None) -> SetpointAnswer | None:
    """Send one setpoint request as a Zenoh client, as a query, and wait for its answer.

    The query is sent once the coordinator's queryable is seen, and its reply is the answer. A
    query that ends without a reply, or no queryable within ``timeout``, is the outcome "not
    authorised or no run listening" (None): another endpoint or run id, a run that is over, or a
    certificate that may not send setpoints, whose query the access control ends unanswered.

    Parameters
    ----------
    connect : str or sequence of str
        The coordinator's endpoint (or a router's), e.g. ``tcp/127.0.0.1:7447``.
    run_id, subsystem : str
    x, u : ndarray, shape (n_i,) and (m_i,), or (0,)
        From :func:`components`: NaN where free, empty for all free.
    sender : str
        The request's sender name (the key's last chunk), where the answer is sent.
    tls_dir : path, optional
        A certificate directory with the ``operator`` certificate: TLS with mutual
        authentication (``tls/`` endpoints), and its ``acl.json``.
    timeout : float
        Seconds for all of it: connecting, publishing and the answer.
    request_id : int, optional
        The request's id; a random one by default.

    Returns
    -------
    SetpointAnswer or None
        None when no answer came: not authorised or no run listening (:data:`UNANSWERED`).

    Raises
    ------
    SetpointInputError
        A malformed endpoint, run id, sender or subsystem name, or a missing certificate file.
    dmpc.bus.session.BusError
        The endpoint could not be reached.
    """
    if not timeout > 0:
        raise SetpointInputError(f"timeout: expected a positive number of seconds, got {timeout}")
    message = Setpoint(run=_chunk(run_id, "run id"), sender=_chunk(sender, "sender name"),
                       id=secrets.randbelow(2**31) if request_id is None else int(request_id),
                       subsystem=_name(subsystem), x=np.asarray(x, dtype=float), u=np.asarray(u, dtype=float))
    deadline = time.monotonic() + timeout
    bus = ZenohBus(_client_config(connect, tls_dir), open_timeout=timeout)
    try:
        replies = bus.query(keys.setpoint(message.run, message.sender), encode(message),
                            max(0.0, deadline - time.monotonic()))
    finally:
        bus.close()
    answers = [answer for answer in map(_decoded_answer, replies or [])
               if answer is not None and answer.id == message.id and answer.run == message.run]
    return answers[0] if answers else None


UNANSWERED = "not authorised or no run listening"
"""The outcome of a request that no coordinator answered: the access control ended it unanswered
(a certificate other than the operator's), or no run listens at that endpoint under that run id."""


def unanswered_text(run_id: str, connect: str | Sequence[str], timeout: float) -> str:
    """What to tell the sender of a request to run ``run_id`` at ``connect`` that got no answer
    within ``timeout`` seconds."""
    where = connect if isinstance(connect, str) else ", ".join(connect)
    return (f"{UNANSWERED}: no answer from the coordinator of run {run_id} at {where} within {timeout:g} s "
            "(under TLS only the operator certificate may send setpoints; check the endpoint and the run id, "
            "which dmpc run prints)")


def _decoded_answer(payload: bytes) -> SetpointAnswer | None:
    try:
        answer = decode(payload)
    except DecodeError:
        return None
    return answer if isinstance(answer, SetpointAnswer) else None


def _client_config(connect: str | Sequence[str], tls_dir: str | Path | None):
    endpoints = [connect] if isinstance(connect, str) else list(connect)
    if not endpoints:
        raise SetpointInputError("connect: the coordinator's endpoint is needed, e.g. tcp/127.0.0.1:7447")
    secure = [endpoint for endpoint in endpoints if endpoint.startswith("tls/")]
    if secure and tls_dir is None:
        raise SetpointInputError(f"connect: {secure[0]} is a TLS endpoint: give the certificate directory "
                                 "with the operator certificate (--tls DIR, tls=DIR)")
    try:
        tls, acl = node_security(tls_dir, keys.OPERATOR_ROLE) if tls_dir is not None else (None, None)
        return session_config(mode="client", connect=endpoints, tls=tls, acl=acl)
    except ValueError as exc:
        raise SetpointInputError(str(exc)) from None


def _chunk(text: str, what: str) -> str:
    try:
        return keys.check_chunk(text, what)
    except (ValueError, TypeError) as exc:
        raise SetpointInputError(str(exc)) from None


def _name(subsystem: str) -> str:
    if not isinstance(subsystem, str) or not 0 < len(subsystem) <= MAX_NAME:
        raise SetpointInputError(f"subsystem: expected a subsystem's name, 1 to {MAX_NAME} characters, "
                                 f"got {subsystem!r:.70}")
    return subsystem

"""The one encode/decode pair of the wire format: msgpack maps with a protocol version.

Arrays travel as ``{"dtype": "<f8", "shape": [...], "data": bytes}`` (``"<i8"`` for integer
arrays). ``decode`` checks everything that can be checked without knowing the scenario (types,
finiteness, array encodings, field sets) and raises ``DecodeError`` for anything else; it never
raises another exception type. ``decode(encode(m))`` equals ``m``.

Both run on every message of every step, so the plan and the release have encoders and parsers
of their own, with each check done once and no walk over the values.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import fields

import msgpack
import numpy as np

from dmpc.bus.messages import (
    MESSAGE_TYPES,
    PROTOCOL_VERSION,
    TYPE_NAMES,
    Inputs,
    Kept,
    Message,
    PlanMessage,
    Ready,
    Release,
    Setpoint,
    SetpointAnswer,
    State,
    Stop,
)
from dmpc.core.errors import DmpcError
from dmpc.core.qp_status import SOLVED

MAX_PAYLOAD = 1 << 20
MAX_NAME = 64
MAX_ARRAY_ELEMENTS = 1 << 16
MAX_REASON = 1000


VERSION_FIELD = "protocol"
OLD_VERSION_FIELD = "schema"  # what protocol versions 1 and 2 called it


class DecodeError(DmpcError, ValueError):
    """A payload that is not a valid message; the text says what is wrong."""


class VersionMismatch(DecodeError):
    """A message of another protocol version; ``version`` is the one it carries (None if none)."""

    def __init__(self, version: object) -> None:
        self.version = version if type(version) is int else None
        shown = "no protocol version" if self.version is None else f"protocol version {self.version}"
        super().__init__(f"{shown}; this process speaks protocol version {PROTOCOL_VERSION}")


# the wire names of the fields whose Python name differs (the Jacobi round kept its first wire name)
_WIRE_NAME = {"round": "iteration"}
_FIELDS: dict[type, tuple[str, ...]] = {cls: tuple(_WIRE_NAME.get(f.name, f.name) for f in fields(cls))
                                        for cls in MESSAGE_TYPES.values()}


def wire_fields(cls: type) -> tuple[str, ...]:
    """The field names of message class ``cls`` as they appear on the wire, in order."""
    return _FIELDS[cls]


_FIELD_SETS: dict[type, frozenset] = {cls: frozenset(names) for cls, names in _FIELDS.items()}
# fields a sender may leave out (added after the first release of the format); decode fills in the default
_OPTIONAL: dict[type, frozenset] = {Ready: frozenset({"scenario", "horizon"}), Release: frozenset({"target", "kept", "iterate"}),
                                    PlanMessage: frozenset({"reason"}), State: frozenset({"y"})}


def encode(msg: Message) -> bytes:
    """Serialise a message to bytes.

    Parameters
    ----------
    msg : Message
        The message to send, one of the classes of :data:`dmpc.bus.messages.MESSAGE_TYPES` exactly
        (a subclass has no wire name).

    Returns
    -------
    bytes
        A msgpack map with the protocol version and the message's type name; ``decode`` reads it back.
    """
    cls = type(msg)
    # type(msg) is C (not isinstance): the exact class picks the encoder, as the wire name does
    if type(msg) is PlanMessage:
        body = _plan_body(msg)
    elif type(msg) is Release:
        body = _release_body(msg)
    elif type(msg) is Setpoint:
        body = _setpoint_body(msg)
    elif type(msg) is SetpointAnswer:
        body = _answer_body(msg)
    elif type(msg) is State:
        body = _state_body(msg)
    else:
        body = {VERSION_FIELD: PROTOCOL_VERSION, "type": TYPE_NAMES[cls]}
        for field, name in zip(fields(cls), _FIELDS[cls]):
            body[name] = _to_wire(getattr(msg, field.name))
    return msgpack.packb(body, use_bin_type=True)


def _scalar(value):
    return value.item() if isinstance(value, np.generic) else value


def _wire_array(value: np.ndarray) -> dict:
    dtype = "<i8" if value.dtype.kind in "iub" else "<f8"
    arr = np.ascontiguousarray(value, dtype=dtype)
    return {"dtype": dtype, "shape": list(arr.shape), "data": arr.tobytes()}


def _plan_body(m: PlanMessage) -> dict:
    return {VERSION_FIELD: PROTOCOL_VERSION, "type": "plan", "run": m.run, "k": _scalar(m.k), "iteration": _scalar(m.round),
            "sender": m.sender, "status": m.status, "z": _wire_array(m.z), "v": _wire_array(m.v),
            "cost": _scalar(m.cost), "solve_time": _scalar(m.solve_time), "qp_iterations": _scalar(m.qp_iterations),
            "sent_at": _scalar(m.sent_at), **({"reason": m.reason} if m.reason else {})}


def _release_body(m: Release) -> dict:
    return {VERSION_FIELD: PROTOCOL_VERSION, "type": "release", "run": m.run, "k": _scalar(m.k),
            "iteration": _scalar(m.round), "x": _wire_array(m.x), "centres": _wire_array(m.centres),
            "sizes": _wire_array(m.sizes), "assumed": _wire_array(m.assumed), "sender": m.sender,
            "skipped": list(m.skipped),
            "provided": {name: [_wire_array(z), _wire_array(v)] for name, (z, v) in m.provided.items()},
            **({} if m.target is None else {"target": [_wire_array(m.target[0]), _wire_array(m.target[1])]}),
            **({"kept": list(m.kept)} if m.kept else {}),
            **({} if m.iterate is None else {"iterate": [_wire_array(m.iterate[0]), _wire_array(m.iterate[1])]})}


def _setpoint_body(m: Setpoint) -> dict:
    # float64 whatever the caller gave: an empty list would otherwise travel as an integer array
    return {VERSION_FIELD: PROTOCOL_VERSION, "type": "setpoint", "run": m.run, "sender": m.sender, "id": _scalar(m.id),
            "subsystem": m.subsystem, "x": _wire_array(np.asarray(m.x, dtype=float)),
            "u": _wire_array(np.asarray(m.u, dtype=float))}


def _state_body(m: State) -> dict:
    # y only when given: a state that measures the whole state is what it was before outputs existed
    return {VERSION_FIELD: PROTOCOL_VERSION, "type": "state", "run": m.run, "k": _scalar(m.k), "sender": m.sender,
            "x": _to_wire(m.x), **({"y": _to_wire(m.y)} if m.y else {})}


def _answer_body(m: SetpointAnswer) -> dict:
    return {VERSION_FIELD: PROTOCOL_VERSION, "type": "setpoint-answer", "run": m.run, "id": _scalar(m.id),
            "subsystem": m.subsystem, "accepted": bool(m.accepted), "k": _scalar(m.k), "reason": m.reason}


def _to_wire(value):
    if isinstance(value, np.ndarray):
        return _wire_array(value)
    if isinstance(value, dict):
        return {k: _to_wire(v) for k, v in value.items()}
    if isinstance(value, (tuple, list)):
        return [_to_wire(v) for v in value]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


def decode(payload: bytes) -> Message:
    """Parse and check a payload; DecodeError if it is not a valid message."""
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise DecodeError("payload is not bytes")
    if len(payload) > MAX_PAYLOAD:
        raise DecodeError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    try:
        body = msgpack.unpackb(bytes(payload), raw=False, strict_map_key=True,
                               max_bin_len=MAX_PAYLOAD, max_str_len=4096, max_array_len=4096, max_map_len=4096)
    except Exception as exc:  # noqa: BLE001 - msgpack raises several unrelated types on garbage
        raise DecodeError(f"not msgpack: {type(exc).__name__}") from None
    if type(body) is not dict:
        raise DecodeError("top level is not a map")
    if body.get(VERSION_FIELD) != PROTOCOL_VERSION:
        raise VersionMismatch(body.get(VERSION_FIELD, body.get(OLD_VERSION_FIELD)))
    kind = body.get("type")
    cls = MESSAGE_TYPES.get(kind) if isinstance(kind, str) else None
    if cls is None:
        raise DecodeError(f"unknown message type {kind!r}")
    if body.keys() == _WIRE_KEYS[cls]:
        return _PARSERS[cls](body)
    expected = _FIELD_SETS[cls]
    present = set(body) - {VERSION_FIELD, "type"}
    if not expected - _OPTIONAL.get(cls, frozenset()) <= present <= expected:
        raise DecodeError(_field_set_error(cls.__name__, sorted((expected - _OPTIONAL.get(cls, frozenset())) - present),
                                           sorted(map(str, present - expected))))
    return _PARSERS[cls](body)


def _field_set_error(kind: str, missing: list[str], extra: list[str]) -> str:
    """``Setpoint: missing field 'u'; unexpected field 'colour'``: the fields a message of class
    ``kind`` lacks (``missing``) and those it should not have (``extra``, names from the sender,
    shown with escapes and at most 32 characters each)."""
    parts = []
    for what, names in (("missing", missing), ("unexpected", extra)):
        if names:
            parts.append(f"{what} field{'s' if len(names) > 1 else ''} " + ", ".join(repr(n[:32]) for n in names))
    return f"{kind}: " + "; ".join(parts)


def _int(body: dict, name: str, minimum: int = 0) -> int:
    v = body[name]
    if type(v) is not int or v < minimum or v > 2**53:
        raise DecodeError(f"{name}: expected an integer >= {minimum}, got {v!r:.40}")
    return v


def _str(value, name: str) -> str:
    if type(value) is not str or not value or len(value) > MAX_NAME:
        raise DecodeError(f"{name}: expected a non-empty string of at most {MAX_NAME} characters")
    return value


def _float(body: dict, name: str, allow_nan: bool = False) -> float:
    v = body[name]
    if type(v) is not float:
        if type(v) is not int:
            raise DecodeError(f"{name}: expected a number, got {type(v).__name__}")
        v = float(v)
    if v - v != 0.0 and (math.isinf(v) or not allow_nan):  # v - v is NaN for NaN and infinities
        raise DecodeError(f"{name}: not a finite number")
    return v


_ARRAY_KEYS = {"dtype", "shape", "data"}


def _array(value, name: str, ndim: int, allow_nan: bool = False, dtype: str = "<f8") -> np.ndarray:
    if type(value) is not dict or value.keys() != _ARRAY_KEYS:
        raise DecodeError(f"{name}: expected an array map with dtype, shape, data")
    if value["dtype"] != dtype:
        raise DecodeError(f"{name}: dtype {value['dtype']!r:.20} is not {dtype}")
    shape = value["shape"]
    if type(shape) is not list or len(shape) != ndim:
        raise DecodeError(f"{name}: shape must be {ndim} non-negative integers")
    count = 1
    for s in shape:
        if type(s) is not int or not 0 <= s <= MAX_ARRAY_ELEMENTS:
            raise DecodeError(f"{name}: shape must be {ndim} non-negative integers")
        count *= s
    data = value["data"]
    if type(data) is not bytes or count > MAX_ARRAY_ELEMENTS or len(data) != 8 * count:
        raise DecodeError(f"{name}: data length does not match shape {shape}")
    # read-only view on the payload: nothing downstream writes into received arrays
    arr = np.frombuffer(data, dtype=dtype).reshape(shape)
    if dtype == "<f8" and not np.isfinite(arr).all() and (not allow_nan or np.isinf(arr).any()):
        raise DecodeError(f"{name}: non-finite values")
    return arr


def _parse_release(b: dict) -> Release:
    x = _array(b["x"], "x", 1)
    centres = _array(b["centres"], "centres", 1)
    if centres.shape != x.shape:
        raise DecodeError(f"centres: {centres.size} entries for a state of {x.size}")
    sizes = _array(b["sizes"], "sizes", 1)
    if sizes.size == 0 or sizes.min() < 0:
        raise DecodeError("sizes: expected one non-negative size per agent")
    assumed = _array(b["assumed"], "assumed", 2, dtype="<i8")
    if assumed.shape != (sizes.size, 2):
        raise DecodeError(f"assumed: expected one [k, round] row per agent ({sizes.size}), got shape {assumed.shape}")
    if assumed.min() < 0:
        none = assumed[:, 0] < 0
        if (assumed[none] != -1).any() or (assumed[~none, 1] < 0).any():
            raise DecodeError("assumed: rows must be [k, round] >= 0, or [-1, -1] for none")
    if assumed.max() > 2**53:
        raise DecodeError("assumed: step beyond 2^53")
    skipped = b["skipped"]
    if type(skipped) is not list or len(skipped) > sizes.size:
        raise DecodeError("skipped: expected a list of at most one name per agent")
    for name in skipped:
        _str(name, "skipped name")
    provided = b["provided"]
    if type(provided) is not dict or len(provided) > sizes.size:
        raise DecodeError("provided: expected a map name -> [z, v], at most one per agent")
    parsed_provided = {}
    for key, pair in provided.items():
        _str(key, "provided key")
        if type(pair) is not list or len(pair) != 2:
            raise DecodeError(f"provided[{key}]: expected [z, v]")
        z, v = _array(pair[0], f"provided[{key}].z", 2), _array(pair[1], f"provided[{key}].v", 2)
        if z.shape[0] != v.shape[0] + 1:
            raise DecodeError(f"provided[{key}]: z needs one row more than v")
        parsed_provided[key] = (z, v)
    target = None
    if "target" in b:
        pair = b["target"]
        if type(pair) is not list or len(pair) != 2:
            raise DecodeError("target: expected [x_s, u_s]")
        target = (_array(pair[0], "target.x", 1), _array(pair[1], "target.u", 1))
        if target[0].shape != x.shape:
            raise DecodeError(f"target: x_s has {target[0].size} entries for a state of {x.size}")
    kept = b.get("kept", [])
    if type(kept) is not list or len(kept) > sizes.size or ("kept" in b and not kept):
        raise DecodeError("kept: expected a non-empty list of at most one name per agent")
    for name in kept:
        _str(name, "kept name")
    iterate = None
    if "iterate" in b:
        pair = b["iterate"]
        if type(pair) is not list or len(pair) != 2:
            raise DecodeError("iterate: expected [z, v]")
        iterate = (_array(pair[0], "iterate.z", 2), _array(pair[1], "iterate.v", 2))
        if iterate[0].shape[1] != x.size or iterate[0].shape[0] != iterate[1].shape[0] + 1:
            raise DecodeError(f"iterate: z must have shape (N + 1, {x.size}) with one row more than v, got "
                              f"{iterate[0].shape} and {iterate[1].shape}")
    return Release(run=_str(b["run"], "run"), k=_int(b, "k"), round=_int(b, "iteration"), x=x, centres=centres,
                   sizes=sizes, assumed=assumed, sender=_str(b["sender"], "sender"), skipped=tuple(skipped),
                   provided=parsed_provided, target=target, kept=tuple(kept), iterate=iterate)


def _parse_plan(b: dict) -> PlanMessage:
    status = _str(b["status"], "status")
    solved = status in SOLVED
    z = _array(b["z"], "z", 2, allow_nan=not solved)
    v = _array(b["v"], "v", 2, allow_nan=not solved)
    if z.shape[0] != v.shape[0] + 1 or v.shape[0] < 1:
        raise DecodeError(f"z has {z.shape[0]} rows and v {v.shape[0]}: expected N+1 and N >= 1")
    cost = _float(b, "cost", allow_nan=not solved)
    solve_time = _float(b, "solve_time")
    sent_at = _float(b, "sent_at")
    if solve_time < 0:
        raise DecodeError("solve_time: negative")
    reason = b.get("reason", "")
    if type(reason) is not str or len(reason) > MAX_NAME or ("reason" in b and not reason):
        raise DecodeError(f"reason: expected a word of 1 to {MAX_NAME} characters")
    return PlanMessage(run=_str(b["run"], "run"), k=_int(b, "k"), round=_int(b, "iteration"),
                       sender=_str(b["sender"], "sender"), status=status, z=z, v=v, cost=cost,
                       solve_time=solve_time, qp_iterations=_int(b, "qp_iterations"), sent_at=sent_at, reason=reason)


def _parse_kept(b: dict) -> Kept:
    return Kept(run=_str(b["run"], "run"), k=_int(b, "k"), round=_int(b, "iteration"), sender=_str(b["sender"], "sender"),
                sent_at=_float(b, "sent_at"))


def _parse_ready(b: dict) -> Ready:
    scenario = b.get("scenario", "")
    if not isinstance(scenario, str) or len(scenario) > MAX_NAME:
        raise DecodeError(f"scenario: expected a string of at most {MAX_NAME} characters")
    return Ready(run=_str(b["run"], "run"), sender=_str(b["sender"], "sender"),
                 design_digest=_str(b["design_digest"], "design_digest"), pid=_int(b, "pid"),
                 scenario=scenario, horizon=_int(b, "horizon") if "horizon" in b else 0)


def _parse_stop(b: dict) -> Stop:
    reason = b["reason"]
    if not isinstance(reason, str) or len(reason) > MAX_REASON:
        raise DecodeError("reason: expected a string")
    return Stop(run=_str(b["run"], "run"), k=_int(b, "k"), reason=reason, sender=_str(b["sender"], "sender"))


def _vectors(value, name: str, limit: int, least: int = 1) -> dict[str, np.ndarray]:
    """A map subsystem name -> finite float64 vector, ``least`` to ``limit`` entries."""
    if type(value) is not dict or not least <= len(value) <= limit:
        raise DecodeError(f"{name}: expected a map subsystem name -> vector, {least} to {limit} entries")
    return {_str(key, f"{name} key"): _array(vec, f"{name}[{key}]", 1) for key, vec in value.items()}


def _parse_inputs(b: dict) -> Inputs:
    return Inputs(run=_str(b["run"], "run"), k=_int(b, "k"), u=_vectors(b["u"], "u", 4096),
                  sender=_str(b["sender"], "sender"))


def _parse_state(b: dict) -> State:
    if "y" not in b:
        return State(run=_str(b["run"], "run"), k=_int(b, "k"), sender=_str(b["sender"], "sender"),
                     x=_vectors(b["x"], "x", 4096))
    # with outputs, the states may be none: every subsystem of the message reports its outputs
    x, y = _vectors(b["x"], "x", 4096, least=0), _vectors(b["y"], "y", 4096)
    if both := sorted(x.keys() & y.keys()):
        raise DecodeError(f"subsystem {both[0]!r} is in both x and y: send its state or its outputs")
    return State(run=_str(b["run"], "run"), k=_int(b, "k"), sender=_str(b["sender"], "sender"), x=x, y=y)


def _parse_setpoint(b: dict) -> Setpoint:
    # NaN marks a free component; an infinite value is refused like everywhere else
    return Setpoint(run=_str(b["run"], "run"), sender=_str(b["sender"], "sender"), id=_int(b, "id"),
                    subsystem=_str(b["subsystem"], "subsystem"), x=_array(b["x"], "x", 1, allow_nan=True),
                    u=_array(b["u"], "u", 1, allow_nan=True))


def _parse_answer(b: dict) -> SetpointAnswer:
    accepted, reason = b["accepted"], b["reason"]
    if type(accepted) is not bool:
        raise DecodeError(f"accepted: expected true or false, got {type(accepted).__name__}")
    k = _int(b, "k", minimum=-1)
    if accepted != (k >= 0):
        raise DecodeError("k: expected a step >= 0 when accepted, -1 when refused")
    if type(reason) is not str or len(reason) > MAX_REASON or accepted != (reason == ""):
        raise DecodeError(f"reason: expected \"\" when accepted, else a string of 1 to {MAX_REASON} characters")
    return SetpointAnswer(run=_str(b["run"], "run"), id=_int(b, "id"), subsystem=_str(b["subsystem"], "subsystem"),
                          accepted=accepted, k=k, reason=reason)


_PARSERS: dict[type, Callable[[dict], Message]] = {Release: _parse_release, PlanMessage: _parse_plan, Kept: _parse_kept, Ready: _parse_ready, Stop: _parse_stop,
            Inputs: _parse_inputs, State: _parse_state, Setpoint: _parse_setpoint, SetpointAnswer: _parse_answer}
# every field present: the common case, checked with one comparison
_WIRE_KEYS = {cls: frozenset(names) | {VERSION_FIELD, "type"} for cls, names in _FIELD_SETS.items()}

"""The one encode/decode pair of the wire format: msgpack maps with a schema version.

Arrays travel as ``{"dtype": "<f8", "shape": [...], "data": bytes}``. ``decode`` checks
everything that can be checked without knowing the scenario (types, finiteness, array
encodings, field sets) and raises ``DecodeError`` for anything else; it never raises another
exception type. ``decode(encode(m))`` equals ``m``.
"""
from __future__ import annotations

import math
from dataclasses import fields

import msgpack
import numpy as np

from dmpc.bus.messages import (MESSAGE_TYPES, SCHEMA_VERSION, TYPE_NAMES, Message, PlanMessage, Ready,
                               Release, Stop)

MAX_PAYLOAD = 1 << 20
MAX_NAME = 64
MAX_ARRAY_ELEMENTS = 1 << 16


class DecodeError(ValueError):
    """A payload that is not a valid message; the text says what is wrong."""


_FIELDS: dict[type, tuple[str, ...]] = {cls: tuple(f.name for f in fields(cls)) for cls in MESSAGE_TYPES.values()}
_FIELD_SETS: dict[type, frozenset] = {cls: frozenset(names) for cls, names in _FIELDS.items()}


def encode(msg: Message) -> bytes:
    """Serialise a message to bytes."""
    body = {"schema": SCHEMA_VERSION, "type": TYPE_NAMES[type(msg)]}
    for name in _FIELDS[type(msg)]:
        body[name] = _to_wire(getattr(msg, name))
    return msgpack.packb(body, use_bin_type=True)


def _to_wire(value):
    if isinstance(value, np.ndarray):
        arr = np.ascontiguousarray(value, dtype="<f8")
        return {"dtype": "<f8", "shape": list(arr.shape), "data": arr.tobytes()}
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
    except Exception as exc:  # msgpack raises several unrelated types on garbage
        raise DecodeError(f"not msgpack: {type(exc).__name__}") from None
    if not isinstance(body, dict):
        raise DecodeError("top level is not a map")
    if body.get("schema") != SCHEMA_VERSION:
        raise DecodeError(f"schema version {body.get('schema')!r} is not {SCHEMA_VERSION}")
    cls = MESSAGE_TYPES.get(body.get("type")) if isinstance(body.get("type"), str) else None
    if cls is None:
        raise DecodeError(f"unknown message type {body.get('type')!r}")
    expected = _FIELD_SETS[cls]
    present = set(body) - {"schema", "type"}
    if present != expected:
        missing, extra = sorted(expected - present), sorted(map(str, present - expected))
        raise DecodeError(f"{cls.__name__}: missing fields {missing}, unexpected fields {extra}")
    return _PARSERS[cls](body)


def _int(body: dict, name: str, minimum: int = 0) -> int:
    v = body[name]
    if not isinstance(v, int) or isinstance(v, bool) or v < minimum or v > 2**53:
        raise DecodeError(f"{name}: expected an integer >= {minimum}, got {v!r:.40}")
    return v


def _str(value, name: str) -> str:
    if not isinstance(value, str) or not value or len(value) > MAX_NAME:
        raise DecodeError(f"{name}: expected a non-empty string of at most {MAX_NAME} characters")
    return value


def _float(body: dict, name: str, allow_nan: bool = False) -> float:
    v = body[name]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise DecodeError(f"{name}: expected a number, got {type(v).__name__}")
    v = float(v)
    if math.isinf(v) or (math.isnan(v) and not allow_nan):
        raise DecodeError(f"{name}: not a finite number")
    return v


def _array(value, name: str, ndim: int, allow_nan: bool = False) -> np.ndarray:
    if not isinstance(value, dict) or set(value) != {"dtype", "shape", "data"}:
        raise DecodeError(f"{name}: expected an array map with dtype, shape, data")
    if value["dtype"] != "<f8":
        raise DecodeError(f"{name}: dtype {value['dtype']!r:.20} is not <f8")
    shape = value["shape"]
    if not isinstance(shape, list) or len(shape) != ndim:
        raise DecodeError(f"{name}: shape must be {ndim} non-negative integers")
    for s in shape:
        if type(s) is not int or not 0 <= s <= MAX_ARRAY_ELEMENTS:
            raise DecodeError(f"{name}: shape must be {ndim} non-negative integers")
    count = math.prod(shape)
    data = value["data"]
    if not isinstance(data, bytes) or count > MAX_ARRAY_ELEMENTS or len(data) != 8 * count:
        raise DecodeError(f"{name}: data length does not match shape {shape}")
    # read-only view on the payload: nothing downstream writes into received arrays
    arr = np.frombuffer(data, dtype="<f8").reshape(shape)
    if not np.isfinite(arr).all() and (not allow_nan or np.isinf(arr).any()):
        raise DecodeError(f"{name}: non-finite values")
    return arr


def _parse_release(b: dict) -> Release:
    states = b["states"]
    if not isinstance(states, dict) or not states or len(states) > 1024:
        raise DecodeError("states: expected a non-empty map name -> array")
    parsed_states = {_str(k, "states key"): _array(v, f"states[{k}]", 1) for k, v in states.items()}
    assumed = b["assumed"]
    if not isinstance(assumed, dict) or len(assumed) > 1024:
        raise DecodeError("assumed: expected a map name -> [k, round] or nil")
    parsed_assumed = {}
    for key, ref in assumed.items():
        _str(key, "assumed key")
        if ref is None:
            parsed_assumed[key] = None
        elif (isinstance(ref, list) and len(ref) == 2
              and all(isinstance(x, int) and not isinstance(x, bool) and 0 <= x <= 2**53 for x in ref)):
            parsed_assumed[key] = (ref[0], ref[1])
        else:
            raise DecodeError(f"assumed[{key}]: expected [k, round] or nil")
    beta = _float(b, "beta")
    if beta < 0:
        raise DecodeError("beta: negative")
    provided = b["provided"]
    if not isinstance(provided, dict) or len(provided) > 1024:
        raise DecodeError("provided: expected a map name -> [z, v]")
    parsed_provided = {}
    for key, pair in provided.items():
        _str(key, "provided key")
        if not isinstance(pair, list) or len(pair) != 2:
            raise DecodeError(f"provided[{key}]: expected [z, v]")
        z, v = _array(pair[0], f"provided[{key}].z", 2), _array(pair[1], f"provided[{key}].v", 2)
        if z.shape[0] != v.shape[0] + 1:
            raise DecodeError(f"provided[{key}]: z needs one row more than v")
        parsed_provided[key] = (z, v)
    return Release(run=_str(b["run"], "run"), k=_int(b, "k"), iteration=_int(b, "iteration"),
                   target=_str(b["target"], "target"), states=parsed_states,
                   alpha=_array(b["alpha"], "alpha", 1), beta=beta, assumed=parsed_assumed,
                   sender=_str(b["sender"], "sender"), provided=parsed_provided)


def _parse_plan(b: dict) -> PlanMessage:
    status = _str(b["status"], "status")
    solved = status in ("solved", "solved_inaccurate")
    z = _array(b["z"], "z", 2, allow_nan=not solved)
    v = _array(b["v"], "v", 2, allow_nan=not solved)
    if z.shape[0] != v.shape[0] + 1 or v.shape[0] < 1:
        raise DecodeError(f"z has {z.shape[0]} rows and v {v.shape[0]}: expected N+1 and N >= 1")
    cost = _float(b, "cost", allow_nan=not solved)
    solve_time = _float(b, "solve_time")
    sent_at = _float(b, "sent_at")
    if solve_time < 0:
        raise DecodeError("solve_time: negative")
    return PlanMessage(run=_str(b["run"], "run"), k=_int(b, "k"), iteration=_int(b, "iteration"),
                       sender=_str(b["sender"], "sender"), status=status, z=z, v=v, cost=cost,
                       solve_time=solve_time, qp_iterations=_int(b, "qp_iterations"), sent_at=sent_at)


def _parse_ready(b: dict) -> Ready:
    return Ready(run=_str(b["run"], "run"), sender=_str(b["sender"], "sender"),
                 design_digest=_str(b["design_digest"], "design_digest"), pid=_int(b, "pid"))


def _parse_stop(b: dict) -> Stop:
    reason = b["reason"]
    if not isinstance(reason, str) or len(reason) > 1000:
        raise DecodeError("reason: expected a string")
    return Stop(run=_str(b["run"], "run"), k=_int(b, "k"), reason=reason, sender=_str(b["sender"], "sender"))


_PARSERS = {Release: _parse_release, PlanMessage: _parse_plan, Ready: _parse_ready, Stop: _parse_stop}

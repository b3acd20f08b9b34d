"""Fuzzing the wire decoder: whatever the bytes, ``decode`` returns a checked message or raises
DecodeError, never anything else; what it returns satisfies the checks it promises."""
from __future__ import annotations

import math

import msgpack
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dmpc.bus.codec import MAX_NAME, DecodeError, decode, encode
from dmpc.bus.messages import PROTOCOL_VERSION, PlanMessage, Ready, Release, Stop

FUZZ = settings(max_examples=1000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
FUZZ_NESTED = settings(FUZZ, max_examples=500)  # slower to generate

N, n, m = 4, 2, 1
PLAN = PlanMessage(run="r", k=3, round=1, sender="2", status="solved", z=np.arange((N + 1) * n, dtype=float).reshape(N + 1, n),
                   v=np.ones((N, m)), cost=1.5, solve_time=0.001, qp_iterations=25, sent_at=12.5)
RELEASE = Release(run="r", k=3, round=0, x=np.array([1.0, 1.0, 0.0, 0.0, -1.0, -1.0]),
                  centres=np.array([0.0, 0.0, 0.1, 0.2, 0.0, 0.0]), sizes=np.full(3, 0.9),
                  assumed=np.array([[2, 0], [2, 0], [-1, -1]]), skipped=("3",),
                  provided={"1": (np.zeros((N + 1, n)), np.zeros((N, m)))})
VALID = [encode(PLAN), encode(RELEASE), encode(Ready(run="r", sender="2", design_digest="abc", pid=7, scenario="paper", horizon=10)),
         encode(Stop(run="r", k=9, reason="finished"))]

# msgpack values of every kind, nested: the building blocks of well-formed garbage
scalars = st.one_of(st.none(), st.booleans(), st.integers(-2**63, 2**64 - 1),
                    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=20), st.binary(max_size=40))
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                      st.dictionaries(st.text(max_size=8), inner, max_size=4)),
                      max_leaves=12)


def check_invariants(msg) -> None:
    """What a message returned by decode must satisfy."""
    assert isinstance(msg, (PlanMessage, Release, Ready, Stop))
    for name in ("run", "sender"):
        text = getattr(msg, name)
        assert isinstance(text, str) and 0 < len(text) <= MAX_NAME
    if isinstance(msg, Ready):
        assert isinstance(msg.scenario, str) and len(msg.scenario) <= MAX_NAME
        assert type(msg.horizon) is int and 0 <= msg.horizon <= 2**53
    if isinstance(msg, (PlanMessage, Release, Stop)):
        assert type(msg.k) is int and 0 <= msg.k <= 2**53
    if isinstance(msg, PlanMessage):
        assert msg.z.dtype == np.float64 and msg.z.ndim == 2 and msg.v.ndim == 2
        assert msg.z.shape[0] == msg.v.shape[0] + 1 >= 2
        if msg.status in ("solved", "solved_inaccurate"):
            assert np.isfinite(msg.z).all() and np.isfinite(msg.v).all() and math.isfinite(msg.cost)
        assert not np.isinf(msg.z).any() and not np.isinf(msg.v).any()
        assert math.isfinite(msg.solve_time) and msg.solve_time >= 0 and math.isfinite(msg.sent_at)
    if isinstance(msg, Release):
        assert msg.sizes.ndim == 1 and msg.sizes.size >= 1 and (msg.sizes >= 0).all()
        assert msg.x.ndim == 1 and msg.centres.shape == msg.x.shape
        arrays = [msg.x, msg.centres, msg.sizes] + [a for pair in msg.provided.values() for a in pair]
        assert all(a.dtype == np.float64 and np.isfinite(a).all() for a in arrays)
        assert msg.assumed.dtype == np.int64 and msg.assumed.shape == (msg.sizes.size, 2)
        for j in range(msg.sizes.size):
            ref = msg.reference(j)
            assert ref is None or all(type(x) is int and 0 <= x <= 2**53 for x in ref)
        assert all(isinstance(name, str) and 0 < len(name) <= MAX_NAME for name in msg.skipped)


def decode_or_reject(payload: bytes):
    try:
        msg = decode(payload)
    except DecodeError:
        return None
    check_invariants(msg)
    return msg


@FUZZ
@given(st.binary(max_size=600))
def test_random_bytes(payload):
    decode_or_reject(payload)


@FUZZ
@given(st.sampled_from(VALID), st.data())
def test_truncated_messages(payload, data):
    cut = data.draw(st.integers(0, len(payload) - 1))
    assert decode_or_reject(payload[:cut]) is None


@FUZZ
@given(st.sampled_from(VALID), st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 255)), min_size=1, max_size=6))
def test_corrupted_bytes(payload, flips):
    data = bytearray(payload)
    for pos, byte in flips:
        data[pos % len(data)] = byte
    decode_or_reject(bytes(data))


@FUZZ_NESTED
@given(st.sampled_from(VALID), st.data())
def test_fields_replaced_by_wrong_types(payload, data):
    """Well-formed msgpack maps whose fields hold anything: strings for numbers, NaN, nested junk."""
    body = msgpack.unpackb(payload, raw=False)
    for name in data.draw(st.lists(st.sampled_from(sorted(body)), min_size=1, max_size=4, unique=True)):
        body[name] = data.draw(values)
    if data.draw(st.booleans()):
        body[data.draw(st.text(max_size=6))] = data.draw(values)  # an unexpected field
    decode_or_reject(msgpack.packb(body, use_bin_type=True))


def _array_map(draw) -> dict:
    dtype = draw(st.sampled_from(["<f8", "<f4", ">f8", "<i8", "|O", "object", ""]))
    shape = draw(st.lists(st.integers(-2, 70_000), max_size=3))
    data = draw(st.one_of(st.binary(max_size=96), st.just(np.full(6, np.nan).tobytes()),
                          st.just(np.array([1.0, np.inf, 2.0, -np.inf]).tobytes()), st.text(max_size=8)))
    return {"dtype": dtype, "shape": shape, "data": data}


@FUZZ_NESTED
@given(st.data())
def test_arrays_with_wrong_dtype_shape_or_values(data):
    """Array maps with other dtypes (object ones included), negative or huge shapes, sizes that do
    not match, NaN and infinities in a solved plan or a release."""
    body = msgpack.unpackb(data.draw(st.sampled_from(VALID[:2])), raw=False)
    if body["type"] == "plan":
        field = data.draw(st.sampled_from(["z", "v"]))
        body[field] = _array_map(data.draw)
    else:
        target = data.draw(st.sampled_from(["x", "centres", "sizes", "assumed", "provided"]))
        if target != "provided":
            body[target] = _array_map(data.draw)
        else:
            body["provided"]["1"][data.draw(st.integers(0, 1))] = _array_map(data.draw)
    decode_or_reject(msgpack.packb(body, use_bin_type=True))


@FUZZ
@given(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from(["z", "v", "cost"]), st.sampled_from(["solved", "solved_inaccurate", "infeasible"]))
def test_non_finite_numbers_in_plans(value, field, status):
    body = msgpack.unpackb(VALID[0], raw=False)
    body["status"] = status
    if field == "cost":
        body["cost"] = value
    else:
        arr = np.frombuffer(body[field]["data"], dtype="<f8").copy()
        arr[0] = value
        body[field]["data"] = arr.tobytes()
    msg = decode_or_reject(msgpack.packb(body, use_bin_type=True))
    if math.isinf(value) or (math.isnan(value) and status != "infeasible"):
        assert msg is None


def test_every_valid_payload_decodes():
    """The fuzz above starts from payloads the decoder accepts (or it would test nothing)."""
    for payload in VALID:
        check_invariants(decode(payload))


def test_schema_version_and_unknown_types_are_refused():
    body = msgpack.unpackb(VALID[0], raw=False)
    for change in ({"protocol": PROTOCOL_VERSION + 1}, {"protocol": None}, {"type": "plan2"}, {"type": ["plan"]}):
        assert decode_or_reject(msgpack.packb({**body, **change}, use_bin_type=True)) is None

"""The wire format: decode(encode(m)) == m, and garbage never escapes as another exception."""
from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from dmpc.bus.codec import DecodeError, decode, encode
from dmpc.bus.messages import PlanMessage, Ready, Release, Stop, messages_equal

names = st.text(alphabet="abcdefghijklmnopqrstuvwxyz0123456789_-", min_size=1, max_size=12)
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
counts = st.integers(min_value=0, max_value=10**9)


def vectors(n=st.integers(1, 6)):
    return n.flatmap(lambda k: arrays(np.float64, (k,), elements=finite))


@st.composite
def releases(draw):
    group = draw(st.lists(names, min_size=1, max_size=5, unique=True))
    refs = st.one_of(st.none(), st.tuples(counts, counts))
    return Release(run=draw(names), k=draw(counts), iteration=draw(counts), target=group[0],
                   states={g: draw(vectors()) for g in group}, alpha=draw(vectors()),
                   beta=draw(st.floats(min_value=0, max_value=1e6)),
                   assumed={g: draw(refs) for g in group[1:]})


@st.composite
def plans(draw):
    N = draw(st.integers(1, 12))
    n = draw(st.integers(1, 4))
    m = draw(st.integers(1, 3))
    return PlanMessage(run=draw(names), k=draw(counts), iteration=draw(counts), sender=draw(names), status="solved",
                       z=draw(arrays(np.float64, (N + 1, n), elements=finite)),
                       v=draw(arrays(np.float64, (N, m), elements=finite)),
                       cost=draw(finite), solve_time=draw(st.floats(0, 10)), qp_iterations=draw(counts),
                       sent_at=draw(finite))


messages = st.one_of(
    releases(), plans(),
    st.builds(Ready, run=names, sender=names, design_digest=names, pid=counts),
    st.builds(Stop, run=names, k=counts, reason=st.text(max_size=50), sender=names),
)


@settings(max_examples=400, deadline=None)
@given(messages)
def test_round_trip(msg):
    assert messages_equal(decode(encode(msg)), msg)


def test_infeasible_plan_carries_nan():
    msg = PlanMessage(run="r", k=1, iteration=0, sender="1", status="infeasible", z=np.full((3, 2), np.nan),
                      v=np.full((2, 1), np.nan), cost=math.nan, solve_time=0.0, qp_iterations=7)
    assert messages_equal(decode(encode(msg)), msg)


def test_solved_plan_with_nan_is_rejected():
    msg = PlanMessage(run="r", k=1, iteration=0, sender="1", status="solved", z=np.full((3, 2), np.nan),
                      v=np.zeros((2, 1)), cost=1.0, solve_time=0.0, qp_iterations=7)
    with pytest.raises(DecodeError, match="non-finite"):
        decode(encode(msg))


@settings(max_examples=2000, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_only_raise_decode_error(payload):
    try:
        decode(payload)
    except DecodeError:
        pass


@settings(max_examples=1000, deadline=None)
@given(plans(), st.data())
def test_mutated_fields_only_raise_decode_error(msg, data):
    body = msgpack.unpackb(encode(msg), raw=False)
    key = data.draw(st.sampled_from(sorted(body)))
    body[key] = data.draw(st.one_of(st.none(), st.integers(-2**63, 2**64 - 1), st.floats(), st.text(max_size=5), st.binary(max_size=8),
                                    st.lists(st.integers(-2**63, 2**63), max_size=3), st.booleans()))
    try:
        decoded = decode(msgpack.packb(body, use_bin_type=True))
    except DecodeError:
        return
    # whatever survived is a well-formed plan
    assert isinstance(decoded, PlanMessage)
    assert decoded.z.shape[0] == decoded.v.shape[0] + 1


@settings(max_examples=300, deadline=None)
@given(plans(), st.integers(min_value=1, max_value=50))
def test_truncated_payload_rejected(msg, cut):
    raw = encode(msg)
    with pytest.raises(DecodeError):
        decode(raw[: max(0, len(raw) - cut)])


@pytest.mark.parametrize("mutate, match", [
    (lambda b: b.update(schema=99), "schema"),
    (lambda b: b.update(type="bogus"), "unknown message type"),
    (lambda b: b.pop("cost"), "missing"),
    (lambda b: b.update(extra=1), "unexpected"),
    (lambda b: b.update(k=-1), "k"),
    (lambda b: b.update(k=True), "k"),
    (lambda b: b["z"].update(dtype="<f4"), "dtype"),
    (lambda b: b["z"].update(shape=[3, 2]), "data length"),
    (lambda b: b.update(cost=float("inf")), "cost"),
    (lambda b: b["v"].update(data=np.array([[np.inf]]).tobytes(), shape=[1, 1]), "non-finite"),
    (lambda b: b.update(sender=""), "sender"),
])
def test_specific_defects_named(mutate, match):
    msg = PlanMessage(run="r", k=1, iteration=0, sender="1", status="solved", z=np.zeros((2, 2)),
                      v=np.zeros((1, 1)), cost=1.0, solve_time=0.0, qp_iterations=7)
    body = msgpack.unpackb(encode(msg), raw=False)
    mutate(body)
    with pytest.raises(DecodeError, match=match):
        decode(msgpack.packb(body, use_bin_type=True))

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
from dmpc.bus.messages import PlanMessage, Ready, Release, Setpoint, SetpointAnswer, Stop, messages_equal

names = st.text(alphabet="abcdefghijklmnopqrstuvwxyz0123456789_-", min_size=1, max_size=12)
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
counts = st.integers(min_value=0, max_value=10**9)
vector_lengths = st.integers(1, 6)


def vectors(n=vector_lengths):
    return n.flatmap(lambda k: arrays(np.float64, (k,), elements=finite))


@st.composite
def releases(draw):
    agents = draw(st.lists(names, min_size=1, max_size=5, unique=True))
    n = draw(st.integers(1, 8))
    refs = st.one_of(st.just((-1, -1)), st.tuples(counts, counts))
    N = draw(st.integers(1, 4))
    provided = {a: (draw(arrays(np.float64, (N + 1, 2), elements=finite)), draw(arrays(np.float64, (N, 1), elements=finite)))
                for a in draw(st.lists(st.sampled_from(agents), max_size=2, unique=True))}
    return Release(run=draw(names), k=draw(counts), round=draw(counts), x=draw(arrays(np.float64, (n,), elements=finite)),
                   centres=draw(arrays(np.float64, (n,), elements=finite)),
                   sizes=draw(arrays(np.float64, (len(agents),), elements=st.floats(min_value=0, max_value=1e6))),
                   assumed=np.array([draw(refs) for _ in agents], dtype=np.int64).reshape(len(agents), 2),
                   skipped=tuple(draw(st.lists(st.sampled_from(agents), max_size=2, unique=True))), provided=provided)


@st.composite
def plans(draw):
    N = draw(st.integers(1, 12))
    n = draw(st.integers(1, 4))
    m = draw(st.integers(1, 3))
    return PlanMessage(run=draw(names), k=draw(counts), round=draw(counts), sender=draw(names), status="solved",
                       z=draw(arrays(np.float64, (N + 1, n), elements=finite)),
                       v=draw(arrays(np.float64, (N, m), elements=finite)),
                       cost=draw(finite), solve_time=draw(st.floats(0, 10)), qp_iterations=draw(counts),
                       sent_at=draw(finite))


@st.composite
def setpoints(draw):
    """A request with NaN (free) components mixed in, or empty x or u (all free)."""
    component = st.one_of(finite, st.just(math.nan))
    x, u = (draw(st.one_of(st.just(np.zeros(0)), arrays(np.float64, (draw(st.integers(1, 6)),), elements=component)))
            for _ in range(2))
    return Setpoint(run=draw(names), sender=draw(names), id=draw(counts), subsystem=draw(names), x=x, u=u)


@st.composite
def answers(draw):
    accepted = draw(st.booleans())
    return SetpointAnswer(run=draw(names), id=draw(counts), subsystem=draw(names), accepted=accepted,
                          k=draw(counts) if accepted else -1, reason="" if accepted else draw(st.text(min_size=1,
                                                                                                      max_size=50)))


messages = st.one_of(
    releases(), plans(), setpoints(), answers(),
    st.builds(Ready, run=names, sender=names, design_digest=names, pid=counts,
              scenario=st.one_of(st.just(""), names), horizon=counts),
    st.builds(Stop, run=names, k=counts, reason=st.text(max_size=50), sender=names),
)


@settings(max_examples=400, deadline=None)
@given(messages)
def test_round_trip(msg):
    assert messages_equal(decode(encode(msg)), msg)


@pytest.mark.parametrize("mutate, match", [
    (lambda b: b["centres"].update(shape=[2], data=np.zeros(2).tobytes()), "centres"),
    (lambda b: b["sizes"].update(data=np.array([-1.0, 1.0]).tobytes()), "sizes"),
    (lambda b: b["assumed"].update(data=np.array([[3, -1], [2, 0]]).tobytes()), "assumed"),
    (lambda b: b["assumed"].update(shape=[1, 2], data=np.array([[3, 0]]).tobytes()), "assumed"),
    (lambda b: b["assumed"].update(dtype="<f8"), "dtype"),
    (lambda b: b.update(skipped=["a"] * 3), "skipped"),
    (lambda b: b.update(skipped=[""]), "skipped"),
])
def test_release_defects_named(mutate, match):
    msg = Release(run="r", k=1, round=0, x=np.zeros(3), centres=np.zeros(3), sizes=np.ones(2),
                  assumed=np.array([[0, 0], [-1, -1]]))
    body = msgpack.unpackb(encode(msg), raw=False)
    mutate(body)
    with pytest.raises(DecodeError, match=match):
        decode(msgpack.packb(body, use_bin_type=True))


def test_release_reference():
    msg = Release(run="r", k=4, round=0, x=np.zeros(2), centres=np.zeros(2), sizes=np.ones(2),
                  assumed=np.array([[3, 1], [-1, -1]]))
    assert decode(encode(msg)).reference(0) == (3, 1) and decode(encode(msg)).reference(1) is None


def test_infeasible_plan_carries_nan():
    msg = PlanMessage(run="r", k=1, round=0, sender="1", status="infeasible", z=np.full((3, 2), np.nan),
                      v=np.full((2, 1), np.nan), cost=math.nan, solve_time=0.0, qp_iterations=7)
    assert messages_equal(decode(encode(msg)), msg)


def test_solved_plan_with_nan_is_rejected():
    msg = PlanMessage(run="r", k=1, round=0, sender="1", status="solved", z=np.full((3, 2), np.nan),
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
    (lambda b: b.update(protocol=99), "protocol version 99; this process speaks protocol version 3"),
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
    msg = PlanMessage(run="r", k=1, round=0, sender="1", status="solved", z=np.zeros((2, 2)),
                      v=np.zeros((1, 1)), cost=1.0, solve_time=0.0, qp_iterations=7)
    body = msgpack.unpackb(encode(msg), raw=False)
    mutate(body)
    with pytest.raises(DecodeError, match=match):
        decode(msgpack.packb(body, use_bin_type=True))


def setpoint_body(**changes) -> dict:
    msg = Setpoint(run="r", sender="cli", id=3, subsystem="1", x=np.array([1.0, math.nan]), u=np.zeros(0))
    body = msgpack.unpackb(encode(msg), raw=False)
    body.update(changes)
    return body


def answer_body(**changes) -> dict:
    body = msgpack.unpackb(encode(SetpointAnswer(run="r", id=3, subsystem="1", accepted=True, k=7)), raw=False)
    body.update(changes)
    return body


def test_a_setpoint_with_free_components_and_an_empty_u_round_trips():
    msg = decode(msgpack.packb(setpoint_body(), use_bin_type=True))
    assert isinstance(msg, Setpoint) and msg.x[0] == 1.0 and math.isnan(msg.x[1]) and msg.u.shape == (0,)
    assert msg.x.dtype == np.float64 and msg.u.dtype == np.float64
    # an empty list given by the caller still travels as float64
    assert decode(encode(Setpoint("r", "cli", 3, "1", np.array([]), np.array([], dtype=int)))).u.dtype == np.float64


@pytest.mark.parametrize("body, match", [
    (setpoint_body(x={"dtype": "<f8", "shape": [2], "data": np.array([1.0, math.inf]).tobytes()}), "x: non-finite"),
    (setpoint_body(u={"dtype": "<f8", "shape": [1], "data": np.array([-math.inf]).tobytes()}), "u: non-finite"),
    (setpoint_body(x={"dtype": "<i8", "shape": [1], "data": np.array([1]).tobytes()}), "x: dtype"),
    (setpoint_body(x={"dtype": "<f8", "shape": [1, 1], "data": np.zeros(1).tobytes()}), "x: shape"),
    (setpoint_body(x=[1.0, None]), "x: expected an array map"),
    (setpoint_body(id=-1), "id"),
    (setpoint_body(id="3"), "id"),
    (setpoint_body(subsystem=""), "subsystem"),
    (setpoint_body(sender=7), "sender"),
    (setpoint_body(extra=1), "unexpected"),
    ({k: v for k, v in setpoint_body().items() if k != "u"}, "missing"),
    (answer_body(accepted=1), "accepted: expected true or false"),
    (answer_body(k=-1), "k: expected a step >= 0 when accepted"),
    (answer_body(accepted=False, reason="no"), "k: expected a step >= 0 when accepted, -1 when refused"),
    (answer_body(accepted=False, k=-1, reason=""), "reason"),
    (answer_body(reason="but"), "reason"),
    (answer_body(k=-2), "k: expected an integer >= -1"),
    (answer_body(reason="x" * 1001), "reason"),
])
def test_setpoint_defects_named(body, match):
    with pytest.raises(DecodeError, match=match):
        decode(msgpack.packb(body, use_bin_type=True))


@settings(max_examples=500, deadline=None)
@given(st.one_of(setpoints(), answers()), st.data())
def test_mutated_setpoint_fields_only_raise_decode_error(msg, data):
    body = msgpack.unpackb(encode(msg), raw=False)
    key = data.draw(st.sampled_from(sorted(body)))
    body[key] = data.draw(st.one_of(st.none(), st.integers(-2**63, 2**64 - 1), st.floats(), st.text(max_size=5),
                                    st.binary(max_size=8), st.booleans(), st.lists(st.floats(), max_size=3)))
    try:
        decoded = decode(msgpack.packb(body, use_bin_type=True))
    except DecodeError:
        return
    # whatever survived is a well-formed message of the same type
    assert type(decoded) is type(msg)
    if isinstance(decoded, Setpoint):
        assert decoded.x.ndim == decoded.u.ndim == 1 and not np.isinf(decoded.x).any() and not np.isinf(decoded.u).any()
    else:
        assert decoded.accepted == (decoded.k >= 0) and decoded.accepted == (decoded.reason == "")


def test_ready_without_scenario_and_horizon_decodes_with_defaults():
    """A Ready from a sender that does not send the optional fields is still a Ready."""
    body = msgpack.unpackb(encode(Ready(run="r", sender="2", design_digest="abc", pid=7, scenario="paper",
                                        horizon=12)), raw=False)
    assert decode(msgpack.packb(body, use_bin_type=True)) == Ready("r", "2", "abc", 7, "paper", 12)
    del body["scenario"], body["horizon"]
    assert decode(msgpack.packb(body, use_bin_type=True)) == Ready(run="r", sender="2", design_digest="abc", pid=7)


@pytest.mark.parametrize("mutate, match", [
    (lambda b: b.pop("design_digest"), "missing"),
    (lambda b: b.update(scenario=3), "scenario"),
    (lambda b: b.update(scenario="x" * 65), "scenario"),
    (lambda b: b.update(horizon=-1), "horizon"),
    (lambda b: b.update(horizon="10"), "horizon"),
    (lambda b: b.update(extra=1), "unexpected"),
])
def test_ready_defects_named(mutate, match):
    body = msgpack.unpackb(encode(Ready(run="r", sender="2", design_digest="abc", scenario="paper", horizon=10)),
                           raw=False)
    mutate(body)
    with pytest.raises(DecodeError, match=match):
        decode(msgpack.packb(body, use_bin_type=True))


@given(z=arrays(np.float64, (3, 2), elements=st.one_of(finite, st.sampled_from([1e154, -1e200, 1.7e308]))),
       bad=st.sampled_from([math.nan, math.inf, -math.inf, None]), at=st.integers(0, 5),
       status=st.sampled_from(["solved", "infeasible"]))
def test_non_finite_values_are_found_whatever_the_other_values(z, bad, at, status):
    """The finiteness check's shortcut (a finite sum of squares) must not hide a NaN or an
    infinity, nor refuse finite values whose squares overflow."""
    z = z.copy()
    if bad is not None:
        z.flat[at] = bad
    msg = PlanMessage(run="r", k=1, round=0, sender="1", status=status, z=z, v=np.zeros((2, 1)), cost=1.0,
                      solve_time=0.0, qp_iterations=3)
    refused = bad is not None and (status == "solved" or math.isinf(bad))
    if refused:
        with pytest.raises(DecodeError, match="non-finite"):
            decode(encode(msg))
    else:
        assert np.array_equal(decode(encode(msg)).z, z, equal_nan=True)


def _cooperative_release(z: np.ndarray, v: np.ndarray) -> Release:
    return Release(run="r", k=2, round=1, x=np.zeros(3), centres=np.zeros(3), sizes=np.ones(2),
                   assumed=np.full((2, 2), -1), iterate=(z, v))


def test_release_with_a_cooperative_iterate_round_trips():
    z, v = np.arange(12.0).reshape(4, 3), np.arange(6.0).reshape(3, 2)
    msg = _cooperative_release(z, v)
    assert messages_equal(decode(encode(msg)), msg)
    assert "iterate" not in msgpack.unpackb(encode(Release(run="r", k=1, round=0, x=np.zeros(3), centres=np.zeros(3),
                                                           sizes=np.ones(2), assumed=np.full((2, 2), -1))), raw=False)


@pytest.mark.parametrize("z, v", [
    (np.zeros((4, 2)), np.zeros((3, 2))),  # z's columns are not the state's
    (np.zeros((3, 3)), np.zeros((3, 2))),  # z needs one row more than v
])
def test_release_with_a_malformed_iterate_is_named(z, v):
    with pytest.raises(DecodeError, match="iterate"):
        decode(encode(_cooperative_release(z, v)))

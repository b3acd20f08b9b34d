"""The reasons a node counts its drops under (``summary.json`` ``rejected_reasons``, the printed
``dropped by the coordinator``) name the field at fault and are never cut mid-word."""
from __future__ import annotations

import logging
import re

import msgpack
import numpy as np
import pytest

from dmpc.bus.codec import DecodeError, decode, encode
from dmpc.bus.messages import Setpoint
from dmpc.security.rejects import MAX_REASON, Rejections, reason_of


def _setpoint_body(**changes) -> dict:
    body = msgpack.unpackb(encode(Setpoint(run="r", sender="scada", id=3, subsystem="1", x=np.array([1.0, np.nan]),
                                           u=np.zeros(0))), raw=False)
    body.update(changes)
    return {k: v for k, v in body.items() if v is not None}


def counted(body: dict) -> str:
    """The reason a coordinator counts the message ``body`` under."""
    with pytest.raises(DecodeError) as caught:
        decode(msgpack.packb(body, use_bin_type=True))
    rejects = Rejections(logging.getLogger("test.reasons"), "coordinator", lambda: 0.0, known=["scada"])
    rejects("scada", str(caught.value))
    (reason,) = rejects.reasons
    return reason


def test_an_extra_or_missing_field_is_named():
    assert counted(_setpoint_body(colour="red")) == "Setpoint: unexpected field 'colour'"
    assert counted(_setpoint_body(u=None)) == "Setpoint: missing field 'u'"
    assert counted(_setpoint_body(u=None, id=None, colour=1)) == ("Setpoint: missing fields 'id', 'u'; "
                                                                  "unexpected field 'colour'")


def test_a_reason_is_kept_whole_or_cut_between_words():
    assert counted(_setpoint_body(subsystem="s" * 65)) == "subsystem: expected a non-empty string of at most 64 characters"
    long = reason_of("k: " + " ".join(["seventeen"] * 20))
    assert len(long) <= MAX_REASON and long.endswith("...")
    assert all(word == "seventeen" for word in long[len("k: "):-len("...")].split())
    many = reason_of("Setpoint: unexpected fields " + ", ".join(f"'field{i}'" for i in range(30)))
    assert len(many) <= MAX_REASON and re.search(r", 'field\d+'\.\.\.$", many), many

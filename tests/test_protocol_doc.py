"""docs/protocol.md agrees with the code: version, keys, roles, message fields and wire types,
limits, and the access control per role.

The tables of the page are parsed and compared with ``bus.messages`` (dataclass fields),
``bus.codec`` (what ``encode`` actually puts on the wire, the limits), ``bus.keys`` (every key
expression and role name) and ``dmpc.security.acl`` (what each role may do).
"""
from __future__ import annotations

import ast
import dataclasses
import inspect
import re
from pathlib import Path

import msgpack
import numpy as np
import pytest

from dmpc.bus import codec, keys
from dmpc.bus.messages import (
    MESSAGE_TYPES,
    PROTOCOL_VERSION,
    Inputs,
    Kept,
    PlanMessage,
    Ready,
    Release,
    Setpoint,
    SetpointAnswer,
    State,
    Stop,
)
from dmpc.security.acl import access_control

DOC = Path(__file__).resolve().parents[1] / "docs" / "protocol.md"


# ------------------------------------------------------------------------------ parsing the page
def sections(text: str) -> dict[str, str]:
    """Heading text (without #) -> the text up to the next heading of any level."""
    out: dict[str, str] = {}
    title, lines, fenced = None, [], False
    for line in text.splitlines():
        fenced ^= line.startswith("```")
        if not fenced and line.startswith("#"):
            if title is not None:
                out[title] = "\n".join(lines)
            title, lines = line.lstrip("#").strip(), []
        else:
            lines.append(line)
    if title is not None:
        out[title] = "\n".join(lines)
    return out


def tables(body: str) -> list[list[list[str]]]:
    """The Markdown tables in ``body``: rows of cells (header first, separator left out)."""
    found, rows = [], []
    for line in body.splitlines() + [""]:
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if not all(re.fullmatch(r":?-+:?", c) for c in cells):
                rows.append(cells)
        elif rows:
            found.append(rows)
            rows = []
    return found


def plain(cell: str) -> str:
    return cell.replace("`", "").strip()


def one_table(title: str, doc: dict[str, str]) -> list[list[str]]:
    assert title in doc, f"docs/protocol.md has no heading {title!r}"
    found = tables(doc[title])
    assert found, f"docs/protocol.md, {title!r}: no table"
    return found[0]


def message_section(doc: dict[str, str], type_name: str) -> str:
    titles = [t for t in doc if re.match(rf"`{re.escape(type_name)}`[:\s]", t)]
    assert len(titles) == 1, f"docs/protocol.md: expected one heading for message `{type_name}`, found {titles}"
    return titles[0]


@pytest.fixture(scope="module")
def text() -> str:
    return DOC.read_text()


@pytest.fixture(scope="module")
def doc(text) -> dict[str, str]:
    return sections(text)


# --------------------------------------------------------------------------------------- version
def test_the_stated_protocol_version_is_the_codes(text, doc):
    stated = re.findall(r"protocol version \*\*(\d+)\*\*", text)
    assert [int(v) for v in stated] == [PROTOCOL_VERSION]
    shown = re.findall(r'"protocol": (\d+)', text)
    assert shown and {int(v) for v in shown} == {PROTOCOL_VERSION}
    version = doc["Protocol version"]
    assert f'`"{codec.VERSION_FIELD}"`' in version and f'`"{codec.OLD_VERSION_FIELD}"`' in version
    assert str(codec.VersionMismatch(PROTOCOL_VERSION - 1)) in version  # the message a mismatch gives


# ------------------------------------------------------------------------------------ keys, roles
def key_functions() -> dict[str, tuple]:
    """Every function of bus.keys that builds a key of a run: name -> its parameter names."""
    found = {}
    for name, fn in inspect.getmembers(keys, inspect.isfunction):
        params = list(inspect.signature(fn).parameters)
        if fn.__module__ == keys.__name__ and params and params[0] == "run":
            found[name] = params
    return found


def built(name: str, params: list[str]) -> str:
    return getattr(keys, name)("<run>", *[f"<{p}>" for p in params[1:]])


def test_the_key_table_is_every_key_of_bus_keys(doc):
    rows = one_table("Key expressions", doc)
    assert [plain(c) for c in rows[0][:2]] == ["key", "carries"]
    documented = {plain(row[0]) for row in rows[1:]}
    functions = key_functions()
    exact = {built(n, p) for n, p in functions.items() if not n.endswith("_prefix")}
    assert documented == exact
    for name, params in functions.items():  # the wildcards stand for one chunk of a documented key
        if name.endswith("_prefix"):
            pattern = built(name, params)
            assert any(re.sub(r"<\w+>$", "*", key) == pattern for key in documented), pattern
    carried = {plain(row[1]) for row in rows[1:]}
    assert set(MESSAGE_TYPES) <= carried


def test_the_key_table_names_the_message_of_each_key(doc):
    rows = one_table("Key expressions", doc)
    carried = {plain(row[0]): plain(row[1]) for row in rows[1:]}
    assert carried[keys.release("<run>")] == "release"
    assert carried[keys.plan("<run>", "<agent>")] == "plan"
    assert carried[keys.ready("<run>", "<agent>")] == "ready"
    assert carried[keys.control("<run>")] == "stop"
    assert carried[keys.inputs("<run>")] == "inputs"
    assert carried[keys.state("<run>", "<source>")] == "state"
    assert carried[keys.setpoint("<run>", "<sender>")] == "setpoint"
    assert carried[keys.setpoint_answer("<run>", "<sender>")] == "setpoint-answer"


def test_the_role_table_has_every_role_name(doc):
    rows = one_table("Roles", doc)
    roles = {plain(row[0]) for row in rows[1:]}
    assert {keys.COORDINATOR_ROLE, keys.PLANT_ROLE, keys.sensor_role("<name>"), keys.agent_role("<name>"),
            "observer", keys.OPERATOR_ROLE, "router"} == roles
    tokens = {plain(row[0]): plain(row[-1]) for row in rows[1:]}
    for role in (keys.COORDINATOR_ROLE, keys.PLANT_ROLE, keys.sensor_role("<name>"), keys.agent_role("<name>")):
        assert "dmpc/<run>/" + tokens[role] == keys.alive("<run>", role)


# -------------------------------------------------------------------------------------- messages
def field_problems(doc: dict[str, str], type_name: str, cls: type) -> list[str]:
    """How the field table of message ``type_name`` differs from the dataclass ``cls``."""
    rows = one_table(message_section(doc, type_name), doc)
    assert [plain(c) for c in rows[0][:3]] == ["field", "wire type", "shape"]
    documented = [plain(row[0]) for row in rows[1:]]
    fields = list(codec.wire_fields(cls)) if cls in MESSAGE_TYPES.values() else [f.name for f in dataclasses.fields(cls)]
    if documented == fields:
        return []
    return [f"{type_name}: the page lists {documented}, the code has {fields}"]


def test_every_message_has_a_field_table_equal_to_its_dataclass(doc):
    problems = [p for name, cls in MESSAGE_TYPES.items() for p in field_problems(doc, name, cls)]
    assert problems == []


def test_a_field_added_to_a_message_is_caught(doc):
    """The comparison sees a field the page does not list (so the test above can fail)."""
    grown = dataclasses.make_dataclass("State", [(f.name, f.type) for f in dataclasses.fields(State)]
                                       + [("quality", float)], frozen=True)
    assert field_problems(doc, "state", grown)
    shrunk = dataclasses.make_dataclass("Stop", [(f.name, f.type) for f in dataclasses.fields(Stop)][:-1])
    assert field_problems(doc, "stop", shrunk)


def examples() -> dict[str, object]:
    """One message of each type, every optional part filled in so that every value has a type."""
    z, v = np.zeros((3, 2)), np.zeros((2, 1))
    return {
        "release": Release(run="r", k=1, round=2, x=np.zeros(4), centres=np.zeros(4), sizes=np.ones(2),
                           assumed=np.array([[-1, -1], [0, 1]], dtype=np.int64), skipped=("b",),
                           provided={"a": (z, v)}, target=(np.zeros(4), np.zeros(2)), kept=("a",),
                           iterate=(np.zeros((3, 4)), np.zeros((2, 2)))),
        "plan": PlanMessage(run="r", k=1, round=2, sender="a", status="solved", z=z, v=v, cost=1.0,
                            solve_time=0.01, qp_iterations=25, sent_at=12.5, reason="cost"),
        "kept": Kept(run="r", k=3, round=0, sender="a", sent_at=12.5),
        "ready": Ready(run="r", sender="a", design_digest="d", pid=7, scenario="paper", horizon=2),
        "stop": Stop(run="r", k=3, reason="finished"),
        "inputs": Inputs(run="r", k=3, u={"a": np.zeros(1), "b": np.ones(1)}),
        "state": State(run="r", k=4, sender="plant", x={"a": np.zeros(2)}, y={"b": np.ones(1)}),
        "setpoint": Setpoint(run="r", sender="scada", id=17, subsystem="a", x=np.array([1.0, np.nan]),
                             u=np.zeros(0)),
        "setpoint-answer": SetpointAnswer(run="r", id=17, subsystem="a", accepted=True, k=23),
    }


def wire_type(value) -> str:
    """The page's name for the msgpack type of ``value`` as unpacked."""
    if isinstance(value, bool):
        return "bool"
    for kind, name in ((int, "int"), (float, "float"), (str, "str"), (bytes, "bin")):
        if isinstance(value, kind):
            return name
    if isinstance(value, dict) and set(value) == {"dtype", "shape", "data"}:
        return f"array({value['dtype']})"
    if isinstance(value, dict):
        inner = {wire_type(v) for v in value.values()}
        assert len(inner) == 1 and all(isinstance(k, str) for k in value), value
        return f"map[str, {inner.pop()}]"
    if isinstance(value, list):
        inner = {wire_type(v) for v in value}
        assert len(inner) == 1, value
        return f"list[{inner.pop()}]"
    return type(value).__name__


def test_the_wire_types_are_what_encode_sends(doc):
    messages = examples()
    assert set(messages) == set(MESSAGE_TYPES)
    for name, msg in messages.items():
        body = msgpack.unpackb(codec.encode(msg), raw=False)
        assert body.pop(codec.VERSION_FIELD) == PROTOCOL_VERSION and body.pop("type") == name
        rows = one_table(message_section(doc, name), doc)
        documented = {plain(row[0]): (plain(row[1]), plain(row[2])) for row in rows[1:]}
        assert set(body) == set(documented), name
        for field, value in body.items():
            wire, shape = documented[field]
            assert wire == wire_type(value), (name, field, wire, wire_type(value))
            if wire.startswith("array(") or wire.startswith("map[str, array("):
                sample = value if wire.startswith("array(") else next(iter(value.values()))
                dims = [d for d in shape.strip("()").split(",") if d.strip()]
                assert len(dims) == len(sample["shape"]), (name, field, shape)
            else:
                assert shape == "-", (name, field, shape)


def test_the_example_state_on_the_page_decodes(doc):
    blocks = re.findall(r"```\n(\{.*?\})\n```", doc["Encoding"], flags=re.S)
    assert len(blocks) == 1
    body = ast.literal_eval(blocks[0])
    msg = codec.decode(msgpack.packb(body, use_bin_type=True))
    assert isinstance(msg, State) and msg.sender == "sensor-2" and list(msg.x) == ["2"]
    assert msg.x["2"].tolist() == [1.5, -0.25]


def python_blocks(section: str) -> list[object]:
    """The msgpack bodies written as Python literals in ``section``'s plain code blocks."""
    return [ast.literal_eval(block) for block in re.findall(r"```\n(\{.*?\})\n```", section, flags=re.S)]


def test_the_setpoint_examples_on_the_page_decode(doc):
    request, answer = (codec.decode(msgpack.packb(body, use_bin_type=True))
                       for body in python_blocks(doc["Setpoints while a run goes on"]))
    assert isinstance(request, Setpoint) and request.sender == "scada" and request.subsystem == "1"
    assert request.x[0] == 1.0 and np.isnan(request.x[1]) and request.u.shape == (0,)
    assert isinstance(answer, SetpointAnswer) and answer.accepted and answer.id == request.id and answer.k == 23


def test_the_limits_are_the_codecs(doc):
    rows = next(table for table in tables(doc["Encoding"]) if plain(table[0][0]) == "limit")
    limits = {plain(row[2]): int(re.match(r"\d+", plain(row[1])).group()) for row in rows[1:]}
    assert limits == {name: getattr(codec, name) for name in limits}
    assert set(limits) == {"MAX_PAYLOAD", "MAX_NAME", "MAX_ARRAY_ELEMENTS", "MAX_REASON"}


# -------------------------------------------------------------------------------- access control
ACTIONS = {"may publish": "put", "may declare a token": "liveliness_token", "may subscribe to": "declare_subscriber",
           "may query": "query", "may declare a queryable": "declare_queryable"}


def documented_keys(cell: str) -> set[str]:
    cell = re.sub(r"\([^)]*\)", "", plain(cell))
    return set() if cell.strip() == "nothing" else {part.strip() for part in cell.split(",") if part.strip()}


def granted(acl: dict, role: str, action: str) -> set[str]:
    """The keys (relative to dmpc/<run>/) that ``role`` may ``action`` on its way in."""
    rules = {rule["id"]: rule for rule in acl["rules"]}
    policy = next(p for p in acl["policies"] if role in p["subjects"])
    found = set()
    for rule_id in policy["rules"]:
        rule = rules[rule_id]
        if "ingress" in rule["flows"] and action in rule["messages"]:
            found |= {key.removeprefix(f"{keys.ROOT}/*/") for key in rule["key_exprs"]}
    return found


def test_the_access_control_table_is_the_generated_one(doc):
    rows = one_table("Access control", doc)
    header = [plain(c) for c in rows[0]]
    assert header[0] == "role" and set(ACTIONS) == set(header[1:])
    acl = access_control(["I", "J"], {"I": ["J"], "J": ["I"]}, "*")
    subjects = {s["id"] for s in acl["subjects"]}
    documented_roles = {plain(row[0]) for row in rows[1:]}
    assert documented_roles == subjects - {"agent-J", "sensor-J"}
    for row in rows[1:]:
        role = plain(row[0])
        for column, cell in zip(header[1:], row[1:]):
            assert documented_keys(cell) == granted(acl, role, ACTIONS[column]), (role, column)

"""examples/outside_plant.py stands alone: it imports no dmpc, and its own copy of the paper's
example is dmpc's model of scenarios/paper.yaml, spoken in dmpc's wire format.

No network here: the example's plant logic is driven with messages made by dmpc's codec
(tests/test_outside_plant_wire.py runs it over Zenoh).
"""
from __future__ import annotations

import ast
import importlib.util
import re
import sys
from pathlib import Path

import msgpack
import numpy as np
import pytest

from dmpc.bus.codec import decode, encode
from dmpc.bus.messages import PROTOCOL_VERSION, Inputs, State, Stop
from dmpc.plant.dynamics import Plant
from dmpc.scenario import build_system, load_scenario

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "outside_plant.py"
ALLOWED = {"zenoh", "msgpack", "numpy"}


def foreign_imports(source: str) -> list[str]:
    """Imports of ``source`` other than zenoh, msgpack, numpy and the standard library.

    Relative imports, ``__import__`` and ``importlib`` count as foreign: they could bring in
    anything.
    """
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = ["." * node.level + (node.module or "")]
        elif isinstance(node, ast.Name) and node.id == "__import__":
            names = ["__import__"]
        else:
            continue
        for name in names:
            top = name.split(".")[0]
            if name.startswith(".") or name == "__import__" or top == "importlib" or (
                    top not in ALLOWED and top not in sys.stdlib_module_names and top != "__future__"):
                found.append(name)
    return found


def test_the_example_imports_only_zenoh_msgpack_numpy_and_the_standard_library():
    assert foreign_imports(EXAMPLE.read_text()) == []


@pytest.mark.parametrize("source, caught", [
    ("import dmpc", ["dmpc"]),
    ("from dmpc.bus import codec", ["dmpc.bus"]),
    ("import numpy, yaml", ["yaml"]),
    ("from . import keys", ["."]),
    ("def f():\n    import dmpc.bus.codec as c", ["dmpc.bus.codec"]),
    ("m = __import__('dmpc')", ["__import__"]),
    ("import importlib\nimportlib.import_module('dmpc')", ["importlib"]),
    ("from __future__ import annotations\nimport json, numpy as np, zenoh, msgpack", []),
])
def test_the_import_check_catches_dmpc(source, caught):
    assert foreign_imports(source) == caught


@pytest.fixture(scope="module")
def example():
    spec = importlib.util.spec_from_file_location("outside_plant", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def system():
    return build_system(load_scenario(ROOT / "scenarios" / "paper.yaml"))


def test_the_examples_dynamics_are_dmpcs_model_of_the_paper(example, system):
    scenario = load_scenario(ROOT / "scenarios" / "paper.yaml")
    assert scenario.plant.model == "nominal" and scenario.plant.disturbance is None  # the plant is the model
    A, B, x0 = example.paper_model()
    assert list(example.NAMES) == [s.name for s in system.subsystems]
    assert np.array_equal(A, system.A) and np.array_equal(B, system.B) and np.array_equal(x0, system.x0)
    assert example.PROTOCOL_VERSION == PROTOCOL_VERSION


def answer(plant, k: int, u: np.ndarray, system) -> list[tuple[str, State]]:
    parts = {s.name: u[system.us(i)] for i, s in enumerate(system.subsystems)}
    return [(role, decode(payload)) for role, payload in plant.on_inputs(encode(Inputs(run="t", k=k, u=parts)))]


def whole(states: list[tuple[str, State]]) -> np.ndarray:
    parts = {name: x for _, msg in states for name, x in msg.x.items()}
    return np.concatenate([parts[name] for name in sorted(parts)])


def test_the_examples_plant_follows_the_rules_in_dmpcs_wire_format(example, system):
    plant = example.OutsidePlant("t")
    reference = Plant(system)
    first = [(role, decode(payload)) for role, payload in plant.states()]
    assert [(role, msg.k, msg.sender) for role, msg in first] == [("plant", 0, "plant")]
    assert np.array_equal(whole(first), reference.x)
    rng = np.random.default_rng(3)
    for k in range(30):
        u = rng.uniform(-2.5, 2.5, size=system.m)
        if k % 7 == 3:  # another step's inputs: ignored
            assert answer(plant, k + 1, u, system) == []
        states = answer(plant, k, u, system)
        expected = reference.step(u)
        assert [msg.k for _, msg in states] == [k + 1]
        assert np.array_equal(whole(states), expected)  # bit for bit
        again = answer(plant, k, rng.uniform(-2.5, 2.5, size=system.m), system)  # a repeat: not applied twice
        assert [msg.k for _, msg in again] == [k + 1] and np.array_equal(whole(again), expected)
    plant.on_control(encode(Stop(run="t", k=30, reason="finished")))
    assert plant.finished == "finished"


def test_the_examples_sensors_send_their_own_subsystems(example, system):
    plant = example.OutsidePlant("t", sensors=["2", "4"])
    states = [(role, decode(payload)) for role, payload in plant.states()]
    assert [(role, msg.sender, list(msg.x)) for role, msg in states] == [("sensor-2", "sensor-2", ["2"]),
                                                                        ("sensor-4", "sensor-4", ["4"])]
    states = answer(plant, 0, np.ones(system.m), system)
    expected = Plant(system).step(np.ones(system.m))
    assert np.array_equal(states[0][1].x["2"], expected[system.xs(1)])
    assert np.array_equal(states[1][1].x["4"], expected[system.xs(3)])


@pytest.mark.parametrize("change, words", [
    (lambda b: b.update(protocol=2), "protocol version 2; this process speaks protocol version 3"),
    (lambda b: (b.pop("protocol"), b.update(schema=2)), "protocol version 2; this process speaks protocol version 3"),
    (lambda b: b.update(sender="plant"), "from the coordinator"),
    (lambda b: b.update(run="other"), "of run 't'"),
    (lambda b: b["u"].pop("3"), "one entry per subsystem"),
    (lambda b: b["u"]["2"].update(shape=[2], data=bytes(16)), "u[2]: expected a <f8 array of shape [1]"),
    (lambda b: b["u"]["2"].update(data=np.array([np.nan]).tobytes()), "u[2]: non-finite values"),
])
def test_the_example_drops_bad_inputs_without_applying_them(example, system, change, words):
    plant = example.OutsidePlant("t")
    body = msgpack.unpackb(encode(Inputs(run="t", k=0, u={s.name: np.ones(1) for s in system.subsystems})), raw=False)
    change(body)
    with pytest.raises(example.Dropped, match=re.escape(words)):
        plant.on_inputs(msgpack.packb(body, use_bin_type=True))
    assert plant.k == 0 and np.array_equal(plant.x, system.x0)

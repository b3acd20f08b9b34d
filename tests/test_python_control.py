"""python-control models in the Python API: ``system=control.ss(...)`` in place of A and B.

A system gives the same scenario as its matrices written out; its labels name the states and
inputs; its time base sets ``time`` and ``dt``; systems that disagree, a non-zero D, or something
that is not a StateSpace are one clear error each. dmpc never imports python-control.
"""
from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import dmpc
from dmpc.scenario import ScenarioError

control = pytest.importorskip("control")

ROOT = Path(__file__).resolve().parents[1]
AC = np.array([[0.0, 1.0], [0.0, 0.0]])
BC = np.array([[0.0], [1.0]])
WEIGHTS = dict(Q=np.eye(2), R=0.1 * np.eye(1), input={"lower": [-1.0], "upper": [1.0]})


def cart(dt=0, **labels):
    continuous = control.ss(AC, BC, np.eye(2), 0, **labels)
    return continuous if dt == 0 else control.c2d(continuous, dt)


def two_carts(left, right=None, couplings=(), **top) -> dict:
    right = left if right is None else right
    return {"name": "carts", **top,
            "subsystems": [dict(WEIGHTS, name="left", x0=[1.0, 0.0], **left),
                           dict(WEIGHTS, name="right", x0=[-1.0, 0.0], **right)],
            "couplings": list(couplings)}


def spelt_out(**top) -> dict:
    """The two carts with their matrices written out (what a system stands for)."""
    return two_carts({"A": AC, "B": BC}, **top)


# ------------------------------------------------------------------------------- what a system gives
def test_a_continuous_system_is_its_matrices_in_continuous_time():
    scenario = dmpc.load_scenario(two_carts({"system": cart()}, dt=0.1))
    assert scenario.time == "continuous" and scenario.dt == 0.1
    assert scenario == dmpc.load_scenario(spelt_out(time="continuous", dt=0.1))


def test_a_discrete_system_sets_time_and_dt_from_its_own():
    discrete = cart(0.1)
    scenario = dmpc.load_scenario(two_carts({"system": discrete}))
    assert scenario.time == "discrete" and scenario.dt == 0.1
    assert np.array_equal(np.array(scenario.subsystems[0].A), discrete.A)
    assert np.array_equal(np.array(scenario.subsystems[1].B), discrete.B)
    assert dmpc.load_scenario(two_carts({"system": discrete}, dt=0.1)).dt == 0.1  # the same dt beside it
    unspecified = control.ss(discrete.A, discrete.B, np.eye(2), 0, True)  # dt = True: discrete, no period
    scenario = dmpc.load_scenario(two_carts({"system": unspecified}))
    assert scenario.time == "discrete" and scenario.dt is None


def test_labels_name_the_states_and_inputs_unless_defaults_or_given():
    named = dmpc.load_scenario(two_carts({"system": cart(states=["p", "v"], inputs=["F"])}, dt=0.1))
    assert [s.name for s in named.subsystems[0].states] == ["p", "v"]
    assert [s.name for s in named.subsystems[0].inputs] == ["F"]
    assert named.subsystems[0].states[0].unit == ""
    default = dmpc.load_scenario(two_carts({"system": cart()}, dt=0.1))
    assert default.subsystems[0].states is None and default.subsystems[0].inputs is None
    given = dmpc.load_scenario(two_carts({"system": cart(states=["p", "v"]),
                                          "states": [{"name": "x", "unit": "m"}, {"name": "xdot", "unit": "m/s"}]},
                                         dt=0.1))
    assert [(s.name, s.unit) for s in given.subsystems[0].states] == [("x", "m"), ("xdot", "m/s")]


def test_a_coupling_and_a_family_take_systems_too():
    spring = control.ss(0.01 * np.eye(2), np.full((2, 1), 0.5), np.eye(2), 0)
    scenario = dmpc.load_scenario(two_carts({"system": cart()}, dt=0.1,
                                            couplings=[{"target": "left", "source": "right", "system": spring}]))
    assert scenario.couplings[0].A == (0.01 * np.eye(2)).tolist() and scenario.couplings[0].B == [[0.5], [0.5]]
    family = dmpc.load_scenario({"name": "chain", "dt": 0.1, "family": {
        "kind": "chain", "M": 3, "subsystem": dict(WEIGHTS, system=cart(states=["p", "v"])),
        "x0_cycle": [[1.0, 0.0]], "coupling": {"system": spring}}})
    assert family.time == "continuous"
    assert family.family.subsystem.A == AC.tolist() and family.family.coupling.B == [[0.5], [0.5]]
    assert [s.name for s in family.resolved_subsystems()[2].states] == ["p", "v"]


def test_a_scenario_of_systems_runs_like_the_one_spelt_out():
    from_systems = dmpc.simulate(dmpc.load_scenario(two_carts({"system": cart()}, dt=0.1), steps=15))
    reference = dmpc.simulate(dmpc.load_scenario(spelt_out(time="continuous", dt=0.1), steps=15))
    assert from_systems.verdict == "ok"
    assert np.array_equal(from_systems.stacked_x(), reference.stacked_x())


def test_the_example_of_the_python_page_runs():
    page = (ROOT / "docs" / "python.md").read_text()
    section = page.split("\n## From python-control\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)\n```", section, flags=re.S)
    assert len(blocks) == 1
    namespace: dict = {}
    exec(compile(blocks[0], "docs/python.md", "exec"), namespace)  # the page's own example
    assert namespace["result"].verdict == "ok" and namespace["result"].states["left"][0].name == "p"


# ------------------------------------------------------------------------------------- what is refused
@pytest.mark.parametrize("left, right, top, message", [
    ({"system": cart(0.1)}, {"system": cart(0.2)}, {},
     r"^subsystems\[1\]\.system: discrete-time with dt = 0.2 s, but subsystems\[0\]\.system is discrete-time with "
     r"dt = 0.1 s: every system of a scenario needs the same time base"),
    ({"system": cart(0.1)}, {"system": cart()}, {"dt": 0.1},
     r"^subsystems\[1\]\.system: continuous-time \(dt = 0\), but subsystems\[0\]\.system is discrete-time"),
    ({"system": cart()}, None, {},
     r"^dt: required: subsystems\[0\]\.system is continuous-time \(dt = 0\), so the scenario needs the sampling period"),
    ({"system": cart(0.1)}, None, {"dt": 0.2},
     r"^dt: 0.2 differs from the sampling period of subsystems\[0\]\.system \(0.1 s\)"),
    ({"system": cart()}, None, {"dt": 0.1, "time": "discrete"},
     r"^time: 'discrete', but subsystems\[0\]\.system is continuous-time"),
    ({"system": cart(0.1)}, None, {"time": "continuous", "dt": 0.1},
     r"^time: 'continuous', but subsystems\[0\]\.system is discrete-time with dt = 0.1 s"),
    ({"system": control.ss(AC, BC, np.eye(2), [[0.5], [0.0]])}, None, {"dt": 0.1},
     r"^subsystems\[0\]\.system: D is not zero \(largest \|D\| entry 0.5\)"),
    ({"system": cart(), "A": AC}, None, {"dt": 0.1},
     r"^subsystems\[0\]\.system: give either a system or A, not both"),
    ({"system": control.tf([1.0], [1.0, 1.0])}, None, {"dt": 0.1},
     r"^subsystems\[0\]\.system: expected a python-control StateSpace \(control.ss, control.c2d\), got "
     r"control\.xferfcn\.TransferFunction; a transfer function becomes one with control.ss"),
    ({"system": AC}, None, {"dt": 0.1},
     r"^subsystems\[0\]\.system: expected a python-control StateSpace .* got numpy\.ndarray"),
])
def test_systems_that_do_not_fit_are_one_clear_error(left, right, top, message):
    with pytest.raises(ScenarioError, match=message) as caught:
        dmpc.load_scenario(two_carts(left, right, **top))
    assert "\n" not in str(caught.value)


def test_a_coupling_system_of_another_time_base_is_named():
    spring = control.c2d(control.ss(0.01 * np.eye(2), np.zeros((2, 1)), np.eye(2), 0), 0.1)
    with pytest.raises(ScenarioError, match=r"^couplings\[0\]\.system: discrete-time with dt = 0.1 s, but "
                                            r"subsystems\[0\]\.system is continuous-time"):
        dmpc.load_scenario(two_carts({"system": cart()}, dt=0.1,
                                     couplings=[{"target": "left", "source": "right", "system": spring}]))


def test_a_time_base_that_is_not_set_is_an_error():
    loose = control.ss(AC, BC, np.eye(2), 0)
    loose.dt = None  # python-control's "either" time base
    with pytest.raises(ScenarioError, match=r"^subsystems\[0\]\.system: its time base is not set \(dt = None\)"):
        dmpc.load_scenario(two_carts({"system": loose}, dt=0.1))


# ------------------------------------------------------------------------------- an optional extra
def test_dmpc_never_imports_python_control():
    imports = []
    for path in list((ROOT / "dmpc").rglob("*.py")) + [p for d in ("agents", "plant", "bus")
                                                       for p in (ROOT / d).rglob("*.py")]:
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            imports += [f"{path.relative_to(ROOT)}: {n}" for n in names if n.split(".")[0] == "control"]
    assert imports == []
    check = ("import sys, dmpc, dmpc.api, dmpc.scenario.state_space, dmpc.agents.process; "
             "print(sorted(m for m in sys.modules if m == 'control' or m.startswith('control.')))")
    done = subprocess.run([sys.executable, "-c", check], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "[]", done.stderr


def test_the_extra_is_declared_and_tested():
    import tomllib

    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert any(req.startswith("control") for req in extras["control"])
    assert any(req.startswith("control") for req in extras["test"])

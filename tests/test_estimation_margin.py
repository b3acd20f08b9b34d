"""``estimation.margin``: the controllers keep the estimate within the state bounds moved in by a
margin, the plant's state is judged against the bounds themselves, and the verdict says when the
estimation error outgrew the margin (docs/algorithm.md, "Offset-free tracking")."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

import dmpc
from dmpc.prepared.bundle import bundle_json, load_bundle
from dmpc.records.verdict import RunLimits, judge
from dmpc.scenario import build_system
from dmpc.setup import prepare

ROOT = Path(__file__).resolve().parents[1]
UPPER = 0.83  # the upper tanks' bound in this test: the levels' steady state at 0.8 m puts h4 at 0.817


def _tanks(margin=None, steps: int = 400) -> dict:
    data = yaml.safe_load((ROOT / "scenarios/fourtank-absolute.yaml").read_text())
    data["steps"] = steps
    data["setpoints"] = [{"at": 0, "subsystem": "a", "y": {"h1": 0.8}}, {"at": 0, "subsystem": "b", "y": {"h2": 0.8}}]
    for sub in data["subsystems"]:
        sub["state"]["upper"][1] = UPPER
    if margin is not None:
        data["estimation"]["margin"] = margin
    return data


def test_the_controllers_bounds_are_moved_in_and_the_plants_are_kept():
    system = build_system(dmpc.load_scenario(_tanks({"a": [0.0, 0.01], "b": [0.0, 0.02]})))
    a, b = system.subsystems
    assert a.state_set is not None and a.plant_state_set is not None and b.state_set is not None
    np.testing.assert_allclose(a.state_set.upper, np.array([1.36, UPPER - 0.01]) - a.state_offset)
    np.testing.assert_allclose(b.state_set.lower, np.array([0.2, 0.22]) - b.state_offset)
    np.testing.assert_allclose(a.plant_state_set.upper, np.array([1.36, UPPER]) - a.state_offset)
    plain = build_system(dmpc.load_scenario(_tanks()))
    assert all(s.state_margin is None and s.plant_state_set is s.state_set for s in plain.subsystems)


def test_one_number_is_every_states_margin_and_travels_in_the_bundle(tmp_path):
    prepared = prepare(dmpc.load_scenario(_tanks(0.005)))
    assert [s.state_margin.tolist() for s in prepared.system.subsystems] == [[0.005, 0.005]] * 2
    path = tmp_path / "run.json"
    path.write_text(json.dumps(bundle_json(prepared)))
    again = load_bundle(path)
    for s, t in zip(prepared.system.subsystems, again.system.subsystems):
        np.testing.assert_array_equal(s.state_margin, t.state_margin)
        np.testing.assert_array_equal(s.state_set.upper, t.state_set.upper)


def test_a_polytopes_rows_move_by_their_weighted_margin():
    data = yaml.safe_load((ROOT / "scenarios/paper.yaml").read_text())
    data["subsystems"][0]["state"] = {"H": [[1.0, -2.0]], "h": [5.0]}
    data["estimation"] = {"margin": {"1": [0.1, 0.2]}}
    sub = build_system(dmpc.load_scenario(data)).subsystems[0]
    assert sub.state_set is not None and sub.plant_state_set is not None
    assert sub.state_set.upper.tolist() == pytest.approx([5.0 - 0.1 - 0.4])
    assert sub.plant_state_set.upper.tolist() == pytest.approx([5.0])


@pytest.mark.parametrize(("margin", "field", "words"), [
    ({"c": [0.0, 0.1]}, "estimation.margin.c", "unknown subsystem"),
    ({"a": [0.1]}, "estimation.margin.a", "expected 2"),
    ({"a": [0.0, -0.1]}, "estimation.margin.a[1]", ">= 0"),
    ({"a": [0.0, 0.2]}, "estimation.margin.a", "too large"),
])
def test_bad_margins_name_the_field(margin, field, words):
    with pytest.raises(dmpc.DmpcError) as info:
        dmpc.load_scenario(_tanks(margin))
    assert field in str(info.value) and words in str(info.value)


def test_a_subsystem_without_state_bounds_has_no_margin_to_keep():
    data = yaml.safe_load((ROOT / "scenarios/paper.yaml").read_text())
    data["estimation"] = {"margin": 0.1}
    with pytest.raises(dmpc.DmpcError, match="estimation.margin.1: subsystem '1' has no state bounds"):
        dmpc.load_scenario(data)


@pytest.fixture(scope="module")
def runs():
    return dmpc.simulate(_tanks()), dmpc.simulate(_tanks({"a": [0.0, 0.0025], "b": [0.0, 0.0025]}))


def test_without_a_margin_the_estimate_keeps_the_bound_and_the_plant_does_not(runs):
    plain, _ = runs
    assert plain.x_hat["b"][:, 1].max() <= UPPER + 1e-6
    assert plain.x["b"][:, 1].max() > UPPER + 1e-4  # by the estimation error: what the margin is for
    assert [f["kind"] for f in plain.summary["failures"]] == ["state-violated"]
    assert not any(w["kind"] == "estimation-margin" for w in plain.summary["warnings"])


def test_with_a_margin_the_estimate_keeps_it_and_the_verdict_says_when_the_error_outgrew_it(runs):
    plain, kept = runs
    assert kept.x_hat["b"][:, 1].max() <= UPPER - 0.0025 + 1e-6
    assert kept.x["b"][:, 1].max() < plain.x["b"][:, 1].max()
    found = [w for w in kept.summary["warnings"] if w["kind"] == "estimation-margin"]
    assert sorted(w["subsystem"] for w in found) == ["a", "b"]
    assert all("h3" in w["message"] or "h4" in w["message"] for w in found)  # h1, h2 have no margin: not judged
    for w in found:
        assert w["amount"] > 0.004  # the upper tanks' estimate is off by 7 to 9 mm during the climb


def test_the_verdict_judges_the_plant_against_its_own_bounds():
    prepared = prepare(dmpc.load_scenario(_tanks({"a": [0.0, 0.01], "b": [0.0, 0.01]}, steps=3)))
    system = prepared.system
    x = np.zeros((4, system.n))  # every state at the operating point
    x[:, 1] = system.subsystems[0].state_set.upper[1] + 0.005  # between the controllers' bound and the plant's
    x_hat = x[:3].copy()
    x_hat[:, 1] -= 0.009  # an estimation error within the margin
    arrays = {"x": x, "u": np.zeros((3, system.m)), "x_hat": x_hat, "rounds": np.ones(3, int),
              "max_change": np.zeros(3), "fallback": np.zeros((3, system.M), bool), "J": np.zeros(3)}
    verdict = judge(system, arrays, [], RunLimits(steps=3))
    assert not verdict.failures  # the plant's state is inside the plant's bounds
    assert not [w for w in verdict.warnings if w.kind == "estimation-margin"]
    over = copy.deepcopy(arrays)
    over["x_hat"][:, 1] -= 0.002  # now 11 mm off: over the margin
    found = [w for w in judge(system, over, [], RunLimits(steps=3)).warnings if w.kind == "estimation-margin"]
    assert [(w.subsystem, w.steps) for w in found] == [("a", [0, 1, 2])]
    outside = copy.deepcopy(arrays)
    outside["x"][:, 1] += 0.006  # past the plant's own bound
    assert [f.kind for f in judge(system, outside, [], RunLimits(steps=3)).failures] == ["state-violated"]

"""Absolute coordinates: a subsystem's ``operating_point`` puts x0, the bounds, the setpoints, the
records and the user's plant function in the plant's own units, while the controllers work in
deviations from it (docs/scenarios.md, "Operating point")."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

import dmpc
from dmpc.bus.messages import Setpoint
from dmpc.coordinator.setpoint_intake import SetpointIntake
from dmpc.prepared.bundle import bundle_json, load_bundle
from dmpc.records.plant_units import PlantUnits
from dmpc.scenario import build_system
from dmpc.setup import prepare
from dmpc.tracking.tracker import Tracker

ROOT = Path(__file__).resolve().parents[1]

# the paper's example, with subsystem 1's first state tracked; operating points of both signs
OFFSET_X = {"1": [10.0, -4.0], "2": [0.5, 0.25], "3": [-3.0, 7.0], "4": [0.0, 1.0]}
OFFSET_U = {"1": [2.0], "2": [-1.0], "3": [0.0], "4": [4.0]}


def _paper(steps: int = 25) -> dict:
    data = yaml.safe_load((ROOT / "scenarios/paper.yaml").read_text())
    data["steps"] = steps
    data["design"] = {"gains": "lmi"}
    data["options"] = {"method": "tv-box"}
    for sub in data["subsystems"]:
        sub.pop("K", None)
        sub.pop("P", None)
        sub["state"] = {"lower": [-6.0, -6.0], "upper": [6.0, 6.0]}
    data["setpoints"] = [{"at": 0, "subsystem": 1, "x": [0.5, None]}, {"at": 12, "subsystem": 3, "u": [0.2]}]
    return data


def _absolute(data: dict) -> dict:
    """``data`` with every subsystem given an operating point, and x0, bounds and setpoints moved to it."""
    out = copy.deepcopy(data)
    for sub in out["subsystems"]:
        name = str(sub["name"])
        x_op, u_op = np.array(OFFSET_X[name]), np.array(OFFSET_U[name])
        sub["operating_point"] = {"x": x_op.tolist(), "u": u_op.tolist()}
        sub["x0"] = (np.array(sub["x0"]) + x_op).tolist()
        sub["state"] = {key: (np.array(sub["state"][key]) + x_op).tolist() for key in ("lower", "upper")}
        sub["input"] = {key: (np.array(sub["input"][key]) + u_op).tolist() for key in ("lower", "upper")}
    for entry in out["setpoints"]:
        name = str(entry["subsystem"])
        for kind, offset in (("x", OFFSET_X[name]), ("u", OFFSET_U[name])):
            if kind in entry:
                entry[kind] = [None if v is None else v + o for v, o in zip(entry[kind], offset)]
    return out


def _stacked(offsets: dict) -> np.ndarray:
    return np.concatenate([offsets[str(i)] for i in range(1, 5)])


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("op")
    data = _paper()
    model = dmpc.simulate(data, out=folder / "model")
    plant = dmpc.simulate(_absolute(data), out=folder / "plant")
    return model, plant


def test_the_run_in_plant_units_is_the_run_in_deviations_moved(runs):
    model, plant = runs
    assert model.verdict == plant.verdict == "ok"
    assert model.summary["fallbacks"] == plant.summary["fallbacks"] == 0
    for name in model.names:
        np.testing.assert_allclose(plant.x[name], model.x[name] + OFFSET_X[name], atol=1e-9)
        np.testing.assert_allclose(plant.u[name], model.u[name] + OFFSET_U[name], atol=1e-9)
        np.testing.assert_allclose(plant.target[name], model.target[name] + OFFSET_X[name], atol=1e-9)
        np.testing.assert_allclose(plant.setpoint_u[name], model.setpoint_u[name] + OFFSET_U[name], atol=1e-9)
    np.testing.assert_allclose(plant.J, model.J, rtol=1e-7, atol=1e-9)  # costs stay the model's


def test_every_record_is_in_plant_units(runs):
    model, plant = runs
    assert model.folder is not None and plant.folder is not None
    x_op, u_op = _stacked(OFFSET_X), _stacked(OFFSET_U)
    lines = [json.loads(line) for line in (plant.folder / "steps.jsonl").read_text().splitlines()]
    plain = [json.loads(line) for line in (model.folder / "steps.jsonl").read_text().splitlines()]
    for line, base in zip(lines, plain):
        for key, offset in (("x", x_op), ("x_next", x_op), ("u", u_op), ("target", x_op), ("target_u", u_op),
                            ("reference", x_op), ("reference_u", u_op)):
            if key in base:
                np.testing.assert_allclose(line[key], np.array(base[key]) + offset, atol=1e-9)
        assert line["alpha"] == pytest.approx(base["alpha"], abs=1e-9)  # a scale, not moved
    npz, base_npz = np.load(plant.folder / "trajectory.npz"), np.load(model.folder / "trajectory.npz")
    np.testing.assert_allclose(npz["x"], base_npz["x"] + x_op, atol=1e-9)
    np.testing.assert_allclose(npz["plan_z_1"], base_npz["plan_z_1"] + OFFSET_X["1"], atol=1e-9)
    np.testing.assert_allclose(npz["plan_v_4"], base_npz["plan_v_4"] + OFFSET_U["4"], atol=1e-9)
    segments = plant.summary["tracking"]["segments"]
    base_segments = model.summary["tracking"]["segments"]
    assert [s["asked"] for s in segments] == pytest.approx([10.5, 0.2])
    for seg, base in zip(segments, base_segments):
        assert seg["asked"] - base["asked"] == pytest.approx(seg["target"] - base["target"])
        assert seg["error_at_end"] == pytest.approx(base["error_at_end"], abs=1e-9)
        assert seg["reached"] == base["reached"]
    assert plant.summary["operating_point"] is True and "operating_point" not in model.summary


def test_without_an_operating_point_nothing_is_moved():
    system = build_system(dmpc.load_scenario(_paper()))
    assert not system.has_operating_point and PlantUnits.of(system) is None
    assert all(s.x_op is None and s.u_op is None for s in system.subsystems)


def test_the_model_is_built_in_deviations():
    system = build_system(dmpc.load_scenario(_absolute(_paper())))
    base = build_system(dmpc.load_scenario(_paper()))
    np.testing.assert_allclose(system.x0, base.x0, atol=1e-12)
    for sub, ref in zip(system.subsystems, base.subsystems):
        assert sub.state_set is not None and ref.state_set is not None
        np.testing.assert_allclose(sub.state_set.lower, ref.state_set.lower, atol=1e-12)
        np.testing.assert_allclose(sub.input_set.upper, ref.input_set.upper, atol=1e-12)
    np.testing.assert_array_equal(system.state_offset, _stacked(OFFSET_X))
    np.testing.assert_array_equal(system.input_offset, _stacked(OFFSET_U))


def test_a_polytope_is_moved_too():
    data = _absolute(_paper())
    data["subsystems"][0]["input"] = {"H": [[1.0], [-1.0]], "h": [4.5, 0.5]}  # -0.5 <= u <= 4.5 around u_op = 2
    system = build_system(dmpc.load_scenario(data))
    np.testing.assert_allclose(system.subsystems[0].input_set.upper, [2.5, 2.5])


@pytest.mark.parametrize(("change", "path", "words"), [
    (lambda d: d["subsystems"][0]["operating_point"].update(x=[1.0]), "subsystems[0].operating_point.x", "expected 2"),
    (lambda d: d["subsystems"][0]["operating_point"].update(u=[1.0, 2.0]), "subsystems[0].operating_point.u",
     "expected 1"),
    (lambda d: d["subsystems"][0]["operating_point"].update(x=[100.0, -4.0]), "subsystems[0].state.upper[0]",
     "the operating point (operating_point.x)"),
    (lambda d: d["subsystems"][1]["operating_point"].update(u=[9.0]), "subsystems[1].input.upper[0]",
     "the operating point (operating_point.u)"),
    (lambda d: d["subsystems"][0].update(x0=[30.0, 2.5]), "subsystems[0].x0", "outside"),
])
def test_bad_operating_points_name_the_field(change, path, words):
    data = _absolute(_paper())
    change(data)
    with pytest.raises(dmpc.DmpcError) as info:
        dmpc.load_scenario(data)
    assert path in str(info.value) and words in str(info.value)


def test_the_operating_inputs_default_to_zero():
    data = _paper()
    data["subsystems"][0]["operating_point"] = {"x": [1.0, 1.0]}
    data["subsystems"][0]["x0"] = [3.794, 3.5]
    data["subsystems"][0]["state"] = {"lower": [-5.0, -5.0], "upper": [7.0, 7.0]}
    sub = build_system(dmpc.load_scenario(data)).subsystems[0]
    np.testing.assert_array_equal(sub.input_offset, [0.0])
    np.testing.assert_allclose(sub.x0, [2.794, 2.5])


def test_the_plant_function_sees_the_plants_units(tmp_path):
    data = _absolute(_paper(steps=4))
    system = build_system(dmpc.load_scenario(data))
    seen = []

    def plant(x, u, k):
        seen.append((x.copy(), u.copy()))
        dx, du = x - system.state_offset, u - system.input_offset
        return system.A @ dx + system.B @ du + system.state_offset

    result = dmpc.simulate(data, plant=plant, out=tmp_path / "f")
    base = dmpc.simulate(_paper(steps=4), out=tmp_path / "b")
    np.testing.assert_allclose(seen[0][0], system.x0 + system.state_offset)
    np.testing.assert_allclose(seen[0][1], result.stacked_u()[0])  # the records' input, in the plant's units
    for name in base.names:
        np.testing.assert_allclose(result.x[name], base.x[name] + OFFSET_X[name], atol=1e-9)


def test_live_requests_are_in_plant_units():
    scenario = dmpc.load_scenario(_absolute(_paper()))
    prepared = prepare(scenario)
    gain = prepared.design.gains.K_global()
    tracker = Tracker(prepared.system, prepared.design.terminal, prepared.system.A + prepared.system.B @ gain, gain,
                      (), prepared.setpoint_margin)
    intake = SetpointIntake(prepared.system, "r", 100, tracker, "tv-box")
    msg = Setpoint(run="r", sender="op", id=1, subsystem="1", x=np.array([11.0, np.nan]), u=np.zeros(0))
    answer, note = intake.answer(msg, 3, False)
    assert answer.accepted, answer.reason
    assert "x = [11, free]" in note
    np.testing.assert_allclose(tracker.schedule.request(3).x[:2], [1.0, np.nan])  # 11 around x_op = 10
    far = Setpoint(run="r", sender="op", id=2, subsystem="1", x=np.array([17.0, np.nan]), u=np.zeros(0))
    refusal = intake.refusal(far, 3, False)
    assert refusal is not None and "outside X_i [4, 16]" in refusal.reason


def test_the_bundle_carries_the_operating_point(tmp_path):
    prepared = prepare(dmpc.load_scenario(_absolute(_paper())))
    path = tmp_path / "run.json"
    path.write_text(json.dumps(bundle_json(prepared)))
    again = load_bundle(path)
    np.testing.assert_array_equal(again.system.state_offset, prepared.system.state_offset)
    np.testing.assert_array_equal(again.system.input_offset, prepared.system.input_offset)
    plain = prepare(dmpc.load_scenario(_paper()))
    assert "x_op" not in bundle_json(plain)["subsystems"][0]


def test_the_four_tank_in_absolute_units_refuses_mixed_coordinates():
    data = yaml.safe_load((ROOT / "scenarios/fourtank-absolute.yaml").read_text())
    deviations = yaml.safe_load((ROOT / "scenarios/fourtank-levels.yaml").read_text())
    mixed = copy.deepcopy(data)
    mixed["subsystems"][1] = deviations["subsystems"][1]  # subsystem b in deviations, a in levels
    with pytest.raises(dmpc.DmpcError, match=r"subsystems\[1\]\.operating_point: required"):
        dmpc.load_scenario(mixed)
    both = copy.deepcopy(data)
    both["plant"]["fourtank"] = {"q0": [1.63, 2.0]}
    with pytest.raises(dmpc.DmpcError, match=r"plant\.fourtank\.q0: not read"):
        dmpc.load_scenario(both)


def test_the_four_tank_in_levels_and_flows_tracks_without_offset(tmp_path):
    """The shipped case: the nonlinear tanks, h1 and h2 measured only, setpoints in absolute levels;
    every segment ends within 1e-4 of its setpoint step, with no fallback."""
    result = dmpc.simulate(ROOT / "scenarios/fourtank-absolute.yaml", out=tmp_path / "abs")
    summary = result.summary
    assert result.verdict == "ok", summary["failures"]
    assert summary["fallbacks"] == 0 and not summary["warnings"]
    segments = summary["tracking"]["segments"]
    assert len(segments) == 6
    for seg in segments:
        assert seg["output"] and seg["reached"]
        assert abs(seg["error_at_end"]) <= 1e-4 * abs(seg["step"]), seg
    assert [round(s["asked"], 6) for s in segments] == [0.8, 0.8, 0.5, 0.5, 0.653752, 0.64982]
    h1 = result.x["a"][:, 0]
    assert 0.49 < h1.min() and h1.max() < 0.81  # in metres, as the scenario writes them
    assert result.states["a"][0].lower == 0.2 and result.inputs["a"][0].upper == 3.26
    assert result.u["a"].min() >= 0.0 - 1e-9 and result.u["b"].max() <= 4.0 + 1e-9  # the pumps' own range


def test_the_four_tank_in_levels_is_the_four_tank_in_deviations(tmp_path):
    data = yaml.safe_load((ROOT / "scenarios/fourtank-absolute.yaml").read_text())
    data["steps"] = 200
    deviations = yaml.safe_load((ROOT / "scenarios/fourtank-levels.yaml").read_text())
    deviations["steps"] = 200
    ops = {sub["name"]: sub["operating_point"] for sub in data["subsystems"]}
    deviations["setpoints"] = [{"at": 0, "subsystem": "a", "y": {"h1": 0.8 - ops["a"]["x"][0]}},
                               {"at": 0, "subsystem": "b", "y": {"h2": 0.8 - ops["b"]["x"][0]}}]
    data["setpoints"] = data["setpoints"][:2]
    levels = dmpc.simulate(data, out=tmp_path / "levels")
    plain = dmpc.simulate(deviations, out=tmp_path / "plain")
    for name in ("a", "b"):
        np.testing.assert_allclose(levels.x[name], plain.x[name] + ops[name]["x"], atol=1e-9)
        np.testing.assert_allclose(levels.u[name], plain.u[name] + ops[name]["u"], atol=1e-7)

"""Outputs and estimation in scenarios (issue 31, the scenario side): ``C`` and ``outputs`` per
subsystem, setpoints on outputs (``y``), the ``estimation`` section designed at ``prepare`` and
reported by ``dmpc validate`` / ``dmpc design``, the prepared bundle that carries the gains, and
``plant.measurement_noise``.

The figures asserted are recomputed here where they can be (the augmented model, the noise
weights' scales); the estimator's own numbers are the core's (tests/test_estimation.py checks them).
"""
from __future__ import annotations

import copy
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

import dmpc
from dmpc.estimation.kalman import DISTURBANCE_NOISE, MEASUREMENT_NOISE, STATE_NOISE, design_estimator
from dmpc.estimation.model import augment
from dmpc.prepared.bundle import bundle_json, load_bundle, write_bundle
from dmpc.scenario import ScenarioError, build_system, load_scenario, setpoint_entries, validate_scenario
from dmpc.setup import prepare
from tests.e2e_helpers import run_cli
from tests.helpers.cli import call, one_error_line

ROOT = Path(__file__).resolve().parents[1]
FOURTANK = ROOT / "scenarios" / "fourtank.yaml"
LEVELS = {"subsystems[0].C": [[1.0, 0.0]], "subsystems[1].C": [[1.0, 0.0]]}
"""The four-tank's measurements: h1 of subsystem a (h1, h3), h2 of b (h2, h4)."""
LEVELS_SET = ["--set", "subsystems[0].C=[[1,0]]", "--set", "subsystems[1].C=[[1,0]]"]


def small(**top) -> dict:
    """Two stable scalar-input subsystems of two states each, coupled a <- b, discrete time."""
    sub = {"A": [[0.9, 0.1], [0.0, 0.8]], "B": [[1.0], [0.5]], "Q": [[1.0, 0.0], [0.0, 1.0]], "R": [[0.1]],
           "input": {"lower": [-1.0], "upper": [1.0]}, "state": {"lower": [-2.0, -2.0], "upper": [2.0, 2.0]},
           "states": [{"name": "p", "unit": "m"}, {"name": "q"}], "x0": [0.1, 0.0]}
    data = {"name": "small", "subsystems": [dict(copy.deepcopy(sub), name="a"), dict(copy.deepcopy(sub), name="b")],
            "couplings": [{"target": "a", "source": "b", "A": [[0.05, 0.0], [0.0, 0.05]]}], "horizon": 5,
            "options": {"method": "tv-box-coop"}}
    data.update(top)
    return data


def refused(data: dict, *words: str) -> str:
    with pytest.raises(ScenarioError) as caught:
        validate_scenario(data)
    message = str(caught.value)
    for word in words:
        assert word in message, message
    return message


# ---------------------------------------------------------------------------- the schema
def test_c_and_outputs_are_checked_with_the_field_named():
    data = small(estimation={})
    data["subsystems"][0]["C"] = [[1.0, 0.0, 0.0]]
    refused(data, "subsystems[0].C:", "expected 2 columns (n = 2 states, from A), got 3")
    data["subsystems"][0]["C"] = [[1.0, 0.0], [2.0, 0.0]]
    refused(data, "subsystems[0].C:", "rows must be independent", "rank is 1")
    data["subsystems"][0]["C"] = [[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]
    refused(data, "subsystems[0].C:", "at most 2 rows")
    data["subsystems"][0]["C"] = [[0.0, 0.0]]
    refused(data, "subsystems[0].C:", "rank is 0")
    data["subsystems"][0]["C"] = [[1.0, 0.0]]
    data["subsystems"][0]["outputs"] = [{"name": "p"}, {"name": "q"}]
    refused(data, "subsystems[0].outputs:", "expected 1 entries (p = 1 outputs, the rows of C), got 2")
    del data["subsystems"][0]["C"]  # C omitted: p = n
    data["subsystems"][0]["outputs"] = [{"name": "p"}]
    refused(data, "subsystems[0].outputs:", "expected 2 entries", "C is omitted")


def test_a_c_other_than_the_identity_needs_estimation():
    data = small()
    data["subsystems"][1]["C"] = [[0.0, 1.0]]
    refused(data, "subsystems[1].C:", "need an observer", "add 'estimation'")
    data["subsystems"][1]["C"] = [[1.0, 0.0], [0.0, 1.0]]  # the identity written out: as if omitted
    scn = validate_scenario(data)
    assert build_system(scn).subsystems[1].C is None
    assert scn.resolved_subsystems()[1].output_labels()[0].name == "p"  # the states' names
    family = yaml.safe_load((ROOT / "scenarios" / "chain.yaml").read_text())
    family["family"]["subsystem"]["C"] = [[1.0, 0.0]]
    refused(family, "family.subsystem.C:", "add 'estimation'")
    family["estimation"] = {"disturbance": "input"}
    system = build_system(validate_scenario(family))
    assert system.p == system.M and all(np.array_equal(s.C, [[1.0, 0.0]]) for s in system.subsystems)


def test_the_estimation_section_and_the_measurement_noise():
    assert validate_scenario(small()).estimation is None
    spec = validate_scenario(small(estimation={})).estimation
    assert spec.disturbance == "output"
    assert (spec.noise.state, spec.noise.disturbance, spec.noise.measurement) == (STATE_NOISE, DISTURBANCE_NOISE,
                                                                                MEASUREMENT_NOISE)
    refused(small(estimation={"disturbance": "state"}), "estimation.disturbance:", "output, input")
    refused(small(estimation={"disturbance": {"c": "input"}}), "estimation.disturbance.c:", "unknown subsystem 'c'")
    refused(small(estimation={"disturbance": {"a": "bias"}}), "estimation.disturbance.a:", "output, input")
    refused(small(estimation={"noise": {"measurement": 0}}), "estimation.noise.measurement:", "> 0")
    refused(small(estimation={"noise": {"state": {"a": -1}}}), "estimation.noise.state.a:", ">= 0")
    refused(small(estimation={"noise": {"disturbance": {"z": 1e-3}}}), "estimation.noise.disturbance.z:",
            "unknown subsystem")
    refused(small(estimation={"noise": {"sensor": 1}}), "estimation.noise.sensor:", "unknown field")
    noisy = small(estimation={})
    noisy["subsystems"][0]["C"] = [[1.0, 0.0]]
    noisy["plant"] = {"measurement_noise": {"std": {"a": [0.1, 0.2]}}}
    refused(noisy, "plant.measurement_noise.std.a:", "expected 1 entries (p = 1 outputs of subsystem 'a')")
    noisy["plant"] = {"measurement_noise": {"std": {"a": [-0.1]}}}
    refused(noisy, "plant.measurement_noise.std.a[0]:", ">= 0")
    noisy["plant"] = {"measurement_noise": {"std": -1}}
    refused(noisy, "plant.measurement_noise.std:", ">= 0")


def test_setpoints_on_outputs():
    data = small(setpoints=[{"at": 0, "subsystem": "a", "y": [0.5, None]}])
    refused(small(setpoints=[{"at": 0, "subsystem": "a", "y": [0.5]}]), "setpoints[0].y:",
            "expected 2 entries (p_i = 2 outputs of subsystem 'a')")
    refused(small(setpoints=[{"at": 0, "subsystem": "a", "y": {"h": 0.5}}]), "setpoints[0].y.h:",
            "no output 'h' (it has p, q)")
    refused(small(setpoints=[{"at": 0, "subsystem": "a", "y": {"p": 0.5}, "x": {"q": 0.1}}]), "setpoints[0].y:",
            "either x (states) or y (outputs), not both")
    refused(small(setpoints=[{"at": 0, "subsystem": "a", "y": {"p": 2.5}}]), "setpoints[0].y.p:",
            "outside X_i [-2, 2]", "measures the state p [m]")
    # without estimation an output is a state: the entry is the one x would give, bit for bit
    by_y = setpoint_entries(validate_scenario(data))[0]
    by_x = setpoint_entries(validate_scenario(small(setpoints=[{"at": 0, "subsystem": "a", "x": [0.5, None]}])))[0]
    assert by_y.y is None and by_x.y is None
    assert by_y.x.tobytes() == by_x.x.tobytes() and by_y.u.tobytes() == by_x.u.tobytes()


def test_with_estimation_setpoints_name_outputs_or_states_measured_alone():
    data = small(estimation={})
    data["subsystems"][0]["C"] = [[0.0, 1.0]]  # q alone: output y1
    data["subsystems"][1]["C"] = [[1.0, 1.0]]  # p + q, no state alone
    data["subsystems"][1]["outputs"] = [{"name": "sum", "unit": "m"}]
    data["setpoints"] = [{"at": 0, "subsystem": "a", "x": {"q": 0.3}, "u": [0.1]},
                         {"at": 2, "subsystem": "b", "y": {"sum": 0.4}}]
    entries = setpoint_entries(validate_scenario(data))
    assert np.isnan(entries[0].x).all() and entries[0].y.tolist() == [0.3] and entries[0].u.tolist() == [0.1]
    assert np.isnan(entries[1].x).all() and entries[1].y.tolist() == [0.4] and entries[1].at == 2
    data["setpoints"] = [{"at": 0, "subsystem": "a", "x": {"p": 0.3}}]
    message = refused(data, "setpoints[0].x.p:", "with estimation, setpoints name measured outputs (y) or inputs "
                                                  "(u): state p of subsystem 'a' is not measured")
    assert "subsystems[0].C" in message
    data["setpoints"] = [{"at": 0, "subsystem": "b", "x": [None, 0.2]}]
    refused(data, "setpoints[0].x[1]:", "state q of subsystem 'b' is not measured")
    data["setpoints"] = [{"at": 0, "subsystem": "a", "y": {"y1": 5.0}}]  # y1 measures q alone: its box holds
    refused(data, "setpoints[0].y.y1:", "outside X_i")


# ---------------------------------------------------------------------------- prepare
def test_prepare_designs_the_estimator_of_the_scenario():
    scn = load_scenario(FOURTANK, {**LEVELS, "estimation": {"disturbance": {"b": "input"},
                                                            "noise": {"measurement": {"a": 0.02}}}})
    prepared = prepare(scn)
    est = prepared.estimator
    assert est is not None and [p.kind for p in est.model.parts] == ["output", "input"]
    assert np.array_equal(est.model.C, [[1, 0, 0, 0], [0, 0, 1, 0]]) and np.array_equal(prepared.system.C, est.model.C)
    # the weights: the given fraction on a's sensor, the default elsewhere, times the scales of the bounds
    half = (prepared.system.subsystems[0].state_set.upper - prepared.system.subsystems[0].state_set.lower) / 2
    assert est.gains[0].noise.measurement[0, 0] == pytest.approx((0.02 * half[0]) ** 2)
    assert est.gains[1].noise.measurement[0, 0] == pytest.approx(
        (MEASUREMENT_NOISE * (prepared.system.subsystems[1].state_set.upper[0]
                              - prepared.system.subsystems[1].state_set.lower[0]) / 2) ** 2)
    # the same design as the core's from the same model and weights
    again = design_estimator(augment(prepared.system, [s.C for s in prepared.system.subsystems], ["output", "input"]),
                             [g.noise for g in est.gains])
    assert all(np.array_equal(g.L, h.L) for g, h in zip(est.gains, again.gains))
    assert est.radius < 1
    # the setpoints become output requests (h1, h2 are measured alone)
    assert [e.y.tolist() for e in prepared.setpoints] == [[0.15], [0.15], [0.0], [0.0]]
    # the estimator is part of the design digest
    assert prepared.digest != prepare(load_scenario(FOURTANK)).digest
    assert prepare(load_scenario(FOURTANK)).estimator is None


def test_the_bundle_carries_the_gains_exactly(tmp_path):
    prepared = prepare(load_scenario(FOURTANK, {**LEVELS, "estimation": {"disturbance": "input"}}))
    write_bundle(prepared, tmp_path / "run.json")
    loaded = load_bundle(tmp_path / "run.json")
    assert loaded.digest == prepared.digest
    assert [s.C.tolist() for s in loaded.system.subsystems] == [[[1.0, 0.0]], [[1.0, 0.0]]]
    for g, h in zip(prepared.estimator.gains, loaded.estimator.gains):
        assert g.L.tobytes() == h.L.tobytes() and g.P.tobytes() == h.P.tobytes() and g.radius == h.radius
        assert g.noise.measurement.tobytes() == h.noise.measurement.tobytes()
    assert [p.kind for p in loaded.estimator.model.parts] == ["input", "input"]
    # a changed gain no longer matches the digest
    data = json.loads((tmp_path / "run.json").read_text())
    data["estimation"]["gains"][0]["L"][0][0] += 1e-12
    (tmp_path / "tampered.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match="does not match its digest"):
        load_bundle(tmp_path / "tampered.json")
    # without estimation the bundle has neither C nor gains
    plain = prepare(load_scenario(FOURTANK))
    write_bundle(plain, tmp_path / "plain.json")
    data = json.loads((tmp_path / "plain.json").read_text())
    assert "estimation" not in data and all("C" not in s for s in data["subsystems"])
    assert load_bundle(tmp_path / "plain.json").estimator is None


def test_an_agent_loads_the_estimator_without_scipy_linalg(tmp_path):
    write_bundle(prepare(load_scenario(FOURTANK, {**LEVELS, "estimation": {}})), tmp_path / "run.json")
    code = ("import sys; from dmpc.prepared.bundle import load_bundle; "
            f"p = load_bundle({str(tmp_path / 'run.json')!r}); "
            "from dmpc.estimation.observer import Observer; Observer(p.estimator).update(None, [0.1, 0.0]); "
            "print('scipy.linalg' in sys.modules, 'pydantic' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]


def test_the_measurement_noise_is_a_pure_function_of_the_step():
    scn = load_scenario(FOURTANK, {**LEVELS, "estimation": {}, "seed": 5,
                                   "plant.measurement_noise": {"std": {"b": [0.002]}}})
    noise = prepare(scn).plant.measurement_noise
    assert noise.seed == 5 and noise.std.tolist() == [0.0, 0.002]
    v3 = noise(3)
    assert noise(0).shape == (2,) and v3[0] == 0.0 and v3[1] != 0.0
    assert noise(3).tobytes() == v3.tobytes() and noise(4)[1] != v3[1]  # the same at k whatever came before
    draws = np.array([noise(k)[1] for k in range(2000)])
    assert abs(draws.std() - 0.002) < 2e-4 and abs(draws.mean()) < 2e-4
    everywhere = prepare(load_scenario(FOURTANK, {"plant.measurement_noise": {"std": 0.01, "seed": 2}}))
    assert everywhere.plant.measurement_noise.std.tolist() == [0.01] * 4  # C the identity: p = n
    assert everywhere.plant.describe()["measurement_noise_seed"] == 2
    assert prepare(load_scenario(FOURTANK)).plant.measurement_noise is None


def test_continuous_time_keeps_c_through_the_discretisation():
    system = build_system(load_scenario(FOURTANK, {**LEVELS, "estimation": {}}))  # time: continuous, local-zoh
    assert [s.C.tolist() for s in system.subsystems] == [[[1.0, 0.0]], [[1.0, 0.0]]]
    assert system.p == 2 and system.ys(1) == slice(1, 2)
    assert np.array_equal(system.C, [[1, 0, 0, 0], [0, 0, 1, 0]])


def test_python_control_brings_c_with_estimation():
    control = pytest.importorskip("control")
    level = control.ss([[0.9, 0.1], [0.0, 0.8]], [[1.0], [0.5]], [[1.0, 0.0]], 0, True, states=["p", "q"],
                       inputs=["u"], outputs=["level"])
    data = small()
    for sub in data["subsystems"]:
        del sub["A"], sub["B"], sub["states"]
        sub["system"] = level
    without = dmpc.load_scenario(data)
    assert without.subsystems[0].C is None and without.subsystems[0].outputs is None  # C is not used
    scn = dmpc.load_scenario({**data, "estimation": {}, "setpoints": [{"at": 0, "subsystem": "a", "y": {"level": 0.2}}]})
    assert scn.subsystems[0].C == [[1.0, 0.0]] and scn.subsystems[0].outputs[0].name == "level"
    assert setpoint_entries(scn)[0].y.tolist() == [0.2]
    full = control.ss([[0.9, 0.1], [0.0, 0.8]], [[1.0], [0.5]], np.eye(2), 0, True)
    data["subsystems"][1]["system"] = full
    assert dmpc.load_scenario({**data, "estimation": {}}).subsystems[1].C is None  # the identity: left out


# ---------------------------------------------------------------------------- the command line
def test_validate_and_design_report_the_estimator(monkeypatch, capsys):
    code, out, err = call(monkeypatch, capsys, "validate", str(FOURTANK), *LEVELS_SET, "--set",
                          "estimation={disturbance: output}")
    assert code == 0, err
    assert "estimation: detectable (2 measured outputs, 2 disturbances" in out and "n + n_d = 6" in out
    code, out, err = call(monkeypatch, capsys, "design", str(FOURTANK), *LEVELS_SET, "--set",
                          "estimation={disturbance: output}", "--json")
    assert code == 0, err
    data = json.loads(out)["estimation"]
    assert data["coupled_radius"] == pytest.approx(0.980, abs=5e-4)
    assert set(data["subsystems"]) == {"a", "b"} and all(0 < s["radius"] < 1 for s in data["subsystems"].values())
    assert data["subsystems"]["a"] == {**data["subsystems"]["a"], "disturbance": "output", "outputs": 1,
                                       "disturbances": 1}
    assert [d["rank"] for d in data["detectability"]] == [3, 3, 6]
    code, out, err = call(monkeypatch, capsys, "design", str(FOURTANK), *LEVELS_SET, "--set", "estimation={}")
    assert code == 0, err
    assert "coupled spectral radius 0.980" in out and "own filter's spectral radius" in out
    code, out, _ = call(monkeypatch, capsys, "design", str(FOURTANK), "--json")
    assert "estimation" not in json.loads(out)


def test_an_undetectable_scenario_fails_at_validate_with_the_cores_message(tmp_path, monkeypatch, capsys):
    data = small(estimation={"disturbance": "output"})
    data["subsystems"][1]["A"] = [[1.0, 0.1], [0.0, 0.8]]  # an integrating mode: output disturbances cannot see it
    path = tmp_path / "integrator.yaml"
    path.write_text(yaml.safe_dump(data))
    code, _, err = call(monkeypatch, capsys, "validate", str(path))
    line = one_error_line(err)
    assert code == 2
    for words in ("estimation: subsystem b", "rank is 3 < 4", "eigenvalue 1 of A_bb", "use estimation.disturbance: input"):
        assert words in line, line
    data["estimation"] = {"disturbance": {"b": "input"}}
    path.write_text(yaml.safe_dump(data))
    code, out, err = call(monkeypatch, capsys, "validate", str(path))
    assert code == 0 and "estimation: detectable" in out, err


def test_a_bad_c_exits_2_with_one_line_through_a_real_process():
    res = run_cli("validate", str(FOURTANK), "--set", "subsystems[0].C=[[1, 0, 0]]", "--set", "estimation={}")
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert res.stderr.startswith("error: subsystems[0].C: expected 2 columns") and len(res.stderr.splitlines()) == 1
    res = run_cli("validate", str(FOURTANK), "--set", "subsystems[0].C=[[0, 1]]")
    assert res.returncode == 2 and "subsystems[0].C: measures only some of the states" in res.stderr


def test_the_identity_written_out_prepares_as_if_omitted():
    """C given as the identity, outputs named, no estimation: the same design digest, bundle and setpoints."""
    path = ROOT / "scenarios" / "paper.yaml"
    plain = prepare(load_scenario(path))
    names = [s.name for s in plain.system.subsystems]
    written = {f"subsystems[{i}].C": np.eye(s.n).tolist() for i, s in enumerate(plain.system.subsystems)}
    written.update({f"subsystems[{i}].outputs": [{"name": f"o{j}"} for j in range(s.n)]
                    for i, s in enumerate(plain.system.subsystems)})
    same = prepare(load_scenario(path, written))
    assert same.digest == plain.digest and same.estimator is None and names == same.names
    assert json.dumps(bundle_json(same), sort_keys=True) == json.dumps(bundle_json(plain), sort_keys=True)

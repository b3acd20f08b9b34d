"""The plant: disturbances, the tube against them, and your own plant function (in this process and the CLI)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import dmpc
from dmpc.plant.disturbance import DisturbanceSequence, gaussian_sequence, uniform_sequence
from dmpc.scenario import ScenarioError
from dmpc.setup.plant import function_reference, load_plant_function
from tests.helpers.user_plants import NONLINEARITY, fails_at_step_2, mildly_nonlinear

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "scenarios" / "paper.yaml"
CARTS = ROOT / "scenarios" / "carts-continuous.yaml"


def _example(name: str):
    """A module of examples/ (not a package), loaded from its file."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"examples_{name}", ROOT / "examples" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


tube_scenario = _example("disturbance_tube").scenario


def test_uniform_and_gaussian_sequences_are_seeded_bounded_and_prefix_stable():
    bound = np.array([0.0, 0.5, 2.0])
    w = uniform_sequence(bound, 400, seed=4)
    assert w.shape == (400, 3) and not w[:, 0].any()
    assert np.all(np.abs(w) <= bound) and np.abs(w[:, 2]).max() > 1.9
    np.testing.assert_array_equal(uniform_sequence(bound, 10, seed=4), w[:10])
    assert not np.array_equal(uniform_sequence(bound, 10, seed=5), w[:10])
    g = gaussian_sequence(np.array([1.0, 0.0]), 4000, seed=1)
    assert abs(g[:, 0].std() - 1.0) < 0.05 and not g[:, 1].any()
    seq = DisturbanceSequence(w[:2])
    np.testing.assert_array_equal(seq(1), w[1])
    assert not seq(2).any()


def _disturbed(kind: str, **fields) -> dmpc.Scenario:
    return dmpc.load_scenario(PAPER, steps=8, plant__disturbance={"kind": kind, **fields})


def test_a_uniform_disturbance_is_applied_recorded_and_the_same_for_the_same_seed(tmp_path):
    scn = _disturbed("uniform", bound={"2": [0.05, 0.1]}, seed=7)
    r = dmpc.simulate(scn, out=tmp_path / "w")
    w = np.load(tmp_path / "w" / "disturbance.npy")
    assert w.shape == (8, 8) and not w[:, :2].any() and not w[:, 4:].any()
    np.testing.assert_array_equal(r.w["2"], w[:, 2:4])
    assert np.all(np.abs(r.w["2"]) <= [0.05, 0.1])
    system = dmpc.design(scn)  # the plant's update: the nominal model plus w(k)
    from dmpc.scenario import build_system

    s = build_system(scn)
    np.testing.assert_allclose(r.stacked_x()[1:], r.stacked_x()[:-1] @ s.A.T + r.stacked_u() @ s.B.T + w,
                               rtol=0, atol=1e-12)
    assert r.summary["plant"]["disturbance"] == "uniform" and system.horizon == r.design.horizon
    again = dmpc.simulate(scn)
    np.testing.assert_array_equal(again.stacked_x(), r.stacked_x())
    other = dmpc.simulate(dmpc.load_scenario(scn, **{"plant.disturbance.seed": 8}))
    assert not np.array_equal(other.w["2"], r.w["2"])


def test_a_disturbance_file_is_read_from_the_scenarios_folder(tmp_path):
    w = np.zeros((8, 8))
    w[:, 1] = 0.01 * np.arange(8)
    np.save(tmp_path / "w.npy", w)
    np.savetxt(tmp_path / "w.csv", w, delimiter=",")
    text = PAPER.read_text() + "\nplant:\n  disturbance: {kind: file, file: w.npy}\n"
    (tmp_path / "paper-w.yaml").write_text(text)
    scn = dmpc.load_scenario(tmp_path / "paper-w.yaml", steps=8)
    assert scn.plant.disturbance.file == str(tmp_path / "w.npy")
    r = dmpc.simulate(scn)
    np.testing.assert_array_equal(r.w["1"], w[:, 0:2])
    from_csv = dmpc.simulate(dmpc.load_scenario(scn, **{"plant.disturbance.file": str(tmp_path / "w.csv")}))
    np.testing.assert_allclose(from_csv.stacked_x(), r.stacked_x(), rtol=0, atol=1e-12)
    with pytest.raises(ScenarioError, match=r"plant.disturbance.file: .* has 8 rows; the run needs 9"):
        dmpc.simulate(scn, steps=9)
    with pytest.raises(ScenarioError, match=r"plant.disturbance.bound: required when kind is 'uniform'"):
        dmpc.load_scenario(scn, **{"plant.disturbance.kind": "uniform"})
    with pytest.raises(ScenarioError, match=r"plant.disturbance.bound.9: unknown subsystem '9'"):
        _disturbed("uniform", bound={"9": [0.1, 0.1]})


def test_the_tube_keeps_the_constraints_under_the_same_bounded_disturbance():
    """Same seeded w on the carts with |v| <= 1.2: broken without the tube, held with it."""
    none = dmpc.simulate(tube_scenario(25, "none"))
    robust = dmpc.simulate(tube_scenario(25, "robust"))
    np.testing.assert_array_equal(none.w["2"], robust.w["2"])
    assert np.abs(none.w["2"][:, 1]).max() > 0.004
    worst_none = max(none.summary["state_bound_excess"].values())
    worst_robust = max(robust.summary["state_bound_excess"].values())
    assert worst_none > 1e-3 and none.verdict == "failed"
    assert "state-violated" in [f["kind"] for f in none.summary["failures"]]
    assert worst_robust <= 0 and robust.verdict == "ok" and robust.summary["fallbacks"] == 0
    # the velocity bound is active: the tube is what keeps it, not slack
    assert max(np.abs(robust.x[name][:, 1]).max() for name in robust.names) > 1.19


def test_the_tube_takes_a_bounded_disturbance_in():
    from dmpc.setup import prepare

    plain = prepare(tube_scenario(5, "robust").model_copy(update={"plant": dmpc.Scenario.model_fields["plant"]
                                                                 .default_factory()}))
    disturbed = prepare(tube_scenario(5, "robust"))
    for a, b in zip(plain.design.tightening, disturbed.design.tightening):
        assert np.all(b.state_margin >= a.state_margin) and np.all(b.state_margin[1:, 1] > a.state_margin[1:, 1])
        # one step: E(1) = W, whose support in the velocity direction grows by |w_v| <= 0.005 exactly
        assert b.state_margin[1, 1] - a.state_margin[1, 1] == pytest.approx(0.005, abs=1e-12)
        assert b.state_margin[1, 0] == a.state_margin[1, 0]  # no disturbance on the positions
        assert not (b.state_margin[0] - a.state_margin[0]).any()
        assert np.all(b.terminal_margin > a.terminal_margin)


def test_simulate_with_your_own_plant():
    scn = dmpc.load_scenario(PAPER, steps=10)
    linear = dmpc.simulate(scn)
    own = dmpc.simulate(scn, plant=mildly_nonlinear)
    assert own.summary["plant"] == {"model": "function", "function": "tests.helpers.user_plants:mildly_nonlinear"}
    from dmpc.scenario import build_system

    s = build_system(scn)
    x, u = own.stacked_x(), own.stacked_u()
    np.testing.assert_allclose(x[1:], x[:-1] @ s.A.T + u @ s.B.T + NONLINEARITY * np.sin(x[:-1]), rtol=0, atol=1e-12)
    assert np.abs(x - linear.stacked_x()).max() > 1e-3 and own.verdict == "ok"
    central = dmpc.simulate(scn, plant=mildly_nonlinear, method="centralized")
    np.testing.assert_allclose(central.stacked_x()[1], s.A @ x[0] + s.B @ central.stacked_u()[0]
                               + NONLINEARITY * np.sin(x[0]), atol=1e-12)


def test_an_error_in_your_plant_stops_the_run_with_your_traceback(tmp_path):
    with pytest.raises(dmpc.PlantModelError, match=r"the plant function .*fails_at_step_2 failed at step k = 2: "
                                                    r"ZeroDivisionError: a bug") as err:
        dmpc.simulate(PAPER, steps=5, plant=fails_at_step_2, out=tmp_path / "run")
    assert isinstance(err.value.__cause__, ZeroDivisionError)
    assert err.value.__cause__.__traceback__.tb_next.tb_frame.f_code.co_name == "fails_at_step_2"
    assert len((tmp_path / "run" / "steps.jsonl").read_text().splitlines()) == 2
    with pytest.raises(dmpc.PlantModelError, match="it returned 3 numbers, the state has 8"):
        dmpc.simulate(PAPER, steps=2, plant=lambda x, u, k: x[:3])


def test_plant_functions_are_found_by_reference():
    assert function_reference(mildly_nonlinear) == "tests.helpers.user_plants:mildly_nonlinear"
    with pytest.raises(ValueError, match="cannot be imported by another process"):
        function_reference(lambda x, u, k: x)

    def local(x, u, k):
        return x

    with pytest.raises(ValueError, match="inside a function"):
        function_reference(local)
    assert load_plant_function("tests.helpers.user_plants:mildly_nonlinear")[0] is mildly_nonlinear
    by_file, _ = load_plant_function(f"{ROOT / 'examples' / 'plants.py'}:carts_stiffening_springs")
    assert by_file(np.zeros(6), np.ones(3), 0).shape == (6,)
    for bad, why in (("nocolon", "expected module:function"), ("tests.helpers.user_plants:nothing", "has no nothing"),
                     ("no_such_module_here:f", "cannot import"), ("tests.helpers.user_plants:NONLINEARITY",
                                                                  "not a function")):
        with pytest.raises(ValueError, match=why):
            load_plant_function(bad)


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dmpc.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)


def test_the_command_line_takes_a_plant_function_and_reports_its_errors(tmp_path):
    ok = _cli("simulate", str(PAPER), "--steps", "4", "--quiet", "--out", str(tmp_path / "a"),
              "--model", "tests.helpers.user_plants:mildly_nonlinear")
    assert ok.returncode == 0, ok.stderr
    assert dmpc.load_run(tmp_path / "a").summary["plant"]["function"] == "tests.helpers.user_plants:mildly_nonlinear"
    bad = _cli("simulate", str(PAPER), "--steps", "4", "--quiet", "--out", str(tmp_path / "b"),
               "--model", "tests/helpers/user_plants.py:fails_at_step_2")
    assert bad.returncode == 1
    assert "Traceback" in bad.stderr and 'in fails_at_step_2\n    raise ZeroDivisionError' in bad.stderr
    assert bad.stderr.strip().splitlines()[-1].startswith("error: the plant function "
                                                          "tests/helpers/user_plants.py:fails_at_step_2 failed at "
                                                          "step k = 2: ZeroDivisionError")
    missing = _cli("plant", str(PAPER), "--out", str(tmp_path / "c"), "--model", "tests.helpers.user_plants:nope")
    assert missing.returncode == 2 and "has no nope" in missing.stderr
    scenario_cannot = _cli("validate", str(PAPER), "--set", "plant.model=tests.helpers.user_plants:mildly_nonlinear")
    assert scenario_cannot.returncode == 2 and "plant.model" in scenario_cannot.stderr

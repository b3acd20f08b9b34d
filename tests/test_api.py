"""The Python API: dmpc.load_scenario, design, simulate, load_run and the Result."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

import dmpc
from dmpc.scenario import ScenarioError

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "scenarios" / "paper.yaml"
CARTS = ROOT / "scenarios" / "carts-continuous.yaml"


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory):
    """dmpc.simulate of the paper's example, 12 steps, into a kept run folder."""
    out = tmp_path_factory.mktemp("api") / "paper"
    return dmpc.simulate(dmpc.load_scenario(PAPER, steps=12), out=out)


def test_public_names_and_a_light_import():
    for name in dmpc.__all__:
        assert getattr(dmpc, name) is not None, name
    assert dmpc.Scenario is __import__("dmpc.scenario").scenario.Scenario
    assert callable(dmpc.design) and dmpc.design.__doc__
    from dmpc.offline import DesignError  # the offline design's package: no function hides it

    assert dmpc.DesignError is DesignError and issubclass(DesignError, dmpc.DmpcError)
    assert all(issubclass(getattr(dmpc, name), dmpc.DmpcError) for name in ("PlantModelError", "RunError", "ScenarioError"))
    code = "import sys, dmpc; print('pydantic' in sys.modules, 'matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]


def test_load_scenario_from_a_file_a_mapping_of_arrays_and_a_scenario():
    from_file = dmpc.load_scenario(PAPER, steps=7, options__method="centralized", **{"terminal.beta0": 0.4})
    assert (from_file.steps, from_file.options.method, from_file.terminal.beta0) == (7, "centralized", 0.4)
    raw = yaml.safe_load(PAPER.read_text())
    for sub in raw["subsystems"]:
        for key in ("A", "B", "Q", "R", "K", "P"):
            sub[key] = np.array(sub[key])
    from_arrays = dmpc.load_scenario(raw)
    assert from_arrays == dmpc.load_scenario(PAPER)
    again = dmpc.load_scenario(from_arrays, steps=3)
    assert again.steps == 3 and again.subsystems == from_arrays.subsystems
    assert dmpc.load_scenario(from_arrays) is from_arrays
    with pytest.raises(ScenarioError, match=r"^subsystems\[0\]\.states: expected 2 entries"):
        dmpc.load_scenario(raw, **{"subsystems[0].states": [{"name": "p", "unit": "m"}]})


def test_design_is_design_json(tmp_path):
    design = dmpc.design(PAPER)
    out = subprocess.run([sys.executable, "-m", "dmpc.cli", "design", str(PAPER), "--json"], cwd=ROOT,
                         capture_output=True, text=True, check=True).stdout
    cli = json.loads(out)
    assert design.json["digest"] == cli["digest"]
    assert design.json == cli
    assert design.names == ("1", "2", "3", "4") and design.horizon == cli["horizon"] == 10
    np.testing.assert_array_equal(design.K["2"], np.array(cli["K"][1]))
    assert design.K["2"].shape == (1, 2) and design.P["4"].shape == (2, 2)
    assert design.sigma0 == pytest.approx(design.sigma(np.zeros(8)))
    assert design.rho < 1 and design.lyapunov_margin <= design.lyapunov_tolerance
    assert "horizon N" in design.table() and design.model is None


def test_simulate_gives_names_shapes_and_the_run_folders_numbers(paper_run):
    r = paper_run
    assert r.names == ("1", "2", "3", "4") and r.steps == 12 and r.verdict == "ok"
    assert r.dt is None and r.time_label == "step k"
    np.testing.assert_array_equal(r.t, np.arange(13))
    for name in r.names:
        assert r.x[name].shape == (13, 2) and r.u[name].shape == (12, 1) and r.alpha[name].shape == (13, 2)
        assert not r.w[name].any()
    with np.load(r.folder / "trajectory.npz") as data:
        np.testing.assert_array_equal(r.stacked_x(), data["x"])
        np.testing.assert_array_equal(r.stacked_u(), data["u"])
        assert list(data["names"]) == list(r.names)
        assert list(data["state_sizes"]) == [2] * 4 and list(data["input_sizes"]) == [1] * 4
    summary = json.loads((r.folder / "summary.json").read_text())
    assert r.cost == summary["closed_loop_cost"] and r.summary == summary
    np.testing.assert_array_equal(r.J, summary["J"])
    assert r.beta.shape == (13,) and r.design.digest == summary["design_digest"]
    assert r.states["1"][0].name == "x1" and r.inputs["1"][0].upper == 2.5


def test_simulate_prints_nothing_and_keeps_no_folder_by_default(capfd):
    r = dmpc.simulate(PAPER, steps=3)
    captured = capfd.readouterr()
    assert captured.out == "" and captured.err == ""
    assert r.folder is None and r.steps == 3
    other = dmpc.simulate(PAPER, steps=3, method="centralized")
    assert other.method == "centralized" and np.isnan(other.beta).all()


def test_load_run_round_trips(paper_run):
    again = dmpc.load_run(paper_run.folder)
    assert again.names == paper_run.names and again.verdict == paper_run.verdict and again.cost == paper_run.cost
    for name in again.names:
        for field in ("x", "u", "w", "alpha"):
            np.testing.assert_array_equal(getattr(again, field)[name], getattr(paper_run, field)[name])
    np.testing.assert_array_equal(again.beta, paper_run.beta)
    assert again.design.json == paper_run.design.json


def test_old_run_folders_still_load(paper_run, tmp_path):
    """A trajectory.npz without names and sizes is split by scenario.yaml, or without it by design.json."""
    old = tmp_path / "old"
    old.mkdir()
    for name in ("summary.json", "design.json", "scenario.yaml"):
        (old / name).write_bytes((paper_run.folder / name).read_bytes())
    with np.load(paper_run.folder / "trajectory.npz") as data:
        kept = {k: data[k] for k in data.files if k not in ("names", "state_sizes", "input_sizes")}
    np.savez(old / "trajectory.npz", **kept)
    loaded = dmpc.load_run(old)
    np.testing.assert_array_equal(loaded.x["3"], paper_run.x["3"])
    (old / "scenario.yaml").unlink()
    bare = dmpc.load_run(old)
    assert bare.names == ("1", "2", "3", "4")
    np.testing.assert_array_equal(bare.u["4"], paper_run.u["4"])
    with pytest.raises(ValueError, match="not a finished run folder"):
        dmpc.load_run(tmp_path)


def test_names_units_seconds_and_bounds_reach_the_table_and_the_figures():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = dmpc.simulate(CARTS, steps=15)
    np.testing.assert_allclose(r.t, np.arange(16) * 0.1)
    assert [q.label for q in r.states["2"]] == ["p [m]", "v [m/s]"]
    assert r.inputs["3"][0].label == "u [m/s^2]" and r.states["1"][1].upper == 3.0
    table = r.table()
    assert "v [m/s]" in table and "[-5, 5]" in table
    figures = r.plot()
    try:
        assert sorted(figures) == ["cost", "inputs", "states"]
        axes = [ax for ax in figures["states"].axes if ax.get_visible()]
        assert len(axes) == 6 and axes[1].get_ylabel() == "v [m/s]" and axes[-1].get_xlabel() == "t [s]"
        dashed = {round(line.get_ydata()[0], 6) for line in axes[1].lines if line.get_linestyle() == "--"
                  and len(line.get_ydata())}
        assert dashed == {-3.0, 3.0}
        inputs = [ax for ax in figures["inputs"].axes if ax.get_visible()]
        assert {round(line.get_ydata()[0], 6) for line in inputs[0].lines if line.get_linestyle() == "--"
                and len(line.get_ydata())} == {-1.0, 1.0}
        assert figures["cost"].axes[0].get_xlabel() == "t [s]"
        none = r.plot(bounds=False)
        assert not [line for line in none["states"].axes[1].lines if line.get_linestyle() == "--"]
    finally:
        plt.close("all")


def test_every_error_class_of_dmpc_is_a_dmpc_error():
    """One base for the errors dmpc raises on purpose (the setpoint targets' work in progress aside)."""
    import importlib
    import inspect

    from dmpc.core.errors import DmpcError, InputError
    from tests.test_layering import modules_of, package_dirs

    found = {}
    for name in modules_of(package_dirs()):
        if name.startswith("dmpc.tracking") or name.endswith(".__main__"):  # __main__ runs the command
            continue
        module = importlib.import_module(name)
        for cls_name, cls in inspect.getmembers(module, inspect.isclass):
            if issubclass(cls, BaseException) and cls.__module__ == name:
                found[f"{name}.{cls_name}"] = cls
    assert len(found) >= 20
    assert [name for name, cls in found.items() if not issubclass(cls, DmpcError)] == []
    bad_input = {name.rpartition(".")[2] for name, cls in found.items() if issubclass(cls, InputError)}
    assert {"ScenarioError", "DesignError", "RunFolderError", "RunFolderNotReadable", "ReportError"} <= bad_input
    assert not {"RecordWriteError", "RunError", "PlantModelError", "BusError"} & bad_input

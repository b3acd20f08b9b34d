"""dmpc.run from Python: the same Result as dmpc.simulate, your own plant in the plant process, cleanup."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import dmpc
from dmpc.runtime import launcher
from tests.e2e_helpers import pid_alive
from tests.helpers.user_plants import fails_at_step_2, mildly_nonlinear

pytestmark = pytest.mark.e2e

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "scenarios" / "paper.yaml"


def _same(a: dmpc.Result, b: dmpc.Result) -> None:
    assert a.names == b.names and a.steps == b.steps and a.verdict == b.verdict
    for name in a.names:
        np.testing.assert_allclose(a.x[name], b.x[name], rtol=0, atol=1e-9)
        np.testing.assert_allclose(a.u[name], b.u[name], rtol=0, atol=1e-9)
        np.testing.assert_allclose(a.alpha[name], b.alpha[name], rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.beta, b.beta, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.J, b.J, rtol=0, atol=1e-9)
    assert a.cost == pytest.approx(b.cost, abs=1e-9)


def test_run_gives_the_result_of_simulate_and_load_run_round_trips(tmp_path):
    scn = dmpc.load_scenario(PAPER, steps=10)
    simulated = dmpc.simulate(scn, out=tmp_path / "sim")
    ran = dmpc.run(scn, out=tmp_path / "run")
    assert ran.summary["runtime"] != simulated.summary["runtime"]
    _same(ran, simulated)
    _same(dmpc.load_run(tmp_path / "run"), ran)
    _same(dmpc.load_run(tmp_path / "sim"), simulated)
    pids = json.loads((tmp_path / "run" / "processes.json").read_text())
    assert len(pids) == 5 and not any(pid_alive(pid) for pid in pids.values())


def test_your_own_plant_runs_in_the_plant_process():
    scn = dmpc.load_scenario(PAPER, steps=8)
    ran = dmpc.run(scn, plant=mildly_nonlinear)
    assert ran.summary["plant"]["function"] == "tests.helpers.user_plants:mildly_nonlinear"
    _same(ran, dmpc.simulate(scn, plant=mildly_nonlinear))
    assert np.abs(ran.stacked_x() - dmpc.simulate(scn).stacked_x()).max() > 1e-3


def test_an_error_in_your_plant_stops_the_run_and_shows_its_traceback(tmp_path):
    with pytest.raises(dmpc.PlantModelError, match=r"(?s)plant process.*in fails_at_step_2.*ZeroDivisionError"):
        dmpc.run(PAPER, steps=6, plant=fails_at_step_2, out=tmp_path / "run")
    pids = json.loads((tmp_path / "run" / "processes.json").read_text())
    assert not any(pid_alive(pid) for pid in pids.values())
    with pytest.raises(ValueError, match="cannot be imported by another process"):
        dmpc.run(PAPER, steps=2, plant=lambda x, u, k: x)


def test_ctrl_c_stops_every_process(tmp_path, monkeypatch):
    update = launcher.StepCounter.update

    def interrupted(self):
        count = update(self)
        if count >= 2:
            raise KeyboardInterrupt
        return count

    monkeypatch.setattr(launcher.StepCounter, "update", interrupted)
    with pytest.raises(KeyboardInterrupt):
        dmpc.run(PAPER, steps=200, out=tmp_path / "run")
    pids = json.loads((tmp_path / "run" / "processes.json").read_text())
    assert not any(pid_alive(pid) for pid in pids.values())
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert 2 <= summary["steps"] < 200

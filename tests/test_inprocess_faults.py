"""In-process runs on the in-memory bus: determinism, delays, losses, a lost agent."""
from __future__ import annotations

import numpy as np
import pytest

from dmpc.bus import keys
from dmpc.bus.faults import FaultPlan, FaultyBus, LinkFault
from dmpc.records.run_folder import summarise, trajectory_arrays
from dmpc.runtime.inprocess import build_run, simulate
from dmpc.runtime.setup import prepare
from dmpc.scenario import load_scenario


def run(overrides=None, bus_for=None):
    prepared = prepare(load_scenario("scenarios/paper.yaml", overrides or {}))
    records = []
    result = simulate(prepared, records.append, bus_for=bus_for)
    arrays = trajectory_arrays(prepared.system, records)
    return prepared, result, arrays, summarise(prepared.system, records, arrays)


@pytest.fixture(scope="module")
def clean():
    return run()


def test_two_clean_runs_identical(clean):
    _, _, again, _ = run()
    assert np.array_equal(clean[2]["x"], again["x"])
    assert np.array_equal(clean[2]["u"], again["u"])


def test_delay_shorter_than_deadline_changes_nothing(clean):
    _, _, arrays, summary = run({"faults.delay_ms": 2.0, "faults.jitter_ms": 1.0, "seed": 7})
    assert summary["fallbacks"] == 0
    assert np.abs(arrays["x"] - clean[2]["x"]).max() <= 1e-12


def test_loss_in_realtime_falls_back_and_converges():
    prepared, _, arrays, summary = run({"faults.loss": 0.2, "options.mode": "realtime", "options.deadline": 0.05,
                                        "seed": 3})
    assert summary["fallbacks"] > 0
    assert summary["input_bound_excess"] <= 1e-7
    assert summary["final_state_norm_inf"] < 1e-3
    # fallbacks are counted per agent and step and add up
    assert sum(summary["fallbacks_per_agent"].values()) == summary["fallbacks"]
    assert len(summary["fallback_steps"]) == summary["fallbacks"]


def test_loss_is_reproducible_from_the_seed():
    overrides = {"faults.loss": 0.3, "options.mode": "realtime", "options.deadline": 0.05, "seed": 11}
    _, _, a, sa = run(overrides)
    _, _, b, sb = run(overrides)
    assert sa["fallback_steps"] == sb["fallback_steps"]
    assert np.array_equal(a["x"], b["x"])


def test_per_link_loss_only_hits_that_agent():
    plan = FaultPlan(links=(("2", "plant", LinkFault(loss=0.5)),), seed=0)
    _, _, arrays, summary = run({"options.mode": "realtime", "options.deadline": 0.05},
                                bus_for=lambda bus, name: FaultyBus(bus, name, plan))
    assert summary["steps"] == 30
    assert summary["fallbacks_per_agent"]["2"] > 0
    assert all(summary["fallbacks_per_agent"][n] == 0 for n in ("1", "3", "4"))
    assert summary["input_bound_excess"] <= 1e-7


def test_lost_agent_gets_fallback_every_step_and_run_completes():
    prepared = prepare(load_scenario("scenarios/paper.yaml"))
    records = []
    runner = build_run(prepared, records.append)
    runner.bus.run(until=lambda: len(records) >= 5)
    runner.bus.drop_alive(keys.alive("local", keys.agent_role("2")))
    # a lost agent stops answering: silence it by stopping its node
    runner.agents[1].stopped = True
    runner.bus.run(until=lambda: runner.plant.finished)
    arrays = trajectory_arrays(prepared.system, records)
    summary = summarise(prepared.system, records, arrays)
    assert summary["steps"] == prepared.protocol.steps
    fb = arrays["fallback"]
    assert not fb[:5].any()
    assert fb[6:, 1].all() and not fb[:, [0, 2, 3]].any()
    assert summary["input_bound_excess"] <= 1e-7
    assert summary["final_state_norm_inf"] < 1e-2


def test_dead_link_fails_startup_instead_of_hanging():
    plan = FaultPlan(links=(("2", "plant", LinkFault(loss=1.0)),), seed=0)
    _, result, _, summary = run(bus_for=lambda bus, name: FaultyBus(bus, name, plan))
    assert summary["steps"] == 0
    assert "2" in result.plant.failure and "not ready" in result.plant.failure

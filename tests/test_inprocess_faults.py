"""In-process runs on the in-memory bus: determinism, delays, losses, a lost agent, inputs outside U_i."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from dmpc.bus import keys
from dmpc.bus.codec import decode, encode
from dmpc.bus.faults import FaultPlan, FaultyBus, LinkFault
from dmpc.bus.interface import Bus
from dmpc.bus.messages import PlanMessage
from dmpc.records.run_folder import summarise, trajectory_arrays
from dmpc.records.session import RunRecorder
from dmpc.runtime import inprocess
from dmpc.runtime.inprocess import build_run, simulate
from dmpc.scenario import load_scenario
from dmpc.setup import prepare


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
    # ||x(30)||_inf is 2.5e-7, as in the clean run (2.4e-7 to 3.2e-7 over seeds 0-19): a fallback
    # applies the shifted plan with its state feedback. Without the feedback (the plan's input
    # alone), with K_i x_i in place of the plan, or with the plan's first input unshifted, the
    # same run ends at 1.7e-6, 1.4e-6 and 2.9e-6.
    assert summary["final_state_norm_inf"] < 1e-6
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
    runner.bus.run(until=lambda: runner.coordinator.finished)
    arrays = trajectory_arrays(prepared.system, records)
    summary = summarise(prepared.system, records, arrays)
    assert summary["steps"] == prepared.protocol.steps
    fb = arrays["fallback"]
    assert not fb[:5].any()
    assert fb[6:, 1].all() and not fb[:, [0, 2, 3]].any()
    assert summary["input_bound_excess"] <= 1e-7
    # 1.5e-6 with agent 2's shifted plan applied for 24 steps; K_2 x_2 in its place ends at 5.1e-6,
    # the plan's first input unshifted at 0.2, its inputs without state feedback at 2.7
    assert summary["final_state_norm_inf"] < 4e-6


def test_dead_link_fails_startup_instead_of_hanging():
    plan = FaultPlan(links=(("2", "plant", LinkFault(loss=1.0)),), seed=0)
    _, result, _, summary = run(bus_for=lambda bus, name: FaultyBus(bus, name, plan))
    assert summary["steps"] == 0
    assert "2" in result.coordinator.failure and "not ready" in result.coordinator.failure


class OutOfBoundsPlans(Bus):
    """Agent ``name``'s view of the bus: its plans of the given steps leave U_i (v(k) = ``value``).

    Every subscriber gets the tampered plan, as from a compromised agent."""

    def __init__(self, bus: Bus, steps: set[int], value: float) -> None:
        self.bus, self.steps, self.value = bus, steps, value

    def publish(self, key: str, payload: bytes) -> None:
        msg = decode(payload)
        if isinstance(msg, PlanMessage) and msg.k in self.steps and msg.status == "solved":
            v = msg.v.copy()
            v[0] = self.value
            payload = encode(dataclasses.replace(msg, v=v))
        self.bus.publish(key, payload)

    def subscribe(self, key, handler, hot=False):
        self.bus.subscribe(key, handler, hot)

    def declare_alive(self, key):
        self.bus.declare_alive(key)

    def watch_alive(self, pattern, handler):
        self.bus.watch_alive(pattern, handler)

    def now(self):
        return self.bus.now()

    def call_later(self, delay, fn):
        return self.bus.call_later(delay, fn)

    def run(self, until, timeout=None):
        return self.bus.run(until, timeout)

    def close(self):
        self.bus.close()


def test_plans_outside_U_i_are_refused_counted_and_fall_back(tmp_path, monkeypatch):
    """Agent 2 sends v(k) = 40 (U_2 = [-2.5, 2.5]) at steps 3 and 7: the plant applies its
    fallback instead, inside U_2, counts the refusals in summary.json, and the run completes."""
    prepared = prepare(load_scenario("scenarios/paper.yaml"))
    tamper = lambda bus, name: OutOfBoundsPlans(bus, {3, 7}, 40.0) if name == "2" else bus
    monkeypatch.setattr(inprocess, "simulate",
                        lambda prepared, on_step: simulate(prepared, on_step, bus_for=tamper))
    with RunRecorder(tmp_path / "run", prepared, show_progress=False) as recorder:
        summary, failure = inprocess.record_run(prepared, recorder)
    assert failure == ""
    assert summary["steps"] == prepared.protocol.steps
    assert summary["inputs_refused"] == {"2": 2}
    assert summary["fallback_steps"] == [[3, "2"], [7, "2"]]
    assert summary["input_bound_excess"] <= 1e-7 and summary["max_abs_u"] <= 2.5 + 1e-7
    steps = [json.loads(line) for line in (tmp_path / "run" / "steps.jsonl").read_text().splitlines()]
    assert [s["fallback_reason"][1] for s in steps if s["k"] in (3, 7)] == ["input outside U_i"] * 2
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["inputs_refused"] == {"2": 2}
    assert summary["final_state_norm_inf"] < 1e-6  # 2.5e-7, as in the clean run


def test_a_fault_plan_reads_back_from_its_json_as_the_same_plan():
    plan = FaultPlan(default=LinkFault(delay_ms=2.0, jitter_ms=0.5), seed=7,
                     links=(("2", "plant", LinkFault(loss=0.25)), ("plant", "3", LinkFault(delay_ms=10.0))))
    again = FaultPlan.from_json(json.loads(json.dumps(plan.to_json())))
    assert again == plan and again.link("2", "plant").loss == 0.25 and again.link("1", "plant") == plan.default
    with pytest.raises(TypeError):
        FaultPlan.from_json({**plan.to_json(), "default": {"delay": 1.0}})


def test_the_in_process_nodes_are_built_as_the_processes_build_theirs():
    """One construction of the coordinator and the agents from a prepared run: in this process
    as in `dmpc plant` and `dmpc agent`, down to the scenario name their design checks quote."""
    prepared = prepare(load_scenario("scenarios/paper.yaml"))
    built = build_run(prepared, lambda record: None)
    assert built.coordinator.scenario == prepared.name == "paper"
    assert [agent.scenario for agent in built.agents] == ["paper"] * 4
    assert built.coordinator.deadline == prepared.deadline and built.coordinator.mode == prepared.mode

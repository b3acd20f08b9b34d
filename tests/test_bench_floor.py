"""The bus floor of the benchmark: a bare lockstep loop over Zenoh that mirrors a run."""
from __future__ import annotations

import pytest

from dmpc.bench.floor import FloorSpec, measure
from dmpc.bench.measures import floor_spec
from dmpc.bus.codec import encode
from dmpc.bus.messages import Release
from dmpc.scenario import load_scenario
from dmpc.setup import prepare


def test_floor_spec_mirrors_the_run():
    spec = floor_spec(4, 50, 60.0)
    assert (spec.M, spec.steps, spec.compute_us, spec.topology) == (4, 50, 60.0, "mesh")
    assert spec.neighbours == [[1], [0, 2], [1, 3], [2]]  # the paper's chain
    system = prepare(load_scenario("scenarios/paper.yaml")).system
    import numpy as np

    release = Release(run="paper-0123abcd", k=50, round=0, x=np.ones(system.n), centres=np.ones(system.n),
                      sizes=np.ones(4), assumed=np.full((4, 2), 50))
    assert spec.release_bytes == len(encode(release))
    assert 300 < spec.plan_bytes < 1000


@pytest.mark.e2e
def test_floor_loop_runs_and_reports_its_steps():
    result = measure(FloorSpec(M=2, steps=40, neighbours=[[1], [0]], release_bytes=300, plan_bytes=400,
                               compute_us=50.0, warmup=5), timeout=120)
    assert result["completed"], result
    assert result["steps"] == 40
    assert 0.05 < result["step_ms_p50"] <= result["step_ms_p99"]

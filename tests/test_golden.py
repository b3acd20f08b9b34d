"""Every shipped scenario, without setpoints, gives the trajectory it gave before setpoints existed.

tests/data/golden/<scenario>.npz holds x, u, J and beta of ``dmpc.simulate`` of each scenario (the
default method) as computed by the release before setpoint tracking; the tracking path must leave a
run that requests nothing exactly as it was. The tolerance is a few units in the last place of
the largest entry, for a different CPU's rounding; a change of the algorithm moves them by far more.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import dmpc

ROOT = Path(__file__).resolve().parents[1]
GOLDEN = ROOT / "tests" / "data" / "golden"
SCENARIOS = sorted(p.stem for p in GOLDEN.glob("*.npz"))


def test_every_shipped_scenario_has_a_golden_trajectory():
    assert SCENARIOS == sorted(p.stem for p in (ROOT / "scenarios").glob("*.yaml"))


@pytest.mark.parametrize("name", SCENARIOS)
def test_without_setpoints_the_trajectory_is_the_one_from_before(name):
    golden = np.load(GOLDEN / f"{name}.npz")
    steps = golden["u"].shape[0]  # the scenario's steps then (the rooms ran 12 h before their day of setpoints)
    scenario = dmpc.load_scenario(ROOT / "scenarios" / f"{name}.yaml", setpoints=[], steps=steps)
    result = dmpc.simulate(scenario)
    for key, value in (("x", result.stacked_x()), ("u", result.stacked_u()), ("J", result.J), ("beta", result.beta)):
        expected = golden[key]
        assert value.shape == expected.shape, key
        scale = max(float(np.nanmax(np.abs(expected))), 1.0)
        np.testing.assert_allclose(value, expected, rtol=0, atol=1e-13 * scale, err_msg=f"{name}: {key}")

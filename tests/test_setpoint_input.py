"""Bad setpoint entries in a scenario: one line naming the entry at fault, exit code 2, nothing run."""
from __future__ import annotations

import math

import pytest

from dmpc.scenario import ScenarioError, load_scenario
from tests.e2e_helpers import run_cli
from tests.helpers.reference import PAPER, ROOT

ROOMS = ROOT / "scenarios" / "rooms.yaml"

CASES = [
    (PAPER, {}, [{"at": 0, "subsystem": "1", "x": [1.0]}], ["setpoints[0].x:", "expected 2 entries", "got 1"]),
    (PAPER, {}, [{"at": 0, "subsystem": "9", "x": [1.0, None]}], ["setpoints[0].subsystem:", "unknown subsystem '9'"]),
    (PAPER, {}, [{"at": 0, "subsystem": "1", "u": [3.0]}], ["setpoints[0].u[0]:", "outside U_i [-2.5, 2.5]"]),
    (PAPER, {}, [{"at": 0, "subsystem": "1", "x": [math.nan, None]}], ["setpoints[0].x[0]:", "NaN"]),
    (PAPER, {}, [{"at": 0, "subsystem": "1", "x": [math.inf, None]}], ["setpoints[0].x[0]:", "finite"]),
    (PAPER, {}, [{"at": 1.5, "subsystem": "1", "x": [1.0, None]}], ["setpoints[0].at:", "whole step"]),
    (PAPER, {}, [{"at": -1, "subsystem": "1", "x": [1.0, None]}], ["setpoints[0].at:", ">= 0"]),
    (PAPER, {}, [{"at": 0, "subsystem": "1", "x": {"Ta": 1.0}}], ["setpoints[0].x:", "'states'"]),
    (PAPER, {}, [{"at": 0, "subsystem": "1", "x": [1.0, None], "w": 2}], ["setpoints[0].w:", "unknown field"]),
    (PAPER, {}, [{"at": 0, "subsystem": "1", "y": 2}], ["setpoints[0].y:", "a list of numbers and nulls"]),
    (PAPER, {"options.method": "ellipsoid"}, [{"at": 0, "subsystem": "1", "x": [1.0, None]}],
     ["setpoints:", "'ellipsoid' does not track setpoints"]),
    (ROOMS, {}, [{"at": 0, "subsystem": "room1", "x": {"Tx": 1.0}}], ["setpoints[0].x.Tx:", "has no state 'Tx'", "Ta, Tm"]),
    (ROOMS, {}, [{"at": 0, "subsystem": "room1", "x": {"Ta": 3.5}}], ["setpoints[0].x[0]:", "(Ta [K])", "outside X_i"]),
]


@pytest.mark.parametrize("path, extra, setpoints, words", CASES)
def test_a_bad_entry_is_named(path, extra, setpoints, words):
    with pytest.raises(ScenarioError) as info:
        load_scenario(path, {**extra, "setpoints": setpoints})
    message = str(info.value)
    assert "\n" not in message
    for word in words:
        assert word in message, message


def test_the_command_line_refuses_it_with_exit_2_and_one_line(tmp_path):
    res = run_cli("simulate", "scenarios/paper.yaml", "--out", str(tmp_path / "run"), "--set",
                  'setpoints=[{at: 0, subsystem: "1", u: [3.0]}]')
    assert res.returncode == 2
    assert res.stderr.count("\n") == 1 and "setpoints[0].u[0]:" in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "run").exists()


def test_entries_in_seconds_take_effect_at_the_first_step_at_or_after_them():
    from dmpc.scenario import setpoint_entries

    scenario = load_scenario(ROOMS, {"setpoints": [{"at": 0, "subsystem": "room2", "x": {"Tm": 0.5}},
                                                   {"at": 600, "subsystem": "room1", "x": [-1.0, None]},
                                                   {"at": 601, "subsystem": "room1", "x": [-0.5, None]}]})
    entries = setpoint_entries(scenario)
    assert [(e.at, e.index) for e in entries] == [(0, 1), (2, 0), (3, 0)]  # dt = 300 s
    assert math.isnan(entries[0].x[0]) and entries[0].x[1] == 0.5

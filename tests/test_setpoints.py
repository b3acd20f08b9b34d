"""Setpoints on the paper's example, in one process (docs/algorithm.md, "Setpoints"): tracking with
the guarantees kept, unreachable requests, large jumps through the reference governor, and a run
without setpoints unchanged. Every figure is recomputed here from the recorded arrays and the
hand-built matrices of tests/helpers/reference.py."""
from __future__ import annotations

import json

import numpy as np
import pytest

import dmpc
from dmpc.scenario import build_system, load_scenario
from dmpc.setup import prepare
from dmpc.tracking.targets import Request, TargetSpace
from tests.helpers.reference import PAPER, U_BAR, chain_matrices

A, B = chain_matrices(4)
NAMES = ("1", "2", "3", "4")
PAPER_SYSTEM = build_system(load_scenario(PAPER))


def setpoint_run(setpoints, steps, out=None):
    return dmpc.simulate(dmpc.load_scenario(PAPER, steps=steps, setpoints=setpoints), out=out)


def stacked(result, field):
    return np.hstack([getattr(result, field)[name] for name in NAMES])


@pytest.fixture(scope="module")
def schedule():
    """x_11 = 1.0 from k = 0, -0.5 from k = 40, 80 steps."""
    return setpoint_run([{"at": 0, "subsystem": "1", "x": [1.0, None]},
                         {"at": 40, "subsystem": 1, "x": [-0.5, None]}], 80)


@pytest.fixture(scope="module")
def jump(tmp_path_factory):
    """x_11 = 1.0, then 18.0 from k = 40: the jump leaves the shifted candidates infeasible."""
    return setpoint_run([{"at": 0, "subsystem": "1", "x": [1.0, None]},
                         {"at": 40, "subsystem": "1", "x": [18.0, None]}], 110,
                        out=tmp_path_factory.mktemp("jump") / "run")


def check_guarantees(result):
    """No fallback, every QP solved, every bound held, every target a steady state, and the cost
    non-increasing while the applied target stays."""
    s = result.summary
    assert result.verdict == "ok", s["failures"]
    assert s["fallbacks"] == 0 and s["qp_failed"] == 0 and s["feasible"]
    assert np.abs(result.stacked_u()).max() <= U_BAR + 1e-7
    for field in ("target", "reference"):
        xs, us = stacked(result, field), np.hstack([getattr(result, field + "_u")[n] for n in NAMES])
        assert np.abs(xs @ A.T + us @ B.T - xs).max() < 1e-9, field
        assert np.abs(us).max() <= U_BAR * 0.95 + 1e-9, field  # the margin kept from U
    targets = np.hstack([stacked(result, "target"), np.hstack([result.target_u[n] for n in NAMES])])
    steady = np.all(targets[1:] == targets[:-1], axis=1)
    assert np.all(np.diff(result.J)[steady] <= 1e-6)
    assert s["J_non_increasing"]


def test_a_schedule_is_tracked_with_the_guarantees_kept(schedule):
    check_guarantees(schedule)
    x11 = schedule.x["1"][:, 0]
    assert abs(x11[40] - 1.0) < 1e-4  # x(40): the last state before the change takes effect
    assert abs(x11[80] + 0.5) < 1e-4
    x = schedule.stacked_x()
    assert np.linalg.norm(x[-1] - x[-2]) < 1e-6  # a steady state of the coupled system
    assert np.abs(x[-1] - stacked(schedule, "target")[-1]).max() < 1e-6
    assert not [w for w in schedule.summary["warnings"] if w["kind"] in ("not-converged", "setpoint-unreachable")]
    tracked = schedule.summary["tracking"]["components"]
    assert [(c["subsystem"], c["component"], c["asked"]) for c in tracked] == [("1", "x1", -0.5)]
    assert abs(tracked[0]["error"]) < 1e-4


def test_the_records_hold_the_request_its_target_and_the_applied_target(schedule):
    setpoint, reference, target = (stacked(schedule, f) for f in ("setpoint", "reference", "target"))
    assert setpoint.shape == reference.shape == target.shape == (80, 8)
    # the request: x_11 only, as scheduled; every other component free
    assert np.all(setpoint[:40, 0] == 1.0) and np.all(setpoint[40:, 0] == -0.5)
    assert np.isnan(setpoint[:, 1:]).all() and np.isnan(np.hstack([schedule.setpoint_u[n] for n in NAMES])).all()
    # its target meets the request; the free components follow the rule (least Q/R-weighted norm)
    assert np.allclose(reference[:40, 0], 1.0, atol=1e-9) and np.allclose(reference[40:, 0], -0.5, atol=1e-9)
    space = TargetSpace(PAPER_SYSTEM)
    wanted = np.full(8, np.nan)
    wanted[0] = 1.0
    rule = space.target(Request(wanted, np.full(4, np.nan)))
    assert np.allclose(reference[0], rule.x, atol=1e-12)
    # step 0 applies the origin (the design's own target); the governor moves from there
    assert np.all(target[0] == 0.0) and schedule.governor[0] == 0.0
    assert np.all(schedule.governor[1:] == 1.0)  # nominal and small: the whole way at once
    assert np.allclose(target[1:40], reference[1:40], atol=1e-12)


def test_the_step_log_carries_the_targets_only_where_something_was_asked(tmp_path):
    result = setpoint_run([{"at": 3, "subsystem": "2", "x": [None, 0.5], "u": [None]}], 8, out=tmp_path / "run")
    lines = [json.loads(line) for line in (tmp_path / "run" / "steps.jsonl").read_text().splitlines()]
    assert all(set(line) >= {"setpoint", "reference", "target", "governor"} for line in lines)
    assert lines[2]["setpoint"][3] is None and lines[3]["setpoint"][3] == 0.5
    assert np.allclose(lines[7]["target"], result.target["1"][7].tolist() + result.target["2"][7].tolist()
                       + result.target["3"][7].tolist() + result.target["4"][7].tolist())
    plain = dmpc.simulate(PAPER, steps=3, out=tmp_path / "plain")
    first = json.loads((tmp_path / "plain" / "steps.jsonl").read_text().splitlines()[0])
    assert "target" not in first and plain.verdict == "ok"
    assert np.all(plain.target["1"] == 0.0) and np.isnan(plain.setpoint["1"]).all()


def test_an_unreachable_setpoint_tracks_the_nearest_admissible_target():
    """x_12 = 60: the steady states of the paper's system hold x_12 within +-4.98 (+-4.735 with the margin)."""
    result = setpoint_run([{"at": 0, "subsystem": "1", "x": [None, 60.0]}], 60)
    check_guarantees(result)
    warnings = [w for w in result.summary["warnings"] if w["kind"] == "setpoint-unreachable"]
    assert len(warnings) == 1
    target = result.target["1"][-1, 1]
    assert 4.6 < target < 4.98
    text = warnings[0]["message"]
    assert "subsystem 1: x2 = 60 asked" in text and f"{target:.6g}" in text and f"gap {target - 60.0:.3g}" in text
    assert warnings[0]["amount"] == pytest.approx(60.0 - target)
    assert abs(result.x["1"][-1, 1] - target) < 1e-3
    assert result.verdict == "ok"


def test_a_large_jump_moves_the_applied_target_by_the_governor(jump):
    check_guarantees(jump)
    theta = jump.governor
    moved = np.flatnonzero(theta[1:] < 1.0) + 1
    assert moved.size >= 2 and moved.min() == 40, theta  # the jump was taken in several safe steps
    applied = jump.target["1"][:, 0]
    assert np.all(np.diff(applied[40:]) >= -1e-12)  # towards the request, never back
    assert 1.0 < applied[40] < 18.0 and applied[-1] == pytest.approx(18.0, abs=1e-9)
    assert abs(jump.x["1"][-1, 0] - 18.0) < 1e-4
    assert jump.summary["tracking"]["governor_steps"][1:] == [int(k) for k in moved]


def test_the_plain_shifted_problem_is_infeasible_at_the_jump(jump):
    """Without the governor the target of step 40 would be the request itself: the plans of step 39
    end where the terminal box of step 40 around it would be empty (beta(40) = sigma(alpha(40)) < 0),
    so every QP of step 40 would be infeasible. The target the governor applied keeps it non-empty."""
    arrays = np.load(jump.folder / "trajectory.npz")
    prepared = prepare(load_scenario(PAPER))
    terminal, K = prepared.design.terminal, prepared.design.gains.K_global()
    AK = A + B @ K
    eta = np.hstack([arrays[f"plan_z_{name}"][39][-1] for name in NAMES])  # eta(39)
    space = TargetSpace(PAPER_SYSTEM)
    requested = stacked(jump, "reference")[40], np.hstack([jump.reference_u[n] for n in NAMES])[40]
    applied = stacked(jump, "target")[40], np.hstack([jump.target_u[n] for n in NAMES])[40]
    assert terminal.sigma(AK @ (eta - requested[0]), space.scale(*requested)) < -0.1
    beta_40 = terminal.sigma(AK @ (eta - applied[0]), space.scale(*applied))
    assert beta_40 >= -1e-9 and beta_40 == pytest.approx(arrays["beta"][40], abs=1e-9)


def test_free_setpoints_change_nothing():
    """A schedule that requests nothing runs the tracking path around the origin: bit for bit the
    run without setpoints."""
    plain = dmpc.simulate(dmpc.load_scenario(PAPER))
    free = setpoint_run([{"at": 0, "subsystem": "2", "x": [None, None]}], 30)
    assert np.array_equal(plain.stacked_x(), free.stacked_x())
    assert np.array_equal(plain.stacked_u(), free.stacked_u())
    assert np.array_equal(plain.J, free.J)

"""The verdict's setpoint warnings say what happened: a request exactly on the
margin is reachable to the target solver's tolerance, every unreachable request is reported with
its own gap, and ``not-converged`` is measured against the setpoint steps, not against a start
that happens to sit on the target.

The arrays are built as a run records them (dmpc/records/run_folder.py), from targets that
:class:`~dmpc.tracking.targets.TargetSpace` computes, with a state that follows them.
"""
from __future__ import annotations

import numpy as np
import pytest

from dmpc.records.tracking import gap_tolerance
from dmpc.records.verdict import RunLimits, judge
from dmpc.scenario import build_system, load_scenario
from dmpc.tracking.targets import DEFAULT_MARGIN, MARGIN_ROOM, SOLVER_TOLERANCE, Request, TargetSpace
from tests.helpers.reference import PAPER, SCENARIOS

CARTS = build_system(load_scenario(SCENARIOS / "carts.yaml"))
PAPER_SYSTEM = build_system(load_scenario(PAPER))


def tracked_arrays(system, schedule: list[tuple[int, int, float]], steps: int, x0=None, end_offset: float = 0.0) -> dict:
    """The arrays of a run of ``steps`` steps whose request sets state component ``column`` to
    ``value`` from step ``at`` on (``schedule``: (at, column, value)); the target is applied at once
    and the state is on it one step later, off by ``end_offset`` in every component at the end."""
    space = TargetSpace(system)
    n, m = system.n, system.m
    setpoint = np.full((steps, n), np.nan)
    for at, column, value in schedule:
        setpoint[at:, column] = value
    reference, reference_u = np.zeros((steps, n)), np.zeros((steps, m))
    for k in range(steps):
        if k == 0 or not np.array_equal(setpoint[k], setpoint[k - 1], equal_nan=True):
            target = space.target(Request(setpoint[k], np.full(m, np.nan)))
        reference[k], reference_u[k] = target.x, target.u
    x = np.vstack([reference[:1] if x0 is None else np.asarray(x0, float)[None], reference])
    x[-1] += end_offset
    return {"x": x, "u": reference_u.copy(), "setpoint": setpoint, "setpoint_u": np.full((steps, m), np.nan),
            "reference": reference, "reference_u": reference_u, "target": reference.copy(),
            "target_u": reference_u.copy(), "governor": np.ones(steps), "rounds": np.ones(steps, int),
            "max_change": np.zeros(steps)}


def warnings_of(system, arrays: dict, kind: str) -> list:
    verdict = judge(system, arrays, [], RunLimits(arrays["u"].shape[0]))
    return [w for w in verdict.warnings if w.kind == kind]


def test_a_request_exactly_on_the_margin_is_reachable():
    """Cart 1 at p = 4.75 = (1 - margin) 5: on the margin, met to the target solver's tolerance
    (the nearest target misses it by about 7e-6, as cart 5 at 1.9 did on the ten carts)."""
    arrays = tracked_arrays(CARTS, [(0, 0, 4.75)], 20)
    gap = arrays["reference"][0, 0] - 4.75
    assert 1e-6 * 4.75 < abs(gap) < gap_tolerance(arrays["setpoint"][0], np.full(3, np.nan), CARTS)[0]
    assert warnings_of(CARTS, arrays, "setpoint-unreachable") == []


def test_the_gap_tolerance_is_the_solvers():
    """One pinned component of weight w asked a: sqrt(SOLVER_TOLERANCE max(1, w a^2) / w), plus the
    room the targets keep inside the margin, a MARGIN_ROOM / (1 - margin), plus 1e-6 max(1, |a|)."""
    asked = np.array([4.75, np.nan, np.nan, np.nan, np.nan, np.nan])
    tol = gap_tolerance(asked, np.full(3, np.nan), CARTS)
    expected = (np.sqrt(SOLVER_TOLERANCE * 4.75 ** 2) + 4.75 * MARGIN_ROOM / (1 - DEFAULT_MARGIN) + 1e-6 * 4.75)
    assert tol[0] == pytest.approx(expected)
    assert SOLVER_TOLERANCE == 1e-10


def test_every_unreachable_request_is_reported_with_its_own_gap():
    """4.75 (on the margin), then 4.8 and 4.9 for the same component: two warnings, each with the
    step it was asked from and its own gap; none for the request on the margin."""
    arrays = tracked_arrays(CARTS, [(0, 0, 4.75), (10, 0, 4.8), (20, 0, 4.9)], 30)
    found = warnings_of(CARTS, arrays, "setpoint-unreachable")
    assert [w.steps for w in found] == [[10], [20]]
    for w, asked, k in zip(found, (4.8, 4.9), (10, 20)):
        gap = arrays["reference"][k, 0] - asked
        assert w.amount == pytest.approx(abs(gap))
        assert f"x1 = {asked:.6g} asked from k = {k}" in w.message and f"gap {gap:.3g}" in w.message
    assert found[1].amount > found[0].amount + 0.09


def test_not_converged_is_measured_against_the_setpoint_steps():
    """The run starts on its last target (||x(0) - x_s|| ~ 0), steps x1 up to 1 and back: a final
    error of 3e-6 is converged (1 % of the step of 1 is 0.01); 0.05 is not."""
    schedule = [(0, 0, 1.0), (12, 0, 0.0)]
    last = tracked_arrays(PAPER_SYSTEM, schedule, 40)["reference"][-1]
    settled = tracked_arrays(PAPER_SYSTEM, schedule, 40, x0=last, end_offset=3e-6)
    assert np.abs(settled["x"][0] - last).max() < 1e-12
    assert warnings_of(PAPER_SYSTEM, settled, "not-converged") == []
    short = tracked_arrays(PAPER_SYSTEM, schedule, 40, x0=last, end_offset=0.05)
    found = warnings_of(PAPER_SYSTEM, short, "not-converged")
    assert len(found) == 1 and "largest setpoint step" in found[0].message
    assert found[0].amount == pytest.approx(0.05)


def test_a_run_that_starts_on_its_only_target_is_converged():
    """Nothing to move: the state stays on the target (to 1e-12), no warning."""
    arrays = tracked_arrays(PAPER_SYSTEM, [(0, 0, 1.0)], 10)
    arrays["x"][0] = arrays["reference"][0]
    arrays["x"][-1] += 1e-12
    assert warnings_of(PAPER_SYSTEM, arrays, "not-converged") == []

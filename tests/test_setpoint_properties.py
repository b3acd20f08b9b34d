"""The guarantees kept with setpoints, for random schedules (docs/algorithm.md, "Setpoints").

Hypothesis draws schedules of one to three entries (a subsystem, a component, a value that may lie
beyond the reachable steady states, a step) on the paper's example (inputs bounded) and on the
carts (states and inputs bounded). Every run, in nominal conditions, must keep: every QP
feasible and no fallback; every state and input bound; every target applied a steady state of
the coupled system inside the margin; the applied target never moving away from the request's
target while that stays; the cost non-increasing while the applied target stays; and, once the
schedule has settled, the state at the applied target and the applied target at the request's.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dmpc.core.steps import ProtocolOptions
from dmpc.records.run_folder import summarise, trajectory_arrays
from dmpc.runtime.inprocess import simulate
from dmpc.scenario import load_scenario
from dmpc.setup import prepare
from dmpc.tracking.schedule import SetpointEntry
from dmpc.tracking.targets import DEFAULT_MARGIN, TargetSpace
from tests.helpers.reference import PAPER, ROOT

STEPS = 260
LAST_CHANGE = 30
"""Entries take effect at steps 0..LAST_CHANGE; the runs go on for STEPS - LAST_CHANGE steps more:
a target at the margin of U (lambda = 0.05) has a small terminal set, and the governor needs up
to about 150 steps to bring the applied target there on these systems."""


@pytest.fixture(scope="module", params=["paper", "carts"])
def system_case(request):
    path = PAPER if request.param == "paper" else ROOT / "scenarios" / "carts.yaml"
    prepared = prepare(load_scenario(path))
    limits = 8.0 if request.param == "paper" else None  # the paper has no state bounds
    return prepared, limits, TargetSpace(prepared.system)


@st.composite
def schedules(draw, system, limits):
    entries = []
    for _ in range(draw(st.integers(1, 3))):
        i = draw(st.integers(0, system.M - 1))
        sub = system.subsystems[i]
        x, u = np.full(sub.n, np.nan), np.full(sub.m, np.nan)
        c = draw(st.integers(0, sub.n - 1))
        bound = limits if sub.state_set is None else float(sub.state_set.upper[c])
        x[c] = draw(st.floats(-bound, bound, allow_nan=False))
        entries.append(SetpointEntry(draw(st.integers(0, LAST_CHANGE)), i, x, u))
    return tuple(entries)


def run_with(prepared, entries):
    prepared = dataclasses.replace(prepared, setpoints=entries,
                                   protocol=dataclasses.replace(prepared.protocol, steps=STEPS))
    assert isinstance(prepared.protocol, ProtocolOptions)
    records = []
    simulate(prepared, records.append)
    arrays = trajectory_arrays(prepared.system, records)
    return arrays, summarise(prepared.system, records, arrays)


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                HealthCheck.too_slow])
@given(data=st.data())
def test_random_schedules_keep_the_guarantees(system_case, data):
    prepared, limits, space = system_case
    system = prepared.system
    entries = data.draw(schedules(system, limits))
    arrays, summary = run_with(prepared, entries)
    assert summary["steps"] == STEPS
    assert summary["qp_failed"] == 0 and summary["fallbacks"] == 0 and summary["feasible"], summary["notes"]
    assert summary["verdict"] == "ok", summary["failures"]  # every bound held, nothing diverged
    assert summary["J_non_increasing"]

    target, target_u = arrays["target"], arrays["target_u"]
    reference, reference_u = arrays["reference"], arrays["reference_u"]
    steady = np.abs(target @ system.A.T + target_u @ system.B.T - target).max()
    assert steady < 1e-8 * (1 + np.abs(target).max())
    for k in range(STEPS):
        assert space.gauge(target[k], target_u[k]) <= 1 - DEFAULT_MARGIN + 1e-7
    # toward the request's target, never away, while the request stays
    gap = np.max(np.abs(np.hstack([reference - target, reference_u - target_u])), axis=1)
    same = np.all(np.hstack([reference[1:] == reference[:-1], reference_u[1:] == reference_u[:-1]]), axis=1)
    assert np.all(gap[1:][same] <= gap[:-1][same] + 1e-9)
    # settled: the applied target at the request's, the state at the applied target
    assert gap[-1] <= 1e-9, arrays["governor"][-10:]
    scale = 1 + np.abs(target[-1]).max()
    assert np.abs(arrays["x"][-1] - target[-1]).max() < 1e-4 * scale
    assert np.linalg.norm(arrays["x"][-1] - arrays["x"][-2]) < 1e-5 * scale

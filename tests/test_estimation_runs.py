"""Offset-free tracking in closed loop (issue 31, "Must show"; docs/algorithm.md, "Offset-free
tracking"): runs through the coordinator, the agents and the plant in this process
(``dmpc.simulate``, the in-memory bus), with the coordinator measuring y = C x and releasing the
observers' estimate x^ in place of x.

- The nonlinear four-tank with h1 and h2 measured only (scenarios/fourtank-levels.yaml): no
  fallback, every QP solved, every bound held on the plant's state, h1 and h2 at their setpoints at
  the end of each segment (<= 1e-4 of the 0.15 m step), the estimate reconciled with the
  measurements; the same scenario without estimation settles off its raised setpoints; C the
  identity written out (no estimation) is the run without C, bit for bit.
- The linear four-tank (scenarios/fourtank.yaml's model) with h1, h2 measured and constant
  disturbance steps at step 100: an input-like one (pump a's flow, through ``plant.disturbance``),
  with output and with input disturbance models, and a sensor bias (the coordinator's measurement,
  patched): the estimates converge, the offset goes to zero, every bound holds.
- Random coupled systems (2 subsystems, B_ij as large as B_jj and larger) with one state of each
  measured, a constant plant disturbance and an output request: zero offset at the end.
- Live requests in a run with estimation: a measured state is taken as an output, an unmeasured
  state or an input is refused with the reason.

Everything asserted is recomputed from the scenario's numbers (bounds, requests, C, the disturbance
written here), the run folder's arrays and step log; not from the summary's verdict alone.

Figures measured when these tests were written:

    fourtank-levels.yaml (1200 steps, 3.6 s)  |h1 - r|, |h2 - r| at k = 599: 9.7e-7, 7.7e-7 m;
                                             at k = 1199: 1.3e-7, 2.0e-8 m; |x^ - x|_inf at k = 599
                                             8.0e-3 m (the mismatch is explained as an output
                                             bias: C x^ + d^ = y, innovation 1.0e-8), at k = 1199
                                             7.3e-8 m (the model is exact at the operating point)
    the same without estimation (600 steps)  h1 - r = 8.54e-4 m, h2 - r = 8.28e-4 m at k = 599
    linear plant, 800 steps, step at 100     |y - r| at the end: pump a's flow 0.3 m^3/h,
                                             output model 1.2e-6, input model 6.0e-7 (d^_a -> 0.3);
                                             sensor bias (0.01, -0.005) m, output model 2.1e-10
                                             (d^ -> the bias, x^ -> x)
    live request h1 = 0.1 from step 6          h1 - 0.1 = -1.8e-6 m, h2 - 0.15 = 1.8e-6 m at k = 600
    random systems (60 examples, 400 steps)  |C x - r| / |r| at the end <= 2e-11 (most ~1e-16)
"""
from __future__ import annotations

import copy
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, Phase, assume, event, example, given, settings
from hypothesis import strategies as st

import dmpc
import dmpc.coordinator.process as coordinator_process
from dmpc.api.result import Result
from dmpc.bus.messages import Setpoint
from dmpc.coordinator.estimation import Estimation
from dmpc.runtime.inprocess import build_run
from dmpc.scenario import Scenario, load_scenario
from dmpc.setup import prepare
from tests.helpers.closed_loop import (
    SOLVED,
    bound_excess,
    designed,
    fallback_steps,
    read_steps,
    scenario_bounds,
    statuses,
)

ROOT = Path(__file__).resolve().parents[1]
LEVELS = ROOT / "scenarios" / "fourtank-levels.yaml"
FOURTANK = ROOT / "scenarios" / "fourtank.yaml"

OFFSET_FRACTION = 1e-4
"""A tracked output within this fraction of its setpoint step of the value asked, at the end of
its segment (issue 31)."""
BOUND_TOLERANCE = 1e-7
"""A plant state or an input may pass its bound by this much."""
NO_ESTIMATION_OFFSET = 5e-4
"""Without estimation the raised levels of the four-tank settle at least this far (m) off."""
WALL_TIME = ("solve_time", "step_time")
"""Columns that measure wall time: they differ between any two runs."""


# ------------------------------------------------------------------------------------- scenarios
def levels_data() -> dict:
    return yaml.safe_load(LEVELS.read_text())


def without_estimation(data: dict) -> dict:
    """The same scenario mapping without ``estimation``, ``C`` and ``outputs``, the requests on the
    outputs (h1, h2: states measured alone) given on the states of the same names."""
    data = copy.deepcopy(data)
    del data["estimation"]
    for sub in data["subsystems"]:
        del sub["C"], sub["outputs"]
    data["setpoints"] = [{"at": e["at"], "subsystem": e["subsystem"], "x": e["y"]} for e in data["setpoints"]]
    return data


def with_identity(data: dict) -> dict:
    """``data`` (without estimation) with every C the identity and the outputs the states, written out."""
    data = copy.deepcopy(data)
    for sub in data["subsystems"]:
        n = len(sub["A"])
        sub["C"] = np.eye(n).tolist()
        sub["outputs"] = [dict(q) for q in sub["states"]]
    return data


@dataclass(frozen=True)
class Run:
    scenario: Scenario
    result: Result
    steps: list[dict]
    arrays: dict[str, np.ndarray]
    folder: Path


class Runs:
    """The module's runs, made on first use and shared by the tests that read them."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.done: dict[str, Run] = {}

    def get(self, key: str, make) -> Run:
        if key not in self.done:
            self.done[key] = make(self.folder / key)
        return self.done[key]


def simulate(data: dict, out: Path) -> Run:
    scenario = dmpc.load_scenario(data)
    result = dmpc.simulate(scenario, out=out)
    with np.load(out / "trajectory.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    return Run(scenario, result, read_steps(out), arrays, out)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return Runs(tmp_path_factory.mktemp("estimation-runs"))


def levels_run(runs: Runs) -> Run:
    return runs.get("levels", lambda out: simulate(levels_data(), out))


def plain_run(runs: Runs) -> Run:
    """fourtank-levels without estimation, its raised segment (600 steps)."""
    return runs.get("plain", lambda out: simulate(dict(without_estimation(levels_data()), steps=600), out))


def assert_nominal(run: Run) -> None:
    """Verdict ok, no fallback, every QP solved (summary and step log), every bound held on the
    plant's state and on the inputs (from the scenario's boxes)."""
    result, summary = run.result, run.result.summary
    assert result.verdict == "ok", summary["failures"]
    assert summary["fallbacks"] == 0 and summary["qp_failed"] == 0 and summary["feasible"], summary.get("notes")
    assert fallback_steps(run.steps) == [] and statuses(run.steps) == {SOLVED}
    assert len(run.steps) == result.steps == run.scenario.steps
    x_excess, u_excess = bound_excess(result, scenario_bounds(run.scenario))
    assert x_excess <= BOUND_TOLERANCE and u_excess <= BOUND_TOLERANCE, (x_excess, u_excess)


def output_matrix(scenario: Scenario) -> np.ndarray:
    """The global C (p, n), block diagonal, from the scenario's own C (the identity where omitted)."""
    blocks = [np.asarray(s.C, float) if s.C is not None else np.eye(len(s.A)) for s in scenario.resolved_subsystems()]
    C = np.zeros((sum(b.shape[0] for b in blocks), sum(b.shape[1] for b in blocks)))
    r = c = 0
    for b in blocks:
        C[r:r + b.shape[0], c:c + b.shape[1]] = b
        r, c = r + b.shape[0], c + b.shape[1]
    return C


def output_segments(data: dict) -> list[tuple[int, int, dict[tuple[str, str], float], dict[tuple[str, str], float]]]:
    """The schedule's segments from the scenario mapping's requests on outputs (``y`` by name):
    (first step, last step, the values asked then, each one's step from the previous segment's
    value, 0 before the first) by (subsystem, output name); ``at`` in seconds with ``dt``."""
    dt = data.get("dt") or 1.0
    entries = sorted(data["setpoints"], key=lambda e: e["at"])
    starts = sorted({round(e["at"] / dt) for e in entries})
    asked: dict[tuple[str, str], float] = {}
    out = []
    for i, start in enumerate(starts):
        before = dict(asked)
        for e in entries:
            if round(e["at"] / dt) == start:
                asked.update({(e["subsystem"], name): float(v) for name, v in e["y"].items()})
        end = starts[i + 1] - 1 if i + 1 < len(starts) else data["steps"] - 1
        out.append((start, end, dict(asked), {key: v - before.get(key, 0.0) for key, v in asked.items()}))
    return out


def column_of(scenario: Scenario, subsystem: str, state: str) -> int:
    """The global state column of ``state`` of ``subsystem``."""
    column = 0
    for spec in scenario.resolved_subsystems():
        names = [q.name for q in spec.states]
        if spec.name == subsystem:
            return column + names.index(state)
        column += len(names)
    raise KeyError(subsystem)


# ------------------------------------------------------------------ the nonlinear four-tank, h1 and h2 measured
def test_fourtank_levels_runs_nominally(runs):
    """fourtank-levels.yaml as shipped: verdict ok, no fallback, every QP solved, every bound held
    on the plant's (not the estimate's) state; its records carry what the controllers saw."""
    run = levels_run(runs)
    assert run.scenario.options.method == "tv-box-coop" and run.scenario.plant.model == "fourtank"
    assert run.scenario.estimation is not None and run.scenario.estimation.disturbance == "output"
    assert_nominal(run)
    assert run.result.summary["warnings"] == []  # no offset, no estimator diverging, nothing not converged
    K = run.result.steps
    assert run.arrays["y"].shape == (K, 2) and run.arrays["x_hat"].shape == (K, 4)
    assert run.arrays["d_hat"].shape == (K, 2) and run.arrays["innovation"].shape == (K,)
    # y is the plant's C x, no more (no measurement noise in the scenario): h1 and h2
    C = output_matrix(run.scenario)
    assert np.array_equal(C, [[1, 0, 0, 0], [0, 0, 1, 0]])
    assert np.array_equal(run.arrays["y"], run.result.stacked_x()[:K] @ C.T)
    # the step log holds the same
    assert run.steps[599]["x_hat"] == run.arrays["x_hat"][599].tolist()
    assert run.steps[599]["d_hat"] == run.arrays["d_hat"][599].tolist()


def test_fourtank_levels_settle_on_their_setpoints_without_offset(runs):
    """h1 and h2 (the plant's levels, not the estimate) within 1e-4 of the setpoint step (0.15 m)
    of the values asked, at the last step of each segment and at the end of the run."""
    run = levels_run(runs)
    data = levels_data()
    parts = output_segments(data)
    assert [(a, b) for a, b, _, _ in parts] == [(0, 599), (600, 1199)]  # 0 s and 3000 s at dt = 5 s
    x = run.result.stacked_x()
    for _start, end, asked, steps in parts:
        assert set(asked) == {("a", "h1"), ("b", "h2")}
        for (name, output), value in asked.items():
            assert abs(steps[(name, output)]) == 0.15
            column = column_of(run.scenario, name, output)
            for k in (end, end + 1) if end + 1 == len(x) - 1 else (end,):
                offset = abs(x[k, column] - value)
                assert offset <= OFFSET_FRACTION * abs(steps[(name, output)]), (name, output, k, offset)
    # the requests on outputs as recorded, and the summary's segments of the outputs
    assert np.array_equal(run.arrays["setpoint_y"][[0, 599, 600, 1199]], [[0.15, 0.15]] * 2 + [[0.0, 0.0]] * 2)
    segments = run.result.summary["tracking"]["segments"]
    assert [(s["at"], s["subsystem"], s["component"]) for s in segments] == [
        (0, "a", "h1 [m]"), (0, "b", "h2 [m]"), (600, "a", "h1 [m]"), (600, "b", "h2 [m]")]
    for segment in segments:
        assert segment["output"] is True
        assert abs(segment["error_at_end"]) <= OFFSET_FRACTION * abs(segment["step"]), segment


def test_fourtank_levels_estimate_agrees_with_the_plant(runs):
    """At each segment's end the estimate is settled and explains the measurements: d^ constant,
    C x^ + d^ = y (the innovation ~ 0). Where the model is the plant (at the operating point, the
    second segment's end) x^ is the plant's state, the unmeasured upper tanks h3 and h4 included;
    with the tanks raised, the linearisation's error is taken up by the output disturbances and
    x^ - x stays within 0.1 of the setpoint step on every state (measured 8.0e-3 m)."""
    run = levels_run(runs)
    x, x_hat, d_hat, y = run.result.stacked_x(), run.arrays["x_hat"], run.arrays["d_hat"], run.arrays["y"]
    C = output_matrix(run.scenario)
    for end, closeness in ((599, 0.1 * 0.15), (1199, 1e-6)):
        assert np.abs(d_hat[end] - d_hat[end - 1]).max() <= 1e-8, d_hat[end - 1:end + 1]
        assert np.abs(C @ x_hat[end] + d_hat[end] - y[end]).max() <= 1e-7
        assert run.arrays["innovation"][end] <= 1e-7
        error = np.abs(x_hat[end] - x[end])
        assert error.max() <= closeness, (end, error)
    assert np.abs(d_hat[599]).min() > 1e-3  # the raised segment: the model is not the plant, and d^ says so


def test_without_estimation_the_raised_levels_settle_off_their_setpoints(runs):
    """The same scenario without ``estimation`` (no C, no outputs, the requests on the states h1 and
    h2): the controllers track the linear model's steady state and the nonlinear tanks settle off it."""
    run = plain_run(runs)
    assert run.scenario.estimation is None and "x_hat" not in run.arrays
    assert run.result.verdict == "ok" and run.result.summary["fallbacks"] == 0
    x = run.result.stacked_x()
    for name, state in (("a", "h1"), ("b", "h2")):
        column = column_of(run.scenario, name, state)
        offset = abs(x[599, column] - 0.15)
        assert offset >= NO_ESTIMATION_OFFSET, (name, state, offset)
        assert abs(x[599, column] - x[589, column]) <= 1e-7  # settled there: an offset, not a slow approach
    # and the verdict says so, naming the levels, the step and the remedy
    offsets = [w for w in run.result.summary["warnings"] if w["kind"] == "offset"]
    assert [(w["subsystem"], w["steps"]) for w in offsets] == [("a", [599]), ("b", [599])], offsets
    for w, state in zip(offsets, ("h1", "h2")):
        assert w["message"].startswith(f"{state} of subsystem") and "estimation:" in w["message"], w["message"]
        assert w["amount"] >= NO_ESTIMATION_OFFSET


def test_c_the_identity_written_out_changes_nothing(runs):
    """No estimation, every C the identity and the outputs the states, written out: bit for bit
    the run of the scenario without them (every recorded array but the wall times, every line of
    the step log, the design)."""
    plain = plain_run(runs)
    ident = runs.get("identity", lambda out: simulate(dict(with_identity(without_estimation(levels_data())),
                                                           steps=600), out))
    assert ident.scenario.resolved_subsystems()[0].C is not None  # the keys were there
    assert set(plain.arrays) == set(ident.arrays)
    differing = [k for k in plain.arrays if k not in WALL_TIME
                 and (plain.arrays[k].shape != ident.arrays[k].shape
                      or plain.arrays[k].tobytes() != ident.arrays[k].tobytes())]
    assert differing == []

    def deterministic(step: dict) -> dict:
        return {k: v for k, v in step.items() if k not in WALL_TIME}

    assert [deterministic(s) for s in plain.steps] == [deterministic(s) for s in ident.steps]
    assert plain.result.summary["design_digest"] == ident.result.summary["design_digest"]
    assert json.loads((plain.folder / "design.json").read_text()) == json.loads((ident.folder / "design.json").read_text())


# ------------------------------------------------------------- the linear four-tank, constant disturbance steps
DISTURBANCE_START = 100
"""The step from which the disturbances below act."""
PUMP_OFFSET = 0.3
"""m^3/h: the input-like disturbance, an extra flow of pump a (into tank 1 and tank 4)."""
SENSOR_BIAS = np.array([0.01, -0.005])
"""m: the sensor bias on the measured h1, h2."""
LINEAR_STEPS = 800
LINEAR_REQUEST = 0.15


def linear_levels(kind: str) -> dict:
    """scenarios/fourtank.yaml (the linear plant) with h1 and h2 measured, ``estimation`` with
    disturbance model ``kind``, and h1 = h2 = 0.15 m asked for from step 0."""
    data = yaml.safe_load(FOURTANK.read_text())
    for sub, name in zip(data["subsystems"], ("h1", "h2")):
        sub["C"] = [[1.0, 0.0]]
        sub["outputs"] = [{"name": name, "unit": "m"}]
    data.update(steps=LINEAR_STEPS, estimation={"disturbance": kind},
                setpoints=[{"at": 0, "subsystem": "a", "y": {"h1": LINEAR_REQUEST}},
                           {"at": 0, "subsystem": "b", "y": {"h2": LINEAR_REQUEST}}])
    return data


def pump_disturbance(data: dict, folder: Path) -> np.ndarray:
    """The plant disturbance w (steps, n) of an extra ``PUMP_OFFSET`` on pump a from
    ``DISTURBANCE_START`` (the controllers' discrete B's column of qa, where its flow enters: h1,
    and h4 through the coupling), written to ``folder``/w.npy and set as the scenario's."""
    B = prepare(dmpc.load_scenario(data)).system.B
    column = np.asarray(B.toarray() if hasattr(B, "toarray") else B, float)[:, 0]
    assert column[0] > 0 and column[3] > 0 and column[1] == 0  # h1 and h4: pump a's tanks
    w = np.zeros((data["steps"], 4))
    w[DISTURBANCE_START:] = PUMP_OFFSET * column
    folder.mkdir(parents=True, exist_ok=True)
    np.save(folder / "w.npy", w)
    data["plant"] = {"disturbance": {"kind": "file", "file": str(folder / "w.npy")}}
    return w


class BiasedSensors(Estimation):
    """The coordinator's measurement with a constant sensor bias from ``DISTURBANCE_START``."""

    def measure(self, k: int, x: np.ndarray, outputs=None) -> np.ndarray:
        y = super().measure(k, x, outputs)
        return y + SENSOR_BIAS if k >= DISTURBANCE_START else y


def disturbed_run(runs: Runs, case: str, kind: str) -> Run:
    def make(out: Path) -> Run:
        data = linear_levels(kind)
        if case == "pump":
            pump_disturbance(data, out.parent / f"{out.name}-w")
            return simulate(data, out)
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(coordinator_process, "Estimation", BiasedSensors)
            return simulate(data, out)

    return runs.get(f"linear-{case}-{kind}", make)


@pytest.mark.parametrize("case, kind", [("pump", "output"), ("pump", "input"), ("bias", "output")])
def test_a_constant_disturbance_step_is_removed_from_the_tracked_outputs(runs, case, kind):
    """The linear plant, h3 and h4 unmeasured, a disturbance step at step 100 (pump a's flow 0.3
    m^3/h more, or a sensor bias on h1, h2): every bound held, the estimates settle (d^ constant),
    the measured outputs end within 1e-4 of the 0.15 m step of the request. Before the step the
    plant is the model: x^ = x exactly and d^ = 0."""
    run = disturbed_run(runs, case, kind)
    assert_nominal(run)
    K, a = run.result.steps, run.arrays
    x, y, x_hat, d_hat = run.result.stacked_x(), a["y"], a["x_hat"], a["d_hat"]
    C = output_matrix(run.scenario)
    bias = SENSOR_BIAS if case == "bias" else np.zeros(2)
    # what the coordinator measured: C x, plus the bias from its step
    assert np.array_equal(y[:DISTURBANCE_START], x[:DISTURBANCE_START] @ C.T)
    assert np.array_equal(y[DISTURBANCE_START:], x[DISTURBANCE_START:K] @ C.T + bias)
    if case == "pump":
        assert np.abs(run.result.w["a"][-1]).max() > 0 and not np.any(run.result.stacked_x()[0])
    # undisturbed, the linear plant is the model: the estimate is exact
    assert np.array_equal(x_hat[:DISTURBANCE_START], x[:DISTURBANCE_START])
    assert not np.any(d_hat[:DISTURBANCE_START])
    # after the step the estimate moves, and settles
    assert np.abs(d_hat[-1]).max() >= 1e-3
    assert np.abs(d_hat[-1] - d_hat[-2]).max() <= 1e-7 and np.abs(d_hat[-1] - d_hat[-11]).max() <= 1e-6
    assert a["innovation"][-1] <= 1e-6
    # zero offset in the tracked (measured) outputs
    if case == "pump":
        assert run.result.summary["warnings"] == []  # no offset, no estimator diverging
    offset = np.abs(y[-1] - LINEAR_REQUEST)
    assert offset.max() <= OFFSET_FRACTION * LINEAR_REQUEST, offset
    if case == "bias":
        # a sensor bias is an output disturbance: the model identifies it exactly and x^ = x; the
        # levels themselves settle off by the bias (what the sensors show is what is tracked)
        assert np.abs(d_hat[-1] - SENSOR_BIAS).max() <= 1e-6
        assert np.abs(x_hat[-1] - x[K - 1]).max() <= 1e-6
        assert np.abs(C @ x[K] - (LINEAR_REQUEST - SENSOR_BIAS)).max() <= OFFSET_FRACTION * LINEAR_REQUEST
        # the verdict judges the plant's outputs C x, which the bias keeps off the request, and says so
        offsets = [w for w in run.result.summary["warnings"] if w["kind"] == "offset"]
        assert [w["subsystem"] for w in offsets] == ["a", "b"]
        assert np.allclose([w["amount"] for w in offsets], np.abs(SENSOR_BIAS), rtol=0, atol=1e-6)
    else:
        # no noise: the measured outputs are the levels
        assert np.abs(C @ x[K] - LINEAR_REQUEST).max() <= OFFSET_FRACTION * LINEAR_REQUEST
        if kind == "input":  # the extra flow of pump a enters h1 as B_aa d_a does: d^_a is that flow
            assert abs(d_hat[-1, 0] - PUMP_OFFSET) <= 1e-6, d_hat[-1]


# ------------------------------------------------------------------- random coupled systems (property)
U_BOUND = 1.0
X_BOUND = 4.0
RANDOM_STEPS = 400
RANDOM_HORIZON = 10
FAST_ESTIMATOR = 0.95
"""The coupled estimator's spectral radius at most this (RANDOM_STEPS steps: 0.95^400 ~ 1e-9)."""
RANDOM_OFFSET = 1e-6
"""Each requested output within this times the largest |request| of its value at the end."""


def random_case(seed: int, factor: float, method: str, folder: Path) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray]:
    """A scenario mapping of 2 subsystems (n_i = 2, m_i = 1, discrete time), each B_ij (i != j) a
    random direction of norm ``factor`` |B_jj|, A_ij up to 0.1; one state of each measured
    (``C``), ``estimation: {disturbance: output}``, a constant plant disturbance w (a file), and
    requests on the outputs that a steady state of the plant meets: u_s drawn in [-0.25, 0.25]^2,
    x_s = (I - A)^-1 (B u_s + w), the request C x_s, with A, B, C the global matrices assembled here
    by hand. Returns (mapping, the request (2,), the plant's and the model's steady states of u_s
    stacked (8,), C (2, 4)); w is written to ``folder``/w.npy."""
    rng = np.random.default_rng(seed)
    subsystems, own = [], []
    measured = rng.integers(0, 2, 2)
    for i in range(2):
        A = rng.uniform(-0.3, 0.3, (2, 2)) + np.diag(rng.uniform(0.5, 0.95, 2))
        B = (rng.uniform(0.3, 1.0, 2) * rng.choice([-1.0, 1.0], 2))[:, None]
        L = rng.normal(size=(2, 2))
        C = np.zeros((1, 2))
        C[0, measured[i]] = 1.0
        subsystems.append(dict(name=f"s{i}", A=A.tolist(), B=B.tolist(), Q=(L @ L.T + 0.5 * np.eye(2)).tolist(),
                               R=[[float(rng.uniform(0.05, 1.0))]], input=dict(lower=[-U_BOUND], upper=[U_BOUND]),
                               state=dict(lower=[-X_BOUND] * 2, upper=[X_BOUND] * 2), x0=[0.0, 0.0],
                               C=C.tolist(), outputs=[{"name": f"y{i}"}]))
        own.append(B)
    couplings = []
    for i, j in ((0, 1), (1, 0)):
        B_ij = rng.normal(size=(2, 1))
        B_ij *= factor * np.linalg.norm(own[j]) / np.linalg.norm(B_ij)
        couplings.append(dict(target=f"s{i}", source=f"s{j}", A=rng.uniform(-0.1, 0.1, (2, 2)).tolist(),
                              B=B_ij.tolist()))
    # the global model, by hand
    A_g, B_g, C_g = np.zeros((4, 4)), np.zeros((4, 2)), np.zeros((2, 4))
    for i, s in enumerate(subsystems):
        A_g[2 * i:2 * i + 2, 2 * i:2 * i + 2] = s["A"]
        B_g[2 * i:2 * i + 2, i:i + 1] = s["B"]
        C_g[i, 2 * i:2 * i + 2] = s["C"][0]
    for c in couplings:
        i, j = int(c["target"][1]), int(c["source"][1])
        A_g[2 * i:2 * i + 2, 2 * j:2 * j + 2] += c["A"]
        B_g[2 * i:2 * i + 2, j:j + 1] += c["B"]
    w = rng.uniform(-0.01, 0.01, 4)
    u_s = rng.uniform(-0.25, 0.25, 2)
    x_s = np.linalg.solve(np.eye(4) - A_g, B_g @ u_s + w)
    request = C_g @ x_s
    folder.mkdir(parents=True, exist_ok=True)
    np.save(folder / "w.npy", np.tile(w, (RANDOM_STEPS, 1)))
    mapping = dict(name=f"random-estimation-{seed}", subsystems=subsystems, couplings=couplings,
                   horizon=RANDOM_HORIZON, steps=RANDOM_STEPS, design=dict(gains="lmi"), options=dict(method=method),
                   estimation={"disturbance": "output"},
                   plant={"disturbance": {"kind": "file", "file": str(folder / "w.npy")}},
                   setpoints=[{"at": 0, "subsystem": f"s{i}", "y": [float(request[i])]} for i in range(2)])
    model_x_s = np.linalg.solve(np.eye(4) - A_g, B_g @ u_s)  # the model's steady state of u_s (no w)
    return mapping, request, np.concatenate([x_s, model_x_s]), C_g


COUPLINGS = st.one_of(st.tuples(st.just("tv-box-coop"), st.floats(1.0, 2.0)),
                      st.tuples(st.just("tv-box"), st.floats(0.1, 0.4)))
"""(method, factor): ``tv-box-coop`` with B_ij as large as B_jj and up to twice as large;
``tv-box`` with weaker input couplings (with B_ij as large as B_jj it fails to track the request
even with the whole state measured and no disturbance: e.g. seed 0, factor 1.0, QPs infeasible
from step 3 and the run diverges, although its design passes)."""


def measured_state_mapping(mapping: dict) -> dict:
    """The random case's mapping without estimation: the whole state measured, the requests on the
    measured states, the same disturbance."""
    data = copy.deepcopy(mapping)
    del data["estimation"]
    for entry, sub in zip(data["setpoints"], data["subsystems"]):
        C, value = sub.pop("C"), entry.pop("y")[0]
        del sub["outputs"]
        entry["x"] = [value if c else None for c in C[0]]
    return data


@settings(max_examples=7, deadline=None, phases=(Phase.explicit, Phase.reuse, Phase.generate),
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                 HealthCheck.filter_too_much])
@given(seed=st.integers(0, 2**32 - 1), coupling=COUPLINGS)
@example(seed=574671949, coupling=("tv-box-coop", 1.788))
def test_random_coupled_systems_with_a_constant_disturbance_track_outputs_without_offset(tmp_path_factory, seed,
                                                                                        coupling):
    """Random coupled systems, one state of each subsystem measured, a constant disturbance on every
    state, a request on both outputs that a steady state meets: the run is nominal and converges
    (x, d^ constant) with the requested outputs at the request (<= 1e-6 relative).

    Discarded: a request whose steady state (the plant's, or the model's without w) is not well
    inside the boxes; a system whose design fails (undetectable, the coupled estimator unstable, no
    gains); an estimator slower than 0.95 per step (the run's 400 steps would not be long enough);
    a system on which the method does not track the request with the whole state measured and the
    same disturbance (no estimation): what estimation adds is asked where the method works without
    it. That one is not rare: ``tv-box`` (no guarantee under a disturbance), e.g. seed 0, factor
    0.363: QPs infeasible from step 3 with or without estimation, the run diverges (nominal without
    the disturbance); and ``tv-box-coop`` too, e.g. seed 18, factor 1.0: QPs ``max_iter`` then
    ``infeasible`` at steps 8-25 with or without estimation, with or without the disturbance
    (verdict failed, 12 fallbacks on the nominal run; regulation to the origin is nominal).
    Of the rest, the runs that converge without a fallback are asked for zero offset (the guarantee
    is conditional on convergence). Not shrunk: the examples are seeds, and a run of a failing one
    is slow."""
    method, factor = coupling
    event(method)
    folder = tmp_path_factory.mktemp("random-estimation")
    mapping, request, steady, C = random_case(seed, factor, method, folder / "w")
    # a request some steady state of the plant and of the model meets well inside the boxes
    assume(np.abs(steady).max() <= 0.5 * X_BOUND)
    scenario = dmpc.load_scenario(mapping)
    prepared = designed(scenario)
    assume(prepared is not None)  # detectable, the coupled estimator stable, the controller designed
    assume(prepared.estimator.radius <= FAST_ESTIMATOR)
    # what estimation adds is asked of systems on which the method tracks the request with the
    # whole state measured (and the same disturbance)
    reference = dmpc.simulate(dmpc.load_scenario(measured_state_mapping(mapping)))
    assume(reference.verdict == "ok" and reference.summary["fallbacks"] == 0)
    result = dmpc.simulate(scenario, out=folder / "run")
    summary = result.summary
    x = result.stacked_x()
    with np.load(folder / "run" / "trajectory.npz") as npz:
        d_hat = npz["d_hat"]
    # What is guaranteed (docs/algorithm.md, "Offset-free tracking"): zero offset WHEN the loop
    # converges. Neither convergence nor feasibility under the estimation error of the transient
    # is (e.g. seed 154441, tv-box-coop, factor 1.0: QPs infeasible while the estimate settles,
    # clean with the whole state measured), so the runs that converge nominally are the ones asked.
    scale = max(1.0, float(np.abs(request).max()))
    converged = (np.abs(x[-1] - x[-2]).max() <= 1e-8 * scale and np.abs(d_hat[-1] - d_hat[-2]).max() <= 1e-8 * scale)
    event(f"converged without fallback: {converged and summary['fallbacks'] == 0}")
    assume(converged and summary["fallbacks"] == 0 and summary["qp_failed"] == 0)
    assert result.verdict == "ok", summary["failures"]
    x_excess, u_excess = bound_excess(result, scenario_bounds(scenario))
    assert x_excess <= BOUND_TOLERANCE and u_excess <= BOUND_TOLERANCE, (x_excess, u_excess)
    # ... then the requested outputs are at the request
    offset = np.abs(C @ x[-1] - request)
    assert offset.max() <= RANDOM_OFFSET * float(np.abs(request).max()), (offset, request)


# ------------------------------------------------------------------------- live requests with estimation
RUN = "live"


def live_request(subsystem: str, x=(), u=(), id_=1) -> Setpoint:
    return Setpoint(run=RUN, sender="ops", id=id_, subsystem=subsystem, x=np.array(x, dtype=float),
                    u=np.array(u, dtype=float))


def test_live_requests_with_estimation_name_measured_states_only():
    """fourtank-levels (its first segment, 600 steps): a live request on h1 (a measured state) is taken as a
    request on the output h1 and tracked without offset; one on h3 (not measured) or on an input is
    refused, with the reason, and changes nothing."""
    prepared = prepare(load_scenario(LEVELS, {"steps": 600}))
    records = []
    run = build_run(prepared, records.append, run_id=RUN)
    assert run.bus.run(until=lambda: run.coordinator.coordinator.k >= 5)
    coordinator = run.coordinator.coordinator
    before = list(coordinator.tracker.schedule.entries)
    refused = coordinator.on_setpoint(live_request("a", x=(math.nan, 0.1), id_=2))
    assert not refused.accepted and refused.k == -1
    assert refused.reason.startswith("x[1]: this run estimates its state (estimation), and state 1 of subsystem 'a' "
                                     "is not measured on its own"), refused.reason
    refused = coordinator.on_setpoint(live_request("a", u=(0.5,), id_=3))
    assert not refused.accepted and refused.reason.startswith("u: this run estimates its state"), refused.reason
    assert list(coordinator.tracker.schedule.entries) == before
    answer = coordinator.on_setpoint(live_request("a", x=(0.1, math.nan), id_=4))
    assert answer.accepted and answer.k == 6, answer
    (entry,) = [e for e in coordinator.tracker.schedule.entries if e.source == "ops"]
    assert entry.at == 6 and entry.index == 0
    assert np.isnan(entry.x).all() and entry.y.tolist() == [0.1] and np.isnan(entry.u).all()
    assert run.bus.run(until=lambda: run.coordinator.finished) and not run.coordinator.failure
    assert len(records) == 600 and not any(any(rec.fallback) for rec in records)
    # from step 6 on, subsystem a's output request is 0.1 (b's stays 0.15) ...
    requested = [rec.tracking.request.y for rec in records]
    assert all(r is not None and r.tolist() == [0.15, 0.15] for r in requested[:6])
    assert all(r.tolist() == [0.1, 0.15] for r in requested[6:])
    # ... and the plant's h1 settles there
    h1, h2 = records[-1].x_next[0], records[-1].x_next[2]
    assert abs(h1 - 0.1) <= OFFSET_FRACTION * 0.1 and abs(h2 - 0.15) <= OFFSET_FRACTION * 0.15, (h1, h2)

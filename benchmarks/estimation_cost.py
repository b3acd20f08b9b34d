"""What an estimate costs per step: the chain of M subsystems run without estimation and with it.

The same scenario twice, back to back, on one controller design: the chain family
(``scenarios/chain.yaml``, ``family.M``) with a setpoint on x_1 of subsystem 1 (0.5 from step 0),

- (a) without estimation: C omitted, the plant reports the whole state;
- (b) with x_1 of every subsystem measured (``family.subsystem.C: [[1, 0]]``) and an observer
  (``estimation``; :data:`ESTIMATION`): each step the coordinator measures y = C x, updates every
  subsystem's filter and recomputes the offset-free target from the disturbance estimate.

The plant is the model itself and no disturbance acts: (b) sees the states (a) sees, to rounding,
its agents solve the same QPs, and the difference of the step times is what the estimate costs.

Per step (k >= 1; step 0 iterates Jacobi to convergence): the median and p95 of the step time of
both runs and their ratios, and the estimator's own time: ``Estimation.measure`` and
``Estimation.update`` (the coordinator's calls, :mod:`dmpc.coordinator.estimation`) and the target
recomputation (:meth:`~dmpc.estimation.targets.OffsetFreeTargets.target`, and ``bounded`` where the
affine target leaves the bounds), timed around the calls where they happen in a run in this
process, and for a run as processes (the coordinator in the plant's process) timed by making the
same calls again here on the run's own recorded states and inputs (the replayed estimates are
checked against the recorded ones). In this process also the reference governor's step, in both
runs (with estimation the target it is given is a new one every step). Design: the detectability check (what ``dmpc validate`` does),
the estimator's design (checks, gains, coupled stability: what ``prepare`` does), the coupled
radius ``dmpc design`` reports, the factorisation of the target map; the estimator's arrays in MB;
for runs as processes the largest resident memory of the plant's process. With
``estimation.disturbance: output`` the chain's estimator is refused at design time (its coupled
error dynamics are unstable whatever C and weights: :data:`OUTPUT`); its design time until the
refusal is measured too.

    python benchmarks/estimation_cost.py [--quick] [--M 4 64 1024] [--no-design] [--json FILE] [--out DIR]

``--quick``: M = 4 and 64 in this process and M = 4 as processes, fewer steps (about 15 s).
Without it (about 7.5 minutes on two cores) also M = 64 with a process per agent and M = 1024 in
this process and hosted (8 processes of 128 agents), pairs repeated and alternated, and the output
disturbance's design at M = 1024 (its dense checks: 15 s on a quiet machine, minutes under load). ``--M``: only those sizes of the plan.
Every measure says the machine's speed figure (ms for 10^6 Python additions) just before, and the
load average (processes running or waiting for a core) before and after.
"""
from __future__ import annotations

import argparse
import json
import re
import secrets
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dmpc.bench.common import calibration_ms, load_average, machine  # noqa: E402
from dmpc.bench.scale import launch_sampled  # noqa: E402
from dmpc.coordinator.estimation import Estimation  # noqa: E402
from dmpc.core.errors import DesignError  # noqa: E402
from dmpc.estimation.kalman import EstimatorDesign  # noqa: E402
from dmpc.estimation.model import check_detectable  # noqa: E402
from dmpc.estimation.observer import Observer  # noqa: E402
from dmpc.estimation.targets import OffsetFreeTargets  # noqa: E402
from dmpc.evaluation.compare import timed_run  # noqa: E402
from dmpc.records.files import SUMMARY, TRAJECTORY  # noqa: E402
from dmpc.scenario import build_system, load_scenario  # noqa: E402
from dmpc.setup import prepare  # noqa: E402
from dmpc.setup.estimation import design_estimation, estimation_model  # noqa: E402
from dmpc.tracking.governor import ReferenceGovernor  # noqa: E402

CHAIN = ROOT / "scenarios" / "chain.yaml"
MEASURED = [[1.0, 0.0]]
"""Every subsystem's C: x_1 measured, x_2 not ((A_ii, C_i) observable: C A_ii = [1.1, 1])."""
ESTIMATION = {"disturbance": "input", "noise": {"state": 1e-2}}
"""(b)'s observer: one input disturbance per subsystem, the states' process noise at 1e-2 of their
scale (the default 1e-4 leaves the chain's coupled estimator unstable from M = 64 on: radius 1.008)."""
OUTPUT = {"disturbance": "output"}
"""The output disturbance model: refused on the chain (coupled radius 1.50 at M = 4, 1.57 at M = 8, 1.60 at
M = 64 and 1024 with the defaults; no C of x_1, x_2 and no weights of a grid from 1e-5 to 10 bring it below 1)."""
TARGET = 0.5
SETPOINT: dict[str, Any] = {"at": 0, "subsystem": "1", "x": [TARGET, None]}
"""x_1 of subsystem 1 to 0.5 from step 0 (with estimation a request on a measured state: on its output)."""
SAMPLE_PER_PROCESS = 0.05
"""Seconds between memory samples of a run as processes, per process (at least 0.25 s): reading a
process's memory map costs CPU that the run needs (as dmpc.bench.scale)."""
TARGETS_PER_STEP = 2
"""Target recomputations per step with estimation, as a run makes them: the step's tracking record
(the target of the request holding at step k) and the next step's target (step k + 1, from the new
disturbance estimate)."""


def overrides(M: int, steps: int, estimation: dict | None) -> dict:
    """The chain's overrides: M subsystems, ``steps`` steps, :data:`SETPOINT`, and with
    ``estimation`` (the scenario's section) every subsystem's C :data:`MEASURED`."""
    out: dict[str, Any] = {"family.M": M, "steps": steps, "setpoints": [dict(SETPOINT)]}
    if estimation is not None:
        out.update({"family.subsystem.C": MEASURED, "estimation": estimation})
    return out


def now() -> dict:
    """The machine's speed figure (ms for 10^6 Python additions, best of 3) and load average now."""
    return {"speed_ms": calibration_ms(3), "load": load_average()}


# ----------------------------------------------------------------------------- timing the calls
@dataclass
class CallTimes:
    """Seconds spent in the estimator's calls, per step of a run.

    Attributes
    ----------
    measure : dict of int to float
        Per step k: ``Estimation.measure`` of step k (y = C x).
    observer : dict of int to float
        Per step k: ``Estimation.update`` of step k (the filters).
    targets : dict of int to float
        Per step k: the target recomputations after the update of step k.
    governor : list of float
        Every call of the reference governor (``ReferenceGovernor.step``, once per step, with or
        without estimation), in order.
    fallbacks : int
        Calls of the bounded target (a QP): the affine target left the bounds.
    estimation : Estimation or None
        The coordinator's object, for its arrays' size.
    targets_object : OffsetFreeTargets or None
        The coordinator's targets, for their arrays' size.
    step : int
        The step of the last update (the target recomputations after it are that step's).
    """

    measure: dict[int, float] = field(default_factory=lambda: defaultdict(float))
    observer: dict[int, float] = field(default_factory=lambda: defaultdict(float))
    targets: dict[int, float] = field(default_factory=lambda: defaultdict(float))
    governor: list[float] = field(default_factory=list)
    fallbacks: int = 0
    estimation: Estimation | None = None
    targets_object: OffsetFreeTargets | None = None
    step: int = -1

    def per_step(self, first: int = 1) -> dict:
        """Median, p95 and mean in ms of the estimator's time per step from step ``first`` on:
        ``estimator`` (all of it), ``measure``, ``observer``, ``targets``."""
        steps = sorted(k for k in set(self.measure) | set(self.observer) | set(self.targets) if k >= first)
        out: dict[str, Any] = {"steps_timed": len(steps), "fallbacks": self.fallbacks}
        if len(self.governor) > first:
            governor = np.array(self.governor[first:]) * 1e3
            out.update(governor_ms_p50=float(np.median(governor)), governor_ms_p95=float(np.percentile(governor, 95)))
        if not steps:
            return out
        mea = np.array([self.measure.get(k, 0.0) for k in steps]) * 1e3
        obs = np.array([self.observer.get(k, 0.0) for k in steps]) * 1e3
        tgt = np.array([self.targets.get(k, 0.0) for k in steps]) * 1e3
        for name, values in (("estimator", mea + obs + tgt), ("measure", mea), ("observer", obs), ("targets", tgt)):
            out.update({f"{name}_ms_p50": float(np.median(values)), f"{name}_ms_p95": float(np.percentile(values, 95)),
                        f"{name}_ms_mean": float(values.mean())})
        return out


class Timed:
    """While open, every call of the estimator in this process is timed into ``times``
    (:class:`CallTimes`): the methods are wrapped on their classes and put back on close; nothing
    else changes (the wrappers return what the calls return)."""

    def __init__(self) -> None:
        self.times = CallTimes()
        self._saved: list[tuple[type, str, Callable]] = []

    def __enter__(self) -> "Timed":
        times = self.times

        def wrap(cls: type, name: str, where: Callable[[Any, tuple, float], None]) -> None:
            original = getattr(cls, name)

            def timed(obj, *args, **kwargs):
                t0 = time.perf_counter()
                try:
                    return original(obj, *args, **kwargs)
                finally:
                    where(obj, args, time.perf_counter() - t0)

            self._saved.append((cls, name, original))
            setattr(cls, name, timed)

        def on_measure(obj, args, seconds):
            times.estimation = obj
            times.measure[int(args[0])] += seconds

        def on_update(obj, args, seconds):
            times.step = int(args[0])
            times.observer[times.step] += seconds

        def on_target(obj, args, seconds):
            times.targets_object = obj
            times.targets[times.step] += seconds

        def on_bounded(obj, args, seconds):
            times.fallbacks += 1
            times.targets[times.step] += seconds

        wrap(Estimation, "measure", on_measure)
        wrap(Estimation, "update", on_update)
        wrap(OffsetFreeTargets, "target", on_target)
        wrap(OffsetFreeTargets, "bounded", on_bounded)
        wrap(ReferenceGovernor, "step", lambda obj, args, seconds: times.governor.append(seconds))
        return self

    def __exit__(self, *exc) -> None:
        for cls, name, original in reversed(self._saved):
            setattr(cls, name, original)


def array_mb(*objects) -> float:
    """MB of the arrays among ``objects`` (ndarrays, sparse matrices; others count 0)."""
    total = 0
    for obj in objects:
        if isinstance(obj, np.ndarray):
            total += obj.nbytes
        elif sp.issparse(obj):
            coo = obj if hasattr(obj, "indptr") else sp.csr_matrix(obj)
            total += coo.data.nbytes + coo.indices.nbytes + coo.indptr.nbytes
    return total / 2**20


def estimator_mb(design: EstimatorDesign, observer: Observer | None, targets: OffsetFreeTargets | None) -> dict:
    """The estimator's arrays in MB.

    Parameters
    ----------
    design : EstimatorDesign
        Its gains: every agent's L and P (``gains_mb``).
    observer : Observer or None
        The matrices its step multiplies (``observer_mb``).
    targets : OffsetFreeTargets or None
        Its factored target maps: L and U of each LU, and the gauge rows (``targets_mb``).
    """
    gains = array_mb(*[m for g in design.gains for m in (g.L, g.P)])
    ops = 0.0 if observer is None else array_mb(*vars(observer).values())
    factors = 0.0
    if targets is not None:
        for found in targets._maps.values():
            lu = found._lu
            factors += array_mb(lu.L, lu.U)
        factors += array_mb(targets._gx, targets._gu)
    return {"gains_mb": gains, "observer_mb": ops, "targets_mb": factors}


# ----------------------------------------------------------------------------- the design
def design_figures(M: int, estimation: dict) -> dict:
    """The estimator's design for the chain of M with the section ``estimation``, timed in parts.

    Parameters
    ----------
    M : int
        The chain's size.
    estimation : dict
        The scenario's ``estimation``.

    Returns
    -------
    dict
        ``augmented_states`` (n + n_d), ``check_s`` (:func:`~dmpc.estimation.model.check_detectable`),
        ``design_s`` (:func:`~dmpc.setup.estimation.design_estimation`), ``radius_s`` and
        ``radius`` (the coupled radius as ``dmpc design`` reports it; refused: the message's),
        ``targets_s`` (the target map of the setpoint's pattern factored), ``refused`` (the start
        of the DesignError's message, or None) and ``refused_after_s``, with the speed figure and
        load before.
    """
    out: dict[str, Any] = {"M": M, "disturbance": estimation["disturbance"], **now()}
    scenario = load_scenario(CHAIN, overrides(M, 2, estimation))
    system = build_system(scenario)
    model = estimation_model(scenario, system)
    assert model is not None
    out["augmented_states"] = model.n + model.nd
    t0 = time.perf_counter()
    try:
        check_detectable(model)
        out["check_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        design = design_estimation(scenario, system)
        out["design_s"] = time.perf_counter() - t0
    except DesignError as exc:
        text = str(exc)
        found = re.search(r"spectral radius ([0-9.eE+-]+) >= 1", text)
        out.update(refused=text[:300], refused_after_s=time.perf_counter() - t0,
                   radius=float(found.group(1)) if found else None)
        return out
    assert design is not None
    t0 = time.perf_counter()
    out["radius"] = design.radius
    out["radius_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    targets = OffsetFreeTargets(model)
    pinned = np.zeros(model.p, dtype=bool)
    pinned[0] = True
    targets.pattern(pinned)
    out["targets_s"] = time.perf_counter() - t0
    out["refused"] = None
    return out


# ----------------------------------------------------------------------------- runs
def step_figures(step_s: np.ndarray) -> dict:
    """Median and p95 in ms of the step times ``step_s`` (s), NaN left out."""
    step = np.asarray(step_s, float) * 1e3
    step = step[np.isfinite(step)]
    if not step.size:
        return {}
    return {"step_ms_p50": float(np.median(step)), "step_ms_p95": float(np.percentile(step, 95)), "steps_timed": int(step.size)}


def prepared_pair(M: int, steps: int, design: dict | None = None) -> tuple[Any, Any, float, float]:
    """(a) and (b) for M and ``steps``, on the controller design ``design`` (design.json's content;
    None: (a)'s, designed now), and the seconds each ``prepare`` took ((b)'s: the estimator
    designed, the controller's offline solves skipped)."""
    t0 = time.perf_counter()
    plain = prepare(load_scenario(CHAIN, overrides(M, steps, None)), design_data=design)
    plain_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    estimated = prepare(load_scenario(CHAIN, overrides(M, steps, ESTIMATION)), design_data=design or plain.design_json())
    return plain, estimated, plain_s, time.perf_counter() - t0


def inprocess_pair(plain, estimated, workdir: Path, repeats: int) -> dict:
    """(a) then (b) in this process (``dmpc simulate``'s loop), ``repeats`` times alternating;
    step times from k = 1 (the wall time between steps' completions), the estimator's calls timed.

    Parameters
    ----------
    plain, estimated : Prepared
        (a) and (b).
    workdir : Path
        Where the run folders go.
    repeats : int
        Pairs run.
    """
    out: dict[str, Any] = {"where": "in process", "M": plain.system.M, "steps": plain.protocol.steps, **now(),
                           "pairs": []}
    for r in range(repeats):
        with Timed() as plain_timed:
            a = timed_run(plain, workdir / f"a-M{plain.system.M}-{r}")
        with Timed() as timed:
            b = timed_run(estimated, workdir / f"b-M{plain.system.M}-{r}")
        pair = {"a": {**step_figures(a.step_times), "verdict": a.summary.get("verdict"),
                      "fallbacks": a.summary.get("fallbacks"), "cost": a.summary.get("closed_loop_cost"),
                      **plain_timed.times.per_step()},
                "b": {**step_figures(b.step_times), "verdict": b.summary.get("verdict"),
                      "fallbacks": b.summary.get("fallbacks"), "cost": b.summary.get("closed_loop_cost"),
                      **timed.times.per_step()}}
        if r == 0:
            est = timed.times.estimation
            out.update(estimator_mb(estimated.estimator, None if est is None else est.observer,
                                    timed.times.targets_object))
        out["pairs"].append(pair)
    out["load_after"] = load_average()
    return out


def hosted_run(prepared, per_process: int, folder: Path, startup_timeout: float) -> dict:
    """``prepared`` as processes of ``per_process`` agents (``dmpc run --agents-per-process``) into the
    run folder ``folder``, each process waiting at most ``startup_timeout`` seconds to start, their
    memory sampled: step times from the plant's records (k >= 1), start-up, peak RSS."""
    result, peak, processes = launch_sampled(prepared, folder, f"estimate-{secrets.token_hex(4)}", per_process,
                                             startup_timeout)
    if result.code != 0 or not (folder / TRAJECTORY).is_file():
        return {"completed": False, "reason": result.message[-400:]}
    summary = json.loads((folder / SUMMARY).read_text())
    step_s = np.load(folder / TRAJECTORY)["step_time"][1:]
    agents = [v[0] for role, v in peak.items() if role != "plant"]
    return {"completed": True, **step_figures(step_s), "verdict": summary.get("verdict"),
            "fallbacks": summary.get("fallbacks"), "cost": summary.get("closed_loop_cost"),
            "startup_s": summary.get("startup_s"), "plant_rss_mb": peak.get("plant", (None, None))[0],
            "agent_rss_mb": max(agents) if agents else None, "processes": processes}


def replay(estimated, folder: Path) -> dict:
    """The estimator's calls of the run in ``folder`` made again in this process on its recorded
    states and inputs, as the coordinator makes them (``Estimation.measure``, ``update``, the target
    of the setpoint's request :data:`TARGETS_PER_STEP` times), timed; the largest difference of the
    replayed estimates from the recorded ones is returned with the times (0 when the replay is exact).

    Parameters
    ----------
    estimated : Prepared
        The run (b), with its estimator.
    folder : Path
        Its run folder.
    """
    arrays = np.load(folder / TRAJECTORY)
    x, u = arrays["x"], arrays["u"]
    recorded = arrays["x_hat"]
    estimation = Estimation(estimated.estimator, estimated.plant.measurement_noise)
    model = estimated.estimator.model
    targets = OffsetFreeTargets(model, estimated.setpoint_margin)
    request = np.full(model.p, np.nan)
    request[0] = TARGET
    targets.pattern(~np.isnan(request))
    times = CallTimes()
    worst = 0.0
    for k in range(u.shape[0]):
        t0 = time.perf_counter()
        y = estimation.measure(k, x[k])
        tm = time.perf_counter()
        estimate = estimation.update(k, u[k - 1] if k else None, y)
        t1 = time.perf_counter()
        for _ in range(TARGETS_PER_STEP):
            found = targets.target(request, estimate.d_hat)
            if not found.inside:
                times.fallbacks += 1
                targets.bounded(request, estimate.d_hat)
        t2 = time.perf_counter()
        times.measure[k], times.observer[k], times.targets[k] = tm - t0, t1 - tm, t2 - t1
        worst = max(worst, float(np.max(np.abs(estimate.x_hat - recorded[k]), initial=0.0)))
    return {**times.per_step(), "replay_x_hat_max_difference": worst,
            **estimator_mb(estimated.estimator, estimation.observer, targets)}


def processes_pair(plain, estimated, per_process: int, workdir: Path, startup_timeout: float, repeats: int = 1) -> dict:
    """(a) ``plain`` then (b) ``estimated`` as processes, ``repeats`` times alternating, ``per_process``
    agents to a process, the run folders in ``workdir``, each process waiting at most
    ``startup_timeout`` seconds to start; the estimator's calls of the first (b) replayed
    (:func:`replay`)."""
    M = plain.system.M
    out: dict[str, Any] = {"where": "as processes", "M": M, "steps": plain.protocol.steps,
                           "agents_per_process": per_process, **now(), "pairs": []}
    for r in range(repeats):
        pair = {"a": hosted_run(plain, per_process, workdir / f"a-hosted-M{M}-{r}", startup_timeout),
                "b": hosted_run(estimated, per_process, workdir / f"b-hosted-M{M}-{r}", startup_timeout)}
        if r == 0 and pair["b"].get("completed"):
            pair["b"].update(replay(estimated, workdir / f"b-hosted-M{M}-{r}"))
        out["pairs"].append(pair)
    out["load_after"] = load_average()
    return out


# ----------------------------------------------------------------------------- the tables
def cell(value, spec: str = ".2f") -> str:
    """A table cell of ``value``: "-" for None, a number in ``spec``."""
    return "-" if value is None else format(value, spec)


def ratio(b: dict, a: dict, key: str) -> float | None:
    """b[key] / a[key], or None."""
    return b[key] / a[key] if b.get(key) is not None and a.get(key) else None


def run_rows(runs: list[dict]) -> list[str]:
    """The step table of ``runs``: one line per measure, pairs in process as the median over the
    repeats (of each figure, and of each pair's ratio)."""
    head = ["M", "where", "steps", "pairs", "step median without (ms)", "with (ms)", "ratio", "step p95 without (ms)",
            "with (ms)", "ratio", "estimator per step: median (ms)", "p95 (ms)", "y = C x / filters / targets: median (ms)",
            "estimator / step with", "target QPs", "governor median without / with (ms)", "speed figure (ms)", "load"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for run in runs:
        pairs = run["pairs"]
        if not all(p["a"].get("step_ms_p50") and p["b"].get("step_ms_p50") for p in pairs):
            lines.append(f"| {run['M']} | {run['where']} | did not complete: "
                         f"{(pairs[0]['a'].get('reason') or pairs[0]['b'].get('reason') or '?')[-120:]} |")
            continue

        def med(side: str, key: str, pairs: list[dict] = pairs) -> float | None:
            values = [p[side][key] for p in pairs if p[side].get(key) is not None]
            return float(np.median(values)) if values else None

        def med_ratio(key: str, pairs: list[dict] = pairs) -> float | None:
            values = [v for p in pairs if (v := ratio(p["b"], p["a"], key)) is not None]
            return float(np.median(values)) if values else None

        where = run["where"] + (f", {run['agents_per_process']} agents / process" if "agents_per_process" in run else "")
        est, step_b = med("b", "estimator_ms_p50"), med("b", "step_ms_p50")
        share = None if est is None or not step_b else est / step_b
        lines.append("| " + " | ".join([
            str(run["M"]), where, str(run["steps"]), str(len(pairs)),
            cell(med("a", "step_ms_p50")), cell(med("b", "step_ms_p50")), cell(med_ratio("step_ms_p50"), ".3f"),
            cell(med("a", "step_ms_p95")), cell(med("b", "step_ms_p95")), cell(med_ratio("step_ms_p95"), ".3f"),
            cell(est, ".3f"), cell(med("b", "estimator_ms_p95"), ".3f"),
            " / ".join(cell(med("b", f"{part}_ms_p50"), ".3f") for part in ("measure", "observer", "targets")),
            cell(share, ".1%"), str(sum(p["b"].get("fallbacks", 0) or 0 for p in pairs)),
            f"{cell(med('a', 'governor_ms_p50'), '.3f')} / {cell(med('b', 'governor_ms_p50'), '.3f')}",
            cell(run["speed_ms"], ".1f"), f"{run['load']:.1f} - {run.get('load_after', run['load']):.1f}"]) + " |")
    return lines


def design_rows(designs: list[dict]) -> list[str]:
    """The design table of ``designs`` (:func:`design_figures`): one line per M and disturbance model."""
    head = ["M", "disturbance", "n + n_d", "detectability check (s)", "estimator design (s)", "coupled radius",
            "radius as reported (s)", "target map (s)", "outcome", "speed figure (ms)", "load"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for d in designs:
        reason = (d.get("refused") or "").removeprefix("estimation: ").split(":")[0]
        outcome = "designed" if d.get("refused") is None else f"refused after {d['refused_after_s']:.2f} s: {reason}"
        lines.append("| " + " | ".join([
            str(d["M"]), d["disturbance"], str(d["augmented_states"]), cell(d.get("check_s"), ".3f"),
            cell(d.get("design_s"), ".3f"), cell(d.get("radius"), ".6f"), cell(d.get("radius_s"), ".2f"),
            cell(d.get("targets_s"), ".3f"), outcome, cell(d["speed_ms"], ".1f"), cell(d["load"], ".1f")]) + " |")
    return lines


def memory_rows(runs: list[dict]) -> list[str]:
    """The memory table of ``runs``: the estimator's arrays, and for runs as processes the largest
    resident memory of the plant's process and of an agent process (the largest over the pairs)."""
    head = ["M", "where", "gains (MB)", "observer's matrices (MB)", "target map (MB)",
            "plant process RSS without / with (MB)", "agent process RSS without / with (MB)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for run in runs:
        pairs = run.get("pairs") or []
        src = run if "gains_mb" in run else (pairs[0]["b"] if pairs else {})

        def peak(side: str, key: str, pairs: list[dict] = pairs) -> str:
            values = [p[side][key] for p in pairs if p[side].get(key) is not None]
            return cell(max(values), ".0f") if values else "-"

        processes = run["where"] == "as processes"
        lines.append("| " + " | ".join([
            str(run["M"]), run["where"], cell(src.get("gains_mb"), ".3f"), cell(src.get("observer_mb"), ".3f"),
            cell(src.get("targets_mb"), ".3f"),
            f"{peak('a', 'plant_rss_mb')} / {peak('b', 'plant_rss_mb')}" if processes else "-",
            f"{peak('a', 'agent_rss_mb')} / {peak('b', 'agent_rss_mb')}" if processes else "-"]) + " |")
    return lines


# ----------------------------------------------------------------------------- main
@dataclass(frozen=True)
class Plan:
    """What to measure.

    Attributes
    ----------
    inprocess : tuple of (int, int, int)
        (M, steps, repeats) of the pairs in this process.
    processes : tuple of (int, int, int, int)
        (M, steps, agents per process, repeats) of the pairs as processes.
    designs : tuple of int
        The M of the estimator's designs.
    output_designs : tuple of int
        The M of the output disturbance model's designs (refused on the chain).
    """

    inprocess: tuple[tuple[int, int, int], ...]
    processes: tuple[tuple[int, int, int, int], ...]
    designs: tuple[int, ...]
    output_designs: tuple[int, ...]


QUICK = Plan(inprocess=((4, 200, 3), (64, 40, 2)), processes=((4, 200, 1, 1),), designs=(4, 64),
             output_designs=(4, 64))
FULL = Plan(inprocess=((4, 300, 5), (64, 60, 3), (1024, 20, 2)),
            processes=((4, 300, 1, 3), (64, 40, 1, 3), (1024, 30, 128, 3)),
            designs=(4, 64, 1024), output_designs=(4, 64, 1024))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="M = 4 and 64, fewer steps")
    parser.add_argument("--out", type=Path, help="keep the run folders here (default: a temporary folder)")
    parser.add_argument("--json", type=Path, help="write every figure to this file")
    parser.add_argument("--startup-timeout", type=float, default=900.0)
    parser.add_argument("--M", type=int, nargs="+", help="only these M of the plan")
    parser.add_argument("--no-design", action="store_true", help="leave out the design table")
    args = parser.parse_args()
    plan = QUICK if args.quick else FULL
    if args.M:
        keep = set(args.M)
        plan = Plan(tuple(r for r in plan.inprocess if r[0] in keep), tuple(r for r in plan.processes if r[0] in keep),
                    tuple(M for M in plan.designs if M in keep), tuple(M for M in plan.output_designs if M in keep))
    if args.no_design:
        plan = Plan(plan.inprocess, plan.processes, (), ())
    host = machine()
    print(f"machine: {host}", flush=True)
    started = time.monotonic()
    results: dict[str, Any] = {"machine": host, "designs": [], "runs": []}
    for M in plan.designs:
        results["designs"].append(design_figures(M, ESTIMATION))
        print(design_rows(results["designs"][-1:])[-1], flush=True)
    for M in plan.output_designs:
        results["designs"].append(design_figures(M, OUTPUT))
        print(design_rows(results["designs"][-1:])[-1], flush=True)
    with tempfile.TemporaryDirectory(prefix="estimation-cost-") as tmp:
        workdir = args.out or Path(tmp)
        workdir.mkdir(parents=True, exist_ok=True)
        designs: dict[int, dict] = {}

        def pair_for(M: int, steps: int):
            plain, estimated, plain_s, est_s = prepared_pair(M, steps, designs.get(M))
            first = M not in designs
            designs.setdefault(M, plain.design_json())
            print(f"M = {M}, {steps} steps: prepare {plain_s:.1f} s without estimation"
                  f"{' (the controller designed)' if first else ''}, {est_s:.1f} s with it (the estimator designed, "
                  "the controller's design reused)", flush=True)
            return plain, estimated

        for M, steps, repeats in plan.inprocess:
            plain, estimated = pair_for(M, steps)
            results["runs"].append(inprocess_pair(plain, estimated, workdir, repeats))
            print(run_rows(results["runs"][-1:])[-1], flush=True)
        for M, steps, per_process, repeats in plan.processes:
            plain, estimated = pair_for(M, steps)
            results["runs"].append(processes_pair(plain, estimated, per_process, workdir, args.startup_timeout,
                                                  repeats))
            print(run_rows(results["runs"][-1:])[-1], flush=True)
    results["wall_s"] = time.monotonic() - started
    results["end"] = now()
    print()
    print("\n".join(design_rows(results["designs"])))
    print()
    print("\n".join(run_rows(results["runs"])))
    print()
    print("\n".join(memory_rows(results["runs"])))
    print(f"\n{results['wall_s']:.0f} s in all; speed figure at the end {results['end']['speed_ms']:.1f} ms, "
          f"load {results['end']['load']:.1f}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=float))


if __name__ == "__main__":
    main()

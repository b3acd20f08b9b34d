"""Cooperative DMPC (``tv-box-coop``) against ``tv-box``, on the same design.

Two measures, each running ``tv-box`` and then ``tv-box-coop`` on one design (``tv-box``'s, reused
as ``dmpc compare`` does):

- :func:`inprocess_pair`: in this process (``dmpc simulate``'s path, :func:`dmpc.evaluation.compare.timed_run`):
  the paper's example, the chain, the four-tank benchmark (where ``tv-box`` fails);
- :func:`hosted_pair`: as processes (``dmpc run``, :func:`dmpc.bench.trigger.hosted_run`), one agent
  per process or agents hosted many to a process.

Every row has what the run's ``summary.json`` says (verdict, fallbacks, closed-loop cost, plan
messages and their bytes, the QP's solve median, the run's wall time, start-up), the step median
and the slowest step from k = 1, and from its ``trajectory.npz`` the Jacobi rounds of each step and
the QP's iterations. A release carries
the whole system's iterate with ``tv-box-coop``, so its size grows with n N: :func:`release_bytes`
measures the payload of the run's first release, encoded by the coordinator itself.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dmpc.bench import trigger
from dmpc.bench.common import calibration_ms, cell, chain_overrides
from dmpc.bus.codec import MAX_PAYLOAD
from dmpc.bus.faults import PLANT_PROCESS
from dmpc.bus.interface import AliveHandler, Bus, Handler, Timer
from dmpc.bus.memory import MemoryBus
from dmpc.evaluation.compare import timed_run
from dmpc.records.files import SUMMARY, TRAJECTORY
from dmpc.runtime.hosting import group_agents
from dmpc.runtime.inprocess import build_run
from dmpc.runtime.launcher import default_topology
from dmpc.scenario import load_scenario
from dmpc.setup import prepare

METHODS = ("tv-box", "tv-box-coop")
"""The reference first, then the cooperative method, on the reference's design."""
REFERENCE = METHODS[0]
FOURTANK = "scenarios/fourtank.yaml"
FIRST_RELEASE_FROM = 256
"""From this M on, a pair run as processes takes the size of its first release (k = 0, round 0; no
agent solves) rather than stepping every agent once more in this process to step 1."""


# ----------------------------------------------------------------------------- what is run
def case_overrides(case: str, M: int, steps: int | None) -> tuple[str, dict]:
    """The scenario file and overrides of a ``case``: ``paper`` (M = 4) or ``chain`` (M subsystems)
    for ``steps`` steps, or ``fourtank`` (M = 2; ``steps`` None: the scenario's own 600)."""
    if case == "fourtank":
        return FOURTANK, {} if steps is None else {"steps": steps}
    if steps is None:
        raise ValueError(f"the {case} needs a number of steps")
    path, overrides = chain_overrides(M, steps)
    if (case == "paper") != (M == 4):
        raise ValueError(f"the {case} case does not have M = {M}")
    return path, overrides


def method_overrides(method: str) -> dict:
    """The scenario override that selects ``method``."""
    return {"options.method": method}


# ----------------------------------------------------------------------------- figures of one run
def _verdict(summary: dict) -> str:
    """``ok``, or ``failed (<the kinds of its failures>)``."""
    kinds = list(dict.fromkeys(f.get("kind", "?") for f in summary.get("failures") or []))
    verdict = str(summary.get("verdict"))
    return f"{verdict} ({', '.join(kinds)})" if kinds and verdict != "ok" else verdict


def wire_figures(summary: dict, rounds: np.ndarray, M: int) -> dict:
    """Messages of a run from its ``summary`` and the Jacobi ``rounds`` of each of its steps, M agents.

    Returns
    -------
    dict
        ``steps``, ``rounds_k0``, ``rounds_p50`` (rounds per step from k = 1), ``plans_per_step``
        (plan messages per step from k = 1: the plan messages less the k = 0 rounds' M each, over
        K - 1 steps, when every agent answered every round, ``plan_messages`` = M x the rounds; the
        run's plan messages over its K steps otherwise, and ``plans_all_steps`` True),
        ``plan_bytes`` (bytes per plan message), ``solve_us_p50`` (the QP's solve median),
        ``inputs_refused`` (plans refused for inputs outside U_i), ``verdict_text``, ``wall_s`` (the
        run's wall time, ``summary.json``'s: k = 0 and every step, not the start-up).
    """
    rounds = np.asarray(rounds, int)
    messages = summary.get("messages") or {}
    plans, size = messages.get("plan_messages"), messages.get("bytes")
    steps = int(rounds.size)
    every = plans is not None and plans == M * int(rounds.sum()) and steps > 1
    per_step: float | None = None
    if plans is not None and every:
        per_step = (plans - M * int(rounds[0])) / (steps - 1)
    elif plans is not None and steps:
        per_step = plans / steps
    solve = summary.get("solve_time_median_s")
    return {"steps": summary.get("steps", steps), "rounds_k0": int(rounds[0]) if steps else None,
            "rounds_p50": float(np.median(rounds[1:])) if steps > 1 else None,
            "plans_per_step": per_step, "plans_all_steps": not every,
            "plan_bytes": size / plans if plans else None,
            "solve_us_p50": None if solve is None else solve * 1e6,
            "inputs_refused": int(sum((summary.get("inputs_refused") or {}).values())),
            "verdict_text": _verdict(summary), "wall_s": summary.get("wall_time_s")}


def slowest_step(step_s) -> float | None:
    """The slowest step from k = 1 in ms, from per-step times in seconds ``step_s`` (index k: step k,
    NaN where not measured), or None."""
    step = np.asarray(step_s, float)[1:] * 1e3
    step = step[np.isfinite(step)]
    return float(step.max()) if step.size else None


def folder_figures(folder: Path, M: int) -> dict:
    """:func:`wire_figures` of the run folder ``folder`` (M agents), with the QP's iterations from
    k = 1 (``qp_iterations_p50`` and ``qp_iterations_max``, over every agent and step) and, for a
    run as processes (the plant's step times recorded), ``step_ms_max`` (:func:`slowest_step`)."""
    summary = json.loads((folder / SUMMARY).read_text())
    arrays = np.load(folder / TRAJECTORY)
    iterations = np.asarray(arrays["qp_iterations"])[1:]
    figures = wire_figures(summary, arrays["rounds"], M)
    figures.update(qp_iterations_p50=float(np.median(iterations)) if iterations.size else None,
                   qp_iterations_max=int(iterations.max()) if iterations.size else None)
    if summary.get("runtime") == "multi-process":
        figures["step_ms_max"] = slowest_step(arrays["step_time"])
    return figures


class _ReleaseTally(Bus):
    """The coordinator's view of the in-memory bus ``bus``: for every release it publishes (key
    ``.../release``), the open step (``step()``) and the payload's size are appended to ``sizes``."""

    def __init__(self, bus: Bus, sizes: list[tuple[int, int]]) -> None:
        self.bus, self.sizes = bus, sizes
        self.step = lambda: -1

    def publish(self, key: str, payload: bytes) -> None:
        if key.endswith("/release"):
            self.sizes.append((self.step(), len(payload)))
        self.bus.publish(key, payload)

    def subscribe(self, key: str, handler: Handler, hot: bool = False) -> None:
        self.bus.subscribe(key, handler, hot)

    def expect(self, key: str | None) -> None:
        self.bus.expect(key)

    def declare_alive(self, key: str) -> None:
        self.bus.declare_alive(key)

    def watch_alive(self, pattern: str, handler: AliveHandler) -> None:
        self.bus.watch_alive(pattern, handler)

    def now(self) -> float:
        return self.bus.now()

    def call_later(self, delay: float, fn) -> Timer:
        return self.bus.call_later(delay, fn)

    def run(self, until, timeout: float | None = None) -> bool:
        return self.bus.run(until, timeout)

    def close(self) -> None:
        self.bus.close()


def release_sizes(prepared, until=None) -> list[tuple[int, int]]:
    """(step, payload bytes) of each release the coordinator of ``prepared`` publishes, in order, its
    nodes on the in-memory bus of ``dmpc simulate``, until ``until(sizes)`` is true (default: after
    the first release) or the run ends."""
    sizes: list[tuple[int, int]] = []
    done = until or (lambda s: len(s) >= 1)
    tallies: list[_ReleaseTally] = []

    def view(bus: MemoryBus, name: str) -> Bus:
        if name != PLANT_PROCESS:
            return bus
        tallies.append(_ReleaseTally(bus, sizes))
        return tallies[-1]

    run = build_run(prepared, lambda record: None, "wire", bus_for=view)
    for tally in tallies:
        tally.step = lambda: run.coordinator.coordinator.k
    try:
        run.bus.run(until=lambda: done(sizes) or run.coordinator.finished)
    finally:
        run.bus.close()
    return sizes


def release_bytes(prepared, step: int | None = 1) -> int | None:
    """The payload size in bytes of one release of ``prepared``, as its coordinator encodes it on the
    in-memory bus: the last release of step ``step`` (the run is stepped that far, every agent
    solving), or with ``step`` None the first release (k = 0, round 0: no agent has to solve; on a
    system without setpoints every release of a run has its size, tests/test_bench_cooperative.py).
    None if no such release was published."""
    if step is None:
        sizes = release_sizes(prepared)
    else:
        sizes = [(k, size) for k, size in release_sizes(prepared, lambda s: bool(s) and s[-1][0] > step)
                 if k == step]
    return sizes[-1][1] if sizes else None


def step_bytes(row: dict) -> dict:
    """What travels per step from k = 1 in the run ``row``: ``release_bytes_per_step`` (the release's
    size times the rounds per step) and ``kb_per_step`` (those and the plan messages' bytes, each
    payload counted once, whoever receives it)."""
    size, rounds = row.get("release_bytes"), row.get("rounds_p50")
    release = None if size is None or rounds is None else size * rounds
    plans = (None if row.get("plans_per_step") is None or row.get("plan_bytes") is None
             else row["plans_per_step"] * row["plan_bytes"])
    return {"release_bytes_per_step": release,
            "kb_per_step": None if release is None or plans is None else (release + plans) / 1e3}


# ----------------------------------------------------------------------------- the measures
def inprocess_pair(case: str, M: int, steps: int | None, workdir: Path, root: Path = Path(".")) -> dict:
    """``case`` (:func:`case_overrides`: M, ``steps``) run in this process with ``tv-box`` and then
    ``tv-box-coop`` on the same design; run folders in ``workdir``, ``root`` the folder of
    ``scenarios/``.

    Returns
    -------
    dict
        ``case``, ``M``, ``steps``, ``where``, ``calibration_ms`` (this machine's speed just before)
        and ``rows``: per method, the figures of :func:`dmpc.bench.trigger.inprocess_row` (the run
        and its step median), ``step_ms_max`` (:func:`slowest_step`), :func:`folder_figures`, ``release_bytes`` (at step 1), ``release_step`` and :func:`step_bytes`.
    """
    path, base = case_overrides(case, M, steps)
    out: dict = {"case": case, "M": M, "steps": steps, "where": "in process", "calibration_ms": calibration_ms(3),
                 "rows": []}
    design = None
    for method in METHODS:
        prepared = prepare(load_scenario(root / path, {**base, **method_overrides(method)}), design_data=design)
        design = design or prepared.design_json()
        folder = Path(workdir) / f"coop-{case}-M{M}-{method}"
        run = timed_run(prepared, folder)  # what trigger.inprocess_row does, keeping every step's time
        step_s = np.concatenate([[np.nan], run.step_times])
        row = {"method": method, **trigger.run_figures(run.summary), **trigger.step_figures(step_s),
               "step_ms_max": slowest_step(step_s), **folder_figures(folder, M),
               "release_bytes": release_bytes(prepared), "release_step": 1}
        out["rows"].append({**row, **step_bytes(row)})
    out["steps"] = out["rows"][0].get("steps", steps)
    return out


def hosted_pair(case: str, M: int, per_process: int, steps: int, workdir: Path, root: Path = Path("."),
                startup_timeout: float = 900.0, release_step: int | None | str = "auto") -> dict:
    """``case`` (:func:`case_overrides`) designed once, then run as processes for ``steps`` steps with
    ``tv-box`` and right after with ``tv-box-coop``, ``per_process`` agents to a process (what
    ``dmpc run --agents-per-process`` does after designing), each waiting at most
    ``startup_timeout`` seconds to start; run folders in ``workdir``, ``root`` the folder of
    ``scenarios/``; ``release_step``: the step whose release :func:`release_bytes` measures (None:
    the first release; ``"auto"``: step 1 below :data:`FIRST_RELEASE_FROM`, the first release from it on).

    Returns
    -------
    dict
        ``case``, ``M``, ``processes``, ``agents_per_process``, ``topology``, ``steps``, ``where``,
        ``calibration_ms`` (this machine's speed just before) and ``rows``: per method,
        :func:`dmpc.bench.trigger.hosted_run`'s figures (``completed`` False and ``reason`` for a
        run that did not complete), :func:`folder_figures`, ``release_bytes``, ``release_step`` (the
        step whose release was measured, None: the first release) and :func:`step_bytes`.
    """
    path, base = case_overrides(case, M, steps)
    reference = prepare(load_scenario(root / path, {**base, **method_overrides(REFERENCE)}))
    runs = [reference] + [prepare(load_scenario(root / path, {**base, **method_overrides(m)}),
                                  design_data=reference.design_json()) for m in METHODS[1:]]
    hosts = group_agents(reference.names, per_process)
    at = (1 if M < FIRST_RELEASE_FROM else None) if release_step == "auto" else release_step
    assert at is None or isinstance(at, int)
    out: dict = {"case": case, "M": M, "processes": len(hosts), "agents_per_process": max(len(h.agents) for h in hosts),
                 "topology": default_topology(len(hosts)), "steps": steps, "where": "as processes",
                 "calibration_ms": calibration_ms(3), "rows": []}
    for method, prepared in zip(METHODS, runs):
        folder = Path(workdir) / f"coop-hosted-{case}-M{M}-{method}"
        row = {"method": method, **trigger.hosted_run(prepared, per_process, folder, startup_timeout)}
        if (folder / SUMMARY).is_file() and (folder / TRAJECTORY).is_file():
            row.update(folder_figures(folder, M))
        row.update(release_bytes=release_bytes(prepared, at), release_step=at)
        out["rows"].append({**row, **step_bytes(row)})
    return out


# ----------------------------------------------------------------------------- the report's tables
FIGURE_HEADER = ["method", "verdict", "fallbacks", "cost", "cost / tv-box", "k = 0 rounds", "step median (ms)",
                 "slowest step (ms)", "run wall (s)",
                 "plan messages / step", "plan B / message", "release bytes / step", "kB / step",
                 "QP solve median (us)", "QP iterations median / max"]
INPROCESS_HEADER = ["case", "M", "steps", *FIGURE_HEADER, "speed figure (ms)"]
HOSTED_HEADER = ["case", "M", "processes", "agents / process", "steps", *FIGURE_HEADER, "start-up (s)",
                 "speed figure (ms)"]


def cost_ratio(row: dict, ref: dict) -> str:
    """``row``'s closed-loop cost over ``ref``'s (the ``tv-box`` run), or "-" where there is none or
    ``ref`` failed (its cost is then not a reference: its verdict says why)."""
    if row.get("closed_loop_cost") is None or not ref.get("closed_loop_cost") or ref.get("verdict") != "ok":
        return "-"
    return f"{row['closed_loop_cost'] / ref['closed_loop_cost']:.4f}"


def _iterations(row: dict) -> str:
    if row.get("qp_iterations_p50") is None:
        return "-"
    return f"{row['qp_iterations_p50']:.0f} / {row['qp_iterations_max']}"


def _release(row: dict) -> str:
    text = cell(row.get("release_bytes_per_step"), ".0f")
    return f"{text} (k = 0)" if text != "-" and "release_step" in row and row["release_step"] is None else text


def _per_step(row: dict) -> str:
    text = cell(row.get("plans_per_step"), ".1f")
    return f"{text} (all k)" if row.get("plans_all_steps") and text != "-" else text


def figure_cells(row: dict, ref: dict) -> list[str]:
    """The cells of :data:`FIGURE_HEADER` for the run ``row``, ``ref`` the ``tv-box`` run of the pair."""
    return [row["method"], row.get("verdict_text") or cell(row.get("verdict")), cell(row.get("fallbacks")),
            cell(row.get("closed_loop_cost"), ".4f"), cost_ratio(row, ref), cell(row.get("rounds_k0")),
            cell(row.get("step_ms_p50"), ".2f"), cell(row.get("step_ms_max"), ".0f"), cell(row.get("wall_s"), ".1f"),
            _per_step(row), cell(row.get("plan_bytes"), ".0f"),
            _release(row), cell(row.get("kb_per_step"), ".1f"),
            cell(row.get("solve_us_p50"), ".0f"), _iterations(row)]


def inprocess_rows(pair: dict) -> list[list[str]]:
    """The lines of the :func:`inprocess_pair` ``pair``: ``tv-box`` first."""
    ref = pair["rows"][0]
    return [[pair["case"], str(pair["M"]), cell(pair["steps"]), *figure_cells(row, ref),
             cell(pair.get("calibration_ms"), ".1f")] for row in pair["rows"]]


def hosted_rows(pair: dict) -> list[list[str]]:
    """The lines of the :func:`hosted_pair` ``pair`` (a run that did not complete says why)."""
    ref = pair["rows"][0]
    lines = []
    for row in pair["rows"]:
        head = [pair["case"], str(pair["M"]), str(pair["processes"]), str(pair["agents_per_process"]), str(pair["steps"])]
        if not row.get("completed"):
            why = " ".join(str(row.get("reason") or "?").split())[-200:].replace("|", "/")
            lines.append(head + [row["method"], f"did not complete: {why}"]
                         + [""] * (len(HOSTED_HEADER) - len(head) - 2))
            continue
        lines.append(head + figure_cells(row, ref) + [cell(row.get("startup_s"), ".1f"),
                                                      cell(pair.get("calibration_ms"), ".1f")])
    return lines


def payload_note(pairs: list[dict]) -> str:
    """A sentence on the largest release measured in ``pairs`` against the codec's limit."""
    sizes = [(row["release_bytes"], pair["M"], row["method"]) for pair in pairs for row in pair["rows"]
             if row.get("release_bytes")]
    if not sizes:
        return ""
    size, M, method = max(sizes)
    return (f"Largest release measured: {size / 1e3:.1f} kB ({method}, M = {M}), {size / MAX_PAYLOAD:.0%} of the "
            f"codec's limit (`MAX_PAYLOAD`, {MAX_PAYLOAD} bytes).")

"""The event trigger against solving at every step (``options.trigger``: ``event`` and ``always``).

Four measures, each run with ``always`` and then with ``event`` on the same design:

- :func:`sweep`: the paper's example or the chain in this process, the trigger's cost threshold
  (``trigger_cost``) swept over :data:`COSTS`;
- :func:`hosted_pair`: the chain run as processes (``dmpc run --agents-per-process K``), both runs
  back to back, the step time also from step :data:`LATE` on (once the states have settled);
- :func:`disturbed_pair`: the carts with a seeded uniform disturbance on every state, which the
  trigger sees as a prediction error (above its threshold, it solves).

Every row has the closed-loop cost, the QP solves (the plans that reached the coordinator), the
plans kept, the plan messages, kept notices and their bytes (``summary.json``) and the step time.
"""
from __future__ import annotations

import json
import secrets
from pathlib import Path

import numpy as np

from dmpc.bench.common import calibration_ms, cell, chain_overrides
from dmpc.evaluation.compare import timed_run
from dmpc.records.files import SUMMARY, TRAJECTORY
from dmpc.runtime.hosting import group_agents
from dmpc.runtime.launcher import default_topology, launch
from dmpc.scenario import load_scenario
from dmpc.setup import prepare

COSTS = (0.0, 1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0)
"""The cost thresholds swept (``options.trigger_cost``)."""
DEFAULT_COST = 1e-3
"""The cost threshold of the pairs (the scenario option's default)."""
LATE = 20
"""Hosted runs also give the step median from this step on."""
CARTS = "scenarios/carts.yaml"
THRESHOLD = 1e-6
"""The prediction-error threshold of the disturbed carts (``options.trigger_threshold``'s default)."""


# ----------------------------------------------------------------------------- figures of one run
def step_figures(step_s: np.ndarray, late: int = LATE) -> dict:
    """Step medians in ms from per-step times in seconds ``step_s`` (index k: step k, NaN where not
    measured): ``step_ms_p50`` over steps 1 to K-1 (step 0 iterates Jacobi), ``step_ms_p50_late``
    from step ``late`` on (None when the run is shorter)."""
    step = np.asarray(step_s, float)[1:] * 1e3
    step = step[np.isfinite(step)]
    tail = np.asarray(step_s, float)[late:] * 1e3
    tail = tail[np.isfinite(tail)]
    return {"step_ms_p50": float(np.median(step)) if step.size else None,
            "step_ms_p50_late": float(np.median(tail)) if tail.size else None}


def run_figures(summary: dict) -> dict:
    """What a run's ``summary.json`` says of its cost and of what the agents solved, kept and sent."""
    messages = summary.get("messages") or {}
    return {"verdict": summary.get("verdict"), "feasible": summary.get("feasible"),
            "fallbacks": summary.get("fallbacks"), "closed_loop_cost": summary.get("closed_loop_cost"),
            "solves": summary.get("solves"), "keeps": int(summary.get("keeps") or 0),
            "plan_messages": messages.get("plan_messages"), "kept_notices": messages.get("kept_notices"),
            "bytes": messages.get("bytes"), "solve_reasons": dict(summary.get("solve_reasons") or {})}


def trigger_overrides(trigger: str, cost: float | None = None, threshold: float | None = None) -> dict:
    """The scenario overrides of the ``trigger`` (``always`` or ``event``) and its thresholds ``cost`` and
    ``threshold`` (None: the scenario's)."""
    overrides: dict = {"options.trigger": trigger}
    if trigger == "event" and cost is not None:
        overrides["options.trigger_cost"] = cost
    if trigger == "event" and threshold is not None:
        overrides["options.trigger_threshold"] = threshold
    return overrides


def labelled(trigger: str, cost: float | None) -> dict:
    """The keys that name a row: its trigger and cost threshold (None with ``always``)."""
    return {"trigger": trigger, "trigger_cost": cost if trigger == "event" else None}


# ----------------------------------------------------------------------------- in this process
def inprocess_row(path: Path, overrides: dict, workdir: Path, name: str, design: dict | None) -> tuple[dict, dict]:
    """One run of the scenario at ``path`` with ``overrides`` in this process, into ``workdir/name``.

    Returns
    -------
    (dict, dict)
        The row (:func:`run_figures` and :func:`step_figures`) and the design it used (design.json).
    """
    prepared = prepare(load_scenario(path, overrides), design_data=design)
    run = timed_run(prepared, Path(workdir) / name)
    step_s = np.concatenate([[np.nan], run.step_times])
    return {**run_figures(run.summary), **step_figures(step_s)}, design or prepared.design_json()


def sweep(M: int, steps: int, workdir: Path, root: Path = Path("."), costs=COSTS) -> dict:
    """The paper's example (M = 4) or the chain of M in this process for ``steps`` steps: ``always``,
    then ``event`` at each cost threshold of ``costs``; run folders in ``workdir``, ``root`` the
    folder of ``scenarios/``.

    Returns
    -------
    dict
        ``case``, ``M``, ``steps``, ``where``, ``always`` (its row) and ``event`` (a row per threshold).
    """
    path, base = chain_overrides(M, steps)
    always, design = inprocess_row(root / path, {**base, **trigger_overrides("always")}, workdir,
                                   f"sweep-M{M}-always", None)
    rows = []
    for n, cost in enumerate(costs):
        row, _ = inprocess_row(root / path, {**base, **trigger_overrides("event", cost)}, workdir,
                               f"sweep-M{M}-event-{n}", design)
        rows.append({**labelled("event", cost), **row})
    return {"case": "paper" if M == 4 else "chain", "M": M, "steps": steps, "where": "in process",
            "always": {**labelled("always", None), **always}, "event": rows}


def disturbed_pair(bound: float, steps: int, workdir: Path, root: Path = Path("."), threshold: float = THRESHOLD,
                   cost: float = DEFAULT_COST, seed: int = 1) -> dict:
    """The carts (:data:`CARTS`) with a uniform disturbance |w| <= ``bound`` on every state (drawn from
    ``seed``), ``steps`` steps with ``always`` and then ``event`` (``threshold``, ``cost``), in this
    process; run folders in ``workdir``, ``root`` is the folder of ``scenarios/``."""
    names = [str(s.name) for s in load_scenario(root / CARTS).resolved_subsystems()]
    disturbance = {"kind": "uniform", "bound": {name: [bound, bound] for name in names}, "seed": seed}
    base = {"steps": steps, "plant.disturbance": disturbance}
    always, design = inprocess_row(root / CARTS, {**base, **trigger_overrides("always")}, workdir,
                                   f"carts-{bound:g}-always", None)
    event, _ = inprocess_row(root / CARTS, {**base, **trigger_overrides("event", cost, threshold)}, workdir,
                             f"carts-{bound:g}-event", design)
    return {"case": "carts", "M": len(names), "steps": steps, "bound": bound, "seed": seed, "threshold": threshold,
            "always": {**labelled("always", None), **always}, "event": [{**labelled("event", cost), **event}]}


# ----------------------------------------------------------------------------- as processes
def hosted_run(prepared, per_process: int, out: Path, startup_timeout: float = 600.0) -> dict:
    """``prepared`` run as processes of ``per_process`` agents (what ``dmpc run --agents-per-process``
    does after designing) into ``out``, each waiting at most ``startup_timeout`` seconds to start:
    the row of a hosted run, or ``completed`` False and why."""
    result = launch(prepared, out, f"trigger-{len(prepared.names)}-{secrets.token_hex(4)}",
                    startup_timeout=startup_timeout, show_progress=False,
                    topology=default_topology(len(group_agents(prepared.names, per_process))),
                    agents_per_process=per_process)
    if result.code != 0 or not (out / TRAJECTORY).is_file():
        return {"completed": False, "reason": result.message[-600:]}
    summary = json.loads((out / SUMMARY).read_text())
    step_s = np.load(out / TRAJECTORY)["step_time"]
    return {"completed": summary["steps"] == prepared.protocol.steps, "startup_s": summary.get("startup_s"),
            "step0_ms": float(step_s[0] * 1e3) if step_s.size else None,
            **run_figures(summary), **step_figures(step_s)}


def hosted_pair(M: int, per_process: int, steps: int, workdir: Path, root: Path = Path("."),
                cost: float = DEFAULT_COST) -> dict:
    """The chain of M designed once, then run for ``steps`` steps as processes with ``always`` and
    right after with ``event`` (cost threshold ``cost``), both with ``per_process`` agents to a
    process; run folders in ``workdir``, ``root`` the folder of ``scenarios/``.

    Returns
    -------
    dict
        ``M``, ``processes``, ``agents_per_process``, ``topology``, ``steps``, ``calibration_ms``
        (this machine's speed just before), ``always`` and ``event`` (:func:`hosted_run`'s rows).
    """
    path, base = chain_overrides(M, steps)
    scenario = load_scenario(root / path, {**base, **trigger_overrides("always")})
    always = prepare(scenario)
    event = prepare(load_scenario(root / path, {**base, **trigger_overrides("event", cost)}),
                    design_data=always.design_json())
    hosts = group_agents(always.names, per_process)
    row = {"M": M, "processes": len(hosts), "agents_per_process": max(len(h.agents) for h in hosts),
           "topology": default_topology(len(hosts)), "steps": steps, "late": LATE, "calibration_ms": calibration_ms(3)}
    row["always"] = {**labelled("always", None), **hosted_run(always, per_process, workdir / f"hosted-M{M}-always")}
    row["event"] = {**labelled("event", cost), **hosted_run(event, per_process, workdir / f"hosted-M{M}-event")}
    return row


# ----------------------------------------------------------------------------- the report's tables
def _ratio(row: dict, ref: dict, key: str, digits: int) -> str:
    """``row[key]`` over ``ref[key]``, or "-"."""
    if row.get(key) is None or not ref.get(key):
        return "-"
    return f"{row[key] / ref[key]:.{digits}f}"


def _reasons(row: dict) -> str:
    return ", ".join(f"{reason} {count}" for reason, count in row.get("solve_reasons", {}).items()) or "-"


def _threshold(row: dict) -> str:
    return "-" if row.get("trigger_cost") is None else f"{row['trigger_cost']:g}"


def figure_cells(row: dict, ref: dict) -> list[str]:
    """The cells every table of the trigger has, for the run ``row``: trigger, cost threshold, closed-loop
    cost and its ratio to ``ref``'s (the ``always`` run), solves, kept, plan messages, kept notices,
    kB and the share of ``ref``'s solves."""
    size = row.get("bytes")
    return [row["trigger"], _threshold(row), cell(row.get("closed_loop_cost"), ".4f"),
            _ratio(row, ref, "closed_loop_cost", 6), cell(row.get("solves")), cell(row.get("keeps")),
            cell(row.get("plan_messages")), cell(row.get("kept_notices")),
            "-" if size is None else f"{size / 1e3:.1f}", _ratio(row, ref, "solves", 2)]


FIGURE_HEADER = ["trigger", "trigger_cost", "cost", "cost / always", "solves", "kept", "plan messages",
                 "kept notices", "kB", "solves / always"]
SWEEP_HEADER = ["case", "M", "steps", *FIGURE_HEADER, "step median (ms)", "solved for"]
HOSTED_HEADER = ["M", "processes", "agents / process", "steps", *FIGURE_HEADER, "start-up (s)", "step median (ms)",
                 "step median from k = 20 (ms)", "speed figure (ms)"]
CARTS_HEADER = ["disturbance bound", "threshold", *FIGURE_HEADER, "step median (ms)", "solved for"]


def table(header: list[str], rows: list[list[str]]) -> list[str]:
    """A markdown table of the columns ``header`` and the ``rows``."""
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header), *("| " + " | ".join(r) + " |" for r in rows)]


def sweep_rows(s: dict) -> list[list[str]]:
    """One line per run of the :func:`sweep` ``s``: ``always`` first."""
    ref = s["always"]
    return [[s["case"], str(s["M"]), str(s["steps"]), *figure_cells(row, ref), cell(row.get("step_ms_p50"), ".2f"),
             _reasons(row)] for row in [ref, *s["event"]]]


def hosted_rows(h: dict) -> list[list[str]]:
    """The two lines of the :func:`hosted_pair` ``h`` (a run that did not complete says why)."""
    lines = []
    for row in (h["always"], h["event"]):
        head = [str(h["M"]), str(h["processes"]), str(h["agents_per_process"]), str(h["steps"])]
        if not row.get("completed"):
            why = " ".join(str(row.get("reason") or "?").split())[-160:].replace("|", "/")
            lines.append(head + [row["trigger"], f"did not complete: {why}"] + [""] * (len(HOSTED_HEADER) - 6))
            continue
        lines.append(head + figure_cells(row, h["always"]) + [cell(row.get("startup_s"), ".1f"),
                     cell(row.get("step_ms_p50"), ".1f"), cell(row.get("step_ms_p50_late"), ".1f"), cell(h.get("calibration_ms"), ".1f")])
    return lines


def carts_rows(d: dict) -> list[list[str]]:
    """The two lines of the :func:`disturbed_pair` ``d``."""
    ref = d["always"]
    return [[f"{d['bound']:g}", f"{d['threshold']:g}", *figure_cells(row, ref), cell(row.get("step_ms_p50"), ".2f"),
             _reasons(row)] for row in (ref, *d["event"])]


def at_cost(s: dict, cost: float = DEFAULT_COST) -> dict | None:
    """The event row of the sweep ``s`` at the cost threshold ``cost``, or None."""
    return next((row for row in s.get("event", []) if row.get("trigger_cost") == cost), None)

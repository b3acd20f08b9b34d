"""``dmpc compare``: every method on one scenario, each into a normal run folder, side by side.

The offline design is computed once and reused by every method (they share it by definition).
``DIR/<method>/`` is the run folder of each method; ``DIR/comparison.json`` holds, per method:

| key | meaning |
|---|---|
| ``run_dir`` | the method's run folder, relative to DIR |
| ``closed_loop_cost`` | sum_k x(k)'Q x(k) + u(k)'R u(k) |
| ``J``, ``S`` | the lists over k (``summary.json``) |
| ``steps_to_1e-3`` | the first k with ||x(k) - x_s||_inf < 1e-3 (x_s: the last target applied, the origin without setpoints), or null if never |
| ``feasible`` | every QP of every step solved |
| ``fallbacks`` | fallbacks applied (agent-steps) |
| ``solve_time_median_s`` | median QP solve time |
| ``verdict``, ``failures`` | the run's verdict (``ok`` or ``failed``) and the kinds of its failures |

On a scenario with setpoints, the methods that track them run (``MethodSpec.tracks_setpoints``):
by default every one of them, the others left out and named in ``skipped`` with why; a method
listed by name that does not track them is refused. Each entry then also has ``tracking_cost``,
sum_k ||x(k) - x_r(k)||_Q^2 + ||u(k) - u_r(k)||_R^2 around the references (x_r, u_r) (the targets
of the requests, the same for every method), where ``closed_loop_cost`` is around each method's own
applied targets, which its reference governor may hold back for a different number of steps.

With triggers (``triggers=[...]``, ``dmpc compare --triggers always event``, or a scenario whose own
``options.trigger`` is ``event``), each method runs with each trigger, the event trigger only with
the methods that support it (``MethodSpec.supports_trigger``). An entry is then named ``<method>`` for
``always`` and ``<method>+<trigger>`` otherwise (its run folder too), and it also holds:

| key | meaning |
|---|---|
| ``method``, ``trigger`` | the run's method and trigger |
| ``trigger_cost`` | ``options.trigger_cost`` of an ``event`` run (a number or a map by subsystem), else null |
| ``solves`` | QP solves whose plans reached the coordinator (``summary.json``), null for ``centralized`` |
| ``keeps`` | plans kept instead of solved (0 with ``always``), null for ``centralized`` |
| ``plan_messages``, ``kept_notices``, ``bytes`` | the agents' answers that reached the coordinator and their bytes |
| ``solve_reasons`` | why agents solved rather than kept, counted (empty with ``always``) |
| ``step_time_median_s`` | median wall time of a step in this process, steps 1 to K-1 (k = 0 iterates Jacobi) |

and ``comparison.json`` has ``triggers`` (those run). With triggers or setpoints it has ``skipped``:
for each run left out, its entry name and why it did not run (the error of
:func:`dmpc.methods.lacks`, naming the method and what it cannot do).
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dmpc.core.steps import TRIGGERS
from dmpc.core.system import CoupledSystem
from dmpc.methods import METHOD_NAMES, lacks, method_spec, require
from dmpc.records.files import COMPARISON, STEP_LOG, TRAJECTORY
from dmpc.records.run_folder import claim_folder, refuse_used, stage_cost, write_json
from dmpc.records.session import RunRecorder
from dmpc.records.tables import number_text
from dmpc.runtime.inprocess import record_run
from dmpc.setup import prepare

CONVERGED = 1e-3
ALWAYS = "always"
"""The trigger of every step solving: the reference of the event trigger."""


def steps_to(x: np.ndarray, tol: float = CONVERGED, target: np.ndarray | None = None) -> int | None:
    """The first k with ||x(k) - target||_inf < tol, or None; x has shape (K+1, n), target (n,)
    (the origin by default)."""
    hit = np.flatnonzero(np.max(np.abs(x if target is None else x - target), axis=1) < tol)
    return int(hit[0]) if hit.size else None


SETPOINTS_SKIPPED = "the scenario has setpoints"
"""What a method that does not track setpoints cannot do on a scenario that has them."""


def check_methods(methods: list[str] | None, setpoints: bool = False) -> list[str]:
    """The methods to run, checked: by default all of them (with ``setpoints``, :func:`plan_runs`
    leaves out those that do not track them, and names them). ValueError naming an unknown method,
    one listed twice, or, with ``setpoints``, one listed that does not track them."""
    if not methods:
        return list(METHOD_NAMES)
    for name in methods:
        if setpoints:
            require(name, "tracks_setpoints", SETPOINTS_SKIPPED)
        else:
            method_spec(name)
    if len(set(methods)) != len(methods):
        raise ValueError(f"a method is listed twice: {', '.join(methods)}")
    return list(methods)


# ----------------------------------------------------------------------------- triggers
def run_label(method: str, trigger: str) -> str:
    """The name of a run in ``comparison.json`` and of its folder: the method, with ``+<trigger>``
    unless the trigger is ``always``."""
    return method if trigger == ALWAYS else f"{method}+{trigger}"


def check_triggers(triggers: list[str] | None, scenario) -> list[str]:
    """The triggers to run, checked: by default the scenario's own.

    Raises
    ------
    ValueError
        An unknown trigger, one listed twice, or ``event`` with more than one Jacobi round per step.
    """
    chosen = list(triggers) if triggers else [scenario.options.trigger]
    for name in chosen:
        if name not in TRIGGERS:
            raise ValueError(f"unknown trigger '{name}' (known: {', '.join(TRIGGERS)})")
    if len(set(chosen)) != len(chosen):
        raise ValueError(f"a trigger is listed twice: {', '.join(chosen)}")
    if "event" in chosen and scenario.options.iterations != 1:
        raise ValueError(f"'event' needs one Jacobi round per step (options.iterations is {scenario.options.iterations})")
    return chosen


def plan_runs(methods: list[str], triggers: list[str],
              setpoints: bool = False) -> tuple[list[tuple[str, str]], dict[str, str]]:
    """Each of the ``methods`` with each of the ``triggers``: the (method, trigger) pairs to run, in
    that order, and the names of the pairs left out with the reason: with ``setpoints`` (the
    scenario has some), a method that does not track them; a trigger other than ``always`` with a
    method that does not support it."""
    runs, skipped = [], {}
    for method in methods:
        untracked = lacks(method, "tracks_setpoints", SETPOINTS_SKIPPED) if setpoints else None
        for trigger in triggers:
            error = untracked or (None if trigger == ALWAYS else lacks(method, "supports_trigger"))
            if error is None:
                runs.append((method, trigger))
            else:
                skipped[run_label(method, trigger)] = str(error)
    return runs, skipped


def runnable(methods: list[str], triggers: list[str],
             setpoints: bool = False) -> tuple[list[tuple[str, str]], dict[str, str]]:
    """:func:`plan_runs` of ``methods``, ``triggers`` and ``setpoints``; ValueError when it leaves
    nothing to run."""
    runs, skipped = plan_runs(methods, triggers, setpoints)
    if not runs:
        raise ValueError(f"none of the methods {', '.join(methods)} works with the trigger "
                         f"{' or '.join(triggers)} ({'; '.join(sorted(set(skipped.values())))})")
    return runs, skipped


# ----------------------------------------------------------------------------- one run
class TimedRecorder(RunRecorder):
    """A :class:`RunRecorder` that also notes when each step completed (wall clock, this process)."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.completed: list[float] = []

    def on_step(self, record) -> None:
        super().on_step(record)
        self.completed.append(time.perf_counter())

    def step_times(self) -> np.ndarray:
        """Seconds between consecutive steps' completion, shape (K-1,): steps 1 to K-1 (step 0
        iterates Jacobi to convergence and has no step before it)."""
        return np.diff(np.asarray(self.completed, float))


@dataclass
class TimedRun:
    """A run recorded in this process: its summary, failure ("" if none) and step_times (s, one
    per step after the first)."""

    summary: dict
    failure: str
    step_times: np.ndarray

    @property
    def step_time_median_s(self) -> float | None:
        return float(np.median(self.step_times)) if self.step_times.size else None


def timed_run(prepared, run_dir: Path, show_progress: bool = False) -> TimedRun:
    """Run ``prepared`` in this process into the run folder ``run_dir``, timing its steps
    (``show_progress``: a progress bar)."""
    recorder = TimedRecorder(run_dir, prepared, show_progress=show_progress)
    with recorder:
        summary, failure = record_run(prepared, recorder)
    return TimedRun(summary, failure, recorder.step_times())


def with_options(scenario, **options):
    """``scenario`` with some of its ``options`` replaced (method, trigger, ...)."""
    return scenario.model_copy(update={"options": scenario.options.model_copy(update=options)})


# ----------------------------------------------------------------------------- entries
def check_out(out: Path, methods: list[str]) -> None:
    """Create the comparison folder ``out``; RunFolderError if it already holds a comparison or a
    run of one of the ``methods`` (their entry names)."""
    claim_folder(out, COMPARISON, "a comparison")
    for name in methods:
        refuse_used(out / name, STEP_LOG, "a run")


def tracking_cost(arrays, system: CoupledSystem) -> float:
    """sum_k l(x(k) - x_r(k), u(k) - u_r(k)) over the run's steps, around the references x_r, u_r
    (the targets of the requests) of ``trajectory.npz``'s ``arrays``, with the weights of ``system``."""
    u = arrays["u"]
    dx, du = arrays["x"][: u.shape[0]] - arrays["reference"], u - arrays["reference_u"]
    return float(sum(stage_cost(system, dx[k], du[k]) for k in range(u.shape[0])))


def method_entry(run_dir: Path, out: Path, summary: dict, system: CoupledSystem | None = None) -> dict:
    """The comparison.json entry of one method's run folder ``run_dir`` (inside the comparison
    folder ``out``) from its ``summary``; with ``system`` (a scenario with setpoints), also its
    ``tracking_cost``."""
    arrays = np.load(run_dir / TRAJECTORY)
    x = arrays["x"]
    target = arrays["target"][-1] if "target" in arrays.files and arrays["target"].shape[0] else None
    tracked = {} if system is None else {"tracking_cost": tracking_cost(arrays, system)}
    return {
        "run_dir": str(run_dir.relative_to(out)),
        "closed_loop_cost": float(summary["closed_loop_cost"]),
        "J": summary["J"],
        "S": summary["S"],
        "steps_to_1e-3": steps_to(x, target=target),
        "feasible": bool(summary["feasible"]),
        "fallbacks": int(summary["fallbacks"]),
        "solve_time_median_s": summary.get("solve_time_median_s"),
        "verdict": summary.get("verdict"),
        "failures": list(dict.fromkeys(f["kind"] for f in summary.get("failures", []))),
        **tracked,
    }


def trigger_entry(summary: dict, method: str, trigger: str, trigger_cost, step_time_s: float | None) -> dict:
    """What a comparison with triggers adds to an entry: what the agents solved, kept and sent
    (the run's ``summary``), its ``method``, ``trigger`` and ``trigger_cost`` (kept only for a
    trigger other than ``always``), and the step time measured in this process, ``step_time_s``."""
    messages = summary.get("messages") or {}
    sent = bool(messages)
    return {
        "method": method, "trigger": trigger, "trigger_cost": trigger_cost if trigger != ALWAYS else None,
        "solves": summary.get("solves") if sent else None,
        "keeps": int(summary.get("keeps") or 0) if sent else None,
        "plan_messages": messages.get("plan_messages"), "kept_notices": messages.get("kept_notices"),
        "bytes": messages.get("bytes"), "solve_reasons": dict(summary.get("solve_reasons") or {}),
        "step_time_median_s": step_time_s,
    }


def compare(scenario, out: Path, methods: list[str] | None, show_progress: bool = True,
            on_method: Callable[[str, dict], None] | None = None, triggers: list[str] | None = None) -> dict:
    """Run each method (with each trigger) in this process and write ``comparison.json``; returns its content.

    Parameters
    ----------
    scenario : Scenario
        The validated scenario (overrides applied); its ``options.method`` (and ``options.trigger``)
        is replaced by each method's (trigger's).
    out : Path
        The comparison folder (created).
    methods : list of str or None
        Checked with :func:`check_methods`. None (or empty): every method, and on a scenario with
        setpoints those that do not track them are left out and named (``skipped``); a method
        listed that does not track them is refused.
    show_progress : bool
        A progress bar per run.
    on_method : callable (name, entry), optional
        Called after each run.
    triggers : list of str, optional
        Run each method with each of these triggers (:func:`check_triggers`); by default the
        scenario's own. With triggers given, or the scenario's own ``event``, the entries carry
        the trigger's figures (:func:`trigger_entry`).
    """
    setpoints = bool(scenario.setpoints)
    methods = check_methods(methods, setpoints)
    chosen = check_triggers(triggers, scenario)
    runs, skipped = runnable(methods, chosen, setpoints)
    with_triggers = triggers is not None or chosen != [ALWAYS]
    check_out(out, [run_label(m, t) for m, t in runs])
    design_data = None
    entries: dict[str, dict] = {}
    for method, trigger in runs:
        label = run_label(method, trigger)
        prepared = prepare(with_options(scenario, method=method, trigger=trigger), design_data=design_data)
        design_data = design_data or prepared.design_json()
        run = timed_run(prepared, out / label, show_progress)
        entries[label] = method_entry(out / label, out, run.summary, prepared.system if setpoints else None)
        if with_triggers:
            entries[label].update(trigger_entry(run.summary, method, trigger, scenario.options.trigger_cost,
                                                run.step_time_median_s))
        if on_method is not None:
            on_method(label, entries[label])
    data: dict = {"scenario": scenario.name, "methods": entries}
    if with_triggers:
        data["triggers"] = chosen
    if with_triggers or setpoints:
        data["skipped"] = skipped
    write_json(out / COMPARISON, data)
    return data


# ----------------------------------------------------------------------------- the table
def cost_ratios(data: dict, reference: str = "centralized", key: str = "closed_loop_cost") -> dict[str, float | None]:
    """closed-loop cost (or another cost of the entries, ``key``) / the ``reference`` method's, per
    method of the comparison ``data`` (None without the reference)."""
    ref = data["methods"].get(reference)
    if ref is None or not ref.get(key):
        return {m: None for m in data["methods"]}
    return {m: e[key] / ref[key] if key in e else None for m, e in data["methods"].items()}


def has_tracking(data: dict) -> bool:
    """Whether the comparison ``data`` ran on setpoints (its entries carry ``tracking_cost``)."""
    return any("tracking_cost" in e for e in data["methods"].values())


def always_ratios(data: dict) -> dict[str, float | None]:
    """closed-loop cost / the same method's with the trigger ``always``, per entry of the comparison
    ``data`` (None for the ``always`` entries themselves and where that run is missing)."""
    methods = data["methods"]
    ratios: dict[str, float | None] = {}
    for name, e in methods.items():
        ref = methods.get(e.get("method", name)) if e.get("trigger", ALWAYS) != ALWAYS else None
        ratios[name] = e["closed_loop_cost"] / ref["closed_loop_cost"] if ref and ref["closed_loop_cost"] else None
    return ratios


def has_triggers(data: dict) -> bool:
    """Whether the comparison ``data`` ran with triggers (its entries carry the trigger's figures)."""
    return "triggers" in data


def comparison_rows(data: dict) -> list[list[str]]:
    """The comparison as table rows (strings), one per method, in the order run; with setpoints,
    also the column of :data:`TRACKING_HEADER`; with triggers, also those of :data:`TRIGGER_HEADER`."""
    ratios = cost_ratios(data)
    tracking = cost_ratios(data, key="tracking_cost") if has_tracking(data) else None
    more = trigger_cells(data) if has_triggers(data) else {}
    rows = []
    for method, e in data["methods"].items():
        ratio = ratios[method]
        solve = e["solve_time_median_s"]
        verdict = e.get("verdict") or "-"
        if e.get("failures"):
            verdict = f"failed ({', '.join(e['failures'])})"
        tracked = [] if tracking is None else ["-" if tracking[method] is None else number_text(tracking[method])]
        rows.append([method, verdict, "yes" if e["feasible"] else "no", str(e["fallbacks"]), number_text(e["closed_loop_cost"]),
                     "-" if ratio is None else number_text(ratio), *tracked,
                     "never" if e["steps_to_1e-3"] is None else str(e["steps_to_1e-3"]),
                     "-" if solve is None else f"{solve * 1e6:.0f}", *more.get(method, [])])
    return rows


def _count(value) -> str:
    return "-" if value is None else str(value)


def trigger_cells(data: dict) -> dict[str, list[str]]:
    """Per entry, the cells of :data:`TRIGGER_HEADER`."""
    ratios = always_ratios(data)
    cells = {}
    for name, e in data["methods"].items():
        step = e.get("step_time_median_s")
        size = e.get("bytes")
        cells[name] = ["-" if ratios[name] is None else f"{ratios[name]:.6f}", _count(e.get("solves")),
                       _count(e.get("keeps")), _count(e.get("plan_messages")),
                       "-" if size is None else f"{size / 1e3:.1f}", "-" if step is None else f"{step * 1e3:.2f}"]
    return cells


def comparison_header(data: dict) -> list[str]:
    """The table's columns: :data:`COMPARISON_HEADER`, with setpoints :data:`TRACKING_HEADER` after
    its ``/ central``, and with triggers :data:`TRIGGER_HEADER` at the end."""
    header = list(COMPARISON_HEADER)
    if has_tracking(data):
        at = header.index("/ central") + 1
        header[at:at] = TRACKING_HEADER
    return header + (TRIGGER_HEADER if has_triggers(data) else [])


def comparison_legend(data: dict) -> str:
    """What the columns mean (:data:`COMPARISON_LEGEND`, with setpoints :data:`TRACKING_LEGEND`, with
    triggers :data:`TRIGGER_LEGEND`)."""
    return (COMPARISON_LEGEND + (f"; {TRACKING_LEGEND}" if has_tracking(data) else "")
            + (f"; {TRIGGER_LEGEND}" if has_triggers(data) else ""))


COMPARISON_HEADER = ["method", "verdict", "feasible", "fallbacks", "cost", "/ central", "k to 1e-3", "QP us"]
COMPARISON_LEGEND = ("verdict: ok, or the failures found (see each run's summary.json); feasible: every QP solved; "
                     "cost: closed-loop sum of x'Qx + u'Ru (around the targets applied, with setpoints); / central: "
                     "that cost over the centralised one; k to 1e-3: first k with ||x(k) - x_s||_inf < 1e-3 (x_s the "
                     "last target, the origin without setpoints); QP us: median solve time")
TRACKING_HEADER = ["tracking / central"]
TRACKING_LEGEND = ("tracking / central: sum of ||x - x_r||_Q^2 + ||u - u_r||_R^2 around the references (the targets of "
                   "the requests, the same for every method) over the centralised one's; the cost column is around "
                   "each method's own applied targets, which its reference governor may hold back longer")
TRIGGER_HEADER = ["/ always", "solves", "kept", "plans", "kB", "step ms"]
TRIGGER_LEGEND = ("/ always: the cost over the same method's with the trigger always; solves: QP solves whose plans "
                  "reached the coordinator; kept: plans kept instead; plans: plan messages; kB: bytes of the agents' "
                  "answers; step ms: median wall time of a step in this process, k >= 1")

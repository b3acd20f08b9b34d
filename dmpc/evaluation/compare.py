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
"""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from dmpc.core.steps import SETPOINT_METHODS
from dmpc.methods import METHOD_NAMES, method_spec
from dmpc.records.files import COMPARISON, STEP_LOG, TRAJECTORY
from dmpc.records.run_folder import claim_folder, refuse_used, write_json
from dmpc.records.session import RunRecorder
from dmpc.records.tables import number_text
from dmpc.runtime.inprocess import record_run
from dmpc.setup import prepare

CONVERGED = 1e-3


def steps_to(x: np.ndarray, tol: float = CONVERGED, target: np.ndarray | None = None) -> int | None:
    """The first k with ||x(k) - target||_inf < tol, or None; x has shape (K+1, n), target (n,)
    (the origin by default)."""
    hit = np.flatnonzero(np.max(np.abs(x if target is None else x - target), axis=1) < tol)
    return int(hit[0]) if hit.size else None


def check_methods(methods: list[str] | None, setpoints: bool = False) -> list[str]:
    """The methods to run, checked; ValueError naming an unknown one, or one that does not track the
    scenario's ``setpoints``. By default all of them, or with setpoints those that track them."""
    if not methods:
        return list(SETPOINT_METHODS if setpoints else METHOD_NAMES)
    for name in methods:
        method_spec(name)
        if setpoints and name not in SETPOINT_METHODS:
            raise ValueError(f"the method '{name}' does not track setpoints, and the scenario has them (methods that "
                             f"do: {', '.join(SETPOINT_METHODS)})")
    if len(set(methods)) != len(methods):
        raise ValueError(f"a method is listed twice: {', '.join(methods)}")
    return list(methods)


def check_out(out: Path, methods: list[str]) -> None:
    """Create DIR; RunFolderError if it already holds a comparison or a run of one of the methods."""
    claim_folder(out, COMPARISON, "a comparison")
    for name in methods:
        refuse_used(out / name, STEP_LOG, "a run")


def method_entry(run_dir: Path, out: Path, summary: dict) -> dict:
    """The comparison.json entry of one method's run folder."""
    arrays = np.load(run_dir / TRAJECTORY)
    x = arrays["x"]
    target = arrays["target"][-1] if "target" in arrays.files and arrays["target"].shape[0] else None
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
    }


def compare(scenario, out: Path, methods: list[str], show_progress: bool = True,
            on_method: Callable[[str, dict], None] | None = None) -> dict:
    """Run each method in this process and write ``comparison.json``; returns its content.

    Parameters
    ----------
    scenario : Scenario
        The validated scenario (overrides applied); its ``options.method`` is replaced by each method.
    out : Path
        The comparison folder (created).
    methods : list of str
        Checked with :func:`check_methods` (for a scenario with setpoints, those that track them).
    show_progress : bool
        A progress bar per run.
    on_method : callable (method, entry), optional
        Called after each method's run.
    """
    check_methods(methods, setpoints=bool(scenario.setpoints))
    check_out(out, methods)
    design_data = None
    entries: dict[str, dict] = {}
    for method in methods:
        scn = scenario.model_copy(update={"options": scenario.options.model_copy(update={"method": method})})
        prepared = prepare(scn, design_data=design_data)
        if design_data is None:
            design_data = prepared.design_json()
        run_dir = out / method
        with RunRecorder(run_dir, prepared, show_progress=show_progress) as recorder:
            summary, _failure = record_run(prepared, recorder)
        entries[method] = method_entry(run_dir, out, summary)
        if on_method is not None:
            on_method(method, entries[method])
    data = {"scenario": scenario.name, "methods": entries}
    write_json(out / COMPARISON, data)
    return data


def cost_ratios(data: dict, reference: str = "centralized") -> dict[str, float | None]:
    """closed-loop cost / the reference method's, per method (None without the reference)."""
    ref = data["methods"].get(reference)
    if ref is None or not ref["closed_loop_cost"]:
        return {m: None for m in data["methods"]}
    return {m: e["closed_loop_cost"] / ref["closed_loop_cost"] for m, e in data["methods"].items()}


def comparison_rows(data: dict) -> list[list[str]]:
    """The comparison as table rows (strings), one per method, in the order run."""
    ratios = cost_ratios(data)
    rows = []
    for method, e in data["methods"].items():
        ratio = ratios[method]
        solve = e["solve_time_median_s"]
        verdict = e.get("verdict") or "-"
        if e.get("failures"):
            verdict = f"failed ({', '.join(e['failures'])})"
        rows.append([method, verdict, "yes" if e["feasible"] else "no", str(e["fallbacks"]), number_text(e["closed_loop_cost"]),
                     "-" if ratio is None else number_text(ratio),
                     "never" if e["steps_to_1e-3"] is None else str(e["steps_to_1e-3"]),
                     "-" if solve is None else f"{solve * 1e6:.0f}"])
    return rows


COMPARISON_HEADER = ["method", "verdict", "feasible", "fallbacks", "cost", "/ central", "k to 1e-3", "QP us"]
COMPARISON_LEGEND = ("verdict: ok, or the failures found (see each run's summary.json); feasible: every QP solved; "
                     "cost: closed-loop sum of x'Qx + u'Ru (around the targets applied, with setpoints); / central: "
                     "that cost over the centralised one; k to 1e-3: first k with ||x(k) - x_s||_inf < 1e-3 (x_s the "
                     "last target, the origin without setpoints); QP us: median solve time")



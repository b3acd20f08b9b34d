"""``dmpc bench``: run the benchmarks of dmpc.bench.measures and write benchmarks/RESULTS.md."""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from rich.progress import Progress

from dmpc.bench import common, cooperative, measures, setpoints, trigger
from dmpc.bench.common import cell
from dmpc.bench.scale import HEADER as SCALE_HEADER
from dmpc.bench.scale import markdown_row as scale_markdown_row
from dmpc.bench.scale import scale_row
from dmpc.terminal.console import stderr_console

FULL: dict[str, Any] = {
    "qp_horizons": [5, 10, 20], "qp_repeat": 20,
    "runtime": [(4, 300), (16, 150), (32, 80), (64, 30), (128, 15)],
    "baselines": [4, 16, 32, 64], "baseline_steps": 30, "design": [4, 8, 16, 32, 64, 128, 256, 1024],
    "design_compare": 256, "floor_sets": 5, "scale": [(256, 64, 30), (1024, 128, 10)], "setpoints": [4, 64, 256],
    "trigger": {"sweeps": [(4, 60), (64, 30)], "hosted": [(64, 1, 40), (1024, 128, 40)],
                "carts": [1e-7, 1e-6, 1e-5, 1e-3], "carts_steps": 80},
    "cooperative": {"inprocess": [("paper", 4, 60), ("chain", 64, 30), ("fourtank", 2, None)],
                    "hosted": [("paper", 4, 1, 60), ("chain", 64, 1, 30), ("chain", 1024, 128, 10)]}}
QUICK: dict[str, Any] = {
    "qp_horizons": [10], "qp_repeat": 3, "runtime": [(4, 300)], "baselines": [4], "baseline_steps": 30,
    "design": [4, 8], "design_compare": 8, "floor_sets": 3, "scale": [], "setpoints": [4],
    "trigger": {"sweeps": [(4, 60)], "hosted": [], "carts": [1e-5], "carts_steps": 40},
    "cooperative": {"inprocess": [("paper", 4, 60)], "hosted": [("paper", 4, 1, 60)]}}
"""``floor_sets``: floor and run alternated that many times at M = 4 (once at larger M). ``scale``:
rows (M, agents per process, steps) of the chain run with agents hosted many to a process.
``setpoints``: the M of the chain for what a setpoint costs (:mod:`dmpc.bench.setpoints`).
``trigger`` (:mod:`dmpc.bench.trigger`): ``sweeps``, (M, steps) in this process over the cost
threshold; ``hosted``, (M, agents per process, steps) as processes; ``carts``, the disturbance
bounds of the carts, run ``carts_steps`` steps. ``cooperative`` (:mod:`dmpc.bench.cooperative`):
``inprocess``, (case, M, steps) in this process (steps None: the scenario's); ``hosted``, (case, M,
agents per process, steps) as processes."""

HISTORY_HEADING = "## History: earlier measurements (dated, not regenerated)"
"""Everything of a report from this heading on is written by hand and kept when it is regenerated."""


def run_all(quick: bool, root: Path, show_progress: bool = True) -> dict:
    """Run every benchmark of the ``quick`` or the full plan (:data:`QUICK`, :data:`FULL`); ``root`` is the
    folder of ``scenarios/``;
    ``show_progress``: a progress bar on the terminal. The results as JSON-ready data."""
    plan = QUICK if quick else FULL
    tasks = (len(plan["qp_horizons"]) + len(plan["runtime"]) + 3 * len(plan["baselines"]) + len(plan["design"])
             + len(plan["scale"]) + len(plan["setpoints"]) + trigger_tasks(plan["trigger"])
             + cooperative_tasks(plan["cooperative"]))
    results: dict = {"machine": common.machine(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                     "quick": quick, "qp": [], "runtime": [], "inprocess": [], "central_osqp": [],
                     "central_cvxpy": [], "design": [], "scale": [], "setpoints": [],
                     "trigger": {"sweeps": [], "hosted": [], "carts": []},
                     "cooperative": {"inprocess": [], "hosted": []}}
    started = time.monotonic()
    with Progress(console=stderr_console(), transient=True, disable=not show_progress) as progress, \
            common.workdir() as tmp:
        task = progress.add_task("benchmarks", total=tasks)

        def step(label: str) -> None:
            progress.update(task, advance=1, description=label)

        for N in plan["qp_horizons"]:
            results["qp"].append(measures.qp_solve_times(N, plan["qp_repeat"], root))
            step(f"QP N={N}")
        qp10 = next((q for q in results["qp"] if q["N"] == 10), None) or measures.qp_solve_times(10, 1, root)
        for M, steps in plan["runtime"]:
            results["runtime"].append(measures.run_against_floor(M, steps, qp10["us_p50"], Path(tmp), root,
                                                              sets=plan["floor_sets"] if M == 4 else 1))
            step(f"multi-process M={M}")
        for M in plan["baselines"]:
            results["inprocess"].append(measures.run_inprocess(M, plan["baseline_steps"], root))
            step(f"in-process M={M}")
            results["central_osqp"].append(measures.run_central_osqp(M, plan["baseline_steps"], root))
            step(f"centralised OSQP M={M}")
            results["central_cvxpy"].append(measures.run_central_cvxpy(M, plan["baseline_steps"], root))
            step(f"centralised CVXPY M={M}")
        for M in plan["design"]:
            results["design"].append(measures.design_scaling(M, root, compare=M <= plan["design_compare"]))
            step(f"design M={M}")
        for M, per_process, steps in plan["scale"]:
            results["scale"].append(scale_row(M, per_process, steps, Path(tmp), root))
            step(f"hosted M={M}")
        for M in plan["setpoints"]:
            results["setpoints"].append({**setpoints.target_costs(M, root), **setpoints.step_costs(M, root=root)})
            step(f"setpoints M={M}")
        run_trigger(plan["trigger"], results["trigger"], Path(tmp), root, step)
        run_cooperative(plan["cooperative"], results["cooperative"], Path(tmp), root, step)
    results["seconds"] = time.monotonic() - started
    results["machine"]["load_average_end"] = common.load_average()
    results["headline"] = headline(results)
    return results


def trigger_tasks(plan: dict) -> int:
    """The progress steps of the event trigger's measures in ``plan`` (:data:`FULL`'s ``trigger``)."""
    return len(plan["sweeps"]) + len(plan["hosted"]) + len(plan["carts"])


def run_trigger(plan: dict, into: dict, workdir: Path, root: Path, step) -> None:
    """The event trigger against ``always`` (:mod:`dmpc.bench.trigger`) as ``plan`` (:data:`FULL`'s
    ``trigger``) says, appended to ``into``; runs go to ``workdir``, ``root`` is the folder of ``scenarios/``,
    and ``step(label)``
    is called after each measure (progress)."""
    for M, steps in plan["sweeps"]:
        into["sweeps"].append(trigger.sweep(M, steps, workdir, root))
        step(f"trigger sweep M={M}")
    for bound in plan["carts"]:
        into["carts"].append(trigger.disturbed_pair(bound, plan["carts_steps"], workdir, root))
        step(f"trigger carts w={bound:g}")
    for M, per_process, steps in plan["hosted"]:
        into["hosted"].append(trigger.hosted_pair(M, per_process, steps, workdir, root))
        step(f"trigger hosted M={M}")


def cooperative_tasks(plan: dict) -> int:
    """The progress steps of the cooperative method's measures in ``plan`` (:data:`FULL`'s ``cooperative``)."""
    return len(plan["inprocess"]) + len(plan["hosted"])


def run_cooperative(plan: dict, into: dict, workdir: Path, root: Path, step) -> None:
    """``tv-box-coop`` against ``tv-box`` (:mod:`dmpc.bench.cooperative`) as ``plan`` (:data:`FULL`'s
    ``cooperative``) says, appended to ``into``; runs go to ``workdir``, ``root`` is the folder of
    ``scenarios/``, and ``step(label)`` is called after each measure (progress)."""
    for case, M, steps in plan["inprocess"]:
        into["inprocess"].append(cooperative.inprocess_pair(case, M, steps, workdir, root))
        step(f"cooperative {case} M={M}")
    for case, M, per_process, steps in plan["hosted"]:
        into["hosted"].append(cooperative.hosted_pair(case, M, per_process, steps, workdir, root))
        step(f"cooperative hosted M={M}")


def headline(results: dict) -> dict:
    """The figures that matter most, from ``results`` (:func:`run_all`), None where not measured."""
    qp10 = next((q for q in results["qp"] if q["N"] == 10), None)
    m4 = next((r for r in results["runtime"] if r["M"] == 4 and r.get("completed")), None)
    done = [r["M"] for r in results["runtime"] if r.get("completed")]
    floor = m4.get("floor") if m4 and m4.get("floor", {}).get("completed") else None
    return {
        "qp_solve_us_p50": qp10["us_p50"] if qp10 else None,
        "step_ms_p50_m4": m4["step_ms_p50"] if m4 else None,
        "step_ms_p99_m4": m4["step_ms_p99"] if m4 else None,
        "floor_step_ms_p50_m4": floor["step_ms_p50"] if floor else None,
        "floor_step_ms_p99_m4": floor["step_ms_p99"] if floor else None,
        "step_over_floor_p50_m4": m4.get("over_floor_p50") if m4 else None,
        "step_over_floor_p99_m4": m4.get("over_floor_p99") if m4 else None,
        "rss_mb_per_agent": max((r["rss_mb_per_agent"] for r in results["runtime"] if r.get("rss_mb_per_agent")),
                                default=None),
        "max_agents_run": max(done + [r["M"] for r in results.get("scale", []) if r.get("completed")], default=0),
        "startup_s_m128": _at(results["runtime"], 128, "startup_s"),
        "design_s_m1024": _at(results["design"], 1024, "design_s"),
        "step_ms_p50_m1024_hosted": _at(results.get("scale", []), 1024, "step_ms_p50"),
        **trigger_headline(results.get("trigger") or {}),
    }


def trigger_headline(measured: dict) -> dict:
    """The event trigger's figures of the headline, from its ``measured`` results: on the paper's
    example in process (cost threshold :data:`~dmpc.bench.trigger.DEFAULT_COST`), its QP solves,
    bytes and closed-loop cost over ``always``'s; at M = 1024 hosted, both step medians from step 20 on."""
    paper = next((s for s in measured.get("sweeps", []) if s["M"] == 4), None)
    event = trigger.at_cost(paper) if paper else None
    hosted = next((h for h in measured.get("hosted", []) if h["M"] == 1024), None)
    both = hosted is not None and hosted["always"].get("completed") and hosted["event"].get("completed")
    out: dict = {}
    if paper and event:
        always = paper["always"]
        out.update(event_solves_over_always_paper=event["solves"] / always["solves"],
                   event_bytes_over_always_paper=event["bytes"] / always["bytes"],
                   event_cost_over_always_paper=event["closed_loop_cost"] / always["closed_loop_cost"])
    if both and hosted is not None:
        out.update(always_step_ms_p50_late_m1024_hosted=hosted["always"]["step_ms_p50_late"],
                   event_step_ms_p50_late_m1024_hosted=hosted["event"]["step_ms_p50_late"])
    return out


def _at(rows: list[dict], M: int, key: str):
    """``key`` of the completed row of ``M`` (a design row counts as completed), or None."""
    row = next((r for r in rows if r["M"] == M and r.get("completed", True)), None)
    return None if row is None else row.get(key)


def targets(results: dict) -> list[tuple[str, str, str]]:
    """(target, measured, met) for each performance target dmpc is held to, from ``results``; "-" where
    not measured."""
    rows: list[tuple[str, str, str]] = []

    def row(target: str, measured: str, met: bool | None) -> None:
        rows.append((target, measured, "-" if met is None else ("yes" if met else "no")))

    qp10 = next((q for q in results["qp"] if q["N"] == 10), None)
    row("local QP, N = 10: median <= 60 us", f"{qp10['us_p50']:.1f} us" if qp10 else "-",
        qp10["us_p50"] <= 60 if qp10 else None)
    m4 = next((r for r in results["runtime"] if r["M"] == 4 and r.get("completed")), None)
    row("M = 4 lockstep step: median <= 1 ms", f"{m4['step_ms_p50']:.2f} ms" if m4 else "-",
        m4["step_ms_p50"] <= 1 if m4 else None)
    row("M = 4 lockstep step: p99 <= 3 ms", f"{m4['step_ms_p99']:.2f} ms" if m4 else "-",
        m4["step_ms_p99"] <= 3 if m4 else None)
    ratio50, ratio99 = (m4.get("over_floor_p50"), m4.get("over_floor_p99")) if m4 else (None, None)
    row("M = 4 lockstep step: median <= 1.5x the bus floor's (same run)",
        f"{ratio50:.2f}x ({m4['step_ms_p50']:.2f} / {m4['floor']['step_ms_p50']:.2f} ms)" if ratio50 and m4 else "-",
        ratio50 <= 1.5 if ratio50 else None)
    row("M = 4 lockstep step: p99 <= 2x the bus floor's p99 (same run)",
        f"{ratio99:.2f}x ({m4['step_ms_p99']:.2f} / {m4['floor']['step_ms_p99']:.2f} ms)" if ratio99 and m4 else "-",
        ratio99 <= 2 if ratio99 else None)
    by_m = {r["M"]: r for r in results["runtime"]}
    for M, what in ((64, "runs to completion"), (128, "attempted")):
        r = by_m.get(M)
        if r is None:
            row(f"M = {M} {what}", "not run", None)
        else:
            done = bool(r.get("completed"))
            row(f"M = {M} {what}", f"{'completed' if done else 'did not complete'} ({r.get('topology', '-')})",
                done if M == 64 else True)
    startup = _at(results["runtime"], 128, "startup_s")
    row("M = 128, one process per agent: start-up <= 30 s", "not run" if startup is None else f"{startup:.1f} s",
        None if startup is None else startup <= 30)
    rss = [(r["M"], r["rss_mb_per_agent"]) for r in results["runtime"] if r.get("rss_mb_per_agent")]
    over = [M for M, mb in rss if mb > 80]
    row("resident memory per agent <= 80 MB",
        ", ".join(f"{mb:.0f} MB at M = {M}" for M, mb in rss) or "-", (not over) if rss else None)
    multi = {r["M"]: r["step_ms_p50"] for r in results["runtime"] if r.get("completed")}
    for key, label, from_m in (("central_cvxpy", "the centralised CVXPY step, every M", 0),
                               ("central_osqp", "the centralised OSQP step, M >= 32", 32)):
        pairs = [(c["M"], multi[c["M"]], c["step_ms_p50"]) for c in results[key]
                 if c["M"] in multi and c["M"] >= from_m]
        row(f"DMPC multi-process step faster than {label}",
            ", ".join(f"{mp / ref:.2g}x at M = {M}" for M, mp, ref in pairs) or "-",
            all(mp < ref for _, mp, ref in pairs) if pairs else None)
    hosted = next((r for r in results.get("scale", []) if r["M"] == 1024), None)
    if hosted is None:
        row("M = 1024 end to end, agents hosted many to a process: completes", "not run", None)
    else:
        done = bool(hosted.get("completed"))
        said = (f"{hosted['steps']} steps, {hosted['processes']} processes of {hosted['agents_per_process']} agents"
                if done else "did not complete")
        row("M = 1024 end to end, agents hosted many to a process: completes", said, done)
    design = _at(results["design"], 1024, "design_s")
    row("M = 1024 design <= 3 min", "not run" if design is None else f"{design:.1f} s",
        None if design is None else design <= 180)
    return rows


def markdown(results: dict, command: str) -> str:
    """The report of ``results``: when and where, the headline and the targets first, then every table.

    ``command`` is what regenerates it. The figures and the history are added by
    :func:`write_report`.
    """
    m = results["machine"]
    when = f" {results['date']}" if results.get("date") else ""
    lines = ["# Benchmarks", "",
             f"Measured{when} on {m['machine']}, {m['cores']} cores, {m['memory_gib']} GiB, Python {m['python']}; "
             f"{results['seconds']:.0f} s in all{' (the quick subset)' if results.get('quick') else ''}. "
             f"Regenerate with `{command}`.", "",
             f"Speed of this machine at the time: {m.get('calibration_ms', float('nan')):.1f} ms for 10^6 Python "
             "additions (best of 7). Shared virtual machines vary from hour to hour; compare runs only with this "
             "figure alongside." + _load_text(m), ""]
    lines += headline_lines(results)
    lines += ["## Targets", "", "Step ratios are DMPC multi-process time over the reference's (below 1 is faster).", "",
              "| target | measured | met |", "|---|---|---|"]
    lines += [f"| {t} | {m} | {ok} |" for t, m, ok in targets(results)]
    lines += ["", "## Local QP (paper's subsystem, one agent's closed-loop sequence replayed, vector updates included)",
              "", "| N | solves | median (us) | p99 (us) |", "|---|---|---|---|"]
    lines += [f"| {q['N']} | {q['solves']} | {q['us_p50']:.1f} | {q['us_p99']:.1f} |" for q in results["qp"]]
    lines += ["", "## Multi-process lockstep (`dmpc run`, all processes on this machine)", "",
              "Step time: from the plant starting to send the release of step k to the step's completion, on the "
              "plant's clock, k = 0 (Jacobi to convergence) excluded. Bus share: step time minus the slowest agent's QP "
              "time. Memory: peak while stepping.", "",
              "Floor: a bare Zenoh lockstep loop measured just before each run (`dmpc.bench.floor`): the same "
              "processes, topology and neighbours, payloads of the run's release and plan sizes, one release "
              "broadcast per step, and the QP's median (N = 10) burnt as CPU by each agent; nothing decoded, "
              "checked or recorded. x floor: the run's step figure over the floor's.", "",
              "Topology: `mesh` (agents peer to peer) up to 64 agents, `star` (agents as clients of the "
              "plant's router) above; wall: the whole `dmpc run`, start-up included.", "",
              "| M | topology | steps | wall (s) | step median (ms) | step p99 (ms) | floor median (ms) | floor p99 (ms) | "
              "x floor median | x floor p99 | bus share | RSS/agent (MB) | PSS/agent (MB) | RSS total (MB) | "
              "PSS total (MB) |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results["runtime"]:
        floor = r.get("floor") if r.get("floor", {}).get("completed") else {}
        if r.get("completed"):
            lines.append(f"| {r['M']} | {r.get('topology', '-')} | {r['steps']} | {r['wall_s']:.0f} | "
                         f"{r['step_ms_p50']:.2f} | {r['step_ms_p99']:.2f} | {cell(floor.get('step_ms_p50'))} | "
                         f"{cell(floor.get('step_ms_p99'))} | {cell(r.get('over_floor_p50'))} | "
                         f"{cell(r.get('over_floor_p99'))} | "
                         f"{r['bus_share_p50']:.0%} | {cell(r['rss_mb_per_agent'])} | {cell(r['pss_mb_per_agent'])} | "
                         f"{r['rss_mb_total']:.0f} | {r['pss_mb_total']:.0f} |")
        else:
            reason = " ".join(str(r.get("reason", "?")).split())[:160].replace("|", "/")
            lines.append(f"| {r['M']} | {r.get('topology', '-')} | did not complete: {reason} | | | | | | | | | | | | |")
    for r in results["runtime"]:
        if len(r.get("sets", [])) > 1:
            shown = "; ".join(f"{p['floor_ms_p50']:.2f} / {p['floor_ms_p99']:.2f} then {p['step_ms_p50']:.2f} / "
                              f"{p['step_ms_p99']:.2f}" for p in r["sets"])
            lines += ["", f"M = {r['M']}: floor and run alternated {len(r['sets'])} times (step median / p99 in ms, "
                          f"floor then run): {shown}. The row gives the medians over the sets and the medians of "
                          "each set's ratios."]
    lines += ["", "## Side by side: the same closed loop, per-step time and closed-loop cost", "",
              "| M | DMPC multi-process (ms) | DMPC in-process (ms) | centralised OSQP (ms) | centralised CVXPY (ms) | "
              "cost DMPC | cost centralised OSQP | cost CVXPY | multi-process / CVXPY | multi-process / OSQP |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    multi = {r["M"]: r for r in results["runtime"] if r.get("completed")}
    for ip, co, cc in zip(results["inprocess"], results["central_osqp"], results["central_cvxpy"]):
        M = ip["M"]
        mp = multi.get(M)
        mp_ms = mp["step_ms_p50"] if mp else None
        lines.append(f"| {M} | {cell(mp_ms)} | {ip['step_ms_p50']:.3g} | {co['step_ms_p50']:.3g} | "
                     f"{cc['step_ms_p50']:.3g} | {ip['closed_loop_cost']:.4g} | {co['closed_loop_cost']:.4g} | "
                     f"{cc['closed_loop_cost']:.4g} | {cell(mp_ms / cc['step_ms_p50'] if mp_ms else None)} | "
                     f"{cell(mp_ms / co['step_ms_p50'] if mp_ms else None)} |")
    lines += ["", "## Offline design against M (chain family, LMI gains, horizon 10)", "",
              "LMI: gains and their check; X^f: the terminal set (redundancy decided on each row's neighbourhood); "
              "start LP: the start's feasibility at the horizon; design: all of it. X^f plain: one LP over the whole "
              "set per test (the earlier method), with its set compared to the other's.", "",
              "| M | LMI (s) | X^f (s) | start LP (s) | design (s) | rows of Omega | t* | sigma0 | X^f plain (s) | "
              "same Omega, sigma0 |", "|---|---|---|---|---|---|---|---|---|---|"]
    for d in results["design"]:
        same = "-" if "same_omega" not in d else ("yes" if d["same_omega"] and d["same_sigma0"] else "NO")
        lines.append(f"| {d['M']} | {d['lmi_s']:.2f} | {d['terminal_set_s']:.2f} | {cell(d.get('start_check_s'))} | "
                     f"{cell(d.get('design_s'))} | {d['omega_rows']} | {d['t_star']} | {cell(d.get('sigma0'), '.6g')} | "
                     f"{cell(d.get('terminal_set_plain_s'))} | {same} |")
    lines += scale_lines(results.get("scale", []))
    lines += setpoint_lines(results.get("setpoints", []))
    lines += trigger_lines(results.get("trigger") or {})
    lines += cooperative_lines(results.get("cooperative") or {})
    return "\n".join(lines) + "\n"


def _load_text(m: dict) -> str:
    """The machine's load average at the start and the end, if measured: other work slows every figure."""
    if m.get("load_average") is None:
        return ""
    end = f" and {m['load_average_end']:.1f} at the end" if m.get("load_average_end") is not None else ""
    return (f" Load average (1 min): {m['load_average']:.1f} at the start{end}, on {m['cores']} cores: other work "
            "running beside the benchmarks slows them.")


def headline_lines(results: dict) -> list[str]:
    """The headline of ``results``: the figures that matter in a sentence each, and as JSON
    (``dmpc bench --json``)."""
    h = results["headline"]
    said = []
    if h.get("step_ms_p50_m4") is not None:
        floor = (f" ({h['step_over_floor_p50_m4']:.2f}x and {h['step_over_floor_p99_m4']:.2f}x a bare Zenoh loop's)"
                 if h.get("step_over_floor_p50_m4") and h.get("step_over_floor_p99_m4") else "")
        said.append(f"- The paper's example (M = 4) over Zenoh, one process per agent: step median "
                    f"{h['step_ms_p50_m4']:.2f} ms, p99 {h['step_ms_p99_m4']:.2f} ms{floor}.")
    if h.get("qp_solve_us_p50") is not None:
        said.append(f"- One agent's QP (N = 10): median {h['qp_solve_us_p50']:.0f} us.")
    if h.get("startup_s_m128") is not None:
        said.append(f"- M = 128, one process per agent: start-up {h['startup_s_m128']:.1f} s.")
    if h.get("design_s_m1024") is not None or h.get("step_ms_p50_m1024_hosted") is not None:
        parts = []
        if h.get("design_s_m1024") is not None:
            parts.append(f"design {h['design_s_m1024']:.0f} s")
        if h.get("step_ms_p50_m1024_hosted") is not None:
            parts.append(f"step median {h['step_ms_p50_m1024_hosted']:.0f} ms with agents hosted many to a process")
        said.append(f"- M = 1024: {', '.join(parts)}.")
    if h.get("rss_mb_per_agent") is not None:
        said.append(f"- Largest resident memory of an agent process: {h['rss_mb_per_agent']:.0f} MB; largest M run: "
                    f"{h['max_agents_run']}.")
    said += trigger_said(results)
    rows = targets(results)
    judged = [ok for _, _, ok in rows if ok != "-"]
    said.append(f"- Targets met: {judged.count('yes')} of {len(judged)} measured (table below).")
    return ["## Headline", "", *said, "", "```json", json.dumps(h, indent=2), "```", ""]


def trigger_said(results: dict) -> list[str]:
    """The headline's lines of the event trigger in ``results`` (none when it was not measured)."""
    h = results["headline"]
    said = []
    if h.get("event_solves_over_always_paper") is not None:
        paper = next(s for s in results["trigger"]["sweeps"] if s["M"] == 4)
        event = trigger.at_cost(paper)
        assert event is not None
        said.append(f"- Event trigger (trigger_cost {trigger.DEFAULT_COST:g}), the paper's example in process, "
                    f"{paper['steps']} steps: {event['solves']} QP solves and plan messages against "
                    f"{paper['always']['solves']} ({h['event_solves_over_always_paper']:.0%}), "
                    f"{h['event_bytes_over_always_paper']:.0%} of the bytes, closed-loop cost x"
                    f"{h['event_cost_over_always_paper']:.6f}.")
    if h.get("event_step_ms_p50_late_m1024_hosted") is not None:
        said.append(f"- M = 1024 hosted, from step {trigger.LATE} on: step median "
                    f"{h['event_step_ms_p50_late_m1024_hosted']:.0f} ms with the event trigger, "
                    f"{h['always_step_ms_p50_late_m1024_hosted']:.0f} ms solving at every step (run just before).")
    return said


def scale_lines(rows: list[dict]) -> list[str]:
    """The table of the chain run with agents hosted many to a process (:mod:`dmpc.bench.scale`), one
    line per row of ``rows``."""
    if not rows:
        return []
    return ["", "## Agents hosted many to a process", "",
            "The chain of M copies of the paper's subsystem, designed (the same `prepare` as `dmpc run`), run with "
            "`dmpc run --agents-per-process K` in lockstep, then the centralised MPC (one OSQP problem over the "
            "whole system, same design) in closed loop for the same steps (`dmpc.bench.scale`). Start-up: processes "
            "started to the first release. Step: steps 1 to K-1. RSS: peak while stepping, shared pages counted in "
            "every process. Cost ratio: the DMPC run's closed-loop cost over the centralised loop's.", "",
            "| " + " | ".join(SCALE_HEADER) + " |", "|" + "---|" * len(SCALE_HEADER),
            *[scale_markdown_row(r) for r in rows]]


def setpoint_lines(rows: list[dict]) -> list[str]:
    """The table of what a setpoint costs (:mod:`dmpc.bench.setpoints`), one line per row of ``rows``."""
    if not rows:
        return []
    return ["", "## What a setpoint costs (chain family, in this process)", "",
            "A new target: the steady-state QP of a new request (x_{1,1} asked; median of five values, the first "
            "request of a run, which also builds the QP's matrices, apart). Its terminal set: lambda and sigma at "
            "its centre (X^f scaled, no LP). Governor: one step of the reference governor that bisects (a jump "
            "from the origin). Step times in process (`dmpc simulate`'s loop, 40 steps, x_{1,1} = 1 asked from "
            "step 20): the median step without setpoints, with the schedule before the change, the step whose end "
            "decides the new target, and the median step after it (around the target).", "",
            "| M | n | rows of Omega | first target (ms) | new target (ms) | terminal set (ms) | governor step (ms) "
            "| step without (ms) | step before (ms) | step deciding the target (ms) | step around the target (ms) |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
            *[f"| {r['M']} | {r['n']} | {r['omega_rows']} | {r['first_target_ms']:.1f} | {r['target_ms']:.1f} | "
              f"{r['terminal_set_ms']:.2f} | {r['governor_ms']:.1f} | {r['plain_ms_p50']:.2f} | "
              f"{r['tracked_ms_p50']:.2f} | {r['change_step_ms']:.2f} | {r['around_target_ms_p50']:.2f} |"
              for r in rows]]


def trigger_lines(measured: dict) -> list[str]:
    """The section of the event trigger against ``always`` (:mod:`dmpc.bench.trigger`), from its
    ``measured`` results."""
    if not any(measured.get(key) for key in ("sweeps", "hosted", "carts")):
        return []
    lines = ["", "## Event-triggered DMPC against solving at every step", "",
             "Each case runs with `options.trigger: always`, then with `event` on the same design "
             "(`dmpc.bench.trigger`). Solves: QP solves whose plans reached the coordinator, one plan message "
             "each; kept: plans kept instead, one kept notice each; kB: the bytes of both. Cost: the closed-loop "
             "cost; / always: over the `always` run's. Step median: k >= 1 (k = 0 iterates Jacobi), in this process "
             "the wall time between steps' completions (records written), as processes the plant's step time. "
             "Solved for: why agents solved rather than kept (the first test that failed: `no plan`, `changed` "
             "neighbours' feed-forward, `prediction` error above the threshold, `constraints`, `cost`)."]
    if measured.get("sweeps"):
        lines += ["", "### In this process, over the cost threshold", "",
                  f"`trigger_cost` swept; the prediction threshold is the default ({trigger.THRESHOLD:g}).", "",
                  *trigger.table(trigger.SWEEP_HEADER, [r for s in measured["sweeps"] for r in trigger.sweep_rows(s)])]
    if measured.get("hosted"):
        lines += ["", "### As processes, agents hosted many to a process", "",
                  "The chain designed once, run with `dmpc run --agents-per-process K` with `always` and right "
                  f"after with `event` (trigger_cost {trigger.DEFAULT_COST:g}). Step median from k = "
                  f"{trigger.LATE}: once the states have settled. Speed figure: this machine's, just before the pair "
                  "(ms for 10^6 Python additions).", "",
                  *trigger.table(trigger.HOSTED_HEADER, [r for h in measured["hosted"] for r in trigger.hosted_rows(h)])]
    if measured.get("carts"):
        steps = measured["carts"][0]["steps"]
        lines += ["", "### The carts with a disturbance", "",
                  f"`scenarios/carts.yaml`, {steps} steps, `plant.disturbance`: uniform, |w| <= the bound on every "
                  f"state, seed {measured['carts'][0]['seed']}; `event` with `trigger_threshold` (the prediction error "
                  f"kept) and trigger_cost {trigger.DEFAULT_COST:g}. A disturbance above the threshold makes the "
                  "trigger fire; below it, a disturbance of a neighbour still changes an agent's feed-forward.", "",
                  *trigger.table(trigger.CARTS_HEADER, [r for d in measured["carts"] for r in trigger.carts_rows(d)])]
    return lines


COOPERATIVE_HEADING = "## Cooperative DMPC against tv-box"


def cooperative_lines(measured: dict) -> list[str]:
    """The section of ``tv-box-coop`` against ``tv-box`` (:mod:`dmpc.bench.cooperative`), from its
    ``measured`` results."""
    if not any(measured.get(key) for key in ("inprocess", "hosted")):
        return []
    lines = ["", COOPERATIVE_HEADING, "",
             "Each case runs with `options.method: tv-box`, then with `tv-box-coop` on the same design "
             "(`dmpc.bench.cooperative`). With `tv-box-coop` every release carries the whole system's iterate, "
             "z (N+1, n) and v (N, m), and each agent answers with its proposal: its own inputs minimising the cost "
             "of every subsystem they reach, a QP over the states of that reach (docs/algorithm.md, \"Cooperative "
             "DMPC\"). Cost: the closed-loop cost; / tv-box: over the `tv-box` run's (\"-\" where `tv-box` failed). "
             "k = 0 rounds: the rounds of the first step (`tv-box` iterates Jacobi to convergence, `tv-box-coop` "
             "starts from the centralised QP's plan where the terminal controller's rollout leaves the "
             "constraints). Step median: k >= 1, in this process the wall time between steps' completions, as "
             "processes the plant's step time; slowest step: the largest of those. Run wall: `summary.json`'s "
             "`wall_time_s`, k = 0 and every step (not the start-up). Plan messages / step: from k = 1 (the run's plan messages less M per "
             "round of k = 0; \"all k\": over every step, where not every agent answered every round); plan B / "
             "message: their bytes over their number (`summary.json`). Release bytes / step: the payload of a "
             "release as the coordinator encodes it, measured on the in-memory bus (the last release of step 1; "
             "\"(k = 0)\": the first release, where stepping every agent of the run once more in this process "
             "would take minutes; on the chain every release of a run has that size), times the rounds per step; "
             "it is published once and every agent process receives a copy. kB / step: the releases and the plan "
             "messages of a step from k = 1, each payload counted once. QP solve median: `summary.json`, every "
             "agent and step, a solve's wall time in its process (as processes, shared with every other process "
             "on the machine's cores while the agents of a round solve at once). QP iterations: OSQP's, from k = 1, "
             "median and largest over every agent and step (10000 is OSQP's cap: a `tv-box-coop` agent's QP that "
             "reaches it is solved again by Clarabel, dmpc/cooperative/agent_qp.py). "
             "Speed figure: this machine's just before the pair (ms for 10^6 Python additions)."]
    if measured.get("inprocess"):
        lines += ["", "### In this process", "",
                  *trigger.table(cooperative.INPROCESS_HEADER,
                                 [r for p in measured["inprocess"] for r in cooperative.inprocess_rows(p)])]
    if measured.get("hosted"):
        lines += ["", "### As processes", "",
                  "`dmpc run` (the launcher after the design), both runs back to back; agents / process 1: one "
                  "process per agent, otherwise hosted many to a process (`--agents-per-process`). Start-up: the "
                  "processes started to the first release.", "",
                  *trigger.table(cooperative.HOSTED_HEADER,
                                 [r for p in measured["hosted"] for r in cooperative.hosted_rows(p)])]
    note = cooperative.payload_note([*measured.get("inprocess", []), *measured.get("hosted", [])])
    return lines + (["", note] if note else [])


def kept_history(previous: str) -> str:
    """The hand-written history of the ``previous`` report (from :data:`HISTORY_HEADING` to its end), or ''."""
    at = previous.find(HISTORY_HEADING)
    return "" if at < 0 else previous[at:].rstrip() + "\n"


def write_report(results: dict, path: Path, command: str) -> None:
    """Write the report of ``results`` to ``path`` (Markdown), its figures to ``figures/`` beside it
    and the raw results to ``path`` with ``.json``; the history of the report there before is kept
    at the end. ``command`` is what regenerates it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    previous = path.read_text(errors="replace") if path.is_file() else ""
    figures = plot(results, path.parent / "figures")
    text = markdown(results, command)
    if figures:
        text += "\n" + "\n".join(f"![{p.stem}](figures/{p.name})" for p in figures) + "\n"
    history = kept_history(previous)
    if history:
        text += "\n" + history
    path.write_text(text)
    path.with_suffix(".json").write_text(json.dumps(results, indent=2) + "\n")


def plot(results: dict, folder: Path) -> list[Path]:
    """The figures of ``results`` (step time against M, the QP's solve times, ...) drawn into ``folder``;
    their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    done = [r for r in results["runtime"] if r.get("completed")]
    if done:
        fig, ax = plt.subplots(figsize=(6, 4))
        Ms = [r["M"] for r in done]
        ax.loglog(Ms, [r["step_ms_p50"] for r in done], "o-", label="DMPC multi-process, median")
        ax.loglog(Ms, [r["step_ms_p99"] for r in done], "o--", label="DMPC multi-process, p99")
        for key, label in (("inprocess", "DMPC in-process"), ("central_osqp", "centralised OSQP"),
                           ("central_cvxpy", "centralised CVXPY")):
            rows = results[key]
            ax.loglog([r["M"] for r in rows], [r["step_ms_p50"] for r in rows], "s-", label=label)
        ax.set_xlabel("subsystems M")
        ax.set_ylabel("time per step (ms)")
        ax.set_title("Per-step time against M (2 cores)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        paths.append(folder / "step_time.png")
        fig.savefig(paths[-1], dpi=120)
        plt.close(fig)
    sweeps = (results.get("trigger") or {}).get("sweeps") or []
    if sweeps:
        from dmpc.plots.tradeoff import draw_tradeoff  # start-up time: the figure only where the sweep ran

        drawn = draw_tradeoff(sweeps, folder)
        paths += [drawn] if drawn is not None else []
    if results["design"]:
        fig, ax = plt.subplots(figsize=(6, 4))
        d = results["design"]
        ax.loglog([r["M"] for r in d], [r["lmi_s"] for r in d], "o-", label="LMI (Clarabel)")
        ax.loglog([r["M"] for r in d], [r["terminal_set_s"] for r in d], "s-", label="X^f (Gilbert-Tan, HiGHS)")
        if all("design_s" in r for r in d):
            ax.loglog([r["M"] for r in d], [r["design_s"] for r in d], "^-", label="whole design")
        ax.set_xlabel("subsystems M")
        ax.set_ylabel("seconds")
        ax.set_title("Offline design time against M")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
        fig.tight_layout()
        paths.append(folder / "design_time.png")
        fig.savefig(paths[-1], dpi=120)
        plt.close(fig)
    return paths

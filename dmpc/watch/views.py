"""What the page shows, computed from the rows of a run (no Bokeh here).

Per agent at step k: alive, its state (``ok``, ``late``, ``fallback``, ``lost``, ``waiting``),
the last solve time and latency, fallbacks and rejoins up to k, and dropped messages; with an
event trigger also whether it solved or kept its plan at k, why it solved, and its QP solves and
plans kept up to k. Per link
of the communication graph: ``up``, ``late``, ``down`` or ``idle``. The readout of the values at
step k and the summary at the end, as HTML.
"""
from __future__ import annotations

import html
import math
import re
from typing import Any

import numpy as np

from dmpc.bus.keys import COORDINATOR_ROLE as COORDINATOR
from dmpc.core.qp_status import KEPT
from dmpc.watch.meta import RunMeta
from dmpc.watch.state import StateRow, StepRow

COLORS = {"ok": "#2ca02c", "up": "#2ca02c", "late": "#ff7f0e", "fallback": "#e6b800", "lost": "#d62728",
          "down": "#d62728", "waiting": "#999999", "idle": "#999999", "coordinator": "#1f77b4"}
CELL_COLORS = {"ok": "#dff0d8", "late": "#fde3c8", "fallback": "#fcf3c4", "lost": "#f6d0d0", "waiting": "#eeeeee"}
_EVENT = re.compile(r"agent (\S+) (lost|back)")
NO_ANSWER = frozenset({KEPT, "missed"})
"""Statuses of an agent that ran no QP at a step (or whose plan never came)."""
REASONS = {
    "no plan": "no plan of the step before to keep (after a fallback, a refused or a missed plan)",
    "limit": "it had kept its plan trigger_max_keep steps in a row",
    "prediction": "its state left the prediction by more than trigger_threshold",
    "changed": "a neighbour's plan changed its feed-forward: the kept plan no longer meets the QP's dynamics",
    "constraints": "the kept plan breaks an input, state or terminal-box row of the QP",
    "cost": "keeping its plan would give up more than trigger_cost",
    "target": "the setpoint target moved",
}
"""Why an agent solved, as the event trigger says it (docs/algorithm.md, "Event-triggered DMPC")."""


def fmt(value: float | None, digits: int = 6) -> str:
    """The number ``value`` for a person: ``digits`` significant digits, ``-`` when not a number."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.{digits}g}"


def ms(seconds: float | None) -> str:
    """``seconds`` in milliseconds with two decimals, ``-`` when not a number."""
    return "-" if seconds is None or not math.isfinite(seconds) else f"{seconds * 1e3:.2f}"


class AgentHistory:
    """Per-agent counts over the steps, kept as they arrive, for any number of first steps.

    Parameters
    ----------
    meta : RunMeta
    """

    def __init__(self, meta: RunMeta) -> None:
        self.names = meta.names
        self._fallback = np.zeros((64, meta.M), dtype=bool)
        self._solves = np.zeros((64, meta.M), dtype=int)  # QP solves: the step's rounds, where it solved
        self._kept = np.zeros((64, meta.M), dtype=bool)
        self._reasons: list[list[str] | None] = []
        self.n = 0
        self._events: list[tuple[int, str, str]] = []  # (step index, agent, "lost" | "back")

    def add(self, steps: list[StepRow]) -> None:
        """Append steps (in step order)."""
        for step in steps:
            if self.n == len(self._fallback):
                self._fallback, self._solves, self._kept = (np.vstack([a, np.zeros_like(a)]) for a in
                                                            (self._fallback, self._solves, self._kept))
            self._fallback[self.n] = step.fallback
            self._solves[self.n] = [0 if s in NO_ANSWER else step.rounds for s in step.status]
            self._kept[self.n] = [s == KEPT for s in step.status]
            self._reasons.append(step.solve_reason)
            self._events.extend((self.n, name, event) for name, event in _EVENT.findall(step.note)
                                if name in self.names)
            self.n += 1

    def fallbacks(self, n: int) -> list[int]:
        """Fallbacks per agent in the first ``n`` steps."""
        return self._fallback[:n].sum(axis=0).astype(int).tolist()

    def solves(self, n: int) -> list[int]:
        """QP solves per agent in the first ``n`` steps (every Jacobi round's)."""
        return self._solves[:n].sum(axis=0).astype(int).tolist()

    def keeps(self, n: int) -> list[int]:
        """Plans kept per agent in the first ``n`` steps."""
        return self._kept[:n].sum(axis=0).astype(int).tolist()

    def solve_reasons(self, n: int) -> dict[str, int]:
        """Why agents solved in the first ``n`` steps: reason -> agent-steps, by reason (as
        ``summary.json``'s ``solve_reasons``)."""
        counts: dict[str, int] = {}
        for reasons in self._reasons[:n]:
            for reason in reasons or ():
                if reason:
                    counts[reason] = counts.get(reason, 0) + 1
        return dict(sorted(counts.items()))

    def alive(self, n: int) -> dict[str, bool]:
        """Liveliness after the first ``n`` steps, as their notes tell it (``agent 2 lost`` ...)."""
        alive = {name: True for name in self.names}
        for index, name, event in self._events:
            if index < n:
                alive[name] = event == "back"
        return alive

    def rejoins(self, n: int) -> dict[str, int]:
        """How often each agent came back after it was lost, in the first ``n`` steps."""
        counts = {name: 0 for name in self.names}
        for index, name, event in self._events:
            if index < n and event == "back":
                counts[name] += 1
        return counts


def agent_states(meta: RunMeta, last: StepRow | None, alive: dict[str, bool]) -> list[str]:
    """Each agent's state in step ``last`` (None: no step yet), for the agents of ``meta``, with the
    liveliness ``alive`` (name -> alive)."""
    states = []
    for i, name in enumerate(meta.names):
        if not alive[name]:
            states.append("lost")
        elif last is None:
            states.append("waiting")
        elif last.fallback[i]:
            reason = last.fallback_reason[i]
            states.append("late" if reason == "missed" else "lost" if reason == "lost" else "fallback")
        else:
            states.append("ok")
    return states


def agent_table(meta: RunMeta, history: AgentHistory, n: int, last: StepRow | None,
                alive_now: dict[str, bool] | None, plant: dict, summary: dict | None) -> dict[str, list]:
    """The per-agent table of the agents of ``meta`` after the first ``n`` steps of ``history``
    (``last``: the n-th), one row per agent.

    ``alive_now`` (name -> alive), when given, replaces the liveliness the notes tell. Dropped
    messages: those the coordinator dropped from each agent (its ``plant`` status, or the summary's
    ``rejected``), and, once the run has ended, those each agent dropped, by reason (its
    report in the summary's ``agents``).
    """
    alive = history.alive(n)
    if alive_now:
        alive.update({k: v for k, v in alive_now.items() if k in alive})
    states = agent_states(meta, last, alive)
    fallbacks = history.fallbacks(n)
    back = history.rejoins(n)
    rejected = (summary or {}).get("rejected") or plant.get("rejected") or {}
    reports = (summary or {}).get("agents") or {}
    columns: dict[str, list] = {key: [] for key in ("agent", "alive", "state", "color", "status", "solve_ms",
                                                   "latency_ms", "fallbacks", "dropped_coordinator", "dropped_agent",
                                                   "rejoins")}
    for i, name in enumerate(meta.names):
        report = reports.get(name) or {}
        reasons = report.get("rejected_reasons") or {}
        dropped = sum((report.get("rejected") or {}).values()) if report else None
        columns["agent"].append(name)
        columns["alive"].append("yes" if alive[name] else "no")
        columns["state"].append(states[i])
        columns["color"].append(CELL_COLORS[states[i]])
        columns["status"].append(last.status[i] if last else "-")
        columns["solve_ms"].append(ms(last.solve_time[i]) if last and last.status[i] != KEPT else "-")
        columns["latency_ms"].append(ms(last.latency[i]) if last and i < len(last.latency) else "-")
        columns["fallbacks"].append(fallbacks[i])
        columns["dropped_coordinator"].append(int(rejected.get(name, 0)))
        columns["dropped_agent"].append("-" if dropped is None else f"{dropped}" + (
            " (" + ", ".join(f"{r}: {c}" for r, c in reasons.items()) + ")" if reasons else ""))
        columns["rejoins"].append(back[name])
    if meta.trigger == "event" or (last is not None and last.solve_reason is not None):
        columns.update(trigger_columns(history, n, last))
    return columns


def plan_text(status: str, reason: str) -> str:
    """What an agent did with its plan at a step (its ``status`` and ``reason``): ``kept``, ``solved:
    <why>``, ``solved`` (k = 0, or a step of several rounds, where no reason is given), or ``-``
    (no answer)."""
    if status == KEPT:
        return "kept"
    if status in NO_ANSWER:
        return "-"
    return f"solved: {reason}" if reason else "solved"


def trigger_columns(history: AgentHistory, n: int, last: StepRow | None) -> dict[str, list]:
    """The event trigger's columns of the agent table after the first ``n`` steps of ``history``
    (``last``: the n-th): the plan at the n-th (``plan``, and ``plan_title``, what its reason means),
    QP solves and plans kept."""
    names = history.names
    reasons = (last.solve_reason if last is not None else None) or [""] * len(names)
    plans = [plan_text(last.status[i], reasons[i]) if last else "-" for i in range(len(names))]
    return {"plan": plans, "plan_title": [REASONS.get(reason, "") for reason in reasons],
            "solves": history.solves(n), "keeps": history.keeps(n)}


TABLE_COLUMNS = [("agent", "agent"), ("alive", "alive"), ("state", "state"), ("status", "QP status"),
                 ("plan", "plan at k"), ("solves", "QP solves"), ("keeps", "plans kept"), ("solve_ms", "solve (ms)"), ("latency_ms", "latency (ms)"), ("fallbacks", "fallbacks"),
                 ("dropped_coordinator", "dropped by coordinator"), ("dropped_agent", "dropped by agent"), ("rejoins", "rejoins")]


def table_html(columns: dict[str, list]) -> str:
    """The per-agent table as HTML; each cell has the class ``dmpc-<column>``, the state cell
    the colour of the state, a plan cell what its reason means as its tooltip. The event
    trigger's columns are there only when ``columns`` has them."""
    shown = [(key, title) for key, title in TABLE_COLUMNS if key in columns]
    head = "".join(f"<th>{html.escape(title)}</th>" for _, title in shown)
    rows = []
    for r in range(len(columns["agent"])):
        cells = []
        for key, _ in shown:
            style = f" style='background:{columns['color'][r]}'" if key == "state" else ""
            if key == "plan" and columns["plan_title"][r]:
                style = f" title='{html.escape(columns['plan_title'][r])}'"
            cells.append(f"<td class='dmpc-{key}'{style}>{html.escape(str(columns[key][r]))}</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table class='dmpc-agents'><tr>{head}</tr>{''.join(rows)}</table>"


def positions(meta: RunMeta) -> dict[str, tuple[float, float]]:
    """Where each node of the graph of ``meta`` is drawn: the agents on a circle, the coordinator at
    its centre."""
    M = meta.M
    pos = {COORDINATOR: (0.0, 0.0)}
    for i, name in enumerate(meta.names):
        angle = math.pi / 2 - 2 * math.pi * i / max(M, 1)
        pos[name] = (math.cos(angle), math.sin(angle))
    return pos


def _fault_text(meta: RunMeta, source: str, target: str) -> str:
    f = meta.link_fault(source, target)
    parts = []
    if f.get("delay_ms") or f.get("jitter_ms"):
        parts.append(f"delay {f.get('delay_ms', 0):g} ms" + (f" + {f['jitter_ms']:g} jitter" if f.get("jitter_ms") else ""))
    if f.get("loss"):
        parts.append(f"loss {f['loss']:g}")
    return f"{source}→{target}: " + (", ".join(parts) if parts else "no faults injected")


def link_state(a: str, b: str) -> str:
    """A link's state from the states of its two ends ``a`` and ``b``."""
    ends = {a, b}
    if "lost" in ends:
        return "down"
    if "waiting" in ends:
        return "idle"
    if "late" in ends:
        return "late"
    return "up"


def graph_tables(meta: RunMeta, states: list[str], coordinator_alive: bool = True) -> tuple[dict, dict]:
    """Nodes and links of the communication graph of ``meta``, with each agent's state in ``states``
    and the coordinator's liveliness ``coordinator_alive``: (nodes, edges) columns.

    Links are the neighbour pairs (each agent receives its neighbours' plans) and the coordinator's
    link to every agent (releases and plans).
    """
    pos = positions(meta)
    by_name = dict(zip(meta.names, states))
    nodes: dict[str, list[Any]] = {"x": [pos[COORDINATOR][0]], "y": [pos[COORDINATOR][1]], "name": [COORDINATOR],
             "state": ["alive" if coordinator_alive else "gone"],
             "color": [COLORS[COORDINATOR] if coordinator_alive else COLORS["lost"]]}
    for name, state in by_name.items():
        nodes["x"].append(pos[name][0])
        nodes["y"].append(pos[name][1])
        nodes["name"].append(name)
        nodes["state"].append(state)
        nodes["color"].append(COLORS[state])
    edge_keys = ("x0", "y0", "x1", "y1", "link", "state", "color", "dash", "faults")
    edges: dict[str, list[Any]] = {key: [] for key in edge_keys}
    links = [(a, b, "plans") for a, b in meta.edges] + [(COORDINATOR, name, "release/plan") for name in meta.names]
    for a, b, what in links:
        state = link_state(by_name.get(a, "ok" if coordinator_alive else "lost"), by_name[b])
        edges["x0"].append(pos[a][0])
        edges["y0"].append(pos[a][1])
        edges["x1"].append(pos[b][0])
        edges["y1"].append(pos[b][1])
        edges["link"].append(f"{a} – {b} ({what})")
        edges["state"].append(state)
        edges["color"].append(COLORS[state])
        edges["dash"].append("dashed" if a == COORDINATOR else "solid")
        edges["faults"].append("; ".join([_fault_text(meta, a, b), _fault_text(meta, b, a)]))
    return nodes, edges


def readout_html(meta: RunMeta, row: StateRow | None, step: StepRow | None, shown: int = 8) -> str:
    """The values at the shown step (its state ``row`` and ``step``; None where there is none) of the
    run ``meta``: beta(k), J(k), and x_i(k), u_i(k), alpha_i(k) of the first
    ``shown`` subsystems; with setpoints also the target x_s,i(k) applied and the setpoint (``-``
    where free); with estimation also the innovation, and the outputs measured y_i(k) and the
    estimates x^_i(k), d^_i(k)."""
    if row is None:
        return "<i>no step yet</i>"
    head = (f"<b>k = <span class='dmpc-readout-k'>{row.k}</span></b> &nbsp; β(k) = "
            f"<span class='dmpc-beta'>{fmt(row.beta)}</span>"
            f" &nbsp; J(k) = <span class='dmpc-J'>{fmt(step.J) if step else '-'}</span>")
    targets = step.targets if step else None
    estimate = step.estimate if step is not None and meta.estimation else None
    if estimate is not None:
        head += f" &nbsp; innovation = <span class='dmpc-innovation'>{fmt(estimate.innovation)}</span>"
    extra = "<th>target x_s(k)</th><th>setpoint</th>" if targets else ""
    extra += "<th>y(k)</th><th>x̂(k)</th><th>d̂(k)</th>" if estimate else ""
    y_slices, d_slices = meta.output_slices(), meta.disturbance_slices()
    lines = [f"<table class='dmpc-readout'><tr><th>subsystem</th><th>x(k)</th><th>u(k)</th><th>α(k)</th>{extra}</tr>"]
    for i, (sub, xs, us) in enumerate(list(zip(meta.subsystems, meta.state_slices(), meta.input_slices()))[:shown]):
        x = ", ".join(fmt(v) for v in row.x[xs])
        u = ", ".join(fmt(v) for v in step.u[us]) if step else "-"
        a = ", ".join(fmt(v) for v in row.alpha[xs])
        cells = ""
        if targets:
            cells = (f"<td class='dmpc-target'>{', '.join(fmt(v) for v in targets.x[xs])}</td>"
                     f"<td class='dmpc-setpoint'>{', '.join(fmt(v) for v in targets.setpoint[xs])}</td>")
        if estimate:
            cells += (f"<td class='dmpc-y'>{', '.join(fmt(v) for v in estimate.y[y_slices[i]])}</td>"
                      f"<td class='dmpc-x-hat'>{', '.join(fmt(v) for v in estimate.x_hat[xs])}</td>"
                      f"<td class='dmpc-d-hat'>{', '.join(fmt(v) for v in estimate.d_hat[d_slices[i]])}</td>")
        lines.append(f"<tr><td>{html.escape(sub.name)}</td><td class='dmpc-x'>{x}</td><td class='dmpc-u'>{u}</td>"
                     f"<td class='dmpc-alpha'>{a}</td>{cells}</tr>")
    lines.append("</table>")
    return head + "".join(lines)


def verdict_of(summary: dict) -> str:
    """The summary's verdict, or how the run ended when the summary has none."""
    if summary.get("verdict"):
        return str(summary["verdict"])
    if summary.get("failure"):
        return "failed"
    if summary.get("aborted"):
        return "aborted"
    return "finished"


def summary_html(summary: dict | None, source: str = "") -> str:
    """The run's verdict and key figures from its ``summary`` once it has ended (empty before);
    ``source`` says where the summary came from."""
    if summary is None:
        return ""
    verdict = verdict_of(summary)
    color = {"ok": COLORS["ok"], "finished": COLORS["ok"]}.get(verdict, COLORS["lost"])
    J = [j for j in summary.get("J") or [] if j is not None]
    rows = [("steps", summary.get("steps")), ("every QP feasible", "yes" if summary.get("feasible") else "no"),
            ("fallbacks", summary.get("fallbacks")),
            ("fallbacks per agent", ", ".join(f"{a}: {n}" for a, n in (summary.get("fallbacks_per_agent") or {}).items())),
            ("final J", fmt(J[-1]) if J else "-"), ("closed-loop cost", fmt(summary.get("closed_loop_cost"))),
            ("‖x(end)‖∞", fmt(summary.get("final_state_norm_inf"))),
            ("step time median / p99 (ms)", f"{ms(summary.get('step_time_median_s'))} / "
                                            f"{ms(summary.get('step_time_p99_s'))}"),
            ("wall time (s)", fmt(summary.get("wall_time_s"), 4))]
    for key in ("aborted", "failure"):
        if summary.get(key):
            rows.append((key, summary[key]))
    if summary.get("keeps") is not None:
        rows.append(("QP solves / plans kept", f"{summary.get('solves', '-')} / {summary['keeps']}"))
        rows.append(("agents solved for", ", ".join(f"{r}: {c}" for r, c in (summary.get("solve_reasons") or {}).items())
                     or "-"))
    if summary.get("rejected"):
        rows.append(("dropped by the coordinator", ", ".join(f"{s}: {n}" for s, n in summary["rejected"].items())))
    names = {"final J": "dmpc-final-J", "closed-loop cost": "dmpc-cost", "fallbacks": "dmpc-fallbacks-total",
             "fallbacks per agent": "dmpc-fallbacks-per-agent", "QP solves / plans kept": "dmpc-solves-keeps"}
    body = "".join(f"<tr><td>{html.escape(str(k))}</td><td class='{names.get(k, '')}'>{html.escape(str(v))}</td></tr>"
                   for k, v in rows)
    findings = ""
    for key in ("failures", "warnings"):
        items = summary.get(key) or []
        if items:
            findings += f"<b>{key}</b><ul>" + "".join(
                f"<li>{html.escape(str(f.get('kind', '')))}: {html.escape(str(f.get('message', '')))}</li>"
                if isinstance(f, dict) else f"<li>{html.escape(str(f))}</li>" for f in items) + "</ul>"
    origin = f" <small>(summary from the {html.escape(source)})</small>" if source else ""
    return (f"<div class='dmpc-summary'><b>verdict: <span class='dmpc-verdict' style='color:{color}'>"
            f"{html.escape(verdict)}</span></b>{origin}<table>{body}</table>{findings}</div>")

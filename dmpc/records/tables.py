"""Human-readable reports: the design and the run summary."""
from __future__ import annotations

import math

import numpy as np
from rich.table import Table
from rich.text import Text

from dmpc.prepared import Prepared
from dmpc.terminal.console import stdout_console


def design_report(prepared: Prepared, coupling: str = "") -> Table:
    """A table of the figures and gains of the ``prepared`` run's design; ``coupling``: the
    input-coupling check in words (``dmpc design``, :mod:`dmpc.offline.input_coupling`), a row of its
    own when given."""
    d = prepared.design
    g = d.gains
    table = Table(title=f"design of '{prepared.name}'", show_header=False)
    table.add_column("what", style="bold")
    table.add_column("value")
    table.add_row("gains", f"{g.method}" + (f" ({g.objective})" if g.objective else ""))
    table.add_row("rho(A+BK)", f"{g.rho:.4f}")
    table.add_row("(10) margin", margin_text(g))
    if g.margin_thin:
        table.add_row("(10) thin margin", g.margin_note)
    table.add_row("X^f rows", str(d.terminal.rows))
    table.add_row("t*", str(d.terminal.t_star))
    table.add_row("sigma(alpha0)", f"{d.sigma0:.4f}")
    table.add_row("beta0", f"{d.beta0:.4g}")
    table.add_row("tube", d.tube)
    table.add_row("horizon N", horizon_text(d))
    if prepared.model is not None:
        table.add_row("model", model_text(prepared.model))
    if coupling:
        table.add_row("input coupling", coupling)
    for s, K, P in zip(prepared.system.subsystems, g.K, g.P):
        table.add_row(f"K_{s.name}", np.array2string(K, precision=4))
        table.add_row(f"P_{s.name}", np.array2string(P, precision=4).replace("\n", ""))
    table.add_row("digest", prepared.digest)
    return table


def model_text(model: dict) -> str:
    """How a continuous-time model was discretised, and how far that is from the exact model."""
    fill = model["fill_in"]
    spread = (f"the exact model couples subsystems outside the graph by up to {fill['largest']:.3g} "
              f"({'dropped' if model['method'] == 'exact-zoh' else 'absent from this model'})"
              if fill["blocks"] else "the exact model stays inside the graph")
    return (f"continuous time, dt = {model['dt']:g} s, {model['method']}; largest entry of the model error "
            f"{model['model_error']:.3g}; {spread}")


def margin_text(g) -> str:
    """What the check value of (10) is, its value, and that it passes (GainDesign ``g``: verified)."""
    verdict = "holds, thin: within one tolerance of zero" if g.margin_thin else "holds"
    return (f"largest eigenvalue of (A+BK)'P(A+BK) - P + Q + K'RK: {g.lyapunov_margin:.4g} "
            f"({verdict}; must be <= {g.lyapunov_tolerance:.2g})")


def verdict_text(summary: dict) -> Text:
    """The verdict line of ``summary`` and its reasons, coloured: failures red, warnings yellow, notes dim.

    Summaries written before verdicts existed show none.
    """
    text = Text()
    verdict = summary.get("verdict")
    if verdict is None:
        return text
    failures, warnings = summary.get("failures") or [], summary.get("warnings") or []
    if verdict == "ok":
        text.append("verdict: ok", style="bold green")
        if warnings:
            text.append(f" ({len(warnings)} warning{'s' if len(warnings) > 1 else ''})", style="yellow")
    else:
        text.append(f"verdict: FAILED ({', '.join(dict.fromkeys(f['kind'] for f in failures))})", style="bold red")
    for f in failures:
        text.append(f"\n  failure {f['kind']}: {f['message']}", style="red")
    for w in warnings:
        text.append(f"\n  warning {w['kind']}: {w['message']}", style="yellow")
    for note in summary.get("notes") or []:
        text.append(f"\n  note {note}", style="dim")
    return text


def horizon_text(design) -> str:
    """The horizon of ``design`` (a ControllerDesign) and, for ``horizon: auto``, how it was chosen."""
    start = design.start or {}
    if start.get("horizon") == "auto":
        return (f"{design.horizon} (auto: smallest feasible N = {start['smallest_feasible']} for the distributed "
                f"k = 0 step, {start['smallest_centrally_feasible']} for the centralised problem, "
                f"+ margin {start['margin']})")
    if start.get("centrally_feasible"):
        return f"{design.horizon} (the start is feasible for the centralised problem)"
    return str(design.horizon)


def dropped_text(summary: dict) -> str:
    """The messages the coordinator dropped as invalid, per sender and reason, from the run's
    ``summary`` ('' if none): a state
    dropped once and then sent again valid leaves the run ok, and this is where it shows."""
    counts = summary.get("rejected") or {}
    if not counts:
        return ""
    senders = ", ".join(f"{n} from {sender}" for sender, n in sorted(counts.items()))
    reasons = summary.get("rejected_reasons") or {}
    why = "; ".join(f"{reason} ({n} times)" if n > 1 else reason for reason, n in reasons.items())
    return f"{senders} ({why})" if why else senders


SHOWN_COSTS = 4
"""J(0), J(1), ... shown in the run summary."""
FIXED_RANGE = (1e-3, 1e6)
"""Magnitudes printed with fixed decimals; outside it (a diverged run's cost) in scientific notation."""


def number_text(value, decimals: int = 4) -> str:
    """``value`` with ``decimals`` decimals: ``93.6838``; ``2.5873e+17`` or ``1.2000e-05`` outside
    ``FIXED_RANGE``; ``n/a`` for a missing value."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    size = abs(value)
    if size == 0 or not math.isfinite(size) or FIXED_RANGE[0] <= size < FIXED_RANGE[1]:
        return f"{value:.{decimals}f}"
    return f"{value:.{decimals}e}"


def first_costs(J: list) -> tuple[str, str]:
    """The row of J(0), J(1), ... (label, values): each in its place, ``n/a`` where the step has no
    J (an agent's plan was lost or late), so that a value never stands under another step's label."""
    shown = list(J[:SHOWN_COSTS])
    if not shown:
        return "J(k)", "none (no step completed)"
    label = "J(0)" if len(shown) == 1 else f"J(0..{len(shown) - 1})"
    return label, ", ".join(number_text(j, 2) for j in shown)


def feasibility_text(summary: dict) -> str:
    """Whether every QP of the run (its ``summary``) was solved, and if not what happened instead: QPs
    that failed, or plans missed or lost (which are not QP failures: nothing is known of those QPs)."""
    if summary["feasible"]:
        return "yes"
    if not summary.get("steps"):
        return "no step completed"
    failed, missing = summary.get("qp_failed"), summary.get("plans_missing")
    if failed is None or missing is None:  # a summary written before these counts existed
        return "no"
    parts = []
    if failed:
        parts.append(f"{failed} QP solve{'s' if failed > 1 else ''} gave no plan")
    if missing:
        parts.append(f"{missing} plan{'s' if missing > 1 else ''} missed or lost (fallbacks)")
    if not parts:
        return "no"
    if not failed:
        return "no QP failed; " + parts[0]
    return "no: " + "; ".join(parts)


def trigger_text(summary: dict) -> str:
    """With an event trigger, from the run's ``summary``: the QP solves and the plans kept, why agents
    solved, and the bytes of the agents' answers."""
    reasons = ", ".join(f"{reason} {count}" for reason, count in summary.get("solve_reasons", {}).items())
    messages = summary.get("messages") or {}
    sent = f"; {messages['bytes']:,} bytes sent" if "bytes" in messages else ""
    return f"{summary.get('solves', '-')} / {summary['keeps']}" + (f" (solved for: {reasons})" if reasons else "") + sent


MAX_TRACKED_ROWS = 8
"""Requested components listed in the summary table of a summary without segments (the rest are in summary.json)."""
MAX_SEGMENT_LINES = 8
"""Lines of setpoint segments in the summary table: beyond, the last line sums up the rest."""
LISTED_COMPONENTS = 2
"""Components of one segment described one by one on its line; more are counted instead."""
SHOWN_MISSES = 4
"""Components not reached named on a line that counts them."""


def _segment_label(at: int, dt: float | None) -> str:
    return f"setpoint k = {at}" + (f" (t = {at * dt:g} s)" if dt else "")


def _segment_text(entry: dict) -> str:
    """One segment ``entry`` of ``tracking.segments``: the value asked, and whether it was reached
    (when, and the error at the segment's end) or not (the error, the tolerance and an unreachable
    request's target; an output's reachability is not judged, ``reachable`` None)."""
    text = f"{entry['subsystem']}: {entry['component']} = {entry['asked']:.6g}"
    if entry["reached"]:
        seconds = f" ({entry['settling_s']:.3g} s)" if entry.get("settling_s") is not None else ""
        return f"{text} reached in {entry['settling_steps']} steps{seconds}, error {entry['error_at_end']:.2g}"
    unreachable = ("" if entry.get("reachable") is not False
                   else f"; no admissible steady state, target {entry['target']:.6g}")
    return f"{text} not reached (error {entry['error_at_end']:.2g}, tolerance {entry['tolerance']:.2g}{unreachable})"


def _missed_text(missed: list[dict], with_step: bool = False) -> str:
    """``not reached: ...`` naming the first ``SHOWN_MISSES`` segments of ``missed`` ('' if none),
    each with its step ``k`` when ``with_step``."""
    if not missed:
        return ""
    named = ", ".join((f"k = {e['at']} " if with_step else "") + f"{e['subsystem']}: {e['component']} "
                      f"(error {e['error_at_end']:.2g})" for e in missed[:SHOWN_MISSES])
    return "; not reached: " + named + (", ..." if len(missed) > SHOWN_MISSES else "")


def _counted_text(entries: list[dict], what: str) -> str:
    """``entries`` counted: how many reached and how fast at most, the largest error at the end,
    and those not reached (``what``: ``components`` of one segment or ``more segments``)."""
    reached = [e for e in entries if e["reached"]]
    text = f"{len(entries)} {what}: {len(reached)} reached"
    if reached:
        text += f" in up to {max(e['settling_steps'] for e in reached)} steps"
        seconds = [e["settling_s"] for e in reached if e.get("settling_s") is not None]
        if seconds:
            text += f" ({max(seconds):.3g} s)"
    text += f", largest |error| {max(abs(e['error_at_end']) for e in entries):.2g}"
    return text + _missed_text([e for e in entries if not e["reached"]], with_step=what != "components")


def tracking_lines(tracking: dict | None) -> list[tuple[str, str]]:
    """Rows of the summary table for setpoints, from the summary's ``tracking``: a line per setpoint
    segment (the components whose request changed at one step; more than ``LISTED_COMPONENTS``
    counted), the segments beyond ``MAX_SEGMENT_LINES`` summed up in one line that still names
    those not reached; and the steps where the reference governor held a target back. A summary
    written before segments existed shows its components requested at the end."""
    if not tracking:
        return []
    rows = []
    if tracking.get("segments") is None:
        shown = tracking["components"][:MAX_TRACKED_ROWS]
        for c in shown:
            rows.append((f"setpoint {c['subsystem']}: {c['component']}",
                         f"{c['asked']:.6g}, reached {c['final']:.6g} (error {c['error']:.2g})"))
        more = len(tracking["components"]) - len(shown)
        if more > 0:
            rows.append(("setpoints", f"and {more} more components (summary.json, tracking)"))
    else:
        groups: dict[int, list[dict]] = {}
        for entry in tracking["segments"]:
            groups.setdefault(entry["at"], []).append(entry)
        steps = list(groups)
        shown_steps = steps if len(steps) <= MAX_SEGMENT_LINES else steps[:MAX_SEGMENT_LINES - 1]
        for at in shown_steps:
            entries = groups[at]
            text = ("; ".join(_segment_text(e) for e in entries) if len(entries) <= LISTED_COMPONENTS
                    else _counted_text(entries, "components"))
            rows.append((_segment_label(at, tracking.get("dt")), text))
        rest = steps[len(shown_steps):]
        if rest:
            rows.append((f"setpoint k = {rest[0]} ... {rest[-1]}",
                         _counted_text([e for at in rest for e in groups[at]], "more segments")
                         + " (summary.json, tracking.segments)"))
    governed = tracking["governor_steps"]
    if governed:
        rows.append(("reference governor", f"held the target back at {len(governed)} step(s) (first k = {governed[0]})"))
    return rows


def print_summary(summary: dict, out) -> None:
    """One screen of the run's ``summary`` on the console ``out``: the verdict and its reasons, then
    feasibility, fallbacks, cost, convergence, timing, and where the records are."""
    console = stdout_console()
    verdict = verdict_text(summary)
    if verdict:
        console.print(verdict)
    table = Table(title="run summary", show_header=False)
    table.add_column("what", style="bold")
    table.add_column("value")
    J = summary.get("J", [])
    table.add_row("scenario", str(summary.get("scenario")))
    table.add_row("steps", str(summary["steps"]))
    if summary.get("horizon") is not None:
        table.add_row("horizon N", f"{summary['horizon']}" + (" (auto)" if summary.get("horizon_auto") else ""))
    table.add_row("every QP feasible", feasibility_text(summary))
    table.add_row("fallbacks", str(summary["fallbacks"]))
    if summary.get("keeps") is not None:
        table.add_row("solves / plans kept", trigger_text(summary))
    around = bool(summary.get("operating_point"))  # the norms are of the deviations from it
    table.add_row("max |u - u_op|" if around else "max |u|", f"{summary['max_abs_u']:.4g}")
    table.add_row(*first_costs(J))
    table.add_row("closed-loop cost", number_text(summary["closed_loop_cost"]))
    table.add_row("||x(end) - x_op||_inf" if around else "||x(end)||_inf", f"{summary['final_state_norm_inf']:.3g}")
    for line in tracking_lines(summary.get("tracking")):
        table.add_row(*(Text(cell) for cell in line))  # as written: a unit's [m] is not markup
    if summary.get("solve_time_median_s") is not None:
        table.add_row("QP solve median", f"{summary['solve_time_median_s'] * 1e6:.0f} us")
    if summary.get("step_time_median_s") is not None and summary.get("runtime") != "in-process":
        table.add_row("step time median / p99",
                      f"{summary['step_time_median_s'] * 1e3:.3f} / {summary['step_time_p99_s'] * 1e3:.3f} ms")
    if summary.get("startup_s") is not None:
        table.add_row("start-up", f"{summary['startup_s']:.2f} s (processes started to first release)")
    if summary.get("security"):
        table.add_row("security", "TLS with mutual authentication, access control "
                      + ("on" if summary["security"].get("access_control") else "off"))
    dropped = dropped_text(summary)
    if dropped:
        table.add_row("dropped by the coordinator", dropped)
    if summary.get("aborted"):
        table.add_row("aborted", str(summary["aborted"]))
    if summary.get("failure"):
        table.add_row("failure", str(summary["failure"]))
    console.print(table)
    console.print(f"run folder: {out}")

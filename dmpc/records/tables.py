"""Human-readable reports: the design and the run summary."""
from __future__ import annotations

import numpy as np
from rich.table import Table
from rich.text import Text

from dmpc.console import stdout_console
from dmpc.run_spec import Prepared


def design_report(prepared: Prepared) -> Table:
    """A table of the design's figures and gains."""
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
    """The verdict line and its reasons, coloured: failures red, warnings yellow, notes dim.

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
    """The horizon and, for ``horizon: auto``, how it was chosen."""
    start = design.start or {}
    if start.get("horizon") == "auto":
        return (f"{design.horizon} (auto: smallest feasible N = {start['smallest_feasible']} for the distributed "
                f"k = 0 step, {start['smallest_centrally_feasible']} for the centralised problem, "
                f"+ margin {start['margin']})")
    if start.get("centrally_feasible"):
        return f"{design.horizon} (the start is feasible for the centralised problem)"
    return str(design.horizon)


def print_summary(summary: dict, out) -> None:
    """One screen: the verdict and its reasons, then feasibility, fallbacks, cost, convergence,
    timing, and where the records are."""
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
    table.add_row("every QP feasible", "yes" if summary["feasible"] else "no")
    table.add_row("fallbacks", str(summary["fallbacks"]))
    table.add_row("max |u|", f"{summary['max_abs_u']:.4g}")
    table.add_row("J(0..3)", ", ".join(f"{j:.2f}" for j in J[:4] if j is not None))
    table.add_row("closed-loop cost", f"{summary['closed_loop_cost']:.4f}")
    table.add_row("||x(end)||_inf", f"{summary['final_state_norm_inf']:.3g}")
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
    if summary.get("aborted"):
        table.add_row("aborted", str(summary["aborted"]))
    if summary.get("failure"):
        table.add_row("failure", str(summary["failure"]))
    console.print(table)
    console.print(f"run folder: {out}")

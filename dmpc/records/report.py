"""Human-readable reports: the design and the run summary."""
from __future__ import annotations

import numpy as np
from rich.table import Table

from dmpc.console import stdout_console
from dmpc.runtime.setup import Prepared


def design_report(prepared: Prepared) -> Table:
    """A table of the design's figures and gains."""
    d = prepared.design
    g = d.gains
    table = Table(title=f"design of '{prepared.name}'", show_header=False)
    table.add_column("what", style="bold")
    table.add_column("value")
    table.add_row("gains", f"{g.method}" + (f" ({g.objective})" if g.objective else ""))
    table.add_row("rho(A+BK)", f"{g.rho:.4f}")
    table.add_row("(10) margin", f"{g.lyapunov_margin:.4g} (must be <= {g.lyapunov_tolerance:.2g})")
    table.add_row("X^f rows", str(d.terminal.rows))
    table.add_row("t*", str(d.terminal.t_star))
    table.add_row("sigma(alpha0)", f"{d.sigma0:.4f}")
    table.add_row("beta0", f"{d.beta0:.4g}")
    table.add_row("tube", d.tube)
    for s, K, P in zip(prepared.system.subsystems, g.K, g.P):
        table.add_row(f"K_{s.name}", np.array2string(K, precision=4))
        table.add_row(f"P_{s.name}", np.array2string(P, precision=4).replace("\n", ""))
    table.add_row("digest", prepared.digest)
    return table


def print_summary(summary: dict, out) -> None:
    """One screen: feasibility, fallbacks, cost, convergence, timing, where the records are."""
    console = stdout_console()
    table = Table(title="run summary", show_header=False)
    table.add_column("what", style="bold")
    table.add_column("value")
    J = summary.get("J", [])
    table.add_row("scenario", str(summary.get("scenario")))
    table.add_row("steps", str(summary["steps"]))
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
    if summary.get("aborted"):
        table.add_row("aborted", str(summary["aborted"]))
    if summary.get("failure"):
        table.add_row("failure", str(summary["failure"]))
    console.print(table)
    console.print(f"run folder: {out}")

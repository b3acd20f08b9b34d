"""Closed-loop cost and constraint margin of the paper's example against loss and delay.

    python benchmarks/fault_sweep.py [--seeds 8] [--out docs/figures/faults.png] [--json]

Every run is in-process (``dmpc.runtime.inprocess.simulate``) in realtime mode on the in-memory
bus's simulated clock: step k is released at k dt (dt = 0.1 s), each round has a deadline of
50 ms, and the seeded fault injector delays or drops every message on every link. Solves take
no simulated time, so a run is fast and depends only on the seed.

- closed-loop cost: sum over k of x(k)'Qx(k) + u(k)'Ru(k) (the summary's ``closed_loop_cost``);
- constraint margin: the smallest slack of any input (and state, where the scenario has state
  constraints) over every step; negative means a violation. The example has no state
  constraints, so this is min over k of (2.5 - |u(k)|);
- late margin: the same from step 3 on, after the saturated first steps.
"""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from dmpc.terminal.console import silence_c_stdout

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "scenarios" / "paper.yaml"
DEADLINE = 0.05
LOSSES = [0.0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5]
DELAYS_MS = [0, 5, 10, 15, 20, 22, 24, 26, 28, 30, 35, 40, 50, 60]
JITTER_MS = 2.0
LATE_FROM = 3


def run_case(overrides: dict) -> dict:
    """One in-process run of the paper's example with ``overrides``; its key figures."""
    from dmpc.records.run_folder import summarise, trajectory_arrays
    from dmpc.runtime.inprocess import simulate
    from dmpc.scenario import load_scenario
    from dmpc.setup import prepare

    prepared = prepare(load_scenario(SCENARIO, {"options.mode": "realtime", "options.deadline": DEADLINE,
                                                **overrides}))
    records = []
    run = simulate(prepared, records.append)
    if run.coordinator.failure:
        raise RuntimeError(f"{overrides}: {run.coordinator.failure}")
    arrays = trajectory_arrays(prepared.system, records)
    summary = summarise(prepared.system, records, arrays)
    slack = constraint_slack(prepared.system, arrays["x"][:-1], arrays["u"])
    return {"cost": summary["closed_loop_cost"], "margin": float(slack.min()),
            "late_margin": float(slack[LATE_FROM:].min()), "fallbacks": summary["fallbacks"],
            "final_norm": summary["final_state_norm_inf"], "steps": summary["steps"]}


def constraint_slack(system, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Per step, the smallest slack of every input and state constraint, shape (K,)."""
    slack = np.full(len(u), np.inf)
    for i, sub in enumerate(system.subsystems):
        for linear_set, values in ((sub.input_set, u[:, system.us(i)]), (sub.state_set, x[:, system.xs(i)])):
            if linear_set is None:
                continue
            G, g = linear_set.one_sided()
            if len(g):
                slack = np.minimum(slack, np.min(g[None, :] - values @ G.T, axis=1))
    return slack


def sweep(values, make_overrides, seeds: int) -> dict:
    """For each value, the figures of ``seeds`` runs (seeds 0 .. seeds-1)."""
    out = {}
    for value in values:
        runs = [run_case({**make_overrides(value), "seed": seed}) for seed in range(seeds)]
        out[value] = {key: [r[key] for r in runs] for key in runs[0]}
    return out


def plot(loss: dict, delay: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(13, 7), constrained_layout=True)
    rows = [(loss, "message loss probability"), (delay, f"delay per message [ms] (+ jitter 0-{JITTER_MS:g} ms)")]
    for row, (data, label) in enumerate(rows):
        xs = np.array(list(data))
        for col, (key, title) in enumerate([("cost", "closed-loop cost"), ("margin", "constraint margin"),
                                            ("fallbacks", "fallbacks per run (of 120 agent-steps)")]):
            ax = axes[row, col]
            values = np.array([data[v][key] for v in data], dtype=float)
            ax.fill_between(xs, values.min(axis=1), values.max(axis=1), alpha=0.25, label="min-max over seeds")
            ax.plot(xs, np.median(values, axis=1), "o-", label="median")
            if key == "margin":
                late = np.array([data[v]["late_margin"] for v in data], dtype=float)
                ax.plot(xs, np.median(late, axis=1), "s--", label=f"median, from step {LATE_FROM} on")
                ax.axhline(0.0, color="k", lw=0.8)
            if row == 1:
                ax.axvline(1000 * DEADLINE / 2, color="grey", ls=":", lw=1, label="deadline / 2")
            ax.set_xlabel(label)
            ax.set_title(title)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
    fig.suptitle(f"Paper's example, realtime (dt = 0.1 s, deadline {1000 * DEADLINE:g} ms), "
                 "seeded faults on every link, in-process")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def table(name: str, data: dict) -> str:
    lines = [f"{name:>8} | cost median [min, max] | margin min | late margin median | fallbacks median | max final |x|"]
    for value, r in data.items():
        lines.append(f"{value:>8g} | {np.median(r['cost']):8.3f} [{min(r['cost']):.3f}, {max(r['cost']):.3f}] | "
                     f"{min(r['margin']):+.2e} | {np.median(r['late_margin']):+.3f} | "
                     f"{np.median(r['fallbacks']):5.1f} | {max(r['final_norm']):.2e}")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=8, help="runs per point (seeds 0 .. N-1)")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "figures" / "faults.png")
    parser.add_argument("--json", action="store_true", help="print the numbers as JSON instead of tables")
    args = parser.parse_args()
    if args.seeds < 1:
        parser.error("--seeds must be at least 1")
    silence_c_stdout()
    logging.getLogger("dmpc").setLevel(logging.ERROR)  # lost messages make agents report drops: expected here
    loss = sweep(LOSSES, lambda p: {"faults.loss": p}, args.seeds)
    delay = sweep(DELAYS_MS, lambda d: {"faults.delay_ms": d, "faults.jitter_ms": JITTER_MS}, args.seeds)
    plot(loss, delay, args.out)
    if args.json:
        print(json.dumps({"loss": loss, "delay_ms": delay}, indent=1))
    else:
        print(table("loss", loss) + "\n\n" + table("delay ms", delay) + f"\n\nfigure: {args.out}")


if __name__ == "__main__":
    main()

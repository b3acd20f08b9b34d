"""``dmpc roa``: an empirical region of attraction per method and horizon.

Initial states are drawn uniformly from the box {|x_j| <= R} of the global state space, with
one seeded generator, so the same seed gives the same states for every method and horizon,
and the same table. R defaults to the largest |entry| of the scenario's x(0) (2.8 on the
paper's example): the box the scenario's own initial state sits on the edge of.

Per method and horizon N, each sample is run in closed loop for the scenario's number of
steps and counted as

- **feasible at k = 0**: every QP of the first step solved in its last round (after the k = 0
  Jacobi iterations and, if needed, the centralised seed), and no fallback;
- **converged**: ||x(k)||_inf < 1e-3 for some k <= steps (fallbacks allowed);
- **always feasible**: converged with every QP of every step solved and no fallback.

A run stops as soon as it has converged, or once ||x||_inf exceeds ``DIVERGED`` times R (it is
then counted as not converged). The QPs are set up once per (method, N) and only x(0)
changes between samples (dmpc.runtime.direct, dmpc.runtime.central_loop).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dmpc.core.qp_status import SOLVED
from dmpc.evaluation.compare import CONVERGED
from dmpc.methods import method_spec
from dmpc.runtime.central_loop import CentralLoop
from dmpc.runtime.direct import DirectLoop
from dmpc.setup import prepare

DIVERGED = 1e3
ROA_FILE = "roa.json"
ROA_PLOT = "roa.png"


@dataclass(frozen=True)
class SampleOutcome:
    """One closed-loop run from one initial state: whether the QPs of step 0 were solved
    (``feasible_k0``), whether the state ``converged`` to the origin, and whether it did with every
    QP solved at every step (``always_feasible``)."""

    feasible_k0: bool
    converged: bool
    always_feasible: bool


def sample_states(n: int, samples: int, box: float, seed: int) -> np.ndarray:
    """Initial states uniform in {|x_j| <= box}, shape (samples, n), from ``seed``."""
    return np.random.default_rng(seed).uniform(-box, box, size=(samples, n))


def default_box(x0: np.ndarray) -> float:
    """The largest |entry| of the scenario's initial state x0 (1 if it is the origin)."""
    scale = float(np.max(np.abs(x0))) if x0.size else 0.0
    return scale if scale > 0 else 1.0


class Outcome:
    """Collects one run's step records into a SampleOutcome, and tells the loop when to stop: the run
    has converged when ||x||_inf < ``tol``, diverged beyond DIVERGED times the sampling ``box``."""

    def __init__(self, box: float, tol: float = CONVERGED) -> None:
        self.tol = tol
        self.limit = DIVERGED * box
        self.first = None
        self.failures = 0
        self.converged = False
        self.diverged = False

    def __call__(self, record) -> None:
        if self.first is None:
            self.first = record
            self.converged = float(np.max(np.abs(record.x))) < self.tol
        self.failures += int(_failed(record))
        size = float(np.max(np.abs(record.x_next)))
        self.converged = self.converged or size < self.tol
        self.diverged = not np.isfinite(size) or size > self.limit

    def stop(self, record) -> bool:
        """Whether the run may stop after the step ``record``: it has converged or diverged."""
        return self.converged or self.diverged

    def result(self) -> SampleOutcome:
        feasible = self.first is not None and not _failed(self.first)
        return SampleOutcome(feasible, self.converged, self.converged and self.failures == 0)


def _failed(record) -> bool:
    """A QP of the step not solved in its last round, or a fallback applied.

    At k = 0 an agent whose QP fails in a later Jacobi round keeps its plan of an earlier round
    (no fallback), but its problem from the final assumptions was infeasible: that counts.
    """
    return any(record.fallback) or any(s not in SOLVED for s in record.status)


def horizon_loop(scenario, method: str, N: int, design_data: dict):
    """(loop, steps) for one ``method`` of the ``scenario`` and horizon N: a DirectLoop or CentralLoop
    set up once.

    ``design_data`` (``design.json`` content) is reused, so the gains and X^f are not recomputed.
    """
    scn = scenario.model_copy(update={"horizon": N})
    prepared = prepare(scn, design_data={**design_data, "horizon": N})
    if not method_spec(method).distributed:
        return CentralLoop(prepared.system, prepared.design), prepared.protocol.steps

    return (DirectLoop(prepared.system, prepared.design, prepared.protocol, method_spec(method).name,
                       prepared.coupling),
            prepared.protocol.steps)


def run_samples(loop, steps: int, states: np.ndarray, box: float,
                advance: Callable[[], None] | None = None) -> list[SampleOutcome]:
    """Every sample through one ``loop`` (DirectLoop or CentralLoop), in order: from each initial state
    of ``states`` (samples, n), at most ``steps`` steps, judged against the sampling ``box``;
    ``advance`` is called after each sample (progress)."""
    out = []
    for x0 in states:
        outcome = Outcome(box)
        loop.run(steps, outcome, x0=x0, stop=outcome.stop)
        out.append(outcome.result())
        if advance is not None:
            advance()
    return out


def region_of_attraction(scenario, horizons: list[int], methods: list[str], samples: int, seed: int,
                         box: float | None = None, advance: Callable[[], None] | None = None) -> dict:
    """The content of roa.json.

    Parameters
    ----------
    scenario : Scenario
        The validated scenario (its method option is ignored: every method in ``methods`` runs).
    horizons : list of int
    methods : list of str
    samples : int
    seed : int
    box : float, optional
        R of the sampling box (default: :func:`default_box` of the scenario's x(0)).
    advance : callable, optional
        Called after each sample (progress).
    """
    # the samples replace the scenario's x(0): design at a fixed horizon, without its start check
    unchecked = scenario.model_copy(update={"horizon": horizons[0], "design": scenario.design.model_copy(
        update={"check_start": False})})
    base = prepare(unchecked)
    design_data = base.design_json()
    R = default_box(base.system.x0) if box is None else float(box)
    states = sample_states(base.system.n, samples, R, seed)
    results: dict[str, dict[str, dict]] = {}
    for method in methods:
        results[method] = {}
        for N in horizons:
            loop, steps = horizon_loop(scenario, method, N, design_data)
            outcomes = run_samples(loop, steps, states, R, advance)
            results[method][str(N)] = {
                "feasible_k0": float(np.mean([o.feasible_k0 for o in outcomes])),
                "converged": float(np.mean([o.converged for o in outcomes])),
                "always_feasible": float(np.mean([o.always_feasible for o in outcomes])),
                "feasible_k0_samples": [int(o.feasible_k0) for o in outcomes],
                "converged_samples": [int(o.converged) for o in outcomes],
            }
    return {"scenario": base.name, "seed": seed, "samples": samples, "box": R, "steps": base.protocol.steps,
            "horizons": list(horizons), "methods": results,
            "criterion": f"converged: ||x(k)||_inf < {CONVERGED:g} for some k <= steps; sampled uniformly in "
                         f"|x_j| <= {R:g}"}


ROA_COLUMNS = (("feasible_k0", "feasible at k=0 %"), ("converged", "converged %"),
               ("always_feasible", "always feasible %"))


def roa_header(data: dict) -> list[str]:
    """Columns of the long table of the region of attraction ``data`` (roa.json): method, N, then one
    per criterion."""
    return ["method", "N"] + [title for _, title in ROA_COLUMNS]


def roa_rows(data: dict) -> list[list[str]]:
    """The long table of ``data`` (roa.json): one row per method and horizon, percentages."""
    rows = []
    for method, per_N in data["methods"].items():
        for N in data["horizons"]:
            r = per_N[str(N)]
            rows.append([method, str(N)] + [f"{100 * r[key]:.1f}" for key, _ in ROA_COLUMNS])
    return rows


ROA_LEGEND = ("feasible at k=0: every QP of the first step solved; converged: ||x(k)||_inf < 1e-3 within the "
              "scenario's steps; always feasible: converged with every QP of every step solved")


def roa_markdown(data: dict) -> str:
    """One Markdown table per criterion of ``data`` (roa.json): methods as rows, horizons as columns
    (percent)."""
    out = []
    for key, title in ROA_COLUMNS:
        header = [f"{title.rstrip(' %')} (%)"] + [f"N = {N}" for N in data["horizons"]]
        lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        for method, per_N in data["methods"].items():
            lines.append("| " + " | ".join([method] + [f"{100 * per_N[str(N)][key]:.1f}" for N in data["horizons"]])
                         + " |")
        out.append("\n".join(lines))
    return "\n\n".join(out)


def plot_roa(data: dict, path: Path) -> Path:
    """Fractions feasible at k = 0, converged and always feasible against N, one line per method, from
    ``data`` (roa.json), drawn to ``path``; returns it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    horizons = data["horizons"]
    panels = (("feasible_k0", "feasible at k = 0"), ("converged", "converged"),
              ("always_feasible", "converged, every QP feasible"))
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.8), sharey=True, constrained_layout=True)
    markers, styles = "osv^Dx*", ["-", "--", "-.", ":"]
    count = len(data["methods"])
    spread = 0.04 * (max(horizons) - min(horizons) or 1)  # side by side, so that equal values stay visible
    for ax, (key, title) in zip(axes, panels):
        for q, (method, per_N) in enumerate(data["methods"].items()):
            shift = (q - (count - 1) / 2) * spread
            ax.plot([N + shift for N in horizons], [100 * per_N[str(N)][key] for N in horizons],
                    marker=markers[q % len(markers)], linestyle=styles[q % len(styles)], label=method)
        ax.set_title(title)
        ax.set_xlabel("horizon N")
        ax.set_xticks(horizons)
        ax.set_ylim(-2, 102)
        ax.grid(True, alpha=0.3)
    axes[0].set_ylabel("% of sampled initial states")
    axes[-1].legend(loc="lower right", fontsize=8)
    fig.suptitle(f"region of attraction, {data['scenario']}: {data['samples']} states uniform in "
                 f"|x_j| <= {data['box']:g}, seed {data['seed']} (methods drawn side by side at each N)")
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path

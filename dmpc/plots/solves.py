"""Figure 6 of ``dmpc report``: at each step, how many agents solved their QP, how many kept their
plan (an event trigger, docs/algorithm.md "Event-triggered DMPC") and how many fell back.

Above, the three counts stacked over the steps, against the number of agents; below, the same
per agent (the first ``MAX_AGENTS``), one row each, coloured by what it did. A run without an
event trigger is drawn too: every agent solves at every step, unless it fell back. Matplotlib
is passed in (``plt``), as in :mod:`dmpc.plots.style`.
"""
from __future__ import annotations

import textwrap
from dataclasses import dataclass

import numpy as np

SOLVED, KEPT, FALLBACK = 0, 1, 2
KINDS = (("solved its QP", "C0"), ("kept its plan", "C2"), ("fell back", "C3"))
"""What an agent did at a step (its code is the index), and its colour."""
MAX_AGENTS = 32
"""Agents with a row of their own in the lower panel (the first ones, in scenario order)."""


@dataclass(frozen=True)
class Solves:
    """What each agent did at each step of a run, and the counts ``summary.json`` has of it.

    Attributes
    ----------
    codes : ndarray, shape (K, M)
        ``SOLVED``, ``KEPT`` or ``FALLBACK`` per step and agent (a fallback counts as such even
        where the agent's QP ran: its plan was not applied).
    rounds : ndarray, shape (K,)
        Jacobi rounds per step (1 where the records have none).
    trigger : str
        ``always`` or ``event``.
    method : str
    kept_recorded : bool
        The arrays say which plans were kept (``trajectory.npz``'s ``kept``); without it a run
        with an event trigger counts its kept plans as solved.
    solves, keeps : int or None
        ``summary.json``'s QP solves (every round's) and plans kept.
    reasons : dict
        ``summary.json``'s ``solve_reasons``: why agents solved, reason -> agent-steps.
    """

    codes: np.ndarray
    rounds: np.ndarray
    trigger: str
    method: str
    kept_recorded: bool
    solves: int | None = None
    keeps: int | None = None
    reasons: dict | None = None

    @classmethod
    def of(cls, arrays: dict, summary: dict, trigger: str, method: str, steps: int, agents: int) -> "Solves":
        """From the run's ``arrays`` (``kept``, ``fallback``, ``rounds``, each optional) and its ``summary``,
        of ``method`` with the ``trigger`` (``always`` or ``event``), ``steps`` steps and ``agents`` agents."""
        codes = np.full((steps, agents), SOLVED, dtype=np.int8)
        kept = _flags(arrays, "kept", steps, agents)
        if kept is not None:
            codes[kept] = KEPT
        fallback = _flags(arrays, "fallback", steps, agents)
        if fallback is not None:
            codes[fallback] = FALLBACK
        rounds = np.ones(steps, dtype=int)
        if "rounds" in arrays and np.shape(arrays["rounds"]) == (steps,):
            rounds = np.asarray(arrays["rounds"], int)
        return cls(codes=codes, rounds=rounds, trigger=trigger, method=method, kept_recorded=kept is not None,
                   solves=_count(summary.get("solves")), keeps=_count(summary.get("keeps")),
                   reasons=summary.get("solve_reasons") if isinstance(summary.get("solve_reasons"), dict) else None)

    @property
    def M(self) -> int:
        return self.codes.shape[1]

    def counts(self) -> np.ndarray:
        """Agents per step that solved, kept and fell back, shape (K, 3)."""
        return np.stack([(self.codes == code).sum(axis=1) for code in range(len(KINDS))], axis=1)

    def notes(self) -> list[str]:
        """What the figure says under its title: the trigger, the totals, why agents solved."""
        if self.method == "centralized":
            notes = ["centralized: one QP of the whole system per step, counted here per subsystem"]
        elif self.trigger == "event":
            notes = [f"event trigger: {_total(self.solves)} QP solves, {_total(self.keeps)} plans kept"]
            if self.reasons:
                notes.append("agents solved for: " + ", ".join(f"{r} {n}" for r, n in self.reasons.items()))
            if not self.kept_recorded:
                notes.append("the records drawn (steps.jsonl) do not say which plans were kept: counted as solved")
        else:
            notes = ["no event trigger: every agent solves at every step"
                     + (f" ({self.solves} QP solves)" if self.solves is not None else "")]
        if self.rounds.size and self.rounds[0] > 1:
            notes.append(f"k = 0 took {self.rounds[0]} Jacobi rounds, a solve per agent in each")
        several = int(np.count_nonzero(self.rounds[1:] > 1))
        if several:
            notes.append(f"{several} later step{'s' if several > 1 else ''} took more than one round")
        return notes


def _flags(arrays: dict, key: str, steps: int, agents: int) -> np.ndarray | None:
    """A (K, M) bool array of the records, None where it is absent or of another shape."""
    values = arrays.get(key)
    if values is None or np.shape(values) != (steps, agents):
        return None
    return np.asarray(values, bool)


def _count(value) -> int | None:
    return int(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def _total(value: int | None) -> str:
    return "-" if value is None else f"{value:,}"


def _stacked(ax, times: np.ndarray, solves: Solves) -> None:
    """The counts per step stacked, each held over its step, against the number of agents."""
    counts = solves.counts()
    lower = np.zeros(counts.shape[0])
    for code, (label, colour) in enumerate(KINDS):
        upper = lower + counts[:, code]
        if counts[:, code].any() or code == SOLVED:
            ax.fill_between(times, np.append(lower, lower[-1]), np.append(upper, upper[-1]), step="post",
                            color=colour, alpha=0.85, linewidth=0, label=label)
        lower = upper
    ax.axhline(solves.M, color="grey", linestyle=":", linewidth=1.0, label=f"{solves.M} agents")
    ax.set_ylim(0, solves.M * 1.08)
    ax.set_ylabel("agents")


def _raster(ax, times: np.ndarray, solves: Solves, names: list[str], time_label: str) -> None:
    """One row per agent (the first ``MAX_AGENTS``), each step coloured by what the agent did."""
    from matplotlib.colors import ListedColormap

    shown = min(solves.M, MAX_AGENTS)
    cmap = ListedColormap([colour for _, colour in KINDS])
    ax.imshow(solves.codes[:, :shown].T, aspect="auto", interpolation="nearest", cmap=cmap, vmin=-0.5,
              vmax=len(KINDS) - 0.5, extent=(times[0], times[-1], shown - 0.5, -0.5))
    every = max(1, -(-shown // 16))
    ax.set_yticks(range(0, shown, every), [names[i] for i in range(0, shown, every)])
    ax.set_ylabel("agent" + (f" (first {shown} of {solves.M})" if shown < solves.M else ""))
    ax.set_xlabel(time_label)
    ax.grid(False)


def solves_figure(plt, solves: Solves, times: np.ndarray, names: list[str], time_label: str, title: str):
    """Figure 6: the counts per step above, the agents below.

    Parameters
    ----------
    plt : module
        matplotlib.pyplot.
    solves : Solves
    times : ndarray, shape (K+1,)
        The start of each step and the end of the last (seconds or steps, as the run's axes).
    names : list of str
        The agents' names, in scenario order.
    time_label : str
    title : str

    Returns
    -------
    Figure
    """
    rows = min(solves.M, MAX_AGENTS)
    fig, (top, bottom) = plt.subplots(2, 1, sharex=True, layout="constrained",
                                      figsize=(7.2, 4.4 + min(rows, 16) * 0.12),
                                      height_ratios=[2.0, 0.6 + min(rows, 16) * 0.12])
    _stacked(top, times, solves)
    _raster(bottom, times, solves, names, time_label)
    top.set_xlim(times[0], times[-1])
    handles, labels = top.get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=len(labels), framealpha=0.9)
    fig.suptitle("\n".join([title, *_lines(solves.notes())]))
    return fig


def _lines(notes: list[str], width: int = 90) -> list[str]:
    """The notes joined by "; " into lines of at most ``width`` characters, a note broken only
    where it is longer than a line."""
    lines: list[str] = []
    for note in notes:
        if lines and len(lines[-1]) + 2 + len(note) <= width:
            lines[-1] += "; " + note
        else:
            lines.extend(textwrap.wrap(note, width))
    return lines

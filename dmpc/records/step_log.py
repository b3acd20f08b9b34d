"""Reading ``steps.jsonl``: the steps completed so far, even from a run that is still going or
that was killed (its last line may be partial: it is skipped and said so)."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dmpc.core.qp_status import KEPT


@dataclass(frozen=True)
class StepLog:
    """The complete lines of a step log.

    Attributes
    ----------
    steps : list of dict
        One per complete line, in order.
    partial : bool
        The file ended in a partial line, which was skipped.
    """

    steps: list[dict]
    partial: bool

    @property
    def note(self) -> str:
        """What a reader should say about the log ("" if nothing)."""
        return "the last line of steps.jsonl was incomplete and is skipped" if self.partial else ""


def read_step_log(path: Path) -> StepLog:
    """The complete lines of ``path``; a last line without its newline (or not valid JSON) is skipped.

    Raises
    ------
    OSError
        The file cannot be read.
    ValueError
        A line other than the last is not valid JSON (the file is not a step log).
    """
    text = Path(path).read_text(encoding="utf-8", errors="replace")
    lines = text.split("\n")
    partial = lines[-1] != ""
    complete = lines[:-1]
    steps = []
    for number, line in enumerate(complete, 1):
        try:
            steps.append(json.loads(line))
        except json.JSONDecodeError:
            if number == len(complete) and not partial:  # cut inside the last line by a crash
                partial = True
                break
            raise ValueError(f"{path}: line {number} is not a step record") from None
    return StepLog(steps, partial)


def _floats(value) -> np.ndarray:
    return np.array(value, dtype=float) if value is not None else np.array(np.nan)


def arrays_from_log(log: StepLog) -> dict[str, np.ndarray]:
    """The main arrays of ``trajectory.npz`` rebuilt from the log: x, alpha (K+1, n), u (K, m),
    beta, S (K+1,), J (K,), J_agents, fallback (K, M), rounds (K,), and with an event trigger kept
    (K, M). K = 0 gives empty arrays."""
    steps = log.steps
    if not steps:
        return {}
    last = steps[-1]
    x = np.vstack([_floats(s["x"]) for s in steps] + [_floats(last["x_next"])])
    return {
        "x": x,
        "u": np.vstack([_floats(s["u"]) for s in steps]),
        "alpha": np.vstack([_floats(s["alpha"]) for s in steps] + [_floats(last["alpha_next"])]),
        "beta": np.array([s["beta"] if s["beta"] is not None else np.nan for s in steps]
                         + [last["beta_next"] if last["beta_next"] is not None else np.nan], dtype=float),
        "J": np.array([s["J"] if s["J"] is not None else np.nan for s in steps], dtype=float),
        "S": np.array([s["S"] for s in steps] + [np.nan], dtype=float),
        "J_agents": np.array([[v if v is not None else np.nan for v in s["J_agents"]] for s in steps], dtype=float),
        "fallback": np.array([s["fallback"] for s in steps], dtype=bool),
        "rounds": np.array([s["rounds"] for s in steps], dtype=int),
        **({"kept": np.array([[status == KEPT for status in s["status"]] for s in steps], dtype=bool)}
           if "solve_reason" in last else {}),
    }

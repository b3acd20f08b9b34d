"""Reading a run folder back: the one reader behind ``dmpc report`` (:mod:`dmpc.plots.report`) and
``dmpc.load_run`` (:mod:`dmpc.api.result`).

It reads ``trajectory.npz`` (or, from a run that ended before writing it, the arrays rebuilt from
``steps.jsonl``), ``summary.json``, ``design.json``, ``scenario.yaml`` and the disturbance drawn,
and finds how the global state and input split into subsystems (the layout): from the names and
sizes in ``trajectory.npz``, else from the scenario, else from the design's gains (K_i is
m_i x n_i), else one subsystem ``system`` for all of it. A summary, design or scenario that
cannot be read is left out, and ``notes`` says so: older run folders still load.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dmpc.core.errors import InputError
from dmpc.core.quantities import Quantity, run_quantities
from dmpc.records.files import DESIGN, DISTURBANCE, SCENARIO, STEP_LOG, SUMMARY, TRAJECTORY
from dmpc.records.step_log import arrays_from_log, read_step_log
from dmpc.scenario import Scenario, load_scenario

FALLBACK_NAME = "system"
"""The one subsystem of a run folder whose layout nothing tells."""


class RunFolderNotReadable(InputError, ValueError):
    """Not a run folder, or one whose arrays cannot be read (one line that says which and why)."""


@dataclass(frozen=True, eq=False)
class RunRecords:
    """What a run folder holds.

    Attributes
    ----------
    path : Path
    arrays : dict of str -> ndarray
        ``trajectory.npz``'s arrays, or those rebuilt from the step log (``finished`` False):
        at least x (K+1, n) and u (K, m).
    finished : bool
        ``trajectory.npz`` was written (the run came to its end, whatever its verdict).
    summary : dict or None
        ``summary.json``; None when it is missing or cannot be read.
    design : dict or None
        ``design.json``; None when it is missing or cannot be read.
    scenario : Scenario or None
        ``scenario.yaml``; None when it is missing or cannot be read.
    names : list of str
        Subsystem names, in scenario order.
    n, m : list of int
        States and inputs per subsystem.
    """

    path: Path
    arrays: dict[str, np.ndarray]
    finished: bool
    summary: dict | None
    design: dict | None
    scenario: Scenario | None
    names: list[str]
    n: list[int]
    m: list[int]

    @property
    def dt(self) -> float | None:
        """The scenario's sampling period in seconds (None: time counts steps)."""
        return self.scenario.dt if self.scenario is not None else None

    def quantities(self) -> tuple[dict[str, tuple[Quantity, ...]], dict[str, tuple[Quantity, ...]]]:
        """Names, units and bounds of each subsystem's states and inputs, by subsystem name."""
        return run_quantities(self.scenario, self.names, self.n, self.m)

    def disturbance(self) -> np.ndarray:
        """The plant disturbance w(k) added to x(k+1), shape (K, n): zeros without one."""
        x, u = self.arrays["x"], self.arrays["u"]
        steps = u.shape[0]
        w = np.zeros((steps, x.shape[1]))
        if (self.path / DISTURBANCE).is_file():
            drawn = np.load(self.path / DISTURBANCE, allow_pickle=False)
            w[:min(steps, drawn.shape[0])] = drawn[:steps]
        return w


TRACKING_KEYS = ("setpoint", "setpoint_u", "reference", "reference_u", "target", "target_u")
"""The setpoint arrays of trajectory.npz, (K, n) for the states' and (K, m) for the inputs'."""
STATE_KEYS = ("setpoint", "reference", "target")


def tracking_arrays(arrays: dict, steps: int, n: int, m: int) -> dict[str, np.ndarray]:
    """The setpoint arrays of a run (its ``arrays``, ``steps`` steps on n states and m inputs) and
    ``governor`` (K,), as a run without setpoints has them where trajectory.npz has none (the
    origin, nothing requested, the governor at 1)."""
    out = {}
    for key in TRACKING_KEYS:
        size = n if key in STATE_KEYS else m
        default = np.full((steps, size), np.nan) if key.startswith("setpoint") else np.zeros((steps, size))
        out[key] = np.asarray(arrays[key], float) if key in arrays else default
    out["governor"] = np.asarray(arrays["governor"], float) if "governor" in arrays else np.ones(steps)
    return out


def read_run(path, notes: list[str] | None = None) -> RunRecords:
    """Read a run folder (``notes`` gets what the reader had to work around).

    Parameters
    ----------
    path : path-like
        A folder written by ``dmpc simulate``, ``dmpc run``, ``dmpc plant`` or ``dmpc.simulate``.
    notes : list of str, optional

    Raises
    ------
    RunFolderNotReadable
        Not a folder, not a run folder, no ``trajectory.npz`` and no completed step, arrays that
        cannot be read, or arrays that do not fit the layout.
    """
    path = Path(path)
    _check_run_folder(path)
    arrays, finished = _arrays(path, notes)
    summary = _json(path / SUMMARY, notes)
    design = _json(path / DESIGN, notes)
    scenario = _scenario(path / SCENARIO, notes)
    names, n, m = _layout(arrays, scenario, design)
    x, u = arrays["x"], arrays["u"]
    if x.shape[1] != sum(n) or u.shape[1] != sum(m):
        raise RunFolderNotReadable(f"{path}: trajectory.npz has {x.shape[1]} states and {u.shape[1]} inputs, the "
                                   f"scenario {sum(n)} and {sum(m)}")
    return RunRecords(path=path, arrays=arrays, finished=finished, summary=summary, design=design,
                      scenario=scenario, names=names, n=n, m=m)


def is_finished_run_folder(path) -> bool:
    """Whether ``path`` holds the records written at the end of a run (``trajectory.npz`` and
    ``summary.json``)."""
    path = Path(path)
    return (path / TRAJECTORY).is_file() and (path / SUMMARY).is_file()


def _check_run_folder(path: Path) -> None:
    if not path.is_dir():
        raise RunFolderNotReadable(f"{path} is not a folder")
    markers = (TRAJECTORY, STEP_LOG, SUMMARY, DESIGN, SCENARIO)
    if not any((path / name).exists() for name in markers):
        raise RunFolderNotReadable(f"{path} is not a run folder (no {TRAJECTORY}, {SCENARIO} or {DESIGN})")
    if not (path / TRAJECTORY).is_file() and not (path / STEP_LOG).is_file():
        raise RunFolderNotReadable(f"{path} has no {TRAJECTORY}: the run was not completed or is still running "
                                   "(it is written at the end of a run)")


def _arrays(path: Path, notes: list[str] | None) -> tuple[dict[str, np.ndarray], bool]:
    """trajectory.npz, or (a run that ended before writing it) the arrays rebuilt from steps.jsonl,
    said in ``notes``; and whether it was trajectory.npz."""
    if not (path / TRAJECTORY).is_file():
        try:
            log = read_step_log(path / STEP_LOG)
        except (OSError, ValueError) as exc:
            raise RunFolderNotReadable(f"{path / STEP_LOG} cannot be read ({exc})") from None
        if not log.steps:
            raise RunFolderNotReadable(f"{path} has no {TRAJECTORY} and no completed step in {STEP_LOG}")
        if notes is not None:
            notes.append(f"{path}: no {TRAJECTORY} (the run did not finish); drawn from the {len(log.steps)} "
                         f"steps of {STEP_LOG}" + (f"; {log.note}" if log.partial else ""))
        return arrays_from_log(log), False
    try:
        with np.load(path / TRAJECTORY, allow_pickle=False) as npz:
            arrays = {key: npz[key] for key in npz.files}
    except (OSError, ValueError, EOFError) as exc:
        raise RunFolderNotReadable(f"{path / TRAJECTORY} cannot be read ({exc})") from None
    for key in ("x", "u"):
        if key not in arrays or arrays[key].ndim != 2:
            raise RunFolderNotReadable(f"{path / TRAJECTORY} has no 2-D array {key!r}: not a run's trajectory")
    return arrays, True


def _json(path: Path, notes: list[str] | None) -> dict | None:
    """A JSON object from ``path``; None (said in ``notes``) when it is missing or not one."""
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        data, why = None, f"cannot be read ({exc})"
    else:
        why = "is not a JSON object"
    if isinstance(data, dict):
        return data
    if notes is not None:
        notes.append(f"{path} {why}: left out")
    return None


def _scenario(path: Path, notes: list[str] | None) -> Scenario | None:
    """The run's resolved scenario; None (said in ``notes``) when it is missing or does not load:
    an older or hand-edited scenario leaves the arrays readable."""
    if not path.is_file():
        return None
    try:
        return load_scenario(path)
    except Exception as exc:  # noqa: BLE001 - whatever the file holds, the arrays still load
        if notes is not None:
            notes.append(f"{path} does not load ({exc}): names, units and bounds left out")
        return None


def _layout(arrays: dict, scenario: Scenario | None, design: dict | None) -> tuple[list[str], list[int], list[int]]:
    """Subsystem names and state and input sizes: from the arrays, else the scenario, else the design."""
    if "names" in arrays:
        return ([str(v) for v in arrays["names"]], [int(v) for v in arrays["state_sizes"]],
                [int(v) for v in arrays["input_sizes"]])
    if scenario is not None:
        subs = scenario.resolved_subsystems()
        return [s.name for s in subs], [s.n for s in subs], [s.m for s in subs]
    if design and design.get("K"):
        shapes = [np.atleast_2d(np.asarray(k, float)).shape for k in design["K"]]
        return [str(i + 1) for i in range(len(shapes))], [s[1] for s in shapes], [s[0] for s in shapes]
    return [FALLBACK_NAME], [arrays["x"].shape[1]], [arrays["u"].shape[1]]

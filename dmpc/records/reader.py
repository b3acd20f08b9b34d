"""Reading a run folder back: the one reader behind ``dmpc report`` (:mod:`dmpc.plots.report`) and
``dmpc.load_run`` (:mod:`dmpc.api.result`).

It reads ``trajectory.npz`` (or, from a run that ended before writing it, the arrays rebuilt from
``steps.jsonl``), ``summary.json``, ``design.json``, ``scenario.yaml`` and the disturbance drawn,
and finds how the global state and input split into subsystems (the layout): from the names and
sizes in ``trajectory.npz``, else from the scenario, else from the design's gains (K_i is
m_i x n_i), else one subsystem ``system`` for all of it. A summary, design or scenario that
cannot be read is left out, and ``notes`` says so: older run folders still load.

A run with ``estimation`` also has what its controllers saw (:class:`Estimates`: the outputs
measured, the state and disturbance estimates), split by the output and disturbance sizes of
``trajectory.npz``, else of ``design.json``'s ``estimation``, else of the scenario.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dmpc.core.errors import InputError
from dmpc.core.quantities import Quantity, run_quantities
from dmpc.estimation.model import DEFAULT_KIND
from dmpc.records.files import DESIGN, DISTURBANCE, SCENARIO, STEP_LOG, SUMMARY, TRAJECTORY
from dmpc.records.step_log import arrays_from_log, read_step_log
from dmpc.scenario import Scenario, load_scenario

FALLBACK_NAME = "system"
"""The one subsystem of a run folder whose layout nothing tells."""


class RunFolderNotReadable(InputError, ValueError):
    """Not a run folder, or one whose arrays cannot be read (one line that says which and why)."""


ESTIMATE_KEYS = ("y", "x_hat", "d_hat", "innovation")
"""The arrays of ``trajectory.npz`` (and fields of ``steps.jsonl``) that a run with ``estimation`` adds."""


def measured_states(C) -> dict[int, int]:
    """The outputs of one subsystem that measure a state alone (the rule of the scenario's requests
    on outputs).

    Parameters
    ----------
    C : array_like, shape (p_i, n_i)
        The subsystem's C.

    Returns
    -------
    dict of int -> int
        Output row r -> state j, where row r of C is the unit vector e_j.
    """
    out = {}
    for r, row in enumerate(np.atleast_2d(np.asarray(C, float))):
        nonzero = np.flatnonzero(row)
        if nonzero.size == 1 and row[nonzero[0]] == 1.0:
            out[r] = int(nonzero[0])
    return out


def output_quantities(spec, p: int) -> tuple[Quantity, ...]:
    """The names and units of one subsystem's outputs.

    Parameters
    ----------
    spec : dmpc.scenario.SubsystemSpec or None
        The subsystem's scenario entry: its ``outputs``, else its states' names when C is omitted,
        else ``y1, y2, ...``. None (no scenario): ``y1, y2, ...``.
    p : int
        The number of outputs p_i.
    """
    if spec is not None:
        labels = spec.output_labels()
        if len(labels) == p:
            return tuple(Quantity(label.name, label.unit) for label in labels)
    return tuple(Quantity(f"y{r + 1}") for r in range(p))


def disturbance_quantities(kind: str, outputs, inputs, nd: int) -> tuple[Quantity, ...]:
    """The names and units of one subsystem's ``nd`` disturbance estimates.

    Parameters
    ----------
    kind : str
        Its disturbance model: ``output`` (one per output, in the output's unit), ``input`` (one per
        input, in the input's unit), or "" when unknown.
    outputs, inputs : sequence of Quantity
        The subsystem's outputs and inputs.
    nd : int
        The number of disturbances n_d,i.

    Returns
    -------
    tuple of Quantity
        ``d(h1)`` for the disturbance on output or input ``h1``; ``d1, d2, ...`` where the model
        does not say which.
    """
    over = {"output": list(outputs), "input": list(inputs)}.get(kind)
    if over is not None and len(over) == nd:
        return tuple(Quantity(f"d({q.name})", q.unit) for q in over)
    return tuple(Quantity(f"d{r + 1}") for r in range(nd))


@dataclass(frozen=True, eq=False)
class Estimates:
    """What the controllers of a run with ``estimation`` saw of the plant, stacked over the
    subsystems (docs/algorithm.md, "Offset-free tracking").

    Attributes
    ----------
    y : ndarray, shape (K, p)
        The outputs y(k) the plant measured at steps 0 .. K-1 (with its measurement noise).
    x_hat : ndarray, shape (K, n)
        The state estimates x^(k|k) the controllers worked from.
    d_hat : ndarray, shape (K, n_d)
        The disturbance estimates d^(k|k).
    innovation : ndarray, shape (K,)
        ||y(k) - C x^(k|k-1) - C_d d^(k|k-1)||_inf.
    setpoint_y : ndarray, shape (K, p)
        The outputs requested at each step, NaN where free (all NaN when nothing named outputs).
    p, nd : list of int
        Outputs p_i and disturbances n_d,i per subsystem.
    outputs, disturbances : list of tuple of Quantity
        Per subsystem, the names and units of its outputs and of its disturbances.
    C : list of ndarray or None
        Per subsystem C_i, shape (p_i, n_i); None when the records do not hold the scenario.
    kinds : list of str
        Per subsystem its disturbance model, ``output`` or ``input`` ("" where unknown).
    """

    y: np.ndarray
    x_hat: np.ndarray
    d_hat: np.ndarray
    innovation: np.ndarray
    setpoint_y: np.ndarray
    p: list[int]
    nd: list[int]
    outputs: list[tuple[Quantity, ...]]
    disturbances: list[tuple[Quantity, ...]]
    C: list[np.ndarray] | None = None
    kinds: list[str] | None = None

    def output_slice(self, i: int) -> slice:
        """Columns of subsystem ``i`` in ``y`` and ``setpoint_y``."""
        start = sum(self.p[:i])
        return slice(start, start + self.p[i])

    def disturbance_slice(self, i: int) -> slice:
        """Columns of subsystem ``i`` in ``d_hat``."""
        start = sum(self.nd[:i])
        return slice(start, start + self.nd[i])

    def measured(self, i: int) -> dict[int, int]:
        """Subsystem ``i``'s outputs that measure one of its states alone: output r -> state j
        (:func:`measured_states`); empty when C is unknown."""
        return measured_states(self.C[i]) if self.C is not None else {}


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

    def estimates(self, notes: list[str] | None = None) -> Estimates | None:
        """What the controllers saw (:class:`Estimates`), or None for a run without ``estimation``.

        Parameters
        ----------
        notes : list of str, optional
            Gets why the estimates are left out when the records do not say how to split them by
            subsystem.
        """
        return read_estimates(self, notes)

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


def read_estimates(records: RunRecords, notes: list[str] | None = None) -> Estimates | None:
    """What the controllers of a run saw, split by subsystem.

    Parameters
    ----------
    records : RunRecords
        The run folder's records (:func:`read_run`).
    notes : list of str, optional
        Gets why the estimates are left out when nothing in the records says how to split them by
        subsystem: the output sizes from ``trajectory.npz`` (``output_sizes``), else ``design.json``
        (``estimation``), else the scenario; the disturbance sizes the same way
        (``disturbance_sizes``), else from the disturbance models.

    Returns
    -------
    Estimates or None
        None for a run without ``estimation``.
    """
    arrays = records.arrays
    if not all(key in arrays for key in ESTIMATE_KEYS[:3]):
        return None
    steps, M = arrays["u"].shape[0], len(records.names)
    if any(np.ndim(arrays[key]) != 2 or np.shape(arrays[key])[0] != steps for key in ESTIMATE_KEYS[:3]):
        if notes is not None:
            notes.append(f"{records.path}: the outputs and estimates do not have a row per step: left out")
        return None
    y, x_hat, d_hat = (np.asarray(arrays[key], float) for key in ESTIMATE_KEYS[:3])
    innovation = (np.asarray(arrays["innovation"], float).reshape(-1) if "innovation" in arrays
                  else np.full(steps, np.nan))
    setpoint_y = np.asarray(arrays["setpoint_y"], float) if "setpoint_y" in arrays else np.full(y.shape, np.nan)
    scenario = records.scenario
    specs = scenario.resolved_subsystems() if scenario is not None else None
    if specs is not None and len(specs) != M:
        specs = None
    designed = ((records.design or {}).get("estimation") or {}).get("subsystems") or {}
    designed = designed if isinstance(designed, dict) else {}
    kinds = _kinds(records.names, designed, scenario)
    p = _sizes(arrays.get("output_sizes"), designed, "outputs", records.names, y.shape[1],
               [[s.p for s in specs]] if specs is not None else [])
    nd_options = []
    if p is not None and all(kinds):
        nd_options.append([p[i] if kind == "output" else records.m[i] for i, kind in enumerate(kinds)])
    nd_options += [p] if p is not None else []
    nd = _sizes(arrays.get("disturbance_sizes"), designed, "disturbances", records.names, d_hat.shape[1], nd_options)
    if p is None or nd is None or x_hat.shape[1] != sum(records.n) or innovation.shape != (steps,) \
            or setpoint_y.shape != y.shape:
        if notes is not None:
            notes.append(f"{records.path}: the outputs and estimates ({y.shape[1]} outputs, {d_hat.shape[1]} "
                         "disturbances) cannot be split by subsystem: left out")
        return None
    _, inputs = records.quantities()
    outputs = [output_quantities(specs[i] if specs is not None else None, p[i]) for i in range(M)]
    disturbances = [disturbance_quantities(kinds[i], outputs[i], inputs[records.names[i]], nd[i]) for i in range(M)]
    C = None
    if specs is not None:
        C = [np.asarray(s.C, float) if s.C is not None else np.eye(s.n) for s in specs]
        if [c.shape for c in C] != list(zip(p, records.n)):
            C = None
    return Estimates(y=y, x_hat=x_hat, d_hat=d_hat, innovation=innovation, setpoint_y=setpoint_y, p=p, nd=nd,
                     outputs=outputs, disturbances=disturbances, C=C, kinds=kinds)


def _kinds(names: list[str], designed: dict, scenario: Scenario | None) -> list[str]:
    """Each subsystem's disturbance model: from design.json, else the scenario, else "" (unknown)."""
    spec = scenario.estimation if scenario is not None else None
    kinds = []
    for name in names:
        kind = _entry(designed, name).get("disturbance")
        if kind is None and spec is not None:
            kind = spec.disturbance.get(name, DEFAULT_KIND) if isinstance(spec.disturbance, dict) else spec.disturbance
        kinds.append(str(kind or ""))
    return kinds


def _entry(designed: dict, name: str) -> dict:
    """design.json's ``estimation.subsystems.<name>`` ({} when it is not there)."""
    entry = designed.get(name)
    return entry if isinstance(entry, dict) else {}


def _sizes(stored, designed: dict, key: str, names: list[str], width: int, others: list[list[int]]) -> list[int] | None:
    """Per-subsystem sizes of a stacked array ``width`` wide: trajectory.npz's ``stored`` (M,), else
    design.json's ``estimation.subsystems.<name>.<key>``, else the first of ``others`` (a single
    subsystem has all of it); None when none of them adds up to ``width``."""
    options = []
    if stored is not None:
        options.append([int(v) for v in np.asarray(stored).ravel()])
    if all(isinstance(_entry(designed, name).get(key), int) for name in names):
        options.append([int(_entry(designed, name)[key]) for name in names])
    options += others + ([[width]] if len(names) == 1 else [])
    return next((sizes for sizes in options if len(sizes) == len(names) and sum(sizes) == width
                 and min(sizes, default=0) >= 0), None)


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
        return {**arrays_from_log(log), **_estimates_from_log(log.steps)}, False
    try:
        with np.load(path / TRAJECTORY, allow_pickle=False) as npz:
            arrays = {key: npz[key] for key in npz.files}
    except (OSError, ValueError, EOFError) as exc:
        raise RunFolderNotReadable(f"{path / TRAJECTORY} cannot be read ({exc})") from None
    for key in ("x", "u"):
        if key not in arrays or arrays[key].ndim != 2:
            raise RunFolderNotReadable(f"{path / TRAJECTORY} has no 2-D array {key!r}: not a run's trajectory")
    return arrays, True


def _estimates_from_log(steps: list[dict]) -> dict[str, np.ndarray]:
    """The estimation arrays of ``trajectory.npz`` (y, x_hat, d_hat, innovation (K, ...), and
    setpoint_y where a line has it, NaN in the others) rebuilt from the step log's lines ``steps``;
    empty for a run without estimation."""
    if not steps or not all(key in steps[0] for key in ESTIMATE_KEYS):
        return {}
    try:
        out = {key: np.array([[np.nan if v is None else v for v in np.atleast_1d(s.get(key, np.nan))]
                              for s in steps], dtype=float) for key in ESTIMATE_KEYS}
        out["innovation"] = out["innovation"].reshape(-1)
        asked = [s.get("setpoint_y") for s in steps]
        if any(a is not None for a in asked):
            p = out["y"].shape[1]
            out["setpoint_y"] = np.array([[np.nan] * p if a is None else [np.nan if v is None else v for v in a]
                                          for a in asked], dtype=float)
    except (TypeError, ValueError):  # lines of different sizes: the rest of the log still draws
        return {}
    return out


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

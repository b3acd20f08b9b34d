"""What an observer needs to know about a run besides its steps: names, dimensions, bounds, graph.

The plant sends it as JSON (:func:`meta_json`, raw constraint sets, no solver work in the
plant); the observer turns it into a :class:`RunMeta`, computing the per-coordinate bounds a
plot can draw (a polytope is shown by its bounding box).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dmpc.core.quantities import default_quantities, quantities
from dmpc.core.system import box_hull
from dmpc.records.reader import disturbance_quantities, measured_states, output_quantities

META_VERSION = 1


def _floats(values) -> list:
    """Floats with infinities as None (JSON has no infinity)."""
    return [float(v) if math.isfinite(v) else None for v in np.asarray(values, float).ravel()]


def _set_json(linear_set) -> dict | None:
    if linear_set is None:
        return None
    return {"H": np.asarray(linear_set.H, float).tolist(), "lower": _floats(linear_set.lower),
            "upper": _floats(linear_set.upper)}


def _labels(prepared) -> dict[str, tuple[list, list]]:
    """Names and units of each subsystem's states and inputs, where the scenario gives them."""
    if prepared.scenario is None:  # a run bundle: the scenario's labels did not travel
        return {}

    states, inputs = quantities(prepared.scenario)
    return {name: ([[q.name, q.unit] for q in states[name]], [[q.name, q.unit] for q in inputs[name]])
            for name in states}


def _estimation(prepared) -> list[dict] | None:
    """Per subsystem, the names and units of its outputs and disturbances and the state each output
    measures alone (None where it measures a combination); None without ``estimation``."""
    estimator = getattr(prepared, "estimator", None)
    if estimator is None:
        return None
    system = prepared.system
    names = [s.name for s in system.subsystems]
    specs = prepared.scenario.resolved_subsystems() if prepared.scenario is not None else None
    if prepared.scenario is not None:
        inputs = quantities(prepared.scenario)[1]
    else:
        inputs = default_quantities(names, [s.m for s in system.subsystems], "u")
    out = []
    for i, part in enumerate(estimator.model.parts):
        outputs = output_quantities(specs[i] if specs is not None else None, part.p)
        measured = measured_states(part.C)
        out.append({"outputs": [[q.name, q.unit] for q in outputs],
                    "disturbances": [[q.name, q.unit] for q in
                                     disturbance_quantities(part.kind, outputs, inputs[names[i]], part.nd)],
                    "measures": [measured.get(r) for r in range(part.p)]})
    return out


def meta_json(prepared, run_id: str) -> dict:
    """The run's description for observers, JSON-ready.

    Parameters
    ----------
    prepared : dmpc.prepared.Prepared
    run_id : str

    Returns
    -------
    dict
        ``run_id``, ``scenario``, ``method``, ``mode``, ``dt``, ``deadline``, ``steps``,
        ``horizon``, ``digest``, ``subsystems`` (name, n, m, raw input and state sets, and the
        ``[name, unit]`` of each state and input where the scenario names them),
        ``edges`` (undirected pairs of names), ``faults`` (default and per directed link) and
        ``trigger`` (``options.trigger``: ``always`` or ``event``). With ``estimation`` also
        ``estimation`` (true) and per subsystem ``outputs`` and ``disturbances`` (``[name, unit]``
        of each) and ``measures`` (per output, the state it is alone, or None).
    """
    system = prepared.system
    names = [s.name for s in system.subsystems]
    faults = prepared.faults
    labels = _labels(prepared)
    estimation = _estimation(prepared)
    data = {
        "meta_version": META_VERSION,
        "run_id": run_id,
        "scenario": prepared.name,
        "method": prepared.method,
        "mode": prepared.mode,
        "dt": prepared.dt,
        "deadline": prepared.deadline,
        "steps": prepared.protocol.steps,
        "horizon": prepared.design.horizon,
        "digest": prepared.digest,
        "subsystems": [{"name": s.name, "n": s.n, "m": s.m, "input": _set_json(s.input_set),
                        "state": _set_json(s.state_set), "states": labels.get(s.name, (None, None))[0],
                        "inputs": labels.get(s.name, (None, None))[1]} for s in system.subsystems],
        "edges": [[names[i], names[j]] for i, j in system.edges],
        "faults": {"default": vars(faults.default),
                   "links": [{"source": s, "target": r, **vars(f)} for s, r, f in faults.links]},
        "trigger": prepared.trigger.mode,
    }
    if estimation is not None:
        data["estimation"] = True
        for entry, extra in zip(data["subsystems"], estimation):
            entry.update(extra)
    return data


@dataclass(frozen=True)
class SubsystemMeta:
    """One subsystem as the page shows it.

    Attributes
    ----------
    name : str
    state_names, input_names : tuple of str
        As the scenario names them; ``x1 … xn`` and ``u1 … um`` where it does not.
    state_units, input_units : tuple of str
        Empty where the scenario gives none.
    state_lower, state_upper, input_lower, input_upper : tuple of float
        Per-coordinate bounds (the bounding box of a polytope); ``nan`` where unbounded.
    input_is_box : bool
        False when the input bounds are a polytope's bounding box.
    output_names, output_units, disturbance_names, disturbance_units : tuple of str
        With estimation: the outputs measured and the disturbances estimated (empty without).
    measures : tuple of int or None
        With estimation, per output: the state it measures alone, None where it is a combination.
    """

    name: str
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    state_lower: tuple[float, ...]
    state_upper: tuple[float, ...]
    input_lower: tuple[float, ...]
    input_upper: tuple[float, ...]
    input_is_box: bool = True
    state_units: tuple[str, ...] = ()
    input_units: tuple[str, ...] = ()
    output_names: tuple[str, ...] = ()
    output_units: tuple[str, ...] = ()
    disturbance_names: tuple[str, ...] = ()
    disturbance_units: tuple[str, ...] = ()
    measures: tuple[int | None, ...] = ()

    @staticmethod
    def _label(name: str, unit: str) -> str:
        return f"{name} [{unit}]" if unit else name

    def state_label(self, j: int) -> str:
        """``name [unit]`` of state j."""
        return self._label(self.state_names[j], self.state_units[j] if self.state_units else "")

    def input_label(self, j: int) -> str:
        """``name [unit]`` of input j."""
        return self._label(self.input_names[j], self.input_units[j] if self.input_units else "")

    def output_label(self, r: int) -> str:
        """``name [unit]`` of output r."""
        return self._label(self.output_names[r], self.output_units[r] if self.output_units else "")

    def disturbance_label(self, r: int) -> str:
        """``name [unit]`` of disturbance r."""
        return self._label(self.disturbance_names[r], self.disturbance_units[r] if self.disturbance_units else "")

    @property
    def p(self) -> int:
        """Outputs measured (0 without estimation)."""
        return len(self.output_names)

    @property
    def nd(self) -> int:
        """Disturbances estimated (0 without estimation)."""
        return len(self.disturbance_names)

    @property
    def n(self) -> int:
        return len(self.state_names)

    @property
    def m(self) -> int:
        return len(self.input_names)


@dataclass(frozen=True)
class RunMeta:
    """A run's description on the observer's side (:func:`meta_json` writes it).

    Attributes
    ----------
    run_id, scenario, method, mode : str
        The run's id, its scenario's name, the method and ``lockstep`` or ``realtime``.
    dt : float
        The sampling period (s).
    deadline : float or None
        The step deadline (s) of a real-time run.
    steps, horizon : int
        The steps K and the horizon N.
    digest : str
        The design's digest.
    subsystems : tuple of SubsystemMeta
    edges : tuple of (name, name)
        The communication graph's undirected pairs.
    faults : dict
        ``default`` and per directed link (``links``): delay, jitter and loss.
    trigger : str
        ``options.trigger``: ``always`` or ``event``.
    estimation : bool
        The controllers work from estimates: the steps carry ``y``, ``x_hat`` and ``d_hat``."""

    run_id: str
    scenario: str
    method: str
    mode: str
    dt: float
    deadline: float | None
    steps: int
    horizon: int
    digest: str
    subsystems: tuple[SubsystemMeta, ...]
    edges: tuple[tuple[str, str], ...]
    faults: dict
    trigger: str = "always"
    estimation: bool = False

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.subsystems]

    @property
    def M(self) -> int:
        return len(self.subsystems)

    def state_slices(self) -> list[slice]:
        """Each subsystem's block of the global state vector."""
        return _slices([s.n for s in self.subsystems])

    def input_slices(self) -> list[slice]:
        """Each subsystem's block of the global input vector."""
        return _slices([s.m for s in self.subsystems])

    def output_slices(self) -> list[slice]:
        """Each subsystem's block of the global output vector y (with estimation)."""
        return _slices([s.p for s in self.subsystems])

    def disturbance_slices(self) -> list[slice]:
        """Each subsystem's block of the global disturbance estimate d^ (with estimation)."""
        return _slices([s.nd for s in self.subsystems])

    def link_fault(self, source: str, target: str) -> dict:
        """Delay, jitter and loss configured on the directed link ``source -> target``."""
        for link in self.faults.get("links", []):
            if link["source"] == source and link["target"] == target:
                return {k: link[k] for k in ("delay_ms", "jitter_ms", "loss")}
        return dict(self.faults.get("default", {}))

    @classmethod
    def from_json(cls, data: dict) -> "RunMeta":
        """Build from :func:`meta_json` output ``data``.

        Raises
        ------
        ValueError
            A missing field, a wrong version or inconsistent dimensions.
        """
        try:
            if data.get("meta_version") != META_VERSION:
                raise ValueError(f"meta version {data.get('meta_version')!r} is not {META_VERSION}")
            subsystems = tuple(_subsystem(s) for s in data["subsystems"])
            return cls(run_id=str(data["run_id"]), scenario=str(data["scenario"]), method=str(data["method"]),
                       mode=str(data["mode"]), dt=float(data["dt"]),
                       deadline=None if data["deadline"] is None else float(data["deadline"]),
                       steps=int(data["steps"]), horizon=int(data["horizon"]), digest=str(data["digest"]),
                       subsystems=subsystems, edges=tuple((str(a), str(b)) for a, b in data["edges"]),
                       faults=dict(data.get("faults") or {}), trigger=str(data.get("trigger") or "always"),
                       estimation=bool(data.get("estimation")))
        except (KeyError, TypeError, IndexError) as exc:
            raise ValueError(f"not a run description ({type(exc).__name__}: {exc})") from None


def _slices(sizes: list[int]) -> list[slice]:
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    return [slice(int(offsets[i]), int(offsets[i + 1])) for i in range(len(sizes))]


def _subsystem(data: dict) -> SubsystemMeta:
    n, m = int(data["n"]), int(data["m"])
    state_lower, state_upper, _ = _bounds(data.get("state"), n)
    input_lower, input_upper, is_box = _bounds(data["input"], m)
    state_names, state_units = _names(data.get("states"), n, "x")
    input_names, input_units = _names(data.get("inputs"), m, "u")
    outputs, disturbances = data.get("outputs") or [], data.get("disturbances") or []
    output_names, output_units = _names(outputs, len(outputs), "y")
    disturbance_names, disturbance_units = _names(disturbances, len(disturbances), "d")
    measures = list(data.get("measures") or [None] * len(outputs))
    if len(measures) != len(outputs):
        raise ValueError(f"subsystem {data['name']}: {len(measures)} entries of 'measures' for {len(outputs)} outputs")
    return SubsystemMeta(name=str(data["name"]), state_names=state_names, input_names=input_names,
                         state_lower=state_lower, state_upper=state_upper, input_lower=input_lower,
                         input_upper=input_upper, input_is_box=is_box, state_units=state_units,
                         input_units=input_units, output_names=output_names, output_units=output_units,
                         disturbance_names=disturbance_names, disturbance_units=disturbance_units,
                         measures=tuple(None if j is None or not 0 <= int(j) < n else int(j) for j in measures))


def _names(labels: list | None, dim: int, prefix: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(names, units) from ``[[name, unit], ...]``, or ``x1 …`` and no units."""
    if not labels or len(labels) != dim:
        return tuple(f"{prefix}{j + 1}" for j in range(dim)), ("",) * dim
    return tuple(str(name) for name, _ in labels), tuple(str(unit) for _, unit in labels)


def _bounds(linear_set: dict | None, dim: int) -> tuple[tuple[float, ...], tuple[float, ...], bool]:
    """Per-coordinate (lower, upper, is_box) of ``lower <= H v <= upper``; NaN where unbounded."""
    nan = (math.nan,) * dim
    if linear_set is None:
        return nan, nan, True
    H = np.array(linear_set["H"], float).reshape(-1, dim)
    lower = np.array([-np.inf if v is None else v for v in linear_set["lower"]], float)
    upper = np.array([np.inf if v is None else v for v in linear_set["upper"]], float)
    if H.shape == (dim, dim) and np.array_equal(H, np.eye(dim)):
        lo, hi, is_box = lower, upper, True
    else:
        lo, hi, is_box = *box_hull(H, lower, upper), False
    return (tuple(float(v) if np.isfinite(v) else math.nan for v in lo),
            tuple(float(v) if np.isfinite(v) else math.nan for v in hi), is_box)

"""A prepared run as plain JSON: what an agent process needs, loadable without pydantic.

``dmpc run`` writes ``run.json`` into the run folder and starts its agents from it, so an
agent process imports neither the scenario schema (pydantic) nor the design solvers: it
starts faster and stays smaller. The design digest inside is checked by the plant as usual.
The bundle is derived data: the scenario file stays the source of truth.

With ``estimation``, the bundle carries each subsystem's C and the estimator's gains themselves
(L, P and the noise weights, as JSON floats, which read back exactly): an agent rebuilds the same
:class:`~dmpc.estimation.kalman.EstimatorDesign` bit for bit without solving a Riccati equation or
loading scipy.linalg, and the design digest, which covers C and L, checks that it did.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from dmpc.bus.faults import FaultPlan
from dmpc.core.errors import DesignError
from dmpc.core.steps import ProtocolOptions, TriggerOptions
from dmpc.core.system import CoupledSystem, Coupling, LinearSet, Subsystem
from dmpc.estimation.kalman import EstimatorDesign, LocalGain, NoiseWeights
from dmpc.estimation.model import augment
from dmpc.methods import DEFAULT_METHOD, method_spec
from dmpc.offline import design_from_json
from dmpc.offline.tubes import Tightening
from dmpc.prepared import Prepared, design_digest

BUNDLE_VERSION = 2


def _set_json(s: LinearSet | None) -> dict | None:
    if s is None:
        return None
    return {"H": s.H.tolist(), "lower": _floats(s.lower), "upper": _floats(s.upper)}


def _floats(a: np.ndarray) -> list:
    """Floats with infinities as strings, which JSON cannot hold as numbers."""
    return [float(v) if np.isfinite(v) else ("inf" if v > 0 else "-inf") for v in np.asarray(a, float)]


def _set_from(d: dict | None) -> LinearSet | None:
    return None if d is None else _linear_set(d)


def _linear_set(d: dict) -> LinearSet:
    return LinearSet(np.array(d["H"], float), np.array(d["lower"], float), np.array(d["upper"], float))


def _sparse_json(a: np.ndarray) -> dict:
    """A matrix as its shape and nonzero entries (Omega's rows reach a few subsystems each)."""
    rows, cols = np.nonzero(a)
    return {"shape": list(a.shape), "rows": rows.tolist(), "cols": cols.tolist(), "values": a[rows, cols].tolist()}


def _dense(d: dict) -> np.ndarray:
    a = np.zeros(tuple(int(v) for v in d["shape"]))
    a[np.asarray(d["rows"], dtype=np.intp), np.asarray(d["cols"], dtype=np.intp)] = np.asarray(d["values"], float)
    return a


def bundle_json(prepared: Prepared) -> dict:
    """Everything an agent needs of the ``prepared`` run, as JSON-ready data."""
    system = prepared.system
    return {
        "bundle_version": BUNDLE_VERSION,
        "name": prepared.name,
        "coupling": prepared.coupling,
        "method": prepared.method,
        "subsystems": [{"name": s.name, "A": s.A.tolist(), "B": s.B.tolist(), "Q": s.Q.tolist(), "R": s.R.tolist(),
                        "x0": s.x0.tolist(), "input": _set_json(s.input_set), "state": _set_json(s.state_set),
                        **({} if s.C is None else {"C": s.C.tolist()}),
                        **({} if s.x_op is None else {"x_op": s.state_offset.tolist(), "u_op": s.input_offset.tolist()}),
                        **({} if s.state_margin is None else {"state_margin": s.state_margin.tolist()})}
                       for s in system.subsystems],
        "couplings": [{"target": c.target, "source": c.source, "A": c.A.tolist(), "B": c.B.tolist()}
                      for c in system.couplings],
        "edges": [list(e) for e in system.edges],
        "design": {**prepared.design_json(omega=False), "omega": _sparse_json(prepared.design.terminal.omega)},
        "tightening": [{"input": t.input_margin.tolist(), "state": t.state_margin.tolist(),
                        "terminal": t.terminal_margin.tolist()} for t in prepared.design.tightening],
        "protocol": prepared.protocol.to_json(),
        "mode": prepared.mode, "dt": prepared.dt, "deadline": prepared.deadline,
        "faults": prepared.faults.to_json(),
        "trigger": prepared.trigger.to_json(),
        **({} if prepared.estimator is None else {"estimation": _estimator_json(prepared.estimator)}),
    }


def _estimator_json(estimator: EstimatorDesign) -> dict:
    """The disturbance models and every agent's gain, L and P with their noise weights."""
    return {"disturbance": [part.kind for part in estimator.model.parts],
            "gains": [{"L": g.L.tolist(), "P": g.P.tolist(), "radius": g.radius,
                       "noise": {"state": g.noise.state.tolist(), "disturbance": g.noise.disturbance.tolist(),
                                 "measurement": g.noise.measurement.tolist()}} for g in estimator.gains]}


def _estimator_from(system: CoupledSystem, d: dict) -> EstimatorDesign:
    """The estimator written by :func:`_estimator_json` for ``system`` (the detectability figures stay
    with the design that checked them)."""
    model = augment(system, [s.C for s in system.subsystems], [str(kind) for kind in d["disturbance"]])
    if len(d["gains"]) != model.M:
        raise ValueError(f"{len(d['gains'])} estimator gains for {model.M} subsystems")
    gains = []
    for part, g in zip(model.parts, d["gains"]):
        noise = NoiseWeights(*(np.array(g["noise"][key], float).reshape(size, size) for key, size in
                               (("state", part.n), ("disturbance", part.nd), ("measurement", part.p))))
        L = np.array(g["L"], float).reshape(part.n + part.nd, part.p)
        P = np.array(g["P"], float).reshape(part.n + part.nd, part.n + part.nd)
        gains.append(LocalGain(part.name, L, P, noise, float(g["radius"])))
    return EstimatorDesign(model, tuple(gains))


def write_bundle(prepared: Prepared, path: Path) -> None:
    """Write the ``prepared`` run's :func:`bundle_json` to ``path`` (``run.json``)."""
    Path(path).write_text(json.dumps(bundle_json(prepared)))


def _optional_array(d: dict, key: str) -> np.ndarray | None:
    """``d[key]`` as a float array, None when absent."""
    return None if d.get(key) is None else np.array(d[key], float)


def load_bundle(path: Path) -> Prepared:
    """Rebuild a Prepared from ``run.json`` at ``path`` (ValueError with a clear message if malformed)."""
    try:
        d = json.loads(Path(path).read_text())
        if d.get("bundle_version") != BUNDLE_VERSION:
            raise ValueError(f"bundle version {d.get('bundle_version')!r} is not {BUNDLE_VERSION}")
        subsystems = tuple(Subsystem(s["name"], np.array(s["A"], float), np.array(s["B"], float),
                                     np.array(s["Q"], float), np.array(s["R"], float), np.array(s["x0"], float),
                                     _linear_set(s["input"]), _set_from(s["state"]),
                                     None if s.get("C") is None else np.array(s["C"], float).reshape(-1, len(s["A"])),
                                     x_op=_optional_array(s, "x_op"), u_op=_optional_array(s, "u_op"),
                                     state_margin=_optional_array(s, "state_margin"))
                           for s in d["subsystems"])
        couplings = tuple(Coupling(c["target"], c["source"], np.array(c["A"], float), np.array(c["B"], float))
                          for c in d["couplings"])
        system = CoupledSystem(subsystems, couplings, tuple(tuple(e) for e in d["edges"]))
        design_data = {**d["design"], "omega": _dense(d["design"]["omega"])}
        # written by dmpc run from the design it verified, and checked against its digest below
        design = design_from_json(system, design_data, horizon=int(design_data["horizon"]),
                                  alpha0=np.array(design_data["alpha0"], float), beta0=float(design_data["beta0"]),
                                  verify=False)
        # the tube margins travel as computed: recomputing them would need the scenario's revision bounds
        tightening = [Tightening(np.array(t["input"], float).reshape(design.horizon, -1),
                                 np.array(t["state"], float).reshape(design.horizon + 1, -1),
                                 np.array(t["terminal"], float)) for t in d["tightening"]]
        design = dataclasses.replace(design, tightening=tightening, tube=design_data["tube"])
        plan = FaultPlan.from_json(d["faults"])
        method = method_spec(str(d.get("method", DEFAULT_METHOD))).name
        trigger = TriggerOptions.from_json(d.get("trigger", {}))
        estimator = None if d.get("estimation") is None else _estimator_from(system, d["estimation"])
        prepared = Prepared(scenario=None, system=system, design=design,
                            digest=design_digest(design, method, trigger, estimator),
                            protocol=ProtocolOptions.from_json(d["protocol"]), mode=d["mode"], dt=float(d["dt"]),
                            deadline=d["deadline"], faults=plan, name=d["name"], coupling=d["coupling"],
                            method=method, trigger=trigger, estimator=estimator)
    except (OSError, KeyError, TypeError, ValueError, IndexError, DesignError) as exc:
        raise ValueError(f"{path}: not a usable run bundle ({exc})") from None
    if prepared.digest != design_data.get("digest"):
        raise ValueError(f"{path}: the design does not match its digest")
    return prepared

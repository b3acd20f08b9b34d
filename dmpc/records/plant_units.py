"""The records in the plant's own units: a run whose subsystems give an ``operating_point`` is
controlled in deviations from it (the model's coordinates), and recorded around it.

Every state-like record (the state, the targets and setpoints, the estimate, the plans) is written
as ``x_op + value``, every input-like one as ``u_op + value``, every output-like one as
``C x_op + value``; scales and differences (alpha, beta, costs, the disturbance estimate, the
innovation) are not moved. Without an operating point nothing is moved, not even by adding zeros.
"""
from __future__ import annotations

import numpy as np

from dmpc.core.system import CoupledSystem

STATE_KEYS = ("x", "x_next", "setpoint", "reference", "target", "x_hat")
"""Records of n values (or rows of them) in the states' coordinates."""
INPUT_KEYS = ("u", "setpoint_u", "reference_u", "target_u")
"""Records of m values in the inputs' coordinates."""
OUTPUT_KEYS = ("y", "setpoint_y")
"""Records of p values in the outputs' coordinates."""


class PlantUnits:
    """The operating point of a ``system`` per record key.

    Parameters
    ----------
    system : CoupledSystem
        Its subsystems' ``x_op`` and ``u_op`` (zeros where a subsystem gives none).

    Attributes
    ----------
    offsets : dict of str -> ndarray
        Per key the offset that a record of that key gets added (its last axis): ``x`` (n,),
        ``u`` (m,), ``y`` (p,) and the keys of each, and ``plan_z_<name>`` (n_i,),
        ``plan_v_<name>`` (m_i,) per subsystem.
    """

    def __init__(self, system: CoupledSystem) -> None:
        x, u = system.state_offset, system.input_offset
        y = np.concatenate([s.operating_output for s in system.subsystems])
        self.offsets: dict[str, np.ndarray] = {
            **{key: x for key in STATE_KEYS}, **{key: u for key in INPUT_KEYS}, **{key: y for key in OUTPUT_KEYS}}
        for s in system.subsystems:
            self.offsets[f"plan_z_{s.name}"] = s.state_offset
            self.offsets[f"plan_v_{s.name}"] = s.input_offset

    @classmethod
    def of(cls, system: CoupledSystem) -> PlantUnits | None:
        """The plant's units of ``system``, or None when it has no operating point (nothing to move)."""
        return cls(system) if system.has_operating_point else None

    def line(self, line: dict) -> dict:
        """The step line ``line`` (its values as arrays or lists, None where unknown) with the values of
        the keys in :attr:`offsets` moved to the plant's units; changed in place and returned."""
        for key, value in line.items():
            offset = self.offsets.get(key)
            if offset is not None and value is not None:
                line[key] = np.asarray(value, dtype=float) + offset
        return line

    def array(self, key: str, value: np.ndarray) -> np.ndarray:
        """The array ``value`` of the record ``key`` (rows of its values) in the plant's units; other
        keys are returned as they are."""
        offset = self.offsets.get(key)
        return value if offset is None else np.asarray(value, dtype=float) + offset

"""Plants that are not the controllers' own model: other matrices, or a function of the user's,
and :func:`make_plant`, the plant a prepared run steps.

Both keep the interface of :class:`~dmpc.plant.dynamics.Plant` that the coordinator uses: the
state ``x``, the step index ``k`` and ``step(u) -> x_next``; the optional additive disturbance
is applied after the model.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from dmpc.core.errors import DmpcError
from dmpc.core.system import CoupledSystem
from dmpc.plant.disturbance import DisturbanceSequence
from dmpc.plant.dynamics import Plant
from dmpc.prepared import PlantFunction, Prepared


class PlantModelError(DmpcError, RuntimeError):
    """The user's plant function failed or returned something that is not a state.

    The exception it raised, if any, is the ``__cause__`` (its traceback shows the user's code).
    """


class MatrixPlant(Plant):
    """x(k+1) = A x(k) + B u(k) (+ w(k)) with matrices other than the system's.

    Parameters
    ----------
    system : CoupledSystem
        Gives x0 and the dimensions.
    A : ndarray, shape (n, n)
    B : ndarray, shape (n, m)
    disturbance : callable k -> ndarray (n,), optional
    """

    def __init__(self, system: CoupledSystem, A: np.ndarray, B: np.ndarray, x0: np.ndarray | None = None,
                 disturbance: Callable[[int], np.ndarray] | None = None) -> None:
        super().__init__(system, x0, disturbance)
        self.A = np.asarray(A, dtype=float)
        self.B = np.asarray(B, dtype=float)

    def step(self, u: np.ndarray) -> np.ndarray:
        """Apply u(k) (shape (m,)) and return x(k+1) (shape (n,))."""
        return self._advance(self.A @ self.x + self.B @ u)

    def _advance(self, x_next: np.ndarray) -> np.ndarray:
        if self._disturbance is not None:
            x_next = x_next + self._disturbance(self.k)
        self.x = x_next
        self.k += 1
        return x_next


class FunctionPlant(MatrixPlant):
    """x(k+1) = f(x(k), u(k), k) (+ w(k)) with the user's function f.

    With an operating point (the subsystems' ``x_op``, ``u_op``), f works in the plant's own units:
    it is given x_op + x and u_op + u and returns the next state in those units, from which x_op is
    taken back; the plant's state stays in the model's deviations, like the rest of the run.

    Parameters
    ----------
    system : CoupledSystem
        Gives x0, the dimensions and the operating point.
    function : callable (x, u, k) -> x_next
        x (n,), u (m,): copies, so the function may change them; it returns n numbers.
    name : str
        How the function is named in messages (e.g. ``module:function``).
    disturbance : callable k -> ndarray (n,), optional
    """

    def __init__(self, system: CoupledSystem, function: PlantFunction, name: str = "",
                 x0: np.ndarray | None = None, disturbance: Callable[[int], np.ndarray] | None = None) -> None:
        super().__init__(system, system.A, system.B, x0, disturbance)
        self.function = function
        self.name = name or getattr(function, "__qualname__", repr(function))
        self._operating = (system.state_offset, system.input_offset) if system.has_operating_point else None

    def step(self, u: np.ndarray) -> np.ndarray:
        """Call the function for step k with the inputs u (m,) and return x(k+1); PlantModelError if it fails."""
        where = f"the plant function {self.name} failed at step k = {self.k}"
        x, u = self.x.copy(), np.array(u, dtype=float)
        if self._operating is not None:
            x, u = x + self._operating[0], u + self._operating[1]
        try:
            out = self.function(x, u, self.k)
        except Exception as exc:
            raise PlantModelError(f"{where}: {type(exc).__name__}: {exc}") from exc
        try:
            x_next = np.asarray(out, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            raise PlantModelError(f"{where}: it returned {type(out).__name__}, not {self.x.size} numbers") from None
        if x_next.size != self.x.size:
            raise PlantModelError(f"{where}: it returned {x_next.size} numbers, the state has {self.x.size}")
        if self._operating is not None:
            x_next = x_next - self._operating[0]
        return self._advance(x_next)


def make_plant(prepared: Prepared, x0: np.ndarray | None = None) -> Plant:
    """The plant of the ``prepared`` run: its model (nominal, exact or the user's function) and disturbance,
    starting from x0 (n,) (the scenario's by default)."""
    setup, system = prepared.plant, prepared.system
    w = None if setup.disturbance is None else DisturbanceSequence(setup.disturbance)
    if setup.function is not None:
        return FunctionPlant(system, setup.function, setup.function_name, x0=x0, disturbance=w)
    if setup.A is not None and setup.B is not None:  # given together, for the exact model
        return MatrixPlant(system, setup.A, setup.B, x0=x0, disturbance=w)
    return Plant(system, x0, disturbance=w)

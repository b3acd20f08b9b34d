"""Offline design: gains, terminal set, sigma and tube tightening, assembled and reported."""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from dmpc.core.errors import DesignError
from dmpc.core.system import CoupledSystem
from dmpc.offline.gains import GainDesign, lmi_gains, lqr_gains, verify_gains
from dmpc.offline.terminal_set import TerminalSet, maximal_admissible_set
from dmpc.offline.tubes import RevisionBound, Tightening, robust_tightening

__all__ = ["Design", "DesignError", "assemble", "design_gains", "design_from_json", "GainDesign", "RevisionBound", "TerminalSet", "Tightening", "design_system"]


@dataclass(frozen=True)
class ControllerDesign:
    """Everything computed offline that the agents and the coordinator use.

    Attributes
    ----------
    gains : GainDesign
    terminal : TerminalSet
    tightening : list of Tightening, one per subsystem
    horizon : int
    alpha0 : ndarray, shape (n,)
    beta0 : float
    tube : str
    start : dict or None
        How ``horizon: auto`` and ``beta0: auto`` were resolved and what the start check found
        (reported in design.json beside the design; not part of it, nor of its digest).
    """

    gains: GainDesign
    terminal: TerminalSet
    tightening: list[Tightening]
    horizon: int
    alpha0: np.ndarray
    beta0: float
    tube: str
    start: dict | None = field(default=None, compare=False)

    @property
    def sigma0(self) -> float:
        return self.terminal.sigma(self.alpha0)

    def to_json(self, omega: bool = True) -> dict:
        """The design as plain JSON (the content of ``design.json``); ``omega=False`` leaves out
        the rows of X^f (``omega``), the bulk of it."""
        g = self.gains
        return {
            "gains_method": g.method,
            "objective": g.objective,
            "rho": g.rho,
            "lyapunov_margin": g.lyapunov_margin,
            "lyapunov_tolerance": g.lyapunov_tolerance,
            "lyapunov_margin_thin": g.margin_thin,
            "K": [k.tolist() for k in g.K],
            "P": [p.tolist() for p in g.P],
            "omega_rows": self.terminal.rows,
            "t_star": self.terminal.t_star,
            **({"omega": self.terminal.omega.tolist()} if omega else {}),
            "sigma0": self.sigma0,
            "alpha0": self.alpha0.tolist(),
            "beta0": self.beta0,
            "horizon": self.horizon,
            "tube": self.tube,
            "terminal_margin": [t.terminal_margin.tolist() for t in self.tightening],
        }

    def with_start(self, start: dict) -> "ControllerDesign":
        """The same design with the start report ``start``."""
        return replace(self, start=start)


def design_gains(system: CoupledSystem, gains: str,
                 given: tuple[list[np.ndarray], list[np.ndarray]] | None = None) -> tuple[GainDesign, TerminalSet]:
    """The gains of ``system`` by the method ``gains`` (``lmi``, ``lqr`` or ``given``: K_i and P_i in
    ``given``, verified) and the terminal set X^f they give."""
    if gains == "lmi":
        g = lmi_gains(system)
    elif gains == "lqr":
        g = lqr_gains(system)
    elif gains == "given":
        if given is None:
            raise DesignError("gains 'given' needs K and P for every subsystem")
        g = verify_gains(system, given[0], given[1], "given")
    else:
        raise DesignError(f"unknown gain design method {gains!r} (expected lmi, lqr or given)")
    return g, maximal_admissible_set(system, g.K)


def assemble(system: CoupledSystem, gains: GainDesign, terminal: TerminalSet, *, horizon: int, alpha0: np.ndarray,
             beta0: float, tube: str = "none", revision_bounds: dict[int, RevisionBound] | None = None,
             disturbance_bounds: dict[int, np.ndarray] | None = None) -> ControllerDesign:
    """A ControllerDesign of ``system`` from its gains and terminal set at one horizon (checks beta0
    and the tubes), with the terminal box's start ``alpha0`` (n,), ``beta0``; ``revision_bounds``
    (per subsystem index) bound the neighbours' plan revisions for the tube of ``tube: robust``.

    ``disturbance_bounds``: per subsystem index, the bound (n_i,) of an additive plant
    disturbance, added to the tube's W_i when ``tube`` is ``robust``.
    """
    return _assemble(system, gains, terminal, horizon, alpha0, beta0, tube, revision_bounds, disturbance_bounds)


def design_system(system: CoupledSystem, *, gains: str, horizon: int, alpha0: np.ndarray, beta0: float,
                  given: tuple[list[np.ndarray], list[np.ndarray]] | None = None, tube: str = "none",
                  revision_bounds: dict[int, RevisionBound] | None = None) -> ControllerDesign:
    """Run the whole offline design; DesignError (one line, with figures) if anything fails.

    Parameters
    ----------
    system : CoupledSystem
    gains : {"lmi", "lqr", "given"}
    horizon : int
        N.
    alpha0 : ndarray, shape (n,)
    beta0 : float
    given : (K list, P list), required for ``gains="given"``
    tube : {"none", "robust"}
    revision_bounds : dict subsystem index -> RevisionBound, required for ``tube="robust"``
    """
    g, terminal = design_gains(system, gains, given)
    return _assemble(system, g, terminal, horizon, alpha0, beta0, tube, revision_bounds)


def design_from_json(system: CoupledSystem, data: dict, *, horizon: int, alpha0: np.ndarray, beta0: float,
                     tube: str = "none", revision_bounds: dict[int, RevisionBound] | None = None,
                     disturbance_bounds: dict[int, np.ndarray] | None = None, verify: bool = True) -> ControllerDesign:
    """Rebuild a design of ``system`` from ``design.json`` content ``data`` without re-solving the
    LMI or the LPs, at ``horizon`` with ``alpha0``, ``beta0``, ``tube``, ``revision_bounds`` and
    ``disturbance_bounds`` as :func:`assemble` takes them.

    The gains are verified again, the tubes recomputed; DesignError if the file does not fit the
    system. ``verify=False`` takes the gains' figures (rho, the margin of (10)) from the file
    instead: for a file this program wrote from a verified design (a run bundle), since the
    check costs O(n^3) on the global system, seconds per process at a thousand subsystems.
    """
    try:
        K = [np.asarray(k, dtype=float) for k in data["K"]]
        P = [np.asarray(p, dtype=float) for p in data["P"]]
        omega = np.asarray(data["omega"], dtype=float)
        t_star = int(data["t_star"])
        method, objective = str(data["gains_method"]), str(data.get("objective", ""))
    except (KeyError, TypeError, ValueError) as exc:
        raise DesignError(f"design file: missing or malformed entry ({exc})") from None
    shapes_ok = (len(K) == system.M and len(P) == system.M and omega.ndim == 2 and omega.shape[1] == system.n
                 and all(K[i].shape == (s.m, s.n) and P[i].shape == (s.n, s.n) for i, s in enumerate(system.subsystems)))
    if not shapes_ok:
        raise DesignError("design file: K, P or omega do not match the scenario's dimensions")
    if int(data.get("horizon", horizon)) != horizon:
        raise DesignError(f"design file: made for horizon {data.get('horizon')}, the scenario has {horizon}")
    g = verify_gains(system, K, P, method, objective) if verify else _recorded_gains(data, K, P, method, objective)
    terminal = TerminalSet(omega=omega, t_star=t_star)
    design = _assemble(system, g, terminal, horizon, alpha0, beta0, tube, revision_bounds, disturbance_bounds)
    start = data.get("start")
    return design.with_start(start) if isinstance(start, dict) else design


def _recorded_gains(data: dict, K: list[np.ndarray], P: list[np.ndarray], method: str, objective: str) -> GainDesign:
    """The gains with the verification figures ``design.json`` recorded."""
    try:
        return GainDesign(K=K, P=P, method=method, rho=float(data["rho"]), lyapunov_margin=float(data["lyapunov_margin"]),
                          lyapunov_tolerance=float(data["lyapunov_tolerance"]), objective=objective,
                          margin_thin=bool(data.get("lyapunov_margin_thin", False)))
    except (KeyError, TypeError, ValueError) as exc:
        raise DesignError(f"design file: missing or malformed entry ({exc})") from None


def _assemble(system: CoupledSystem, g: GainDesign, terminal: TerminalSet, horizon: int, alpha0: np.ndarray,
              beta0: float, tube: str, revision_bounds: dict[int, RevisionBound] | None,
              disturbance_bounds: dict[int, np.ndarray] | None = None) -> ControllerDesign:
    sigma0 = terminal.sigma(alpha0)
    if beta0 > sigma0 + 1e-12:
        raise DesignError(f"terminal: beta0 = {beta0:.6g} exceeds sigma(alpha0) = {sigma0:.6g}: the initial "
                          "terminal box would leave X^f; lower beta0 or move alpha0")
    tightening = []
    for i, s in enumerate(system.subsystems):
        if tube == "robust":
            t = robust_tightening(system, i, g.K[i], horizon, revision_bounds or {},
                                  (disturbance_bounds or {}).get(i))
            if np.any(t.terminal_margin >= beta0):
                raise DesignError(
                    f"tube: robust: the tightened terminal box of subsystem {s.name} is empty at k = 0 "
                    f"(margin {np.max(t.terminal_margin):.4g} >= beta0 = {beta0:.4g})")
        else:
            r_x = 0 if s.state_set is None else s.state_set.H.shape[0]
            t = Tightening.none(s.n, s.input_set.H.shape[0], r_x, horizon)
        tightening.append(t)
    return ControllerDesign(gains=g, terminal=terminal, tightening=tightening, horizon=horizon,
                  alpha0=np.asarray(alpha0, float), beta0=float(beta0), tube=tube)

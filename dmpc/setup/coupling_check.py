"""The input-coupling check of ``dmpc design`` and ``dmpc validate`` (:mod:`dmpc.offline.input_coupling`):
its figures for a designed run, or for a scenario before any design, and whether the scenario's
method is one the check applies to.

``dmpc design`` uses the design's N, K_i and P_i. ``dmpc validate`` designs nothing: it uses the
given gains (``design.gains: given``) or each subsystem's own LQR gain (the discrete Riccati
equation of A_ii, B_ii, Q_i, R_i), and the scenario's horizon (VALIDATE_HORIZON when it is
``auto``); it checks only scenarios with some B_ij != 0, since without them nothing is reported.
"""
from __future__ import annotations

import numpy as np

from dmpc.core.system import CoupledSystem
from dmpc.methods import method_spec
from dmpc.offline.input_coupling import InputCoupling, input_coupling
from dmpc.prepared import Prepared
from dmpc.scenario import Scenario, build_system, given_gains

COOPERATIVE_METHOD = "tv-box-coop"
"""The method for systems whose inputs drive their neighbours (docs/fourtank.md)."""
VALIDATE_HORIZON = 10
"""The horizon ``dmpc validate`` checks at when the scenario's is ``auto`` (it is not chosen before the design)."""


def non_cooperative(method: str) -> bool:
    """True if ``method`` is one whose agents minimise their own cost only (every distributed one
    but the cooperative ones); False for an unknown name."""
    try:
        spec = method_spec(method)
    except ValueError:
        return False
    return bool(spec.distributed) and not bool(getattr(spec, "cooperative", method == COOPERATIVE_METHOD))


def design_coupling(prepared: Prepared) -> InputCoupling:
    """The figures for a prepared run: its design's N, K_i, P_i and the rounds per step."""
    gains = prepared.design.gains
    return input_coupling(prepared.system, gains.K, gains.P, prepared.design.horizon, prepared.protocol.rounds)


def design_with_coupling(prepared: Prepared, coupling: InputCoupling | None = None) -> dict:
    """``dmpc design --json`` of a ``prepared`` run: its ``design.json`` and the input-coupling
    figures (``coupling``, computed here when not given)."""
    coupling = design_coupling(prepared) if coupling is None else coupling
    return {**prepared.design_json(), "input_coupling": coupling.to_json(prepared.names)}


def scenario_coupling(scenario: Scenario, system: CoupledSystem | None = None) -> InputCoupling | None:
    """The figures for a ``scenario`` without its design (``dmpc validate``); None when no B_ij != 0.
    ``system``: the scenario's, if built already (it is built only when the file has some B_ij != 0)."""
    if system is None:
        exact = scenario.time == "continuous" and scenario.discretisation.method == "exact-zoh"
        if not exact and not any(c.B is not None and np.any(c.B) for c in scenario.resolved_couplings()):
            return None  # B_ij = 0 in the file, so in the discrete model too: spare building it
        system = build_system(scenario)
    if not any(np.any(c.B) for c in system.couplings):
        return None
    if scenario.design.gains == "given":
        K, P = given_gains(scenario)
    else:
        K, P = local_lqr(system)
    horizon = scenario.horizon if isinstance(scenario.horizon, int) else VALIDATE_HORIZON
    return input_coupling(system, K, P, horizon, scenario.options.iterations)


def local_lqr(system: CoupledSystem) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Each subsystem's own LQR gain K_i (m_i, n_i) and Riccati solution P_i (n_i, n_i) in ``system``, from A_ii,
    B_ii, Q_i, R_i alone; K_i = 0, P_i = Q_i where the Riccati equation has no stabilising solution."""
    from scipy.linalg import solve_discrete_are  # start-up time: scipy.linalg only where a check needs it

    K, P = [], []
    for s in system.subsystems:
        try:
            X = solve_discrete_are(s.A, s.B, s.Q, s.R)
        except (ValueError, np.linalg.LinAlgError):
            K.append(np.zeros((s.m, s.n)))
            P.append(np.array(s.Q, dtype=float))
            continue
        K.append(-np.linalg.solve(s.R + s.B.T @ X @ s.B, s.B.T @ X @ s.A))
        P.append(0.5 * (X + X.T))
    return K, P

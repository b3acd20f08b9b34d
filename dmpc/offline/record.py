"""The offline design as a record: a frozen result indexed by subsystem name (``dmpc.Design``).

It holds exactly what ``design.json`` holds (``dmpc design --json``), read into arrays: the
gains, the terminal set X^f, sigma(alpha(0)), the initial box, the horizon and how it was
chosen, the checks, and for a continuous-time model the discrete matrices used.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Mapping

import numpy as np


@dataclass(frozen=True, eq=False, repr=False)
class Design:
    """The offline design.

    Attributes
    ----------
    names : tuple of str
        Subsystem names, in scenario order.
    K : mapping name -> ndarray, shape (m_i, n_i)
        Terminal gains.
    P : mapping name -> ndarray, shape (n_i, n_i)
        Terminal weights.
    omega : ndarray, shape (rows, n)
        X^f = {x : omega x <= 1} on the global state.
    t_star : int
        Steps of the maximal admissible set construction.
    horizon : int
        N.
    alpha0 : mapping name -> ndarray, shape (n_i,)
    beta0 : float
    sigma0 : float
        sigma(alpha(0)): the largest box around alpha(0) inside X^f.
    gains_method : str
        ``lmi``, ``lqr`` or ``given``.
    rho : float
        Spectral radius of A + BK (< 1: the terminal controller is stabilising).
    lyapunov_margin, lyapunov_tolerance : float
        The largest eigenvalue of (A+BK)'P(A+BK) - P + Q + K'RK, and what it must not exceed.
    tube : str
    digest : str
        The design's short hash; every process of a run agrees on it.
    start : dict or None
        How the horizon and beta0 were chosen.
    model : dict or None
        ``time: continuous`` only: the discrete matrices used, the fill-in of the exact
        discretisation and the largest model error (``design.json`` ``model``).
    json : dict
        The content of ``design.json``.
    """

    names: tuple[str, ...]
    K: Mapping[str, np.ndarray]
    P: Mapping[str, np.ndarray]
    omega: np.ndarray
    t_star: int
    horizon: int
    alpha0: Mapping[str, np.ndarray]
    beta0: float
    sigma0: float
    gains_method: str
    rho: float
    lyapunov_margin: float
    lyapunov_tolerance: float
    tube: str
    digest: str
    start: dict | None = None
    model: dict | None = None
    json: dict = field(default_factory=dict, repr=False)

    def __repr__(self) -> str:
        return (f"Design(horizon={self.horizon}, beta0={self.beta0:.4g}, sigma0={self.sigma0:.4g}, "
                f"gains_method={self.gains_method!r}, rho={self.rho:.4g}, names={self.names}, digest={self.digest!r})")

    @classmethod
    def from_json(cls, data: dict, names: list[str] | None = None) -> "Design":
        """Read ``design.json`` content ``data``; ``names`` default to "1".."M"."""
        K = [np.asarray(k, float) for k in data["K"]]
        P = [np.asarray(p, float) for p in data["P"]]
        names = list(names) if names is not None else [str(i + 1) for i in range(len(K))]
        sizes = np.cumsum([0] + [p.shape[0] for p in P])
        alpha = np.asarray(data.get("alpha0", np.zeros(sizes[-1])), float)
        return cls(
            names=tuple(names),
            K=MappingProxyType(dict(zip(names, K))),
            P=MappingProxyType(dict(zip(names, P))),
            omega=np.asarray(data["omega"], float),
            t_star=int(data.get("t_star", 0)),
            horizon=int(data["horizon"]),
            alpha0=MappingProxyType({name: alpha[sizes[i]:sizes[i + 1]] for i, name in enumerate(names)}),
            beta0=float(data["beta0"]),
            sigma0=float(data.get("sigma0", np.nan)),
            gains_method=str(data.get("gains_method", "")),
            rho=float(data.get("rho", np.nan)),
            lyapunov_margin=float(data.get("lyapunov_margin", np.nan)),
            lyapunov_tolerance=float(data.get("lyapunov_tolerance", np.nan)),
            tube=str(data.get("tube", "none")),
            digest=str(data.get("digest", "")),
            start=data.get("start"),
            model=data.get("model"),
            json=data,
        )

    def sigma(self, alpha: np.ndarray) -> float:
        """sigma(alpha) = min_l (1 - omega_l alpha) / ||omega_l||_1 for a global alpha of shape (n,)."""
        rows = self.omega
        return float(np.min((1.0 - rows @ np.asarray(alpha, float)) / np.abs(rows).sum(axis=1)))

    def table(self) -> str:
        """The design's figures as a plain-text table."""
        lines = [("gains", self.gains_method), ("rho(A+BK)", f"{self.rho:.4f}"),
                 ("(10) margin", f"{self.lyapunov_margin:.3g} (must be <= {self.lyapunov_tolerance:.2g})"),
                 ("X^f rows, t*", f"{self.omega.shape[0]}, {self.t_star}"), ("sigma(alpha0)", f"{self.sigma0:.4g}"),
                 ("beta0", f"{self.beta0:.4g}"), ("horizon N", str(self.horizon)), ("tube", self.tube)]
        if self.model is not None:
            fill = self.model["fill_in"]
            lines.append(("model", f"continuous, dt = {self.model['dt']:g} s, {self.model['method']}; exact "
                                   f"model's entries outside the graph up to {fill['largest']:.3g}, model error "
                                   f"{self.model['model_error']:.3g}"))
        for name in self.names:
            lines.append((f"K_{name}", np.array2string(self.K[name], precision=4).replace("\n", "")))
        width = max(len(a) for a, _ in lines)
        return "\n".join(f"{a:<{width}}  {b}" for a, b in lines)

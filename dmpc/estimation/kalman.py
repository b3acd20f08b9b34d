"""Steady-state Kalman gains of the agents' filters and the coupled estimator's stability.

Agent i's filter runs on its own augmented model (:meth:`~dmpc.estimation.model.LocalModel.augmented`:
A_ii, B_d,i, C_i, C_d,i) with the process noise covariance W_i = diag(W_x,i, W_d,i) (the states, and
the disturbances' random walk) and the measurement noise covariance V_i. Its prior (predicted)
covariance P_i solves the Riccati equation of the dual system,

    P = A P A' - A P C' (C P C' + V)^-1 C P A' + W     (``solve_discrete_are(A', C', W, V)``),

and its gain is the filter-form L_i = P_i C_i' (C_i P_i C_i' + V_i)^-1, of shape (n_i + n_d,i, p_i):
the estimate at step k uses y(k). The global gain is block diagonal, L = diag(L_i): agent i corrects
with its own y_i only, and the couplings enter its prediction through its neighbours' previous
estimates and inputs (:mod:`dmpc.estimation.observer`).

**Coupled stability.** Each L_i makes its own error dynamics (I - L_i C_aug,i) A_aug,i stable (the
Riccati equation guarantees it), but the couplings A_ij, B_ij (i != j) are not in agent i's model.
The estimation error of the whole system, e = [x - x^; d - d^], follows

    e+ = (I - L C_aug) A_aug e

with the coupled A_aug (the inputs cancel: every agent knows the inputs applied), and
:func:`design_estimator` requires its spectral radius below 1; otherwise a DesignError with the figure.
What helps is a filter that leans on its measurements rather than on its model, which leaves the
couplings out: more state noise or less measurement noise (I - L_i C_i, through which a neighbour's
error passes, shrinks). A slower filter makes it worse: on two scalar subsystems a_ii = 0.5,
a_12 = 2, a_21 = -2, both measured, the coupled radius is 2.06 with the default weights and with a
hundredfold measurement noise, and 0.97 with state noise 1e-2 against measurement noise 1e-4.

**At scale.** Up to :data:`~dmpc.estimation.model.COUPLED_DENSE_LIMIT` states of the augmented model
(n + n_d) the radius is the largest |eigenvalue| of the dense error dynamics and the coupled
detectability is checked densely first (:func:`~dmpc.estimation.model.check_coupled`). Above it (a
chain of 1024 subsystems has 3072: 21 s of dense SVDs and eigenvalues on a quiet two-core machine,
150 s under load, about 500 MB) the error dynamics F = (I - L C_aug) A_aug is built sparse
(:func:`error_operator`) and certified stable by a norm of one of its powers: rho(F) <=
||F^k||^(1/k) for every k and every induced norm, so ||F^k||_inf^(1/k) or ||F^k||_1^(1/k) below
1 - ``STABILITY_MARGIN`` for some k proves what the dense check tests (:func:`certify_schur`; the
chain: k = 6). A stable F also proves the coupled detectability conditions: an undetectable mode v
of the augmented pair (A_aug v = lambda v, C_aug v = 0, |lambda| >= 1) would be an eigenvector of
F with the same lambda, whatever the gains. When no power up to ``CERTIFICATE_POWERS`` certifies,
the dense checks run as below the limit: the same decisions and the same messages. The radius that
``dmpc design`` reports is then the largest |eigenvalue| ARPACK finds on the sparse F (the dense
one where ARPACK does not converge); the decision never rests on it.

**Default noise weights** (:meth:`NoiseWeights.scaled`). Each quantity has a scale, half the width
of its bounds (:func:`subsystem_scales`; 1 where unbounded); an output's scale is sum_j |C_rj| s_x,j;
an output disturbance has its output's scale, an input disturbance its input's. The covariances are
diagonal, with standard deviations as fractions of those scales:

- measurement noise ``MEASUREMENT_NOISE`` = 1e-2 (a sensor good to 1 % of its range);
- the disturbances' random walk ``DISTURBANCE_NOISE`` = 1e-3 per step;
- the states' process noise ``STATE_NOISE`` = 1e-4 per step.

Only the ratios shape the gain: a disturbance variance 1e-2 of the measurement's gives a scalar
bias filter a gain of about 0.1 (about ten steps to take up a step in the disturbance), slow enough
not to chase sensor noise; states ten times quieter still make the filter attribute a persistent
innovation to the disturbances, which is what removes the offset. Raising the measurement weight
slows the filter; raising the disturbance weight speeds up the offset's removal.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from dmpc.core.errors import DesignError
from dmpc.core.system import LinearSet, Subsystem, box_hull
from dmpc.estimation.model import (
    COUPLED_DENSE_LIMIT,
    AugmentedSystem,
    Detectability,
    LocalModel,
    check_coupled,
    check_subsystem,
)

STATE_NOISE = 1e-4
"""Default standard deviation of the states' process noise per step, as a fraction of each state's scale."""

DISTURBANCE_NOISE = 1e-3
"""Default standard deviation of the disturbances' random walk per step, as a fraction of their scale."""

MEASUREMENT_NOISE = 1e-2
"""Default standard deviation of the measurement noise, as a fraction of each output's scale."""

STABILITY_MARGIN = 1e-9
"""The coupled estimator counts as stable when its spectral radius is below 1 - this."""

CERTIFICATE_POWERS = 64
"""The most powers F^k of a large coupled estimator's error dynamics whose norms are tried as a
certificate of its stability (:func:`certify_schur`) before the dense check."""

CERTIFICATE_NONZEROS = 5_000_000
"""The powers stop early once F^k has more nonzeros than this (about 80 MB of values)."""

ARPACK_VALUES, ARPACK_VECTORS, ARPACK_TOLERANCE = 6, 60, 1e-6
"""The eigenvalues of largest magnitude ARPACK finds for the reported radius, its Krylov basis and
its relative tolerance (on the chain at M = 30, 256, 400 and 1024: the dense radius to 1e-10, 1.3 s
at M = 1024; one value with 40 vectors was 4e-6 short, a tolerance of 1e-9 took 5 s). The start
vector is random (seeded): a symmetric one, on a chain that is its own mirror image, never sees
the antisymmetric modes."""

CERTIFICATE_STATE_NOISE = (STATE_NOISE, 1e-2, 1.0)
"""The state noise fractions whose default gains :func:`certify_detectable` tries, the filter leaning
more on its measurements each time (what stabilises a coupled estimator)."""


def set_scales(linear_set: LinearSet | None, dim: int) -> np.ndarray:
    """Half the width of a set along each coordinate, 1 where it is unbounded.

    Parameters
    ----------
    linear_set : LinearSet or None
        A box is read directly; another polytope through its bounding box (LPs, :func:`box_hull`);
        None is unbounded.
    dim : int
        The set's dimension.

    Returns
    -------
    ndarray, shape (dim,)
    """
    if linear_set is None:
        return np.ones(dim)
    if linear_set.is_box:
        lo, hi = linear_set.lower, linear_set.upper
    else:
        lo, hi = box_hull(np.asarray(linear_set.H, float), linear_set.lower, linear_set.upper)
    width = (hi - lo) / 2.0
    return np.where(np.isfinite(width) & (width > 0), width, 1.0)


def subsystem_scales(sub: Subsystem) -> tuple[np.ndarray, np.ndarray]:
    """The scales of a subsystem's states (n_i,) and inputs (m_i,), from its bounds (:func:`set_scales`).

    Parameters
    ----------
    sub : Subsystem
    """
    return set_scales(sub.state_set, sub.n), set_scales(sub.input_set, sub.m)


@dataclass(frozen=True, eq=False)
class NoiseWeights:
    """The noise covariances of one subsystem's filter, in the units of its quantities.

    Attributes
    ----------
    state : ndarray, shape (n_i, n_i)
        Process noise on the states, per step (positive semidefinite).
    disturbance : ndarray, shape (n_d,i, n_d,i)
        The disturbances' random walk, per step (positive definite: every disturbance moves).
    measurement : ndarray, shape (p_i, p_i)
        Measurement noise (positive definite).
    """

    state: np.ndarray
    disturbance: np.ndarray
    measurement: np.ndarray

    @classmethod
    def scaled(cls, part: LocalModel, state_scale: np.ndarray, input_scale: np.ndarray, state: float = STATE_NOISE,
               disturbance: float = DISTURBANCE_NOISE, measurement: float = MEASUREMENT_NOISE) -> "NoiseWeights":
        """Diagonal covariances whose standard deviations are fractions of the quantities' scales.

        Parameters
        ----------
        part : LocalModel
            The subsystem's model (its C and disturbance kind).
        state_scale : ndarray, shape (n_i,)
        input_scale : ndarray, shape (m_i,)
            The scales of its states and inputs (:func:`subsystem_scales`).
        state, disturbance, measurement : float
            The fractions (the module's text gives the defaults and why).
        """
        output_scale = np.abs(part.C) @ state_scale
        output_scale = np.where(output_scale > 0, output_scale, 1.0)
        d_scale = output_scale if part.kind == "output" else input_scale
        return cls(np.diag((state * state_scale) ** 2), np.diag((disturbance * d_scale) ** 2),
                   np.diag((measurement * output_scale) ** 2))

    def covariance(self) -> np.ndarray:
        """W = diag(state, disturbance), shape (n_i + n_d,i, n_i + n_d,i)."""
        n, nd = self.state.shape[0], self.disturbance.shape[0]
        W = np.zeros((n + nd, n + nd))
        W[:n, :n] = self.state
        W[n:, n:] = self.disturbance
        return W


def default_noise(sub: Subsystem, part: LocalModel) -> NoiseWeights:
    """The default noise weights of one subsystem (:meth:`NoiseWeights.scaled` with the module's fractions).

    Parameters
    ----------
    sub : Subsystem
        Its bounds give the scales.
    part : LocalModel
        Its model of measurements and disturbances.
    """
    x_scale, u_scale = subsystem_scales(sub)
    return NoiseWeights.scaled(part, x_scale, u_scale)


def _check_noise(part: LocalModel, noise: NoiseWeights) -> None:
    """Shapes and definiteness of one subsystem's weights; DesignError otherwise."""
    where = f"estimation: subsystem {part.name}: noise"
    for label, matrix, size, definite in (("state", noise.state, part.n, False),
                                          ("disturbance", noise.disturbance, part.nd, True),
                                          ("measurement", noise.measurement, part.p, True)):
        if matrix.shape != (size, size):
            raise DesignError(f"{where}: the {label} covariance must be {size} x {size}, got {matrix.shape}")
        if not np.isfinite(matrix).all() or not np.allclose(matrix, matrix.T, rtol=1e-9, atol=0.0):
            raise DesignError(f"{where}: the {label} covariance must be finite and symmetric")
        if size:
            smallest = float(np.linalg.eigvalsh(matrix).min())
            if smallest < 0 or (definite and smallest <= 0):
                need = "positive definite" if definite else "positive semidefinite"
                raise DesignError(f"{where}: the {label} covariance must be {need} (smallest eigenvalue "
                                  f"{smallest:.3g})")


def kalman_gain(A: np.ndarray, C: np.ndarray, W: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The steady-state Kalman filter of x+ = A x + w, y = C x + v (cov w = W, cov v = V).

    Parameters
    ----------
    A : ndarray, shape (n, n)
    C : ndarray, shape (p, n)
    W : ndarray, shape (n, n)
    V : ndarray, shape (p, p)

    Returns
    -------
    L : ndarray, shape (n, p)
        The filter-form gain P C' (C P C' + V)^-1: x^ = x^- + L (y - C x^-).
    P : ndarray, shape (n, n)
        The prior covariance, the stabilising solution of the dual Riccati equation (the module's text).

    Raises
    ------
    ValueError, numpy.linalg.LinAlgError
        When the Riccati equation has no stabilising solution (scipy's message).
    """
    import scipy.linalg as sla  # design time only: agents running the observer do not load it

    if C.shape[0] == 0:  # nothing measured: the filter only predicts (A must be stable)
        P = sla.solve_discrete_lyapunov(A, W)
        return np.zeros((A.shape[0], 0)), (P + P.T) / 2.0
    P = sla.solve_discrete_are(A.T, C.T, W, V)
    P = (P + P.T) / 2.0
    L = np.linalg.solve(C @ P @ C.T + V, C @ P).T
    return L, P


def spectral_radius(matrix: np.ndarray) -> float:
    """The largest |eigenvalue| of a square matrix (0 for an empty one).

    Parameters
    ----------
    matrix : ndarray, shape (k, k)
    """
    return float(np.abs(np.linalg.eigvals(matrix)).max(initial=0.0)) if matrix.size else 0.0


def sparse_spectral_radius(matrix: sp.spmatrix) -> float:
    """The largest |eigenvalue| of a large sparse square matrix, by ARPACK (the dense
    :func:`spectral_radius` where ARPACK does not converge or the matrix is too small for it).

    Parameters
    ----------
    matrix : scipy.sparse matrix, shape (k, k)
    """
    import scipy.sparse.linalg as spla  # design time only

    size = matrix.shape[0]
    if size < ARPACK_VECTORS + 2:
        return spectral_radius(sp.csr_matrix(matrix).toarray())
    try:  # several eigenvalues, not one: in a cluster (identical subsystems) the first found is not always the largest
        values = spla.eigs(sp.csr_matrix(matrix, dtype=float), k=ARPACK_VALUES, which="LM", return_eigenvectors=False,
                           ncv=min(size - 1, ARPACK_VECTORS), maxiter=max(1000, size), tol=ARPACK_TOLERANCE,
                           v0=np.random.default_rng(0).standard_normal(size))  # a start of no symmetry
    except (spla.ArpackNoConvergence, spla.ArpackError):
        return spectral_radius(sp.csr_matrix(matrix).toarray())
    return float(np.abs(values).max(initial=0.0))


def _block_diagonal(blocks: Sequence[np.ndarray]) -> sp.csr_matrix:
    """The sparse block-diagonal stack of ``blocks`` (empty blocks included: their rows or columns
    are kept)."""
    rows, cols, values = [], [], []
    r = c = 0
    for block in blocks:
        i, j = np.nonzero(block)
        rows.append(i + r)
        cols.append(j + c)
        values.append(block[i, j])
        r += block.shape[0]
        c += block.shape[1]
    return sp.csr_matrix((np.concatenate(values) if values else np.zeros(0),
                          (np.concatenate(rows) if rows else np.zeros(0, int),
                           np.concatenate(cols) if cols else np.zeros(0, int))), shape=(r, c))


def error_operator(model: AugmentedSystem, gains: Sequence[LocalGain]) -> sp.csr_matrix:
    """The coupled estimator's error dynamics F = (I - L C_aug) A_aug as a sparse matrix, e+ = F e.

    Parameters
    ----------
    model : AugmentedSystem
        The coupled augmented model.
    gains : sequence of LocalGain
        One per subsystem, in order: L = diag(L_i) on the estimator's state [x; d].

    Returns
    -------
    scipy.sparse.csr_matrix, shape (n + n_d, n + n_d)
        The same matrix as :meth:`EstimatorDesign.error_dynamics`.
    """
    nd = model.nd
    A_aug = sp.bmat([[sp.csr_matrix(model.system.A), _block_diagonal([part.Bd for part in model.parts])],
                     [sp.csr_matrix((nd, model.n)), sp.eye(nd, format="csr")]], format="csr")
    C_aug = sp.hstack([_block_diagonal([part.C for part in model.parts]),
                       _block_diagonal([part.Cd for part in model.parts])], format="csr")
    L = sp.vstack([_block_diagonal([g.Lx for g in gains]), _block_diagonal([g.Ld for g in gains])], format="csr")
    F: sp.csr_matrix = sp.csr_matrix(A_aug - L @ (C_aug @ A_aug))
    F.eliminate_zeros()
    return F


@dataclass(frozen=True)
class Certificate:
    """What :func:`certify_schur` found.

    Attributes
    ----------
    certified : bool
        Some power's norm proves the spectral radius below the bound.
    power : int
        The power k that did (the last one tried otherwise).
    bound : float
        min over the powers tried of ||F^k||^(1/k) (inf- or 1-norm): an upper bound of the spectral radius.
    """

    certified: bool
    power: int
    bound: float


def certify_schur(F: sp.spmatrix, below: float, powers: int = CERTIFICATE_POWERS,
                  nonzeros: int = CERTIFICATE_NONZEROS) -> Certificate:
    """Prove rho(F) < ``below`` by a norm of a power of F: rho(F) <= ||F^k||^(1/k) for every k.

    Products and row or column sums of the sparse F only (they cost its nonzeros), no eigenvalue
    solve; their rounding (about 1e-16 of the norm per product) is far below the margin the bound
    leaves. A proof when it succeeds; when it does not, nothing is decided (the dense check is left
    to the caller).

    Parameters
    ----------
    F : scipy.sparse matrix, shape (k, k)
        The matrix.
    below : float
        The bound to prove (1 - ``STABILITY_MARGIN`` for an estimator).
    powers : int
        The most powers tried.
    nonzeros : int
        Stop once a power has more nonzeros than this.

    Returns
    -------
    Certificate
    """
    F = sp.csr_matrix(F, dtype=float)
    power = sp.csr_matrix(F, copy=True)
    best = np.inf
    for k in range(1, powers + 1):
        magnitude = abs(power)
        rows = np.asarray(magnitude.sum(axis=1)).ravel()
        cols = np.asarray(magnitude.sum(axis=0)).ravel()
        norm = min(float(rows.max(initial=0.0)), float(cols.max(initial=0.0)))
        value = norm ** (1.0 / k) if norm > 0 else 0.0
        best = min(best, value)
        if value < below:
            return Certificate(True, k, best)
        if k == powers or power.nnz > nonzeros:
            return Certificate(False, k, best)
        power = sp.csr_matrix(F @ power)
    return Certificate(False, powers, best)


@dataclass(frozen=True, eq=False)
class LocalGain:
    """One agent's filter.

    Attributes
    ----------
    name : str
        The subsystem's name.
    L : ndarray, shape (n_i + n_d,i, p_i)
        The filter-form gain on [x_i; d_i].
    P : ndarray, shape (n_i + n_d,i, n_i + n_d,i)
        The prior covariance (the Riccati solution).
    noise : NoiseWeights
    radius : float
        The spectral radius of the agent's own error dynamics (I - L C_aug,i) A_aug,i (couplings left out).
    """

    name: str
    L: np.ndarray
    P: np.ndarray
    noise: NoiseWeights
    radius: float

    @property
    def n(self) -> int:
        return int(self.noise.state.shape[0])

    @property
    def Lx(self) -> np.ndarray:
        """The state rows of L, shape (n_i, p_i)."""
        return self.L[: self.n]

    @property
    def Ld(self) -> np.ndarray:
        """The disturbance rows of L, shape (n_d,i, p_i)."""
        return self.L[self.n:]


@dataclass(frozen=True, eq=False)
class EstimatorDesign:
    """The estimator of the whole system: the model, the agents' gains and the checks' figures.

    Attributes
    ----------
    model : AugmentedSystem
    gains : tuple of LocalGain
        One per subsystem, in order.
    detectability : tuple of Detectability
        The figures of the checks (per subsystem, then the coupled system).
    """

    model: AugmentedSystem
    gains: tuple[LocalGain, ...]
    detectability: tuple[Detectability, ...] = ()

    @cached_property
    def Lx(self) -> np.ndarray:
        """The global state gain, block diagonal, shape (n, p)."""
        return self._stack(lambda g: g.Lx, self.model.n)

    @cached_property
    def Ld(self) -> np.ndarray:
        """The global disturbance gain, block diagonal, shape (n_d, p)."""
        return self._stack(lambda g: g.Ld, self.model.nd)

    def _stack(self, rows_of: Callable[[LocalGain], np.ndarray], total: int) -> np.ndarray:
        out = np.zeros((total, self.model.p))
        r = 0
        for i, g in enumerate(self.gains):
            block = rows_of(g)
            out[r:r + block.shape[0], self.model.ys(i)] = block
            r += block.shape[0]
        return out

    def gain(self) -> np.ndarray:
        """The global gain L = [L_x; L_d] on the estimator's state [x; d], shape (n + n_d, p)."""
        return np.vstack([self.Lx, self.Ld])

    def error_dynamics(self) -> np.ndarray:
        """(I - L C_aug) A_aug of the coupled augmented model, shape (n + n_d, n + n_d): e+ = it e."""
        A_aug, _, C_aug = self.model.augmented()
        L = self.gain()
        out: np.ndarray = A_aug - L @ (C_aug @ A_aug)
        return out

    def error_operator(self) -> sp.csr_matrix:
        """:meth:`error_dynamics` as a sparse matrix (:func:`error_operator`)."""
        return error_operator(self.model, self.gains)

    @property
    def dense(self) -> bool:
        """The augmented model has at most ``COUPLED_DENSE_LIMIT`` states: its checks are dense."""
        return self.model.n + self.model.nd <= COUPLED_DENSE_LIMIT

    @cached_property
    def radius(self) -> float:
        """The spectral radius of :meth:`error_dynamics`: below 1 for a stable estimator (above
        ``COUPLED_DENSE_LIMIT`` states, ARPACK's on the sparse matrix: the module's text)."""
        if self.dense:
            return spectral_radius(self.error_dynamics())
        return sparse_spectral_radius(self.error_operator())


def design_estimator(model: AugmentedSystem, noise: Sequence[NoiseWeights | None] | None = None) -> EstimatorDesign:
    """Check detectability, design every agent's gain and check the coupled estimator's stability.

    Parameters
    ----------
    model : AugmentedSystem
        From :func:`dmpc.estimation.model.augment`.
    noise : sequence of NoiseWeights or None, optional
        One per subsystem; None (the whole argument or an entry) takes :func:`default_noise`.

    Returns
    -------
    EstimatorDesign

    Raises
    ------
    DesignError
        Detectability fails (:func:`dmpc.estimation.model.check_detectable`), weights of the wrong
        shape or not definite, a Riccati equation without a stabilising solution, or the coupled
        error dynamics with spectral radius >= 1; each message says which subsystem, the figures
        and what to change. Above ``COUPLED_DENSE_LIMIT`` states the coupled conditions are
        decided after the gains (the module's text, "At scale"): the same messages, a weight's
        error first where both fail.
    """
    dense = model.n + model.nd <= COUPLED_DENSE_LIMIT
    local = tuple(check_subsystem(part) for part in model.parts)
    coupled = check_coupled(model) if dense else None  # above the limit: after the gains (the module's text)
    given = [None] * model.M if noise is None else list(noise)
    if len(given) != model.M:
        raise DesignError(f"estimation: {model.M} subsystems but {len(given)} noise weights")
    gains = local_gains(model, given)
    exact: float | None = None
    if coupled is None:
        if certify_schur(error_operator(model, gains), 1.0 - STABILITY_MARGIN).certified:
            # a stable coupled estimator proves the coupled detectability conditions
            coupled = Detectability("the coupled system", model.n, model.nd, model.p, model.n + model.nd)
        else:  # no certificate: the dense checks decide, as below the limit
            coupled = check_coupled(model)
            exact = spectral_radius(error_operator(model, gains).toarray())
    design = EstimatorDesign(model, gains, local + (coupled,))
    if exact is not None:
        design.__dict__["radius"] = exact  # the cached radius: the dense one just computed
    if not (design.dense or exact is not None) or design.radius < 1.0 - STABILITY_MARGIN:
        return design
    own = ", ".join(f"{g.name}: {g.radius:.4g}" for g in gains)
    raise DesignError(
        f"estimation: the coupled estimator is unstable: its error dynamics (I - L C) A over the whole "
        f"augmented system have spectral radius {design.radius:.6g} >= 1, though each agent's own filter is "
        f"stable (spectral radius {own}): the couplings A_ij, B_ij, which each agent's own model leaves out, "
        f"carry the neighbours' estimation errors into each prediction faster than the local gains remove them; "
        f"make the filters trust their measurements more than their models (raise estimation.noise.state, or "
        f"lower estimation.noise.measurement), or measure more outputs")


def local_gains(model: AugmentedSystem, noise: Sequence[NoiseWeights | None]) -> tuple[LocalGain, ...]:
    """Every agent's steady-state Kalman filter on its own augmented model (:func:`kalman_gain`).

    Subsystems with the same augmented model and weights (the copies of a family) share one
    Riccati solution: the same numbers, solved once.

    Parameters
    ----------
    model : AugmentedSystem
    noise : sequence of NoiseWeights or None
        One per subsystem; None takes :func:`default_noise`.

    Returns
    -------
    tuple of LocalGain
        One per subsystem, in order.

    Raises
    ------
    DesignError
        Weights of the wrong shape or not definite, or a Riccati equation without a stabilising solution.
    """
    solved: dict[bytes, tuple[np.ndarray, np.ndarray, float]] = {}
    gains = []
    for sub, part, weights in zip(model.system.subsystems, model.parts, noise):
        weights = weights if weights is not None else default_noise(sub, part)
        _check_noise(part, weights)
        A_aug, _, C_aug = part.augmented()
        W, V = weights.covariance(), weights.measurement
        key = b"|".join(repr(m.shape).encode() + np.ascontiguousarray(m, dtype=np.float64).tobytes()
                        for m in (A_aug, C_aug, W, V))
        if key not in solved:
            try:
                L, P = kalman_gain(A_aug, C_aug, W, V)
            except (ValueError, np.linalg.LinAlgError) as exc:
                raise DesignError(f"estimation: subsystem {part.name}: the filter's Riccati equation has no "
                                  f"stabilising solution ({exc}); check the noise weights") from None
            solved[key] = (L, P, spectral_radius(A_aug - L @ (C_aug @ A_aug)))
        L, P, radius = solved[key]
        gains.append(LocalGain(part.name, L.copy(), P.copy(), weights, radius))
    return tuple(gains)


def certify_detectable(model: AugmentedSystem) -> bool:
    """Whether some block-diagonal gain proves the coupled detectability conditions: the default
    filters (:func:`default_noise`, state noise raised through ``CERTIFICATE_STATE_NOISE``) whose
    coupled error dynamics :func:`certify_schur` proves stable (the module's text: a stable coupled
    estimator has no undetectable mode). False decides nothing.

    Parameters
    ----------
    model : AugmentedSystem
        Every subsystem passed :func:`~dmpc.estimation.model.check_subsystem`.
    """
    for state in CERTIFICATE_STATE_NOISE:
        weights = []
        for sub, part in zip(model.system.subsystems, model.parts):
            x_scale, u_scale = subsystem_scales(sub)
            weights.append(NoiseWeights.scaled(part, x_scale, u_scale, state=state))
        try:
            gains = local_gains(model, weights)
        except DesignError:
            continue
        if certify_schur(error_operator(model, gains), 1.0 - STABILITY_MARGIN).certified:
            return True
    return False


__all__ = ["CERTIFICATE_NONZEROS", "CERTIFICATE_POWERS", "Certificate", "DISTURBANCE_NOISE", "EstimatorDesign",
           "LocalGain", "MEASUREMENT_NOISE", "NoiseWeights", "STATE_NOISE", "certify_detectable", "certify_schur",
           "default_noise", "design_estimator", "error_operator", "kalman_gain", "local_gains", "set_scales",
           "sparse_spectral_radius", "spectral_radius", "subsystem_scales"]

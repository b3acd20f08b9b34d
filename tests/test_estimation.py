"""The pure estimation core (dmpc.estimation): disturbance models and their
detectability, the agents' Kalman gains and the coupled estimator's stability, the observer, and the
offset-free targets as an affine map of the estimate.

Everything the checks assert is recomputed here from the matrices (ranks, Riccati residuals, error
dynamics, an independent cvxpy/Clarabel solve of the target QP), not read from the module's figures.
"""
from __future__ import annotations

from pathlib import Path

import cvxpy as cp
import numpy as np
import pytest
import scipy.linalg as sla
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

import dmpc.scenario
from dmpc.core.errors import DesignError
from dmpc.core.system import CoupledSystem, Coupling, LinearSet, Subsystem, stack_sets
from dmpc.estimation.kalman import (
    DISTURBANCE_NOISE,
    MEASUREMENT_NOISE,
    STATE_NOISE,
    NoiseWeights,
    design_estimator,
    subsystem_scales,
)
from dmpc.estimation.model import augment, check_detectable, rank_condition, undetectable_modes
from dmpc.estimation.observer import Observer, local_update
from dmpc.estimation.targets import REGULARISATION, OffsetFreeTargets, gauge_rows
from dmpc.plant.fourtank import FourTank, FourTankPlant

ROOT = Path(__file__).resolve().parents[1]
FOURTANK = ROOT / "scenarios" / "fourtank.yaml"
LEVELS = [[[1.0, 0.0]], [[1.0, 0.0]]]
"""The four-tank's measurements: h1 of subsystem a (h1, h3) and h2 of b (h2, h4)."""


# ---------------------------------------------------------------------------- systems
def subsystem(name: str, A, B, bound: float = 10.0, u_bound: float = 10.0) -> Subsystem:
    A, B = np.atleast_2d(np.asarray(A, float)), np.atleast_2d(np.asarray(B, float))
    n, m = A.shape[0], B.shape[1]
    return Subsystem(name, A, B, np.eye(n), 0.1 * np.eye(m), np.zeros(n), LinearSet.box([-u_bound] * m, [u_bound] * m),
                     LinearSet.box([-bound] * n, [bound] * n))


def fourtank() -> CoupledSystem:
    return dmpc.scenario.build_system(dmpc.scenario.load_scenario(FOURTANK))


def random_system(rng: np.random.Generator, M: int, n: int = 2, m: int = 1, factor: float = 1.0) -> CoupledSystem:
    """M subsystems (n states, m inputs), spectral radius of each A_ii in [0.5, 1.1], every B_ij (i != j)
    of norm ``factor`` ||B_jj||, small state couplings; boxes of 10 on states and inputs."""
    subs = []
    for i in range(M):
        A = rng.normal(size=(n, n))
        A *= rng.uniform(0.5, 1.1) / max(np.abs(np.linalg.eigvals(A)).max(), 1e-3)
        subs.append(subsystem(f"s{i}", A, rng.normal(size=(n, m))))
    couplings = []
    for i in range(M):
        for j in range(M):
            if i != j:
                B = rng.normal(size=(n, m))
                B *= factor * np.linalg.norm(subs[j].B) / np.linalg.norm(B)
                couplings.append(Coupling(i, j, rng.uniform(-0.1, 0.1, (n, n)), B))
    return CoupledSystem(tuple(subs), tuple(couplings))


def lqr(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """K with u = K x (A + B K stable)."""
    P = sla.solve_discrete_are(A, B, Q, R)
    return -np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)


# ---------------------------------------------------------------------------- detectability
def integrating_pair(kind: str):
    """Subsystem a is stable and fully measured; b = (integrator, stable mode), both states measured."""
    a = subsystem("a", [[0.8, 0.1], [0.0, 0.7]], [[1.0], [0.5]])
    b = subsystem("b", [[1.0, 1.0], [0.0, 0.5]], [[0.0], [1.0]])
    system = CoupledSystem((a, b), (Coupling(1, 0, 0.05 * np.ones((2, 2)), np.zeros((2, 1))),))
    return system, augment(system, None, kind)


def test_an_integrating_mode_fails_with_output_disturbances_and_passes_with_input_ones():
    system, output = integrating_pair("output")
    b = output.parts[1]
    # the condition, computed here: rank [[I - A, -B_d], [C, C_d]] with B_d = 0, C_d = I
    M = np.block([[np.eye(2) - b.A, np.zeros((2, 2))], [np.eye(2), np.eye(2)]])
    assert np.linalg.matrix_rank(M) == 3 < 4 == b.n + b.nd
    assert rank_condition(b.A, b.Bd, b.C, b.Cd) == (3, 4)
    with pytest.raises(DesignError) as caught:
        check_detectable(output)
    message = str(caught.value)
    for words in ("subsystem b", "2 output disturbance(s)", "rank is 3 < 4", "eigenvalue 1 of A_bb",
                  "use estimation.disturbance: input"):
        assert words in message, message
    with pytest.raises(DesignError, match="subsystem b"):
        design_estimator(output)

    _, inputs = integrating_pair("input")
    b = inputs.parts[1]
    M = np.block([[np.eye(2) - b.A, -b.B], [np.eye(2), np.zeros((2, 1))]])
    assert np.linalg.matrix_rank(M) == 3 == b.n + b.nd
    figures = check_detectable(inputs)
    assert [f.rank for f in figures] == [3, 3, 6] and figures[-1].where == "the coupled system"
    design = design_estimator(inputs)
    assert design.radius < 1


def test_more_input_disturbances_than_outputs_and_an_unseen_unstable_mode_are_refused():
    two_inputs = subsystem("c", [[0.5, 0.1], [0.0, 0.6]], np.eye(2))
    system = CoupledSystem((two_inputs,))
    with pytest.raises(DesignError, match=r"subsystem c: 2 input disturbance\(s\) but only 1 measured output"):
        check_detectable(augment(system, [[[1.0, 0.0]]], "input"))
    unstable = subsystem("u", [[1.2, 0.0], [0.0, 0.5]], [[1.0], [1.0]])
    values, _ = undetectable_modes(unstable.A, np.array([[0.0, 1.0]]))
    assert np.allclose(values, [1.2])
    with pytest.raises(DesignError, match=r"subsystem u: \(A, C\) is not detectable.*1\.2"):
        check_detectable(augment(CoupledSystem((unstable,)), [[[0.0, 1.0]]]))
    # the same mode seen by the output: detectable
    assert undetectable_modes(unstable.A, np.array([[1.0, 1.0]]))[0].size == 0


def test_a_coupled_integrating_mode_is_found_though_each_subsystem_passes():
    """A_aa = A_bb = 0.5 but the coupled A = [[0.5, 0.5], [0.5, 0.5]] has an eigenvalue 1."""
    a, b = subsystem("a", [[0.5]], [[1.0]]), subsystem("b", [[0.5]], [[1.0]])
    system = CoupledSystem((a, b), (Coupling(0, 1, np.array([[0.5]]), np.zeros((1, 1))),
                                    Coupling(1, 0, np.array([[0.5]]), np.zeros((1, 1)))))
    model = augment(system)
    M = np.block([[np.eye(2) - system.A, np.zeros((2, 2))], [np.eye(2), np.eye(2)]])
    assert np.linalg.matrix_rank(M) == 3
    with pytest.raises(DesignError) as caught:
        check_detectable(model)
    message = str(caught.value)
    assert "the coupled system" in message and "rank is 3 < 4" in message and "subsystem(s) a, b" in message
    assert "every subsystem passes on its own" in message
    assert design_estimator(augment(system, None, "input")).radius < 1


# ---------------------------------------------------------------------------- gains
def test_the_fourtank_gains_solve_the_riccati_equation_and_the_coupled_estimator_is_stable():
    system = fourtank()
    model = augment(system, LEVELS)
    assert (model.p, model.nd) == (2, 2) and np.array_equal(model.C, [[1, 0, 0, 0], [0, 0, 1, 0]])
    design = design_estimator(model)
    for sub, part, gain in zip(system.subsystems, model.parts, design.gains):
        A, _, C = part.augmented()
        W, V, P = gain.noise.covariance(), gain.noise.measurement, gain.P
        residual = A @ P @ A.T - A @ P @ C.T @ np.linalg.solve(C @ P @ C.T + V, C @ P @ A.T) + W - P
        assert np.abs(residual).max() <= 1e-10 * np.abs(P).max()
        assert np.allclose(gain.L, P @ C.T @ np.linalg.inv(C @ P @ C.T + V))
        # the default weights: fractions of the bounds' half widths
        x_scale, _ = subsystem_scales(sub)
        assert np.allclose(x_scale, (sub.state_set.upper - sub.state_set.lower) / 2)
        assert np.allclose(np.diag(gain.noise.state), (STATE_NOISE * x_scale) ** 2)
        assert np.allclose(np.diag(gain.noise.measurement), (MEASUREMENT_NOISE * x_scale[0]) ** 2)
        assert np.allclose(np.diag(gain.noise.disturbance), (DISTURBANCE_NOISE * x_scale[0]) ** 2)
    # the coupled error dynamics, built here: A_aug with the coupled A, the block-diagonal gain
    n, nd = 4, 2
    A_aug = np.block([[system.A, np.zeros((n, nd))], [np.zeros((nd, n)), np.eye(nd)]])
    C_aug = np.hstack([model.C, np.eye(2)])
    L = np.zeros((n + nd, 2))
    L[0:2, 0], L[2:4, 1] = design.gains[0].Lx[:, 0], design.gains[1].Lx[:, 0]
    L[4, 0], L[5, 1] = design.gains[0].Ld[0, 0], design.gains[1].Ld[0, 0]
    error = (np.eye(n + nd) - L @ C_aug) @ A_aug
    assert np.allclose(error, design.error_dynamics())
    radius = float(np.abs(np.linalg.eigvals(error)).max())
    assert radius == pytest.approx(design.radius) and radius < 1
    assert 0.97 < radius < 0.99  # the slowest tank (0.980 per 5 s): the output disturbance model leaves it open loop


def test_a_coupling_the_local_filters_do_not_see_makes_the_coupled_estimator_unstable():
    a, b = subsystem("a", [[0.5]], [[1.0]]), subsystem("b", [[0.5]], [[1.0]])
    system = CoupledSystem((a, b), (Coupling(0, 1, np.array([[2.0]]), np.zeros((1, 1))),
                                    Coupling(1, 0, np.array([[-2.0]]), np.zeros((1, 1)))))
    model = augment(system)
    slow = [NoiseWeights(np.eye(1) * 1e-6, np.eye(1) * 1e-6, np.eye(1)) for _ in range(2)]
    with pytest.raises(DesignError) as caught:
        design_estimator(model, slow)
    message = str(caught.value)
    assert "the coupled estimator is unstable" in message and "spectral radius" in message
    assert "raise estimation.noise.state, or lower estimation.noise.measurement" in message
    assert "measure more outputs" in message
    # what the message advises: a filter that leans on its measurements makes the coupled estimator stable
    fast = [NoiseWeights(np.eye(1) * 1e-2, np.eye(1) * 1e-4, np.eye(1) * 1e-4) for _ in range(2)]
    assert design_estimator(model, fast).radius < 1
    with pytest.raises(DesignError, match="measurement covariance must be positive definite"):
        design_estimator(model, [NoiseWeights(np.eye(1), np.eye(1), np.zeros((1, 1)))] * 2)


# ---------------------------------------------------------------------------- the observer
@pytest.mark.parametrize("kind", ["output", "input"])
def test_the_observer_converges_on_a_linear_plant_with_a_constant_disturbance(kind):
    """The plant is the model with a constant disturbance of the model's kind; h3 and h4 are not measured."""
    system = fourtank()
    model = augment(system, LEVELS, kind)
    design = design_estimator(model)
    observer = Observer(design)
    rng = np.random.default_rng(1)
    d = np.array([0.02, -0.03]) if kind == "output" else np.array([0.3, -0.2])
    x = rng.uniform(-0.05, 0.05, 4)
    u = np.array([0.2, -0.1])
    first = None
    for k in range(1500):
        y = model.outputs(x, d)
        x_hat, d_hat = observer.update(None if k == 0 else u, y)
        error = np.linalg.norm(np.concatenate([x - x_hat, d - d_hat]))
        first = error if first is None else first
        x = system.A @ x + system.B @ u + model.Bd @ d
    assert error <= 1e-7 * first, (first, error)
    assert observer.innovation_norm <= 1e-9 and observer.steps == 1500
    assert np.allclose(observer.state(1), x_hat[2:]) and np.allclose(observer.disturbance(0), d_hat[:1])


def test_the_observer_explains_the_outputs_of_a_disturbance_outside_its_model():
    """A constant input disturbance on a plant estimated with output disturbances: the estimate is not
    the plant's state, but the outputs it explains converge to the measurements."""
    system = fourtank()
    model = augment(system, LEVELS)
    observer = Observer(design_estimator(model))
    x, u, w = np.zeros(4), np.array([0.3, 0.1]), np.array([0.2, -0.4])
    for k in range(1500):
        y = model.C @ x
        observer.update(None if k == 0 else u, y)
        x = system.A @ x + system.B @ (u + w)
    assert np.abs(observer.output_estimate() - y).max() <= 1e-9
    assert observer.innovation_norm <= 1e-9


def test_an_agents_share_of_the_step_is_the_observers():
    rng = np.random.default_rng(3)
    system = random_system(rng, 3)
    model = augment(system, [rng.normal(size=(1, 2)), None, rng.normal(size=(2, 2))])
    design = design_estimator(model)
    observer = Observer(design, x0=rng.normal(size=model.n), d0=rng.normal(size=model.nd))
    x_prev, d_prev = observer.x_hat, observer.d_hat
    u, y = rng.normal(size=model.m), rng.normal(size=model.p)
    x_hat, d_hat = observer.update(u, y)
    for i in range(3):
        x_i, d_i, e_i = local_update(design, i, x_prev, d_prev, u, y[model.ys(i)])
        assert np.allclose(x_i, x_hat[system.xs(i)], atol=1e-13) and np.allclose(d_i, d_hat[model.ds(i)], atol=1e-13)
        assert np.allclose(e_i, observer.innovation[model.ys(i)], atol=1e-13)
        assert np.linalg.norm(e_i) == pytest.approx(observer.innovation_norms()[i])
    with pytest.raises(ValueError, match="y needs"):
        observer.update(u, y[:-1])


# ---------------------------------------------------------------------------- targets
def cvxpy_target(model, request, d_hat, gauge_limit=None):
    """The target QP solved by cvxpy with Clarabel, from the matrices (with gauge <= ``gauge_limit`` in X
    and U, by the setpoint targets' gauge rows, when given)."""
    system = model.system
    n, m = model.n, model.m
    D = sla.block_diag(system.Q, system.R)
    D = D + REGULARISATION * max(1.0, np.abs(np.diag(D)).max()) * np.eye(n + m)
    x, u = cp.Variable(n), cp.Variable(m)
    pinned = ~np.isnan(request)
    constraints = [(np.eye(n) - system.A) @ x - system.B @ u == model.Bd @ d_hat]
    if pinned.any():
        constraints.append(model.C[pinned] @ x + model.Cd[pinned] @ d_hat == request[pinned])
    if gauge_limit is not None:
        subs = system.subsystems
        X = stack_sets([s.state_set for s in subs], [s.n for s in subs])
        U = stack_sets([s.input_set for s in subs], [s.m for s in subs])
        constraints += [gauge_rows(X, n).toarray() @ x <= gauge_limit,
                        gauge_rows(U, m).toarray() @ u <= gauge_limit]
    problem = cp.Problem(cp.Minimize(cp.quad_form(cp.hstack([x, u]), cp.psd_wrap(D))), constraints)
    problem.solve(solver=cp.CLARABEL)
    if problem.status not in ("optimal", "optimal_inaccurate"):
        return None
    return x.value, u.value


@pytest.mark.parametrize("seed", range(6))
def test_the_affine_target_is_the_qps_solution(seed):
    rng = np.random.default_rng(100 + seed)
    M = 2 + seed % 2
    system = random_system(rng, M, n=3, m=2, factor=rng.uniform(0.5, 1.5))
    C = [rng.normal(size=(int(rng.integers(1, 4)), 3)) for _ in range(M)]
    model = augment(system, C, "output") if seed % 3 else augment(system, None, "input")  # input: every state measured
    targets = OffsetFreeTargets(model)
    q = int(rng.integers(0, min(model.m, model.p) + 1))
    request = np.full(model.p, np.nan)
    request[rng.choice(model.p, q, replace=False)] = rng.normal(size=q)
    d_hat = rng.normal(size=model.nd)
    target = targets.target(request, d_hat)
    x_ref, u_ref = cvxpy_target(model, request, d_hat)
    scale = 1.0 + np.abs(np.concatenate([x_ref, u_ref])).max()
    assert np.abs(target.x - x_ref).max() <= 1e-6 * scale and np.abs(target.u - u_ref).max() <= 1e-6 * scale
    # a steady state of the model with the estimate, meeting the request exactly
    assert np.abs(target.x - system.A @ target.x - system.B @ target.u - model.Bd @ d_hat).max() <= 1e-12 * scale
    pinned = ~np.isnan(request)
    assert np.allclose(model.outputs(target.x, d_hat)[pinned], request[pinned], atol=1e-12 * scale)
    # affine in (r, d^): the map's matrices give the same target
    Gr, Gd = targets.pattern(pinned).affine()
    assert np.allclose(Gr @ request[pinned] + Gd @ d_hat, np.concatenate([target.x, target.u]), atol=1e-12 * scale)
    assert targets.pattern(pinned) is targets.pattern(pinned.copy())  # factored once per pattern


def test_the_bound_check_and_the_bounded_fallback():
    rng = np.random.default_rng(7)
    system = random_system(rng, 2, n=3, m=2)
    model = augment(system, [np.eye(3)[:1], np.eye(3)[:2]])
    request = np.array([0.5, np.nan, 0.4])
    d_hat = rng.normal(size=model.nd) * 0.1
    free = OffsetFreeTargets(model).target(request, d_hat)
    assert free.inside
    # tighten the bound of the largest free state below the affine target's value
    states = [1, 2, 3, 5]  # not measured, or measured but not pinned (y0 of s1: state 3)
    j = states[int(np.argmax(np.abs(free.x[states])))]
    subs = list(system.subsystems)
    i, k = divmod(j, 3)
    bound = 0.7 * abs(free.x[j]) / (1 - 0.05)
    upper = np.full(3, 10.0)
    upper[k] = bound
    subs[i] = Subsystem(subs[i].name, subs[i].A, subs[i].B, subs[i].Q, subs[i].R, subs[i].x0, subs[i].input_set,
                        LinearSet.box(-upper, upper))
    tight = augment(CoupledSystem(tuple(subs), system.couplings), [np.eye(3)[:1], np.eye(3)[:2]])
    targets = OffsetFreeTargets(tight)
    affine = targets.target(request, d_hat)
    assert np.allclose(affine.x, free.x) and not affine.inside and affine.gauge > 1 - targets.margin
    bounded = targets.bounded(request, d_hat)
    reference = cvxpy_target(tight, request, d_hat, 1 - targets.margin)
    assert reference is not None  # this seed's tightened bound leaves a steady state that meets the request
    if True:
        assert bounded is not None and bounded.gauge <= 1 - targets.margin + 1e-8
        assert np.abs(bounded.x - reference[0]).max() <= 1e-6 and np.abs(bounded.u - reference[1]).max() <= 1e-6
        pinned = ~np.isnan(request)
        assert np.allclose(tight.outputs(bounded.x, d_hat)[pinned], request[pinned], atol=1e-8)
    # a request beyond a bound: the affine target leaves it and no bounded one exists
    model4 = augment(fourtank(), LEVELS)
    targets4 = OffsetFreeTargets(model4)
    beyond = targets4.target([0.7, 0.0], np.zeros(2))
    assert not beyond.inside and targets4.bounded([0.7, 0.0], np.zeros(2)) is None
    assert targets4.target([0.15, 0.15], np.zeros(2)).inside


def test_a_pattern_that_cannot_be_met_is_a_design_error():
    model = augment(fourtank())  # every level measured: 4 outputs, 2 inputs
    targets = OffsetFreeTargets(model)
    with pytest.raises(DesignError, match=r"3 outputs pinned \(y0 of a, y1 of a, y0 of b\) but the system has 2"):
        targets.target([0.1, 0.1, 0.1, np.nan], np.zeros(4))
    # an integrating mode the inputs cannot reach: no steady state for every estimate
    lost = subsystem("z", [[1.0, 0.0], [0.0, 0.5]], [[0.0], [1.0]])
    with pytest.raises(DesignError, match=r"rank \[I - A, -B\] = 1 < n = 2"):
        OffsetFreeTargets(augment(CoupledSystem((lost,)), None, "input")).target([np.nan, np.nan], np.zeros(1))


def test_the_gauge_rows_give_the_sets_gauge():
    """max(0, max_p a_p v) is the Minkowski gauge of the set: v / gauge lies on its boundary."""
    rng = np.random.default_rng(5)
    for _ in range(5):
        H = rng.normal(size=(4, 3))
        lower = np.where(rng.random(4) < 0.3, -np.inf, -rng.uniform(0.5, 2, 4))
        upper = np.where(rng.random(4) < 0.3, np.inf, rng.uniform(0.5, 2, 4))
        rows = gauge_rows(LinearSet(H, lower, upper), 3).toarray()
        for v in rng.normal(size=(10, 3)):
            gauge = max(0.0, float((rows @ v).max()))
            if gauge == 0.0:  # every multiple of v is in the set: no finite bound in its way
                hv = H @ v
                assert np.all(hv[np.isfinite(upper)] <= 1e-12) and np.all(hv[np.isfinite(lower)] >= -1e-12)
                continue
            w = H @ (v / gauge)
            assert np.all(w <= upper + 1e-9) and np.all(w >= lower - 1e-9)
            assert np.any(np.isclose(w, upper)) or np.any(np.isclose(w, lower))


# ---------------------------------------------------------------------------- closed loop
def run_loop(system, model, plant, request, steps, x0, saturate=True, estimate=True):
    """Unconstrained offset-free loop: targets from the estimate, u = u_s + K (x^ - x_s), inputs clipped to U.

    With ``estimate=False`` the controller reads the plant's state and the targets assume no
    disturbance (today's behaviour): the offset of the model's mismatch stays."""
    design = design_estimator(model)
    targets = OffsetFreeTargets(model)
    K = lqr(system.A, system.B, system.Q, system.R)
    lower = np.concatenate([s.input_set.lower for s in system.subsystems])
    upper = np.concatenate([s.input_set.upper for s in system.subsystems])
    observer = Observer(design, x0=np.zeros(model.n))
    x, u = np.asarray(x0, float), None
    for k in range(steps):
        y = model.C @ x if plant.measure is None else plant.measure(x)
        if estimate:
            x_hat, d_hat = observer.update(u, y)
        else:
            x_hat, d_hat = x, np.zeros(model.nd)
        target = targets.target(request, d_hat)
        u = target.u + K @ (x_hat - target.x)
        if saturate:
            u = np.clip(u, lower, upper)
        x = plant.step(x, u, k)
    return x, y, observer


class LinearPlant:
    def __init__(self, system, C, w_u, w_x, v):
        self.system, self.C, self.w_u, self.w_x, self.v = system, C, w_u, w_x, v

    def measure(self, x):
        return self.C @ x + self.v

    def step(self, x, u, k):
        return self.system.A @ x + self.system.B @ (u + self.w_u) + self.w_x


class NonlinearTanks:
    measure = None

    def __init__(self):
        self.plant = FourTankPlant(FourTank(), np.array([1.63, 2.00]), 5.0, (0, 2, 1, 3), (0, 1))

    def step(self, x, u, k):
        return self.plant(x, u, k)


def test_the_nonlinear_fourtank_levels_settle_on_their_setpoints_without_offset():
    """The linear model controls the nonlinear tanks, h1 and h2 measured only, +0.15 m on both: with
    the estimate the offset is below 1e-4 of the step; without it, millimetres."""
    system = fourtank()
    model = augment(system, LEVELS)
    request = np.array([0.15, 0.15])
    x, y, observer = run_loop(system, model, NonlinearTanks(), request, 1500, np.zeros(4))
    assert np.abs(y - request).max() <= 1e-4 * 0.15, y - request
    assert observer.innovation_norm <= 1e-8
    x, y, _ = run_loop(system, model, NonlinearTanks(), request, 1500, np.zeros(4), estimate=False)
    assert np.abs(y - request).max() > 5e-4  # today's offset: the model's steady state is not the tanks'


def test_a_linear_plant_with_input_and_output_disturbances_tracks_without_offset():
    system = fourtank()
    model = augment(system, LEVELS, "input")
    plant = LinearPlant(system, model.C, w_u=np.array([0.3, -0.2]), w_x=np.zeros(4), v=np.array([0.01, -0.02]))
    request = np.array([0.1, -0.05])
    x, y, observer = run_loop(system, model, plant, request, 2000, np.zeros(4))
    assert np.abs(y - request).max() <= 1e-9


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(seed=st.integers(0, 2**32 - 1), M=st.sampled_from([2, 3]), kind=st.sampled_from(["output", "input"]),
       factor=st.floats(0.5, 1.5))
def test_random_coupled_systems_with_constant_disturbances_track_without_offset(seed, M, kind, factor):
    """Random coupled systems (B_ij as large as B_jj), constant disturbances on the inputs, the states
    and the outputs; the disturbance model passes the detectability checks; the unconstrained loop
    (targets from the estimate, a global LQR around them) converges with zero offset in the tracked outputs."""
    rng = np.random.default_rng(seed)
    n, m = 2, 1
    system = random_system(rng, M, n=n, m=m, factor=factor)
    p = [int(rng.integers(1, n + 1)) if kind == "output" else m for _ in range(M)]
    C = [rng.normal(size=(pi, n)) for pi in p]
    model = augment(system, C, kind)
    try:
        design = design_estimator(model)
    except DesignError:
        assume(False)
    assert model.nd == model.p and np.linalg.matrix_rank(design.Ld) == model.nd  # the zero-offset argument's premise
    q = min(model.m, model.p)
    pinned = np.zeros(model.p, dtype=bool)
    pinned[rng.choice(model.p, q, replace=False)] = True
    targets = OffsetFreeTargets(model)
    try:
        targets.pattern(pinned)
    except DesignError:
        assume(False)
    K = lqr(system.A, system.B, system.Q, system.R)
    radius = max(float(np.abs(np.linalg.eigvals(system.A + system.B @ K)).max()), design.radius)
    assume(radius < 0.99)
    steps = int(np.ceil(np.log(1e-12) / np.log(radius))) + 20
    request = np.where(pinned, rng.uniform(-1, 1, model.p), np.nan)
    plant = LinearPlant(system, model.C, w_u=rng.uniform(-0.5, 0.5, model.m), w_x=rng.uniform(-0.1, 0.1, model.n),
                        v=rng.uniform(-0.1, 0.1, model.p))
    x, y, observer = run_loop(system, model, plant, request, steps, rng.uniform(-1, 1, model.n), saturate=False)
    assert np.abs(y[pinned] - request[pinned]).max() <= 1e-7, (y[pinned] - request[pinned])
    assert observer.innovation_norm <= 1e-7

"""The estimator's design at scale (dmpc.estimation.kalman, "At scale"): above COUPLED_DENSE_LIMIT
states the coupled checks are a certificate on the sparse error dynamics, with the dense checks
kept where it fails. Here the limit is lowered so that small systems take that path, and every
figure and message is compared with the dense path's on the same system.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import dmpc.estimation.kalman as kalman
import dmpc.estimation.model as model_module
from dmpc.core.errors import DesignError
from dmpc.core.system import CoupledSystem, Coupling, LinearSet, Subsystem
from dmpc.estimation.kalman import (
    STABILITY_MARGIN,
    NoiseWeights,
    certify_schur,
    design_estimator,
    error_operator,
    kalman_gain,
    spectral_radius,
)
from dmpc.estimation.model import augment, check_detectable
from dmpc.scenario import build_system, load_scenario
from dmpc.setup.estimation import estimation_model, noise_weights

ROOT = Path(__file__).resolve().parents[1]


def chain(M: int):
    """The chain family (scenarios/chain.yaml) with x1 of every subsystem measured, input
    disturbances and state noise 1e-2: the scenario of benchmarks/estimation_cost.py."""
    scenario = load_scenario(ROOT / "scenarios" / "chain.yaml",
                             {"family.M": M, "family.subsystem.C": [[1.0, 0.0]],
                              "estimation": {"disturbance": "input", "noise": {"state": 1e-2}}})
    model = estimation_model(scenario, build_system(scenario))
    assert model is not None and scenario.estimation is not None
    return model, noise_weights(scenario.estimation.noise, model)


def subsystem(name: str, a: float) -> Subsystem:
    return Subsystem(name, np.array([[a]]), np.array([[1.0]]), np.eye(1), 0.1 * np.eye(1), np.zeros(1),
                     LinearSet.box([-10.0], [10.0]), LinearSet.box([-10.0], [10.0]))


def pair(coupling: float) -> CoupledSystem:
    """Two scalar subsystems a_ii = 0.5, coupled both ways by +-``coupling``."""
    return CoupledSystem((subsystem("a", 0.5), subsystem("b", 0.5)),
                         (Coupling(0, 1, np.array([[coupling]]), np.zeros((1, 1))),
                          Coupling(1, 0, np.array([[-coupling]]), np.zeros((1, 1)))))


def sparse_path(monkeypatch) -> None:
    """Every system above the limit from now on."""
    monkeypatch.setattr(model_module, "COUPLED_DENSE_LIMIT", 0)
    monkeypatch.setattr(kalman, "COUPLED_DENSE_LIMIT", 0)


def message(call) -> str:
    with pytest.raises(DesignError) as caught:
        call()
    return str(caught.value)


@pytest.mark.parametrize("seed", range(6))
def test_the_certificate_never_proves_a_radius_it_does_not_bound(seed):
    rng = np.random.default_rng(seed)
    F = rng.normal(size=(40, 40)) * (rng.random((40, 40)) < 0.2)
    radius = spectral_radius(F)
    for target in (0.5, 0.9, 0.999, 1.0, 1.01):
        scaled = F * (target / radius)
        found = certify_schur(scaled, 1.0 - STABILITY_MARGIN)
        assert found.bound >= target * (1 - 1e-12)  # every power's norm bounds the radius
        assert found.certified == (found.bound < 1.0 - STABILITY_MARGIN)
        if target >= 1.0:
            assert not found.certified
    assert certify_schur(0.5 * F / radius, 1.0 - STABILITY_MARGIN).certified or radius == 0


def test_above_the_limit_the_chain_has_the_dense_gains_radius_and_ranks(monkeypatch):
    model, noise = chain(30)  # 90 states [x; d]: ARPACK's radius
    dense = design_estimator(model, noise)
    assert dense.dense and dense.radius < 1  # computed (and kept) below the limit
    sparse_path(monkeypatch)
    sparse = design_estimator(model, noise)
    assert not sparse.dense
    for a, b in zip(dense.gains, sparse.gains):
        assert np.array_equal(a.L, b.L) and np.array_equal(a.P, b.P) and a.radius == b.radius
    assert [(d.where, d.rank) for d in dense.detectability] == [(d.where, d.rank) for d in sparse.detectability]
    assert sparse.detectability[-1].rank == model.n + model.nd
    assert sparse.radius == pytest.approx(dense.radius, abs=1e-9) and sparse.radius < 1
    assert np.allclose(error_operator(model, sparse.gains).toarray(), dense.error_dynamics(), rtol=0, atol=1e-14)
    assert [f.rank for f in check_detectable(model)] == [f.rank for f in dense.detectability]


def test_a_shared_riccati_solution_is_each_subsystems_own():
    model, noise = chain(5)
    design = design_estimator(model, noise)
    for part, weights, gain in zip(model.parts, noise, design.gains):
        A, _, C = part.augmented()
        L, P = kalman_gain(A, C, weights.covariance(), weights.measurement)
        assert np.array_equal(gain.L, L) and np.array_equal(gain.P, P)
    assert design.gains[0].L is not design.gains[1].L


def test_above_the_limit_an_unstable_coupled_estimator_has_the_dense_message(monkeypatch):
    model = augment(pair(2.0))
    slow = [NoiseWeights(np.eye(1) * 1e-6, np.eye(1) * 1e-6, np.eye(1)) for _ in range(2)]
    dense = message(lambda: design_estimator(model, slow))
    sparse_path(monkeypatch)
    assert message(lambda: design_estimator(model, slow)) == dense
    assert "the coupled estimator is unstable" in dense
    fast = [NoiseWeights(np.eye(1) * 1e-2, np.eye(1) * 1e-4, np.eye(1) * 1e-4) for _ in range(2)]
    assert design_estimator(model, fast).radius < 1


def test_above_the_limit_a_coupled_integrating_mode_has_the_dense_message(monkeypatch):
    """A_aa = A_bb = 0.5, the coupled A with an eigenvalue 1: no gain can certify, the dense check speaks."""
    system = CoupledSystem((subsystem("a", 0.5), subsystem("b", 0.5)),
                           (Coupling(0, 1, np.array([[0.5]]), np.zeros((1, 1))),
                            Coupling(1, 0, np.array([[0.5]]), np.zeros((1, 1)))))
    model = augment(system)
    dense = (message(lambda: check_detectable(model)), message(lambda: design_estimator(model)))
    sparse_path(monkeypatch)
    assert (message(lambda: check_detectable(model)), message(lambda: design_estimator(model))) == dense
    assert "the coupled system" in dense[0] and "rank is 3 < 4" in dense[0]


def test_a_chain_of_1024_is_designed_without_a_dense_check(monkeypatch):
    model, noise = chain(1024)

    def dense(*args, **kwargs):
        raise AssertionError("a dense check ran")

    monkeypatch.setattr(kalman, "check_coupled", dense)
    monkeypatch.setattr(model_module, "check_coupled", dense)
    monkeypatch.setattr(kalman, "spectral_radius", lambda matrix: dense() if matrix.shape[0] > 10 else
                        float(np.abs(np.linalg.eigvals(matrix)).max()))
    design = design_estimator(model, noise)
    assert design.detectability[-1].rank == 3072 and len(design.gains) == 1024
    assert check_detectable(model)[-1].rank == 3072

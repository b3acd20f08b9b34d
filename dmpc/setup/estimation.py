"""The scenario's ``estimation`` section and ``plant.measurement_noise`` as the estimation core's
objects (:mod:`dmpc.estimation`): the augmented model with the subsystems' C, its detectability
(``dmpc validate``), the agents' gains (``dmpc design`` and every run), and the plant's noise on
the outputs.
"""
from __future__ import annotations

import numpy as np

from dmpc.core.measurement import MeasurementNoise
from dmpc.core.system import CoupledSystem
from dmpc.estimation.kalman import EstimatorDesign, NoiseWeights, design_estimator, subsystem_scales
from dmpc.estimation.model import AugmentedSystem, Detectability, augment, check_detectable
from dmpc.scenario import Scenario
from dmpc.scenario.schema import EstimationSpec, NoiseSpec, per_subsystem


def disturbance_kinds(spec: EstimationSpec, names: list[str]) -> list[str]:
    """The disturbance model of each subsystem, in order.

    Parameters
    ----------
    spec : EstimationSpec
        The scenario's ``estimation``: one kind for all, or a map by subsystem name.
    names : list of str
        The subsystems' names, in order.
    """
    kinds = spec.disturbance
    if isinstance(kinds, dict):
        default = EstimationSpec.model_fields["disturbance"].default
        return [str(kinds.get(name, default)) for name in names]
    return [str(kinds)] * len(names)


def estimation_model(scenario: Scenario, system: CoupledSystem) -> AugmentedSystem | None:
    """The augmented model of ``system`` (the scenario's, with each subsystem's C) with the
    scenario's disturbance models; None without ``estimation``.

    Parameters
    ----------
    scenario : Scenario
    system : CoupledSystem
        ``build_system(scenario)``.
    """
    spec = scenario.estimation
    if spec is None:
        return None
    names = [s.name for s in system.subsystems]
    return augment(system, [s.C for s in system.subsystems], disturbance_kinds(spec, names))


def check_estimation(scenario: Scenario, system: CoupledSystem) -> tuple[Detectability, ...]:
    """The detectability conditions of the scenario's estimator (per subsystem, then coupled); ()
    without ``estimation``. What ``dmpc validate`` checks: no gain is designed.

    Parameters
    ----------
    scenario : Scenario
    system : CoupledSystem
        ``build_system(scenario)``.

    Raises
    ------
    DesignError
        The first condition that fails, with the figures and what to change.
    """
    model = estimation_model(scenario, system)
    return () if model is None else check_detectable(model)


def noise_weights(spec: NoiseSpec, model: AugmentedSystem) -> list[NoiseWeights]:
    """Each subsystem's filter weights: the fractions of ``spec`` times the scales of its bounds
    (:meth:`dmpc.estimation.kalman.NoiseWeights.scaled`).

    Parameters
    ----------
    spec : NoiseSpec
        The scenario's ``estimation.noise``.
    model : AugmentedSystem
        From :func:`estimation_model`.
    """
    system = model.system
    names = [s.name for s in system.subsystems]
    fields = NoiseSpec.model_fields
    fractions = {field: per_subsystem(getattr(spec, field), names, fields[field].default) for field in fields}
    out = []
    for i, (sub, part) in enumerate(zip(system.subsystems, model.parts)):
        x_scale, u_scale = subsystem_scales(sub)
        out.append(NoiseWeights.scaled(part, x_scale, u_scale, state=fractions["state"][i],
                                       disturbance=fractions["disturbance"][i],
                                       measurement=fractions["measurement"][i]))
    return out


def design_estimation(scenario: Scenario, system: CoupledSystem) -> EstimatorDesign | None:
    """The scenario's estimator: detectability checked, every agent's gain designed and the coupled
    estimator's stability checked (:func:`dmpc.estimation.kalman.design_estimator`); None without
    ``estimation``.

    Parameters
    ----------
    scenario : Scenario
    system : CoupledSystem
        ``build_system(scenario)``.

    Raises
    ------
    DesignError
        Detectability, a filter without a stabilising solution, or an unstable coupled estimator.
    """
    model = estimation_model(scenario, system)
    if model is None:
        return None
    assert scenario.estimation is not None  # a model is built only with estimation
    return design_estimator(model, noise_weights(scenario.estimation.noise, model))


def measurement_noise(scenario: Scenario, system: CoupledSystem) -> MeasurementNoise | None:
    """The noise of ``plant.measurement_noise`` on the global output of ``system`` (p,); None
    without it.

    Parameters
    ----------
    scenario : Scenario
    system : CoupledSystem
        ``build_system(scenario)``: its outputs' order and sizes.
    """
    spec = scenario.plant.measurement_noise
    if spec is None:
        return None
    std = np.zeros(system.p)
    if isinstance(spec.std, dict):
        for i, sub in enumerate(system.subsystems):
            if sub.name in spec.std:
                std[system.ys(i)] = spec.std[sub.name]
    else:
        std[:] = spec.std
    return MeasurementNoise(std, scenario.seed if spec.seed is None else spec.seed)

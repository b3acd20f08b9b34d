"""Every shipped scenario, without setpoints, gives the trajectory it gave before setpoints existed.

tests/data/golden/<scenario>.npz holds x, u, J and beta of ``dmpc.simulate`` of each scenario (the
default method, the steps it had then) as computed by the release before setpoint tracking; the
tracking path must leave a run that requests nothing exactly as it was. The comparison is to
1e-13 of the largest entry: a few units in the last place. Once the design is fixed, that is all
another CPU's rounding moves a run (measured: at most 5e-15 of the scale, with OpenBLAS's Haswell,
Sandybridge, Nehalem and Prescott kernels forced through OPENBLAS_CORETYPE); a change of the
online algorithm moves it by far more.

The design is fixed because the design itself is not reproducible to 1e-13 across machines. The
gains of ``gains: lmi`` come from an interior-point SDP (Clarabel, solved to 1e-9) whose PSD cones
call BLAS and LAPACK (dsyevr, dgemm, ... of scipy's OpenBLAS), and OpenBLAS picks its kernels by
CPU. The log-det optimum is flat in K, so the rounding alone moves the solution: measured between
the OpenBLAS kernels SkylakeX, Haswell, Sandybridge, Nehalem, Prescott and Clarabel's two KKT
solvers (qdldl, faer), by up to 1.8e-4 of the largest entry in K (fourtank; 2e-5 in rooms), 1.4e-5
in P, 2e-5 in X^f and 6e-6 in beta0 = sigma(alpha0). The loop carries that into the trajectory (up
to 4e-8 of the scale in x of rooms, 9e-6 in beta; rooms has slow modes). The goldens were made
where OpenBLAS runs its AVX-512 kernels: with OPENBLAS_CORETYPE=SkylakeX (or Cooperlake,
SapphireRapids) this code reproduces every one of them bit for bit, with the Haswell kernels that
an AMD EPYC gets a designed scenario is off by up to 3e-6 of the scale (beta of rooms). So a
scenario whose gains are designed runs with the design stored beside its trajectory
(<scenario>.design.json, the content of design.json, ``prepare(scenario).design_json()``) made with
OPENBLAS_CORETYPE=SkylakeX: identical, for the scenarios it had, to what the release of the goldens
writes so, and the design with which the current code gives the stored trajectories bit for bit
there. A scenario with given gains (paper) runs the whole pipeline, its design included.

That the scenarios still design what is stored is checked separately, to the SDP's reach: the
fresh design's gains method, horizon, t_star, rows of X^f, alpha0, tube and terminal margins
exactly, and K, P, X^f and beta0 to DESIGN_RTOL of each one's largest entry, about ten times the
spread above. That catches a changed design (another objective, Q, strictness, a broken solve),
not one that moves the SDP's solution by less than about ten rounding spreads: the LMI's
strictness margin doubled (1e-4 -> 2e-4 of lambda_max(Q)) moves P by 1.0e-4 to 3e-4 and fails rooms
only, ten times it fails all seven. The design's own tests are tests/test_design*.py.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import dmpc
from dmpc.api.result import load_run
from dmpc.records.session import RunRecorder
from dmpc.runtime.inprocess import record_run
from dmpc.setup import prepare

ROOT = Path(__file__).resolve().parents[1]
GOLDEN = ROOT / "tests" / "data" / "golden"
SCENARIOS = sorted(p.stem for p in GOLDEN.glob("*.npz"))
DESIGNED = sorted(p.name.removesuffix(".design.json") for p in GOLDEN.glob("*.design.json"))

# About ten times the largest difference of a fresh design from the stored one measured over
# OpenBLAS kernels and Clarabel's KKT solvers (module docstring: 1.8e-4, 1.4e-5, 2e-5, 6e-6),
# relative to the field's largest entry
DESIGN_RTOL = {"K": 2e-3, "P": 1.5e-4, "omega": 2e-4, "beta0": 6e-5}
DESIGN_EXACT = ("gains_method", "horizon", "t_star", "omega_rows", "alpha0", "tube", "terminal_margin")


def scenario_without_setpoints(name: str):
    steps = np.load(GOLDEN / f"{name}.npz")["u"].shape[0]  # the rooms ran 12 h before their day of setpoints
    return dmpc.load_scenario(ROOT / "scenarios" / f"{name}.yaml", setpoints=[], steps=steps)


def stored_design(name: str) -> dict:
    return json.loads((GOLDEN / f"{name}.design.json").read_text())


def test_every_shipped_scenario_has_a_golden_trajectory():
    assert SCENARIOS == sorted(p.stem for p in (ROOT / "scenarios").glob("*.yaml"))
    # and each one whose gains are designed has its design: without it the comparison below would
    # depend on this machine's SDP rounding
    designed = [name for name in SCENARIOS if scenario_without_setpoints(name).design.gains != "given"]
    assert DESIGNED == designed


@pytest.mark.parametrize("name", SCENARIOS)
def test_without_setpoints_the_trajectory_is_the_one_from_before(name, tmp_path):
    golden = np.load(GOLDEN / f"{name}.npz")
    design = stored_design(name) if name in DESIGNED else None
    prepared = prepare(scenario_without_setpoints(name), design_data=design)
    # as dmpc.simulate runs a scenario, with the design given
    with RunRecorder(tmp_path / "run", prepared, show_progress=False) as recorder:
        _, failure = record_run(prepared, recorder)
    assert not failure
    result = load_run(tmp_path / "run")
    for key, value in (("x", result.stacked_x()), ("u", result.stacked_u()), ("J", result.J), ("beta", result.beta)):
        expected = golden[key]
        assert value.shape == expected.shape, key
        scale = max(float(np.nanmax(np.abs(expected))), 1.0)
        np.testing.assert_allclose(value, expected, rtol=0, atol=1e-13 * scale, err_msg=f"{name}: {key}")


def entries(design: dict, key: str) -> np.ndarray:
    """The entries of the design.json field ``key``, flat (K and P: the blocks one after another)."""
    blocks = design[key] if key in ("K", "P") else [design[key]]
    return np.concatenate([np.ravel(np.asarray(block, float)) for block in blocks])


@pytest.mark.parametrize("name", DESIGNED)
def test_the_scenario_still_designs_the_stored_design(name):
    stored = stored_design(name)
    fresh = prepare(scenario_without_setpoints(name)).design_json()
    for key in DESIGN_EXACT:
        assert fresh[key] == stored[key], f"{name}: {key}"
    for key, rtol in DESIGN_RTOL.items():
        expected = entries(stored, key)
        np.testing.assert_allclose(entries(fresh, key), expected, rtol=0, atol=rtol * float(np.max(np.abs(expected))),
                                   err_msg=f"{name}: {key}")

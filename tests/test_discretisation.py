"""Continuous-time models: the discrete matrices against scipy, the fill-in, and the plant's exact model."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.signal import cont2discrete

import dmpc
from dmpc.core.discretisation import discretise, fill_in, local_zoh
from dmpc.scenario import ScenarioError, build_system, discrete_model

ROOT = Path(__file__).resolve().parents[1]
CARTS = ROOT / "scenarios" / "carts-continuous.yaml"
DT = 0.1


@pytest.fixture(scope="module")
def carts():
    return dmpc.load_scenario(CARTS)


def _continuous(scn):
    """The matrices as written (continuous time), from the YAML file itself."""
    return discrete_model(scn).continuous


def _zoh(A, B, dt=DT):
    Ad, Bd, *_ = cont2discrete((A, B, np.eye(A.shape[0]), np.zeros((A.shape[0], B.shape[1]))), dt, method="zoh")
    return Ad, Bd


def test_local_zoh_is_each_subsystems_exact_hold_with_neighbours_held(carts):
    """design.json's model equals scipy's zero-order hold of (A_ii, [B_ii A_ij B_ij ...]) per cart."""
    model = dmpc.design(carts).model
    ct = _continuous(carts)
    assert model["method"] == "local-zoh" and model["dt"] == DT
    couplings = {(c["target"], c["source"]): c for c in model["couplings"]}
    names = [s.name for s in ct.subsystems]
    for i, sub in enumerate(ct.subsystems):
        incoming = [c for c in ct.couplings if c.target == i]
        Ad, Gd = _zoh(sub.A, np.hstack([sub.B] + [np.hstack([c.A, c.B]) for c in incoming]))
        np.testing.assert_allclose(model["subsystems"][i]["A"], Ad, rtol=0, atol=1e-12)
        np.testing.assert_allclose(model["subsystems"][i]["B"], Gd[:, :sub.m], rtol=0, atol=1e-12)
        col = sub.m
        for c in incoming:
            written = couplings[(names[i], names[c.source])]
            np.testing.assert_allclose(written["A"], Gd[:, col:col + 2], rtol=0, atol=1e-12)
            np.testing.assert_allclose(written["B"], Gd[:, col + 2:col + 3], rtol=0, atol=1e-12)
            col += 3
    assert len(model["couplings"]) == len(ct.couplings) == 4  # the graph is kept: no coupling 1-3


def test_exact_model_is_the_whole_systems_hold_and_its_fill_in_is_reported(carts):
    model = dmpc.design(carts).model
    ct = _continuous(carts)
    Ad, Bd = _zoh(ct.A, ct.B)
    np.testing.assert_allclose(model["exact"]["A"], Ad, rtol=0, atol=1e-12)
    np.testing.assert_allclose(model["exact"]["B"], Bd, rtol=0, atol=1e-12)
    block = np.zeros((ct.n + ct.m, ct.n + ct.m))
    block[:ct.n, :ct.n], block[:ct.n, ct.n:] = ct.A, ct.B
    np.testing.assert_allclose(model["exact"]["A"], expm(block * DT)[:ct.n, :ct.n], rtol=0, atol=1e-12)
    # carts 1 and 3 are two springs apart: the exponential couples them, of order k dt^2 / 2
    outside = max(np.abs(Ad[0:2, 4:6]).max(), np.abs(Ad[4:6, 0:2]).max(), np.abs(Bd[0:2, 2]).max())
    fill = model["fill_in"]
    assert fill["largest"] == pytest.approx(outside, rel=1e-12)
    assert 1e-5 < fill["largest"] < 1e-3
    assert {(b["target"], b["source"]) for b in fill["blocks"]} == {("1", "3"), ("3", "1")}
    # local-zoh differs from the exact model inside the graph by O(dt^2)
    local = build_system(carts)
    assert model["model_error"] == pytest.approx(max(np.abs(local.A - Ad).max(), np.abs(local.B - Bd).max()))
    assert 1e-5 < model["model_error"] < 1e-2


def test_exact_zoh_is_refused_above_the_tolerance_and_truncated_on_request(carts):
    with pytest.raises(ScenarioError, match=r"discretisation: .*outside the coupling graph: entries up to 0.000134"
                                            r".*A_3,1.*truncate: true") as err:
        build_system(dmpc.load_scenario(carts, discretisation__method="exact-zoh"))
    assert err.value.field == "discretisation.truncate"
    accepted = build_system(dmpc.load_scenario(carts, discretisation__method="exact-zoh",
                                               discretisation__tolerance=1e-3))
    truncated = dmpc.load_scenario(carts, discretisation__method="exact-zoh", discretisation__truncate=True)
    system = build_system(truncated)
    ct = _continuous(carts)
    Ad, Bd = _zoh(ct.A, ct.B)
    inside = np.ones_like(Ad, dtype=bool)
    inside[0:2, 4:6] = inside[4:6, 0:2] = False
    np.testing.assert_allclose(system.A[inside], Ad[inside], rtol=0, atol=1e-12)
    assert not system.A[~inside].any() and not system.B[0:2, 2].any()
    np.testing.assert_allclose(accepted.A, system.A, rtol=0, atol=0)
    assert dmpc.design(truncated).model["model_error"] == pytest.approx(discrete_model(truncated).fill_in.largest)


def test_a_system_without_paths_of_length_two_has_no_fill_in():
    """Two coupled subsystems: the exact hold stays inside the graph, and both methods agree with it on the diagonal."""
    ct = build_system(dmpc.load_scenario({
        "name": "pair", "subsystems": [
            {"name": "a", "A": [[0.0, 1.0], [-1.0, 0.0]], "B": [[0.0], [1.0]], "Q": np.eye(2), "R": [[1.0]],
             "input": {"lower": [-1.0], "upper": [1.0]}, "x0": [0.1, 0.0]},
            {"name": "b", "A": [[-1.0]], "B": [[1.0]], "Q": [[1.0]], "R": [[1.0]],
             "input": {"lower": [-1.0], "upper": [1.0]}, "x0": [0.2]}],
        "couplings": [{"target": "a", "source": "b", "A": [[0.0], [0.5]]}]}))
    model = discretise(ct, 0.2, "exact-zoh")
    assert model.fill_in.largest == 0.0 and model.fill_in.blocks == []
    np.testing.assert_allclose(model.system.A, _zoh(ct.A, ct.B, 0.2)[0], rtol=0, atol=1e-12)
    local = local_zoh(ct, 0.2)
    assert fill_in(ct, local.A, local.B).largest == 0.0
    np.testing.assert_allclose(local.subsystems[1].A, np.exp([[-0.2]]), rtol=0, atol=1e-14)


def test_continuous_time_needs_dt_and_exact_plant_needs_continuous_time(carts):
    with pytest.raises(ScenarioError, match=r"^dt: required when time is 'continuous'"):
        dmpc.load_scenario(carts, dt=None)
    with pytest.raises(ScenarioError, match=r"^plant.model: 'exact' needs time: continuous"):
        dmpc.load_scenario(ROOT / "scenarios" / "paper.yaml", plant__model="exact")


def test_closed_loop_with_the_exact_plant_against_local_zoh_controllers(carts):
    """The plant simulates the exact model; the controllers keep local-zoh: the loop still holds, and differs."""
    scn = dmpc.load_scenario(carts, steps=40, horizon=34)
    nominal = dmpc.simulate(scn)
    exact = dmpc.simulate(dmpc.load_scenario(scn, plant__model="exact"))
    assert nominal.verdict == exact.verdict == "ok"
    assert exact.summary["plant"] == {"model": "exact"}
    gap = max(np.abs(exact.x[name] - nominal.x[name]).max() for name in nominal.names)
    assert 1e-4 < gap < 0.1
    assert exact.cost != pytest.approx(nominal.cost, rel=1e-6)
    # the plant really steps the exact matrices: replay its first step
    model = exact.design.model
    x0, u0 = exact.stacked_x()[0], exact.stacked_u()[0]
    np.testing.assert_allclose(exact.stacked_x()[1], np.array(model["exact"]["A"]) @ x0
                               + np.array(model["exact"]["B"]) @ u0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(exact.t, np.arange(41) * DT)

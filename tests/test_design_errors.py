"""Design errors that name their cause, solver warnings kept off the terminal, and the margin of (10).

Each failing system is built so that the cause can be shown here by hand: a rank test on
[A_ii - lambda I, B_ii] for a stuck mode, an eigenvalue bound for couplings too strong for any
block-diagonal gain, and an exact Lyapunov solution for a margin of (10) that sits on zero.
"""
from __future__ import annotations

import logging
import warnings
from dataclasses import replace

import numpy as np
import pytest
import yaml
from rich.console import Console
from scipy.linalg import solve_discrete_lyapunov

from dmpc.core.system import CoupledSystem, LinearSet, Subsystem
from dmpc.offline import DesignError, gains
from dmpc.offline.gains import lmi_gains, lqr_gains, verify_gains
from dmpc.offline.stabilisable import stuck_modes
from dmpc.records.tables import design_report
from dmpc.scenario import build_system, load_scenario
from dmpc.setup import prepare
from tests.helpers.cli import call
from tests.helpers.reference import A_II, B_II, PAPER, PAPER_LMI, Q_I, R_I, block_diag, chain_matrices

ZERO_B2 = {"subsystems.1.B": [[0.0], [0.0]]}
# eigenvalues 3 and 4; B_ii = [1, 1]' is orthogonal to the left eigenvector [1, -1] of 3
STUCK_A2 = {"subsystems.1.A": [[3.0, 1.0], [0.0, 4.0]]}


def pbh_rank(A, B, lam) -> int:
    return int(np.linalg.matrix_rank(np.hstack([A - lam * np.eye(A.shape[0]), B]), tol=1e-9))


def render(table) -> str:
    console = Console(width=400, record=True, color_system=None)
    console.print(table)
    return console.export_text()


def scalar_network(path, couplings: dict[tuple[str, str], float]) -> str:
    """Scalar subsystems x+ = 0.5 x + u + sum c x_j named a, b, c, LMI gains."""
    data = {
        "name": "scalar-network",
        "subsystems": [{"name": name, "A": [[0.5]], "B": [[1.0]], "Q": [[1.0]], "R": [[1.0]],
                        "input": {"lower": [-1.0], "upper": [1.0]}, "x0": [0.1]} for name in "abc"],
        "couplings": [{"target": t, "source": s, "A": [[c]]} for (t, s), c in couplings.items()],
        "design": {"gains": "lmi"},
    }
    path.write_text(yaml.safe_dump(data))
    return str(path)


def symmetric_pair(c: float) -> dict:
    return {("a", "b"): c, ("b", "a"): c}


# ---------------------------------------------------------------- not stabilisable

@pytest.mark.parametrize("method", ["lmi", "lqr"])
def test_zero_input_matrix_names_the_subsystem_before_any_solve(method, monkeypatch):
    def no_solve(*args, **kwargs):
        raise AssertionError("an SDP or Riccati solve ran")

    monkeypatch.setattr(gains, "_solve_lmi", no_solve)
    monkeypatch.setattr("scipy.linalg.solve_discrete_are", no_solve)
    # by hand: B_22 = 0 leaves both unstable modes of A_22 (1.1 and 1.3) where they are
    assert all(pbh_rank(A_II, np.zeros((2, 1)), lam) == 1 for lam in (1.1, 1.3))
    with pytest.raises(DesignError) as info:
        prepare(load_scenario(PAPER_LMI, {**ZERO_B2, "design.gains": method}))
    text = str(info.value)
    assert f"gains ({method})" in text and "subsystem 2" in text and "not stabilisable" in text
    assert "1.1" in text and "1.3" in text
    assert "SDP solver" not in text and "Riccati" not in text


def test_a_stuck_unstable_mode_is_named_with_a_nonzero_input_matrix():
    A2 = np.array(STUCK_A2["subsystems.1.A"])
    assert pbh_rank(A2, B_II, 3.0) == 1 and pbh_rank(A2, B_II, 4.0) == 2
    with pytest.raises(DesignError, match=r"subsystem 2 is not stabilisable.*lambda = 3 \(") as info:
        prepare(load_scenario(PAPER_LMI, STUCK_A2))
    assert "lambda = 4" not in str(info.value)


@pytest.mark.parametrize("A, B, stuck", [
    (A_II, B_II, []),                                       # the paper's subsystem: controllable
    (np.diag([0.5, 1.2]), np.array([[1.0], [0.0]]), [1.2]),  # the unstable mode is the unreachable one
    (np.diag([1.2, 0.5]), np.array([[1.0], [0.0]]), []),     # only a stable mode is unreachable
    (np.array([[0.0, -1.5], [1.5, 0.0]]), np.zeros((2, 1)), [1.5]),  # a rotating pair, reported once
])
def test_stuck_modes(A, B, stuck):
    found = stuck_modes(A, B)
    assert sorted(abs(m.eigenvalue) for m in found) == pytest.approx(stuck)
    for m in found:
        assert pbh_rank(A, B, m.eigenvalue) == m.rank < A.shape[0]


def test_cli_error_is_one_line_without_warnings(monkeypatch, capsys):
    code, _, err = call(monkeypatch, capsys, "design", str(PAPER_LMI), "--set", "subsystems[1].B=[[0],[0]]")
    assert code != 0
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: gains (lmi): (A_ii, B_ii) of subsystem 2"), err
    assert "Warning" not in err and ".py" not in err


# ---------------------------------------------------------------- infeasible LMI

def test_a_pair_coupled_too_strongly_is_named(tmp_path):
    """x_a+ = d_a x_a + 2 x_b, x_b+ = 2 x_a + d_b x_b: a symmetric matrix whose eigenvalues differ by
    sqrt((d_a - d_b)^2 + 16) >= 4, so no diagonal gain (d_i = 0.5 + k_i) puts both inside (-1, 1)."""
    d = np.linspace(-5.0, 5.0, 101)
    spread = np.sqrt((d[:, None] - d[None, :]) ** 2 + 16.0)
    assert np.min(spread) >= 4.0 > 2.0
    path = scalar_network(tmp_path / "s.yaml", {**symmetric_pair(2.0), ("b", "c"): 0.1, ("c", "b"): 0.1})
    with pytest.raises(DesignError) as info:
        prepare(load_scenario(path))
    text = str(info.value)
    assert "infeasible" in text and "(10)" in text and "block-diagonal" in text
    assert "subsystems a-b alone" in text and "b-c" not in text


def test_a_network_too_strongly_coupled_as_a_whole_is_told_so(tmp_path):
    """Couplings 0.9 along a-b-c. Each pair alone is stabilised by k_i = -0.5: [[0, .9], [.9, 0]] has
    eigenvalues +-0.9. The three together are not stabilisable by any diagonal gain: for
    v = (1, sqrt 2, 1)/2 and w = (1, -sqrt 2, 1)/2, v'Mv - w'Mw = 1.8 sqrt 2 > 2 whatever the
    diagonal of the symmetric closed loop M, so its eigenvalues cannot all lie in (-1, 1)."""
    assert np.max(np.abs(np.linalg.eigvals(np.array([[0.0, 0.9], [0.9, 0.0]])))) < 1.0
    v, w = np.array([1, np.sqrt(2), 1]) / 2, np.array([1, -np.sqrt(2), 1]) / 2
    off = np.array([[0, 0.9, 0], [0.9, 0, 0.9], [0, 0.9, 0]])
    assert v @ off @ v - w @ off @ w == pytest.approx(1.8 * np.sqrt(2)) and 1.8 * np.sqrt(2) > 2
    path = scalar_network(tmp_path / "s.yaml", {**symmetric_pair(0.9), ("b", "c"): 0.9, ("c", "b"): 0.9})
    with pytest.raises(DesignError, match=r"infeasible.*every coupled pair meets it alone.*network together"):
        prepare(load_scenario(path))


def test_a_feasible_pair_designs(tmp_path):
    prepared = prepare(load_scenario(scalar_network(tmp_path / "s.yaml", symmetric_pair(0.5))))
    assert prepared.design.gains.rho < 1.0


# ---------------------------------------------------------------- solver warnings

def test_solver_warnings_go_to_the_design_logger(monkeypatch, caplog):
    from dmpc.offline import lmi_conic

    original = lmi_conic.solve_lmi

    def warning_solve(*args, **kwargs):
        warnings.warn("Solution may be inaccurate (injected).", UserWarning, stacklevel=2)
        return original(*args, **kwargs)

    monkeypatch.setattr(lmi_conic, "solve_lmi", warning_solve)
    system = build_system(load_scenario(PAPER_LMI))
    with warnings.catch_warnings(record=True) as escaped, caplog.at_level(logging.INFO, logger="dmpc.offline"):
        warnings.simplefilter("always")
        g = lmi_gains(system)
    assert g.rho < 1.0
    assert [str(w.message) for w in escaped] == []
    logged = [r for r in caplog.records if r.name == "dmpc.offline" and "injected" in r.getMessage()]
    assert logged and all(r.levelno == logging.INFO for r in logged)


def test_an_unstable_subsystem_designs_without_warnings():
    system = build_system(load_scenario(PAPER_LMI, {"subsystems.1.A": [[8.0, 1.0], [0.0, 6.0]]}))
    with warnings.catch_warnings(record=True) as escaped:
        warnings.simplefilter("always")
        g = lmi_gains(system)
    assert [str(w.message) for w in escaped] == []
    assert g.lyapunov_margin <= -g.lyapunov_tolerance and not g.margin_thin


# ---------------------------------------------------------------- the margin of (10)

def independent_margin(K, P, Qs) -> tuple[float, float]:
    """Check value of (10) and its tolerance for the paper's chain with weights Qs (one per subsystem)."""
    A, B = chain_matrices(len(Qs))
    Kg, Pg = block_diag(K), block_diag(P)
    AK = A + B @ Kg
    lhs = AK.T @ Pg @ AK - Pg + block_diag(Qs) + Kg.T @ block_diag([R_I] * len(Qs)) @ Kg
    lam_p = float(np.max(np.linalg.eigvalsh(Pg)))
    return float(np.max(np.linalg.eigvalsh((lhs + lhs.T) / 2))), 1e-6 * lam_p


@pytest.mark.parametrize("q1", [1.0, 100.0])
def test_lmi_design_passes_10_with_a_clear_margin(q1):
    g = prepare(load_scenario(PAPER_LMI, {"subsystems.0.Q": (q1 * Q_I).tolist()})).design.gains
    margin, tolerance = independent_margin(g.K, g.P, [q1 * Q_I, Q_I, Q_I, Q_I])
    assert g.lyapunov_margin == pytest.approx(margin, abs=1e-3 * tolerance)
    assert g.lyapunov_tolerance == pytest.approx(tolerance, rel=1e-9)
    # at least one tolerance below zero, so twice the tolerance away from the limit
    assert margin <= -tolerance
    assert not g.margin_thin and g.margin_note == ""
    # still close to the log-det optimum: (10) is only slightly off its boundary (1e-3 lambda_max(P))
    assert margin >= -1e3 * tolerance


def one_subsystem(A, B, Q, R) -> CoupledSystem:
    return CoupledSystem((Subsystem("s", A, B, Q, R, np.zeros(A.shape[0]), LinearSet.box([-1.0], [1.0])),))


def test_gains_on_the_boundary_of_10_are_thin_and_say_why():
    """P solving (A+BK)'P(A+BK) - P = -(Q + K'RK) exactly puts the check value of (10) at 0."""
    K = np.array([[-0.7, -1.1]])
    AK = A_II + B_II @ K
    P = solve_discrete_lyapunov(AK.T, Q_I + K.T @ R_I @ K)
    system = one_subsystem(A_II, B_II, Q_I, R_I)
    thin = verify_gains(system, [K], [P], "given")
    assert abs(thin.lyapunov_margin) < 1e-9 and thin.margin_thin
    assert "tolerance" in thin.margin_note and "reject" in thin.margin_note
    clear = verify_gains(system, [K], [1.01 * P], "given")
    # 1.01 P: the left side of (10) becomes -0.01 (Q + K'RK), whose largest eigenvalue is known
    expected = -0.01 * float(np.min(np.linalg.eigvalsh(Q_I + K.T @ R_I @ K)))
    assert clear.lyapunov_margin == pytest.approx(expected, rel=1e-6)
    assert not clear.margin_thin and clear.margin_note == ""


def test_lqr_gains_on_a_single_subsystem_are_checked_the_same_way():
    g = lqr_gains(one_subsystem(A_II, B_II, Q_I, R_I))
    # the DARE solution meets (10) with equality: thin, and said so
    assert abs(g.lyapunov_margin) < 1e-6 and g.margin_thin


def test_design_report_and_json_show_the_margin_in_words():
    prepared = prepare(load_scenario(PAPER))
    g = prepared.design.gains
    text = render(design_report(prepared))
    row = next(line for line in text.splitlines() if "(10) margin" in line)
    assert "largest eigenvalue of (A+BK)'P(A+BK) - P + Q + K'RK" in row
    assert f"{g.lyapunov_margin:.4g}" in row and "-0.35" in row and "(holds;" in row
    assert f"must be <= {g.lyapunov_tolerance:.2g}" in row
    assert "thin" not in text
    assert prepared.design.to_json()["lyapunov_margin_thin"] is False

    K = [np.asarray(k) for k in g.K]
    exact = [solve_discrete_lyapunov((A_II + B_II @ k).T, Q_I + k.T @ R_I @ k) for k in K]
    thin = verify_gains(one_subsystem(A_II, B_II, Q_I, R_I), K[:1], exact[:1], "given")
    thin_prepared = replace(prepared, design=replace(prepared.design, gains=replace(g, margin_thin=True,
                                                                                    margin_note=thin.margin_note)))
    text = render(design_report(thin_prepared))
    assert "holds, thin" in text and "(10) thin margin" in text and "reject" in text
    assert thin_prepared.design.to_json()["lyapunov_margin_thin"] is True

"""Independent computations for the tests of the cooperative core (tests/test_cooperative_core.py).

Nothing here imports ``dmpc.cooperative``: the global matrices are assembled by hand from the
subsystems' and couplings' raw blocks (not ``CoupledSystem.A``), trajectories and costs are plain
loops, the constraint rows come from each subsystem's raw sets, and the restricted and centralised
problems are written out in cvxpy (Clarabel) and scipy's linprog (HiGHS).
"""
from __future__ import annotations

from dataclasses import replace

import cvxpy as cp
import numpy as np
from scipy.optimize import linprog

from dmpc.core.system import CoupledSystem, Coupling, LinearSet, Subsystem

# ---------------------------------------------------------------- global matrices, by hand

def offsets(system: CoupledSystem) -> tuple[list[slice], list[slice]]:
    """Each subsystem's slice in the global state and input."""
    xs, us, r, c = [], [], 0, 0
    for s in system.subsystems:
        n, m = s.A.shape[0], s.B.shape[1]
        xs.append(slice(r, r + n))
        us.append(slice(c, c + m))
        r, c = r + n, c + m
    return xs, us


def global_AB(system: CoupledSystem) -> tuple[np.ndarray, np.ndarray]:
    """Global A (n, n) and B (n, m) assembled from the raw blocks."""
    xs, us = offsets(system)
    n, m = xs[-1].stop, us[-1].stop
    A, B = np.zeros((n, n)), np.zeros((n, m))
    for i, s in enumerate(system.subsystems):
        A[xs[i], xs[i]] += s.A
        B[xs[i], us[i]] += s.B
    for c in system.couplings:
        A[xs[c.target], xs[c.source]] += c.A
        B[xs[c.target], us[c.source]] += c.B
    return A, B


def dense_block_diag(blocks: list[np.ndarray]) -> np.ndarray:
    out = np.zeros((sum(b.shape[0] for b in blocks), sum(b.shape[1] for b in blocks)))
    r = c = 0
    for b in blocks:
        out[r:r + b.shape[0], c:c + b.shape[1]] = b
        r, c = r + b.shape[0], c + b.shape[1]
    return out


def simulate(A: np.ndarray, B: np.ndarray, x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """z (N+1, n): z(0) = x, z(t+1) = A z(t) + B v(t)."""
    z = [np.asarray(x, float)]
    for t in range(v.shape[0]):
        z.append(A @ z[-1] + B @ v[t])
    return np.array(z)


def plan_cost(z: np.ndarray, v: np.ndarray, Q: np.ndarray, R: np.ndarray, P: np.ndarray) -> float:
    """sum_{t<N} z'Qz + v'Rv + z(N)'P z(N), term by term."""
    total = 0.0
    for t in range(v.shape[0]):
        total += float(z[t] @ Q @ z[t] + v[t] @ R @ v[t])
    return total + float(z[-1] @ P @ z[-1])


def part_costs(system: CoupledSystem, P: list[np.ndarray], z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per subsystem: its states' part of the cost (stage and terminal) and its inputs' part."""
    xs, us = offsets(system)
    state = np.array([sum(float(z[t, xs[j]] @ s.Q @ z[t, xs[j]]) for t in range(v.shape[0]))
                      + float(z[-1, xs[j]] @ P[j] @ z[-1, xs[j]]) for j, s in enumerate(system.subsystems)])
    inputs = np.array([sum(float(v[t, us[j]] @ s.R @ v[t, us[j]]) for t in range(v.shape[0]))
                       for j, s in enumerate(system.subsystems)])
    return state, inputs


# ---------------------------------------------------------------- the centralised problem's rows, from the raw sets

def largest_violation(system: CoupledSystem, z: np.ndarray, v: np.ndarray, x_s: np.ndarray, u_s: np.ndarray,
                      alpha: np.ndarray, beta: float) -> float:
    """The largest absolute excess of the iterate (deviation coordinates around (x_s, u_s)) over
    every row of the centralised problem: U_i on v_i(t) + u_s,i (t < N), X_i on z_i(t) + x_s,i
    (t = 1..N), and |z(N) - alpha| <= beta componentwise. 0 when feasible."""
    xs, us = offsets(system)
    worst = 0.0
    for i, s in enumerate(system.subsystems):
        for the_set, part, shift, times in ((s.input_set, v[:, us[i]], u_s[us[i]], range(v.shape[0])),
                                            (s.state_set, z[:, xs[i]], x_s[xs[i]], range(1, z.shape[0]))):
            if the_set is None:
                continue
            H = np.asarray(the_set.H, float)
            for t in times:
                value = H @ (part[t] + shift)
                with np.errstate(invalid="ignore"):
                    over = np.concatenate([value - the_set.upper, the_set.lower - value])
                over = over[np.isfinite(over)]
                if over.size:
                    worst = max(worst, float(over.max()))
    worst = max(worst, float(np.max(np.abs(z[-1] - alpha) - beta)))
    return worst


def _set_rows(the_set: LinearSet | None, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """G w <= g for the finite sides of the set."""
    if the_set is None:
        return np.zeros((0, dim)), np.zeros(0)
    H = np.asarray(the_set.H, float)
    up, lo = np.isfinite(the_set.upper), np.isfinite(the_set.lower)
    return np.vstack([H[up], -H[lo]]), np.concatenate([the_set.upper[up], -the_set.lower[lo]])


def centrally_feasible(system: CoupledSystem, x0: np.ndarray, horizon: int, alpha: np.ndarray, beta: float) -> bool:
    """Whether some inputs over the horizon meet every row from x0 (the origin as target): an LP
    (HiGHS) over the condensed prediction z(t) = A^t x0 + sum_{s<t} A^(t-1-s) B v(s)."""
    A, B = global_AB(system)
    n, m, N = A.shape[0], B.shape[1], horizon
    xs, us = offsets(system)
    G_rows, g_rows = [], []
    free = [x0]  # z(t) without inputs
    gain = [np.zeros((n, N * m))]  # z(t)'s dependence on the stacked inputs
    for t in range(N):
        free.append(A @ free[-1])
        step = A @ gain[-1]
        step[:, t * m:(t + 1) * m] += B
        gain.append(step)
    for i, s in enumerate(system.subsystems):
        Gu, gu = _set_rows(s.input_set, s.B.shape[1])
        for t in range(N):
            sel = np.zeros((s.B.shape[1], N * m))
            sel[:, t * m + us[i].start:t * m + us[i].stop] = np.eye(s.B.shape[1])
            G_rows.append(Gu @ sel)
            g_rows.append(gu)
        Gx, gx = _set_rows(s.state_set, s.A.shape[0])
        for t in range(1, N + 1):
            G_rows.append(Gx @ gain[t][xs[i]])
            g_rows.append(gx - Gx @ free[t][xs[i]])
    G_rows += [gain[N], -gain[N]]
    g_rows += [alpha + beta - free[N], beta - alpha + free[N]]
    res = linprog(np.zeros(N * m), A_ub=np.vstack(G_rows), b_ub=np.concatenate(g_rows), bounds=(None, None),
                  method="highs")
    return res.status == 0


def restricted_optimum(system: CoupledSystem, P: list[np.ndarray], z: np.ndarray, v: np.ndarray, agent: int,
                       x_s: np.ndarray, u_s: np.ndarray, alpha: np.ndarray, beta: float) -> tuple[np.ndarray, float]:
    """The centralised problem over agent ``agent``'s inputs, every other agent's at v, from z(0):
    its minimiser v_i (N, m_i) and the global cost there (cvxpy, Clarabel). Deviation coordinates."""
    A, B = global_AB(system)
    xs, us = offsets(system)
    N = v.shape[0]
    own = us[agent]
    w = cp.Variable((N, own.stop - own.start))
    select = np.zeros((own.stop - own.start, B.shape[1]))
    select[:, own] = np.eye(own.stop - own.start)
    fixed = v.copy()
    fixed[:, own] = 0.0
    Q = dense_block_diag([s.Q for s in system.subsystems])
    R = dense_block_diag([s.R for s in system.subsystems])
    P_all = dense_block_diag(P)
    state = z[0]
    cost, cons = 0, []
    for t in range(N):
        vt = fixed[t] + w[t] @ select
        cost += cp.quad_form(state, Q) if isinstance(state, cp.Expression) else float(state @ Q @ state)
        cost += cp.quad_form(vt, R)
        state = A @ state + B @ vt
        for i, s in enumerate(system.subsystems):
            Gx, gx = _set_rows(s.state_set, s.A.shape[0])
            if Gx.shape[0]:
                cons.append(Gx @ (state[xs[i]] + x_s[xs[i]]) <= gx)
        s = system.subsystems[agent]
        Gu, gu = _set_rows(s.input_set, s.B.shape[1])
        if Gu.shape[0]:
            cons.append(Gu @ (w[t] + u_s[own]) <= gu)
    cost += cp.quad_form(state, P_all)
    cons += [state - alpha <= beta, alpha - state <= beta]
    problem = cp.Problem(cp.Minimize(cost), cons)
    problem.solve(solver=cp.CLARABEL, tol_gap_abs=1e-10, tol_gap_rel=1e-10, tol_feas=1e-10)
    assert problem.status == cp.OPTIMAL, problem.status
    return np.asarray(w.value), float(problem.value)


# ---------------------------------------------------------------- random systems and feasible iterates

def random_system(rng: np.random.Generator, M: int, input_factor: float, couple: float = 0.7,
                  decoupled: bool = False, no_own_input: int | None = None) -> CoupledSystem:
    """M subsystems, n_i = 2, m_i = 1, without sets yet (see :func:`with_sets_around`).

    Each ordered pair is coupled with probability ``couple``: A_ij entries up to 0.2, B_ij a
    random direction of norm ``input_factor`` |B_jj|. ``no_own_input``: that subsystem gets
    B_ii = 0 (its inputs act only through its couplings)."""
    subs = []
    for i in range(M):
        A = rng.uniform(-0.4, 0.4, (2, 2)) + np.diag(rng.uniform(0.7, 1.1, 2))
        B = (rng.uniform(0.3, 1.0, 2) * rng.choice([-1.0, 1.0], 2))[:, None]
        if i == no_own_input:
            B = np.zeros((2, 1))
        L = rng.normal(size=(2, 2))
        subs.append(Subsystem(name=f"s{i}", A=A, B=B, Q=L @ L.T + 0.5 * np.eye(2),
                              R=np.array([[rng.uniform(0.05, 1.0)]]), x0=np.zeros(2),
                              input_set=LinearSet.box([-np.inf], [np.inf])))
    couplings = []
    if not decoupled:
        for i in range(M):
            for j in range(M):
                if i != j and rng.random() < couple:
                    Bij = rng.normal(size=(2, 1))
                    scale = max(float(np.linalg.norm(subs[j].B)), 0.5)
                    Bij *= input_factor * scale / np.linalg.norm(Bij)
                    couplings.append(Coupling(target=i, source=j, A=rng.uniform(-0.2, 0.2, (2, 2)), B=Bij))
    if no_own_input is not None and not any(c.source == no_own_input and np.any(c.B) for c in couplings):
        target = (no_own_input + 1) % M
        couplings = [c for c in couplings if not (c.source == no_own_input and c.target == target)]
        couplings.append(Coupling(target=target, source=no_own_input, A=rng.uniform(-0.2, 0.2, (2, 2)),
                                  B=rng.normal(size=(2, 1))))
    return CoupledSystem(subsystems=tuple(subs), couplings=tuple(couplings))


def random_weights(rng: np.random.Generator, M: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Random K_i (1, 2) and positive definite P_i (2, 2)."""
    K, P = [], []
    for _ in range(M):
        K.append(rng.uniform(-0.6, 0.6, (1, 2)))
        L = rng.normal(size=(2, 2))
        P.append(L @ L.T + np.eye(2))
    return K, P


def steady_target(rng: np.random.Generator, system: CoupledSystem, size: float) -> tuple[np.ndarray, np.ndarray]:
    """A steady state (x_s, u_s) of the coupled system, x_s = A x_s + B u_s (zero for size 0)."""
    A, B = global_AB(system)
    u_s = size * rng.uniform(-1.0, 1.0, B.shape[1])
    x_s = np.linalg.solve(np.eye(A.shape[0]) - A, B @ u_s)
    return x_s, u_s


def with_sets_around(rng: np.random.Generator, system: CoupledSystem, z: np.ndarray, v: np.ndarray,
                     x_s: np.ndarray, u_s: np.ndarray, polytopes: bool = True) -> CoupledSystem:
    """The system with input and state sets that the iterate (deviation coordinates) meets, a
    random margin (0.02 to 0.5) away from it, so that some rows bind once agents optimise; some
    subsystems get no state set, some a polytope of three rows."""
    xs, us = offsets(system)
    subs = []
    for i, s in enumerate(system.subsystems):
        vi, zi = v[:, us[i]] + u_s[us[i]], z[1:, xs[i]] + x_s[xs[i]]
        U = LinearSet.box(vi.min(axis=0) - rng.uniform(0.02, 0.5, vi.shape[1]),
                          vi.max(axis=0) + rng.uniform(0.02, 0.5, vi.shape[1]))
        kind = rng.integers(0, 3) if polytopes else 1
        if kind == 0:
            X = None
        elif kind == 1:
            X = LinearSet.box(zi.min(axis=0) - rng.uniform(0.02, 0.5, 2), zi.max(axis=0) + rng.uniform(0.02, 0.5, 2))
        else:
            H = rng.normal(size=(3, 2))
            X = LinearSet.polytope(H, (zi @ H.T).max(axis=0) + rng.uniform(0.02, 0.5, 3))
        subs.append(replace(s, input_set=U, state_set=X))
    return replace(system, subsystems=tuple(subs))


def terminal_box_around(rng: np.random.Generator, zN: np.ndarray) -> tuple[np.ndarray, float]:
    """A terminal box |z(N) - alpha| <= beta that z(N) meets with a small margin."""
    alpha = zN + rng.uniform(-0.3, 0.3, zN.size)
    return alpha, float(np.abs(zN - alpha).max() + rng.uniform(0.01, 0.3))

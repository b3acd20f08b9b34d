"""The step barrier and coordinator: a pure state machine (no bus, no clock).

Per step k it releases round 0 to every agent, collects their plans, runs further Jacobi rounds
while the plans still move (k = 0: to convergence), then finalises the step: inputs (with the
fallback of docs/algorithm.md, "Online step k, agent i", item 7, for missing, infeasible or
refused plans), alpha(k+1) = (A+BK) eta, beta(k+1) = sigma(alpha(k+1)) (or another method's
terminal update, dmpc.methods.policy), the plant update and the step record.

Inputs are method calls (``start``, ``on_plan``, ``on_deadline``, ``on_agent_lost``,
``on_agent_back``); outputs are lists of actions for the hosting process to carry out.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dmpc.bus.messages import PlanMessage, Release
from dmpc.design import Design
from dmpc.mpc_qp import QPStatus, plan_cost
from dmpc.plant.dynamics import Plant
from dmpc.security.rejects import MAX_MAGNITUDE, magnitude
from dmpc.system import CoupledSystem, LinearSet, project_onto
from dmpc.trajectories import Plan, candidate_plan, shifted_input

SOLVED_STATUSES = ("solved", "solved_inaccurate")
KNOWN_STATUSES = frozenset(s.value for s in QPStatus)
# A solved plan may leave U_i by this much times max(1, |bound|): OSQP solves to about 1e-7,
# so an honest plan stays well inside, and anything beyond is refused.
INPUT_TOLERANCE = 1e-6
INPUT_REFUSED = "input outside U_i"


_LIMITS: dict[int, tuple] = {}  # id(input set) -> (the set, H^T or None for a box, lower and upper limits)


def _limits(input_set: LinearSet) -> tuple:
    entry = _LIMITS.get(id(input_set))
    if entry is None or entry[0] is not input_set:
        H, lower, upper = input_set.H, input_set.lower, input_set.upper
        box = H.shape[0] == H.shape[1] and np.array_equal(H, np.eye(H.shape[0]))
        entry = (input_set, None if box else H.T, lower - INPUT_TOLERANCE * np.maximum(1.0, np.abs(lower)),
                 upper + INPUT_TOLERANCE * np.maximum(1.0, np.abs(upper)))
        _LIMITS[id(input_set)] = entry
    return entry


def input_excess(input_set: LinearSet, v: np.ndarray) -> float:
    """How far the inputs ``v`` (one per row, shape (N, m_i)) leave ``input_set`` beyond
    ``INPUT_TOLERANCE``; > 0 means refused. Infinite bounds never bind."""
    _, HT, lower, upper = _limits(input_set)
    Hv = v if HT is None else v @ HT
    if Hv.size == 0:
        return -math.inf
    return float(max((Hv - upper).max(), (lower - Hv).max()))


@dataclass(frozen=True)
class ProtocolOptions:
    """What the coordinator needs from the scenario's options."""

    steps: int
    iterations: int = 1
    tolerance: float = 1e-9
    initial_iterations: int = 200
    initial_tolerance: float = 1e-9


@dataclass(frozen=True)
class SendRelease:
    release: Release


@dataclass(frozen=True)
class RoundOpened:
    """A round was released; the host arms its deadline (if any) for it."""

    k: int
    iteration: int


@dataclass(frozen=True)
class StepCompleted:
    record: "StepRecord"


@dataclass(frozen=True)
class RunFinished:
    reason: str


@dataclass
class StepRecord:
    """Everything recorded about one step.

    Array shapes: x (n,), u (m,), alpha (n,), x_next (n,); per-agent lists have M entries.
    ``r`` and ``r_next`` (M,) are the ellipsoid levels of the ellipsoid methods (None otherwise);
    those methods record alpha = 0 and beta = NaN.
    """

    k: int
    x: np.ndarray
    u: np.ndarray
    alpha: np.ndarray
    beta: float
    x_next: np.ndarray
    alpha_next: np.ndarray
    beta_next: float
    J: float
    J_agents: list[float]
    S: float
    rounds: int
    max_change: float
    status: list[str]
    fallback: list[bool]
    fallback_reason: list[str]
    solve_time: list[float]
    qp_iterations: list[int]
    plans_z: list[np.ndarray]
    plans_v: list[np.ndarray]
    latency: list[float] = field(default_factory=list)
    step_time: float = float("nan")
    note: str = ""
    r: np.ndarray | None = None
    r_next: np.ndarray | None = None


class Coordinator:
    """The barrier for one run.

    Parameters
    ----------
    system : CoupledSystem
    design : Design
    plant : Plant
    options : ProtocolOptions
    run_id : str
    policy : dmpc.methods.policy.TerminalPolicy, optional
        The method's terminal sets: what each agent is released and how the terminal
        parameters move (the paper's time-varying boxes by default).
    """

    def __init__(self, system: CoupledSystem, design: Design, plant: Plant, options: ProtocolOptions,
                 run_id: str, policy=None) -> None:
        self.system = system
        self.design = design
        self.plant = plant
        self.options = options
        self.run_id = run_id
        self.names = [s.name for s in system.subsystems]
        self.index = {name: i for i, name in enumerate(self.names)}
        self.N = design.horizon
        K = design.gains.K
        self._K = K
        self._gamma = [s.A + s.B @ K[i] for i, s in enumerate(system.subsystems)]
        if policy is None:
            from dmpc.methods import terminal_policy

            policy = terminal_policy("tv-box", system, design)
        self.policy = policy
        self.terminal = policy.initial(plant.x)
        self.k = 0
        self.iteration = 0
        self.finished = False
        self.last_plan: list[Plan | None] = [None] * system.M
        self._round: dict[int, PlanMessage] = {}
        self._missed: set[int] = set()
        self._lost: set[int] = set()
        self._step_latest: dict[int, Plan] = {}
        self._prev_round: dict[int, Plan] = {}
        self._round_status: dict[int, PlanMessage] = {}
        self._max_change = float("nan")
        self.rejected: dict[str, int] = {}
        self.duplicates = 0
        self.inputs_refused: dict[str, int] = {}
        self._refused: dict[int, PlanMessage] = {}  # per agent: its last plan refused (kept until replaced)
        self._provided: dict[int, Plan] = {}
        self._note = self.terminal.note

    @property
    def alpha(self) -> np.ndarray:
        """The terminal box centres alpha(k), shape (n,) (zeros for the ellipsoid methods)."""
        return self.terminal.alpha

    @property
    def beta(self) -> float:
        """The terminal box radius beta(k) (NaN for the ellipsoid methods)."""
        return self.terminal.beta

    # ------------------------------------------------------------------ inputs
    def start(self) -> list:
        """Actions that release step 0, round 0."""
        return self._release_round()

    def on_plan(self, msg: PlanMessage, checked: bool = False) -> list:
        """A plan arrived; returns the actions it triggers (possibly none).

        ``checked``: the caller has just run :meth:`check` on it and found no problem.
        """
        if self.finished:
            return []
        problem = None if checked else self.check(msg)
        if problem is not None:
            self.rejected[problem] = self.rejected.get(problem, 0) + 1
            return []
        i = self.index[msg.sender]
        if i in self._round or i in self._missed:
            self.duplicates += 1
            return []
        self._round[i] = msg
        if msg.status in SOLVED_STATUSES and input_excess(self.system.subsystems[i].input_set, msg.v) > 0:
            self._refuse(i, msg)
        return self._maybe_close_round()

    def _refuse(self, i: int, msg: PlanMessage) -> None:
        """Agent i's plan leaves U_i: it stands as the agent's answer for the round, but its
        fallback applies (as for an infeasible QP), and the refusal is counted."""
        self._refused[i] = msg
        self.inputs_refused[msg.sender] = self.inputs_refused.get(msg.sender, 0) + 1

    def _usable(self, i: int, msg: PlanMessage | None) -> bool:
        """True if ``msg`` is a solved plan of agent i that was not refused."""
        return msg is not None and msg.status in SOLVED_STATUSES and self._refused.get(i) is not msg

    def _fallback_reason(self, i: int, msg: PlanMessage | None) -> str:
        if msg is None:
            return "lost" if i in self._lost else "missed"
        return INPUT_REFUSED if self._refused.get(i) is msg else f"qp {msg.status}"

    def on_deadline(self, k: int, iteration: int) -> list:
        """The round's deadline passed: whoever has not delivered missed it."""
        if self.finished or (k, iteration) != (self.k, self.iteration):
            return []
        for i in range(self.system.M):
            if i not in self._round:
                self._missed.add(i)
        return self._maybe_close_round()

    def on_agent_lost(self, name: str) -> list:
        """Liveliness of agent ``name`` disappeared: stop waiting for it and stop releasing to it.

        Its fallback applies from the open round on; the step record notes the loss.
        """
        i = self.index.get(name)
        if i is None or self.finished:
            return []
        if i not in self._lost:
            self._add_note(f"agent {name} lost")
        self._lost.add(i)
        if i not in self._round:
            self._missed.add(i)
        return self._maybe_close_round()

    def on_agent_back(self, name: str) -> bool:
        """Agent ``name`` is ready again: it is released to and waited for from the next round on.

        Returns True if it had been lost (the step record then notes its return).
        """
        i = self.index.get(name)
        if i is None or i not in self._lost or self.finished:
            return False
        self._lost.discard(i)
        self._add_note(f"agent {name} back")
        return True

    def _add_note(self, text: str) -> None:
        self._note = f"{self._note}; {text}" if self._note else text

    # ------------------------------------------------------------------ checks
    def check(self, msg: PlanMessage) -> str | None:
        """None if the plan belongs to the open round and has the right shapes; else the reason."""
        if msg.run != self.run_id:
            return "wrong run"
        i = self.index.get(msg.sender)
        if i is None:
            return "unknown sender"
        if (msg.k, msg.iteration) != (self.k, self.iteration):
            return "stale" if (msg.k, msg.iteration) < (self.k, self.iteration) else "future"
        sub = self.system.subsystems[i]
        if msg.z.shape != (self.N + 1, sub.n) or msg.v.shape != (self.N, sub.m):
            return "wrong shape"
        if msg.status not in KNOWN_STATUSES:
            return "unknown status"
        if msg.status in SOLVED_STATUSES:
            size = magnitude(msg.z, msg.v, msg.cost)
            if not math.isfinite(size):
                return "non-finite plan"
            if size > MAX_MAGNITUDE:
                return "out of range"
        return None

    def has_plan(self, name: str) -> bool:
        """True if agent ``name``'s plan for the open round is in (or the agent was marked missed)."""
        i = self.index.get(name)
        return i is not None and (i in self._round or i in self._missed)

    # ------------------------------------------------------------------ rounds
    def _release_round(self) -> list:
        self._round = {}
        self._missed = set(self._lost)
        actions: list = []
        M = self.system.M
        if len(self._lost) < M:
            assumed = np.full((M, 2), -1, dtype=np.int64)
            for j in range(M):
                ref = self._reference(j)
                if ref is not None:
                    assumed[j] = (ref.k, ref.iteration)
            centres, sizes = self.policy.release_all(self.terminal)
            # lost agents are skipped: their plans would not be used, and the first release after
            # their Ready tells them they are back
            release = Release(run=self.run_id, k=self.k, iteration=self.iteration, x=self.plant.x.copy(),
                              centres=centres, sizes=sizes, assumed=assumed,
                              skipped=tuple(self.names[i] for i in sorted(self._lost)),
                              provided={self.names[j]: (plan.z, plan.v) for j, plan in self._provided.items()})
            actions.append(SendRelease(release))
        actions.append(RoundOpened(self.k, self.iteration))
        actions.extend(self._maybe_close_round())
        return actions

    def _reference(self, j: int) -> Plan | None:
        """The plan of agent j its neighbours build their assumption from."""
        if self.iteration > 0 and j in self._step_latest:
            return self._step_latest[j]
        return self.last_plan[j]

    def _maybe_close_round(self) -> list:
        if len(self._round) + len(self._missed) < self.system.M or (
                self._missed and len(self._round) + len(self._missed - self._round.keys()) < self.system.M):
            return []
        self._prev_round = dict(self._step_latest)
        self._provided = {}
        for i, msg in self._round.items():
            self._round_status[i] = msg
            if self._usable(i, msg):
                self._step_latest[i] = Plan(msg.k, msg.iteration, msg.z, msg.v)
        infeasible = [self.names[i] for i, msg in self._round.items() if msg.status not in SOLVED_STATUSES]
        if self.k == 0 and self.iteration == 0 and infeasible and not self._missed:
            self._seed_from_centralized(infeasible)
        rounds_allowed = self.options.initial_iterations if self.k == 0 else self.options.iterations
        tol = self.options.initial_tolerance if self.k == 0 else self.options.tolerance
        change = self._round_change()
        self._max_change = change
        converged = self.iteration > 0 and change < tol
        if self.iteration + 1 < rounds_allowed and not converged and not self._missed:
            self.iteration += 1
            return self._release_round()
        return self._finalise_step()

    def _seed_from_centralized(self, infeasible: list[str]) -> None:
        """Replace the first round's plans by the centralised QP's plan
        (docs/algorithm.md, "Online step k, agent i", item 4)."""
        from dmpc.centralized import CentralQP

        T, lower, upper = self.policy.joint_terminal(self.terminal)
        qp = CentralQP(self.system, self.design.gains.P_global(), self.N, terminal="rows", rows=T)
        sol = qp.solve_rows(self.plant.x, lower, upper)
        if not sol.status.feasible:
            self._add_note(f"k=0: round 0 infeasible for agents {', '.join(infeasible)} and the centralised QP is "
                           f"{sol.status.value} too")
            return
        for i in range(self.system.M):
            plan = Plan(0, 0, sol.z[:, self.system.xs(i)], sol.v[:, self.system.us(i)])
            self._step_latest[i] = plan
            self._provided[i] = plan
        self._add_note(f"k=0: round 0 infeasible from decoupled rollouts for agents {', '.join(infeasible)}; "
                       "started from the centralised QP's plan")

    def _round_change(self) -> float:
        """Largest change of this round's plans: max over agents of max |z - z_ref|, |v - v_ref|.

        Round 0 compares each plan with what the neighbours assumed of it: the agent's candidate,
        its last plan shifted to step k and continued with K_i (at k = 0, or without any plan,
        the decoupled K-rollout from x_i(k)), with the measured x_i(k) as first state. Later
        rounds compare with the agent's plan of the previous round; inf if it has none there
        (its QP was infeasible), so the rounds go on. Agents without a plan in this round do not
        count (0 if none has one).
        """
        x_parts = self.system.split_state(self.plant.x) if self.iteration == 0 else None
        change = 0.0
        for i, plan in self._step_latest.items():
            if self.iteration == 0:
                z_ref, v_ref = self._candidate(i, self.last_plan[i], x_parts[i])
                z_ref[0] = x_parts[i]
            else:
                prev = self._prev_round.get(i)
                if prev is None:
                    return float("inf")
                z_ref, v_ref = prev.z, prev.v
            change = max(change, float(np.abs(plan.z - z_ref).max()), float(np.abs(plan.v - v_ref).max()))
        return change

    # ------------------------------------------------------------------ step end
    def _finalise_step(self) -> list:
        system, M = self.system, self.system.M
        x = self.plant.x.copy()
        x_parts = system.split_state(x)
        u_parts, eta_parts, J_agents = [], [], []
        status, fallback, reasons, solve_time, qp_iters, latency, plans_z, plans_v = ([] for _ in range(8))
        for i in range(M):
            sub = system.subsystems[i]
            plan = self._step_latest.get(i)
            msg = self._round_status.get(i)
            status.append(msg.status if msg is not None else "missed")
            solve_time.append(msg.solve_time if msg is not None else float("nan"))
            qp_iters.append(msg.qp_iterations if msg is not None else 0)
            latency.append(msg.sent_at if msg is not None else float("nan"))
            if plan is not None:
                u_parts.append(plan.v[0])  # concatenated into new arrays below
                eta_parts.append(plan.z[-1])
                J_agents.append(float(msg.cost) if self._usable(i, msg) else self._candidate_cost(i, plan))
                self.last_plan[i] = plan
                fallback.append(False)
                reasons.append("")
                plans_z.append(plan.z)
                plans_v.append(plan.v)
            else:
                last = self.last_plan[i]
                u_c = shifted_input(last, self.k, x_parts[i], self._gamma[i], self._K[i])
                u_parts.append(project_onto(sub.input_set, u_c))
                J_agents.append(self._candidate_cost(i, last) if last is not None else float("nan"))
                fallback.append(True)
                reasons.append(self._fallback_reason(i, msg))
                z_c, v_c = self._candidate(i, last, x_parts[i])
                eta_parts.append(self.policy.fallback_terminal(self.terminal, i, z_c[-1]))
                plans_z.append(z_c)
                plans_v.append(v_c)
        u = np.concatenate(u_parts)
        eta = np.concatenate(eta_parts)
        nxt = self.policy.update(self.terminal, eta)
        note = "; ".join(t for t in (self._note, nxt.note) if t)
        S = system.spread(x)
        x_next = self.plant.step(u)
        record = StepRecord(
            k=self.k, x=x, u=u, alpha=self.alpha.copy(), beta=self.beta, x_next=x_next.copy(),
            alpha_next=nxt.alpha, beta_next=nxt.beta, J=float(np.sum(J_agents)), J_agents=J_agents, S=S,
            rounds=self.iteration + 1, max_change=self._max_change, status=status, fallback=fallback,
            fallback_reason=reasons, solve_time=solve_time, qp_iterations=qp_iters, plans_z=plans_z,
            plans_v=plans_v, latency=latency, note=note, r=self.terminal.r, r_next=nxt.r)
        actions: list = [StepCompleted(record)]
        self.terminal = nxt
        self.k += 1
        self.iteration = 0
        self._step_latest = {}
        self._prev_round = {}
        self._round_status = {}
        self._note = ""
        if self.k >= self.options.steps:
            self.finished = True
            actions.append(RunFinished("finished"))
            return actions
        actions.extend(self._release_round())
        return actions

    def _candidate(self, i: int, last: Plan | None, x_i: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The shifted candidate plan of agent i at this step, shapes (N+1, n_i), (N, m_i)."""
        return candidate_plan(last, self.k, x_i, self.N, self._gamma[i], self._K[i])

    def _candidate_cost(self, i: int, plan: Plan) -> float:
        sub = self.system.subsystems[i]
        z, v = candidate_plan(plan, self.k, None, self.N, self._gamma[i], self._K[i])
        return plan_cost(z, v, sub.Q, sub.R, self.design.gains.P[i])

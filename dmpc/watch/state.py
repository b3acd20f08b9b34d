"""Everything an observer knows about one run, gathered from the bus or a run folder.

Feeds (the bus observer's thread, the folder reader) write; every page session reads. Rows
are kept in step order and only appended; a row that arrives out of order (a gap filled from
the run folder) is inserted and bumps ``epoch``, which tells readers to start over.
"""
from __future__ import annotations

import bisect
import math
import threading
from dataclasses import dataclass, field

from dmpc.bus import keys
from dmpc.core.errors import DmpcError
from dmpc.watch.meta import RunMeta


def floats(values) -> list[float]:
    """The JSON list of numbers ``values`` (None for NaN) as floats."""
    return [math.nan if v is None else float(v) for v in values]


def number(value) -> float:
    """The JSON number ``value`` as a float (None: NaN)."""
    return math.nan if value is None else float(value)


@dataclass(frozen=True)
class StateRow:
    """x(k), alpha(k), beta(k): known for k = 0 .. K (one more than the steps)."""

    k: int
    x: list[float]
    alpha: list[float]
    beta: float


@dataclass(frozen=True)
class Targets:
    """What step k tracked (docs/scenarios.md, "Setpoints: `setpoints`"): the target it applied and
    the setpoint requested (NaN where free), for the states (n,) and the inputs (m,).

    Attributes
    ----------
    x, u : list of float
        The target applied: x_s (n,) and u_s (m,).
    setpoint, setpoint_u : list of float
        The setpoint requested for the states (n,) and the inputs (m,)."""

    x: list[float]
    u: list[float]
    setpoint: list[float]
    setpoint_u: list[float]


@dataclass(frozen=True)
class Estimate:
    """What the controllers saw of step k in a run with ``estimation`` (docs/algorithm.md,
    "Offset-free tracking").

    Attributes
    ----------
    y : list of float
        The outputs the plant measured, y(k) (p,).
    x_hat : list of float
        The state estimate x^(k|k) the controllers worked from (n,).
    d_hat : list of float
        The disturbance estimate d^(k|k) (n_d,).
    innovation : float
        ||y(k) - C x^(k|k-1) - C_d d^(k|k-1)||_inf."""

    y: list[float]
    x_hat: list[float]
    d_hat: list[float]
    innovation: float


@dataclass(frozen=True)
class StepRow:
    """What happened in step k (the fields of a ``steps.jsonl`` line that the page shows).

    ``targets`` is None in a step before anything was requested (and in every step of a run
    without setpoints), whose line has no targets. ``solve_reason`` (M,) says, with an event
    trigger, why each agent solved ("" where it kept its plan or solved in a step of several
    rounds); None without a trigger. ``rounds`` counts the step's Jacobi rounds. ``estimate`` is
    what the controllers saw (the outputs measured, the state and disturbance estimates) in a run
    with ``estimation``; None without.

    Attributes
    ----------
    k : int
    u : list of float
        The inputs applied, u(k) (m,).
    J : float
        The cost J(k).
    status, fallback, fallback_reason, solve_time, latency : list
        Per agent (M,): its QP's status, whether it fell back and why, its solve time and its plan's
        latency (s).
    step_time : float
        The step's wall time (s; NaN when not timed).
    note : str
        What the records say of the step ("" if nothing)."""

    k: int
    u: list[float]
    J: float
    status: list[str]
    fallback: list[bool]
    fallback_reason: list[str]
    solve_time: list[float]
    latency: list[float]
    step_time: float
    note: str
    targets: Targets | None = None
    rounds: int = 1
    solve_reason: list[str] | None = None
    estimate: Estimate | None = None


class BadStep(DmpcError, ValueError):
    """A step line that cannot be shown: missing fields or the wrong dimensions."""


def parse_targets(line: dict) -> Targets | None:
    """The targets of a ``steps.jsonl`` line, None when it has none (nothing requested yet)."""
    if "target" not in line:
        return None
    return Targets(x=floats(line["target"]), u=floats(line["target_u"]), setpoint=floats(line["setpoint"]),
                   setpoint_u=floats(line["setpoint_u"]))


def parse_estimate(line: dict) -> Estimate | None:
    """The outputs measured and the estimates of a ``steps.jsonl`` line, None when it has none (a run
    without ``estimation``)."""
    if "x_hat" not in line:
        return None
    return Estimate(y=floats(line["y"]), x_hat=floats(line["x_hat"]), d_hat=floats(line["d_hat"]),
                    innovation=number(line.get("innovation")))


def _reasons(line: dict) -> list[str] | None:
    """Why each agent solved (an event trigger's ``solve_reason``), None when the line has none."""
    reasons = line.get("solve_reason")
    return None if reasons is None else [str(r) for r in reasons]


def parse_step(line: dict, meta: RunMeta | None) -> tuple[StepRow, StateRow, StateRow]:
    """The step row and the state rows k and k+1 of one ``steps.jsonl`` line.

    Raises
    ------
    BadStep
        A field is missing or malformed, or (with ``meta``) a dimension does not match.
    """
    try:
        k = int(line["k"])
        if k < 0:
            raise ValueError("negative step")
        step = StepRow(k=k, u=floats(line["u"]), J=number(line["J"]), status=[str(s) for s in line["status"]],
                       fallback=[bool(f) for f in line["fallback"]],
                       fallback_reason=[str(r) for r in line["fallback_reason"]],
                       solve_time=floats(line["solve_time"]), latency=floats(line.get("latency") or []),
                       step_time=number(line.get("step_time")), note=str(line.get("note") or ""),
                       targets=parse_targets(line), rounds=int(line.get("rounds") or 1),
                       solve_reason=_reasons(line), estimate=parse_estimate(line))
        now = StateRow(k, floats(line["x"]), floats(line["alpha"]), number(line["beta"]))
        nxt = StateRow(k + 1, floats(line["x_next"]), floats(line["alpha_next"]), number(line["beta_next"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise BadStep(f"not a step line ({type(exc).__name__}: {exc})") from None
    if meta is not None:
        n = sum(s.n for s in meta.subsystems)
        m = sum(s.m for s in meta.subsystems)
        M = meta.M
        sizes = {"x": len(now.x), "x_next": len(nxt.x), "u": len(step.u), "status": len(step.status),
                 "fallback": len(step.fallback), "solve_time": len(step.solve_time)}
        want = {"x": n, "x_next": n, "u": m, "status": M, "fallback": M, "solve_time": M}
        if step.solve_reason is not None:
            sizes["solve_reason"], want["solve_reason"] = len(step.solve_reason), M
        if step.targets is not None:
            t = step.targets
            sizes.update({"target": len(t.x), "setpoint": len(t.setpoint), "target_u": len(t.u),
                          "setpoint_u": len(t.setpoint_u)})
            want.update({"target": n, "setpoint": n, "target_u": m, "setpoint_u": m})
        if step.estimate is not None and meta.estimation:
            e = step.estimate
            sizes.update({"y": len(e.y), "x_hat": len(e.x_hat), "d_hat": len(e.d_hat)})
            want.update({"y": sum(s.p for s in meta.subsystems), "x_hat": n,
                         "d_hat": sum(s.nd for s in meta.subsystems)})
        wrong = [key for key in sizes if sizes[key] != want[key]]
        if wrong:
            raise BadStep(f"step {k}: {wrong[0]} has {sizes[wrong[0]]} entries, the run {want[wrong[0]]}")
    return step, now, nxt


@dataclass
class Snapshot:
    """What a reader gets from :meth:`RunState.read`: new rows since its last read, and the rest.

    Attributes
    ----------
    epoch : int
        Changes when rows arrived out of order: the reader starts over.
    version : int
        Changes with every change of the state.
    state_rows, step_rows : list
        The rows added since the reader's last read (every row in a new epoch).
    meta : RunMeta or None
        The run's description, once it has come.
    plant : dict
        The plant's last status (liveliness, readiness, dropped messages).
    alive : dict of str -> bool
        The liveliness of each role seen.
    summary : dict or None
        The run's summary, once it has ended; ``summary_from`` says where it came from.
    summary_from : str
    connection : str
        The observer's connection, in words.
    ended : bool
        The run has a summary, or its plant is gone.
    dropped : int
        Messages or lines that could not be used; ``problems``: the first few reasons.
    problems : list of str
    source, run_id : str
        Where the data comes from, and the run's id."""

    epoch: int
    version: int
    state_rows: list[StateRow]
    step_rows: list[StepRow]
    meta: RunMeta | None
    plant: dict
    alive: dict[str, bool]
    summary: dict | None
    summary_from: str
    connection: str
    ended: bool
    dropped: int
    source: str
    run_id: str
    problems: list[str] = field(default_factory=list)


class RunState:
    """One run as the observer knows it; every method is thread-safe.

    Parameters
    ----------
    source : str
        Where the data comes from, for the page (e.g. ``run folder runs/x``).
    run_id : str
        The run's id, when known before its description arrives.
    """

    def __init__(self, source: str, run_id: str = "") -> None:
        self._lock = threading.Lock()
        self.source = source
        self.run_id = run_id
        self.meta: RunMeta | None = None
        self.version = 0
        self.epoch = 0
        self._state_rows: list[StateRow] = []
        self._state_ks: list[int] = []
        self._step_rows: list[StepRow] = []
        self._step_ks: list[int] = []
        self.plant: dict = {}
        self.alive: dict[str, bool] = {}
        self.summary: dict | None = None
        self.summary_from = ""
        self.connection = ""
        self.plant_gone = False
        self.dropped = 0
        self.problems: list[str] = []

    # -- writers ---------------------------------------------------------------------------
    def _changed(self) -> None:
        self.version += 1

    def set_meta(self, meta: RunMeta) -> None:
        """The run's description ``meta`` (the first one counts)."""
        with self._lock:
            if self.meta is None:
                self.meta = meta
                self.run_id = self.run_id or meta.run_id
                self._changed()

    def add_step(self, line: dict) -> bool:
        """Add one ``steps.jsonl`` line; False if it is malformed (counted) or known already."""
        try:
            step, now, nxt = parse_step(line, self.meta)
        except BadStep as exc:
            self.note_dropped(str(exc))
            return False
        with self._lock:
            at = _insert(self._step_rows, self._step_ks, step)
            if at is None:
                return False
            in_order = at == len(self._step_ks) - 1
            for row in (now, nxt):
                at = _insert(self._state_rows, self._state_ks, row)
                in_order = in_order and (at is None or at == len(self._state_ks) - 1)
            if not in_order:
                self.epoch += 1
            self._changed()
            return True

    def set_plant(self, status: dict) -> None:
        """The plant's status ``status`` (liveliness, readiness, dropped messages) now."""
        with self._lock:
            self.plant = dict(status)
            self._changed()

    def set_alive(self, role: str, alive: bool) -> None:
        """The liveliness token of ``role`` appeared (``alive``) or went; the coordinator's going ends the run."""
        with self._lock:
            self.alive[role] = alive
            if role == keys.COORDINATOR_ROLE and not alive:
                self.plant_gone = True
            self._changed()

    def set_summary(self, summary: dict, source: str) -> None:
        """The run's ``summary``, from ``source`` (``run folder`` or the bus); one from the run folder is
        kept over one from the bus."""
        with self._lock:
            if self.summary_from == "run folder" and source != "run folder":
                return
            self.summary = dict(summary)
            self.summary_from = source
            self._changed()

    def set_connection(self, text: str) -> None:
        """The observer's connection in words, ``text``."""
        with self._lock:
            if text != self.connection:
                self.connection = text
                self._changed()

    def note_dropped(self, why: str) -> None:
        """Count a message or line that could not be used, and why (``why``; the first few reasons are kept)."""
        with self._lock:
            self.dropped += 1
            if len(self.problems) < 5:
                self.problems.append(why[:200])
            self._changed()

    # -- readers ---------------------------------------------------------------------------
    @property
    def steps(self) -> int:
        with self._lock:
            return len(self._step_rows)

    def read(self, epoch: int, state_seen: int, steps_seen: int) -> Snapshot:
        """Rows added since a reader saw ``state_seen`` state rows and ``steps_seen`` step rows in
        ``epoch`` (every row when the epoch has changed), and the current everything else."""
        with self._lock:
            if epoch != self.epoch:
                state_seen = steps_seen = 0
            return Snapshot(epoch=self.epoch, version=self.version, state_rows=self._state_rows[state_seen:],
                            step_rows=self._step_rows[steps_seen:], meta=self.meta, plant=dict(self.plant),
                            alive=dict(self.alive), summary=self.summary, summary_from=self.summary_from,
                            connection=self.connection, ended=self.summary is not None or self.plant_gone,
                            dropped=self.dropped, source=self.source, run_id=self.run_id,
                            problems=list(self.problems))


def _insert(rows: list, ks: list[int], row) -> int | None:
    """Insert ``row`` in k order; its index, or None if its k is there already."""
    at = bisect.bisect_left(ks, row.k)
    if at < len(ks) and ks[at] == row.k:
        return None
    ks.insert(at, row.k)
    rows.insert(at, row)
    return at

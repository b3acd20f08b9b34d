"""The launcher's supervision of its processes, on fake children and a fake clock."""
from __future__ import annotations

from pathlib import Path

from dmpc.runtime.supervisor import BACKOFF, BACKOFF_MAX, RestartPolicy, Supervisor, restart_note

ROOT = Path(__file__).resolve().parents[1]


class FakeChild:
    """Exits with ``codes[n]`` at time ``times[n]`` of its n-th incarnation (None: runs on)."""

    def __init__(self, role: str, clock, times=(None,), codes=(1,)) -> None:
        self.role, self.clock = role, clock
        self.times, self.codes = list(times), list(codes)
        self.incarnation = 0
        self.started_at = [0.0]

    def poll(self):
        t = self.times[min(self.incarnation, len(self.times) - 1)]
        if t is None or self.clock() < t:
            return None
        return self.codes[min(self.incarnation, len(self.codes) - 1)]


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now

    def sleep(self, dt: float) -> None:
        self.now += dt


def supervise(children, policy):
    clock = children[0].clock

    def spawn(child):
        child.incarnation += 1
        child.started_at.append(clock())

    sup = Supervisor(children, spawn, policy, clock=clock, sleep=clock.sleep)
    return sup, sup.run()


def test_a_crashed_agent_is_restarted_with_backoff_and_the_run_ends_with_the_plant():
    clock = Clock()
    plant = FakeChild("plant", clock, times=(10.0,), codes=(0,))
    agent = FakeChild("agent-1", clock, times=(2.0, 3.0, 100.0), codes=(-9, -9, 0))
    other = FakeChild("agent-2", clock, times=(10.2,), codes=(0,))
    sup, ending = supervise([plant, agent, other], RestartPolicy(restarts=3))
    assert ending.failed == {}
    assert agent.incarnation == 2
    assert abs(agent.started_at[1] - (2.0 + BACKOFF)) <= 0.11
    assert abs(agent.started_at[2] - (3.0 + 2 * BACKOFF)) <= 0.11  # doubled the second time
    assert sup.record.restarts == {"agent-1": 2} and sup.record.lost == []
    assert sup.record.exits == {"agent-1": [-9, -9]}
    assert restart_note(sup.record) == "restarted agent-1 x2"


def test_without_restarts_a_crashed_agent_is_lost_and_the_run_goes_on():
    clock = Clock()
    plant = FakeChild("plant", clock, times=(5.0,), codes=(3,))  # finished, verdict failed
    agent = FakeChild("agent-1", clock, times=(1.0,), codes=(1,))
    sup, ending = supervise([plant, agent], RestartPolicy())
    assert ending.failed == {} and agent.incarnation == 0
    assert sup.record.lost == ["agent-1"]
    assert clock.now >= 5.0


def test_fail_fast_ends_the_run_at_the_first_lost_agent():
    clock = Clock()
    plant = FakeChild("plant", clock)
    agent = FakeChild("agent-1", clock, times=(1.0,), codes=(-9,))
    _, ending = supervise([plant, agent], RestartPolicy(fail_fast=True))
    assert ending.failed == {"agent-1": -9} and "--fail-fast" in ending.message
    assert clock.now < 1.2


def test_a_failed_plant_ends_the_run_and_an_agent_leaving_normally_is_not_restarted():
    clock = Clock()
    plant = FakeChild("plant", clock, times=(4.0,), codes=(1,))
    agent = FakeChild("agent-1", clock, times=(3.9,), codes=(0,))
    sup, ending = supervise([plant, agent], RestartPolicy(restarts=5))
    assert ending.failed == {"plant": 1}
    assert agent.incarnation == 0 and sup.record.restarts == {}


class CrashesAfter:
    """An agent whose every incarnation exits with ``code`` ``after`` s after it was started."""

    def __init__(self, role: str, clock, after: float, code: int = -9) -> None:
        self.role, self.clock, self.after, self.code = role, clock, after, code
        self.incarnation = 0
        self.started_at = [0.0]
        self.crashed_at: list[float] = []

    def poll(self):
        if self.clock() < self.started_at[self.incarnation] + self.after:
            return None
        if len(self.crashed_at) == self.incarnation:
            self.crashed_at.append(self.clock())  # the supervisor sees the exit now
        return self.code


def test_the_restart_backoff_doubles_up_to_its_cap_of_8_s():
    """0.5, 1, 2, 4 s, then 8 s for every further restart (docs/runtime.md, "Supervision")."""
    clock = Clock()
    plant = FakeChild("plant", clock, times=(120.0,), codes=(0,))
    agent = CrashesAfter("agent-1", clock, after=0.3)
    sup, ending = supervise([plant, agent], RestartPolicy(restarts=8))
    assert BACKOFF_MAX == 8.0 and ending.failed == {}
    waits = [start - crash for crash, start in zip(agent.crashed_at, agent.started_at[1:])]
    expected = [0.5, 1.0, 2.0, 4.0, 8.0, 8.0, 8.0, 8.0]
    assert len(waits) == len(expected) and agent.incarnation == 8
    assert all(abs(wait - want) <= 0.11 for wait, want in zip(waits, expected)), waits  # the poll is 0.05 s
    assert sup.record.restarts == {"agent-1": 8} and sup.record.lost == ["agent-1"]  # the 9th crash is the last


def test_the_docs_state_the_backoff_of_the_code():
    text = " ".join((ROOT / "docs" / "runtime.md").read_text().split())
    said = f"after {BACKOFF:g} s, doubled for each further restart of the same agent (at most {BACKOFF_MAX:g} s)"
    assert said in text

"""Ctrl-C and SIGTERM at any instant of ``dmpc run``'s start-up end it like an interrupt mid-run.

The launcher goes through several phases before the first step: the imports, the design, the
run folder, the plant's start, the fork server's imports, the burst of forked agents, the wait
for every agent to be ready. A signal in any of them must end the run with one line
``error: interrupted...``, exit code 130, no traceback and no process of the run left behind.
The instants are swept over the whole start-up (:data:`MARKS`, :data:`OFFSETS`) instead of
picking one.
"""
from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from tests.e2e_helpers import DMPC, ROOT, handles_sigterm, session_members, step_lines, wait_for

pytestmark = pytest.mark.e2e

SIGNALS = {
    "ctrl-c": lambda pid: os.killpg(pid, signal.SIGINT),  # a terminal's Ctrl-C reaches the whole group
    "sigterm": lambda pid: os.kill(pid, signal.SIGTERM),  # `kill PID`, a service manager
    "sigint": lambda pid: os.kill(pid, signal.SIGINT),  # `kill -INT PID`: the launcher alone
}
MARKS = {
    "imports": "the launcher handles signals: its imports, then the design",
    "design.json": "the run folder is written: the plant is being started",
    "logs/forkserver.log": "the fork server is starting (it imports the agent's modules), then forks the agents",
    "processes.json": "every process is started: the agents are getting ready",
}
"""The instants the sweep starts from, each with what the launcher is doing then. Seconds counted
from these rather than from the launcher's start land in the same phases on a fast machine and on
a loaded one."""
OFFSETS = {"imports": (0.0, 0.3, 0.7), "design.json": (0.0, 0.15), "logs/forkserver.log": (0.0, 0.25, 0.5, 0.8, 1.2),
           "processes.json": (0.0, 0.4)}
CASES = [(mark, offset, list(SIGNALS)[i % len(SIGNALS)])
         for i, (mark, offset) in enumerate((m, o) for m, offsets in OFFSETS.items() for o in offsets)]


def reached(mark: str, pid: int, out: Path) -> bool:
    return handles_sigterm(pid) if mark == "imports" else (out / mark).exists()


@pytest.mark.parametrize("mark, offset, how", CASES, ids=[f"{how}-{offset}s-after-{Path(mark).stem}"
                                                           for mark, offset, how in CASES])
def test_an_interrupt_during_start_up_stops_everything_with_exit_130(tmp_path, mark, offset, how):
    out = tmp_path / "run"
    # realtime steps of 0.2 s: the run is still going when the last signal of the sweep arrives
    launcher = subprocess.Popen(DMPC + ["run", "scenarios/paper.yaml", "--out", str(out), "--quiet",
                                        "--set", "options.mode=realtime", "--set", "options.dt=0.2", "--steps", "40"],
                                cwd=ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, start_new_session=True)
    try:
        assert wait_for(lambda: reached(mark, launcher.pid, out), timeout=60, interval=0.002), \
            f"never reached: {MARKS[mark]}"
        time.sleep(offset)
        SIGNALS[how](launcher.pid)
        t0 = time.monotonic()
        stdout, stderr = launcher.communicate(timeout=30)
        stopped_in = time.monotonic() - t0
        assert launcher.returncode == 130, f"exit {launcher.returncode}\n{stderr}"
        assert "Traceback" not in stderr, stderr
        errors = [line for line in stderr.splitlines() if line.startswith("error:")]
        assert len(errors) == 1 and errors[0].startswith("error: interrupted"), stderr
        if step_lines(out) == 0:
            assert "completed steps are in the run folder" not in stderr, stderr
        assert stopped_in < 8, f"the launcher took {stopped_in:.1f} s to stop"
        assert wait_for(lambda: not session_members(launcher.pid), timeout=1), \
            f"left running: {session_members(launcher.pid)}"
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.wait()
        for member in session_members(launcher.pid):
            os.kill(int(member.split()[0]), signal.SIGKILL)

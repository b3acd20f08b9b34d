"""Helpers for end-to-end tests with real processes: start, wait, always clean up."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

DMPC = [sys.executable, "-m", "dmpc.cli"]
ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def in_ci() -> bool:
    """True under ``CI=true`` (or 1, yes): tests that need a tool then fail rather than skip without it."""
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie still answers kill(0): look at its state
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


class Processes:
    """Starts dmpc processes and guarantees they are gone at the end."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.procs: list[subprocess.Popen] = []

    def start(self, *args: str, log: str | None = None) -> subprocess.Popen:
        out = open(self.tmp / (log or f"proc{len(self.procs)}.log"), "wb")
        proc = subprocess.Popen(DMPC + list(args), cwd=ROOT, stdin=subprocess.DEVNULL, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)
        out.close()
        proc.log_path = self.tmp / (log or f"proc{len(self.procs)}.log")
        self.procs.append(proc)
        return proc

    def log(self, proc: subprocess.Popen) -> str:
        return Path(proc.log_path).read_text(errors="replace")

    def cleanup(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            proc.wait()


def run_cli(*args: str, timeout: float = 240, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    return subprocess.run(DMPC + list(args), cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          stdin=subprocess.DEVNULL)


def simulate_paper(out: Path, *args: str) -> Path:
    """``dmpc simulate`` of the paper's example into ``out`` (extra CLI ``args``), the reference of the e2e runs."""
    res = run_cli("simulate", "scenarios/paper.yaml", "--out", str(out), "--quiet", *args)
    assert res.returncode == 0, res.stderr
    return out


def handles_sigterm(pid: int) -> bool:
    """True once process ``pid`` catches SIGTERM (its SigCgt mask in /proc): dmpc's first line ran."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            caught = next(line.split()[1] for line in fh if line.startswith("SigCgt:"))
    except (OSError, StopIteration):
        return False
    return bool(int(caught, 16) >> (signal.SIGTERM - 1) & 1)


def session_members(sid: int) -> list[str]:
    """The live (not zombie) processes of session ``sid``: ``pid name`` each."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                stat = fh.read()
        except OSError:
            continue
        name, rest = stat[stat.index("(") + 1:stat.rindex(")")], stat[stat.rindex(")") + 2:].split()
        if rest[0] != "Z" and int(rest[3]) == sid:
            found.append(f"{entry} {name}")
    return found


def wait_for(predicate, timeout: float, interval: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval)
    return predicate()


def max_abs_diff(a: Path, b: Path, keys=("x", "u", "alpha", "beta", "J", "S")) -> float:
    A, B = np.load(a / "trajectory.npz"), np.load(b / "trajectory.npz")
    return max(float(np.nanmax(np.abs(A[k] - B[k]))) for k in keys)


def step_lines(folder: Path) -> int:
    try:
        return (folder / "steps.jsonl").read_text().count("\n")
    except FileNotFoundError:
        return 0

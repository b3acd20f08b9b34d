"""``dmpc run``: the plant and every agent as separate processes on this machine.

The launcher opens no Zenoh session itself. It designs once, writes the resolved scenario and
the design into the run folder (every child loads those, so all agree), starts the children
with a private loopback port and multicast off, shows progress from the step log, and makes
sure no child outlives it: children get SIGTERM when the launcher dies (PR_SET_PDEATHSIG),
and on Ctrl-C or a failed child every process is stopped within a few seconds.
"""
from __future__ import annotations

import ctypes
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from dmpc.console import stderr_console
from dmpc.records.run_folder import STEP_LOG, claim_folder, write_json
from dmpc.runtime.bundle import write_bundle
from dmpc.runtime.setup import Prepared
from dmpc.scenario import dump_resolved

STOP_GRACE = 3.0
BUNDLE = "run.json"
PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:  # runs in the child between fork and exec
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


@dataclass
class Child:
    role: str
    cmd: list[str]
    log_path: Path
    proc: subprocess.Popen | None = None

    @property
    def pid(self) -> int:
        return self.proc.pid if self.proc else -1

    def poll(self) -> int | None:
        return self.proc.poll() if self.proc else None


@dataclass
class LaunchResult:
    code: int
    message: str
    summary: dict | None = None
    failed: dict[str, int] = field(default_factory=dict)


def free_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def prepare_run_folder(out: Path, prepared: Prepared) -> tuple[Path, Path]:
    """Write the resolved scenario and the design the children load; returns their paths."""
    claim_folder(out, STEP_LOG, "a run")
    scenario_path = out / "scenario.yaml"
    scenario_path.write_text(dump_resolved(prepared.scenario))
    design_path = out / "design.json"
    write_json(design_path, prepared.design_json())
    write_bundle(prepared, out / BUNDLE)
    return scenario_path, design_path


STAR_ABOVE = 64  # beyond this many agents a full peer mesh overloads a small machine (liveliness leases expire)
TOPOLOGIES = ("mesh", "star")


def default_topology(agents: int) -> str:
    """``mesh`` up to ``STAR_ABOVE`` agents, ``star`` above."""
    return "mesh" if agents <= STAR_ABOVE else "star"


def child_commands(prepared: Prepared, out: Path, scenario_path: Path, design_path: Path, run_id: str, port: int,
                   startup_timeout: float, extra: list[str] | None = None, tls_dir: Path | None = None,
                   topology: str = "mesh") -> list[Child]:
    """The plant and agent command lines (``python -m dmpc.cli ...``); ``tls_dir``: every link
    over TLS with the certificates (and access control) of that directory.

    ``mesh``: every process a peer, agents linked directly to each other (lowest latency for
    small M). ``star``: the plant's session is a router and agents are its clients, so there are
    M links instead of M^2/2 and agent-to-agent plans are forwarded by the plant's router.
    """
    base = [sys.executable, "-m", "dmpc.cli"]
    proto = "tcp" if tls_dir is None else "tls"
    endpoint = f"{proto}/127.0.0.1:{port}"
    common = ["--design", str(design_path), "--run-id", run_id, "--startup-timeout", str(startup_timeout),
              "--no-multicast"] + (extra or []) + ([] if tls_dir is None else ["--tls", str(tls_dir)])
    logs = out / "logs"
    logs.mkdir(exist_ok=True)
    star = topology == "star"
    children = [Child("plant", base + ["plant", str(scenario_path), "--out", str(out), "--listen", endpoint,
                                       "--quiet"] + (["--mode", "router"] if star else []) + common,
                      logs / "plant.log")]
    agent_net = ["--mode", "client"] if star else ["--listen", f"{proto}/127.0.0.1:0"]
    agent_common = [arg for arg in common if arg not in ("--design", str(design_path))]
    for name in prepared.names:
        children.append(Child(f"agent-{name}", base + ["agent", str(out / BUNDLE), "--id", name, "--connect", endpoint]
                              + agent_net + agent_common + ["--report", str(logs / f"agent-{name}.json")],
                              logs / f"agent-{name}.log"))
    return children


def start(children: list[Child]) -> None:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    for child in children:
        log = open(child.log_path, "ab")
        try:
            child.proc = subprocess.Popen(child.cmd, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                          env=env, preexec_fn=_die_with_parent, close_fds=True)
        finally:
            log.close()


def stop_all(children: list[Child], first_signal: int = signal.SIGINT, grace: float = STOP_GRACE) -> None:
    """Signal every live child, wait up to ``grace`` s, then SIGKILL what is left and reap all."""
    for child in children:
        if child.poll() is None:
            try:
                child.proc.send_signal(first_signal)
            except ProcessLookupError:
                pass
    deadline = time.monotonic() + grace
    while time.monotonic() < deadline and any(c.poll() is None for c in children):
        time.sleep(0.02)
    for child in children:
        if child.poll() is None:
            child.proc.kill()
    for child in children:
        if child.proc is not None:
            child.proc.wait()


class StepCounter:
    """Counts complete lines of the step log as it grows."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.offset = 0
        self.count = 0

    def update(self) -> int:
        try:
            with open(self.path, "rb") as fh:
                fh.seek(self.offset)
                chunk = fh.read()
        except FileNotFoundError:
            return self.count
        complete = chunk.rfind(b"\n") + 1
        self.count += chunk[:complete].count(b"\n")
        self.offset += complete
        return self.count


def tail(path: Path, lines: int = 5) -> str:
    try:
        text = path.read_text(errors="replace").strip().splitlines()
    except FileNotFoundError:
        return ""
    return "\n".join("    " + line for line in text[-lines:])


def launch(prepared: Prepared, out: Path, run_id: str, startup_timeout: float = 30.0, show_progress: bool = True,
           extra_args: list[str] | None = None, tls_dir: Path | None = None, secure: bool = False,
           topology: str = "mesh") -> LaunchResult:
    """Run the plant and M agents as processes; returns when all have exited.

    ``tls_dir`` runs every link over TLS with that certificate directory; ``secure`` first
    makes one in ``out/tls`` (certificates and access control bound to ``run_id``).
    """
    scenario_path, design_path = prepare_run_folder(out, prepared)
    if secure:
        from dmpc.security.certs import make_run_security

        tls_dir = out / "tls"
        make_run_security(tls_dir, prepared.system, run_id=run_id)
    children = child_commands(prepared, out, scenario_path, design_path, run_id, free_port(), startup_timeout,
                              extra_args, tls_dir, topology)
    progress = None
    try:
        start(children)
        write_json(out / "processes.json", {c.role: c.pid for c in children})
        counter = StepCounter(out / STEP_LOG)
        if show_progress:
            progress = Progress(TextColumn("[bold]steps"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                                console=stderr_console(), transient=True)
            task = progress.add_task("run", total=prepared.protocol.steps)
            progress.start()
        plant = children[0]
        while True:
            done = counter.update()
            if progress is not None:
                progress.update(task, completed=done)
            failed = {c.role: c.poll() for c in children if c.poll() not in (None, 0)}
            if failed:
                stop_all(children)
                return _result(children, out, failed)
            if plant.poll() == 0:
                # the plant finished and sent Stop: give the agents a moment to exit on their own
                if _still_running_after(children, 5.0):
                    stop_all(children)
                failed = {c.role: c.poll() for c in children if c.poll() not in (None, 0)}
                return _result(children, out, failed)
            time.sleep(0.05)
    except KeyboardInterrupt:
        stop_all(children)
        result = _result(children, out, {})
        return LaunchResult(130, "interrupted: every process stopped; completed steps are in the run folder",
                            result.summary)
    finally:
        if progress is not None:
            progress.stop()
        if any(c.poll() is None for c in children):
            stop_all(children, signal.SIGTERM)


def _still_running_after(children: list[Child], timeout: float) -> bool:
    """True if some child is still running after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if all(c.poll() is not None for c in children):
            return False
        time.sleep(0.02)
    return True


def merge_agent_reports(out: Path, children: list[Child]) -> dict | None:
    """Add each agent's report (``logs/agent-<name>.json``) to ``summary.json`` as ``agents``.

    The plant writes the summary before the agents exit; their drop counts are known only to
    them. Returns the summary, or None if the plant wrote none.
    """
    try:
        summary = json.loads((out / "summary.json").read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None
    agents = {}
    for child in children:
        if not child.role.startswith("agent-"):
            continue
        try:
            report = json.loads((out / "logs" / f"{child.role}.json").read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            continue  # killed before it could write one
        if isinstance(report, dict):
            agents[child.role[len("agent-"):]] = {k: v for k, v in report.items() if k not in ("agent", "run_id")}
    if agents:
        summary["agents"] = agents
        write_json(out / "summary.json", summary)
    return summary


def _result(children: list[Child], out: Path, failed: dict[str, int]) -> LaunchResult:
    summary = merge_agent_reports(out, children)
    if not failed:
        return LaunchResult(0, "finished", summary)
    lines = []
    for child in children:
        if child.role in failed:
            lines.append(f"{child.role} exited with code {failed[child.role]} (log {child.log_path}):\n{tail(child.log_path)}")
    return LaunchResult(1, "\n".join(lines), summary, failed)

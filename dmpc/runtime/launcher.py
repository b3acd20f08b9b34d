"""``dmpc run``: the plant and every agent as separate processes on this machine.

The launcher opens no Zenoh session itself. It designs once, writes the resolved scenario and
the design into the run folder (every child loads those, so all agree), starts the children
with a private loopback port and multicast off, shows progress from the step log, and makes
sure no child outlives it: children get SIGTERM when the launcher dies (PR_SET_PDEATHSIG),
and on Ctrl-C or a failed child every process is stopped within a few seconds.
"""
from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from dmpc.console import stderr_console
from dmpc.exit_codes import EXIT_INTERRUPTED
from dmpc.records.agent_reports import merge_agent_reports as merge_reports
from dmpc.records.run_folder import STEP_LOG, RunFolderError, claim_folder, write_error, write_json
from dmpc.runtime.bundle import write_bundle
from dmpc.runtime.logpump import LogPump
from dmpc.runtime.supervisor import RestartPolicy, Supervision, Supervisor, restart_note
from dmpc.runtime.setup import Prepared
from dmpc.scenario import dump_resolved

STOP_GRACE = 3.0
PORT_ATTEMPTS = 5
"""Launches tried when the plant's port is taken before the plant could bind it."""
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
    """A port free on 127.0.0.1 now, outside the kernel's ephemeral range.

    The plant binds it a second or so later. A port from the ephemeral range could meanwhile be
    handed to any process that binds port 0 (the agents of a concurrent run do), so the port is
    drawn below that range, where only another explicit choice can take it; the launcher
    retries such a clash with a new port.
    """
    import random
    import socket

    low, high = _ephemeral_range()
    candidates = range(10000, low) if low > 11000 else range(high + 1, 65536)
    rng = random.SystemRandom()
    for _ in range(100):
        port = rng.choice(candidates)
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _ephemeral_range() -> tuple[int, int]:
    try:
        low, high = (int(v) for v in Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
        return low, high
    except (OSError, ValueError):
        return 32768, 60999


def prepare_run_folder(out: Path, prepared: Prepared) -> tuple[Path, Path]:
    """Write the resolved scenario and the design the children load; returns their paths."""
    claim_folder(out, STEP_LOG, "a run")
    scenario_path = out / "scenario.yaml"
    design_path = out / "design.json"
    target = scenario_path
    try:
        scenario_path.write_text(dump_resolved(prepared.scenario))
        target = design_path
        write_json(design_path, prepared.design_json())
        target = out / BUNDLE
        write_bundle(prepared, out / BUNDLE)
        target = out / "logs"
        target.mkdir(exist_ok=True)
    except OSError as exc:
        raise write_error(exc, target, RunFolderError) from None
    return scenario_path, design_path


STAR_ABOVE = 64  # beyond this many agents a full peer mesh overloads a small machine (liveliness leases expire)
TOPOLOGIES = ("mesh", "star")


def default_topology(agents: int) -> str:
    """``mesh`` up to ``STAR_ABOVE`` agents, ``star`` above."""
    return "mesh" if agents <= STAR_ABOVE else "star"


def child_commands(prepared: Prepared, out: Path, scenario_path: Path, design_path: Path, run_id: str, port: int,
                   startup_timeout: float, extra: list[str] | None = None, tls_dir: Path | None = None,
                   topology: str = "mesh", plant_model: str | None = None) -> list[Child]:
    """The plant and agent command lines (``python -m dmpc.cli ...``); ``tls_dir``: every link
    over TLS with the certificates (and access control) of that directory.

    ``mesh``: every process a peer, agents linked directly to each other (lowest latency for
    small M). ``star``: the plant's session is a router and agents are its clients, so there are
    M links instead of M^2/2 and agent-to-agent plans are forwarded by the plant's router.
    ``plant_model`` (``module:function``) is the plant process's ``--model``.
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
                                       "--quiet"] + (["--mode", "router"] if star else [])
                      + (["--model", plant_model] if plant_model else []) + common,
                      logs / "plant.log")]
    agent_net = ["--mode", "client"] if star else ["--listen", f"{proto}/127.0.0.1:0"]
    agent_common = [arg for arg in common if arg not in ("--design", str(design_path))]
    for name in prepared.names:
        children.append(Child(f"agent-{name}", base + ["agent", str(out / BUNDLE), "--id", name, "--connect", endpoint]
                              + agent_net + agent_common + ["--report", str(logs / f"agent-{name}.json")],
                              logs / f"agent-{name}.log"))
    return children


def start(children: list[Child], pump: LogPump | None = None) -> None:
    """Start the children; their output goes to their log files, through ``pump`` if given."""
    for child in children:
        spawn(child, pump)


def spawn(child: Child, pump: LogPump | None = None) -> None:
    """Start (or restart) one child, its SIGTERM tied to this process's end."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    if pump is None:
        log = open(child.log_path, "ab")
        try:
            child.proc = subprocess.Popen(child.cmd, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                          env=env, preexec_fn=_die_with_parent, close_fds=True)
        finally:
            log.close()
        return
    read_end, write_end = os.pipe()
    try:
        child.proc = subprocess.Popen(child.cmd, stdin=subprocess.DEVNULL, stdout=write_end, stderr=subprocess.STDOUT,
                                      env=env, preexec_fn=_die_with_parent, close_fds=True)
    except BaseException:
        os.close(read_end)
        raise
    finally:
        os.close(write_end)
    pump.add(child.role, read_end, child.log_path)


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
           topology: str = "mesh", on_ready=None, plant_model: str | None = None,
           policy: RestartPolicy | None = None) -> LaunchResult:
    """Run the plant and M agents as processes; returns when all have exited.

    ``tls_dir`` runs every link over TLS with that certificate directory; ``secure`` first
    makes one in ``out/tls`` (certificates and access control bound to ``run_id``).
    ``on_ready(out, run_id, endpoint, tls_dir)`` is called when the run folder is ready and
    before any process starts (``dmpc run --watch`` starts its observer there), and again with
    the new endpoint if the plant's port was taken and the run starts again on another.
    """
    scenario_path, design_path = prepare_run_folder(out, prepared)
    if secure:
        from dmpc.security.certs import make_run_security

        tls_dir = out / "tls"
        make_run_security(tls_dir, prepared.system, run_id=run_id)
    policy = policy or RestartPolicy()
    if show_progress:
        agents = len(prepared.names)
        stderr_console().print(f"starting {agents + 1} processes: the plant and {agents} agents "
                               f"({topology}{', TLS' if tls_dir is not None else ''}); logs in {out / 'logs'}")
    for attempt in range(PORT_ATTEMPTS):
        port = free_port()
        children = child_commands(prepared, out, scenario_path, design_path, run_id, port, startup_timeout,
                                  extra_args, tls_dir, topology, plant_model)
        if on_ready is not None:
            on_ready(out, run_id, f"{'tcp' if tls_dir is None else 'tls'}/127.0.0.1:{port}", tls_dir)
        result = _supervise(children, prepared, out, show_progress, policy)
        if not _port_clash(result, out) or attempt == PORT_ATTEMPTS - 1:
            return result
        if show_progress:
            stderr_console().print(f"port {port} was taken before the plant could bind it: starting again on another")
    return result


def _port_clash(result: LaunchResult, out: Path) -> bool:
    """True if the plant failed to bind its port before any step was recorded."""
    return ("plant" in result.failed and "Address already in use" in result.message
            and StepCounter(out / STEP_LOG).update() == 0)


def _supervise(children: list[Child], prepared: Prepared, out: Path, show_progress: bool,
               policy: RestartPolicy) -> LaunchResult:
    """Start the children, watch them to the end (:mod:`dmpc.runtime.supervisor`), stop them all."""
    pump = LogPump()
    progress = None
    supervisor = None
    try:
        start(children, pump)
        write_json(out / "processes.json", {c.role: c.pid for c in children})
        counter = StepCounter(out / STEP_LOG)
        if show_progress:
            progress = Progress(TextColumn("[bold]steps"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                                console=stderr_console(), transient=True)
            task = progress.add_task("run", total=prepared.protocol.steps)
            progress.start()

        def tick() -> None:
            done = counter.update()
            if progress is not None:
                progress.update(task, completed=done)

        def respawn(child: Child) -> None:
            spawn(child, pump)
            write_json(out / "processes.json", {c.role: c.pid for c in children})

        supervisor = Supervisor(children, respawn, policy, on_tick=tick)
        ending = supervisor.run()
        stop_all(children)
        return _result(children, out, ending.failed, pump, supervisor.record, ending.message)
    except KeyboardInterrupt:
        stop_all(children)
        result = _result(children, out, {}, pump, supervisor.record if supervisor is not None else None)
        return LaunchResult(EXIT_INTERRUPTED, "interrupted: every process stopped; completed steps are in the run "
                                              "folder", result.summary)
    finally:
        if progress is not None:
            progress.stop()
        if any(c.poll() is None for c in children):
            stop_all(children, signal.SIGTERM)
        pump.close()


def security_entry(children: list[Child]) -> dict | None:
    """How the run's links were secured, read from the plant's command line (None: plain TCP).

    Every child gets the same ``--tls DIR``; its ``acl.json``, if there, is the access control.
    """
    cmd = children[0].cmd if children else []
    if "--tls" not in cmd:
        return None
    tls_dir = Path(cmd[cmd.index("--tls") + 1])
    return {"tls": True, "mutual_authentication": True, "access_control": (tls_dir / "acl.json").is_file(),
            "certificates": str(tls_dir)}


def merge_agent_reports(out: Path, children: list[Child], record: Supervision | None = None) -> dict | None:
    """Add the agents' reports to ``summary.json`` (see :mod:`dmpc.records.agent_reports`), and
    what the launcher knows: for a run over TLS :func:`security_entry` as ``security``, and with
    ``record`` the agents restarted and lost as ``launcher``. None if the plant wrote no summary.
    """
    names = [c.role[len("agent-"):] for c in children if c.role.startswith("agent-")]
    extra = {}
    security = security_entry(children)
    if security is not None:
        extra["security"] = security
    if record is not None:
        extra["launcher"] = record.to_json()
    return merge_reports(out, names, extra)


def _result(children: list[Child], out: Path, failed: dict[str, int], pump: LogPump | None = None,
            record: Supervision | None = None, message: str = "") -> LaunchResult:
    summary = merge_agent_reports(out, children, record)
    if not failed:
        note = restart_note(record) if record is not None else ""
        return LaunchResult(0, f"finished ({note})" if note else "finished", summary)
    lines = [message] if message else []
    for child in children:
        if child.role in failed:
            said = "\n".join("    " + line for line in pump.tail(child.role)) if pump is not None else tail(child.log_path)
            broken = pump.log_failed(child.role) if pump is not None else ""
            where = f"log {child.log_path}" + (f", which could not be written: {broken}" if broken else "")
            lines.append(f"{child.role} exited with code {failed[child.role]} ({where}):\n{said}")
    return LaunchResult(1, "\n".join(lines), summary, failed)

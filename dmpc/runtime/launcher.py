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

from dmpc.bus import keys
from dmpc.prepared import Prepared
from dmpc.prepared.bundle import write_bundle
from dmpc.records.agent_reports import merge_agent_reports as merge_reports
from dmpc.records.files import BUNDLE, DESIGN, LOGS, PROCESSES, SCENARIO, STEP_LOG, TLS, log_file, report_file
from dmpc.records.run_folder import RunFolderError, claim_folder, write_error, write_json
from dmpc.runtime.forkserver import ForkedProcess, ForkServer, ForkServerError
from dmpc.runtime.hosting import HOST_PREFIX, group_agents
from dmpc.runtime.logpump import LogPump
from dmpc.runtime.output import LOG_ENV
from dmpc.runtime.supervisor import RestartPolicy, Supervision, Supervisor, restart_note
from dmpc.scenario import dump_resolved
from dmpc.security.acl import ACL_FILE
from dmpc.terminal.console import stderr_console
from dmpc.terminal.exit_codes import EXIT_ADDRESS_IN_USE, EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK
from dmpc.terminal.progress import ProgressBar
from dmpc.terminal.signals import interrupts_deferred, interrupts_held, raise_if_interrupted

STOP_GRACE = 3.0
DMPC = (sys.executable, "-m", "dmpc.cli")
PORT_ATTEMPTS = 5
"""Launches tried when the plant's port is taken before the plant could bind it."""
PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:  # runs in the child between fork and exec
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


@dataclass
class Child:
    """A process of the run; ``agents``: the subsystems it serves (none for the plant).

    Attributes
    ----------
    role : str
        ``plant``, or the agent process's role.
    cmd : list of str
        Its command line.
    log_path : path
        Where its output goes.
    proc : Popen or ForkedProcess or None
        The process, once started.
    agents : tuple of str"""

    role: str
    cmd: list[str]
    log_path: Path
    proc: subprocess.Popen | ForkedProcess | None = None
    agents: tuple[str, ...] = ()

    @property
    def pid(self) -> int:
        return self.proc.pid if self.proc else -1

    def poll(self) -> int | None:
        return self.proc.poll() if self.proc else None

    @property
    def running(self) -> bool:
        """Started and not yet exited (a child not started yet is not running)."""
        return self.proc is not None and self.proc.poll() is None


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
    """Write the resolved scenario and the design the children load into the run folder ``out``, from
    the ``prepared`` run; returns their paths."""
    claim_folder(out, STEP_LOG, "a run")
    scenario_path = out / SCENARIO
    design_path = out / DESIGN
    target = scenario_path
    if prepared.scenario is None:
        raise ValueError("a run folder is prepared from a scenario, not from a run bundle")
    try:
        scenario_path.write_text(dump_resolved(prepared.scenario))
        target = design_path
        write_json(design_path, prepared.design_json())
        target = out / BUNDLE
        write_bundle(prepared, out / BUNDLE)
        target = out / LOGS
        target.mkdir(exist_ok=True)
    except OSError as exc:
        raise write_error(exc, target, RunFolderError) from None
    return scenario_path, design_path


STAR_ABOVE = 64  # beyond this many agents a full peer mesh overloads a small machine (liveliness leases expire)
TOPOLOGIES = ("mesh", "star")


def default_topology(agents: int) -> str:
    """``mesh`` up to ``STAR_ABOVE`` agent processes (``agents``), ``star`` above."""
    return "mesh" if agents <= STAR_ABOVE else "star"


def child_commands(prepared: Prepared, out: Path, scenario_path: Path, design_path: Path, run_id: str, port: int,
                   startup_timeout: float, extra: list[str] | None = None, tls_dir: Path | None = None,
                   topology: str = "mesh", plant_model: str | None = None,
                   plant_timeout: float | None = None, agents_per_process: int = 1) -> list[Child]:
    """The plant and agent command lines (``python -m dmpc.cli ...``) of the ``prepared`` run in the
    folder ``out``, loading ``scenario_path`` and ``design_path``, with id ``run_id``, the plant
    listening on ``port``, each waiting ``startup_timeout`` seconds to start, and ``extra``
    arguments for every child; ``tls_dir``: every link over TLS with the certificates (and access
    control) of that directory.

    With ``plant_timeout`` (an outside plant, ``dmpc run --plant external``) the first child is
    ``dmpc coordinator --plant external`` instead of ``dmpc plant``.

    ``topology``: ``mesh``, every process a peer, agents linked directly to each other (lowest
    latency for small M). ``star``: the plant's session is a router and agents are its clients, so there are
    M links instead of M^2/2 and agent-to-agent plans are forwarded by the plant's router.
    ``plant_model`` (``module:function``) is the plant process's ``--model``.
    ``agents_per_process``: K agents (at most) served by each agent process
    (:mod:`dmpc.runtime.hosting`).
    """
    base = list(DMPC)
    proto = "tcp" if tls_dir is None else "tls"
    endpoint = f"{proto}/127.0.0.1:{port}"
    common = ["--design", str(design_path), "--run-id", run_id, "--startup-timeout", str(startup_timeout),
              "--no-multicast"] + (extra or []) + ([] if tls_dir is None else ["--tls", str(tls_dir)])
    logs = out / LOGS
    logs.mkdir(exist_ok=True)
    star = topology == "star"
    if plant_timeout is None:
        role, command = keys.PLANT_ROLE, ["plant"] + (["--model", plant_model] if plant_model else [])
    else:
        role, command = keys.COORDINATOR_ROLE, ["coordinator", "--plant", "external", "--plant-timeout", str(plant_timeout)]
    children = [Child(role, base + command + [str(scenario_path), "--out", str(out), "--listen", endpoint, "--quiet"]
                      + (["--mode", "router"] if star else []) + common, logs / log_file(role))]
    agent_net = ["--mode", "client"] if star else ["--listen", f"{proto}/127.0.0.1:0"]
    agent_common = [arg for arg in common if arg not in ("--design", str(design_path))]
    for host in group_agents(prepared.names, agents_per_process):
        ids = [arg for name in host.agents for arg in ("--id", name)]
        report = logs / report_file(keys.agent_role(host.agents[0] if len(host.agents) == 1 else "{id}"))
        children.append(Child(host.role, base + ["agent", str(out / BUNDLE), *ids, "--connect", endpoint]
                              + agent_net + agent_common + ["--report", str(report)],
                              logs / log_file(host.role), agents=host.agents))
    return children


def start(children: list[Child], pump: LogPump | None = None, forks: ForkServer | None = None) -> None:
    """Start the children; their output goes to their log files, through ``pump`` if given.
    Agent processes are forked by ``forks`` all at once when given (exec where that fails)."""
    if forks is not None and pump is not None:
        _fork_all([c for c in children if _forkable(c)], pump, forks)
    for child in children:
        if child.proc is None:
            spawn(child, pump)


def _forkable(child: Child) -> bool:
    return bool(child.agents) and tuple(child.cmd[:3]) == DMPC


def _fork_all(children: list[Child], pump: LogPump, forks: ForkServer) -> None:
    pipes = [os.pipe() for _ in children]
    pumped = set()
    try:
        try:
            forked = forks.spawn_all([(c.cmd[3:], write_end, str(c.log_path))
                                      for c, (_, write_end) in zip(children, pipes)])
        except ForkServerError:
            forked = [None] * len(children)
        for child, proc, (read_end, _) in zip(children, forked, pipes):
            if proc is not None:
                child.proc = proc
                pump.add(child.role, read_end, child.log_path)
                pumped.add(read_end)
    finally:  # also when interrupted mid-burst (the fork server stops the agents it forked meanwhile)
        for read_end, write_end in pipes:
            os.close(write_end)
            if read_end not in pumped:
                os.close(read_end)


def child_env() -> dict:
    return dict(os.environ, PYTHONUNBUFFERED="1")


def spawn(child: Child, pump: LogPump | None = None, forks: ForkServer | None = None) -> None:
    """Start (or restart) one child, its SIGTERM tied to this process's end, its output read by
    ``pump`` (None: straight to its log file); an agent process is forked by ``forks``
    (:mod:`dmpc.runtime.forkserver`) when given and working."""
    if forks is not None and pump is not None and _forkable(child) and forks.alive:
        read_end, write_end = os.pipe()
        try:
            child.proc = forks.spawn(child.cmd[3:], write_end, str(child.log_path))
        except ForkServerError:
            os.close(read_end)  # started with exec below
        else:
            pump.add(child.role, read_end, child.log_path)
            return
        finally:
            os.close(write_end)
    env = child_env()
    if pump is None:
        log = open(child.log_path, "ab")
        try:
            with interrupts_deferred():
                child.proc = subprocess.Popen(child.cmd, stdin=subprocess.DEVNULL, stdout=log,
                                              stderr=subprocess.STDOUT, env=env, preexec_fn=_die_with_parent,
                                              close_fds=True)
        finally:
            log.close()
        return
    read_end, write_end = os.pipe()
    env[LOG_ENV] = str(child.log_path)  # where its output goes should this process die (dmpc.runtime.output)
    try:
        with interrupts_deferred():
            try:
                child.proc = subprocess.Popen(child.cmd, stdin=subprocess.DEVNULL, stdout=write_end,
                                              stderr=subprocess.STDOUT, env=env, preexec_fn=_die_with_parent,
                                              close_fds=True)
            except BaseException:
                os.close(read_end)
                raise
            pump.add(child.role, read_end, child.log_path)
    finally:
        os.close(write_end)


def stop_all(children: list[Child], first_signal: int = signal.SIGINT, grace: float = STOP_GRACE) -> None:
    """Send ``first_signal`` to every live child, wait up to ``grace`` s, then SIGKILL what is left and reap all
    (children not started yet are skipped: start-up may have been interrupted before them)."""
    for child in children:
        proc = child.proc
        if proc is not None and proc.poll() is None:  # child.running
            try:
                proc.send_signal(first_signal)
            except ProcessLookupError:
                pass
    deadline = time.monotonic() + grace
    while time.monotonic() < deadline and any(c.running for c in children):
        time.sleep(0.02)
    for child in children:
        proc = child.proc
        if proc is not None and proc.poll() is None:  # child.running
            try:
                proc.kill()
            except ProcessLookupError:
                pass
    for child in children:
        if child.proc is not None:
            child.proc.wait()


class StepCounter:
    """Counts complete lines of the step log ``path`` as it grows."""

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
    """The last ``lines`` lines of the file ``path``, indented ("" when it does not exist)."""
    try:
        text = path.read_text(errors="replace").strip().splitlines()
    except FileNotFoundError:
        return ""
    return "\n".join("    " + line for line in text[-lines:])


def launch(prepared: Prepared, out: Path, run_id: str, startup_timeout: float = 30.0, show_progress: bool = True,
           extra_args: list[str] | None = None, tls_dir: Path | None = None, secure: bool = False,
           topology: str = "mesh", on_ready=None, plant_model: str | None = None,
           policy: RestartPolicy | None = None, plant_timeout: float | None = None,
           port: int | None = None, agents_per_process: int = 1) -> LaunchResult:
    """Run the plant and M agents of the ``prepared`` run as processes, each waiting at most
    ``startup_timeout`` seconds for the run to start; returns when all have exited.
    ``show_progress``: a progress bar on the terminal; ``extra_args``: more arguments for every
    child; ``topology``: ``mesh`` or ``star`` (:func:`child_commands`); ``plant_model``: the plant
    process's ``--model``; ``policy``: when agent processes are restarted (the default
    :class:`~dmpc.runtime.supervisor.RestartPolicy` without).

    ``tls_dir`` runs every link over TLS with that certificate directory; ``secure`` first
    makes one in ``out/tls`` (certificates and access control bound to ``run_id``).
    ``on_ready(out, run_id, endpoint, tls_dir)`` is called when the run folder is ready and
    before any process starts (``dmpc run --watch`` starts its observer there), and again with
    the new endpoint if the plant's port was taken and the run starts again on another.

    ``plant_timeout`` starts the coordinator without a plant and waits for an outside one
    (docs/protocol.md); ``port`` fixes the local port the coordinator listens on (default: a
    free one, chosen again if it is taken meanwhile).

    ``agents_per_process``: each agent process serves up to this many agents
    (:mod:`dmpc.runtime.hosting`); a restart or a crash concerns the whole process.
    """
    scenario_path, design_path = prepare_run_folder(out, prepared)
    if secure:
        from dmpc.security.certs import make_run_security  # start-up time: cryptography only for --secure

        tls_dir = out / TLS
        make_run_security(tls_dir, prepared.system, run_id=run_id)
    policy = policy or RestartPolicy()
    if show_progress:
        agents = len(prepared.names)
        hosts = len(group_agents(prepared.names, agents_per_process))
        head = "the plant" if plant_timeout is None else "the coordinator (the plant is outside)"
        served = f"{agents} agents" if hosts == agents else f"{agents} agents in {hosts} processes"
        stderr_console().print(f"starting {hosts + 1} processes: {head} and {served} "
                               f"({topology}{', TLS' if tls_dir is not None else ''}); logs in {out / LOGS}")
    fixed = port
    for attempt in range(1 if fixed is not None else PORT_ATTEMPTS):
        raise_if_interrupted()  # one that Python dropped during the design or the run folder
        port = fixed if fixed is not None else free_port()
        children = child_commands(prepared, out, scenario_path, design_path, run_id, port, startup_timeout,
                                  extra_args, tls_dir, topology, plant_model, plant_timeout, agents_per_process)
        endpoint = f"{'tcp' if tls_dir is None else 'tls'}/127.0.0.1:{port}"
        if on_ready is not None:
            on_ready(out, run_id, endpoint, tls_dir)
        if plant_timeout is not None:
            stderr_console().print(f"waiting for the plant: connect it to {endpoint} with run id {run_id} "
                                   f"(docs/protocol.md)")
        elif show_progress:
            stderr_console().print(f"run id {run_id}: the coordinator listens on {endpoint} (dmpc setpoint, "
                                   "dmpc watch --connect)")
        result = _supervise(children, prepared, out, show_progress, policy)
        if fixed is not None or not _port_clash(result, children[0].role, out) or attempt == PORT_ATTEMPTS - 1:
            return result
        if show_progress:
            stderr_console().print(f"port {port} was taken before the plant could bind it: starting again on another")
    return result


def _port_clash(result: LaunchResult, head: str, out: Path) -> bool:
    """True if the process that listens (role ``head``) could not bind its port
    (``EXIT_ADDRESS_IN_USE``) before any step was recorded."""
    return result.failed.get(head) == EXIT_ADDRESS_IN_USE and StepCounter(out / STEP_LOG).update() == 0


def _supervise(children: list[Child], prepared: Prepared, out: Path, show_progress: bool,
               policy: RestartPolicy) -> LaunchResult:
    """Start the children, watch them to the end (:mod:`dmpc.runtime.supervisor`), stop them all."""
    pump = LogPump()
    progress = None
    supervisor = None
    forks = None
    launched_at = time.monotonic()
    try:
        head = [c for c in children if not c.agents]
        start(head, pump)  # the plant imports and loads while the fork server does
        raise_if_interrupted()
        forks = _fork_server(children[0].log_path.parent)
        raise_if_interrupted()
        start([c for c in children if c.agents], pump, forks)
        write_json(out / PROCESSES, {c.role: c.pid for c in children})
        counter = StepCounter(out / STEP_LOG)
        if show_progress:
            progress = ProgressBar("steps", prepared.protocol.steps)
            progress.start()

        def tick() -> None:
            raise_if_interrupted()
            done = counter.update()
            if progress is not None:
                progress.update(done)

        def respawn(child: Child) -> None:
            spawn(child, pump, forks)
            write_json(out / PROCESSES, {c.role: c.pid for c in children})

        supervisor = Supervisor(children, respawn, policy, on_tick=tick)
        ending = supervisor.run()
        stop_all(children)
        return _result(children, out, ending.failed, pump, supervisor.record, ending.message, launched_at)
    except KeyboardInterrupt:
        with interrupts_held():
            stop_all(children)
            result = _result(children, out, {}, pump, supervisor.record if supervisor is not None else None,
                             launched_at=launched_at)
        return LaunchResult(EXIT_INTERRUPTED, interrupted_message(StepCounter(out / STEP_LOG).update()),
                            result.summary)
    finally:
        with interrupts_held():
            if progress is not None:
                progress.stop()
            if any(c.running for c in children):
                stop_all(children, signal.SIGTERM)
            if forks is not None:
                forks.close()
            pump.close()


def interrupted_message(steps: int) -> str:
    """What an interrupted run says, after ``steps`` completed steps."""
    if steps == 0:
        return ("interrupted before the first step: every process stopped; no step was run (the run folder holds "
                "the design and the logs)")
    return (f"interrupted after {steps} step{'s' if steps != 1 else ''}: every process stopped; the completed steps "
            "are in the run folder")


def _fork_server(logs: Path) -> ForkServer | None:
    """A fork server for the agent processes, or None (they are then started with exec)."""
    try:
        return ForkServer(child_env(), logs / "forkserver.log")
    except (ForkServerError, OSError) as exc:
        stderr_console().print(f"agents started one by one with exec: {exc}")
        return None


def security_entry(children: list[Child]) -> dict | None:
    """How the run's links were secured, read from the plant's command line among ``children`` (None:
    plain TCP).

    Every child gets the same ``--tls DIR``; its ``acl.json``, if there, is the access control."""
    cmd = children[0].cmd if children else []
    if "--tls" not in cmd:
        return None
    tls_dir = Path(cmd[cmd.index("--tls") + 1])
    return {"tls": True, "mutual_authentication": True, "access_control": (tls_dir / ACL_FILE).is_file(),
            "certificates": str(tls_dir)}


def merge_agent_reports(out: Path, children: list[Child], record: Supervision | None = None,
                        launched_at: float | None = None) -> dict | None:
    """Add the agents' reports to ``summary.json`` in the run folder ``out`` (see
    :mod:`dmpc.records.agent_reports`; the processes: ``children``), and
    what the launcher knows: for a run over TLS :func:`security_entry` as ``security``, with
    ``record`` the agent processes restarted and lost as ``launcher``, and with ``launched_at``
    (when the processes were started) ``startup_s``. None if the plant wrote no summary.
    """
    names = [name for child in children for name in child.agents]
    extra = {}
    security = security_entry(children)
    if security is not None:
        extra["security"] = security
    if record is not None:
        extra["launcher"] = record.to_json()
        hosted = {c.role: list(c.agents) for c in children if c.role.startswith(HOST_PREFIX)}  # a lone agent too
        if hosted:
            extra["launcher"]["hosts"] = hosted
    return merge_reports(out, names, extra, launched_at)


def _result(children: list[Child], out: Path, failed: dict[str, int], pump: LogPump | None = None,
            record: Supervision | None = None, message: str = "", launched_at: float | None = None) -> LaunchResult:
    summary = merge_agent_reports(out, children, record, launched_at)
    if not failed:
        note = restart_note(record) if record is not None else ""
        return LaunchResult(EXIT_OK, f"finished ({note})" if note else "finished", summary)
    lines = [message] if message else []
    for child in children:
        if child.role in failed:
            said = "\n".join("    " + line for line in pump.tail(child.role)) if pump is not None else tail(child.log_path)
            broken = pump.log_failed(child.role) if pump is not None else ""
            where = f"log {child.log_path}" + (f", which could not be written: {broken}" if broken else "")
            lines.append(f"{child.role} exited with code {failed[child.role]} ({where}):\n{said}")
    return LaunchResult(EXIT_FAILED, "\n".join(lines), summary, failed)

"""The commands that are one process of a run over Zenoh: an agent (or several), the coordinator,
the plant, a router, a delaying relay; and the certificates that secure them."""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from dmpc.bus import keys
from dmpc.bus.faults import PLANT_PROCESS
from dmpc.cli.common import (
    ConnectOpt,
    DeadlineOpt,
    DelayOpt,
    DesignOpt,
    FaultFlags,
    InputError,
    JitterOpt,
    LeaseOpt,
    ListenOpt,
    LossOpt,
    ModelOpt,
    MulticastOpt,
    NodeFlags,
    PlantTimeoutOpt,
    QuietTableOpt,
    RunIdOpt,
    ScenarioArg,
    SeedOpt,
    ServerModeOpt,
    SetOpt,
    StartupOpt,
    StepsOpt,
    TlsOpt,
    ZenohConfigOpt,
    check_mode,
    checked_run_id,
    checked_side,
    listed,
    load_scenario_file,
    require_agents,
    role_security,
    with_faults,
    with_model,
)
from dmpc.records.run_folder import write_json
from dmpc.runtime.memory import settle_after_startup
from dmpc.terminal import signals
from dmpc.terminal.console import error_line
from dmpc.terminal.exit_codes import EXIT_FAILED, EXIT_INPUT, EXIT_INTERRUPTED


def _write_report(path: Path, report: dict) -> None:
    """Write an agent's JSON report; a failure to write is reported, not raised."""
    try:
        write_json(path, report)
    except OSError as exc:
        error_line(f"--report {path}: cannot write ({exc.strerror})")


def agent(scenario: ScenarioArg,
          id_: Annotated[list[str], typer.Option("--id", help="A subsystem this process controls (its name in the scenario); repeat it to serve several on one Zenoh session.", show_default=False)],
          connect: ConnectOpt = None, listen: ListenOpt = None,
          mode: Annotated[str, typer.Option("--mode", help="Zenoh mode: peer or client.")] = "peer",
          run_id: RunIdOpt = None, design_file: DesignOpt = None, startup_timeout: StartupOpt = 30.0,
          multicast: MulticastOpt = False, lease: LeaseOpt = None, zenoh_config: ZenohConfigOpt = None,
          tls: TlsOpt = None, delay: DelayOpt = None, jitter: JitterOpt = None, loss: LossOpt = None, seed: SeedOpt = None,
          deadline: DeadlineOpt = None, set_: SetOpt = None,
          report: Annotated[Optional[Path], typer.Option("--report", help="Write a JSON report here at exit: invalid messages dropped per sender and reason, duplicates, solves. With several --id, the path must contain {id}, replaced by each agent's name.")] = None) -> None:
    """Run subsystems' agents on the Zenoh bus until the plant stops the run: one --id, or several
    served by this one process on one session."""
    from dmpc.agents.process import process_exit_code, run_agents  # start-up time: osqp only for agents

    if mode not in ("peer", "client"):
        raise InputError(f"--mode: expected peer or client, got {mode!r}")
    ids = list(dict.fromkeys(id_))
    if len(ids) < len(id_):
        raise InputError(f"--id: {next(i for i in ids if id_.count(i) > 1)!r} is given more than once")
    if len(ids) > 1 and tls is not None:
        raise InputError("--tls: a certificate belongs to one agent, so a process serving several agents cannot "
                         "use TLS; give one --id per process with --tls")
    if len(ids) > 1 and report is not None and "{id}" not in str(report):
        raise InputError(f"--report {report}: with several --id the path must contain {{id}}, e.g. "
                         "logs/agent-{id}.json")
    signals.sigterm_as_interrupt()
    flags = NodeFlags(connect, listen, mode, run_id, design_file, startup_timeout, None, multicast, lease, zenoh_config,
                      tls, FaultFlags(delay, jitter, loss, seed, deadline), set_)
    prepared = flags.prepare(scenario)
    require_agents(prepared, "agent")
    unknown = [i for i in ids if i not in prepared.names]
    if unknown:
        raise InputError(f"--id: no subsystem {unknown[0]!r} in the scenario (subsystems: "
                         f"{listed(prepared.names)})")
    rid = checked_run_id(run_id, prepared)
    bus = flags.open_bus(keys.agent_role(ids[0]), shared=len(ids) > 1)
    bus_for = None if prepared.faults.is_clean else (lambda name: with_faults(bus, prepared, name))
    settle_after_startup()
    try:
        outcomes = run_agents(prepared, ids, bus, rid, startup_timeout, bus_for)
    except KeyboardInterrupt:
        raise typer.Exit(EXIT_INTERRUPTED) from None
    finally:
        bus.close()
    for name, outcome in zip(ids, outcomes):
        if report is not None:
            _write_report(Path(str(report).replace("{id}", name)),
                          {"agent": name, "run_id": rid, "exit_code": outcome.code, **outcome.report})
        if outcome.code == 0:
            print(outcome.message)
        else:
            error_line(outcome.message)
    raise typer.Exit(process_exit_code(outcomes))


def coordinator(scenario: ScenarioArg,
                out: Annotated[Path, typer.Option("--out", help="Run folder to write (created).")],
                plant_side: Annotated[str, typer.Option("--plant", help="internal: simulate the plant in this process (as 'dmpc plant' does); external: wait for a plant on the bus ('dmpc plant --coordinator external', or your own program: docs/protocol.md).")] = "internal",
                plant_timeout: PlantTimeoutOpt = 10.0,
                connect: ConnectOpt = None, listen: ListenOpt = None,
                mode: ServerModeOpt = "peer",
                run_id: RunIdOpt = None, design_file: DesignOpt = None, startup_timeout: StartupOpt = 30.0,
                steps: StepsOpt = None,
                multicast: MulticastOpt = False, lease: LeaseOpt = None, zenoh_config: ZenohConfigOpt = None,
                quiet: QuietTableOpt = False,
                tls: TlsOpt = None, delay: DelayOpt = None, jitter: JitterOpt = None, loss: LossOpt = None,
                seed: SeedOpt = None, deadline: DeadlineOpt = None, set_: SetOpt = None, model: ModelOpt = None) -> None:
    """Run the step barrier: wait for every agent (and an outside plant), step, record."""
    checked_side(plant_side, "--plant")
    if plant_side == "external" and model is not None:
        raise InputError("--model: the plant is outside this process (--plant external): give the model to it")
    flags = NodeFlags(connect, listen, mode, run_id, design_file, startup_timeout, steps, multicast, lease, zenoh_config,
                      tls, FaultFlags(delay, jitter, loss, seed, deadline), set_, model)
    _host_coordinator(scenario, out, flags, plant_side, plant_timeout, quiet)


def plant(scenario: ScenarioArg,
          out: Annotated[Optional[Path], typer.Option("--out", help="Run folder to write (created); needed when this process hosts the coordinator.")] = None,
          coordinator_side: Annotated[str, typer.Option("--coordinator", help="internal (default): host the coordinator too, one process for both; external: be the plant alone, for a 'dmpc coordinator --plant external'.")] = "internal",
          sensor: Annotated[Optional[list[str]], typer.Option("--sensor", help="With --coordinator external: report only this subsystem's state, as its own sensor (repeatable).", show_default=False)] = None,
          outputs: Annotated[bool, typer.Option("--outputs", help="With --coordinator external and a scenario with estimation: report the measured outputs y_i = C_i x_i of the subsystems whose C is not the identity in place of their states, as their sensors would.")] = False,
          connect: ConnectOpt = None, listen: ListenOpt = None,
          mode: ServerModeOpt = "peer",
          run_id: RunIdOpt = None, design_file: DesignOpt = None, startup_timeout: StartupOpt = 30.0,
          steps: StepsOpt = None,
          multicast: MulticastOpt = False, lease: LeaseOpt = None, zenoh_config: ZenohConfigOpt = None,
          quiet: QuietTableOpt = False,
          tls: TlsOpt = None, delay: DelayOpt = None, jitter: JitterOpt = None, loss: LossOpt = None, seed: SeedOpt = None,
          deadline: DeadlineOpt = None, set_: SetOpt = None, model: ModelOpt = None) -> None:
    """Run the plant: by default with the step barrier in the same process (wait for every agent,
    step, record); with --coordinator external, the plant alone on the bus."""
    flags = NodeFlags(connect, listen, mode, run_id, design_file, startup_timeout, steps, multicast, lease, zenoh_config,
                      tls, FaultFlags(delay, jitter, loss, seed, deadline), set_, model)
    if checked_side(coordinator_side, "--coordinator") == "internal":
        if sensor or outputs:
            raise InputError(f"{'--sensor' if sensor else '--outputs'}: only with --coordinator external (a process "
                             "that hosts the coordinator measures every subsystem itself)")
        if out is None:
            raise InputError("--out: a run folder is needed when this process hosts the coordinator "
                             "(or pass --coordinator external to be the plant alone)")
        _host_coordinator(scenario, out, flags, "internal", 10.0, quiet, command="plant")
        return
    if out is not None:
        raise InputError("--out: the plant alone writes no run folder (the coordinator does)")
    _serve_plant(scenario, sensor, flags, outputs)


def _host_coordinator(scenario: Path, out: Path, flags: NodeFlags, plant_side: str, plant_timeout: float, quiet: bool,
                      command: str = "coordinator") -> None:
    """The process that hosts the coordinator (and the simulated plant, if ``plant_side`` is internal)."""
    from dmpc.coordinator.process import run_coordinator  # start-up time: only for `dmpc plant`
    from dmpc.records.session import RunRecorder  # start-up time: it loads pydantic
    from dmpc.records.tables import print_summary  # start-up time: tables only where printed
    from dmpc.watch.telemetry import open_telemetry  # start-up time: only where the coordinator runs

    check_mode(flags.mode)
    signals.sigterm_as_interrupt()
    prepared = flags.prepare(scenario)
    require_agents(prepared, command)
    prepared = with_model(prepared, flags.model)
    rid = checked_run_id(flags.run_id, prepared)
    bus = with_faults(flags.open_bus(keys.COORDINATOR_ROLE), prepared, PLANT_PROCESS)
    settle_after_startup()
    try:
        sources = [path for path in (scenario, flags.design_file) if path is not None]
        with RunRecorder(out, prepared, show_progress=not quiet, sources=sources) as recorder:
            outcome = run_coordinator(prepared, recorder, bus, rid, flags.startup_timeout,
                                      external_plant=plant_side == "external", plant_timeout=plant_timeout,
                                      telemetry=open_telemetry(bus, rid, prepared))
    finally:
        bus.close()
    if not quiet and outcome.summary is not None:
        print_summary(outcome.summary, out)
    if outcome.code != 0:
        error_line(outcome.message)
    raise typer.Exit(outcome.code)


def _serve_plant(scenario: Path, sensors: list[str] | None, flags: NodeFlags, outputs: bool = False) -> None:
    """``dmpc plant --coordinator external``: the simulated plant (or some sensors) alone; with ``outputs``
    it reports the outputs of the subsystems that measure less than their state."""
    from dmpc.plant.process import run_plant_role  # start-up time: the plant role only for its command

    check_mode(flags.mode)
    signals.sigterm_as_interrupt()
    prepared = with_model(flags.prepare(scenario), flags.model)
    if sensors:
        unknown = [name for name in sensors if name not in prepared.names]
        if unknown:
            raise InputError(f"--sensor: no subsystem {', '.join(map(repr, unknown))} in the scenario "
                             f"(subsystems: {', '.join(prepared.names)})")
        if len(set(sensors)) != len(sensors):
            raise InputError("--sensor: a subsystem is named twice")
        if flags.tls is not None and len(sensors) > 1:
            raise InputError("--sensor: with --tls, one sensor per process (each has its own certificate)")
    if outputs and prepared.estimator is None:
        raise InputError("--outputs: the scenario has no 'estimation', so the coordinator needs every state "
                         "(add estimation, or leave --outputs out)")
    role = keys.PLANT_ROLE if not sensors else keys.sensor_role(sensors[0])
    rid = checked_run_id(flags.run_id, prepared)
    bus = flags.open_bus(role)
    try:
        outcome = run_plant_role(prepared, bus, rid, flags.startup_timeout, sensors=list(sensors) if sensors else None,
                                 outputs=outputs)
    finally:
        bus.close()
    if outcome.code != 0:
        error_line(outcome.message)
    else:
        print(outcome.message)
    raise typer.Exit(outcome.code)


def router(listen: ListenOpt = None,
           multicast: MulticastOpt = False, tls: TlsOpt = None) -> None:
    """Host a Zenoh router in this process (no external binary) until Ctrl-C."""
    import time

    from dmpc.bus.session import session_config  # start-up time: zenoh only for network commands

    signals.sigterm_as_interrupt()
    endpoints = list(listen or ["tls/0.0.0.0:7447" if tls else "tcp/0.0.0.0:7447"])
    tls_files, acl = role_security(tls, "router")
    try:
        config = session_config(mode="router", listen=endpoints, multicast=multicast, tls=tls_files, acl=acl)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    import zenoh

    try:
        session = zenoh.open(config)
    except Exception as exc:  # noqa: BLE001 - zenoh reports bind failures as a generic error
        error_line(f"router: cannot listen on {', '.join(endpoints)} ({exc})")
        raise typer.Exit(EXIT_FAILED) from None
    print(f"router listening on {', '.join(endpoints)} (Ctrl-C to stop)", flush=True)
    try:
        while True:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        session.close()


def relay(listen: Annotated[str, typer.Option("--listen", help="HOST:PORT to accept connections on, e.g. 0.0.0.0:7448.", show_default=False)],
          to: Annotated[str, typer.Option("--to", help="HOST:PORT to forward every connection to, e.g. the plant's or router's Zenoh port.", show_default=False)],
          delay: Annotated[float, typer.Option("--delay", min=0, help="Milliseconds every chunk is held, in each direction.", show_default=False)],
          jitter: Annotated[float, typer.Option("--jitter", min=0, help="Hold each chunk for delay ± MS (uniform; byte order is kept).")] = 0.0,
          seed: SeedOpt = None) -> None:
    """Relay TCP connections (e.g. Zenoh links) with a set delay, until Ctrl-C."""
    import time

    from dmpc.bus.relay import Relay, RelayError, format_address, parse_address  # start-up time: asyncio only here

    try:
        listen_at = parse_address(listen, listen=True)
    except ValueError as exc:
        raise InputError(f"--listen: {exc}") from None
    try:
        target = parse_address(to)
    except ValueError as exc:
        raise InputError(f"--to: {exc}") from None
    signals.sigterm_as_interrupt()
    server = Relay(listen_at, target, delay_ms=delay, jitter_ms=jitter, seed=seed)
    try:
        server.start()
    except RelayError as exc:
        error_line(f"relay: {exc}")
        raise typer.Exit(EXIT_FAILED) from None
    spread = f" ± {jitter:g}" if jitter else ""
    print(f"relay {format_address(server.address)} -> {format_address(target)}, delay {delay:g}{spread} ms "
          f"(Ctrl-C to stop)", flush=True)
    try:
        while server.running:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
    if server.error is not None:
        error_line(f"relay: stopped by an unexpected error ({server.error!r})")
        raise typer.Exit(EXIT_FAILED)
    s = server.stats
    print(f"relay stopped: {s.connections} connections ({s.failed} without target), {s.bytes} bytes, "
          f"at most {s.max_late_ms:.1f} ms later than the delay", flush=True)


def certs(directory: Annotated[Path, typer.Argument(help="Directory to write (created).", show_default=False)],
          scenario: Annotated[Path, typer.Option("--scenario", help="Scenario YAML: one certificate per agent, and its access control.")],
          host: Annotated[Optional[list[str]], typer.Option("--host", help="Another IP address or DNS name the processes are reached at (repeatable; 127.0.0.1 and localhost are always in).")] = None,
          run_id: Annotated[Optional[str], typer.Option("--run-id", help="Bind the access control to this run id (default: any run of the scenario).")] = None,
          days: Annotated[int, typer.Option("--days", min=1, help="Validity of the certificates in days.")] = 365,
          force: Annotated[bool, typer.Option("--force", help="Replace certificates already in DIRECTORY, and the CA key file.")] = False,
          ca_key: Annotated[Optional[Path], typer.Option("--ca-key", help="Where to write the CA's private key, mode 0600 (default: DIRECTORY-ca.key beside DIRECTORY, never inside it).", show_default=False)] = None,
          set_: SetOpt = None) -> None:
    """Make a CA, a certificate and key per role (router, coordinator, plant, agent-<name>, sensor-<name>, observer, operator) and acl.json."""
    from dmpc.scenario import build_system  # start-up time: pydantic only where needed
    from dmpc.security.certs import (  # start-up time: cryptography only here
        DEFAULT_HOSTS,
        default_ca_key_path,
        make_run_security,
    )

    system = build_system(load_scenario_file(scenario, set_))
    ca_key = ca_key if ca_key is not None else default_ca_key_path(directory)
    try:
        if run_id is not None:
            keys.check_chunk(run_id, "--run-id")
        roles = make_run_security(directory, system, hosts=list(DEFAULT_HOSTS) + list(host or []),
                                  run_id=run_id or "*", days=days, force=force, ca_key=ca_key)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    print(f"{directory}: CA certificate, {len(roles)} certificates ({', '.join(roles)}) and acl.json")
    print(f"the CA's private key is {ca_key} (mode 0600): keep it off the nodes, offline; whoever has it can "
          "make a certificate for any role. Give each node ca.pem, acl.json and its own role's files")


def setpoint(connect: ConnectOpt = None,
             run_id: Annotated[Optional[str], typer.Option("--run-id", help="The id of the run whose setpoint to change (dmpc run prints it with the coordinator's endpoint).", show_default=False)] = None,
             subsystem: Annotated[Optional[str], typer.Option("--subsystem", help="The subsystem's name in the scenario.", show_default=False)] = None,
             x: Annotated[Optional[list[str]], typer.Option("--x", help="Target states: by position, 1.0,null (null: free); or by name, Ta=1.5 (repeatable, needs --scenario). Omitted: every state free.", show_default=False)] = None,
             u: Annotated[Optional[list[str]], typer.Option("--u", help="Target inputs, the same way as --x. Omitted: every input free.", show_default=False)] = None,
             scenario: Annotated[Optional[Path], typer.Option("--scenario", help="The run's scenario (or its run folder's scenario.yaml): lets --x and --u name components, and checks the subsystem and the number of entries before sending.", show_default=False)] = None,
             tls: Annotated[Optional[Path], typer.Option("--tls", help="Certificate directory from 'dmpc certs' (or a 'dmpc run --secure' folder's tls/): connect over TLS as the role 'operator'.", show_default=False)] = None,
             timeout: Annotated[float, typer.Option("--timeout", min=0.1, help="Seconds to wait for the coordinator's answer, connecting included.")] = 5.0,
             name: Annotated[str, typer.Option("--name", help="This program's name as the request's sender (where the answer is sent).")] = "cli") -> None:
    """Change a subsystem's setpoint while a run goes on: send the request to the run's coordinator
    and wait for its answer (exit 0 accepted, 2 refused, 1 not authorised or no run listening)."""
    from dmpc.bus.session import BusError  # start-up time: zenoh only for network commands
    from dmpc.runtime.setpoints import (  # start-up time: zenoh only here
        components,
        scenario_subsystem,
        send_setpoint,
        unanswered_text,
    )

    if not connect:
        raise InputError("--connect: the coordinator's endpoint is needed, e.g. tcp/127.0.0.1:7447")
    if run_id is None:
        raise InputError("--run-id: the id of the run is needed (dmpc run prints it with the coordinator's endpoint)")
    if subsystem is None:
        raise InputError("--subsystem: the name of the subsystem whose setpoint to change is needed")
    if x is None and u is None:
        raise InputError("give --x or --u (null for a free component; --x null,null frees both states of a "
                         "subsystem with two)")
    given = {"--x": flag_components(x, "--x"), "--u": flag_components(u, "--u")}
    named = next((flag for flag, values in given.items() if isinstance(values, dict)), None)
    if named is not None and scenario is None:
        raise InputError(f"{named}: values by name need --scenario FILE (the run's scenario, which names the "
                         f"components), or give them by position, e.g. {named} 1.5,null")
    spec = scenario_subsystem(load_scenario_file(scenario, None), subsystem) if scenario is not None else None
    x_values = components(given["--x"], "x", "--x", subsystem, spec)
    u_values = components(given["--u"], "u", "--u", subsystem, spec)
    try:
        answer = send_setpoint(connect, run_id, subsystem, x_values, u_values, sender=name, tls_dir=tls,
                               timeout=timeout)
    except BusError as exc:
        error_line(str(exc))
        raise typer.Exit(EXIT_FAILED) from None
    if answer is None:
        print(unanswered_text(run_id, connect, timeout), file=sys.stderr)
        raise typer.Exit(EXIT_FAILED)
    if not answer.accepted:
        print(f"refused: {' '.join(answer.reason.split())}", file=sys.stderr)
        raise typer.Exit(EXIT_INPUT)
    print(f"accepted: subsystem {answer.subsystem} from step {answer.k}")


def flag_components(texts: list[str] | None, flag: str) -> list[float | None] | dict[str, float | None] | None:
    """The values of ``--x`` or ``--u`` (``flag``) from their ``texts``: ``1.0,null`` by position (one
    flag), or ``NAME=VALUE`` by name (comma-separated, the flag repeatable); None when not given."""
    if texts is None:
        return None
    parts = [part.strip() for text in texts for part in text.split(",")]
    named = ["=" in part for part in parts]
    if any(named) and not all(named):
        raise InputError(f"{flag}: give every value by position (1.0,null) or every one by name (Ta=1.5), not both")
    if not any(named):
        if len(texts) > 1:
            raise InputError(f"{flag}: by position, give one {flag} with every value, e.g. {flag} 1.0,null")
        return [_flag_value(part, flag) for part in parts]
    pairs = [part.split("=", 1) for part in parts]
    out: dict[str, float | None] = {}
    for key, value in pairs:
        key = key.strip()
        if not key or key in out:
            raise InputError(f"{flag}: {'a name is missing' if not key else f'{key!r} is given twice'} in "
                             f"{', '.join(texts)}")
        out[key] = _flag_value(value.strip(), f"{flag} {key}")
    return out


def _flag_value(text: str, where: str) -> float | None:
    if text.lower() in ("null", "none", "free"):
        return None
    try:
        return float(text)
    except ValueError:
        raise InputError(f"{where}: expected a number or null (free), got {text!r}") from None

"""The ``dmpc`` command line."""
from __future__ import annotations

import functools
import json
import logging
import os
import sys
from pathlib import Path
from typing import Annotated, Optional

import click
import typer

from dmpc import console
from dmpc.bus import keys
from dmpc.bus.faults import PLANT_PROCESS, FaultyBus
from dmpc.console import error_line, silence_c_stdout, stderr_console, stdout_console
from dmpc.design import DesignError
from dmpc.exit_codes import EXIT_ADDRESS_IN_USE, EXIT_FAILED, EXIT_INPUT, EXIT_INTERRUPTED, EXIT_OK, EXIT_VERDICT
from dmpc.methods import method_spec
from dmpc.plant.models import PlantModelError
from dmpc.records.files import COMPARISON, STEP_LOG, SUMMARY
from dmpc.records.run_folder import RecordWriteError, RunFolderError, claim_folder, write_json
from dmpc.run_bundle import load_bundle
from dmpc.runtime.memory import settle_after_startup
from dmpc.runtime.signals import sigterm_as_interrupt

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Distributed MPC with time-varying terminal sets: design, simulate, run over Zenoh.")
scenario_app = typer.Typer(add_completion=False, no_args_is_help=True, help="Scenario file tools.")
app.add_typer(scenario_app, name="scenario")

ScenarioArg = Annotated[Path, typer.Argument(help="Scenario YAML file.", show_default=False)]
SetOpt = Annotated[Optional[list[str]], typer.Option("--set", help="Override a field: KEY=VALUE, e.g. family.M=16 (repeatable).")]
ModelOpt = Annotated[Optional[str], typer.Option("--model", help="Your own plant: module:function or path/file.py:function, a function (x, u, k) -> x_next that replaces the linear plant (a flag only: never read from a scenario file).", show_default=False)]
MethodOpt = Annotated[Optional[str], typer.Option("--method", help="Control method: tv-box (default), tv-box-opt, fixed-box, ellipsoid, ellipsoid-adaptive, centralized (sets options.method).", show_default=False)]
ServerModeOpt = Annotated[str, typer.Option("--mode", help="Zenoh mode: peer, client, or router (agents then connect as clients).")]
StepsOpt = Annotated[Optional[int], typer.Option("--steps", min=1, help="Steps to run (default: the scenario's).")]
QuietTableOpt = Annotated[bool, typer.Option("--quiet", help="No progress bar and no summary table.")]


class InputError(Exception):
    """A usage or input error: exit code 2, one line."""


Override = str | tuple[str, object]
"""A scenario override: a ``--set`` text (``KEY=VALUE``, the value read as YAML), or a (key, value)
pair from a typed flag such as ``--loss``, passed on as it is."""


def _with_method(overrides: list[Override] | None, method: str | None) -> list[Override]:
    """The overrides plus ``options.method`` from ``--method`` (checked: InputError if unknown)."""
    extra = list(overrides or [])
    if method is not None:
        try:
            method_spec(method)
        except ValueError as exc:
            raise InputError(f"--method: {exc}") from None
        extra.append(("options.method", method))
    return extra


def _with_model(prepared, model: str | None):
    """``prepared`` with the plant function of ``--model`` (InputError if it cannot be imported)."""
    if model is None:
        return prepared
    from dmpc.runtime.plant_setup import load_plant_function, with_plant_function  # start-up time: it loads pydantic

    try:
        function, name = load_plant_function(model)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    return with_plant_function(prepared, function, name)


def _default_out(out: Path | None, scenario_name: str) -> Path:
    if out is not None:
        return out
    import re
    import time

    safe = re.sub(r"[^A-Za-z0-9_.-]", "-", scenario_name)[:40]
    return Path("runs") / f"{safe}-{time.strftime('%Y%m%d-%H%M%S')}"


def _load(path: Path, overrides: list[Override] | None, steps: int | None = None):
    """Load the scenario with ``overrides`` applied in order, then ``steps``."""
    from dmpc.scenario import load_scenario, parse_override  # start-up time: pydantic only where needed

    pairs = {}
    for item in overrides or []:
        key, value = parse_override(item) if isinstance(item, str) else item
        pairs[key] = value
    if steps is not None:
        pairs["steps"] = steps
    return load_scenario(path, pairs)


def _prepare(path: Path, overrides: list[Override] | None, steps: int | None = None):
    from dmpc.runtime.setup import prepare  # start-up time: it loads pydantic

    return prepare(_load(path, overrides, steps))


@scenario_app.command("schema")
def scenario_schema() -> None:
    """Print the JSON Schema of scenario files."""
    from dmpc.scenario import scenario_json_schema  # start-up time: pydantic only where needed

    print(json.dumps(scenario_json_schema(), indent=2))


@app.command()
def validate(scenario: ScenarioArg, set_: SetOpt = None) -> None:
    """Check a scenario file (schema and cross-field rules) without designing."""
    scn = _load(scenario, set_)
    subs = scn.resolved_subsystems()
    print(f"{scenario}: valid ({len(subs)} subsystems, horizon {scn.horizon}, gains {scn.design.gains})")


@app.command()
def design(scenario: ScenarioArg, set_: SetOpt = None,
           as_json: Annotated[bool, typer.Option("--json", help="Print design.json instead of the report.")] = False) -> None:
    """Run the offline design (gains, terminal set, tubes) and report it."""
    prepared = _prepare(scenario, set_)
    if as_json:
        print(json.dumps(prepared.design_json(), indent=2))
        return
    from dmpc.records.tables import design_report  # start-up time: tables only where printed

    stdout_console().print(design_report(prepared))


@app.command()
def simulate(scenario: ScenarioArg,
             out: Annotated[Optional[Path], typer.Option("--out", help="Run folder to write (default: runs/<scenario>-<time>).")] = None,
             steps: StepsOpt = None,
             set_: SetOpt = None,
             quiet: Annotated[bool, typer.Option("--quiet", help="No progress bar.")] = False,
             method: MethodOpt = None, model: ModelOpt = None) -> None:
    """Run every agent, the barrier and the plant in this process (in-memory bus)."""
    from dmpc.runtime.inprocess import record_run  # start-up time: the in-process runtime only where it runs
    from dmpc.records.tables import print_summary  # start-up time: tables only where printed
    from dmpc.records.session import RunRecorder  # start-up time: it loads pydantic

    prepared = _with_model(_prepare(scenario, _with_method(set_, method), steps), model)
    out = _default_out(out, prepared.name)
    with RunRecorder(out, prepared, show_progress=not quiet) as recorder:
        summary, failure = record_run(prepared, recorder)
    print_summary(summary, out)
    raise typer.Exit(_run_exit_code(summary, failure))


def _run_exit_code(summary: dict | None, failure: str = "") -> int:
    """1 when the run failed to run, 3 when it ran but its verdict is failed, else 0."""
    if failure:
        return EXIT_FAILED
    if summary is not None and summary.get("verdict") == "failed":
        return EXIT_VERDICT
    return EXIT_OK


# ---------------------------------------------------------------------------- network processes
ConnectOpt = Annotated[Optional[list[str]], typer.Option("--connect", help="Zenoh endpoint to connect to, e.g. tcp/10.0.0.1:7447 (repeatable).")]
ListenOpt = Annotated[Optional[list[str]], typer.Option("--listen", help="Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable).")]
RunIdOpt = Annotated[Optional[str], typer.Option("--run-id", help="Key prefix shared by the processes of one run (default: the scenario's name).")]
DesignOpt = Annotated[Optional[Path], typer.Option("--design", help="design.json to use instead of designing again (every process must agree).")]
StartupOpt = Annotated[float, typer.Option("--startup-timeout", min=0.1, help="Seconds to wait for the other processes before giving up.")]
MulticastOpt = Annotated[bool, typer.Option("--multicast/--no-multicast", help="Zenoh multicast scouting (off by default: give endpoints).")]
LeaseOpt = Annotated[Optional[float], typer.Option("--lease", min=0.1, help="Liveliness lease in seconds: a hung process is declared lost after it (Zenoh default 10).")]
DelayOpt = Annotated[Optional[float], typer.Option("--delay", min=0, help="Delay every link by MS milliseconds (seeded fault injection).")]
JitterOpt = Annotated[Optional[float], typer.Option("--jitter", min=0, help="Add a uniform random delay in [0, MS] ms on every link.")]
LossOpt = Annotated[Optional[float], typer.Option("--loss", min=0, max=0.999, help="Drop each message with probability P (needs a deadline).")]
SeedOpt = Annotated[Optional[int], typer.Option("--seed", min=0, help="Seed of the fault injection.")]
DeadlineOpt = Annotated[Optional[float], typer.Option("--deadline", min=0.001, help="Seconds an agent has to deliver its plan; later plans are missed.")]
ZenohConfigOpt = Annotated[Optional[Path], typer.Option("--zenoh-config", help="A Zenoh JSON5 config file applied before the options above.")]
TlsOpt = Annotated[Optional[Path], typer.Option("--tls", help="Certificate directory from 'dmpc certs': TLS with mutual authentication on every link (tls/ endpoints), and its acl.json.")]


def _prepare_for_process(scenario: Path, set_: list[Override] | None, design_file: Path | None,
                         steps: int | None = None):
    if scenario.suffix == ".json":
        # a run bundle written by ``dmpc run`` (no scenario schema needed: smaller, faster agents)
        if set_ or design_file or steps:
            raise InputError("--set, --design and --steps do not apply to a run bundle (.json)")
        try:
            return load_bundle(scenario)
        except ValueError as exc:
            raise InputError(str(exc)) from None
    from dmpc.runtime.setup import prepare  # start-up time: pydantic only for a scenario file

    scn = _load(scenario, set_, steps)
    data = None
    if design_file is not None:
        try:
            data = json.loads(design_file.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"--design {design_file}: cannot read a JSON design ({exc})") from None
    return prepare(scn, design_data=data)


def _fault_overrides(set_: list[Override] | None, delay, jitter, loss, seed, deadline) -> list[Override]:
    """The overrides plus the fault flags given (they apply to every link)."""
    extra = list(set_ or [])
    for key, value in (("faults.delay_ms", delay), ("faults.jitter_ms", jitter), ("faults.loss", loss),
                       ("seed", seed), ("options.deadline", deadline)):
        if value is not None:
            extra.append((key, value))
    return extra


def _with_faults(bus, prepared, receiver: str):
    """Wrap the bus in the seeded fault injector when the scenario asks for faults."""
    if prepared.faults.is_clean:
        return bus

    return FaultyBus(bus, receiver, prepared.faults)


def _run_id(given: str | None, prepared) -> str:
    import re

    rid = given or re.sub(r"[^A-Za-z0-9_.-]", "-", prepared.name)[:64]
    try:
        return keys.check_chunk(rid, "run id")
    except ValueError as exc:
        raise InputError(f"--run-id: {exc}") from None


def _security(tls_dir: Path | None, role: str):
    """(TlsFiles, access control) of ``role`` from a certificate directory, or (None, None)."""
    if tls_dir is None:
        return None, None
    from dmpc.security.files import node_security  # start-up time: zenoh only for network commands

    try:
        return node_security(tls_dir, role)
    except ValueError as exc:
        raise InputError(str(exc)) from None


def _open_bus(mode: str, connect, listen, multicast: bool, lease: float | None, config_file: Path | None,
              timeout: float, tls_dir: Path | None = None, role: str = "", shared: bool = False):
    from dmpc.bus.session import AddressInUse, BusError, session_config  # start-up time: zenoh only for network commands
    from dmpc.bus.zenoh_bus import ZenohBus  # start-up time: zenoh only for network commands

    tls, acl = _security(tls_dir, role)
    try:
        config = session_config(mode=mode, listen=list(listen or []), connect=list(connect or []), multicast=multicast,
                                config_file=str(config_file) if config_file else None,
                                lease_ms=int(lease * 1000) if lease else None, tls=tls, acl=acl)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    try:
        return ZenohBus(config, open_timeout=timeout, shared=shared)
    except BusError as exc:
        error_line(str(exc))
        raise typer.Exit(EXIT_ADDRESS_IN_USE if isinstance(exc, AddressInUse) else EXIT_FAILED) from None


def _write_report(path: Path, report: dict) -> None:
    """Write an agent's JSON report; a failure to write is reported, not raised."""
    try:
        write_json(path, report)
    except OSError as exc:
        error_line(f"--report {path}: cannot write ({exc.strerror})")


@app.command()
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
    sigterm_as_interrupt()
    set_ = _fault_overrides(set_, delay, jitter, loss, seed, deadline)
    prepared = _prepare_for_process(scenario, set_, design_file)
    _require_agents(prepared, "agent")
    unknown = [i for i in ids if i not in prepared.names]
    if unknown:
        raise InputError(f"--id: no subsystem {unknown[0]!r} in the scenario (subsystems: "
                         f"{_listed(prepared.names)})")
    rid = _run_id(run_id, prepared)
    bus = _open_bus(mode, connect, listen, multicast, lease, zenoh_config, startup_timeout, tls,
                    keys.agent_role(ids[0]), shared=len(ids) > 1)
    bus_for = None if prepared.faults.is_clean else (lambda name: _with_faults(bus, prepared, name))
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


def _listed(names: list[str], shown: int = 20) -> str:
    """The names, comma-separated; the first ``shown`` and the count beyond that."""
    if len(names) <= shown:
        return ", ".join(names)
    return f"{', '.join(names[:shown])}, ... ({len(names)} in all)"


PlantTimeoutOpt = Annotated[float, typer.Option("--plant-timeout", min=0.1, help="With an outside plant: seconds to wait for the state of each step before the run stops (docs/protocol.md).")]
PLANT_SIDES = ("internal", "external")


def _side(value: str, flag: str) -> str:
    if value not in PLANT_SIDES:
        raise InputError(f"{flag}: expected internal or external, got {value!r}")
    return value


@app.command()
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
    _side(plant_side, "--plant")
    if plant_side == "external" and model is not None:
        raise InputError("--model: the plant is outside this process (--plant external): give the model to it")
    _host_coordinator(scenario, out, plant_side, plant_timeout, connect, listen, mode, run_id, design_file,
                      startup_timeout, steps, multicast, lease, zenoh_config, quiet, tls,
                      (delay, jitter, loss, seed, deadline), set_, model)


@app.command()
def plant(scenario: ScenarioArg,
          out: Annotated[Optional[Path], typer.Option("--out", help="Run folder to write (created); needed when this process hosts the coordinator.")] = None,
          coordinator_side: Annotated[str, typer.Option("--coordinator", help="internal (default): host the coordinator too, one process for both; external: be the plant alone, for a 'dmpc coordinator --plant external'.")] = "internal",
          sensor: Annotated[Optional[list[str]], typer.Option("--sensor", help="With --coordinator external: report only this subsystem's state, as its own sensor (repeatable).", show_default=False)] = None,
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
    faults = (delay, jitter, loss, seed, deadline)
    if _side(coordinator_side, "--coordinator") == "internal":
        if sensor:
            raise InputError("--sensor: only with --coordinator external (a process that hosts the coordinator "
                             "measures every subsystem itself)")
        if out is None:
            raise InputError("--out: a run folder is needed when this process hosts the coordinator "
                             "(or pass --coordinator external to be the plant alone)")
        _host_coordinator(scenario, out, "internal", 10.0, connect, listen, mode, run_id, design_file,
                          startup_timeout, steps, multicast, lease, zenoh_config, quiet, tls, faults, set_, model,
                          command="plant")
        return
    if out is not None:
        raise InputError("--out: the plant alone writes no run folder (the coordinator does)")
    _serve_plant(scenario, sensor, connect, listen, mode, run_id, design_file, startup_timeout, steps, multicast,
                 lease, zenoh_config, tls, faults, set_, model)


def _check_mode(mode: str) -> None:
    if mode not in ("peer", "client", "router"):
        raise InputError(f"--mode: expected peer, client or router, got {mode!r}")


def _host_coordinator(scenario: Path, out: Path, plant_side: str, plant_timeout: float, connect, listen, mode: str,
                      run_id, design_file, startup_timeout: float, steps, multicast: bool, lease, zenoh_config,
                      quiet: bool, tls, faults: tuple, set_, model, command: str = "coordinator") -> None:
    """The process that hosts the coordinator (and the simulated plant, if ``plant_side`` is internal)."""
    from dmpc.plant.process import run_plant  # start-up time: only for `dmpc plant`
    from dmpc.records.tables import print_summary  # start-up time: tables only where printed
    from dmpc.records.session import RunRecorder  # start-up time: it loads pydantic

    _check_mode(mode)
    sigterm_as_interrupt()
    set_ = _fault_overrides(set_, *faults)
    prepared = _prepare_for_process(scenario, set_, design_file, steps)
    _require_agents(prepared, command)
    prepared = _with_model(prepared, model)
    rid = _run_id(run_id, prepared)
    role = keys.COORDINATOR_ROLE
    bus = _open_bus(mode, connect, listen, multicast, lease, zenoh_config, startup_timeout, tls, role)
    bus = _with_faults(bus, prepared, PLANT_PROCESS)
    settle_after_startup()
    try:
        sources = [path for path in (scenario, design_file) if path is not None]
        with RunRecorder(out, prepared, show_progress=not quiet, sources=sources) as recorder:
            outcome = run_plant(prepared, recorder, bus, rid, startup_timeout,
                                external_plant=plant_side == "external", plant_timeout=plant_timeout)
    finally:
        bus.close()
    if not quiet and outcome.summary is not None:
        print_summary(outcome.summary, out)
    if outcome.code != 0:
        error_line(outcome.message)
    raise typer.Exit(outcome.code)


def _serve_plant(scenario: Path, sensors, connect, listen, mode: str, run_id, design_file, startup_timeout: float,
                 steps, multicast: bool, lease, zenoh_config, tls, faults: tuple, set_, model) -> None:
    """``dmpc plant --coordinator external``: the simulated plant (or some sensors) alone."""
    from dmpc.plant.plant_process import run_plant_role  # start-up time: the plant role only for its command

    _check_mode(mode)
    sigterm_as_interrupt()
    prepared = _prepare_for_process(scenario, _fault_overrides(set_, *faults), design_file, steps)
    prepared = _with_model(prepared, model)
    if sensors:
        unknown = [name for name in sensors if name not in prepared.names]
        if unknown:
            raise InputError(f"--sensor: no subsystem {', '.join(map(repr, unknown))} in the scenario "
                             f"(subsystems: {', '.join(prepared.names)})")
        if len(set(sensors)) != len(sensors):
            raise InputError("--sensor: a subsystem is named twice")
        if tls is not None and len(sensors) > 1:
            raise InputError("--sensor: with --tls, one sensor per process (each has its own certificate)")
    role = keys.PLANT_ROLE if not sensors else keys.sensor_role(sensors[0])
    rid = _run_id(run_id, prepared)
    bus = _open_bus(mode, connect, listen, multicast, lease, zenoh_config, startup_timeout, tls, role)
    try:
        outcome = run_plant_role(prepared, bus, rid, startup_timeout, sensors=list(sensors) if sensors else None)
    finally:
        bus.close()
    if outcome.code != 0:
        error_line(outcome.message)
    else:
        print(outcome.message)
    raise typer.Exit(outcome.code)


@app.command()
def router(listen: ListenOpt = None,
           multicast: MulticastOpt = False, tls: TlsOpt = None) -> None:
    """Host a Zenoh router in this process (no external binary) until Ctrl-C."""
    import time

    from dmpc.bus.session import session_config  # start-up time: zenoh only for network commands

    sigterm_as_interrupt()
    endpoints = list(listen or ["tls/0.0.0.0:7447" if tls else "tcp/0.0.0.0:7447"])
    tls_files, acl = _security(tls, "router")
    try:
        config = session_config(mode="router", listen=endpoints, multicast=multicast, tls=tls_files, acl=acl)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    import zenoh

    try:
        session = zenoh.open(config)
    except Exception as exc:  # zenoh reports bind failures as a generic error
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


@app.command()
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
    sigterm_as_interrupt()
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


@app.command()
def certs(directory: Annotated[Path, typer.Argument(help="Directory to write (created).", show_default=False)],
          scenario: Annotated[Path, typer.Option("--scenario", help="Scenario YAML: one certificate per agent, and its access control.")],
          host: Annotated[Optional[list[str]], typer.Option("--host", help="Another IP address or DNS name the processes are reached at (repeatable; 127.0.0.1 and localhost are always in).")] = None,
          run_id: Annotated[Optional[str], typer.Option("--run-id", help="Bind the access control to this run id (default: any run of the scenario).")] = None,
          days: Annotated[int, typer.Option("--days", min=1, help="Validity of the certificates in days.")] = 365,
          force: Annotated[bool, typer.Option("--force", help="Replace certificates already in DIRECTORY.")] = False,
          set_: SetOpt = None) -> None:
    """Make a CA, a certificate and key per role (router, coordinator, plant, agent-<name>, sensor-<name>, observer) and acl.json."""
    from dmpc.scenario import build_system  # start-up time: pydantic only where needed
    from dmpc.security.certs import DEFAULT_HOSTS, make_run_security  # start-up time: cryptography only here

    system = build_system(_load(scenario, set_))
    try:
        if run_id is not None:
            keys.check_chunk(run_id, "--run-id")
        roles = make_run_security(directory, system, hosts=list(DEFAULT_HOSTS) + list(host or []),
                                  run_id=run_id or "*", days=days, force=force)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    print(f"{directory}: CA, {len(roles)} certificates ({', '.join(roles)}) and acl.json")
    print(f"keep {directory / 'ca.key'} away from the nodes; give each node ca.pem, acl.json and its own role's files")


def _require_agents(prepared, role: str) -> None:
    """InputError unless the method runs agents (``centralized`` has no agent or plant process)."""
    if prepared.method == "centralized":
        raise InputError(f"dmpc {role}: method 'centralized' runs no agents and no plant process; "
                         "use dmpc simulate or dmpc run, which run it in one process")


def _run_centralized_here(prepared, out: Path | None, quiet: bool, network_flags: list[str]) -> None:
    """``dmpc run --method centralized``: one QP over the whole system per step, in this process."""
    from dmpc.records.tables import print_summary  # start-up time: tables only where printed
    from dmpc.records.session import RunRecorder  # start-up time: it loads pydantic
    from dmpc.runtime.inprocess import record_run  # start-up time: the in-process runtime only where it runs

    if network_flags:
        raise InputError(f"{', '.join(network_flags)}: method 'centralized' runs in one process without a bus, "
                         "so there are no links to configure")
    out = _default_out(out, prepared.name)
    print("method centralized: one QP over the whole system, run in this process (no agents, no Zenoh)",
          file=sys.stderr)
    with RunRecorder(out, prepared, show_progress=not quiet) as recorder:
        summary, failure = record_run(prepared, recorder)
    print_summary(summary, out)
    raise typer.Exit(_run_exit_code(summary, failure))


@app.command()
def run(scenario: ScenarioArg,
        out: Annotated[Optional[Path], typer.Option("--out", help="Run folder to write (default: runs/<scenario>-<time>).")] = None,
        steps: StepsOpt = None,
        run_id: RunIdOpt = None, startup_timeout: StartupOpt = 60.0,
        quiet: Annotated[bool, typer.Option("--quiet", help="No progress bar.")] = False,
        tls: TlsOpt = None,
        secure: Annotated[bool, typer.Option("--secure", help="Make certificates and access control in the run folder (tls/) and run every link over TLS with them.")] = False,
        topology: Annotated[Optional[str], typer.Option("--topology", help="mesh (agents link to each other) or star (through the plant's router); default: mesh up to 64 agent processes, star above.")] = None,
        delay: DelayOpt = None, jitter: JitterOpt = None, loss: LossOpt = None, seed: SeedOpt = None,
        deadline: DeadlineOpt = None, set_: SetOpt = None, method: MethodOpt = None, model: ModelOpt = None,
        watch: Annotated[bool, typer.Option("--watch", help="Serve a live view of the run on a local web page (the URL is printed); it stays up after the run until Ctrl-C.")] = False,
        restart: Annotated[int, typer.Option("--restart", min=0, help="Start a crashed agent again, up to N times per agent (backoff 0.5 s, doubled each time); it rejoins the run.")] = 0,
        fail_fast: Annotated[bool, typer.Option("--fail-fast", help="Stop the run when an agent is lost for good (default: its fallback applies and the run goes on).")] = False,
        lease: LeaseOpt = None,
        plant_side: Annotated[str, typer.Option("--plant", help="internal: simulate the plant (default); external: start everything but the plant and wait for one to connect (docs/protocol.md).")] = "internal",
        plant_timeout: PlantTimeoutOpt = 10.0,
        port: Annotated[Optional[int], typer.Option("--port", min=1, max=65535, help="Local port the coordinator listens on (default: a free one); where an outside plant connects.", show_default=False)] = None,
        agents_per_process: Annotated[int, typer.Option("--agents-per-process", min=1, help="Serve up to K agents in each agent process, on one Zenoh session (default 1: a process per agent). A crashed process is the loss of all its agents.")] = 1) -> None:
    """Start the plant and every agent as processes on this machine and wait for the run.

    A crashed agent is a lost agent: its fallback applies and the run goes on (``--restart`` starts
    it again, ``--fail-fast`` stops the run instead). ``--method centralized`` has no agents: it
    runs its one QP per step in this process.
    """
    import secrets

    from dmpc.records.tables import print_summary  # start-up time: tables only where printed
    from dmpc.runtime.launcher import TOPOLOGIES, default_topology, launch  # start-up time: only for `dmpc run`
    from dmpc.runtime.setup import prepare  # start-up time: it loads pydantic
    from dmpc.runtime.supervisor import RestartPolicy  # start-up time: only for `dmpc run`

    if tls is not None and secure:
        raise InputError("--tls and --secure exclude each other (--secure makes its own certificates)")
    prepared = prepare(_load(scenario, _with_method(_fault_overrides(set_, delay, jitter, loss, seed, deadline), method),
                             steps))
    prepared = _with_model(prepared, model)
    if prepared.method == "centralized":
        network = {"--tls": tls is not None, "--secure": secure, "--topology": topology is not None,
                   "--run-id": run_id is not None, "--delay": delay is not None, "--jitter": jitter is not None,
                   "--loss": loss is not None, "--deadline": deadline is not None}
        network["--watch"] = watch
        network.update({"--restart": restart > 0, "--fail-fast": fail_fast, "--lease": lease is not None,
                        "--agents-per-process": agents_per_process > 1})
        _run_centralized_here(prepared, out, quiet, [flag for flag, given in network.items() if given])
    external = _side(plant_side, "--plant") == "external"
    if external and model is not None:
        raise InputError("--model: the plant is outside (--plant external): give the model to it")
    for role in [keys.COORDINATOR_ROLE] + [keys.agent_role(name) for name in prepared.names] if tls is not None else []:
        _security(tls, role)  # every file present before any process starts
    if agents_per_process > 1 and (tls is not None or secure):
        raise InputError(f"--agents-per-process {agents_per_process}: a certificate belongs to one agent, so agents "
                         f"sharing a process cannot use {'--tls' if tls is not None else '--secure'}; leave "
                         "--agents-per-process at 1 for a run over TLS")
    if topology is not None and topology not in TOPOLOGIES:
        raise InputError(f"--topology: expected mesh or star, got {topology!r}")
    topology = topology or default_topology(-(-prepared.system.M // agents_per_process))
    out = _default_out(out, prepared.name)
    rid = _run_id(run_id or f"{prepared.name}-{secrets.token_hex(4)}", prepared)
    watcher = None
    if watch:
        from dmpc.watch.attach import Watcher  # start-up time: the live view only with --watch

        if tls is not None:
            _security(tls, "observer")
        watcher = Watcher()

    result = launch(prepared, out, rid, startup_timeout=startup_timeout, show_progress=not quiet,
                    tls_dir=tls, secure=secure, topology=topology, on_ready=watcher.start if watcher else None,
                    plant_model=model, policy=RestartPolicy(restart, fail_fast),
                    extra_args=["--lease", str(lease)] if lease is not None else None,
                    plant_timeout=plant_timeout if external else None, port=port,
                    agents_per_process=agents_per_process)
    if result.summary is not None:
        print_summary(result.summary, out)
    if result.code == EXIT_INTERRUPTED:
        error_line(result.message)
    elif result.code != 0:
        print(f"error: {result.message}", file=sys.stderr)  # keeps the children's log tails on their lines
    if watcher is not None:
        watcher.after_run(interrupted=result.code == EXIT_INTERRUPTED)
    raise typer.Exit(result.code if result.code != 0 else _run_exit_code(result.summary))


@app.command()
def bench(quick: Annotated[bool, typer.Option("--quick", help="A subset that runs in under a minute.")] = False,
          as_json: Annotated[bool, typer.Option("--json", help="Print the results as JSON.")] = False,
          write: Annotated[Optional[Path], typer.Option("--write", help="Write the Markdown report here (figures and the raw results as .json beside it).")] = None) -> None:
    """Measure QP, multi-process step time, memory, design time and baselines on this machine."""
    from dmpc.bench_results import markdown, plot, run_all  # start-up time: the benchmarks only for `dmpc bench`

    root = Path.cwd()
    if not (root / "scenarios" / "paper.yaml").exists():
        raise InputError("run dmpc bench from the project folder (it needs scenarios/)")
    results = run_all(quick, root, show_progress=not as_json)
    if write is not None:
        write.parent.mkdir(parents=True, exist_ok=True)
        figures = plot(results, write.parent / "figures")
        command = "dmpc bench" + (" --quick" if quick else "") + f" --write {write}"
        text = markdown(results, command)
        text += "\n" + "\n".join(f"![{p.stem}](figures/{p.name})" for p in figures) + "\n"
        write.write_text(text)
        write.with_suffix(".json").write_text(json.dumps(results, indent=2) + "\n")
    if as_json:
        print(json.dumps({**results["headline"], "results": results}, indent=2))
    else:
        stdout_console().print(markdown(results, "dmpc bench"))


@app.command()
def report(run_dir: Annotated[Path, typer.Argument(help="A run folder, or a folder with comparison.json from 'dmpc compare'.", show_default=False)],
           out: Annotated[Optional[Path], typer.Option("--out", help="Folder for the PNG files (default: RUN_DIR/figures).")] = None) -> None:
    """Draw the paper's five figures (terminal sets, states, inputs, J, S) from a run or comparison folder."""
    from dmpc.figures import ReportError, draw  # start-up time: the figures (matplotlib) only for `dmpc report`

    notes: list[str] = []
    try:
        paths = draw(run_dir, out, notes)
    except ReportError as exc:
        raise InputError(str(exc)) from None
    for line in notes:
        print(line)
    for path in paths:
        print(path)


@app.command()
def watch(run_dir: Annotated[Optional[Path], typer.Argument(help="A run folder: replayed, or followed while it is written; with --connect, where the run's description and summary are read.", show_default=False)] = None,
          connect: ConnectOpt = None,
          run_id: Annotated[Optional[str], typer.Option("--run-id", help="The run to watch over the bus (needed with --connect).")] = None,
          port: Annotated[int, typer.Option("--port", min=0, max=65535, help="Port of the web page (0: any free port).")] = 0,
          listen: Annotated[str, typer.Option("--listen", help="Address the web page listens on (loopback by default; 0.0.0.0 for every interface).")] = "127.0.0.1",
          tls: Annotated[Optional[Path], typer.Option("--tls", help="Certificate directory from 'dmpc certs': connect over TLS as the read-only role 'observer'.")] = None) -> None:
    """Serve a web page that shows a run: live over Zenoh (--connect, --run-id) or from its run folder."""
    from dmpc.watch.folder import FolderError, FolderFeed  # start-up time: the live view only for `dmpc watch`
    from dmpc.watch.state import RunState  # start-up time: the live view only for `dmpc watch`

    if run_dir is None and not connect:
        raise InputError("give a run folder to replay, or --connect ENDPOINT --run-id ID to watch a live run")
    if connect and not run_id:
        raise InputError("--connect needs --run-id: the id of the run to watch (the plant's --run-id, by default "
                         "its scenario's name)")
    if tls is not None and not connect:
        raise InputError("--tls applies to --connect only")
    if run_dir is not None and not run_dir.is_dir():
        raise InputError(f"{run_dir}: no such folder")
    if run_id is not None:
        run_id = _run_id(run_id, None)
    source = (f"live over Zenoh from {', '.join(connect)}" if connect else f"run folder {run_dir}")
    if connect and run_dir is not None:
        source += f", run folder {run_dir}"
    state = RunState(source, run_id or "")
    feed = None
    if run_dir is not None:
        feed = FolderFeed(run_dir, state, steps=not connect)
        try:
            feed.load_meta()
        except FolderError as exc:
            raise InputError(str(exc)) from None
        feed.poll()
    observer = None
    if connect:
        from dmpc.watch.observer import BusObserver  # start-up time: zenoh only when watching a live run

        tls_files, acl = _security(tls, "observer")
        try:
            observer = BusObserver(state, run_id, list(connect), tls=tls_files, acl=acl)
        except ValueError as exc:
            raise InputError(str(exc)) from None
    from dmpc.watch.server import WatchServer, announce  # start-up time: the live view only for `dmpc watch`

    try:
        server = WatchServer(state, live=observer is not None, address=listen, port=port,
                             poll=feed.poll if feed else None)
    except OSError as exc:
        raise InputError(f"--listen {listen} --port {port}: cannot serve the page ({exc.strerror or exc})") from None
    sigterm_as_interrupt()
    if observer is not None:
        observer.start()
    try:
        server.serve(on_ready=announce)
    finally:
        if observer is not None:
            observer.close()


MethodsOpt = Annotated[Optional[list[str]], typer.Option("--methods", help="Methods to run (default: all): --methods tv-box centralized ...", show_default=False)]


def _checked_methods(methods: list[str] | None) -> list[str]:
    from dmpc.evaluation.compare import check_methods  # start-up time: the comparison only for `dmpc compare`

    try:
        return check_methods(methods)
    except ValueError as exc:
        raise InputError(f"--methods: {exc}") from None


def _table(title: str, header: list[str], rows: list[list[str]]):
    from rich import box
    from rich.table import Table

    table = Table(title=title, box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True)
    for name in header:
        table.add_column(name, justify="left" if name in ("method", "verdict") else "right", no_wrap=True)
    for row in rows:
        table.add_row(*row)
    return table


@app.command()
def compare(scenario: ScenarioArg,
            out: Annotated[Path, typer.Option("--out", help="Folder to write: DIR/<method>/ run folders and DIR/comparison.json.")],
            steps: Annotated[Optional[int], typer.Option("--steps", min=1, help="Steps per run (default: the scenario's).")] = None,
            methods: MethodsOpt = None, set_: SetOpt = None,
            quiet: Annotated[bool, typer.Option("--quiet", help="No progress bars.")] = False) -> None:
    """Run every method on the same scenario in this process, compare them, and draw the figures."""
    from dmpc.evaluation.compare import (COMPARISON_HEADER, COMPARISON_LEGEND, compare as run_compare,
                                         comparison_rows, cost_ratios)  # start-up time: the comparison only for `dmpc compare`

    methods = _checked_methods(methods)
    scn = _load(scenario, set_, steps)
    data = run_compare(scn, out, methods, show_progress=not quiet)
    console = stdout_console()
    console.print(_table(f"methods on '{data['scenario']}'", COMPARISON_HEADER, comparison_rows(data)))
    console.print(COMPARISON_LEGEND)
    ratio = cost_ratios(data).get("tv-box")
    if ratio is not None:
        console.print(f"closed-loop cost tv-box / centralized = {ratio:.4f}")
    console.print(f"comparison: {out / COMPARISON}")
    _draw_comparison_figures(out)
    failed = [m for m, e in data["methods"].items() if e.get("verdict") == "failed"]
    if failed:
        error_line(f"verdict failed for {', '.join(failed)} (reasons in {', '.join(str(out / m / SUMMARY) for m in failed)})")
        raise typer.Exit(EXIT_VERDICT)


def _draw_comparison_figures(out: Path) -> None:
    """Draw the comparison figures (:func:`dmpc.figures.draw_comparison`); a failure is reported, not raised."""
    from dmpc.figures import draw_comparison  # lazy: matplotlib only when drawing

    try:
        paths = draw_comparison(out)
    except Exception as exc:  # the results are written already; a drawing problem must not hide them
        print(f"figures: not drawn ({type(exc).__name__}: {exc})", file=sys.stderr)
        return
    if paths:
        print(f"figures: {', '.join(str(p) for p in paths)}")


@app.command()
def roa(scenario: ScenarioArg,
        horizons: Annotated[list[int], typer.Option("--N", help="Horizons to test, e.g. --N 3 5 8 10 (the default).", show_default=False)] = [3, 5, 8, 10],  # noqa: B006
        samples: Annotated[int, typer.Option("--samples", help="Initial states sampled (>= 1).")] = 500,
        seed: Annotated[int, typer.Option("--seed", help="Seed of the sampling (>= 0).")] = 0,
        box: Annotated[Optional[float], typer.Option("--box", help="Sample x(0) uniformly in |x_j| <= R (default: the largest |entry| of the scenario's x0).", show_default=False)] = None,
        methods: MethodsOpt = None,
        out: Annotated[Optional[Path], typer.Option("--out", help="Folder for roa.json and roa.png (default: runs/roa-<scenario>-<time>).")] = None,
        set_: SetOpt = None,
        quiet: Annotated[bool, typer.Option("--quiet", help="No progress bar.")] = False) -> None:
    """Region of attraction: per method and horizon, the fraction of sampled x(0) feasible at k = 0 and converging."""
    from dmpc.evaluation.roa import (ROA_FILE, ROA_LEGEND, ROA_PLOT, plot_roa, region_of_attraction, roa_header,
                                     roa_rows)  # start-up time: the region of attraction only for `dmpc roa`

    if not horizons or any(N < 1 for N in horizons):
        raise InputError(f"--N: horizons must be integers >= 1, got {' '.join(map(str, horizons)) or 'none'}")
    if len(set(horizons)) != len(horizons):
        raise InputError(f"--N: a horizon is listed twice: {' '.join(map(str, horizons))}")
    if samples < 1:
        raise InputError(f"--samples: must be >= 1, got {samples}")
    if seed < 0:
        raise InputError(f"--seed: must be >= 0, got {seed}")
    if box is not None and not (box > 0 and box < float("inf")):
        raise InputError(f"--box: must be a positive number, got {box}")
    methods = _checked_methods(methods)
    scn = _load(scenario, set_)
    out = out or _default_out(None, f"roa-{scn.name}")
    claim_folder(out, ROA_FILE, "a region-of-attraction table")
    progress = None
    if not quiet:
        from dmpc.evaluation.run_progress import RunProgress  # start-up time: the progress display only for `dmpc roa`

        plan = (f"{len(methods)} method{'s' * (len(methods) > 1)} x {len(horizons)} horizon"
                f"{'s' * (len(horizons) > 1)} x {samples} sample{'s' * (samples > 1)}, up to {scn.steps} steps each")
        progress = RunProgress("roa", len(methods) * len(horizons) * samples, plan, stderr_console())
        progress.start()
    try:
        data = region_of_attraction(scn, sorted(horizons), methods, samples, seed, box,
                                    progress.advance if progress is not None else None)
    finally:
        if progress is not None:
            progress.stop()
    write_json(out / ROA_FILE, data)
    plot = plot_roa(data, out / ROA_PLOT)
    console = stdout_console()
    console.print(_table(f"region of attraction, '{data['scenario']}' ({samples} samples, |x_j| <= {data['box']:g}, "
                         f"seed {seed})", roa_header(data), roa_rows(data)))
    console.print(ROA_LEGEND)
    console.print(f"results: {out / ROA_FILE}, plot: {plot}")


def _expand_multi_values(args: list[str]) -> list[str]:
    """``--N 3 5 8`` -> ``--N 3 --N 5 --N 8`` (and the same for ``--methods``): click options take
    one value each, so the values that follow these options are given one option each."""
    import re

    takes = {"--N": re.compile(r"^[+-]?\d+(\.\d*)?$"), "--methods": re.compile(r"^[a-z][a-z0-9-]*$")}
    out: list[str] = []
    current, given = None, 0
    for arg in args:
        if current is not None and takes[current].match(arg):
            out += [current, arg]
            given += 1
            continue
        if current is not None and not given:
            out.append(current)  # no value of its own: click reports the next argument as a bad value
        current, given = (arg, 0) if arg in takes else (None, 0)
        if current is None:
            out.append(arg)
    if current is not None and not given:
        out.append(current)
    return out


def _report_plant_error(exc: Exception) -> None:
    """The traceback of the user's plant function (not of dmpc's), then one error line."""
    import traceback

    if exc.__cause__ is not None:
        sys.stderr.write("".join(traceback.format_exception(exc.__cause__)))
    error_line(f"{exc} (the run stopped; the steps before it are in the run folder)")


def _is_scenario_error(exc: Exception) -> bool:
    """ScenarioError, checked lazily: the scenario package (pydantic) is not always loaded."""
    module = sys.modules.get("dmpc.scenario.load")
    return module is not None and isinstance(exc, module.ScenarioError)


def main() -> None:
    """Console entry point: maps expected errors to one line and exit code 2."""
    sigterm_as_interrupt()  # from the start: SIGTERM during the design ends the process cleanly too
    silence_c_stdout()
    code = _run_app()
    zenoh_bus = sys.modules.get("dmpc.bus.zenoh_bus")
    if zenoh_bus is not None and zenoh_bus.sessions_left_open():
        # A Zenoh session still closing in the background would abort a normal interpreter exit.
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


@functools.cache
def click_command() -> click.Command:
    """The click command of ``app``. Typer builds it from the commands' signatures at every call
    (a tenth of a second of CPU); the fork server of ``dmpc run`` builds it once for all agents."""
    return typer.main.get_command(app)


def _run_app() -> int:
    """Run the CLI; the process's exit code (expected errors reported on one line)."""
    try:
        # without standalone mode, click returns the code of typer.Exit instead of raising it
        code = click_command()(args=_expand_multi_values(sys.argv[1:]), standalone_mode=False)
        code = code if isinstance(code, int) else 0
        if code == EXIT_INTERRUPTED and not console.errors_printed:
            # typer returns Ctrl-C and SIGTERM as a bare exit code 130
            error_line("interrupted")
        return code
    except RecordWriteError as exc:  # during the run: the completed steps are in the step log
        error_line(f"{exc}; the run stopped, its completed steps are kept in {STEP_LOG}")
        return EXIT_FAILED
    except (DesignError, RunFolderError, InputError) as exc:
        error_line(str(exc))
        return EXIT_INPUT
    except click.exceptions.Exit as exc:
        return exc.exit_code
    except KeyboardInterrupt:
        error_line("interrupted")
        return EXIT_INTERRUPTED
    except click.exceptions.Abort:
        error_line("aborted")
        return EXIT_INTERRUPTED
    except click.ClickException as exc:  # usage errors: unknown option, missing argument, bad value
        exc.show()
        return exc.exit_code
    except PlantModelError as exc:
        _report_plant_error(exc)
        return EXIT_FAILED
    except Exception as exc:
        if not _is_scenario_error(exc):
            raise
        error_line(str(exc))
        return EXIT_INPUT


if __name__ == "__main__":
    main()

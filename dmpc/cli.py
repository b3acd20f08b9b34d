"""The ``dmpc`` command line."""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Optional

import click
import typer

from dmpc.console import error_line, silence_c_stdout, stdout_console
from dmpc.design import DesignError
from dmpc.records.run_folder import RunFolderError

EXIT_INPUT = 2
EXIT_INTERRUPTED = 130

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Distributed MPC with time-varying terminal sets: design, simulate, run over Zenoh.")
scenario_app = typer.Typer(add_completion=False, no_args_is_help=True, help="Scenario file tools.")
app.add_typer(scenario_app, name="scenario")

ScenarioArg = Annotated[Path, typer.Argument(help="Scenario YAML file.", show_default=False)]
SetOpt = Annotated[Optional[list[str]], typer.Option("--set", help="Override a field: KEY=VALUE, e.g. family.M=16 (repeatable).")]


class InputError(Exception):
    """A usage or input error: exit code 2, one line."""


def _default_out(out: Path | None, scenario_name: str) -> Path:
    if out is not None:
        return out
    import re
    import time

    safe = re.sub(r"[^A-Za-z0-9_.-]", "-", scenario_name)[:40]
    return Path("runs") / f"{safe}-{time.strftime('%Y%m%d-%H%M%S')}"


def _load(path: Path, overrides: list[str] | None, steps: int | None = None):
    from dmpc.scenario import load_scenario, parse_override

    pairs = {}
    for text in overrides or []:
        key, value = parse_override(text)
        pairs[key] = value
    if steps is not None:
        pairs["steps"] = steps
    return load_scenario(path, pairs)


def _prepare(path: Path, overrides: list[str] | None, steps: int | None = None):
    from dmpc.runtime.setup import prepare

    return prepare(_load(path, overrides, steps))


@scenario_app.command("schema")
def scenario_schema() -> None:
    """Print the JSON Schema of scenario files."""
    from dmpc.scenario import scenario_json_schema

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
    from dmpc.records.report import design_report

    stdout_console().print(design_report(prepared))


@app.command()
def simulate(scenario: ScenarioArg,
             out: Annotated[Optional[Path], typer.Option("--out", help="Run folder to write (default: runs/<scenario>-<time>).")] = None,
             steps: Annotated[Optional[int], typer.Option("--steps", min=1, help="Steps to run (default: the scenario's).")] = None,
             set_: SetOpt = None,
             quiet: Annotated[bool, typer.Option("--quiet", help="No progress bar.")] = False) -> None:
    """Run every agent, the barrier and the plant in this process (in-memory bus)."""
    from dmpc.runtime.inprocess import simulate as run_inprocess
    from dmpc.records.report import print_summary
    from dmpc.records.session import RunRecorder

    prepared = _prepare(scenario, set_, steps)
    out = _default_out(out, prepared.name)
    with RunRecorder(out, prepared, show_progress=not quiet) as recorder:
        run = run_inprocess(prepared, recorder.on_step)
        summary = recorder.complete(runtime="in-process", failure=run.plant.failure or None,
                                    rejected=run.plant.rejected, duplicates=run.plant.coordinator.duplicates)
    print_summary(summary, out)
    if run.plant.failure:
        raise typer.Exit(1)


# ---------------------------------------------------------------------------- network processes
ConnectOpt = Annotated[Optional[list[str]], typer.Option("--connect", help="Zenoh endpoint to connect to, e.g. tcp/10.0.0.1:7447 (repeatable).")]
ListenOpt = Annotated[Optional[list[str]], typer.Option("--listen", help="Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable).")]
RunIdOpt = Annotated[Optional[str], typer.Option("--run-id", help="Key prefix shared by the processes of one run (default: the scenario's name).")]
DesignOpt = Annotated[Optional[Path], typer.Option("--design", help="design.json to use instead of designing again (every process must agree).")]
StartupOpt = Annotated[float, typer.Option("--startup-timeout", min=0.1, help="Seconds to wait for the other processes before giving up.")]
MulticastOpt = Annotated[bool, typer.Option("--multicast/--no-multicast", help="Zenoh multicast scouting (off by default: give endpoints).")]
LeaseOpt = Annotated[Optional[float], typer.Option("--lease", min=0.1, help="Liveliness lease in seconds: a hung process is declared lost after it (Zenoh default 10).")]
ZenohConfigOpt = Annotated[Optional[Path], typer.Option("--zenoh-config", help="A Zenoh JSON5 config file applied before the options above.")]


def _prepare_for_process(scenario: Path, set_: list[str] | None, design_file: Path | None, steps: int | None = None):
    from dmpc.runtime.setup import prepare

    if scenario.suffix == ".json":
        # a run bundle written by ``dmpc run`` (no scenario schema needed: smaller, faster agents)
        from dmpc.runtime.bundle import load_bundle

        if set_ or design_file or steps:
            raise InputError("--set, --design and --steps do not apply to a run bundle (.json)")
        try:
            return load_bundle(scenario)
        except ValueError as exc:
            raise InputError(str(exc)) from None

    scn = _load(scenario, set_, steps)
    data = None
    if design_file is not None:
        try:
            data = json.loads(design_file.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"--design {design_file}: cannot read a JSON design ({exc})") from None
    return prepare(scn, design_data=data)


def _run_id(given: str | None, prepared) -> str:
    from dmpc.bus import keys

    import re

    rid = given or re.sub(r"[^A-Za-z0-9_.-]", "-", prepared.name)[:64]
    try:
        return keys.check_chunk(rid, "run id")
    except ValueError as exc:
        raise InputError(f"--run-id: {exc}") from None


def _open_bus(mode: str, connect, listen, multicast: bool, lease: float | None, config_file: Path | None,
              timeout: float):
    from dmpc.bus.session import BusError, session_config
    from dmpc.bus.zenoh_bus import ZenohBus

    try:
        config = session_config(mode=mode, listen=list(listen or []), connect=list(connect or []), multicast=multicast,
                                config_file=str(config_file) if config_file else None,
                                lease_ms=int(lease * 1000) if lease else None)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    try:
        return ZenohBus(config, open_timeout=timeout)
    except BusError as exc:
        error_line(str(exc))
        raise typer.Exit(1) from None


@app.command()
def agent(scenario: ScenarioArg,
          id_: Annotated[str, typer.Option("--id", help="The subsystem this process controls (its name in the scenario).")],
          connect: ConnectOpt = None, listen: ListenOpt = None,
          mode: Annotated[str, typer.Option("--mode", help="Zenoh mode: peer or client.")] = "peer",
          run_id: RunIdOpt = None, design_file: DesignOpt = None, startup_timeout: StartupOpt = 30.0,
          multicast: MulticastOpt = False, lease: LeaseOpt = None, zenoh_config: ZenohConfigOpt = None,
          set_: SetOpt = None) -> None:
    """Run one subsystem's agent on the Zenoh bus until the plant stops the run."""
    from dmpc.agents.process import run_agent
    from dmpc.runtime.memory import settle_after_startup
    from dmpc.runtime.signals import sigterm_as_interrupt

    if mode not in ("peer", "client"):
        raise InputError(f"--mode: expected peer or client, got {mode!r}")
    sigterm_as_interrupt()
    prepared = _prepare_for_process(scenario, set_, design_file)
    if id_ not in prepared.names:
        raise InputError(f"--id: no subsystem {id_!r} in the scenario (subsystems: {', '.join(prepared.names)})")
    rid = _run_id(run_id, prepared)
    bus = _open_bus(mode, connect, listen, multicast, lease, zenoh_config, startup_timeout)
    settle_after_startup()
    try:
        outcome = run_agent(prepared, id_, bus, rid, startup_timeout)
    except KeyboardInterrupt:
        raise typer.Exit(EXIT_INTERRUPTED) from None
    finally:
        bus.close()
    if outcome.code == 0:
        print(outcome.message)
    else:
        error_line(outcome.message)
    raise typer.Exit(outcome.code)


@app.command()
def plant(scenario: ScenarioArg,
          out: Annotated[Path, typer.Option("--out", help="Run folder to write (created).")],
          connect: ConnectOpt = None, listen: ListenOpt = None,
          mode: Annotated[str, typer.Option("--mode", help="Zenoh mode: peer or client.")] = "peer",
          run_id: RunIdOpt = None, design_file: DesignOpt = None, startup_timeout: StartupOpt = 30.0,
          steps: Annotated[Optional[int], typer.Option("--steps", min=1, help="Steps to run (default: the scenario's).")] = None,
          multicast: MulticastOpt = False, lease: LeaseOpt = None, zenoh_config: ZenohConfigOpt = None,
          quiet: Annotated[bool, typer.Option("--quiet", help="No progress bar and no summary table.")] = False,
          set_: SetOpt = None) -> None:
    """Run the plant and step barrier: wait for every agent, step, record."""
    from dmpc.plant.process import run_plant
    from dmpc.runtime.memory import settle_after_startup
    from dmpc.records.report import print_summary
    from dmpc.records.session import RunRecorder
    from dmpc.runtime.signals import sigterm_as_interrupt

    if mode not in ("peer", "client"):
        raise InputError(f"--mode: expected peer or client, got {mode!r}")
    sigterm_as_interrupt()
    prepared = _prepare_for_process(scenario, set_, design_file, steps)
    rid = _run_id(run_id, prepared)
    bus = _open_bus(mode, connect, listen, multicast, lease, zenoh_config, startup_timeout)
    settle_after_startup()
    try:
        with RunRecorder(out, prepared, show_progress=not quiet) as recorder:
            outcome = run_plant(prepared, recorder, bus, rid, startup_timeout)
    finally:
        bus.close()
    if not quiet and outcome.summary is not None:
        print_summary(outcome.summary, out)
    if outcome.code != 0:
        error_line(outcome.message)
    raise typer.Exit(outcome.code)


@app.command()
def router(listen: ListenOpt = None,
           multicast: MulticastOpt = False) -> None:
    """Host a Zenoh router in this process (no external binary) until Ctrl-C."""
    import time

    from dmpc.bus.session import BusError, session_config
    from dmpc.runtime.signals import sigterm_as_interrupt

    sigterm_as_interrupt()
    endpoints = list(listen or ["tcp/0.0.0.0:7447"])
    try:
        config = session_config(mode="router", listen=endpoints, multicast=multicast)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    import zenoh

    try:
        session = zenoh.open(config)
    except Exception as exc:  # zenoh reports bind failures as a generic error
        error_line(f"router: cannot listen on {', '.join(endpoints)} ({exc})")
        raise typer.Exit(1) from None
    print(f"router listening on {', '.join(endpoints)} (Ctrl-C to stop)", flush=True)
    try:
        while True:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        session.close()


@app.command()
def run(scenario: ScenarioArg,
        out: Annotated[Optional[Path], typer.Option("--out", help="Run folder to write (default: runs/<scenario>-<time>).")] = None,
        steps: Annotated[Optional[int], typer.Option("--steps", min=1, help="Steps to run (default: the scenario's).")] = None,
        run_id: RunIdOpt = None, startup_timeout: StartupOpt = 60.0,
        quiet: Annotated[bool, typer.Option("--quiet", help="No progress bar.")] = False,
        set_: SetOpt = None) -> None:
    """Start the plant and every agent as processes on this machine and wait for the run."""
    import secrets

    from dmpc.records.report import print_summary
    from dmpc.runtime.launcher import launch
    from dmpc.runtime.setup import prepare

    prepared = prepare(_load(scenario, set_, steps))
    out = _default_out(out, prepared.name)
    rid = _run_id(run_id or f"{prepared.name}-{secrets.token_hex(4)}", prepared)
    result = launch(prepared, out, rid, startup_timeout=startup_timeout, show_progress=not quiet)
    if result.summary is not None:
        print_summary(result.summary, out)
    if result.code == EXIT_INTERRUPTED:
        error_line(result.message)
    elif result.code != 0:
        print(f"error: {result.message}", file=sys.stderr)  # keeps the children's log tails on their lines
    raise typer.Exit(result.code)


def _is_scenario_error(exc: Exception) -> bool:
    """ScenarioError, checked lazily: the scenario package (pydantic) is not always loaded."""
    module = sys.modules.get("dmpc.scenario.load")
    return module is not None and isinstance(exc, module.ScenarioError)


def main() -> None:
    """Console entry point: maps expected errors to one line and exit code 2."""
    silence_c_stdout()
    try:
        # without standalone mode, click returns the code of typer.Exit instead of raising it
        code = app(standalone_mode=False)
        if isinstance(code, int) and code != 0:
            sys.exit(code)
    except (DesignError, RunFolderError, InputError) as exc:
        error_line(str(exc))
        sys.exit(EXIT_INPUT)
    except click.exceptions.Exit as exc:
        sys.exit(exc.exit_code)
    except KeyboardInterrupt:
        error_line("interrupted")
        sys.exit(EXIT_INTERRUPTED)
    except click.exceptions.Abort:
        error_line("aborted")
        sys.exit(EXIT_INTERRUPTED)
    except click.ClickException as exc:  # usage errors: unknown option, missing argument, bad value
        exc.show()
        sys.exit(exc.exit_code)
    except Exception as exc:
        if not _is_scenario_error(exc):
            raise
        error_line(str(exc))
        sys.exit(EXIT_INPUT)


if __name__ == "__main__":
    main()

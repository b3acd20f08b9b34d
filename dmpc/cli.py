"""The ``dmpc`` command line."""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from dmpc.console import error_line, silence_c_stdout, stdout_console
from dmpc.design import DesignError
from dmpc.records.run_folder import RunFolderError
from dmpc.scenario import ScenarioError, load_scenario, parse_override

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


def _load(path: Path, overrides: list[str] | None, steps: int | None = None):
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
             out: Annotated[Path, typer.Option("--out", help="Run folder to write (created).")],
             steps: Annotated[Optional[int], typer.Option("--steps", min=1, help="Steps to run (default: the scenario's).")] = None,
             set_: SetOpt = None,
             quiet: Annotated[bool, typer.Option("--quiet", help="No progress bar.")] = False) -> None:
    """Run every agent, the barrier and the plant in this process (in-memory bus)."""
    from dmpc.runtime.inprocess import simulate as run_inprocess
    from dmpc.records.report import print_summary
    from dmpc.records.session import RunRecorder

    prepared = _prepare(scenario, set_, steps)
    with RunRecorder(out, prepared, show_progress=not quiet) as recorder:
        run = run_inprocess(prepared, recorder.on_step)
        summary = recorder.complete(method="tv-box", runtime="in-process",
                                    failure=run.plant.failure or None)
    print_summary(summary, out)
    if run.plant.failure:
        raise typer.Exit(1)


def main() -> None:
    """Console entry point: maps expected errors to one line and exit code 2."""
    silence_c_stdout()
    try:
        app(standalone_mode=False)
    except (ScenarioError, DesignError, RunFolderError, InputError) as exc:
        error_line(str(exc))
        sys.exit(EXIT_INPUT)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except KeyboardInterrupt:
        error_line("interrupted")
        sys.exit(EXIT_INTERRUPTED)
    except Exception as exc:  # click usage errors and aborts
        import click

        if isinstance(exc, click.exceptions.ClickException):
            exc.show()
            sys.exit(exc.exit_code)
        if isinstance(exc, click.exceptions.Abort):
            error_line("aborted")
            sys.exit(EXIT_INTERRUPTED)
        raise


if __name__ == "__main__":
    main()

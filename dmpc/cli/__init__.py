"""The ``dmpc`` command line: its commands (:mod:`.local`, :mod:`.network`, :mod:`.launch`),
the options they share (:mod:`.common`), and the entry point that turns expected errors into one
line and an exit code."""
from __future__ import annotations

import functools
import logging
import os
import sys

import click
import typer

from dmpc.cli import launch, local, network
from dmpc.cli.common import app, scenario_app
from dmpc.core.errors import InputError
from dmpc.plant.models import PlantModelError
from dmpc.records.files import STEP_LOG
from dmpc.records.run_folder import RecordWriteError
from dmpc.runtime.output import guard_output
from dmpc.terminal import console, signals
from dmpc.terminal.console import error_line, silence_c_stdout
from dmpc.terminal.exit_codes import EXIT_FAILED, EXIT_INPUT, EXIT_INTERRUPTED

COMMANDS = (local.validate, local.design, local.simulate, network.agent, network.coordinator, network.plant,
            network.router, network.relay, network.certs, network.setpoint, launch.run, launch.bench, local.report, launch.watch,
            local.compare, local.roa)
"""Every command, in the order ``dmpc --help`` lists them."""
for command in COMMANDS:
    app.command()(command)
scenario_app.command("schema")(local.scenario_schema)


def _expand_multi_values(args: list[str]) -> list[str]:
    """``--N 3 5 8`` -> ``--N 3 --N 5 --N 8`` (and the same for ``--methods`` and ``--triggers``): click options take
    one value each, so the values that follow these options are given one option each."""
    import re

    takes = {"--N": re.compile(r"^[+-]?\d+(\.\d*)?$"), "--methods": re.compile(r"^[a-z][a-z0-9-]*$"),
             "--triggers": re.compile(r"^[a-z][a-z0-9-]*$")}
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


def main() -> None:
    """Console entry point: maps expected errors to one line and exit code 2."""
    signals.sigterm_as_interrupt()  # from the start: SIGTERM during the design ends the process cleanly too
    silence_c_stdout()
    guard_output()  # a child of `dmpc run` outlives its launcher's pipes (dmpc.runtime.output)
    code = _run_app()
    zenoh_bus = sys.modules.get("dmpc.bus.zenoh_bus")
    interrupted = code == EXIT_INTERRUPTED and signals.handles_interrupts()
    if interrupted or (zenoh_bus is not None and zenoh_bus.sessions_left_open()):
        # A Zenoh session still closing in the background would abort a normal interpreter exit.
        # After an interrupt that passed through code run by exec() (a dataclass being made),
        # CPython would end the process by SIGINT instead of with exit code 130.
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
    except InputError as exc:  # a flag, the scenario, a design that cannot work, a folder
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

"""What the commands of the ``dmpc`` command line share: the typer app, the options that several
commands take, and the steps from their flags to a prepared run or an open bus."""
from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Optional

import typer

from dmpc.bus import keys
from dmpc.bus.faults import FaultyBus
from dmpc.core.errors import InputError
from dmpc.methods import lacks, method_spec
from dmpc.prepared.bundle import load_bundle
from dmpc.terminal.console import error_line
from dmpc.terminal.exit_codes import EXIT_ADDRESS_IN_USE, EXIT_FAILED, EXIT_OK, EXIT_VERDICT

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Distributed MPC with time-varying terminal sets: design, simulate, run over Zenoh.")
scenario_app = typer.Typer(add_completion=False, no_args_is_help=True, help="Scenario file tools.")
app.add_typer(scenario_app, name="scenario")

ScenarioArg = Annotated[Path, typer.Argument(help="Scenario YAML file.", show_default=False)]
SetOpt = Annotated[Optional[list[str]], typer.Option("--set", help="Override a field: KEY=VALUE, e.g. family.M=16 (repeatable).")]
ModelOpt = Annotated[Optional[str], typer.Option("--model", help="Your own plant: module:function or path/file.py:function, a function (x, u, k) -> x_next that replaces the linear plant (a flag only: never read from a scenario file).", show_default=False)]
MethodOpt = Annotated[Optional[str], typer.Option("--method", help="Control method: tv-box (default), tv-box-opt, tv-box-coop, fixed-box, ellipsoid, ellipsoid-adaptive, centralized (sets options.method).", show_default=False)]
ServerModeOpt = Annotated[str, typer.Option("--mode", help="Zenoh mode: peer, client, or router (agents then connect as clients).")]
StepsOpt = Annotated[Optional[int], typer.Option("--steps", min=1, help="Steps to run (default: the scenario's).")]
QuietTableOpt = Annotated[bool, typer.Option("--quiet", help="No progress bar and no summary table.")]


Override = str | tuple[str, object]
"""A scenario override: a ``--set`` text (``KEY=VALUE``, the value read as YAML), or a (key, value)
pair from a typed flag such as ``--loss``, passed on as it is."""


def with_method(overrides: Sequence[Override] | None, method: str | None) -> list[Override]:
    """The overrides plus ``options.method`` from ``--method`` (checked: InputError if unknown)."""
    extra = list(overrides or [])
    if method is not None:
        try:
            method_spec(method)
        except ValueError as exc:
            raise InputError(f"--method: {exc}") from None
        extra.append(("options.method", method))
    return extra


def with_model(prepared, model: str | None):
    """``prepared`` with the plant function of ``--model`` (InputError if it cannot be imported)."""
    if model is None:
        return prepared
    from dmpc.setup.plant import load_plant_function, with_plant_function  # start-up time: it loads pydantic

    try:
        function, name = load_plant_function(model)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    return with_plant_function(prepared, function, name)


def default_out(out: Path | None, scenario_name: str) -> Path:
    """``out`` if given, else ``runs/<scenario_name>-<date>-<time>`` (the name made safe for a path)."""
    if out is not None:
        return out
    import re
    import time

    safe = re.sub(r"[^A-Za-z0-9_.-]", "-", scenario_name)[:40]
    return Path("runs") / f"{safe}-{time.strftime('%Y%m%d-%H%M%S')}"


def load_scenario_file(path: Path, overrides: Sequence[Override] | None, steps: int | None = None):
    """Load the scenario file ``path`` with ``overrides`` (``--set``) applied in order, then ``steps``."""
    from dmpc.scenario import load_scenario, parse_override  # start-up time: pydantic only where needed

    pairs = {}
    for item in overrides or []:
        key, value = parse_override(item) if isinstance(item, str) else item
        pairs[key] = value
    if steps is not None:
        pairs["steps"] = steps
    return load_scenario(path, pairs)


def prepare_scenario(path: Path, overrides: Sequence[Override] | None, steps: int | None = None):
    """The prepared run of the scenario file ``path`` with ``overrides`` and ``steps``
    (:func:`load_scenario_file`)."""
    from dmpc.setup import prepare  # start-up time: it loads pydantic

    return prepare(load_scenario_file(path, overrides, steps))


def run_exit_code(summary: dict | None, failure: str = "") -> int:
    """1 when the run failed to run (``failure`` says why), 3 when it ran but the verdict of its
    ``summary`` is failed, else 0."""
    if failure:
        return EXIT_FAILED
    if summary is not None and summary.get("verdict") == "failed":
        return EXIT_VERDICT
    return EXIT_OK

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


@dataclass(frozen=True)
class FaultFlags:
    """``--delay``, ``--jitter``, ``--loss``, ``--seed`` and ``--deadline``: faults on every link."""

    delay: float | None = None
    jitter: float | None = None
    loss: float | None = None
    seed: int | None = None
    deadline: float | None = None

    def overrides(self, set_: Sequence[Override] | None) -> list[Override]:
        """``set_`` plus the fault flags given."""
        return fault_overrides(set_, self.delay, self.jitter, self.loss, self.seed, self.deadline)


@dataclass(frozen=True)
class NodeFlags:
    """The flags of a process of a run over Zenoh (``dmpc agent``, ``coordinator``, ``plant``):
    the scenario's overrides and faults, the design file, and how it reaches the bus.

    Attributes
    ----------
    connect, listen : list of str or None
        The Zenoh endpoints to connect to and to listen on (``--connect``, ``--listen``).
    mode : str
        ``peer``, ``client`` or ``router`` (``--mode``).
    run_id : str or None
        The run's id (``--run-id``); None: from the scenario's name.
    design_file : path or None
        A ``design.json`` to use instead of designing (``--design``).
    startup_timeout : float
        Seconds to wait for the session and the run's start (``--startup-timeout``).
    steps : int or None
        Overrides the scenario's steps (``--steps``).
    multicast : bool
        Find peers by multicast scouting (``--multicast``).
    lease : float or None
        The Zenoh lease in seconds (``--lease``).
    zenoh_config : path or None
        A Zenoh configuration file (``--zenoh-config``).
    tls : path or None
        The certificate directory (``--tls``).
    faults : FaultFlags
        The fault flags, applied to every link.
    set_ : sequence of overrides or None
        The scenario's overrides (``--set``).
    model : str or None
        The plant's model function (``--model``)."""

    connect: list[str] | None = None
    listen: list[str] | None = None
    mode: str = "peer"
    run_id: str | None = None
    design_file: Path | None = None
    startup_timeout: float = 30.0
    steps: int | None = None
    multicast: bool = False
    lease: float | None = None
    zenoh_config: Path | None = None
    tls: Path | None = None
    faults: FaultFlags = FaultFlags()
    set_: Sequence[Override] | None = None
    model: str | None = None

    def prepare(self, scenario: Path):
        """The prepared run of ``scenario`` (or of a run bundle) with these flags' overrides and faults."""
        return prepare_for_process(scenario, self.faults.overrides(self.set_), self.design_file, self.steps)

    def open_bus(self, role: str, shared: bool = False):
        """The Zenoh bus of ``role`` (its certificate with ``--tls``); ``shared``: one bus for many agents."""
        return open_bus(self.mode, self.connect, self.listen, self.multicast, self.lease, self.zenoh_config,
                        self.startup_timeout, self.tls, role, shared)


def prepare_for_process(scenario: Path, set_: Sequence[Override] | None, design_file: Path | None,
                         steps: int | None = None):
    """The prepared run of a process: from a run bundle (``scenario`` a ``.json`` written by
    ``dmpc run``, which takes no ``set_``, ``design_file`` or ``steps``), else from the scenario file
    with the overrides ``set_``, ``steps`` and the design read from ``design_file`` if given."""
    if scenario.suffix == ".json":
        # a run bundle written by ``dmpc run`` (no scenario schema needed: smaller, faster agents)
        if set_ or design_file or steps:
            raise InputError("--set, --design and --steps do not apply to a run bundle (.json)")
        try:
            return load_bundle(scenario)
        except ValueError as exc:
            raise InputError(str(exc)) from None
    from dmpc.setup import prepare  # start-up time: pydantic only for a scenario file

    scn = load_scenario_file(scenario, set_, steps)
    data = None
    if design_file is not None:
        try:
            data = json.loads(design_file.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"--design {design_file}: cannot read a JSON design ({exc})") from None
    return prepare(scn, design_data=data)


def fault_overrides(set_: Sequence[Override] | None, delay, jitter, loss, seed, deadline) -> list[Override]:
    """The overrides ``set_`` plus the fault flags given (``delay``, ``jitter``, ``loss``, ``seed``,
    ``deadline``; None: not given), which apply to every link."""
    extra = list(set_ or [])
    for key, value in (("faults.delay_ms", delay), ("faults.jitter_ms", jitter), ("faults.loss", loss),
                       ("seed", seed), ("options.deadline", deadline)):
        if value is not None:
            extra.append((key, value))
    return extra


def with_faults(bus, prepared, receiver: str):
    """Wrap ``bus`` in the seeded fault injector when the ``prepared`` run asks for faults, with
    ``receiver`` the role that receives through it."""
    if prepared.faults.is_clean:
        return bus

    return FaultyBus(bus, receiver, prepared.faults)


def checked_run_id(given: str | None, prepared) -> str:
    """The ``given`` run id (``--run-id``), or one made from the ``prepared`` run's name, checked as a key
    chunk (InputError otherwise)."""
    import re

    rid = given or re.sub(r"[^A-Za-z0-9_.-]", "-", prepared.name)[:64]
    try:
        return keys.check_chunk(rid, "run id")
    except ValueError as exc:
        raise InputError(f"--run-id: {exc}") from None


def role_security(tls_dir: Path | None, role: str):
    """(TlsFiles, access control) of ``role`` from the certificate directory ``tls_dir``, or (None, None)
    without one."""
    if tls_dir is None:
        return None, None
    from dmpc.security.files import node_security  # start-up time: zenoh only for network commands

    try:
        return node_security(tls_dir, role)
    except ValueError as exc:
        raise InputError(str(exc)) from None


def open_bus(mode: str, connect, listen, multicast: bool, lease: float | None, config_file: Path | None,
              timeout: float, tls_dir: Path | None = None, role: str = "", shared: bool = False):
    """Open the Zenoh bus of a process: ``mode`` (peer, client, router), the endpoints to ``connect`` to
    and to ``listen`` on, ``multicast`` scouting, the ``lease`` (s), a Zenoh ``config_file``, waiting
    at most ``timeout`` seconds; with ``tls_dir``, the certificate of ``role``; ``shared``: one bus
    for many agents. InputError for settings that do not make a session; a bus that does not open
    is reported and the command exits (with the address-in-use code when the address is taken)."""
    from dmpc.bus.session import (  # start-up time: zenoh only for network commands
        AddressInUse,
        BusError,
        session_config,
    )
    from dmpc.bus.zenoh_bus import ZenohBus  # start-up time: zenoh only for network commands

    tls, acl = role_security(tls_dir, role)
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


def listed(names: list[str], shown: int = 20) -> str:
    """The names, comma-separated; the first ``shown`` and the count beyond that."""
    if len(names) <= shown:
        return ", ".join(names)
    return f"{', '.join(names[:shown])}, ... ({len(names)} in all)"


PlantTimeoutOpt = Annotated[float, typer.Option("--plant-timeout", min=0.1, help="With an outside plant: seconds to wait for the state of each step before the run stops (docs/protocol.md).")]
PLANT_SIDES = ("internal", "external")


def checked_side(value: str, flag: str) -> str:
    """``value`` if it is ``internal`` or ``external``; InputError naming the option ``flag`` otherwise."""
    if value not in PLANT_SIDES:
        raise InputError(f"{flag}: expected internal or external, got {value!r}")
    return value


def check_mode(mode: str) -> None:
    """InputError unless ``mode`` is ``peer``, ``client`` or ``router``."""
    if mode not in ("peer", "client", "router"):
        raise InputError(f"--mode: expected peer, client or router, got {mode!r}")


def require_agents(prepared, role: str) -> None:
    """InputError unless the method of the ``prepared`` run runs agents (``centralized`` has no agent
    or plant process): ``dmpc role`` cannot run it."""
    if (error := lacks(prepared.method, "distributed")) is not None:
        raise InputError(f"dmpc {role}: {error}, and no plant process: use dmpc simulate or dmpc run, which run "
                         "it in one process")

MethodsOpt = Annotated[Optional[list[str]], typer.Option("--methods", help="Methods to run (default: all): --methods tv-box centralized ...", show_default=False)]


def checked_methods(methods: list[str] | None, setpoints: bool = False) -> list[str]:
    """The ``methods`` of ``--methods`` checked (all by default; with ``setpoints``, those that track
    setpoints); InputError otherwise."""
    from dmpc.evaluation.compare import check_methods  # start-up time: the comparison only for `dmpc compare`

    try:
        return check_methods(methods, setpoints)
    except ValueError as exc:
        raise InputError(f"--methods: {exc}") from None


def table(title: str, header: list[str], rows: list[list[str]]):
    """A rich table titled ``title`` with the columns ``header`` and the ``rows`` (text)."""
    from rich import box
    from rich.table import Table

    table = Table(title=title, box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True)
    for name in header:
        table.add_column(name, justify="left" if name in ("method", "verdict") else "right", no_wrap=True)
    for row in rows:
        table.add_row(*row)
    return table

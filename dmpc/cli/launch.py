"""The commands that start or watch a whole run: ``dmpc run`` (every process on this machine),
``dmpc watch`` (the live view) and ``dmpc bench``."""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from dmpc.bus import keys
from dmpc.cli.common import (
    ConnectOpt,
    DeadlineOpt,
    DelayOpt,
    InputError,
    JitterOpt,
    LeaseOpt,
    LossOpt,
    MethodOpt,
    ModelOpt,
    PlantTimeoutOpt,
    ScenarioArg,
    SeedOpt,
    SetOpt,
    StartupOpt,
    StepsOpt,
    TlsOpt,
    checked_run_id,
    checked_side,
    default_out,
    fault_overrides,
    load_scenario_file,
    role_security,
    run_exit_code,
    with_method,
    with_model,
)
from dmpc.methods import method_spec
from dmpc.terminal import signals
from dmpc.terminal.console import error_line, stdout_console
from dmpc.terminal.exit_codes import EXIT_INTERRUPTED


def _run_centralized_here(prepared, out: Path | None, quiet: bool, network_flags: list[str]) -> None:
    """``dmpc run --method centralized``: one QP over the whole system per step, in this process."""
    from dmpc.records.session import RunRecorder  # start-up time: it loads pydantic
    from dmpc.records.tables import print_summary  # start-up time: tables only where printed
    from dmpc.runtime.inprocess import record_run  # start-up time: the in-process runtime only where it runs

    if network_flags:
        raise InputError(f"{', '.join(network_flags)}: method 'centralized' runs in one process without a bus, "
                         "so there are no links to configure")
    out = default_out(out, prepared.name)
    print("method centralized: one QP over the whole system, run in this process (no agents, no Zenoh)",
          file=sys.stderr)
    with RunRecorder(out, prepared, show_progress=not quiet) as recorder:
        summary, failure = record_run(prepared, recorder)
    print_summary(summary, out)
    raise typer.Exit(run_exit_code(summary, failure))


RUN_ID_HELP = ("The run's id, the key prefix shared by its processes (default: the scenario's name and 8 random hex "
               "digits, e.g. paper-1a2b3c4d, printed when the run starts). An operator's program and dmpc watch "
               "--connect need it.")


def default_run_id(name: str) -> str:
    """``dmpc run``'s id of a run of the scenario ``name``: the name, made a key chunk (``A-Z a-z 0-9 _ . -``,
    at most 55 characters), ``-`` and 8 random hex digits (``paper-1a2b3c4d``), as ``dmpc.run`` makes it."""
    import re
    import secrets

    return re.sub(r"[^A-Za-z0-9_.-]", "-", name)[:55] + "-" + secrets.token_hex(4)


def designing_line(run_id: str, port: int | None, tls: bool) -> str:
    """What ``dmpc run`` says before it designs: the run's id ``run_id``, and that the coordinator
    listens (on ``port`` of this machine, over TLS with ``tls``, when the port is fixed) once the
    design is done."""
    where = f"on {'tls' if tls else 'tcp'}/127.0.0.1:{port} " if port is not None else ""
    return f"run id {run_id}: designing the controllers; the coordinator listens {where}once the design is done"


def run(scenario: ScenarioArg,
        out: Annotated[Optional[Path], typer.Option("--out", help="Run folder to write (default: runs/<scenario>-<time>).")] = None,
        steps: StepsOpt = None,
        run_id: Annotated[Optional[str], typer.Option("--run-id", help=RUN_ID_HELP, show_default=False)] = None,
        startup_timeout: StartupOpt = 60.0,
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
    from dmpc.records.tables import print_summary  # start-up time: tables only where printed
    from dmpc.runtime.launcher import TOPOLOGIES, default_topology, launch  # start-up time: only for `dmpc run`
    from dmpc.runtime.supervisor import RestartPolicy  # start-up time: only for `dmpc run`
    from dmpc.setup import prepare  # start-up time: it loads pydantic

    if tls is not None and secure:
        raise InputError("--tls and --secure exclude each other (--secure makes its own certificates)")
    scn = load_scenario_file(scenario, with_method(fault_overrides(set_, delay, jitter, loss, seed, deadline), method),
                             steps)
    if not method_spec(scn.options.method).distributed:
        prepared = with_model(prepare(scn), model)
        network = {"--tls": tls is not None, "--secure": secure, "--topology": topology is not None,
                   "--run-id": run_id is not None, "--delay": delay is not None, "--jitter": jitter is not None,
                   "--loss": loss is not None, "--deadline": deadline is not None}
        network["--watch"] = watch
        network.update({"--restart": restart > 0, "--fail-fast": fail_fast, "--lease": lease is not None,
                        "--agents-per-process": agents_per_process > 1})
        _run_centralized_here(prepared, out, quiet, [flag for flag, given in network.items() if given])
    # what needs no design is checked before it: the design may take minutes
    external = checked_side(plant_side, "--plant") == "external"
    if external and model is not None:
        raise InputError("--model: the plant is outside (--plant external): give the model to it")
    names = [sub.name for sub in scn.resolved_subsystems()]
    for role in [keys.COORDINATOR_ROLE] + [keys.agent_role(name) for name in names] if tls is not None else []:
        role_security(tls, role)  # every file present before any process starts
    if agents_per_process > 1 and (tls is not None or secure):
        raise InputError(f"--agents-per-process {agents_per_process}: a certificate belongs to one agent, so agents "
                         f"sharing a process cannot use {'--tls' if tls is not None else '--secure'}; leave "
                         "--agents-per-process at 1 for a run over TLS")
    if topology is not None and topology not in TOPOLOGIES:
        raise InputError(f"--topology: expected mesh or star, got {topology!r}")
    topology = topology or default_topology(-(-len(names) // agents_per_process))
    rid = checked_run_id(run_id or default_run_id(scn.name), None)
    if external or not quiet:
        print(designing_line(rid, port, tls is not None or secure), file=sys.stderr, flush=True)
    prepared = with_model(prepare(scn), model)
    out = default_out(out, prepared.name)
    watcher = None
    if watch:
        from dmpc.watch.attach import Watcher  # start-up time: the live view only with --watch

        if tls is not None:
            role_security(tls, "observer")
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
    raise typer.Exit(result.code if result.code != 0 else run_exit_code(result.summary))


def bench(quick: Annotated[bool, typer.Option("--quick", help="A subset that runs in under a minute.")] = False,
          as_json: Annotated[bool, typer.Option("--json", help="Print the results as JSON.")] = False,
          write: Annotated[Optional[Path], typer.Option("--write", help="Write the Markdown report here (figures and the raw results as .json beside it; a hand-written history at its end is kept).")] = None) -> None:
    """Measure QP, multi-process step time, memory, design time and baselines on this machine."""
    from dmpc.bench.results import (  # start-up time: the benchmarks only for `dmpc bench`
        markdown,
        run_all,
        write_report,
    )

    root = Path.cwd()
    if not (root / "scenarios" / "paper.yaml").exists():
        raise InputError("run dmpc bench from the project folder (it needs scenarios/)")
    results = run_all(quick, root, show_progress=not as_json)
    if write is not None:
        write_report(results, write, "dmpc bench" + (" --quick" if quick else "") + f" --write {write}")
    if as_json:
        print(json.dumps({**results["headline"], "results": results}, indent=2))
    else:
        stdout_console().print(markdown(results, "dmpc bench"))


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
        raise InputError("--connect needs --run-id: the id of the run to watch (the one dmpc run printed, its "
                         "scenario's name and 8 hex digits unless given --run-id; dmpc plant and dmpc coordinator use "
                         "the scenario's name unless given one)")
    if tls is not None and not connect:
        raise InputError("--tls applies to --connect only")
    if run_dir is not None and not run_dir.is_dir():
        raise InputError(f"{run_dir}: no such folder")
    if run_id is not None:
        run_id = checked_run_id(run_id, None)
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
    if connect and run_id is not None:  # --connect needs --run-id (checked above)
        from dmpc.watch.observer import BusObserver  # start-up time: zenoh only when watching a live run

        tls_files, acl = role_security(tls, "observer")
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
    signals.sigterm_as_interrupt()
    if observer is not None:
        observer.start()
    try:
        server.serve(on_ready=announce)
    finally:
        if observer is not None:
            observer.close()

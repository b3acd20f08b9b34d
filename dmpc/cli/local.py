"""The commands that work in this process, without a bus: check and design a scenario, simulate
it, compare the methods, their region of attraction, and the figures of a run."""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from dmpc.cli.common import (
    InputError,
    MethodOpt,
    MethodsOpt,
    ModelOpt,
    ScenarioArg,
    SetOpt,
    StepsOpt,
    checked_methods,
    default_out,
    load_scenario_file,
    prepare_scenario,
    run_exit_code,
    table,
    with_method,
    with_model,
)
from dmpc.prepared import estimation_json
from dmpc.records.files import COMPARISON, SUMMARY
from dmpc.records.run_folder import claim_folder, write_json
from dmpc.terminal.console import error_line, stderr_console, stdout_console
from dmpc.terminal.exit_codes import EXIT_VERDICT


def scenario_schema() -> None:
    """Print the JSON Schema of scenario files."""
    from dmpc.scenario import scenario_json_schema  # start-up time: pydantic only where needed

    print(json.dumps(scenario_json_schema(), indent=2))


def validate(scenario: ScenarioArg, set_: SetOpt = None) -> None:
    """Check a scenario file (schema and cross-field rules) without designing."""
    from dmpc.setup.coupling_check import scenario_coupling  # start-up time: pydantic and scipy only where needed

    scn = load_scenario_file(scenario, set_)
    subs = scn.resolved_subsystems()
    system = None
    if scn.estimation is not None:
        from dmpc.scenario import build_system  # start-up time: as above
        from dmpc.setup.estimation import check_estimation  # start-up time: as above

        system = build_system(scn)
        detectable = check_estimation(scn, system)[-1]  # DesignError (exit 2) where a condition fails
    print(f"{scenario}: valid ({len(subs)} subsystems, horizon {scn.horizon}, gains {scn.design.gains})")
    if scn.estimation is not None:
        print(f"estimation: detectable ({detectable.p} measured outputs, {detectable.nd} disturbances; the rank "
              f"condition holds per subsystem and for the coupled system, n + n_d = {detectable.rank}); "
              "'dmpc design' designs the gains")
    _warn_coupling(scenario_coupling(scn, system), scn.options.method, [s.name for s in subs])


def design(scenario: ScenarioArg, set_: SetOpt = None,
           as_json: Annotated[bool, typer.Option("--json", help="Print design.json instead of the report.")] = False) -> None:
    """Run the offline design (gains, terminal set, tubes) and report it."""
    from dmpc.cli.coupling import coupling_text  # start-up time: the check loads the scenario schema (pydantic)
    from dmpc.setup.coupling_check import design_coupling, design_with_coupling  # start-up time: as above

    prepared = prepare_scenario(scenario, set_)
    coupling = design_coupling(prepared)
    if as_json:
        print(json.dumps(design_with_coupling(prepared, coupling), indent=2))
    else:
        from dmpc.records.tables import design_report  # start-up time: tables only where printed

        report = design_report(prepared, coupling_text(coupling, prepared.names))
        for what, value in estimation_rows(prepared):
            report.add_row(what, value)
        stdout_console().print(report)
    _warn_coupling(coupling, prepared.method, prepared.names)


def estimation_rows(prepared) -> list[tuple[str, str]]:
    """The rows of the design report on the ``prepared`` run's estimator ([] without one): the coupled
    estimator's spectral radius, then each agent's filter."""
    if prepared.estimator is None:
        return []
    data = estimation_json(prepared.estimator)
    rows = [("estimator", f"coupled spectral radius {data['coupled_radius']:.4f} (the estimation error's dynamics "
                          "(I - L C) A over the whole system, couplings included; stable below 1)")]
    for name, sub in data["subsystems"].items():
        rows.append((f"L_{name}", f"{sub['outputs']} measured output(s), {sub['disturbances']} {sub['disturbance']} "
                                  f"disturbance(s); own filter's spectral radius {sub['radius']:.4f}"))
    return rows


def _warn_coupling(coupling, method: str, names: list[str]) -> None:
    """The one warning line on stderr where the method is likely to fail on the input coupling."""
    from dmpc.cli.coupling import coupling_warning  # start-up time: the check loads the scenario schema (pydantic)

    line = coupling_warning(coupling, method, names)
    if line is not None:
        print(f"warning: {line}", file=sys.stderr, flush=True)


def simulate(scenario: ScenarioArg,
             out: Annotated[Optional[Path], typer.Option("--out", help="Run folder to write (default: runs/<scenario>-<time>).")] = None,
             steps: StepsOpt = None,
             set_: SetOpt = None,
             quiet: Annotated[bool, typer.Option("--quiet", help="No progress bar.")] = False,
             method: MethodOpt = None, model: ModelOpt = None) -> None:
    """Run every agent, the barrier and the plant in this process (in-memory bus)."""
    from dmpc.records.session import RunRecorder  # start-up time: it loads pydantic
    from dmpc.records.tables import print_summary  # start-up time: tables only where printed
    from dmpc.runtime.inprocess import record_run  # start-up time: the in-process runtime only where it runs

    prepared = with_model(prepare_scenario(scenario, with_method(set_, method), steps), model)
    out = default_out(out, prepared.name)
    with RunRecorder(out, prepared, show_progress=not quiet) as recorder:
        summary, failure = record_run(prepared, recorder)
    print_summary(summary, out)
    raise typer.Exit(run_exit_code(summary, failure))


def report(run_dir: Annotated[Path, typer.Argument(help="A run folder, or a folder with comparison.json from 'dmpc compare'.", show_default=False)],
           out: Annotated[Optional[Path], typer.Option("--out", help="Folder for the PNG files (default: RUN_DIR/figures).")] = None) -> None:
    """Draw the paper's five figures (terminal sets, states, inputs, J, S) from a run or comparison folder, and
    for a run folder the agents' solves per step."""
    from dmpc.plots.report import ReportError, draw  # start-up time: the figures (matplotlib) only for `dmpc report`

    notes: list[str] = []
    try:
        paths = draw(run_dir, out, notes)
    except ReportError as exc:
        raise InputError(str(exc)) from None
    for line in notes:
        print(line)
    for path in paths:
        print(path)


TriggersOpt = Annotated[Optional[list[str]], typer.Option("--triggers", help="Run each method with each trigger, e.g. --triggers always event (default: the scenario's own; event only with tv-box and tv-box-opt).", show_default=False)]


def compare(scenario: ScenarioArg,
            out: Annotated[Path, typer.Option("--out", help="Folder to write: DIR/<method>/ run folders and DIR/comparison.json.")],
            steps: Annotated[Optional[int], typer.Option("--steps", min=1, help="Steps per run (default: the scenario's).")] = None,
            methods: MethodsOpt = None, set_: SetOpt = None,
            quiet: Annotated[bool, typer.Option("--quiet", help="No progress bars.")] = False,
            triggers: TriggersOpt = None) -> None:
    """Run every method on the same scenario in this process, compare them, and draw the figures."""
    from dmpc.evaluation.compare import compare as run_compare  # start-up time: the comparison only for `dmpc compare`
    from dmpc.evaluation.compare import (  # start-up time: as above
        comparison_header,
        comparison_legend,
        comparison_rows,
        cost_ratios,
    )
    from dmpc.methods import DEFAULT_METHOD  # start-up time: as above

    scn = load_scenario_file(scenario, set_, steps)
    _check_triggers(checked_methods(methods, bool(scn.setpoints)), triggers, scn)
    data = run_compare(scn, out, methods, show_progress=not quiet, triggers=triggers)
    console = stdout_console()
    console.print(table(f"methods on '{data['scenario']}'", comparison_header(data), comparison_rows(data)))
    console.print(comparison_legend(data))
    for name, why in data.get("skipped", {}).items():
        console.print(f"not run: {name}: {why}")
    ratio = cost_ratios(data).get(DEFAULT_METHOD)
    if ratio is not None:
        console.print(f"closed-loop cost {DEFAULT_METHOD} / centralized = {ratio:.4f}")
    tracking = cost_ratios(data, key="tracking_cost").get(DEFAULT_METHOD)
    if tracking is not None:
        console.print(f"tracking cost {DEFAULT_METHOD} / centralized = {tracking:.4f} (around the references)")
    console.print(f"comparison: {out / COMPARISON}")
    _draw_comparison_figures(out)
    failed = [m for m, e in data["methods"].items() if e.get("verdict") == "failed"]
    if failed:
        error_line(f"verdict failed for {', '.join(failed)} (reasons in {', '.join(str(out / m / SUMMARY) for m in failed)})")
        raise typer.Exit(EXIT_VERDICT)


def _check_triggers(methods: list[str], triggers: list[str] | None, scn) -> None:
    """InputError (``--triggers: ...``) for triggers that are unknown, listed twice, not possible
    with the scenario's options, or leave no method to run."""
    from dmpc.evaluation.compare import (  # start-up time: the comparison only for `dmpc compare`
        check_triggers,
        runnable,
    )

    try:
        runnable(methods, check_triggers(triggers, scn), bool(scn.setpoints))
    except ValueError as exc:
        raise InputError(f"--triggers: {exc}") from None


def _draw_comparison_figures(out: Path) -> None:
    """Draw the comparison figures (:func:`dmpc.plots.report.draw_comparison`); a failure is reported, not raised."""
    from dmpc.plots.report import draw_comparison  # lazy: matplotlib only when drawing

    try:
        paths = draw_comparison(out)
    except Exception as exc:  # noqa: BLE001 - the results are written already; a drawing problem must not hide them
        print(f"figures: not drawn ({type(exc).__name__}: {exc})", file=sys.stderr)
        return
    if paths:
        print(f"figures: {', '.join(str(p) for p in paths)}")


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
    from dmpc.evaluation.roa import (
        ROA_FILE,
        ROA_LEGEND,
        ROA_PLOT,
        plot_roa,
        region_of_attraction,
        roa_header,
        roa_rows,  # start-up time: the region of attraction only for `dmpc roa`
    )

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
    methods = checked_methods(methods)
    scn = load_scenario_file(scenario, set_)
    if scn.setpoints:
        raise InputError(f"{scenario}: dmpc roa measures where regulation to the origin succeeds, and the scenario "
                         "has setpoints: run it without them (--set 'setpoints=[]')")
    out = out or default_out(None, f"roa-{scn.name}")
    claim_folder(out, ROA_FILE, "a region-of-attraction table")
    progress = None
    if not quiet:
        from dmpc.terminal.progress import RunProgress  # start-up time: the progress display only for `dmpc roa`

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
    console.print(table(f"region of attraction, '{data['scenario']}' ({samples} samples, |x_j| <= {data['box']:g}, "
                         f"seed {seed})", roa_header(data), roa_rows(data)))
    console.print(ROA_LEGEND)
    console.print(f"results: {out / ROA_FILE}, plot: {plot}")

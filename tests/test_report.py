"""dmpc report: the six figures of a run folder, the five of a comparison folder, and bad input."""
from __future__ import annotations

import json
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest

from dmpc import cli
from dmpc.plots import report
from dmpc.plots.style import use_log
from tests.helpers.cli import call

FIGURE_FILES = [f"{name}.png" for name in report.FIGURES]
"""A comparison folder's figures: the paper's five."""
RUN_FIGURE_FILES = [f"{name}.png" for name in report.RUN_FIGURES]
"""A run folder's: the paper's five and the solves per step."""
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def simulate(out: Path, overrides: dict | None = None) -> Path:
    """The records of ``dmpc simulate scenarios/paper.yaml --out out --set KEY=VALUE ...``."""
    sets = [arg for key, value in (overrides or {}).items() for arg in ("--set", f"{key}={value}")]
    code = cli.app(["simulate", "scenarios/paper.yaml", "--out", str(out), "--quiet", *sets], standalone_mode=False)
    assert code in (None, 0) and (out / "trajectory.npz").is_file()
    return out


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory) -> Path:
    return simulate(tmp_path_factory.mktemp("report") / "run")


def static_level(design: dict) -> float:
    """The comparator's common level r = min_l 1 / (sum_i ||Omega_{l,i}||_{P_i^-1})^2."""
    omega = np.asarray(design["omega"])
    inverses = [np.linalg.inv(np.asarray(P)) for P in design["P"]]
    sizes = [len(P) for P in design["P"]]
    starts = np.cumsum([0] + sizes)
    totals = [sum(np.sqrt(row[a:b] @ Pinv @ row[a:b]) for a, b, Pinv in zip(starts, starts[1:], inverses))
              for row in omega]
    return float(min(1.0 / t ** 2 for t in totals))


@pytest.fixture(scope="module")
def comparison_folder(tmp_path_factory, paper_run) -> Path:
    """tv-box (the paper run), a fake 'ellipsoid' (its copy with levels r) and a 'fixed-box' (N = 6)."""
    folder = tmp_path_factory.mktemp("compare")
    shutil.copytree(paper_run, folder / "tv-box", ignore=shutil.ignore_patterns("figures"))
    shutil.copytree(paper_run, folder / "ellipsoid", ignore=shutil.ignore_patterns("figures"))
    simulate(folder / "fixed-box", {"horizon": 6})
    arrays = dict(np.load(folder / "ellipsoid" / "trajectory.npz"))
    level = static_level(json.loads((folder / "ellipsoid" / "design.json").read_text()))
    arrays["r"] = np.full((arrays["x"].shape[0], 4), level)
    np.savez(folder / "ellipsoid" / "trajectory.npz", **arrays)
    methods = {}
    for method in ("tv-box", "fixed-box", "ellipsoid"):
        s = json.loads((folder / method / "summary.json").read_text())
        methods[method] = {"run_dir": method, "closed_loop_cost": s["closed_loop_cost"], "J": s["J"], "S": s["S"],
                           "steps_to_1e-3": None, "feasible": s["feasible"], "fallbacks": s["fallbacks"],
                           "solve_time_median_s": s["solve_time_median_s"]}
    (folder / "comparison.json").write_text(json.dumps({"scenario": "paper", "methods": methods}))
    return folder


def png_size(path: Path) -> tuple[int, int]:
    """Width and height from the PNG header; fails unless the file is a PNG."""
    head = path.read_bytes()[:24]
    assert head[:8] == PNG_SIGNATURE and head[12:16] == b"IHDR", f"{path} is not a PNG"
    return struct.unpack(">II", head[16:24])


def assert_figures(folder: Path, files: list[str] = RUN_FIGURE_FILES) -> None:
    """``folder`` holds exactly ``files`` (a run folder's figures by default), each a drawn PNG."""
    assert sorted(p.name for p in folder.glob("*.png")) == sorted(files)
    for name in files:
        width, height = png_size(folder / name)
        assert 500 <= width <= 2600 and 300 <= height <= 2600, (name, width, height)
        assert (folder / name).stat().st_size > 15_000, name  # not a blank canvas
    import matplotlib.image as mpimg

    for name in files:
        pixels = mpimg.imread(folder / name)
        assert pixels.std() > 0.02, name  # something is drawn


# ----------------------------------------------------------------------------- one run
def test_report_draws_the_six_figures_of_a_run(paper_run, tmp_path, monkeypatch, capsys):
    out = tmp_path / "figs"
    code, stdout, err = call(monkeypatch, capsys, "report", str(paper_run), "--out", str(out))
    assert code == 0, err
    assert_figures(out)
    assert [Path(line).name for line in stdout.split()] == RUN_FIGURE_FILES


def test_report_defaults_to_the_figures_subfolder(tmp_path, paper_run):
    run = tmp_path / "run"
    shutil.copytree(paper_run, run, ignore=shutil.ignore_patterns("figures"))
    paths = report.draw(run)
    assert [p.parent for p in paths] == [run / "figures"] * 6
    assert_figures(run / "figures")


def test_figure1_draws_one_box_per_step_where_they_are_recorded(paper_run):
    run = report.load_run(paper_run)
    plt = report._pyplot()
    fig = report._fig1(plt, [report.PlaneSet(run, run.method)], "t", [])
    try:
        boxes = [p for p in fig.axes[0].patches if type(p).__name__ == "Rectangle"]
        assert len(boxes) == run.x.shape[0] == 31
        first = boxes[0]
        np.testing.assert_allclose(first.get_xy(), -run.beta[0] * np.ones(2))  # alpha(0) = 0, beta(0) = 0.5
        np.testing.assert_allclose(first.get_width(), 2 * 0.5)
        trajectory = fig.axes[0].lines[0].get_xydata()
        np.testing.assert_allclose(trajectory, run.x[:, :2])
    finally:
        plt.close(fig)


def test_run_reads_bounds_names_and_dimensions(paper_run):
    run = report.load_run(paper_run)
    assert run.names == ["1", "2", "3", "4"] and run.n == [2] * 4 and run.m == [1] * 4
    assert all(lo.tolist() == [-2.5] and hi.tolist() == [2.5] for lo, hi in zip(run.lower, run.upper))
    assert run.method == "tv-box" and run.scenario == "paper" and run.r is None
    assert use_log([run.J]) and use_log([run.S])  # J falls by > 10 decades


def test_without_scenario_yaml_the_design_gives_the_dimensions(tmp_path, paper_run):
    run_dir = tmp_path / "run"
    shutil.copytree(paper_run, run_dir, ignore=shutil.ignore_patterns("figures", "scenario.yaml"))
    run = report.load_run(run_dir)
    assert run.n == [2] * 4 and run.m == [1] * 4 and run.lower == [None] * 4
    assert_figures(Path(report.draw_run(run_dir)[0]).parent)


def test_report_and_load_run_read_a_folder_alike(tmp_path, paper_run):
    """One reader: a scenario.yaml that no longer loads is left out, with a note, by the figures
    and by dmpc.load_run alike; both split the arrays by the names and sizes trajectory.npz holds."""
    import dmpc

    run_dir = tmp_path / "run"
    shutil.copytree(paper_run, run_dir, ignore=shutil.ignore_patterns("figures"))
    (run_dir / "scenario.yaml").write_text("name: paper\nsubsystems: not a list\n")
    notes: list[str] = []
    run = report.load_run(run_dir, notes)
    result = dmpc.load_run(run_dir)
    assert run.names == list(result.names) == ["1", "2", "3", "4"] and run.n == [2] * 4 and run.m == [1] * 4
    assert run.lower == [None] * 4 and result.dt is None
    assert len(notes) == 1 and "scenario.yaml does not load" in notes[0]
    np.testing.assert_array_equal(run.x[:, 2:4], result.x["2"])


def test_polytope_input_bounds_are_its_bounding_box():
    H = np.array([[1.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
    lower, upper = report._box_hull(H, np.array([2.0, 1.0, 1.0]))
    np.testing.assert_allclose(lower, [-1.0, -1.0], atol=1e-9)
    np.testing.assert_allclose(upper, [3.0, 3.0], atol=1e-9)


@pytest.mark.parametrize("n", [2, 3])
def test_ellipse_outline_is_the_projection_of_the_ellipsoid(n):
    rng = np.random.default_rng(n)
    G = rng.normal(size=(n, n))
    P = G @ G.T + n * np.eye(n)
    level = 2.0
    pts = report._ellipse_points(P, level)
    # the support of {x : x^T P x <= r} in direction d (in the first two coordinates) is sqrt(r d^T P^-1 d)
    Pinv = np.linalg.inv(P)
    for angle in np.linspace(0, np.pi, 7):
        d = np.zeros(n)
        d[:2] = [np.cos(angle), np.sin(angle)]
        support = np.sqrt(level * d @ Pinv @ d)
        assert abs((d[:2] @ pts).max() - support) < 1e-3 * support


# ----------------------------------------------------------------------------- figure 6: solves per step
@pytest.fixture(scope="module")
def event_run(tmp_path_factory) -> Path:
    return simulate(tmp_path_factory.mktemp("report-event") / "run", {"options.trigger": "event"})


def test_figure6_of_a_run_without_trigger_shows_every_agent_solving_at_every_step(paper_run):
    run = report.load_run(paper_run)
    summary = json.loads((paper_run / "summary.json").read_text())
    solves = run.solves
    assert solves.trigger == "always" and not solves.kept_recorded
    np.testing.assert_array_equal(solves.counts(), np.tile([4, 0, 0], (30, 1)))
    assert solves.notes() == [f"no event trigger: every agent solves at every step ({summary['solves']} QP solves)",
                              f"k = 0 took {summary['rounds_k0']} Jacobi rounds, a solve per agent in each"]
    plt = report._pyplot()
    fig = report._solves(plt, run, "t")
    try:
        top, bottom = fig.axes
        assert [c.get_label() for c in top.collections] == ["solved its QP"]
        np.testing.assert_array_equal(bottom.images[0].get_array(), np.zeros((4, 30)))
    finally:
        plt.close(fig)


def test_figure6_of_an_event_triggered_run_counts_the_solves_and_kept_plans_of_the_records(event_run):
    """Per step, the agents that solved and kept are trajectory.npz's; over the run (with every
    round of k = 0) summary.json's solves and keeps; the lower panel is the agents' steps."""
    npz = np.load(event_run / "trajectory.npz")
    summary = json.loads((event_run / "summary.json").read_text())
    run = report.load_run(event_run)
    solves = run.solves
    assert solves.trigger == "event" and solves.kept_recorded
    counts = solves.counts()
    np.testing.assert_array_equal(counts[:, 1], npz["kept"].sum(axis=1))
    np.testing.assert_array_equal(counts[:, 0] + counts[:, 1], 4)  # no fallback
    assert (counts[:, 0] * npz["rounds"]).sum() == summary["solves"] and counts[:, 1].sum() == summary["keeps"]
    reasons = ", ".join(f"{r} {n}" for r, n in summary["solve_reasons"].items())
    assert solves.notes()[:2] == [f"event trigger: {summary['solves']} QP solves, {summary['keeps']} plans kept",
                                  f"agents solved for: {reasons}"]
    plt = report._pyplot()
    fig = report._solves(plt, run, "t")
    try:
        top, bottom = fig.axes
        assert [c.get_label() for c in top.collections] == ["solved its QP", "kept its plan"]
        np.testing.assert_array_equal(bottom.images[0].get_array(), npz["kept"].T.astype(int))
        assert [t.get_text() for t in fig.legends[0].get_texts()] == ["solved its QP", "kept its plan", "4 agents"]
        assert f"{summary['solves']} QP solves" in fig.get_suptitle()
    finally:
        plt.close(fig)


def test_figure6_of_a_run_drawn_from_its_step_log_has_the_kept_plans_of_its_arrays(tmp_path, event_run):
    """A run that ended before its arrays were written: steps.jsonl's statuses give the same kept plans."""
    run_dir = tmp_path / "run"
    shutil.copytree(event_run, run_dir, ignore=shutil.ignore_patterns("figures", "trajectory.npz"))
    from_log, from_arrays = report.load_run(run_dir).solves, report.load_run(event_run).solves
    assert from_log.kept_recorded and from_log.counts()[:, 1].sum() > 0
    np.testing.assert_array_equal(from_log.counts(), from_arrays.counts())
    assert not any("do not say which plans were kept" in note for note in from_log.notes())
    assert len(report.draw_run(run_dir)) == 6


def test_figure6_notes_break_into_lines_between_notes():
    from dmpc.plots.solves import _lines

    assert _lines(["a" * 50, "b" * 30, "c" * 20], 90) == ["a" * 50 + "; " + "b" * 30, "c" * 20]
    assert _lines(["word " * 30], 40)[0] == ("word " * 8).strip()


# ----------------------------------------------------------------------------- bad input
def _not_a_run(tmp: Path) -> Path:
    (tmp / "empty").mkdir()
    return tmp / "empty"


def _no_trajectory(tmp: Path, run: Path) -> Path:
    # no arrays and no step log (a folder with a step log is drawn from it: test_records_streaming)
    shutil.copytree(run, tmp / "crashed", ignore=shutil.ignore_patterns("trajectory.npz", "summary.json", "figures",
                                                                       "steps.jsonl"))
    return tmp / "crashed"


def _broken_comparison(tmp: Path) -> Path:
    (tmp / "cmp").mkdir()
    (tmp / "cmp" / "comparison.json").write_text("{not json")
    return tmp / "cmp"


def _comparison_without_runs(tmp: Path) -> Path:
    (tmp / "cmp2").mkdir()
    (tmp / "cmp2" / "comparison.json").write_text(json.dumps({"methods": {"tv-box": {"run_dir": "missing"}}}))
    return tmp / "cmp2"


def _broken_trajectory(tmp: Path, run: Path) -> Path:
    shutil.copytree(run, tmp / "garbled", ignore=shutil.ignore_patterns("figures"))
    (tmp / "garbled" / "trajectory.npz").write_bytes(b"not a zip file")
    return tmp / "garbled"


@pytest.mark.parametrize("make, expected", [
    (lambda tmp, run: tmp / "does-not-exist", "does not exist"),
    (lambda tmp, run: Path("scenarios/paper.yaml"), "not a folder"),
    (lambda tmp, run: _not_a_run(tmp), "not a run folder"),
    (_no_trajectory, "no trajectory.npz"),
    (_broken_trajectory, "cannot be read"),
    (lambda tmp, run: _broken_comparison(tmp), "not valid JSON"),
    (lambda tmp, run: _comparison_without_runs(tmp), "none of the methods"),
], ids=["missing", "file", "empty-folder", "no-trajectory", "garbled-npz", "bad-json", "no-method-runs"])
def test_bad_input_exits_2_with_one_line(tmp_path, paper_run, monkeypatch, capsys, make, expected):
    code, _, err = call(monkeypatch, capsys, "report", str(make(tmp_path, paper_run)))
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and expected in lines[0], err
    assert "Traceback" not in err


def test_unwritable_output_exits_2(tmp_path, paper_run, monkeypatch, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    code, _, err = call(monkeypatch, capsys, "report", str(paper_run), "--out", str(blocker))
    assert code == 2 and err.startswith("error: cannot write")


# ----------------------------------------------------------------------------- comparison
def test_report_draws_the_comparison_figures(comparison_folder, monkeypatch, capsys):
    code, stdout, err = call(monkeypatch, capsys, "report", str(comparison_folder))
    assert code == 0, err
    assert_figures(comparison_folder / "figures", FIGURE_FILES)
    assert "not drawn" not in stdout


def test_comparison_reads_every_method_and_the_levels(comparison_folder):
    cmp = report.load_comparison(comparison_folder)
    assert list(cmp.runs) == ["tv-box", "fixed-box", "ellipsoid"] and not cmp.skipped
    assert cmp.runs["ellipsoid"].r.shape == (31, 4) and cmp.runs["tv-box"].r is None
    specs, notes = report._fig1_sets(cmp)
    assert [(s.method, s.boxes, s.ellipses) for s in specs] == [("tv-box", True, False), ("ellipsoid", False, True)]
    assert notes == []


def test_figure1_of_a_comparison_draws_boxes_and_one_static_ellipse(comparison_folder):
    cmp = report.load_comparison(comparison_folder)
    specs, _ = report._fig1_sets(cmp)
    plt = report._pyplot()
    fig = report._fig1(plt, specs, "t", [])
    try:
        ax = fig.axes[0]
        assert len([p for p in ax.patches if type(p).__name__ == "Rectangle"]) == 31  # tv-box only
        dashed = [line for line in ax.lines if line.get_linestyle() == "--" and len(line.get_xdata()) > 100]
        assert len(dashed) == 1  # a constant level: one ellipse
        P, r = cmp.runs["ellipsoid"].P[0], cmp.runs["ellipsoid"].r[0, 0]
        xy = dashed[0].get_xydata()
        np.testing.assert_allclose(np.einsum("ij,jk,ik->i", xy, P, xy), r, rtol=1e-9)
    finally:
        plt.close(fig)


def test_comparison_without_levels_says_so_and_still_draws(tmp_path, comparison_folder, monkeypatch, capsys):
    folder = tmp_path / "cmp"
    shutil.copytree(comparison_folder, folder, ignore=shutil.ignore_patterns("figures"))
    arrays = dict(np.load(folder / "ellipsoid" / "trajectory.npz"))
    del arrays["r"]
    np.savez(folder / "ellipsoid" / "trajectory.npz", **arrays)
    _, notes = report._fig1_sets(report.load_comparison(folder))
    assert notes == ["ellipsoid: no levels r in its trajectory.npz, ellipses not drawn"]
    code, _, err = call(monkeypatch, capsys, "report", str(folder), "--out", str(tmp_path / "figs"))
    assert code == 0, err
    assert_figures(tmp_path / "figs", FIGURE_FILES)


def test_a_method_without_its_run_folder_is_skipped_and_named(tmp_path, comparison_folder, monkeypatch, capsys):
    folder = tmp_path / "cmp"
    shutil.copytree(comparison_folder, folder, ignore=shutil.ignore_patterns("figures", "fixed-box"))
    code, stdout, err = call(monkeypatch, capsys, "report", str(folder))
    assert code == 0, err
    assert "not drawn: fixed-box" in stdout
    assert_figures(folder / "figures", FIGURE_FILES)


# ----------------------------------------------------------------------------- the real methods
def test_comparison_of_the_real_methods(tmp_path, paper_run, monkeypatch, capsys):
    """Run folders of the real methods (options.method), gathered by hand into a comparison folder."""
    shutil.copytree(paper_run, tmp_path / "tv-box", ignore=shutil.ignore_patterns("figures"))
    methods = {"tv-box": {"run_dir": "tv-box"}}
    for method in ("ellipsoid-adaptive", "centralized", "ellipsoid"):
        simulate(tmp_path / method, {"options.method": method})
        methods[method] = {"run_dir": method}
    (tmp_path / "comparison.json").write_text(json.dumps({"scenario": "paper", "methods": methods}))
    cmp = report.load_comparison(tmp_path)
    assert not cmp.skipped and list(cmp.runs) == ["tv-box", "ellipsoid", "ellipsoid-adaptive", "centralized"]
    assert cmp.runs["ellipsoid"].r is not None and cmp.runs["ellipsoid"].method == "ellipsoid"
    specs, notes = report._fig1_sets(cmp)
    assert [s.method for s in specs] == ["tv-box", "ellipsoid"] and notes == []
    code, _, err = call(monkeypatch, capsys, "report", str(tmp_path))
    assert code == 0, err
    assert_figures(tmp_path / "figures", FIGURE_FILES)
    for method in ("ellipsoid-adaptive", "centralized"):  # a single-method run of each draws too
        assert len(report.draw_run(tmp_path / method)) == 6
    assert report.load_run(tmp_path / "centralized").solves.notes()[0].startswith("centralized: one QP")


def test_report_on_the_output_of_dmpc_compare(tmp_path, monkeypatch, capsys):
    out = tmp_path / "compare"
    code, _, err = call(monkeypatch, capsys, "compare", "scenarios/paper.yaml", "--out", str(out), "--steps", "12",
                        "--quiet")
    assert code == 0, err
    cmp = report.load_comparison(out)
    assert not cmp.skipped and {"tv-box", "ellipsoid", "centralized"} <= set(cmp.runs)
    assert cmp.runs["ellipsoid"].r is not None and report._fig1_sets(cmp)[1] == []
    shutil.rmtree(out / "figures", ignore_errors=True)  # drawn by compare; draw them again here
    code, stdout, err = call(monkeypatch, capsys, "report", str(out))
    assert code == 0, err
    assert "not drawn" not in stdout
    assert_figures(out / "figures", FIGURE_FILES)


# ----------------------------------------------------------------------------- setpoints
SETPOINTS = [{"at": 0, "subsystem": "1", "x": [1.0, None]}, {"at": 12, "subsystem": "1", "x": [-0.5, None]},
             {"at": 20, "subsystem": "3", "u": [0.2]}]
"""x_11 = 1 from k = 0, -0.5 from k = 12, and u_3 = 0.2 from k = 20: requests on a state and an input."""


@pytest.fixture(scope="module")
def setpoint_run(tmp_path_factory) -> Path:
    import dmpc

    out = tmp_path_factory.mktemp("setpoints") / "run"
    result = dmpc.simulate(dmpc.load_scenario("scenarios/paper.yaml", steps=30, setpoints=SETPOINTS), out=out)
    assert result.verdict == "ok", result.summary["failures"]
    return out


def labelled(ax, label: str) -> list:
    return [line for line in ax.get_lines() if line.get_label() == label]


def held(values: np.ndarray) -> np.ndarray:
    """A per-step series (K,) as a steps-post line draws it on the times 0 .. K: its last value repeated."""
    return np.append(values, values[-1])


def test_a_run_with_setpoints_draws_the_target_dashed_and_the_setpoint_dotted(setpoint_run):
    from dmpc.plots.targets import SETPOINT_LABEL, TARGET_LABEL

    run = report.load_run(setpoint_run)
    npz = np.load(setpoint_run / "trajectory.npz")
    plt = report._pyplot()
    states = report._signal_figure(plt, [(run, run.method)], "x", "states")
    inputs = report._signal_figure(plt, [(run, run.method)], "u", "inputs")
    try:
        for column, ax in enumerate(states.axes):  # 4 subsystems of 2 states: panel = global state column
            (target,) = labelled(ax, TARGET_LABEL)
            assert target.get_drawstyle() == "steps-post" and target.get_linestyle() == "--"
            np.testing.assert_array_equal(target.get_xdata(), np.arange(31))
            np.testing.assert_array_equal(target.get_ydata(), held(npz["target"][:, column]))
            asked = labelled(ax, SETPOINT_LABEL)
            assert len(asked) == (1 if column == 0 else 0)  # x_11 requested, every other state free
        (asked,) = labelled(states.axes[0], SETPOINT_LABEL)
        assert asked.get_drawstyle() == "steps-post" and asked.get_linestyle() == ":"
        np.testing.assert_array_equal(asked.get_ydata(), held(npz["setpoint"][:, 0]))
        assert asked.get_ydata()[11] == 1.0 and asked.get_ydata()[12] == -0.5
        for i, ax in enumerate(inputs.axes):
            np.testing.assert_array_equal(labelled(ax, TARGET_LABEL)[0].get_ydata(), held(npz["target_u"][:, i]))
            assert len(labelled(ax, SETPOINT_LABEL)) == (1 if i == 2 else 0)
        u3 = labelled(inputs.axes[2], SETPOINT_LABEL)[0].get_ydata()
        assert np.isnan(u3[:20]).all() and np.all(u3[20:] == 0.2)  # free until it was asked for
        for fig, expected in ((states, ["tv-box", TARGET_LABEL, SETPOINT_LABEL]),
                              (inputs, ["tv-box", TARGET_LABEL, SETPOINT_LABEL, "bounds"])):
            assert [t.get_text() for t in fig.legends[0].get_texts()] == expected  # one legend, below
            assert not any(ax.get_legend() for ax in fig.axes)
    finally:
        plt.close("all")


def test_the_cost_marks_the_steps_where_the_setpoint_changed(setpoint_run):
    from dmpc.plots.targets import CHANGE_LABEL

    run = report.load_run(setpoint_run)
    np.testing.assert_array_equal(report.setpoint_changes(run), [12, 20])
    plt = report._pyplot()
    fig = report._series_figure(plt, [("", run.J, {}, run.method)], "J", "cost", run, report.setpoint_changes(run))
    try:
        ax = fig.axes[0]
        marks = [line for line in ax.get_lines() if line.get_xdata()[0] == line.get_xdata()[-1]]
        assert [line.get_xdata()[0] for line in marks] == [12, 20]
        assert [t.get_text() for t in ax.get_legend().get_texts()] == [CHANGE_LABEL]
    finally:
        plt.close(fig)


def test_a_run_without_setpoints_draws_as_before(paper_run):
    """Nothing of the setpoints' drawing appears: per state panel the trajectory and the zero line,
    per input panel the trajectory, the two bounds and the zero line, the legend in the first input
    panel, and no mark on the cost."""
    run = report.load_run(paper_run)
    assert run.tracked is None and report.setpoint_changes(run) is None
    np.testing.assert_array_equal(run.box_centres(), run.alpha)
    plt = report._pyplot()
    states = report._signal_figure(plt, [(run, run.method)], "x", "states")
    inputs = report._signal_figure(plt, [(run, run.method)], "u", "inputs")
    cost = report._series_figure(plt, [("", run.J, {}, run.method)], "J", "cost", run, report.setpoint_changes(run))
    try:
        assert [len(ax.get_lines()) for ax in states.axes] == [2] * 8
        assert [len(ax.get_lines()) for ax in inputs.axes] == [4] * 4
        assert not states.legends and not inputs.legends and not any(ax.get_legend() for ax in states.axes)
        assert [t.get_text() for t in inputs.axes[0].get_legend().get_texts()] == ["tv-box", "bounds"]
        assert len(cost.axes[0].get_lines()) == 1 and cost.axes[0].get_legend() is None
    finally:
        plt.close("all")


def test_terminal_boxes_of_a_run_with_setpoints_lie_around_the_targets(setpoint_run):
    run = report.load_run(setpoint_run)
    npz = np.load(setpoint_run / "trajectory.npz")
    plt = report._pyplot()
    fig = report._fig1(plt, [report.PlaneSet(run, run.method)], "t", [])
    try:
        boxes = [p for p in fig.axes[0].patches if type(p).__name__ == "Rectangle"]
        assert len(boxes) == 31  # the last target had reached its reference: the box of x(K) is known too
        centres = np.array([np.asarray(b.get_xy()) + b.get_width() / 2 for b in boxes])
        expected = npz["alpha"][:, :2] + np.vstack([npz["target"], npz["target"][-1:]])[:, :2]
        np.testing.assert_allclose(centres, expected, atol=1e-12)
        assert "x_{s,i}" in fig.legends[0].get_texts()[0].get_text()
    finally:
        plt.close(fig)


def test_result_plot_draws_the_targets_as_the_report_does(setpoint_run):
    import dmpc
    from dmpc.plots.targets import SETPOINT_LABEL, TARGET_LABEL

    run = report.load_run(setpoint_run)
    plt = report._pyplot()
    mine = report._signal_figure(plt, [(run, run.method)], "x", "states")
    theirs = dmpc.load_run(setpoint_run).plot()
    try:
        for label in (TARGET_LABEL, SETPOINT_LABEL):
            for a, b in zip(mine.axes, theirs["states"].axes):
                ours, result = labelled(a, label), labelled(b, label)
                assert len(ours) == len(result)
                for one, other in zip(ours, result):
                    np.testing.assert_array_equal(one.get_xydata(), other.get_xydata())
                    assert one.get_linestyle() == other.get_linestyle()
        marks = [line.get_xdata()[0] for line in theirs["cost"].axes[0].get_lines() if len(line.get_xdata()) == 2]
        assert marks == [12, 20]
    finally:
        plt.close("all")

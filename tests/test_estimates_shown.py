"""What the controllers of a run with ``estimation`` saw, shown: the outputs measured y, the state
estimates x^ and the disturbance estimates d^ (docs/algorithm.md, "Offset-free tracking") in the
Python API's Result, in ``dmpc report``'s figures and ``result.plot()``, and in the live view's page
(without a browser; the browser's check is in test_watch_browser.py).

The run is the first 40 steps of scenarios/fourtank-levels.yaml (h1 and h2 measured, an output
disturbance per subsystem); every number shown is compared with its ``steps.jsonl`` line. A run
without estimation (the paper's example) shows none of it, and an estimation run folder written
before ``output_sizes`` existed, or without its scenario and design, still loads.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import dmpc
from dmpc.plots import report
from dmpc.plots.estimates import ESTIMATE_LABEL, MEASURED_LABEL
from dmpc.plots.targets import SETPOINT_LABEL
from dmpc.watch.folder import folder_meta
from dmpc.watch.meta import RunMeta, meta_json
from dmpc.watch.state import RunState
from dmpc.watch.telemetry import decode, encode
from tests.helpers.closed_loop import read_steps

ROOT = Path(__file__).resolve().parents[1]
LEVELS = ROOT / "scenarios" / "fourtank-levels.yaml"
PAPER = ROOT / "scenarios" / "paper.yaml"
STEPS = 40
NAMES = ("a", "b")
STATES = {"a": slice(0, 2), "b": slice(2, 4)}


@pytest.fixture(scope="module")
def levels(tmp_path_factory) -> Path:
    """The run folder of the first STEPS steps of fourtank-levels."""
    out = tmp_path_factory.mktemp("estimates") / "levels"
    result = dmpc.simulate(dmpc.load_scenario(LEVELS, steps=STEPS), out=out)
    assert result.verdict == "ok", result.summary["failures"]
    return out


@pytest.fixture(scope="module")
def paper(tmp_path_factory) -> Path:
    """A run folder of the paper's example: no estimation."""
    out = tmp_path_factory.mktemp("estimates") / "paper"
    dmpc.simulate(dmpc.load_scenario(PAPER, steps=10), out=out)
    return out


def logged(folder: Path, key: str) -> np.ndarray:
    """The field ``key`` of every line of the folder's steps.jsonl, stacked (K, ...)."""
    return np.array([[np.nan if v is None else v for v in np.atleast_1d(line[key])] for line in read_steps(folder)],
                    dtype=float)


# ---------------------------------------------------------------------------------- the Result
def test_result_has_the_outputs_measured_and_the_estimates_of_steps_jsonl(levels):
    result = dmpc.load_run(levels)
    assert result.estimated and set(result.y) == set(result.x_hat) == set(result.d_hat) == set(NAMES)
    y, x_hat, d_hat = logged(levels, "y"), logged(levels, "x_hat"), logged(levels, "d_hat")
    for i, name in enumerate(NAMES):
        assert result.y[name].shape == (STEPS, 1) and result.x_hat[name].shape == (STEPS, 2)
        assert result.d_hat[name].shape == (STEPS, 1)
        np.testing.assert_array_equal(result.y[name], y[:, i:i + 1])
        np.testing.assert_array_equal(result.x_hat[name], x_hat[:, STATES[name]])
        np.testing.assert_array_equal(result.d_hat[name], d_hat[:, i:i + 1])
        np.testing.assert_array_equal(result.C[name], [[1.0, 0.0]])
        np.testing.assert_array_equal(result.setpoint_y[name], np.full((STEPS, 1), 0.15))
    np.testing.assert_array_equal(result.innovation, logged(levels, "innovation")[:, 0])
    # the level measured is the plant's h1 (no measurement noise); the estimate is not the plant's state
    np.testing.assert_array_equal(result.y["a"][:, 0], result.x["a"][:STEPS, 0])
    assert np.abs(result.x_hat["a"] - result.x["a"][:STEPS]).max() > 1e-4
    assert [q.label for q in result.outputs["a"]] == ["h1 [m]"]
    assert [q.label for q in result.disturbances["b"]] == ["d(h2) [m]"]
    assert np.abs(result.d_hat["a"][-1]).max() > 0  # the model is not the plant: the observer did work
    with np.load(levels / "trajectory.npz") as npz:
        assert list(npz["output_sizes"]) == [1, 1]


def test_result_table_lists_the_outputs_and_estimates(levels):
    table = dmpc.load_run(levels).table()
    rows = {line.split()[1] + " " + " ".join(line.split()[2:4]) for line in table.splitlines()[2:]}
    for expected in ("h1 [m] (measured)", "h3 [m] (estimate)", "d(h1) [m] (estimate)", "d(h2) [m] (estimate)"):
        assert any(row.startswith(expected) for row in rows), (expected, table)


def test_a_run_without_estimation_has_empty_estimates(paper):
    result = dmpc.load_run(paper)
    assert not result.estimated
    for mapping in (result.y, result.x_hat, result.d_hat, result.setpoint_y, result.C, result.outputs,
                    result.disturbances):
        assert dict(mapping) == {}
    assert result.innovation.shape == (0,)
    assert "(estimate)" not in result.table() and "estimates" not in result.plot()


def test_older_estimation_folders_still_load(levels, tmp_path):
    """Without ``output_sizes`` the design splits the arrays; without the design the scenario; without
    both (and two subsystems) the estimates are left out and the reader says so."""
    old = tmp_path / "old"
    shutil.copytree(levels, old, ignore=shutil.ignore_patterns("figures"))
    with np.load(old / "trajectory.npz") as npz:
        arrays = {key: npz[key] for key in npz.files if key != "output_sizes"}
    np.savez(old / "trajectory.npz", **arrays)
    expected = dmpc.load_run(levels)
    np.testing.assert_array_equal(dmpc.load_run(old).d_hat["b"], expected.d_hat["b"])  # split by design.json
    (old / "design.json").unlink()
    np.testing.assert_array_equal(dmpc.load_run(old).y["b"], expected.y["b"])  # by the scenario
    (old / "scenario.yaml").unlink()
    notes: list[str] = []
    run = report.load_run(old, notes)
    assert run.estimates is None and any("cannot be split by subsystem" in note for note in notes)
    assert dmpc.load_run(old).y == {}  # names and sizes from trajectory.npz: the rest still loads


def test_a_run_drawn_from_its_step_log_has_its_estimates(levels, tmp_path):
    cut = tmp_path / "cut"
    shutil.copytree(levels, cut, ignore=shutil.ignore_patterns("figures", "trajectory.npz", "summary.json"))
    run = report.load_run(cut)
    assert run.estimates is not None
    with np.load(levels / "trajectory.npz") as npz:
        for key in ("y", "x_hat", "d_hat", "innovation", "setpoint_y"):
            np.testing.assert_array_equal(getattr(run.estimates, key), npz[key], err_msg=key)


# ----------------------------------------------------------------------------- the report's figures
def labelled(ax, label: str) -> list:
    return [line for line in ax.get_lines() if line.get_label() == label]


def test_report_draws_the_estimates_figure_and_the_estimates_beside_the_states(levels, tmp_path):
    paths = report.draw(levels, tmp_path / "figs")
    assert [p.name for p in paths] == [f"{name}.png" for name in report.RUN_FIGURES + (report.ESTIMATES_FIGURE,)]
    assert paths[-1].stat().st_size > 15_000
    run = report.load_run(levels)
    npz = np.load(levels / "trajectory.npz")
    plt = report._pyplot()
    states = report._signal_figure(plt, [(run, run.method)], "x", "states")
    try:
        for column, ax in enumerate(states.axes):  # 2 subsystems of 2 states: panel = global state column
            (estimate,) = labelled(ax, ESTIMATE_LABEL)
            assert estimate.get_linestyle() == "--"
            np.testing.assert_array_equal(estimate.get_ydata(), npz["x_hat"][:, column])
            np.testing.assert_array_equal(estimate.get_xdata(), np.arange(STEPS) * 5.0)  # dt = 5 s
            measured = labelled(ax, MEASURED_LABEL)
            assert len(measured) == (1 if column in (0, 2) else 0)  # h1 and h2 are measured, h3 and h4 not
            if measured:
                np.testing.assert_array_equal(measured[0].get_ydata(), npz["y"][:, column // 2])
        labels = [t.get_text() for t in states.legends[0].get_texts()]
        assert ESTIMATE_LABEL in labels and MEASURED_LABEL in labels  # one legend, below
    finally:
        plt.close("all")


def test_the_estimates_figure_holds_the_outputs_the_disturbances_and_the_innovation(levels):
    run = report.load_run(levels)
    npz = np.load(levels / "trajectory.npz")
    plt = report._pyplot()
    fig = report.estimates_figure(plt, run, "t", 2)
    try:
        output_a, d_a, output_b, d_b, innovation = [ax for ax in fig.axes if ax.get_visible()]
        for i, (out, dist) in enumerate(((output_a, d_a), (output_b, d_b))):
            np.testing.assert_array_equal(labelled(out, MEASURED_LABEL)[0].get_ydata(), npz["y"][:, i])
            (asked,) = labelled(out, SETPOINT_LABEL)
            assert np.all(asked.get_ydata() == 0.15)
            (line,) = labelled(dist, f"d(h{i + 1}) [m]")
            np.testing.assert_array_equal(line.get_ydata(), npz["d_hat"][:, i])
        values = innovation.get_lines()[0].get_ydata()
        expected = npz["innovation"].copy()
        if innovation.get_yscale() == "log":
            expected[~(expected > 0)] = np.nan
        np.testing.assert_array_equal(values, expected)
    finally:
        plt.close(fig)


def test_result_plot_draws_the_estimates_as_the_report_does(levels):
    run = report.load_run(levels)
    plt = report._pyplot()
    mine = report._signal_figure(plt, [(run, run.method)], "x", "states")
    figures = dmpc.load_run(levels).plot()
    try:
        assert set(figures) == {"states", "inputs", "cost", "estimates"}
        for label in (ESTIMATE_LABEL, MEASURED_LABEL):
            for a, b in zip(mine.axes, figures["states"].axes):
                ours, theirs = labelled(a, label), labelled(b, label)
                assert len(ours) == len(theirs)
                for one, other in zip(ours, theirs):
                    np.testing.assert_array_equal(one.get_xydata(), other.get_xydata())
        lines = [line.get_ydata() for ax in figures["estimates"].axes for line in labelled(ax, "d(h1) [m]")]
        np.testing.assert_array_equal(lines, [np.load(levels / "trajectory.npz")["d_hat"][:, 0]])
    finally:
        plt.close("all")


def test_report_of_a_run_without_estimation_draws_no_estimates(paper, tmp_path):
    paths = report.draw(paper, tmp_path / "figs")
    assert [p.name for p in paths] == [f"{name}.png" for name in report.RUN_FIGURES]
    run = report.load_run(paper)
    assert run.estimates is None
    plt = report._pyplot()
    states = report._signal_figure(plt, [(run, run.method)], "x", "states")
    try:
        assert [len(ax.get_lines()) for ax in states.axes] == [2] * 8 and not states.legends
    finally:
        plt.close("all")


# ------------------------------------------------------------------------------------ the live view
def fed(folder: Path, steps: int | None = None) -> RunState:
    state = RunState(f"run folder {folder}")
    state.set_meta(folder_meta(folder))
    for line in read_steps(folder)[:steps]:
        assert state.add_step(line)
    return state


def test_the_description_names_the_outputs_and_disturbances_only_with_estimation(levels, paper):
    from dmpc.scenario import load_scenario
    from dmpc.setup import prepare

    data = meta_json(prepare(load_scenario(LEVELS, {"steps": STEPS})), "r-1")
    assert data["estimation"] is True
    assert [(s["outputs"], s["disturbances"], s["measures"]) for s in data["subsystems"]] == [
        ([["h1", "m"]], [["d(h1)", "m"]], [0]), ([["h2", "m"]], [["d(h2)", "m"]], [0])]
    meta = RunMeta.from_json(json.loads(json.dumps(data)))
    assert meta.estimation and [s.output_label(0) for s in meta.subsystems] == ["h1 [m]", "h2 [m]"]
    assert meta.subsystems[1].disturbance_label(0) == "d(h2) [m]" and meta.subsystems[0].measures == (0,)
    assert [(sl.start, sl.stop) for sl in meta.disturbance_slices()] == [(0, 1), (1, 2)]
    plain = meta_json(prepare(load_scenario(PAPER)), "r-2")
    assert "estimation" not in plain and not any("outputs" in s for s in plain["subsystems"])
    assert not RunMeta.from_json(plain).estimation and folder_meta(paper).subsystems[0].p == 0


def test_a_step_carries_its_estimates_and_a_wrong_size_is_dropped(levels):
    line = read_steps(levels)[7]
    msg = decode(encode("step", "r-1", step=line, plant={}), "r-1")["step"]
    live = fed(levels, 0)
    assert live.add_step(msg)
    snap = live.read(-1, 0, 0)
    estimate = snap.step_rows[0].estimate
    assert estimate.y == line["y"] and estimate.x_hat == line["x_hat"] and estimate.d_hat == line["d_hat"]
    assert estimate.innovation == line["innovation"]
    state = fed(levels, 0)
    assert not state.add_step(dict(line, d_hat=line["d_hat"] + [0.0]))
    assert "d_hat has 3 entries, the run 2" in state.problems[0]


def test_page_draws_the_estimates_outputs_and_disturbances_of_a_replayed_run(levels):
    from bokeh.document import Document

    from dmpc.watch.page import WatchPage

    npz = np.load(levels / "trajectory.npz")
    page = WatchPage(Document(), fed(levels), live=False)
    for i, name in enumerate(NAMES):
        source = page.doc.get_model_by_name(f"estimates-{name}")
        assert source.data["k"] == list(range(STEPS))
        np.testing.assert_array_equal(np.column_stack([source.data["xhat1"], source.data["xhat2"]]),
                                      npz["x_hat"][:, STATES[name]])
        np.testing.assert_array_equal(source.data["y1"], npz["y"][:, i])
        np.testing.assert_array_equal(source.data["d1"], npz["d_hat"][:, i])
        assert page.doc.get_model_by_name(f"estimate-{name}-1") is not None  # x^ on the state plot
        assert page.doc.get_model_by_name(f"measured-{name}-1") is not None  # y on the state plot (h1, h2)
        assert page.doc.get_model_by_name(f"disturbances-{name}") is not None
        assert page.doc.get_model_by_name(f"outputs-{name}") is None  # every output is a state alone
    page.slider.value = 12
    source = page.doc.get_model_by_name("estimates-b")
    assert source.data["k"] == list(range(13))
    np.testing.assert_array_equal(source.data["d1"], npz["d_hat"][:13, 1])
    text = page.readout.text
    assert f"dmpc-x-hat'>{', '.join(f'{v:.6g}' for v in npz['x_hat'][12, 2:4])}<" in text
    assert f"dmpc-y'>{npz['y'][12, 0]:.6g}<" in text and f"dmpc-d-hat'>{npz['d_hat'][12, 1]:.6g}<" in text
    assert f"dmpc-innovation'>{npz['innovation'][12]:.6g}<" in text


def test_page_of_a_run_without_estimation_has_no_estimates(paper):
    from bokeh.document import Document

    from dmpc.watch.page import WatchPage

    page = WatchPage(Document(), fed(paper), live=False)
    assert page.estimates == []
    for name in ("1", "2", "3", "4"):
        for model in (f"estimates-{name}", f"disturbances-{name}", f"estimate-{name}-1", f"measured-{name}-1"):
            assert page.doc.get_model_by_name(model) is None
    assert "dmpc-x-hat" not in page.readout.text and "innovation" not in page.readout.text
    grid = page.root.children[-1]  # as before: the subsystems' plots four to a row
    assert [(r, c) for _, r, c in grid.children] == [(r, c) for r in range(2) for c in range(4)]

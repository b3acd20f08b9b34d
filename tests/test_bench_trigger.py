"""The event trigger against ``always``: the measures of dmpc.bench.trigger on small runs, and the
trade-off figure (dmpc.plots.tradeoff)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dmpc.bench import trigger
from dmpc.plots.tradeoff import TRADEOFF_FIGURE, cost_ppm, draw_tradeoff, share

ROOT = Path(__file__).resolve().parents[1]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def test_step_medians_leave_out_step_0_and_start_late_where_asked():
    step_s = np.array([np.nan, 0.002, 0.004, 0.001, 0.003, 0.005])
    assert trigger.step_figures(step_s, late=3) == {"step_ms_p50": 3.0, "step_ms_p50_late": 3.0}
    assert trigger.step_figures(step_s[:3], late=3)["step_ms_p50_late"] is None


def test_a_sweep_of_the_paper_counts_what_the_agents_solved_kept_and_sent(tmp_path):
    sweep = trigger.sweep(4, 20, tmp_path, ROOT, costs=(1e-3, 10.0))
    always, (default, loose) = sweep["always"], sweep["event"]
    assert (always["trigger"], always["trigger_cost"], always["keeps"]) == ("always", None, 0)
    assert [row["trigger_cost"] for row in sweep["event"]] == [1e-3, 10.0]
    for row in (always, default, loose):
        assert row["verdict"] == "ok" and row["plan_messages"] == row["solves"] and row["kept_notices"] == row["keeps"]
        assert row["step_ms_p50"] > 0
    assert always["solves"] > default["solves"] > loose["solves"] and loose["bytes"] < always["bytes"]
    assert default["closed_loop_cost"] == pytest.approx(always["closed_loop_cost"], rel=1e-5)
    assert share(sweep, "solves")[0] == pytest.approx(100 * default["solves"] / always["solves"])


def test_a_disturbance_above_the_threshold_makes_the_trigger_fire_at_every_step(tmp_path):
    pair = trigger.disturbed_pair(1e-5, 15, tmp_path, ROOT)
    always, (event,) = pair["always"], pair["event"]
    assert (pair["bound"], pair["threshold"], pair["seed"]) == (1e-5, trigger.THRESHOLD, 1)
    assert event["solves"] == always["solves"] and event["keeps"] == 0
    assert event["solve_reasons"]["prediction"] > 0


def _sweep(case: str, M: int, costs: list[float], solves: list[int], closed: list[float]) -> dict:
    def row(trigger_name, cost, n, c):
        return {"trigger": trigger_name, "trigger_cost": cost, "solves": n, "plan_messages": n, "bytes": 450 * n,
                "closed_loop_cost": c}

    return {"case": case, "M": M, "steps": 60, "always": row("always", None, 308, 102.044),
            "event": [row("event", c, n, k) for c, n, k in zip(costs, solves, closed)]}


def test_the_tradeoff_figure_is_drawn_from_the_sweeps(tmp_path):
    sweeps = [_sweep("paper", 4, [0.0, 1e-3, 1.0, 10.0], [228, 141, 141, 72], [102.044, 102.04398, 102.04398, 102.0458]),
              _sweep("chain", 64, [0.0, 1e-3, 10.0], [300, 220, 180], [102.044, 102.044, 102.05])]
    path = draw_tradeoff(sweeps, tmp_path / "figures")
    assert path == tmp_path / "figures" / f"{TRADEOFF_FIGURE}.png"
    assert path.read_bytes()[:8] == PNG_SIGNATURE and path.stat().st_size > 20_000
    assert cost_ppm(sweeps[0])[0] == 0.0 and cost_ppm(sweeps[0])[3] == pytest.approx(17.64, abs=0.01)
    assert draw_tradeoff([dict(sweeps[0], event=[])], tmp_path / "none") is None


def test_the_report_of_a_sweep_has_the_tradeoff_figure(tmp_path):
    from dmpc.bench.results import plot
    from tests.test_bench_results import _results

    sweep = _sweep("paper", 4, [0.0, 1e-3], [228, 141], [102.044, 102.04398])
    paths = plot({**_results(), "trigger": {"sweeps": [sweep], "hosted": [], "carts": []}}, tmp_path)
    assert tmp_path / f"{TRADEOFF_FIGURE}.png" in paths

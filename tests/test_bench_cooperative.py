"""tv-box-coop against tv-box: the figures and rows of dmpc.bench.cooperative, on fake summaries
and on small runs of the paper's example."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dmpc.bench import cooperative
from dmpc.bench.results import COOPERATIVE_HEADING, cooperative_lines, markdown
from dmpc.scenario import load_scenario
from dmpc.setup import prepare

ROOT = Path(__file__).resolve().parents[1]


def _summary(plans: int, size: int, verdict: str = "ok", failures=()) -> dict:
    return {"steps": 5, "verdict": verdict, "failures": [{"kind": k} for k in failures],
            "messages": {"plan_messages": plans, "kept_notices": 0, "bytes": size},
            "solve_time_median_s": 2.5e-4, "inputs_refused": {"2": 1, "3": 2}}


def test_plan_messages_per_step_leave_out_the_rounds_of_k_0():
    rounds = np.array([18, 1, 1, 2, 1])
    figures = cooperative.wire_figures(_summary(4 * 23, 4 * 23 * 450), rounds, 4)
    assert figures["plans_per_step"] == pytest.approx((4 * 23 - 4 * 18) / 4) and not figures["plans_all_steps"]
    assert (figures["rounds_k0"], figures["rounds_p50"], figures["plan_bytes"]) == (18, 1.0, 450.0)
    assert (figures["solve_us_p50"], figures["inputs_refused"], figures["verdict_text"]) == (250.0, 3, "ok")


def test_a_run_where_not_every_agent_answered_every_round_counts_over_every_step():
    figures = cooperative.wire_figures(_summary(90, 9000, "failed", ("state-violated", "infeasible", "infeasible")),
                                       np.array([18, 1, 1, 2, 1]), 4)
    assert figures["plans_per_step"] == 90 / 5 and figures["plans_all_steps"]
    assert figures["verdict_text"] == "failed (state-violated, infeasible)"


def test_bytes_per_step_are_the_release_times_the_rounds_and_the_plans():
    row = {"release_bytes": 1527, "rounds_p50": 2.0, "plans_per_step": 4.0, "plan_bytes": 450.0}
    assert cooperative.step_bytes(row) == {"release_bytes_per_step": 3054.0, "kb_per_step": pytest.approx(4.854)}
    assert cooperative.step_bytes({**row, "release_bytes": None})["kb_per_step"] is None


def _row(method: str, cost: float, verdict: str = "ok", **extra) -> dict:
    return {"method": method, "verdict": verdict, "verdict_text": verdict, "fallbacks": 0, "closed_loop_cost": cost,
            "rounds_k0": 1, "step_ms_p50": 1.234, "step_ms_max": 40123.4, "wall_s": 12.34, "plans_per_step": 4.0, "plans_all_steps": False,
            "plan_bytes": 448.6, "release_bytes_per_step": 1527.0, "kb_per_step": 3.3214, "solve_us_p50": 340.2,
            "qp_iterations_p50": 75.0, "qp_iterations_max": 10000, "release_step": 1, **extra}


def test_the_rows_have_the_cost_over_tv_box_s_and_leave_it_out_where_tv_box_failed():
    pair = {"case": "paper", "M": 4, "steps": 60, "calibration_ms": 31.04,
            "rows": [_row("tv-box", 102.0441), _row("tv-box-coop", 101.7906)]}
    ref, coop = cooperative.inprocess_rows(pair)
    assert ref == ["paper", "4", "60", "tv-box", "ok", "0", "102.0441", "1.0000", "1", "1.23", "40123", "12.3", "4.0",
                   "449", "1527", "3.3", "340", "75 / 10000", "31.0"]
    assert coop[3:8] == ["tv-box-coop", "ok", "0", "101.7906", "0.9975"]
    failed = {**pair, "case": "fourtank", "M": 2,
              "rows": [_row("tv-box", 197.5, "failed", verdict_text="failed (state-violated)"), _row("tv-box-coop", 1.26)]}
    assert [line[7] for line in cooperative.inprocess_rows(failed)] == ["-", "-"]
    assert len(ref) == len(cooperative.INPROCESS_HEADER)


def test_a_hosted_run_that_did_not_complete_says_why_and_a_first_release_is_marked():
    pair = {"case": "chain", "M": 1024, "processes": 8, "agents_per_process": 128, "steps": 10, "calibration_ms": 30.0,
            "rows": [_row("tv-box", 32151.9, completed=True, startup_s=14.2, release_step=None),
                     {"method": "tv-box-coop", "completed": False, "reason": "agents not ready | within\n900 s"}]}
    done, failed = cooperative.hosted_rows(pair)
    assert done[:6] == ["chain", "1024", "8", "128", "10", "tv-box"] and done[16] == "1527 (k = 0)"
    assert done[-2:] == ["14.2", "30.0"] and len(done) == len(failed) == len(cooperative.HOSTED_HEADER)
    assert failed[6] == "did not complete: agents not ready / within 900 s"


def test_the_report_has_the_section_and_the_largest_release_against_the_limit():
    from tests.test_bench_results import _results

    inprocess = {"case": "paper", "M": 4, "steps": 60, "calibration_ms": 31.0,
                 "rows": [_row("tv-box", 102.0, release_bytes=438), _row("tv-box-coop", 101.8, release_bytes=1527)]}
    text = markdown({**_results(), "cooperative": {"inprocess": [inprocess], "hosted": []}}, "dmpc bench")
    assert COOPERATIVE_HEADING in text and "### In this process" in text and "### As processes" not in text
    assert "| paper | 4 | 60 | tv-box-coop | ok |" in text
    assert "Largest release measured: 1.5 kB (tv-box-coop, M = 4)" in text
    assert cooperative_lines({"inprocess": [], "hosted": []}) == []


@pytest.mark.parametrize("method", cooperative.METHODS)
def test_every_release_of_a_run_without_setpoints_has_the_first_release_s_size(method):
    prepared = prepare(load_scenario(ROOT / "scenarios/paper.yaml", {"steps": 4, "options.method": method}))
    sizes = cooperative.release_sizes(prepared, until=lambda s: False)
    assert [k for k, _ in sizes][-1] == 3 and {size for _, size in sizes} == {cooperative.release_bytes(prepared, None)}
    assert cooperative.release_bytes(prepared) == sizes[0][1]


def test_a_pair_in_this_process_on_the_paper(tmp_path):
    pair = cooperative.inprocess_pair("paper", 4, 6, tmp_path, ROOT)
    ref, coop = pair["rows"]
    assert (pair["steps"], ref["method"], coop["method"]) == (6, "tv-box", "tv-box-coop")
    for row in (ref, coop):
        assert row["verdict"] == "ok" and row["plans_per_step"] == 4.0 and not row["plans_all_steps"]
        assert row["step_ms_max"] >= row["step_ms_p50"] > 0 and row["solve_us_p50"] > 0 and row["release_step"] == 1
        assert row["wall_s"] > 0 and row["qp_iterations_max"] >= row["qp_iterations_p50"] > 0
    # the cooperative release carries the iterate, z (N+1, n) and v (N, m): 11 x 8 + 10 x 4 more numbers
    assert coop["release_bytes"] - ref["release_bytes"] >= (11 * 8 + 10 * 4) * 8
    assert ref["rounds_k0"] > coop["rounds_k0"] >= 1  # Jacobi to convergence against the cooperative start
    with pytest.raises(ValueError, match="M = 8"):
        cooperative.case_overrides("paper", 8, 6)

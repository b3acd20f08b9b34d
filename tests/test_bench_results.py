"""The benchmark report: every measured figure lands in RESULTS.md, failures with their reason."""
from __future__ import annotations

import json

from dmpc.bench.common import calibration_ms
from dmpc.bench.results import markdown, targets


def _results() -> dict:
    done = {"M": 4, "completed": True, "topology": "mesh", "steps": 100, "wall_s": 5.6, "step_ms_p50": 4.48,
            "step_ms_p99": 8.52, "step0_ms": 94.0, "bus_ms_p50": 4.09, "bus_share_p50": 0.962,
            "rss_mb_per_agent": 74.8, "pss_mb_per_agent": 45.1, "rss_mb_plant": 86.0, "rss_mb_total": 385.0,
            "pss_mb_total": 236.0, "closed_loop_cost": 102.04, "feasible": True,
            "floor": {"M": 4, "completed": True, "steps": 100, "step_ms_p50": 2.24, "step_ms_p99": 2.84},
            "over_floor_p50": 2.0, "over_floor_p99": 3.0}
    failed = {"M": 64, "completed": False, "topology": "mesh",
              "reason": "error: agent-30 exited with code -6 | see\nits log"}
    loop = {"step_ms_p50": 4.39, "step_ms_p99": 4.7, "closed_loop_cost": 102.044}
    return {
        "machine": {"machine": "x86_64", "cores": 2, "memory_gib": 23.5, "python": "3.11.7", "calibration_ms": 37.3},
        "quick": False, "seconds": 512.0,
        "qp": [{"N": 10, "solves": 940, "us_p50": 49.4, "us_p99": 138.5}],
        "runtime": [done, failed],
        "inprocess": [{"M": 4, **loop}, {"M": 64, **loop}],
        "central_osqp": [{"M": 4, **loop, "closed_loop_cost": 101.79}, {"M": 64, **loop}],
        "central_cvxpy": [{"M": 4, **loop, "step_ms_p50": 3.38}, {"M": 64, **loop}],
        "design": [{"M": 4, "lmi_s": 0.08, "terminal_set_s": 0.09, "omega_rows": 24, "t_star": 2}],
        "headline": {"qp_solve_us_p50": 49.4, "step_ms_p50_m4": 4.48, "step_ms_p99_m4": 8.52,
                     "rss_mb_per_agent": 74.8, "max_agents_run": 4},
    }


def test_every_figure_and_the_machine_are_in_the_report():
    text = markdown(_results(), "dmpc bench --write benchmarks/RESULTS.md")
    assert "2 cores, 23.5 GiB" in text and "37.3 ms for 10^6 Python additions" in text
    assert "`dmpc bench --write benchmarks/RESULTS.md`" in text
    assert "| 10 | 940 | 49.4 | 138.5 |" in text
    assert "| 4 | mesh | 100 | 6 | 4.48 | 8.52 | 2.24 | 2.84 | 2 | 3 | 96% | 74.8 | 45.1 | 385 | 236 |" in text
    # the side-by-side ratio multi-process / CVXPY = 4.48 / 3.38
    assert "| 1.33 |" in text
    headline = json.loads(text.split("```json")[1].split("```")[0])
    assert headline["max_agents_run"] == 4


def test_a_run_that_did_not_complete_is_a_row_with_its_reason_on_one_line():
    text = markdown(_results(), "dmpc bench")
    row = next(line for line in text.splitlines() if line.startswith("| 64 | mesh |"))
    assert "did not complete: error: agent-30 exited with code -6 / see its log" in row
    # the side-by-side row of M = 64 has no multi-process figure rather than a made-up one
    side = [line for line in text.splitlines() if line.startswith("| 64 | - |")]
    assert len(side) == 1


def test_headline_has_the_floor_and_the_ratios():
    from dmpc.bench.results import headline

    h = headline(_results())
    assert (h["floor_step_ms_p50_m4"], h["floor_step_ms_p99_m4"]) == (2.24, 2.84)
    assert (h["step_over_floor_p50_m4"], h["step_over_floor_p99_m4"]) == (2.0, 3.0)


def test_calibration_is_a_positive_time():
    assert 0.0 < calibration_ms(repeat=1) < 10_000.0


def test_targets_say_which_are_met_from_the_figures():
    rows = {target: (measured, met) for target, measured, met in
            targets(_results())}
    assert rows["local QP, N = 10: median <= 60 us"] == ("49.4 us", "yes")
    assert rows["M = 4 lockstep step: median <= 1 ms"] == ("4.48 ms", "no")
    assert rows["M = 4 lockstep step: p99 <= 3 ms"] == ("8.52 ms", "no")
    assert rows["M = 4 lockstep step: median <= 1.5x the bus floor's (same run)"] == ("2.00x (4.48 / 2.24 ms)", "no")
    assert rows["M = 4 lockstep step: p99 <= 2x the bus floor's p99 (same run)"] == ("3.00x (8.52 / 2.84 ms)", "no")
    assert rows["M = 64 runs to completion"] == ("did not complete (mesh)", "no")
    assert rows["M = 128 attempted"] == ("not run", "-")
    assert rows["resident memory per agent <= 80 MB"] == ("75 MB at M = 4", "yes")
    assert rows["DMPC multi-process step faster than the centralised CVXPY step, every M"] == ("1.3x at M = 4", "no")
    # no M >= 32 completed: nothing to compare, so not claimed either way
    assert rows["DMPC multi-process step faster than the centralised OSQP step, M >= 32"] == ("-", "-")


def test_alternated_sets_give_medians_and_the_median_of_each_sets_ratio(monkeypatch, tmp_path):
    """Floor and run alternate; a set whose run failed is left out; the ratios are per set."""
    from dmpc.bench import measures as bench

    floors = iter([(1.0, 2.0), (0.5, 1.0), (1.0, 1.0), (2.0, 4.0)])
    runs = iter([(3.0, 4.0), (2.0, 5.0), None, (4.0, 6.0)])
    monkeypatch.setattr(bench, "run_floor", lambda *a, **k: dict(zip(("step_ms_p50", "step_ms_p99"), next(floors)),
                                                                  completed=True))

    def run(M, steps, workdir, root, timeout):
        assert workdir.is_dir()
        figures = next(runs)
        if figures is None:
            return {"M": M, "completed": False, "reason": "lost"}
        return {"M": M, "completed": True, "step_ms_p50": figures[0], "step_ms_p99": figures[1], "rss_mb_total": 1.0}

    monkeypatch.setattr(bench, "run_multiprocess", run)
    result = bench.run_against_floor(4, 10, 50.0, tmp_path, sets=4)
    assert [(p["floor_ms_p50"], p["step_ms_p50"]) for p in result["sets"]] == [(1.0, 3.0), (0.5, 2.0), (2.0, 4.0)]
    assert result["step_ms_p50"] == 3.0 and result["step_ms_p99"] == 5.0
    assert result["floor"]["step_ms_p50"] == 1.0 and result["floor"]["step_ms_p99"] == 2.0
    assert result["over_floor_p50"] == 3.0  # ratios 3, 4, 2
    assert result["over_floor_p99"] == 2.0  # ratios 2, 5, 1.5
    text = markdown({**_results(), "runtime": [dict(_results()["runtime"][0], sets=result["sets"])]}, "dmpc bench")
    assert "alternated 3 times" in text and "1.00 / 2.00 then 3.00 / 4.00" in text


def _full_results() -> dict:
    """The figures of a full run: M = 128 one process per agent, M = 1024 designed and run hosted."""
    results = _results()
    m128 = dict(results["runtime"][0], M=128, topology="star", startup_s=6.2)
    hosted = {"M": 1024, "processes": 8, "agents_per_process": 128, "topology": "mesh", "steps": 10, "design_s": 40.1,
              "completed": True, "startup_s": 14.0, "step_ms_p50": 215.0, "step_ms_p99": 260.0, "rss_mb_total": 1800.0,
              "rss_mb_per_process": 184.0, "closed_loop_cost": 32151.9, "central_cost": 31790.5,
              "cost_ratio": 1.0114, "central_solve_s_p50": 2.94}
    results["machine"] = dict(results["machine"], load_average=3.2, load_average_end=1.5)
    results.update(runtime=[results["runtime"][0], m128], scale=[hosted], date="2026-11-25 10:00 UTC",
                   design=results["design"] + [{"M": 1024, "lmi_s": 30.0, "terminal_set_s": 12.0, "omega_rows": 6144,
                                                "t_star": 2, "design_s": 52.5}])
    from dmpc.bench.results import headline

    results["headline"] = headline(results)
    return results


def test_the_targets_of_start_up_and_of_a_thousand_subsystems():
    rows = {target: (measured, met) for target, measured, met in targets(_full_results())}
    assert rows["M = 128, one process per agent: start-up <= 30 s"] == ("6.2 s", "yes")
    assert rows["M = 1024 end to end, agents hosted many to a process: completes"] == (
        "10 steps, 8 processes of 128 agents", "yes")
    assert rows["M = 1024 design <= 3 min"] == ("52.5 s", "yes")
    quick = {target: (measured, met) for target, measured, met in targets(_results())}
    assert quick["M = 1024 design <= 3 min"] == ("not run", "-")
    assert quick["M = 128, one process per agent: start-up <= 30 s"] == ("not run", "-")
    assert quick["M = 1024 end to end, agents hosted many to a process: completes"] == ("not run", "-")


def test_the_report_opens_with_its_date_headline_and_targets_and_has_the_hosted_table():
    text = markdown(_full_results(), "dmpc bench --write benchmarks/RESULTS.md")
    assert text.startswith("# Benchmarks\n\nMeasured 2026-11-25 10:00 UTC on x86_64")
    assert "Load average (1 min): 3.2 at the start and 1.5 at the end, on 2 cores" in text
    order = [text.index(h) for h in ("## Headline", "## Targets", "## Local QP", "## Multi-process lockstep",
                                     "## Agents hosted many to a process")]
    assert order == sorted(order)
    assert "- The paper's example (M = 4) over Zenoh, one process per agent: step median 4.48 ms, p99 8.52 ms " \
           "(2.00x and 3.00x a bare Zenoh loop's)." in text
    assert "- M = 128, one process per agent: start-up 6.2 s." in text
    assert "- M = 1024: design 52 s, step median 215 ms with agents hosted many to a process." in text
    assert "| 1024 | 8 | 128 | mesh | 40.1 | 14.0 | 215.0 | 260.0 | 1800 | 184 |" in text
    headline = json.loads(text.split("```json")[1].split("```")[0])
    assert headline["max_agents_run"] == 1024 and headline["startup_s_m128"] == 6.2


def test_regenerating_replaces_the_figures_and_keeps_the_dated_history_at_the_end(tmp_path, monkeypatch):
    from dmpc.bench import results as bench_results
    from dmpc.bench.results import HISTORY_HEADING, write_report

    monkeypatch.setattr(bench_results, "plot", lambda results, folder: [])
    report = tmp_path / "RESULTS.md"
    history = f"{HISTORY_HEADING}\n\n### Soak (measured 2026-11-20)\n\n100,000 steps, RSS flat.\n"
    report.write_text("# Benchmarks\n\nSpeed of this machine at the time: 64.2 ms\n\n| M = 4 | 3.66 ms |\n\n"
                      + history)
    write_report(_full_results(), report, "dmpc bench --write benchmarks/RESULTS.md")
    write_report(_full_results(), report, "dmpc bench --write benchmarks/RESULTS.md")
    text = report.read_text()
    assert "64.2 ms" not in text and "3.66 ms" not in text
    assert text.count(HISTORY_HEADING) == 1 and text.endswith(history)
    assert text.index("## Targets") < text.index(HISTORY_HEADING)
    assert json.loads(report.with_suffix(".json").read_text())["headline"]["startup_s_m128"] == 6.2
    fresh = tmp_path / "new.md"
    write_report(_full_results(), fresh, "dmpc bench")
    assert HISTORY_HEADING not in fresh.read_text()


def test_what_a_setpoint_costs_is_a_table_of_its_own():
    row = {"M": 64, "n": 128, "omega_rows": 384, "first_target_ms": 9.0, "target_ms": 7.03, "terminal_set_ms": 0.033,
           "governor_ms": 2.5, "governor_theta": 0.18, "plain_ms_p50": 20.5, "tracked_ms_p50": 21.7,
           "change_step_ms": 22.9, "around_target_ms_p50": 25.2}
    text = markdown({**_results(), "setpoints": [row]}, "dmpc bench")
    assert "## What a setpoint costs" in text
    assert "| 64 | 128 | 384 | 9.0 | 7.0 | 0.03 | 2.5 | 20.50 | 21.70 | 22.90 | 25.20 |" in text
    assert "## What a setpoint costs" not in markdown(_results(), "dmpc bench")  # older results: no table


def _trigger_row(trigger: str, cost, solves: int, keeps: int, kbytes: float, closed: float, step: float) -> dict:
    return {"trigger": trigger, "trigger_cost": cost, "verdict": "ok", "feasible": True, "fallbacks": 0,
            "closed_loop_cost": closed, "solves": solves, "keeps": keeps, "plan_messages": solves,
            "kept_notices": keeps, "bytes": int(kbytes * 1e3), "solve_reasons": {"changed": 67} if keeps else {},
            "step_ms_p50": step, "step_ms_p50_late": step}


def _trigger_results() -> dict:
    """The event trigger's figures: the paper swept, M = 1024 hosted, the carts disturbed."""
    always = _trigger_row("always", None, 308, 0, 138.0, 102.044, 1.3)
    paper = {"case": "paper", "M": 4, "steps": 60, "where": "in process", "always": always,
             "event": [_trigger_row("event", 1e-3, 141, 167, 76.1, 102.044, 1.4),
                       _trigger_row("event", 10.0, 72, 236, 49.1, 102.0458, 1.3)]}
    hosted = {"M": 1024, "processes": 8, "agents_per_process": 128, "topology": "mesh", "steps": 40, "late": 20,
              "calibration_ms": 38.2,
              "always": {**_trigger_row("always", None, 45000, 0, 21000.0, 32150.0, 380.0), "completed": True,
                         "startup_s": 27.0},
              "event": {**_trigger_row("event", 1e-3, 30000, 15000, 15000.0, 32150.0, 250.0), "completed": False,
                        "reason": "error: agent process 3 | exited\nwith code 1"}}
    carts = {"case": "carts", "M": 3, "steps": 40, "bound": 1e-5, "seed": 1, "threshold": 1e-6,
             "always": _trigger_row("always", None, 150, 0, 117.8, 81.7503, 1.9),
             "event": [{**_trigger_row("event", 1e-3, 150, 0, 119.9, 81.7503, 3.2),
                        "solve_reasons": {"no plan": 3, "prediction": 117}}]}
    results = {**_results(), "trigger": {"sweeps": [paper], "hosted": [hosted], "carts": [carts]}}
    from dmpc.bench.results import headline

    results["headline"] = headline(results)
    return results


def test_the_event_trigger_is_a_section_of_its_own_with_its_headline():
    text = markdown(_trigger_results(), "dmpc bench")
    assert "## Event-triggered DMPC against solving at every step" in text
    assert "| paper | 4 | 60 | always | - | 102.0440 | 1.000000 | 308 | 0 | 308 | 0 | 138.0 | 1.00 | 1.30 | - |" in text
    assert "| paper | 4 | 60 | event | 0.001 | 102.0440 | 1.000000 | 141 | 167 | 141 | 167 | 76.1 | 0.46 | 1.40 | " \
           "changed 67 |" in text
    assert "| paper | 4 | 60 | event | 10 | 102.0458 | 1.000018 | 72 | 236 |" in text
    assert "| 1024 | 8 | 128 | 40 | always | - | 32150.0000 | 1.000000 | 45000 | 0 | 45000 | 0 | 21000.0 | 1.00 | " \
           "27.0 | 380.0 | 380.0 | 38.2 |" in text
    assert "| 1024 | 8 | 128 | 40 | event | did not complete: error: agent process 3 / exited with code 1 |" in text
    assert "| 1e-05 | 1e-06 | event | 0.001 | 81.7503 | 1.000000 | 150 | 0 | 150 | 0 | 119.9 | 1.00 | 3.20 | " \
           "no plan 3, prediction 117 |" in text
    assert "- Event trigger (trigger_cost 0.001), the paper's example in process, 60 steps: 141 QP solves and plan " \
           "messages against 308 (46%), 55% of the bytes, closed-loop cost x1.000000." in text
    headline = json.loads(text.split("```json")[1].split("```")[0])
    assert headline["event_solves_over_always_paper"] == 141 / 308
    assert "event_step_ms_p50_late_m1024_hosted" not in headline  # the event run did not complete
    assert "Event-triggered" not in markdown(_results(), "dmpc bench")  # older results: no section


def test_both_hosted_step_medians_are_in_the_headline_when_both_runs_completed():
    results = _trigger_results()
    results["trigger"]["hosted"][0]["event"].update(completed=True)
    from dmpc.bench.results import headline

    results["headline"] = headline(results)
    assert (results["headline"]["always_step_ms_p50_late_m1024_hosted"],
            results["headline"]["event_step_ms_p50_late_m1024_hosted"]) == (380.0, 250.0)
    assert "- M = 1024 hosted, from step 20 on: step median 250 ms with the event trigger, 380 ms solving at every " \
           "step (run just before)." in markdown(results, "dmpc bench")


def test_the_plans_measure_the_trigger_quick_on_the_paper_and_the_carts_only(monkeypatch, tmp_path):
    from dmpc.bench import results as bench_results
    from dmpc.bench import trigger

    calls: list[tuple] = []
    monkeypatch.setattr(trigger, "sweep", lambda M, steps, *a, **k: calls.append(("sweep", M, steps)) or {"M": M})
    monkeypatch.setattr(trigger, "disturbed_pair", lambda b, steps, *a, **k: calls.append(("carts", b, steps)) or {})
    monkeypatch.setattr(trigger, "hosted_pair", lambda M, K, steps, *a, **k: calls.append(("hosted", M, K, steps)) or {})
    into: dict = {"sweeps": [], "hosted": [], "carts": []}
    bench_results.run_trigger(bench_results.QUICK["trigger"], into, tmp_path, tmp_path, lambda label: None)
    assert calls == [("sweep", 4, 60), ("carts", 1e-5, 40)]
    calls.clear()
    bench_results.run_trigger(bench_results.FULL["trigger"], into, tmp_path, tmp_path, lambda label: None)
    assert ("sweep", 64, 30) in calls and ("hosted", 1024, 128, 40) in calls and ("hosted", 64, 1, 40) in calls
    assert bench_results.trigger_tasks(bench_results.FULL["trigger"]) == len(calls)

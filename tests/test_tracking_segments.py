"""Every setpoint in the summary: ``summary.json`` ``tracking.segments`` has one
entry per setpoint segment and requested component, and the printed summary a line per segment,
so that a schedule whose last entry is the origin no longer hides a miss before it.

The settling figures are recomputed here from the recorded states: the 2 % settling time, the
first step after which the component stays within 2 % of its step of the value asked."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from dmpc.records.tables import print_summary, tracking_lines
from tests.helpers.cli import call
from tests.helpers.reference import PAPER

ROOT = Path(__file__).resolve().parents[1]
TWO_ENTRIES = '[{at: 0, subsystem: "1", x: [1.0, null]}, {at: 40, subsystem: "1", x: [-0.5, null]}]'


def simulate(monkeypatch, capsys, out: Path, *argv: str) -> tuple[str, dict, np.lib.npyio.NpzFile]:
    code, stdout, err = call(monkeypatch, capsys, "simulate", str(PAPER), "--out", str(out), "--quiet", *argv)
    assert code == 0, err
    return stdout, json.loads((out / "summary.json").read_text()), np.load(out / "trajectory.npz")


def settling(values: np.ndarray, asked: float, band: float) -> int | None:
    """The first index from which every value is within ``band`` of ``asked`` (None: the last is not)."""
    outside = np.flatnonzero(np.abs(values - asked) > band)
    if outside.size and outside[-1] == values.size - 1:
        return None
    return int(outside[-1] + 1) if outside.size else 0


def segment_rows(stdout: str) -> dict[str, str]:
    """The rows of the printed summary that start with ``setpoint k = ``, label -> value."""
    rows = {}
    for line in stdout.splitlines():
        cells = [c.strip() for c in line.split("│")]
        if len(cells) >= 3 and cells[1].startswith("setpoint k = "):
            rows[cells[1]] = cells[2]
    return rows


def test_the_papers_example_with_two_entries_lists_both_segments_reached_with_settling_times(monkeypatch, capsys,
                                                                                               tmp_path):
    """Issue 32 must show: x_11 = 1.0 from k = 0, -0.5 from k = 40, 80 steps."""
    stdout, summary, arrays = simulate(monkeypatch, capsys, tmp_path / "run", "--steps", "80",
                                       "--set", f"setpoints={TWO_ENTRIES}")
    segments = summary["tracking"]["segments"]
    assert [(s["at"], s["until"], s["subsystem"], s["component"], s["asked"]) for s in segments] == [
        (0, 40, "1", "x1", 1.0), (40, 80, "1", "x1", -0.5)]
    x11 = arrays["x"][:, 0]
    for s in segments:
        assert s["reached"] is True and s["reachable"] is True
        assert s["target"] == pytest.approx(s["asked"], abs=1e-9)
        step = s["asked"] - x11[s["at"]]
        assert s["step"] == pytest.approx(step)
        assert s["tolerance"] == pytest.approx(0.02 * abs(step))
        expected = settling(x11[s["at"]: s["until"] + 1], s["asked"], 0.02 * abs(step))
        assert s["settling_steps"] == expected and 0 < expected < 40
        assert s["settling_s"] is None  # the paper's example has no dt
        assert s["error_at_end"] == pytest.approx(x11[s["until"]] - s["asked"])
        assert abs(s["error_at_end"]) < 1e-4
    rows = segment_rows(stdout)
    assert list(rows) == ["setpoint k = 0", "setpoint k = 40"]
    for s, value in zip(segments, rows.values()):
        assert f"1: x1 = {s['asked']:g} reached in {s['settling_steps']} steps" in value


def test_settling_in_seconds_with_the_scenarios_dt(monkeypatch, capsys, tmp_path):
    """With ``dt: 0.5`` the schedule's ``at`` is in seconds (20 s = step 40), and each segment has
    ``settling_s`` = settling_steps dt; the trajectory is the one without dt."""
    entries = TWO_ENTRIES.replace("at: 40", "at: 20")
    stdout, summary, arrays = simulate(monkeypatch, capsys, tmp_path / "run", "--steps", "80",
                                       "--set", f"setpoints={entries}", "--set", "dt=0.5")
    segments = summary["tracking"]["segments"]
    assert [s["at"] for s in segments] == [0, 40] and summary["tracking"]["dt"] == 0.5
    for s in segments:
        assert s["settling_s"] == pytest.approx(0.5 * s["settling_steps"])
    rows = segment_rows(stdout)
    assert list(rows) == ["setpoint k = 0 (t = 0 s)", "setpoint k = 40 (t = 20 s)"]
    assert f"({segments[1]['settling_s']:.3g} s)" in rows["setpoint k = 40 (t = 20 s)"]


def test_a_miss_before_a_last_entry_at_the_origin_is_shown(monkeypatch, capsys, tmp_path):
    """x_11 = 1.0 for 3 steps only, then the origin: the first segment is not reached, and says so
    in summary.json and on the screen, though the run ends on its last setpoint."""
    entries = '[{at: 0, subsystem: "1", x: [1.0, null]}, {at: 3, subsystem: "1", x: [0.0, null]}]'
    stdout, summary, arrays = simulate(monkeypatch, capsys, tmp_path / "run", "--steps", "60",
                                       "--set", f"setpoints={entries}")
    first, last = summary["tracking"]["segments"]
    assert first["reached"] is False and first["settling_steps"] is None and first["settling_s"] is None
    assert first["error_at_end"] == pytest.approx(arrays["x"][3, 0] - 1.0)
    assert abs(first["error_at_end"]) > first["tolerance"]
    assert last["reached"] is True
    rows = segment_rows(stdout)
    assert "not reached" in rows["setpoint k = 0"] and f"error {first['error_at_end']:.2g}" in rows["setpoint k = 0"]


def test_an_unreachable_request_is_a_segment_not_reached():
    """x_12 = 60 (the steady states hold x_12 within +-4.98): not reachable, not reached, its target named."""
    import dmpc

    result = dmpc.simulate(dmpc.load_scenario(PAPER, steps=40, setpoints=[{"at": 0, "subsystem": "1",
                                                                           "x": [None, 60.0]}]))
    (segment,) = result.summary["tracking"]["segments"]
    assert segment["reachable"] is False and segment["reached"] is False
    assert 4.6 < segment["target"] < 4.98 and segment["component"] == "x2"
    assert segment["error_at_end"] == pytest.approx(result.x["1"][-1, 1] - 60.0)


def _segment(at: int, subsystem: str, component: str, reached: bool, settling: int | None = 12,
             error: float = 1e-7) -> dict:
    return {"at": at, "until": at + 50, "subsystem": subsystem, "component": component, "asked": 1.0, "target": 1.0,
            "reachable": True, "step": 1.0, "reached": reached, "tolerance": 0.02,
            "settling_steps": settling if reached else None, "settling_s": None, "error_at_end": error}


def test_long_schedules_are_grouped_and_keep_every_miss_in_view():
    """Ten carts asked at once: one line for the segment; 14 segments: the first ones in full, the rest
    in one line that still names the misses."""
    many = [_segment(0, str(i), "p [m]", reached=i != 7, error=0.3 if i == 7 else 1e-7) for i in range(1, 11)]
    lines = dict(tracking_lines({"segments": many, "governor_steps": [], "dt": None}))
    assert list(lines) == ["setpoint k = 0"]
    assert re.search(r"10 components: 9 reached in up to 12 steps", lines["setpoint k = 0"])
    assert "not reached: 7: p [m] (error 0.3)" in lines["setpoint k = 0"]
    long = [_segment(10 * j, "1", "x1", reached=j != 12, error=0.2 if j == 12 else 1e-7) for j in range(14)]
    rows = tracking_lines({"segments": long, "governor_steps": [], "dt": None})
    labels = [label for label, _ in rows]
    assert len(rows) <= 8 and labels[-1] == "setpoint k = 70 ... 130"
    assert "7 more segments: 6 reached" in rows[-1][1] and "k = 120 1: x1" in rows[-1][1]


def test_a_unit_in_a_label_is_printed_as_written(capsys):
    """``p [m]`` is a label with its unit, not console markup."""
    summary = {"verdict": "ok", "failures": [], "warnings": [], "scenario": "s", "steps": 60, "feasible": True,
               "qp_failed": 0, "plans_missing": 0, "fallbacks": 0, "max_abs_u": 1.0, "J": [1.0],
               "closed_loop_cost": 1.0, "final_state_norm_inf": 0.5,
               "tracking": {"segments": [_segment(0, "3", "p [m]", reached=True)], "governor_steps": [], "dt": 0.2}}
    print_summary(summary, "runs/x")
    rows = segment_rows(capsys.readouterr().out)
    assert rows == {"setpoint k = 0 (t = 0 s)": "3: p [m] = 1 reached in 12 steps, error 1e-07"}


def test_records_md_documents_the_segments():
    text = (ROOT / "docs" / "records.md").read_text()
    line = next(row for row in text.splitlines() if row.startswith("| `tracking` |"))
    for field in ("segments", "at", "until", "asked", "target", "reachable", "reached", "tolerance",
                  "settling_steps", "settling_s", "error_at_end", "2 %"):
        assert field in line, field

"""Progress over many runs (``dmpc roa``): the number of runs up front, the time left after a few."""
from __future__ import annotations

import io

import pytest
from rich.console import Console

from dmpc.terminal.progress import ProgressBar, RunProgress, duration_text
from tests.helpers.cli import call
from tests.helpers.reference import PAPER


@pytest.mark.parametrize("seconds, text", [(0.04, "0.0 s"), (3.21, "3.2 s"), (42.4, "42 s"), (185, "3 min 5 s"),
                                           (7620, "2 h 7 min"), (-1, "0.0 s")])
def test_duration_text(seconds, text):
    assert duration_text(seconds) == text


def test_lines_announce_the_runs_then_estimate_the_time_left():
    out = io.StringIO()
    now = [100.0]
    progress = RunProgress("roa", 200, "2 methods x 4 horizons x 25 samples", Console(file=out, width=200),
                           clock=lambda: now[0], estimate_after=10)
    progress.start()
    for _ in range(12):
        now[0] += 0.5
        progress.advance()
    progress.stop()
    lines = [line for line in out.getvalue().splitlines() if line]
    assert lines[0] == ("roa: 200 closed-loop runs (2 methods x 4 horizons x 25 samples); an estimate of the time "
                        "follows after the first 10")
    assert lines[1] == "roa: 10 of 200 runs in 5.0 s; about 1 min 35 s left at that pace"
    assert len(lines) == 2  # one estimate only; the bar is not drawn on a non-terminal


def test_roa_announces_its_runs_on_stderr(tmp_path, monkeypatch, capsys):
    code, _, err = call(monkeypatch, capsys, "roa", str(PAPER), "--N", "3", "5", "--samples", "6",
                        "--methods", "tv-box", "--out", str(tmp_path / "r"))
    assert code == 0
    lines = err.splitlines()
    assert lines[0].startswith("roa: 12 closed-loop runs (1 method x 2 horizons x 6 samples, up to 30 steps each)")
    assert lines[1].startswith("roa: 10 of 12 runs in ") and "left at that pace" in lines[1]
    code, _, err = call(monkeypatch, capsys, "roa", str(PAPER), "--N", "3", "--samples", "2", "--methods", "tv-box",
                        "--out", str(tmp_path / "q"), "--quiet")
    assert code == 0 and "closed-loop runs" not in err


def test_one_bar_for_the_steps_drawn_only_where_it_is_seen():
    """The bar of dmpc simulate and dmpc run: nothing at all in a file or pipe; on a terminal the
    count and the fields it was given."""
    out = io.StringIO()
    bar = ProgressBar("steps", 3, Console(file=out, width=100), fields={"J": "-"})
    with bar:
        bar.advance(J="1.5")
        bar.update(3)
    assert not bar.shown and out.getvalue() == ""
    out = io.StringIO()
    bar = ProgressBar("steps", 3, Console(file=out, width=100, force_terminal=True), fields={"J": "-"})
    with bar:
        bar.advance(J="1.5")
        bar.update(3, J="0.25")
    assert bar.shown and "steps" in out.getvalue() and "3/3" in out.getvalue() and "J=0.25" in out.getvalue()

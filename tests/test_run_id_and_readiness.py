"""Starting and finding a run: ``dmpc run --help`` tells what the run id is by
default, ``dmpc run`` says it, and that it designs, before the design, and docs/protocol.md says
where an operator finds the id and how a plant knows the run is ready."""
from __future__ import annotations

import re
from pathlib import Path

from dmpc.core.errors import InputError
from tests.helpers.cli import call
from tests.helpers.reference import PAPER

ROOT = Path(__file__).resolve().parents[1]


def flat(text: str) -> str:
    """``text`` without the boxes of a help screen, on one line."""
    return " ".join(text.replace("│", " ").split())


def test_run_help_gives_the_default_run_id_as_it_is(monkeypatch, capsys):
    code, out, _ = call(monkeypatch, capsys, "run", "--help")
    text = flat(out)
    assert code == 0
    assert re.search(r"--run-id TEXT .*default: the scenario's name and 8 random hex digits, e\.g\. paper-1a2b3c4d", text)
    assert "--run-id TEXT Key prefix shared by the processes of one run (default: the scenario's name)" not in text
    # the other commands' default is the scenario's name, as before
    code, out, _ = call(monkeypatch, capsys, "plant", "--help")
    assert "(default: the scenario's name)" in flat(out)


def _stopped_at_the_design(*args, **kwargs):
    raise InputError("stopped at the design")


def test_run_says_its_id_and_that_it_designs_before_the_design(monkeypatch, capsys, tmp_path):
    monkeypatch.setattr("dmpc.setup.prepare", _stopped_at_the_design)
    code, _, err = call(monkeypatch, capsys, "run", str(PAPER), "--out", str(tmp_path / "a"))
    lines = err.strip().splitlines()
    assert code == 2 and lines[-1] == "error: stopped at the design"
    assert re.fullmatch(r"run id paper-[0-9a-f]{8}: designing the controllers; the coordinator listens once the "
                        r"design is done", lines[0]), lines
    code, _, err = call(monkeypatch, capsys, "run", str(PAPER), "--out", str(tmp_path / "b"), "--run-id", "lab-0412",
                        "--plant", "external", "--port", "7447", "--quiet")
    assert code == 2
    assert err.splitlines()[0] == ("run id lab-0412: designing the controllers; the coordinator listens on "
                                   "tcp/127.0.0.1:7447 once the design is done")


def test_checks_that_need_no_design_come_before_it(monkeypatch, capsys, tmp_path):
    """A wrong option fails at once, in one line, without designing first."""
    monkeypatch.setattr("dmpc.setup.prepare", _stopped_at_the_design)
    for argv, said in ((["--topology", "ring"], "--topology"), (["--plant", "external", "--model", "m:f"], "--model"),
                       (["--tls", str(tmp_path / "none")], "no such directory")):
        code, _, err = call(monkeypatch, capsys, "run", str(PAPER), "--out", str(tmp_path / "c"), *argv)
        assert code == 2 and err.strip().splitlines() == [err.strip()] and said in err, err


def test_protocol_md_says_where_the_run_id_is_and_when_the_run_is_ready():
    text = flat((ROOT / "docs" / "protocol.md").read_text())
    for said in ("`<scenario>-<8 hex digits>`", "run id paper-1a2b3c4d: designing the controllers",
                 "waiting for the plant: connect it to", "live view of `dmpc run --watch` shows it", "`--run-id` of your own",
                 "65-90 s", "`timeout_ms: -1`", "`dmpc design SCENARIO --json > design.json`"):
        assert said in text, said


def test_a_scenario_name_that_is_no_key_chunk_still_gets_a_run_id(monkeypatch, capsys, tmp_path):
    """``name: my carts (v2)``: the id is the name made a key chunk, not a refusal of a --run-id never given."""
    scenario = tmp_path / "named.yaml"
    scenario.write_text(PAPER.read_text().replace("name: paper", "name: my carts (v2)"))
    monkeypatch.setattr("dmpc.setup.prepare", _stopped_at_the_design)
    code, _, err = call(monkeypatch, capsys, "run", str(scenario), "--out", str(tmp_path / "r"))
    assert code == 2 and re.match(r"run id my-carts--v2--[0-9a-f]{8}: designing", err), err

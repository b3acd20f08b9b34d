"""Agents hosted many to a process: the grouping, the host's command line, its outcome and the
start-up time in the summary (no processes started here)."""
from __future__ import annotations

import json

import pytest

from dmpc.agents.process import AgentOutcome, names_text, process_exit_code
from dmpc.records.agent_reports import FIRST_RELEASE, STARTUP, merge_agent_reports
from dmpc.runtime.hosting import group_agents
from dmpc.terminal.exit_codes import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK

NAMES = [str(i) for i in range(1, 11)]


@pytest.mark.parametrize("per_process, sizes", [(1, [1] * 10), (2, [2] * 5), (3, [3, 3, 2, 2]), (4, [4, 3, 3]),
                                                (9, [5, 5]), (10, [10]), (64, [10])])
def test_groups_are_consecutive_balanced_and_at_most_k(per_process, sizes):
    hosts = group_agents(NAMES, per_process)
    assert [len(h.agents) for h in hosts] == sizes
    assert len(hosts) == -(-len(NAMES) // per_process)
    assert [name for h in hosts for name in h.agents] == NAMES  # every name once, in order
    assert max(sizes) - min(sizes) <= 1 and max(sizes) <= per_process


def test_roles_name_a_lone_agent_or_a_numbered_host():
    assert [h.role for h in group_agents(NAMES[:3], 1)] == ["agent-1", "agent-2", "agent-3"]
    assert [h.role for h in group_agents(NAMES, 4)] == ["host-1", "host-2", "host-3"]
    assert group_agents([], 4) == []


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2"])
def test_agents_per_process_must_be_a_positive_integer(bad):
    with pytest.raises(ValueError, match="agents per process"):
        group_agents(NAMES, bad)


def test_host_command_lines_list_their_agents_and_a_report_per_agent(tmp_path):
    from dmpc.runtime.launcher import child_commands
    from dmpc.scenario import load_scenario
    from dmpc.setup import prepare

    prepared = prepare(load_scenario("scenarios/paper.yaml"))
    children = child_commands(prepared, tmp_path, tmp_path / "scenario.yaml", tmp_path / "design.json", "r", 7447,
                              30.0, agents_per_process=3)
    hosts = children[1:]
    assert [c.role for c in hosts] == ["host-1", "host-2"]
    assert [c.agents for c in hosts] == [("1", "2"), ("3", "4")]
    for child in hosts:
        cmd = child.cmd
        assert [cmd[i + 1] for i, arg in enumerate(cmd) if arg == "--id"] == list(child.agents)
        assert cmd[cmd.index("--report") + 1] == str(tmp_path / "logs" / "agent-{id}.json")
        assert child.log_path == tmp_path / "logs" / f"{child.role}.log"
    alone = child_commands(prepared, tmp_path, tmp_path / "scenario.yaml", tmp_path / "design.json", "r", 7447, 30.0)
    assert [(c.role, c.agents) for c in alone[1:]] == [(f"agent-{n}", (n,)) for n in "1234"]
    assert all(c.cmd[c.cmd.index("--report") + 1] == str(tmp_path / "logs" / f"{c.role}.json") for c in alone[1:])


def test_the_process_exits_with_the_worst_code_of_its_agents():
    outcome = [AgentOutcome(EXIT_OK, "a"), AgentOutcome(EXIT_FAILED, "b"), AgentOutcome(EXIT_OK, "c")]
    assert process_exit_code(outcome) == EXIT_FAILED
    assert process_exit_code(outcome + [AgentOutcome(EXIT_INTERRUPTED, "d")]) == EXIT_INTERRUPTED
    assert process_exit_code([AgentOutcome(EXIT_OK, "a")]) == EXIT_OK


def test_long_lists_of_names_are_shortened():
    assert names_text(["1", "2", "3"]) == "1, 2, 3"
    assert names_text(NAMES) == "1, 2, 3, ..., 8, 9, 10 (10 agents)"


def test_startup_is_launch_to_the_first_release_any_agent_saw(tmp_path):
    (tmp_path / "logs").mkdir()
    (tmp_path / "summary.json").write_text(json.dumps({"steps": 3}))
    for name, released in (("1", 105.25), ("2", 104.5), ("3", None)):
        report = {"agent": name, "run_id": "r", "exit_code": 0, "solves": 3, FIRST_RELEASE: released}
        (tmp_path / "logs" / f"agent-{name}.json").write_text(json.dumps(report))
    summary = merge_agent_reports(tmp_path, ["1", "2", "3"])  # the plant's merge: it knows no launch time
    assert STARTUP not in summary
    assert all(FIRST_RELEASE not in entry for entry in summary["agents"].values())
    summary = merge_agent_reports(tmp_path, ["1", "2", "3"], launched_at=100.0)  # the launcher's
    assert summary[STARTUP] == pytest.approx(4.5)
    assert json.loads((tmp_path / "summary.json").read_text())[STARTUP] == summary[STARTUP]


@pytest.mark.parametrize("args, words", [
    (["agent", "scenarios/paper.yaml", "--id", "1", "--id", "1"], ["'1'", "more than once"]),
    (["agent", "scenarios/paper.yaml", "--id", "1", "--id", "9"], ["no subsystem '9'", "1, 2, 3, 4"]),
    (["agent", "scenarios/paper.yaml", "--id", "1", "--id", "2", "--report", "r.json"], ["{id}"]),
    (["agent", "scenarios/paper.yaml", "--id", "1", "--id", "2", "--tls", "certs"], ["--tls", "one --id"]),
    (["run", "scenarios/paper.yaml", "--agents-per-process", "2", "--secure"], ["--agents-per-process 2", "--secure"]),
])
def test_bad_hosting_options_exit_2_with_one_line(monkeypatch, capsys, args, words):
    from tests.helpers.cli import call

    code, _, err = call(monkeypatch, capsys, *args, "--startup-timeout", "1")
    assert code == 2, err
    assert err.startswith("error: ") and len(err.strip().splitlines()) == 1, err
    assert all(w in err for w in words), err


def test_agents_per_process_below_one_is_a_usage_error(monkeypatch, capsys):
    from tests.helpers.cli import call

    code, _, err = call(monkeypatch, capsys, "run", "scenarios/paper.yaml", "--agents-per-process", "0")
    assert code == 2 and "--agents-per-process" in err


@pytest.mark.parametrize("agents, per_process, hosts", [
    (5, 2, {"host-1": ["1", "2"], "host-2": ["3", "4"], "host-3": ["5"]}),  # the last process serves one agent
    (4, 3, {"host-1": ["1", "2"], "host-2": ["3", "4"]}),
    (3, 1, None),  # a process per agent: nothing to list
])
def test_the_summary_lists_every_host_process_and_its_agents(tmp_path, agents, per_process, hosts):
    from dmpc.runtime.launcher import Child
    from dmpc.runtime.launcher import merge_agent_reports as launcher_merge
    from dmpc.runtime.supervisor import Supervision

    names = NAMES[:agents]
    (tmp_path / "logs").mkdir()
    (tmp_path / "summary.json").write_text(json.dumps({"steps": 3}))
    children = [Child("plant", [], tmp_path / "logs" / "plant.log")]
    children += [Child(h.role, [], tmp_path / "logs" / f"{h.role}.log", agents=h.agents)
                 for h in group_agents(names, per_process)]
    summary = launcher_merge(tmp_path, children, Supervision())
    assert summary["launcher"].get("hosts") == hosts
    assert json.loads((tmp_path / "summary.json").read_text())["launcher"].get("hosts") == hosts

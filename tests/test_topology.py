"""The default topology of ``dmpc run`` and ``dmpc.run``: a peer mesh up to ``STAR_ABOVE`` agent
processes, a star through the plant's router above (docs/runtime.md, "Topologies (`dmpc run --topology`)").
No process is started: the launch is replaced by one that records what it was asked for."""
from __future__ import annotations

from pathlib import Path

import pytest

import dmpc
import dmpc.api
from dmpc.runtime import launcher
from dmpc.runtime.launcher import STAR_ABOVE, default_topology

ROOT = Path(__file__).resolve().parents[1]
CHAIN = str(ROOT / "scenarios" / "chain.yaml")


class Launched(Exception):
    """Raised by the recording launch with the topology it was given."""

    def __init__(self, topology: str) -> None:
        super().__init__(topology)
        self.topology = topology


def record_launch(*args, topology: str = "mesh", **kwargs):
    raise Launched(topology)


def test_the_threshold_is_64_agent_processes():
    assert STAR_ABOVE == 64
    assert [default_topology(n) for n in (1, 2, STAR_ABOVE - 1, STAR_ABOVE)] == ["mesh"] * 4
    assert [default_topology(n) for n in (STAR_ABOVE + 1, 128, 1024)] == ["star"] * 3


@pytest.mark.parametrize("agents, per_process, topology", [
    (STAR_ABOVE + 1, 1, "star"),  # 65 processes
    (STAR_ABOVE + 1, 2, "mesh"),  # the same agents in 33 processes
])
def test_dmpc_run_counts_agent_processes_not_agents(monkeypatch, capsys, tmp_path, agents, per_process, topology):
    from tests.helpers.cli import call

    monkeypatch.setattr(launcher, "launch", record_launch)
    with pytest.raises(Launched) as launched:
        call(monkeypatch, capsys, "run", CHAIN, "--set", f"family.M={agents}", "--agents-per-process",
             str(per_process), "--out", str(tmp_path / "run"), "--quiet")
    assert launched.value.topology == topology


@pytest.mark.parametrize("per_process, topology", [(1, "star"), (2, "mesh")])
def test_dmpc_run_from_python_chooses_the_same(monkeypatch, per_process, topology):
    monkeypatch.setattr(dmpc.api, "launch", record_launch)
    with pytest.raises(Launched) as launched:
        dmpc.run(dmpc.load_scenario(CHAIN, **{"family.M": STAR_ABOVE + 1}), steps=2, agents_per_process=per_process)
    assert launched.value.topology == topology


def test_the_docs_and_the_help_give_the_threshold():
    from dmpc.cli import click_command

    text = " ".join((ROOT / "docs" / "runtime.md").read_text().split())
    assert f"`mesh` (the default up to {STAR_ABOVE} agent processes)" in text
    assert f"`star` (the default above {STAR_ABOVE} agent processes)" in text
    option = next(p for p in click_command().commands["run"].params if p.name == "topology")
    assert f"mesh up to {STAR_ABOVE} agent processes, star above" in option.help

"""Runs of the paper's example started process by process, for the tests of the live view.

Starting the plant, an observer and the agents one by one lets a test attach the observer and
its page before the run starts, and stop or kill them at a chosen moment.
"""
from __future__ import annotations

import time
from pathlib import Path

from tests.e2e_helpers import ROOT, Processes, free_port

NAMES = ("1", "2", "3", "4")


def prepare_inputs(folder: Path, overrides: dict) -> Path:
    """scenario.yaml, design.json and run.json of the paper's example with ``overrides``."""
    from dmpc.runtime.launcher import prepare_run_folder
    from dmpc.scenario import load_scenario
    from dmpc.setup import prepare

    prepare_run_folder(folder, prepare(load_scenario(ROOT / "scenarios" / "paper.yaml", overrides)))
    return folder


class HandRun:
    """A plant and its agents as separate ``dmpc`` processes on loopback.

    Parameters
    ----------
    procs : Processes
    inputs : Path
        From :func:`prepare_inputs`.
    out : Path
        The run folder.
    run_id : str
    tls : Path, optional
        A certificate directory: every link over TLS.
    """

    def __init__(self, procs: Processes, inputs: Path, out: Path, run_id: str, tls: Path | None = None) -> None:
        self.procs = procs
        self.inputs = inputs
        self.out = out
        self.run_id = run_id
        self.tls = tls
        proto = "tls" if tls else "tcp"
        self.endpoint = f"{proto}/127.0.0.1:{free_port()}"
        self._agent_listen = f"{proto}/127.0.0.1:0"
        self.plant = None
        self.agents: list = []

    def _tls(self) -> list[str]:
        return ["--tls", str(self.tls)] if self.tls else []

    def start_plant(self):
        self.plant = self.procs.start(
            "plant", str(self.inputs / "scenario.yaml"), "--design", str(self.inputs / "design.json"),
            "--out", str(self.out), "--listen", self.endpoint, "--run-id", self.run_id, "--quiet",
            "--startup-timeout", "60", *self._tls(), log=f"{self.out.name}-plant.log")
        return self.plant

    def start_agents(self) -> list:
        reports = self.out.parent / f"{self.out.name}-reports"
        reports.mkdir(exist_ok=True)
        self.agents = [self.procs.start(
            "agent", str(self.inputs / "run.json"), "--id", name, "--connect", self.endpoint,
            "--listen", self._agent_listen, "--run-id", self.run_id, "--startup-timeout", "60",
            "--report", str(reports / f"agent-{name}.json"), *self._tls(), log=f"{self.out.name}-agent-{name}.log")
            for name in NAMES]
        return self.agents

    def start_watch(self, port: int):
        """``dmpc watch --connect`` on the plant (no run folder: everything comes over the bus)."""
        return self.procs.start("watch", "--connect", self.endpoint, "--run-id", self.run_id, "--port", str(port),
                                *self._tls(), log=f"{self.out.name}-watch.log")

    def wait(self, timeout: float = 120) -> dict[str, int]:
        """Exit codes of the plant and the agents once all have exited."""
        deadline = time.monotonic() + timeout
        codes = {}
        for name, proc in [("plant", self.plant)] + [(f"agent-{n}", a) for n, a in zip(NAMES, self.agents)]:
            codes[name] = proc.wait(timeout=max(1.0, deadline - time.monotonic()))
        return codes

    def reports(self) -> dict[str, dict]:
        import json

        folder = self.out.parent / f"{self.out.name}-reports"
        return {p.stem.split("-", 1)[1]: json.loads(p.read_text()) for p in sorted(folder.glob("agent-*.json"))}

    def log(self, proc) -> str:
        return self.procs.log(proc)

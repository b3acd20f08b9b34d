"""End to end: setpoints changed while a run goes on, over Zenoh (docs/protocol.md, "Setpoints while
a run goes on").

One realtime run of the paper's example takes a request from ``dmpc setpoint`` and one from a
plain Zenoh client written here from docs/protocol.md alone (zenoh, msgpack and numpy: no dmpc
import for the message). A run over TLS with access control (``dmpc.run(secure=True,
on_start=...)``) takes the operator's requests and never sees the one signed by the observer's
certificate. Real processes on loopback, multicast off, a free port per test, every process
stopped at the end.
"""
from __future__ import annotations

import json
import math
import re
import secrets
import subprocess
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh

from tests.e2e_helpers import DMPC, ROOT, Processes, free_port, step_lines, wait_for

pytestmark = pytest.mark.e2e

SCENARIO = "scenarios/paper.yaml"
REALTIME = ["--set", "options.mode=realtime", "--set", "options.dt=0.05"]
ANSWER_WAIT = 5.0


@pytest.fixture
def procs(tmp_path):
    p = Processes(tmp_path)
    yield p
    p.cleanup()


def dmpc_setpoint(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run(DMPC + ["setpoint", *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout,
                          stdin=subprocess.DEVNULL)


# ----------------------------------------------------------------- a client from docs/protocol.md only
def f8(values) -> dict:
    """An ``array(<f8)`` as the page's Encoding section describes it."""
    a = np.asarray(values, dtype="<f8")
    return {"dtype": "<f8", "shape": list(a.shape), "data": a.tobytes()}


def client_config(endpoint: str, tls_dir: Path | None = None, role: str = "operator") -> zenoh.Config:
    """The page's Connecting settings (a client, multicast off); with TLS, ``role``'s certificate."""
    settings = {"mode": "client", "connect": {"endpoints": [endpoint], "timeout_ms": 10000},
                "scouting": {"multicast": {"enabled": False}}}
    if tls_dir is not None:
        settings["transport"] = {"link": {"tls": {
            "root_ca_certificate": str(tls_dir / "ca.pem"), "connect_certificate": str(tls_dir / f"{role}.pem"),
            "connect_private_key": str(tls_dir / f"{role}.key"), "enable_mtls": True}}}
    return zenoh.Config.from_json5(json.dumps(settings))


def ask(config: zenoh.Config, run: str, sender: str, request_id: int, subsystem: str, x, u,
        wait: float = ANSWER_WAIT) -> dict | None:
    """Subscribe to the answer first, publish once a subscriber matches, wait for the answer with our id."""
    body = {"protocol": 3, "type": "setpoint", "run": run, "sender": sender, "id": request_id,
            "subsystem": subsystem, "x": f8(x), "u": f8(u)}
    with zenoh.open(config) as session:
        answers = session.declare_subscriber(f"dmpc/{run}/setpoint-answer/{sender}")
        publisher = session.declare_publisher(f"dmpc/{run}/setpoint/{sender}")
        deadline = time.monotonic() + wait
        while not publisher.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        publisher.put(msgpack.packb(body, use_bin_type=True))
        while time.monotonic() < deadline:
            sample = answers.try_recv()
            if sample is None:
                time.sleep(0.01)
                continue
            answer = msgpack.unpackb(sample.payload.to_bytes(), raw=False)
            if answer.get("type") == "setpoint-answer" and answer.get("id") == request_id:
                return answer
    return None


# ---------------------------------------------------------------------------------------- tests
def test_dmpc_setpoint_and_a_plain_zenoh_client_change_a_running_runs_setpoint(procs, tmp_path):
    port, run_id, out = free_port(), f"live-{secrets.token_hex(4)}", tmp_path / "run"
    run = procs.start("run", SCENARIO, *REALTIME, "--set", "steps=120", "--port", str(port), "--run-id", run_id,
                      "--out", str(out), "--quiet", log="run.log")
    assert wait_for(lambda: step_lines(out) >= 2 or run.poll() is not None, 90), procs.log(run)
    endpoint = f"tcp/127.0.0.1:{port}"

    res = dmpc_setpoint("--connect", endpoint, "--run-id", run_id, "--subsystem", "1", "--x", "1.0,null")
    assert res.returncode == 0, res.stderr
    found = re.fullmatch(r"accepted: subsystem 1 from step (\d+)\n", res.stdout)
    assert found, res.stdout
    K = int(found.group(1))

    answer = ask(client_config(endpoint), run_id, "scada", 17, "1", [1.0, math.nan], [])
    assert answer is not None and answer["accepted"] is True and answer["reason"] == ""
    assert answer["run"] == run_id and answer["subsystem"] == "1" and answer["k"] >= K
    refused = ask(client_config(endpoint), run_id, "scada", 18, "1", [], [3.0])
    assert refused == {"protocol": 3, "type": "setpoint-answer", "run": run_id, "id": 18, "subsystem": "1",
                       "accepted": False, "k": -1,
                       "reason": "u[0]: the target 3 of subsystem '1' is outside U_i [-2.5, 2.5]"}

    import dmpc

    with pytest.raises(dmpc.SetpointRefused, match=r"refused: unknown subsystem '9'") as refusal:
        dmpc.setpoint(endpoint, run_id, "9", x=[1.0, None])
    assert refusal.value.answer.k == -1

    assert run.wait(timeout=120) == 0, procs.log(run)
    steps = [json.loads(line) for line in (out / "steps.jsonl").read_text().splitlines()]
    assert "setpoint from cli (" in steps[K - 1]["note"] and f"from step {K}" in steps[K - 1]["note"]
    assert "setpoint from scada (id 17)" in steps[answer["k"] - 1]["note"]
    assert set(steps[K - 1].get("setpoint", [None])) == {None} and steps[K]["setpoint"][:2] == [1.0, None]
    with np.load(out / "trajectory.npz") as t:
        assert K < 80 and np.isnan(t["setpoint"][:K]).all()
        assert (t["setpoint"][K:, 0] == 1.0).all() and np.isnan(t["setpoint"][K:, 1:]).all()
        assert abs(t["x"][-1, 0] - 1.0) < 1e-3
    summary = json.loads((out / "summary.json").read_text())
    assert summary["verdict"] == "ok" and summary["fallbacks"] == 0, summary["failures"]
    log = (out / "logs" / "plant.log").read_text()
    assert "setpoint request 18 from scada for subsystem 1 refused: u[0]" in log


def test_under_access_control_only_the_operators_certificate_changes_a_setpoint(tmp_path):
    import dmpc

    steps = 160

    seen: dict = {}

    def supervise(live: dmpc.LiveRun) -> None:
        assert live.wait_for_step(1, timeout=90)
        assert live.tls is not None and live.endpoint.startswith("tls/")
        seen["cli"] = dmpc_setpoint("--connect", live.endpoint, "--tls", str(live.tls), "--run-id", live.run_id,
                                    "--subsystem", "1", "--x", "1.0,null")
        seen["python"] = live.setpoint("3", x=[0.2, None])
        # a client of its own with the operator's certificate is answered too
        seen["operator"] = ask(client_config(live.endpoint, live.tls, "operator"), live.run_id, "panel", 6, "4",
                               [], [math.nan])
        # the observer's certificate is valid, but the access control lets it publish nothing
        seen["observer"] = ask(client_config(live.endpoint, live.tls, "observer"), live.run_id, "scada", 5, "2",
                               [0.5, math.nan], [], wait=2.0)
        seen["steps then"] = live.steps()

    scenario = dmpc.load_scenario(ROOT / SCENARIO, steps=steps, **{"options.mode": "realtime", "options.dt": 0.05})
    result = dmpc.run(scenario, out=tmp_path / "run", secure=True, on_start=supervise)

    assert seen["observer"] is None and seen["steps then"] < steps  # the run was still going
    assert seen["operator"]["accepted"] is True and seen["operator"]["subsystem"] == "4"
    assert seen["cli"].returncode == 0 and seen["cli"].stdout.startswith("accepted: subsystem 1 from step "), \
        seen["cli"].stderr
    answer = seen["python"]
    assert answer.accepted and answer.subsystem == "3"
    assert result.verdict == "ok" and result.summary["security"]["access_control"]
    assert np.isnan(result.setpoint["2"]).all()  # the observer's request never arrived
    assert (result.setpoint["3"][answer.k:, 0] == 0.2).all() and np.isnan(result.setpoint["3"][:answer.k]).all()
    notes = " ".join(json.loads(line)["note"] for line in (tmp_path / "run" / "steps.jsonl").read_text().splitlines())
    assert all(f"setpoint from {who}" in notes for who in ("panel", "cli", "python")) and "scada" not in notes
    assert "scada" not in (tmp_path / "run" / "logs" / "plant.log").read_text()

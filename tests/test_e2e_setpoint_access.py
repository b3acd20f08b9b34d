"""End to end: a setpoint request under TLS and access control always ends with a definite outcome
(docs/protocol.md, "Setpoints while a run goes on" and "Access control").

One run of the paper's example with ``dmpc run --secure`` (real time, so that it goes on while the
requests are sent) takes requests signed by the operator's certificate, by the observer's, the
plant's and an agent's, and from clients without a certificate. The operator's is accepted; the
others end, within their timeout, as "not authorised or no run listening" (``dmpc setpoint``), or
as a query that ends without a reply (a client of its own, from docs/protocol.md alone), though a
publisher with the same certificate matches the coordinator's subscriber: a match is not a
delivery. Without a certificate no session opens. The run never sees any of them.

Real processes on loopback, multicast off, a free port, every process stopped at the end; the
tests wait for events (steps recorded, processes exiting, queries ending), never for fixed times.
"""
from __future__ import annotations

import json
import math
import secrets
import shutil
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
STEPS = 4000  # 200 s at dt = 0.05: longer than every test of the module; stopped at its end
TIMEOUT = 10.0  # seconds each request may take, connecting included
REFUSED_ROLES = ["observer", "plant", "agent-1"]


@pytest.fixture(scope="module")
def secure_run(tmp_path_factory):
    """A realtime run under ``--secure``: its endpoint, run id, folder and certificate directory."""
    base = tmp_path_factory.mktemp("secure-setpoints")
    procs = Processes(base)
    port, run_id, out = free_port(), f"acl-{secrets.token_hex(4)}", base / "run"
    run = procs.start("run", SCENARIO, "--secure", "--set", "options.mode=realtime", "--set", "options.dt=0.05",
                      "--set", f"steps={STEPS}", "--port", str(port), "--run-id", run_id, "--out", str(out),
                      "--quiet", log="run.log")
    try:
        assert wait_for(lambda: step_lines(out) >= 2 or run.poll() is not None, 120), procs.log(run)
        assert run.poll() is None, procs.log(run)
        yield {"endpoint": f"tls/127.0.0.1:{port}", "run_id": run_id, "out": out, "tls": out / "tls",
               "base": base, "procs": procs, "run": run}
    finally:
        procs.cleanup()


def as_role(secure_run: dict, role: str) -> Path:
    """A certificate directory whose ``operator`` files are ``role``'s: what a program given the
    wrong certificate presents."""
    folder = secure_run["base"] / f"as-{role}"
    if not folder.exists():
        folder.mkdir()
        tls = secure_run["tls"]
        for name in ("ca.pem", "acl.json"):
            shutil.copy(tls / name, folder / name)
        shutil.copy(tls / f"{role}.pem", folder / "operator.pem")
        shutil.copy(tls / f"{role}.key", folder / "operator.key")
    return folder


def dmpc_setpoint(secure_run: dict, *args: str) -> subprocess.CompletedProcess:
    """``dmpc setpoint`` on the run, subsystem 1's x_11 = 0.5 (``args`` add the TLS and sender flags)."""
    return subprocess.run(DMPC + ["setpoint", "--connect", secure_run["endpoint"], "--run-id", secure_run["run_id"],
                                  "--subsystem", "1", "--x", "0.5,null", "--timeout", str(TIMEOUT), *args],
                          cwd=ROOT, capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL)


def client(secure_run: dict, role: str) -> zenoh.Config:
    """docs/protocol.md's client settings with ``role``'s certificate."""
    tls = secure_run["tls"]
    settings = {"mode": "client", "connect": {"endpoints": [secure_run["endpoint"]], "timeout_ms": 10000},
                "scouting": {"multicast": {"enabled": False}},
                "transport": {"link": {"tls": {"root_ca_certificate": str(tls / "ca.pem"),
                                               "connect_certificate": str(tls / f"{role}.pem"),
                                               "connect_private_key": str(tls / f"{role}.key"),
                                               "enable_mtls": True}}}}
    return zenoh.Config.from_json5(json.dumps(settings))


def request_body(run_id: str, sender: str, request_id: int) -> bytes:
    x = np.array([0.5, math.nan], dtype="<f8")
    return msgpack.packb({"protocol": 3, "type": "setpoint", "run": run_id, "sender": sender, "id": request_id,
                          "subsystem": "1", "x": {"dtype": "<f8", "shape": [2], "data": x.tobytes()},
                          "u": {"dtype": "<f8", "shape": [0], "data": b""}}, use_bin_type=True)


def ask_by_query(config: zenoh.Config, run_id: str, sender: str, request_id: int) -> dict:
    """As docs/protocol.md says: wait for the coordinator's queryable, send the request as a query,
    read the replies until the query ends. Also publishes the same request, to see the publisher
    match. Returns the answer (None if the query ended without one), whether the query ended by
    itself (not at its timeout), and whether the publisher matched."""
    key = f"dmpc/{run_id}/setpoint/{sender}"
    with zenoh.open(config) as session:
        querier = session.declare_querier(key, timeout=TIMEOUT)
        publisher = session.declare_publisher(key)
        deadline = time.monotonic() + TIMEOUT
        while not (querier.matching_status.matching and publisher.matching_status.matching) \
                and time.monotonic() < deadline:
            time.sleep(0.01)
        matched = bool(publisher.matching_status.matching)
        answer, timed_out = None, False
        for reply in querier.get(payload=request_body(run_id, sender, request_id)):
            if reply.ok is not None:
                answer = msgpack.unpackb(reply.ok.payload.to_bytes(), raw=False)
            else:
                timed_out = True  # Zenoh's "Timeout" error: nobody ended the query
        publisher.put(request_body(run_id, sender, request_id + 1))
    return {"answer": answer, "ended": not timed_out, "publisher_matched": matched}


# ------------------------------------------------------------------------------------------ tests
def test_the_operators_certificate_is_answered(secure_run):
    res = dmpc_setpoint(secure_run, "--tls", str(secure_run["tls"]), "--name", "panel")
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith("accepted: subsystem 1 from step "), res.stdout
    asked = ask_by_query(client(secure_run, "operator"), secure_run["run_id"], "scada", 17)
    assert asked["answer"]["accepted"] is True and asked["answer"]["id"] == 17 and asked["ended"]


@pytest.mark.parametrize("role", REFUSED_ROLES)
def test_another_roles_certificate_is_told_not_authorised_or_no_run_listening(secure_run, role):
    res = dmpc_setpoint(secure_run, "--tls", str(as_role(secure_run, role)), "--name", f"as-{role}")
    assert res.returncode == 1, res.stdout + res.stderr
    assert res.stderr.startswith(f"not authorised or no run listening: no answer from the coordinator of run "
                                 f"{secure_run['run_id']} at {secure_run['endpoint']} within {TIMEOUT:g} s"), res.stderr
    assert "accepted" not in res.stdout
    asked = ask_by_query(client(secure_run, role), secure_run["run_id"], f"own-{role}", 40)
    assert asked["answer"] is None
    assert asked["ended"], "the query ran into its timeout instead of ending unanswered"
    assert asked["publisher_matched"], "a publisher with this certificate matches the coordinator's subscriber"
    assert secure_run["run"].poll() is None  # the run goes on


def test_without_a_certificate_no_request_leaves(secure_run):
    res = dmpc_setpoint(secure_run, "--name", "none")  # a tls/ endpoint without --tls
    assert res.returncode == 2
    assert "is a TLS endpoint: give the certificate directory with the operator certificate" in res.stderr
    empty = secure_run["base"] / "no-operator"
    empty.mkdir(exist_ok=True)
    shutil.copy(secure_run["tls"] / "ca.pem", empty / "ca.pem")
    res = dmpc_setpoint(secure_run, "--tls", str(empty), "--name", "none")
    assert res.returncode == 2 and "no operator.pem for role 'operator'" in res.stderr, res.stderr
    # a client of its own that trusts the CA but has no certificate: the handshake fails, no session
    settings = {"mode": "client", "connect": {"endpoints": [secure_run["endpoint"]], "timeout_ms": 2000},
                "scouting": {"multicast": {"enabled": False}},
                "transport": {"link": {"tls": {"root_ca_certificate": str(secure_run["tls"] / "ca.pem")}}}}
    with pytest.raises(zenoh.ZError):
        zenoh.open(zenoh.Config.from_json5(json.dumps(settings))).close()


def test_the_run_never_saw_a_refused_request(secure_run):
    """Last in the module: the run's records and log name the operator's requests only."""
    procs, out = secure_run["procs"], secure_run["out"]
    lines = [json.loads(line) for line in (out / "steps.jsonl").read_text().splitlines()]
    notes = " ".join(line["note"] for line in lines)
    assert "setpoint from panel (" in notes and "setpoint from scada (id 17)" in notes
    log = (out / "logs" / "plant.log").read_text()
    for role in REFUSED_ROLES:
        assert f"as-{role}" not in notes and f"own-{role}" not in notes
        assert f"as-{role}" not in log and f"own-{role}" not in log
    assert "from none" not in log
    assert secure_run["run"].poll() is None, procs.log(secure_run["run"])

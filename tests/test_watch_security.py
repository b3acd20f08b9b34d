"""The observer on a secure bus: its certificate lets it read the telemetry and nothing else.

A TLS run of the paper's example (real processes, real time at 0.1 s a step so that the run
lasts while the observer acts, a deadline no plan comes near). A rogue holding the run's valid
``observer`` certificate subscribes to the telemetry, to releases and plans, and for every step
it sees publishes well-formed plans, releases, a Stop and Ready on others' keys, and garbage.
With the scenario's access control nothing of it arrives anywhere, it receives no release or
plan, and the run is the clean one; without the access control the same rogue is heard.

``python -m tests.test_watch_security rogue ...`` is that rogue.
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tests.e2e_helpers import ROOT, Processes, max_abs_diff, simulate_paper, wait_for
from tests.helpers.watch_runs import HandRun, prepare_inputs

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

OPTIONS = {"options.mode": "realtime", "options.dt": 0.1, "options.deadline": 5.0}


@pytest.fixture(scope="module")
def setup(tmp_path_factory) -> dict:
    """The reference (``dmpc simulate``), the run's inputs and a certificate directory."""
    from dmpc.prepared.bundle import load_bundle
    from dmpc.security.certs import make_run_security

    base = tmp_path_factory.mktemp("watch-security")
    inputs = prepare_inputs(base / "inputs", OPTIONS)
    make_run_security(base / "tls", load_bundle(inputs / "run.json").system)
    return {"sim": simulate_paper(base / "sim"), "inputs": inputs, "tls": base / "tls"}


def rogue_run(tmp_path: Path, setup: dict, tls: Path) -> tuple[Path, dict, dict]:
    """A TLS run with the rogue observer; returns (run folder, what the rogue did, agent reports)."""
    procs = Processes(tmp_path)
    try:
        run = HandRun(procs, setup["inputs"], tmp_path / "run", "observed", tls=tls)
        run.start_plant()
        rogue = start_rogue(procs, run, tls, setup, tmp_path)
        lines = iter(rogue.stdout)
        assert wait_for_line(lines, "ROGUE READY", 30) is not None, (tmp_path / "rogue.log").read_text()
        run.start_agents()
        codes = run.wait()
        done = wait_for_line(lines, "ROGUE DONE ", 30)
        assert done is not None, (tmp_path / "rogue.log").read_text()
        done = json.loads(done)
        assert codes["plant"] in (0, 1, 3), run.log(run.plant)[-2000:]
        return run.out, done, run.reports()
    finally:
        procs.cleanup()


def start_rogue(procs: Processes, run: HandRun, tls: Path, setup: dict, tmp_path: Path) -> subprocess.Popen:
    """This module's rogue with the observer's certificate of ``tls``, on ``run``'s plant."""
    with open(tmp_path / "rogue.log", "wb") as log:
        rogue = subprocess.Popen([sys.executable, "-m", "tests.test_watch_security", "rogue", "--connect", run.endpoint,
                                  "--run", run.run_id, "--tls", str(tls), "--bundle", str(setup["inputs"] / "run.json")],
                                 cwd=ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=log,
                                 start_new_session=True)
    procs.procs.append(rogue)
    return rogue


def wait_for_line(lines, prefix: str, timeout: float) -> str | None:
    """What follows ``prefix`` on the next line of ``lines`` that starts with it (None after ``timeout``)."""
    found: list[str] = []

    def reader():
        for raw in lines:
            text = raw.decode(errors="replace").strip()
            if text.startswith(prefix):
                found.append(text[len(prefix):])
                return

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    thread.join(timeout)
    return found[0] if found else None


def test_the_observer_certificate_reads_telemetry_and_can_publish_nothing(tmp_path, setup):
    out, done, reports = rogue_run(tmp_path, setup, setup["tls"])
    assert done["telemetry"] > 0, done  # connected, authenticated, and reading what it may
    assert done["forged"] > 0 and done["garbage"] > 0, done
    assert done["releases"] == 0 and done["plans"] == 0, done  # subscriptions to the protocol: denied
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 30 and summary["fallbacks"] == 0 and not summary.get("failure")
    assert max_abs_diff(setup["sim"], out) <= 1e-9
    assert summary["rejected"] == {} and summary["duplicates"] == 0  # nothing it sent reached the plant
    for name, report in reports.items():
        assert report["exit_code"] == 0 and report["rejected"] == {}, (name, report)


def test_without_access_control_the_same_rogue_is_heard(tmp_path, setup):
    """The control experiment: with the same certificates but no acl.json, the plant receives
    the rogue's messages (it drops its garbage on plan/1 and says so)."""
    open_tls = tmp_path / "tls-no-acl"
    shutil.copytree(setup["tls"], open_tls)
    (open_tls / "acl.json").unlink()
    procs = Processes(tmp_path)
    try:
        run = HandRun(procs, setup["inputs"], tmp_path / "run", "open", tls=open_tls)
        run.start_plant()
        rogue = start_rogue(procs, run, open_tls, setup, tmp_path)
        assert wait_for_line(iter(rogue.stdout), "ROGUE READY", 30) is not None, (tmp_path / "rogue.log").read_text()
        run.start_agents()
        assert wait_for(lambda: "dropped a message from 1" in run.log(run.plant), 60), run.log(run.plant)[-2000:]
    finally:
        procs.cleanup()


# ------------------------------------------------------------------------------------- the rogue
def _rogue(argv: list[str]) -> int:
    import zenoh

    from dmpc.bus import keys
    from dmpc.bus.codec import encode
    from dmpc.bus.messages import PlanMessage, Ready, Stop
    from dmpc.bus.session import open_session, session_config
    from dmpc.prepared.bundle import load_bundle
    from dmpc.security.files import node_security

    p = argparse.ArgumentParser(prog="rogue")
    p.add_argument("--connect", required=True)
    p.add_argument("--run", required=True)
    p.add_argument("--tls", type=Path, required=True)
    p.add_argument("--bundle", type=Path, required=True)
    args = p.parse_args(argv)
    prepared = load_bundle(args.bundle)
    N = prepared.design.horizon
    R = args.run
    tls, acl = node_security(args.tls, "observer")
    session = open_session(session_config(mode="client", connect=[args.connect], tls=tls, acl=acl), timeout=20)
    counts = {"telemetry": 0, "releases": 0, "plans": 0, "forged": 0, "garbage": 0}
    steps: list[int] = []
    alive: set[str] = set()
    gone = threading.Event()
    lock = threading.Lock()

    def on_telemetry(sample):
        msg = json.loads(sample.payload.to_bytes())
        with lock:
            counts["telemetry"] += 1
            if msg.get("type") == "step":
                steps.append(msg["step"]["k"])

    def count(kind):
        def callback(sample):
            with lock:
                counts[kind] += 1
        return callback

    def on_alive(sample):
        role = keys.last_chunk(str(sample.key_expr))
        if sample.kind == zenoh.SampleKind.PUT:
            alive.add(role)
        elif role == keys.COORDINATOR_ROLE:
            gone.set()

    entities = [session.declare_subscriber(keys.telemetry_prefix(R), on_telemetry),
                # remote only: its own puts on these keys would otherwise come back to it
                session.declare_subscriber(f"{keys.ROOT}/{R}/release/**", count("releases"),
                                           allowed_origin=zenoh.Locality.REMOTE),
                session.declare_subscriber(f"{keys.ROOT}/{R}/release", count("releases"),
                                           allowed_origin=zenoh.Locality.REMOTE),
                session.declare_subscriber(keys.plan(R, "*"), count("plans"), allowed_origin=zenoh.Locality.REMOTE),
                session.liveliness().declare_subscriber(keys.alive_prefix(R), on_alive, history=True)]
    deadline = time.monotonic() + 20
    while keys.COORDINATOR_ROLE not in alive and time.monotonic() < deadline:
        time.sleep(0.01)
    try:
        entities.append(session.liveliness().declare_token(keys.alive(R, "agent-1")))  # denied by the plant
    except zenoh.ZError:
        pass
    print("ROGUE READY", flush=True)
    rng = np.random.default_rng(5)
    n3, m3 = prepared.system.subsystems[2].n, prepared.system.subsystems[2].m
    end = time.monotonic() + 120
    while not gone.is_set() and time.monotonic() < end:
        with lock:
            k = steps[-1] + 1 if steps else 0
        for r in range(2):  # the rounds a step of this run can have open
            plan = PlanMessage(run=R, k=k, round=r, sender="3", status="solved", z=np.zeros((N + 1, n3)),
                               v=np.full((N, m3), 2.0), cost=0.0, solve_time=0.0, qp_iterations=1)
            session.put(keys.plan(R, "3"), encode(plan))
            counts["forged"] += 1
        session.put(keys.ready(R, "1"), encode(Ready(run=R, sender="1", design_digest=prepared.digest)))
        session.put(keys.control(R), encode(Stop(run=R, k=k, reason="finished")))
        counts["forged"] += 2
        for key in (keys.plan(R, "1"), keys.ready(R, "2"), keys.control(R), f"{keys.ROOT}/{R}/release",
                    keys.telemetry(R, "step")):
            session.put(key, rng.bytes(int(rng.integers(1, 64))))
            counts["garbage"] += 1
        time.sleep(0.005)
    for entity in entities:
        try:
            entity.undeclare()
        except zenoh.ZError:
            pass
    session.close()
    print("ROGUE DONE " + json.dumps(counts), flush=True)
    return 0


def main(argv: list[str]) -> int:
    if argv and argv[0] == "rogue":
        return _rogue(argv[1:])
    print("usage: python -m tests.test_watch_security rogue ...", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

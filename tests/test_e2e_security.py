"""End to end: TLS with mutual authentication, access control, and a bus flooded with garbage.

Real processes on loopback (multicast off, a free port per test). Besides the dmpc processes,
two kinds of hostile or probing processes run this module as a script:

``python -m tests.test_e2e_security probe ...``
    tries to connect to a secure router or plant with a valid certificate, without one, with
    one from another CA and over plain TCP, and prints what each attempt achieved (JSON).
``python -m tests.test_e2e_security rogue ...``
    joins a run and, until the plant leaves, either floods every bus key with garbage
    (``flood``) or, holding agent 1's valid certificate, sends well-formed messages on keys
    that are not agent 1's (``spoof``). It prints how many messages it sent (JSON).
"""
from __future__ import annotations

import argparse
import json
import re
import shutil
import stat
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tests.e2e_helpers import ROOT, Processes, free_port, max_abs_diff, pid_alive, run_cli
from tests.helpers.tls import ca_key_files

pytestmark = pytest.mark.e2e

SCENARIO = "scenarios/paper.yaml"
PYTHON = sys.executable
OPEN_TIMEOUT = 2.0  # seconds an unauthenticated probe keeps trying before it gives up


# ----------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def paper(tmp_path_factory):
    """The reference run (``dmpc simulate``) and a run folder's inputs for hand-started processes."""
    from dmpc.runtime.launcher import prepare_run_folder
    from dmpc.scenario import load_scenario
    from dmpc.setup import prepare

    base = tmp_path_factory.mktemp("paper")
    res = run_cli("simulate", SCENARIO, "--out", str(base / "sim"), "--quiet")
    assert res.returncode == 0, res.stderr
    inputs = base / "inputs"
    prepare_run_folder(inputs, prepare(load_scenario(ROOT / SCENARIO)))  # scenario.yaml, design.json, run.json
    return {"sim": base / "sim", "inputs": inputs}


@pytest.fixture(scope="module")
def certs(tmp_path_factory, paper):
    """A certificate directory for the paper's roles (any run id), and agent-1 from another CA."""
    from dmpc.prepared.bundle import load_bundle
    from dmpc.security.certs import make_certificates, make_run_security

    base = tmp_path_factory.mktemp("certs")
    make_run_security(base / "tls", load_bundle(paper["inputs"] / "run.json").system)
    make_certificates(base / "other", ["agent-1"])
    return {"tls": base / "tls", "other": base / "other"}


# ------------------------------------------------------------------------------------ helpers
def start_plant(procs: Processes, paper: dict, out: Path, endpoint: str, run_id: str, tls: Path | None = None,
                topology: str = "mesh"):
    """``dmpc plant`` listening on ``endpoint``; in the star topology its session is a router."""
    inputs = paper["inputs"]
    return procs.start("plant", str(inputs / "scenario.yaml"), "--design", str(inputs / "design.json"),
                       "--out", str(out), "--listen", endpoint, "--run-id", run_id, "--quiet",
                       "--startup-timeout", "60", *(["--tls", str(tls)] if tls else []),
                       *(["--mode", "router"] if topology == "star" else []), log="plant.log")


def start_agents(procs: Processes, paper: dict, endpoint: str, run_id: str, reports: Path,
                 tls: Path | None = None, topology: str = "mesh") -> list:
    """The four agents, as ``dmpc run`` starts them (peers that listen, or the router's clients)."""
    proto = endpoint.split("/", 1)[0]
    net = ["--mode", "client"] if topology == "star" else ["--listen", f"{proto}/127.0.0.1:0"]
    reports.mkdir(exist_ok=True)
    return [procs.start("agent", str(paper["inputs"] / "run.json"), "--id", name, "--connect", endpoint, *net,
                        "--run-id", run_id, "--startup-timeout", "60",
                        "--report", str(reports / f"agent-{name}.json"), *(["--tls", str(tls)] if tls else []),
                        log=f"agent-{name}.log")
            for name in ("1", "2", "3", "4")]


def start_script(procs: Processes, *args: str, log: str):
    """This module as a script (probe or rogue) in its own process."""
    import subprocess

    out = open(procs.tmp / log, "wb")
    proc = subprocess.Popen([PYTHON, "-m", "tests.test_e2e_security", *args], cwd=ROOT, stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=out, start_new_session=True)
    out.close()
    proc.log_path = procs.tmp / log
    procs.procs.append(proc)
    return proc


def read_line(proc, prefix: str, timeout: float) -> dict:
    """The JSON after ``prefix`` on the next stdout line that starts with it."""
    result: dict = {}
    found = threading.Event()

    def reader():
        for raw in proc.stdout:
            line = raw.decode(errors="replace").strip()
            if line.startswith(prefix):
                result.update(json.loads(line[len(prefix):] or "{}"))
                found.set()
                return

    threading.Thread(target=reader, daemon=True).start()
    assert found.wait(timeout), f"no '{prefix}' line within {timeout} s; stderr:\n{Path(proc.log_path).read_text()}"
    return result


def wait_exit(procs: Processes, proc, timeout: float, what: str) -> int:
    try:
        return proc.wait(timeout=timeout)
    except Exception:  # noqa: BLE001 - report the log, the fixture kills it
        pytest.fail(f"{what} did not exit within {timeout} s; log:\n{procs.log(proc)[-3000:]}")


def clean_steps(paper: dict) -> int:
    return json.loads((paper["sim"] / "summary.json").read_text())["steps"]


def clean_solves(paper: dict, name: str) -> int:
    """How many QPs agent ``name`` solved in the clean (in-process) run."""
    return json.loads((paper["sim"] / "summary.json").read_text())["agents"][name]["solves"]


def reports(folder: Path) -> dict:
    return {p.stem.split("-", 1)[1]: json.loads(p.read_text()) for p in sorted(folder.glob("agent-*.json"))}


# ------------------------------------------------------------------------ 1. who may connect
@pytest.mark.parametrize("target", ["router", "plant"])
def test_clients_without_a_valid_certificate_cannot_connect(procs, tmp_path, paper, certs, target):
    """A client without a certificate, with one from another CA, or over plain TCP never gets a
    session with a secure router or plant; one with a valid certificate does, and sees the bus."""
    port = free_port()
    endpoint = f"tls/127.0.0.1:{port}"
    run_id = "conn"
    if target == "router":
        server = procs.start("router", "--listen", endpoint, "--tls", str(certs["tls"]), log="router.log")
    else:
        server = start_plant(procs, paper, tmp_path / "run", endpoint, run_id, certs["tls"])
    probe = start_script(procs, "probe", "--connect", endpoint, "--run", run_id, "--tls", str(certs["tls"]),
                         "--other", str(certs["other"]), "--target", target, log="probe.log")
    result = read_line(probe, "PROBE ", timeout=40)
    assert wait_exit(procs, probe, 10, "probe") == 0
    # the valid client is in and sees the bus: the coordinator's token (the plant process hosts
    # it), or (router) another client's
    assert result["valid"]["opened"], result
    assert result["valid"]["seen"] == (["coordinator"] if target == "plant" else ["agent-2"]), result
    assert result["valid_raw"]["opened"] and result["valid_raw"]["seen"] == result["valid"]["seen"], result
    for name in ("no_cert", "other_ca", "tcp"):
        assert not result[name]["opened"], f"{name} got a session: {result}"
        assert "cannot open" in result[name]["error"], result[name]
    assert server.poll() is None, "the server died of the attempts:\n" + procs.log(server)


# ------------------------------------------------------------- 2. access control on the bus
def spoof_run(procs: Processes, tmp_path: Path, paper: dict, tls: Path, run_id: str,
              topology: str = "mesh") -> tuple[Path, dict, dict]:
    """A TLS run with a rogue holding agent 1's certificate; returns (run folder, rogue counts, reports)."""
    port = free_port()
    endpoint = f"tls/127.0.0.1:{port}"
    out = tmp_path / "run"
    plant = start_plant(procs, paper, out, endpoint, run_id, tls, topology)
    rogue = start_script(procs, "rogue", "spoof", "--connect", endpoint, "--run", run_id, "--tls", str(tls),
                         "--role", "agent-1", "--bundle", str(paper["inputs"] / "run.json"),
                         "--mode", "client" if topology == "star" else "peer", log="rogue.log")
    read_line(rogue, "ROGUE READY", timeout=30)
    agents = start_agents(procs, paper, endpoint, run_id, tmp_path / "reports", tls, topology)
    wait_exit(procs, plant, 90, "plant")
    sent = read_line(rogue, "ROGUE SENT ", timeout=20)
    for agent in agents:
        wait_exit(procs, agent, 20, "agent")
    return out, sent, reports(tmp_path / "reports")


@pytest.mark.parametrize("topology", ["mesh", "star"])
def test_acl_denies_an_authenticated_agent_on_other_agents_keys(procs, tmp_path, paper, certs, topology):
    """Holding agent 1's valid certificate, a rogue sends well-formed plans on plan/3, releases on
    release, Stop on control and garbage on those keys and on ready/3: none of it arrives
    anywhere and the trajectory is the clean one. Its garbage on plan/1, its own key, does
    arrive and is counted: the rogue was connected, and only the access control stopped it.
    In the mesh every node filters what the rogue's direct links bring in; in the star the
    plant's router filters it at the first hop."""
    out, sent, agent_reports = spoof_run(procs, tmp_path, paper, certs["tls"], f"acl-{topology}", topology)
    assert sent["releases_seen"] > 0 and sent["forged"] > 0, sent
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == clean_steps(paper) and summary["fallbacks"] == 0 and not summary.get("failure")
    assert max_abs_diff(paper["sim"], out) <= 1e-9
    # counted on the plant only from agent 1's own key, never from "3" or an unknown sender
    assert set(summary["rejected"]) == {"1"} and summary["rejected"]["1"] > 0, summary["rejected"]
    # agent 2 subscribes to plan/1 and counts the garbage; nothing from the plant's keys anywhere
    assert agent_reports["2"]["rejected"].get("1", 0) > 0, agent_reports
    for name, report in agent_reports.items():
        assert report["exit_code"] == 0 and report["solves"] == clean_solves(paper, name), (name, report)
        assert set(report["rejected"]) <= {"1"}, (name, report)  # no release/control/plan-3 garbage got in
    assert summary["duplicates"] == 0 and all(r["duplicates"] == 0 for r in agent_reports.values())


def test_without_access_control_the_same_rogue_breaks_the_run(procs, tmp_path, paper, certs):
    """The control experiment: the same certificates without acl.json let the rogue's forged
    messages through, and the run no longer follows the clean trajectory."""
    open_tls = tmp_path / "tls-no-acl"
    shutil.copytree(certs["tls"], open_tls)
    (open_tls / "acl.json").unlink()
    out, sent, agent_reports = spoof_run(procs, tmp_path, paper, open_tls, "noacl")
    assert sent["forged"] > 0, sent
    summary = json.loads((out / "summary.json").read_text())
    broken = (summary["steps"] < clean_steps(paper) or summary["fallbacks"] > 0 or bool(summary.get("failure"))
              or max_abs_diff(paper["sim"], out) > 1e-6)
    assert broken, "forged messages had no effect without access control: the ACL test would prove nothing"


# --------------------------------------------------------------------------- 3. a garbage flood
def test_run_survives_a_flood_of_garbage(procs, tmp_path, paper):
    """A rogue peer floods plan/*, release, ready/* and control with random bytes, truncated
    and malformed msgpack, plausible but wrong messages and replayed plans during a plain TCP
    run: the run has the clean trajectory, and every drop is counted per sender (plant in
    summary.json, agents in their reports), with at most one log line per sender per second."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    run_id = "flood"
    out = tmp_path / "run"
    plant = start_plant(procs, paper, out, endpoint, run_id)
    rogue = start_script(procs, "rogue", "flood", "--connect", endpoint, "--run", run_id,
                         "--bundle", str(paper["inputs"] / "run.json"), log="rogue.log")
    read_line(rogue, "ROGUE READY", timeout=30)
    agents = start_agents(procs, paper, endpoint, run_id, tmp_path / "reports")
    wait_exit(procs, plant, 90, "plant")
    sent = read_line(rogue, "ROGUE SENT ", timeout=20)
    for agent in agents:
        wait_exit(procs, agent, 20, "agent")
    agent_reports = reports(tmp_path / "reports")

    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == clean_steps(paper) and summary["fallbacks"] == 0 and not summary.get("failure")
    assert max_abs_diff(paper["sim"], out) <= 1e-9
    plant_drops = sum(summary["rejected"].values())
    agent_drops = {name: sum(r["rejected"].values()) for name, r in agent_reports.items()}
    assert sent["replayed"] > 0, sent  # plans exist only while the run steps: the flood overlapped it
    assert plant_drops > 0 and all(n > 0 for n in agent_drops.values()), (summary["rejected"], agent_drops)
    assert plant_drops + sum(agent_drops.values()) <= sent["total"] * 4  # control reaches four agents, a plan three
    # per sender: the agents, and everything else under one name
    assert set(summary["rejected"]) <= {"1", "2", "3", "4", "(unknown)"}
    assert sum(summary["rejected_reasons"].values()) == plant_drops
    for name, report in agent_reports.items():
        assert report["exit_code"] == 0 and report["solves"] == clean_solves(paper, name), (name, report)
        assert set(report["rejected"]) <= {"coordinator", "1", "2", "3", "4", "(unknown)"}
    # throttled logging: at most one line per sender per second of flooding (plus the first)
    lines = re.findall(r"plant: dropped a message from (\S+)", procs.log(plant))
    per_sender = {s: lines.count(s) for s in set(lines)}
    assert lines and max(per_sender.values()) <= sent["seconds"] + 2, (per_sender, sent["seconds"])
    duplicates = {"plant": summary["duplicates"], **{n: r["duplicates"] for n, r in agent_reports.items()}}
    assert sum(duplicates.values()) > 0, duplicates  # replayed plans: ignored, and counted
    print(f"\nflood: rogue sent {sent['total']} ({sent['replayed']} replayed plans) in {sent['seconds']:.1f} s; "
          f"plant dropped {plant_drops} {summary['rejected']}; agents dropped {agent_drops}; "
          f"duplicates ignored {duplicates}; plant log lines per sender {per_sender}")


# ------------------------------------------------------------------------ 4. dmpc run --secure
def test_secure_run_equals_plain_run_and_simulate(tmp_path, paper):
    """``dmpc run --secure`` (certificates, TLS and access control made in the run folder) gives
    the trajectory of ``dmpc run`` and of ``dmpc simulate``; no message was dropped."""
    plain, secure = tmp_path / "plain", tmp_path / "secure"
    res = run_cli("run", SCENARIO, "--out", str(plain), "--quiet")
    assert res.returncode == 0, res.stderr + res.stdout
    assert "starting" not in res.stderr and "security" not in res.stdout
    res = run_cli("run", SCENARIO, "--secure", "--out", str(secure))
    assert res.returncode == 0, res.stderr + res.stdout
    assert f"starting 5 processes: the plant and 4 agents (mesh, TLS); logs in {secure / 'logs'}" in res.stderr
    assert "TLS with mutual authentication, access control on" in res.stdout
    assert max_abs_diff(plain, secure) <= 1e-9
    assert max_abs_diff(paper["sim"], secure) <= 1e-9
    check_secure_records(secure, plain)


def test_secure_star_run_equals_simulate(tmp_path, paper):
    """The same through the plant's router (``--topology star``): the plant relays the agents'
    plans and tokens, and the access control lets exactly that through."""
    secure = tmp_path / "secure"
    res = run_cli("run", SCENARIO, "--secure", "--topology", "star", "--out", str(secure), "--quiet",
                  "--startup-timeout", "30")
    assert res.returncode == 0, res.stderr + res.stdout
    assert max_abs_diff(paper["sim"], secure) <= 1e-9
    check_secure_records(secure, paper["sim"])


def check_secure_records(secure: Path, plain: Path) -> None:
    """No drops, the agents' reports merged, the same summary keys as ``plain``, private keys
    readable by the owner only, and the access control bound to the run's id."""
    summary = json.loads((secure / "summary.json").read_text())
    assert summary["feasible"] and summary["fallbacks"] == 0 and summary["rejected"] == {}
    assert set(summary["agents"]) == {"1", "2", "3", "4"}
    assert all(a["rejected"] == {} and a["exit_code"] == 0 for a in summary["agents"].values())
    tls = secure / "tls"
    assert summary["security"] == {"tls": True, "mutual_authentication": True, "access_control": True,
                                   "certificates": str(tls)}
    launcher_only = {"launcher", "agent_reports_missing", "startup_s"}  # absent when ``plain`` ran in one process
    assert set(summary) - {"security"} - launcher_only == \
        set(json.loads((plain / "summary.json").read_text())) - launcher_only
    assert {p.name for p in tls.iterdir()} >= {"ca.pem", "plant.pem", "plant.key", "agent-4.pem", "acl.json"}
    assert all(stat.S_IMODE(p.stat().st_mode) == 0o600 for p in tls.glob("*.key"))
    assert stat.S_IMODE(tls.stat().st_mode) == 0o700
    assert ca_key_files(secure, tls / "ca.pem") == []  # nothing in the run folder can mint a role
    run_id = json.loads((secure / "logs" / "agent-1.json").read_text())["run_id"]
    acl = json.loads((tls / "acl.json").read_text())
    assert all(k.startswith(f"dmpc/{run_id}/") for rule in acl["rules"] for k in rule["key_exprs"])
    processes = json.loads((secure / "processes.json").read_text())
    assert not any(pid_alive(pid) for pid in processes.values())


# ========================================================================= script: probe, rogue
def _tls_config(connect: str, ca: Path | None, cert: Path | None, key: Path | None):
    """A client configuration for ``connect`` with exactly the TLS files given."""
    import zenoh

    config = zenoh.Config()
    for k, v in (("mode", "client"), ("scouting/multicast/enabled", False), ("connect/endpoints", [connect])):
        config.insert_json5(k, json.dumps(v))
    if ca is not None:
        config.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(ca)))
    if cert is not None:
        config.insert_json5("transport/link/tls/connect_certificate", json.dumps(str(cert)))
        config.insert_json5("transport/link/tls/connect_private_key", json.dumps(str(key)))
        config.insert_json5("transport/link/tls/enable_mtls", "true")
    return config


def _probe(argv: list[str]) -> int:
    from dmpc.bus import keys
    from dmpc.bus.session import BusError, open_session, session_config
    from dmpc.security.files import tls_files

    p = argparse.ArgumentParser(prog="probe")
    p.add_argument("--connect", required=True)
    p.add_argument("--run", required=True)
    p.add_argument("--tls", type=Path, required=True)
    p.add_argument("--other", type=Path, required=True)
    p.add_argument("--target", choices=["router", "plant"], required=True)
    args = p.parse_args(argv)
    host_port = args.connect.split("/", 1)[1]
    result: dict = {}

    # the valid client first (it also waits for the server to come up)
    seen: set[str] = set()
    watcher = open_session(session_config(mode="client", connect=[args.connect], tls=tls_files(args.tls, "agent-1")),
                           timeout=30)
    other = None
    try:
        watcher.liveliness().declare_subscriber(
            keys.alive_prefix(args.run), lambda s: seen.add(keys.last_chunk(str(s.key_expr))), history=True)
        if args.target == "router":  # a second valid client whose token the router must relay
            other = open_session(session_config(mode="client", connect=[args.connect],
                                                tls=tls_files(args.tls, "agent-2")), timeout=10)
            token = other.liveliness().declare_token(keys.alive(args.run, "agent-2"))  # noqa: F841 - kept alive
        want = "coordinator" if args.target == "plant" else "agent-2"
        deadline = time.monotonic() + 10
        while want not in seen and time.monotonic() < deadline:
            time.sleep(0.02)
        result["valid"] = {"opened": True, "seen": sorted(seen)}
        want_key = keys.alive(args.run, want)

        attempts = {
            # the same kind of configuration with the right files: the way the others are built
            # is not what stops them
            "valid_raw": _tls_config(args.connect, args.tls / "ca.pem", args.tls / "agent-1.pem",
                                     args.tls / "agent-1.key"),
            # trusts the CA, so only the server's demand for a client certificate stops it
            "no_cert": _tls_config(args.connect, args.tls / "ca.pem", None, None),
            # trusts the CA, presents agent-1 from another CA
            "other_ca": _tls_config(args.connect, args.tls / "ca.pem", args.other / "agent-1.pem",
                                    args.other / "agent-1.key"),
            "tcp": _tls_config(f"tcp/{host_port}", None, None, None),
        }

        def attempt(name, config):
            try:
                session = open_session(config, timeout=OPEN_TIMEOUT)
            except BusError as exc:
                result[name] = {"opened": False, "error": str(exc)[:300]}
                return
            got: set[str] = set()
            session.liveliness().declare_subscriber(keys.alive_prefix(args.run),
                                                    lambda s: got.add(str(s.key_expr)), history=True)
            until = time.monotonic() + 3.0
            while want_key not in got and time.monotonic() < until:
                time.sleep(0.02)
            result[name] = {"opened": True, "seen": sorted(keys.last_chunk(k) for k in got)}
            session.close()

        threads = [threading.Thread(target=attempt, args=item) for item in attempts.items()]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        if other is not None:
            other.close()
        watcher.close()
    print("PROBE " + json.dumps(result), flush=True)
    return 0


class _Garbage:
    """Hostile payloads for every key of a run: random bytes, broken msgpack, plausible but
    wrong messages (each with exactly one defect the receivers check for)."""

    def __init__(self, run: str, prepared, seed: int = 7) -> None:
        self.rng = np.random.default_rng(seed)
        self.run = run
        self.names = [s.name for s in prepared.system.subsystems]
        self.n = {s.name: s.n for s in prepared.system.subsystems}
        self.m = {s.name: s.m for s in prepared.system.subsystems}
        self.N = prepared.design.horizon
        self.groups = {self.names[i]: [self.names[j] for j in nb] for i, nb in enumerate(prepared.system.neighbours)}

    def pick(self, seq):
        return seq[int(self.rng.integers(len(seq)))]

    def plan(self, name: str, **change):
        from dmpc.bus.messages import PlanMessage

        fields = dict(run=self.run, k=int(self.rng.integers(0, 30)), round=0, sender=name, status="solved",
                      z=np.zeros((self.N + 1, self.n[name])), v=np.zeros((self.N, self.m[name])), cost=0.0,
                      solve_time=0.0, qp_iterations=1)
        fields.update(change)
        return PlanMessage(**fields)

    def release(self, **change):
        from dmpc.bus.messages import Release

        M, n = len(self.names), sum(self.n.values())
        fields = dict(run=self.run, k=int(self.rng.integers(0, 30)), round=0, x=np.zeros(n), centres=np.zeros(n),
                      sizes=np.ones(M), assumed=np.full((M, 2), -1, dtype=np.int64))
        fields.update(change)
        return Release(**fields)

    def payload(self, key_kind: str, name: str) -> bytes:
        import msgpack

        from dmpc.bus.codec import encode
        from dmpc.bus.messages import Ready, Stop

        kind = int(self.rng.integers(0, 4))
        if kind == 0:
            return self.rng.bytes(int(self.rng.integers(0, 300)))
        if kind == 1:
            return self.pick([msgpack.packb([1, 2, 3]), msgpack.packb(42), msgpack.packb({"schema": 1}),
                              msgpack.packb({"schema": 2, "type": "plan"}), msgpack.packb({"schema": 1, "type": "x"}),
                              msgpack.packb({"schema": 1, "type": "plan", "run": self.run, "k": "0"})])
        other = self.pick([n for n in self.names if n != name] or ["x"])
        if key_kind == "plan":
            msg = self.pick([
                lambda: self.plan(name, run="another-run"),
                lambda: self.plan(name, sender=other),                                     # not its key's agent
                lambda: self.plan(name, z=np.zeros((self.N, self.n[name]))),               # wrong shape
                lambda: self.plan(name, z=np.full((self.N + 1, self.n[name]), 1e15)),      # out of range
                lambda: self.plan(name, z=np.full((self.N + 1, self.n[name]), np.nan)),    # NaN in a solved plan
                lambda: self.plan(name, k=10**9),                                           # far future
            ])()
        elif key_kind == "release":
            M, n = len(self.names), sum(self.n.values())
            msg = self.pick([
                lambda: self.release(run="another-run"),
                lambda: self.release(sender=other),
                lambda: self.release(x=np.zeros(n + 1), centres=np.zeros(n + 1)),
                lambda: self.release(sizes=np.ones(M + 1), assumed=np.zeros((M + 1, 2), dtype=np.int64)),
                lambda: self.release(k=3, round=0, assumed=np.full((M, 2), 3, dtype=np.int64)),
                lambda: self.release(provided={"nobody": (np.zeros((self.N + 1, 2)), np.zeros((self.N, 1)))}),
            ])()
        elif key_kind == "ready":
            msg = self.pick([Ready(run="another-run", sender=name, design_digest="0" * 16),
                             Ready(run=self.run, sender=other, design_digest="0" * 16),
                             Ready(run=self.run, sender=name, design_digest="deadbeefdeadbeef")])
        else:
            msg = self.pick([Stop(run="another-run", k=0, reason="finished"),
                             Stop(run=self.run, k=0, reason="finished", sender="rogue")])
        data = encode(msg)
        if kind == 2:
            return data[:int(self.rng.integers(1, len(data)))]  # truncated
        return data


def _rogue(argv: list[str]) -> int:
    import zenoh

    from dmpc.bus import keys
    from dmpc.bus.codec import DecodeError, decode, encode
    from dmpc.bus.messages import Release, Stop
    from dmpc.bus.session import open_session, session_config
    from dmpc.prepared.bundle import load_bundle
    from dmpc.security.files import tls_files

    p = argparse.ArgumentParser(prog="rogue")
    p.add_argument("attack", choices=["flood", "spoof"])
    p.add_argument("--connect", required=True)
    p.add_argument("--run", required=True)
    p.add_argument("--bundle", type=Path, required=True)
    p.add_argument("--tls", type=Path)
    p.add_argument("--role", default="agent-1")
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--mode", choices=["peer", "client"], default="peer")
    args = p.parse_args(argv)
    prepared = load_bundle(args.bundle)
    garbage = _Garbage(args.run, prepared)
    R = args.run
    tls = tls_files(args.tls, args.role) if args.tls else None
    session = open_session(session_config(mode=args.mode, connect=[args.connect], tls=tls), timeout=20)
    alive: set[str] = set()
    gone = threading.Event()
    lock = threading.Lock()
    releases: list = []
    replays: list[tuple[str, bytes]] = []
    replayed: set[int] = set()

    def on_alive(sample):
        role = keys.last_chunk(str(sample.key_expr))
        if sample.kind == zenoh.SampleKind.PUT:
            alive.add(role)
        elif role == keys.COORDINATOR_ROLE:
            gone.set()

    def on_plan(sample):  # replay every plan of the run once (the rogue's own puts are not seen here)
        data = sample.payload.to_bytes()
        h = hash(data)
        with lock:
            if h not in replayed:
                replayed.add(h)
                replays.append((str(sample.key_expr), data))

    def on_release(sample):
        try:
            msg = decode(sample.payload.to_bytes())
        except DecodeError:
            return
        with lock:
            releases.append(msg)

    entities = [session.liveliness().declare_subscriber(keys.alive_prefix(R), on_alive, history=True)]
    if args.attack == "flood":
        entities.append(session.declare_subscriber(keys.plan(R, "*"), on_plan, allowed_origin=zenoh.Locality.REMOTE))
    else:
        entities.append(session.declare_subscriber(keys.release(R), on_release))
    deadline = time.monotonic() + 20
    while keys.COORDINATOR_ROLE not in alive and time.monotonic() < deadline:
        time.sleep(0.01)
    print("ROGUE READY", flush=True)

    sent = {"total": 0, "forged": 0, "replayed": 0, "releases_seen": 0}
    names = garbage.names
    flood_keys = ([("plan", n) for n in names + ["evil", "99"]] + [("release", n) for n in names]
                  + [("ready", n) for n in names + ["nobody"]] + [("control", "")])

    def put(key: str, payload: bytes, what: str = "total") -> None:
        session.put(key, payload)
        sent["total"] += 1
        if what != "total":
            sent[what] += 1

    t0 = time.monotonic()
    end = t0 + args.seconds
    while not gone.is_set() and time.monotonic() < end:
        if args.attack == "flood":
            kind, name = garbage.pick(flood_keys)
            key = (keys.control(R) if kind == "control" else keys.release(R) if kind == "release"
                   else f"{keys.ROOT}/{R}/{kind}/{name}")
            payload_name = name if name in names else garbage.pick(names)
            put(key, garbage.payload(kind, payload_name))
            with lock:
                pending, replays[:] = list(replays), []
            for key, data in pending:
                put(key, data, "replayed")
            time.sleep(0.0005)
        else:
            with lock:
                pending, releases[:] = list(releases), []
            for rel in pending:  # well-formed messages for the round just released, on others' keys
                sent["releases_seen"] += 1
                if not isinstance(rel, Release):
                    continue
                put(keys.plan(R, "3"), encode(garbage.plan("3", k=rel.k, round=rel.round,
                                                             v=np.full((garbage.N, garbage.m["3"]), 2.0))), "forged")
                put(keys.release(R), encode(garbage.release(k=rel.k, round=rel.round + 1)), "forged")
                put(keys.control(R), encode(Stop(run=R, k=rel.k, reason="finished")), "forged")
            for key in (keys.plan(R, "3"), keys.release(R), keys.ready(R, "3"), keys.control(R), keys.plan(R, "1")):
                put(key, garbage.rng.bytes(int(garbage.rng.integers(1, 100))))
            time.sleep(0.002)
    sent["seconds"] = time.monotonic() - t0
    for entity in entities:
        entity.undeclare()
    session.close()
    print("ROGUE SENT " + json.dumps(sent), flush=True)
    return 0


def main(argv: list[str]) -> int:
    if argv and argv[0] == "probe":
        return _probe(argv[1:])
    if argv and argv[0] == "rogue":
        return _rogue(argv[1:])
    print("usage: python -m tests.test_e2e_security probe|rogue ...", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

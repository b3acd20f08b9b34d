"""End to end across separate network hosts made with Linux network namespaces.

Each role runs in its own network namespace with its own address, as if on its own machine::

    ns router  198.18.N.1  dmpc router --listen tcp/198.18.N.1:7447
    ns plant   198.18.N.2  dmpc plant  ...
    ns agent1  198.18.N.11 dmpc agent --id 1 ...        (and agent2..agent4 at .12-.14)
         \\ each namespace's eth0 is one end of a veth pair /
    ns switch  br0: a bridge holding the other ends (no address, no other port)

The switch is a namespace of its own, so nothing is added to this machine's own network
namespace, and the namespaces have no default route, no NAT and no link to a physical
interface: no packet can leave the machine. 198.18.0.0/15 is the range reserved for network
benchmarks (RFC 2544); the namespaces' names carry this process's id, so concurrent test runs
do not collide. Everything made is removed at the end, also on failure.

Three deployments are run, each compared with ``dmpc simulate`` to 1e-9:

- ``clients``: plant and agents are clients of the router; every message goes through it;
- ``peers``: plant and agents are peers that connect to the router to find each other. They
  listen on their own default endpoint (every interface, a free port) and link to each other
  directly across the namespaces;
- ``plant-hub``: no router; the plant listens on a known port, the agents connect to it and,
  as peers, to each other.

Skipped, with the reason, only where namespaces cannot be made (not root, no ``ip``, or the
kernel refuses); under ``CI=true`` that is a failure instead (.ci/run installs iproute2).
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.e2e_helpers import ROOT, Processes, in_ci, max_abs_diff, step_lines, wait_for

pytestmark = pytest.mark.e2e

ROUTER_PORT = 7447
AGENTS = ("1", "2", "3", "4")


class NetnsError(RuntimeError):
    """An ``ip`` command failed while building the namespaces."""


def _ip(*args: str) -> str:
    res = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)
    if res.returncode != 0:
        raise NetnsError(f"'ip {' '.join(args)}' failed: {res.stderr.strip() or res.returncode}")
    return res.stdout


class Lab:
    """Network namespaces joined by one bridge; remembers what it made so it can remove it.

    Parameters
    ----------
    tag : str
        Prefix of every namespace's name (include the process id).
    subnet : str
        The first three octets of a private /24, e.g. ``198.18.7``.
    """

    def __init__(self, tag: str, subnet: str) -> None:
        self.tag = tag
        self.subnet = subnet
        self.namespaces: list[str] = []
        self.hosts: dict[str, str] = {}  # role -> address
        self.switch = self.ns("switch")
        try:
            self._add_namespace("switch")
            _ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
            _ip("-n", self.switch, "link", "set", "br0", "up")
        except BaseException:
            self.remove()
            raise

    def ns(self, role: str) -> str:
        return f"{self.tag}-{role}"

    def _add_namespace(self, role: str) -> str:
        name = self.ns(role)
        _ip("netns", "add", name)
        self.namespaces.append(name)
        _ip("-n", name, "link", "set", "lo", "up")
        return name

    def add_host(self, role: str, host: int) -> str:
        """A namespace for ``role`` with address ``<subnet>.<host>`` on the bridge; returns the address."""
        name = self._add_namespace(role)
        port = f"v{role}"[:15]  # the bridge's end, named in the switch namespace only
        _ip("-n", name, "link", "add", "eth0", "type", "veth", "peer", "name", port, "netns", self.switch)
        _ip("-n", self.switch, "link", "set", port, "master", "br0")
        _ip("-n", self.switch, "link", "set", port, "up")
        address = f"{self.subnet}.{host}"
        _ip("-n", name, "addr", "add", f"{address}/24", "dev", "eth0")
        _ip("-n", name, "link", "set", "eth0", "up")
        self.hosts[role] = address
        return address

    def exec_prefix(self, role: str) -> list[str]:
        return ["ip", "netns", "exec", self.ns(role)]

    def remove(self) -> list[str]:
        """Delete every namespace made (their veth ends and the bridge go with them); returns failures."""
        failures = []
        for name in reversed(self.namespaces):
            res = subprocess.run(["ip", "netns", "del", name], capture_output=True, text=True, timeout=20)
            if res.returncode != 0:
                failures.append(f"{name}: {res.stderr.strip()}")
        self.namespaces.clear()
        return failures


def cannot_run(reason: str) -> None:
    """Skip with ``reason``; fail under ``CI=true``, where the test must run."""
    if in_ci():
        pytest.fail(f"CI must run the multi-host test: {reason}")
    pytest.skip(reason)


@pytest.fixture(scope="module")
def lab():
    if not sys.platform.startswith("linux"):
        cannot_run("network namespaces need Linux")
    if os.geteuid() != 0:
        cannot_run("creating network namespaces (ip netns) needs root")
    if shutil.which("ip") is None:
        cannot_run("the 'ip' command is not installed (Debian: apt-get install iproute2)")
    pid = os.getpid()
    made = None
    try:
        made = Lab(f"dmpct{pid}", f"198.18.{pid % 250 + 1}")
        made.add_host("router", 1)
        made.add_host("plant", 2)
        for i, name in enumerate(AGENTS):
            made.add_host(f"agent{name}", 11 + i)
    except NetnsError as exc:
        if made is not None:
            made.remove()
        cannot_run(f"network namespaces cannot be made here: {exc}")
    except BaseException:
        if made is not None:
            made.remove()
        raise
    try:
        yield made
    finally:
        failures = made.remove()
        assert not failures, f"namespaces left behind: {failures}"


class NsProcesses(Processes):
    """Processes.start, but inside a role's namespace (``ip netns exec NS python -m dmpc.cli ...``)."""

    def __init__(self, tmp: Path, lab: Lab) -> None:
        super().__init__(tmp)
        self.lab = lab

    def start_in(self, role: str, *args: str) -> subprocess.Popen:
        log = self.tmp / f"{role}.log"
        with open(log, "wb") as out:
            proc = subprocess.Popen(self.lab.exec_prefix(role) + [sys.executable, "-m", "dmpc.cli", *args], cwd=ROOT,
                                    stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
                                    start_new_session=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
        proc.log_path = log
        self.procs.append(proc)
        return proc


@pytest.fixture
def procs(tmp_path, lab):
    p = NsProcesses(tmp_path, lab)
    yield p
    p.cleanup()


def test_namespaces_are_isolated(lab):
    """Each host sees only the lab's subnet (no default route) and the bridge holds only the lab's ports."""
    for role in lab.hosts:
        routes = [r.strip() for r in _ip("-n", lab.ns(role), "-4", "route", "show").splitlines()]
        assert routes == [f"{lab.subnet}.0/24 dev eth0 proto kernel scope link src {lab.hosts[role]}"], routes
        assert "default" not in _ip("-n", lab.ns(role), "-6", "route", "show")
    ports = {line.split(":")[1].strip().split("@")[0] for line in
             _ip("-n", lab.switch, "-o", "link", "show", "master", "br0").splitlines()}
    assert ports == {f"v{role}" for role in lab.hosts}
    links = {line.split(":")[1].strip().split("@")[0] for line in _ip("-n", lab.switch, "-o", "link").splitlines()}
    assert links == ports | {"lo", "br0"}


def _established_peers(pid: int) -> set[str]:
    """Remote IPv4 addresses of the established TCP connections in ``pid``'s network namespace."""
    try:
        lines = Path(f"/proc/{pid}/net/tcp").read_text().splitlines()[1:]
    except OSError:
        return set()
    peers = set()
    for line in lines:
        fields = line.split()
        if fields[3] == "01":  # ESTABLISHED
            addr = fields[2].split(":")[0]
            peers.add(".".join(str(int(addr[i:i + 2], 16)) for i in (6, 4, 2, 0)))  # little-endian hex
    return peers


def test_nothing_routes_off_the_lab(lab):
    """An address outside the subnet is unreachable from inside: the kernel refuses before sending."""
    probe = ("import errno, socket\n"
             "s = socket.socket()\n"
             "code = s.connect_ex(('192.0.2.1', 9))\n"  # TEST-NET-1 (RFC 5737)
             "print(errno.errorcode.get(code, code))")
    res = subprocess.run(lab.exec_prefix("plant") + [sys.executable, "-c", probe], capture_output=True, text=True,
                         timeout=30)
    assert res.stdout.strip() == "ENETUNREACH", res.stdout + res.stderr


DEPLOYMENTS = {
    # name: (router?, plant's network options, agents' network options); ROUTER and PLANT stand
    # for the router's and the plant's endpoint
    "clients": (True, ["--mode", "client", "--connect", "ROUTER"], ["--mode", "client", "--connect", "ROUTER"]),
    "peers": (True, ["--connect", "ROUTER"], ["--connect", "ROUTER"]),
    "plant-hub": (False, ["--listen", "tcp/0.0.0.0:7447"], ["--connect", "PLANT"]),
}


@pytest.mark.parametrize("deployment", list(DEPLOYMENTS))
def test_paper_across_namespaces_equals_simulate(procs, lab, paper_simulated, tmp_path, deployment):
    """The paper's example with every role on its own host; as docs/deploy.md describes it."""
    with_router, plant_net, agent_net = DEPLOYMENTS[deployment]
    router = f"tcp/{lab.hosts['router']}:{ROUTER_PORT}"
    endpoints = {"ROUTER": router, "PLANT": f"tcp/{lab.hosts['plant']}:7447"}
    plant_net = [endpoints.get(a, a) for a in plant_net]
    agent_net = [endpoints.get(a, a) for a in agent_net]
    out = tmp_path / "out"
    common = ["--run-id", f"netns-{deployment}", "--design", str(paper_simulated / "design.json"),
              "--startup-timeout", "60"]

    t0 = time.monotonic()
    if with_router:
        router_proc = procs.start_in("router", "router", "--listen", router)
        assert wait_for(lambda: "router listening" in procs.log(router_proc) or router_proc.poll() is not None,
                        timeout=30), procs.log(router_proc)
        assert router_proc.poll() is None, procs.log(router_proc)
    plant = procs.start_in("plant", "plant", "scenarios/paper.yaml", "--out", str(out), "--quiet",
                           *plant_net, *common)
    # --delay: every message an agent sends waits 50 ms, so the 30 lockstep steps take at least 3 s
    # (the trajectory is the same: lockstep waits for every plan), long enough for the sampling below
    # to see each agent's links on a machine so busy that this process waits a second for the CPU
    agents = [procs.start_in(f"agent{name}", "agent", "scenarios/paper.yaml", "--id", name, "--delay", "50",
                             *agent_net, *common)
              for name in AGENTS]
    # whom does each agent's host hold TCP connections with while the run starts and steps? Sampled
    # from the agents' start to the end: Zenoh may replace a link (two peers dialling each other),
    # so one snapshot can miss it, and a short run can end before a sampling that waits for it.
    linked: dict[str, set[str]] = {name: set() for name in AGENTS}

    def sample() -> None:
        for name, a in zip(AGENTS, agents):
            linked[name] |= _established_peers(a.pid)

    def stepping() -> bool:
        sample()
        return step_lines(out) >= 1 or plant.poll() is not None

    assert wait_for(stepping, timeout=90), procs.log(plant)
    deadline = time.monotonic() + 120
    while plant.poll() is None and time.monotonic() < deadline:
        sample()
        time.sleep(0.05)
    plant.wait(timeout=10)
    for a in agents:
        a.wait(timeout=20)
    elapsed = time.monotonic() - t0
    assert plant.returncode == 0, procs.log(plant)
    assert all(a.returncode == 0 for a in agents), [procs.log(a) for a in agents]
    assert max_abs_diff(paper_simulated, out) <= 1e-9

    others = {lab.hosts[role] for role in lab.hosts if role not in ("router",)}
    for name, peers in linked.items():
        assert peers, f"agent {name}: no connection seen"
        if deployment == "clients":
            assert peers == {lab.hosts["router"]}, (name, peers)
        else:  # peers: direct links to the plant's and the neighbours' hosts
            assert lab.hosts["plant"] in peers, (name, peers)
            assert peers & (others - {lab.hosts[f"agent{name}"], lab.hosts["plant"]}), (name, peers)
    print(f"{deployment}: paper example across {len(lab.hosts)} namespaces in {elapsed:.1f} s; agents linked to "
          + "; ".join(f"{name}: {sorted(peers)}" for name, peers in linked.items()))


def test_two_machines_each_hosting_two_agents_equal_simulate(procs, lab, paper_simulated, tmp_path):
    """Agents 1 and 2 served by one process on one host, 3 and 4 by one on another, the plant on a
    third (the plant as the meeting point, as docs/deploy.md describes a host per machine)."""
    plant_ep = f"tcp/{lab.hosts['plant']}:7447"
    out = tmp_path / "out"
    common = ["--run-id", "netns-hosts", "--design", str(paper_simulated / "design.json"), "--startup-timeout", "60"]
    plant = procs.start_in("plant", "plant", "scenarios/paper.yaml", "--out", str(out), "--quiet",
                           "--listen", "tcp/0.0.0.0:7447", *common)
    machines = {"agent1": ("1", "2"), "agent2": ("3", "4")}
    # --delay 50: the 30 steps take at least 3 s (the same trajectory), for the sampling of the links below
    hosts = {role: procs.start_in(role, "agent", "scenarios/paper.yaml", *[a for n in names for a in ("--id", n)],
                                  "--connect", plant_ep, "--report", str(tmp_path / f"{role}-{{id}}.json"),
                                  "--delay", "50", *common)
             for role, names in machines.items()}
    linked: dict[str, set[str]] = {role: set() for role in machines}

    def stepping() -> bool:
        for role, proc in hosts.items():
            linked[role] |= _established_peers(proc.pid)
        return step_lines(out) >= 1 or plant.poll() is not None

    assert wait_for(stepping, timeout=90), procs.log(plant)
    deadline = time.monotonic() + 120
    while plant.poll() is None and time.monotonic() < deadline:
        for role, proc in hosts.items():
            linked[role] |= _established_peers(proc.pid)
        time.sleep(0.05)
    plant.wait(timeout=10)
    for proc in hosts.values():
        proc.wait(timeout=20)
    assert plant.returncode == 0, procs.log(plant)
    assert all(p.returncode == 0 for p in hosts.values()), [procs.log(p) for p in hosts.values()]
    assert max_abs_diff(paper_simulated, out) <= 1e-9
    for role, names in machines.items():  # one process, one report per agent, each finished
        for name in names:
            assert f"agent {name}: finished" in procs.log(hosts[role])
            assert (tmp_path / f"{role}-{name}.json").is_file()
    # one session per machine: links to the plant's host and to the other machine, nothing else
    assert linked["agent1"] == {lab.hosts["plant"], lab.hosts["agent2"]}, linked
    assert linked["agent2"] == {lab.hosts["plant"], lab.hosts["agent1"]}, linked

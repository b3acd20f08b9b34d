"""The bus's own floor: a bare lockstep loop over Zenoh, for comparison with ``dmpc run``.

One coordinator process and M agent processes, linked as a run of the same size is (``mesh``:
peers linked directly; ``star``: the coordinator's session is the router and the agents its
clients), with the same session settings (:func:`dmpc.bus.session.session_config`). Per step
the coordinator publishes one release on one key; each agent, once it holds the release and its
neighbours' plans of the step before, burns ``compute_us`` of CPU (a stand-in for its QP) and
publishes its plan on its own key, which reaches the coordinator and its neighbours. Payloads
have the sizes of the run's own release and plan messages. Every process reads its
subscriptions' FIFO channels on its main thread; nothing is decoded, checked or recorded.

The step time is measured as the run's is: on the coordinator's clock, from the start of the
release to the last plan of the step.
"""
from __future__ import annotations

import json
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from dmpc.bus.session import free_tcp_port, open_session, session_config

KEY = "dmpc-floor"
_HEADER = struct.Struct("<q")
STOP = -1
HELLO = -2
START_TIMEOUT = 120.0


@dataclass(frozen=True)
class FloorSpec:
    """What the floor loop mirrors of a run.

    Attributes
    ----------
    M : int
        Agents.
    steps : int
        Steps measured after ``warmup`` unmeasured ones.
    neighbours : list of list of int
        Per agent, the other agents whose plans it waits for (N_i without i).
    release_bytes, plan_bytes : int
        Payload sizes.
    compute_us : float
        CPU burnt by each agent per step.
    topology : {"mesh", "star"}
    warmup : int
    """

    M: int
    steps: int
    neighbours: list[list[int]]
    release_bytes: int
    plan_bytes: int
    compute_us: float
    topology: str = "mesh"
    warmup: int = 20


def _payload(k: int, size: int) -> bytes:
    return _HEADER.pack(k) + bytes(max(0, size - _HEADER.size))


def _step_of(sample) -> int:
    return _HEADER.unpack_from(sample.payload.to_bytes())[0]


def _open(spec: FloorSpec, port: int, coordinator: bool):
    endpoint = f"tcp/127.0.0.1:{port}"
    if coordinator:
        config = session_config(mode="router" if spec.topology == "star" else "peer", listen=[endpoint])
    elif spec.topology == "star":
        config = session_config(mode="client", connect=[endpoint])
    else:
        config = session_config(mode="peer", connect=[endpoint], listen=["tcp/127.0.0.1:0"])
    return open_session(config, 30.0)


def _publisher(session, key: str):
    import zenoh

    return session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK,
                                     reliability=zenoh.Reliability.RELIABLE, priority=zenoh.Priority.REAL_TIME,
                                     express=True)


def _fifo(session, key: str):
    import zenoh

    return session.declare_subscriber(key, zenoh.handlers.FifoChannel(1024))


def _alive(session, needed: set[str], deadline: float) -> None:
    """Wait until every liveliness token in ``needed`` is seen (declared after its subscribers)."""
    while True:
        seen = {str(reply.ok.key_expr).rsplit("/", 1)[-1] for reply in session.liveliness().get(f"{KEY}/alive/*")
                if reply.ok is not None}
        if needed <= seen:
            return
        if time.monotonic() > deadline:
            raise TimeoutError(f"floor: not alive: {sorted(needed - seen)}")
        time.sleep(0.02)


def run_coordinator(spec: FloorSpec, port: int, out: Path) -> None:
    """The coordinator's side of the floor ``spec``: listen on ``port``, release every step once every
    agent's plan is in, and write the step times to ``out``."""
    session = _open(spec, port, True)
    try:
        plans = _fifo(session, f"{KEY}/plan/*")
        release = _publisher(session, f"{KEY}/release")
        token = session.liveliness().declare_token(f"{KEY}/alive/plant")
        deadline = time.monotonic() + START_TIMEOUT
        hello: set[int] = set()
        while len(hello) < spec.M:
            sample = plans.try_recv()
            if sample is None:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"floor: {spec.M - len(hello)} agents never said hello")
                time.sleep(0.001)
                continue
            if _step_of(sample) == HELLO:
                hello.add(int(str(sample.key_expr).rsplit("/", 1)[-1]))
        times = np.empty(spec.warmup + spec.steps)
        for k in range(times.size):
            t0 = time.perf_counter()
            release.put(_payload(k, spec.release_bytes))
            got = 0
            while got < spec.M:
                if _step_of(plans.recv()) == k:
                    got += 1
            times[k] = time.perf_counter() - t0
        release.put(_payload(STOP, spec.release_bytes))
        out.write_text(json.dumps(times[spec.warmup:].tolist()))
        time.sleep(0.2)
        token.undeclare()
    finally:
        session.close()


def _burn(us: float) -> None:
    end = time.perf_counter() + us * 1e-6
    while time.perf_counter() < end:
        pass


def run_agent(spec: FloorSpec, i: int, port: int) -> None:
    """Agent i's side of the floor ``spec``, connected to the coordinator on ``port``: answer each
    release with a plan once its neighbours' plans are in, after ``compute_us`` of work."""
    session = _open(spec, port, False)
    try:
        release = _fifo(session, f"{KEY}/release")
        neighbours = [(j, _fifo(session, f"{KEY}/plan/{j}")) for j in spec.neighbours[i]]
        plan = _publisher(session, f"{KEY}/plan/{i}")
        token = session.liveliness().declare_token(f"{KEY}/alive/{i}")
        _alive(session, {"plant"} | {str(j) for j in spec.neighbours[i]}, time.monotonic() + START_TIMEOUT)
        plan.put(_payload(HELLO, spec.plan_bytes))
        while True:
            k = _step_of(release.recv())
            if k == STOP:
                break
            if k > 0:
                for _, sub in neighbours:
                    while _step_of(sub.recv()) != k - 1:
                        pass
            _burn(spec.compute_us)
            plan.put(_payload(k, spec.plan_bytes))
        token.undeclare()
    finally:
        session.close()


def measure(spec: FloorSpec, timeout: float = 600.0,
            while_running: Callable[[list[subprocess.Popen]], None] | None = None) -> dict:
    """Run the floor loop as M + 1 processes; its step times' median, p99 and mean in ms.

    ``while_running`` is called with the processes (the coordinator first) once all are started,
    to observe them while they step (benchmarks/step_profile.py reads their CPU time).

    Returns
    -------
    dict
        ``step_ms_p50``, ``step_ms_p99``, ``step_ms_mean``, ``steps``, and the spec's figures;
        ``completed`` False with a ``reason`` if a process failed or the loop did not end within
        ``timeout`` s.
    """
    port = free_tcp_port()
    with tempfile.TemporaryDirectory(prefix="dmpc-floor-") as tmp:
        spec_path, out = Path(tmp) / "spec.json", Path(tmp) / "times.json"
        spec_path.write_text(json.dumps(asdict(spec)))
        base = [sys.executable, "-m", "dmpc.bench.floor", str(spec_path), str(port)]
        procs = [subprocess.Popen(base + ["coordinator", str(out)], stderr=subprocess.PIPE)]
        time.sleep(0.3)  # the coordinator listens before the agents connect
        procs += [subprocess.Popen(base + ["agent", str(i)], stderr=subprocess.PIPE) for i in range(spec.M)]
        end = time.monotonic() + timeout
        failure = ""
        try:
            if while_running is not None:
                while_running(procs)
            for proc in procs:
                code = proc.wait(max(1.0, end - time.monotonic()))
                if code != 0 and not failure and proc.stderr is not None:
                    failure = proc.stderr.read().decode(errors="replace")[-400:]
        except subprocess.TimeoutExpired:
            failure = f"timeout after {timeout:.0f} s"
        finally:
            for proc in procs:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
        info = {"M": spec.M, "topology": spec.topology, "compute_us": spec.compute_us,
                "release_bytes": spec.release_bytes, "plan_bytes": spec.plan_bytes}
        if failure or not out.exists():
            return {**info, "completed": False, "reason": failure or "no times written"}
        t = np.array(json.loads(out.read_text())) * 1e3
    return {**info, "completed": True, "steps": int(t.size), "step_ms_p50": float(np.median(t)),
            "step_ms_p99": float(np.percentile(t, 99)), "step_ms_mean": float(t.mean())}


def main(argv: list[str]) -> None:
    """A process of the floor from its command line ``argv``: the spec file, the port, the role
    (``coordinator`` OUT or ``agent`` I)."""
    spec = FloorSpec(**json.loads(Path(argv[0]).read_text()))
    port, role = int(argv[1]), argv[2]
    if role == "coordinator":
        run_coordinator(spec, port, Path(argv[3]))
    else:
        run_agent(spec, int(argv[3]), port)


if __name__ == "__main__":
    main(sys.argv[1:])

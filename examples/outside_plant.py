"""A plant that is not dmpc: the paper's example simulated here, speaking docs/protocol.md over Zenoh.

    python examples/outside_plant.py --connect tcp/127.0.0.1:7447 --run-id RUN
    python examples/outside_plant.py --connect tcp/127.0.0.1:7447 --run-id RUN --sensor 1 --sensor 2
    python examples/outside_plant.py --connect tls/127.0.0.1:7447 --run-id RUN --tls DIR

It needs only zenoh, msgpack and numpy, and follows "The plant's side" of docs/protocol.md:
x(0) is sent every 0.5 s until the inputs of step 0 arrive; the inputs of the awaited step are
applied once and answered with x(k+1); a repeat of the inputs just applied gets the same x(k+1)
again; inputs of any other step are ignored. Without ``--sensor`` it reports the whole state as
``plant``; with ``--sensor NAME`` (repeatable) it reports only those subsystems, each as
``sensor-NAME``, as one sensor process per subsystem would (it still simulates the whole plant,
deterministically, so several such processes agree).

It may be started before the coordinator listens: opening the Zenoh session keeps trying
(``connect/timeout_ms``, ``connect/retry``) for up to ``--startup-timeout`` seconds, the time it
also waits for the coordinator's liveliness token. It subscribes to the exact keys ``inputs`` and
``control`` (under TLS the access control refuses wider ones without a word).

It exits 0 when the coordinator stops the run with "finished"; 1 when it stops it otherwise
("failed: ..." or "aborted"), when the coordinator's liveliness token is gone for 1.5 s, or when
no coordinator is reached or seen within ``--startup-timeout``; 130 on Ctrl-C; 2 on bad
arguments. Its last line says why.
"""
from __future__ import annotations

import argparse
import math
import queue
import re
import sys
import time
from pathlib import Path

import msgpack
import numpy as np
import zenoh

PROTOCOL_VERSION = 3
REPEAT = 0.5  # seconds between copies of x(0) until the inputs of step 0 arrive
GRACE = 1.5  # seconds the coordinator's token may be gone before this plant gives up
COORDINATOR = "coordinator"

# The paper's example, copied by hand from scenarios/paper.yaml: four subsystems "1".."4" on the
# chain 1-2-3-4, x_i(k+1) = A_ii x_i + B_ii u_i + sum over neighbours j of (A_ij x_j + B_ij u_j).
NAMES = ("1", "2", "3", "4")
A_II = np.array([[1.1, 1.0], [0.0, 1.3]])
B_II = np.array([[1.0], [1.0]])
A_IJ = np.array([[0.0, 0.1], [0.2, 0.2]])
B_IJ = np.array([[0.0], [0.0]])
COUPLINGS = (("1", "2"), ("2", "1"), ("2", "3"), ("3", "2"), ("3", "4"), ("4", "3"))  # (target, source)
X0 = {"1": [2.794, 2.5], "2": [2.08, 2.2], "3": [2.194, -2.305], "4": [-2.8, 2.5]}
N_I, M_I = 2, 1  # every subsystem: 2 states, 1 input


def paper_model() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The global A (8, 8), B (8, 4) and x0 (8,), subsystems stacked in the order of NAMES."""
    M = len(NAMES)
    A, B = np.zeros((N_I * M, N_I * M)), np.zeros((N_I * M, M_I * M))
    at = {name: i for i, name in enumerate(NAMES)}
    for i in at.values():
        A[N_I * i:N_I * (i + 1), N_I * i:N_I * (i + 1)] = A_II
        B[N_I * i:N_I * (i + 1), M_I * i:M_I * (i + 1)] = B_II
    for target, source in COUPLINGS:
        t, s = at[target], at[source]
        A[N_I * t:N_I * (t + 1), N_I * s:N_I * (s + 1)] += A_IJ
        B[N_I * t:N_I * (t + 1), M_I * s:M_I * (s + 1)] += B_IJ
    x0 = np.concatenate([np.array(X0[name], dtype=float) for name in NAMES])
    return A, B, x0


# ---------------------------------------------------------------------------------- wire format
class Dropped(Exception):
    """A message this plant does not use; the text says why."""


def wire_array(values: np.ndarray) -> dict:
    """A float vector as the protocol's array map: little-endian float64 bytes, C order."""
    arr = np.ascontiguousarray(values, dtype="<f8")
    return {"dtype": "<f8", "shape": list(arr.shape), "data": arr.tobytes()}


def state_message(run: str, k: int, sender: str, parts: dict[str, np.ndarray]) -> bytes:
    """A ``state`` message: x(k) of the subsystems in ``parts`` (name -> shape (2,))."""
    body = {"protocol": PROTOCOL_VERSION, "type": "state", "run": run, "k": k, "sender": sender,
            "x": {name: wire_array(x) for name, x in parts.items()}}
    return msgpack.packb(body, use_bin_type=True)


def read_message(payload: bytes, run: str, kind: str) -> dict:
    """The msgpack map in ``payload`` if it is a ``kind`` message of run ``run`` from the coordinator."""
    try:
        body = msgpack.unpackb(payload, raw=False)
    except Exception as exc:  # noqa: BLE001 - msgpack raises several unrelated types on garbage
        raise Dropped(f"not msgpack ({type(exc).__name__})") from None
    if not isinstance(body, dict):
        raise Dropped("not a map")
    version = body.get("protocol", body.get("schema"))  # versions 1 and 2 called the field "schema"
    if version != PROTOCOL_VERSION:
        shown = "no protocol version" if version is None else f"protocol version {version!r:.20}"
        raise Dropped(f"{shown}; this process speaks protocol version {PROTOCOL_VERSION}")
    if body.get("type") != kind or body.get("run") != run or body.get("sender") != COORDINATOR:
        raise Dropped(f"not a {kind} message of run {run!r} from the coordinator")
    k = body.get("k")
    if type(k) is not int or k < 0:
        raise Dropped("k: expected a non-negative integer")
    return body


def read_inputs(body: dict) -> np.ndarray:
    """u(k), shape (4,), from an ``inputs`` message: one finite (1,) vector per subsystem, in order."""
    u = body.get("u")
    if not isinstance(u, dict) or list(u) != list(NAMES):
        raise Dropped(f"u: expected one entry per subsystem, in the order {', '.join(NAMES)}")
    parts = []
    for name, arr in u.items():
        if not isinstance(arr, dict) or arr.get("dtype") != "<f8" or arr.get("shape") != [M_I] \
                or not isinstance(arr.get("data"), bytes) or len(arr["data"]) != 8 * M_I:
            raise Dropped(f"u[{name}]: expected a <f8 array of shape [{M_I}]")
        values = np.frombuffer(arr["data"], dtype="<f8")
        if not np.isfinite(values).all():
            raise Dropped(f"u[{name}]: non-finite values")
        parts.append(values)
    return np.concatenate(parts)


# ----------------------------------------------------------------------------------- the plant
class OutsidePlant:
    """The simulated plant and the protocol rules of its side, without any transport.

    Parameters
    ----------
    run : str
    sensors : list of str or None
        Report only these subsystems, each as ``sensor-<name>``; None reports everything as ``plant``.
    """

    def __init__(self, run: str, sensors: list[str] | None = None) -> None:
        self.run = run
        self.sensors = sensors
        self.A, self.B, self.x = paper_model()
        self.k = 0  # the step whose state was sent last
        self.finished = ""  # the reason of the coordinator's Stop, once it came

    @property
    def roles(self) -> list[str]:
        return ["plant"] if self.sensors is None else [f"sensor-{name}" for name in self.sensors]

    def states(self) -> list[tuple[str, bytes]]:
        """(role, payload) of every state message for x(k)."""
        parts = {name: self.x[N_I * i:N_I * (i + 1)] for i, name in enumerate(NAMES)}
        if self.sensors is None:
            return [("plant", state_message(self.run, self.k, "plant", parts))]
        return [(f"sensor-{name}", state_message(self.run, self.k, f"sensor-{name}", {name: parts[name]}))
                for name in self.sensors]

    def on_inputs(self, payload: bytes) -> list[tuple[str, bytes]]:
        """The state messages to send in answer to an ``inputs`` message (none if it is ignored)."""
        body = read_message(payload, self.run, "inputs")
        if body["k"] == self.k - 1:
            return self.states()  # the coordinator missed x(k): the same answer, not applied twice
        if body["k"] != self.k:
            return []  # another step's inputs: not for this plant now
        u = read_inputs(body)
        self.x = self.A @ self.x + self.B @ u
        self.k += 1
        return self.states()

    def on_control(self, payload: bytes) -> None:
        body = read_message(payload, self.run, "stop")
        if not isinstance(body.get("reason"), str):
            raise Dropped("reason: expected a string")
        self.finished = body["reason"]


# ------------------------------------------------------------------------------------ transport
CONNECT_RETRY = {"period_init_ms": 1000, "period_max_ms": 4000, "period_increase_factor": 2}
"""Waits between tries to reach the endpoint: 1 s, then doubling up to 4 s."""


def zenoh_config(connect: str, tls: Path | None, role: str, timeout: float) -> zenoh.Config:
    """A client session to ``connect`` only: multicast scouting off, TLS files of ``role`` if given.

    Opening it keeps trying for ``timeout`` seconds (the coordinator may not listen yet), and
    then fails (docs/protocol.md, "Connecting").
    """
    config = zenoh.Config()
    settings = {"mode": "client", "scouting/multicast/enabled": False, "connect/endpoints": [connect],
                "connect/timeout_ms": int(timeout * 1000), "connect/exit_on_failure": True,
                "connect/retry": CONNECT_RETRY}
    if tls is not None:
        settings.update({"transport/link/tls/root_ca_certificate": str(tls / "ca.pem"),
                         "transport/link/tls/connect_certificate": str(tls / f"{role}.pem"),
                         "transport/link/tls/connect_private_key": str(tls / f"{role}.key"),
                         "transport/link/tls/enable_mtls": True})
    for key, value in settings.items():
        config.insert_json5(key, _json5(value))
    return config


def _json5(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return str(value)
    if isinstance(value, list):
        return "[" + ", ".join(_json5(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{key}: {_json5(v)}" for key, v in value.items()) + "}"
    return '"' + str(value).replace("\\", "\\\\").replace('"', '\\"') + '"'


def serve(plant: OutsidePlant, session: zenoh.Session, startup_timeout: float) -> tuple[int, str]:
    """Answer the coordinator until the run stops or the coordinator is gone; (exit code, why)."""
    events: queue.SimpleQueue = queue.SimpleQueue()
    root = f"dmpc/{plant.run}"
    declared = [
        session.declare_subscriber(f"{root}/inputs", lambda s: events.put(("inputs", s.payload.to_bytes()))),
        session.declare_subscriber(f"{root}/control", lambda s: events.put(("control", s.payload.to_bytes()))),
        session.liveliness().declare_subscriber(
            f"{root}/alive/{COORDINATOR}", lambda s: events.put(("alive", s.kind == zenoh.SampleKind.PUT)),
            history=True),
    ]
    publishers = {role: session.declare_publisher(f"{root}/state/{role}", encoding="application/msgpack",
                                                  congestion_control=zenoh.CongestionControl.BLOCK,
                                                  reliability=zenoh.Reliability.RELIABLE)
                  for role in plant.roles}
    # the tokens last: whoever sees them can reach the subscribers declared above
    declared += [session.liveliness().declare_token(f"{root}/alive/{role}") for role in plant.roles]
    seen_reasons: set[str] = set()
    started = time.monotonic()
    next_first = started  # when x(0) goes out again
    lost_since: float | None = None
    seen = False

    def send(messages):
        for role, payload in messages:
            publishers[role].put(payload)

    try:
        while not plant.finished:
            now = time.monotonic()
            if plant.k == 0 and now >= next_first:
                send(plant.states())
                next_first = now + REPEAT
            if lost_since is not None and now - lost_since > GRACE:
                return 1, f"lost the coordinator after {plant.k} steps (its token was gone for {GRACE:g} s)"
            if not seen and now - started > startup_timeout:
                return 1, f"no coordinator of run {plant.run!r} within {startup_timeout:g} s"
            try:
                kind, value = events.get(timeout=0.1)
            except queue.Empty:
                continue
            try:
                if kind == "alive" and value:
                    seen, lost_since = True, None
                elif kind == "alive":
                    if seen and lost_since is None:
                        lost_since = time.monotonic()
                elif kind == "inputs":
                    send(plant.on_inputs(value))
                else:
                    plant.on_control(value)
            except Dropped as exc:
                if str(exc) not in seen_reasons:  # each reason once: a flood must not flood the log
                    seen_reasons.add(str(exc))
                    print(f"outside plant: dropped a message on {kind}: {exc}", file=sys.stderr, flush=True)
    finally:
        for item in reversed(declared):
            item.undeclare()
    if plant.finished == "finished":
        return 0, f"finished after {plant.k} steps"
    return 1, f"the coordinator stopped the run after {plant.k} steps ({plant.finished})"


def arguments(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connect", required=True, help="the coordinator's (or a router's) Zenoh endpoint, "
                                                         "e.g. tcp/127.0.0.1:7447")
    parser.add_argument("--run-id", required=True, help="the run id the coordinator was given")
    parser.add_argument("--sensor", action="append", metavar="NAME",
                        help=f"report only subsystem NAME as sensor-NAME (repeatable; one of {', '.join(NAMES)})")
    parser.add_argument("--tls", type=Path, metavar="DIR", help="ca.pem and this role's .pem and .key "
                                                                "(plant, or sensor-NAME)")
    parser.add_argument("--startup-timeout", type=float, default=60.0,
                        help="seconds to reach the endpoint and see the coordinator")
    args = parser.parse_args(argv)
    if not re.fullmatch(r"(tcp|tls)/[^/\s]+:\d{1,5}", args.connect):
        parser.error(f"--connect {args.connect!r}: expected tcp/HOST:PORT or tls/HOST:PORT")
    if not re.fullmatch(r"[A-Za-z0-9_.-]{1,64}", args.run_id):
        parser.error(f"--run-id {args.run_id!r}: expected 1-64 characters from A-Z a-z 0-9 _ . -")
    for name in args.sensor or []:
        if name not in NAMES:
            parser.error(f"--sensor {name!r}: the subsystems are {', '.join(NAMES)}")
    if args.sensor is not None and len(set(args.sensor)) != len(args.sensor):
        parser.error("--sensor: each subsystem once")
    if not math.isfinite(args.startup_timeout) or args.startup_timeout <= 0:
        parser.error("--startup-timeout: expected a positive number of seconds")
    if args.tls is not None:
        roles = ["plant"] if args.sensor is None else [f"sensor-{name}" for name in args.sensor]
        if len(roles) > 1:
            parser.error("--tls: a certificate names one role; give --sensor once per process")
        if not args.connect.startswith("tls/"):
            parser.error(f"--connect {args.connect!r}: with --tls the endpoint must be tls/HOST:PORT")
        for file in ("ca.pem", f"{roles[0]}.pem", f"{roles[0]}.key"):
            if not (args.tls / file).is_file():
                parser.error(f"--tls: {args.tls / file} does not exist")
    return args


def main(argv: list[str] | None = None) -> int:
    args = arguments(argv)
    plant = OutsidePlant(args.run_id, args.sensor)
    who = " ".join(plant.roles)
    try:
        session = zenoh.open(zenoh_config(args.connect, args.tls, plant.roles[0], args.startup_timeout))
    except zenoh.ZError as exc:
        reason = re.sub(r"\s+at /\S+?\.rs:\d+\.?", "", str(exc)).strip()  # drop Zenoh's source locations
        print(f"outside plant ({who}): cannot reach {args.connect} within {args.startup_timeout:g} s ({reason})",
              flush=True)
        return 1
    try:
        code, why = serve(plant, session, args.startup_timeout)
    except KeyboardInterrupt:
        code, why = 130, f"interrupted after {plant.k} steps"
    finally:
        session.close()
    print(f"outside plant ({who}): {why}", flush=True)
    return code


if __name__ == "__main__":
    sys.exit(main())

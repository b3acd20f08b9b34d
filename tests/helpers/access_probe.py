"""What one role's certificate lets a session do on a node that enforces dmpc's access control.

``python -m tests.helpers.access_probe --tls DIR --role sensor-2 --port P [--no-acl]`` opens two
real Zenoh sessions over TLS on loopback:

* the **node**, configured as a dmpc process that hosts the coordinator configures itself
  (``session_config`` with the ``coordinator`` certificate and the directory's ``acl.json``),
  listening on ``tls/127.0.0.1:P``; with ``--no-acl``, the same without the access control;
* the **probe**, holding ``--role``'s valid certificate and no access control of its own (as a
  process that does not follow the rules would), connected to the node.

The probe puts on every key of the run, declares liveliness tokens of several roles and
subscribes to every key; the node subscribes to everything under the run, publishes on every
key and watches the tokens. Each side then reports what reached it, as one JSON line on stdout
(``ACCESS {...}``): ``node_received`` and ``probe_received`` (keys; ``probe_received_wide``: what
a second session of the role got on its one subscriber, to ``dmpc/<run>/**``), ``node_saw_alive``
and ``probe_saw_alive`` (roles). Each exchange ends with a marker on a key that must get through,
sent after everything else on the same link, so whatever is missing by then was dropped.
"""
from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

import zenoh

from dmpc.bus import keys
from dmpc.bus.session import open_session, session_config
from dmpc.security.acl import read_acl
from dmpc.security.files import tls_files

RUN = "access"
COPIES = 3  # puts per key: a single one could be lost for reasons other than the rules
GRACE = 0.5  # seconds to wait after the marker for anything that was not dropped
MARKER = b"last"


def run_keys(names: list[str]) -> dict[str, str]:
    """Every key expression of the protocol for run ``RUN``, by a short label."""
    labels = {"release": keys.release(RUN), "control": keys.control(RUN), "inputs": keys.inputs(RUN),
              "telemetry": keys.telemetry(RUN, "steps"), "state/plant": keys.state(RUN, keys.PLANT_ROLE)}
    for name in names:
        labels[f"plan/{name}"] = keys.plan(RUN, name)
        labels[f"ready/{name}"] = keys.ready(RUN, name)
        labels[f"state/sensor-{name}"] = keys.state(RUN, keys.sensor_role(name))
    return labels


class Inbox:
    """Keys (by label) that reached a subscriber, and whether the marker came on ``marker_key``."""

    def __init__(self, labels: dict[str, str], marker_key: str) -> None:
        self.by_key = {key: label for label, key in labels.items()}
        self.marker_key = marker_key
        self.received: set[str] = set()
        self.marked = threading.Event()
        self.lock = threading.Lock()

    def __call__(self, sample) -> None:
        key = str(sample.key_expr)
        with self.lock:
            self.received.add(self.by_key.get(key, key))
        if key == self.marker_key and sample.payload.to_bytes() == MARKER:
            self.marked.set()


def wait(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"no {what} within {timeout:g} s")
        time.sleep(0.02)


def exchange(sender, labels: dict[str, str], own: str, inbox: Inbox) -> None:
    """``sender`` puts on ``own`` until ``inbox`` has it (the route exists), then ``COPIES`` times
    on every key, then the marker on ``own``; returns once the marker arrived and the grace passed."""
    deadline = time.monotonic() + 20
    while not labels_of(inbox, own):
        if time.monotonic() > deadline:
            raise TimeoutError(f"nothing on {own} got through within 20 s")
        sender.put(labels[own], b"hello")
        time.sleep(0.05)
    for _ in range(COPIES):
        for key in labels.values():
            sender.put(key, b"probe")
    sender.put(labels[own], MARKER)
    if not inbox.marked.wait(20):
        raise TimeoutError(f"the marker on {own} did not arrive within 20 s")
    time.sleep(GRACE)


def labels_of(inbox: Inbox, label: str) -> bool:
    with inbox.lock:
        return label in inbox.received


def probe(tls: Path, role: str, port: int, acl: bool, names: list[str], own_key: str) -> dict:
    endpoint = f"tls/127.0.0.1:{port}"
    labels = run_keys(names)
    node = open_session(session_config(mode="peer", listen=[endpoint], tls=tls_files(tls, keys.COORDINATOR_ROLE),
                                       acl=read_acl(tls) if acl else None), timeout=10)
    entities: list = []
    sessions: list = []
    try:
        node_inbox = Inbox(labels, labels[own_key])
        node_alive: set[str] = set()
        entities.append(node.declare_subscriber(f"{keys.ROOT}/{RUN}/**", node_inbox,
                                                allowed_origin=zenoh.Locality.REMOTE))
        entities.append(node.liveliness().declare_subscriber(
            keys.alive_prefix(RUN), lambda s: node_alive.add(keys.last_chunk(str(s.key_expr))), history=True))
        entities.append(node.liveliness().declare_token(keys.alive(RUN, keys.COORDINATOR_ROLE)))

        # a second session of the role with one subscriber to the whole run, and nothing else
        # (beside the probe's exact ones, it would be handed what they are sent); a client, linked
        # to the node alone (a peer would link to the probe's session too, which puts on every key)
        wide_session = open_session(session_config(mode="client", connect=[endpoint], tls=tls_files(tls, role)),
                                    timeout=10)
        sessions.append(wide_session)
        wide_inbox = Inbox(labels, labels["control"])
        entities.append(wide_session.declare_subscriber(f"{keys.ROOT}/{RUN}/**", wide_inbox))
        probe_session = open_session(session_config(mode="peer", connect=[endpoint], tls=tls_files(tls, role)),
                                     timeout=10)
        sessions.append(probe_session)
        probe_inbox = Inbox(labels, labels["control"])
        probe_alive: set[str] = set()
        for key in labels.values():
            entities.append(probe_session.declare_subscriber(key, probe_inbox, allowed_origin=zenoh.Locality.REMOTE))
        entities.append(probe_session.liveliness().declare_subscriber(
            keys.alive_prefix(RUN), lambda s: probe_alive.add(keys.last_chunk(str(s.key_expr))), history=True))
        tokens = [role, keys.PLANT_ROLE, keys.agent_role(names[0])] + [keys.sensor_role(n) for n in names]
        for token in dict.fromkeys(tokens):
            entities.append(probe_session.liveliness().declare_token(keys.alive(RUN, token)))

        exchange(probe_session, labels, own_key, node_inbox)  # what the probe may publish
        exchange(node, labels, "control", probe_inbox)  # what the probe is sent
        wait(lambda: role in node_alive and keys.COORDINATOR_ROLE in probe_alive, 10, "liveliness")
        time.sleep(GRACE)
        return {"node_received": sorted(node_inbox.received), "probe_received": sorted(probe_inbox.received),
                "probe_received_wide": sorted(wide_inbox.received),
                "node_saw_alive": sorted(node_alive), "probe_saw_alive": sorted(probe_alive)}
    finally:
        for entity in reversed(entities):
            entity.undeclare()
        for session in sessions:
            session.close()
        node.close()


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="access_probe")
    p.add_argument("--tls", type=Path, required=True)
    p.add_argument("--role", required=True)
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--names", default="1,2,3,4", help="the subsystems, comma-separated")
    p.add_argument("--own", required=True, help="the label of the key the role may publish on, e.g. state/sensor-2")
    p.add_argument("--no-acl", action="store_true")
    args = p.parse_args(argv)
    result = probe(args.tls, args.role, args.port, not args.no_acl, args.names.split(","), args.own)
    print("ACCESS " + json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

"""A passive observer of a live run on the Zenoh bus.

It opens a client session (it links only to the endpoints it is given, and never joins the
mesh of the run's peers), subscribes to the run's telemetry and watches the liveliness tokens.
It publishes nothing and declares no token; with TLS its certificate's role is ``observer``,
which the run's access control lets subscribe and nothing else.

Messages are handled on a thread of its own; the bus's receiving queue is bounded, so an
observer that falls behind drops telemetry instead of growing without limit.
"""
from __future__ import annotations

import json
import logging
import threading

from dmpc.bus import keys
from dmpc.bus.session import BusError, session_config
from dmpc.bus.zenoh_bus import ZenohBus
from dmpc.watch.meta import RunMeta
from dmpc.watch.state import RunState
from dmpc.watch.telemetry import MAX_PAYLOAD, TelemetryError, decode

log = logging.getLogger("dmpc.watch")
RETRY = 5.0  # seconds each attempt to reach the endpoints lasts
# within an attempt, how soon Zenoh tries again: a plant that comes up is reached at once
RETRY_PERIOD = {"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 1.5}
QUEUE = 10_000  # messages waiting to be handled; more are dropped (and counted)


class BusObserver:
    """Feeds a RunState from a run's telemetry and liveliness tokens.

    Parameters
    ----------
    state : RunState
    run_id : str
    connect : list of str
        Zenoh endpoints of the plant or a router.
    tls, acl : optional
        The observer's TLS files and the access control (``dmpc.security.files.node_security``).
    """

    def __init__(self, state: RunState, run_id: str, connect: list[str], tls=None, acl=None) -> None:
        self.state = state
        self.run_id = run_id
        self.connect = list(connect)
        self._tls, self._acl = tls, acl
        self._config()  # a malformed endpoint fails here, in the caller, not on the thread
        self._stop = threading.Event()
        self._bus: ZenohBus | None = None
        self._thread = threading.Thread(target=self._main, name="dmpc-observer", daemon=True)

    def _config(self):
        config = session_config(mode="client", connect=self.connect, tls=self._tls, acl=self._acl)
        config.insert_json5("connect/retry", json.dumps(RETRY_PERIOD))
        return config

    def start(self) -> None:
        self._thread.start()

    def close(self, timeout: float = 2.0) -> None:
        """Stop handling messages and close the session, waiting at most ``timeout`` seconds; idempotent."""
        self._stop.set()
        self._thread.join(timeout)
        if self._bus is not None:
            self._bus.close()

    # -- on the observer's thread ------------------------------------------------------------
    def _main(self) -> None:
        where = ", ".join(self.connect)
        self.state.set_connection(f"connecting to {where}")
        while not self._stop.is_set():
            try:
                bus = ZenohBus(self._config(), open_timeout=RETRY, max_queue=QUEUE, max_payload=MAX_PAYLOAD)
                break
            except BusError:
                self.state.set_connection(f"connecting to {where} (not reachable yet, retrying)")
        else:
            return
        self._bus = bus
        try:
            bus.subscribe(keys.telemetry_prefix(self.run_id), self._on_telemetry)
            bus.watch_alive(keys.alive_prefix(self.run_id), self._on_alive)
        except BusError:
            return  # closed while starting
        self.state.set_connection(f"connected to {where}")
        try:
            bus.run(until=self._stop.is_set)
        except BusError:
            pass
        except Exception as exc:  # logged: the page keeps what it has and says why it stopped
            log.exception("observer stopped")
            self.state.set_connection(f"observer stopped: {type(exc).__name__}: {exc}")

    def _on_telemetry(self, key: str, payload: bytes) -> None:
        try:
            msg = decode(payload, self.run_id)
        except TelemetryError as exc:
            self.state.note_dropped(f"telemetry on {key}: {exc}")
            return
        kind = msg["type"]
        if kind == "step":
            self.state.add_step(msg["step"])
            self.state.set_plant(msg["plant"])
        elif kind == "meta":
            if self.state.meta is None:
                try:
                    self.state.set_meta(RunMeta.from_json(msg["meta"]))
                except ValueError as exc:
                    self.state.note_dropped(f"telemetry meta: {exc}")
        else:
            self.state.set_summary(msg["summary"], "bus")

    def _on_alive(self, key: str, alive: bool) -> None:
        self.state.set_alive(keys.last_chunk(key), alive)

"""Telemetry: the plant publishes each completed step for observers, best effort.

Keys (``bus.keys.telemetry``): ``dmpc/<run>/telemetry/step`` (one message per completed
step, the ``steps.jsonl`` line plus the plant's view of the agents), ``.../meta`` (the run's
description, :mod:`.meta`, repeated every second so that a late observer learns it) and
``.../end`` (``summary.json``'s content once the run has ended). Payloads are JSON objects
``{"type": ..., "run": ..., ...}``.

The plant's thread only appends the finished record to a bounded queue, and only while some
subscriber matches (the publishing thread looks every half second); that thread encodes and
publishes it, with congestion control DROP and best-effort reliability at low priority. A slow
or stopped observer therefore loses telemetry, and never delays the plant.
"""
from __future__ import annotations

import collections
import json
import math
import threading
import time

from dmpc.bus import keys
from dmpc.bus.interface import Broadcast, Bus
from dmpc.core.errors import DmpcError
from dmpc.prepared import Prepared
from dmpc.records.plant_units import PlantUnits
from dmpc.records.run_folder import jsonable, step_line
from dmpc.watch.meta import meta_json

KINDS = ("step", "meta", "end")
ENCODING = "application/json"
META_EVERY = 1.0  # seconds between two copies of the run's description
QUEUE = 256  # steps waiting for the publishing thread; the oldest are dropped beyond it
MAX_PAYLOAD = 16 << 20  # an observer drops larger messages unread


plain = jsonable


def encode(kind: str, run: str, **fields) -> bytes:
    """One telemetry message of ``kind`` (``step``, ``meta``, ``end``) of run ``run``, with ``fields``,
    as JSON bytes."""
    return json.dumps({"type": kind, "run": run, **plain(fields)}, allow_nan=False,
                      separators=(",", ":")).encode()


class TelemetryError(DmpcError, ValueError):
    """A telemetry payload that is not a message of this run."""


def decode(payload: bytes, run: str) -> dict:
    """The message in ``payload``, checked to be a known kind of run ``run``.

    Raises
    ------
    TelemetryError
        Too large, not a JSON object, an unknown kind, another run, or the fields of its kind
        missing.
    """
    if len(payload) > MAX_PAYLOAD:
        raise TelemetryError(f"{len(payload)} bytes is over the limit")
    try:
        msg = json.loads(payload)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise TelemetryError(f"not JSON ({exc})") from None
    if not isinstance(msg, dict) or msg.get("type") not in KINDS:
        raise TelemetryError("not a telemetry message")
    if msg.get("run") != run:
        raise TelemetryError(f"run {msg.get('run')!r}, not {run!r}")
    need = {"step": ("step", "plant"), "meta": ("meta",), "end": ("summary",)}[msg["type"]]
    if not all(isinstance(msg.get(k), dict) for k in need):
        raise TelemetryError(f"a {msg['type']} message without {', '.join(need)}")
    return msg


def plant_status(node) -> dict:
    """The plant's view of the agents now, from the CoordinatorNode ``node``: liveliness, readiness,
    dropped messages."""
    return {"alive": sorted(node.alive), "ready": sorted(node.ready), "rejected": dict(node.rejects.counts),
            "rejected_reasons": dict(node.rejects.reasons), "duplicates": node.coordinator.duplicates}


class Telemetry:
    """Publishes a run's steps, description and summary on its own thread.

    Parameters
    ----------
    publishers : mapping of kind -> Broadcast
        One best-effort publisher per kind of message (``KINDS``), from the coordinator's bus
        (:meth:`dmpc.bus.interface.Bus.broadcast`).
    run_id : str
    meta : dict
        The run's description (:func:`dmpc.watch.meta.meta_json`).
    meta_every : float
        Seconds between two copies of the description while an observer listens.
    units : PlantUnits, optional
        The run's operating point: the steps are published in the plant's units, as in ``steps.jsonl``.

    Attributes
    ----------
    watched : bool
        Some subscriber matches the step key (as of the publishing thread's last look).
    sent, overflow, errors : int
        Messages published, steps dropped because the queue was full, and failed puts.
    """

    def __init__(self, publishers: dict[str, Broadcast], run_id: str, meta: dict, meta_every: float = META_EVERY,
                 units: PlantUnits | None = None) -> None:
        self.run_id = run_id
        self._units = units
        self._publishers = dict(publishers)
        self._meta = encode("meta", run_id, meta=meta)
        self._meta_every = meta_every
        self._meta_at = -math.inf
        self._queue: collections.deque = collections.deque(maxlen=QUEUE)
        self._wake = threading.Event()
        self._closing = False
        self._end: bytes | None = None
        self.watched = False
        self.sent = 0
        self.overflow = 0
        self.errors = 0
        self._thread = threading.Thread(target=self._loop, name="dmpc-telemetry", daemon=True)
        self._thread.start()

    # -- the plant's thread ----------------------------------------------------------------
    def step(self, rec, node) -> None:
        """Queue the completed step ``rec`` (a StepRecord) with the plant's status (``node``: the
        CoordinatorNode) if an observer listens; never blocks."""
        if not self.watched:
            return
        if len(self._queue) == self._queue.maxlen:
            self.overflow += 1
        self._queue.append(("step", rec, plant_status(node)))
        self._wake.set()

    def summary(self, summary: dict) -> None:
        """Queue the run's summary; it is sent again on :meth:`close`."""
        self._queue.append(("end", summary, None))
        self._wake.set()

    def close(self, timeout: float = 1.0) -> None:
        """Send what is queued (waiting at most ``timeout`` seconds), stop the thread and undeclare the
        publishers; idempotent."""
        if self._closing:
            return
        self._closing = True
        self._wake.set()
        self._thread.join(timeout)
        if self._end is not None:
            self._put("end", self._end)  # a second copy: the first may have been dropped
        for publisher in self._publishers.values():
            publisher.close()

    # -- the publishing thread -------------------------------------------------------------
    def _put(self, kind: str, payload: bytes) -> None:
        try:
            self._publishers[kind].put(payload)
            self.sent += 1
        except Exception:  # noqa: BLE001 - telemetry must never disturb the run
            self.errors += 1

    def _observed(self) -> bool:
        return self._publishers["step"].matched

    def _loop(self) -> None:
        while True:
            self._wake.wait(0.5)
            self._wake.clear()
            self.watched = observed = self._observed()
            if observed and time.monotonic() - self._meta_at >= self._meta_every:
                self._meta_at = time.monotonic()
                self._put("meta", self._meta)
            while self._queue:
                kind, item, status = self._queue.popleft()
                if kind == "end":
                    self._end = encode("end", self.run_id, summary=item)
                    self._put("end", self._end)
                elif observed:
                    try:
                        payload = encode("step", self.run_id, step=step_line(item, self._units), plant=status)
                    except Exception:  # noqa: BLE001 - a record that does not encode is skipped
                        self.errors += 1
                        continue
                    self._put("step", payload)
            if self._closing:
                return


def open_telemetry(bus: Bus, run_id: str, prepared: Prepared) -> Telemetry | None:
    """Telemetry of run ``run_id`` (the ``prepared`` run) on the coordinator's bus, or None for a bus that
    nothing outside the run can observe (the in-memory bus)."""
    made = {kind: bus.broadcast(keys.telemetry(run_id, kind), ENCODING) for kind in KINDS}
    publishers = {kind: p for kind, p in made.items() if p is not None}
    if len(publishers) < len(made):
        return None
    return Telemetry(publishers, run_id, meta_json(prepared, run_id), units=PlantUnits.of(prepared.system))

"""Misbehaving outside plants for the end-to-end tests: examples/outside_plant.py with one fault.

    python -m tests.helpers.bad_plant MODE --connect EP --run-id RUN [--from-step K] [--sensor NAME] [--tls DIR]

MODE is one of

``shape``
    from step K on, subsystem 2's state has 3 entries instead of 2;
``nan``
    from step K on, subsystem 2's state holds NaN;
``version``
    every state is written in protocol version 2 (its version in ``"schema"``);
``rogue``
    a correct plant that also publishes, at every step, a well-formed release, a plan of agent 1,
    a ready of agent 1 and a Stop, on keys that are not the plant's. Its last line is
    ``ROGUE SENT <n>``: how many it published.

Everything else (the dynamics, the rules, the exit codes) is the example's.
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

import msgpack
import numpy as np
import zenoh

from dmpc.bus import keys
from dmpc.bus.codec import encode
from dmpc.bus.messages import PlanMessage, Ready, Release, Stop

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "outside_plant.py"
MODES = ("shape", "nan", "version", "rogue")
FORGED_REASON = "failed: forged by the plant"


def load_example():
    spec = importlib.util.spec_from_file_location("outside_plant", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


example = load_example()


class BadPlant(example.OutsidePlant):
    """The example's plant with the fault of ``mode`` (see the module's text)."""

    def __init__(self, run: str, sensors: list[str] | None, mode: str, from_step: int) -> None:
        super().__init__(run, sensors)
        self.mode = mode
        self.from_step = from_step
        self.session: zenoh.Session | None = None
        self.forged = 0

    def states(self) -> list[tuple[str, bytes]]:
        sent = super().states()
        if self.mode not in ("shape", "nan", "version") or self.k < self.from_step:
            return sent
        return [(role, self._spoil(payload)) for role, payload in sent]

    def _spoil(self, payload: bytes) -> bytes:
        body = msgpack.unpackb(payload, raw=False)
        if self.mode == "version":
            del body["protocol"]
            body["schema"] = 2
        elif "2" in body["x"]:
            bad = np.zeros(3) if self.mode == "shape" else np.array([np.nan, 0.0])
            body["x"]["2"] = example.wire_array(bad)
        return msgpack.packb(body, use_bin_type=True)

    def on_inputs(self, payload: bytes) -> list[tuple[str, bytes]]:
        answer = super().on_inputs(payload)
        if self.mode == "rogue" and answer and self.session is not None:
            self._forge()
        return answer

    def on_control(self, payload: bytes) -> None:
        body = msgpack.unpackb(payload, raw=False)
        if isinstance(body, dict) and body.get("reason") == FORGED_REASON:
            return  # its own forgery, delivered inside its own session
        super().on_control(payload)

    def _forge(self) -> None:
        run, k, M, N = self.run, self.k, len(example.NAMES), 10
        forged = [
            (keys.release(run), Release(run=run, k=k, round=0, x=np.zeros(2 * M), centres=np.zeros(2 * M),
                                        sizes=np.ones(M), assumed=np.full((M, 2), -1, dtype=np.int64))),
            (keys.plan(run, "1"), PlanMessage(run=run, k=k, round=0, sender="1", status="solved",
                                              z=np.full((N + 1, 2), 2.0), v=np.full((N, 1), 2.0), cost=0.0,
                                              solve_time=0.0, qp_iterations=1)),
            (keys.ready(run, "1"), Ready(run=run, sender="1", design_digest="forged", pid=1)),
            (keys.control(run), Stop(run=run, k=k, reason=FORGED_REASON)),
        ]
        for key, msg in forged:
            self.session.put(key, encode(msg))
            self.forged += 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bad_plant")
    parser.add_argument("mode", choices=MODES)
    parser.add_argument("--connect", required=True)
    parser.add_argument("--run-id", required=True)
    parser.add_argument("--from-step", type=int, default=0)
    parser.add_argument("--sensor", action="append")
    parser.add_argument("--tls", type=Path)
    parser.add_argument("--startup-timeout", type=float, default=60.0)
    args = parser.parse_args(argv)
    plant = BadPlant(args.run_id, args.sensor, args.mode, args.from_step)
    session = zenoh.open(example.zenoh_config(args.connect, args.tls, plant.roles[0], args.startup_timeout))
    plant.session = session
    try:
        code, why = example.serve(plant, session, args.startup_timeout)
    finally:
        session.close()
    print(f"bad plant ({args.mode}): {why}", flush=True)
    if args.mode == "rogue":
        print(f"ROGUE SENT {plant.forged}", flush=True)
    return code


if __name__ == "__main__":
    sys.exit(main())

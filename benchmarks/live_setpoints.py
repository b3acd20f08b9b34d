"""Live setpoints in real time: do the steps that take a request stay as short as the others?

Runs ten spring-coupled carts (the chain of scenarios/carts.yaml made ten long) with ``dmpc run``'s
processes in real time (dt = 0.2 s) and, while the run goes on, sends five setpoint requests
(``dmpc.setpoint``), each for a new target, with ``--hogs`` CPU-busy processes beside the run (two
by default: ``python -c 'while True: pass'``, stopped at the end). Prints, per run, the median and
largest recorded step time (release of step k to x(k+1)), the steps over dt, the fallbacks, and the
step time of the steps that took a request (every step from the one the request arrived in to the
one whose close decided its first target, the answer's ``k`` - 1) against three times the median,
and how long each request waited for its answer; with the machine's speed figure (ms for 10^6
Python additions, ``dmpc.bench.common.calibration_ms``).

    python benchmarks/live_setpoints.py [--runs 1] [--hogs 2] [--steps 150] [--json]

The design of the ten carts (about 30 s on two cores) is made once for every run.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import dmpc  # noqa: E402
from dmpc.api.setpoints import LiveRun, StartHook  # noqa: E402
from dmpc.bench.common import calibration_ms, load_average  # noqa: E402
from dmpc.runtime.launcher import launch  # noqa: E402
from dmpc.setup import prepare  # noqa: E402

CARTS = 10
DT = 0.2
REQUESTS = (("2", 1.0), ("5", -1.0), ("8", 1.5), ("3", 0.5), ("10", -0.5))
"""(cart, position): each request moves one cart's position, a new target each time."""
FIRST, EVERY = 10, 20
"""The first request once step FIRST is recorded, the next ones EVERY steps apart."""
HOG = "while True: pass"


def carts(M: int = CARTS, steps: int = 150) -> dmpc.Scenario:
    """A chain of M carts as in scenarios/carts.yaml (spring constant 0.25, dt = 0.2 s), in real time."""
    spring = 0.25
    subsystems = []
    for i in range(M):
        springs = (i > 0) + (i < M - 1)
        subsystems.append({
            "name": str(i + 1),
            "A": [[1 - springs * spring * DT ** 2 / 2, DT], [-springs * spring * DT, 1.0]],
            "B": [[DT ** 2 / 2], [DT]], "Q": [[1.0, 0.0], [0.0, 0.1]], "R": [[0.1]],
            "input": {"lower": [-1.0], "upper": [1.0]}, "state": {"lower": [-5.0, -3.0], "upper": [5.0, 3.0]},
            "x0": [round(3 * float(np.sin(i + 1)), 2), 0.0]})
    pull = [[spring * DT ** 2 / 2, 0.0], [spring * DT, 0.0]]
    couplings = [c for i in range(M - 1) for c in ({"target": str(i + 1), "source": str(i + 2), "A": pull},
                                                   {"target": str(i + 2), "source": str(i + 1), "A": pull})]
    return dmpc.load_scenario({"name": f"carts{M}", "subsystems": subsystems, "couplings": couplings,
                               "steps": steps, "design": {"gains": "lmi"},
                               "options": {"mode": "realtime", "dt": DT}})


def supervise(answers: list, errors: list):
    """The run's ``on_start``: the requests of REQUESTS, EVERY steps apart, their answers kept."""

    def call(live: LiveRun) -> None:
        try:
            for n, (cart, position) in enumerate(REQUESTS):
                if not live.wait_for_step(FIRST + n * EVERY, timeout=120):
                    errors.append(f"step {FIRST + n * EVERY} never recorded")
                    return
                t0, open_step = time.monotonic(), live.steps()  # steps 0 .. open_step - 1 are recorded
                answer = live.setpoint(cart, x=[position, None], sender="bench")
                answers.append({"cart": cart, "x": position, "k": answer.k, "sent_in": open_step,
                                "answer_ms": (time.monotonic() - t0) * 1e3})
        except Exception as exc:  # noqa: BLE001 - reported with the figures
            errors.append(f"{type(exc).__name__}: {exc}")

    return call


def one_run(prepared, folder: Path, hogs: int) -> dict:
    """One real-time run taking the requests, with ``hogs`` busy processes beside it."""
    answers: list[dict] = []
    errors: list[str] = []
    hook = StartHook(supervise(answers, errors), prepared.scenario)
    busy = [subprocess.Popen([sys.executable, "-c", HOG]) for _ in range(hogs)]
    try:
        outcome = launch(prepared, folder, f"bench-{time.monotonic_ns() % 10**8}", show_progress=False,
                         on_ready=hook, startup_timeout=120)
    finally:
        for proc in busy:
            proc.kill()
            proc.wait()
    hook.finish(wait=5.0)
    lines = [json.loads(line) for line in (folder / "steps.jsonl").read_text().splitlines()]
    times = np.array([rec["step_time"] for rec in lines[1:]])  # step 0 runs its rounds to convergence
    median = float(np.median(times))
    # the steps a request can touch: from the one it arrived in to the one whose close decided its
    # first target (the answer's k - 1), which also notes it
    taking = sorted({k for a in answers for k in range(a["sent_in"], a["k"])})
    taken = {k: lines[k]["step_time"] for k in taking if k < len(lines)}
    summary = json.loads((folder / "summary.json").read_text())
    return {"exit_code": outcome.code, "errors": errors, "steps": len(lines), "answers": answers,
            "median_ms": median * 1e3, "max_ms": float(times.max()) * 1e3,
            "over_dt": int((times > DT).sum()), "fallbacks": summary["fallbacks"], "verdict": summary.get("verdict"),
            "taking_ms": {k: v * 1e3 for k, v in taken.items()},
            "taking_ratio": max(taken.values()) / median if taken else float("nan")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--hogs", type=int, default=2, help="CPU-busy processes beside the run")
    parser.add_argument("--steps", type=int, default=FIRST + len(REQUESTS) * EVERY + 20)
    parser.add_argument("--keep", type=Path, help="keep the run folders here")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    speed = calibration_ms()
    t0 = time.monotonic()
    prepared = prepare(carts(CARTS, args.steps))
    print(f"{CARTS} carts: design {time.monotonic() - t0:.0f} s; speed figure {speed:.1f} ms "
          f"(10^6 Python additions); load {load_average():.1f}", flush=True)
    base = args.keep or Path(tempfile.mkdtemp(prefix="live-setpoints-"))
    results = []
    for n in range(args.runs):
        result = one_run(prepared, base / f"run{n}", args.hogs)
        results.append(result)
        taking = ", ".join(f"{k}: {ms:.1f}" for k, ms in result["taking_ms"].items())
        waits = ", ".join(f"{a['answer_ms']:.0f}" for a in result["answers"])
        print(f"run {n}: {result['steps']} steps, exit {result['exit_code']}, verdict {result['verdict']}, "
              f"{len(result['answers'])} requests answered; step time median {result['median_ms']:.1f} ms, "
              f"max {result['max_ms']:.1f} ms; steps over dt {result['over_dt']}; fallbacks {result['fallbacks']}; "
              f"steps taking a request (k: ms) {taking or 'none'}: at most {result['taking_ratio']:.2f} x the median; "
              f"answers after (ms) {waits or 'none'}"
              + (f"; errors {result['errors']}" if result["errors"] else ""), flush=True)
    ok = all(r["exit_code"] == 0 and not r["errors"] and r["over_dt"] == 0 and r["fallbacks"] == 0
             and len(r["answers"]) == len(REQUESTS) and r["taking_ratio"] <= 3.0 for r in results)
    print(("met" if ok else "NOT met") + f": no fallback, no step over dt, the steps taking a request within 3x "
          f"the median, with {args.hogs} busy processes beside the run; speed figure {calibration_ms():.1f} ms")
    if args.json:
        print(json.dumps({"speed_ms": speed, "hogs": args.hogs, "runs": results}, indent=1, default=str))
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()

"""Where a step's CPU goes at M = 4: each process's main thread and Zenoh's threads, run against floor.

Runs the paper's example in lockstep with ``dmpc run`` and the bus floor (``dmpc.bench.floor``:
the same five processes, payloads and neighbours, nothing decoded or checked, the QP replaced by
``--compute-us`` of CPU), alternating, and while each is stepping reads every thread's CPU time
from ``/proc/<pid>/task`` over a window of ``--window`` seconds. Prints, per process, the main
thread's and its other threads' (Zenoh's) CPU per step, the total, and the step median of the window, with
the machine's speed figure (ms for 10^6 Python additions).

On two cores the five processes are CPU-bound, so the step follows the total: this is the table
to read before and after a change to the message path (benchmarks/RESULTS.md).

    python benchmarks/step_profile.py [--steps 6000] [--window 4] [--repeats 2] [--json]

Linux only (``/proc``).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dmpc.bench.common import calibration_ms  # noqa: E402
from dmpc.bench.floor import measure  # noqa: E402
from dmpc.bench.measures import floor_spec  # noqa: E402

SETTLE = 2.5  # seconds after launch before the window opens: start-up and step 0 are over


def thread_cpu(pids: list[int]) -> dict[tuple[int, str], float]:
    """CPU seconds so far per (process, "main" or "other"), from /proc/<pid>/task/*/stat; the
    other threads are Zenoh's (and the bus's alarm thread, which mostly sleeps)."""
    tick = os.sysconf("SC_CLK_TCK")
    out: dict[tuple[int, str], float] = {}
    for pid in pids:
        for tid in os.listdir(f"/proc/{pid}/task"):
            try:
                fields = Path(f"/proc/{pid}/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue  # the thread ended
            kind = "main" if tid == str(pid) else "other"
            out[(pid, kind)] = out.get((pid, kind), 0.0) + (int(fields[11]) + int(fields[12])) / tick
    return out


def cpu_window(procs: list[subprocess.Popen], names: dict[int, str], seconds: float, what: str) -> dict:
    """Read the processes' CPU time now and ``seconds`` later."""
    pids = list(names)
    before, t0 = thread_cpu(pids), time.monotonic()
    time.sleep(seconds)
    after, elapsed = thread_cpu(pids), time.monotonic() - t0
    if any(p.poll() is not None for p in procs):
        raise SystemExit(f"the {what} ended inside the window: give it more --steps")
    return {"before": before, "after": after, "elapsed": elapsed}


def per_step(reading: dict, step_ms_mean: float, step_ms_p50: float, names: dict[int, str]) -> dict:
    """Each process's main-thread and other threads' CPU per step (us) over the window."""
    steps = reading["elapsed"] * 1e3 / step_ms_mean
    rows = []
    for pid, name in names.items():
        row = {"process": name}
        for kind in ("main", "other"):
            spent = reading["after"].get((pid, kind), 0.0) - reading["before"].get((pid, kind), 0.0)
            row[f"{kind}_us"] = spent / steps * 1e6
        rows.append(row)
    return {"step_ms_p50": step_ms_p50, "steps_in_window": steps, "processes": rows,
            "total_us": sum(r["main_us"] + r["other_us"] for r in rows)}


def profile_run(steps: int, seconds: float) -> dict:
    out = Path(tempfile.mkdtemp(prefix="dmpc-profile-")) / "run"
    proc = subprocess.Popen([sys.executable, "-m", "dmpc.cli", "run", "scenarios/paper.yaml", "--out", str(out),
                             "--quiet", "--set", f"steps={steps}"], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        time.sleep(SETTLE)
        names = {}
        for child in psutil.Process(proc.pid).children(recursive=True):
            cmd = " ".join(child.cmdline())
            if "dmpc.cli plant" in cmd:
                names[child.pid] = "coordinator (plant process)"
            elif child.children() == [] and "forkserver" in cmd:
                names[child.pid] = f"agent {len([n for n in names.values() if n.startswith('agent')]) + 1}"
        reading = cpu_window([proc], names, seconds, "run")
        lines = (out / "steps.jsonl").read_text().splitlines()[1:]
        times = np.array([json.loads(line)["step_time"] for line in lines[-2000:]]) * 1e3
        return per_step(reading, float(times.mean()), float(np.median(times)), names)
    finally:
        proc.wait()


def profile_floor(steps: int, seconds: float, compute_us: float) -> dict:
    readings: list[dict] = []
    names: dict[int, str] = {}

    def observe(procs: list[subprocess.Popen]) -> None:
        names.update({procs[0].pid: "floor coordinator", **{p.pid: f"floor agent {i + 1}" for i, p in enumerate(procs[1:])}})
        time.sleep(SETTLE)
        readings.append(cpu_window(procs, names, seconds, "floor"))

    result = measure(floor_spec(4, steps, compute_us, ROOT), while_running=observe)
    if not result["completed"]:
        raise SystemExit(f"the floor failed: {result['reason']}")
    return per_step(readings[0], result["step_ms_mean"], result["step_ms_p50"], names)


def show(label: str, result: dict) -> None:
    print(f"{label}: step median {result['step_ms_p50']:.2f} ms, CPU {result['total_us']:.0f} us per step "
          f"({result['steps_in_window']:.0f} steps in the window)")
    for row in result["processes"]:
        print(f"  {row['process']:<28} main thread {row['main_us']:6.0f} us   other (Zenoh's) threads {row['other_us']:5.0f} us")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=6000, help="steps of each run (long enough for the window)")
    parser.add_argument("--window", type=float, default=4.0, help="seconds of CPU reading per run")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--compute-us", type=float, default=56.0, help="the floor's CPU per agent and step")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    results = []
    for _ in range(args.repeats):
        speed = calibration_ms()
        floor = profile_floor(4 * args.steps, args.window, args.compute_us)  # its steps are about 4x shorter
        run = profile_run(args.steps, args.window)
        results.append({"speed_figure_ms": speed, "floor": floor, "run": run})
        if not args.json:
            print(f"speed figure {speed:.1f} ms")
            show("floor", floor)
            show("dmpc run", run)
    if args.json:
        print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()

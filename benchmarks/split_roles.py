"""Step time at M = 4: the coordinator and the plant in one process, against the two as separate roles.

Runs the paper's example in lockstep with ``dmpc run`` (combined: the default) and with
``dmpc run --plant external`` driven by ``dmpc plant --coordinator external`` (split), alternating,
and prints the median and p99 of the recorded step time (release of step k to the next state) of
each, with the machine's speed figure (seconds for 10^6 Python additions).

    python benchmarks/split_roles.py [--steps 300] [--repeats 3] [--json]
"""
from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "scenarios" / "paper.yaml"
DMPC = [sys.executable, "-m", "dmpc.cli"]


def speed_figure() -> float:
    """Seconds for 10^6 additions in a Python loop (the machine's speed right now)."""
    start = time.perf_counter()
    total = 0
    for i in range(1_000_000):
        total += i
    return time.perf_counter() - start


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def step_times(out: Path) -> np.ndarray:
    with np.load(out / "trajectory.npz") as arrays:
        times = arrays["step_time"]
    return times[np.isfinite(times)][1:]  # step 0 runs its Jacobi rounds to convergence


def run_combined(out: Path, steps: int) -> np.ndarray:
    subprocess.run(DMPC + ["run", str(SCENARIO), "--out", str(out), "--steps", str(steps), "--quiet"], check=True,
                   stdout=subprocess.DEVNULL)
    return step_times(out)


def run_split(out: Path, steps: int) -> np.ndarray:
    port, run_id = free_port(), f"split-{out.name}"
    run = subprocess.Popen(DMPC + ["run", str(SCENARIO), "--out", str(out), "--steps", str(steps), "--quiet",
                                   "--plant", "external", "--port", str(port), "--run-id", run_id],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    plant = subprocess.Popen(DMPC + ["plant", str(SCENARIO), "--coordinator", "external", "--steps", str(steps),
                                     "--connect", f"tcp/127.0.0.1:{port}", "--run-id", run_id],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        if run.wait(timeout=600) != 0:
            raise SystemExit(f"the split run failed: see {out}/logs")
    finally:
        for proc in (plant, run):
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    return step_times(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    times: dict[str, list[np.ndarray]] = {"combined": [], "split": []}
    speed = [speed_figure()]
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            times["combined"].append(run_combined(Path(tmp) / f"combined-{r}", args.steps))
            times["split"].append(run_split(Path(tmp) / f"split-{r}", args.steps))
    speed.append(speed_figure())
    result = {"speed_s_per_1e6_additions": [round(s, 4) for s in speed], "steps": args.steps, "repeats": args.repeats}
    for name, runs in times.items():
        all_times = np.concatenate(runs) * 1e3
        result[f"{name}_step_ms_p50"] = round(float(np.median(all_times)), 3)
        result[f"{name}_step_ms_p99"] = round(float(np.percentile(all_times, 99)), 3)
    result["split_over_combined_p50"] = round(result["split_step_ms_p50"] / result["combined_step_ms_p50"], 2)
    if args.json:
        print(json.dumps(result, indent=1))
        return
    for key, value in result.items():
        print(f"{key:32s} {value}")


if __name__ == "__main__":
    main()

"""Soak benchmark: a long lockstep run, with the memory of every process sampled as it goes.

    .venv/bin/python benchmarks/soak.py --steps 100000 --M 8 --out runs/soak

Starts ``dmpc run scenarios/chain.yaml`` (family.M = M) and samples the resident memory (RSS) of
the plant and of every agent process every ``--every`` seconds, with the number of steps done.
Writes ``soak.json`` beside the run folder and prints: RSS of each process at the first sample
past ``--from`` steps and at the end, their growth, and the median / p99 step time of the first
and last ``--window`` steps (from ``trajectory.npz``). The machine's speed figure (best of 7 timings
of 10^6 Python additions) is printed first, since this VM's speed varies by the hour.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import psutil

from dmpc.records.files import PROCESSES, STEP_LOG, TRAJECTORY

ROOT = Path(__file__).resolve().parents[1]


def speed_ms() -> float:
    """Best of 7 timings of 10^6 Python additions, in ms."""
    best = float("inf")
    for _ in range(7):
        t0 = time.perf_counter()
        total = 0
        for i in range(1_000_000):
            total += i
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def steps_done(path: Path) -> int:
    try:
        with open(path, "rb") as fh:
            return fh.read().count(b"\n")
    except FileNotFoundError:
        return 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=100_000)
    parser.add_argument("--M", type=int, default=8)
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "soak")
    parser.add_argument("--every", type=float, default=2.0, help="seconds between samples")
    parser.add_argument("--from", dest="start", type=int, default=10_000, help="growth is measured from this step")
    parser.add_argument("--window", type=int, default=10_000, help="steps in the first/last step-time windows")
    args = parser.parse_args()
    print(f"machine speed: {speed_ms():.1f} ms for 10^6 Python additions", flush=True)
    out = args.out
    cmd = [str(ROOT / ".venv" / "bin" / "dmpc"), "run", "scenarios/chain.yaml", "--set", f"family.M={args.M}",
           "--steps", str(args.steps), "--quiet", "--out", str(out)]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    samples = []
    started = time.monotonic()
    try:
        while proc.poll() is None:
            time.sleep(args.every)
            try:
                pids = json.loads((out / PROCESSES).read_text())
            except (FileNotFoundError, json.JSONDecodeError):
                continue
            rss = {}
            for role, pid in pids.items():
                try:
                    rss[role] = psutil.Process(pid).memory_info().rss / 2**20
                except psutil.Error:
                    pass
            launcher = psutil.Process(proc.pid).memory_info().rss / 2**20 if proc.poll() is None else None
            samples.append({"t": time.monotonic() - started, "steps": steps_done(out / STEP_LOG), "rss_mb": rss,
                            "launcher_mb": launcher})
    finally:
        if proc.poll() is None:
            proc.terminate()
        stdout, stderr = proc.communicate()
    wall = time.monotonic() - started
    result = {"steps": args.steps, "M": args.M, "wall_s": wall, "exit_code": proc.returncode, "samples": samples}
    during = [s for s in samples if s["steps"] < args.steps]  # before the arrays are written at the end
    base = next((s for s in during if s["steps"] >= args.start), None)
    if base is not None and during:
        last = during[-1]
        growth = {role: last["rss_mb"][role] - base["rss_mb"][role] for role in base["rss_mb"]
                  if role in last["rss_mb"]}
        result.update(base_sample=base, last_sample=last, growth_mb=growth)
    trajectory = out / TRAJECTORY
    if trajectory.exists():
        step_time = np.load(trajectory)["step_time"] * 1e3
        first, tail = step_time[:args.window], step_time[-args.window:]
        result["step_ms"] = {"first": [float(np.median(first)), float(np.percentile(first, 99))],
                             "last": [float(np.median(tail)), float(np.percentile(tail, 99))]}
    (out.parent / f"{out.name}-soak.json").write_text(json.dumps(result, indent=1))
    print(f"exit code {proc.returncode}, {wall:.0f} s for {args.steps} steps")
    if "growth_mb" in result:
        print(f"RSS from step {result['base_sample']['steps']} to step {result['last_sample']['steps']}:")
        for role, grown in sorted(result["growth_mb"].items()):
            print(f"  {role:>10}: {result['base_sample']['rss_mb'][role]:7.1f} -> "
                  f"{result['last_sample']['rss_mb'][role]:7.1f} MB ({grown:+.1f})")
    if "step_ms" in result:
        f, l = result["step_ms"]["first"], result["step_ms"]["last"]
        print(f"step time median / p99: first {args.window} steps {f[0]:.3f} / {f[1]:.3f} ms, "
              f"last {args.window} {l[0]:.3f} / {l[1]:.3f} ms")
    if proc.returncode not in (0, 3):
        print(stderr[-2000:], file=sys.stderr)


if __name__ == "__main__":
    main()

"""The scale table of benchmarks/RESULTS.md: the chain of M subsystems, designed, run with agents
hosted many to a process, and compared with the centralised OSQP loop. Run from the project folder:

    python benchmarks/scale_table.py [--rows 4:1:300 ... 1024:128:10] [--out DIR]

Each row is ``M:K:STEPS`` (K agents per process). Rows run one after another; each is appended
to DIR/scale.jsonl as it completes and the Markdown table is printed at the end. Memory is
sampled while the run steps, so small systems get enough steps to be sampled.
"""
import argparse
import json
import sys
from pathlib import Path

from dmpc.bench.common import calibration_ms
from dmpc.bench.scale import HEADER, markdown_row, scale_row

DEFAULT_ROWS = ["4:1:300", "16:1:150", "64:1:60", "256:64:30", "1024:128:10"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", nargs="+", default=DEFAULT_ROWS, help="M:K:STEPS (default: %(default)s)")
    parser.add_argument("--out", type=Path, default=Path("/tmp/dmpc-scale"), help="folder for the runs and scale.jsonl")
    parser.add_argument("--no-central", action="store_true", help="skip the centralised OSQP loop")
    args = parser.parse_args()
    rows = []
    for text in args.rows:
        try:
            M, K, steps = (int(v) for v in text.split(":"))
        except ValueError:
            sys.exit(f"--rows: {text!r} is not M:K:STEPS")
        args.out.mkdir(parents=True, exist_ok=True)
        print(f"M = {M}, {K} agents per process: speed figure {calibration_ms(3):.1f} ms", flush=True)
        row = scale_row(M, K, steps, args.out, central=not args.no_central)
        rows.append(row)
        with open(args.out / "scale.jsonl", "a") as fh:
            fh.write(json.dumps(row) + "\n")
        print(markdown_row(row), flush=True)
    print("| " + " | ".join(HEADER) + " |")
    print("|" + "---|" * len(HEADER))
    for row in rows:
        print(markdown_row(row))


if __name__ == "__main__":
    main()

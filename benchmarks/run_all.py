"""All benchmarks (the same as ``dmpc bench``); run from the project folder.

    python benchmarks/run_all.py [--quick] [--json]

writes benchmarks/RESULTS.md and benchmarks/figures/*.png.
"""
import sys

from dmpc.cli import main

if __name__ == "__main__":
    sys.argv = ["dmpc", "bench", "--write", "benchmarks/RESULTS.md", *sys.argv[1:]]
    main()

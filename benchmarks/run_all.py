"""Every benchmark, and benchmarks/RESULTS.md regenerated from them (the same as
``dmpc bench --write benchmarks/RESULTS.md``); run from the project folder:

    python benchmarks/run_all.py [--quick] [--json]

It writes benchmarks/RESULTS.md (when and where, the headline and the targets table first, then
every table), benchmarks/RESULTS.json (the raw results) and benchmarks/figures/*.png. The
report's hand-written history (its last section, dated) is kept as it is. The full run took 21
and 34 minutes on the 2-core machine of the report (most of it the X^f method comparison at
M = 256 and the M = 1024 design and run); ``--quick`` takes under a minute.
"""
import sys

from dmpc.cli import main

if __name__ == "__main__":
    sys.argv = ["dmpc", "bench", "--write", "benchmarks/RESULTS.md", *sys.argv[1:]]
    main()

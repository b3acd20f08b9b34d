"""A child whose output pipe loses its reader (``dmpc run``'s launcher killed) finishes its work and
writes the rest into its log file (dmpc.runtime.output)."""
from __future__ import annotations

import os
import subprocess
import sys

from dmpc.runtime.output import LOG_ENV

CHILD = """
import sys, time
from dmpc.runtime.output import guard_output
guard_output()
print("before", flush=True)
sys.stdin.readline()  # the parent closes the pipe's read end meanwhile
print("after: the reader is gone", flush=True)
print("on stderr too", file=sys.stderr, flush=True)
open(sys.argv[1], "w").write("done")
"""


def test_a_child_outlives_the_reader_of_its_output(tmp_path):
    log, done = tmp_path / "child.log", tmp_path / "done"
    read_end, write_end = os.pipe()
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(done)], stdin=subprocess.PIPE, stdout=write_end,
                            stderr=write_end, env={**os.environ, LOG_ENV: str(log)})
    os.close(write_end)
    with os.fdopen(read_end, "rb") as reader:
        assert reader.readline() == b"before\n"
    # the reader is closed: the next write finds the pipe broken
    proc.communicate(b"go\n", timeout=60)
    assert proc.returncode == 0
    assert done.read_text() == "done"
    assert log.read_text() == "after: the reader is gone\non stderr too\n"


def test_without_a_log_file_nothing_is_guarded():
    out = subprocess.run([sys.executable, "-c", "import sys; from dmpc.runtime.output import guard_output; "
                          "guard_output(); print(type(sys.stdout).__name__)"], capture_output=True, text=True,
                         env={k: v for k, v in os.environ.items() if k != LOG_ENV}, timeout=60)
    assert out.stdout.strip() == "TextIOWrapper"

"""``python -m dmpc.cli.forkserver FD``: the agents' fork server (:mod:`dmpc.runtime.forkserver`),
forking ``dmpc`` command lines; FD is its end of the launcher's socket pair."""
from __future__ import annotations

import sys

from dmpc.cli import click_command, main
from dmpc.runtime.forkserver import serve

if __name__ == "__main__":
    serve(int(sys.argv[1]), main, prepare=click_command)

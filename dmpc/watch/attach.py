"""``dmpc run --watch``: the live view as one more process beside the run.

It is started once the run folder (and, with ``--secure``, the certificates) exists, and
before the plant and the agents, so that the page sees the run from its first step. It is no
part of the run: it observes the plant over the bus like any other observer, its failure does
not stop the run, and it stays up after the run, until Ctrl-C, so the page can be read.
"""
from __future__ import annotations

import signal
import socket
import sys
import time
from pathlib import Path

from dmpc.records.files import LOGS, log_file
from dmpc.runtime.launcher import Child, free_port, start, stop_all

READY_TIMEOUT = 20.0  # seconds to wait for the page's server before starting the run anyway


def port_open(port: int, host: str = "127.0.0.1") -> bool:
    """Whether something accepts connections on ``port`` of ``host``."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.settimeout(0.2)
        return sock.connect_ex((host, port)) == 0


class Watcher:
    """The ``dmpc watch`` process of a ``dmpc run --watch``.

    Attributes
    ----------
    child : Child or None
        The process, once started.
    url : str
        The page's address, once started.
    """

    def __init__(self) -> None:
        self.child: Child | None = None
        self.url = ""
        self._port = 0

    def start(self, out: Path, run_id: str, endpoint: str, tls_dir: Path | None) -> None:
        """Start ``dmpc watch`` on the run's plant ``endpoint`` (run ``run_id``, its folder ``out``, the
        certificates in ``tls_dir`` if any) and wait until its page is served.

        Called by the launcher when the run folder is ready (``launch(..., on_ready=...)``), and
        again if it has to start the run on another port: the page then moves to the new
        endpoint and keeps its address.
        """
        if self.child is not None:
            stop_all([self.child])
        port = self._port or free_port()
        self._port = port
        cmd = [sys.executable, "-m", "dmpc.cli", "watch", str(out), "--connect", endpoint, "--run-id", run_id,
               "--port", str(port)] + ([] if tls_dir is None else ["--tls", str(tls_dir)])
        (out / LOGS).mkdir(exist_ok=True)
        self.child = Child("watch", cmd, out / LOGS / log_file("watch"))
        start([self.child])
        self.url = f"http://127.0.0.1:{port}/"
        deadline = time.monotonic() + READY_TIMEOUT
        while time.monotonic() < deadline and self.child.poll() is None and not port_open(port):
            time.sleep(0.05)
        if self.child.poll() is not None:
            print(f"live view: did not start (exit code {self.child.poll()}; see {self.child.log_path})",
                  file=sys.stderr, flush=True)
        else:
            print(f"live view: {self.url}", flush=True)

    def after_run(self, interrupted: bool) -> None:
        """Keep the page up until Ctrl-C (at once if the run was interrupted), then stop it."""
        child = self.child
        if child is None:
            return
        try:
            if child.poll() is None and not interrupted:
                print(f"live view: {self.url} stays up; Ctrl-C to stop", flush=True)
                while child.poll() is None:
                    time.sleep(0.2)
        except KeyboardInterrupt:
            pass
        finally:
            stop_all([child], signal.SIGINT)
        if child.poll() not in (0, None) and not interrupted:
            print(f"live view: exited with code {child.poll()} (see {child.log_path})", file=sys.stderr, flush=True)

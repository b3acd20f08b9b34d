"""Agent processes forked from one process that has imported what an agent needs.

A Python process that imports numpy, scipy.sparse, OSQP and Zenoh spends about 0.35 s of CPU
before it does anything else; a hundred agents pay that a hundred times, a minute of start-up on
a machine with two cores. ``dmpc run`` therefore starts one *fork server* before its agents (as
``multiprocessing``'s forkserver does): a process that imports the agent's modules once and then
forks each agent process on request. A forked agent is an ordinary process of its own with its
own Zenoh session (the server never opens one, which is what makes forking safe, see
docs/runtime.md) and runs the same ``dmpc agent`` command line as one started with exec.

The launcher talks to the server over a Unix socket pair: it sends the command line with the
write end of the process's output pipe (``SCM_RIGHTS``), the server answers with the new pid,
and later with its exit code once it has reaped it. :class:`ForkedProcess` offers the part of
``subprocess.Popen`` that the launcher and the supervisor use.

Processes: launcher -> fork server (PR_SET_PDEATHSIG) -> agents (PR_SET_PDEATHSIG), so no agent
outlives the launcher, as with exec.
"""
from __future__ import annotations

import array
import ctypes
import gc
import json
import os
import select
import selectors
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable

from dmpc.core.errors import DmpcError
from dmpc.runtime.output import LOG_ENV
from dmpc.terminal.exit_codes import EXIT_INTERRUPTED
from dmpc.terminal.signals import interrupts_deferred, sigterm_as_interrupt

PRELOAD = ("dmpc.agents.process", "dmpc.bus.zenoh_bus", "dmpc.prepared.bundle")
"""Modules the server imports before forking: everything ``dmpc agent`` needs (with the command
line, which :mod:`dmpc.cli.forkserver` imports and hands to :func:`serve`)."""
READY_TIMEOUT = 60.0
"""Seconds the launcher waits for the server's imports before starting agents with exec instead."""
REAP_EVERY = 0.02
"""Seconds between the server's checks for exited agents (the latency of an exit code)."""
STRAY_GRACE = 10.0
"""Seconds the server gives its agents to end after SIGTERM once the launcher has closed its end,
before it kills them: the wait ends when they have (well under a second, their reports written);
the grace bounds a hung one, and leaves a machine that is busy time to let them finish."""
_MAX_MESSAGE = 1 << 20
_PR_SET_PDEATHSIG = 1
_PR_SET_NAME = 15


class ForkServerError(DmpcError, RuntimeError):
    """The fork server could not start or answer."""


def _die_with_parent() -> None:
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


def _name_process(name: bytes) -> None:
    """The name ``ps -o comm`` and ``top`` show (the command line stays the server's)."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_NAME, ctypes.c_char_p(name[:15]), 0, 0, 0)
    except OSError:
        pass


class ForkServer:
    """The launcher's end: start the server, fork agents through it, learn their exit codes.

    Parameters
    ----------
    env : dict
        The server's environment, which its agents inherit.
    log : path-like
        Where the server's own output goes.
    """

    def __init__(self, env: dict, log) -> None:
        mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self._sock = mine
        self.exits: dict[int, int] = {}
        self._closed = False
        self.proc: subprocess.Popen | None = None
        with open(log, "ab") as out:
            try:
                with interrupts_deferred():
                    self.proc = subprocess.Popen([sys.executable, "-m", "dmpc.cli.forkserver",
                                                  str(theirs.fileno())], stdin=subprocess.DEVNULL, stdout=out,
                                                 stderr=subprocess.STDOUT, env=env, pass_fds=[theirs.fileno()],
                                                 preexec_fn=_die_with_parent, close_fds=True)
            except KeyboardInterrupt:
                self.close(kill=True)
                raise
            finally:
                theirs.close()
        try:
            reply = self._receive(READY_TIMEOUT, lambda m: "ready" in m)
        except BaseException:  # no answer, or interrupted while it imports: it has forked nothing yet
            self.close(kill=True)
            raise
        if not reply.get("ready"):
            self.close()
            raise ForkServerError(f"the fork server could not import the agent's modules: {reply.get('error')}")

    def _receive(self, timeout: float | None, wanted) -> dict:
        """Read messages (noting exit codes) until one satisfies ``wanted``; None timeout: none pending."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            try:  # the socket stays blocking for the requests sent meanwhile (spawn_all)
                data = self._sock.recv(_MAX_MESSAGE, socket.MSG_DONTWAIT)
            except BlockingIOError:
                left = 0.0 if deadline is None else deadline - time.monotonic()
                if left <= 0:
                    if deadline is None:
                        return {}
                    raise ForkServerError(f"the fork server did not answer within {timeout:g} s") from None
                select.select([self._sock], [], [], left)
                continue
            except OSError as exc:
                raise ForkServerError(f"the fork server is gone ({exc})") from None
            if not data:
                raise ForkServerError("the fork server is gone")
            message = json.loads(data)
            if "exit" in message:
                self.exits[int(message["exit"])] = int(message["code"])
            if wanted(message):
                return message

    def spawn(self, args: list[str], output: int, log: str | None = None) -> ForkedProcess:
        """Fork ``dmpc ARGS`` (``args``) with stdout and stderr on file descriptor ``output`` (and its
        output guarded for ``log``, :func:`dmpc.runtime.output.guard_output`)."""
        forked = self.spawn_all([(args, output, log)])[0]
        if forked is None:
            raise ForkServerError("the fork server could not fork")
        return forked

    def spawn_all(self, requests: list[tuple[list[str], int, str | None]]) -> list[ForkedProcess | None]:
        """Fork ``dmpc ARGS`` for each (ARGS, output descriptor, log file or None), all requests sent
        before any answer is read (the server forks them as one burst); None where a fork failed.
        The log file is where the child's output goes should the descriptor's reader be gone
        (:mod:`dmpc.runtime.output`).

        Raises ForkServerError if the server is gone before any was forked.
        """
        failed: list[OSError] = []

        def send_all() -> None:  # on its own thread: the answers are read meanwhile, so no buffer fills up
            try:
                for args, output, log in requests:
                    socket.send_fds(self._sock, [json.dumps({"argv": list(args), "log": log}).encode()], [output])
            except OSError as exc:
                failed.append(exc)

        sender = threading.Thread(target=send_all, name="dmpc-fork-requests", daemon=True)
        sender.start()
        forked: list[ForkedProcess | None] = []
        # on an error or an interrupt the sender is not waited for: it ends when the socket closes
        for _ in requests:
            try:
                reply = self._receive(READY_TIMEOUT, lambda m: "pid" in m or "error" in m)
            except ForkServerError:
                if not forked:
                    raise ForkServerError(f"the fork server is gone ({failed[0] if failed else 'no answer'})") from None
                reply = {"error": "gone"}
            forked.append(ForkedProcess(self, int(reply["pid"])) if "pid" in reply else None)
        sender.join(READY_TIMEOUT)
        return forked

    def collect(self) -> None:
        """Note the exit codes the server has sent (never blocks)."""
        if self._closed:
            return
        try:
            self._receive(None, lambda m: False)
        except ForkServerError:
            self._closed = True

    @property
    def alive(self) -> bool:
        return not self._closed and self.proc is not None and self.proc.poll() is None

    def close(self, kill: bool = False) -> None:
        """End the server; idempotent. Agents still running (forked while the launcher was
        interrupted, before it learnt their pids) are stopped by the server
        (:data:`STRAY_GRACE`); ``kill``: kill the server at once (it must have forked nothing)."""
        self._closed = True
        try:
            self._sock.close()
        except OSError:
            pass
        if self.proc is None:
            return
        if kill and self.proc.poll() is None:
            self.proc.kill()
        try:
            self.proc.wait(timeout=STRAY_GRACE + 2)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


class ForkedProcess:
    """An agent forked by the ``server`` with process id ``pid``: the part of ``subprocess.Popen`` the
    launcher uses."""

    def __init__(self, server: ForkServer, pid: int) -> None:
        self.server = server
        self.pid = pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            self.server.collect()
            if self.pid in self.server.exits:
                self.returncode = self.server.exits.pop(self.pid)
            elif not self.server.alive and not _exists(self.pid):
                self.returncode = 1  # the server died first: the exit code is lost
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        """Wait for the process to end, at most ``timeout`` seconds (None: as long as it takes; TimeoutExpired
        after); its exit code."""
        start = time.monotonic()
        while (code := self.poll()) is None:
            if timeout is not None and time.monotonic() - start >= timeout:
                raise subprocess.TimeoutExpired(f"pid {self.pid}", timeout)
            time.sleep(REAP_EVERY / 2)
        return code

    def send_signal(self, sig: int) -> None:
        """Send signal ``sig`` to the process if it is still running."""
        if self.poll() is None:
            os.kill(self.pid, sig)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


def _exists(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[-1].split()[0] != "Z"
    except OSError:
        return False


# ---------------------------------------------------------------------------- the server
def serve(fd: int, main: Callable[[], None], prepare: Callable[[], object] | None = None) -> None:
    """The server's loop on the socket ``fd``: fork on request, reap and report, end when the launcher goes.

    ``main`` is what a forked process runs (``dmpc``'s command line, reading ``sys.argv``);
    ``prepare`` is called once before the first fork (building the command line's parser).
    """
    sock = socket.socket(fileno=fd)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C at the terminal is for the launcher and the agents
    try:
        import importlib

        for name in PRELOAD:
            importlib.import_module(name)
        if prepare is not None:
            prepare()
        gc.collect()
        gc.freeze()  # the agents' collections skip what is shared (and leave its pages shared)
    except Exception as exc:  # noqa: BLE001 - reported to the launcher, which falls back to exec
        sock.send(json.dumps({"ready": False, "error": f"{type(exc).__name__}: {exc}"}).encode())
        return
    try:
        sock.send(json.dumps({"ready": True}).encode())
    except OSError:
        return  # the launcher is gone (interrupted while this server imported)
    children: set[int] = set()
    selector = selectors.DefaultSelector()
    selector.register(sock, selectors.EVENT_READ)
    open_ = True
    while open_:
        ready = selector.select(REAP_EVERY)
        _reap(sock, children)
        if ready:
            open_ = _fork_burst(sock, children, main)
    _stop_strays(sock, children)


def _stop_strays(sock: socket.socket, children: set[int]) -> None:
    """The launcher has closed its end, after stopping every agent it knew of: stop the others
    (forked while it was interrupted, their pids never read) with SIGTERM, SIGKILL after
    :data:`STRAY_GRACE` s, and reap them all."""
    _signal_all(children, signal.SIGTERM)
    deadline = time.monotonic() + STRAY_GRACE
    while children and time.monotonic() < deadline:
        _reap(sock, children)
        time.sleep(REAP_EVERY)
    _signal_all(children, signal.SIGKILL)
    while children:
        _reap(sock, children, block=True)


def _signal_all(pids: set[int], sig: int) -> None:
    for pid in pids:
        try:
            os.kill(pid, sig)
        except ProcessLookupError:
            pass


def _fork_burst(sock: socket.socket, children: set[int], main: Callable[[], None]) -> bool:
    """Fork every request waiting on the socket; False once the launcher has closed its end.

    The agents of a burst wait behind a gate until all of it is forked: started at once, a
    hundred agents would take the CPU from this process and each fork would wait for it.
    """
    gate, release = os.pipe()
    open_ = True
    try:
        while True:
            try:
                data, fds = _recv_waiting(sock)
            except BlockingIOError:
                break
            except OSError:
                return False
            if not data:
                open_ = False
                break
            try:
                request = json.loads(data)
                argv, log = request["argv"], request.get("log")
                server = os.getpid()
                pid = os.fork()
            except Exception as exc:  # noqa: BLE001
                for f in fds:
                    os.close(f)
                sock.send(json.dumps({"error": f"{type(exc).__name__}: {exc}"}).encode())
                continue
            if pid == 0:
                os.close(release)
                _child(sock, fds[0], argv, gate, main, server, log)  # never returns
            children.add(pid)
            for f in fds:
                os.close(f)
            sock.send(json.dumps({"pid": pid}).encode())
    finally:
        os.close(gate)
        os.close(release)  # the gate opens
    return open_


def _recv_waiting(sock: socket.socket) -> tuple[bytes, list[int]]:
    """A request already on the socket and its descriptor; BlockingIOError if there is none.

    (``socket.recv_fds`` ignores its ``flags``: MSG_DONTWAIT must reach ``recvmsg`` itself, and
    the socket stays blocking for the answers.)
    """
    fds = array.array("i")
    data, ancillary, _, _ = sock.recvmsg(_MAX_MESSAGE, socket.CMSG_LEN(fds.itemsize), socket.MSG_DONTWAIT)
    for level, kind, payload in ancillary:
        if level == socket.SOL_SOCKET and kind == socket.SCM_RIGHTS:
            fds.frombytes(payload[:len(payload) - len(payload) % fds.itemsize])
    return data, list(fds)


def _reap(sock: socket.socket, children: set[int], block: bool = False) -> None:
    while children:
        try:
            pid, status = os.waitpid(-1, 0 if block else os.WNOHANG)
        except ChildProcessError:
            children.clear()
            return
        if pid == 0:
            return
        children.discard(pid)
        try:
            sock.send(json.dumps({"exit": pid, "code": os.waitstatus_to_exitcode(status)}).encode())
        except OSError:
            pass  # the launcher is gone
        if block:
            return


def _child(sock: socket.socket, output: int, argv: list[str], gate: int, main: Callable[[], None],
           server: int, log: str | None = None) -> None:
    """In the forked agent: its own output (guarded for the ``log`` file, :mod:`dmpc.runtime.output`),
    default signals, tied to the server (pid ``server``), then ``dmpc ARGV`` once ``gate`` (a pipe's
    read end) reports the end of the burst, or the server's end."""
    code = 1
    try:
        sock.close()
        os.read(gate, 1)
        os.close(gate)
        os.dup2(output, 1)
        os.dup2(output, 2)
        os.close(output)
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        # from the first instant, as the command will: a SIGTERM before it installs its own
        # handler must still end it through KeyboardInterrupt (exit 130), not kill it outright
        sigterm_as_interrupt()
        _die_with_parent()
        _name_process(b"dmpc-" + " ".join(argv[:1]).encode())
        if os.getppid() != server:
            os._exit(1)  # the server died before the agent was tied to it (the gate opens then too)
        if log:
            os.environ[LOG_ENV] = log  # the command guards its output with it (dmpc.cli.main)
        sys.argv = ["dmpc", *argv]
        main()
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except KeyboardInterrupt:  # SIGTERM or Ctrl-C before the command could handle it
        code = EXIT_INTERRUPTED
    except BaseException:  # noqa: BLE001 - the traceback goes to the agent's log
        import traceback

        traceback.print_exc()
    finally:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code)

"""Children's output: copied to their log files, and the last lines kept in memory.

The launcher reads every child's stdout and stderr through a pipe rather than letting the
child write its log file itself: when the disk is full or the folder read-only, the child's
last words (the one line that says why it stopped) still reach the launcher, which shows them.
One thread serves every pipe with a selector.
"""
from __future__ import annotations

import os
import selectors
import threading
from collections import deque
from pathlib import Path
from typing import BinaryIO

TAIL_LINES = 20
READ_SIZE = 65536


class _Stream:
    __slots__ = ("name", "log", "log_failed", "lines", "partial")

    def __init__(self, name: str, log_path: Path) -> None:
        self.name = name
        self.lines: deque[str] = deque(maxlen=TAIL_LINES)
        self.partial = b""
        self.log_failed = ""
        self.log: BinaryIO | None
        try:
            self.log = open(log_path, "ab")
        except OSError as exc:
            self.log, self.log_failed = None, exc.strerror or str(exc)

    def feed(self, data: bytes) -> None:
        if self.log is not None:
            try:
                self.log.write(data)
                self.log.flush()
            except OSError as exc:
                self.log_failed = exc.strerror or str(exc)
                self._close_log()
        text = self.partial + data
        *complete, self.partial = text.split(b"\n")
        self.lines.extend(line.decode(errors="replace") for line in complete)

    def finish(self) -> None:
        if self.partial:
            self.lines.append(self.partial.decode(errors="replace"))
            self.partial = b""
        self._close_log()

    def _close_log(self) -> None:
        if self.log is not None:
            try:
                self.log.close()
            except OSError:
                pass
            self.log = None


class LogPump:
    """Reads the output pipes of the children until each closes.

    ``add(name, fd, log_path)`` may be called at any time (a restarted child); ``tail(name)``
    gives its last lines, ``log_failed(name)`` why its log file could not be written ("" if it
    could).
    """

    def __init__(self) -> None:
        self._selector = selectors.DefaultSelector()
        self._streams: dict[str, _Stream] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="log-pump", daemon=True)
        self._thread.start()

    def add(self, name: str, fd: int, log_path: Path) -> None:
        """Read the pipe ``fd`` of child ``name`` into its log file ``log_path`` (a restarted child keeps
        the last lines of the one before)."""
        stream = _Stream(name, log_path)
        with self._lock:
            old = self._streams.get(name)
            if old is not None:
                stream.lines.extend(old.lines)  # a restarted child: keep what the last one said
            self._streams[name] = stream
            self._selector.register(fd, selectors.EVENT_READ, stream)

    def tail(self, name: str, lines: int = 5) -> list[str]:
        """The last ``lines`` lines child ``name`` wrote (none for a child not added)."""
        with self._lock:
            stream = self._streams.get(name)
            if stream is None:
                return []
            shown = list(stream.lines) + ([stream.partial.decode(errors="replace")] if stream.partial else [])
        return [line for line in shown if line.strip()][-lines:]

    def log_failed(self, name: str) -> str:
        """Why child ``name``'s log file could not be written ("" if it could)."""
        stream = self._streams.get(name)
        return "" if stream is None else stream.log_failed

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                empty = not self._selector.get_map()
            if empty:
                self._stop.wait(0.05)
                continue
            for key, _ in self._selector.select(timeout=0.1):
                try:
                    data = os.read(key.fd, READ_SIZE)
                except OSError:
                    data = b""
                with self._lock:
                    if data:
                        key.data.feed(data)
                        continue
                    key.data.finish()
                    self._selector.unregister(key.fd)
                try:
                    os.close(key.fd)
                except OSError:
                    pass

    def close(self, timeout: float = 1.0) -> None:
        """Stop after the pipes still open have been drained for at most ``timeout`` s."""
        end = threading.Event()
        deadline = timeout
        while deadline > 0:
            with self._lock:
                if not self._selector.get_map():
                    break
            end.wait(0.02)
            deadline -= 0.02
        self._stop.set()
        self._thread.join(timeout=1.0)
        with self._lock:
            for key in list(self._selector.get_map().values()):
                key.data.finish()
                try:
                    os.close(key.fd)
                except OSError:
                    pass
            self._selector.close()

"""The fork server of ``dmpc run``: agents forked from one process that imported their modules."""
from __future__ import annotations

import os
import signal
import subprocess

import pytest

from dmpc.runtime.forkserver import ForkServer, ForkServerError
from tests.e2e_helpers import pid_alive, wait_for

pytestmark = pytest.mark.e2e


@pytest.fixture
def server(tmp_path):
    forks = ForkServer(dict(os.environ, PYTHONUNBUFFERED="1"), tmp_path / "forkserver.log")
    yield forks
    forks.close()


def _read_all(fd: int) -> str:
    chunks = []
    while chunk := os.read(fd, 65536):
        chunks.append(chunk)
    os.close(fd)
    return b"".join(chunks).decode(errors="replace")


def _spawn(server: ForkServer, *args: str):
    read_end, write_end = os.pipe()
    try:
        proc = server.spawn(list(args), write_end)
    finally:
        os.close(write_end)
    return proc, read_end


def test_a_forked_command_runs_with_its_own_output_and_exit_code(server):
    proc, out = _spawn(server, "validate", "scenarios/paper.yaml")
    assert proc.wait(timeout=30) == 0
    assert "scenarios/paper.yaml: valid (4 subsystems" in _read_all(out)
    proc, out = _spawn(server, "agent", "scenarios/paper.yaml", "--id", "9", "--startup-timeout", "1")
    assert proc.wait(timeout=30) == 2  # an input error, as with exec
    assert "no subsystem '9'" in _read_all(out)


def test_a_forked_agent_can_be_signalled_and_its_end_is_reported(server):
    proc, out = _spawn(server, "agent", "scenarios/paper.yaml", "--id", "1", "--startup-timeout", "60",
                       "--run-id", "forked")
    assert proc.poll() is None and pid_alive(proc.pid)
    assert wait_for(lambda: open(f"/proc/{proc.pid}/comm").read().strip() == "dmpc-agent", 5)  # named once forked
    proc.send_signal(signal.SIGTERM)  # handled as an interrupt: exit code 130
    assert proc.wait(timeout=30) == 130
    _read_all(out)
    proc, out = _spawn(server, "agent", "scenarios/paper.yaml", "--id", "2", "--startup-timeout", "60",
                       "--run-id", "forked")
    proc.kill()
    assert proc.wait(timeout=30) == -signal.SIGKILL
    assert wait_for(lambda: not pid_alive(proc.pid), 5)
    _read_all(out)


def test_agents_do_not_outlive_a_server_that_dies(server):
    proc, out = _spawn(server, "agent", "scenarios/paper.yaml", "--id", "3", "--startup-timeout", "60",
                       "--run-id", "forked")
    server.proc.kill()
    assert wait_for(lambda: not pid_alive(proc.pid), 15), "the agent outlived its fork server"
    assert proc.wait(timeout=5) is not None
    _read_all(out)
    with pytest.raises(ForkServerError):
        _spawn(server, "validate", "scenarios/paper.yaml")


def test_agents_the_launcher_did_not_stop_are_stopped_when_it_closes_the_server(tmp_path):
    """Interrupted mid-burst, the launcher never learns some agents' pids: closing the server stops them."""
    forks = ForkServer(dict(os.environ, PYTHONUNBUFFERED="1"), tmp_path / "forkserver.log")
    try:
        proc, out = _spawn(forks, "agent", "scenarios/paper.yaml", "--id", "1", "--startup-timeout", "60",
                           "--run-id", "stray")
        assert wait_for(lambda: open(f"/proc/{proc.pid}/comm").read().strip() == "dmpc-agent", 5)
    finally:
        forks.close()
    assert not pid_alive(proc.pid), "an agent outlived the closed fork server"
    assert forks.proc.returncode == 0  # the server ended on its own, it was not killed
    _read_all(out)


def test_a_server_interrupted_while_it_imports_is_ended(tmp_path, monkeypatch):
    started = []
    real_popen = subprocess.Popen

    def popen(*args, **kwargs):
        started.append(real_popen(*args, **kwargs))
        return started[-1]

    def interrupted(self, timeout, wanted):
        raise KeyboardInterrupt

    monkeypatch.setattr(subprocess, "Popen", popen)
    monkeypatch.setattr(ForkServer, "_receive", interrupted)
    with pytest.raises(KeyboardInterrupt):
        ForkServer(dict(os.environ), tmp_path / "forkserver.log")
    assert len(started) == 1 and started[0].poll() is not None, "the fork server was left running"

"""Interrupts in the launcher: children not started yet, a signal during a fork, a second signal
during the shutdown, and what an interrupted run says (small processes only, no Zenoh)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from dmpc.runtime.launcher import Child, interrupted_message, stop_all
from dmpc.terminal.signals import interrupts_deferred, interrupts_held, sigterm_as_interrupt
from tests.e2e_helpers import DMPC, ROOT, pid_alive, wait_for


@pytest.fixture
def launcher_signals():
    """The launcher's handlers for the test; pytest's are put back afterwards."""
    saved = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    hook = sys.unraisablehook
    sigterm_as_interrupt()
    yield
    for sig, handler in saved.items():
        signal.signal(sig, handler)
    sys.unraisablehook = hook


def test_stopping_skips_children_not_started_yet(tmp_path):
    """An interrupt while the fork server starts: the agents have no process yet."""
    started = Child("plant", [sys.executable, "-c", "import time; time.sleep(60)"], tmp_path / "plant.log")
    started.proc = subprocess.Popen(started.cmd)
    waiting = [Child(f"agent-{i}", [], tmp_path / f"agent-{i}.log", agents=(str(i),)) for i in (1, 2)]
    stop_all([started, *waiting], grace=2.0)
    assert started.proc.returncode is not None and not pid_alive(started.proc.pid)
    assert all(child.proc is None and not child.running for child in waiting)


def test_a_signal_during_a_deferred_block_is_raised_at_its_end(launcher_signals):
    done = []
    with pytest.raises(KeyboardInterrupt):
        with interrupts_deferred():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)  # the handler has run by now
            done.append("the block went on")
    assert done == ["the block went on"]
    with interrupts_deferred():  # no signal: no interrupt
        pass


DROPPED = textwrap.dedent("""
    import gc, os, signal, subprocess, sys, time, weakref
    from dmpc.terminal.signals import interrupts_deferred, raise_if_interrupted, sigterm_as_interrupt

    sigterm_as_interrupt()
    where = sys.argv[1]
    child = None
    try:
        if where == "weakref":  # Python drops what a weakref callback raises
            class Thing:
                pass

            thing = Thing()
            ref = weakref.ref(thing, lambda _: (os.kill(os.getpid(), signal.SIGINT), time.sleep(0.05)))
            del thing
            gc.collect()
        else:  # Python drops what a fork hook raises
            os.register_at_fork(after_in_parent=lambda: (os.kill(os.getpid(), signal.SIGINT), time.sleep(0.05)))
            if where == "fork, deferred":
                with interrupts_deferred():
                    child = subprocess.Popen(["sleep", "30"], preexec_fn=lambda: None)
            else:
                child = subprocess.Popen(["sleep", "30"], preexec_fn=lambda: None)
        print("went on", flush=True)
        raise_if_interrupted()
        print("not interrupted", flush=True)
    except KeyboardInterrupt:
        print("interrupted", "with the child known" if child is not None else "", flush=True)
    finally:
        if child is not None:
            child.kill()
            child.wait()
""")


@pytest.mark.parametrize("where, said", [
    ("weakref", ["went on", "interrupted"]),  # dropped, then taken up at the next check
    ("fork", ["went on", "interrupted with the child known"]),
    ("fork, deferred", ["interrupted with the child known"]),  # raised as the block ends
])
def test_an_interrupt_python_drops_is_not_lost(where, said):
    res = subprocess.run([sys.executable, "-c", DROPPED, where], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert [line.strip() for line in res.stdout.splitlines()] == said, res.stdout + res.stderr
    assert res.stderr == ""  # no "Exception ignored ... KeyboardInterrupt" either


def test_without_the_command_handlers_nothing_is_raised_later():
    """A program that imported dmpc keeps its own handlers: no check raises on its behalf."""
    probe = ("import os, signal, time\n"
             "from dmpc.terminal.signals import raise_if_interrupted\n"
             "signal.signal(signal.SIGINT, lambda *a: None)\n"
             "os.kill(os.getpid(), signal.SIGINT); time.sleep(0.05)\n"
             "raise_if_interrupted(); print('fine')\n")
    res = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert res.stdout.strip() == "fine", res.stderr


def test_signals_are_ignored_while_held_and_handled_again_after(launcher_signals):
    with interrupts_held():
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)
    with pytest.raises(KeyboardInterrupt):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.5)


def test_an_interrupted_run_says_whether_any_step_was_completed():
    before = interrupted_message(0)
    assert before.startswith("interrupted before the first step") and "completed steps" not in before
    assert interrupted_message(1).startswith("interrupted after 1 step:")
    assert interrupted_message(7).startswith("interrupted after 7 steps:")
    assert "the completed steps are in the run folder" in interrupted_message(7)


def test_importing_dmpc_leaves_the_signal_handlers_alone():
    """Only the ``dmpc`` command handles signals during its imports; a program that imports dmpc
    (a notebook, a script) keeps its own."""
    probe = "import signal, dmpc.core.system; print(signal.getsignal(signal.SIGTERM) == signal.SIG_DFL, " \
            "signal.getsignal(signal.SIGINT) is signal.default_int_handler)"
    res = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert res.stdout.split() == ["True", "True"], res.stderr


def maps(pid: int, name: str) -> bool:
    """True once process ``pid`` has mapped a file whose path holds ``name`` (a loaded extension)."""
    try:
        with open(f"/proc/{pid}/maps") as fh:
            return name in fh.read()
    except OSError:
        return False


COMMANDS = {"module": DMPC, "script": [str(Path(sys.executable).parent / "dmpc")]}  # python -m dmpc.cli; dmpc


@pytest.mark.parametrize("command, sig", [("module", signal.SIGTERM), ("module", signal.SIGINT),
                                          ("script", signal.SIGTERM)])
def test_the_command_interrupted_while_it_imports_says_so_and_exits_130(command, sig):
    proc = subprocess.Popen(COMMANDS[command] + ["validate", "scenarios/paper.yaml"], cwd=ROOT,
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # numpy's core is mapped: the imports are under way, and take most of a second more
        assert wait_for(lambda: maps(proc.pid, "_multiarray_umath"), timeout=30, interval=0.001)
        os.kill(proc.pid, sig)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130 and err.strip() == "error: interrupted", err

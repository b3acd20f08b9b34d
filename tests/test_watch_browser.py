"""The live view in a real browser (headless Chromium): a live ``dmpc run --watch`` and the replays
of finished run folders (the paper's example, a run with setpoints, an event-triggered run).

Chromium and its driver come from Debian (``apt-get install chromium chromium-driver``; .ci/run
installs them). Without them these tests are skipped, except in CI, where they fail.
With ``DMPC_WATCH_SCREENSHOTS=DIR`` the tests save what the browser showed into DIR
(docs/figures/watch-live.png, watch-end.png, watch-replay.png, watch-setpoints.png and
watch-trigger.png were made so).
"""
from __future__ import annotations

import contextlib
import json
import os
import queue
import re
import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tests.e2e_helpers import DMPC, ROOT
from tests.helpers.browser import chromium, class_text, class_texts, model, require_chromium, wait_until

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


def start(*args: str) -> subprocess.Popen:
    return subprocess.Popen(DMPC + list(args), cwd=ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()


class Lines:
    """The lines a process prints, read on a thread (so a test can wait for one with a timeout)."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.lines: queue.Queue = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=lambda: [self.lines.put(line) for line in proc.stdout], daemon=True).start()

    def wait_for(self, pattern: str, timeout: float) -> re.Match:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.1)
            except queue.Empty:
                continue
            self.seen.append(line)
            found = re.search(pattern, line)
            if found:
                return found
        pytest.fail(f"no line matching {pattern!r} within {timeout} s; output:\n{''.join(self.seen)}")


def screenshot(driver, name: str) -> None:
    folder = os.environ.get("DMPC_WATCH_SCREENSHOTS")
    if folder:
        Path(folder).mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(str(Path(folder) / name))


@contextlib.contextmanager
def replaying(driver, folder: Path, last_step: int):
    """``dmpc watch`` of the run folder, its page open in ``driver`` with the slider at the run's last step."""
    proc = start("watch", str(folder))
    try:
        url = Lines(proc).wait_for(r"live view: (http://127\.0\.0\.1:\d+/)", 60).group(1)
        driver.get(url)
        wait_until(lambda: model(driver, "step-slider", "m.value") == last_step, 30, what="the slider at the end")
        yield proc
    finally:
        stop(proc)


def test_live_view_follows_a_run_and_ends_with_its_summary(tmp_path):
    """``dmpc run --watch`` on the paper's example, 80 steps in real time (0.15 s a step, 5 % of
    the messages lost, so that some plans miss their deadline; 12 s, so that a browser that a busy
    machine lets redraw only every few seconds still sees the run going): the page's step counter advances
    while the run goes, and at the end the page shows summary.json's final cost, verdict and
    fallbacks per agent; its agent table, counted from the steps the page received over the
    bus, has the same fallbacks. Ctrl-C then stops the page and the command."""
    require_chromium()
    out = tmp_path / "run"
    with chromium() as driver:  # first: the browser takes seconds to start on a small machine
        proc = start("run", "scenarios/paper.yaml", "--watch", "--out", str(out), "--quiet", "--steps", "80",
                     "--set", "options.mode=realtime", "--set", "options.dt=0.15", "--loss", "0.05", "--seed", "3")
        try:
            lines = Lines(proc)
            url = lines.wait_for(r"live view: (http://127\.0\.0\.1:\d+/)$", 60).group(1)
            driver.get(url)
            running: list[int] = []
            seen = []
            deadline = time.monotonic() + 90
            while time.monotonic() < deadline:
                count, state = class_text(driver, "dmpc-step"), class_text(driver, "dmpc-run-state")
                seen.append((count, state))
                if state == "running" and (not running or int(count) != running[-1]):
                    running.append(int(count))
                    if running[-1] >= 20 and len(running) > 1 and running[-2] < 20:
                        screenshot(driver, "watch-live.png")
                if state and state.startswith("ended"):
                    break
                time.sleep(0.3)
            assert len(running) >= 2 and running == sorted(running) and running[0] < 80, (running, seen[-20:])
            lines.wait_for(r"stays up; Ctrl-C to stop", 30)  # the run is over and its summary complete
            summary = json.loads((out / "summary.json").read_text())
            per_agent = summary["fallbacks_per_agent"]
            assert sum(per_agent.values()) > 0, "no fallback: the comparison below would show little"
            wait_until(lambda: "summary from the run folder" in (model(driver, "summary", "m.text") or ""), 10,
                       what="summary.json on the page")  # with the agents' reports, which the bus's lacks
            expected_J = f"{summary['J'][-1]:.6g}"
            wait_until(lambda: class_text(driver, "dmpc-final-J") == expected_J, 10,
                       what=f"final J {expected_J} on the page")
            assert class_text(driver, "dmpc-step") == str(summary["steps"])
            assert class_text(driver, "dmpc-cost") == f"{summary['closed_loop_cost']:.6g}"
            assert class_text(driver, "dmpc-verdict") == summary.get("verdict", "finished")
            assert class_text(driver, "dmpc-fallbacks-per-agent") == ", ".join(f"{a}: {n}" for a, n in per_agent.items())
            assert class_texts(driver, "dmpc-agent") == list(per_agent)
            assert class_texts(driver, "dmpc-fallbacks") == [str(n) for n in per_agent.values()]
            screenshot(driver, "watch-end.png")
            proc.send_signal(signal.SIGINT)
            assert proc.wait(timeout=20) == 0
        finally:
            stop(proc)
    assert "exited with code" not in "".join(lines.seen)


def test_replay_shows_the_numbers_of_trajectory_npz_at_a_chosen_step(paper_simulated):
    """``dmpc watch RUN_FOLDER``: moving the slider (with the keyboard, as a person would) to a
    step shows the run up to that step; the plots' data and the readout are trajectory.npz's.
    The replay button plays the run on from there."""
    require_chromium()
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    npz = np.load(paper_simulated / "trajectory.npz")
    with chromium() as driver:
        with replaying(driver, paper_simulated, 30) as proc:
            handle = driver.execute_script(
                "function find(n) { if (n.classList && n.classList.contains('noUi-handle')) return n;"
                " for (const c of [...(n.shadowRoot ? n.shadowRoot.childNodes : []), ...n.childNodes]) {"
                " const h = find(c); if (h) return h; } return null; } return find(document.body);")
            driver.execute_script("arguments[0].focus()", handle)
            ActionChains(driver).send_keys(Keys.ARROW_LEFT * 18).perform()
            k = 12
            wait_until(lambda: class_text(driver, "dmpc-readout-k") == str(k), 20, what=f"the readout at k = {k}")
            screenshot(driver, "watch-replay.png")
            for i, name in enumerate(["1", "2", "3", "4"]):
                states = model(driver, f"states-{name}", "[m.data.k, m.data.x1, m.data.x2].map(a => Array.from(a))")
                inputs = model(driver, f"inputs-{name}", "[m.data.k, m.data.u1].map(a => Array.from(a))")
                assert list(states[0]) == list(range(k + 1)) and list(inputs[0]) == list(range(k + 1))
                np.testing.assert_array_equal(np.column_stack(states[1:]), npz["x"][:k + 1, 2 * i:2 * i + 2])
                np.testing.assert_array_equal(inputs[1], npz["u"][:k + 1, i])
                shown = class_texts(driver, "dmpc-x")[i]
                assert shown == ", ".join(f"{v:.6g}" for v in npz["x"][k, 2 * i:2 * i + 2])
            np.testing.assert_array_equal(model(driver, "cost", "Array.from(m.data.J)"), npz["J"][:k + 1])
            np.testing.assert_array_equal(model(driver, "terminal", "Array.from(m.data.beta)"), npz["beta"][:k + 1])
            assert class_text(driver, "dmpc-J") == f"{npz['J'][k]:.6g}"
            assert class_text(driver, "dmpc-beta") == f"{npz['beta'][k]:.6g}"
            driver.execute_script("Bokeh.documents[0].get_model_by_name('play').active = true")
            wait_until(lambda: model(driver, "step-slider", "m.value") >= k + 5, 20, what="the replay advancing")
            proc.send_signal(signal.SIGINT)
            assert proc.wait(timeout=10) == 0


def test_replay_of_a_run_with_setpoints_draws_its_targets(tmp_path):
    """``dmpc watch`` on the night of scenarios/rooms.yaml (12 h of its setpoints): each room's plots hold
    the targets applied and the setpoints of trajectory.npz, their lines and legend entries shown;
    the readout has the target and the setpoint at the chosen step."""
    require_chromium()
    import dmpc

    folder = tmp_path / "rooms"
    dmpc.simulate("scenarios/rooms.yaml", out=folder, steps=144)  # the night: setback, then the warm-up
    npz = np.load(folder / "trajectory.npz")
    with chromium(height=1700) as driver:
        with replaying(driver, folder, 144) as proc:
            for i in range(5):
                name = f"room{i + 1}"
                targets = model(driver, f"targets-{name}",
                                "['k', 'target_x1', 'target_x2', 'setpoint_x1', 'target_u1']"
                                ".map(c => Array.from(m.data[c]))")
                assert targets[0] == list(range(144))
                np.testing.assert_array_equal(np.column_stack(targets[1:3]), npz["target"][:, 2 * i:2 * i + 2])
                np.testing.assert_array_equal(targets[3], npz["setpoint"][:, 2 * i])
                np.testing.assert_array_equal(targets[4], npz["target_u"][:, i])
                for what, kind in (("target", "x"), ("setpoint", "x"), ("target", "u")):
                    assert model(driver, f"legend-{what}-{kind}-{name}", "m.visible") is True, (what, kind, name)
                assert model(driver, f"legend-setpoint-u-{name}", "m.visible") is False  # no input requested
            k = 50  # 02:10: room5 warms up, the others are still set back
            driver.execute_script(f"Bokeh.documents[0].get_model_by_name('step-slider').value = {k}")
            expected = ", ".join(f"{v:.6g}" for v in npz["target"][k, :2])
            wait_until(lambda: class_text(driver, "dmpc-target") == expected, 10, what="the target in the readout")
            assert class_texts(driver, "dmpc-setpoint")[4] == f"{npz['setpoint'][k, 8]:.6g}, -"
            screenshot(driver, "watch-setpoints.png")
            proc.send_signal(signal.SIGINT)
            assert proc.wait(timeout=10) == 0


PLAN_TITLES = """
function find(node, out) {
  if (node.classList && node.classList.contains('dmpc-plan')) out.push(node.getAttribute('title') || '');
  for (const child of [...(node.shadowRoot ? node.shadowRoot.childNodes : []), ...node.childNodes]) find(child, out);
  return out;
}
return find(document.body, []);
"""
"""The tooltips of the agent table's plan cells, in page order."""


def test_replay_of_an_event_triggered_run_shows_who_solved_and_why(tmp_path):
    """``dmpc watch`` on the paper's example with ``options.trigger: event``: the agent table says,
    per agent at the chosen step, whether it kept its plan or solved and why (steps.jsonl's status
    and solve_reason, the reason's meaning as the cell's tooltip), and counts its QP solves and
    plans kept up to that step; at the end, summary.json's counts."""
    require_chromium()
    import dmpc
    from dmpc.scenario import load_scenario

    folder = tmp_path / "event"
    dmpc.simulate(load_scenario(ROOT / "scenarios" / "paper.yaml", {"options.trigger": "event"}), out=folder, steps=40)
    steps = [json.loads(line) for line in (folder / "steps.jsonl").read_text().splitlines()]
    summary = json.loads((folder / "summary.json").read_text())
    with chromium() as driver:
        with replaying(driver, folder, 40) as proc:
            wait_until(lambda: class_text(driver, "dmpc-solves-keeps") is not None, 10, what="the summary")
            assert class_text(driver, "dmpc-solves-keeps") == f"{summary['solves']} / {summary['keeps']}"
            assert class_texts(driver, "dmpc-plan") == ["kept"] * 4  # the run has settled: nobody solves
            assert class_texts(driver, "dmpc-solves") == [str(n) for n in summary["solves_per_agent"].values()]
            assert class_texts(driver, "dmpc-keeps") == [str(n) for n in summary["keeps_per_agent"].values()]
            k = max(k for k, line in enumerate(steps) if "kept" in line["status"] and "changed" in line["solve_reason"])
            driver.execute_script(f"Bokeh.documents[0].get_model_by_name('step-slider').value = {k}")
            wait_until(lambda: class_text(driver, "dmpc-readout-k") == str(k), 10, what=f"the readout at k = {k}")
            line = steps[k]
            expected = ["kept" if s == "kept" else f"solved: {r}" for s, r in zip(line["status"], line["solve_reason"])]
            wait_until(lambda: class_texts(driver, "dmpc-plan") == expected, 10, what=f"the plans at k = {k}")
            titles = driver.execute_script(PLAN_TITLES)
            assert [bool(t) for t in titles] == [s != "kept" for s in line["status"]]
            assert all("neighbour's plan changed" in t for t, r in zip(titles, line["solve_reason"]) if r == "changed")
            solves = [sum(step["rounds"] for step in steps[:k + 1] if step["status"][i] not in ("kept", "missed"))
                      for i in range(4)]
            keeps = [sum(step["status"][i] == "kept" for step in steps[:k + 1]) for i in range(4)]
            assert class_texts(driver, "dmpc-solves") == [str(n) for n in solves]
            assert class_texts(driver, "dmpc-keeps") == [str(n) for n in keeps]
            screenshot(driver, "watch-trigger.png")
            proc.send_signal(signal.SIGINT)
            assert proc.wait(timeout=10) == 0

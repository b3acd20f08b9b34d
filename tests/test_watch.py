"""The live view without a browser: telemetry, the run's state, the run folder reader, the page's
documents, the observer's access control and the ``dmpc watch`` command line.

The browser tests are in test_watch_browser.py; a run with and without an observer in
test_watch_e2e.py; the observer's rights on a secure bus in test_watch_security.py.
"""
from __future__ import annotations

import json
import math
import shutil
import signal
import socket
import subprocess
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from dmpc.watch.folder import FolderFeed, folder_meta
from dmpc.watch.meta import RunMeta, meta_json
from dmpc.watch.state import RunState, StepRow
from dmpc.watch.telemetry import TelemetryError, decode, encode, step_line
from dmpc.watch.views import AgentHistory, agent_table, graph_tables, link_state, summary_html, verdict_of
from tests.e2e_helpers import DMPC, ROOT, wait_for
from tests.helpers.cli import call, one_error_line

PAPER = ROOT / "scenarios" / "paper.yaml"


@pytest.fixture(scope="module")
def prepared():
    from dmpc.scenario import load_scenario
    from dmpc.setup import prepare

    return prepare(load_scenario(PAPER))


@pytest.fixture(scope="module")
def recorded(tmp_path_factory, prepared):
    """A simulated run of the paper's example: (run folder, its StepRecords)."""
    from dmpc.records.session import RunRecorder
    from dmpc.runtime.inprocess import simulate

    out = tmp_path_factory.mktemp("watch") / "run"
    records = []
    with RunRecorder(out, prepared, show_progress=False) as recorder:
        def on_step(rec):
            recorder.on_step(rec)
            records.append(rec)

        simulate(prepared, on_step)
        recorder.complete(runtime="in-process")
    return out, records


def lines(folder: Path) -> list[dict]:
    return [json.loads(line) for line in (folder / "steps.jsonl").read_text().splitlines()]


def fed(folder: Path, steps: int | None = None) -> RunState:
    """A RunState with the folder's description and its first ``steps`` steps (all by default)."""
    state = RunState(f"run folder {folder}")
    state.set_meta(folder_meta(folder))
    for line in lines(folder)[:steps]:
        assert state.add_step(line)
    return state


# ------------------------------------------------------------------------------ the run's description
def test_meta_carries_names_bounds_and_graph(prepared):
    meta = RunMeta.from_json(json.loads(json.dumps(meta_json(prepared, "r-1"))))
    assert meta.names == ["1", "2", "3", "4"] and meta.run_id == "r-1" and meta.steps == 30 and meta.horizon == 10
    assert meta.edges == (("1", "2"), ("2", "3"), ("3", "4"))
    sub = meta.subsystems[1]
    assert sub.state_names == ("x1", "x2") and sub.input_names == ("u1",)
    assert sub.input_lower == (-2.5,) and sub.input_upper == (2.5,) and sub.input_is_box
    assert all(math.isnan(v) for v in sub.state_lower + sub.state_upper)  # no state constraints
    assert [s.start for s in meta.state_slices()] == [0, 2, 4, 6]
    assert meta.link_fault("1", "2") == {"delay_ms": 0.0, "jitter_ms": 0.0, "loss": 0.0}


def test_a_polytope_is_shown_by_its_bounding_box(prepared):
    data = json.loads(json.dumps(meta_json(prepared, "r")))
    # |u1| <= 2 as a polytope of two rows, and a state polytope x1 + x2 <= 1, -x1 <= 3, -x2 <= 4
    data["subsystems"][0]["input"] = {"H": [[2.0], [-1.0]], "lower": [None, None], "upper": [4.0, 2.0]}
    data["subsystems"][0]["state"] = {"H": [[1.0, 1.0], [-1.0, 0.0], [0.0, -1.0]], "lower": [None] * 3,
                                      "upper": [1.0, 3.0, 4.0]}
    sub = RunMeta.from_json(data).subsystems[0]
    assert not sub.input_is_box
    assert sub.input_lower == pytest.approx((-2.0,)) and sub.input_upper == pytest.approx((2.0,))
    assert sub.state_lower == pytest.approx((-3.0, -4.0)) and sub.state_upper == pytest.approx((5.0, 4.0))
    with pytest.raises(ValueError, match="meta version"):
        RunMeta.from_json({**data, "meta_version": 99})
    with pytest.raises(ValueError, match="not a run description"):
        RunMeta.from_json({"meta_version": 1})


# ---------------------------------------------------------------------------------------- telemetry
def test_a_step_message_holds_the_steps_jsonl_line(recorded):
    """Telemetry and the run folder say the same about every step (one format, two writers)."""
    folder, records = recorded
    assert [json.loads(json.dumps(step_line(rec))) for rec in records] == lines(folder)


def test_telemetry_messages_are_checked(recorded):
    _, records = recorded
    payload = encode("step", "r-1", step=step_line(records[3]), plant={"alive": ["1"]})
    msg = decode(payload, "r-1")
    assert msg["type"] == "step" and msg["step"]["k"] == 3 and msg["plant"] == {"alive": ["1"]}
    assert "NaN" not in payload.decode()  # strict JSON: NaN is null
    for bad, why in [(payload, "run 'r-1', not 'r-2'"), (b"\xff\x00", "not JSON"), (b"[1, 2]", "not a telemetry"),
                     (encode("plan", "r-2"), "not a telemetry"), (encode("step", "r-2", step={}), "without step, plant"),
                     (encode("end", "r-2"), "without summary"), (b" " * (17 << 20), "over the limit")]:
        with pytest.raises(TelemetryError, match=why):
            decode(bad, "r-2")


def test_the_plant_hands_every_step_to_its_telemetry_after_recording_it(prepared):
    from dmpc.runtime.inprocess import build_run

    recorded, order = [], []

    class Telemetry:
        def step(self, rec, node):
            assert recorded and recorded[-1] is rec  # the run folder has it first
            order.append((rec.k, sorted(node.alive)))

    run = build_run(prepared, recorded.append)
    run.coordinator.telemetry = Telemetry()
    run.bus.run(until=lambda: run.coordinator.finished, timeout=60)
    assert [k for k, _ in order] == list(range(30)) and order[0][1] == ["1", "2", "3", "4"]


def test_telemetry_reaches_an_observer_only_while_one_listens(recorded, prepared):
    """Over a real Zenoh session: nothing is encoded without a subscriber; an observer that
    connects gets the description, every step and the summary."""
    from dmpc.bus import keys
    from dmpc.bus.session import free_tcp_port, session_config
    from dmpc.bus.zenoh_bus import ZenohBus
    from dmpc.watch.observer import BusObserver
    from dmpc.watch.telemetry import ENCODING, KINDS, Telemetry

    folder, records = recorded

    class Node:  # what the telemetry reads of the plant
        alive, ready = {"1", "2"}, {"1"}
        coordinator = type("C", (), {"duplicates": 2})()
        rejects = type("R", (), {"counts": {"3": 1}, "reasons": {"stale": 1}})()

    port = free_tcp_port()
    bus = ZenohBus(session_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"]))
    publishers = {kind: bus.broadcast(keys.telemetry("r-1", kind), ENCODING) for kind in KINDS}
    telemetry = Telemetry(publishers, "r-1", meta_json(prepared, "r-1"), meta_every=0.2)
    observer = None
    try:
        for rec in records[:3]:
            telemetry.step(rec, Node)
        time.sleep(0.8)
        assert telemetry.sent == 0  # nobody listened: nothing was encoded or sent
        state = RunState("bus", "r-1")
        observer = BusObserver(state, "r-1", [f"tcp/127.0.0.1:{port}"])
        observer.start()
        assert wait_for(lambda: state.meta is not None and telemetry.watched, 10), state.connection
        for rec in records:  # a step every few ms, as a plant gives them (a burst can outrun a loaded machine)
            telemetry.step(rec, Node)
            time.sleep(0.003)
        summary = json.loads((folder / "summary.json").read_text())
        telemetry.summary(summary)
        assert wait_for(lambda: state.steps == len(records) and state.summary is not None, 10), state.steps
        snap = state.read(-1, 0, 0)
        assert [r.k for r in snap.step_rows] == list(range(30)) and len(snap.state_rows) == 31
        assert snap.plant == {"alive": ["1", "2"], "ready": ["1"], "rejected": {"3": 1},
                              "rejected_reasons": {"stale": 1}, "duplicates": 2}
        assert snap.summary == summary and snap.summary_from == "bus" and snap.dropped == 0
        assert snap.state_rows[-1].x == records[-1].x_next.tolist()
    finally:
        telemetry.close()
        if observer is not None:
            observer.close()
        bus.close()


def test_telemetry_goes_through_the_bus_and_a_fault_injector_and_not_the_in_memory_bus(prepared):
    """The coordinator's telemetry is made by its bus: a Zenoh bus (seen through the fault
    injector, which does not touch observers) gives one; the in-memory bus, which nothing outside
    the run can watch, gives none."""
    from dmpc.bus.faults import PLANT_PROCESS, FaultPlan, FaultyBus, LinkFault
    from dmpc.bus.memory import MemoryBus
    from dmpc.bus.session import free_tcp_port, session_config
    from dmpc.bus.zenoh_bus import ZenohBus
    from dmpc.watch.telemetry import open_telemetry

    assert MemoryBus().broadcast("dmpc/r/telemetry/step", "application/json") is None
    assert open_telemetry(MemoryBus(), "r", prepared) is None
    bus = ZenohBus(session_config(mode="peer", listen=[f"tcp/127.0.0.1:{free_tcp_port()}"]))
    try:
        faulty = FaultyBus(bus, PLANT_PROCESS, FaultPlan(default=LinkFault(0.0, 0.0, 0.5), seed=1))
        telemetry = open_telemetry(faulty, "r", prepared)
        assert telemetry is not None and telemetry.watched is False
        telemetry.close()
    finally:
        bus.close()


# ----------------------------------------------------------------------------------- the run's state
def test_state_keeps_steps_in_order_and_starts_readers_over_on_a_late_one(recorded):
    folder, _ = recorded
    all_lines = lines(folder)
    state = RunState("x")
    state.set_meta(folder_meta(folder))
    for line in all_lines[:3] + all_lines[5:7]:
        state.add_step(line)
    snap = state.read(-1, 0, 0)
    assert [r.k for r in snap.step_rows] == [0, 1, 2, 5, 6]
    assert [r.k for r in snap.state_rows] == [0, 1, 2, 3, 5, 6, 7]  # x(k+1) comes with step k
    later = state.read(snap.epoch, len(snap.state_rows), len(snap.step_rows))
    assert later.step_rows == [] and later.epoch == snap.epoch
    assert state.add_step(all_lines[3]) and not state.add_step(all_lines[3])  # a gap filled; a copy ignored
    after = state.read(snap.epoch, len(snap.state_rows), len(snap.step_rows))
    assert after.epoch != snap.epoch and [r.k for r in after.step_rows] == [0, 1, 2, 3, 5, 6]
    bad = dict(all_lines[8], x=[1.0, 2.0])  # the wrong dimension for this run
    assert not state.add_step(bad) and not state.add_step({"k": "x"})
    snap = state.read(after.epoch, 0, 0)
    assert snap.dropped == 2 and "x has 2 entries" in snap.problems[0]


def test_folder_feed_reads_a_run_folder_while_it_is_written(tmp_path, recorded):
    """A half-written last line is left for the next read; summary.json is read when it
    appears and again when it is replaced."""
    folder, _ = recorded
    live = tmp_path / "live"
    live.mkdir()
    for name in ("scenario.yaml", "design.json"):
        shutil.copy(folder / name, live / name)
    raw = (folder / "steps.jsonl").read_bytes()
    lines_end = [n for n, byte in enumerate(raw) if byte == ord("\n")]
    cut = lines_end[10] - 40  # in the middle of step 10's line (the 11th)
    (live / "steps.jsonl").write_bytes(raw[:cut])
    state = RunState(f"run folder {live}")
    feed = FolderFeed(live, state)
    feed.poll()
    assert state.meta is not None and state.steps == 10 and state.summary is None
    with open(live / "steps.jsonl", "ab") as fh:
        fh.write(raw[cut:])
    feed.poll()
    assert state.steps == 30 and state.read(-1, 0, 0).dropped == 0
    summary = json.loads((folder / "summary.json").read_text())
    (live / "summary.json").write_text(json.dumps(summary))
    feed.poll()
    assert state.summary == summary and state.summary_from == "run folder"
    (live / "summary.json").write_text(json.dumps({**summary, "agents": {"1": {"solves": 1}}}) + "\n")
    feed.poll()
    assert state.summary["agents"] == {"1": {"solves": 1}}


def test_folder_feed_for_a_live_run_reads_steps_only_to_fill_gaps_at_the_end(tmp_path, recorded):
    folder = shutil.copytree(recorded[0], tmp_path / "run")
    (folder / "summary.json").rename(tmp_path / "summary.json")
    state = RunState("x")
    feed = FolderFeed(folder, state, steps=False)
    feed.poll()
    assert state.meta is not None and state.steps == 0
    (tmp_path / "summary.json").rename(folder / "summary.json")
    feed.poll()
    assert state.steps == 30 and state.summary is not None


def test_a_folder_that_is_not_a_run_is_refused(tmp_path):
    from dmpc.watch.folder import FolderError

    with pytest.raises(FolderError, match="not a run folder"):
        folder_meta(tmp_path)


# ------------------------------------------------------------------------------------ what is shown
def step(k: int, fallback=(False,) * 4, reasons=("",) * 4, note: str = "") -> StepRow:
    return StepRow(k=k, u=[0.0] * 4, J=1.0, status=["missed" if f else "solved" for f in fallback],
                   fallback=list(fallback), fallback_reason=list(reasons), solve_time=[1e-4] * 4,
                   latency=[2e-4] * 4, step_time=1e-3, note=note)


def test_agent_table_counts_fallbacks_rejoins_and_drops(prepared):
    meta = RunMeta.from_json(meta_json(prepared, "r"))
    steps = [step(0), step(1, (False, True, False, False), ("", "missed", "", "")),
             step(2, (False, True, False, False), ("", "lost", "", ""), note="agent 2 lost"),
             step(3, note="agent 2 back"), step(4, (True, False, False, False), ("qp infeasible", "", "", ""))]
    history = AgentHistory(meta)
    history.add(steps)
    assert history.fallbacks(5) == [1, 2, 0, 0] and history.fallbacks(2) == [0, 1, 0, 0]
    assert history.alive(3)["2"] is False and history.alive(4)["2"] is True and history.rejoins(5)["2"] == 1
    summary = {"rejected": {"3": 4}, "agents": {"3": {"rejected": {"plant": 2}, "rejected_reasons": {"stale": 2}}}}
    table = agent_table(meta, history, 5, steps[4], None, {"rejected": {"1": 9}}, summary)
    assert table["fallbacks"] == [1, 2, 0, 0] and table["rejoins"] == [0, 1, 0, 0]
    assert table["state"] == ["fallback", "ok", "ok", "ok"]
    assert table["dropped_coordinator"] == [0, 0, 4, 0]  # the summary's counts, once there
    assert table["dropped_agent"] == ["-", "-", "2 (stale: 2)", "-"]
    table = agent_table(meta, history, 2, steps[1], {"3": False}, {"rejected": {"1": 9}}, None)
    assert table["state"] == ["ok", "late", "lost", "ok"] and table["alive"] == ["yes", "yes", "no", "yes"]
    assert table["dropped_coordinator"] == [9, 0, 0, 0]
    nodes, edges = graph_tables(meta, table["state"])
    assert nodes["name"] == ["coordinator", "1", "2", "3", "4"]
    states = dict(zip(edges["link"], edges["state"]))
    assert states["1 – 2 (plans)"] == "late" and states["2 – 3 (plans)"] == "down" and states["coordinator – 4 (release/plan)"] == "up"
    assert link_state("ok", "waiting") == "idle"


def test_summary_shows_the_verdict_and_its_reasons():
    summary = {"verdict": "failed", "failures": [{"kind": "incomplete", "message": "3 of 30 steps"}],
               "warnings": [{"kind": "fallbacks", "message": "2 fallback(s)"}], "steps": 3, "J": [5.0, 2.0, None],
               "fallbacks_per_agent": {"1": 2}, "closed_loop_cost": 12.5}
    text = summary_html(summary, "run folder")
    assert "failed" in text and "incomplete: 3 of 30 steps" in text and "fallbacks: 2 fallback(s)" in text
    assert ">2<" in text and "1: 2" in text and "12.5" in text
    assert verdict_of({"aborted": "interrupted"}) == "aborted" and verdict_of({}) == "finished"


def test_page_follows_the_run_and_replays_any_step(recorded):
    """One document as a browser tab gets it: it follows the steps as they come, and the slider
    shows the run up to the chosen step, with the numbers of trajectory.npz."""
    from bokeh.document import Document

    from dmpc.watch.page import WatchPage

    folder, _ = recorded
    npz = np.load(folder / "trajectory.npz")
    state = fed(folder, 12)
    page = WatchPage(Document(), state, live=True)
    states = page.doc.get_model_by_name("states-2")
    assert page.slider.value == 12 and page.slider.end == 12 and states.data["k"][-1] == 12
    for line in lines(folder)[12:]:
        state.add_step(line)
    page.tick()
    assert page.slider.value == 30 and page.follow
    np.testing.assert_array_equal(np.column_stack([states.data["x1"], states.data["x2"]]), npz["x"][:, 2:4])
    page.slider.value = 7
    assert not page.follow
    inputs = page.doc.get_model_by_name("inputs-3")
    cost = page.doc.get_model_by_name("cost")
    terminal = page.doc.get_model_by_name("terminal")
    np.testing.assert_array_equal(states.data["x1"], npz["x"][:8, 2])
    np.testing.assert_array_equal(inputs.data["u1"], npz["u"][:8, 2])
    np.testing.assert_array_equal(cost.data["J"], npz["J"][:8])
    np.testing.assert_array_equal(terminal.data["beta"], npz["beta"][:8])
    assert "dmpc-readout-k'>7<" in page.readout.text and f"{npz['J'][7]:.6g}" in page.readout.text
    page.slider.value = 30
    assert page.follow and len(cost.data["J"]) == 30 and "verdict" in page.summary.text


def test_a_page_that_gets_the_description_after_some_steps_counts_them_too(recorded):
    from bokeh.document import Document

    from dmpc.watch.page import WatchPage

    folder, _ = recorded
    state = RunState("bus")
    page = WatchPage(Document(), state, live=True)
    for line in lines(folder):
        if line["k"] in (3, 5):  # agent 2 missed these
            line["fallback"][1], line["fallback_reason"][1], line["status"][1] = True, "missed", "missed"
        state.add_step(line)
    page.tick()
    assert not page.built and "waiting for the run's description" in page.counter.text
    state.set_meta(folder_meta(folder))
    page.tick()
    assert page.table["fallbacks"] == [0, 2, 0, 0] and "dmpc-step'>30<" in page.counter.text
    page.slider.value = 5
    assert page.table["fallbacks"] == [0, 2, 0, 0] and page.table["state"] == ["ok", "late", "ok", "ok"]
    page.slider.value = 4
    assert page.table["fallbacks"] == [0, 1, 0, 0] and page.table["state"] == ["ok"] * 4


# --------------------------------------------------------------------------------- access control
def test_the_observer_role_may_subscribe_and_nothing_else(prepared):
    from dmpc.bus import keys
    from dmpc.security.acl import scenario_access_control
    from tests.test_security import allowed

    acl = scenario_access_control(prepared.system, "r")
    can = lambda flow, message, key: allowed(acl, "observer", flow, message, key)
    telemetry = keys.telemetry("r", "step")
    assert can("ingress", "declare_subscriber", telemetry)
    assert can("ingress", "declare_liveliness_subscriber", keys.alive("r", "agent-1"))
    assert can("egress", "put", telemetry)
    protocol = [keys.plan("r", "1"), keys.release("r"), keys.ready("r", "1"), keys.control("r")]
    for key in protocol + [telemetry]:
        assert not can("ingress", "put", key), key
        assert not can("ingress", "delete", key), key
    for key in protocol:
        assert not can("ingress", "declare_subscriber", key) and not can("egress", "put", key), key
    assert not can("ingress", "liveliness_token", keys.alive("r", "observer"))
    assert not can("ingress", "declare_subscriber", keys.telemetry("other", "step"))
    assert allowed(acl, "coordinator", "ingress", "put", telemetry)
    assert not allowed(acl, "agent-1", "ingress", "put", telemetry)


# ----------------------------------------------------------------------------------- the command line
def test_watch_needs_a_folder_or_a_live_run(monkeypatch, capsys, tmp_path):
    code, _, err = call(monkeypatch, capsys, "watch")
    assert code == 2 and "--connect" in one_error_line(err)
    code, _, err = call(monkeypatch, capsys, "watch", "--connect", "tcp/127.0.0.1:7447")
    assert code == 2 and "--run-id" in one_error_line(err)
    code, _, err = call(monkeypatch, capsys, "watch", str(tmp_path))
    assert code == 2 and "not a run folder" in one_error_line(err)
    code, _, err = call(monkeypatch, capsys, "watch", "--connect", "tcp/nowhere", "--run-id", "r")
    assert code == 2 and "bad Zenoh endpoint" in one_error_line(err)


def test_watch_serves_the_page_and_bokehjs_on_loopback_and_stops_on_ctrl_c(recorded):
    """The page and BokehJS come from this process (no internet), on 127.0.0.1 only; Ctrl-C
    stops the server and the process exits 0."""
    import psutil

    folder, _ = recorded
    proc = subprocess.Popen(DMPC + ["watch", str(folder)], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith("live view: http://127.0.0.1:"), line + proc.stdout.read()
        url = line.split()[2]
        page = urllib.request.urlopen(url, timeout=10).read().decode()
        script = next(part.split('"')[0] for part in page.split('src="') if part.startswith("/static/js/bokeh.min.js"))
        assert "Bokeh" in urllib.request.urlopen(url.rstrip("/") + script, timeout=10).read(200_000).decode()
        port = int(url.rstrip("/").rsplit(":", 1)[1])
        listening = [c.laddr for c in psutil.Process(proc.pid).net_connections("tcp") if c.status == "LISTEN"]
        assert [a.ip for a in listening if a.port == port] == ["127.0.0.1"], listening
        with socket.socket() as other:  # the page is not reachable on another address of this host
            other.settimeout(1)
            hosts = {a.address for addrs in psutil.net_if_addrs().values() for a in addrs
                     if a.family == socket.AF_INET and not a.address.startswith("127.")}
            for host in hosts:
                assert other.connect_ex((host, port)) != 0
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


# ------------------------------------------------------------------------------------------ setpoints
SETPOINTS = [{"at": 0, "subsystem": "1", "x": [1.0, None]}, {"at": 15, "subsystem": "1", "x": [-0.5, None]}]


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    """A simulated run of the paper's example with setpoints on x_11: (run folder, its StepRecords)."""
    import dmpc
    from dmpc.records.session import RunRecorder
    from dmpc.runtime.inprocess import simulate
    from dmpc.setup import prepare

    prepared = prepare(dmpc.load_scenario(PAPER, setpoints=SETPOINTS))
    out = tmp_path_factory.mktemp("watch-setpoints") / "run"
    records = []
    with RunRecorder(out, prepared, show_progress=False) as recorder:
        def on_step(rec):
            recorder.on_step(rec)
            records.append(rec)

        simulate(prepared, on_step)
        recorder.complete(runtime="in-process")
    return out, records


def test_a_step_message_of_a_run_with_setpoints_carries_its_target_and_setpoint(tracked):
    folder, records = tracked
    msg = decode(encode("step", "r-1", step=step_line(records[20]), plant={}), "r-1")["step"]
    npz = np.load(folder / "trajectory.npz")
    np.testing.assert_array_equal(msg["target"], npz["target"][20])
    assert msg["setpoint"] == [-0.5] + [None] * 7 and len(msg["target_u"]) == len(msg["setpoint_u"]) == 4
    live = RunState("bus")
    live.set_meta(folder_meta(folder))
    assert live.add_step(msg)
    bad = dict(msg, target=msg["target"][:3])
    state = fed(folder, 0)
    assert not state.add_step(bad) and "target has 3 entries, the run 8" in state.problems[0]


def test_page_draws_the_targets_and_setpoints_of_a_replayed_run(tracked):
    """A run folder with setpoints: each subsystem's targets go to its plots; the setpoint lines
    show only where a component was requested; the readout has the target at k."""
    from bokeh.document import Document

    from dmpc.watch.page import WatchPage

    folder, _ = tracked
    npz = np.load(folder / "trajectory.npz")
    page = WatchPage(Document(), fed(folder), live=False)
    for i, name in enumerate(["1", "2", "3", "4"]):
        targets = page.doc.get_model_by_name(f"targets-{name}")
        assert targets.data["k"] == list(range(30))
        np.testing.assert_array_equal(np.column_stack([targets.data["target_x1"], targets.data["target_x2"]]),
                                      npz["target"][:, 2 * i:2 * i + 2])
        np.testing.assert_array_equal(targets.data["target_u1"], npz["target_u"][:, i])
        np.testing.assert_array_equal(targets.data["setpoint_x1"], npz["setpoint"][:, 2 * i])
    shown = {(i, kind, what): models[0].visible for i, kind, what, models in page.tracking}
    assert all(shown[i, kind, "target"] for i in range(4) for kind in "xu")
    assert [key for key, visible in shown.items() if key[2] == "setpoint" and visible] == [(0, "x", "setpoint")]
    page.slider.value = 20
    assert "dmpc-target'>-0.5, " in page.readout.text and "dmpc-setpoint'>-0.5, -<" in page.readout.text


def test_page_of_a_run_without_setpoints_shows_no_targets(recorded):
    from bokeh.document import Document

    from dmpc.watch.page import WatchPage

    folder, _ = recorded
    page = WatchPage(Document(), fed(folder), live=False)
    assert page.tracking and not any(model.visible for *_, models in page.tracking for model in models)
    assert page.doc.get_model_by_name("targets-1").data["k"] == []  # nothing sent to the browser
    assert "dmpc-target" not in page.readout.text


def test_a_page_that_follows_a_run_shows_targets_from_the_first_step_that_has_them(tracked):
    """A request taken while the run goes on: the steps before it have no targets, and the page
    starts drawing them when the first one arrives, aligned with the steps already shown."""
    from bokeh.document import Document

    from dmpc.watch.page import WatchPage

    folder, _ = tracked
    npz = np.load(folder / "trajectory.npz")
    untracked = [{key: v for key, v in line.items() if key not in ("setpoint", "setpoint_u", "reference",
                                                                    "reference_u", "target", "target_u", "governor")}
                 for line in lines(folder)[:10]]
    state = fed(folder, 0)
    for line in untracked:
        state.add_step(line)
    page = WatchPage(Document(), state, live=True)
    targets = page.doc.get_model_by_name("targets-1")
    assert not page.tracked and targets.data["k"] == []
    for line in lines(folder)[10:]:
        state.add_step(line)
    page.tick()
    assert page.tracked and targets.data["k"] == list(range(30))
    x1 = np.array(targets.data["target_x1"])
    assert np.isnan(x1[:10]).all()
    np.testing.assert_array_equal(x1[10:], npz["target"][10:, 0])
    page.slider.value = 5
    assert len(targets.data["k"]) == 6 and len(page.doc.get_model_by_name("cost").data["k"]) == 6


# -------------------------------------------------------------------------------------- event trigger
@pytest.fixture(scope="module")
def triggered(tmp_path_factory) -> Path:
    """The run folder of the paper's example simulated with ``options.trigger: event`` (its
    summary with the solves and keeps per agent, as ``dmpc simulate`` writes it)."""
    import dmpc
    from dmpc.scenario import load_scenario

    out = tmp_path_factory.mktemp("watch-trigger") / "run"
    dmpc.simulate(load_scenario(PAPER, {"options.trigger": "event"}), out=out)
    return out


def test_the_description_and_the_steps_of_a_triggered_run_carry_the_trigger(triggered, recorded):
    folder = triggered
    assert folder_meta(folder).trigger == "event" and folder_meta(recorded[0]).trigger == "always"
    older = {key: value for key, value in meta_json(_prepared(folder), "r").items()
             if key != "trigger"}
    assert RunMeta.from_json(older).trigger == "always"  # a description from before the trigger
    msg = decode(encode("step", "r-1", step=lines(folder)[17], plant={}), "r-1")["step"]
    assert len(msg["solve_reason"]) == 4
    state = fed(folder, 0)
    assert state.add_step(msg)
    bad = dict(lines(folder)[18], solve_reason=["", "cost"])
    assert not state.add_step(bad) and "solve_reason has 2 entries, the run 4" in state.problems[0]


def _prepared(folder: Path):
    from dmpc.scenario import load_scenario
    from dmpc.setup import prepare

    return prepare(load_scenario(folder / "scenario.yaml"))


def test_plan_text_says_whether_an_agent_solved_or_kept_its_plan_and_why():
    from dmpc.watch.views import REASONS, plan_text

    assert plan_text("kept", "") == "kept" and plan_text("solved", "changed") == "solved: changed"
    assert plan_text("solved", "") == "solved" and plan_text("missed", "") == "-"
    assert plan_text("infeasible", "cost") == "solved: cost"  # it solved; its QP failed
    from dmpc.agents.trigger import REASONS as TRIGGER_REASONS

    assert set(REASONS) == set(TRIGGER_REASONS)  # every reason the trigger gives has its meaning


def test_agent_table_of_a_triggered_run_shows_who_solved_and_why_and_counts_as_the_summary(triggered):
    """At each step, per agent: kept, or solved and why (steps.jsonl's status and solve_reason);
    QP solves (every round of k = 0) and plans kept up to the step, at the end summary.json's."""
    from bokeh.document import Document

    from dmpc.watch.page import WatchPage
    from dmpc.watch.views import plan_text

    folder = triggered
    summary = json.loads((folder / "summary.json").read_text())
    steps = lines(folder)
    state = fed(folder)
    state.set_summary(summary, "run folder")
    page = WatchPage(Document(), state, live=False)
    assert page.table["solves"] == list(summary["solves_per_agent"].values())
    assert page.table["keeps"] == list(summary["keeps_per_agent"].values())
    assert "event trigger" in page.header.text
    assert f"{summary['solves']} / {summary['keeps']}" in page.summary.text
    reasons = ", ".join(f"{r}: {c}" for r, c in summary["solve_reasons"].items())
    assert f"why agents solved up to this step: {reasons}" in page.agents.text
    page.slider.value = 0
    assert page.table["plan"] == [plan_text("solved", r) for r in steps[0]["solve_reason"]]
    assert page.table["solves"] == [steps[0]["rounds"]] * 4 and page.table["keeps"] == [0] * 4
    changed = next(k for k, line in enumerate(steps) if "kept" in line["status"] and "changed" in line["solve_reason"])
    page.slider.value = changed
    line = steps[changed]
    assert page.table["plan"] == ["kept" if s == "kept" else f"solved: {r}"
                                  for s, r in zip(line["status"], line["solve_reason"])]
    kept = [sum(s == "kept" for s in (step["status"][i] for step in steps[:changed + 1])) for i in range(4)]
    assert page.table["keeps"] == kept
    assert "title='a neighbour&#x27;s plan changed its feed-forward" in page.agents.text
    assert page.table["solve_ms"][line["status"].index("kept")] == "-"


def test_agent_table_of_a_run_without_trigger_has_no_trigger_columns(recorded):
    from bokeh.document import Document

    from dmpc.watch.page import WatchPage

    folder, _ = recorded
    page = WatchPage(Document(), fed(folder), live=False)
    assert "plan" not in page.table and "dmpc-plan" not in page.agents.text and "QP solves" not in page.agents.text
    assert "event trigger" not in page.header.text

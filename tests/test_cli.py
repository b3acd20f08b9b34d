"""The command line: exit codes, one-line errors, the design report and the simulate records."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.e2e_helpers import run_cli
from tests.helpers.cli import call

BAD = Path(__file__).parent / "data" / "bad_scenarios"


@pytest.mark.parametrize("path", sorted(BAD.iterdir()), ids=lambda p: p.name)
def test_every_bad_scenario_exits_2_with_one_line(monkeypatch, capsys, path):
    code, out, err = call(monkeypatch, capsys, "validate", str(path))
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err


@pytest.mark.parametrize("name, field", [("wrong_matrix_shape.yaml", "subsystems[1].A"),
                                         ("python_tag.yaml", "python"), ("q_not_psd.yaml", ".Q")])
def test_bad_scenario_through_a_real_process_names_the_field(name, field):
    res = run_cli("validate", str(BAD / name))
    assert res.returncode == 2
    assert res.stderr.startswith("error: ") and "Traceback" not in res.stderr
    assert field in res.stderr


@pytest.mark.parametrize("overrides, expected", [
    (["--set", "subsystems.1.K=[[0.7452, 1.113]]"], "unstable"),
    (["--set", "terminal.beta0=2.0"], "exceeds sigma"),
    (["--set", "options.tube=robust",
      *[f"--set=subsystems.{i}.revision_bound={{state: [2.8, 2.8], input: [2.5]}}" for i in range(4)]], "empty"),
])
def test_failed_design_exits_2_with_figures(monkeypatch, capsys, overrides, expected):
    code, _, err = call(monkeypatch, capsys, "design", "scenarios/paper.yaml", *overrides)
    assert code == 2
    assert expected in err and err.startswith("error: ") and len(err.strip().splitlines()) == 1
    assert any(ch.isdigit() for ch in err)  # the figures that show why


def test_unknown_option_is_a_usage_error(monkeypatch, capsys):
    code, _, err = call(monkeypatch, capsys, "simulate", "scenarios/paper.yaml", "--bogus")
    assert code == 2 and "bogus" in err


def test_bad_override_syntax_exits_2(monkeypatch, capsys):
    code, _, err = call(monkeypatch, capsys, "validate", "scenarios/paper.yaml", "--set", "horizon")
    assert code == 2 and err.startswith("error: ")


def test_unknown_agent_id_exits_2(monkeypatch, capsys):
    code, _, err = call(monkeypatch, capsys, "agent", "scenarios/paper.yaml", "--id", "9", "--startup-timeout", "1")
    assert code == 2 and "--id" in err and "1, 2, 3, 4" in err


def test_design_json_reference_figures(monkeypatch, capsys):
    code, out, _ = call(monkeypatch, capsys, "design", "scenarios/paper.yaml", "--json")
    assert code == 0
    d = json.loads(out)
    assert d["omega_rows"] == 22 and d["t_star"] == 2
    assert d["sigma0"] == pytest.approx(1.3454, abs=1e-3)
    assert d["rho"] == pytest.approx(0.697, abs=1e-3)
    assert d["lyapunov_margin"] == pytest.approx(-0.350, abs=1e-3)
    assert len(d["K"]) == 4 and len(d["P"]) == 4


def test_design_report_is_readable(monkeypatch, capsys):
    code, out, _ = call(monkeypatch, capsys, "design", "scenarios/paper.yaml")
    assert code == 0
    for text in ("X^f rows", "22", "sigma(alpha0)", "1.3454", "rho(A+BK)", "0.6971"):
        assert text in out


def test_simulate_writes_the_records_with_the_reference_figures(tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    code, stdout, _ = call(monkeypatch, capsys, "simulate", "scenarios/paper.yaml", "--out", str(out), "--quiet")
    assert code == 0 and f"run folder: {out}" in stdout
    assert {p.name for p in out.iterdir()} >= {"scenario.yaml", "design.json", "steps.jsonl", "trajectory.npz",
                                              "summary.json"}
    s = json.loads((out / "summary.json").read_text())
    assert s["steps"] == 30 and s["feasible"] and s["fallbacks"] == 0
    assert s["max_abs_u"] <= 2.5 + 1e-7
    assert s["final_state_norm_inf"] < 1e-5
    np.testing.assert_allclose(s["J"][:4], [102.05, 54.48, 21.60, 8.36], atol=0.05)
    for key in ("S", "beta"):
        assert isinstance(s[key], list)
    t = np.load(out / "trajectory.npz")
    assert t["x"].shape == (31, 8) and t["u"].shape == (30, 4)
    np.testing.assert_allclose(t["u"][0], [-2.5, -2.5, 0.489, -0.472], atol=1e-3)
    np.testing.assert_allclose(t["x"][1], [3.293, 1.606, 2.008, 1.397, 1.068, -1.711, -1.283, 2.755], atol=1e-3)
    lines = (out / "steps.jsonl").read_text().splitlines()
    assert len(lines) == 30 and json.loads(lines[0])["k"] == 0
    # the resolved scenario loads again and designs the same
    code, _, _ = call(monkeypatch, capsys, "validate", str(out / "scenario.yaml"))
    assert code == 0


def test_simulate_steps_override(tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    code, _, _ = call(monkeypatch, capsys, "simulate", "scenarios/chain.yaml", "--set", "family.M=3", "--steps", "5",
                      "--out", str(out), "--quiet")
    assert code == 0
    assert json.loads((out / "summary.json").read_text())["steps"] == 5


def test_simulate_refuses_a_used_folder(tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    assert call(monkeypatch, capsys, "simulate", "scenarios/paper.yaml", "--out", str(out), "--quiet",
                "--steps", "2")[0] == 0
    code, _, err = call(monkeypatch, capsys, "simulate", "scenarios/paper.yaml", "--out", str(out), "--quiet")
    assert code == 2 and "already holds a run" in err


def test_schema_command_prints_json_schema(monkeypatch, capsys):
    code, out, _ = call(monkeypatch, capsys, "scenario", "schema")
    assert code == 0
    schema = json.loads(out)
    assert "properties" in schema and "subsystems" in schema["properties"]


SETPOINT = ["setpoint", "--connect", "tcp/127.0.0.1:7447", "--run-id", "r", "--subsystem", "1"]


@pytest.mark.parametrize("args, expected", [
    (["setpoint", "--run-id", "r", "--subsystem", "1", "--x", "1,null"], "--connect: the coordinator's endpoint"),
    (["setpoint", "--connect", "tcp/127.0.0.1:7447", "--subsystem", "1", "--x", "1"], "--run-id: the id of the run"),
    (["setpoint", "--connect", "tcp/127.0.0.1:7447", "--run-id", "r", "--x", "1"], "--subsystem: the name"),
    (SETPOINT, "give --x or --u"),
    (SETPOINT + ["--x", "1,warm"], "--x: expected a number or null (free), got 'warm'"),
    (SETPOINT + ["--x", "1,inf"], "--x[1]: expected a finite number"),
    (SETPOINT + ["--x", "1", "--x", "2"], "--x: by position, give one --x with every value"),
    (SETPOINT + ["--x", "Ta=1,2"], "--x: give every value by position (1.0,null) or every one by name"),
    (SETPOINT + ["--x", "Ta=1", "--x", "Ta=2"], "--x: 'Ta' is given twice"),
    (SETPOINT + ["--u", "heat=1"], "--u: values by name need --scenario FILE"),
    (SETPOINT + ["--x", "Ta=1", "--scenario", "scenarios/paper.yaml"],
     "--x: names need the subsystem's 'states' (subsystem '1' names none)"),
    (SETPOINT + ["--x", "1", "--scenario", "scenarios/paper.yaml"],
     "--x: expected 2 entries (n_i = 2 states of subsystem '1'), got 1"),
    (["setpoint", "--connect", "tcp/127.0.0.1:7447", "--run-id", "r", "--subsystem", "9", "--x", "1",
      "--scenario", "scenarios/paper.yaml"], "no subsystem '9' in scenario 'paper' (subsystems: 1, 2, 3, 4)"),
    (SETPOINT + ["--x", "1,null", "--connect", "tcp/nowhere"], "bad Zenoh endpoint"),
    (SETPOINT + ["--x", "1,null", "--run-id", "a/b"], "run id 'a/b' must be"),
    (SETPOINT + ["--x", "1,null", "--name", "two words"], "sender name 'two words' must be"),
    (SETPOINT + ["--x", "1,null", "--tls", "no-such-dir"], "--tls no-such-dir: no such directory"),
])
def test_setpoint_flags_that_cannot_work_exit_2_with_one_line(monkeypatch, capsys, args, expected):
    code, _, err = call(monkeypatch, capsys, *args)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    assert expected in lines[0]


@pytest.mark.parametrize("request_args", [
    ["--subsystem", "1", "--x", "1,null"],
    ["--subsystem", "room3", "--x", "Ta=1.5", "--u", "P=null", "--scenario", "scenarios/rooms.yaml"],
])
def test_setpoint_without_a_coordinator_says_so_and_exits_1(monkeypatch, capsys, request_args):
    """A Zenoh peer listens, but no coordinator of the run subscribes: nothing answers."""
    import zenoh

    from dmpc.bus.session import free_tcp_port, session_config

    port = free_tcp_port()
    with zenoh.open(session_config(listen=[f"tcp/127.0.0.1:{port}"])):
        code, out, err = call(monkeypatch, capsys, "setpoint", "--connect", f"tcp/127.0.0.1:{port}", "--run-id",
                              "nobody", *request_args, "--timeout", "0.5")
    assert code == 1 and out == ""
    assert err.strip() == (f"not authorised or no run listening: no answer from the coordinator of run nobody at "
                           f"tcp/127.0.0.1:{port} within 0.5 s (under TLS only the operator certificate may send "
                           "setpoints; check the endpoint and the run id, which dmpc run prints)")


def test_setpoint_to_an_endpoint_where_nothing_listens_exits_1(monkeypatch, capsys):
    from dmpc.bus.session import free_tcp_port

    code, _, err = call(monkeypatch, capsys, *SETPOINT[:2], f"tcp/127.0.0.1:{free_tcp_port()}", *SETPOINT[3:],
                        "--x", "1,null", "--timeout", "0.5")
    assert code == 1 and err.startswith("error: cannot open a Zenoh client session") and "Traceback" not in err

"""Certificates, access control, the ``dmpc certs`` command, drop counting, and the absence of
unsafe deserialisation anywhere in the package (no processes, no Zenoh sessions)."""
from __future__ import annotations

import ast
import importlib
import inspect
import ipaddress
import json
import logging
import stat
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
import zenoh
from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from dmpc.bus.session import TlsFiles, session_config
from dmpc.security.acl import access_control, read_acl, scenario_access_control
from dmpc.security.certs import make_certificates, make_run_security
from dmpc.security.files import node_security, role_names, tls_files
from dmpc.security.rejects import MAX_MAGNITUDE, UNKNOWN, Rejections, clearly_in_range, magnitude, out_of_range
from tests.helpers.cli import call, one_error_line
from tests.helpers.tls import ca_key_files

ROOT = Path(__file__).resolve().parents[1]
PAPER = str(ROOT / "scenarios" / "paper.yaml")
ROLES = ["router", "coordinator", "plant", "agent-1", "agent-2", "agent-3", "agent-4", "sensor-1", "sensor-2", "sensor-3",
         "sensor-4", "observer", "operator"]
# the paper's chain 1-2-3-4: N_I without I
NEIGHBOURS = {"1": ["2"], "2": ["1", "3"], "3": ["2", "4"], "4": ["3"]}
PACKAGE_DIRS = ["dmpc", "agents", "plant", "bus"]


@pytest.fixture(scope="module")
def prepared():
    from dmpc.scenario import load_scenario
    from dmpc.setup import prepare

    return prepare(load_scenario(PAPER))


@pytest.fixture(scope="module")
def cert_dir(tmp_path_factory, prepared):
    directory = tmp_path_factory.mktemp("certs") / "tls"
    roles = make_run_security(directory, prepared.system, hosts=["127.0.0.1", "localhost", "10.1.2.3", "plant.lan"])
    assert roles == ROLES
    return directory


def load_cert(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def common_name(cert: x509.Certificate) -> str:
    return cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value


# -------------------------------------------------------------------------------- certificates
def test_every_role_gets_a_certificate_and_key(cert_dir):
    assert role_names(["1", "2", "3", "4"]) == ROLES
    names = {p.name for p in cert_dir.iterdir()}
    expected = {"ca.pem", "acl.json"} | {f"{r}.pem" for r in ROLES} | {f"{r}.key" for r in ROLES}
    assert names == expected


def test_no_file_of_the_directory_holds_the_ca_key(cert_dir):
    assert ca_key_files(cert_dir, cert_dir / "ca.pem") == []
    assert ca_key_files(cert_dir.parent, cert_dir / "ca.pem") == []  # not kept anywhere when no place is given


def test_the_ca_key_is_kept_apart_and_owner_only_when_asked(tmp_path, prepared):
    from dmpc.security.certs import default_ca_key_path

    directory = tmp_path / "certs"
    ca_key = default_ca_key_path(directory)
    assert ca_key == tmp_path / "certs-ca.key"
    make_run_security(directory, prepared.system, ca_key=ca_key)
    assert ca_key_files(tmp_path, directory / "ca.pem") == ["certs-ca.key"]
    assert ca_key_files(directory, directory / "ca.pem") == []
    assert stat.S_IMODE(ca_key.stat().st_mode) == 0o600
    assert stat.S_IMODE(directory.stat().st_mode) == 0o700
    with pytest.raises(ValueError, match="already holds a CA key"):  # a kept CA key is not overwritten by mistake
        make_run_security(tmp_path / "again", prepared.system, ca_key=ca_key)
    assert not (tmp_path / "again").exists()


def test_common_name_is_the_role_and_the_ca_signed_it(cert_dir):
    ca = load_cert(cert_dir / "ca.pem")
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for role in ROLES:
        cert = load_cert(cert_dir / f"{role}.pem")
        assert common_name(cert) == role
        cert.verify_directly_issued_by(ca)  # raises if the CA did not sign it
        assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
        usage = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        assert {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH} <= set(usage)


def test_certificates_carry_the_hosts_as_subject_alternative_names(cert_dir):
    for role in ROLES:
        san = load_cert(cert_dir / f"{role}.pem").extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert set(san.get_values_for_type(x509.IPAddress)) == {ipaddress.ip_address("127.0.0.1"),
                                                                 ipaddress.ip_address("10.1.2.3")}
        assert set(san.get_values_for_type(x509.DNSName)) == {"localhost", "plant.lan"}


def test_private_keys_are_readable_by_their_owner_only(cert_dir):
    keys = sorted(cert_dir.glob("*.key"))
    assert len(keys) == len(ROLES)
    for path in keys:
        assert stat.S_IMODE(path.stat().st_mode) == 0o600, path.name


def test_forced_renewal_resets_a_widened_key_mode(tmp_path, prepared):
    make_run_security(tmp_path, prepared.system)
    (tmp_path / "plant.key").chmod(0o644)
    with pytest.raises(ValueError, match="already holds certificates"):
        make_run_security(tmp_path, prepared.system)
    make_run_security(tmp_path, prepared.system, force=True)
    assert stat.S_IMODE((tmp_path / "plant.key").stat().st_mode) == 0o600


def test_another_ca_does_not_verify(tmp_path, cert_dir):
    other = make_certificates(tmp_path / "other", ["agent-1"])["agent-1"]
    with pytest.raises((InvalidSignature, ValueError)):  # its signature does not verify (ValueError: another name)
        load_cert(Path(other.cert)).verify_directly_issued_by(load_cert(cert_dir / "ca.pem"))


def test_node_security_finds_a_role_and_names_what_is_missing(tmp_path, cert_dir):
    files, acl = node_security(cert_dir, "agent-2")
    assert files == TlsFiles(cert_dir / "ca.pem", cert_dir / "agent-2.pem", cert_dir / "agent-2.key")
    assert acl == json.loads((cert_dir / "acl.json").read_text())
    with pytest.raises(ValueError, match=r"no agent-9\.pem for role 'agent-9'.*dmpc certs"):
        tls_files(cert_dir, "agent-9")
    with pytest.raises(ValueError, match="no such directory"):
        node_security(tmp_path / "missing", "plant")


# ------------------------------------------------------------------------------ access control
def allowed(acl: dict, cn: str, flow: str, message: str, key: str) -> bool:
    """Zenoh's decision for a message from (ingress) or to (egress) the holder of ``cn``."""
    subjects = {s["id"] for s in acl["subjects"] if cn in s.get("cert_common_names", [])}
    rules = {r["id"]: r for r in acl["rules"]}
    for policy in acl["policies"]:
        if not subjects & set(policy["subjects"]):
            continue
        for rule in (rules[r] for r in policy["rules"]):
            if flow in rule["flows"] and message in rule["messages"] and any(
                    zenoh.KeyExpr(k).includes(zenoh.KeyExpr(key)) for k in rule["key_exprs"]):
                if rule["permission"] == "allow":
                    return True
    return acl["default_permission"] == "allow"


def test_acl_file_structure(cert_dir):
    acl = read_acl(cert_dir)
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert {s["id"]: s["cert_common_names"] for s in acl["subjects"]} == {r: [r] for r in ROLES}
    rule_ids = {r["id"] for r in acl["rules"]}
    assert len(rule_ids) == len(acl["rules"])  # unique ids
    for policy in acl["policies"]:
        assert set(policy["rules"]) <= rule_ids and len(policy["subjects"]) == 1
    for rule in acl["rules"]:
        assert rule["permission"] == "allow" and set(rule["flows"]) <= {"ingress", "egress"}
        assert all(k.startswith("dmpc/*/") for k in rule["key_exprs"])  # any run of this scenario
    session_config(acl=acl)  # Zenoh accepts it


@pytest.mark.parametrize("agent", ["1", "2", "3", "4"])
def test_an_agent_may_publish_only_its_own_keys(cert_dir, agent):
    acl = read_acl(cert_dir)
    cn = f"agent-{agent}"
    for other in NEIGHBOURS:
        mine = other == agent
        assert allowed(acl, cn, "ingress", "put", f"dmpc/r/plan/{other}") is mine
        assert allowed(acl, cn, "ingress", "put", f"dmpc/r/ready/{other}") is mine
        assert allowed(acl, cn, "ingress", "liveliness_token", f"dmpc/r/alive/agent-{other}") is mine
    assert not allowed(acl, cn, "ingress", "put", "dmpc/r/control")
    assert not allowed(acl, cn, "ingress", "put", "dmpc/r/release")
    assert not allowed(acl, cn, "ingress", "liveliness_token", "dmpc/r/alive/plant")
    assert not allowed(acl, cn, "ingress", "delete", f"dmpc/r/plan/{agent}")
    assert not allowed(acl, cn, "ingress", "put", "other/key")


@pytest.mark.parametrize("agent", ["1", "2", "3", "4"])
def test_an_agent_subscribes_and_receives_only_the_release_and_its_neighbours_plans(cert_dir, agent):
    acl = read_acl(cert_dir)
    cn = f"agent-{agent}"
    for flow, message in (("ingress", "declare_subscriber"), ("egress", "put")):
        assert allowed(acl, cn, flow, message, "dmpc/r/release")
        assert allowed(acl, cn, flow, message, "dmpc/r/control")
        for other in NEIGHBOURS:
            assert allowed(acl, cn, flow, message, f"dmpc/r/plan/{other}") is (other in NEIGHBOURS[agent])
            assert not allowed(acl, cn, flow, message, f"dmpc/r/release/{other}")
            assert not allowed(acl, cn, flow, message, f"dmpc/r/ready/{other}")
    assert allowed(acl, cn, "ingress", "declare_liveliness_subscriber", "dmpc/r/alive/*")


def test_coordinator_plant_router_and_strangers(cert_dir):
    acl = read_acl(cert_dir)
    for key in ("dmpc/r/release", "dmpc/r/control", "dmpc/r/inputs", "dmpc/r/plan/2"):  # plans: relayed as the star's router
        assert allowed(acl, "coordinator", "ingress", "put", key)
    assert not allowed(acl, "coordinator", "ingress", "put", "dmpc/r/ready/1")
    assert allowed(acl, "coordinator", "ingress", "declare_subscriber", "dmpc/r/plan/*")
    assert allowed(acl, "coordinator", "ingress", "declare_subscriber", "dmpc/r/state/*")
    # the plant publishes its state and nothing else; a sensor only its own subsystem's
    assert allowed(acl, "plant", "ingress", "put", "dmpc/r/state/plant")
    for key in ("dmpc/r/release", "dmpc/r/control", "dmpc/r/plan/1", "dmpc/r/ready/1", "dmpc/r/inputs",
                "dmpc/r/state/sensor-1"):
        assert not allowed(acl, "plant", "ingress", "put", key)
    assert allowed(acl, "plant", "ingress", "declare_subscriber", "dmpc/r/inputs")
    assert allowed(acl, "sensor-2", "ingress", "put", "dmpc/r/state/sensor-2")
    assert not allowed(acl, "sensor-2", "ingress", "put", "dmpc/r/state/sensor-1")
    assert not allowed(acl, "sensor-2", "ingress", "put", "dmpc/r/state/plant")
    assert allowed(acl, "router", "ingress", "put", "dmpc/r/ready/1")
    assert allowed(acl, "router", "egress", "put", "dmpc/r/plan/1")
    for message in ("put", "declare_subscriber", "liveliness_token"):
        assert not allowed(acl, "intruder", "ingress", message, "dmpc/r/plan/1")
        assert not allowed(acl, "intruder", "egress", message, "dmpc/r/release")


def test_only_the_operator_may_request_setpoints_and_only_the_coordinator_takes_them(cert_dir):
    acl = read_acl(cert_dir)
    for sender in ("operator", "cli", "scada"):  # any sender name under the operator's certificate
        assert allowed(acl, "operator", "ingress", "put", f"dmpc/r/setpoint/{sender}")
        assert allowed(acl, "operator", "ingress", "declare_subscriber", f"dmpc/r/setpoint-answer/{sender}")
        assert allowed(acl, "operator", "egress", "put", f"dmpc/r/setpoint-answer/{sender}")
        assert allowed(acl, "coordinator", "ingress", "declare_subscriber", f"dmpc/r/setpoint/{sender}")
        assert allowed(acl, "coordinator", "egress", "put", f"dmpc/r/setpoint/{sender}")
        assert allowed(acl, "coordinator", "ingress", "put", f"dmpc/r/setpoint-answer/{sender}")
        for role in ("plant", "sensor-1", "agent-1", "agent-2", "observer", "intruder"):
            assert not allowed(acl, role, "ingress", "put", f"dmpc/r/setpoint/{sender}"), role
            assert not allowed(acl, role, "egress", "put", f"dmpc/r/setpoint-answer/{sender}"), role
        assert not allowed(acl, "operator", "ingress", "put", f"dmpc/r/setpoint-answer/{sender}")
    for key in ("dmpc/r/release", "dmpc/r/control", "dmpc/r/inputs", "dmpc/r/plan/1", "dmpc/r/ready/1",
                "dmpc/r/state/plant", "dmpc/r/telemetry/step"):
        assert not allowed(acl, "operator", "ingress", "put", key), key
        assert not allowed(acl, "operator", "egress", "put", key), key
    assert not allowed(acl, "operator", "ingress", "liveliness_token", "dmpc/r/alive/operator")
    assert allowed(acl, "operator", "ingress", "declare_liveliness_subscriber", "dmpc/r/alive/*")


def test_only_the_operator_may_ask_for_a_setpoint_by_query_and_only_the_coordinator_answers(cert_dir):
    """A request sent as a query: only the operator's gets in (any other role's ends unanswered);
    the coordinator's queryable is declared to every role, and its replies reach the operator."""
    acl = read_acl(cert_dir)
    for sender in ("cli", "scada"):
        key = f"dmpc/r/setpoint/{sender}"
        assert allowed(acl, "operator", "ingress", "query", key)
        assert allowed(acl, "operator", "egress", "reply", key)
        assert allowed(acl, "coordinator", "egress", "query", key)
        assert allowed(acl, "coordinator", "ingress", "declare_queryable", key)
        assert allowed(acl, "coordinator", "ingress", "reply", key)
        for role in ("plant", "sensor-1", "agent-1", "agent-2", "observer", "coordinator", "intruder"):
            assert not allowed(acl, role, "ingress", "query", key), role
        for role in ("plant", "sensor-1", "agent-1", "observer", "operator"):
            assert allowed(acl, role, "egress", "declare_queryable", key), role  # they see it: their query ends
            assert not allowed(acl, role, "ingress", "declare_queryable", key), role
        assert not allowed(acl, "intruder", "egress", "declare_queryable", key)
    for key in ("dmpc/r/release", "dmpc/r/plan/1", "dmpc/r/state/plant", "dmpc/r/setpoint-answer/cli"):
        assert not allowed(acl, "operator", "ingress", "query", key), key
        assert not allowed(acl, "coordinator", "ingress", "declare_queryable", key), key


def test_acl_bound_to_one_run(prepared):
    acl = scenario_access_control(prepared.system, run_id="run-7")
    assert all(k.startswith("dmpc/run-7/") for r in acl["rules"] for k in r["key_exprs"])
    assert allowed(acl, "agent-1", "ingress", "put", "dmpc/run-7/plan/1")
    assert not allowed(acl, "agent-1", "ingress", "put", "dmpc/run-8/plan/1")
    with pytest.raises(ValueError, match="run id"):
        access_control(["1"], {"1": []}, run_id="a/b")


def test_malformed_acl_files_are_refused(tmp_path):
    (tmp_path / "acl.json").write_text("{not json")
    with pytest.raises(ValueError, match="not JSON"):
        read_acl(tmp_path)
    (tmp_path / "acl.json").write_text(json.dumps({"rules": []}))
    with pytest.raises(ValueError, match="needs rules, subjects, policies"):
        read_acl(tmp_path)
    assert read_acl(tmp_path / "nothing") is None
    with pytest.raises(ValueError, match="access control"):
        session_config(acl={"enabled": True, "default_permission": "maybe", "rules": [], "subjects": [],
                            "policies": []})


# ---------------------------------------------------------------------------- the command line


def test_certs_command_writes_the_directory(monkeypatch, capsys, tmp_path):
    code, out, err = call(monkeypatch, capsys, "certs", str(tmp_path / "c"), "--scenario", PAPER,
                          "--host", "192.168.1.20", "--run-id", "lab-1")
    assert code == 0, err
    assert "router, coordinator, plant, agent-1, agent-2, agent-3, agent-4, sensor-1" in out
    ca_key = tmp_path / "c-ca.key"  # beside the directory, never in it
    assert f"the CA's private key is {ca_key} (mode 0600)" in out
    assert ca_key_files(tmp_path, tmp_path / "c" / "ca.pem") == ["c-ca.key"]
    assert stat.S_IMODE(ca_key.stat().st_mode) == 0o600
    assert all(stat.S_IMODE(p.stat().st_mode) == 0o600 for p in (tmp_path / "c").glob("*.key"))
    san = load_cert(tmp_path / "c" / "agent-3.pem").extensions.get_extension_for_class(x509.SubjectAlternativeName)
    assert ipaddress.ip_address("192.168.1.20") in san.value.get_values_for_type(x509.IPAddress)
    acl = read_acl(tmp_path / "c")
    assert all(k.startswith("dmpc/lab-1/") for r in acl["rules"] for k in r["key_exprs"])

    ca = (tmp_path / "c" / "ca.pem").read_bytes()
    code, _, err = call(monkeypatch, capsys, "certs", str(tmp_path / "c"), "--scenario", PAPER)
    assert code == 2 and "already holds certificates" in one_error_line(err) and "--force" in err
    assert (tmp_path / "c" / "ca.pem").read_bytes() == ca
    code, _, err = call(monkeypatch, capsys, "certs", str(tmp_path / "c"), "--scenario", PAPER, "--force")
    assert code == 0, err
    assert (tmp_path / "c" / "ca.pem").read_bytes() != ca
    assert ca_key_files(tmp_path, tmp_path / "c" / "ca.pem") == ["c-ca.key"]  # the new CA's key, in the same place


def test_certs_command_writes_the_ca_key_where_asked_and_keeps_an_existing_one(monkeypatch, capsys, tmp_path):
    ca_key = tmp_path / "offline" / "lab-ca.key"
    code, out, err = call(monkeypatch, capsys, "certs", str(tmp_path / "c"), "--scenario", PAPER,
                          "--ca-key", str(ca_key))
    assert code == 0, err
    assert ca_key_files(tmp_path, tmp_path / "c" / "ca.pem") == ["lab-ca.key"] and str(ca_key) in out
    kept = ca_key.read_bytes()
    code, _, err = call(monkeypatch, capsys, "certs", str(tmp_path / "d"), "--scenario", PAPER, "--ca-key", str(ca_key))
    assert code == 2 and "already holds a CA key" in one_error_line(err) and "--force" in err
    assert ca_key.read_bytes() == kept and not (tmp_path / "d").exists()


@pytest.mark.parametrize("args, expected", [
    (["--host", "bad host"], "neither an IP address nor a DNS name"),
    (["--host", "-x-.example"], "neither an IP address nor a DNS name"),
    (["--run-id", "a/b"], "--run-id"),
])
def test_certs_command_input_errors(monkeypatch, capsys, tmp_path, args, expected):
    code, _, err = call(monkeypatch, capsys, "certs", str(tmp_path / "c"), "--scenario", PAPER, *args)
    assert code == 2 and expected in one_error_line(err)
    assert not (tmp_path / "c").exists()  # nothing half-written


def test_certs_command_file_errors(monkeypatch, capsys, tmp_path):
    code, _, err = call(monkeypatch, capsys, "certs", str(tmp_path / "c"), "--scenario", str(tmp_path / "no.yaml"))
    assert code == 2 and "no.yaml" in one_error_line(err)
    (tmp_path / "file").write_text("")
    code, _, err = call(monkeypatch, capsys, "certs", str(tmp_path / "file"), "--scenario", PAPER)
    assert code == 2 and "cannot write the certificates" in one_error_line(err)
    code, _, err = call(monkeypatch, capsys, "certs", str(tmp_path / "c"))
    assert code == 2 and "--scenario" in err and "Traceback" not in err


def test_tls_options_fail_early_with_one_line(monkeypatch, capsys, tmp_path, cert_dir):
    code, _, err = call(monkeypatch, capsys, "run", PAPER, "--secure", "--tls", str(cert_dir))
    assert code == 2 and "exclude each other" in one_error_line(err)
    code, _, err = call(monkeypatch, capsys, "router", "--tls", str(cert_dir), "--listen", "tcp/127.0.0.1:7447")
    assert code == 2 and "not a tls/ endpoint" in one_error_line(err)
    code, _, err = call(monkeypatch, capsys, "agent", PAPER, "--id", "1", "--connect", "tls/127.0.0.1:7447",
                        "--tls", str(tmp_path / "none"))
    assert code == 2 and "no such directory" in one_error_line(err)

    partial = tmp_path / "partial"
    partial.mkdir()
    for path in cert_dir.iterdir():
        if path.name != "agent-3.key":
            (partial / path.name).write_bytes(path.read_bytes())
    code, _, err = call(monkeypatch, capsys, "run", PAPER, "--tls", str(partial), "--out", str(tmp_path / "r"))
    assert code == 2 and "agent-3.key" in one_error_line(err)
    assert not (tmp_path / "r").exists()  # refused before any process started

    (partial / "acl.json").write_text("[]")
    code, _, err = call(monkeypatch, capsys, "plant", PAPER, "--out", str(tmp_path / "p"), "--tls", str(partial),
                        "--listen", "tls/127.0.0.1:0")
    assert code == 2 and "acl.json" in one_error_line(err)


# ------------------------------------------------------------------------------- dmpc run wiring
@pytest.mark.parametrize("topology", ["mesh", "star"])
def test_run_with_tls_puts_every_process_on_tls_links(tmp_path, prepared, cert_dir, topology):
    from dmpc.runtime.launcher import child_commands

    children = child_commands(prepared, tmp_path, tmp_path / "scenario.yaml", tmp_path / "design.json", "r", 7447,
                              30.0, tls_dir=cert_dir, topology=topology)
    assert [c.role for c in children] == ["plant"] + [f"agent-{n}" for n in "1234"]
    for child in children:
        endpoints = [a for a in child.cmd if "/127.0.0.1:" in a]
        assert endpoints and all(e.startswith("tls/") for e in endpoints), child.cmd
        assert child.cmd[child.cmd.index("--tls") + 1] == str(cert_dir)
        if child.role.startswith("agent-"):
            assert child.cmd[child.cmd.index("--report") + 1] == str(tmp_path / "logs" / f"{child.role}.json")


def test_agent_reports_are_merged_into_the_summary(tmp_path):
    from dmpc.runtime.launcher import Child, merge_agent_reports

    children = [Child(role, [], tmp_path / f"{role}.log", agents=agents)
                for role, agents in (("plant", ()), ("agent-1", ("1",)), ("agent-2", ("2",)))]
    assert merge_agent_reports(tmp_path, children) is None  # no summary yet
    (tmp_path / "logs").mkdir()
    (tmp_path / "summary.json").write_text(json.dumps({"steps": 3, "rejected": {"1": 2}, "agents": {}}))
    report = {"agent": "1", "run_id": "r", "exit_code": 0, "rejected": {"plant": 4}, "rejected_reasons": {"x": 4},
              "duplicates": 1, "solves": 5}
    (tmp_path / "logs" / "agent-1.json").write_text(json.dumps(report))
    summary = merge_agent_reports(tmp_path, children)  # agent-2 never wrote one: left out
    assert summary["agents"] == {"1": {"exit_code": 0, "rejected": {"plant": 4}, "rejected_reasons": {"x": 4},
                                       "duplicates": 1, "solves": 5}}
    assert json.loads((tmp_path / "summary.json").read_text()) == summary
    assert summary["rejected"] == {"1": 2}
    assert "security" not in summary  # plain TCP


@pytest.mark.parametrize("acl", [True, False])
def test_run_over_tls_records_its_security_in_the_summary(tmp_path, prepared, cert_dir, acl):
    import shutil

    from dmpc.runtime.launcher import child_commands, merge_agent_reports

    certs = tmp_path / "certs"
    shutil.copytree(cert_dir, certs)
    if not acl:
        (certs / "acl.json").unlink()
    out = tmp_path / "run"
    out.mkdir()
    children = child_commands(prepared, out, out / "scenario.yaml", out / "design.json", "r", 7447, 30.0, tls_dir=certs)
    (out / "summary.json").write_text(json.dumps({"steps": 3}))
    summary = merge_agent_reports(out, children)
    assert summary["security"] == {"tls": True, "mutual_authentication": True, "access_control": acl,
                                   "certificates": str(certs)}
    assert json.loads((out / "summary.json").read_text()) == summary


# ---------------------------------------------------------------------------- counting the drops
def test_drops_are_counted_per_sender_and_logged_at_most_once_a_second(caplog):
    now = [0.0]
    rejects = Rejections(logging.getLogger("test.rejects"), "plant", lambda: now[0], known=["1", "2"])
    with caplog.at_level(logging.WARNING, logger="test.rejects"):
        for i in range(1000):
            now[0] = i * 0.001  # 1000 drops in one second from each of three senders
            rejects("1", "not msgpack: ExtraData")
            rejects("evil-" + str(i), "unknown sender")
            rejects("2", "wrong run id\x1b[31m")
        now[0] = 1.5
        rejects("1", "stale: plan of step 3")
    assert rejects.counts == {"1": 1001, "2": 1000, UNKNOWN: 1000}  # made-up names share one count
    assert rejects.reasons == {"not msgpack": 1000, "unknown sender": 1000, "wrong run id\x1b[31m": 1000, "stale": 1}
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 4  # one per sender in the first second, then one for "1"
    assert "999 more since the last report" in lines[-1] and "1001 dropped from 1" in lines[-1]
    assert all("\x1b" not in line for line in lines)  # the sender's text cannot drive the terminal
    assert rejects.summary() == "plant: dropped 3001 invalid messages ((unknown): 1000, 1: 1001, 2: 1000)"


def test_a_reason_about_a_field_keeps_what_is_wrong_with_it_but_not_the_value_sent():
    import msgpack

    from dmpc.bus.codec import DecodeError, decode

    body = {"protocol": 3, "type": "state", "run": "r", "k": 1, "sender": "plant",
            "x": {"1": {"dtype": "<f8", "shape": [2], "data": np.array([0.0, np.inf], "<f8").tobytes()}}}
    with pytest.raises(DecodeError) as caught:
        decode(msgpack.packb(body, use_bin_type=True))
    rejects = Rejections(logging.getLogger("test.rejects"), "plant", lambda: 0.0, known=["plant"])
    rejects("plant", str(caught.value))
    rejects("plant", "k: expected an integer >= 0, got 'seven'")
    rejects("plant", "design: agent 4 uses design 1f2e (scenario 'paper', horizon 12); give every process ...")
    rejects("plant", "not msgpack: ExtraData")
    assert rejects.reasons == {"x[1]: non-finite values": 1, "k: expected an integer >= 0": 1, "design": 1,
                               "not msgpack": 1}


# ------------------------------------------------------------------ no unsafe deserialisation
UNSAFE_MODULES = {"pickle", "cPickle", "_pickle", "dill", "cloudpickle", "jsonpickle", "shelve", "marshal", "joblib"}
UNSAFE_YAML = {"unsafe_load", "unsafe_load_all", "full_load", "full_load_all"}
SAFE_LOADERS = ("SafeLoader", "CSafeLoader")


def package_sources() -> list[Path]:
    files = [p for d in PACKAGE_DIRS for p in sorted((ROOT / d).rglob("*.py"))]
    assert len(files) > 30
    return files


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[0] != "dmpc":
        parts.insert(0, "dmpc")
    return ".".join(p for p in parts if p != "__init__")


def _name(node: ast.AST) -> str:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return f"{_name(node.value)}.{node.attr}"
    return ""


def unsafe_calls(path: Path) -> list[str]:
    """Every import of a pickle-like module, eval/exec, YAML loading that is not safe, and
    np.load with pickles allowed, in one source file."""
    tree = ast.parse(path.read_text(), str(path))
    found = []
    for node in ast.walk(tree):
        where = f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', '?')}"
        if isinstance(node, ast.Import):
            found += [f"{where} import {a.name}" for a in node.names if a.name.split(".")[0] in UNSAFE_MODULES]
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] in UNSAFE_MODULES:
            found.append(f"{where} from {node.module} import")
        elif isinstance(node, ast.Call):
            name = _name(node.func)
            kwargs = {k.arg: k.value for k in node.keywords}
            if name in ("eval", "exec"):
                found.append(f"{where} {name}()")
            elif name.startswith("yaml.") and name.split(".")[-1] in UNSAFE_YAML:
                found.append(f"{where} {name}()")
            elif name in ("yaml.load", "yaml.load_all"):
                loader = kwargs.get("Loader", node.args[1] if len(node.args) > 1 else None)
                if loader is None or not safe_loader(path, _name(loader)):
                    found.append(f"{where} {name}() without a safe loader")
            elif name.split(".")[-1] == "load" and name.split(".")[0] in ("np", "numpy"):
                flag = kwargs.get("allow_pickle")
                if flag is not None and not (isinstance(flag, ast.Constant) and flag.value is False):
                    found.append(f"{where} {name}(allow_pickle=...)")
            elif name.split(".")[-1] in ("loads", "load") and name.split(".")[0] in UNSAFE_MODULES:
                found.append(f"{where} {name}()")
    return found


def safe_loader(path: Path, loader: str) -> bool:
    """True if ``loader`` (as written in ``path``) builds only plain YAML types: PyYAML's safe
    loaders and their subclasses, not the full or unsafe ones that construct Python objects."""
    if loader.startswith("yaml."):
        cls = getattr(yaml, loader.split(".", 1)[1], None)
    else:
        cls = getattr(importlib.import_module(module_name(path)), loader, None)
    return (inspect.isclass(cls) and issubclass(cls, yaml.constructor.SafeConstructor)
            and not issubclass(cls, yaml.constructor.FullConstructor))


def test_no_unsafe_deserialisation_in_the_package():
    found = [hit for path in package_sources() for hit in unsafe_calls(path)]
    assert not found, "unsafe deserialisation:\n" + "\n".join(found)


def test_the_checker_finds_what_it_looks_for(tmp_path, monkeypatch):
    source = ("import pickle\nimport yaml\nimport numpy as np\n"
              "yaml.load(t)\nyaml.load(t, Loader=yaml.Loader)\nyaml.full_load(t)\n"
              "np.load(p, allow_pickle=True)\npickle.loads(b)\neval('1')\n"
              "yaml.load(t, Loader=yaml.SafeLoader)\nyaml.load(t, yaml.CSafeLoader)\n"
              "np.load(p, allow_pickle=False)\nnp.load(p)\n")
    path = tmp_path / "dmpc" / "example.py"
    path.parent.mkdir()
    path.write_text(source)
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    hits = unsafe_calls(path)
    assert len(hits) == 7, hits  # the last four calls are safe
    assert all(":1" not in h or "import pickle" in h for h in hits)


def test_records_hold_no_pickles(tmp_path, prepared):
    """trajectory.npz loads with pickles refused (numpy's default), and holds no object arrays."""
    from dmpc.records.session import RunRecorder
    from dmpc.runtime.inprocess import simulate

    assert inspect.signature(np.load).parameters["allow_pickle"].default is False
    with RunRecorder(tmp_path / "run", prepared, show_progress=False) as recorder:
        simulate(prepared, recorder.on_step)
        recorder.complete()
    with np.load(tmp_path / "run" / "trajectory.npz", allow_pickle=False) as data:
        assert data.files and all(data[name].dtype != object for name in data.files)
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["steps"] == prepared.protocol.steps


# ---------------------------------------------------------------- magnitude of a received plan

_entries = st.floats(allow_nan=True, allow_infinity=True, width=64)


_near_the_limit = st.one_of(_entries, st.sampled_from([MAX_MAGNITUDE, -MAX_MAGNITUDE, np.nextafter(MAX_MAGNITUDE, np.inf),
                                                       MAX_MAGNITUDE / 2, 7.1e11, 1e154, 1e200, -1e300]))


@given(z=arrays(np.float64, st.tuples(st.integers(0, 6), st.integers(0, 3)), elements=_near_the_limit),
       v=arrays(np.float64, st.integers(0, 5), elements=_near_the_limit), cost=_near_the_limit)
def test_the_sum_of_squares_shortcut_agrees_with_the_largest_entry(z, v, cost):
    """The sum-of-squares shortcut must never change the answer, near the limit and where the
    squares overflow, for arrays alone or with a scalar."""
    for values in ((z, v), (z, v, cost)):
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # an overflowing sum of squares is expected, not warned about
            clearly_in_range(*values)
        everything = np.concatenate([np.ravel(a) for a in values])
        expected = bool(np.isnan(everything).any()) or (everything.size > 0 and np.max(np.abs(everything)) > MAX_MAGNITUDE)
        assert out_of_range(*values) == expected
        if clearly_in_range(*values):
            assert not expected and (everything.size == 0 or np.max(np.abs(everything)) < MAX_MAGNITUDE / 2)


@given(z=arrays(np.float64, st.tuples(st.integers(0, 6), st.integers(0, 3)), elements=_entries),
       v=arrays(np.float64, st.integers(0, 5), elements=_entries), cost=_entries)
def test_magnitude_is_the_largest_absolute_entry_and_nan_wins(z, v, cost):
    everything = np.concatenate([z.ravel(), v.ravel(), [cost]])
    got = magnitude(z, v, cost)
    if np.isnan(everything).any():
        assert np.isnan(got)
        assert out_of_range(z, v, cost)
    else:
        assert got == np.max(np.abs(everything))
        assert out_of_range(z, v, cost) == (got > MAX_MAGNITUDE)

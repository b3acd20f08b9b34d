"""docker-compose.yml and Dockerfile agree with the CLI, the scenario and the Zenoh library.

No Docker engine is needed: every service's command is parsed by the real ``dmpc`` command
line (click's parser, nothing is run), the scenario it names is loaded, and the endpoints are
checked against the router's. ``docker compose config`` runs only where Docker Compose is
installed.
"""
from __future__ import annotations

import importlib.metadata
import re
import shutil
import subprocess
import tomllib
from pathlib import Path

import click
import pytest
import typer.main
import yaml

from dmpc.bus.session import check_endpoint, endpoint_host, session_config
from dmpc.cli import app
from dmpc.scenario import build_system, load_scenario

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "docker-compose.yml"
DOCKERFILE = ROOT / "Dockerfile"
_VARIABLE = re.compile(r"\$\{(?P<name>[A-Za-z_][A-Za-z0-9_]*)(?::?-(?P<default>[^}]*))?\}")


def _interpolate(value, env: dict[str, str]):
    """Compose's ``${NAME:-default}`` substitution, on strings inside lists and dicts."""
    if isinstance(value, str):
        def sub(m):
            if m["name"] in env:
                return env[m["name"]]
            assert m["default"] is not None, f"${{{m['name']}}} has no default in docker-compose.yml"
            return m["default"]
        return _VARIABLE.sub(sub, value)
    if isinstance(value, list):
        return [_interpolate(v, env) for v in value]
    if isinstance(value, dict):
        return {k: _interpolate(v, env) for k, v in value.items()}
    return value


@pytest.fixture(scope="module")
def compose() -> dict:
    return _interpolate(yaml.safe_load(COMPOSE.read_text()), {})


@pytest.fixture(scope="module")
def dmpc_services(compose) -> dict[str, dict]:
    return {name: s for name, s in compose["services"].items() if name != "router"}


def _parse(argv: list[str]) -> tuple[str, dict]:
    """Parse ``dmpc ARGV`` with the real command line, without running it: (command, params)."""
    group = typer.main.get_command(app)
    name, *rest = argv
    command = group.get_command(click.Context(group), name)
    assert command is not None, f"dmpc has no command {name!r}"
    with command.make_context(name, list(rest)) as ctx:
        return name, ctx.params


def _router_port(compose) -> int:
    args = compose["services"]["router"]["command"]
    listen = [args[i + 1] for i, a in enumerate(args) if a in ("--listen", "-l")]
    assert len(listen) == 1, args
    check_endpoint(listen[0])
    assert endpoint_host(listen[0]) in ("0.0.0.0", "[::]", "::"), "the router must listen on every interface"
    return int(listen[0].rsplit(":", 1)[1])


def test_services(compose, dmpc_services):
    assert set(compose["services"]) == {"router", "plant", "agent-1", "agent-2", "agent-3", "agent-4"}
    # one image of the project; the services differ only in their command
    shapes = [{k: v for k, v in s.items() if k != "command"} for s in dmpc_services.values()]
    assert all(shape == shapes[0] for shape in shapes), shapes
    assert shapes[0]["build"] == "." and shapes[0]["image"].startswith("dmpc:")
    assert "router" in shapes[0]["depends_on"]


def test_router_image_matches_the_zenoh_library(compose):
    version = importlib.metadata.version("eclipse-zenoh")
    assert compose["services"]["router"]["image"] == f"eclipse/zenoh:{version}"


def test_commands_parse_with_the_cli(dmpc_services):
    for name, service in dmpc_services.items():
        command, params = _parse(service["command"])
        assert command == ("plant" if name == "plant" else "agent"), name
        assert params["mode"] == "client", f"{name}: clients of the router (no peer-to-peer ports in compose)"
        assert not params["listen"], name
        # the same endpoint checks as the process, without opening a session
        session_config(mode=params["mode"], connect=params["connect"])


def test_agent_ids_match_the_scenario(dmpc_services):
    parsed = {name: _parse(s["command"])[1] for name, s in dmpc_services.items()}
    scenarios = {p["scenario"] for p in parsed.values()}
    assert len(scenarios) == 1, "every process must run the same scenario"
    scenario = scenarios.pop()
    assert (ROOT / scenario).is_file(), scenario
    names = [s.name for s in build_system(load_scenario(ROOT / scenario)).subsystems]
    agents = {name: p["id_"] for name, p in parsed.items() if name != "plant"}
    assert all(len(ids) == 1 for ids in agents.values()), "one agent per service"
    ids = {ids[0] for ids in agents.values()}
    assert sorted(ids) == sorted(names)
    assert {f"agent-{i}" for i in ids} == set(agents)
    assert len({p["run_id"] for p in parsed.values()}) == 1, "one run id for every process"


def test_endpoints_and_ports_agree(compose, dmpc_services):
    port = _router_port(compose)
    for name, service in dmpc_services.items():
        connect = list(_parse(service["command"])[1]["connect"])
        assert connect == [f"tcp/router:{port}"], name
    published = compose["services"]["router"].get("ports", [])
    assert all(str(p).rsplit(":", 1)[1] == str(port) for p in published), published


def test_run_folder_is_on_the_volume(compose, dmpc_services):
    params = _parse(dmpc_services["plant"]["command"])[1]
    (volume,) = dmpc_services["plant"]["volumes"]
    source, target = volume.split(":")[:2]
    assert source in compose["volumes"]
    assert Path(target) in Path(params["out"]).parents
    assert f"mkdir {target}" in DOCKERFILE.read_text()  # owned by the image's user


def test_dockerfile_installs_the_project():
    text = DOCKERFILE.read_text()
    assert re.search(r"^FROM python:3\.11-slim\s*$", text, re.M)
    assert re.search(r"^RUN pip install \.\s*$", text, re.M)
    assert re.search(r'^ENTRYPOINT \["dmpc"\]\s*$', text, re.M)
    copied = set(re.findall(r"^COPY (\S+) ", text, re.M))
    package_dirs = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    missing = {d.split("/")[0] for d in package_dirs.values()} - copied
    assert not missing, f"the Dockerfile does not copy {missing}"
    assert "scenarios" in copied


def test_a_plain_install_holds_every_package():
    """The image runs ``pip install .`` (not editable): a package missing from pyproject's
    ``packages`` list would be missing from the image, although the tests here pass."""
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    found = set()
    for package, folder in setuptools["package-dir"].items():
        for init in (ROOT / folder).rglob("__init__.py"):
            parts = init.parent.relative_to(ROOT / folder).parts
            if "__pycache__" not in parts:
                found.add(".".join((package, *parts)))
    missing = sorted(found - set(setuptools["packages"]))
    assert not missing, f"pyproject.toml [tool.setuptools] packages lacks {missing}"


def _compose_command() -> list[str] | None:
    if shutil.which("docker"):
        res = subprocess.run(["docker", "compose", "version"], capture_output=True, timeout=30)
        if res.returncode == 0:
            return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    return None


def test_docker_compose_config():
    command = _compose_command()
    if command is None:
        pytest.skip("Docker Compose is not installed ('docker compose' and 'docker-compose' both missing); "
                    "the file was checked above without it")
    res = subprocess.run(command + ["-f", str(COMPOSE), "config", "--quiet"], capture_output=True, text=True,
                         timeout=60, cwd=ROOT)
    assert res.returncode == 0, res.stderr

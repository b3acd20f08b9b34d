"""What CI needs to run every test: .ci/run installs it, the README names it, and a test that
cannot run for want of it fails under ``CI=true`` instead of skipping."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from tests.e2e_helpers import ROOT


def ci_packages() -> list[str]:
    """The Debian packages .ci/run installs when their command is missing."""
    return re.findall(r"missing\+=\(([\w.+-]+)\)", (ROOT / ".ci" / "run").read_text())


def test_ci_installs_what_the_readme_names():
    packages = ci_packages()
    assert {"chromium", "chromium-driver", "iproute2"} <= set(packages)
    readme = " ".join((ROOT / "README.md").read_text().split())
    command = re.search(r"`sudo apt-get install -y ([^`]+)`; `\.ci/run` installs them", readme)
    assert command is not None, "the README's apt-get command for the tests is gone"
    assert sorted(command.group(1).split()) == sorted(packages)


def _multihost_without_ip(ci: str | None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "CI"}
    env["PATH"] = str(ROOT / "no-such-folder")  # no `ip` (and no other command) to be found
    if ci is not None:
        env["CI"] = ci
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rs",
                           "tests/test_e2e_multihost.py"], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=120)


def test_the_multihost_test_fails_in_ci_when_it_cannot_run():
    local = _multihost_without_ip(None)
    assert local.returncode == 0 and "skipped" in local.stdout and "failed" not in local.stdout, local.stdout
    ci = _multihost_without_ip("true")
    assert ci.returncode != 0, ci.stdout
    assert "CI must run the multi-host test" in ci.stdout and "skipped" not in ci.stdout, ci.stdout


def test_ci_lints_and_type_checks_before_the_tests_and_the_package_ships_its_types():
    """.ci/run runs ruff and mypy (installed by the test extra) before pytest; py.typed is package data."""
    import tomllib

    script = (ROOT / ".ci" / "run").read_text()
    order = [script.index(".venv/bin/ruff check"), script.index(".venv/bin/mypy"), script.index(".venv/bin/python -m pytest")]
    assert order == sorted(order)
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    extra = " ".join(config["project"]["optional-dependencies"]["test"])
    assert "ruff" in extra and "mypy" in extra
    assert config["tool"]["setuptools"]["package-data"]["dmpc"] == ["py.typed"] and (ROOT / "dmpc" / "py.typed").is_file()
    ruff = subprocess.run([str(Path(sys.executable).parent / "ruff"), "check", "--quiet"], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    assert ruff.returncode == 0, ruff.stdout + ruff.stderr

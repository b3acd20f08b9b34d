"""Fixtures shared by the tests, and the Hypothesis profile for CI."""
from __future__ import annotations

import os

import pytest
from hypothesis import settings

from tests.e2e_helpers import Processes, simulate_paper

# CI replays the same examples on every run (a failure there is reproducible from the log);
# local runs keep exploring new ones.
settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")


@pytest.fixture
def procs(tmp_path):
    """Start ``dmpc`` processes in their own process groups; every one is stopped at the end."""
    p = Processes(tmp_path)
    yield p
    p.cleanup()


@pytest.fixture(scope="module")
def paper_simulated(tmp_path_factory):
    """Run folder of ``dmpc simulate scenarios/paper.yaml`` (the in-process reference)."""
    return simulate_paper(tmp_path_factory.mktemp("sim") / "paper")

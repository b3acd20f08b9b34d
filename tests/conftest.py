"""Fixtures shared by the end-to-end tests."""
from __future__ import annotations

import pytest

from tests.e2e_helpers import Processes


@pytest.fixture
def procs(tmp_path):
    """Start ``dmpc`` processes in their own process groups; every one is stopped at the end."""
    p = Processes(tmp_path)
    yield p
    p.cleanup()

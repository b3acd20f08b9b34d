"""The scale table's row: a real hosted run of the paper's example and its centralised loop."""
from __future__ import annotations

import pytest

from dmpc.bench.scale import HEADER, markdown_row, scale_row
from tests.e2e_helpers import ROOT

pytestmark = pytest.mark.e2e


def test_a_row_runs_hosted_agents_and_compares_with_the_centralised_loop(tmp_path):
    row = scale_row(4, 3, 40, tmp_path, root=ROOT)
    assert row["completed"] and row["feasible"] and row["fallbacks"] == 0
    assert (row["processes"], row["agents_per_process"], row["topology"]) == (2, 2, "mesh")
    assert 0 < row["startup_s"] < 60 and 0 < row["step_ms_p50"] <= row["step_ms_p99"]
    assert row["rss_mb_total"] > row["rss_mb_per_process"] > 0  # sampled while it stepped
    # the DMPC loop costs a little more than the centralised optimum (the paper's example: 102.0 / 101.8)
    assert 1.0 < row["cost_ratio"] < 1.01
    line = markdown_row(row)
    assert line.count("|") == len(HEADER) + 1 and line.startswith("| 4 | 2 | 2 | mesh |")


def test_a_row_that_did_not_complete_says_why():
    row = {"M": 1024, "processes": 8, "agents_per_process": 128, "topology": "mesh", "design_s": 40.0,
           "completed": False, "reason": "error: plant exited with code 1\n    agents not ready within 60 s"}
    assert markdown_row(row).endswith("did not complete: agents not ready within 60 s |")

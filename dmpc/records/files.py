"""The names of the files in a run folder (docs/records.md, the table at the top), in one place.

Plain strings, so that a module that only looks for a file does not import the writers.
"""
from __future__ import annotations

SCENARIO = "scenario.yaml"
"""The resolved scenario (a run started from a scenario file)."""
DESIGN = "design.json"
"""The offline design."""
BUNDLE = "run.json"
"""The prepared run as plain JSON (:mod:`dmpc.prepared.bundle`), which ``dmpc run`` starts its agents from."""
PROCESSES = "processes.json"
"""Role -> pid of the processes ``dmpc run`` started."""
LOGS = "logs"
"""The folder of the processes' logs and the agents' reports (``dmpc run``)."""
TLS = "tls"
"""The folder of the run's certificates (``dmpc run --secure``)."""
DISTURBANCE = "disturbance.npy"
"""The disturbance the plant adds, drawn before the run."""
STEP_LOG = "steps.jsonl"
"""One line per completed step; its presence marks a folder that holds a run."""
ROWS = ".steps.f64"
"""The numbers of each step in a fixed layout while the run goes (removed at the end)."""
TRAJECTORY = "trajectory.npz"
"""The arrays of the completed steps."""
SUMMARY = "summary.json"
"""The key figures and the verdict."""
COMPARISON = "comparison.json"
"""The table of a comparison folder (``dmpc compare``), beside one run folder per method."""


def log_file(role: str) -> str:
    """The log of process ``role`` under :data:`LOGS`."""
    return f"{role}.log"


def report_file(role: str) -> str:
    """The report the agent process of ``role`` writes at exit under :data:`LOGS`."""
    return f"{role}.json"

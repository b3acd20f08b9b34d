"""The agents' own reports (``logs/agent-<name>.json``) merged into a run's ``summary.json``.

The plant writes the summary before the agents exit, and their drop counts are known only to
them, so each agent started by ``dmpc run`` writes a report at exit and the summary gets
them afterwards: from the plant once its agents have left, and again from the launcher (which
also adds what it saw). Either one suffices, so a killed launcher does not lose them.
"""
from __future__ import annotations

import json
from pathlib import Path

from dmpc.bus import keys
from dmpc.records.files import LOGS, SUMMARY, report_file
from dmpc.records.run_folder import write_json

FIRST_RELEASE = "first_release_at"
"""Report key: when the agent got its first release, on its host's monotonic clock (null: never).
It gives ``startup_s`` and stays out of the summary's ``agents``."""
STARTUP = "startup_s"
"""Summary key (``dmpc run``): seconds from the launcher starting the processes to the first release."""


def report_path(out: Path, name: str) -> Path:
    """Where agent ``name`` of a run started by ``dmpc run`` in the run folder ``out`` writes its report."""
    return Path(out) / LOGS / report_file(keys.agent_role(name))


def merge_agent_reports(out: Path, names: list[str], extra: dict | None = None,
                        launched_at: float | None = None) -> dict | None:
    """Add the reports of the agents ``names`` to ``summary.json`` of the run folder ``out`` as
    ``agents``, the names of those without one
    as ``agent_reports_missing``, and ``extra``; returns the summary (None if there is none).

    ``launched_at`` (``time.monotonic()`` when the processes were started, on this machine) adds
    ``startup_s``: from then to the first release any agent reported.
    """
    out = Path(out)
    try:
        summary = json.loads((out / SUMMARY).read_text())
    except (OSError, json.JSONDecodeError):
        return None
    agents, missing, released = {}, [], []
    for name in names:
        try:
            report = json.loads(report_path(out, name).read_text())
        except (OSError, json.JSONDecodeError):
            missing.append(name)  # killed before it could write one
            continue
        if isinstance(report, dict):
            agents[name] = {k: v for k, v in report.items() if k not in ("agent", "run_id", FIRST_RELEASE)}
            if isinstance(report.get(FIRST_RELEASE), (int, float)):
                released.append(float(report[FIRST_RELEASE]))
        else:
            missing.append(name)
    summary["agents"] = agents
    summary["agent_reports_missing"] = missing
    summary.update(extra or {})
    if launched_at is not None and released:
        summary[STARTUP] = min(released) - launched_at
    try:
        write_json(out / SUMMARY, summary)
    except OSError:
        pass  # the summary as the plant wrote it stays; the caller still gets the merged one
    return summary

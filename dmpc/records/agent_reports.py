"""The agents' own reports (``logs/agent-<name>.json``) merged into a run's ``summary.json``.

The plant writes the summary before the agents exit, and their drop counts are known only to
them, so each agent started by ``dmpc run`` writes a report at exit and the summary gets
them afterwards: from the plant once its agents have left, and again from the launcher (which
also adds what it saw). Either one suffices, so a killed launcher does not lose them.
"""
from __future__ import annotations

import json
from pathlib import Path

from dmpc.records.run_folder import SUMMARY, write_json

LOGS = "logs"


def report_path(out: Path, name: str) -> Path:
    """Where agent ``name`` of a run started by ``dmpc run`` writes its report."""
    return Path(out) / LOGS / f"agent-{name}.json"


def merge_agent_reports(out: Path, names: list[str], extra: dict | None = None) -> dict | None:
    """Add the agents' reports to ``summary.json`` as ``agents``, the names of those without one
    as ``agent_reports_missing``, and ``extra``; returns the summary (None if there is none).
    """
    out = Path(out)
    try:
        summary = json.loads((out / SUMMARY).read_text())
    except (OSError, json.JSONDecodeError):
        return None
    agents, missing = {}, []
    for name in names:
        try:
            report = json.loads(report_path(out, name).read_text())
        except (OSError, json.JSONDecodeError):
            missing.append(name)  # killed before it could write one
            continue
        if isinstance(report, dict):
            agents[name] = {k: v for k, v in report.items() if k not in ("agent", "run_id")}
        else:
            missing.append(name)
    summary["agents"] = agents
    summary["agent_reports_missing"] = missing
    summary.update(extra or {})
    try:
        write_json(out / SUMMARY, summary)
    except OSError:
        pass  # the summary as the plant wrote it stays; the caller still gets the merged one
    return summary

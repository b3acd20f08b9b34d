"""Running ``dmpc`` in the test process through its real entry point."""
from __future__ import annotations

import sys

import dmpc.terminal.signals
from dmpc import cli


def call(monkeypatch, capsys, *argv: str) -> tuple[int, str, str]:
    """Run ``dmpc argv``; return (exit code, stdout, stderr).

    pytest's signal handlers and its captured fd 1 are kept: the CLI neither turns SIGTERM
    into Ctrl-C nor redirects C-level stdout here.
    """
    monkeypatch.setattr(sys, "argv", ["dmpc", *argv])
    monkeypatch.setattr("dmpc.terminal.console._silenced", True)
    monkeypatch.setattr(dmpc.terminal.signals, "sigterm_as_interrupt", lambda: None)
    code = 0
    try:
        cli.main()
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(err: str) -> str:
    """The single ``error: ...`` line of an expected failure (no traceback)."""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    return lines[0]

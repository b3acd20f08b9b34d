"""The one base of every error dmpc raises on purpose, and its kind for bad input.

Standard library only: the command line catches these without importing the packages that raise
them (the scenario schema needs pydantic, the bus Zenoh).
"""
from __future__ import annotations


class DmpcError(Exception):
    """An error dmpc raises on purpose: the message is one line that says what is wrong."""


class InputError(DmpcError):
    """What was given is wrong: a flag, a scenario file, a design that cannot work, a folder.
    The command line prints the message as one line and exits with code 2."""


class DesignError(InputError):
    """A design that cannot be used, with the figures that show why (one line)."""

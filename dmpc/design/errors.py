"""Errors raised by the offline design."""


class DesignError(Exception):
    """A design that cannot be used, with the figures that show why (one line)."""

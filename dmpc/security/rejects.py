"""Counting and logging dropped messages without letting a flood flood the log.

Every node drops what fails validation and counts it per sender. A sender that is not part
of the run (any key chunk a rogue process makes up) is counted under one name, ``UNKNOWN``,
so the counts stay bounded whatever arrives. Each sender gets at most one log line per
``interval`` seconds of the bus clock; the line reports the drops suppressed since the last.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import re
from collections.abc import Callable, Iterable

import numpy as np

from dmpc.bus.messages import MESSAGE_TYPES

UNKNOWN = "(unknown)"
STALE = "stale"
"""Why the coordinator drops a plan of a closed round, or a copy of a state already taken: normal
(a plan after its round's deadline in realtime, a state the plant repeats), so not counted."""
LOG_INTERVAL = 1.0
MAX_REASON = 80
"""Characters of a reason counted in ``Rejections.reasons``: a longer one is cut between words."""
_FIELDS = frozenset(f.name for cls in MESSAGE_TYPES.values() for f in dataclasses.fields(cls))
_MESSAGE_CLASSES = frozenset(cls.__name__ for cls in MESSAGE_TYPES.values())  # a message's fields: Setpoint: missing field 'u'
_INDEXED_FIELD = re.compile(r"[a-z_]+\[[^\]]*\]")  # x[1], u[2], provided[a]: one entry of a field
_DETAIL = re.compile(r", got |;| \(")  # what follows is the value the sender sent, or more detail


def reason_of(why: str) -> str:
    """The reason under which a drop said ``why`` is counted: the text before the first colon, except
    that a field of a message (``x[1]``, ``k``) keeps what is wrong with it (``x[1]: non-finite
    values``, ``k: expected an integer >= 0``) without the value the sender sent, and a message with
    fields missing or unexpected names them (``Setpoint: unexpected field 'colour'``). At most
    ``MAX_REASON`` characters, cut between words (``...`` says so)."""
    head, colon, rest = why.partition(":")
    if colon and (head in _FIELDS or _INDEXED_FIELD.fullmatch(head)):
        head = f"{head}: {_DETAIL.split(rest.strip(), maxsplit=1)[0].strip()}"
    elif colon and head in _MESSAGE_CLASSES:
        head = f"{head}: {rest.strip()}"
    return _cut(head, MAX_REASON)


def _cut(text: str, limit: int) -> str:
    """``text`` if at most ``limit`` characters, else its words that fit before ``...``."""
    if len(text) <= limit:
        return text
    room = limit - len("...")
    space = text.rfind(" ", 0, room + 1)
    return text[: space if space > 0 else room].rstrip(" ,;:") + "..."


class Rejections:
    """Per-sender drop counts with a time-throttled warning.

    Parameters
    ----------
    log : logging.Logger
    who : str
        Prefix of every line, e.g. ``plant`` or ``agent 2``.
    clock : callable () -> float
        Seconds; the bus clock (simulated for the in-memory bus).
    known : iterable of str
        Senders counted under their own name; everything else is ``UNKNOWN``.
    interval : float
        Least time between two lines about the same sender.

    Attributes
    ----------
    counts : dict str -> int
        Drops per sender (the records' ``rejected``).
    reasons : dict str -> int
        Drops per reason (:func:`reason_of`).
    """

    def __init__(self, log: logging.Logger, who: str, clock: Callable[[], float], known: Iterable[str],
                 interval: float = LOG_INTERVAL) -> None:
        self.log = log
        self.who = who
        self.clock = clock
        self.known = frozenset(known)
        self.interval = interval
        self.counts: dict[str, int] = {}
        self.reasons: dict[str, int] = {}
        self.lines = 0
        self._last_line: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def sender(self, name: str) -> str:
        """``name`` if it belongs to the run, else ``UNKNOWN``."""
        return name if name in self.known else UNKNOWN

    def __call__(self, sender: str, why: str) -> None:
        """Count one dropped message from ``sender`` and maybe log it."""
        sender = self.sender(sender)
        self.counts[sender] = self.counts.get(sender, 0) + 1
        reason = reason_of(why)
        if reason not in self.reasons and len(self.reasons) >= 64:
            reason = "other"
        self.reasons[reason] = self.reasons.get(reason, 0) + 1
        now = self.clock()
        last = self._last_line.get(sender)
        if last is not None and now - last < self.interval:
            self._suppressed[sender] = self._suppressed.get(sender, 0) + 1
            return
        self._last_line[sender] = now
        skipped = self._suppressed.pop(sender, 0)
        more = f", {skipped} more since the last report" if skipped else ""
        self.lines += 1
        text = "".join(c if c.isprintable() else "?" for c in why[:200])  # the text may come from the sender
        self.log.warning("%s: dropped a message from %s (%s)%s; %d dropped from %s so far",
                         self.who, sender, text, more, self.counts[sender], sender)

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def counts_line(self) -> str:
        """'dropped N invalid messages (per sender)', or '' if nothing was dropped."""
        if not self.counts:
            return ""
        per = ", ".join(f"{s}: {n}" for s, n in sorted(self.counts.items()))
        return f"dropped {self.total} invalid messages ({per})"

    def summary(self) -> str:
        """:meth:`counts_line` after who dropped them, or '' if nothing was dropped."""
        line = self.counts_line()
        return f"{self.who}: {line}" if line else ""


# No state, input or cost of a plan the QP could produce comes near this; beyond it a plan
# would overflow the arithmetic downstream (terminal box, plant update) into inf and NaN.
MAX_MAGNITUDE = 1e12


def magnitude(*values) -> float:
    """The largest absolute entry of the arrays and scalars (0.0 if none); NaN if any entry is NaN.

    Runs on every received plan: array methods rather than numpy's functions, whose dispatch
    costs more than the reduction on arrays this small.
    """
    top = 0.0
    for a in values:
        if hasattr(a, "max"):
            if a.size == 0:
                continue
            m = max(float(a.max()), -float(a.min()))  # a NaN entry makes both NaN
        else:
            m = abs(float(a))
        if m != m:
            return math.nan
        top = max(top, m)
    return top


_CLEARLY_IN_RANGE = (MAX_MAGNITUDE / 2) ** 2


def clearly_in_range(*values) -> bool:
    """True when the sum of squares of every entry of the arrays (and scalars) is finite and below
    (MAX_MAGNITUDE / 2)^2: then every entry is finite and well within ``MAX_MAGNITUDE``. False
    says nothing (ask :func:`magnitude`); one cheap call per array for the common case of a plan
    in range."""
    total = 0.0
    with np.errstate(over="ignore"):  # entries beyond 1e154 overflow the sum to inf: not in range, no warning
        for a in values:
            if isinstance(a, np.ndarray):
                flat = a.ravel()
                total += float(flat.dot(flat))
            else:
                total += float(a) * float(a)
    return total < _CLEARLY_IN_RANGE  # False for NaN


def out_of_range(*values) -> bool:
    """True if an entry of the arrays (or scalars) exceeds ``MAX_MAGNITUDE`` in size, or is NaN."""
    if clearly_in_range(*values):
        return False
    return not magnitude(*values) <= MAX_MAGNITUDE

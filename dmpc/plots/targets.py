"""The setpoints of a run as the figures draw them: the target applied at each step (dashed), the
setpoint requested (dotted, where not free), and the steps where the request changed (faint
vertical lines on the cost, which jumps there: J(k) is measured from the target applied).

Drawn only for a run that requested something (docs/scenarios.md, "Setpoints: `setpoints`"); a run
without setpoints draws as it did before they existed. Matplotlib is passed in (an ``Axes``),
never imported here.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dmpc.records.tracking import is_tracked

TARGET_LABEL = "target (applied)"
SETPOINT_LABEL = "setpoint"
CHANGE_LABEL = "setpoint change"
TARGET_STYLE = dict(color="black", linestyle="--", linewidth=1.1, zorder=2.5)
SETPOINT_STYLE = dict(color="#9467bd", linestyle=":", linewidth=2.6, alpha=0.9, zorder=2.6)
"""The setpoint is drawn over the target, dotted and wider: where the two coincide (a reachable
request once the governor has moved the target there) both stay visible."""
CHANGE_STYLE = dict(color="grey", linestyle="-", linewidth=0.9, alpha=0.45, zorder=0.5)


@dataclass(frozen=True, eq=False)
class Tracked:
    """What a run asked for and the targets it applied, stacked over the subsystems.

    Attributes
    ----------
    setpoint, setpoint_u : ndarray, shape (K, n) and (K, m)
        The components requested at each step, NaN where free.
    reference, reference_u : ndarray, shape (K, n) and (K, m)
        The target of each step's request.
    target, target_u : ndarray, shape (K, n) and (K, m)
        The target each step applied (moved toward the reference by the reference governor).
    """

    setpoint: np.ndarray
    setpoint_u: np.ndarray
    reference: np.ndarray
    reference_u: np.ndarray
    target: np.ndarray
    target_u: np.ndarray

    @classmethod
    def of(cls, arrays: dict) -> "Tracked | None":
        """The tracking arrays of ``arrays`` (names as in trajectory.npz), or None when the run
        requested nothing."""
        if not is_tracked(arrays):
            return None
        return cls(**{key: np.asarray(arrays[key], float) for key in
                      ("setpoint", "setpoint_u", "reference", "reference_u", "target", "target_u")})

    def columns(self, kind: str) -> tuple[np.ndarray, np.ndarray]:
        """(setpoint, target) of the states (``kind`` 'x', (K, n) each) or the inputs ('u', (K, m))."""
        return (self.setpoint, self.target) if kind == "x" else (self.setpoint_u, self.target_u)

    def changes(self) -> np.ndarray:
        """The steps k >= 1 at which the request differs from step k - 1's, shape (c,)."""
        asked = np.hstack([self.setpoint, self.setpoint_u])
        if asked.shape[0] < 2:
            return np.zeros(0, int)
        same = (asked[1:] == asked[:-1]) | (np.isnan(asked[1:]) & np.isnan(asked[:-1]))
        return np.flatnonzero(~same.all(axis=1)) + 1

    def box_offsets(self) -> np.ndarray:
        """The target around which each recorded terminal box lies, shape (K+1, n).

        The records keep alpha(k) relative to the target step k applied. The box of x(K) lies around
        the target of step K, which no step recorded: it is step K-1's when that had reached its
        reference (the governor then applies the reference), else unknown (NaN).
        """
        reached = np.array_equal(self.target[-1], self.reference[-1]) and np.array_equal(
            self.target_u[-1], self.reference_u[-1])
        last = self.target[-1] if reached else np.full(self.target.shape[1], np.nan)
        return np.vstack([self.target, last])


def held(values: np.ndarray) -> np.ndarray:
    """The per-step series ``values`` (K,) with its last value repeated, (K+1,): held over [t_k, t_k+1)
    when drawn with ``drawstyle='steps-post'`` on the times of steps 0 .. K."""
    return np.append(values, values[-1:])


def draw_targets(ax, times: np.ndarray, setpoint: np.ndarray, target: np.ndarray) -> None:
    """On ``ax``, the applied ``target`` of one component (K,) dashed and its ``setpoint`` (K,) dotted
    where it is not free (NaN), both held over each step, on ``times`` (K+1,)."""
    ax.plot(times, held(target), drawstyle="steps-post", label=TARGET_LABEL, **TARGET_STYLE)
    if np.isfinite(setpoint).any():
        ax.plot(times, held(setpoint), drawstyle="steps-post", label=SETPOINT_LABEL, **SETPOINT_STYLE)


def mark_changes(ax, times: np.ndarray) -> None:
    """Faint vertical lines on ``ax`` at the ``times`` (c,) where the setpoint changed, one legend entry."""
    for index, t in enumerate(times):
        ax.axvline(t, label=CHANGE_LABEL if index == 0 else None, **CHANGE_STYLE)


LEGEND_ORDER = (TARGET_LABEL, SETPOINT_LABEL, "bounds")
"""These entries come last in a figure's legend, in this order, after the runs' own lines."""


def unique_legend(axes) -> tuple[list, list[str]]:
    """The legend handles and labels of several axes, each label once: the runs' lines in the order
    first seen, then those of ``LEGEND_ORDER``."""
    seen: dict[str, object] = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            seen.setdefault(label, handle)
    labels = sorted(seen, key=lambda label: LEGEND_ORDER.index(label) + 1 if label in LEGEND_ORDER else 0)
    return [seen[label] for label in labels], labels

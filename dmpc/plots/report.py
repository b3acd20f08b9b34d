"""Figures of a run folder, or of a comparison folder: the paper's figures 1 to 5, and for a run
folder the agents' solves per step.

Reads the records only (``scenario.yaml``, ``design.json``, ``trajectory.npz``,
``summary.json`` and, for a comparison, ``comparison.json``); it never runs anything.
Matplotlib is imported lazily with the Agg backend, so the rest of the package does not pay
for it.

Figures written (PNG, 120 dpi):

- ``fig1_terminal_sets.png``: per subsystem, in the (x_i1, x_i2) plane, the terminal box
  ``||x_i - alpha_i(k)||_inf <= beta(k)`` for every k (colour over k), the ellipse
  ``x_i^T P_i x_i <= r_i(k)`` when the run records levels ``r``, and the state trajectory.
- ``fig2_states.png``: the state components of each subsystem over k.
- ``fig3_inputs.png``: the inputs u_i(k) with the bounds of U_i.
- ``fig4_cost.png``: J(k), on a log scale when it spans more than two decades.

A run that tracked setpoints also shows, in figures 2 and 3, the target applied at each step
(dashed) and the setpoint requested (dotted, where not free), and in figure 4 the steps where the
request changed (faint vertical lines); its terminal boxes in figure 1 lie around the targets
(:mod:`dmpc.plots.targets`).
- ``fig5_S.png``: S(x(k)) = sum_i ||x_i(k)||^2 / |N_i|.
- ``fig6_solves.png`` (a run folder only): per step, the agents that solved their QP, kept their
  plan (an event trigger) or fell back (:mod:`dmpc.plots.solves`).
- ``fig7_estimates.png`` (a run folder with ``estimation`` only): per subsystem the outputs measured
  and their setpoints, the disturbance estimates, and the innovation (:mod:`dmpc.plots.estimates`).
  Figure 2 of such a run also draws the state estimates x^ (dashed) and the outputs measured that
  are a state alone (crosses).

On a comparison folder (``comparison.json`` from ``dmpc compare``), :func:`draw_comparison`
draws the same five figures across the methods: figure 1 sets the tv-box boxes against the
ellipsoid method's ellipses, figures 2 to 5 have one line per method.

At most ``MAX_PANELS`` subsystems get a panel (the first ones, in scenario order); the figure
title says so when some are left out. A subsystem with more than two states is shown by its
first two components (projections of the box and of the ellipse).

Axes count seconds when the scenario has ``dt`` (else steps) and name the states and inputs
with the scenario's names and units, as ``result.plot()`` does: both take their labels from
:mod:`dmpc.core.quantities`.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dmpc.core.errors import InputError
from dmpc.core.quantities import Quantity, time_axis, time_label
from dmpc.core.system import box_hull
from dmpc.methods import DEFAULT_METHOD, METHOD_NAMES
from dmpc.plots.estimates import draw_state_estimates, estimates_figure
from dmpc.plots.solves import Solves, solves_figure
from dmpc.plots.style import bound_lines, panel_grid, positive, use_log
from dmpc.plots.targets import Tracked, draw_targets, mark_changes, unique_legend
from dmpc.records.files import COMPARISON
from dmpc.records.reader import Estimates, RunFolderNotReadable, read_run, tracking_arrays

FIGURES = ("fig1_terminal_sets", "fig2_states", "fig3_inputs", "fig4_cost", "fig5_S")
"""The paper's figures: those of a comparison folder."""
SOLVES_FIGURE = "fig6_solves"
RUN_FIGURES = FIGURES + (SOLVES_FIGURE,)
"""The figures of a run folder."""
ESTIMATES_FIGURE = "fig7_estimates"
"""The figure a run folder with ``estimation`` adds to :data:`RUN_FIGURES`."""
MAX_PANELS = 8
DPI = 120

METHOD_ORDER = METHOD_NAMES
METHOD_STYLE: dict[str, dict[str, Any]] = {
    "tv-box": dict(color="C0", linestyle="-", marker="o"),
    "tv-box-opt": dict(color="C4", linestyle="-", marker="D"),
    "fixed-box": dict(color="C1", linestyle="--", marker="s"),
    "ellipsoid": dict(color="C2", linestyle="-.", marker="^"),
    "ellipsoid-adaptive": dict(color="C3", linestyle=":", marker="v"),
    "centralized": dict(color="black", linestyle=(0, (5, 1, 1, 1)), marker="x"),
}
EXTRA_STYLES: list[dict[str, Any]] = [dict(color=f"C{i}", linestyle="-", marker="d") for i in range(5, 10)]


class ReportError(InputError, ValueError):
    """The folder cannot be drawn: not a run or comparison folder, or incomplete records."""


# ----------------------------------------------------------------------------- reading records
@dataclass
class RunData:
    """The arrays and structure of one run folder that the figures need.

    Attributes
    ----------
    path : Path
        The run folder.
    method : str
        ``summary.json``'s method, or ``"run"`` when it does not say.
    scenario : str
        The scenario's name.
    names : list of str
        Subsystem names, in scenario order.
    n, m : list of int
        States and inputs per subsystem.
    lower, upper : list of ndarray or None
        Per-input bounds of U_i (its bounding box for a polytope); None when unknown.
    P : list of ndarray or None
        P_i from ``design.json``; None when the design is not there.
    x, u : ndarray
        (K+1, n) states and (K, m) inputs.
    alpha, beta, r : ndarray or None
        Terminal box centres (K+1, n) and radii (K+1,), ellipse levels (K+1, M).
    J, S : ndarray
        (K,) and (K+1,); NaN where not recorded.
    states, inputs : list of tuple of Quantity
        Per subsystem, the names, units and bounds of its states and inputs.
    dt : float or None
        The scenario's sampling period in seconds (None: the axes count steps).
    tracked : Tracked or None
        The setpoints requested and the targets applied; None when the run requested nothing.
    solves : Solves or None
        What each agent did at each step: solved, kept its plan or fell back.
    estimates : Estimates or None
        With ``estimation``: the outputs measured, the state and disturbance estimates; None
        without.
    """

    path: Path
    method: str
    scenario: str
    names: list[str]
    n: list[int]
    m: list[int]
    lower: list
    upper: list
    P: list | None
    x: np.ndarray
    u: np.ndarray
    alpha: np.ndarray | None
    beta: np.ndarray | None
    r: np.ndarray | None
    J: np.ndarray
    S: np.ndarray
    states: list[tuple[Quantity, ...]]
    inputs: list[tuple[Quantity, ...]]
    dt: float | None = None
    tracked: Tracked | None = None
    solves: Solves | None = None
    estimates: Estimates | None = None

    @property
    def time_label(self) -> str:
        """``t [s]`` or ``step k``."""
        return time_label(self.dt)

    def times(self, count: int) -> np.ndarray:
        """The time of the first ``count`` steps 0, 1, ..., shape (count,)."""
        return time_axis(count - 1, self.dt)[:count] if count > 0 else np.zeros(0)

    @property
    def M(self) -> int:
        """Number of subsystems."""
        return len(self.names)

    def state_slice(self, i: int) -> slice:
        """Columns of subsystem ``i`` in the global state."""
        start = sum(self.n[:i])
        return slice(start, start + self.n[i])

    def input_slice(self, i: int) -> slice:
        """Columns of subsystem ``i`` in the global input."""
        start = sum(self.m[:i])
        return slice(start, start + self.m[i])

    def box_centres(self) -> np.ndarray | None:
        """The centres of the terminal boxes in the plant's coordinates, shape (K+1, n): alpha, or
        with setpoints alpha around the target of its step (NaN where that target is unknown)."""
        if self.alpha is None or self.tracked is None:
            return self.alpha
        return self.alpha + self.tracked.box_offsets()


def is_comparison_folder(path: Path) -> bool:
    """Whether ``path`` holds a ``comparison.json``."""
    return (Path(path) / COMPARISON).is_file()


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise ReportError(f"cannot read {path}: {exc.strerror}") from None
    except json.JSONDecodeError as exc:
        raise ReportError(f"{path} is not valid JSON ({exc.msg}, line {exc.lineno})") from None
    if not isinstance(data, dict):
        raise ReportError(f"{path}: expected a JSON object")
    return data


def _box_hull(H: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-coordinate bounds of the polytope {v : H v <= h} (inf where unbounded)."""
    return box_hull(H, np.full(h.shape, -np.inf), h)


def _input_bounds(spec) -> tuple[np.ndarray, np.ndarray]:
    if hasattr(spec, "lower"):
        return np.asarray(spec.lower, float), np.asarray(spec.upper, float)
    return _box_hull(np.asarray(spec.H, float), np.asarray(spec.h, float))


def _optional(arrays: dict, key: str, shape0: int) -> np.ndarray | None:
    a = arrays.get(key)
    if a is None or a.shape[0] != shape0 or not np.isfinite(np.asarray(a, float)).any():
        return None
    return np.asarray(a, float)


def _series(arrays: dict, key: str, length: int, fallback=None) -> np.ndarray:
    """A 1-D float series of ``length`` (NaN where absent), from the arrays or a JSON list."""
    out = np.full(length, np.nan)
    values = arrays.get(key)
    if values is None and fallback is not None:
        values = np.array([np.nan if v is None else v for v in fallback], float)
    if values is not None:
        values = np.asarray(values, float).ravel()[:length]
        out[:values.size] = values
    return out


def load_run(path, notes: list[str] | None = None) -> RunData:
    """Read one run folder (``notes`` gets what the reader had to work around).

    Parameters
    ----------
    path : path-like
        A folder written by ``dmpc simulate``, ``dmpc run`` or ``dmpc plant``.

    Returns
    -------
    RunData

    Raises
    ------
    ReportError
        Not a run folder, no ``trajectory.npz``, no completed step, or records inconsistent with
        each other.
    """
    try:
        records = read_run(path, notes)
    except RunFolderNotReadable as exc:
        raise ReportError(str(exc)) from None
    arrays, summary, scenario = records.arrays, records.summary or {}, records.scenario
    x, u = np.asarray(arrays["x"], float), np.asarray(arrays["u"], float)
    if u.shape[0] == 0:
        stopped = summary.get("failure") or summary.get("aborted")
        raise ReportError(f"{records.path}: the run completed no step: there is nothing to draw"
                          + (f" (it stopped: {stopped})" if stopped else ""))
    names = records.names
    lower: list[np.ndarray | None]
    upper: list[np.ndarray | None]
    if scenario is not None:
        bounds = [_input_bounds(s.input) for s in scenario.resolved_subsystems()]
        lower, upper = [b[0] for b in bounds], [b[1] for b in bounds]
    else:
        lower, upper = [None] * len(names), [None] * len(names)
    design = records.design
    P = None
    if design and "P" in design and len(design["P"]) == len(names):
        P = [np.atleast_2d(np.asarray(p, float)) for p in design["P"]]
    steps = u.shape[0]
    states, inputs = records.quantities()
    tracked = Tracked.of(tracking_arrays(arrays, steps, x.shape[1], u.shape[1]))
    method = str(summary.get("method") or "run")
    solves = Solves.of(arrays, summary, _trigger(scenario, arrays), method, steps, len(names))
    return RunData(path=records.path, method=method,
                   scenario=str(summary.get("scenario") or (scenario.name if scenario is not None else records.path.name)),
                   names=names, n=records.n, m=records.m, lower=lower, upper=upper, P=P, x=x, u=u,
                   alpha=_optional(arrays, "alpha", x.shape[0]), beta=_optional(arrays, "beta", x.shape[0]),
                   r=_optional(arrays, "r", x.shape[0]),
                   J=_series(arrays, "J", steps, summary.get("J")),
                   S=_series(arrays, "S", x.shape[0], summary.get("S")),
                   states=[states[name] for name in names], inputs=[inputs[name] for name in names],
                   dt=records.dt, tracked=tracked, solves=solves, estimates=records.estimates(notes))


def _trigger(scenario, arrays: dict) -> str:
    """The run's ``options.trigger``; without its scenario, ``event`` where plans were kept."""
    if scenario is not None:
        return str(scenario.options.trigger)
    return "event" if "kept" in arrays else "always"


@dataclass
class Comparison:
    """The methods of a comparison folder, in a fixed order.

    Attributes
    ----------
    scenario : str
    runs : dict
        method -> RunData, for the methods whose run folder could be read.
    entries : dict
        method -> its entry of ``comparison.json``.
    skipped : dict
        method -> why its run folder was not drawn.
    """

    scenario: str
    runs: dict[str, RunData]
    entries: dict[str, dict]
    skipped: dict[str, str]

    @property
    def reference(self) -> RunData:
        """The run whose structure (names, dimensions, bounds) the panels follow."""
        return self.runs.get(DEFAULT_METHOD) or next(iter(self.runs.values()))


def _method_order(methods) -> list[str]:
    """The known methods in :data:`METHOD_ORDER`, each followed by its runs with another trigger
    (``tv-box+event``, from ``dmpc compare --triggers``), then the others by name."""
    known = [m for base in METHOD_ORDER for m in [base, *sorted(m for m in methods if _base_method(m) == base
                                                                and m != base)] if m in methods]
    return known + sorted(m for m in methods if m not in known)


def _base_method(name: str) -> str:
    """The method of a comparison entry's name: ``tv-box`` for ``tv-box+event``."""
    return name.split("+", 1)[0]


def load_comparison(path) -> Comparison:
    """Read ``comparison.json`` and the run folder of each method in it.

    Parameters
    ----------
    path : path-like
        A folder written by ``dmpc compare``.

    Returns
    -------
    Comparison

    Raises
    ------
    ReportError
        ``comparison.json`` is malformed, or no method's run folder can be read.
    """
    path = Path(path)
    data = _read_json(path / COMPARISON)
    methods = data.get("methods")
    if not isinstance(methods, dict) or not methods:
        raise ReportError(f"{path / COMPARISON}: expected a non-empty object 'methods'")
    runs, entries, skipped = {}, {}, {}
    for method in _method_order(methods):
        entry = methods[method] if isinstance(methods[method], dict) else {}
        entries[method] = entry
        run_dir = path / str(entry.get("run_dir") or method)
        try:
            runs[method] = load_run(run_dir)
        except ReportError as exc:
            skipped[method] = str(exc)
    if not runs:
        raise ReportError(f"{path}: none of the methods' run folders can be read ({'; '.join(skipped.values())})")
    return Comparison(scenario=str(data.get("scenario") or path.name), runs=runs, entries=entries, skipped=skipped)


# ----------------------------------------------------------------------------- shared drawing pieces
def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


STYLE: dict[str, Any] = {"font.size": 9, "axes.titlesize": 10, "axes.labelsize": 9, "legend.fontsize": 8,
         "figure.titlesize": 11, "axes.grid": True, "grid.alpha": 0.3, "lines.linewidth": 1.4,
         "lines.markersize": 3.5}


def _style(method: str) -> dict:
    """The line style of a method: fixed for the known ones, chosen by name for others."""
    if method in METHOD_STYLE:
        return dict(METHOD_STYLE[method])
    if _base_method(method) in METHOD_STYLE:  # another trigger: the method's colour, dotted, open markers
        return dict(METHOD_STYLE[_base_method(method)], linestyle=":", markerfacecolor="none")
    return dict(EXTRA_STYLES[sum(map(ord, method)) % len(EXTRA_STYLES)])


def _layered(style: dict, index: int, count: int) -> dict:
    """Line widths that decrease along the methods, so that lines drawn on top of each other
    (methods that agree) all stay visible."""
    return dict(style, linewidth=1.2 + 0.5 * (count - 1 - index)) if count > 1 else style


def _shown(M: int) -> int:
    return min(M, MAX_PANELS)


def _panel_note(M: int) -> str:
    return f" (first {MAX_PANELS} of {M} subsystems)" if M > MAX_PANELS else ""


def _grid(plt, panels: int, width: float = 3.6, height: float = 3.0, ncols: int | None = None,
          hidden: frozenset[int] | set[int] = frozenset()):
    """:func:`~dmpc.plots.style.panel_grid` with 2 columns up to 4 panels, 4 above."""
    return panel_grid(plt, panels, ncols or (min(panels, 2) if panels <= 4 else 4), width, height, hidden=hidden)


def _save(fig, folder: Path, name: str) -> Path:
    """Write ``folder/name.png`` and release the figure."""
    import matplotlib.pyplot as plt

    target = folder / f"{name}.png"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fig.savefig(target, dpi=DPI)
    except OSError as exc:
        raise ReportError(f"cannot write {target}: {exc.strerror or exc}") from None
    finally:
        plt.close(fig)
    return target


def _ellipse_points(P: np.ndarray, level: float, samples: int = 180) -> np.ndarray:
    """Boundary of the projection of {x : x^T P x <= level} onto the first two coordinates."""
    P2 = np.linalg.inv(np.linalg.inv(P)[:2, :2]) if P.shape[0] > 2 else P
    L = np.linalg.cholesky(P2)
    angles = np.linspace(0.0, 2.0 * np.pi, samples)
    circle = np.vstack([np.cos(angles), np.sin(angles)])
    return math.sqrt(level) * np.linalg.solve(L.T, circle)


def _plane_title(run: RunData, i: int) -> str:
    n = run.n[i]
    extra = "" if n == 2 else (f" (first 2 of {n} states)" if n > 2 else " (1 state: interval over k)")
    return f"subsystem {run.names[i]}{extra}"


def _time_norm(run: RunData, K1: int):
    """Colours over the time of steps 0 .. K1 - 1 (seconds or steps, as the run's axes)."""
    import matplotlib.colors as mcolors

    end = run.times(K1)[-1] if K1 > 1 else 0.0
    return mcolors.Normalize(vmin=0, vmax=end if end > 0 else 1)


# ----------------------------------------------------------------------------- figure 1
@dataclass
class PlaneSet:
    """What figure 1 draws of one ``run``: its ``boxes`` and/or ``ellipses``, and its trajectory's look
    (the ``method``'s ``color``, ``linestyle`` and ``marker``)."""

    run: RunData
    method: str
    boxes: bool = True
    ellipses: bool = True
    color: str = "black"
    linestyle: str = "-"
    marker: str = "o"


def _draw_boxes(ax, run: RunData, i: int, cmap, norm, label: str) -> bool:
    """Terminal boxes of subsystem ``i`` over k; False when the run has none."""
    centres = run.box_centres()
    if centres is None or run.beta is None:
        return False
    from matplotlib.patches import Rectangle

    cols = run.state_slice(i)
    t = run.times(centres.shape[0])
    drawn = False
    for k in range(centres.shape[0]):
        centre, radius = centres[k, cols][:2], run.beta[k]
        if not (np.isfinite(centre).all() and np.isfinite(radius)) or radius < 0:
            continue
        ax.add_patch(Rectangle(centre - radius, 2 * radius, 2 * radius, fill=False, lw=1.0, alpha=0.85,
                               edgecolor=cmap(norm(t[k])), label=label if not drawn else None))
        drawn = True
    return drawn


def _ellipse_levels(run: RunData, i: int) -> list[tuple[int, float]]:
    """(k, r_i(k)) to draw: one level when r_i is constant, every k otherwise."""
    if run.r is None:
        return []
    levels = run.r[:, i] if run.r.ndim == 2 else run.r
    finite = [(k, float(v)) for k, v in enumerate(levels) if np.isfinite(v) and v > 0]
    if finite and np.allclose([v for _, v in finite], finite[0][1], rtol=1e-9, atol=0):
        return finite[:1]
    return finite


def _draw_ellipses(ax, spec: PlaneSet, i: int, cmap, norm, label: str) -> bool:
    """Ellipses x_i^T P_i x_i <= r_i(k); False when the run has no levels or no P.

    A constant level is one ellipse in the method's colour; levels that change with k are one
    ellipse per k, coloured by k like the boxes.
    """
    run = spec.run
    if run.r is None or run.P is None:
        return False
    levels = _ellipse_levels(run, i)
    constant = len(levels) == 1
    t = run.times(run.x.shape[0])
    for j, (k, level) in enumerate(levels):
        pts = _ellipse_points(run.P[i], level)
        colour = spec.color if constant else cmap(norm(t[k]))
        ax.plot(pts[0], pts[1], color=colour, lw=1.8 if constant else 1.0, linestyle="--",
                label=(label + (" (constant r)" if constant else " (r(k), colour = k)")) if j == 0 else None)
    return bool(levels)


def _draw_phase(ax, spec: PlaneSet, i: int, label: str) -> None:
    """The state trajectory x_i(k) in the plane, its start marked with a star."""
    xi = spec.run.x[:, spec.run.state_slice(i)]
    ax.plot(xi[:, 0], xi[:, 1], color=spec.color, linestyle=spec.linestyle, marker=spec.marker,
            lw=1.3, ms=3, label=label, zorder=3)
    ax.plot(xi[0, 0], xi[0, 1], marker="*", ms=11, color=spec.color, mec="white", mew=0.6, ls="none", zorder=4)


def _draw_interval(ax, spec: PlaneSet, i: int, cmap, norm, label: str) -> None:
    """A one-state subsystem: x_i(k) and [alpha_i - beta, alpha_i + beta] over k."""
    run = spec.run
    cols = run.state_slice(i)
    t = run.times(run.x.shape[0])
    centres = run.box_centres()
    if spec.boxes and centres is not None and run.beta is not None:
        centre = centres[:, cols][:, 0]
        ax.vlines(t, centre - run.beta, centre + run.beta, colors=[cmap(norm(v)) for v in t], lw=3, alpha=0.6,
                  label="terminal interval")
    ax.plot(t, run.x[:, cols][:, 0], color=spec.color, linestyle=spec.linestyle, marker=spec.marker, label=label)
    ax.set_xlabel(run.time_label)
    ax.set_ylabel(run.states[i][0].label)


def _finish_plane(ax, run: RunData, i: int) -> None:
    ax.set_xlabel(run.states[i][0].label)
    ax.set_ylabel(run.states[i][1].label)
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.axhline(0, color="grey", lw=0.5)
    ax.axvline(0, color="grey", lw=0.5)


def _colorbar(fig, axes, cmap, norm, label: str) -> None:
    import matplotlib.cm as cm

    bar = fig.colorbar(cm.ScalarMappable(norm=norm, cmap=cmap), ax=axes, shrink=0.8, pad=0.02)
    bar.set_label(f"{label} (colour of the terminal sets)")


def _box_label(run: RunData) -> str:
    """The terminal box in the legend: around alpha, or with setpoints around the target plus alpha."""
    if run.tracked is None:
        return "box $\\|x_i - \\alpha_i(k)\\|_\\infty \\leq \\beta(k)$"
    return "box $\\|x_i - x_{s,i}(k) - \\alpha_i(k)\\|_\\infty \\leq \\beta(k)$ ($x_s$: target)"


def _fig1_panel(ax, specs: list[PlaneSet], i: int, cmap, norm) -> list[str]:
    """One subsystem's panel; returns the methods that had no terminal set to draw."""
    missing = []
    several = len(specs) > 1
    for spec in specs:
        suffix = f", {spec.method}" if several else ""
        label = "$x_i(k)$, star at $x_i(0)$" + suffix
        if spec.run.n[i] == 1:
            _draw_interval(ax, spec, i, cmap, norm, label)
            continue
        has_box = spec.boxes and _draw_boxes(ax, spec.run, i, cmap, norm, _box_label(spec.run) + suffix)
        has_ell = spec.ellipses and _draw_ellipses(ax, spec, i, cmap, norm,
                                                   "ellipse $x_i^T P_i x_i \\leq r_i$" + suffix)
        if not (has_box or has_ell):
            missing.append(spec.method)
        _draw_phase(ax, spec, i, label)
    if specs[0].run.n[i] != 1:
        _finish_plane(ax, specs[0].run, i)
    ax.set_title(_plane_title(specs[0].run, i))
    return missing


def _fig1(plt, specs: list[PlaneSet], title: str, notes: list[str]):
    """Terminal sets and trajectories per subsystem, one legend and one colour bar for k."""
    ref = specs[0].run
    cmap = plt.get_cmap("viridis")
    norm = _time_norm(ref, max(spec.run.x.shape[0] for spec in specs))
    fig, axes = _grid(plt, _shown(ref.M), width=4.0, height=3.6)
    missing = set()
    for i, ax in enumerate(axes):
        missing.update(_fig1_panel(ax, specs, i, cmap, norm))
    notes = notes + [_no_set_note(method) for method in sorted(missing)]
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 3), framealpha=0.9)
    fig.suptitle(title + _panel_note(ref.M) + ("\n" + "; ".join(notes) if notes else ""))
    if len(missing) < len(specs):
        _colorbar(fig, axes, cmap, norm, ref.time_label)
    return fig


def _no_set_note(method: str) -> str:
    if method == "centralized":
        return "centralized: its terminal set is X^f on the whole state, not a set per subsystem"
    return f"{method}: no terminal set recorded"


# ----------------------------------------------------------------------------- figures 2 and 3
MAX_COMPONENTS = 4
"""Components drawn per subsystem (the first ones)."""


def _bounds(run: RunData, kind: str, i: int, j: int) -> tuple[float, float]:
    """The bounds of component ``j`` of subsystem ``i``: X_i's from the quantities, U_i's box hull."""
    if kind == "x":
        q = run.states[i][j]
        return q.lower, q.upper
    if run.lower[i] is None:
        return -np.inf, np.inf
    return float(run.lower[i][j]), float(run.upper[i][j])


def _signal_panel(ax, runs: list[tuple[RunData, str]], i: int, j: int, kind: str) -> None:
    """Component ``j`` of subsystem ``i``'s state or input, one line per run (one run: in the
    component's colour)."""
    for idx, (run, method) in enumerate(runs):
        cols = run.state_slice(i) if kind == "x" else run.input_slice(i)
        values = (run.x if kind == "x" else run.u)[:, cols]
        if j >= values.shape[1]:
            continue
        style = dict(color=f"C{j}", marker="o") if len(runs) == 1 else _layered(_style(method), idx, len(runs))
        series = values[:, j]
        if kind == "u":  # u(k) holds over [t_k, t_k+1): repeat the last one to show its period
            series = np.append(series, series[-1:])
        draw = dict(drawstyle="steps-post") if kind == "u" else {}
        ax.plot(run.times(series.size), series, label=method, **style, **draw)
    if len(runs) == 1 and runs[0][0].tracked is not None:
        _panel_targets(ax, runs[0][0], i, j, kind)
    if len(runs) == 1 and kind == "x":
        draw_state_estimates(ax, runs[0][0], i, j)


def _panel_targets(ax, run: RunData, i: int, j: int, kind: str) -> None:
    """Component ``j`` of subsystem ``i``'s applied target (dashed) and setpoint (dotted, where
    requested), each held over its step."""
    assert run.tracked is not None
    setpoint, target = run.tracked.columns(kind)
    cols = run.state_slice(i) if kind == "x" else run.input_slice(i)
    draw_targets(ax, run.times(target.shape[0] + 1), setpoint[:, cols][:, j], target[:, cols][:, j])


def _blocks_per_row(components: int, subsystems: int) -> int:
    """Subsystems side by side in a row of panels: up to 4 panels to a row (2 for up to 4 scalar
    subsystems)."""
    if components == 1:
        return min(subsystems, 2) if subsystems <= 4 else 4
    return 2 if components == 2 else 1


def _signal_figure(plt, runs: list[tuple[RunData, str]], kind: str, title: str, bounds: bool = True):
    """States (kind 'x') or inputs (kind 'u') over time: a row per subsystem, a panel per
    component, one line per run, the bounds dashed.

    The one drawing of signals: ``dmpc report`` (one run or a comparison) and ``result.plot()``.
    """
    ref = runs[0][0]
    shown = _shown(ref.M)
    dims = [min(d, MAX_COMPONENTS) for d in (ref.n if kind == "x" else ref.m)[:shown]]
    cols = max(dims)
    per_row = _blocks_per_row(cols, shown)
    ncols = per_row * cols
    rows = -(-shown // per_row)
    index = {(i, j): (i // per_row) * ncols + (i % per_row) * cols + j for i in range(shown) for j in range(cols)}
    hidden = {index[i, j] for i in range(shown) for j in range(dims[i], cols)}
    fig, axes = panel_grid(plt, rows * ncols, ncols, 3.4, 2.4, hidden=hidden | set(range(shown * cols, rows * ncols)),
                           sharex=True)
    slots = sorted(((i, j) for i in range(shown) for j in range(dims[i])), key=lambda slot: index[slot])
    full = ref.n if kind == "x" else ref.m
    # one legend below, for the targets' and the estimates' lines too
    tracked = len(runs) == 1 and (ref.tracked is not None or (kind == "x" and ref.estimates is not None))
    legend_done = False
    for ax, (i, j) in zip(axes, slots):
        _signal_panel(ax, runs, i, j, kind)
        bounded = bounds and bound_lines(ax, *_bounds(ref, kind, i, j), label="bounds")
        if bounded and not legend_done and len(runs) == 1 and not tracked:
            ax.legend(loc="best", framealpha=0.85)
            legend_done = True
        ax.axhline(0, color="grey", lw=0.5)
        ax.set_xlabel(ref.time_label)
        ax.set_ylabel((ref.states if kind == "x" else ref.inputs)[i][j].label)
        more = f" (first {MAX_COMPONENTS} of {full[i]})" if j == 0 and full[i] > MAX_COMPONENTS else ""
        ax.set_title(f"subsystem {ref.names[i]}{more}")
    if len(runs) > 1 or tracked:
        handles, labels = unique_legend(axes) if tracked else axes[0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 6), framealpha=0.9)
    fig.suptitle(title + _panel_note(ref.M))
    return fig


# ----------------------------------------------------------------------------- figures 4 and 5
def _series_figure(plt, series: list[tuple[str, np.ndarray, dict, str]], ylabel: str, title: str, ref: RunData,
                   changes: np.ndarray | None = None):
    """One axis, one line per (label, values, style, method), over the time of ``ref``'s axes;
    ``changes``: steps (c,) marked by faint vertical lines (where the setpoint changed)."""
    fig, ax = plt.subplots(figsize=(6.4, 4.0), layout="constrained")
    log = use_log([values for _, values, _, _ in series])
    for index, (label, values, style, _) in enumerate(series):
        y = positive(values) if log else values
        ax.plot(ref.times(len(y)), y, label=label, **_layered(style, index, len(series)))
    marked = changes is not None and changes.size > 0
    if changes is not None and marked:
        mark_changes(ax, ref.times(int(changes.max()) + 1)[changes])
    if log:
        ax.set_yscale("log")
    ax.set_xlabel(ref.time_label)
    ax.set_ylabel(ylabel + (" (log scale)" if log else ""))
    ax.set_title(title)
    if len(series) > 1 or series[0][0] or marked:
        ax.legend(loc="best", framealpha=0.85)
    return fig


def setpoint_changes(run: RunData) -> np.ndarray | None:
    """The steps where ``run``'s setpoint request changed (c,), or None without setpoints."""
    return run.tracked.changes() if run.tracked is not None else None


def _cost_label(method: str, entry: dict) -> str:
    cost = entry.get("closed_loop_cost")
    return method + (f" (closed-loop cost {cost:.6g})" if isinstance(cost, (int, float)) else "")


# ----------------------------------------------------------------------------- entry points
def draw_run(run_dir, fig_dir=None, notes: list[str] | None = None) -> list[Path]:
    """Draw the six figures of one run folder (:data:`RUN_FIGURES`), and with ``estimation`` a seventh
    (:data:`ESTIMATES_FIGURE`).

    Parameters
    ----------
    run_dir : path-like
        A run folder with ``trajectory.npz``.
    fig_dir : path-like, optional
        Where to write the PNG files; default ``run_dir/figures``.
    notes : list of str, optional
        Gets what the reader had to work around (:func:`load_run`).

    Returns
    -------
    list of Path
        The six (seven) files, in figure order.
    """
    run = load_run(run_dir, notes)
    folder = Path(fig_dir) if fig_dir is not None else run.path / "figures"
    plt = _pyplot()
    head = f"{run.scenario}, {run.method}"
    sets = [(run, run.method)]
    paths = []
    with plt.rc_context(STYLE):
        fig1 = _fig1(plt, [PlaneSet(run, run.method)], f"{head}: terminal sets and state trajectories", [])
        paths.append(_save(fig1, folder, FIGURES[0]))
        paths.append(_save(_signal_figure(plt, sets, "x", f"{head}: states"), folder, FIGURES[1]))
        paths.append(_save(_signal_figure(plt, sets, "u", f"{head}: inputs and their bounds"), folder, FIGURES[2]))
        style = dict(_style(run.method), color="C0")
        paths.append(_save(_series_figure(plt, [("", run.J, style, run.method)], "$J(k) = \\sum_i J_i^*(k)$",
                                          f"{head}: optimal cost J(k)", run, setpoint_changes(run)), folder, FIGURES[3]))
        paths.append(_save(_series_figure(plt, [("", run.S, style, run.method)],
                                          "$S(x(k)) = \\sum_i \\|x_i(k)\\|^2 / |N_i|$", f"{head}: S(x(k))", run),
                           folder, FIGURES[4]))
        paths.append(_save(_solves(plt, run, f"{head}: agents solving per step"), folder, SOLVES_FIGURE))
        if run.estimates is not None:
            paths.append(_save(estimates_figure(plt, run, f"{head}: outputs measured and disturbance estimates"
                                                + _panel_note(run.M), _shown(run.M)), folder, ESTIMATES_FIGURE))
    return paths


def _solves(plt, run: RunData, title: str):
    """Figure 6 of a run (:mod:`dmpc.plots.solves`)."""
    assert run.solves is not None
    return solves_figure(plt, run.solves, run.times(run.u.shape[0] + 1), run.names, run.time_label, title)


def _fig1_sets(cmp: Comparison) -> tuple[list[PlaneSet], list[str]]:
    """tv-box's boxes (else tv-box-opt's, else fixed-box's) against the ellipsoid method's ellipses
    (the adaptive one's if it is alone)."""
    specs, notes = [], []
    box = next((m for base in ("tv-box", "tv-box-opt", "fixed-box") for m in cmp.runs if _base_method(m) == base),
               None)
    if box is not None:
        specs.append(PlaneSet(cmp.runs[box], box, boxes=True, ellipses=False))
    ell = next((m for m in ("ellipsoid", "ellipsoid-adaptive") if m in cmp.runs), None)
    if ell is not None:
        specs.append(PlaneSet(cmp.runs[ell], ell, boxes=False, ellipses=True, color="C3", linestyle="--", marker="^"))
        if cmp.runs[ell].r is None:
            notes.append(f"{ell}: no levels r in its trajectory.npz, ellipses not drawn")
    if not specs:
        method = next(iter(cmp.runs))
        specs.append(PlaneSet(cmp.runs[method], method))
        notes.append("no box or ellipsoid method")
    return specs, notes


def _method_series(cmp: Comparison, key: str, label) -> list[tuple[str, np.ndarray, dict, str]]:
    """(label, values, style, method) of J or S for every method, from its run folder or, when that
    could not be read, from its entry in comparison.json."""
    series = []
    for method in cmp.entries:
        if method in cmp.runs:
            values = getattr(cmp.runs[method], key)
        elif isinstance(cmp.entries[method].get(key), list):
            values = np.array([np.nan if v is None else v for v in cmp.entries[method][key]], float)
        else:
            continue
        series.append((label(method), values, _style(method), method))
    return series


def draw_comparison(out_dir, fig_dir=None, notes: list[str] | None = None) -> list[Path]:
    """Draw the five comparison figures of a folder written by ``dmpc compare``.

    Parameters
    ----------
    out_dir : path-like
        The folder with ``comparison.json``; each method's run folder is ``out_dir/<run_dir>``.
    fig_dir : path-like, optional
        Where to write the PNG files; default ``out_dir/figures``.
    notes : list of str, optional
        Receives one line per method whose run folder could not be drawn.

    Returns
    -------
    list of Path
        The five files, in figure order.
    """
    out_dir = Path(out_dir)
    cmp = load_comparison(out_dir)
    folder = Path(fig_dir) if fig_dir is not None else out_dir / "figures"
    plt = _pyplot()
    runs = [(cmp.runs[m], m) for m in cmp.runs]
    skipped = [f"not drawn: {m} ({why})" for m, why in cmp.skipped.items()]
    if notes is not None:
        notes.extend(skipped)
    head = f"{cmp.scenario}, {len(cmp.runs)} method{'s' if len(cmp.runs) > 1 else ''}"
    paths = []
    with plt.rc_context(STYLE):
        specs, set_notes = _fig1_sets(cmp)
        set_notes += [f"{m}: not drawn" for m in cmp.skipped]
        paths.append(_save(_fig1(plt, specs, f"{cmp.scenario}: terminal sets, "
                                 + " against ".join(spec.method for spec in specs), set_notes), folder, FIGURES[0]))
        paths.append(_save(_signal_figure(plt, runs, "x", f"{head}: states"), folder, FIGURES[1]))
        paths.append(_save(_signal_figure(plt, runs, "u", f"{head}: inputs and their bounds"), folder, FIGURES[2]))
        J = _method_series(cmp, "J", lambda m: _cost_label(m, cmp.entries[m]))
        paths.append(_save(_series_figure(plt, J, "$J(k)$", f"{cmp.scenario}: cost J(k) of each method",
                                          cmp.reference), folder, FIGURES[3]))
        S = _method_series(cmp, "S", str)
        paths.append(_save(_series_figure(plt, S, "$S(x(k)) = \\sum_i \\|x_i(k)\\|^2 / |N_i|$",
                                          f"{cmp.scenario}: S(x(k)) of each method", cmp.reference), folder, FIGURES[4]))
    return paths


def draw(path, fig_dir=None, notes: list[str] | None = None) -> list[Path]:
    """Draw the comparison figures of a comparison folder, else the figures of a run folder.

    Parameters
    ----------
    path : path-like
        A run folder, or a folder with ``comparison.json``.
    fig_dir : path-like, optional
        Where to write the PNG files; default ``path/figures``.
    notes : list of str, optional
        Receives what could not be drawn (comparison folders).

    Returns
    -------
    list of Path
        The files, in figure order: six for a run folder (seven with ``estimation``), five for a
        comparison folder.
    """
    path = Path(path)
    if not path.exists():
        raise ReportError(f"{path} does not exist")
    if is_comparison_folder(path):
        return draw_comparison(path, fig_dir, notes)
    return draw_run(path, fig_dir, notes)

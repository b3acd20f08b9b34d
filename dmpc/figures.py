"""Figures of a run folder, or of a comparison folder: the paper's figures 1 to 5.

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
- ``fig5_S.png``: S(x(k)) = sum_i ||x_i(k)||^2 / |N_i|.

On a comparison folder (``comparison.json`` from ``dmpc compare``), :func:`draw_comparison`
draws the same five figures across the methods: figure 1 sets the tv-box boxes against the
ellipsoid method's ellipses, figures 2 to 5 have one line per method.

At most ``MAX_PANELS`` subsystems get a panel (the first ones, in scenario order); the figure
title says so when some are left out. A subsystem with more than two states is shown by its
first two components (projections of the box and of the ellipse).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dmpc.records.files import COMPARISON, DESIGN, SCENARIO, STEP_LOG, SUMMARY, TRAJECTORY
from dmpc.records.step_log import arrays_from_log, read_step_log
from dmpc.scenario import load_scenario
from dmpc.scenario.load import ScenarioError
from dmpc.system import box_hull

FIGURES = ("fig1_terminal_sets", "fig2_states", "fig3_inputs", "fig4_cost", "fig5_S")
MAX_PANELS = 8
DPI = 120
LOG_DECADES = 2.0
"""J and S are drawn on a log scale when max/min over their positive values exceeds 10**LOG_DECADES."""

METHOD_ORDER = ("tv-box", "tv-box-opt", "fixed-box", "ellipsoid", "ellipsoid-adaptive", "centralized")
METHOD_STYLE = {
    "tv-box": dict(color="C0", linestyle="-", marker="o"),
    "tv-box-opt": dict(color="C4", linestyle="-", marker="D"),
    "fixed-box": dict(color="C1", linestyle="--", marker="s"),
    "ellipsoid": dict(color="C2", linestyle="-.", marker="^"),
    "ellipsoid-adaptive": dict(color="C3", linestyle=":", marker="v"),
    "centralized": dict(color="black", linestyle=(0, (5, 1, 1, 1)), marker="x"),
}
EXTRA_STYLES = [dict(color=f"C{i}", linestyle="-", marker="d") for i in range(5, 10)]


class ReportError(ValueError):
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


def _check_run_folder(path: Path) -> None:
    if not path.is_dir():
        raise ReportError(f"{path} is not a folder")
    markers = (TRAJECTORY, STEP_LOG, SUMMARY, DESIGN, SCENARIO)
    if not any((path / name).exists() for name in markers):
        raise ReportError(f"{path} is not a run folder (no {TRAJECTORY}, {SCENARIO} or {DESIGN}) "
                          f"nor a comparison folder (no {COMPARISON})")
    if not (path / TRAJECTORY).is_file() and not (path / STEP_LOG).is_file():
        raise ReportError(f"{path} has no {TRAJECTORY}: the run was not completed or is still running "
                          "(it is written at the end of a run)")


def _load_arrays(path: Path, notes: list[str] | None = None) -> dict[str, np.ndarray]:
    """trajectory.npz, or (a run that ended before writing it) the arrays rebuilt from steps.jsonl,
    said in ``notes``."""
    if not (path / TRAJECTORY).is_file():
        try:
            log = read_step_log(path / STEP_LOG)
        except (OSError, ValueError) as exc:
            raise ReportError(f"{path / STEP_LOG} cannot be read ({exc})") from None
        if not log.steps:
            raise ReportError(f"{path} has no {TRAJECTORY} and no completed step in {STEP_LOG}")
        if notes is not None:
            notes.append(f"{path}: no {TRAJECTORY} (the run did not finish); drawn from the {len(log.steps)} "
                         f"steps of {STEP_LOG}" + (f"; {log.note}" if log.partial else ""))
        return arrays_from_log(log)
    try:
        with np.load(path / TRAJECTORY) as npz:
            arrays = {key: npz[key] for key in npz.files}
    except (OSError, ValueError, EOFError) as exc:
        raise ReportError(f"{path / TRAJECTORY} cannot be read ({exc})") from None
    for key in ("x", "u"):
        if key not in arrays or arrays[key].ndim != 2:
            raise ReportError(f"{path / TRAJECTORY} has no 2-D array {key!r}: not a run's trajectory")
    return arrays


def _box_hull(H: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-coordinate bounds of the polytope {v : H v <= h} (inf where unbounded)."""
    return box_hull(H, np.full(h.shape, -np.inf), h)


def _input_bounds(spec) -> tuple[np.ndarray, np.ndarray]:
    if hasattr(spec, "lower"):
        return np.asarray(spec.lower, float), np.asarray(spec.upper, float)
    return _box_hull(np.asarray(spec.H, float), np.asarray(spec.h, float))


def _structure_from_scenario(path: Path) -> dict | None:
    """Names, dimensions and input bounds from the run's resolved ``scenario.yaml``."""
    file = path / SCENARIO
    if not file.is_file():
        return None

    try:
        scn = load_scenario(file)
    except (ScenarioError, ValueError) as exc:
        raise ReportError(f"{file}: {exc}") from None
    subs = scn.resolved_subsystems()
    bounds = [_input_bounds(s.input) for s in subs]
    return dict(scenario=scn.name, names=[s.name for s in subs], n=[s.n for s in subs], m=[s.m for s in subs],
                lower=[b[0] for b in bounds], upper=[b[1] for b in bounds])


def _structure_from_design(design: dict | None, path: Path) -> dict:
    """Dimensions from ``design.json``'s gains (K_i is m_i x n_i) when there is no scenario.yaml."""
    if not design or "K" not in design:
        raise ReportError(f"{path} has neither scenario.yaml nor design.json: the subsystems are unknown")
    K = [np.atleast_2d(np.asarray(k, float)) for k in design["K"]]
    M = len(K)
    return dict(scenario=path.name, names=[str(i + 1) for i in range(M)], n=[k.shape[1] for k in K],
                m=[k.shape[0] for k in K], lower=[None] * M, upper=[None] * M)


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
        Not a run folder, no ``trajectory.npz``, or records inconsistent with each other.
    """
    path = Path(path)
    _check_run_folder(path)
    arrays = _load_arrays(path, notes)
    design = _read_json(path / DESIGN) if (path / DESIGN).is_file() else None
    summary = _read_json(path / SUMMARY) if (path / SUMMARY).is_file() else {}
    info = _structure_from_scenario(path) or _structure_from_design(design, path)
    x, u = np.asarray(arrays["x"], float), np.asarray(arrays["u"], float)
    if x.shape[1] != sum(info["n"]) or u.shape[1] != sum(info["m"]):
        raise ReportError(f"{path}: trajectory.npz has {x.shape[1]} states and {u.shape[1]} inputs, the scenario "
                          f"{sum(info['n'])} and {sum(info['m'])}")
    P = None
    if design and "P" in design and len(design["P"]) == len(info["names"]):
        P = [np.atleast_2d(np.asarray(p, float)) for p in design["P"]]
    steps = u.shape[0]
    return RunData(path=path, method=str(summary.get("method") or "run"),
                   scenario=str(summary.get("scenario") or info["scenario"]), names=info["names"], n=info["n"],
                   m=info["m"], lower=info["lower"], upper=info["upper"], P=P, x=x, u=u,
                   alpha=_optional(arrays, "alpha", x.shape[0]), beta=_optional(arrays, "beta", x.shape[0]),
                   r=_optional(arrays, "r", x.shape[0]),
                   J=_series(arrays, "J", steps, summary.get("J")),
                   S=_series(arrays, "S", x.shape[0], summary.get("S")))


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
        return self.runs.get("tv-box") or next(iter(self.runs.values()))


def _method_order(methods) -> list[str]:
    known = [m for m in METHOD_ORDER if m in methods]
    return known + sorted(m for m in methods if m not in METHOD_ORDER)


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


STYLE = {"font.size": 9, "axes.titlesize": 10, "axes.labelsize": 9, "legend.fontsize": 8,
         "figure.titlesize": 11, "axes.grid": True, "grid.alpha": 0.3, "lines.linewidth": 1.4,
         "lines.markersize": 3.5}


def _style(method: str) -> dict:
    """The line style of a method: fixed for the known ones, chosen by name for others."""
    if method in METHOD_STYLE:
        return dict(METHOD_STYLE[method])
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
          hidden: set[int] = frozenset()):
    """A figure with ``panels`` axes in a grid (2 columns up to 4 panels, 4 above).

    Returns the figure and the visible axes in order; slots past ``panels`` and those in
    ``hidden`` are switched off.
    """
    ncols = ncols or (min(panels, 2) if panels <= 4 else 4)
    nrows = math.ceil(panels / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(width * ncols, height * nrows + 0.6), squeeze=False,
                             layout="constrained")
    flat = list(axes.ravel())
    for index, ax in enumerate(flat):
        if index >= panels or index in hidden:
            ax.set_visible(False)
    return fig, [ax for index, ax in enumerate(flat[:panels]) if index not in hidden]


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


def _use_log(values: list[np.ndarray]) -> bool:
    """Log scale when the positive finite values span more than LOG_DECADES decades."""
    data = np.concatenate([np.asarray(v, float).ravel() for v in values]) if values else np.array([])
    pos = data[np.isfinite(data) & (data > 0)]
    return pos.size > 1 and math.log10(pos.max() / pos.min()) > LOG_DECADES


def _positive(values: np.ndarray) -> np.ndarray:
    """The values with the non-positive ones masked (NaN), for a log axis."""
    out = np.asarray(values, float).copy()
    out[~(out > 0)] = np.nan
    return out


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


def _k_norm(K1: int):
    import matplotlib.colors as mcolors

    return mcolors.Normalize(vmin=0, vmax=max(K1 - 1, 1))


# ----------------------------------------------------------------------------- figure 1
@dataclass
class PlaneSet:
    """What figure 1 draws of one run: its boxes and/or ellipses, and its trajectory's look."""

    run: RunData
    method: str
    boxes: bool = True
    ellipses: bool = True
    color: str = "black"
    linestyle: str = "-"
    marker: str = "o"


def _draw_boxes(ax, run: RunData, i: int, cmap, norm, label: str) -> bool:
    """Terminal boxes of subsystem ``i`` over k; False when the run has none."""
    if run.alpha is None or run.beta is None:
        return False
    from matplotlib.patches import Rectangle

    cols = run.state_slice(i)
    drawn = False
    for k in range(run.alpha.shape[0]):
        centre, radius = run.alpha[k, cols][:2], run.beta[k]
        if not (np.isfinite(centre).all() and np.isfinite(radius)) or radius < 0:
            continue
        ax.add_patch(Rectangle(centre - radius, 2 * radius, 2 * radius, fill=False, lw=1.0, alpha=0.85,
                               edgecolor=cmap(norm(k)), label=label if not drawn else None))
        drawn = True
    return drawn


def _ellipse_levels(run: RunData, i: int) -> list[tuple[int, float]]:
    """(k, r_i(k)) to draw: one level when r_i is constant, every k otherwise."""
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
    for j, (k, level) in enumerate(levels):
        pts = _ellipse_points(run.P[i], level)
        colour = spec.color if constant else cmap(norm(k))
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
    k = np.arange(run.x.shape[0])
    if spec.boxes and run.alpha is not None and run.beta is not None:
        centre = run.alpha[:, cols][:, 0]
        ax.vlines(k, centre - run.beta, centre + run.beta, colors=[cmap(norm(j)) for j in k], lw=3, alpha=0.6,
                  label="terminal interval")
    ax.plot(k, run.x[:, cols][:, 0], color=spec.color, linestyle=spec.linestyle, marker=spec.marker, label=label)
    ax.set_xlabel("step k")
    ax.set_ylabel(f"$x_{{{run.names[i]},1}}$")


def _finish_plane(ax, run: RunData, i: int) -> None:
    ax.set_xlabel(f"$x_{{{run.names[i]},1}}$")
    ax.set_ylabel(f"$x_{{{run.names[i]},2}}$")
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.axhline(0, color="grey", lw=0.5)
    ax.axvline(0, color="grey", lw=0.5)


def _colorbar(fig, axes, cmap, norm) -> None:
    import matplotlib.cm as cm

    bar = fig.colorbar(cm.ScalarMappable(norm=norm, cmap=cmap), ax=axes, shrink=0.8, pad=0.02)
    bar.set_label("step k (colour of the terminal sets)")


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
        has_box = spec.boxes and _draw_boxes(ax, spec.run, i, cmap, norm,
                                             "box $\\|x_i - \\alpha_i(k)\\|_\\infty \\leq \\beta(k)$" + suffix)
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
    norm = _k_norm(max(spec.run.x.shape[0] for spec in specs))
    fig, axes = _grid(plt, _shown(ref.M), width=4.0, height=3.6)
    missing = set()
    for i, ax in enumerate(axes):
        missing.update(_fig1_panel(ax, specs, i, cmap, norm))
    notes = notes + [_no_set_note(method) for method in sorted(missing)]
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 3), framealpha=0.9)
    fig.suptitle(title + _panel_note(ref.M) + ("\n" + "; ".join(notes) if notes else ""))
    if len(missing) < len(specs):
        _colorbar(fig, axes, cmap, norm)
    return fig


def _no_set_note(method: str) -> str:
    if method == "centralized":
        return "centralized: its terminal set is X^f on the whole state, not a set per subsystem"
    return f"{method}: no terminal set recorded"


# ----------------------------------------------------------------------------- figures 2 and 3
def _bounds_lines(ax, run: RunData, i: int, j: int) -> None:
    lower, upper = run.lower[i], run.upper[i]
    if lower is None:
        return
    for value, name in ((upper[j], "upper"), (lower[j], "lower")):
        if np.isfinite(value):
            ax.axhline(value, color="red", lw=1.0, linestyle="--",
                       label="bounds of $U_i$" if name == "upper" else None)


def _signal_panel(ax, runs: list[tuple[RunData, str]], i: int, j: int, kind: str, component_styles: bool) -> None:
    """One panel: component ``j`` of subsystem ``i``'s state or input, one line per run."""
    for idx, (run, method) in enumerate(runs):
        cols = run.state_slice(i) if kind == "x" else run.input_slice(i)
        values = (run.x if kind == "x" else run.u)[:, cols]
        if j >= values.shape[1]:
            continue
        style = _layered(_style(method), idx, len(runs))
        if component_styles:
            style = dict(color=f"C{j}", linestyle=["-", "--", "-.", ":"][j % 4], marker="o")
        single = values.shape[1] == 1
        label = (f"${kind}_i$" if single else f"${kind}_{{i,{j + 1}}}$") \
            if component_styles else method
        steps = np.arange(values.shape[0])
        draw = dict(drawstyle="steps-post") if kind == "u" else {}
        ax.plot(steps, values[:, j], label=label, **style, **draw)


def _comparison_panels(dims: list[int], shown: int, cap: int, ncols: int) -> list[tuple[int, int] | None]:
    """Panel slots (subsystem, component), row-major: one row per component, one column per
    subsystem, in blocks of ``ncols`` subsystems; None is an empty slot."""
    slots: list[tuple[int, int] | None] = []
    for first in range(0, shown, ncols):
        block = range(first, min(first + ncols, shown))
        for j in range(max(min(dims[i], cap) for i in block)):
            row = [(i, j) if j < min(dims[i], cap) else None for i in block]
            slots.extend(row + [None] * (ncols - len(row)))
    return slots


def _signal_title(name: str, j: int | None, dim: int, cap: int, what: str) -> str:
    if j is None:
        return f"subsystem {name}" + (f" (first {cap} of {dim} {what}s)" if dim > cap else "")
    return f"subsystem {name}" + (f", {what} {j + 1}" if dim > 1 else "")


def _signal_figure(plt, runs: list[tuple[RunData, str]], kind: str, title: str):
    """States (kind 'x') or inputs (kind 'u') over k.

    One run: a panel per subsystem with its components (up to 4). Several runs: a panel per
    subsystem and component (up to 2), one line per run.
    """
    ref = runs[0][0]
    shown = _shown(ref.M)
    dims = ref.n if kind == "x" else ref.m
    single = len(runs) == 1
    cap = 4 if single else 2
    if single:
        slots = [(i, None) for i in range(shown)]
        fig, axes = _grid(plt, shown, width=4.2, height=2.8)
    else:
        scalar = max(dims[:shown]) == 1
        ncols = min(shown, 2) if scalar and shown <= 4 else min(shown, 4)
        slots = _comparison_panels(dims, shown, cap, ncols)
        hidden = {index for index, slot in enumerate(slots) if slot is None}
        fig, axes = _grid(plt, len(slots), width=3.6 if scalar else 3.4, height=2.7, ncols=ncols, hidden=hidden)
        slots = [slot for slot in slots if slot is not None]
    what = "state" if kind == "x" else "input"
    for ax, (i, j) in zip(axes, slots):
        for comp in range(min(dims[i], cap)) if j is None else [j]:
            _signal_panel(ax, runs, i, comp, kind, component_styles=single)
            if kind == "u":
                _bounds_lines(ax, ref, i, comp)
        ax.axhline(0, color="grey", lw=0.5)
        ax.set_xlabel("step k")
        index = "" if j is None or dims[i] == 1 else f",{j + 1}"
        ax.set_ylabel(f"${kind}_{{{ref.names[i]}{index}}}(k)$")
        ax.set_title(_signal_title(ref.names[i], j, dims[i], cap, what))
    if single:
        axes[0].legend(loc="best", framealpha=0.85)
    else:
        handles, labels = axes[0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 6), framealpha=0.9)
    fig.suptitle(title + _panel_note(ref.M))
    return fig


# ----------------------------------------------------------------------------- figures 4 and 5
def _series_figure(plt, series: list[tuple[str, np.ndarray, dict, str]], ylabel: str, title: str):
    """One axis, one line per (label, values, style, method)."""
    fig, ax = plt.subplots(figsize=(6.4, 4.0), layout="constrained")
    log = _use_log([values for _, values, _, _ in series])
    for index, (label, values, style, _) in enumerate(series):
        y = _positive(values) if log else values
        ax.plot(np.arange(len(y)), y, label=label, **_layered(style, index, len(series)))
    if log:
        ax.set_yscale("log")
    ax.set_xlabel("step k")
    ax.set_ylabel(ylabel + (" (log scale)" if log else ""))
    ax.set_title(title)
    if len(series) > 1 or series[0][0]:
        ax.legend(loc="best", framealpha=0.85)
    return fig


def _cost_label(method: str, entry: dict) -> str:
    cost = entry.get("closed_loop_cost")
    return method + (f" (closed-loop cost {cost:.6g})" if isinstance(cost, (int, float)) else "")


# ----------------------------------------------------------------------------- entry points
def draw_run(run_dir, fig_dir=None, notes: list[str] | None = None) -> list[Path]:
    """Draw the five figures of one run folder.

    Parameters
    ----------
    run_dir : path-like
        A run folder with ``trajectory.npz``.
    fig_dir : path-like, optional
        Where to write the PNG files; default ``run_dir/figures``.

    Returns
    -------
    list of Path
        The five files, in figure order.
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
                                          f"{head}: optimal cost J(k)"), folder, FIGURES[3]))
        paths.append(_save(_series_figure(plt, [("", run.S, style, run.method)],
                                          "$S(x(k)) = \\sum_i \\|x_i(k)\\|^2 / |N_i|$", f"{head}: S(x(k))"),
                           folder, FIGURES[4]))
    return paths


def _fig1_sets(cmp: Comparison) -> tuple[list[PlaneSet], list[str]]:
    """tv-box's boxes (else tv-box-opt's, else fixed-box's) against the ellipsoid method's ellipses
    (the adaptive one's if it is alone)."""
    specs, notes = [], []
    box = next((m for m in ("tv-box", "tv-box-opt", "fixed-box") if m in cmp.runs), None)
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
        paths.append(_save(_series_figure(plt, J, "$J(k)$", f"{cmp.scenario}: cost J(k) of each method"),
                           folder, FIGURES[3]))
        S = _method_series(cmp, "S", str)
        paths.append(_save(_series_figure(plt, S, "$S(x(k)) = \\sum_i \\|x_i(k)\\|^2 / |N_i|$",
                                          f"{cmp.scenario}: S(x(k)) of each method"), folder, FIGURES[4]))
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
        The five files, in figure order.
    """
    path = Path(path)
    if not path.exists():
        raise ReportError(f"{path} does not exist")
    if is_comparison_folder(path):
        return draw_comparison(path, fig_dir, notes)
    return draw_run(path, fig_dir, notes)

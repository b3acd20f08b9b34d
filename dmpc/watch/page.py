"""The page: one Bokeh document per browser tab, kept up to date from a RunState.

A timer of the document reads what the state gained since the last read and streams it into
the plots' data sources; nothing on the page can reach the run. The slider picks the step k
shown: the plots show the run up to k, the readout the values at k, and the agent table and
the graph the agents' states at k. While the slider stays at the newest step it follows the
run as it goes; the replay button plays the run on from the slider's step (from the start when
the slider is at the end).

Once a step arrives with targets (the run tracks setpoints), each subsystem's state and input
plots show the target applied (dashed) and the setpoint requested (dotted, where not free), each
in its component's colour; before that, and in a run without setpoints, those lines and their
legend entries stay hidden.

In a run with ``estimation`` each subsystem's state plot also shows the estimates x^ the
controllers worked from (dashed, thinner) and the outputs measured that are a state alone
(crosses); a plot beside it the disturbance estimates d^, and one more the outputs that measure
a combination of states, where there are any. A run without estimation has none of these plots.
"""
from __future__ import annotations

import bisect
import html
import math
from typing import Any, Literal

from bokeh.layouts import column, gridplot, row
from bokeh.models import ColumnDataSource, HoverTool, InlineStyleSheet, Range1d

# from their own modules: bokeh.models builds __all__ of these at import, which a type checker cannot read
from bokeh.models.annotations.geometry import Span
from bokeh.models.annotations.labels import Title
from bokeh.models.annotations.legends import LegendItem
from bokeh.models.widgets.buttons import Toggle
from bokeh.models.widgets.markups import Div
from bokeh.models.widgets.sliders import Slider
from bokeh.palettes import Category10_10
from bokeh.plotting import figure

from dmpc.bus import keys
from dmpc.watch.meta import RunMeta
from dmpc.watch.state import RunState, Snapshot, StateRow, StepRow
from dmpc.watch.views import (
    AgentHistory,
    agent_states,
    agent_table,
    graph_tables,
    readout_html,
    summary_html,
    table_html,
    verdict_of,
)

SHOWN = 8  # subsystems with their own plots (the first ones, in scenario order)
TICK_MS = 500  # the page is redrawn at most this often: each redraw costs the browser tens of ms
PLAY_MS = 150
WINDOW = 20_000  # rows a plot holds at most: a longer run shows its latest steps
BOUND = dict(line_color="#d62728", line_dash="dashed", line_width=1.5)
SIGNAL_HEIGHT = 255  # a subsystem's plots: their legend takes a row below
TARGET = dict(line_dash="dashed", line_width=1.5)
SETPOINT = dict(line_dash="dotted", line_width=3, line_alpha=0.9)
ESTIMATE: dict[str, Any] = dict(line_dash=[7, 4], line_width=1.5, line_alpha=0.85)
"""x^ beside the state: dashed, thinner than the state's line and in its colour."""
MEASURED: dict[str, Any] = dict(marker="x", size=7, line_width=1.5, alpha=0.8)
"""The outputs measured: crosses."""
TABLES = """
table.dmpc-agents, table.dmpc-readout, .dmpc-summary table {border-collapse: collapse; font-size: 10pt}
table.dmpc-agents td, table.dmpc-agents th {border-bottom: 1px solid #ddd; padding: 3px 10px; text-align: left}
table.dmpc-readout td, table.dmpc-readout th, .dmpc-summary td {padding: 1px 12px 1px 0; text-align: left}
"""


def _figure(title: str, x_range: Range1d, y_axis_type: Literal["linear", "log"] = "linear",
            height: int = 230) -> figure:
    fig = figure(title=Title(text=title, text_font_size="11pt"), height=height, width=360, x_axis_label="k",
                 y_axis_type=y_axis_type, x_range=x_range, tools="pan,wheel_zoom,box_zoom,reset,save",
                 toolbar_location="right")
    return fig


class WatchPage:
    """The live view of one run in one browser tab.

    Parameters
    ----------
    doc : bokeh.document.Document
    state : RunState
    live : bool
        The run is watched over the bus (the page says so, and follows the agents' liveliness).
    """

    def __init__(self, doc, state: RunState, live: bool) -> None:
        self.doc = doc
        self.state = state
        self.live = live
        self.epoch = -1
        self.version = -1
        self.state_rows: list[StateRow] = []
        self.step_rows: list[StepRow] = []
        self.state_ks: list[int] = []
        self.step_ks: list[int] = []
        self.shown_states = 0
        self.shown_steps = 0
        self.follow = True
        self.built = False
        self._meta: RunMeta | None = None
        self.snap: Snapshot | None = None
        self._history: AgentHistory | None = None
        # (subsystem, 'x' or 'u', 'target' or 'setpoint', its lines and legend item): shown once tracked
        self.tracking: list[tuple[int, str, str, list]] = []
        self.tracked = False  # a step with targets has arrived: their sources are filled from then on
        self._play = None
        # the Divs that change with every step have a fixed size: new text then redraws the Div
        # alone, not the whole layout
        self.header = Div(name="header", width=1450, height=64)
        self.counter = Div(name="step-counter", width=1000, height=36, styles={"font-size": "16pt"})
        self.status = Div(name="status", width=1000, height=20)
        self.root = column(self.header, self.counter, self.status, name="root")
        doc.title = "dmpc watch"
        doc.add_root(self.root)
        doc.add_periodic_callback(self.tick, TICK_MS)
        self.tick()

    @property
    def meta(self) -> RunMeta:
        """The run's description; the page is built once it has come."""
        if self._meta is None:
            raise RuntimeError("the page is not built yet: the run's description has not come")
        return self._meta

    @property
    def history(self) -> AgentHistory:
        """The agents' counts over the steps (once the page is built)."""
        if self._history is None:
            raise RuntimeError("the page is not built yet: the run's description has not come")
        return self._history

    # -- building ----------------------------------------------------------------------------
    def _build(self, meta: RunMeta) -> None:
        self._meta = meta
        self._history = AgentHistory(meta)
        self.slider = Slider(start=0, end=1, value=0, step=1, title="step k", name="step-slider", width=600,
                             disabled=True)
        self.slider.on_change("value", lambda attr, old, new: self._on_slider(new))
        self.play = Toggle(label="▶ replay", name="play", width=110, button_type="primary")
        self.play.on_change("active", lambda attr, old, new: self._on_play(new))
        tables = InlineStyleSheet(css=TABLES)
        scroll: dict[str, str | None] = {"overflow-y": "auto"}
        rows = min(meta.M, SHOWN)
        # with estimation, more columns: wider, and rows of two lines
        self.readout = Div(name="readout", width=950 if meta.estimation else 700,
                           height=50 + (46 if meta.estimation else 22) * rows, stylesheets=[tables], styles=scroll)
        self.summary = Div(name="summary", width=600, stylesheets=[tables])  # changes once, at the end
        self.cursors: list[Span] = []
        steps = ColumnDataSource({"k": [0, max(meta.steps, 1)]}, name="step-range")
        # shared: zoom one, zoom all
        x_range = Range1d(start=0, end=max(meta.steps, 1), bounds=(-1, max(meta.steps, 1) + 1))

        def bound_line(fig, value: float) -> None:
            # a glyph, not a Span: the y range then includes the bound
            column = f"bound{len(steps.data)}"
            steps.data[column] = [value, value]
            fig.line("k", column, source=steps, **BOUND)

        self.cost = ColumnDataSource({"k": [], "J": []}, name="cost")
        fig_cost = _figure("cost J(k)", x_range, y_axis_type="log")
        fig_cost.line("k", "J", source=self.cost, line_width=2)
        fig_cost.scatter("k", "J", source=self.cost, size=4)
        self.terminal = ColumnDataSource(self._terminal_columns([]), name="terminal")
        fig_terminal = _figure("terminal box: β(k) and ‖α_i(k)‖∞", x_range)
        fig_terminal.line("k", "beta", source=self.terminal, line_width=2.5, color="black", legend_label="β")
        for i, sub in enumerate(meta.subsystems[:SHOWN]):
            fig_terminal.line("k", f"a{i}", source=self.terminal, color=Category10_10[i % 10],
                              legend_label=f"‖α_{sub.name}‖∞")
        fig_terminal.legend.label_text_font_size = "8pt"
        fig_terminal.legend.click_policy = "hide"

        self.nodes = ColumnDataSource(name="graph-nodes")
        self.edges = ColumnDataSource(name="graph-edges")
        self._update_graph()
        fig_graph = figure(title="communication graph", height=300, width=300, tools="hover,save",
                           x_range=Range1d(start=-1.35, end=1.35), y_range=Range1d(start=-1.35, end=1.35),
                           toolbar_location=None)
        fig_graph.axis.visible = False
        fig_graph.grid.visible = False
        edges = fig_graph.segment("x0", "y0", "x1", "y1", source=self.edges, line_color="color", line_width=3,
                                  line_dash="dash")
        nodes = fig_graph.scatter("x", "y", source=self.nodes, size=26, fill_color="color", line_color="black")
        fig_graph.text("x", "y", text="name", source=self.nodes, text_align="center", text_baseline="middle",
                       text_font_size="9pt", text_color="white")
        hover = fig_graph.select_one({"type": HoverTool})
        assert isinstance(hover, HoverTool)  # tools="hover,save" above
        hover.renderers = [nodes, edges]
        hover.tooltips = [("", "@name @link"), ("state", "@state"), ("faults", "@faults")]

        self.agents = Div(name="agents", width=1300, height=min(70 + 27 * meta.M, 600), stylesheets=[tables],
                          styles=scroll)
        self._update_agents()

        self.states: list[ColumnDataSource] = []
        self.inputs: list[ColumnDataSource] = []
        self.targets: list[ColumnDataSource] = []
        self.estimates: list[ColumnDataSource] = []  # a run with estimation only
        panels = []
        rows_of_panels: list[list] = []
        for i, sub in enumerate(meta.subsystems[:SHOWN]):
            # columns x1 … and u1 … whatever the scenario calls them: its names go in the legends
            states = ColumnDataSource({"k": [], **{f"x{j + 1}": [] for j in range(sub.n)}}, name=f"states-{sub.name}")
            inputs = ColumnDataSource({"k": [], **{f"u{j + 1}": [] for j in range(sub.m)}}, name=f"inputs-{sub.name}")
            self.states.append(states)
            self.inputs.append(inputs)
            fig_x = _figure(f"subsystem {sub.name}: states x(k)", x_range, height=SIGNAL_HEIGHT)
            for j in range(sub.n):
                fig_x.line("k", f"x{j + 1}", source=states, color=Category10_10[j % 10], line_width=2,
                           legend_label=sub.state_label(j))
                fig_x.scatter("k", f"x{j + 1}", source=states, color=Category10_10[j % 10], size=3)
                for bound in (sub.state_lower[j], sub.state_upper[j]):
                    if math.isfinite(bound):
                        bound_line(fig_x, bound)
            fig_u = _figure(f"subsystem {sub.name}: inputs u(k)" + ("" if sub.input_is_box else " (U: bounding box)"),
                            x_range, height=SIGNAL_HEIGHT)
            for j in range(sub.m):
                fig_u.step("k", f"u{j + 1}", source=inputs, mode="after", color=Category10_10[j % 10], line_width=2,
                           legend_label=sub.input_label(j))
                for bound in (sub.input_lower[j], sub.input_upper[j]):
                    if math.isfinite(bound):
                        bound_line(fig_u, bound)
            targets = ColumnDataSource(self._target_columns([], sub, 0, 0), name=f"targets-{sub.name}")
            self.targets.append(targets)
            self._target_lines(fig_x, targets, i, "x", sub.n)
            self._target_lines(fig_u, targets, i, "u", sub.m)
            extra = self._estimate_plots(fig_x, sub, x_range) if meta.estimation else []
            for fig in (fig_x, fig_u, *extra):
                _legend_below(fig)
            if meta.estimation:  # its states, targets, estimates and outputs: the legend in two rows
                fig_x.legend[0].nrows = 2
            panels += [fig_x, fig_u, *extra]
            rows_of_panels.append([fig_x, fig_u, *extra])
        for fig in [fig_cost, fig_terminal] + panels:
            cursor = Span(location=0, dimension="height", line_color="#555555", line_dash="dotted", visible=False)
            fig.add_layout(cursor)
            self.cursors.append(cursor)
        self.root.children = [
            self.header, self.counter, self.status,
            row(self.slider, self.play),
            row(self.readout, self.summary),
            row(fig_cost, fig_terminal, fig_graph),
            self.agents,
            self._grid(panels, rows_of_panels),
        ]
        self.built = True

    def _grid(self, panels: list, rows: list[list]):
        """The subsystems' plots: four to a row; with estimation a row per subsystem (its states,
        inputs, disturbance estimates and other outputs)."""
        if not self.meta.estimation:
            return gridplot([*panels], ncols=4, toolbar_location="right", merge_tools=True)
        width = max((len(r) for r in rows), default=0)
        return gridplot([r + [None] * (width - len(r)) for r in rows], toolbar_location="right", merge_tools=True)

    def _estimate_plots(self, fig_x, sub, x_range: Range1d) -> list:
        """A run with estimation: subsystem ``sub``'s estimates x^ (dashed) and the outputs measured
        that are a state alone (crosses) on its state plot ``fig_x``; returns its plot of the
        disturbance estimates d^ and, where some outputs measure a combination of states, a plot of
        those."""
        source = ColumnDataSource(self._estimate_columns([], sub, 0, 0, 0), name=f"estimates-{sub.name}")
        self.estimates.append(source)
        for j in range(sub.n):
            fig_x.line("k", f"xhat{j + 1}", source=source, color=Category10_10[j % 10], legend_label="estimate x̂",
                       name=f"estimate-{sub.name}-{j + 1}", **ESTIMATE)
        others = []
        for r, state in enumerate(sub.measures):
            if state is None:
                others.append(r)
                continue
            fig_x.scatter("k", f"y{r + 1}", source=source, color=Category10_10[state % 10], legend_label="measured y",
                          name=f"measured-{sub.name}-{r + 1}", **MEASURED)
        fig_d = _figure(f"subsystem {sub.name}: disturbances d̂(k)", x_range, height=SIGNAL_HEIGHT)
        fig_d.name = f"disturbances-{sub.name}"
        for r in range(sub.nd):
            fig_d.line("k", f"d{r + 1}", source=source, color=Category10_10[r % 10], line_width=2,
                       legend_label=sub.disturbance_label(r))
        plots = [fig_d]
        if others:
            fig_y = _figure(f"subsystem {sub.name}: outputs y(k)", x_range, height=SIGNAL_HEIGHT)
            fig_y.name = f"outputs-{sub.name}"
            for r in others:
                fig_y.scatter("k", f"y{r + 1}", source=source, color=Category10_10[r % 10],
                              legend_label=sub.output_label(r), **MEASURED)
            plots.append(fig_y)
        return plots

    def _target_lines(self, fig, source: ColumnDataSource, i: int, kind: str, count: int) -> None:
        """The target (dashed) and setpoint (dotted) of each component of subsystem ``i``, held over
        each step; hidden, with their legend entries, until they have something to show."""
        lines: dict[str, list] = {"target": [], "setpoint": []}
        for what, style in (("target", TARGET), ("setpoint", SETPOINT)):  # the setpoints on top
            for j in range(count):
                lines[what].append(fig.step("k", f"{what}_{kind}{j + 1}", source=source, mode="after",
                                            color=Category10_10[j % 10], visible=False, **style))
        for what, label in (("target", "target (applied)"), ("setpoint", "setpoint")):
            item = LegendItem(label=label, renderers=lines[what], visible=False,
                              name=f"legend-{what}-{kind}-{self.meta.subsystems[i].name}")
            fig.legend.items.append(item)
            self.tracking.append((i, kind, what, [*lines[what], item]))

    # -- data ------------------------------------------------------------------------------------
    def _terminal_columns(self, rows: list[StateRow]) -> dict[str, list]:
        data: dict[str, list[Any]] = {"k": [r.k for r in rows], "beta": [r.beta for r in rows]}
        for i, xs in enumerate(self.meta.state_slices()[:SHOWN]):
            data[f"a{i}"] = [max((abs(v) for v in r.alpha[xs]), default=math.nan) for r in rows]
        return data

    def _state_columns(self, rows: list[StateRow]) -> list[dict]:
        """Data for the terminal plot and each subsystem's state plot."""
        ks = [r.k for r in rows]
        out: list[dict[str, list[Any]]] = [self._terminal_columns(rows)]
        for sub, xs in zip(self.meta.subsystems[:SHOWN], self.meta.state_slices()):
            data = {"k": list(ks)}  # each source its own lists: streaming extends them in place
            for j in range(sub.n):
                data[f"x{j + 1}"] = [r.x[xs.start + j] for r in rows]
            out.append(data)
        return out

    def _step_columns(self, rows: list[StepRow]) -> list[dict]:
        """Data for the cost plot, each subsystem's input plot and each subsystem's targets."""
        ks = [r.k for r in rows]
        out: list[dict[str, list[Any]]] = [{"k": ks, "J": [r.J for r in rows]}]
        for sub, us in zip(self.meta.subsystems[:SHOWN], self.meta.input_slices()):
            data = {"k": list(ks)}
            for j in range(sub.m):
                data[f"u{j + 1}"] = [r.u[us.start + j] for r in rows]
            out.append(data)
        out += self._targets_columns(rows) if self.tracked else []
        return out + self._estimates_columns(rows)

    def _targets_columns(self, rows: list[StepRow]) -> list[dict]:
        """Data for each subsystem's targets and setpoints."""
        return [self._target_columns(rows, sub, xs.start, us.start)
                for sub, xs, us in zip(self.meta.subsystems[:SHOWN], self.meta.state_slices(), self.meta.input_slices())]

    def _estimates_columns(self, rows: list[StepRow]) -> list[dict]:
        """Data for each subsystem's estimates and outputs measured (none without estimation)."""
        if not self.estimates:
            return []
        meta = self.meta
        return [self._estimate_columns(rows, sub, xs.start, ys.start, ds.start)
                for sub, xs, ys, ds in zip(meta.subsystems[:SHOWN], meta.state_slices(), meta.output_slices(),
                                           meta.disturbance_slices())]

    @staticmethod
    def _estimate_columns(rows: list[StepRow], sub, x0: int, y0: int, d0: int) -> dict[str, list]:
        """One subsystem's estimates x^ (``xhat1`` ...), outputs measured (``y1`` ...) and disturbance
        estimates (``d1`` ...) over ``rows`` (NaN in a step without them); its states start at column
        ``x0`` of the global state, its outputs at ``y0``, its disturbances at ``d0``."""
        data: dict[str, list] = {"k": [r.k for r in rows]}
        for prefix, what, count, start in (("xhat", "x_hat", sub.n, x0), ("y", "y", sub.p, y0),
                                           ("d", "d_hat", sub.nd, d0)):
            for j in range(count):
                data[f"{prefix}{j + 1}"] = [_estimate_value(r, what, start + j) for r in rows]
        return data

    @staticmethod
    def _target_columns(rows: list[StepRow], sub, x0: int, u0: int) -> dict[str, list]:
        """One subsystem's targets and setpoints over ``rows`` (NaN before anything was requested);
        its states start at column ``x0`` of the global state, its inputs at ``u0``."""
        data: dict[str, list] = {"k": [r.k for r in rows]}
        for kind, count, start in (("x", sub.n, x0), ("u", sub.m, u0)):
            for j in range(count):
                for what in ("target", "setpoint"):
                    data[f"{what}_{kind}{j + 1}"] = [_target_value(r, what, kind, start + j) for r in rows]
        return data

    @staticmethod
    def _sync(sources: list[ColumnDataSource], rows: list, shown: int, target: int, columns) -> int:
        """Bring ``sources`` from the first ``shown`` rows to the first ``target``; returns target."""
        if target > shown and shown >= max(0, target - WINDOW):
            for source, data in zip(sources, columns(rows[shown:target])):
                source.stream(data, rollover=WINDOW)
        elif target != shown:
            for source, data in zip(sources, columns(rows[max(0, target - WINDOW):target])):
                source.data = data
        return target

    # -- updates ---------------------------------------------------------------------------------
    def tick(self) -> None:
        """Take what the run's state gained and show it."""
        snap = self.state.read(self.epoch, len(self.state_rows), len(self.step_rows))
        if snap.version == self.version:
            return
        self.version = snap.version
        if snap.epoch != self.epoch:
            self.epoch = snap.epoch
            self.state_rows, self.step_rows, self.state_ks, self.step_ks = [], [], [], []
            self.shown_states = self.shown_steps = -1  # anything differs: the sources are replaced
            if self._history is not None:
                self._history = AgentHistory(self.meta)
        self.state_rows += snap.state_rows
        self.step_rows += snap.step_rows
        self.state_ks += [r.k for r in snap.state_rows]
        self.step_ks += [r.k for r in snap.step_rows]
        self.snap = snap
        new_steps = snap.step_rows
        if not self.built and snap.meta is not None:
            self._build(snap.meta)
            new_steps = self.step_rows  # those read before the description came, too
        if self.built:
            self.history.add(new_steps)
            self._show_tracking(new_steps)
            last = self.state_ks[-1] if self.state_ks else 0
            self.slider.end = max(1, last)
            self.slider.disabled = not self.state_ks
            if self.follow and self.slider.value != last:
                self.slider.value = last  # calls _on_slider
            else:
                self._refresh()
        self._update_text(snap)

    def _show_tracking(self, rows: list[StepRow]) -> None:
        """Show the targets once a step has them, and a subsystem's setpoints once one of its
        components was requested."""
        tracked = [r.targets for r in rows if r.targets is not None]
        if not tracked:
            return
        if not self.tracked:  # the targets' sources join the others where they are
            self.tracked = True
            shown = max(self.shown_steps, 0)
            for source, data in zip(self.targets, self._targets_columns(self.step_rows[max(0, shown - WINDOW):shown])):
                source.data = data
        slices = {"x": self.meta.state_slices(), "u": self.meta.input_slices()}
        for i, kind, what, models in self.tracking:
            if models[0].visible:
                continue
            if what == "setpoint":
                cols = slices[kind][i]
                asked = (t.setpoint if kind == "x" else t.setpoint_u for t in tracked)
                if not any(math.isfinite(v) for values in asked for v in values[cols]):
                    continue
            for model in models:
                _set(model, "visible", True)

    def _on_slider(self, value: int) -> None:
        self.follow = value >= max((self.state_ks or [0])[-1], 1)
        self._refresh()

    def _on_play(self, active: bool) -> None:
        if active:
            if self.slider.value >= self.slider.end:
                self.slider.value = 0
            self.play.label = "❚❚ pause"
            self._play = self.doc.add_periodic_callback(self._advance, PLAY_MS)
        else:
            self.play.label = "▶ replay"
            if self._play is not None:
                self.doc.remove_periodic_callback(self._play)
                self._play = None

    def _advance(self) -> None:
        if self.slider.value < self.slider.end:
            self.slider.value += 1
        else:
            self.play.active = False

    def _refresh(self) -> None:
        """Show the run up to the slider's step."""
        k = self.slider.value
        n_states = bisect.bisect_right(self.state_ks, k)
        n_steps = bisect.bisect_right(self.step_ks, k)
        self.shown_states = self._sync([self.terminal] + self.states, self.state_rows, self.shown_states, n_states,
                                       self._state_columns)
        step_sources = [self.cost] + self.inputs + (self.targets if self.tracked else []) + self.estimates
        self.shown_steps = self._sync(step_sources, self.step_rows, self.shown_steps, n_steps, self._step_columns)
        for cursor in self.cursors:
            cursor.location = k
            cursor.visible = not self.follow
        row_k = self.state_rows[n_states - 1] if n_states and self.state_ks[n_states - 1] == k else None
        step_k = self.step_rows[n_steps - 1] if n_steps and self.step_ks[n_steps - 1] == k else None
        _set(self.readout, "text", readout_html(self.meta, row_k, step_k, SHOWN))
        self._update_agents(n_steps)
        self._update_graph(n_steps)
        snap = self.snap
        _set(self.summary, "text", summary_html(snap.summary, snap.summary_from) if snap and snap.summary else (
            "<i>the verdict and summary appear here when the run ends</i>"))

    def _alive_now(self) -> dict[str, bool] | None:
        """The agents' liveliness as the bus shows it now (live, following, before the end)."""
        snap = self.snap
        if not self.live or not self.follow or snap is None or snap.ended:
            return None
        agents = {keys.subsystem_of(role, keys.AGENT_PREFIX): alive for role, alive in snap.alive.items()}
        tokens = {name: alive for name, alive in agents.items() if name is not None}
        if not tokens and snap.plant.get("alive") is not None:
            tokens = {name: name in snap.plant["alive"] for name in self.meta.names}
        return tokens or None

    def _update_agents(self, n: int | None = None) -> None:
        n = len(self.step_rows) if n is None else n
        last = self.step_rows[n - 1] if n else None
        snap = self.snap
        self.table = agent_table(self.meta, self.history, n, last, self._alive_now(), snap.plant if snap else {},
                                 snap.summary if snap else None)
        reasons = ((snap.summary if snap else None) or {}).get("rejected_reasons") or (
            snap.plant.get("rejected_reasons") if snap else None) or {}
        notes = []
        why = self.history.solve_reasons(n)
        if why:
            notes.append("why agents solved up to this step: " + ", ".join(f"{r}: {c}" for r, c in why.items())
                         + " (hover over a plan for what its reason means)")
        if reasons:
            notes.append("dropped by the coordinator, by reason: " + ", ".join(f"{r}: {c}" for r, c in reasons.items()))
        if self.meta.M > SHOWN:
            notes.append(f"the first {SHOWN} of {self.meta.M} subsystems have plots below; the table lists every agent")
        _set(self.agents, "text", table_html(self.table) + "".join(f"<p><i>{html.escape(n)}</i></p>" for n in notes))

    def _update_graph(self, n: int | None = None) -> None:
        n = len(self.step_rows) if n is None else n
        last = self.step_rows[n - 1] if n else None
        alive = self.history.alive(n)
        alive.update(self._alive_now() or {})
        snap = self.snap
        coordinator_alive = not (self.live and snap is not None and snap.alive.get(keys.COORDINATOR_ROLE) is False
                                 and self.follow and snap.summary is None)
        nodes, edges = graph_tables(self.meta, agent_states(self.meta, last, alive), coordinator_alive)
        _set(self.nodes, "data", nodes)
        _set(self.edges, "data", edges)

    def _update_text(self, snap: Snapshot) -> None:
        meta = snap.meta
        if meta is None:
            self.header.text = (f"<h2>dmpc watch</h2>run {html.escape(snap.run_id or '?')} · "
                                f"{html.escape(snap.source)}")
            self.counter.text = "waiting for the run's description"
        else:
            mode = meta.mode + (f", dt {meta.dt:g} s" if meta.mode == "realtime" else "")
            self.header.text = (f"<h2>dmpc watch: {html.escape(meta.scenario)}</h2>run "
                                f"<b>{html.escape(snap.run_id or meta.run_id)}</b> · method {html.escape(meta.method)}"
                                f" · {html.escape(mode)}{' · event trigger' if meta.trigger == 'event' else ''}"
                                f" · {meta.M} agents, horizon {meta.horizon} · "
                                f"{html.escape(snap.source)}")
            done = len(self.step_rows)
            missing = (self.step_ks[-1] + 1 - done) if self.step_ks else 0
            gap = f" ({missing} not received)" if missing else ""
            self.counter.text = (f"step <b class='dmpc-step'>{done}</b> of {meta.steps}{gap} · "
                                 f"<span class='dmpc-run-state'>{self._run_state(snap)}</span>")
        notes = [snap.connection] if snap.connection else []
        if snap.dropped:
            notes.append(f"{snap.dropped} messages or lines could not be used ({'; '.join(snap.problems[:2])})")
        self.status.text = "<small>" + " · ".join(html.escape(n) for n in notes) + "</small>"

    def _run_state(self, snap: Snapshot) -> str:
        if snap.summary is not None:
            return f"ended, verdict {html.escape(verdict_of(snap.summary))}"
        if snap.ended:
            return "the plant has gone (no summary received)"
        if not self.step_rows:
            return "waiting for the first step"
        return "running" if self.live else "incomplete (no summary.json yet)"


def _legend_below(fig) -> None:
    """The figure's legend in a row under its plot, where it hides none of the lines."""
    legend = fig.legend[0]
    legend.label_text_font_size = "8pt"
    legend.orientation = "horizontal"
    legend.location = "center"
    legend.padding = legend.margin = 2
    legend.spacing = 8
    legend.glyph_width = 18
    legend.click_policy = "hide"
    fig.add_layout(legend, "below")


def _target_value(row: StepRow, what: str, kind: str, column: int) -> float:
    """Component ``column`` of the target (``what`` 'target') or setpoint of the states (``kind``
    'x') or inputs of a step; NaN in a step without targets."""
    t = row.targets
    if t is None:
        return math.nan
    values = {("target", "x"): t.x, ("target", "u"): t.u, ("setpoint", "x"): t.setpoint,
              ("setpoint", "u"): t.setpoint_u}[what, kind]
    return values[column]


def _estimate_value(row: StepRow, what: str, column: int) -> float:
    """Component ``column`` of a step's ``x_hat``, ``y`` or ``d_hat`` (``what``); NaN in a step
    without estimates."""
    e = row.estimate
    if e is None:
        return math.nan
    values = {"x_hat": e.x_hat, "y": e.y, "d_hat": e.d_hat}[what]
    return values[column] if column < len(values) else math.nan


def _set(model, attr: str, value) -> None:
    """Set a property only when it changes: every change is sent to the browser and redrawn there."""
    if getattr(model, attr) != value:
        setattr(model, attr, value)


def page_factory(state: RunState, live: bool):
    """A Bokeh application function that gives each browser tab its own page of the run ``state``;
    ``live``: the run is watched over the bus."""

    def make(doc) -> None:
        WatchPage(doc, state, live)

    return make

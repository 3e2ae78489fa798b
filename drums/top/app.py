"""`drums top` as a full-screen terminal app (Textual): a view's rows, the selected row's
sparkline, the keys in the footer. It reads the model the collector's threads fill, on a timer,
and draws again when something changed: it never waits on an agent."""
from __future__ import annotations

from rich.text import Text
from textual.app import App
from textual.binding import Binding
from textual.widgets import DataTable, Footer, Input, Sparkline, Static

from drums.top import VIEWS, manual
from drums.top.collector import Collector
from drums.top.history import History
from drums.top.screen import Views, headers, title
from drums.top.table import Table, arrange, cells, fit
from drums.top.widgets import Help, RowTable

DRAW_EVERY = 0.2  # seconds between looks at the model


class TopApp(App):
    CSS_PATH = "top.tcss"
    ENABLE_COMMAND_PALETTE = False
    BINDINGS = [
        Binding("n", "view('nodes')", "Nodes"),
        Binding("t", "view('topics')", "Topics"),
        Binding("e", "view('edges')", "Edges"),
        Binding("c", "view('connections')", "Conns"),
        Binding("h", "view('hosts')", "Hosts"),
        Binding("a", "view('anomalies')", "Anomalies"),
        # Priority: the app takes it at once, so the keys typed right after it go to the filter.
        Binding("slash", "filter", "Filter", priority=True),
        Binding("greater_than_sign", "sort(1)", "Sort"),
        Binding("less_than_sign", "sort(-1)", "Sort", show=False),
        Binding("r", "reverse", "Reverse", show=False),
        Binding("p", "processes", "Processes", show=False),
        Binding("question_mark", "help", "Help"),
        Binding("q", "quit", "Quit"),
        Binding("ctrl+c", "quit", "Quit", show=False, priority=True),
        Binding("escape", "clear_filter", "Clear filter", show=False),
    ]

    def __init__(self, collector: Collector, view: str = "nodes"):
        super().__init__()
        self.collector = collector
        self.views = Views()
        self.history = History(collector.interval)
        self.view = view
        self.sorts = {}  # view -> (column, reversed), once the user sorted it
        self.match = ""
        self.table: Table | None = None
        self._drawn = (-1, "")  # (model version, what else the screen depends on)
        # Kept at hand: the help screen may be on top when they are needed.
        self.heading, self.rows, self.detail = Static(id="title"), RowTable(id="rows"), Static(id="detail")
        self.spark = Sparkline([], id="spark")
        self.field = Input(placeholder="filter: part of a name (Enter keeps it, Escape clears it)", id="filter",
                           select_on_focus=False)  # else the keys typed right after / would be selected, then replaced

    def compose(self):
        yield from (self.heading, self.rows, self.detail, self.spark, self.field)
        yield Footer()

    def on_mount(self) -> None:
        self.collector.start()
        self.rows.focus()
        self.set_interval(DRAW_EVERY, self.draw)
        self.set_interval(self.collector.interval, self.record)

    def check_action(self, action: str, parameters: tuple) -> bool | None:
        """While the filter is typed, / is a character of it; over the help, nothing."""
        return action != "filter" or (self.focused is not self.field and len(self.screen_stack) == 1)

    def sort(self, table: Table) -> tuple[str, bool]:
        return self.sorts.get(self.view, (table.sort, False))

    def record(self) -> None:
        """Every interval, every view's numbers into the history (the sparklines)."""
        frame = self.collector.model.frame()
        for view in VIEWS:
            self.history.record(self.views.table(frame, view))

    def draw(self, force: bool = False) -> None:
        state = (self.collector.model.version, f"{self.view}|{self.sorts}|{self.match}|{self.rows.size}")
        if state != self._drawn or force:
            self._drawn = state
            frame = self.collector.model.frame()
            table = self.table = self.views.table(frame, self.view)
            sort, reverse = self.sort(table)
            rows = arrange(table, sort, reverse, self.match)
            titles = headers(table, sort, reverse)
            texts = [cells(table, r) for r in rows]
            widths = fit(table.columns, titles, texts, max(1, self.rows.scrollable_content_region.width))
            self.rows.show(table.columns, titles, widths, rows, texts)
            heading = title(frame, table, sum(1 for r in rows if not r.group))
            if self.match:
                heading += f"  filter: {self.match}"
            self.heading.update(Text(heading, no_wrap=True, overflow="ellipsis"))
        self.show_selected()

    def show_selected(self) -> None:
        """The selected row's sort column (or its view's main number) over the last minutes."""
        table, key = self.table, self.rows.selected()
        row = next((r for r in table.rows if r.key == key), None) if table else None
        if row is None:
            self.detail.update("")
            self.spark.data = []
            return
        sort, _ = self.sort(table)
        column = table.column(sort if not table.column(sort).name else table.spark)
        values = self.history.values(table.view, key, column.key)
        name = " ".join(str(row.values[c.key]) for c in table.columns if c.name and row.values.get(c.key))
        line = f"{column.title} of {name}: {column.fmt(row.values.get(column.key))}"
        if values:
            line += (f", {column.fmt(min(values))} to {column.fmt(max(values))} "
                     f"over {len(values) * self.collector.interval:.0f} s")
        if row.values.get("error"):
            line += f"  ({row.values['error']})"
        elif table.note:
            line += f"  ({table.note})"
        self.detail.update(Text(line, no_wrap=True, overflow="ellipsis"))
        self.spark.data = values

    def on_data_table_row_highlighted(self, _event: DataTable.RowHighlighted) -> None:
        if self.table is not None:
            self.show_selected()

    def on_data_table_header_selected(self, event: DataTable.HeaderSelected) -> None:
        """A click on a column's title sorts by it; a second click turns the order around."""
        sort, reverse = self.sort(self.table)
        key = event.column_key.value
        self.sorts[self.view] = (key, not reverse if key == sort else False)
        self.draw(force=True)

    def action_view(self, view: str) -> None:
        self.view = view
        self.draw(force=True)

    def action_sort(self, step: int) -> None:
        """Sort by the next column shown to the left or right."""
        shown = self.rows.shown()
        if shown:
            sort, _ = self.sort(self.table)
            at = shown.index(sort) if sort in shown else 0
            self.sorts[self.view] = (shown[(at + step) % len(shown)], False)
            self.draw(force=True)

    def action_reverse(self) -> None:
        sort, reverse = self.sort(self.table)
        self.sorts[self.view] = (sort, not reverse)
        self.draw(force=True)

    def action_processes(self) -> None:
        self.views.processes = not self.views.processes
        self.draw(force=True)

    def action_filter(self) -> None:
        self.field.display = True
        self.field.value = self.match
        self.screen.set_focus(self.field)  # now, not after the keys already typed (focus() waits its turn)

    def on_input_changed(self, event: Input.Changed) -> None:
        self.match = event.value
        self.draw()

    def on_input_submitted(self, _event: Input.Submitted) -> None:
        self.close_filter()

    def close_filter(self) -> None:
        """The filter's field goes; what it holds goes on filtering."""
        self.field.display = False
        self.rows.focus()

    def action_clear_filter(self) -> None:
        self.match = ""
        self.close_filter()
        self.draw()

    def action_help(self) -> None:
        self.push_screen(Help(manual.text(self.view)))

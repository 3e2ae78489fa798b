"""The widgets of `drums top`: the table of a view's rows, the line and sparkline of the selected
row, and the help screen."""
from __future__ import annotations

from rich.text import Text
from textual.containers import VerticalScroll
from textual.screen import ModalScreen
from textual.widgets import DataTable, Static

from drums.top.table import GAP, Column, Row, cut


def padded(column: Column, text: str, width: int, last: bool) -> Text:
    """A cell as plain text (a name with brackets is not markup), with the gap to the next."""
    body = cut(text, width).ljust(width) if column.name else text.rjust(width)[-width:]
    return Text(body if last else body + " " * GAP, no_wrap=True)


class RowTable(DataTable):
    """A view's rows as text fitted to its width. Between refreshes it keeps the cursor on the
    same row (by key) and redraws only the cells that changed while the rows stay in place."""

    def __init__(self, **kwargs):
        super().__init__(cursor_type="row", cell_padding=0, zebra_stripes=False, **kwargs)
        self._layout: tuple = ()
        self._keys: list[str] = []

    def shown(self) -> list[str]:
        """The keys of the columns shown, left to right (those that fit)."""
        return [key for key, _, _ in self._layout]

    def selected(self) -> str | None:
        return self._keys[self.cursor_row] if 0 <= self.cursor_row < len(self._keys) else None

    def show(self, columns: list[Column], titles: list[str], widths: list[int], rows: list[Row],
             texts: list[list[str]]) -> None:
        shown = [i for i, w in enumerate(widths) if w]
        layout = tuple((columns[i].key, titles[i], widths[i]) for i in shown)
        keys = [r.key for r in rows]
        cells = [[padded(columns[i], t[i], widths[i], i == shown[-1]) for i in shown] for t in texts]
        if layout != self._layout:
            selected = self.selected()
            self.clear(columns=True)
            for i in shown:
                self.add_column(padded(columns[i], titles[i], widths[i], i == shown[-1]), key=columns[i].key,
                                width=widths[i] + (0 if i == shown[-1] else GAP))
            self._layout, self._keys = layout, []
            self._keys_replaced(keys, cells, selected)
        elif keys != self._keys:
            self._keys_replaced(keys, cells, self.selected())
        else:
            for key, row in zip(keys, cells):
                for (column, _, _), cell in zip(layout, row):
                    if self.get_cell(key, column) != cell:
                        self.update_cell(key, column, cell)

    def _keys_replaced(self, keys: list[str], cells: list[list[Text]], selected: str | None) -> None:
        self.clear()
        for key, row in zip(keys, cells):
            self.add_row(*row, key=key)
        self._keys = keys
        if selected in keys:
            self.move_cursor(row=keys.index(selected), animate=False)


class Help(ModalScreen):
    """The keys, and what the current view's columns mean."""

    BINDINGS = [("escape,question_mark,q", "app.pop_screen", "Close")]

    def __init__(self, text: str):
        super().__init__()
        self.text = text

    def compose(self):
        with VerticalScroll(id="help"):
            yield Static(Text(self.text))

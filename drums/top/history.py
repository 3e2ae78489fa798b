"""The last minutes of every number of every row, for the sparkline of the selected row."""
from __future__ import annotations

from collections import deque

from drums.top.table import Table

MINUTES = 5


class History:
    def __init__(self, interval: float):
        self.length = max(2, int(MINUTES * 60 / interval))
        self._values: dict[tuple[str, str], dict[str, deque]] = {}  # (view, row key) -> column -> values

    def record(self, table: Table) -> None:
        """Add each row's numbers; rows that left the view leave the history too."""
        keys = set()
        for row in table.rows:
            keys.add((table.view, row.key))
            columns = self._values.setdefault((table.view, row.key), {})
            for c in table.columns:
                value = row.values.get(c.key)
                if not c.name and isinstance(value, (int, float)):
                    columns.setdefault(c.key, deque(maxlen=self.length)).append(value)
        for gone in [k for k in self._values if k[0] == table.view and k not in keys]:
            del self._values[gone]

    def values(self, view: str, key: str, column: str) -> list[float]:
        return list(self._values.get((view, key), {}).get(column, ()))

"""The recent points of every watched series, as one array: a row per series, a column per tick.

The columns are a ring: a tick writes one column for all rows at once. A series missing from a
tick keeps its last point (a scrape that came late is not a fall to zero); one missing for GONE
ticks is forgotten and its row reused. Rows are judged in cohorts of equal length, so that a
series that started a minute ago is judged on its minute and not on points it never had.
"""
from __future__ import annotations

import numpy as np

GONE = 5  # ticks a series may miss before it is forgotten


class History:
    def __init__(self, width: int, capacity: int = 1024):
        self.width = width
        self.points = np.zeros((capacity, width), np.float32)
        self.held = np.zeros(capacity, np.int64)  # points each row holds, up to width
        self.missed = np.zeros(capacity, np.int64)  # ticks since the row last had a point
        self.used = np.zeros(capacity, bool)
        self.times = np.zeros(width)  # when each column's tick was
        self.column = -1  # the column of the newest tick
        self._free: list[int] = list(range(capacity - 1, -1, -1))

    def add(self) -> int:
        """A row for a new series."""
        if not self._free:  # a quarter more: a doubling would leave up to half of the largest array unused
            old = len(self.used)
            more = max(1, old // 4)
            self.points = np.concatenate([self.points, np.zeros((more, self.width), self.points.dtype)])
            self.held, self.missed, self.used = (np.concatenate([a, np.zeros(more, a.dtype)])
                                                 for a in (self.held, self.missed, self.used))
            self._free = list(range(old + more - 1, old - 1, -1))
        row = self._free.pop()
        self.used[row], self.held[row], self.missed[row] = True, 0, 0
        return row

    def tick(self, rows: np.ndarray, values: np.ndarray, at: float = 0.0) -> np.ndarray:
        """Append one column, of time `at`: `values` for `rows`, the last point again for the other
        rows that hold any. Returns the rows forgotten now (missing for GONE ticks)."""
        previous = self.column
        self.column = (self.column + 1) % self.width
        self.times[self.column] = at
        if previous >= 0:
            self.points[:, self.column] = self.points[:, previous]
        self.missed[self.used] += 1
        self.points[rows, self.column] = values
        self.missed[rows] = 0
        self.held[rows] = np.minimum(self.held[rows] + 1, self.width)
        carried = self.used & (self.held > 0) & (self.missed > 0)
        self.held[carried] = np.minimum(self.held[carried] + 1, self.width)
        gone = np.flatnonzero(self.used & (self.missed >= GONE))
        self.used[gone] = False
        self._free.extend(gone.tolist())
        return gone

    def since(self, row: int, since: float) -> np.ndarray:
        """(n, 2) array of [time, value] of the row's points from `since` on, oldest first."""
        length = int(self.held[row])
        columns = (self.column - length + 1 + np.arange(length)) % self.width
        times = self.times[columns]
        keep = times >= since
        return np.column_stack([times[keep], self.points[row, columns[keep]].astype(np.float64)])

    def cohorts(self, least: int):
        """(rows, window) for each group of rows holding the same number of points, at least
        `least`: window is (len(rows), points), oldest first. Rows that missed this tick are left
        out: their newest point is a copy."""
        ready = self.used & (self.held >= least) & (self.missed == 0)
        held = self.held[ready]
        rows = np.flatnonzero(ready)
        for length in np.unique(held):
            group = rows[held == length]
            columns = (self.column - length + 1 + np.arange(length)) % self.width
            yield group, self.points[np.ix_(group, columns)]

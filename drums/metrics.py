"""Metric declarations and the snapshot every exporter reads.

Each probe declares its metrics once, here-shaped: the Prometheus exporter, the README table and
later the HTTP API, the ZeroMQ stream and `drums top` all read the same Snapshot.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Callable

import numpy as np

from drums.arrays import among

COUNTER, GAUGE, HISTOGRAM, INFO = "counter", "gauge", "histogram", "info"


@dataclass(frozen=True, eq=False)  # each metric is declared once: identity is equality, and hashes fast
class Metric:
    name: str  # full Prometheus name, base units, `_total` on counters
    kind: str
    help: str
    labels: tuple[str, ...] = ()
    buckets: tuple[float, ...] = ()  # upper bounds, for histograms; +Inf is implied
    additive: bool = True  # whether a sum over entities means something (not for an RTT or a time)

    def __post_init__(self):
        if self.kind == COUNTER and not self.name.endswith("_total"):
            raise ValueError(f"counter {self.name} must end in _total")
        if self.kind == INFO and not self.name.endswith("_info"):
            raise ValueError(f"info metric {self.name} must end in _info")


@dataclass
class Histogram:
    """Cumulative bucket counts (without +Inf), sum and count. The buckets are Metric.buckets, or
    this row's own `bounds` (a histogram whose buckets follow its data, as the publish periods'
    do); rows with different bounds add and subtract on the union of their bounds."""

    cumulative: list[int]
    sum: float
    count: int
    bounds: tuple[float, ...] | None = None

    def __add__(self, other: "Histogram") -> "Histogram":
        return self._combine(other, 1)

    def __sub__(self, other: "Histogram") -> "Histogram":
        return self._combine(other, -1)

    def _combine(self, other: "Histogram", sign: int) -> "Histogram":
        if self.bounds == other.bounds:
            cumulative = [a + sign * b for a, b in zip(self.cumulative, other.cumulative)]
            return Histogram(cumulative, self.sum + sign * other.sum, self.count + sign * other.count, self.bounds)
        bounds = tuple(sorted(set(self.bounds or ()) | set(other.bounds or ())))
        cumulative = [a + sign * b for a, b in zip(self._at(bounds), other._at(bounds))]
        return Histogram(cumulative, self.sum + sign * other.sum, self.count + sign * other.count, bounds)

    def _at(self, bounds: tuple[float, ...]) -> list[int]:
        """The cumulative count at each of `bounds`: that of the highest own bound not above it."""
        out, i, mine = [], -1, self.bounds or ()
        for b in bounds:
            while i + 1 < len(mine) and mine[i + 1] <= b:
                i += 1
            out.append(self.cumulative[i] if i >= 0 else 0)
        return out


@dataclass
class Changes:
    """A probe's rows of one group (or one metric) told as what changed since its last collect,
    beside the rows themselves: a consumer that holds the rows of collect `since` may apply these
    instead of comparing every row. A probe says nothing (None) when it cannot tell."""
    since: int  # the probe's collect these follow
    mark: int  # this one
    rows: list  # (labels, values) new or changed; maybe some that did not change
    gone: list  # labels in collect `since` and no longer


@dataclass
class Columns:
    """A group's rows as arrays: for the ten thousand sockets of a host, of which the budget gives
    a hundred series of their own and sums the rest. Label values are made only for the rows asked
    for (`rows`); the budget ranks and sums the others as arrays."""

    ids: np.ndarray  # (n,) int64: each row's own id, one each
    # (n, k) int64: the row's counters, in the group's metrics' order. Maybe a view of a probe's
    # arrays, which its next collect writes over: what is kept of them is copied.
    values: np.ndarray
    dims: np.ndarray  # (n,) intp: its value of the group's one dimension label, as an index of dim_names
    dim_names: tuple[str, ...]
    pids: np.ndarray | None  # (n,) int64: the process the row belongs to, for the agent's selection; None: of none
    labels: Callable[[list[int]], list[tuple[str, ...]]]  # the label values of the rows at these indices
    # (n,) int64: each row's local port << 16 | remote port, where rows are sockets or connections,
    # so that a reader can find the few on some ports without the labels of all
    ports: np.ndarray | None = None
    # (n,) int64: the entity each row is of, where an entity has several rows (a thread's voluntary
    # and involuntary switches); None: each row is an entity of its own, named by its id
    entities: np.ndarray | None = None
    units: tuple[int, ...] | None = None  # per metric, the counts in one unit shown (1e9 ns a second); None: 1
    # The stamps of the rows at these indices, (len, k) uint64: what a row's label values are made
    # from beside its id (a thread's name); a reader may take a row's labels again while its id and
    # stamps are the same. None: it may not.
    stamps: Callable[[np.ndarray], np.ndarray] | None = None
    # What changed since the probe's collect `since`, this being collect `mark`: (since, mark, the
    # indices of the rows whose values may differ from those that collect gave, over the same ids).
    # A reader that holds the values of collect `since` compares only those. None: not told.
    told: tuple[int, int, np.ndarray] | None = None

    def rows(self, at: list[int] | None = None) -> list[tuple[tuple[str, ...], tuple]]:
        """(labels, values) rows, as a group's rows are: all, or those at these indices."""
        at = list(range(len(self.ids))) if at is None else at
        return list(zip(self.labels(at), shown(self.values[at], self.units)))

    def of(self) -> np.ndarray:
        """The entity of each row."""
        return self.ids if self.entities is None else self.entities

    def of_processes(self, pids: set[int]) -> "Columns":
        """The rows of these processes (none, for rows that belong to no process)."""
        where = np.flatnonzero(among(self.pids, pids)) if self.pids is not None else np.empty(0, np.intp)
        return self.subset(where)

    def on_ports(self, ports: set[tuple[int, int]]) -> "Columns":
        """The rows on these (local, remote) ports; all of them where the rows have no ports."""
        if self.ports is None:
            return self
        return self.subset(np.flatnonzero(among(self.ports, {local << 16 | remote for local, remote in ports})))

    def subset(self, where: np.ndarray) -> "Columns":
        """The rows at these indices."""
        def part(a):
            return None if a is None else a[where]
        return Columns(self.ids[where], self.values[where], self.dims[where], self.dim_names, part(self.pids),
                       lambda at: self.labels(where[at].tolist()), part(self.ports), part(self.entities), self.units,
                       self.stamps and (lambda at: self.stamps(where[at])))


def shown(values: np.ndarray, units: tuple[int, ...] | None) -> list[tuple]:
    """Rows of counts as the metrics show them: in their units (seconds of nanoseconds), as floats
    where a unit is not 1."""
    if units is None:
        return list(map(tuple, values.tolist()))
    return list(zip(*[(values[:, i] / u if u != 1 else values[:, i]).tolist() for i, u in enumerate(units)]))


def _rows(rows: "list | Columns") -> list:
    return rows.rows() if isinstance(rows, Columns) else rows


class Snapshot:
    """What the agent knows at one instant: metric -> [(label values, value)].

    Metrics that always come together with the same labels (the six counters of a socket) can be
    added as one group row: the budget then handles ten thousand sockets as ten thousand rows,
    not sixty thousand; or as Columns, as arrays. `series` shows every row, groups spread out.
    """

    def __init__(self):
        self._series: dict[Metric, list[tuple[tuple[str, ...], object]]] = {}
        self.groups: dict[tuple[Metric, ...], list[tuple[tuple[str, ...], tuple]] | Columns] = {}
        self.read_at: float | None = None  # time.time() when the probes were read, if known
        self.changes: dict[tuple[Metric, ...], Changes] = {}  # by group (a metric alone: a group of one)
        self.unread: set[Metric] = set()  # the metrics of probes that failed to collect: missing, not gone
        self._spreading = threading.Lock()

    @property
    def series(self) -> dict[Metric, list[tuple[tuple[str, ...], object]]]:
        with self._spreading:  # one snapshot goes to a scrape's render and to /diagnostics at once
            for metrics, rows in self.groups.items():
                rows = _rows(rows)
                for i, metric in enumerate(metrics):
                    self._series.setdefault(metric, []).extend((labels, values[i]) for labels, values in rows)
            self.groups = {}
        return self._series

    @property
    def singles(self) -> dict[Metric, list[tuple[tuple[str, ...], object]]]:
        """The rows added one metric at a time, groups left out."""
        return self._series

    def of(self, metric: Metric, ports: set[tuple[int, int]] | None = None) -> list[tuple[tuple[str, ...], object]]:
        """The metric's rows, without spreading out the groups of other metrics (as `series` does).
        `ports`: the rows on these (local, remote) ports, and maybe others (rows given as Columns
        with ports are made only for those: of ten thousand sockets, the few of a graph's edges)."""
        if metric in self._series:
            return self._series[metric]
        for metrics, rows in self.groups.items():
            if metric in metrics:
                i = metrics.index(metric)
                if isinstance(rows, Columns) and ports is not None:
                    rows = rows.on_ports(ports)
                return [(labels, values[i]) for labels, values in _rows(rows)]
        return []

    def narrow(self, pids: set[int]) -> None:
        """Only the rows of these processes in the groups given as Columns, made into rows now (the
        probe's next collect writes over its arrays): of a host's ten thousand sockets, the few of
        the processes a job follows, and none of the connections, which are no process's."""
        for metrics, rows in self.groups.items():
            if isinstance(rows, Columns):
                self.groups[metrics] = rows.of_processes(pids).rows()

    def leave_out(self, metrics: tuple[Metric, ...]) -> None:
        """Take out the rows of a probe that failed to collect (it may have added some before it
        failed): its metrics are unread in this snapshot, their series missing rather than gone."""
        out = set(metrics)
        self.unread |= out
        for metric in out:
            self._series.pop(metric, None)
        self.groups = {group: rows for group, rows in self.groups.items() if out.isdisjoint(group)}
        self.changes = {group: told for group, told in self.changes.items() if out.isdisjoint(group)}

    def add(self, metric: Metric, labels: tuple[str, ...], value) -> None:
        self._series.setdefault(metric, []).append((labels, value))

    def rows(self, metric: Metric) -> list:
        """The metric's (labels, value) list, to append to in bulk."""
        return self._series.setdefault(metric, [])

    def group_rows(self, metrics: tuple[Metric, ...]) -> list:
        """The (labels, values) list of metrics that share their labels, values in their order."""
        return self.groups.setdefault(metrics, [])

    def values(self, metric: Metric) -> dict[tuple[str, ...], object]:
        return dict(self.series.get(metric, ()))


def highest(prev, value):
    """`value`, but never below `prev` (None: nothing before); a histogram bucket by bucket."""
    if prev is None:
        return value
    if isinstance(value, Histogram):
        return Histogram([max(a, b) for a, b in zip(prev.cumulative, value.cumulative)],
                         max(prev.sum, value.sum), max(prev.count, value.count))
    return max(prev, value)


class Monotonic:
    """Holds per-process totals at their highest value from one collect to the next.

    A total is read from two maps one after the other: the live threads (or sockets) and what
    those that ended left, folded per process; one that ends between the two reads is missing
    from both for that one collect. A series
    not seen in a collect is forgotten, so a process that ends (and a PID reused later) starts
    afresh.
    """

    def __init__(self):
        self._previous: dict = {}
        self._current: dict = {}

    def __call__(self, key, value):
        value = self._current[key] = highest(self._previous.get(key), value)
        return value

    def next_collect(self) -> None:
        self._previous, self._current = self._current, {}

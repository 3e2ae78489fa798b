"""Metric declarations and the snapshot every exporter reads.

Each probe declares its metrics once, here-shaped: the Prometheus exporter, the README table and
later the HTTP API, the ZeroMQ stream and `drums top` all read the same Snapshot.
"""
from __future__ import annotations

from dataclasses import dataclass, field

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
    """Cumulative bucket counts matching Metric.buckets (without +Inf), sum and count."""

    cumulative: list[int]
    sum: float
    count: int


@dataclass
class Snapshot:
    """What the agent knows at one instant: metric -> [(label values, value)]."""

    series: dict[Metric, list[tuple[tuple[str, ...], object]]] = field(default_factory=dict)

    def add(self, metric: Metric, labels: tuple[str, ...], value) -> None:
        self.series.setdefault(metric, []).append((labels, value))

    def rows(self, metric: Metric) -> list:
        """The metric's (labels, value) list, to append to in bulk."""
        return self.series.setdefault(metric, [])

    def values(self, metric: Metric) -> dict[tuple[str, ...], object]:
        return dict(self.series.get(metric, ()))


class Monotonic:
    """Holds per-process totals at their highest value from one collect to the next.

    A total is read as live threads plus exited threads, from two maps one after the other; a
    thread that exits between the two reads is missing from both for that one collect. A series
    not seen in a collect is forgotten, so a process that ends (and a PID reused later) starts
    afresh.
    """

    def __init__(self):
        self._previous: dict = {}
        self._current: dict = {}

    def __call__(self, key, value):
        prev = self._previous.get(key)
        if prev is not None:
            if isinstance(value, Histogram):
                value = Histogram([max(a, b) for a, b in zip(prev.cumulative, value.cumulative)],
                                  max(prev.sum, value.sum), max(prev.count, value.count))
            else:
                value = max(prev, value)
        self._current[key] = value
        return value

    def next_collect(self) -> None:
        self._previous, self._current = self._current, {}

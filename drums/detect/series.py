"""What the detector knows of one series: where it comes from, what it belongs to (host, process,
node, topic, edge), what it measures in which unit, and how big a change must be to matter.

Read once, when the series first appears; the per-tick path only touches numbers.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

from drums import exposition, units

# Families that say what the agent (or this detector, scraped by the same Prometheus) is and does
# rather than what the robot does, families whose value is an identity (a start time) or a
# histogram's buckets (its count and sum are watched), and the per-process message timings, which
# the graph's per-topic, per-node and per-edge ones repeat under their names; and how sure a
# measure is (a clock offset's uncertainty, half an exchange that swings with the load).
SKIPPED = re.compile(r"drums_(probe|budget|graph|http|agent|self|scrape|job|stream|detect)_|drums_anomal|"
                     r"drums_ros_(publish_period|reaction|delivery)_|_info$|_bucket$|"
                     r"_start_time_seconds$|_total_bytes$|_size_bytes$|_deadline_seconds$|_fill_ratio$|"
                     r"_unattributed_rows$|_connection_limit$|_uncertainty_seconds$")

CATEGORIES = (  # the first pattern that matches the name
    ("cpu", re.compile(r"cpu|runqueue|context_switches|_load$")),
    ("memory", re.compile(r"memory|swap|_threads$|open_fds")),
    ("io", re.compile(r"disk|filesystem|_read_bytes|_written_bytes")),
    ("network", re.compile(r".")),
)

# Counts of the scheduler's own doings, which shift by a third and back as threads move between CPUs
# on a healthy host: only a doubling, or a fall to nothing, is news.
CHURN = re.compile(r"context_switches|runqueue_waits|runqueue_latency_seconds_count")
# Watched on request (--detail): per-thread and per-socket series, their process's totals in detail,
# the scheduler's (context switches, run-queue waits), which echo a change of CPU or traffic
# already seen and move with the load of the rest of the host, and the message timings (a
# histogram's sum and count: its rate times its mean), which swing with that load too.
DETAIL = re.compile(r"^drums_(thread|socket)_|context_switches|runqueue|_publish_period_|_reaction_|_delivery_")

# Judged for steady growth besides (drums.detect.checks.growth), from a process's first points: a
# leak from birth, whose history is all growth, never differs from its history.
GROWS = re.compile(r"^drums_(process|node)_resident_memory_bytes$")

KIB, MIB = 1024.0, 1024.0 ** 2


def floors(name: str, counter: bool) -> tuple[float, float]:
    """(absolute, relative) change under which a series' move is noise to a user, by unit: a
    counter is watched as its rate per second."""
    if counter:
        if name.endswith("_seconds_total") or name.endswith("_seconds_sum"):
            return 0.05, 0.25  # 5% of a core (CPU), 50 ms waited per second
        if name.endswith("_bytes_total"):
            return 16 * KIB, 0.25
        if CHURN.search(name):
            return 50.0, 1.0
        return 5.0, 0.25  # messages, calls, packets, errors per second
    if name.endswith("_bytes"):
        return 4 * MIB, 0.05  # memory: a leak shows long before it is a quarter more
    if name.endswith("_seconds"):
        return 0.005, 0.25  # round trips: a loopback RTT that triples is still nothing
    if name.endswith("_ratio"):
        return 0.05, 0.0
    return 2.0, 0.10  # threads, files, load


def measure(name: str, labels: dict[str, str]) -> str:
    """What the series measures, in a user's words: "received bytes", "resident memory", "cpu"."""
    words = name.removeprefix("drums_")
    for prefix in ("process_", "node_", "edge_", "topic_", "thread_", "socket_", "host_", "tcp_connection_",
                   "dds_writer_", "ros_", "latency_"):
        if words.startswith(prefix):
            words = words[len(prefix):]
            break
    words = words.removesuffix("_total").replace("memory_bytes", "memory").replace("_", " ")
    detail = [labels[k] for k in ("protocol", "kind", "mode", "interface", "device", "tid", "thread") if k in labels]
    words = words.removesuffix(" seconds") if "cpu" in words else words
    return words + (f" ({', '.join(detail)})" if detail else "")


@dataclass(slots=True)
class Series:
    source: str  # the agent (host) or Prometheus instance it came from
    text: str  # name{labels}, as the source wrote it
    name: str
    counter: bool
    category: str
    floor: float
    relative: float
    row: int = -1

    @classmethod
    def of(cls, source: str, text: str, counter: bool) -> "Series":
        brace = text.find("{")
        name = text if brace < 0 else text[:brace]
        floor, relative = floors(name, counter)
        category = next(c for c, pattern in CATEGORIES if pattern.search(name))
        return cls(source, text, name, counter, category, floor, relative)

    @property
    def grows(self) -> bool:
        return not self.counter and bool(GROWS.match(self.name))

    @property
    def key(self) -> tuple[str, str]:
        return self.source, self.text

    @property
    def labels(self) -> dict[str, str]:
        """Parsed when asked (for the few series flagged, and edges): ten thousand dicts kept would
        be most of the detector's memory."""
        return exposition.labels(self.text)

    @property
    def what(self) -> str:
        return measure(self.name, self.labels)

    def format(self, value: float) -> str:
        """A value of the series in its unit: 1.5 MiB/s, 12% (of a core), 250 MiB, 1.5 ms, 30/s."""
        if self.name.endswith(("_seconds_total", "_seconds_sum")):
            return units.percent(100 * value)
        if self.name.endswith("_bytes_total"):
            return units.bandwidth(value)
        if self.name.endswith("_bytes"):
            return units.size(value)
        if self.name.endswith("_seconds"):
            return units.duration(value)
        if self.name.endswith("_ratio"):
            return units.percent(100 * value)
        return f"{value:.3g}/s" if self.counter else f"{value:.3g}"


def watched(name: str, detail: bool = False) -> bool:
    return name.startswith("drums_") and not SKIPPED.search(name) and (detail or not DETAIL.search(name))

"""`drums top`: every host and every node of several agents, live, in one terminal.

It is a client (drums.client) like any other: a host job on each agent and a process job for each
node on its own host's agent, their streams merged, and rates from consecutive samples. The jobs
it created are deleted when it ends.
"""
from __future__ import annotations

import sys
import time
from collections import defaultdict

from drums.client import Client, Sample

CLEAR = "\x1b[H\x1b[2J"  # cursor home, clear screen


def _total(sample: Sample, name: str, skip: tuple[tuple[str, str], ...] = ()) -> float | None:
    """The sum of every series of `name` in the sample, but those with any of the `skip` labels."""
    values = [v for (n, labels), v in sample.series.items() if n == name and not set(skip) & set(labels)]
    return sum(values) if values else None


def _rate(now: Sample, before: Sample | None, name: str, skip=()) -> float | None:
    if before is None or now.time <= before.time:
        return None
    a, b = _total(before, name, skip), _total(now, name, skip)
    return None if a is None or b is None or b < a else (b - a) / (now.time - before.time)


def host_row(now: Sample, before: Sample | None) -> list:
    idle = ("mode", "idle"), ("mode", "iowait")
    busy, total = _rate(now, before, "drums_host_cpu_seconds_total", idle), \
        _rate(now, before, "drums_host_cpu_seconds_total")
    used, memory = _total(now, "drums_host_memory_used_bytes"), _total(now, "drums_host_memory_total_bytes")
    lo = (("interface", "lo"),)
    return [now.key.split(":", 1)[0],
            100 * busy / total if busy is not None and total else None,
            100 * used / memory if used is not None and memory else None,
            _rate(now, before, "drums_host_network_received_bytes_total", lo),
            _rate(now, before, "drums_host_network_sent_bytes_total", lo)]


def node_row(names: str, now: Sample, before: Sample | None) -> list:
    host, _, pid = now.key.split(":")
    cpu = _rate(now, before, "drums_process_cpu_seconds_total")
    rss = _total(now, "drums_process_resident_memory_bytes")
    return [host, names, pid, None if cpu is None else 100 * cpu, None if rss is None else rss / 1e6,
            _rate(now, before, "drums_process_socket_received_bytes_total"),
            _rate(now, before, "drums_process_socket_sent_bytes_total")]


def _cell(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:,.1f}"
    return str(value)


def table(headers: list[str], rows: list[list], names: int) -> str:
    """Columns padded to their widest cell: the first `names` to the left, numbers to the right."""
    cells = [headers] + [[_cell(v) for v in row] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    return "\n".join("  ".join(c.ljust(w) if i < names else c.rjust(w)
                               for i, (c, w) in enumerate(zip(row, widths))).rstrip() for row in cells)


class Top:
    def __init__(self, client: Client, interval: float):
        self.client = client
        self.interval = interval
        self.hosts: set[str] = set()  # the host jobs' stream keys
        self.nodes: dict[str, list[str]] = defaultdict(list)  # stream key -> the nodes of that process
        self.latest: dict[str, Sample] = {}
        self.before: dict[str, Sample] = {}

    def start(self) -> None:
        self.hosts = {job["stream"]["key"] for job in self.client.start("host", interval=self.interval)}
        for name, job in sorted(self.client.watch_nodes(self.interval).items()):
            self.nodes[job["stream"]["key"]].append(name)

    def update(self, wait: float) -> None:
        for s in self.client.poll(wait):
            if s.key in self.latest:
                self.before[s.key] = self.latest[s.key]
            self.latest[s.key] = s

    def complete(self) -> bool:
        """Whether every key has two samples: every rate can be shown."""
        return self.hosts | set(self.nodes) <= set(self.before)

    def render(self) -> str:
        hosts = [host_row(s, self.before.get(k)) for k, s in sorted(self.latest.items()) if k in self.hosts]
        nodes = [node_row(", ".join(self.nodes[k]), s, self.before.get(k)) for k, s in self.latest.items()
                 if k in self.nodes]
        nodes.sort(key=lambda r: -(r[3] or 0))
        return "\n".join([
            f"drums top  {len(hosts)} hosts, {sum(len(v) for v in self.nodes.values())} nodes, every "
            f"{self.interval:g} s  (Ctrl-C to quit)", "",
            table(["HOST", "CPU %", "MEM %", "RX B/s", "TX B/s"], hosts, names=1), "",
            table(["HOST", "NODE", "PID", "CPU %", "RSS MB", "RX B/s", "TX B/s"], nodes, names=2), ""])


def run(urls: list[str], token: str, interval: float, once: bool) -> int:
    with Client(urls, token) as client:
        top = Top(client, interval)
        try:
            top.start()
            if once:  # the first view with every rate, for scripts and tests
                deadline = time.monotonic() + 10 * interval + 10
                while not top.complete() and time.monotonic() < deadline:
                    top.update(interval)
                sys.stdout.write(top.render())
                return 0
            while True:
                top.update(interval)
                sys.stdout.write(CLEAR + top.render())
                sys.stdout.flush()
        finally:
            client.stop_all()

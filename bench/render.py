"""/metrics rendering alone: drums.exporters.prometheus.render of a Snapshot beside prometheus_client's
generate_latest of a custom collector that yields the same series from the same Snapshot (the way
a client_python exporter would build them at each scrape). Needs neither root nor BPF.

    .venv/bin/python bench/render.py [--sockets 1000 --processes 500 --threads 500] [--repeats 20]
"""
from __future__ import annotations

import argparse
import time

from common import fmt, main_wrapper, median, print_table, progress, ratio

GOAL_MS = 20  # the whole /metrics answer at a 1 s scrape


def build_snapshot(sockets: int, processes: int, threads: int):
    """Socket, process and thread series shaped as the sockets probe exports them."""
    from drums.metrics import Snapshot
    from drums.probes.sockets import PROCESS, SOCKET, THREAD

    snap = Snapshot()
    for i in range(sockets):
        pid = 1000 + i % max(1, processes)
        labels = (str(pid), f"talker_{pid}", "udp" if i % 3 else "tcp", f"10.0.{i // 250}.{i % 250}:{40000 + i}",
                  f"10.1.0.{i % 200}:7400", "4026531840", str(50000 + i))
        for n, metric in enumerate(SOCKET.values()):
            snap.add(metric, labels, (i + 1) * 1000 + n)
    for i in range(processes):
        labels = (str(1000 + i), f"talker_{1000 + i}", "udp")
        for n, metric in enumerate(PROCESS.values()):
            snap.add(metric, labels, (i + 1) * 4096 + n)
    for i in range(threads):
        labels = (str(1000 + i % max(1, processes)), str(20000 + i), "udp")
        for n, metric in enumerate(THREAD.values()):
            snap.add(metric, labels, (i + 1) * 512 + n)
    return snap


class SnapshotCollector:
    """A prometheus_client custom collector over a Snapshot: fresh families at each collect."""

    def __init__(self, snap):
        self.snap = snap

    def collect(self):
        from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

        for metric, rows in self.snap.series.items():
            cls = CounterMetricFamily if metric.kind == "counter" else GaugeMetricFamily
            family = cls(metric.name, metric.help, labels=metric.labels)
            for labels, value in rows:
                family.add_metric(labels, value)
            yield family


def samples_of(text: str) -> set:
    from prometheus_client.parser import text_string_to_metric_families

    return {(s.name, tuple(sorted(s.labels.items())), float(s.value))
            for family in text_string_to_metric_families(text) for s in family.samples}


def timed(fn, repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t) * 1000)
    return out


def run(args) -> None:
    from prometheus_client import CollectorRegistry, generate_latest

    from drums.exporters.prometheus import render

    snap = build_snapshot(args.sockets, args.processes, args.threads)
    n_series = sum(len(rows) for rows in snap.series.values())
    registry = CollectorRegistry(auto_describe=False)
    registry.register(SnapshotCollector(snap))

    ours_body, peer_body = render(snap), generate_latest(registry)
    same = samples_of(ours_body.decode()) == samples_of(peer_body.decode())
    progress(f"timing {n_series:,} series, {args.repeats} repeats each, interleaved")
    ours, peer = [], []
    for _ in range(args.repeats):  # interleaved, so that drift hits both alike
        ours += timed(lambda: render(snap), 1)
        peer += timed(lambda: generate_latest(registry), 1)
    o, p = median(ours), median(peer)
    rows = [
        ["median ms per render", fmt(o), fmt(p), ratio(o, p)],
        ["fastest ms", fmt(min(ours)), fmt(min(peer)), ratio(min(ours), min(peer))],
        ["body KiB", fmt(len(ours_body) / 1024, 0), fmt(len(peer_body) / 1024, 0),
         ratio(len(ours_body), len(peer_body))],
    ]
    print_table(f"/metrics rendering of {n_series:,} series", ["measure", "Drums render", "prometheus_client",
                                                                "Drums / client"], rows,
                [f"{args.sockets:,} sockets x 6 + {args.processes:,} processes x 6 + {args.threads:,} threads x 2 "
                 f"counter series; median of {args.repeats} interleaved repeats. prometheus_client "
                 "builds its families from the same Snapshot inside collect(), as a custom collector does.",
                 f"both bodies hold the same samples when parsed by prometheus_client: {'yes' if same else 'NO'}",
                 f"goal: the whole /metrics answer in at most {GOAL_MS} ms"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sockets", type=int, default=1000, help="sockets, 6 series each (default 1000)")
    parser.add_argument("--processes", type=int, default=500, help="processes, 6 series each (default 500)")
    parser.add_argument("--threads", type=int, default=500, help="threads, 2 series each (default 500)")
    parser.add_argument("--repeats", type=int, default=20, help="renders of each (default 20)")
    args = parser.parse_args()
    main_wrapper(lambda: run(args))


if __name__ == "__main__":
    main()

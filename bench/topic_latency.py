"""What the per-topic probes (rtps: syscall exits of DDS processes; rcl: uprobes on rcl_publish
and rcl_take) cost a ROS 2 topic: publisher-to-subscriber latency without and with them, and
the CPU of the agent's side (reading and naming the probes' maps once a second).

Nodes are rclpy processes over UDP (FASTDDS_BUILTIN_TRANSPORTS=UDPv4, so that both probes
work); each message carries its publish time. Latency is measured at --rate (default 1,000/s,
which one rclpy subscriber takes without queueing); the agent's CPU at --busy-rate (default
10,000/s). Goal: at most 2 us added per message, at most 2% of a core.

    .venv/bin/python bench/topic_latency.py [--rate 1000] [--busy-rate 10000] [--seconds 5] [--rounds 3]
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import threading
import time

from common import (PYTHON, ROOT, bpftool_json, fmt, main_wrapper, median, print_table, progress, ratio,
                    require_root)

NODES = os.path.join(ROOT, "bench", "latency_nodes.py")
PIN_ROOT = "/sys/fs/bpf/drums_bench_topics"
GOAL_US, GOAL_CPU = 2.0, 2.0
STATS_SYSCTL = "/proc/sys/kernel/bpf_stats_enabled"


def run_nodes(rate: float, seconds: float) -> dict:
    env = {**os.environ, "ROS_DOMAIN_ID": str(50 + os.getpid() % 50), "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4",
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}
    sub = subprocess.Popen([PYTHON, NODES, "sub"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
    try:
        sub.stdout.readline()  # ready
        pub = subprocess.run([PYTHON, NODES, "pub", str(rate), str(seconds)], capture_output=True, text=True,
                             env=env, timeout=seconds + 60)
        time.sleep(1.0)  # the last messages arrive
        out, _ = sub.communicate("", timeout=30)
        result = json.loads(out.strip().splitlines()[-1])
        result["sent"] = int(pub.stdout.split()[-1])
        return result
    finally:
        sub.kill()


class Collector:
    """The agent's side of the probes: collect every second in a thread; its CPU is measured."""

    def __init__(self):
        from drums.kernel.features import Features
        from drums.probes.rcl import RclProbe
        from drums.probes.rtps import RtpsProbe
        from drums.proctable import ProcessTable

        self.table = ProcessTable()
        features = Features()
        self.probes = [RtpsProbe(features, self.table, pin_root=PIN_ROOT), RclProbe(features, self.table,
                                                                                 pin_root=PIN_ROOT)]
        for p in self.probes:
            p.start()
        self.cpu = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from drums.metrics import Snapshot

        while not self._stop.wait(1.0):
            began = time.thread_time()
            self.table.refresh()
            snap = Snapshot()
            for p in self.probes:
                p.collect(snap)
            self.cpu += time.thread_time() - began

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        for p in self.probes:
            p.unload()


@contextlib.contextmanager
def bpf_stats():
    """The kernel's per-program run time statistics, on while the block runs (they cost time)."""
    with open(STATS_SYSCTL, "w") as f:
        f.write("1")
    try:
        yield
    finally:
        with open(STATS_SYSCTL, "w") as f:
            f.write("0")


def program_runs() -> dict[str, tuple[int, int]]:
    """Program name -> (run time ns, runs) of the per-topic probes' programs."""
    from drums.probes.rcl import PROGRAMS
    from drums.probes.rtps import SYSCALLS

    names = set(PROGRAMS) | {f"on_{call}" for call in SYSCALLS}
    return {p["name"]: (p["run_time_ns"], p["run_cnt"]) for p in bpftool_json("prog", "show") or []
            if p.get("name") in names and p.get("run_cnt")}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--rate", type=float, default=1000)
    parser.add_argument("--busy-rate", type=float, default=10000)
    parser.add_argument("--seconds", type=float, default=5)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    require_root()
    results = {"without": [], "with": []}
    for r in range(args.rounds):
        for mode in ("without", "with"):  # alternated, so that drift on the host hits both
            progress(f"latency round {r + 1}/{args.rounds}, {mode} probes")
            collector = Collector() if mode == "with" else None
            try:
                results[mode].append(run_nodes(args.rate, args.seconds))
            finally:
                if collector:
                    collector.close()
    progress(f"agent CPU at {args.busy_rate:.0f} messages/s, and the BPF programs' own run time")
    collector = Collector()
    began = time.monotonic()
    try:
        with bpf_stats():
            busy = run_nodes(args.busy_rate, args.seconds)
            runs = program_runs()
    finally:
        elapsed = time.monotonic() - began
        collector.close()
    cpu_pct = 100 * collector.cpu / elapsed
    per_message = sum(ns for ns, _ in runs.values()) / max(1, busy["sent"])

    p50 = {m: median(x["p50_us"] for x in rows) for m, rows in results.items()}
    p99 = {m: median(x["p99_us"] for x in rows) for m, rows in results.items()}
    lost = {m: sum(x["sent"] - x["count"] for x in rows) for m, rows in results.items()}
    print_table(
        f"Per-topic probes (rtps + rcl) on a ROS 2 topic over UDP: {args.rate:.0f} messages/s, "
        f"{args.seconds:.0f} s x {args.rounds} rounds, median of rounds",
        ("measure", "without probes", "with probes", "ratio", "added", "goal"),
        [("latency p50, us", fmt(p50["without"]), fmt(p50["with"]), ratio(p50["with"], p50["without"]),
          fmt(p50["with"] - p50["without"]), f"<= {GOAL_US:.0f} us added"),
         ("latency p99, us", fmt(p99["without"]), fmt(p99["with"]), ratio(p99["with"], p99["without"]),
          fmt(p99["with"] - p99["without"]), ""),
         ("messages lost", str(lost["without"]), str(lost["with"]), "", "", "0"),
         (f"agent CPU at {args.busy_rate:.0f} msg/s ({busy['sent']} sent), % of a core", "", fmt(cpu_pct), "",
          "", f"<= {GOAL_CPU:.0f}%"),
         ("BPF run time per message sent, us (all programs, both ends)", "", fmt(per_message / 1e3), "", "",
          f"<= {GOAL_US:.0f} us")],
        [f"{name}: {count} runs, {ns / max(1, count):,.0f} ns each" for name, (ns, count) in sorted(runs.items())]
        + ["uprobe traps (about 1-2 us each, 3 per message here) come on top of the BPF run time"])


if __name__ == "__main__":
    main_wrapper(main)

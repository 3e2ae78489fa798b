"""What the per-topic probes (rtps: syscall exits of DDS processes; rcl: uprobes on rcl_publish
and rcl_take) cost a ROS 2 topic: publisher-to-subscriber latency without them, with them
counting messages only (drums agent --no-ros-timing) and counting and timing them (the default),
and the CPU of the agent's side (reading and naming the probes' maps once a second).

Nodes are rclpy processes over UDP (FASTDDS_BUILTIN_TRANSPORTS=UDPv4, so that both probes
work); each message carries its publish time. Latency is measured at --rate (default 1,000/s,
which one rclpy subscriber takes without queueing) on one publisher and one subscriber that run
throughout, in windows of --seconds under each mode in turn (the order rotating every round): the
nodes, their discovery and their places on the CPUs are the same for every mode, and what timing
adds is the median over rounds of the difference within a round. The agent's CPU and the
programs' own run time at --busy-rate (default 10,000/s). Goals: at most 2 us of BPF per message in all, timing
adding at most 0.5 us of it and 5 us of latency to counting alone; at most 2% of a core.

    .venv/bin/python bench/topic_latency.py [--rate 1000] [--busy-rate 10000] [--seconds 5] [--rounds 9]
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import threading
import time

import numpy as np

from common import (PYTHON, ROOT, bpftool_json, fmt, main_wrapper, median, print_table, progress, ratio,
                    require_root)

NODES = os.path.join(ROOT, "bench", "latency_nodes.py")
PIN_ROOT = "/sys/fs/bpf/drums_bench_topics"
GOAL_US, GOAL_CPU = 2.0, 2.0
GOAL_TIMING_US, GOAL_TIMING_LATENCY_US = 0.5, 5.0  # what timing may add to counting alone
MODES = ("without", "counting", "timing")
SETTLE = 1.0  # seconds after the probes changed before a window starts
STATS_SYSCTL = "/proc/sys/kernel/bpf_stats_enabled"


ENV = {"ROS_DOMAIN_ID": str(50 + os.getpid() % 50), "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4",
       "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}


def run_nodes(rate: float, seconds: float) -> dict:
    env = {**os.environ, **ENV}
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


def latency_windows(rate: float, rounds: int, window: float) -> tuple[dict, int]:
    """{mode: [(p50 us, p99 us) of its window in each round]}, and the messages lost in all."""
    env = {**os.environ, **ENV}
    nodes = [subprocess.Popen([PYTHON, NODES, *role], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                              env=env) for role in (("sub", "all"), ("pub", str(rate)))]
    sub, pub = nodes
    windows = []
    try:
        sub.stdout.readline()  # ready
        pub.stdout.readline()  # publishing
        for r in range(rounds):
            for mode in MODES[r % len(MODES):] + MODES[:r % len(MODES)]:
                progress(f"latency round {r + 1}/{rounds}, probes: {mode}")
                collector = Collector(mode == "timing") if mode != "without" else None
                try:
                    time.sleep(SETTLE)
                    began = time.monotonic_ns()
                    time.sleep(window)
                    windows.append((mode, began, time.monotonic_ns()))
                finally:
                    if collector:
                        collector.close()
        sent = int(pub.communicate("", timeout=30)[0].split()[-1])
        time.sleep(1.0)  # the last messages arrive
        got = json.loads(sub.communicate("", timeout=60)[0].strip().splitlines()[-1])
    finally:
        for node in nodes:
            node.kill()
    at, latencies = np.array(got["at"]), np.array(got["latencies"]) / 1e3
    per_mode = {mode: [] for mode in MODES}
    for mode, began, ended in windows:
        inside = latencies[(at >= began) & (at < ended)]
        per_mode[mode].append((float(np.percentile(inside, 50)), float(np.percentile(inside, 99))))
    return per_mode, sent - got["count"]


class Collector:
    """The agent's side of the probes: collect every second in a thread; its CPU is measured.
    `timing`: rcl times the messages as well as counting them."""

    def __init__(self, timing: bool):
        from drums.kernel.features import Features
        from drums.probes.rcl import RclProbe
        from drums.probes.rtps import RtpsProbe
        from drums.proctable import ProcessTable

        self.table = ProcessTable()
        features = Features()
        self.probes = [RtpsProbe(features, self.table, pin_root=PIN_ROOT),
                       RclProbe(features, self.table, timing=timing, pin_root=PIN_ROOT)]
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


TAKE_SIDE = ("on_take", "on_take_return")  # the programs that run once a message is taken


def busy_run(timing: bool, rate: float, seconds: float) -> dict:
    """At `rate`: the agent's CPU (%), BPF ns per message sent and per message sent and taken, the
    programs' runs, and the messages sent and taken. At a busy rate the subscriber takes only some
    of the messages: the second figure charges the programs that run per take to the messages
    taken, what a message costs that goes all the way."""
    collector = Collector(timing)
    began = time.monotonic()
    try:
        with bpf_stats():
            busy = run_nodes(rate, seconds)
            runs = program_runs()
    finally:
        elapsed = time.monotonic() - began
        collector.close()
    sent, taken = max(1, busy["sent"]), max(1, busy["count"])
    from drums.probes.rcl import PROGRAMS

    def per_sent(names) -> float:
        return sum(ns for name, (ns, _) in runs.items() if name in names) / sent

    def per_delivered(names) -> float:
        return (sum(ns for name, (ns, _) in runs.items() if name in names and name not in TAKE_SIDE) / sent
                + sum(ns for name, (ns, _) in runs.items() if name in names and name in TAKE_SIDE) / taken)
    # Timing changes only the rcl programs: what it adds is theirs alone, without the run-to-run
    # noise of the rtps programs (the same code in both modes, a few hundred ns apart run to run).
    return {"cpu": 100 * collector.cpu / elapsed, "per_sent": per_sent(runs), "per_delivered": per_delivered(runs),
            "rcl_per_sent": per_sent(PROGRAMS), "rcl_per_delivered": per_delivered(PROGRAMS),
            "runs": runs, "sent": busy["sent"], "taken": busy["count"]}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--rate", type=float, default=1000)
    parser.add_argument("--busy-rate", type=float, default=10000)
    parser.add_argument("--seconds", type=float, default=5)
    parser.add_argument("--rounds", type=int, default=9)
    args = parser.parse_args()
    require_root()
    windows, lost = latency_windows(args.rate, args.rounds, args.seconds)
    busy = {}
    for mode in MODES[1:]:
        progress(f"agent CPU at {args.busy_rate:.0f} messages/s, and the BPF programs' own run time: {mode}")
        busy[mode] = busy_run(mode == "timing", args.busy_rate, args.seconds)

    p50, p99 = ({m: median(w[q] for w in rows) for m, rows in windows.items()} for q in (0, 1))
    # Within a round, the windows of the modes are seconds apart: their difference leaves out drift.
    differences = [[t[q] - c[q] for t, c in zip(windows["timing"], windows["counting"])] for q in (0, 1)]
    adds = [median(d) for d in differences]
    cpu = {m: b["cpu"] for m, b in busy.items()}
    bpf_us, delivered_us = ({m: b[what] / 1e3 for m, b in busy.items()} for what in ("per_sent", "per_delivered"))
    rcl_adds = [(busy["timing"][what] - busy["counting"][what]) / 1e3
                for what in ("rcl_per_sent", "rcl_per_delivered")]

    def row(what: str, values: dict, goal: str, added: float | None = None) -> tuple:
        return (what, *(fmt(values[m]) if m in values else "" for m in MODES),
                fmt(values["timing"] - values["counting"] if added is None else added), goal)
    print_table(
        f"Per-topic probes (rtps + rcl) on a ROS 2 topic over UDP: {args.rate:.0f} messages/s, windows of "
        f"{args.seconds:.0f} s x {args.rounds} rounds, median of rounds",
        ("measure", "without probes", "counting", "counting and timing", "timing adds", "goal"),
        [row("latency p50, us", p50, f"timing <= {GOAL_TIMING_LATENCY_US:.0f} us", adds[0]),
         row("latency p99, us", p99, f"timing <= {GOAL_TIMING_LATENCY_US:.0f} us", adds[1]),
         row(f"agent CPU at {args.busy_rate:.0f} msg/s, % of a core", cpu, f"<= {GOAL_CPU:.0f}%"),
         row("BPF run time per message sent, us (all programs, both ends; timing adds: rcl's)", bpf_us,
             f"<= {GOAL_US:.0f} us in all; timing <= {GOAL_TIMING_US} us", rcl_adds[0]),
         row("BPF run time per message sent and taken, us (take-side programs per take)", delivered_us,
             f"<= {GOAL_US:.0f} us in all; timing <= {GOAL_TIMING_US} us", rcl_adds[1])],
        [f"{mode}: {name}: {count} runs, {ns / max(1, count):,.0f} ns each"
         for mode, b in busy.items() for name, (ns, count) in sorted(b["runs"].items())]
        + [f"{mode}: {b['taken']} of {b['sent']} messages taken" for mode, b in busy.items()]
        + [f"messages lost in the latency windows' run: {lost} (goal 0)"]
        + [f"timing less counting by round, {q}, us: " + ", ".join(fmt(d, 1) for d in sorted(ds))
           for q, ds in zip(("p50", "p99"), differences)]
        + ["uprobe traps (about 1-2 us each, 3 per message here) come on top of the BPF run time"])


if __name__ == "__main__":
    main_wrapper(main)

"""What monitoring costs a network workload: iperf3 over loopback with no monitor, with empty BPF
programs where the agent's run on every send, receive and context switch (the floor of any monitor
that sees each call, bench/floor.py), with the Drums agent (all probes, scraped every second), and
with tcpdump capturing headers (the paper's pcap socket monitor). Conditions are interleaved round by round so that drift of the host hits all
of them alike; the table gives the median of seven rounds (of three, one fast round put tcpdump
11% above no monitor at all). Beside throughput it gives iperf3's own
CPU time per KiB, where the probes' per-event work is charged: on a host shared with other work,
throughput swings from run to run and that figure is the steadier one. Goal: the agent costs at
most 3%.

    .venv/bin/python bench/workload_overhead.py [--rounds 7] [--seconds 5]
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import subprocess
import tempfile
import threading
import time

from common import (PIN_ROOT, Agent, BenchError, ForeignWatch, cpu_seconds, drums_unload, fetch, fmt, free_port,
                    main_wrapper, median, pin_cpu, print_table, progress, require_root, require_tool, terminate)
from floor import Floor

CONDITIONS = ("none", "empty", "drums", "tcpdump")
# The tracepoints of the agent's programs that run per call or per context switch.
PER_EVENT = ("sock_send_length", "sock_recv_length", "sched_switch")
WORKLOADS = {
    # name: (iperf3 client arguments, what the table calls it)
    "tcp": (["-l", "1K"], "TCP, 1 KiB writes"),
    "udp": (["-u", "-b", "0", "-l", "1K"], "UDP, 1 KiB datagrams, unlimited rate"),
}
# Tracepoints whose programs would tax the workload even without an agent of ours.
HOT_TRACEPOINTS = ("sock_send_length", "sock_recv_length", "sched_switch", "sched_wakeup",
                   "inet_sock_set_state", "net_dev_queue", "netif_receive_skb")


class Scraper(threading.Thread):
    """Scrapes the agent like Prometheus would, so that the agent's collect cost is counted."""

    def __init__(self, url: str, interval: float):
        super().__init__(daemon=True)
        self.url, self.interval = url, interval
        self.done = threading.Event()
        self.scrapes = self.failures = 0

    def run(self) -> None:
        while not self.done.wait(self.interval):
            status, _ = fetch(self.url)
            self.scrapes += 1
            self.failures += status != 200


def iperf_client(port: int, args: list[str], seconds: float, cpu: int | None) -> dict:
    cmd = pin_cpu(cpu) + ["iperf3", "-c", "127.0.0.1", "-p", str(port), "-t", str(seconds), "-J", *args]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=seconds + 30, check=False)
    try:
        data = json.loads(proc.stdout)
    except json.JSONDecodeError:
        raise BenchError(f"iperf3 printed no JSON: {proc.stderr.strip()[-300:]}") from None
    if "error" in data:
        raise BenchError(f"iperf3: {data['error']}")
    end = data["end"]
    sent, received, cpu = end["sum_sent"], end["sum_received"], end["cpu_utilization_percent"]
    # iperf3's own CPU (getrusage of client and server), where the probes' per-event work is
    # charged: it measures the cost per message even when other work on the host slows the flow.
    client_cpu = cpu["host_total"] / 100 * sent["seconds"]
    server_cpu = cpu["remote_total"] / 100 * received["seconds"]
    kib_sent, kib_received = max(1, sent["bytes"] / 1024), max(1, received["bytes"] / 1024)
    cpu_us_per_kib = (client_cpu / kib_sent + server_cpu / kib_received) * 1e6
    return {"gbps": received["bits_per_second"] / 1e9, "loss": received.get("lost_percent", 0.0),
            "cpu_us_per_kib": cpu_us_per_kib}


class Monitor:
    """One condition's monitor, started before and stopped after each workload run."""

    def __init__(self, condition: str, scrape_interval: float, snaplen: int, floor: Floor):
        self.condition = condition
        self.floor = floor
        self.scrape_interval = scrape_interval
        self.snaplen = snaplen
        self.agent: Agent | None = None
        self.scraper: Scraper | None = None
        self.tcpdump: subprocess.Popen | None = None
        self.notes: list[str] = []

    @property
    def pid(self) -> int | None:
        """The monitor's own process, whose CPU is counted beside the workload's."""
        if self.agent is not None:
            return self.agent.proc.pid
        return self.tcpdump.pid if self.tcpdump is not None else None

    def start(self) -> None:
        if self.condition == "drums":
            self.agent = Agent().start()
            self.agent.wait_ready()
            if self.scrape_interval > 0:
                self.scraper = Scraper(self.agent.url, self.scrape_interval)
                self.scraper.start()
        elif self.condition == "empty":
            self.floor.attach(PER_EVENT)
        elif self.condition == "tcpdump":
            self._err = tempfile.TemporaryFile(mode="w+")
            self.tcpdump = subprocess.Popen(["tcpdump", "-i", "lo", "-s", str(self.snaplen), "-n",
                                             "-w", "/dev/null"], stdout=subprocess.DEVNULL, stderr=self._err)
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:  # tcpdump says "listening on" once capturing
                self._err.seek(0)
                if "listening on" in self._err.read():
                    break
                if self.tcpdump.poll() is not None:
                    raise BenchError("tcpdump exited at once")
                time.sleep(0.02)

    def stop(self) -> None:
        if self.scraper is not None:
            self.scraper.done.set()
            self.scraper.join()
            if self.scraper.failures:
                self.notes.append(f"{self.scraper.failures} of {self.scraper.scrapes} scrapes failed")
            self.scraper = None
        if self.agent is not None:
            # Another agent on the host that stops unpins the shared programs, and ours with them.
            if not glob.glob(os.path.join(PIN_ROOT, "sockets-*")):
                self.notes.append("the agent's pins were gone at the end of the run (removed by "
                                  "another agent or `drums unload` on this host)")
            self.agent.stop()
            self.agent = None
        self.floor.detach()
        if self.tcpdump is not None:
            self.tcpdump.send_signal(2)  # SIGINT: tcpdump prints its capture statistics
            try:
                self.tcpdump.wait(10)
            except subprocess.TimeoutExpired:
                terminate(self.tcpdump)
            self._err.seek(0)
            stats = [line for line in self._err.read().splitlines() if "packets" in line]
            self._err.close()
            self.notes.append("; ".join(stats))
            self.tcpdump = None


def run(args) -> None:
    require_root()
    for tool in ("iperf3", "tcpdump", "taskset", "bpftool"):
        require_tool(tool)
    drums_unload()
    from drums.kernel.features import Features
    floor = Floor(Features().kernel_headers)
    watch = ForeignWatch(HOT_TRACEPOINTS)
    notes: list[str] = []
    server_cpu, client_cpu = (None, None) if args.no_pin else (1, 0)
    port = free_port()
    server = subprocess.Popen(pin_cpu(server_cpu) + ["iperf3", "-s", "-p", str(port)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    results = {(w, c): [] for w in WORKLOADS for c in CONDITIONS}
    tcpdump_stats = {w: [] for w in WORKLOADS}
    try:
        time.sleep(0.3)
        for rnd in range(args.rounds):
            for condition in CONDITIONS:
                for workload, (client_args, _) in WORKLOADS.items():
                    progress(f"round {rnd + 1}/{args.rounds}: {workload} with {condition}")
                    if condition != "drums":
                        watch.look()
                    monitor = Monitor(condition, args.scrape_interval, args.snaplen, floor)
                    monitor.start()
                    try:
                        cpu0, t0 = (cpu_seconds(monitor.pid) if monitor.pid else 0.0), time.monotonic()
                        result = iperf_client(port, client_args, args.seconds, client_cpu)
                        if monitor.pid:
                            busy = cpu_seconds(monitor.pid) - cpu0
                            result["monitor_cpu"] = busy / (time.monotonic() - t0) * 100
                        results[workload, condition].append(result)
                    finally:
                        monitor.stop()
                    if condition == "tcpdump":
                        tcpdump_stats[workload].extend(monitor.notes)
                    elif monitor.notes:
                        notes.extend(f"{workload}/{condition}: {n}" for n in monitor.notes)
                    time.sleep(args.pause)
    finally:
        terminate(server)
        floor.close()
        drums_unload()

    rows = []
    for workload, (_, label) in WORKLOADS.items():
        med = {c: median(r["gbps"] for r in results[workload, c]) for c in CONDITIONS}
        rows.append([f"{label}: received Gbit/s", *(fmt(med[c]) for c in CONDITIONS),
                     *(_cost(med[c], med["none"]) for c in CONDITIONS[1:])])
        if workload == "udp":
            loss = {c: median(r["loss"] for r in results[workload, c]) for c in CONDITIONS}
            rows.append([f"{label}: loss %", *(fmt(loss[c]) for c in CONDITIONS), "", "", ""])
        cpu = {c: median(r["cpu_us_per_kib"] for r in results[workload, c]) for c in CONDITIONS}
        rows.append([f"{label}: iperf3 CPU us per KiB", *(fmt(cpu[c], 3) for c in CONDITIONS),
                     *(_cost(cpu[c], cpu["none"]) for c in CONDITIONS[1:])])
        own = {c: median(r.get("monitor_cpu", 0.0) for r in results[workload, c]) for c in CONDITIONS}
        rows.append([f"{label}: monitor's own CPU %", "", "", fmt(own["drums"], 1), fmt(own["tcpdump"], 1),
                     "", "", ""])
    for workload in WORKLOADS:
        for c in CONDITIONS:
            runs = ", ".join(fmt(r["gbps"]) for r in results[workload, c])
            notes.append(f"{workload} {c} per round (Gbit/s): {runs}")
    for workload, stats in tcpdump_stats.items():
        if stats:
            notes.append(f"tcpdump on {workload}, last round: {stats[-1]}")
    notes += watch.notes()
    pinning = "no CPU pinning" if args.no_pin else "iperf3 client on CPU 0, server on CPU 1"
    notes.insert(0, f"median of {args.rounds} interleaved rounds of {args.seconds} s each; {pinning}; "
                    f"the agent runs all probes and is scraped every {args.scrape_interval:g} s; "
                    f"empty programs: one that returns at once on each of {', '.join(PER_EVENT)}, as the "
                    "agent attaches its own (tp_btf where the kernel offers it); "
                    f"tcpdump -s {args.snaplen}. iperf3 CPU per KiB: client CPU per KiB sent plus server CPU per "
                    "KiB received, from iperf3's own accounting; a monitor's own CPU: % of one core during "
                    "the run. Goal: the agent costs at most 3%.")
    notes.insert(1, "tcpdump sees loopback TCP as the segments the stack makes of the writes (up to 64 KiB each, "
                    "see its packet counts below), a program on sock_send_length sees every write: on TCP the empty "
                    "programs' column is the least that any monitor counting each call costs here.")
    print_table("Workload overhead: iperf3 over loopback",
                ["workload", "no monitor", "empty programs", "Drums", "tcpdump", "empty / none", "Drums / none",
                 "tcpdump / none"], rows, notes)


def _cost(with_monitor: float, without: float) -> str:
    """A figure with the monitor over the figure without, and the change in percent."""
    if not without:
        return "n/a"
    r = with_monitor / without
    return f"{r:.3f} ({(r - 1) * 100:+.1f}%)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=7, help="rounds of every condition (default 7)")
    parser.add_argument("--seconds", type=int, default=5, help="length of each iperf3 run (default 5)")
    parser.add_argument("--pause", type=float, default=0.5, help="seconds between runs (default 0.5)")
    parser.add_argument("--scrape-interval", type=float, default=1.0,
                        help="seconds between scrapes of the agent; 0 for none (default 1)")
    parser.add_argument("--snaplen", type=int, default=96, help="tcpdump snap length (default 96)")
    parser.add_argument("--no-pin", action="store_true", help="do not pin the iperf3 client and server")
    args = parser.parse_args()
    main_wrapper(lambda: run(args))


if __name__ == "__main__":
    main()

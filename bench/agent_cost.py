"""What the agent itself costs on a busy host: 1,000 processes and 10,000 open sockets, all started
after the agent (as on a robot whose agent starts at boot), scraped once a second. Beside it, the
paper's approach: a process that polls the same processes with psutil each second (cpu_times,
memory_info, io_counters, num_threads, and net_connections for the sockets). Both are measured
alike, one after the other: CPU from /proc/<pid>/stat over the window, which starts once the agent
has taken the crowd in (what that cost is said apart), USS from smaps_rollup at its end; the kernel
memory its BPF maps hold is said beside. Goals: at most 0.5% of one core, 30 MB USS, /metrics in
10 ms.
The agent runs three times: with the auto graph (no helper process); with the ROS 2 graph, whose
rclpy reader is a child: its whole tree is measured, goal 60 MB; and with the ROS 2 graph and
/diagnostics, which that one child publishes too. Then the first again, and the poller, on a host
of a tenth of the processes and sockets, goal 0.1% of one core; there also with two probes of five,
and with a tenth of its budget: what a scrape costs apart from what it reads and serves.

    .venv/bin/python bench/agent_cost.py [--seconds 30] [--processes 1000] [--sockets 10000]
"""
from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shlex
import subprocess
import sys
import textwrap
import threading
import time

from common import (Agent, BenchError, Scraper, cpu_seconds, drums_unload, fmt, main_wrapper, median,
                    memory, percentile, print_table, progress, ratio, require_root, samples, series_count,
                    terminate, tree, uss_bytes)

GOALS = {"cpu": 0.5, "uss_mb": 30, "metrics_ms": 10, "tree_uss_mb": 60, "small_cpu": 0.1}
SMALL = 10  # the small host: a tenth of the processes and sockets
# The small host again, to tell what a scrape costs apart from what it reads and serves: the agent
# with the two probes whose maps every other kind of row depends on, and with a tenth of its budget.
TWO_PROBES = ["--probe", "sockets", "--probe", "sched"]
TENTH_BUDGET = ["--max-processes", "10", "--max-threads", "20", "--max-sockets", "10", "--max-connections", "10"]
HOLDERS = 4  # processes that hold the sockets
# Seconds of scrapes, unmeasured, once the crowd is ready and the auto graph shows its socket
# holders: the agent takes it in (reads every new process's name and files; the graph, which polls
# every 5 s, dumps its sockets and reads their owners) before the window that measures its steady
# cost. What taking it in cost is reported apart.
SETTLE = 10

# Holds N loopback TCP connections (2N sockets). On "send" each socket sends a few bytes and reads
# its peer's; on end of input it exits.
HOLDER = textwrap.dedent("""
    import socket, sys
    conns = int(sys.argv[1])
    srv = socket.socket(); srv.bind(("127.0.0.1", 0)); srv.listen(1024)
    pairs = []
    for _ in range(conns):
        c = socket.create_connection(srv.getsockname()); s, _ = srv.accept()
        pairs.append((c, s))
    print("ready", flush=True)
    for line in sys.stdin:
        if line.strip() == "send":
            for c, s in pairs:
                c.sendall(b"ping"); s.sendall(b"pong")
            for c, s in pairs:
                s.recv(4); c.recv(4)
            print("sent", flush=True)
""")


def raise_fd_limit(need: int) -> None:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = max(soft, need)
    if want > hard:
        hard = want  # root may raise the hard limit
    resource.setrlimit(resource.RLIMIT_NOFILE, (want, hard))


class Crowd:
    """The host's load: sleeping processes and socket-holding processes, killed on close."""

    def __init__(self, processes: int, sockets: int):
        self.sleepers: list[subprocess.Popen] = []
        self.holders: list[subprocess.Popen] = []
        self.processes, self.sockets = processes, sockets

    def start(self) -> None:
        per_holder = -(-self.sockets // (2 * HOLDERS))  # connections per holder, rounded up
        raise_fd_limit(2 * per_holder + 256)
        for _ in range(HOLDERS):
            self.holders.append(subprocess.Popen([sys.executable, "-c", HOLDER, str(per_holder)],
                                                 stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True))
        for _ in range(max(0, self.processes - HOLDERS)):
            self.sleepers.append(subprocess.Popen(["sleep", "3600"], stdin=subprocess.DEVNULL,
                                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        for h in self.holders:
            if h.stdout.readline().strip() != "ready":
                raise BenchError("a socket holder failed to open its connections")

    def send(self) -> None:
        for h in self.holders:
            h.stdin.write("send\n")
            h.stdin.flush()
        for h in self.holders:
            if h.stdout.readline().strip() != "sent":
                raise BenchError("a socket holder failed to send")

    def pids(self) -> list[int]:
        return [p.pid for p in self.sleepers + self.holders]

    def restart(self) -> None:
        """The crowd made anew, its sockets sending once: started after an agent, as on a robot
        whose agent starts at boot, every process has run and every connection was opened under
        the probes (a crowd older than the agent would be mostly invisible to them: a process that
        never runs and a connection that never changes state leave no entry in their maps)."""
        self.close()
        self.start()
        self.send()

    def close(self) -> None:
        for h in self.holders:
            try:
                h.stdin.close()
            except OSError:
                pass
        for p in self.sleepers:
            p.kill()
        for p in self.sleepers:
            p.wait()
        for h in self.holders:
            terminate(h, timeout=5)
        self.sleepers, self.holders = [], []


def measure_agent(seconds: float, interval: float, agent_args: list[str], crowd: Crowd) -> dict:
    # Each agent starts as the first: cold (no pins of the one before), on a host without the crowd,
    # which starts once it is ready. An agent that starts beside a crowd that is then replaced
    # holds the rows of both for a while: measured, it ends 7 MB larger (72.4 against 65.4 MB),
    # its heap's pages half used after two crowds.
    crowd.close()
    drums_unload()
    agent = Agent(extra=agent_args).start()
    try:
        agent.wait_ready()
        processes = tree(agent.proc.pid)  # the whole tree: the agent and any helper it started
        before = sum(map(cpu_seconds, processes))
        crowd.restart()
        scraper = Scraper(agent.url)
        holders = set() if "ros2" in agent_args else {str(h.pid) for h in crowd.holders}
        settled = time.monotonic() + SETTLE
        while True:
            shown = set(re.findall(r'pid="(\d+)"', "".join(samples(scraper.get()[1], "drums_node_info"))))
            if time.monotonic() >= settled and holders <= shown:
                break
            if time.monotonic() > settled + 60:
                raise BenchError("the auto graph did not show the crowd's socket holders within a minute")
            time.sleep(interval)
        latencies, collect, whole, sizes, per_probe = [], [], [], [], {}
        cpu0, t0 = sum(map(cpu_seconds, processes)), time.monotonic()
        next_at = t0
        while time.monotonic() - t0 < seconds:
            start = time.perf_counter()
            status, body = scraper.get()
            latencies.append((time.perf_counter() - start) * 1000)
            if status != 200:
                raise BenchError(f"/metrics answered {status}")
            durations = samples(body, "drums_probe_collect_duration_seconds")
            collect.append(sum(durations.values()) * 1000)
            whole.append(samples(body, "drums_agent_collect_duration_seconds")[""] * 1000)
            for labels, v in durations.items():
                per_probe.setdefault(labels.split('"')[1], []).append(v * 1000)
            sizes.append((len(body), series_count(body)))
            next_at += interval
            time.sleep(max(0.0, next_at - time.monotonic()))
        cpu1, t1 = sum(map(cpu_seconds, processes)), time.monotonic()
        scraper.close()
        each = [uss_bytes(p) for p in processes]
        return {"cpu": (cpu1 - cpu0) / (t1 - t0) * 100, "settle_cpu": cpu0 - before, "uss": sum(each), "uss_each": each,
                "rss": sum(memory(p).get("Rss", 0) for p in processes), "processes": len(processes),
                "latencies": latencies, "collect": collect, "sizes": sizes[-1],
                "per_probe": {k: median(v) for k, v in per_probe.items()}, "whole": whole,
                "sockets": len(samples(body, "drums_socket_sent_bytes_total")),
                "maps": sum(samples(body, "drums_probe_map_memory_bytes").values())}
    finally:
        agent.stop()


def measure_poller(seconds: float, interval: float, pids: list[int], pid_file: str) -> dict:
    with open(pid_file, "w") as f:
        f.write("\n".join(map(str, pids)))
    proc = subprocess.Popen([sys.executable, os.path.abspath(__file__), "--poller", pid_file,
                             "--interval", str(interval)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        if proc.stdout.readline().strip() != "ready":
            raise BenchError("the psutil poller did not start")
        time.sleep(SETTLE)  # as for the agent: the first cycles are not measured
        cpu0, t0 = cpu_seconds(proc.pid), time.monotonic()
        time.sleep(seconds)
        cpu1, t1 = cpu_seconds(proc.pid), time.monotonic()
        uss, rss = uss_bytes(proc.pid), memory(proc.pid).get("Rss", 0)
        proc.stdin.close()
        cycles = json.loads(proc.stdout.readline())
        proc.wait(30)
    finally:
        terminate(proc)
    measured = cycles[int(SETTLE / interval):] or cycles
    return {"cpu": (cpu1 - cpu0) / (t1 - t0) * 100, "uss": uss, "rss": rss, "cycles": measured}


def poller(pid_file: str, interval: float) -> None:
    """The peer: poll each process and the socket table with psutil every interval, until stdin
    closes; then print the duration of each cycle in ms."""
    import psutil

    with open(pid_file) as f:
        procs = [psutil.Process(int(line)) for line in f if line.strip()]
    stop = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    print("ready", flush=True)
    cycles = []
    next_at = time.monotonic()
    while not stop.is_set():
        start = time.perf_counter()
        for p in procs:
            try:
                with p.oneshot():
                    p.cpu_times(), p.memory_info(), p.io_counters(), p.num_threads()
            except psutil.Error:
                pass
        psutil.net_connections(kind="inet")
        cycles.append((time.perf_counter() - start) * 1000)
        next_at += interval
        stop.wait(max(0.0, next_at - time.monotonic()))
    print(json.dumps(cycles), flush=True)


def measure_host(processes: int, sockets: int, seconds: float, interval: float, agent_args: list[str],
                 variants: list[list[str]]) -> tuple[dict, list[dict], dict]:
    """The agent, then the agent with each variant's extra flags, and the psutil poller on a host of
    `processes` processes holding `sockets` sockets."""
    crowd = Crowd(processes, sockets)
    pid_file = f"/tmp/drums-bench-pids-{os.getpid()}"
    try:
        progress(f"agent: {seconds} s at one scrape per {interval:g} s, once {processes} processes holding "
                 f"{sockets} sockets have started after it")
        ours = measure_agent(seconds, interval, agent_args, crowd)
        others = []
        for extra in variants:
            progress(f"agent with {' '.join(extra)}: {seconds} s")
            others.append(measure_agent(seconds, interval, agent_args + extra, crowd))
        progress(f"psutil poller: {seconds} s")
        crowd.restart()
        peer = measure_poller(seconds, interval, crowd.pids(), pid_file)
    finally:
        crowd.close()
        drums_unload()
        try:
            os.unlink(pid_file)
        except OSError:
            pass
    return ours, others, peer


# What each part of a scrape does, for the profile: why it costs what the run measures.
WHY = {
    "host": "/proc/meminfo; psutil: /proc/stat, diskstats, net/dev; a statvfs per mount (listed when they change)",
    "process": "psutil for the chosen processes due (stat, statm, status, io, fd; smaps_rollup when RSS moved)",
    "sched": "the threads marked changed looked up (the thread map whole when most were), all handed on "
             "as arrays (no row per thread); rows remade for processes whose threads ran, renamed or came",
    "sockets": "the sockets marked changed since the last collect, all handed on as arrays (no row per socket)",
    "tcp": "the connections marked changed; sock_diag RTT of the kept connections every 5 s",
    "latency": "its map, empty unless the TCP latency probe is asked for",
    "rest of the collect": "process table, PIDs to read, the graph's join, the budget's ranking and folds "
                           "(sockets, connections and threads as arrays, processes as rows; a kept row that "
                           "did not change given again as it was), self-metrics",
    "render, gzip, HTTP": "the text of families that changed, ISA-L gzip, h11 on asyncio, and the client's gunzip",
}


def profile(run: dict) -> list[list[str]]:
    """Median ms of each part of one scrape: the probes as the agent times them, the rest of its
    collect, and what the client waited for beyond it."""
    rows = [[name, fmt(ms, 2), WHY.get(name, "")] for name, ms in sorted(run["per_probe"].items(), key=lambda kv: -kv[1])]
    rest = [w - c for w, c in zip(run["whole"], run["collect"])]
    after = [lat - w for lat, w in zip(run["latencies"], run["whole"])]
    rows.append(["rest of the collect", fmt(median(rest), 2), WHY["rest of the collect"]])
    rows.append(["render, gzip, HTTP", fmt(median(after), 2), WHY["render, gzip, HTTP"]])
    rows.append(["a scrape as the client timed it", fmt(median(run["latencies"]), 2), ""])
    return rows


def each_mb(run: dict) -> str:
    """The USS of each process of a measured tree, the agent first."""
    return " + ".join(fmt(uss / 2 ** 20, 1) for uss in run["uss_each"])


def run(args) -> None:
    require_root()
    agent_args = shlex.split(args.agent_args)
    ours, (ros, diag), peer = measure_host(args.processes, args.sockets, args.seconds, args.interval, agent_args,
                                           [["--graph", "ros2"], ["--graph", "ros2", "--diagnostics"]])
    small, (two_probes, tenth), small_peer = measure_host(
        args.processes // SMALL, args.sockets // SMALL, args.seconds, args.interval, agent_args,
        [TWO_PROBES, TENTH_BUDGET])

    lat, cyc = ours["latencies"], peer["cycles"]
    mb = 2 ** 20
    rows = [
        [f"CPU, % of one core (goal <= {GOALS['cpu']})", fmt(ours["cpu"]), fmt(peer["cpu"]),
         ratio(ours["cpu"], peer["cpu"])],
        [f"USS MB at the end (goal <= {GOALS['uss_mb']})", fmt(ours["uss"] / mb, 1), fmt(peer["uss"] / mb, 1),
         ratio(ours["uss"], peer["uss"])],
        ["RSS MB at the end", fmt(ours["rss"] / mb, 1), fmt(peer["rss"] / mb, 1), ratio(ours["rss"], peer["rss"])],
        ["kernel memory of the BPF maps, MB (in neither USS nor RSS)", fmt(ours["maps"] / mb, 1), "", ""],
        [f"ms per cycle, median (goal <= {GOALS['metrics_ms']})", fmt(median(lat), 1), fmt(median(cyc), 1),
         ratio(median(lat), median(cyc))],
        ["ms per cycle, p95", fmt(percentile(lat, 95), 1), fmt(percentile(cyc, 95), 1),
         ratio(percentile(lat, 95), percentile(cyc, 95))],
        [f"taking the crowd in (from its start until {SETTLE} s after it was ready): CPU seconds, once",
         fmt(ours["settle_cpu"]), "", ""],
        ["with the ROS 2 graph (--graph ros2), whole tree: CPU, % of one core", fmt(ros["cpu"]), fmt(peer["cpu"]),
         ratio(ros["cpu"], peer["cpu"])],
        [f"with the ROS 2 graph, whole tree: USS MB (goal <= {GOALS['tree_uss_mb']})", fmt(ros["uss"] / mb, 1),
         fmt(peer["uss"] / mb, 1), ratio(ros["uss"], peer["uss"])],
        ["with the ROS 2 graph and /diagnostics (--graph ros2 --diagnostics), whole tree: CPU, % of one core",
         fmt(diag["cpu"]), fmt(peer["cpu"]), ratio(diag["cpu"], peer["cpu"])],
        ["with the ROS 2 graph and /diagnostics, whole tree: USS MB", fmt(diag["uss"] / mb, 1),
         fmt(peer["uss"] / mb, 1), ratio(diag["uss"], peer["uss"])],
        [f"at {args.processes // SMALL:,} processes / {args.sockets // SMALL:,} sockets: CPU, % of one core "
         f"(goal <= {GOALS['small_cpu']})", fmt(small["cpu"]), fmt(small_peer["cpu"]),
         ratio(small["cpu"], small_peer["cpu"])],
        [f"at {args.processes // SMALL:,} processes / {args.sockets // SMALL:,} sockets: ms per cycle, median",
         fmt(median(small["latencies"]), 1), fmt(median(small_peer["cycles"]), 1),
         ratio(median(small["latencies"]), median(small_peer["cycles"]))],
        [f"there, the sockets and sched probes alone ({' '.join(TWO_PROBES)}): CPU, % of one core",
         fmt(two_probes["cpu"]), fmt(small_peer["cpu"]), ratio(two_probes["cpu"], small_peer["cpu"])],
        [f"there, a tenth of the default budget ({' '.join(TENTH_BUDGET)}): CPU, % of one core",
         fmt(tenth["cpu"]), fmt(small_peer["cpu"]), ratio(tenth["cpu"], small_peer["cpu"])],
    ]
    size, series = ours["sizes"]
    notes = [
        f"{args.processes:,} processes ({HOLDERS} of them hold {args.sockets:,} loopback TCP sockets, each "
        f"of which sent a few bytes), all started after the agent was ready (as on a robot whose agent "
        f"starts at boot: each process has run and each connection opened under the probes), "
        f"{args.seconds} s window after {SETTLE} s of unmeasured cycles (taking the crowd in, below), one cycle per "
        f"{args.interval:g} s; each agent starts cold on a host without the crowd, and runs all probes"
        + f" (its whole process tree measured: {ours['processes']} process{'es' if ours['processes'] > 1 else ''})"
        + (f" with {args.agent_args}" if args.agent_args else " with its default budget") + ".",
        "a Drums cycle is one /metrics request timed by the client (collect + render + HTTP), over one "
        "connection kept alive and gzipped, as Prometheus scrapes; a psutil "
        "cycle is one poll of every process and of net_connections(), with nothing rendered or sent.",
        f"/metrics body: {series:,} series, {size / 1024:,.0f} KiB; per-socket series "
        f"(drums_socket_sent_bytes_total): {ours['sockets']:,}",
        f"the first rows: the auto graph (no helper process); with the ROS 2 graph the tree is "
        f"{ros['processes']} processes (the agent and its rclpy graph reader: {each_mb(ros)} MB USS), started "
        f"and measured alike after the first run, with a crowd started anew once it is ready; with "
        f"/diagnostics too, the tree is {diag['processes']} processes ({each_mb(diag)} MB: that one child "
        f"publishes the arrays too, drawn from the scrapes' snapshots)",
        "the last rows: the agent (auto graph) and the poller again on a host of a tenth of the processes and "
        f"sockets; then the agent there with two probes of five, and with a tenth of its budget "
        f"({two_probes['sizes'][1]:,} and {tenth['sizes'][1]:,} series against {small['sizes'][1]:,}): what a "
        "scrape costs whatever it reads and however many series it serves",
    ]
    print_table("Agent cost: 1 s scrapes on a host with many processes and sockets",
                ["measure", "Drums agent", "psutil poller", "Drums / psutil"], rows, notes)
    print_table(f"Agent cost: where a scrape's time goes at {args.processes:,} processes / {args.sockets:,} sockets",
                ["part", "median ms", "what it does"], profile(ours),
                ["medians over the same run's scrapes, each part on its own (the medians need not add up); "
                 "probes as drums_probe_collect_duration_seconds says, the rest of the collect as "
                 "drums_agent_collect_duration_seconds less them, and the client's time less the collect"])


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--poller":
        parser = argparse.ArgumentParser()
        parser.add_argument("--poller")
        parser.add_argument("--interval", type=float, default=1.0)
        a = parser.parse_args()
        poller(a.poller, a.interval)
        return
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=int, default=30, help="measured window of each (default 30)")
    parser.add_argument("--interval", type=float, default=1.0, help="seconds between cycles (default 1)")
    parser.add_argument("--processes", type=int, default=1000, help="processes on the host (default 1000)")
    parser.add_argument("--sockets", type=int, default=10000, help="open sockets (default 10000)")
    parser.add_argument("--agent-args", default="", help="extra agent flags, e.g. '--max-sockets 20000'")
    args = parser.parse_args()
    main_wrapper(lambda: run(args))


if __name__ == "__main__":
    main()

"""The HTTP front under hostile clients, the agent beside node_exporter (Debian's
prometheus-node-exporter, Go's net/http with its defaults), alike:

- slowloris: 3,000 connections trickling a request head (tests/robustness/hostile.py) while
  /metrics is scraped once a second: scrapes answered, their p99, the server's USS growth, and
  the seconds until a scrape is answered in under 1 s again after the attackers go;
- idle connections beyond the open-file limit: 1,100 idle connections to a server started with
  `prlimit --nofile=1024:1024` (systemd's default soft limit, as hard limit too): scrapes answered;
- 200 concurrent scrapes: answered, p99.

The agent runs twice: as users run it (all probes, which also count the attackers' sockets, here on
the same host) and with its HTTP server alone (no socket probes). Goals (issue 14): slowloris 99%
answered, p99 under 1 s, USS growth under 20 MB, recovery within 5 s; idle: scrapes answered;
concurrent: all answered, p99 under 2 s.

    .venv/bin/python bench/http_robustness.py [--seconds 20]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

from common import (ROOT, Agent, BenchError, fetch, fmt, free_port, main_wrapper, percentile, print_table,
                    progress, ratio, require_root, require_tool, terminate, uss_bytes)

SLOWLORIS, IDLE, CONCURRENT = 3000, 1100, 200
FD_LIMIT = ["prlimit", "--nofile=1024:1024"]
HTTP_ALONE = ["--no-probe", "sockets", "--no-probe", "tcp"]
MB = 1 << 20


class Server:
    """A server to measure: its /metrics URL, its PID, and how to stop it."""

    def __init__(self, name: str, under: list[str], extra: list[str] | None = None):
        self.name, self.under, self.extra = name, under, extra
        self.agent: Agent | None = None
        self.proc: subprocess.Popen | None = None

    def start(self) -> "Server":
        if self.extra is not None:  # the agent
            self.agent = Agent(extra=self.extra, under=self.under).start()
            self.url, self.pid = self.agent.url, self.agent.proc.pid
        else:
            port = free_port()
            self.proc = subprocess.Popen([*self.under, require_tool("prometheus-node-exporter"),
                                          f"--web.listen-address=127.0.0.1:{port}"],
                                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            self.url, self.pid = f"http://127.0.0.1:{port}/metrics", self.proc.pid
        deadline = time.monotonic() + 60
        while fetch(self.url, timeout=2)[0] != 200:
            if time.monotonic() > deadline:
                raise BenchError(f"{self.name} did not serve /metrics within 60 s")
            time.sleep(0.1)
        for _ in range(3):  # warm: caches filled, first collections done
            fetch(self.url, timeout=10)
        return self

    def stop(self) -> None:
        if self.agent is not None:
            self.agent.stop()
        if self.proc is not None:
            terminate(self.proc)

    def __enter__(self) -> "Server":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def hostile(kind: str, url: str, n: int) -> subprocess.Popen:
    port = url.split(":")[2].split("/")[0]
    proc = subprocess.Popen([sys.executable, "-m", "tests.robustness.hostile", kind, "127.0.0.1", port, str(n)],
                            cwd=ROOT, stdout=subprocess.PIPE, text=True)
    if not proc.stdout.readline().startswith("holding"):
        raise BenchError(f"the {kind} client did not start")
    return proc


def timed(url: str, timeout: float = 5) -> float | None:
    began = time.monotonic()
    status, _ = fetch(url, timeout=timeout)
    return time.monotonic() - began if status == 200 else None


def slowloris(server: Server, seconds: int) -> dict:
    before = peak = uss_bytes(server.pid)
    attack = hostile("slowloris", server.url, SLOWLORIS)
    times = []
    try:
        for _ in range(seconds):
            began = time.monotonic()
            times.append(timed(server.url))
            peak = max(peak, uss_bytes(server.pid))
            time.sleep(max(0.0, 1 - (time.monotonic() - began)))
    finally:
        terminate(attack)
    gone = time.monotonic()
    recovery = float("nan")
    while time.monotonic() - gone < 30:
        took = timed(server.url, timeout=2)
        if took is not None and took < 1:
            recovery = time.monotonic() - gone
            break
        time.sleep(0.1)
    answered = [t for t in times if t is not None]
    return {"answered": 100 * len(answered) / len(times), "p99": percentile(answered, 99),
            "uss_mb": (peak - before) / MB, "recovery": recovery}


def idle(server: Server) -> dict:
    attack = hostile("idle", server.url, IDLE)
    try:
        times = []
        for _ in range(10):
            times.append(timed(server.url))
            time.sleep(0.5)
    finally:
        terminate(attack)
    return {"answered": 100 * sum(t is not None for t in times) / len(times)}


def concurrent(server: Server) -> dict:
    port = server.url.split(":")[2].split("/")[0]
    out = subprocess.run([sys.executable, "-m", "tests.robustness.hostile", "scrapes", "127.0.0.1", port,
                          str(CONCURRENT)], cwd=ROOT, capture_output=True, text=True, timeout=120, check=True)
    seconds = json.loads(out.stdout)["seconds"]
    answered = [s for s in seconds if s is not None]
    return {"answered": 100 * len(answered) / len(seconds), "p99": percentile(answered, 99)}


def measure(name: str, extra: list[str] | None, seconds: int) -> dict:
    progress(f"{name}: slowloris, {seconds} s")
    with Server(name, [], extra) as server:
        out = {"slowloris": slowloris(server, seconds)}
    progress(f"{name}: idle connections at the open-file limit")
    with Server(name, FD_LIMIT, extra) as server:
        out["idle"] = idle(server)
    progress(f"{name}: {CONCURRENT} concurrent scrapes")
    with Server(name, [], extra) as server:
        out["concurrent"] = concurrent(server)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=int, default=20, help="scrapes under slowloris, one a second (default 20)")
    args = parser.parse_args()
    require_root()
    require_tool("prometheus-node-exporter")
    ours = measure("agent", [], args.seconds)
    alone = measure("agent, HTTP alone", HTTP_ALONE, args.seconds)
    peer = measure("node_exporter", None, args.seconds)

    def row(what: str, key: tuple, digits: int, goal: str) -> list:
        a, b, c = (r[key[0]][key[1]] for r in (ours, alone, peer))
        return [what, fmt(a, digits), fmt(b, digits), fmt(c, digits), ratio(a, c), goal]
    print_table("HTTP front under hostile clients: the agent beside node_exporter",
                ["measure", "agent", "agent, HTTP alone", "node_exporter", "agent / node_exporter", "goal"],
                [row(f"slowloris ({SLOWLORIS:,} connections): scrapes answered, %", ("slowloris", "answered"), 0, ">= 99"),
                 row("slowloris: scrape p99, s", ("slowloris", "p99"), 3, "< 1"),
                 row("slowloris: USS growth, MB", ("slowloris", "uss_mb"), 1, "< 20"),
                 row("slowloris: recovery after they go, s", ("slowloris", "recovery"), 2, "< 5"),
                 row(f"{IDLE:,} idle connections, 1,024 open files: scrapes answered, %", ("idle", "answered"), 0,
                     "100"),
                 row(f"{CONCURRENT} concurrent scrapes: answered, %", ("concurrent", "answered"), 0, "100"),
                 row(f"{CONCURRENT} concurrent scrapes: p99, s", ("concurrent", "p99"), 3, "< 2")],
                [f"Slowloris: {args.seconds} scrapes, one a second, each given 5 s; the attackers are on the same "
                 "host, so the agent with all probes also counts their sockets (a remote attacker's are the "
                 "agent's own, at most its connection limit).",
                 "node_exporter 1.5 (Debian): Go's net/http without header timeouts, --web.max-requests 40 "
                 "(concurrent scrapes over it are answered 503)."])


if __name__ == "__main__":
    main_wrapper(main)

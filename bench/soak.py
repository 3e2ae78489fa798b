"""A soak: the agent (all probes, the ROS 2 graph) for many minutes under churn, its memory, open
files and threads, and the exactness of its byte counts, printed every minute.

Churn, all the while: short processes started 5 times a second; a process whose threads start and
end 20 times a second; TCP connections opened, used and closed 20 times a second; a ROS 2 talker and
listener started and stopped every 30 s (each minute is read in the same phase); a scrape every
second and a job (created, read, deleted) every 10 s. Exactness: a meter process sends exactly
100,000 bytes over one TCP connection each minute; the agent's drums_process_socket_sent_bytes_total
of it must grow by exactly that. Goals (issue 14): USS flat within 2 MB after the warm-up (the first
2 minutes), open files and threads flat, 0 bytes off.

.venv/bin/python bench/soak.py [--minutes 30]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import textwrap
import threading
import time
import urllib.request

from common import ROOT, Agent, fetch, main_wrapper, print_table, progress, require_root, terminate, tree, uss_bytes

WARMUP = 2  # minutes
METER_BYTES = 100_000
NODES = os.path.join(ROOT, "tests", "graph", "rosnodes.py")

# Sends METER_BYTES over one connection on each line of input, and says so.
METER = textwrap.dedent("""
    import socket, sys, threading
    srv = socket.create_server(("127.0.0.1", 0))
    c = socket.create_connection(srv.getsockname()); s, _ = srv.accept()
    def drain():
        while s.recv(1 << 16):
            pass
    threading.Thread(target=drain, daemon=True).start()
    print("ready", flush=True)
    for line in sys.stdin:
        c.sendall(b"x" * int(line))
        print("sent", flush=True)
""")
# Threads that start and end, and connections opened, used and closed, until killed.
CHURN = textwrap.dedent("""
    import socket, threading, time
    srv = socket.create_server(("127.0.0.1", 0))
    def serve():
        while True:
            s, _ = srv.accept(); s.recv(100); s.close()
    threading.Thread(target=serve, daemon=True).start()
    while True:
        t = threading.Thread(target=time.sleep, args=(0.01,)); t.start(); t.join()
        with socket.create_connection(srv.getsockname()) as c:
            c.sendall(b"hello")
        time.sleep(0.05)
""")


def fds_and_threads(pid: int) -> tuple[int, int]:
    fds = sum(len(os.listdir(f"/proc/{p}/fd")) for p in tree(pid) if os.path.exists(f"/proc/{p}/fd"))
    threads = sum(len(os.listdir(f"/proc/{p}/task")) for p in tree(pid) if os.path.exists(f"/proc/{p}/task"))
    return fds, threads


def sent_by(api: str, pid: int) -> float | None:
    """The meter's TCP bytes sent, from its job's latest sample (before the budget, which may fold
    a process busy once a minute into other)."""
    try:
        job = json.loads(urllib.request.urlopen(f"{api}/monitor/pid/{pid}", timeout=10).read())
    except OSError:
        return None
    return next((r["value"] for r in (job.get("sample") or {}).get("series", [])
                 if r["name"] == "drums_process_socket_sent_bytes_total" and r["labels"].get("protocol") == "tcp"),
                None)


def call(api: str, method: str, path: str, body: bytes | None = None) -> None:
    try:
        urllib.request.urlopen(urllib.request.Request(f"{api}/{path}", method=method, data=body), timeout=10).read()
    except OSError:
        pass


def job_round(api: str, pid: int) -> None:
    for method in ("POST", "GET", "DELETE"):
        call(api, method, f"monitor/pid/{pid}", b'{"interval": 1, "lease": 30}' if method == "POST" else None)


def churn(stop: threading.Event) -> None:
    """Short processes, and ROS 2 nodes that come and go."""
    nodes: list[subprocess.Popen] = []
    tick = 0
    while not stop.wait(0.2):
        subprocess.run(["/bin/true"])
        tick += 1
        if tick % 150 == 0:  # every 30 s
            for n in nodes:
                terminate(n)
            nodes = [] if nodes else [subprocess.Popen([sys.executable, NODES, role, role], stdin=subprocess.PIPE,
                                                       stdout=subprocess.DEVNULL) for role in ("talker", "listener")]
    for n in nodes:
        terminate(n)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--minutes", type=int, default=30)
    args = parser.parse_args()
    require_root()
    stop = threading.Event()
    with Agent(extra=["--graph", "ros2"]) as agent:
        agent.wait_ready()
        api = agent.url.replace("/metrics", "/drums/v1")
        meter = subprocess.Popen([sys.executable, "-c", METER], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        churner = subprocess.Popen([sys.executable, "-c", CHURN])
        background = threading.Thread(target=churn, args=(stop,), daemon=True)
        try:
            meter.stdout.readline()
            call(api, "POST", f"monitor/pid/{meter.pid}", b'{"interval": 1}')
            background.start()
            rows, sent = [], 0
            start = time.monotonic()
            for minute in range(1, args.minutes + 1):
                while time.monotonic() - start < minute * 60:
                    began = time.monotonic()
                    fetch(agent.url, timeout=10)
                    if int(began - start) % 10 == 0:
                        job_round(api, churner.pid)
                    time.sleep(max(0.0, 1 - (time.monotonic() - began)))
                meter.stdin.write(f"{METER_BYTES}\n")
                meter.stdin.flush()
                meter.stdout.readline()
                sent += METER_BYTES
                time.sleep(2.5)  # the job's next samples: the bytes are in them
                counted = sent_by(api, meter.pid)
                off = None if counted is None else counted - sent
                fds, threads = fds_and_threads(agent.proc.pid)
                uss = sum(uss_bytes(p) for p in tree(agent.proc.pid)) / (1 << 20)
                own = uss_bytes(agent.proc.pid) / (1 << 20)
                rows.append([minute, f"{own:.1f}", f"{uss:.1f}", fds, threads, "n/a" if off is None else f"{off:.0f}"])
                progress(f"minute {minute}: USS {own:.1f} MB (tree {uss:.1f}), {fds} open files, {threads} threads, "
                         f"{rows[-1][-1]} bytes off")
        finally:
            stop.set()
            background.join(30)
            terminate(churner)
            meter.stdin.close()
            terminate(meter)
    warm = [r for r in rows if r[0] > WARMUP] or rows
    own, uss = [float(r[1]) for r in warm], [float(r[2]) for r in warm]
    print_table(f"Soak: {args.minutes} minutes of churn", ["minute", "USS, agent, MB", "USS, whole tree, MB",
                                                          "open files", "threads", "bytes off"], rows,
                [f"After the warm-up ({WARMUP} minutes): USS of the agent {min(own):.1f}-{max(own):.1f} MB, of the "
                 f"whole tree {min(uss):.1f}-{max(uss):.1f} MB (goal: flat within 2), open files "
                 f"{min(r[3] for r in warm)}-{max(r[3] for r in warm)}, threads {min(r[4] for r in warm)}-"
                 f"{max(r[4] for r in warm)}; "
                 "bytes off: the meter's bytes as its job's sample counts them, less those it sent (goal 0)."])


if __name__ == "__main__":
    main_wrapper(main)

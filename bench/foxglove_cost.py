"""What `drums foxglove` costs beside the agent it follows: its CPU with one Foxglove client
subscribed to every channel (about a hundred on a host of a hundred processes: a channel per
process that holds no node, per host and interface), polling each second, as a ratio to the
agent's own CPU over the same window (the agent as `make run` starts it, which also answers the
server's polls). Goal: at most the agent's own.

The client is the tests' (tests/foxglove_client.py, written from the protocol's specification),
reading everything it is sent in a thread of this process.

    .venv/bin/python bench/foxglove_cost.py [--seconds 60]
"""
from __future__ import annotations

import argparse
import subprocess
import threading
import time

from common import PYTHON, ROOT, BenchError, cpu_seconds, fmt, free_port, main_wrapper, print_table, progress, \
    ratio, terminate, tree

WARMUP = 10.0  # seconds: the channels advertised and subscribed, two polls made


def wait_serving(url: str, proc: subprocess.Popen, what: str) -> None:
    import urllib.request
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            urllib.request.urlopen(url, timeout=5).read()
            return
        except OSError:
            if proc.poll() is not None:
                raise BenchError(f"{what} ended: {proc.stdout.read()}")
            time.sleep(0.2)
    raise BenchError(f"{what} did not serve {url} in 60 s")


def measure(seconds: float) -> list:
    from tests.foxglove_client import Client
    port = free_port()
    agent = subprocess.Popen([PYTHON, "-m", "drums", "agent", "--port", str(port), "--stream-port", "0",
                              "--pin-dir", f"/sys/fs/bpf/drums_bench_foxglove_{port}"], cwd=ROOT,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    server = None
    try:
        wait_serving(f"http://127.0.0.1:{port}/metrics", agent, "the agent")
        server = subprocess.Popen([PYTHON, "-m", "drums", "foxglove", "--port", "0", "--agent",
                                   f"http://127.0.0.1:{port}"], cwd=ROOT, stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True)
        line = server.stdout.readline()
        if "ws://" not in line:
            raise BenchError(f"drums foxglove did not start: {line}{server.stdout.read()}")
        client = Client(int(line.split("ws://", 1)[1].split()[0].rsplit(":", 1)[1]))
        channels, messages, stop = {}, [0], threading.Event()

        def read() -> None:
            subscribed = set()
            while not stop.is_set():
                try:
                    m = client.message()
                except OSError:  # the server stopped
                    return
                if m["op"] == "advertise":
                    new = [c for c in m["channels"] if c["id"] not in subscribed]
                    channels.update({c["id"]: c["topic"] for c in new})
                    subscribed.update(c["id"] for c in new)
                    client.send({"op": "subscribe", "subscriptions": [{"id": c["id"], "channelId": c["id"]} for c in new]})
                elif m["op"] == "messageData":
                    messages[0] += 1
        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        progress(f"warming up {WARMUP:g} s")
        time.sleep(WARMUP)
        agent_pids = tree(agent.pid)
        cpu0 = [cpu_seconds(server.pid), sum(cpu_seconds(p) for p in agent_pids)]
        got0, began = messages[0], time.monotonic()
        progress(f"measuring {seconds:g} s over {len(channels)} channels")
        time.sleep(seconds)
        elapsed = time.monotonic() - began
        cpu = [cpu_seconds(server.pid) - cpu0[0], sum(cpu_seconds(p) for p in agent_pids) - cpu0[1]]
        stop.set()
        shares = [100 * c / elapsed for c in cpu]
        return [[len(channels), fmt((messages[0] - got0) / elapsed, 1), fmt(shares[0], 2), fmt(shares[1], 2),
                 ratio(shares[0], shares[1])]]
    finally:
        if server is not None:
            terminate(server)
        terminate(agent)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    args = ap.parse_args()
    rows = measure(args.seconds)
    print_table("drums foxglove beside the agent it follows (one client subscribed to every channel)",
                ["channels", "messages/s to the client", "drums foxglove, % of a core", "the agent, % of a core",
                 "foxglove / agent"], rows,
                [f"{args.seconds:g} s after {WARMUP:g} s of warm-up; CPU from /proc/<pid>/stat (the agent's with its "
                 "helpers); goal: at most 1.00x"])


if __name__ == "__main__":
    main_wrapper(main)

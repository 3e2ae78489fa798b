"""Bandwidth of the two ways out of the agent, beside the paper's figure: the ZeroMQ stream of job
samples and the Prometheus scrape of /metrics, at about 300 and 3,000 series sampled each second.

The paper measured 150-310 kbit/s for 243-392 metrics at 1 s: 617-791 bit/s per metric (its
collector pushed JSON-like msgpack maps with every name every time). Goal: under a third of that
per series, 206-264 bit/s.

Both ways are counted as TCP payload from the agent to its reader (ZeroMQ framing and HTTP headers
included, IP and TCP headers not) by a relay between them. The series are process jobs (7 series
each: memory, threads, descriptors, I/O, start time) on idle `sleep` processes; the scrape serves
the same processes (--process-name '^sleep$') plus the agent's own metrics.

    .venv/bin/python bench/stream_bandwidth.py [--seconds 10]
"""
from __future__ import annotations

import argparse
import gzip
import math
import socket
import subprocess
import threading
import time
import urllib.request

from common import PYTHON, ROOT, BenchError, fetch, fmt, free_port, main_wrapper, print_table, progress, \
    series_count, terminate

PAPER_BITS_PER_METRIC = (150_000 / 243, 310_000 / 392)  # the paper's low and high end
SERIES_PER_PROCESS = 7


class Relay:
    """A TCP relay on a free port to `port`, counting the bytes that come back from it."""

    def __init__(self, port: int):
        self.target = port
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.downstream = 0
        self._lock = threading.Lock()
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            server = socket.create_connection(("127.0.0.1", self.target))
            threading.Thread(target=self._pump, args=(client, server, False), daemon=True).start()
            threading.Thread(target=self._pump, args=(server, client, True), daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket, count: bool) -> None:
        try:
            while data := src.recv(1 << 16):
                if count:
                    with self._lock:
                        self.downstream += len(data)
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for s in (src, dst):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def take(self) -> int:
        with self._lock:
            value, self.downstream = self.downstream, 0
        return value

    def close(self) -> None:
        self.listener.close()


def measure(series: int, seconds: float) -> list:
    import msgpack
    import zmq

    from drums.client import Agent

    processes = math.ceil(series / SERIES_PER_PROCESS)
    sleepers = [subprocess.Popen(["sleep", "3600"]) for _ in range(processes)]
    port = free_port()
    agent = subprocess.Popen([PYTHON, "-m", "drums", "agent", "--port", str(port), "--stream-port", "0",
                              "--graph", "auto", "--probe", "process", "--process-name", "^sleep$",
                              "--max-processes", str(processes + 100), "--pin-dir", f"/sys/fs/bpf/drums_bench_{port}"],
                             cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    context = zmq.Context()
    relays = []
    try:
        api = Agent(f"http://127.0.0.1:{port}")
        deadline = time.monotonic() + 30
        while fetch(f"http://127.0.0.1:{port}/metrics")[0] != 200:
            if agent.poll() is not None or time.monotonic() > deadline:
                raise BenchError("the agent did not start")
            time.sleep(0.1)
        progress(f"{processes} process jobs, {processes * SERIES_PER_PROCESS} series")
        stream_port = api.info()["stream"]["address"].rsplit(":", 1)[1]
        for p in sleepers:
            api.start("pid", str(p.pid), interval=1.0)
        stream, scrape = Relay(int(stream_port)), Relay(port)
        relays = [stream, scrape]
        sub = context.socket(zmq.SUB)
        sub.linger = 0
        sub.connect(f"tcp://127.0.0.1:{stream.port}")
        sub.subscribe(b"")
        time.sleep(3)  # past the first keyframes and the first collects
        while sub.poll(0):
            sub.recv_multipart()
        stream.take()
        scrape.take()
        values = scraped = 0
        gzipped = False
        began = time.monotonic()
        next_scrape = began
        while time.monotonic() - began < seconds:
            if time.monotonic() >= next_scrape:  # as Prometheus would, once a second
                request = urllib.request.Request(f"http://127.0.0.1:{scrape.port}/metrics",
                                                 headers={"Accept-Encoding": "gzip"})
                with urllib.request.urlopen(request, timeout=10) as reply:
                    body = reply.read()
                    gzipped = reply.headers.get("Content-Encoding") == "gzip"
                scraped = series_count(gzip.decompress(body) if gzipped else body)
                next_scrape += 1.0
            if sub.poll(50):
                _, payload = sub.recv_multipart()
                values += len(msgpack.unpackb(payload)["values"])
        elapsed = time.monotonic() - began
        stream_rate, scrape_rate = stream.take() / elapsed, scrape.take() / elapsed
        stream_series = values / elapsed
        rows = []
        scrape_way = "Prometheus scrape (gzip)" if gzipped else "Prometheus scrape (text)"
        for way, rate, count in (("ZeroMQ stream", stream_rate, stream_series), (scrape_way, scrape_rate, scraped)):
            per = rate * 8 / count if count else float("nan")
            rows.append([way, fmt(count, 0), fmt(rate * 8 / 1000, 1), fmt(per, 1),
                         f"{per / PAPER_BITS_PER_METRIC[1]:.2f}-{per / PAPER_BITS_PER_METRIC[0]:.2f}x"])
        return rows
    finally:
        for r in relays:
            r.close()
        context.destroy(linger=0)
        terminate(agent)
        for p in sleepers:
            p.kill()
            p.wait()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10, help="measuring time at each size (default 10)")
    args = parser.parse_args()
    rows = []
    for series in (300, 3000):
        rows += [[f"~{series}", *row] for row in measure(series, args.seconds)]
    print_table(
        "Stream and scrape bandwidth at 1 s (bench/stream_bandwidth.py)",
        ["series asked", "way out", "series/s", "kbit/s", "bit/s per series", "vs paper (617-791 bit/s)"],
        rows,
        [f"The paper: 150-310 kbit/s for 243-392 metrics at 1 s. Goal: under a third of it per series "
         f"(below 0.33x). Measured over {args.seconds:g} s at each size, after 3 s of warm-up.",
         "The stream carries labels only with a new layout and every 10th message of a key, values "
         "otherwise, in one message per job; the scrape carries every label every time, in one gzipped "
         "page (asked for with Accept-Encoding: gzip, as Prometheus asks)."])


if __name__ == "__main__":
    main_wrapper(main)

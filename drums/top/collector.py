"""Where `drums top` gets its numbers, in threads of its own so that a slow or dead agent never
holds up the screen: a thread per agent polls its graph and /metrics every interval, and one
thread keeps top's jobs on the agents (a host job, and a latency job to each other host of the
agent's graph) and reads their stream; it alone touches the ZeroMQ sockets, which are not safe
to share between threads.

Each job top makes has a lease, renewed three times per lease: a top that is killed -9 leaves
jobs that end by themselves; any other end deletes them (close()).
"""
from __future__ import annotations

import json
import threading
import time
import urllib.request

from drums.client import AgentError, Client
from drums.exporters.jobs import MAX_LEASE
from drums.top.model import DOWN, Model
from drums.top.poll import fetch

LEASE_INTERVALS, MIN_LEASE = 5, 10.0  # a lease outlives a renewal that a busy agent answers late
RENEWALS_PER_LEASE = 3
STREAM_WAIT = 0.2  # seconds the jobs thread waits for samples before it looks at its jobs again
LATENCY_INTERVAL = 1.0  # at least: a round of probes takes its time
CLOSE_REQUESTS = 3  # how many requests' time top waits for its jobs to be deleted when it ends


def timeout(interval: float) -> float:
    """How long a request may take: long enough for a busy agent, short enough to leave promptly."""
    return min(max(2 * interval, 2.0), 10.0)


class Collector:
    def __init__(self, urls: list[str], token: str, interval: float, detector: str = ""):
        """`detector`: the URL of a `drums detect` whose anomalies the Anomalies view lists."""
        self.interval = interval
        self.detector = detector.rstrip("/")
        self.lease = min(max(MIN_LEASE, LEASE_INTERVALS * interval), MAX_LEASE)
        self.model = Model(urls, interval)
        self.client = Client(urls, token)
        for agent in self.client.agents:
            agent.timeout = timeout(interval)
        self.stopping = threading.Event()
        self._threads: list[threading.Thread] = []
        self._latency: dict[int, set[str]] = {}  # agent index -> the hosts top measures from it

    def start(self) -> None:
        for i, agent in enumerate(self.client.agents):
            self._threads.append(threading.Thread(target=self._follow, args=(i,), name=f"top {agent.url}", daemon=True))
        self._threads.append(threading.Thread(target=self._keep_jobs, name="top jobs", daemon=True))
        if self.detector:
            self._threads.append(threading.Thread(target=self._detect, name="top detector", daemon=True))
        for t in self._threads:
            t.start()

    def close(self) -> None:
        """Stop the threads; the jobs thread deletes the jobs top made on its way out. Not for
        longer than a few requests' time: jobs on an agent that does not answer end with their
        lease."""
        self.stopping.set()
        until = time.monotonic() + CLOSE_REQUESTS * timeout(self.interval)
        for t in self._threads:
            t.join(timeout=max(0.0, until - time.monotonic()))

    def _follow(self, index: int) -> None:
        agent, host = self.client.agents[index], ""
        while not self.stopping.is_set():
            began = time.monotonic()
            try:
                host = host or agent.info()["host"]
                self.model.polled(index, host, fetch(agent))
            except (AgentError, KeyError, TypeError) as e:
                host = ""  # another agent may answer at that URL next time
                self.model.failed(index, str(e) if isinstance(e, AgentError) else f"{agent.url}: not a Drums agent")
            self.stopping.wait(max(0.0, began + self.interval - time.monotonic()))

    def _detect(self) -> None:
        while not self.stopping.is_set():
            began = time.monotonic()
            try:
                with urllib.request.urlopen(f"{self.detector}/anomalies", timeout=timeout(self.interval)) as answer:
                    found = json.load(answer)
                if not isinstance(found, dict) or not isinstance(found.get("incidents"), list):
                    raise ValueError("not the anomalies of drums detect")
                self.model.detected(found)
            except (OSError, ValueError) as e:
                self.model.detected(None, f"no detector at {self.detector} ({e}): start `drums detect`")
            self.stopping.wait(max(0.0, began + self.interval - time.monotonic()))

    def _keep_jobs(self) -> None:
        renew_at = {}  # agent index -> time.monotonic() when its jobs are asked for again
        try:
            while not self.stopping.is_set():
                frame = self.model.frame()
                for i, agent in enumerate(frame.agents):
                    if agent.host and agent.state(frame.at, self.interval) != DOWN and \
                            time.monotonic() >= renew_at.get(i, 0):
                        self._keep(i, agent.latest.hosts if agent.latest else {}, agent.host)
                        renew_at[i] = time.monotonic() + self.lease / RENEWALS_PER_LEASE
                    elif agent.failed:
                        renew_at.pop(i, None)  # when it is back, at once
                for sample in self.client.poll(STREAM_WAIT):
                    self.model.sampled(sample)
        finally:
            self.client.stop_all()
            self.client.close()

    def _keep(self, index: int, hosts: dict[str, dict], own: str) -> None:
        """The host job on an agent, and a latency job to each other host of its graph."""
        agent, errors = self.client.agents[index], []
        targets = {h.get("address") or name for name, h in hosts.items() if name != own}
        for target in self._latency.get(index, set()) - targets:
            self.client.release("latency", target, agent)
        self._latency[index] = targets
        wanted = [("host", "", self.interval)] + [("latency", t, max(self.interval, LATENCY_INTERVAL)) for t in sorted(targets)]
        for kind, target, interval in wanted:
            try:
                self.client.keep(kind, target, agent, interval=interval, lease=self.lease)
            except AgentError as e:
                errors.append(str(e))
        self.model.jobs_done(index, "; ".join(errors))

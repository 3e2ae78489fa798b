"""What `drums top` knows, fed by the collector's threads and read by the screen: each agent's
state and its last two polls, and the last two samples of each job top keeps on the agents.

Writers and readers meet only here, under one lock; `frame()` hands the screen a copy that stays
still while it computes rows from it.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field, replace

from drums.client import Sample
from drums.top.poll import Poll

UP, STALE, DOWN, CONNECTING = "up", "stale", "down", "connecting"
STALE_INTERVALS = 3  # an agent whose last good poll is older than this many intervals is stale


@dataclass
class AgentState:
    url: str
    host: str = ""  # the agent's host name, once it answered
    error: str = ""  # why the last poll failed
    jobs_error: str = ""  # why the jobs top keeps on it could not be made or renewed ("" once they are)
    failed: bool = False  # the last poll failed
    last_ok: float = 0.0  # time.time() of the last good poll
    before: Poll | None = None
    latest: Poll | None = None

    def state(self, now: float, interval: float) -> str:
        if self.failed:
            return DOWN
        if self.latest is None:
            return CONNECTING
        if self.latest.stale or now - self.last_ok > STALE_INTERVALS * max(interval, 1.0):
            return STALE
        return UP


@dataclass
class Frame:
    """The model at one instant, for the views."""

    at: float
    interval: float
    agents: list[AgentState]
    samples: dict[str, tuple[Sample | None, Sample]] = field(default_factory=dict)  # stream key -> (before, latest)
    anomalies: dict | None = None  # the detector's /anomalies, once it answered
    detector_error: str = ""  # why the detector did not answer

    def live(self) -> list[AgentState]:
        """The agents whose rows are shown: up, or stale (their last numbers, marked)."""
        return [a for a in self.agents if a.latest is not None and a.state(self.at, self.interval) in (UP, STALE)]

    def sample(self, key: str) -> tuple[Sample | None, Sample | None]:
        return self.samples.get(key, (None, None))


class Model:
    def __init__(self, urls: list[str], interval: float):
        self.interval = interval
        self.agents = [AgentState(url) for url in urls]
        self.samples: dict[str, tuple[Sample | None, Sample]] = {}
        self.anomalies: dict | None = None
        self.detector_error = ""
        self.version = 0  # grows with every change, so the screen knows when to draw again
        self._lock = threading.Lock()

    def polled(self, index: int, host: str, poll: Poll) -> None:
        with self._lock:
            agent = self.agents[index]
            if agent.host != host or agent.failed:  # another agent at that URL, or back after a gap
                agent.before = None
            else:
                agent.before = agent.latest
            agent.host, agent.latest, agent.failed, agent.last_ok, agent.error = host, poll, False, time.time(), ""
            self.version += 1

    def failed(self, index: int, error: str) -> None:
        with self._lock:
            agent = self.agents[index]
            agent.failed, agent.error = True, error
            self.version += 1

    def jobs_done(self, index: int, error: str = "") -> None:
        """The jobs on an agent were made or renewed, or why not: shown, and top goes on."""
        with self._lock:
            if self.agents[index].jobs_error != error:
                self.agents[index].jobs_error = error
                self.version += 1

    def sampled(self, sample: Sample) -> None:
        with self._lock:
            before, latest = self.samples.get(sample.key, (None, None))
            # A sample soon after another (a renewed job samples at once) measures too short a time:
            # rates are taken from the one before it.
            if latest is None or sample.time - latest.time >= self.interval / 2:
                before = latest
            if before is not None and sample.time <= before.time:
                before = None
            self.samples[sample.key] = (before, sample)
            self.version += 1

    def detected(self, anomalies: dict | None, error: str = "") -> None:
        """The detector's last answer (None and why, when it gave none)."""
        with self._lock:
            if anomalies != self.anomalies or error != self.detector_error:
                self.anomalies, self.detector_error = anomalies, error
                self.version += 1

    def frame(self) -> Frame:
        with self._lock:
            return Frame(time.time(), self.interval, [replace(a) for a in self.agents], dict(self.samples),
                         self.anomalies, self.detector_error)

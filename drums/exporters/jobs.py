"""Monitoring jobs, the paper's runtime API: a client asks the agent to follow one process, the
host, or the sockets on a port; the agent samples each job at its interval and keeps the latest
sample for GET.

A sample is the job's rows of one agent snapshot, taken before the cardinality budget folds
anything: a job names its entity, so the entity always has its own rows. Each row is
{"name", "labels", "value"}, histograms as {"count", "sum"}: the same names and labels as on
/metrics.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

from drums.errors import UsageError
from drums.metrics import Histogram, Snapshot

log = logging.getLogger("drums")

PROTOCOLS = ("tcp", "udp")
DIRECTIONS = ("src", "dst", "any")  # the socket's local port, its peer's port, either
MIN_INTERVAL, MAX_INTERVAL = 0.1, 3600.0
MAX_JOBS = 1000  # each costs a pass over the snapshot per sample


class NotFound(UsageError):
    """The job, or the entity a job would follow, does not exist (HTTP 404)."""


@dataclass
class Job:
    kind: str  # "pid", "host" or "socket"
    target: str  # "1234", "", "tcp/src/8080"
    interval: float
    created: float = field(default_factory=time.time)
    sample: dict | None = None
    due: float = 0.0  # time.monotonic() of the next sample

    @property
    def id(self) -> str:
        return job_id(self.kind, self.target)

    def view(self, host: str) -> dict:
        # No stream yet: its address stays empty until the agent publishes samples.
        return {"id": self.id, "kind": self.kind, "target": self.target, "interval": self.interval,
                "created": self.created, "stream": {"address": "", "key": f"{host}:{self.kind}:{self.target}"},
                "sample": self.sample}

    def pick(self, raw: Snapshot) -> list[dict]:
        """This job's rows of `raw`."""
        rows = []
        for metric, series in raw.series.items():
            labels = metric.labels
            if self.kind == "host":
                if not metric.name.startswith("drums_host_"):
                    continue
                matches = series
            elif self.kind == "pid":
                if "pid" not in labels:
                    continue
                at = labels.index("pid")
                matches = [(v, x) for v, x in series if v[at] == self.target]
            else:
                if "local" not in labels or "protocol" not in labels:
                    continue
                protocol, direction, port = self.target.split("/")
                p, loc, rem = labels.index("protocol"), labels.index("local"), labels.index("remote")

                def on_port(address: str) -> bool:
                    return address.rsplit(":", 1)[-1] == port
                matches = [(v, x) for v, x in series if v[p] == protocol and (
                    (direction != "dst" and on_port(v[loc])) or (direction != "src" and on_port(v[rem])))]
            for values, value in matches:
                if isinstance(value, Histogram):
                    value = {"count": value.count, "sum": value.sum}
                rows.append({"name": metric.name, "labels": dict(zip(labels, values)), "value": value})
        return rows


def parse_interval(body: dict | None) -> float:
    """The request body: {} or {"interval": seconds}; anything else is a UsageError saying why."""
    body = {} if body is None else body
    if not isinstance(body, dict):
        raise UsageError(f"the body is a JSON object, not {type(body).__name__}")
    unknown = sorted(set(body) - {"interval"})
    if unknown:
        raise UsageError(f"unknown field {unknown[0]!r}: a job takes only 'interval'")
    interval = body.get("interval", 1.0)
    if isinstance(interval, bool) or not isinstance(interval, (int, float)) or interval != interval:
        raise UsageError(f"interval: a number of seconds, not {interval!r}")
    if not MIN_INTERVAL <= interval <= MAX_INTERVAL:
        raise UsageError(f"interval: {interval:g} s is outside {MIN_INTERVAL:g}-{MAX_INTERVAL:g} s")
    return float(interval)


def job_id(kind: str, target: str) -> str:
    """How a job is named in the API and in listings: "pid/1234", "host", "socket/tcp/src/80"."""
    return f"{kind}/{target}" if target else kind


def whole(text: str) -> int | None:
    """The number an ASCII string of digits says, else None (str.isdigit also takes "²")."""
    return int(text) if text.isascii() and text.isdigit() else None


def job_target(kind: str, parts: list[str]) -> str:
    """The target of a job from the rest of its path; a UsageError says what is wrong with it."""
    if kind == "host":
        if parts:
            raise NotFound("no such path: a host job is /drums/v1/monitor/host")
        return ""
    if kind == "pid":
        pid = whole(parts[0]) if len(parts) == 1 else None
        if pid is None or not 0 < pid < 1 << 22:
            raise UsageError(f"pid {'/'.join(parts)!r}: a process ID is a whole number from 1 to 4194303")
        return str(pid)
    if len(parts) != 3:
        raise UsageError("a socket job is /drums/v1/monitor/socket/<tcp|udp>/<src|dst|any>/<port>")
    protocol, direction, port = parts
    if protocol not in PROTOCOLS:
        raise UsageError(f"protocol {protocol!r}: one of {', '.join(PROTOCOLS)}")
    if direction not in DIRECTIONS:
        raise UsageError(f"direction {direction!r}: one of {', '.join(DIRECTIONS)}")
    number = whole(port)
    if number is None or not 0 < number < 65536:
        raise UsageError(f"port {port!r}: a whole number from 1 to 65535")
    return f"{protocol}/{direction}/{number}"


class Jobs:
    """The agent's jobs, and the thread that samples them. `collect` returns the agent's raw
    snapshot (before the budget)."""

    def __init__(self, collect: Callable[[], Snapshot], host: str):
        self.collect = collect
        self.host = host
        self._jobs: dict[str, Job] = {}  # by id, oldest first
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="jobs", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5)

    def add(self, kind: str, target: str, interval: float) -> tuple[dict, bool]:
        """(the job, whether it is new). Asking again for a job that exists changes its interval."""
        if kind == "pid" and not os.path.exists(f"/proc/{target}"):
            raise NotFound(f"no process {target}")
        with self._lock:
            job = self._jobs.get(job_id(kind, target))
            created = job is None
            if created:
                if len(self._jobs) >= MAX_JOBS:
                    raise UsageError(f"already {MAX_JOBS} jobs: delete some first")
                job = self._jobs[job_id(kind, target)] = Job(kind, target, interval)
            else:
                job.interval, job.due = interval, 0.0
        self._wake.set()
        return job.view(self.host), created

    def get(self, job_id: str) -> dict:
        with self._lock:
            job = self._jobs.get(job_id)
            if job is None:
                raise NotFound(f"no job {job_id}")
            return job.view(self.host)

    def remove(self, job_id: str) -> None:
        with self._lock:
            if self._jobs.pop(job_id, None) is None:
                raise NotFound(f"no job {job_id}")

    def list(self) -> list[dict]:
        with self._lock:
            return [j.view(self.host) for j in self._jobs.values()]

    def pids(self) -> set[int]:
        with self._lock:
            return {int(j.target) for j in self._jobs.values() if j.kind == "pid"}

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                now = time.monotonic()
                due = [j for j in self._jobs.values() if j.due <= now]
                wait = min((j.due - now for j in self._jobs.values() if j.due > now), default=None)
                for job in due:
                    job.due = now + job.interval
            if due:
                try:
                    self._sample(due)
                except Exception as e:  # a failed collect must not end the sampling
                    log.warning("sampling jobs failed: %s", e)
                continue
            self._wake.wait(wait)
            self._wake.clear()

    def _sample(self, due: list[Job]) -> None:
        raw = self.collect()
        at = time.time()
        for job in due:
            sample = {"time": at, "series": job.pick(raw)}
            with self._lock:
                job.sample = sample

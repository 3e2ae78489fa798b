"""Monitoring jobs, the paper's runtime API: a client asks the agent to follow one process, the
host, the sockets on a port, the round-trip time to another host, or a topic of the graph; the
agent samples each job at its interval, keeps the latest sample for GET and publishes each on the
stream.

A job with a lease ends by itself when its client stops asking for it: each POST to the job
renews it, and a lease that runs out without one deletes the job, so a client that dies leaves no
job sampling forever. A process job ends when its process does (a PID is the process that had it
when the job began: its start time tells a later process that got the PID).

A sample is the job's rows of one agent snapshot, taken before the cardinality budget folds
anything: a job names its entity, so the entity always has its own rows. Each row is
{"name", "labels", "value"}, histograms as {"count", "sum", "buckets": [[upper bound, cumulative
count], ...]}: the same names, labels and buckets as on /metrics, so that a client computes any
quantile between two samples as Prometheus does. A topic job's rows are the graph's: the topic's
publishers (messages, bytes, period, deadlines), its edges (bytes, delivery transport and age)
and the reactions of nodes from or to it.
"""
from __future__ import annotations

import logging
import re
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

from drums.errors import UsageError
from drums.graph.join import METRICS as GRAPH_METRICS
from drums.graph.join import NODE_REACTION
from drums.metrics import Histogram, Snapshot
from drums.probes.latency import METHODS, LatencyProbe
from drums.proctable import process_start

log = logging.getLogger("drums")

PROTOCOLS = ("tcp", "udp")
DIRECTIONS = ("src", "dst", "any")  # the socket's local port, its peer's port, either
MIN_INTERVAL, MAX_INTERVAL = 0.1, 3600.0
MIN_LEASE, MAX_LEASE = 1.0, 3600.0
NEVER = float("inf")
PROC = "/proc"  # when a job without a lease expires
MAX_JOBS = 1000  # each costs a pass over the snapshot per sample
# The probes whose rows each kind of job picks: a sample reads those and no others.
PROBES_OF = {"host": {"host"}, "latency": {"latency"}, "socket": {"sockets", "tcp"},
             "pid": {"sockets", "sched", "tcp", "process", "rtps", "rcl"},
             "topic": {"rcl", "rtps", "sockets", "tcp"}}  # read, then joined onto the graph
MESH_PERIOD = 2.0  # how often the latency mesh follows the graph's hosts
MESH_INTERVAL = 1.0
KINDS = ("pid", "host", "socket", "latency", "topic")
TOPIC_NAME = re.compile(r"[A-Za-z0-9_]+")  # each token of a ROS topic name
# What a job's body may set, beyond its interval: name -> (default, check, what the check wants).
LATENCY_SETTINGS = {
    "count": (3, lambda v: isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 100,
              "a whole number of probes per round, 1-100"),
    "method": ("auto", lambda v: v in METHODS, f"one of {', '.join(METHODS)}"),
    "port": (9969, lambda v: isinstance(v, int) and not isinstance(v, bool) and 0 < v < 65536,
             "the TCP port to connect to, 1-65535"),
}


class NotFound(UsageError):
    """The job, or the entity a job would follow, does not exist (HTTP 404)."""


class Forbidden(UsageError):
    """The request is well formed but not allowed here (HTTP 403)."""


@dataclass
class Job:
    kind: str  # one of KINDS
    target: str  # "1234", "", "tcp/src/8080", "10.0.0.2", "/camera/image"
    interval: float
    settings: dict = field(default_factory=dict)  # a latency job's count, method and port
    created: float = field(default_factory=time.time)
    sample: dict | None = None
    due: float = 0.0  # time.monotonic() of the next sample
    mesh: bool = False  # started by the agent for a host of the graph, not by a client
    lease: float | None = None  # seconds the job lives after each POST; None: until deleted
    expires: float = NEVER  # time.monotonic() when the lease runs out
    started: int | None = None  # a process job's process start time (clock ticks after boot)

    @property
    def id(self) -> str:
        return job_id(self.kind, self.target)

    def view(self, host: str) -> dict:
        # The stream's address depends on where the client reached the agent: the HTTP server adds it.
        lease = {} if self.lease is None else {
            "lease": self.lease, "expires_in": round(max(0.0, self.expires - time.monotonic()), 3)}
        return {"id": self.id, "kind": self.kind, "target": self.target, "interval": self.interval,
                **self.settings, **lease, "created": self.created, "mesh": self.mesh,
                "stream": {"key": self.key(host)}, "sample": self.sample}

    def key(self, host: str) -> str:
        """The job's key on the stream."""
        return f"{host}:{self.kind}:{self.target}"

    def pick(self, raw: Snapshot) -> list[dict]:
        """This job's rows of `raw`."""
        rows = []
        for metric, series in raw.series.items():
            labels = metric.labels
            if self.kind == "host":
                if not metric.name.startswith("drums_host_"):
                    continue
                matches = series
            elif self.kind == "latency":
                if not metric.name.startswith("drums_latency_"):
                    continue
                matches = [(v, x) for v, x in series if v[0] == self.target]
            elif self.kind == "topic":
                if metric is NODE_REACTION:
                    at = (labels.index("input"), labels.index("output"))
                elif metric in GRAPH_METRICS and "topic" in labels:
                    at = (labels.index("topic"),)
                else:
                    continue
                matches = [(v, x) for v, x in series if any(v[i] == self.target for i in at)]
            elif self.kind == "pid":
                if "pid" not in labels or metric in GRAPH_METRICS:  # drums_node_info: not asked for
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
                    bounds = value.bounds or metric.buckets
                    value = {"count": value.count, "sum": value.sum,
                             "buckets": [[b, c] for b, c in zip(bounds, value.cumulative)]}
                rows.append({"name": metric.name, "labels": dict(zip(labels, values)), "value": value})
        return rows


def _seconds(body: dict, name: str, default: float | None, low: float, high: float) -> float | None:
    value = body.get(name, default)
    if value is None and name not in body:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != value:
        raise UsageError(f"{name}: a number of seconds, not {value!r}")
    if not low <= value <= high:
        raise UsageError(f"{name}: {value:g} s is outside {low:g}-{high:g} s")
    return float(value)


def parse_body(kind: str, body: object) -> tuple[float, dict, float | None]:
    """(interval, settings, lease) from a request body: {"interval": seconds, "lease": seconds}
    and, for a latency job, its settings; anything else is a UsageError saying why."""
    if not isinstance(body, dict):
        raise UsageError(f"the body is a JSON object, not {'null' if body is None else type(body).__name__}")
    allowed = {"interval", "lease", *(LATENCY_SETTINGS if kind == "latency" else ())}
    unknown = sorted(set(body) - allowed)
    if unknown:
        raise UsageError(f"unknown field {unknown[0]!r}: a {kind} job takes {', '.join(sorted(allowed))}")
    interval = _seconds(body, "interval", 1.0, MIN_INTERVAL, MAX_INTERVAL)
    lease = _seconds(body, "lease", None, MIN_LEASE, MAX_LEASE)
    settings = {}
    if kind == "latency":
        for name, (default, ok, wanted) in LATENCY_SETTINGS.items():
            settings[name] = body.get(name, default)
            if not ok(settings[name]):
                raise UsageError(f"{name}: {wanted}, not {settings[name]!r}")
    return interval, settings, lease


def job_id(kind: str, target: str) -> str:
    """How a job is named in the API and in listings, as its path: "pid/1234", "host",
    "socket/tcp/src/80", "topic/camera/image"."""
    return f"{kind}/{target.removeprefix('/')}" if target else kind


def whole(text: str) -> int | None:
    """The number an ASCII string of digits says, else None (str.isdigit also takes "²")."""
    return int(text) if text.isascii() and text.isdigit() else None


def job_target(kind: str, parts: list[str]) -> str:
    """The target of a job from the rest of its path; a UsageError says what is wrong with it."""
    if kind == "host":
        if parts:
            raise NotFound("no such path: a host job is /drums/v1/monitor/host")
        return ""
    if kind == "latency":
        if len(parts) != 1:
            raise UsageError("a latency job is /drums/v1/monitor/latency/<host name or address>")
        return parts[0]
    if kind == "topic":
        if not parts or not all(TOPIC_NAME.fullmatch(p) for p in parts):
            raise UsageError(f"topic {'/'.join(parts)!r}: a ROS topic name of letters, digits and _ between slashes, "
                             "as in /drums/v1/monitor/topic/camera/image")
        return "/" + "/".join(parts)
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
    """The agent's jobs, and the thread that samples them. `collect(probes, joined)` reads the named
    probes' rows (before the budget), and with `joined` the graph's rows of them; `stream`, if
    given, gets every sample. Latency jobs run rounds on `latency` to the targets `latency_targets()`
    allows; with `mesh`, the agent keeps a latency job of its own on each host `mesh()` returns
    (host -> its agent's port, where the job asks its time).
    Topic jobs follow the topics of the graph, which `topics()` names."""

    def __init__(self, collect: Callable[[set[str], bool], Snapshot], host: str, stream=None,
                 latency: LatencyProbe | None = None, latency_targets: Callable[[], set[str]] = set,
                 mesh: Callable[[], dict[str, int]] | None = None, topics: Callable[[], set[str]] = set):
        self.collect = collect
        self.topics = topics
        self.host = host
        self.stream = stream
        self.latency = latency
        self.latency_targets = latency_targets
        self.mesh = mesh
        self._jobs: dict[str, Job] = {}  # by id, oldest first
        self._gone: list[str] = []  # stream keys of deleted jobs, for the jobs thread to forget
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

    def add(self, kind: str, target: str, interval: float, settings: dict | None = None,
            lease: float | None = None, mesh: bool = False) -> tuple[dict, bool]:
        """(the job, whether it is new). Asking again for a job that exists changes its settings
        and renews its lease."""
        settings = settings or {}
        started = process_start(PROC, target) if kind == "pid" else None
        if kind == "pid" and started is None:
            raise NotFound(f"no process {target}")
        if kind == "topic" and target not in self.topics():
            raise NotFound(f"no topic {target} in the graph")
        if kind == "latency":
            if self.latency is None:
                raise Forbidden("this agent runs without the latency probe")
            if target not in self.latency_targets():
                raise Forbidden(f"latency to {target!r}: only to hosts of the graph or named by --latency-target")
        with self._lock:
            job = self._jobs.get(job_id(kind, target))
            created = job is None
            if created:
                if len(self._jobs) >= MAX_JOBS:
                    raise UsageError(f"already {MAX_JOBS} jobs: delete some first")
                job = self._jobs[job_id(kind, target)] = Job(kind, target, interval, settings, mesh=mesh,
                                                             started=started)
            else:
                # New settings sample at once; a renewal of the same ones keeps its grid (an extra
                # sample milliseconds after the last would make every rate of it look like zero).
                if (interval, settings) != (job.interval, job.settings):
                    job.due = 0.0
                job.interval, job.settings, job.mesh = interval, settings, job.mesh and mesh
            job.lease = lease
            job.expires = NEVER if lease is None else time.monotonic() + lease
            view = job.view(self.host)
        if kind == "latency":
            self.latency.watch(target, interval, **settings)
        self._wake.set()
        return view, created

    def get(self, job_id: str) -> dict:
        with self._lock:
            job = self._jobs.get(job_id)
            if job is None:
                raise NotFound(f"no job {job_id}")
            return job.view(self.host)

    def remove(self, job_id: str) -> None:
        with self._lock:
            job = self._jobs.pop(job_id, None)
            if job is None:
                raise NotFound(f"no job {job_id}")
            self._gone.append(job.key(self.host))
        if job.kind == "latency":
            self.latency.unwatch(job.target)

    def _end_stale(self) -> float | None:
        """Delete the jobs whose lease ran out or whose process ended; seconds until the next lease
        runs out."""
        now = time.monotonic()
        with self._lock:
            ended = [(j.id, "its lease ran out") for j in self._jobs.values() if j.expires <= now]
            ended += [(j.id, "its process ended") for j in self._jobs.values()
                      if j.kind == "pid" and j.expires > now and process_start(PROC, j.target) != j.started]
            nearest = min((j.expires - now for j in self._jobs.values() if now < j.expires < NEVER), default=None)
        for job, why in ended:
            try:
                self.remove(job)
                log.info("job %s ended: %s", job, why)
            except NotFound:
                pass  # its client deleted it meanwhile
        return nearest

    def list(self) -> list[dict]:
        with self._lock:
            return [j.view(self.host) for j in self._jobs.values()]

    def pids(self) -> set[int]:
        with self._lock:
            return {int(j.target) for j in self._jobs.values() if j.kind == "pid"}

    def _run(self) -> None:
        next_mesh = 0.0
        while not self._stop.is_set():
            if self.mesh is not None and time.monotonic() >= next_mesh:
                self._follow_mesh()
                next_mesh = time.monotonic() + MESH_PERIOD
            lease_ends = self._end_stale()
            with self._lock:
                gone, self._gone = self._gone, []
                now = time.monotonic()
                due = [j for j in self._jobs.values() if j.due <= now]
                wait = min((j.due - now for j in self._jobs.values() if j.due > now), default=None)
                for job in due:  # on the interval's grid: jobs with one interval share their collects
                    job.due = (now // job.interval + 1) * job.interval
                if self.mesh is not None:
                    wait = min(wait or MESH_PERIOD, max(0.0, next_mesh - now))
                if lease_ends is not None:
                    wait = lease_ends if wait is None else min(wait, lease_ends)
            for key in gone if self.stream is not None else ():
                self.stream.forget(key)
            if due:
                try:
                    self._sample(due)
                except Exception as e:  # a failed collect must not end the sampling
                    log.warning("sampling jobs failed: %s", e)
                continue
            self._wake.wait(wait)
            self._wake.clear()

    def _sample(self, due: list[Job]) -> None:
        raw = self.collect(set().union(*(PROBES_OF[j.kind] for j in due)), any(j.kind == "topic" for j in due))
        if not any(j.kind in ("socket", "topic") for j in due):  # the others name a process, or none
            raw.narrow({int(j.target) for j in due if j.kind == "pid"})
        at = time.time()
        for job in due:
            sample = {"time": at, "series": job.pick(raw)}
            with self._lock:
                job.sample = sample
            if self.stream is not None:
                self.stream.publish(job.key(self.host), at, sample["series"])

    def _follow_mesh(self) -> None:
        """A latency job on every host the graph has, none on hosts it no longer has."""
        try:
            targets = self.mesh()
        except Exception as e:  # the graph is read while it changes: try again next period
            log.warning("latency mesh: %s", e)
            return
        with self._lock:
            have = {j.target for j in self._jobs.values() if j.kind == "latency"}
            stale = [j.id for j in self._jobs.values() if j.mesh and j.target not in targets]
        for target in sorted(targets.keys() - have):
            try:
                self.add("latency", target, MESH_INTERVAL, parse_body("latency", {"port": targets[target]})[1],
                         mesh=True)
            except UsageError as e:
                log.warning("latency mesh: %s", e)
        for job in stale:
            try:
                self.remove(job)
            except NotFound:
                pass  # a client deleted it meanwhile

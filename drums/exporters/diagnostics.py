"""ROS 2 /diagnostics: every interval, the agent's latest snapshot as one
diagnostic_msgs/DiagnosticArray, with a status per ROS node that has a process on this host
("drums: /talker") and one for the host ("drums: host <name>"), hardware_id the host's name.

Each status is OK, WARN or ERROR by thresholds: a value above `warn` or `error` crosses it, and
the message names each crossing ("cpu 97% > 95%"), else says "ok". A node whose subscription's
QoS cannot connect to a publisher is an ERROR ("QoS reliability incompatible: nothing from /camera on
/image"), the publisher a WARN. Defaults, each replaceable in a YAML file given with
--diagnostics-config (null: not checked):

    interval: 1                                   # seconds between arrays (0.1-3600)
    node:                                         # of the node's process, shared by its nodes
      cpu_percent: {warn: 80, error: 95}          # of one core
      memory_megabytes: {warn: null, error: null} # resident
    host:
      cpu_percent: {warn: 85, error: 95}          # of all cores
      memory_percent: {warn: 85, error: 95}       # not available without swapping
      network_errors_per_second: {warn: 1, error: 10}
      network_drops_per_second: {warn: 10, error: 100}
      tcp_retransmits_per_second: {warn: 10, error: 100}

Rates (CPU, bytes and messages per second) are the difference between this snapshot and the
previous one, so the first array goes out one interval after the start.

rclpy runs in a child process (drums.rclchild) for the reasons the ros2 graph reader
does: the agent stays lean, and a DDS stack that hangs or crashes costs the diagnostics, never the
agent's kernel data. With the ros2 graph that child is the graph reader (one rclpy process and one
DDS participant, not two of 40 MB each); else one of its own. A child that exits or stops
answering is logged once and started again.
"""
from __future__ import annotations

import importlib.util
import json
import logging
import math
import os
import select
import socket
import subprocess
import sys
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Callable

import psutil

from drums import safeyaml
from drums.errors import UsageError
from drums.graph import join
from drums.metrics import Snapshot
from drums.probes import host as hostprobe
from drums.probes import sockets, tcp
from drums.rclchild import INSTALL_HINT

log = logging.getLogger("drums")

OK, WARN, ERROR = 0, 1, 2  # DiagnosticStatus levels
# (section, key) -> (what a message calls the value, its unit, default warn, default error)
THRESHOLDS = {
    ("node", "cpu_percent"): ("cpu", "%", 80.0, 95.0),
    ("node", "memory_megabytes"): ("memory", " MB", None, None),
    ("host", "cpu_percent"): ("cpu", "%", 85.0, 95.0),
    ("host", "memory_percent"): ("memory", "%", 85.0, 95.0),
    ("host", "network_errors_per_second"): ("network errors", "/s", 1.0, 10.0),
    # Some drivers count frames of protocols nobody listens to as drops: a few per second is normal.
    ("host", "network_drops_per_second"): ("network drops", "/s", 10.0, 100.0),
    ("host", "tcp_retransmits_per_second"): ("tcp retransmits", "/s", 10.0, 100.0),
}
MIN_INTERVAL, MAX_INTERVAL = 0.1, 3600.0
# How old (in intervals) a scrape's snapshot may be for an array to be drawn from it. Scraped as
# often as the arrays go out, each array finds a scrape's snapshot read since the last one, at any
# phase between the two. At most 0.9 interval, a phase past it made the agent collect twice each
# interval: measured at 1,000 processes and 1 s scrapes, 31 collects of its own in 30 s, about 1%
# of a core, in the benchmark's runs where the phase fell so.
MAX_AGE = 1.5


@dataclass
class Config:
    interval: float = 1.0
    limits: dict = field(default_factory=lambda: {k: (w, e) for k, (_, _, w, e) in THRESHOLDS.items()})


def _mapping(doc, allowed: list[str], where: str) -> dict:
    if not isinstance(doc, dict):
        raise UsageError(f"{where}: a mapping of {', '.join(allowed)}, not {type(doc).__name__}")
    unknown = sorted(str(k) for k in doc if k not in allowed)
    if unknown:
        raise UsageError(f"{where}: unknown key {unknown[0]!r} (known: {', '.join(allowed)})")
    return doc


def _number(value, where: str, low: float, high: float = math.inf) -> float:
    try:  # a YAML integer has any number of digits: one too big for a float is no threshold
        number = math.nan if isinstance(value, bool) or not isinstance(value, (int, float)) else float(value)
    except OverflowError:
        number = math.nan
    if not low <= number <= high:
        span = f"from {low:g} to {high:g}" if high < math.inf else f"from {low:g} up"
        shown = repr(value) if len(repr(value)) <= 24 else repr(value)[:20] + "..."
        raise UsageError(f"{where}: a number {span}, not {shown}")
    return number


def load_config(path: str) -> Config:
    """The defaults, with what the YAML file at `path` (if any) replaces; every mistake is a
    UsageError naming the file and the key."""
    import yaml

    config = Config()
    if not path:
        return config
    where = f"--diagnostics-config {path}"
    try:
        doc = safeyaml.load(safeyaml.read(path))
    except OSError as e:
        raise UsageError(f"{where}: {e.strerror}") from None
    except yaml.YAMLError as e:
        raise UsageError(f"{where}: not YAML ({str(e).splitlines()[0]})") from None
    doc = _mapping({} if doc is None else doc, ["interval", "node", "host"], where)
    if "interval" in doc:
        config.interval = _number(doc["interval"], f"{where}: interval", MIN_INTERVAL, MAX_INTERVAL)
    for section in ("node", "host"):
        keys = [k for s, k in THRESHOLDS if s == section]
        given = _mapping({} if doc.get(section) is None else doc[section], keys, f"{where}: {section}")
        for key, levels in given.items():
            at = f"{where}: {section}.{key}"
            limits = dict(zip(("warn", "error"), config.limits[section, key]))
            for level, value in _mapping(levels, ["warn", "error"], at).items():
                limits[level] = None if value is None else _number(value, f"{at}.{level}", 0)
            warn, error = limits["warn"], limits["error"]
            if warn is not None and error is not None and warn > error:
                raise UsageError(f"{at}: warn {warn:g} is above error {error:g}")
            config.limits[section, key] = (warn, error)
    return config


def _cpu_seconds(pid: str) -> float | None:
    """The process's CPU time since it started, as `top` shows it: the sched probe's count
    (drums_node_cpu_seconds_total) starts when the probe loaded, and needs the probe."""
    try:
        times = psutil.Process(int(pid)).cpu_times()
    except (psutil.Error, ValueError):
        return None
    return times.user + times.system


def _short(value: float) -> str:
    return f"{value:.0f}" if abs(value) >= 10 else f"{value:.2g}"


def _text(value) -> str:
    return f"{value:.3f}" if isinstance(value, float) else str(value)


class Diagnostics:
    """Turns snapshots into statuses, and every interval publishes them through the child."""

    def __init__(self, config: Config):
        missing = [m for m in ("rclpy", "diagnostic_msgs") if importlib.util.find_spec(m) is None]
        if missing:
            raise UsageError(f"--diagnostics needs {' and '.join(missing)}: {INSTALL_HINT}")
        self.config = config
        self.host = socket.gethostname()
        self.publisher = Publisher()
        self._previous: dict = {}  # counter key -> value at the last snapshot, for rates
        self._previous_at = 0.0  # time.monotonic() of the last statuses, for the CPU seconds read then
        self._previous_read_at = 0.0  # when the last snapshot's probes were read, for its counters
        self._failure = ""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, recent: Callable[[float, float], Snapshot]) -> None:
        """`recent(max_age, after)`: a snapshot whose probes were read at most max_age seconds ago
        and later than `after`."""
        self._thread = threading.Thread(target=self._run, args=(recent,), name="diagnostics", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2 * self.publisher.timeout)
        self.publisher.stop()

    def _run(self, recent: Callable[[float, float], Snapshot]) -> None:
        # A scrape's snapshot serves if its probes were read since the last array's and at most
        # MAX_AGE intervals ago: no collect of our own then, which costs as much as a scrape's.
        # Never the one the last array was drawn from (that one is young too when its collect took
        # a tenth of the interval): its rates would be over no time at all.
        max_age = MAX_AGE * self.config.interval
        while True:
            began = time.monotonic()
            try:
                first = not self._previous_at
                statuses = self.statuses(recent(max_age, self._previous_read_at), time.monotonic())
                if not first:
                    self.publisher.send(statuses)
                self._failure = ""
            except Exception as e:  # one bad snapshot costs one array, not the thread
                if str(e) != self._failure:
                    log.warning("diagnostics: %s", e)
                self._failure = str(e)
            if self._stop.wait(max(0.0, self.config.interval - (time.monotonic() - began))):
                return

    def statuses(self, snap: Snapshot, at: float) -> list[dict]:
        """A status per node with a process here, then the host's; rates since the last call: of
        the CPU seconds read now, over the time since (`at`, monotonic), and of the snapshot's
        counters over the time between the reads of the two snapshots."""
        counters: dict = {}
        since_now, since_read = at - self._previous_at, (snap.read_at or 0.0) - self._previous_read_at

        def rate(key, value, elapsed: float = since_read) -> float | None:
            counters[key] = value
            before = self._previous.get(key)
            if before is None or value < before or elapsed <= 0:
                return None  # new, or restarted under the same key
            return (value - before) / elapsed

        memory = snap.values(join.NODE_MEMORY)
        traffic = {name: defaultdict(int) for name in ("sent", "received")}
        for name, table in traffic.items():
            for (pid, _, _), value in snap.series.get(sockets.PROCESS[f"{name}_bytes"], ()):
                table[pid] += value
        topics = defaultdict(list)
        for kind, metric in (("published", join.TOPIC_PUBLISHED), ("taken", join.TOPIC_TAKEN)):
            for (topic, node), value in snap.series.get(metric, ()):
                topics[node].append((f"{kind} messages/s {topic}", value))
        # An edge whose QoS cannot connect: its subscriber gets nothing (an error), its publisher
        # misses a reader (a warning).
        problems = defaultdict(list)
        for (topic, publisher, subscriber, policy), value in snap.series.get(join.EDGE_QOS_INCOMPATIBLE, ()):
            if value:
                problems[subscriber].append((ERROR, f"QoS {policy} incompatible: nothing from {publisher} on {topic}"))
                problems[publisher].append((WARN, f"QoS {policy} incompatible: {subscriber} on {topic} cannot connect"))
        out = []
        for (node, pid, process, _, shares), _ in sorted(snap.series.get(join.NODE_INFO, ())):
            if not pid:
                continue  # on another host, or not found here: nothing measured
            values, checks = {"pid": pid, "process": process}, {}
            if shares:
                values["shares process with"] = shares
            seconds = _cpu_seconds(pid)
            if seconds is not None:
                per_second = rate((pid, "cpu"), seconds, since_now)
                if per_second is not None:
                    values["cpu %"] = checks["cpu_percent"] = 100 * per_second
                values["cpu seconds"] = seconds
            if (node,) in memory:
                values["resident memory bytes"] = memory[node,]
                checks["memory_megabytes"] = memory[node,] / 1e6
            for name, table in traffic.items():
                per_second = rate((pid, name), table[pid]) if pid in table else None
                if per_second is not None:
                    values[f"{name} bytes/s"] = per_second
            for key, value in topics.get(node, ()):
                per_second = rate((pid, node, key), value)
                if per_second is not None:
                    values[key] = per_second
            out.append(self._status(f"drums: {node}", "node", values, checks, problems.get(node, ())))
        out.append(self._status(f"drums: host {self.host}", "host", *self._host(snap, rate)))
        self._previous, self._previous_at, self._previous_read_at = counters, at, snap.read_at or 0.0
        return out

    def _host(self, snap: Snapshot, rate) -> tuple[dict, dict]:
        values, checks = {}, {}
        modes = {labels[0]: v for labels, v in snap.series.get(hostprobe.CPU_SECONDS, ())}
        if modes:
            total = rate("cpu", sum(modes.values()))
            idle = rate("idle", modes.get("idle", 0) + modes.get("iowait", 0))
            if total and idle is not None:
                values["cpu %"] = checks["cpu_percent"] = 100 * (total - idle) / total
        mem = {m: v for m in (hostprobe.MEMORY_TOTAL, hostprobe.MEMORY_AVAILABLE)
               for _, v in snap.series.get(m, ())}
        if mem.get(hostprobe.MEMORY_TOTAL):
            total = mem[hostprobe.MEMORY_TOTAL]
            values["memory used %"] = checks["memory_percent"] = \
                100 * (total - mem.get(hostprobe.MEMORY_AVAILABLE, 0)) / total
            values["memory total bytes"] = total
        load = snap.values(hostprobe.LOAD).get(("1m",))
        if load is not None:
            values["load 1m"] = load
        for name, key, metrics in (
                ("network received bytes/s", None, (hostprobe.NET_RECEIVED_BYTES,)),
                ("network sent bytes/s", None, (hostprobe.NET_SENT_BYTES,)),
                ("network errors/s", "network_errors_per_second",
                 (hostprobe.NET_RECEIVE_ERRORS, hostprobe.NET_TRANSMIT_ERRORS)),
                ("network drops/s", "network_drops_per_second",
                 (hostprobe.NET_RECEIVE_DROPS, hostprobe.NET_TRANSMIT_DROPS)),
                ("tcp retransmits/s", "tcp_retransmits_per_second", (tcp.RETRANSMITS,))):
            rows = [v for m in metrics for _, v in snap.series.get(m, ())]
            per_second = rate(name, sum(rows)) if rows else None
            if per_second is not None:
                values[name] = per_second
                if key:
                    checks[key] = per_second
        return values, checks

    def _status(self, name: str, section: str, values: dict, checks: dict, problems=()) -> dict:
        """`problems`: (level, text) of what is wrong besides the thresholds' checks."""
        level, crossed = max((p for p, _ in problems), default=OK), [text for _, text in problems]
        for key, value in checks.items():
            what, unit, _, _ = THRESHOLDS[section, key]
            warn, error = self.config.limits[section, key]
            for limit_level, limit in ((ERROR, error), (WARN, warn)):
                if limit is not None and value > limit:
                    level = max(level, limit_level)
                    crossed.append(f"{what} {_short(value)}{unit} > {limit:g}{unit}")
                    break
        return {"level": level, "name": name, "message": ", ".join(crossed) or "ok", "hardware_id": self.host,
                "values": [[k, _text(v)] for k, v in values.items()]}


class Publisher:
    """The child that publishes DiagnosticArrays on `topic` (drums detect's anomalies go out this way
    too): one JSON array per line on its stdin, one answer per array on its stdout
    (drums.rclchild). A child that exits, or answers nothing for `timeout` s, is replaced,
    at most once every `timeout` s; each new reason it is not publishing is logged once.

    The child is the ROS 2 graph reader once `ride()` put the arrays on it (the agent with the ros2
    graph: one rclpy process for both), else one of its own."""

    def __init__(self, timeout: float = 5.0, topic: str = "/diagnostics"):
        self.timeout, self.topic = timeout, topic
        self._host = None  # the graph reader's adapter, once ride() was called
        self._proc: subprocess.Popen | None = None
        self._reader: threading.Thread | None = None
        self._lock = threading.Lock()
        self._spawned_at = -math.inf
        self._sent = self._answered = 0
        self._heard_at = 0.0
        self._error = ""  # the child's last answer, if it was a failure
        self._said = ""  # the child's last line that was not an answer
        self._killed = ""  # why we killed the child, if we did
        self._reason = ""  # what was logged last; "" while publishing

    def ride(self, host) -> None:
        """Publish through the ROS 2 graph reader (a drums.graph.ros2.Ros2Adapter not started yet)."""
        self._host = host
        host.carry(self.topic, self._answered_by)

    def _spawn(self) -> None:
        with self._lock:
            self._sent = self._answered = 0
            self._error = self._said = self._killed = ""
            self._heard_at = self._spawned_at = time.monotonic()
        if self._host is not None:  # the reader as it is now, or a new one if ours is still it
            self._proc = self._host.respawn(self._proc)
        else:
            self._proc = subprocess.Popen([sys.executable, "-m", "drums.rclchild", self.topic],
                                          stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
            self._reader = threading.Thread(target=self._read, args=(self._proc,), daemon=True,
                                            name="diagnostics-reader")
            self._reader.start()
        os.set_blocking(self._proc.stdin.fileno(), False)  # a child that stops reading must not stop us

    def _read(self, proc: subprocess.Popen) -> None:
        for line in proc.stdout:
            try:
                error = str(json.loads(line)["answer"])
            except (ValueError, TypeError, KeyError):  # not an answer: rmw and DDS print here too
                with self._lock:
                    if proc is self._proc:
                        self._said = line.decode(errors="replace").strip()[:500]
                continue
            self._answered_by(proc, error)

    def _answered_by(self, proc: subprocess.Popen, error: str) -> None:
        with self._lock:
            if proc is self._proc:
                self._answered += 1
                self._heard_at = time.monotonic()
                self._error = error[:500]

    def _write(self, data: bytes) -> bool:
        """All of `data` to the child within the timeout, or False."""
        fd, deadline = self._proc.stdin.fileno(), time.monotonic() + self.timeout
        try:
            while data:
                if not select.select([], [fd], [], max(0.0, deadline - time.monotonic()))[1]:
                    return False
                data = data[os.write(fd, data):]
        except (BlockingIOError, BrokenPipeError):
            return False
        return True

    def _kill(self, reason: str) -> None:
        self._killed = reason
        self._proc.kill()
        self._proc.wait()

    def _problem(self) -> str:
        """Why arrays are not published, "" if they are. A new child changes nothing until it answers."""
        if self._proc is None:
            return ""
        with self._lock:
            error, answered, silent = self._error, self._answered, time.monotonic() - self._heard_at
            waiting = self._sent > answered
        if self._proc.poll() is None and waiting and silent > self.timeout:
            self._kill(f"the publisher answered nothing for {silent:.0f} s")
        code = self._proc.poll()
        if code is not None:
            if self._reader is not None:
                self._reader.join(1)  # its last words, if any, say why it exited
            with self._lock:
                error = self._error or self._said
            return self._killed or f"the publisher exited with {code}" + (f" ({error})" if error else "")
        return error if answered else self._reason

    def send(self, statuses: list[dict]) -> None:
        problem = self._problem()
        if problem != self._reason:
            if problem:
                log.warning("diagnostics: %s; %s is not published until it works again", problem, self.topic)
            else:
                log.info("diagnostics: publishing again")
            self._reason = problem
        if self._proc is None or self._proc.poll() is not None:
            if time.monotonic() - self._spawned_at < self.timeout:
                return  # a child that keeps failing costs a start every `timeout` s, no more
            self._spawn()
        if not self._write((json.dumps({"status": statuses}) + "\n").encode()):
            self._kill(f"the publisher read nothing for {self.timeout:.0f} s")
            return
        with self._lock:
            self._sent += 1

    def stop(self) -> None:
        if self._host is not None or self._proc is None or self._proc.poll() is not None:
            return  # the graph reader's adapter stops a child we share
        self._proc.stdin.close()  # at the end of its input the child leaves the DDS domain and exits
        try:
            self._proc.wait(self.timeout)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()

"""`drums detect` as a process: read every source each interval, tick the detector, and say what it
found: a line per event on standard output, a JSON object per event in the log, the detector's own
counts on /metrics and its live list on /anomalies, and with --ros the anomalies now as a
diagnostic_msgs/DiagnosticArray on the ROS 2 topic /drums/anomalies, for the robot's own
controller (published from a child process, as the agent's /diagnostics are).
"""
from __future__ import annotations

import json
import logging
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor

from drums.detect.detector import Detector, Event
from drums.detect.graph import KINDS
from drums.detect.sources import SourceError
from drums.errors import UsageError
from drums.metrics import COUNTER, GAUGE, Metric, Snapshot
from drums.selfcost import Heap

log = logging.getLogger("drums")

ROS_TOPIC = "/drums/anomalies"
WARN = 1  # DiagnosticStatus level of an anomaly

CATEGORIES = ("cpu", "memory", "io", "network")
STARTED = Metric("drums_anomalies_total", COUNTER,
                 "Anomalies the detector found since it started, by category and by the kind of entity they "
                 "belong to (an anomaly: a series its checks called anomalous, until it is calm for the hold time)",
                 ("category", "kind"))
ACTIVE = Metric("drums_anomalous_series", GAUGE,
                "Series anomalous now, by category and entity kind: stacked, the paper's anomaly graph",
                ("category", "kind"))
CHANGES = Metric("drums_graph_changes_total", COUNTER,
                 "Changes of the computation graph the detector saw: nodes started, stopped, restarted; "
                 "edges and hosts that appeared or went", ("kind", "change"))
WATCHED = Metric("drums_detect_series_watched", GAUGE, "Series the detector holds a history of")
FLAGGED = Metric("drums_detect_series_flagged_total", COUNTER,
                 "Distinct series called anomalous at least once since the start")
TICK = Metric("drums_detect_tick_duration_seconds", GAUGE, "How long the detector's last tick took (reads not included)")
UP = Metric("drums_detect_source_up", GAUGE, "1 if the source answered the last read, else 0", ("source",))
FAILED = Metric("drums_detect_source_failures_total", COUNTER, "Reads of the source that failed", ("source",))
UNLOGGED = Metric("drums_detect_events_unlogged_total", COUNTER,
                  "Events that could not be written to the --log file (a full disk, say): said once, then counted")
METRICS = (STARTED, ACTIVE, CHANGES, WATCHED, FLAGGED, TICK, UP, FAILED, UNLOGGED)


class Loop:
    def __init__(self, sources: list, detector: Detector, interval: float, log_path: str = "", echo=print,
                 ros: bool = False):
        self.sources, self.detector, self.interval, self.echo = sources, detector, interval, echo
        self.heap = Heap()  # each tick frees a page's worth of strings and arrays
        self.publisher = None
        if ros:
            from drums.exporters.diagnostics import Publisher
            self.publisher = Publisher(topic=ROS_TOPIC)
        self.lock = threading.Lock()  # the detector's state, between the loop and the HTTP threads
        self.up = {s.address: 0 for s in sources}
        self.failures = {s.address: 0 for s in sources}
        self._said: dict[str, str] = {}  # source address -> the last error said about it
        self.unlogged = 0
        self._pool = ThreadPoolExecutor(max(1, len(sources)), thread_name_prefix="read")
        try:
            self._log = open(log_path, "a", encoding="utf-8", buffering=1) if log_path else None
        except OSError as e:
            raise UsageError(f"--log {log_path}: {e.strerror}") from None

    def once(self, now: float | None = None) -> list[Event]:
        """Read every source, tick, and say the events."""
        answers = []
        for source, future in [(s, self._pool.submit(s.read)) for s in self.sources]:
            try:
                got = future.result()
            except SourceError as e:
                self.up[source.address] = 0
                self.failures[source.address] += 1
                if self._said.get(source.address) != str(e):  # said once, not every tick
                    self._said[source.address] = str(e)
                    log.warning("detect: %s", e)
                continue
            self.up[source.address] = 1
            if self._said.pop(source.address, None):
                log.info("detect: %s answers again", source.address)
            answers.append((source, got))
        named = Counter(s.name for s in self.sources)  # known once each source answered
        readings = []
        for source, got in answers:
            for r in got:  # agents that share a host name (one per network namespace): by address too
                if r.source == source.name and named[source.name] > 1:
                    r.source = f"{source.name} ({source.address})"
            readings += got
        with self.lock:
            events = self.detector.tick(readings, now)
            statuses = self.statuses() if self.publisher is not None else None
        if statuses is not None:
            self.publisher.send(statuses)
        self.heap.trim()
        for e in events:
            if self.echo is not None:
                try:
                    self.echo(str(e))
                except OSError:  # standard output closed (`drums detect | head`): the rest goes on
                    self.echo = None
            if self._log is not None:
                self._write(e)
        return events

    def _write(self, event: Event) -> None:
        try:
            self._log.write(json.dumps(event.as_dict()) + "\n")
        except OSError as e:
            if not self.unlogged:
                log.warning("detect: cannot write to --log (%s); the events that do not fit are counted "
                            "in drums_detect_events_unlogged_total", e.strerror)
            self.unlogged += 1

    def run(self, done: threading.Event) -> None:
        next_at = time.monotonic()
        while not done.is_set():
            self.once()
            next_at += self.interval
            late = time.monotonic() - next_at
            if late > 0:  # a tick that took longer than the interval: skip, do not pile up
                next_at += self.interval * (late // self.interval + 1)
            done.wait(max(0.0, next_at - time.monotonic()))

    def statuses(self) -> list[dict]:
        """A WARN status per anomaly now, named by its entity ("drums: edge /camera -> /processor on
        /image"), hardware_id its host; none when all is calm."""
        out = []
        for a in sorted(self.detector.active.values(), key=lambda a: (a.incident, not a.leads, -a.severity)):
            d = a.as_dict()
            message = f"{d['what']} {d['change']} since {time.strftime('%H:%M:%S', time.localtime(a.start))}"
            out.append({"level": WARN, "name": f"drums: {a.entity}", "message": message, "hardware_id": a.entity.source,
                        "values": [[k, str(d[k])] for k in ("category", "series", "baseline", "value", "change",
                                                            "checks", "incident", "leads")]})
        return out

    def close(self) -> None:
        if self.publisher is not None:
            self.publisher.stop()
        self._pool.shutdown(wait=False, cancel_futures=True)
        if self._log is not None:
            self._log.close()

    def snapshot(self) -> Snapshot:
        snap = Snapshot()
        with self.lock:
            d = self.detector
            active = {}
            for a in d.active.values():
                key = (a.series.category, a.entity.kind)
                active[key] = active.get(key, 0) + 1
            for category in CATEGORIES:
                for kind in KINDS:
                    snap.add(STARTED, (category, kind), d.started.get((category, kind), 0))
                    snap.add(ACTIVE, (category, kind), active.get((category, kind), 0))
            for (kind, change), n in sorted(d.changes.items()):
                snap.add(CHANGES, (kind, change), n)
            snap.add(WATCHED, (), d.watched)
            snap.add(FLAGGED, (), d.flagged)
            snap.add(TICK, (), d.tick_seconds)
        for name in self.up:
            snap.add(UP, (name,), self.up[name])
            snap.add(FAILED, (name,), self.failures[name])
        snap.add(UNLOGGED, (), self.unlogged)
        return snap

    def anomalies(self) -> dict:
        """The live list: entities with anomalies now, the most suspicious first."""
        with self.lock:
            return {"watched": self.detector.watched, "flagged": self.detector.flagged,
                    "incidents": [{"incident": number,
                                   "entities": [{"entity": {"kind": e.kind, "name": e.name, "host": e.source},
                                                 "anomalies": [a.as_dict() for a in anomalies]}
                                                for e, anomalies in entities]}
                                  for number, entities in self.detector.ranked()]}


def serve(loop: Loop, address: str, port: int):
    """The detector's own HTTP: /metrics and /anomalies, behind the agent's hardened front."""
    from drums.exporters import prometheus
    from drums.exporters.http import HttpServer

    render = prometheus.Renderer()
    pages = {"/": lambda _q: (b"drums detect: /metrics /anomalies\n", "text/plain; charset=utf-8"),
             "/anomalies": lambda _q: (json.dumps(loop.anomalies()).encode() + b"\n", "application/json")}
    pictures = {"/metrics": lambda snap, _q: (render(snap), prometheus.CONTENT_TYPE)}
    server = HttpServer(address, port, pages, pictures, loop.snapshot, None, None)
    server.start()
    return server

"""The detector: each tick takes one Reading per host, appends every series' newest point (a
counter's rate) to the history, judges all of them with the checks, and turns what they flag into
anomalies of the graph's entities, which start, go on and end.

An anomaly is a series whose checks agree that it left its recent behaviour by more than its
floor. It is reported once when it starts ("edge /camera -> /processor on /image: received
bytes -82% since 13:42:29, 4 checks of 5"), held while it is flagged again within HOLD seconds,
and reported ended after that. The series of an entity that just changed in the graph (a node
started or restarted) are left alone for GRACE seconds: the change is reported, not its effects.
"""
from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from drums.detect import GRACE, checks
from drums.detect.graph import KINDS, Change, Entity, Graph, entity_of
from drums.detect.history import History
from drums.detect.incidents import Incidents, touches
from drums.detect.series import Series
from drums.detect.sources import Reading

WIDTH = 240  # points of history per series: 4 minutes at 1 s
HOLD = 30.0  # seconds an anomaly lasts after it was last flagged
BEFORE = 120.0  # seconds of a series before its anomaly kept with it, for the report's plots
UNKNOWN_NODE = "unknown"  # the node the agent sums topic counts under when it can name none (drums.graph.join)
# A series that cries wolf must shout louder: one that started REPEATS anomalies in the recent past
# starts another only if it is more severe than the most severe of them. Both fade with MEMORY
# seconds (e-folding), so a fault that comes back after hours is news again. (On the Numenta
# Anomaly Benchmark this took the detector from 29 to 44: bench/nab.py.)
REPEATS = 2
MEMORY = 10_000.0
# What the detector keeps per row besides its history: the change that matters, a counter's last raw
# value and when it was read (0: never), whether it was ever called anomalous, the anomalies it
# started lately and the severity of the worst (both fading with MEMORY), and whether it is judged
# for steady growth too (checks.growth).
ROW = np.dtype([("floor", "f8"), ("relative", "f8"), ("last", "f8"), ("last_at", "f8"), ("counter", "?"),
                ("flagged", "?"), ("started", "f8"), ("worst", "f8"), ("grows", "?")])


@dataclass
class Anomaly:
    series: Series
    entity: Entity
    start: float
    baseline: float  # the series' median before it started
    value: float  # its latest judged value
    failed: tuple[str, ...]  # the checks that flagged it, the last time
    severity: float
    last: float  # when it was last flagged
    end: float | None = None
    incident: int = 0  # the incident it belongs to (drums.detect.incidents)
    leads: bool = True  # whether it is its incident's first anomaly, which names the incident
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # [time, value] from BEFORE its start
    # (to its end, once ended)

    @property
    def change(self) -> str:
        """+45%, -82%, or the new value where there was nothing before."""
        s = self.series
        if abs(self.baseline) > 1e-9:
            return f"{100 * (self.value - self.baseline) / abs(self.baseline):+.0f}%"
        return f"{s.format(self.value)} from {s.format(self.baseline)}"

    @property
    def what(self) -> str:
        """What changed, with the process where a node's own series is also counted per process."""
        what, pid = self.series.what, self.series.labels.get("pid")
        if not pid or self.entity.kind == "process":
            return what
        return f"{what[:-1]}, pid {pid})" if what.endswith(")") else f"{what} (pid {pid})"

    def __str__(self) -> str:
        since = time.strftime("%H:%M:%S", time.localtime(self.start))
        how = (f"steady growth over its last {checks.GROWTH_POINTS} points" if self.failed == ("growth",)
               else f"{len(self.failed)} checks of {len(checks.CHECKS)}")
        return f"{self.entity}: {self.what} {self.change} since {since} ({how})"

    def as_dict(self) -> dict:
        s = self.series
        return {"entity": {"kind": self.entity.kind, "name": self.entity.name, "host": self.entity.source},
                "category": s.category, "series": s.text, "what": self.what,
                "start": self.start, "end": self.end, "baseline": self.baseline, "value": self.value,
                "change": self.change, "checks": list(self.failed), "severity": round(self.severity, 2),
                "incident": self.incident, "leads": self.leads, "text": str(self)}

    def logged(self) -> dict:
        """As the JSON log has it: with its points, for the report's plots."""
        return {**self.as_dict(), "points": [[round(t, 3), v] for t, v in self.points.tolist()]}


@dataclass
class Event:
    time: float
    kind: str  # anomaly, ended, graph
    anomaly: Anomaly | None = None
    change: Change | None = None

    def as_dict(self) -> dict:
        out = {"time": self.time, "event": self.kind}
        if self.anomaly is not None:
            out.update(self.anomaly.logged())
        if self.change is not None:
            e = self.change.entity
            out.update(entity={"kind": e.kind, "name": e.name, "host": e.source}, category="graph",
                       change=self.change.change, detail=self.change.detail, text=f"graph: {self.change}")
        return out

    def __str__(self) -> str:
        at = time.strftime("%H:%M:%S", time.localtime(self.time))
        if self.change is not None:
            return f"{at} graph: {self.change}"
        if self.kind == "ended":
            return f"{at} ended: {self.anomaly}"
        return f"{at} {'' if self.anomaly.leads else '  + '}{self.anomaly}"  # a member under its incident


class Detector:
    def __init__(self, width: int = WIDTH, hold: float = HOLD, grace: float = GRACE, ignore: set[str] = frozenset()):
        """`ignore`: kinds of entity whose series are watched but never called anomalous."""
        self.history = History(width)
        self.hold, self.grace, self.ignore = hold, grace, ignore
        self.series: dict[tuple[str, str], Series] = {}  # (source, series text) -> its series
        self.by_row: dict[int, Series] = {}
        self._index: dict[str, dict[str, int]] = {}  # source -> series text -> row
        self._state = np.zeros(len(self.history.used), ROW)
        self._edges: dict[tuple[str, str], tuple[Entity, tuple[Entity, ...]]] = {}  # an edge's series -> edge, ends
        self.graph = Graph(grace)
        self.active: dict[tuple[str, str], Anomaly] = {}  # series key -> its anomaly
        self.incidents = Incidents()
        self.started = Counter()  # (category, entity kind) -> anomalies started
        self.changes = Counter()  # (entity kind, change) -> graph changes
        self.flagged = 0  # distinct series called anomalous since the start (a series that comes back anew counts again)
        self.tick_seconds = 0.0
        self._judged_at: float | None = None

    @property
    def watched(self) -> int:
        return len(self.series)

    def tick(self, readings: list[Reading], now: float | None = None) -> list[Event]:
        began = time.perf_counter()
        now = time.time() if now is None else now
        rows, values = self._ingest(readings)
        for row in self.history.tick(rows, values, now).tolist():
            s = self.by_row.pop(row)
            del self.series[s.key]
            self._edges.pop(s.key, None)
            del self._index[s.source][s.text]
        events = [Event(now, "graph", change=c) for c in self._graph(now, readings)]
        events += self._judge(now)
        events += self._expire(now)
        self.tick_seconds = time.perf_counter() - began
        return events

    def _ingest(self, readings: list[Reading]) -> tuple[np.ndarray, np.ndarray]:
        """Rows and newest points of every series read (a counter's rate since its last read)."""
        all_rows, all_values = [], []
        for r in readings:
            index = self._index.setdefault(r.source, {})
            rows = np.fromiter((index.get(text, -1) for text in r.series), np.int64, len(r.series))
            new = np.flatnonzero(rows < 0)  # series seen for the first time
            if len(new):
                texts = list(r.series)
                for i in new.tolist():
                    rows[i] = self._add(r, texts[i])
            values = np.fromiter(r.series.values(), np.float64, len(r.series))
            state = self._state[rows]
            counter = state["counter"]
            if counter.any():
                raw = values[counter]
                increase = raw - state["last"][counter]
                increase = np.where(increase < 0, raw, increase)  # a reset counts from zero
                elapsed = r.time - state["last_at"][counter]
                c_rows = rows[counter]
                self._state["last"][c_rows] = raw
                self._state["last_at"][c_rows] = r.time
                with np.errstate(divide="ignore", invalid="ignore"):
                    values[counter] = increase / elapsed
                # A counter's first read has no rate yet; nor has a read no later than the last.
                keep = np.ones(len(rows), bool)
                keep[np.flatnonzero(counter)[(state["last_at"][counter] <= 0) | (elapsed <= 0)]] = False
                rows, values = rows[keep], values[keep]
            all_rows.append(rows)
            all_values.append(values)
        if not all_rows:
            return np.zeros(0, np.int64), np.zeros(0)
        return np.concatenate(all_rows), np.concatenate(all_values)

    def _add(self, r: Reading, text: str) -> int:
        brace = text.find("{")
        s = Series.of(r.source, text, (text if brace < 0 else text[:brace]) in r.counters)
        key = s.key
        s.row = self.history.add()
        if s.row >= len(self._state):
            grown = np.zeros(len(self.history.used), self._state.dtype)
            grown[:len(self._state)] = self._state
            self._state = grown
        self._state[s.row] = (s.floor, s.relative, 0.0, 0.0, s.counter, False, 0.0, 0.0, s.grows)
        self.series[key] = s
        self.by_row[s.row] = s
        if s.name.startswith("drums_edge_"):
            labels = s.labels
            edge = entity_of(s.source, labels, {})
            self._edges[key] = edge, tuple(e for e in touches(edge, labels, {}) if e != edge and e.source)
        self._index.setdefault(r.source, {})[text] = s.row
        return s.row

    def _graph(self, now: float, readings: list[Reading]) -> list[Change]:
        nodes = {(r.source, node): pid for r in readings for node, pid in r.nodes.items()}
        started = {(r.source, pid): at for r in readings for pid, at in r.started.items()}
        edges = dict(self._edges.values())
        changes = self.graph.update(now, {r.source for r in readings}, nodes, edges, started)
        for c in changes:
            self.changes[c.entity.kind, c.change] += 1
        return changes

    def _entity(self, s: Series) -> Entity:
        return entity_of(s.source, s.labels, self.graph.node_of_pid.get(s.source, {}))

    def _ignored(self, s: Series, entity: Entity) -> bool:
        """Of an ignored kind; with `process` ignored, also what a process that runs no node counts
        (its messages on a topic, say), and what the agent could name no node for."""
        if entity.kind in self.ignore:
            return True
        if "process" not in self.ignore:
            return False
        labels = s.labels
        pid = labels.get("pid")
        return labels.get("node") == UNKNOWN_NODE or (
            bool(pid) and pid not in self.graph.node_of_pid.get(s.source, {}))

    def _settling(self, s: Series, entity: Entity, now: float) -> bool:
        """The entity, or the node its series names, changed in the graph a moment ago."""
        if self.graph.settling(entity, now):
            return True
        labels = s.labels
        node = labels.get("node") or self.graph.node_of_pid.get(s.source, {}).get(labels.get("pid", ""))
        return bool(node) and self.graph.settling(Entity("node", node, s.source), now)

    def _judge(self, now: float) -> list[Event]:
        new = []
        if self._judged_at is not None:
            fade = np.exp(-max(0.0, now - self._judged_at) / MEMORY)
            self._state["started"] *= fade
            self._state["worst"] *= fade
        self._judged_at = now
        for rows, window in self.history.cohorts(checks.MIN_POINTS):
            state = self._state[rows]
            verdict = checks.judge(window, state["floor"], state["relative"])
            failed = verdict.failed.sum(axis=1) >= checks.CONSENSUS
            for i in np.flatnonzero(failed).tolist():
                s = self.by_row[int(rows[verdict.rows[i]])]
                entity = self._entity(s)
                if self._ignored(s, entity):
                    continue
                if self._settling(s, entity, now):
                    # What moved while its entity settled is no fault, nor a baseline to judge by later:
                    # the series starts its history again, to be judged after a new warm-up.
                    self.history.held[s.row] = 0
                    continue
                names = tuple(c for c, f in zip(checks.CHECKS, verdict.failed[i]) if f)
                self._flag(s, entity, names, float(verdict.baseline[i]), float(verdict.value[i]),
                           float(verdict.severity[i]), now, new)
        self._judge_growth(now, new)
        # Links before their ends, streams before their consumers: the first names the incident.
        new.sort(key=lambda a: (KINDS.index(a.entity.kind), -a.severity))
        for a in new:
            a.points = self.history.since(a.series.row, now - BEFORE)
            self.active[a.series.key] = a
            self.started[a.series.category, a.entity.kind] += 1
            if not self._state["flagged"][a.series.row]:
                self._state["flagged"][a.series.row] = True
                self.flagged += 1
            near = touches(a.entity, a.series.labels, self.graph.node_of_pid.get(a.series.source, {}))
            incident = self.incidents.place(a, near, now)
            a.incident, a.leads = incident.id, incident.root is a
        return [Event(now, "anomaly", a) for a in new]

    def _flag(self, s: Series, entity: Entity, names: tuple[str, ...], baseline: float, value: float,
              severity: float, now: float, new: list[Anomaly]) -> None:
        """The series was flagged: its anomaly goes on, or one starts (into `new`) unless it cries wolf."""
        a = self.active.get(s.key)
        row = self._state[s.row]
        if a is not None:
            a.value, a.failed, a.severity, a.last, a.entity = value, names, severity, now, entity
        elif row["started"] < REPEATS - 0.5 or severity > row["worst"]:
            new.append(Anomaly(s, entity, now, baseline, value, names, severity, now))
            row["started"] += 1
        row["worst"] = max(row["worst"], severity)

    def _judge_growth(self, now: float, new: list[Anomaly]) -> None:
        """Memory that grew all along its newest points: judged from a process's first points, and while
        its node settles (a leak from birth is news, not the start-up's effect: checks.growth)."""
        h, k = self.history, checks.GROWTH_POINTS
        n = len(h.used)
        rows = np.flatnonzero(h.used & self._state["grows"][:n] & (h.held >= k) & (h.missed == 0))
        if not len(rows):
            return
        window = h.points[np.ix_(rows, (h.column - k + 1 + np.arange(k)) % h.width)]
        state = self._state[rows]
        for i in np.flatnonzero(checks.growth(window, state["floor"], state["relative"])).tolist():
            s = self.by_row[int(rows[i])]
            entity = self._entity(s)
            if not self._ignored(s, entity):
                first, last = float(window[i, 0]), float(window[i, -1])
                self._flag(s, entity, ("growth",), first, last, (last - first) / max(s.floor, 1e-12), now, new)

    def _expire(self, now: float) -> list[Event]:
        events = []
        for key, a in list(self.active.items()):
            if now - a.last >= self.hold or key not in self.series:
                if key in self.series:  # a series that is gone has only its points from before
                    a.points = np.concatenate([a.points, self.history.since(a.series.row, a.start + 1e-6)])
                a.end = now
                del self.active[key]
                events.append(Event(now, "ended", a))
        self.incidents.close(self.active)
        return events

    def ranked(self) -> list[tuple[int, list[tuple[Entity, list[Anomaly]]]]]:
        """The incidents with anomalies now, the largest first, each as its entities with their
        anomalies, the most severe first (the incident's first anomaly leads)."""
        out = []
        for incident in self.incidents.open:
            live = [a for a in incident.members if self.active.get(a.series.key) is a]
            by_entity: dict[Entity, list[Anomaly]] = {}
            for a in sorted(live, key=lambda a: (not a.leads, -a.severity)):
                by_entity.setdefault(a.entity, []).append(a)
            out.append((incident.id, list(by_entity.items())))
        return sorted(out, key=lambda item: (-sum(len(v) for _, v in item[1]), item[0]))

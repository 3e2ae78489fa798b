"""The computation graph (the paper's section II-A, extended): hosts, processes, middleware nodes,
topics, endpoints and the connections between nodes, with a stream of timestamped changes. It is
kept as two dicts (vertices, edges); `snapshot()` hands readers a networkx MultiDiGraph of it,
imported then: an agent that is never asked for its graph does not carry networkx (15 MB).

Adapters do not edit the graph: each poll hands over a whole `GraphState` (what the middleware
says now), and `Graph.update` works out what was added, removed or changed. That keeps adapters
simple and makes every change visible in one place.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING

from drums.errors import GraphError

if TYPE_CHECKING:  # imported by snapshot(), when a graph is made
    import networkx as nx


@dataclass(frozen=True)
class Host:
    """A machine of the graph. `address` (an IP or DNS name) reaches the host and its Drums agent,
    "" where unknown; `agent` is the agent's base URL (http://10.0.0.2:9969) where it is known."""

    name: str
    address: str = ""
    agent: str = ""


@dataclass(frozen=True)
class Process:
    host: str
    pid: int
    name: str = ""


@dataclass(frozen=True)
class Node:
    """A middleware node. `mapped_by` says how its process was found (e.g. "gid", "cmdline"), or
    "unmapped"; `extra` holds what only one middleware has (a DDS participant, a ROS 1 URI)."""

    name: str  # fully qualified: /namespace/name
    host: str = ""
    pid: int | None = None
    mapped_by: str = "unmapped"
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Topic:
    name: str
    types: tuple[str, ...] = ()


@dataclass(frozen=True)
class Endpoint:
    """A publisher or subscriber of one node on one topic; `id` is its middleware identity (a DDS
    GID in hex, or node and topic for ROS 1)."""

    id: str
    kind: str  # "publisher" or "subscriber"
    node: str
    topic: str
    qos: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Connection:
    """Data flowing from a publishing node to a subscribing node on one topic. Where the
    transport has one socket per connection (TCPROS), its local and remote endpoints."""

    topic: str
    publisher: str
    subscriber: str
    transport: str = ""
    local: str = ""
    remote: str = ""
    qos_check: str = ""  # the middleware's QoS compatibility verdict: "ok", or why not

    def incompatible(self) -> tuple[str, ...]:
        """The QoS policies that keep the two ends apart (the middleware's ERRORs; its WARNINGs,
        where a side's policy is the system default, may connect), in the order it gave them."""
        found = []
        for verdict in self.qos_check.split(";"):
            if verdict.startswith("ERROR:"):
                text = verdict.lower()
                policy = next((p for words, p in QOS_POLICIES if words in text), "other")
                if policy not in found:
                    found.append(policy)
        return tuple(found)


# What an rmw incompatibility (rmw_dds_common's reasons, Galactic on) names: the first match wins.
QOS_POLICIES = (("reliab", "reliability"), ("best effort", "reliability"), ("durab", "durability"),
                ("transient local", "durability"), ("deadline", "deadline"), ("lease duration", "liveliness_lease"),
                ("liveliness", "liveliness"), ("lifespan", "lifespan"))


ENTITIES = {"host": Host, "process": Process, "node": Node, "topic": Topic, "endpoint": Endpoint,
            "connection": Connection}
PLURAL = {kind: "processes" if kind == "process" else f"{kind}s" for kind in ENTITIES}


@dataclass
class GraphState:
    """What an adapter saw at one poll: every entity, no diff."""

    hosts: list[Host] = field(default_factory=list)
    processes: list[Process] = field(default_factory=list)
    nodes: list[Node] = field(default_factory=list)
    topics: list[Topic] = field(default_factory=list)
    endpoints: list[Endpoint] = field(default_factory=list)
    connections: list[Connection] = field(default_factory=list)
    truncated: str = ""  # why the adapter kept only part of what the middleware said ("" if it kept all)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data) -> "GraphState":
        """From JSON (an adapter's child process, a client): anything malformed is a GraphError."""
        if not isinstance(data, dict):
            raise GraphError(f"a graph state is an object, not {type(data).__name__}")
        state = cls(truncated=data.get("truncated", ""))
        if not isinstance(state.truncated, str):
            raise GraphError(f"truncated: a reason, not {type(state.truncated).__name__}")
        for kind, entity in ENTITIES.items():
            items = data.get(PLURAL[kind], [])
            if not isinstance(items, list):
                raise GraphError(f"{PLURAL[kind]}: a list, not {type(items).__name__}")
            for item in items:
                try:
                    obj = entity(**item)
                except TypeError as e:
                    raise GraphError(f"{PLURAL[kind]}: {e}") from None
                if isinstance(obj, Topic):
                    obj = Topic(obj.name, tuple(obj.types))
                getattr(state, PLURAL[kind]).append(obj)
        return state


def vertex_id(kind: str, obj) -> str:
    if kind == "process":
        return f"process:{obj.host}/{obj.pid}"
    if kind == "endpoint":
        return f"endpoint:{obj.id}"
    return f"{kind}:{obj.name}"


@dataclass(frozen=True)
class Change:
    at: float  # time.time() of the poll that saw it
    action: str  # "added", "removed" or "changed"
    kind: str
    id: str
    entity: object  # the entity as it is now (as it was, for "removed")


def _layout(state: GraphState) -> tuple[dict, dict]:
    """(vertices, edges) of a state: id -> (kind, entity), and (u, v, key) -> (kind, entity)."""
    vertices: dict[str, tuple[str, object]] = {}
    edges: dict[tuple[str, str, str], tuple[str, object]] = {}
    for kind in ("host", "process", "node", "topic", "endpoint"):
        for obj in getattr(state, PLURAL[kind]):
            vertices[vertex_id(kind, obj)] = (kind, obj)
    # Structure edges tie entities to what contains or carries them. They exist only between
    # vertices that exist: a node whose process is unknown hangs from no process.
    def link(u, v, key):
        if u in vertices and v in vertices:
            edges[u, v, key] = ("structure", key)
    for p in state.processes:
        link(f"host:{p.host}", vertex_id("process", p), "runs")
    for n in state.nodes:
        if n.pid is not None:
            link(f"process:{n.host}/{n.pid}", f"node:{n.name}", "hosts")
    for e in state.endpoints:
        link(f"node:{e.node}", f"endpoint:{e.id}", "has")
        if e.kind == "publisher":
            link(f"endpoint:{e.id}", f"topic:{e.topic}", "publishes")
        else:
            link(f"topic:{e.topic}", f"endpoint:{e.id}", "delivers")
    for c in state.connections:
        u, v = f"node:{c.publisher}", f"node:{c.subscriber}"
        if u in vertices and v in vertices:
            edges[u, v, c.topic] = ("connection", c)
    return vertices, edges


class Graph:
    """The live graph. Readers take `snapshot()` (a copy); one adapter thread calls `update`."""

    def __init__(self, history: int = 10000, stale_after: float = 5.0):
        self._vertices: dict = {}  # id -> (kind, entity)
        self._edges: dict = {}  # (u, v, key) -> (kind, entity)
        self._lock = threading.Lock()
        self.changes: deque[Change] = deque(maxlen=history)  # the newest changes, oldest dropped
        self.change_count = 0  # changes ever made: a reader's cursor into `changes`
        self.updated_at = 0.0  # time.time() of the last good state
        self.stale_after = stale_after
        self.error = ""  # why the last poll failed, "" after a good one
        self.truncated = ""  # why the last good state is only part of the graph, "" if it is whole

    def update(self, state: GraphState, at: float | None = None) -> list[Change]:
        at = time.time() if at is None else at
        vertices, edges = _layout(state)
        changes = []
        with self._lock:
            for vid in self._vertices.keys() - vertices.keys():
                kind, obj = self._vertices[vid]
                changes.append(Change(at, "removed", kind, vid, obj))
            for vid, (kind, obj) in vertices.items():
                old = self._vertices.get(vid)
                if old is None or old[1] != obj:
                    changes.append(Change(at, "added" if old is None else "changed", kind, vid, obj))
            for key in self._edges.keys() - edges.keys():
                kind, obj = self._edges[key]
                if kind == "connection":
                    changes.append(Change(at, "removed", kind, _edge_id(key), obj))
            for key, (kind, obj) in edges.items():
                old = self._edges.get(key)
                if kind == "connection" and old != (kind, obj):
                    changes.append(Change(at, "added" if old is None else "changed", kind, _edge_id(key), obj))
            self._vertices, self._edges = vertices, edges
            self.changes.extend(changes)
            self.change_count += len(changes)
            self.updated_at = at
            self.error = ""
            self.truncated = state.truncated
        return changes

    def changes_since(self, count: int) -> tuple[list[Change], int]:
        """The changes after the first `count` (those still kept), and the count to ask with next."""
        with self._lock:
            missed = self.change_count - count
            kept = list(self.changes)
            return (kept[-missed:] if 0 < missed else []), self.change_count

    def failed(self, reason: str) -> None:
        """The adapter could not read the middleware: the last good graph stays, marked stale."""
        with self._lock:
            self.error = reason

    def stale(self, now: float | None = None) -> bool:
        now = time.time() if now is None else now
        return bool(self.error) or now - self.updated_at > self.stale_after

    def snapshot(self) -> nx.MultiDiGraph:
        """The graph now, as a networkx MultiDiGraph of its own: vertices with `kind` and `entity`,
        edges keyed by their relation ("runs", "hosts", ...) or a connection's topic."""
        import networkx as nx
        with self._lock:
            vertices, edges = self._vertices, self._edges  # replaced whole by update, never edited
        g = nx.MultiDiGraph()
        g.add_nodes_from((vid, {"kind": kind, "entity": obj}) for vid, (kind, obj) in vertices.items())
        g.add_edges_from((u, v, key, {"kind": kind, "entity": obj}) for (u, v, key), (kind, obj) in edges.items())
        return g

    def entities(self, kind: str) -> list:
        with self._lock:
            return [obj for k, obj in self._vertices.values() if k == kind]

    def connections(self) -> list[Connection]:
        with self._lock:
            return [obj for k, obj in self._edges.values() if k == "connection"]


def _edge_id(key: tuple[str, str, str]) -> str:
    return f"{key[0]}->{key[1]}@{key[2]}"

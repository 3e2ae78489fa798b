"""What a series belongs to in the robot's computation graph, and the graph's own changes.

A series is attributed to the most specific entity its labels name: an edge (publisher ->
subscriber on a topic), a topic, a node, a process (the node that runs in it, where the agent
mapped one), a TCP connection, a latency link, or else the host. The graph changes (a node
started, stopped or restarted; an edge or a host appeared or went) are reported as such, and the
series of a changed entity are not called anomalous while it settles.
"""
from __future__ import annotations

from dataclasses import dataclass

KINDS = ("edge", "topic", "node", "process", "connection", "link", "host")


@dataclass(frozen=True)
class Entity:
    kind: str
    name: str
    source: str  # the host whose agent reported it

    def __str__(self) -> str:
        return f"{self.kind} {self.name}"


def entity_of(source: str, labels: dict[str, str], node_of_pid: dict[str, str]) -> Entity:
    if "publisher" in labels and "subscriber" in labels:
        return Entity("edge", f"{labels['publisher']} -> {labels['subscriber']} on {labels.get('topic', '?')}", source)
    if "topic" in labels:
        return Entity("topic", labels["topic"], source)
    if "node" in labels:
        return Entity("node", labels["node"], source)
    if "pid" in labels:
        node = node_of_pid.get(labels["pid"])
        if node:
            return Entity("node", node, source)
        return Entity("process", f"{labels.get('process', '?')} ({labels['pid']})", source)
    if "local" in labels and "remote" in labels:
        return Entity("connection", f"{labels['local']} -> {labels['remote']}", source)
    if "target" in labels:
        return Entity("link", f"{source} -> {labels['target']}", source)
    return Entity("host", source, source)


@dataclass
class Change:
    entity: Entity
    change: str  # started, stopped, restarted, appeared, went, joined, left
    detail: str = ""

    def __str__(self) -> str:
        return f"{self.entity} {self.change}" + (f" ({self.detail})" if self.detail else "")


class Graph:
    """The nodes (with their processes), edges and hosts seen at the last tick, and when each
    entity last changed."""

    def __init__(self, grace: float):
        self.grace = grace
        self.nodes: dict[tuple[str, str], str] = {}  # (source, node) -> pid
        self.edges: set[Entity] = set()
        self.ends: dict[Entity, tuple[Entity, ...]] = {}  # an edge's topic and nodes
        self.hosts: set[str] = set()
        self.node_of_pid: dict[str, dict[str, str]] = {}  # source -> pid -> node
        self.changed_at: dict[Entity, float] = {}
        self._first = True

    def update(self, now: float, hosts: set[str], nodes: dict[tuple[str, str], str],
               edges: dict[Entity, tuple[Entity, ...]], started: dict[tuple[str, str], float]) -> list[Change]:
        """The changes since the last tick. `edges`: each edge with its ends (its topic and its two
        nodes), which settle with it: a new subscriber changes what its publisher sends. On the
        first tick everything is simply there: nothing changed, but a node whose process `started`
        (source, pid -> Unix time) a moment ago is still settling. A host that did not answer keeps
        its nodes and edges until it answers again."""
        changes = [Change(Entity("host", h, h), "joined") for h in sorted(hosts - self.hosts)]
        changes += [Change(Entity("host", h, h), "left", "its agent does not answer")
                    for h in sorted(self.hosts - hosts)]
        nodes = {**{k: v for k, v in self.nodes.items() if k[0] not in hosts}, **nodes}
        self.ends.update(edges)
        edges = {e for e in self.edges if e.source not in hosts} | set(edges)
        for (source, node), pid in sorted(nodes.items()):
            before = self.nodes.get((source, node))
            if before is None:
                changes.append(Change(Entity("node", node, source), "started", f"pid {pid}"))
            elif before != pid:
                changes.append(Change(Entity("node", node, source), "restarted", f"pid {before} -> {pid}"))
        changes += [Change(Entity("node", node, source), "stopped", f"pid {pid}")
                    for (source, node), pid in sorted(self.nodes.items()) if (source, node) not in nodes]
        changes += [Change(e, "appeared") for e in sorted(edges - self.edges, key=str)]
        changes += [Change(e, "went") for e in sorted(self.edges - edges, key=str)]
        self.hosts, self.nodes, self.edges = set(hosts), nodes, edges
        self.node_of_pid = {}
        for (source, node), pid in nodes.items():
            self.node_of_pid.setdefault(source, {})[pid] = node
        if self._first:
            self._first = False
            for (source, node), pid in nodes.items():
                if (source, pid) in started:
                    self.changed_at[Entity("node", node, source)] = started[source, pid]
            return []
        self.changed_at = {e: at for e, at in self.changed_at.items() if now - at < self.grace}
        for c in changes:
            for entity in (c.entity, *self.ends.get(c.entity, ())):
                self.changed_at[entity] = now
        self.ends = {e: self.ends[e] for e in edges}
        return changes

    def settling(self, entity: Entity, now: float) -> bool:
        """Whether the entity changed less than the grace ago (its series are expected to move)."""
        at = self.changed_at.get(entity)
        return at is not None and now - at < self.grace

"""Anomalies that are one fault seen in several places.

A router that throttles the camera's link slows the edge camera -> processor, then everything the
processor publishes and everyone who takes it, within a second or two. Listing thirty series
would hide the one that matters, so anomalies that start within GAP seconds of an incident's last
one, on entities that touch it in the computation graph (the same node or topic, an edge's topic
or its two nodes), join that incident. The incident is named by its first anomaly; within one tick
edges come first, then topics, then nodes (KINDS order): the link before its ends, the stream
before its consumers.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from drums.detect.graph import Entity

GAP = 10.0  # seconds after an incident's last new anomaly that a connected one still joins it
GRAPH_WIDE = ("node", "topic", "edge")  # one graph across hosts: the same name on two agents is one entity


def touches(entity: Entity, labels: dict[str, str], node_of_pid: dict[str, str]) -> frozenset[Entity]:
    """The entity and the entities of the graph its series names besides it; nodes, topics and edges
    also without the host that measured them, so that the two ends of a link on two hosts touch."""
    near = {entity}
    source = entity.source
    for key in ("node", "publisher", "subscriber"):
        if labels.get(key):
            near.add(Entity("node", labels[key], source))
    if labels.get("topic"):
        near.add(Entity("topic", labels["topic"], source))
    if node_of_pid.get(labels.get("pid", "")):
        near.add(Entity("node", node_of_pid[labels["pid"]], source))
    return frozenset(near | {Entity(e.kind, e.name, "") for e in near if e.kind in GRAPH_WIDE})


@dataclass
class Incident:
    id: int
    start: float
    joined: float  # when its last anomaly joined
    touched: set[Entity] = field(default_factory=set)
    members: list = field(default_factory=list)  # its anomalies, the first one names it

    @property
    def root(self):
        return self.members[0]


class Incidents:
    def __init__(self):
        self.open: list[Incident] = []
        self._next = 1

    def place(self, anomaly, near: frozenset[Entity], now: float) -> Incident:
        """The incident the new anomaly joins, or a new one it starts."""
        for incident in reversed(self.open):
            if now - incident.joined <= GAP and incident.touched & near:
                break
        else:
            incident = Incident(self._next, now, now)
            self._next += 1
            self.open.append(incident)
        incident.members.append(anomaly)
        incident.touched |= near
        incident.joined = now
        return incident

    def close(self, active: dict) -> None:
        """Forget the anomalies that ended (an incident keeps the one that names it) and the incidents
        none of whose anomalies is still active."""
        for i in self.open:
            i.members = [a for n, a in enumerate(i.members) if n == 0 or active.get(a.series.key) is a]
        self.open = [i for i in self.open if any(active.get(a.series.key) is a for a in i.members)]

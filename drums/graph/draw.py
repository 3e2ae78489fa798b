"""The graph as a picture, drawn as ROS developers know it from rqt_graph: nodes as ellipses,
topics as boxes, publisher -> topic -> subscriber, each arrow labelled with its message rate and
bandwidth and as thick as its bandwidth, a subscriber's arrow also with the age of the messages it
took and a node with its slowest reaction; hosts as clusters, and a process that holds several
nodes as a cluster inside its host. /rosout, /parameter_events and Drums' own nodes are left out
unless `everything` is asked for.

DOT is written here rather than through pydot: every id and label is quoted and escaped, so any
name a middleware allows (a `node` attribute, quotes, backslashes) is valid DOT. Graphviz's `dot`
turns it into SVG.
"""
from __future__ import annotations

import math
import subprocess
import threading
import time
from collections import defaultdict
from typing import TYPE_CHECKING

from drums import units
from drums.errors import UsageError
from drums.graph import join
from drums.metrics import COUNTER, Snapshot

if TYPE_CHECKING:  # the graph modules load networkx only when a graph is made (model.snapshot)
    import networkx as nx

HIDDEN_TOPICS = ("/rosout", "/parameter_events")
TIMINGS = (join.EDGE_AGE, join.NODE_REACTION)  # means on the picture
OWN_PREFIX = "/_drums"  # Drums' own nodes: the graph reader and the /diagnostics publisher
DOT_TIMEOUT = 20  # seconds: Graphviz lays out a few hundred vertices in well under a second


def quote(text: str) -> str:
    """A DOT double-quoted string: any text, whatever keyword or character it holds."""
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'


def _attrs(**attrs) -> str:
    return "[" + ", ".join(f"{k}={quote(str(v))}" for k, v in attrs.items()) + "]"


class Rates:
    """Per-second rates of the joined counters, and means of the joined timings, between two looks
    at least `gap` seconds apart: a picture refreshed every few seconds shows what happened since
    the last one."""

    def __init__(self, gap: float = 1.0):
        self.gap = gap
        self._lock = threading.Lock()
        self._before: tuple[float, dict] | None = None
        self._rates: dict = {}

    def update(self, snap: Snapshot, now: float | None = None) -> dict:
        """{(metric name, labels): per second} of every counter of the join in `snap`, and
        {(metric name, labels): mean seconds} of its timings that counted any in between."""
        now = time.monotonic() if now is None else now
        values = {(m.name, labels): v for m in join.METRICS if m.kind == COUNTER
                  for labels, v in snap.series.get(m, ())}
        values.update({(m.name, labels): (h.count, h.sum) for m in TIMINGS for labels, h in snap.series.get(m, ())})
        with self._lock:
            if self._before is None:
                self._before = (now, values)
            elif now - self._before[0] >= self.gap:
                then, old = self._before
                self._rates = {k: r for k, v in values.items()
                               if k in old and (r := _change(v, old[k], now - then)) is not None}
                self._before = (now, values)
            return self._rates


def _change(now, before, seconds: float) -> float | None:
    """A counter's rate, or a timing's mean, between two reads; None if it began again or, for a
    timing, counted nothing."""
    if isinstance(now, tuple):
        counted = now[0] - before[0]
        return (now[1] - before[1]) / counted if counted > 0 else None
    return (now - before) / seconds if now >= before else None


def _hidden(vid: str, entity) -> bool:
    name = getattr(entity, "name", "")
    return (vid.startswith("topic:") and name in HIDDEN_TOPICS) or (vid.startswith("node:") and name.startswith(OWN_PREFIX))


def _penwidth(bytes_per_second: float | None) -> float:
    """1 for nothing known, up to 6 for 100 MiB/s and more: thicker by bandwidth, logarithmically."""
    if not bytes_per_second:
        return 1.0
    return round(1 + min(5.0, math.log10(bytes_per_second / 1024 + 1)), 2)


def _flow(rate: float | None, bandwidth: float | None) -> str:
    parts = [units.rate(rate) if rate is not None else "", units.bandwidth(bandwidth) if bandwidth else ""]
    return "  ".join(p for p in parts if p)


def dot(g: nx.MultiDiGraph, snap: Snapshot | None = None, rates: dict | None = None,
        everything: bool = False) -> str:
    """The picture of graph `g` in DOT; with an agent's joined snapshot and rates on it."""
    rates = rates or {}
    values = {(m.name, labels): v for m in join.METRICS for labels, v in (snap.series.get(m, ()) if snap else ())}
    kinds: dict[str, list] = defaultdict(list)
    for vid, data in g.nodes(data=True):
        if everything or not _hidden(vid, data["entity"]):
            kinds[data["kind"]].append((vid, data["entity"]))
    shown = {vid for items in kinds.values() for vid, _ in items}
    lines = ["digraph drums {",
             '  graph [rankdir="LR", fontname="Helvetica", fontsize="11", nodesep="0.3", ranksep="0.6"];',
             '  node [fontname="Helvetica", fontsize="10"];',
             '  edge [fontname="Helvetica", fontsize="9", color="#555555"];']

    slowest: dict[str, float] = {}  # node -> its slowest reaction's mean
    for (metric, labels), r in rates.items():
        if metric == join.NODE_REACTION.name:
            slowest[labels[0]] = max(r, slowest.get(labels[0], r))

    def node_line(vid: str, n, indent: str) -> str:
        name = n.name
        cpu = rates.get((join.NODE_CPU.name, (name,)))
        memory = values.get((join.NODE_MEMORY.name, (name,)))
        reaction = slowest.get(name)
        detail = "  ".join(x for x in (f"CPU {units.percent(100 * cpu)}" if cpu is not None else "",
                                        units.size(memory) if memory else "",
                                        f"reacts {units.duration(reaction)}" if reaction is not None else "") if x)
        return f"{indent}{quote(vid)} {_attrs(shape='ellipse', label=name + (chr(10) + detail if detail else ''))};"

    nodes_by_process: dict[tuple, list] = defaultdict(list)
    for vid, n in sorted(kinds["node"], key=lambda item: item[0]):
        nodes_by_process[(n.host, n.pid)].append((vid, n))
    processes = {(p.host, p.pid): p for _, p in kinds["process"]}
    hosts = sorted({h.name for _, h in kinds["host"]} | {n.host for _, n in kinds["node"] if n.host})
    for i, host in enumerate(hosts):
        members_of_host = sorted(((key, members) for key, members in nodes_by_process.items() if key[0] == host),
                                 key=lambda kv: kv[0][1] or 0)
        if not members_of_host:
            continue
        lines.append(f"  subgraph {quote(f'cluster_host_{i}')} {{")
        lines.append(f'    label={quote(host)}; style="rounded"; color="#888888";')
        for j, ((h, pid), members) in enumerate(members_of_host):
            if len(members) > 1 and pid is not None:
                p = processes.get((h, pid))
                title = f"{p.name if p and p.name else 'process'} {pid}: {len(members)} nodes"
                lines.append(f"    subgraph {quote(f'cluster_process_{i}_{j}')} {{")
                lines.append(f'      label={quote(title)}; style="dashed"; color="#aaaaaa";')
                lines.extend(node_line(vid, n, "      ") for vid, n in members)
                lines.append("    }")
            else:
                lines.extend(node_line(vid, n, "    ") for vid, n in members)
        lines.append("  }")
    lines.extend(node_line(vid, n, "  ") for vid, n in sorted(kinds["node"], key=lambda item: item[0]) if not n.host)

    topics = {t.name for _, t in kinds["topic"]}
    for name in sorted(topics):
        published = sum(r for (m, labels), r in rates.items() if m == join.TOPIC_PUBLISHED.name and labels[0] == name)
        flow = _flow(published if published else None, None)
        lines.append(f"  {quote('topic:' + name)} {_attrs(shape='box', style='rounded', label=name + (chr(10) + flow if flow else ''))};")

    # Publisher -> topic -> subscriber where the topic is drawn, from the connections and from
    # endpoints without one yet; a connection of a topic that is not drawn (ROS 1 or auto graphs)
    # goes straight from node to node.
    pubs, subs, direct, apart = set(), set(), [], []
    for u, v, _, data in g.edges(keys=True, data=True):
        if data["kind"] == "connection" and u in shown and v in shown:
            c = data["entity"]
            if c.incompatible():
                apart.append(c)  # no data flows: said as such, from node to node
            elif c.topic in topics:
                pubs.add((c.topic, c.publisher))
                subs.add((c.topic, c.subscriber))
            else:
                direct.append(c)
    for _, e in kinds["endpoint"]:
        if e.topic in topics and f"node:{e.node}" in shown:
            (pubs if e.kind == "publisher" else subs).add((e.topic, e.node))
    received: dict[tuple[str, str], float] = defaultdict(float)  # by (topic, subscriber), from every publisher
    ages: dict[tuple[str, str], float] = {}  # by (topic, subscriber): the oldest of its publishers'
    for (metric, labels), r in rates.items():
        if metric == join.EDGE_RECEIVED_BYTES.name:
            received[labels[0], labels[2]] += r
        elif metric == join.EDGE_AGE.name:
            ages[labels[0], labels[2]] = max(r, ages.get((labels[0], labels[2]), 0.0))
    for topic, node in sorted(pubs):
        rate = rates.get((join.TOPIC_PUBLISHED.name, (topic, node)))
        sent = rates.get((join.TOPIC_SENT_BYTES.name, (topic, node)))
        lines.append(f"  {quote('node:' + node)} -> {quote('topic:' + topic)} "
                     f"{_attrs(label=_flow(rate, sent), penwidth=_penwidth(sent))};")
    for topic, node in sorted(subs):
        rate = rates.get((join.TOPIC_TAKEN.name, (topic, node)))
        got = received.get((topic, node))
        age = f"age {units.duration(ages[topic, node])}" if (topic, node) in ages else ""
        label = "  ".join(x for x in (_flow(rate, got), age) if x)
        lines.append(f"  {quote('topic:' + topic)} -> {quote('node:' + node)} "
                     f"{_attrs(label=label, penwidth=_penwidth(got))};")
    for c in sorted(direct, key=lambda c: (c.topic, c.publisher, c.subscriber)):
        got = rates.get((join.EDGE_RECEIVED_BYTES.name, (c.topic, c.publisher, c.subscriber)))
        label = "  ".join(x for x in (c.topic, _flow(None, got)) if x)
        lines.append(f"  {quote('node:' + c.publisher)} -> {quote('node:' + c.subscriber)} "
                     f"{_attrs(label=label, penwidth=_penwidth(got))};")
    for c in sorted(apart, key=lambda c: (c.topic, c.publisher, c.subscriber)):
        label = f"{c.topic}: QoS {', '.join(c.incompatible())} incompatible"
        lines.append(f"  {quote('node:' + c.publisher)} -> {quote('node:' + c.subscriber)} "
                     f"{_attrs(label=label, style='dashed', color='#cc0000', fontcolor='#cc0000')};")
    lines.append("}")
    return "\n".join(lines) + "\n"


def svg(dot_text: str) -> str:
    """The DOT picture laid out and drawn by Graphviz."""
    try:
        done = subprocess.run(["dot", "-Tsvg"], input=dot_text, capture_output=True, text=True, timeout=DOT_TIMEOUT)
    except FileNotFoundError:
        raise UsageError("svg needs Graphviz's dot (Debian/Ubuntu: apt-get install graphviz)") from None
    except subprocess.TimeoutExpired:
        raise UsageError(f"Graphviz took over {DOT_TIMEOUT} s to draw the graph") from None
    if done.returncode != 0:
        raise UsageError(f"Graphviz could not draw the graph: {done.stderr.strip()[:300]}")
    return done.stdout

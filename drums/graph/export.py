"""The graph as text for people and files: a readable listing, JSON and GraphML, and as a
picture (DOT and SVG, drums.graph.draw).

Vertex and edge attributes are the entity's fields and, where given, the joined metrics of an
agent's snapshot; GraphML takes only scalars, so it gets nested values as JSON strings.
"""
from __future__ import annotations

import json
from collections import defaultdict
from dataclasses import asdict
from typing import TYPE_CHECKING

from drums import units
from drums.errors import UsageError
from drums.graph import FORMATS, draw, join, paths
from drums.graph.model import Graph
from drums.metrics import INFO, Histogram, Snapshot

if TYPE_CHECKING:  # the graph modules load networkx only when a graph is made (model.snapshot)
    import networkx as nx

PICTURES = ("dot", "svg")
CONTENT_TYPES = {"text": "text/plain; charset=utf-8", "json": "application/json",
                 "dot": "text/vnd.graphviz", "svg": "image/svg+xml", "graphml": "application/graphml+xml"}


def document(graph: Graph, snap: Snapshot, fmt: str, everything: bool = False,
             rates: draw.Rates | None = None) -> tuple[bytes, str]:
    """The live graph with an agent's snapshot on it, as (body, content type): the agent's /graph.
    `rates` remembers the counters of the last picture, to label its arrows with rates."""
    if fmt not in FORMATS:
        raise UsageError(f"format {fmt!r}: one of {', '.join(FORMATS)}")
    if fmt in PICTURES:
        text = draw.dot(graph.snapshot(), snap, rates.update(snap) if rates else {}, everything)
        return (draw.svg(text) if fmt == "svg" else text).encode(), CONTENT_TYPES[fmt]
    return render(graph.snapshot(), fmt, graph_metrics(snap), stale=graph.error,
                  chains=paths.paths(snap)).encode(), CONTENT_TYPES[fmt]


def graph_metrics(snap: Snapshot) -> dict:
    """The joined metrics of `snap` as attributes: node metrics on the node's vertex, edge metrics
    on the connection, topic metrics on the topic's vertex by node ({node: value}: the labels the
    kernel data has, nothing split or guessed). Names lose their `drums_<scope>_` prefix."""
    attrs: dict = defaultdict(dict)
    for metric in join.METRICS:
        if metric.kind == INFO:
            continue  # the node's own fields already say it
        name = metric.name.split("_", 2)[2]
        for labels, value in snap.series.get(metric, ()):
            if isinstance(value, Histogram):
                value = {"count": value.count, "sum": value.sum}
            if metric.labels[:3] == join.EDGE:
                attrs[f"node:{labels[1]}", f"node:{labels[2]}", labels[0]][name] = value
            elif metric.labels[:2] == join.TOPIC:
                attrs[f"topic:{labels[0]}"].setdefault(name, {})[labels[1]] = value
            elif len(labels) > 2:  # a reaction, by its input and output topics
                attrs[f"node:{labels[0]}"].setdefault(name, {})[f"{labels[1]} -> {labels[2]}"] = value
            elif len(labels) > 1:  # by kind of context switch
                attrs[f"node:{labels[0]}"].setdefault(name, {})[labels[1]] = value
            else:
                attrs[f"node:{labels[0]}"][name] = value
    return dict(attrs)


def _attributes(data: dict, metrics: dict, flat: bool) -> dict:
    out = {"kind": data["kind"]}
    entity = data.get("entity")
    fields = asdict(entity) if hasattr(entity, "__dataclass_fields__") else {}
    for k, v in {**fields, **metrics}.items():
        if v is None:
            continue  # GraphML and DOT have no null
        out[k] = json.dumps(v, sort_keys=True) if flat and isinstance(v, (dict, list, tuple)) else v
    return out


def plain(g: nx.MultiDiGraph, metrics: dict | None = None, flat: bool = False) -> nx.MultiDiGraph:
    """A copy whose attributes are plain values; `metrics` maps a vertex id or an edge
    (u, v, key) to extra attributes."""
    import networkx as nx
    metrics = metrics or {}
    out = nx.MultiDiGraph()
    for vid, data in g.nodes(data=True):
        out.add_node(vid, **_attributes(data, metrics.get(vid, {}), flat))
    for u, v, key, data in g.edges(keys=True, data=True):
        attrs = _attributes(data, metrics.get((u, v, key), {}), flat) if data["kind"] == "connection" \
            else {"kind": data["kind"]}
        out.add_edge(u, v, key=key, **attrs)
    return out


def render(g: nx.MultiDiGraph, fmt: str, metrics: dict | None = None, stale: str = "",
           everything: bool = False, chains: tuple[list[dict], bool] = ([], False)) -> str:
    """The graph in a format; `metrics` from graph_metrics(), `chains` from paths.paths(); pictures
    leave out the topics and nodes of the plumbing unless `everything`."""
    if fmt in PICTURES:
        text = draw.dot(g, everything=everything)
        return draw.svg(text) if fmt == "svg" else text
    import networkx as nx
    if fmt == "json":
        data = nx.node_link_data(plain(g, metrics), edges="edges")
        data["stale"] = stale
        data["paths"], data["paths_truncated"] = chains
        return json.dumps(data, indent=1, sort_keys=True) + "\n"
    if fmt == "graphml":
        flat = plain(g, metrics, flat=True)
        flat.graph.update(paths=json.dumps(chains[0], sort_keys=True), paths_truncated=chains[1])
        return "\n".join(nx.generate_graphml(flat)) + "\n"
    return _text(g, metrics or {}, stale) + _paths(*chains)


def _text(g: nx.MultiDiGraph, metrics: dict, stale: str) -> str:
    """Hosts, their processes and nodes, then each topic with its publishers and subscribers."""
    def of(kind):
        return sorted((vid, d["entity"]) for vid, d in g.nodes(data=True) if d["kind"] == kind)

    lines = [f"(stale: {stale})"] if stale else []
    nodes = of("node")
    for vid, host in of("host"):
        where = ", ".join(f"{k} {v}" for k, v in (("address", host.address), ("agent", host.agent)) if v)
        lines.append(f"host {host.name} ({where})" if where else f"host {host.name}")
        for _, p in [(v, e) for v, e in of("process") if e.host == host.name]:
            lines.append(f"  process {p.pid} {p.name}")
            for vid, n in [(v, e) for v, e in nodes if e.pid == p.pid and e.host == host.name]:
                lines.append(f"    node {n.name} (mapped by {n.mapped_by}){_values(metrics.get(vid, {}))}")
    unplaced = [n for _, n in nodes if n.pid is None]
    if unplaced:
        lines.append("nodes without a local process")
        lines.extend(f"  node {n.name} ({n.mapped_by})" for n in unplaced)
    topics = {t.name: t for _, t in of("topic")}
    by_key: dict[str, list] = {}
    for u, v, key, d in sorted(g.edges(keys=True, data=True)):
        if d["kind"] == "connection":
            by_key.setdefault(key, []).append((d["entity"], metrics.get((u, v, key), {})))
    for key in sorted(topics.keys() | by_key.keys()):
        t = topics.get(key)
        lines.append(f"topic {key} [{', '.join(t.types)}]" if t else f"connections {key}")
        by_node: dict[str, dict] = defaultdict(dict)  # {metric: {node: value}} turned around
        for name, values in metrics.get(f"topic:{key}", {}).items():
            for node, value in values.items():
                by_node[node][name] = value
        lines.extend(f"  {node}:{_values(by_node[node])}" for node in sorted(by_node))
        for c, values in by_key.get(key, []):
            qos = "" if c.qos_check in ("", "ok") else f" QoS: {c.qos_check}"
            lines.append(f"  {c.publisher} -> {c.subscriber}{_values(values)}{qos}")
    return "\n".join(lines) + "\n"


def _paths(found: list[dict], truncated: bool) -> str:
    """A line per path, its time and then each part's."""
    if not found:
        return ""
    lines = [f"paths: mean time since the agent started, the sum of its parts'{' (the slowest)' if truncated else ''}"]
    for path in found:
        hops = "".join(f" -[{topic}]-> {node}" for topic, node in zip(path["topics"], path["nodes"][1:]))
        parts = " + ".join(f"{units.duration(p['seconds'])} {'age' if 'edge' in p else 'reaction'}"
                           for p in path["parts"])
        lines.append(f"  {path['nodes'][0]}{hops}: {units.duration(path['seconds'])} = {parts}")
    return "\n".join(lines) + "\n"


def _values(values: dict) -> str:
    return "".join(f" {k}={json.dumps(v, sort_keys=True) if isinstance(v, dict) else v}"
                   for k, v in sorted(values.items()))

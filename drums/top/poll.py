"""One look at one agent: its graph (/graph?format=json, with the node, topic and edge counters
joined on it) and the /metrics families the graph does not carry, each with the time it was read.

Parsed here, in the thread that fetched it, so that the screen only does arithmetic.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field

from drums.client import Agent, AgentError
from drums import exposition

# From /metrics: processes (those without a node too), sockets, and the run-queue and publish
# period histograms (the graph carries a histogram's count and sum only, and a percentile needs
# its buckets).
METRICS = (
    "drums_process_cpu_seconds_total", "drums_process_resident_memory_bytes",
    "drums_process_socket_sent_bytes_total", "drums_process_socket_received_bytes_total",
    "drums_process_runqueue_latency_seconds_bucket", "drums_node_runqueue_latency_seconds_bucket",
    "drums_socket_sent_bytes_total", "drums_socket_received_bytes_total",
    "drums_tcp_connection_smoothed_rtt_seconds", "drums_topic_publish_period_seconds_bucket",
)


@dataclass
class Poll:
    graph_at: float  # Unix time when the agent read the graph's counters
    metrics_at: float  # and when /metrics was
    stale: str = ""  # why the agent's graph is stale ("" when it is current)
    hosts: dict[str, dict] = field(default_factory=dict)  # name -> vertex attributes
    processes: dict[int, dict] = field(default_factory=dict)  # pid -> vertex
    nodes: dict[str, dict] = field(default_factory=dict)  # node name -> vertex (with its counters)
    topics: dict[str, dict] = field(default_factory=dict)  # topic name -> vertex (counters by node)
    endpoints: list[dict] = field(default_factory=list)
    edges: dict[tuple[str, str, str], dict] = field(default_factory=dict)  # (topic, pub, sub) -> attributes
    metrics: dict[str, exposition.Rows] = field(default_factory=dict)


def graph_poll(graph: dict, graph_at: float, metrics_text: str, metrics_at: float) -> Poll:
    """A Poll from the agent's answers; a graph that is not node-link JSON is an AgentError."""
    poll = Poll(graph_at, metrics_at, str(graph.get("stale") or ""))
    endpoints = {}
    for v in graph["nodes"]:
        kind = v.get("kind")
        if kind == "host":
            poll.hosts[v["name"]] = v
        elif kind == "process":
            poll.processes[v["pid"]] = v
        elif kind == "node":
            poll.nodes[v["name"]] = v
        elif kind == "topic":
            poll.topics[v["name"]] = v
        elif kind in ("publisher", "subscriber"):  # an endpoint: its own kind replaced the vertex's
            endpoints[v["id"]] = v
    poll.endpoints = list(endpoints.values())
    for e in graph["edges"]:
        if e.get("kind") == "connection":
            poll.edges[e["topic"], e["publisher"], e["subscriber"]] = e
    poll.metrics = exposition.rows(metrics_text, METRICS)
    return poll


def fetch(agent: Agent) -> Poll:
    text, graph_at = agent.read("/graph?format=json")
    metrics, metrics_at = agent.read("/metrics")
    try:
        return graph_poll(json.loads(text), graph_at, metrics, metrics_at)
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise AgentError(f"{agent.url}: /graph is not the graph in JSON ({e!r})") from None

"""End-to-end paths through the graph, and how long a message takes along each: the live form of
what CARET computes offline as path latency.

A path is a chain of measured parts: a message's age when the next node takes it (an edge:
publisher -> subscriber on a topic), that node's reaction (its take on the topic to its publish on
another), the age on the next edge, and so on, until a node that does not react. It starts at a
publisher that reacts to nothing (a camera's timer, a driver). Only parts that counted messages
make a path, so a path is one that data really takes.

A path's time is the sum of the means of its parts since the agent started: the mean time from the
first publish to the last take, as means add up (a sum of medians would be no median). Each part
keeps its count and sum, so a reader that looks twice gets the means between its looks.
"""
from __future__ import annotations

from collections import defaultdict

from drums.graph import join
from drums.graph.draw import HIDDEN_TOPICS, OWN_PREFIX
from drums.metrics import Snapshot

MAX_PATHS = 100  # the slowest are kept
MAX_STEPS = 10_000  # parts tried in all: a dense graph has more chains than anyone reads
MAX_NODES = 64  # a path is cut there


def _part(kind: str, labels: tuple[str, ...], hist) -> dict:
    return {kind: list(labels), "count": hist.count, "sum": hist.sum, "seconds": hist.sum / hist.count}


def paths(snap: Snapshot) -> tuple[list[dict], bool]:
    """(the paths that `snap`'s joined timings make, slowest first; whether some were left out)."""
    def plumbing(topic: str, *nodes: str) -> bool:
        return topic in HIDDEN_TOPICS or any(n.startswith(OWN_PREFIX) for n in nodes)

    takes: dict[tuple[str, str], list] = defaultdict(list)  # (publisher, topic) -> [(subscriber, part)]
    for (topic, publisher, subscriber), hist in snap.of(join.EDGE_AGE):
        if hist.count and publisher != subscriber and not plumbing(topic, publisher, subscriber):
            takes[publisher, topic].append((subscriber, _part("edge", (topic, publisher, subscriber), hist)))
    reacts: dict[tuple[str, str], list] = defaultdict(list)  # (node, input) -> [(output, part)]
    reacting: set[tuple[str, str]] = set()  # (node, output): a path through it starts further back
    for (node, taken, published), hist in snap.of(join.NODE_REACTION):
        if hist.count and not plumbing(taken, node) and not plumbing(published):
            reacts[node, taken].append((published, _part("reaction", (node, taken, published), hist)))
            reacting.add((node, published))
    found: list[dict] = []
    steps = 0

    def follow(node: str, topic: str, parts: list[dict], nodes: list[str], topics: list[str]) -> None:
        nonlocal steps
        for subscriber, edge in takes.get((node, topic), ()):
            if subscriber in nodes or steps >= MAX_STEPS:
                continue  # a loop closes here; or enough tried
            steps += 1
            here = parts + [edge]
            onward = [(out, r) for out, r in reacts.get((subscriber, topic), ())
                      if (subscriber, out) in takes and len(nodes) < MAX_NODES]
            if not onward and len(here) > 1:
                found.append({"nodes": nodes + [subscriber], "topics": topics, "parts": here,
                              "seconds": sum(p["seconds"] for p in here)})
            for out, reaction in onward:
                follow(subscriber, out, here + [reaction], nodes + [subscriber], topics + [out])

    for publisher, topic in sorted(takes.keys() - reacting):
        follow(publisher, topic, [], [publisher], [topic])
    found.sort(key=lambda p: -p["seconds"])
    return found[:MAX_PATHS], steps >= MAX_STEPS or len(found) > MAX_PATHS

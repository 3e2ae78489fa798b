"""Messages lost on a topic, counted from when top first saw its subscribers take one: what its
publishers published to the subscribers they are connected to, minus what those took.

Both ends are read in one collect where they share an agent, yet a message is in flight between
its publish and its take (milliseconds, more on a busy host), so the difference alone says "1
lost" now and then. A message is counted lost once it has been missing at READS reads in a row;
a difference that goes below zero says a message was in flight at the first read, and moves the
starting point instead.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

READS = 3


@dataclass
class _Since:
    links: frozenset  # the (publisher, subscriber) pairs counted: another set starts again
    expected: float
    taken: float
    missing: deque = field(default_factory=lambda: deque(maxlen=READS))  # at the last reads
    read: object = None  # which read of the counters was the last one counted


class Losses:
    def __init__(self):
        self._since: dict[str, _Since] = {}

    def lost(self, topic: str, read: object, links: list[tuple[str, str]], published: dict[str, float],
             taken: dict[str, float]) -> float | None:
        """Messages lost on `topic` so far, or None where no end is measured. `read` names the
        read of the counters (the same read asked again counts once); `links` are the topic's
        connections; `published` and `taken` the counters of its nodes (by node)."""
        links = [(p, s) for p, s in links if p in published and s in taken]
        if not links:
            self._since.pop(topic, None)
            return None
        expected = sum(published[p] for p, _ in links)
        took = sum(taken[s] for s in {s for _, s in links})
        since = self._since.get(topic)
        pairs = frozenset(links)
        if since is None or since.links != pairs or expected < since.expected or took < since.taken:
            if took == 0:
                return None  # nothing delivered yet: messages sent before the match are not losses
            since = self._since[topic] = _Since(pairs, expected, took)
        if read != since.read:
            since.read = read
            missing = (expected - since.expected) - (took - since.taken)
            if missing < 0:  # in flight at the first read, taken since
                since.taken -= missing
                missing = 0
            since.missing.append(missing)
        return min(since.missing)

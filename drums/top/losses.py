"""Messages lost on a topic, counted from when top first saw its subscribers take one: what its
publishers published to the subscribers they are connected to, minus what those took.

The counters of both ends are read in one collect where they share an agent: a message still in
flight at that instant (about a millisecond of a 100 ms period) counts until it arrives.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class _Since:
    links: frozenset  # the (publisher, subscriber) pairs counted: another set starts again
    expected: float
    taken: float


class Losses:
    def __init__(self):
        self._since: dict[str, _Since] = {}

    def lost(self, topic: str, links: list[tuple[str, str]], published: dict[str, float],
             taken: dict[str, float]) -> float | None:
        """Messages lost on `topic` so far, or None where an end is not measured. `links` are its
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
        return max(0.0, (expected - since.expected) - (took - since.taken))

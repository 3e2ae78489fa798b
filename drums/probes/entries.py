"""A BPF hash map's entries as sorted numpy arrays, matched in bulk against the previous read.

Of ten thousand sockets most sit idle between two scrapes: the map is read whole (one batch
call), and which entries are new, changed or the same is found with array operations, so the
probe does per-entry Python work only for the few that changed, and reuses what it made of the
others last time (their rows, in an object array beside the keys).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Matched:
    """One read of the map, sorted by key, beside the previous read."""

    keys: np.ndarray  # (n,) uint64
    words: np.ndarray  # (n, value size / 8) uint64: each value as 8-byte little-endian words
    same_head: np.ndarray  # (n,) bool: the key was in the previous read with the same head (what
    # names the entry): the same thing, counted on
    same: np.ndarray  # (n,) bool: ... with the very same value
    rows: np.ndarray  # (n,) object: what the caller kept for the key at the previous read (None if new)


class Entries:
    """The entries of a map with 8-byte keys and values a multiple of 8 bytes long, whose first
    `head` bytes say what the entry is (a key the kernel reuses names a new thing) and the rest
    what it counted."""

    def __init__(self, value_size: int, head: int):
        if value_size % 8 or head % 8:
            raise ValueError(f"values of {value_size} bytes, heads of {head}: not whole 8-byte words")
        self.width, self.head = value_size // 8, head // 8
        self._keys = np.empty(0, np.uint64)
        self._words = np.empty((0, self.width), np.uint64)
        self._rows = np.empty(0, object)
        self._read_keys = np.empty(0, np.uint64)  # the keys as the last read returned them, and
        self._order = np.empty(0, np.intp)  # the order that sorted them: a map that did not change
        # hands its keys back in the same order, and sorting ten thousand is then skipped

    def read(self, keys: bytes, values: bytes) -> Matched:
        k = np.frombuffer(keys, np.uint64)
        w = np.frombuffer(values, np.uint64).reshape(len(k), self.width)
        if not np.array_equal(k, self._read_keys):
            self._read_keys, self._order = k, np.argsort(k)
        k, w = k[self._order], w[self._order]
        rows = np.full(len(k), None, object)
        if not len(self._keys):
            new = np.zeros(len(k), bool)
            return Matched(k, w, new, new, rows)
        at = np.minimum(np.searchsorted(self._keys, k), len(self._keys) - 1)
        known = self._keys[at] == k
        equal = self._words[at] == w
        same_head = known & equal[:, :self.head].all(axis=1)
        same = same_head & equal[:, self.head:].all(axis=1)
        rows[known] = self._rows[at[known]]
        return Matched(k, w, same_head, same, rows)

    def keep(self, matched: Matched, mask: np.ndarray) -> None:
        """What the next read is matched against: the entries of `matched` under `mask`, with the
        rows the caller put in matched.rows."""
        self._keys, self._words, self._rows = matched.keys[mask], matched.words[mask], matched.rows[mask]

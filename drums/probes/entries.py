"""A BPF hash map's entries as sorted numpy arrays, matched in bulk against the previous read.

Of ten thousand sockets most sit idle between two scrapes: the map is read whole (one batch
call), and which entries are new, changed or the same is found with array operations, so the
probe does per-entry Python work only for the few that changed, and reuses what it made of the
others last time (their rows, in an object array beside the keys).
"""
from __future__ import annotations

import struct
from collections.abc import Callable, Hashable
from dataclasses import dataclass

import numpy as np

from drums.arrays import within
from drums.kernel.bpffs import LRU_TYPES, PinnedMap


@dataclass
class Matched:
    """One read of the map, sorted by key, beside the previous read."""

    keys: np.ndarray  # (n,) uint64
    words: np.ndarray  # (n, value size / 8) uint64: each value as 8-byte little-endian words
    same_head: np.ndarray  # (n,) bool: the key was in the previous read with the same head (what
    # names the entry): the same thing, counted on
    same: np.ndarray  # (n,) bool: ... with the very same value
    rows: np.ndarray  # (n,) object: what the caller kept for the key at the previous read (None if new)
    gone: np.ndarray  # object: what the caller kept for the keys of the previous read that are gone
    grown: np.ndarray  # (g,) intp: the entries counted on (same head, another value), ascending
    before: np.ndarray  # (g, width) uint64: their values at the previous read
    since: int | None = None  # the read `same` is told against (the one kept), None: against none
    mark: int = 0  # this read

    def told(self) -> tuple[int, int, np.ndarray] | None:
        """Columns.told of columns of these entries' values, in their order."""
        return None if self.since is None else (self.since, self.mark, np.flatnonzero(~self.same))


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
        # Whether the caller kept the last read (keep()). One that failed between the two may have
        # left values written in place (update) beside rows that do not show them: the next read
        # must be of the whole map, and makes every row anew.
        self.kept = True
        self._reads = 0
        self._kept_read = 0  # the read kept last (0: none yet, the entries empty)

    def read(self, keys: bytes, values: bytes) -> Matched:
        since = self._next_read()
        if since is None:
            self._keys, self._words, self._rows = self._keys[:0], self._words[:0], self._rows[:0]
        k = np.frombuffer(keys, np.uint64)
        w = np.frombuffer(values, np.uint64).reshape(len(k), self.width)
        if not np.array_equal(k, self._read_keys):
            self._read_keys, self._order = k, np.argsort(k)
        k, w = k[self._order], w[self._order]
        rows = np.full(len(k), None, object)
        if not len(self._keys):
            new = np.zeros(len(k), bool)
            return Matched(k, w, new, new, rows, self._rows, np.empty(0, np.intp), self._words[:0], since, self._reads)
        at = np.minimum(np.searchsorted(self._keys, k), len(self._keys) - 1)
        known = self._keys[at] == k
        head, value = self._compare(self._words[at], w)
        same_head = known & head
        same = same_head & value
        rows[known] = self._rows[at[known]]
        grown = np.flatnonzero(same_head & ~same)
        return Matched(k, w, same_head, same, rows, self._rows[~within(self._keys, k)], grown,
                       self._words[at[grown]], since, self._reads)

    def update(self, changes: list[tuple[bytes, bytes | None]]) -> Matched:
        """The entries of the last read (as kept) with these changes: a key's value, or None if the
        key is gone; each key at most once. Matched as read() matches a whole map, at the cost of
        the changes: values are written in place, and the arrays are copied only when keys come
        or go. Only after a read that was kept."""
        since = self._next_read()
        if since is None:
            raise ValueError("the last read was not kept: read the whole map")
        keys, words, rows = self._keys, self._words, self._rows
        changed = np.frombuffer(b"".join(k for k, _ in changes), np.uint64)
        present = np.fromiter((v is not None for _, v in changes), bool, len(changes))
        values = np.frombuffer(b"".join(v for _, v in changes if v is not None), np.uint64).reshape(-1, self.width)
        at = np.searchsorted(keys, changed)
        known = np.zeros(len(changed), bool)
        inside = at < len(keys)
        known[inside] = keys[at[inside]] == changed[inside]
        same_head, same = np.ones(len(keys), bool), np.ones(len(keys), bool)
        counted = known & present  # a key of the last read, with a value now: compared, then written
        grown_keys, before = keys[:0], words[:0]
        if counted.any():
            pos, now = at[counted], values[counted[present]]
            same_head[pos], same[pos] = self._compare(words[pos], now)
            on = pos[same_head[pos] & ~same[pos]]
            grown_keys, before = keys[on], words[on]  # copies (fancy indexing), made before the writes
            words[pos] = now
        ended, new = known & ~present, ~known & present
        gone = rows[at[ended]]
        if ended.any():
            stays = np.ones(len(keys), bool)
            stays[at[ended]] = False
            keys, words, rows, same_head, same = (a[stays] for a in (keys, words, rows, same_head, same))
        if new.any():
            order = np.argsort(changed[new])
            new_keys, new_words = changed[new][order], values[new[present]][order]
            pos = np.searchsorted(keys, new_keys)
            keys, words = np.insert(keys, pos, new_keys), np.insert(words, pos, new_words, axis=0)
            rows = np.insert(rows, pos, None)
            same_head, same = np.insert(same_head, pos, False), np.insert(same, pos, False)
        order = np.argsort(grown_keys)  # as the changes came: ascending, as the entries are
        return Matched(keys, words, same_head, same, rows, gone, np.searchsorted(keys, grown_keys[order]),
                       before[order], since, self._reads)

    def _next_read(self) -> int | None:
        """Count a read in: the read it is matched against (the last, kept), None if that was not kept."""
        since = self._kept_read if self.kept else None
        self.kept, self._reads = False, self._reads + 1
        return since

    def _compare(self, old: np.ndarray, new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per entry: whether the head is the same, and whether the whole value is."""
        equal = old == new
        head = equal[:, :self.head].all(axis=1)
        return head, head & equal[:, self.head:].all(axis=1)

    def __len__(self) -> int:
        return len(self._keys)

    def keep(self, matched: Matched, mask: np.ndarray) -> None:
        """What the next read is matched against: the entries of `matched` under `mask`, with the
        rows the caller put in matched.rows."""
        self.kept, self._kept_read = True, matched.mark
        if mask.all():  # as a rule: no copies
            self._keys, self._words, self._rows = matched.keys, matched.words, matched.rows
        else:
            self._keys, self._words, self._rows = matched.keys[mask], matched.words[mask], matched.rows[mask]


class Remembered:
    """What a probe made for some of its entries at its last collect (their label values), taken
    again at this one for a key whose source (a process's name, a thread's) is the same: of ten
    thousand entries, the budget asks for the hundred it keeps at every scrape, and few changed."""

    def __init__(self):
        self.known: dict = {}  # key -> (source, what was made): the last collect's
        self.made: dict = {}  # and this one's

    def turn(self) -> "Remembered":
        """A new collect: what the last one made is what this one may take again."""
        self.known, self.made = self.made, {}
        return self

    def get(self, key: Hashable, source: Hashable, make: Callable[[], tuple]) -> tuple:
        was = self.made.get(key) or self.known.get(key)
        if was is None or was[0] != source:
            was = source, make()
        self.made[key] = was
        return was[1]


_GENERATION = struct.Struct("<QQ")  # a `generation` array's two entries: the generation, marks lost
_FIRST = struct.pack("<I", 0)


class Marked:
    """A BPF hash map read whole only when much of it changed. Its programs mark each key they
    count into or delete, once per generation, in one of two sets (by the generation's parity);
    a read moves the generation on, takes the set of the one before and looks up those keys only
    (a lookup costs about four times what an entry of a whole read does, so past an eighth of the
    entries the map is read whole: `whole_above`). Ten thousand idle sockets cost a scrape three
    small calls. An LRU map evicts its oldest entries, unmarked, to make room once it is nearly
    full: past half full it is read whole."""

    def __init__(self, entries: PinnedMap, generation: PinnedMap, marks: tuple[PinnedMap, PinnedMap],
                 whole_above: int = 8):
        self.map, self._generation, self._marks = entries, generation, marks
        self.whole_above = whole_above  # read whole when more than 1/whole_above of the entries were marked
        self._gen = self._lost = -1
        self.whole_reads = 0

    def read(self, known: int, whole: bool = False) -> tuple[bytes, bytes, int] | list[tuple[bytes, bytes | None]]:
        """The whole map, as PinnedMap.read gives it; or, to a caller who holds the `known`
        entries of the last read, what changed since: (key, its value, None if it is gone).
        `whole`: the caller does not hold them (its last collect failed, after the marks were taken)."""
        keys = self.changed(known, whole)
        if keys is None:
            return self.map.read()
        return [(key, self.map.lookup(key)) for key in keys]

    def changed(self, known: int, whole: bool = False) -> list[bytes] | None:
        """The keys marked since the last call, to be looked up; None where the map is to be read
        whole (as read() says when)."""
        gen, lost = _GENERATION.unpack_from(self._generation.read()[1])
        self._generation.update(_FIRST, struct.pack("<Q", gen + 1))
        marked, _, n = self._marks[gen & 1].read(delete=True)
        # Whole: when asked, at first, when marks were lost to a full set, or when the generation is
        # not the one this reader left (another reader of the pins moved it).
        whole = (whole or (gen, lost) != (self._gen, self._lost) or n * self.whole_above > max(known, 64)
                 or (self.map.type in LRU_TYPES and 2 * known > self.map.max_entries))
        self._gen, self._lost = gen + 1, lost
        if whole:
            self.whole_reads += 1
            return None
        size = self._marks[0].key_size
        return [marked[i * size:(i + 1) * size] for i in range(n)]

"""The cardinality budget: own series for the most active processes, threads, sockets and TCP
connections; everything else summed into one `other` series per metric.

An entity that gets its own series keeps it while it lives (series that flap in and out confuse
rate()), unless a folded one becomes more than twice as active. A counter's `other` never goes
backwards: it is kept as a running total that each folded row adds its growth to, so a row that
leaves it (its entity ended, or got its own series) leaves what it added.

A counter's series counts from zero, as Prometheus' increase() counts a new series: what an entity
counted before its series began is in `other`, and a series that ends (its entity lost its slot)
shows what it counted until then while `other` goes on from there. So the sum of a counter's
series, `other`'s and those of entities that ended included, is what the entities counted.

The budget remembers each row between collects and does per-row work only for rows that changed:
on an idle host with ten thousand processes' rows a collect is a few dict and set operations. A
probe that tells its rows as changes to those of its last collect (Snapshot.changes) spares it even
comparing them. Groups given as Columns (the sockets, the TCP connections, the threads) are ranked
and summed as arrays, and label values are asked for only for the rows kept (and of those, where
the probe stamps what they are made from, only for the rows that changed): ten thousand sockets
hold no Python object each.
"""
from __future__ import annotations

import heapq
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from itertools import islice
from operator import itemgetter

import numpy as np

from drums.arrays import distinct, rows_differ, within
from drums.metrics import COUNTER, HISTOGRAM, Changes, Columns, Histogram, Metric, Snapshot, shown

# Labels that split an entity's series (they survive folding); every other label names the entity.
DIMENSIONS = {"protocol", "kind"}
OTHER = "other"

# Entity kinds: the labels that identify one, and the counters that rank them by activity.
KINDS = {
    "socket": (("inode",), ("drums_socket_sent_bytes_total", "drums_socket_received_bytes_total")),
    "thread": (("pid", "tid"), ("drums_thread_cpu_seconds_total",)),
    "process": (("pid",), ("drums_process_cpu_seconds_total", "drums_process_socket_sent_bytes_total",
                           "drums_process_socket_received_bytes_total")),
    "connection": (("local", "remote"), ("drums_tcp_connection_retransmits_total",
                                         "drums_tcp_connection_state_changes_total")),
}


_LABELS = itemgetter(0)  # of a (labels, values) row


def _entity_getter(labels: tuple[str, ...], kind: str) -> Callable[[tuple], object]:
    """What gives, from a row's label values, the entity of `kind` it is of."""
    return itemgetter(*[labels.index(label) for label in KINDS[kind][0]])


def kind_of(metric: Metric) -> str | None:
    for kind, (ident, _) in KINDS.items():
        if all(label in metric.labels for label in ident):
            return kind
    return None


def _went_back(new, old) -> bool:
    """Whether a counter went back: its labels now name a new entity, such as a reused PID."""
    return new.count < old.count if isinstance(new, Histogram) else new < old


def _growth(new, old):
    """How much a counter grew since `old`: all of it when it went back, so `other` only ever grows."""
    return new if old is None or _went_back(new, old) else new - old


def _change(new, old):
    """How much a gauge changed since `old`."""
    return new if old is None else new - old


class _Group:
    """What the budget remembers of one group of metrics (metrics sharing their labels) between
    collects, so that each collect does per-row work only for the rows that changed."""

    def __init__(self, metrics: tuple[Metric, ...], kind: str, single: bool):
        """`single`: the rows of one metric added alone, which carry a value, not a tuple of them."""
        rank_names = KINDS[kind][1]
        self.single = single
        labels = metrics[0].labels
        self.metrics = metrics
        self.entity_of = _entity_getter(labels, kind)
        self.dims = [i for i, label in enumerate(labels) if label in DIMENSIONS]
        self.additive = all(m.additive for m in metrics)
        self.counters = all(m.kind in (COUNTER, HISTOGRAM) for m in metrics)
        self.step = _growth if self.counters else _change
        self.rank = [(i, m.name) for i, m in enumerate(metrics) if m.name in rank_names]
        self.last: dict = {}  # labels -> values at the last collect
        # entity -> the labels of its one row, or a set of those of its rows when it has more: ten
        # thousand sockets of one row each, without ten thousand sets (6 MB)
        self._rows_of: dict = {}
        self.folded: dict = {}  # labels -> the values of that row summed into `other` so far
        # Counters that add up count from zero in a series of their own, what they counted before being
        # in `other`: labels of a kept row -> its values (a tuple) when its series began
        self.rebased = self.counters and self.additive
        self.base: dict = {}
        self.resume: dict = {}  # labels of a row whose series ended while it lives -> what it showed last
        self.before: dict = {}  # labels of the rows changed at this collect -> their values at the last
        self._other: dict = {}  # dimension values -> (metrics, labels of the `other` row)
        self._changed: list = []  # rows new or changed at this collect, as they came
        self._gone: set = set()  # and labels of rows gone
        self.came: list = []  # entities that got their first row in the group at this collect
        self.left: list = []  # and those that lost their last
        self._emitted: dict = {}  # labels -> row as it came: the rows emit() gave last, and for which entities
        self._emitted_for: set | None = None
        self.mark: int | None = None  # the probe's collect whose rows `last` holds, if it said

    def other_key(self, labels: tuple) -> tuple:
        dimvals = tuple([labels[i] for i in self.dims])
        key = self._other.get(dimvals)
        if key is None:
            template = [OTHER] * len(labels)
            for i, v in zip(self.dims, dimvals):
                template[i] = v
            key = self._other[dimvals] = (self.metrics, tuple(template))
        return key

    def update(self, rows: list, grew: dict, told: Changes | None = None) -> tuple[list, set]:
        """Take this collect's rows: (rows that are new or changed, labels of rows that are gone).
        What each entity's ranking counters grew by is added to grew[metric name][entity]. `told`:
        the same rows as changes, applied when they follow the collect `last` holds."""
        last, entity_of = self.last, self.entity_of
        if told is not None and told.since == self.mark:
            now = None  # `last` is brought up to date in place below, once it has served as the old values
            told_rows = dict(told.rows)  # `rows` (all of them) go unread
            changed = [(labels, values) for labels, values in told_rows.items()
                       if (was := last.get(labels)) is not values and was != values]
            gone = {labels for labels in told.gone if labels in last}.difference(told_rows)
        else:
            now = dict(rows)
            # An idle entity's row is often the very tuple of the last collect: `is` settles it.
            changed = [(labels, values) for labels, values in now.items()
                       if (was := last.get(labels)) is not values and was != values]
            gone = last.keys() - now.keys()
        self.mark = told.mark if told is not None else None
        came_as = self._changed = changed  # as they came: a single metric's value, a group's tuple
        self.before = {labels: last.get(labels) for labels, _ in changed} if self.rebased else {}
        self._gone = gone
        if self.single:
            changed = [(labels, (value,)) for labels, value in changed]
        for i, name in self.rank:
            into = grew.setdefault(name, {})
            for labels, values in changed:
                old = self.values(labels, last)
                d = values[i] - (old[i] if old is not None else 0)
                if d > 0:
                    entity = entity_of(labels)
                    into[entity] = into.get(entity, 0.0) + d
        rows_of = self._rows_of
        came, left = self.came, self.left = [], []
        for labels in gone:
            entity = entity_of(labels)
            held = rows_of[entity]
            if type(held) is not set:
                del rows_of[entity]
                left.append(entity)
            else:
                held.discard(labels)
                if len(held) == 1:
                    rows_of[entity] = next(iter(held))
        for labels, _ in changed:
            if labels not in last:
                entity = entity_of(labels)
                held = rows_of.get(entity)
                if held is None:
                    rows_of[entity] = labels
                    came.append(entity)
                elif type(held) is set:
                    held.add(labels)
                else:
                    rows_of[entity] = {held, labels}
        if now is None:
            for labels in gone:
                del last[labels]
            last.update(came_as)
        else:
            self.last = now
        return changed, gone

    def rows_of(self, entity) -> tuple | set:
        """The labels of the entity's rows."""
        held = self._rows_of.get(entity, ())
        return held if type(held) is set or not held else (held,)

    def values(self, labels: tuple, rows: dict | None = None) -> tuple | None:
        """The values of a row at the last collect (or in `rows`), as a tuple."""
        values = (self.last if rows is None else rows).get(labels)
        return (values,) if self.single and values is not None else values

    def shown(self, labels: tuple, values):
        """A kept row's values as its series shows them (as they came: a value or a tuple)."""
        base = self.base.get(labels)
        if base is None:
            return values
        if self.single:
            return values - base[0]
        return tuple(v - b for v, b in zip(values, base))

    def emit(self, out: Snapshot, entities: set) -> None:
        """The rows of these entities: those of the last emit brought up to date with this
        collect's changes, or made anew when the entities are not those of the last or when more
        rows changed than are emitted (the changes of entities not kept are passed over)."""
        emitted, shown = self._emitted, self.shown
        if entities != self._emitted_for or len(self._changed) + len(self._gone) > len(emitted):
            last, rows_of = self.last, self.rows_of
            emitted = self._emitted = {labels: (labels, shown(labels, last[labels]))
                                       for entity in entities for labels in rows_of(entity)}
            self._emitted_for = set(entities)
        else:
            entity_of = self.entity_of
            for labels in self._gone:
                emitted.pop(labels, None)
            emitted.update((labels, (labels, shown(labels, values))) for labels, values in self._changed
                           if entity_of(labels) in entities)
        (out.rows(self.metrics[0]) if self.single else out.group_rows(self.metrics)).extend(emitted.values())


class _Columnar:
    """What the budget remembers of a group given as Columns: its rows in the order the last
    Columns gave them (a probe hands its sockets on in the same order while none come or go), the
    same ascending for lookups, and each row's values and what it has summed into `other`. Its
    series are all counters (sockets' bytes and calls, connections' retransmits and resets, threads'
    CPU time and switches)."""

    def __init__(self, metrics: tuple[Metric, ...], kind: str, cols: Columns):
        if not all(m.kind == COUNTER for m in metrics):
            raise ValueError(f"{metrics[0].name}: columns are of counters only")
        labels = metrics[0].labels
        self.metrics, self.dim_names, self.units = metrics, cols.dim_names, cols.units
        self.rank = [i for i, m in enumerate(metrics) if m.name in KINDS[kind][1]]
        self.dim = next((i for i, label in enumerate(labels) if label in DIMENSIONS), None)
        self.ids = np.empty(0, np.int64)
        self.order = np.empty(0, np.intp)  # that sorts ids
        self.sorted = np.empty(0, np.int64)  # ids[order]
        self.last = np.empty((0, len(metrics)), np.int64)  # each row's values at the last collect
        # Whether it is in `other`: then its values there are `last`, for a row not kept that changed
        # adds its growth to `other` at once. A new row is, with nothing in it yet.
        self.infold = np.empty(0, bool)
        # A kept row's values when its series began (what it counted before is in `other`): its
        # series shows its values less these, from zero, or from what it showed when it last ended
        # (`resume`: a series that comes back does not go back).
        self.base = np.empty((0, len(metrics)), np.int64)
        self.resume = np.empty((0, len(metrics)), np.int64)
        self.totals: dict[int, np.ndarray] = {}  # dimension (an index of dim_names) -> its `other`
        self.others: set[int] = set()  # the dimensions whose `other` row was given
        self.entity_of = _entity_getter(labels, kind)
        # The rows given for the kept at the last collect, ids ascending, with those ids and their
        # stamps (Columns.stamps), where the Columns had them
        self.given: list[tuple] = []
        self.given_ids, self.given_stamps = np.empty(0, np.int64), np.empty((0, 0), np.uint64)
        # What the last collect gave: the kept rows (at `own` in its Columns, with those stamps), then
        # the `other` ones; None while a collect that may have failed midway has not given it anew.
        self.emitted: list[tuple] | None = None
        self.mark: int | None = None  # the probe's collect whose values `last` holds, where it said (Columns.told)
        self.own, self.own_stamps = np.empty(0, np.intp), None

    def none(self) -> Columns:
        """The group's Columns of a collect that gave it no rows."""
        return Columns(self.ids[:0], self.last[:0], np.empty(0, np.intp), self.dim_names, self.ids[:0],
                       lambda at: [], units=self.units)

    def follow(self, ids: np.ndarray) -> np.ndarray:
        """Take the rows of a collect whose rows are not those of the last (some came, some went, or
        they came in another order): the arrays follow them. Which are new."""
        order = np.argsort(ids)
        ascending = ids[order]
        new = np.ones(len(ids), bool)
        if len(self.ids):
            pos = np.minimum(np.searchsorted(self.sorted, ascending), len(self.ids) - 1)  # ascending: 8x faster
            src = np.empty(len(ids), np.intp)
            src[order] = self.order[pos]  # where each entity was; any row for a new one, zeroed below
            new[order[self.sorted[pos] == ascending]] = False
            # take: four times faster than indexing with an array
            self.last, self.infold = self.last.take(src, axis=0), self.infold.take(src)
            self.base, self.resume = self.base.take(src, axis=0), self.resume.take(src, axis=0)
        else:
            self.last, self.infold = np.zeros((len(ids), self.last.shape[1]), np.int64), np.zeros(len(ids), bool)
            self.base, self.resume = np.zeros_like(self.last), np.zeros_like(self.last)
        self.last[new], self.infold[new], self.base[new], self.resume[new] = 0, True, 0, 0
        self.ids, self.order, self.sorted = ids, order, ascending
        return new

    def rows_of(self, cols: Columns, entities: np.ndarray) -> np.ndarray:
        """Where the rows of these entities (ascending) are in `cols`, ascending: found among the
        few entities in the rows' sorted ids, where each row is an entity, not the other way round."""
        if not len(entities) or not len(cols.ids):
            return np.empty(0, np.intp)
        if cols.entities is not None:
            return np.flatnonzero(within(cols.entities, entities))
        at = np.minimum(np.searchsorted(self.sorted, entities), len(self.sorted) - 1)
        return np.sort(self.order[at[self.sorted[at] == entities]])

    def rows(self, cols: Columns, own: np.ndarray, changed: np.ndarray) -> list[tuple]:
        """The rows at `own` (ascending): one given at the last collect, with the same id, values
        (not `changed`) and stamps, is given again as it was, its labels not asked for (the two
        hundred threads kept, few of which ran) and the same tuple for the render to compare."""
        self.own = own
        if cols.stamps is None:
            return self._made(cols, own)
        ids, stamps = cols.ids[own], cols.stamps(own)
        self.own_stamps = stamps
        at, same = np.zeros(len(own), np.intp), np.zeros(len(own), bool)
        if len(self.given_ids) and len(own):
            at = np.minimum(np.searchsorted(self.given_ids, ids), len(self.given_ids) - 1)
            same = (self.given_ids[at] == ids) & (self.given_stamps[at] == stamps).all(axis=1)
            same[np.searchsorted(own, changed[within(changed, own)])] = False
        # Each row picked in one pass from the last rows followed by the new ones.
        made = self._made(cols, own[~same])
        at[~same] = len(self.given) + np.arange(len(made))
        out = list(map((self.given + made).__getitem__, at.tolist()))
        order = np.argsort(ids)
        self.given_ids, self.given_stamps = ids[order], stamps[order]
        self.given = list(map(out.__getitem__, order.tolist()))
        return out

    def _made(self, cols: Columns, at: np.ndarray) -> list[tuple]:
        """The rows at these indices, made anew: each counts from where its series began."""
        return list(zip(cols.labels(at.tolist()), shown(cols.values[at] - self.base[at], cols.units)))

    def as_before(self, cols: Columns) -> bool:
        """Whether the kept rows of these Columns, whose ids and values are those of the last, are
        named as they were (their stamps, where the Columns have them, are the same)."""
        return cols.stamps is None or bool((cols.stamps(self.own) == self.own_stamps).all())

    def other_labels(self, dim: int) -> tuple[str, ...]:
        labels = [OTHER] * len(self.metrics[0].labels)
        if self.dim is not None:
            labels[self.dim] = self.dim_names[dim]
        return tuple(labels)


@dataclass
class _KindState:
    limit: int
    kept: set = field(default_factory=set)
    entities: dict = field(default_factory=dict)  # entity -> how many groups hold rows of it
    groups: dict = field(default_factory=dict)  # metrics -> _Group
    totals: dict = field(default_factory=dict)  # (metrics, labels of other) -> values
    members: dict = field(default_factory=dict)  # the same key -> rows summed into it now (for gauges)
    folded_total: int = 0  # entities that went into `other`, ever
    # Whether the kind's first collect is done: what its entities counted before it is no one's
    # news, but an `other` row that begins later begins at 0, as every series does.
    begun: bool = False
    others: set = field(default_factory=set)  # the keys of `totals` whose row was given
    # Where the kind comes as Columns: its groups, its entities (ascending) at the last collect, and
    # those kept by their labels as a kind given as rows names them (ids are the probe's), and
    # those that only the groups beside the columns have, shown too.
    columnar: dict = field(default_factory=dict)  # metrics -> _Columnar
    ids: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    named: set = field(default_factory=set)
    extra: set = field(default_factory=set)


class Budget:
    def __init__(self, limits: dict[str, int]):
        self.kinds = {kind: _KindState(limits.get(kind, 0)) for kind in KINDS}

    def folded_total(self) -> dict[str, int]:
        """How many entities of each kind went into `other` since the agent started."""
        return {kind: st.folded_total for kind, st in self.kinds.items()}

    def folded(self) -> dict[str, int]:
        """Entities of each kind whose series are currently summed into `other`."""
        return {kind: (len(st.ids) if st.columnar else len(st.entities)) - len(st.kept)
                for kind, st in self.kinds.items()}

    def kept(self, kind: str) -> set:
        """Entities of a kind that had their own series at the last collect: a label value for
        kinds named by one label (a pid, an inode), a tuple of values for the others."""
        st = self.kinds[kind]
        return st.named | st.extra if st.columnar else set(st.kept)

    def limit(self, kind: str) -> int:
        return self.kinds[kind].limit

    def apply(self, snap: Snapshot) -> Snapshot:
        """The snapshot's rows within the budget. What it holds of the metrics of a probe that
        failed to collect (snap.unread: the agent took their rows out) stays as it was, and their
        entities keep their slots: their rows are missing, not gone, and the next collect goes on
        from the last one read."""
        out = Snapshot()
        by_kind: dict[str, dict[tuple[Metric, ...], list]] = {kind: {} for kind in KINDS}
        for metric, rows in snap.singles.items():
            kind = kind_of(metric)
            if kind is None:
                out.rows(metric).extend(rows)
            else:  # a metric alone is a group of one
                by_kind[kind][(metric,)] = (rows, True)
        for metrics, rows in snap.groups.items():
            kind = kind_of(metrics[0])
            if kind is None:
                out.group_rows(metrics).extend(rows)
            else:
                by_kind[kind][metrics] = (rows, False)
        for kind, groups in by_kind.items():
            self._apply_kind(self.kinds[kind], kind, groups, snap.changes, snap.unread, out)
            self.kinds[kind].begun = True
        return out

    def _apply_kind(self, st: _KindState, kind: str, groups: dict, told: dict, unread: set, out: Snapshot) -> None:
        held = {metrics for metrics in st.groups.keys() | st.columnar.keys() if not unread.isdisjoint(metrics)}
        columns = {metrics: rows for metrics, (rows, _) in groups.items() if isinstance(rows, Columns)}
        if columns or st.columnar:  # none now: every entity gone
            if held:
                return  # a kind given as columns comes from one probe: held whole while it fails
            beside = {metrics: group for metrics, group in groups.items() if metrics not in columns}
            if any(m.additive for metrics in beside for m in metrics):
                raise ValueError(f"{kind}: groups given as columns may have beside them only gauges that do "
                                 "not add up")
            self._apply_columns(st, kind, {**dict.fromkeys(st.columnar), **columns}, out)
            self._beside_columns(st, kind, beside, out)
            return
        # A thousand processes' rows pass here at each scrape, few of which changed since the last:
        # only changed rows get per-row work, the rest is dict and set operations.
        seen = []  # (group, changed rows, labels gone)
        grew: dict[str, dict] = {}
        for metrics in groups.keys() | (st.groups.keys() - held):  # a group absent this time lost all its rows
            rows, single = groups.get(metrics, ([], False))
            g = st.groups.get(metrics) or st.groups.setdefault(metrics, _Group(metrics, kind, single))
            changed, gone = g.update(rows, grew, told.get(metrics))
            seen.append((g, changed, gone))
        new, ended = self._count_entities(st, [g for g, _, _ in seen])
        entities = st.entities.keys()
        activity: dict = {}
        for per_entity in grew.values():
            whole = sum(per_entity.values())
            for entity, d in per_entity.items():  # a share of all, so bytes and seconds weigh alike
                activity[entity] = activity.get(entity, 0.0) + d / whole
        st.kept -= ended  # entities that ended free their slots
        was_kept = set(st.kept)
        if not held:  # while some of their rows are unread, the entities keep their slots
            self._choose(st, lambda n: islice(entities - st.kept, n), activity)
        kept = st.kept
        promoted, demoted = kept - was_kept, was_kept - kept
        for g, changed, gone in seen:
            if g.additive:
                self._fold(st, g, changed, gone, promoted, demoted)
            # The demoted rows' series end with what they counted until now, `other` goes on from there.
            g.emit(out, kept | demoted if g.rebased else kept)
            for e in demoted if g.rebased else ():
                for labels in g.rows_of(e):
                    values, base = g.values(labels), g.base.pop(labels, None)  # (a row new now has none)
                    g.resume[labels] = values if base is None else tuple(v - b for v, b in zip(values, base))
        st.folded_total += sum(e not in kept for e in new) + len(demoted)
        for key, values in st.totals.items():
            metrics, labels = key
            if metrics in held:
                continue
            if key not in st.others:  # a counter's new `other` row shows 0 (what went into it, at the next)
                st.others.add(key)
                if st.begun and all(m.kind in (COUNTER, HISTOGRAM) for m in metrics):
                    values = [v - v for v in values]
            if len(metrics) == 1:
                out.rows(metrics[0]).append((labels, values[0]))
            else:
                out.group_rows(metrics).append((labels, tuple(values)))

    def _apply_columns(self, st: _KindState, kind: str, given: dict[tuple[Metric, ...], Columns | None],
                       out: Snapshot) -> None:
        """The rows of groups given as Columns (None: a group that has no rows now): as _apply_kind
        does for rows, with the rows' values and their parts of `other` in arrays, per-row work only
        for those that changed (found with one comparison of the arrays), and labels made for the
        rows kept alone."""
        seen = []  # (its _Columnar, the Columns, the rows changed)
        active, parts = [], []  # per group: the entities of the rows that grew, and their shares
        steady = True  # no row came or went since the last collect, which gave every group
        still = True  # nor changed
        for metrics, cols in given.items():
            c = st.columnar.get(metrics) or st.columnar.setdefault(metrics, _Columnar(metrics, kind, cols))
            cols = cols or c.none()
            moved = not np.array_equal(cols.ids, c.ids)
            if not moved and cols.told is not None and cols.told[0] == c.mark:
                changed = cols.told[2]  # the probe said which rows changed since the values `last` holds
            else:
                new = c.follow(cols.ids) if moved else np.zeros(len(cols.ids), bool)
                changed = np.flatnonzero(rows_differ(cols.values, c.last) | new)
            steady = steady and not moved and c.emitted is not None
            still = still and steady and not len(changed)
            # Activity: what each entity's ranking counters grew by, as a share of what the kind's did.
            grew = np.maximum(cols.values[changed][:, c.rank] - c.last[changed][:, c.rank], 0)
            whole = grew.sum(axis=0)
            share = (grew / np.where(whole > 0, whole, 1)).sum(axis=1)
            active.append(cols.of()[changed[share > 0]])
            parts.append(share[share > 0])
            seen.append((c, cols, changed))
        entities, at = np.unique(np.concatenate(active), return_inverse=True)
        activity = dict(zip(entities.tolist(), np.bincount(at, np.concatenate(parts), len(entities)).tolist()))
        full = len(st.kept) in (st.limit, len(st.ids))  # no slot free that an idle entity would take
        # The connections of a host whose connections idle: the same rows again, with no array work.
        # Unless a slot is free that an idle entity would take, or a kept row is named anew.
        if still and full and all(c.as_before(cols) for c, cols, _ in seen):
            for c, cols, _ in seen:
                out.group_rows(c.metrics).extend(c.emitted)
                c.mark = cols.told[1] if cols.told else None
            return
        for c, _, _ in seen:
            c.emitted = None
        # No entity came or went, and none gets or loses its slot (as a rule, between two scrapes):
        # the kept rows are where they were, and the kind's entities are not sorted and searched again.
        if steady and full and self._keep_slots(st, activity):
            self._emit_columns(st, [(c, cols, changed, c.own) for c, cols, changed in seen], np.empty(0, np.int64), out)
            return
        if len(seen) == 1 and seen[0][1].entities is None:
            everyone = seen[0][0].sorted  # the one group's ids, ascending, are the entities
        else:
            everyone = distinct(np.concatenate([cols.of() for _, cols, _ in seen]))
        fresh = everyone[:0] if everyone is st.ids else everyone[~within(everyone, st.ids)]  # as a rule: none
        st.ids = everyone

        def kept() -> np.ndarray:  # the entities with series of their own, ascending
            return np.sort(np.fromiter(st.kept, np.int64, len(st.kept)))
        held = kept()
        st.kept = set(held[within(held, everyone)].tolist())  # entities that ended free their slots
        was_kept = set(st.kept)

        def idle(n: int) -> list[int]:  # entities without series of their own, the first n
            return everyone[~within(everyone, kept())][:n].tolist()
        self._choose(st, idle, activity)
        held = kept()
        demoted = np.array(sorted(was_kept - st.kept), np.int64)
        st.folded_total += int((~within(fresh, held)).sum()) + len(demoted)
        self._emit_columns(st, [(c, cols, changed, c.rows_of(cols, held)) for c, cols, changed in seen], demoted, out)

    def _emit_columns(self, st: _KindState, seen: list[tuple], demoted: np.ndarray, out: Snapshot) -> None:
        """Each group's rows: those kept (at `own` in its Columns), then its `other` ones, which the rows
        not kept that changed, and those of the entities `demoted`, add to. `seen`: (its _Columnar, the
        Columns, the rows changed, own) of each."""
        st.named = set()
        for c, cols, changed, own in seen:
            left, had = c.rows_of(cols, demoted), len(c.others)
            others = self._fold_columns(c, cols, changed, own, left, st.begun)
            # The demoted rows' series end with what they counted until now, `other` goes on from there.
            at = np.sort(np.concatenate((own, left)))
            rows = c.rows(cols, at, changed)
            st.named.update(c.entity_of(row[0]) for row, of_own in zip(rows, ~within(at, left)) if of_own)
            out.group_rows(c.metrics).extend(rows + others)
            # Not given again as they are: the demoted are not shown again, nor a new `other` row at 0.
            c.emitted = None if len(left) or (st.begun and len(c.others) > had) else rows + others
            c.mark = cols.told[1] if cols.told else None

    @classmethod
    def _keep_slots(cls, st: _KindState, activity: dict) -> bool:
        """Whether by this activity every entity kept keeps its slot and no other takes one, where
        no slot is free that an idle entity would take; if not, the kept are left as they were."""
        was = set(st.kept)
        cls._choose(st, lambda n: [], activity)
        if st.kept == was:
            return True
        st.kept = was
        return False

    @staticmethod
    def _fold_columns(c: _Columnar, cols: Columns, changed: np.ndarray, own: np.ndarray,
                      demoted: np.ndarray, from_zero: bool) -> list[tuple]:
        """A group's `other` rows: what each row not kept counted since it last added to it (all of
        it if it went back). A row that gets its own series adds what it counted until now, and its
        series counts from zero; one `demoted` adds nothing now: its series shows what it counted
        one last time, and `other` goes on from there. With `from_zero`, an `other` row new now
        shows 0 (what went into it shows at the next collect)."""
        vals, last, infold = cols.values, c.last, c.infold
        starting = own[infold[own]]
        enters = np.zeros(len(cols.ids), bool)  # (a mask, not setdiff1d and union1d, which import numpy.ma)
        enters[changed] = True
        enters[own] = False
        enters[demoted] = False
        enters[starting] = True
        entering = np.flatnonzero(enters)
        now, was = vals[entering], np.where(infold[entering, None], last[entering], 0)
        steps, into = np.where(now < was, now, now - was), cols.dims[entering]
        sums = np.zeros((len(c.dim_names), len(c.metrics)), np.int64)
        np.add.at(sums, into, steps)
        for d in np.flatnonzero(np.bincount(into, minlength=len(c.dim_names))).tolist():
            c.totals[d] = c.totals.get(d, 0) + sums[d]
        infold[entering] = True
        going = own[~infold[own]]  # kept rows that had their series: one that went back (a reused id) goes on
        c.base[going] -= np.where(vals[going] < last[going], last[going], 0)
        c.base[starting] = vals[starting] - c.resume[starting]
        c.resume[demoted] = vals[demoted] - c.base[demoted]
        infold[own] = False
        infold[demoted] = True
        last[changed] = vals[changed]  # the budget's own copy: the probe's arrays may be written over
        if not c.totals:
            return []
        dims = list(c.totals)
        sums = np.array([c.totals[d] for d in dims])
        if from_zero:
            sums[[d not in c.others for d in dims]] = 0
        c.others.update(dims)
        return list(zip(map(c.other_labels, dims), shown(sums, c.units)))

    @staticmethod
    def _beside_columns(st: _KindState, kind: str, groups: dict, out: Snapshot) -> None:
        """The rows of gauges that do not add up (a connection's RTT) beside a group given as
        Columns: those of the entities kept, and of entities the columns do not have (a connection
        older than the agent, which never moved under its probes) as far as slots are free, the
        first by their labels."""
        named = {metrics: (_entity_getter(metrics[0].labels, kind), rows, single)
                 for metrics, (rows, single) in groups.items()}
        others = {of(row[0]) for of, rows, _ in named.values() for row in rows} - st.named
        st.extra = set(sorted(others)[:max(st.limit - len(st.kept), 0)])
        showing = st.named | st.extra
        for metrics, (of, rows, single) in named.items():
            (out.rows(metrics[0]) if single else out.group_rows(metrics)).extend(
                row for row in rows if of(row[0]) in showing)

    @staticmethod
    def _count_entities(st: _KindState, groups: list) -> tuple[set, set]:
        """Count in the entities the groups' rows came to or left at this collect: (the entities
        new to the kind, those it no longer has). Per change, not per entity."""
        came = [e for g in groups for e in g.came]
        left = [e for g in groups for e in g.left]
        was = {e for e in came + left if e in st.entities}
        counts = st.entities
        for e in left:
            counts[e] -= 1
            if not counts[e]:
                del counts[e]
        for e in came:
            counts[e] = counts.get(e, 0) + 1
        return {e for e in came if e not in was}, {e for e in left if e not in counts}

    @staticmethod
    def _fold(st: _KindState, g: _Group, changed: list, gone: set, promoted: set, demoted: set) -> None:
        """Bring the `other` rows of the group up to date. A counter's `other` keeps what every
        entity that left it (ended, or got its own series) had summed into it, and takes what an
        entity counted before its series began; a gauge's is the sum of the entities folded now."""
        kept, entity_of = st.kept, g.entity_of
        if g.rebased:
            for labels in gone:
                g.folded.pop(labels, None)
                g.base.pop(labels, None)
                g.resume.pop(labels, None)
            starting = {labels: g.values(labels) for e in promoted for labels in g.rows_of(e)}
            starting.update((labels, values) for labels, values in changed
                            if labels not in g.base and entity_of(labels) in kept)
            for labels, values in changed:  # a kept row that went back (a reused PID): its series goes on
                base, old = g.base.get(labels), g.before.get(labels)
                if base is not None and old is not None and labels not in starting:
                    g.base[labels] = tuple(b - o if _went_back(v, o) else b
                                           for v, o, b in zip(values, (old,) if g.single else old, base))
            entering = {labels: values for labels, values in changed
                        if entity_of(labels) not in kept and entity_of(labels) not in demoted}
            entering.update(starting)
            for e in demoted:  # their series show what they counted until now: `other` goes on from there
                g.folded.update((labels, g.values(labels)) for labels in g.rows_of(e))
            Budget._fold_rows(st, g, entering)
            for labels, values in starting.items():
                resume = g.resume.pop(labels, None)
                g.base[labels] = values if resume is None else tuple(v - r for v, r in zip(values, resume))
                del g.folded[labels]
            return
        leaving = [labels for labels in gone if labels in g.folded]
        leaving += [labels for e in promoted for labels in g.rows_of(e) if labels in g.folded]
        for labels in leaving:
            values = g.folded.pop(labels)
            key = g.other_key(labels)
            if not g.counters:
                st.totals[key] = [a - b for a, b in zip(st.totals[key], values)]
                st.members[key] -= 1
                if not st.members[key]:
                    del st.totals[key], st.members[key]
        entering = {labels: values for labels, values in changed if entity_of(labels) not in kept}
        for e in demoted:
            entering.update((labels, g.values(labels)) for labels in g.rows_of(e))
        Budget._fold_rows(st, g, entering)

    @staticmethod
    def _fold_rows(st: _KindState, g: _Group, entering: dict) -> None:
        """Add to `other` what each of these rows grew by since it last went into it."""
        if not entering:
            return
        if any(isinstance(v, Histogram) for v in next(iter(entering.values()))):
            for labels, values in entering.items():  # histograms, one row at a time: few, with buckets
                old = g.folded.get(labels)
                steps = [g.step(new, was) for new, was in zip(values, old or [None] * len(values))]
                Budget._add(st, g.other_key(labels), steps, int(old is None))
                g.folded[labels] = values
            return
        # Numbers, in bulk: what each row grew by since it last went into `other` (a counter that went
        # back: all of it), summed per `other` row with one array operation.
        rows = list(entering.items())
        olds = [g.folded.get(labels) for labels, _ in rows]
        new = np.array([values for _, values in rows])
        zero = (0,) * new.shape[1]
        old = np.array([was if was is not None else zero for was in olds])
        steps = np.where(new < old, new, new - old) if g.counters else new - old
        index: dict = {}
        at = np.fromiter((index.setdefault(g.other_key(labels), len(index)) for labels, _ in rows), np.intp, len(rows))
        sums = np.zeros((len(index), new.shape[1]), steps.dtype)
        np.add.at(sums, at, steps)
        fresh = np.bincount(at, [was is None for was in olds], len(index))
        for key, i in index.items():
            Budget._add(st, key, sums[i].tolist(), int(fresh[i]))
        g.folded.update(rows)

    @staticmethod
    def _add(st: _KindState, key: tuple, steps: list, joined: int) -> None:
        """Add these steps to an `other` row, which `joined` rows new to it now count in (gauges'
        rows leave when their last member does)."""
        total = st.totals.get(key)
        st.totals[key] = steps if total is None else [a + b for a, b in zip(total, steps)]
        if joined:
            st.members[key] = st.members.get(key, 0) + joined

    @staticmethod
    def _choose(st: _KindState, idle: Callable[[int], Iterable], activity: dict) -> None:
        """`idle(n)`: n entities at most that have no series of their own (st.kept), whatever they did."""
        # Activity is what an entity did since the last collect; a newcomer's is all it did so
        # far, so a busy new process can win a slot at once.
        kept = st.kept
        active = sorted((e for e in activity if e not in kept), key=activity.__getitem__, reverse=True)
        free = st.limit - len(kept)
        kept.update(active[:free])
        if free > len(active):  # slots left: idle entities take them
            kept.update(idle(free - len(active)))
        rivals = active[free:] if free > 0 else active  # those left without a slot
        if not rivals:
            return  # every kept entity stays: no need to rank them (a thousand, at each collect)
        weakest = [(activity.get(k, 0.0), i, k) for i, k in enumerate(kept)]  # i: entities may not compare
        heapq.heapify(weakest)
        for i, e in enumerate(rivals):
            if not weakest or activity[e] <= 2 * weakest[0][0]:
                break  # candidates are sorted: no later one can do better
            kept.discard(heapq.heapreplace(weakest, (activity[e], len(kept) + i, e))[2])
            kept.add(e)

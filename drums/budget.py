"""The cardinality budget: own series for the most active processes, threads, sockets and TCP
connections; everything else summed into one `other` series per metric.

An entity that gets its own series keeps it while it lives (series that flap in and out confuse
rate()), unless a folded one becomes more than twice as active. `other` never goes backwards:
when a folded entity leaves it (it ends, or gets its own series), its last values stay in a
baseline.
"""
from __future__ import annotations

import heapq
from dataclasses import dataclass, field
from operator import add, itemgetter

from drums.metrics import COUNTER, GAUGE, HISTOGRAM, Metric, Snapshot

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


def kind_of(metric: Metric) -> str | None:
    for kind, (ident, _) in KINDS.items():
        if all(label in metric.labels for label in ident):
            return kind
    return None


@dataclass
class _KindState:
    limit: int
    kept: set = field(default_factory=set)
    last_score: dict = field(default_factory=dict)  # entity -> its ranking total at the last collect
    folded_last: dict = field(default_factory=dict)  # group -> entity -> (other key, values)
    baseline: dict = field(default_factory=dict)  # (group, labels of other) -> values
    folded_now: int = 0
    folded_set: set = field(default_factory=set)  # entities summed into `other` at the last collect
    folded_total: int = 0  # entities that went into `other`, ever



class Budget:
    def __init__(self, limits: dict[str, int]):
        self.kinds = {kind: _KindState(limits.get(kind, 0)) for kind in KINDS}

    def folded_total(self) -> dict[str, int]:
        """How many entities of each kind went into `other` since the agent started."""
        return {kind: st.folded_total for kind, st in self.kinds.items()}

    def folded(self) -> dict[str, int]:
        """Entities of each kind whose series are currently summed into `other`."""
        return {kind: st.folded_now for kind, st in self.kinds.items()}

    def kept(self, kind: str) -> set:
        """Entities of a kind that had their own series at the last collect: a label value for
        kinds named by one label (a pid, an inode), a tuple of values for the others."""
        return set(self.kinds[kind].kept)

    def limit(self, kind: str) -> int:
        return self.kinds[kind].limit

    def apply(self, snap: Snapshot) -> Snapshot:
        out = Snapshot()
        by_kind: dict[str, list[tuple[tuple[Metric, ...], list]]] = {}
        for metric, rows in snap.singles.items():
            kind = kind_of(metric)
            if kind is None:
                out.rows(metric).extend(rows)
            else:  # a metric alone is a group of one
                by_kind.setdefault(kind, []).append(((metric,), [(labels, (v,)) for labels, v in rows]))
        for metrics, rows in snap.groups.items():
            kind = kind_of(metrics[0])
            if kind is None:
                out.group_rows(metrics).extend(rows)
            else:
                by_kind.setdefault(kind, []).append((metrics, rows))
        for kind, groups in by_kind.items():
            self._apply_kind(kind, groups, out)
        return out

    def _apply_kind(self, kind: str, groups: list, out: Snapshot) -> None:
        # Tens of thousands of rows pass here at each scrape: the loops stay flat on purpose.
        st = self.kinds[kind]
        ident, rank_names = KINDS[kind]
        totals: dict[tuple, float] = {}  # (entity, ranking metric) -> value now
        entities = set()
        for metrics, rows in groups:
            entity_of = itemgetter(*[metrics[0].labels.index(label) for label in ident])
            entities.update(map(entity_of, [labels for labels, _ in rows]))
            for i, metric in enumerate(metrics):
                if metric.name in rank_names:
                    for labels, values in rows:
                        key = (entity_of(labels), metric.name)
                        totals[key] = totals.get(key, 0.0) + values[i]
        self._choose(st, entities, totals)

        kept = st.kept
        baseline = st.baseline
        folded_now: dict[tuple, dict] = {}  # group -> entity -> (other key, values)
        sums: dict[tuple, tuple] = {}
        for metrics, rows in groups:
            labels_of = metrics[0].labels
            entity_of = itemgetter(*[labels_of.index(label) for label in ident])
            dims = [i for i, label in enumerate(labels_of) if label in DIMENSIONS]
            other_keys: dict[tuple, tuple] = {}  # dimension values -> (group, labels of other)
            additive = all(m.additive for m in metrics)
            counters = all(m.kind in (COUNTER, HISTOGRAM) for m in metrics)
            folded = folded_now[metrics] = {}
            own = out.group_rows(metrics)
            for labels, values in rows:
                entity = entity_of(labels)
                if entity in kept:
                    own.append((labels, values))
                    continue
                if not additive:
                    continue  # folded entities of a non-additive gauge have no `other`
                dimvals = tuple([labels[i] for i in dims])
                key = other_keys.get(dimvals)
                if key is None:
                    template = [OTHER] * len(labels)
                    for i, v in zip(dims, dimvals):
                        template[i] = v
                    key = other_keys[dimvals] = (metrics, tuple(template))
                previous = sums.get(key)
                sums[key] = values if previous is None else tuple(map(add, previous, values))
                if counters:
                    folded[entity] = (key, values)
            # Folded entities that left (ended or promoted) leave their last values in the baseline.
            last = st.folded_last.get(metrics, {})
            for entity in last.keys() - folded.keys():
                self._to_baseline(baseline, *last[entity])
        for metrics in st.folded_last.keys() - folded_now.keys():  # no series of it at all this time
            for key, values in st.folded_last[metrics].values():
                self._to_baseline(baseline, key, values)
        st.folded_last = folded_now
        folded_set = entities - kept
        st.folded_total += len(folded_set - st.folded_set)
        st.folded_set = folded_set
        st.folded_now = len(folded_set)
        for key in sums.keys() | baseline.keys():
            metrics, labels = key
            value = sums.get(key)
            if all(m.kind == GAUGE for m in metrics):
                if value is not None:
                    out.group_rows(metrics).append((labels, value))
                continue
            base = baseline.get(key)
            total = value if base is None else base if value is None else tuple(map(add, base, value))
            out.group_rows(metrics).append((labels, total))

    @staticmethod
    def _to_baseline(baseline: dict, key: tuple, values: tuple) -> None:
        previous = baseline.get(key)
        baseline[key] = values if previous is None else tuple(map(add, previous, values))

    @staticmethod
    def _choose(st: _KindState, entities: set, totals: dict[tuple, float]) -> None:
        # Activity is each entity's share of what all entities did since the last collect, summed
        # over the ranking counters, so bytes and seconds weigh alike. A newcomer's activity is all
        # it did so far, so a busy new process can win a slot at once.
        delta = {k: max(0.0, v - st.last_score.get(k, 0.0)) for k, v in totals.items()}
        st.last_score = totals
        per_metric: dict[str, float] = {}
        for (_, name), d in delta.items():
            per_metric[name] = per_metric.get(name, 0.0) + d
        activity = dict.fromkeys(entities, 0.0)
        for (entity, name), d in delta.items():
            if per_metric[name]:
                activity[entity] += d / per_metric[name]
        st.kept &= entities  # entities that ended free their slots
        kept = st.kept
        # Most entities did nothing since the last collect: only active ones are sorted.
        idle, active = [], []
        for e in entities:
            if e not in kept:
                (active if activity[e] > 0 else idle).append(e)
        active.sort(key=activity.__getitem__, reverse=True)
        free = st.limit - len(kept)
        kept.update(active[:free])
        kept.update(idle[:max(0, free - len(active))])
        weakest = [(activity[k], i, k) for i, k in enumerate(kept)]  # i: entities may not compare
        heapq.heapify(weakest)
        for i, e in enumerate(active[free:] if free > 0 else active):
            if not weakest or activity[e] <= 2 * weakest[0][0]:
                break  # candidates are sorted: no later one can do better
            kept.discard(heapq.heapreplace(weakest, (activity[e], len(kept) + i, e))[2])
            kept.add(e)

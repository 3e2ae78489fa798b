"""The text exposition, the cardinality budget and the README table, without the kernel."""
import random
import sys

import numpy as np
import pytest

from prometheus_client.parser import text_string_to_metric_families

from drums import budget as budget_module, docs
from drums.budget import Budget
from drums.exporters.prometheus import Renderer, render
from drums.metrics import COUNTER, GAUGE, HISTOGRAM, Changes, Columns, Histogram, Metric, Snapshot
from drums.probes import sched, tcp

CPU = Metric("drums_process_cpu_seconds_total", COUNTER, "cpu", ("pid", "process"))
MEM = Metric("drums_process_resident_memory_bytes", GAUGE, "rss", ("pid", "process"))
SENT = Metric("drums_process_socket_sent_bytes_total", COUNTER, "sent", ("pid", "process", "protocol"))
LAT = Metric("drums_process_runqueue_latency_seconds", HISTOGRAM, "lat", ("pid", "process"), (0.001, 0.01))


def test_a_renderer_that_remembers_the_last_scrape_writes_what_a_fresh_one_writes():
    """Scrape after scrape, families come, go, change one value and come in another order; a family
    whose rows are equal to the last scrape's is taken as it was written (an equal number too: 2
    where 2.0 came), and a snapshot added to after it was rendered is written anew."""
    def snapshot(cpu: dict, lat: Histogram | None) -> Snapshot:
        snap = Snapshot()
        snap.group_rows((CPU, MEM)).extend(((pid, "p"), (value, 100)) for pid, value in cpu.items())
        if lat is not None:
            snap.add(LAT, ("1", 'a "b" \\ c\nd'), lat)  # its labels escaped, taken again as its counts change
            snap.add(LAT, ("2", "b"), Histogram([1, 1], 0.001, 1))  # the same each time: its text is kept
        return snap

    def sent(pid: str, protocol: str, value: int) -> Snapshot:
        snap = Snapshot()
        snap.add(SENT, (pid, "p", protocol), value)
        return snap

    def parsed(body: bytes) -> list:
        return [(s.name, s.labels, s.value) for f in text_string_to_metric_families(body.decode()) for s in f.samples]

    renderer = Renderer()
    scrapes = [snapshot({"1": 1.5, "2": 2}, None),
               snapshot({"1": 1.5, "2": 2}, Histogram([2, 3], 0.0125, 4)),
               snapshot({"1": 1.5, "2": 2.0}, Histogram([2, 3], 0.0125, 4)),  # equal, but written 2.0
               snapshot({"1": 1.5, "2": 2.25}, Histogram([2, 3], 0.0125, 4)),
               snapshot({"2": 2.25, "1": 1.5}, Histogram([2, 3], 0.0125, 4)),  # the same rows, in another order
               snapshot({"2": 2.25}, Histogram([2, 4], 0.02, 5)),
               sent("3", "tcp", 10), sent("3", "tcp", 10), sent("3", "udp", 10)]
    for snap in scrapes:
        assert parsed(renderer(snap)) == parsed(render(snap))
    snap = scrapes[-1]
    snap.add(SENT, ("4", "p", "tcp"), 7)
    assert parsed(renderer(snap)) == parsed(render(snap)) and b'pid="4"' in render(snap)
    assert [parsed(renderer(s)) == parsed(render(s)) for s in scrapes] == [True] * len(scrapes)


def test_the_page_comes_in_chunks_of_whole_families_that_gzip_one_after_the_other():
    """A page of 3,000 processes is handed on as chunks (a block of its own pages for the page whole
    is faulted in at each scrape): joined, they are the page; gzipped one after the other, one
    stream that gives the page back."""
    import gzip

    from drums.exporters.http import _compressed
    from drums.exporters.prometheus import CHUNK
    snap = Snapshot()
    for pid in range(3000):
        snap.add(CPU, (str(pid), f"worker-{pid}"), pid * 0.5)
        snap.add(MEM, (str(pid), f"worker-{pid}"), pid << 20)
        snap.add(SENT, (str(pid), f"worker-{pid}", "tcp"), pid * 7)
    renderer = Renderer()
    renderer(snap)  # a second render takes the remembered texts
    chunks = renderer.chunks(snap)
    page = render(snap)
    assert len(page) > 3 * CHUNK and len(chunks) == 3  # one family a chunk: each is over CHUNK
    assert b"".join(chunks) == page
    assert all(chunk.startswith(b"# HELP ") for chunk in chunks)
    body, headers = _compressed(chunks, gzipped=True)
    assert headers["Content-Encoding"] == "gzip" and gzip.decompress(body) == page


def test_render_parses_back_with_prometheus_client_including_hostile_label_values():
    snap = Snapshot()
    snap.add(CPU, ("1", 'we"ird\\name\nx'), 1.5)
    snap.add(LAT, ("1", "a"), Histogram([2, 3], 0.0125, 4))
    families = {f.name: f for f in text_string_to_metric_families(render(snap).decode())}
    (cpu,) = families["drums_process_cpu_seconds"].samples
    assert cpu.labels == {"pid": "1", "process": 'we"ird\\name\nx'} and cpu.value == 1.5
    lat = {(s.name, s.labels.get("le")): s.value for s in families["drums_process_runqueue_latency_seconds"].samples}
    assert lat == {("drums_process_runqueue_latency_seconds_bucket", "0.001"): 2,
                   ("drums_process_runqueue_latency_seconds_bucket", "0.01"): 3,
                   ("drums_process_runqueue_latency_seconds_bucket", "+Inf"): 4,
                   ("drums_process_runqueue_latency_seconds_sum", None): 0.0125,
                   ("drums_process_runqueue_latency_seconds_count", None): 4}


def test_a_histogram_with_buckets_of_its_own_renders_them_and_adds_on_their_union():
    import numpy as np

    from drums.probes.rcl import PERIOD, PERIOD_EDGES, SLOTS, timing_histogram
    lower, upper = PERIOD_EDGES
    slots = np.zeros(SLOTS, np.uint32)
    at = np.searchsorted(lower, [0.020, 0.0401], side="right") - 1
    assert upper[at[0]] - lower[at[0]] < 0.016 * 0.020  # slots 1.6% wide at most
    slots[at] = (9, 1)
    h = timing_histogram(slots, 220_100_000, PERIOD_EDGES)
    edges = (lower[at[0]], upper[at[0]], lower[at[1]], upper[at[1]])
    assert h.bounds == edges and (h.cumulative, h.count, h.sum) == ([0, 9, 9, 10], 10, 0.2201)
    snap = Snapshot()
    snap.add(PERIOD, ("1", "a", "/beat", ""), h)
    [family] = text_string_to_metric_families(render(snap).decode())
    buckets = [(float(s.labels["le"]), s.value) for s in family.samples if s.name.endswith("_bucket")]
    assert buckets == list(zip(edges + (float("inf"),), (0, 9, 9, 10, 10)))

    other = Histogram([0, 2], 0.5, 2, (edges[0], 0.5))  # a bucket in common, one not
    both = h + other
    assert both.bounds == edges + (0.5,)
    assert both.cumulative == [0, 9, 9, 10, 12] and both.count == 12
    assert (both - other).cumulative == [0, 9, 9, 10, 10]

    # More slots filled later: every bucket of the sum of two rows is where it was or higher.
    later = slots.copy()
    later[np.searchsorted(lower, [0.010, 0.0205, 0.030], side="right") - 1] += 1
    grown = timing_histogram(later, 260_600_000, PERIOD_EDGES) + other
    assert set(both.bounds) <= set(grown.bounds)
    assert all(grown._at((b,))[0] >= c for b, c in zip(both.bounds, both.cumulative))


def _snap(cpu: dict, sent: dict | None = None, mem: dict | None = None) -> Snapshot:
    snap = Snapshot()
    for pid, v in cpu.items():
        snap.add(CPU, (pid, f"p{pid}"), v)
    for pid, v in (sent or {}).items():
        snap.add(SENT, (pid, f"p{pid}", "tcp"), v)
    for pid, v in (mem or {}).items():
        snap.add(MEM, (pid, f"p{pid}"), v)
    return snap


def test_budget_keeps_the_most_active_and_folds_the_rest_into_other():
    b = Budget({"process": 2})
    # Shares of CPU plus shares of bytes: 1 (0.61) and 2 (0.06 + 0.91) beat 3 (0.30) and 4 (0.12).
    out = b.apply(_snap({"1": 10.0, "2": 1.0, "3": 5.0, "4": 0.5}, sent={"2": 10, "4": 1},
                        mem={"1": 7, "2": 8, "3": 9, "4": 10}))
    # A counter's series counts from zero: what was counted before it began is in `other`.
    assert out.values(CPU) == {("1", "p1"): 0.0, ("2", "p2"): 0.0, ("other", "other"): 16.5}
    assert out.values(SENT) == {("2", "p2", "tcp"): 0, ("other", "other", "tcp"): 11}  # dimensions survive
    assert out.values(MEM) == {("1", "p1"): 7, ("2", "p2"): 8, ("other", "other"): 19}  # gauges as they are
    assert b.folded()["process"] == 2
    out = b.apply(_snap({"1": 12.0, "2": 1.5, "3": 5.0, "4": 0.75}, sent={"2": 30, "4": 1}))
    assert out.values(CPU) == {("1", "p1"): 2.0, ("2", "p2"): 0.5, ("other", "other"): 16.75}
    assert out.values(SENT) == {("2", "p2", "tcp"): 20, ("other", "other", "tcp"): 11}
    b.apply(_snap({"1": 10.0, "2": 1.0, "3": 5.0, "5": 0.0}))  # 4 ended, 5 came and was folded
    assert b.folded()["process"] == 2 and b.folded_total()["process"] == 3


def test_other_never_goes_backwards_and_the_series_sum_to_what_the_entities_counted():
    """As entities end, get a series and lose it, each series counts from zero and `other` only
    grows: the last value of every series there was, summed, is what the entities counted."""
    b = Budget({"process": 1})
    rounds = [
        ({"1": 100.0, "2": 1.0, "3": 2.0}, {"1": 0.0}, 103.0),  # 1 kept, from zero; 2 and 3 folded
        ({"1": 101.0, "2": 1.25, "3": 2.0}, {"1": 1.0}, 103.25),  # 1 stays busiest
        ({"1": 102.0, "3": 2.5}, {"1": 2.0}, 103.75),  # 2 ended at 1.25: `other` keeps it
        # 1 idle, 3 busy: 3 promoted (what it counted until now goes to `other`); 1 shows its last
        ({"1": 102.0, "3": 50.0}, {"1": 2.0, "3": 0.0}, 151.25),
        ({"3": 60.0}, {"3": 10.0}, 151.25),  # 1 ended
    ]
    last = {}
    for counters, own, other in rounds:
        out = {labels[0]: v for labels, v in b.apply(_snap(counters)).values(CPU).items()}
        assert out == {**own, "other": other}, counters
        last.update(out)
    assert sum(last.values()) == 102.0 + 1.25 + 60.0


def test_an_other_row_that_begins_after_the_first_collect_begins_at_zero():
    """Processes that come after the first collect (as under --process-name, which chose none at
    first): the new `other` row shows 0, and what went into it at the next collect, so that
    Prometheus' increase() counts it."""
    b = Budget({"process": 1})
    assert b.apply(_snap({})).values(CPU) == {}
    assert b.apply(_snap({"1": 5.0, "2": 3.0})).values(CPU) == {("1", "p1"): 0.0, ("other", "other"): 0.0}
    assert b.apply(_snap({"1": 6.0, "2": 3.0})).values(CPU) == {("1", "p1"): 1.0, ("other", "other"): 8.0}


SOCKET_SENT = Metric("drums_socket_sent_bytes_total", COUNTER, "sent", ("pid", "inode", "protocol"))
SOCKET_RECEIVED = Metric("drums_socket_received_bytes_total", COUNTER, "received", ("pid", "inode", "protocol"))


def test_the_budget_gives_the_same_whether_an_idle_row_comes_as_the_last_object_or_a_new_one():
    """A probe may hand an idle socket's row on as the very object of the last collect (the budget
    then skips it by identity) or make it anew: over random steps of sockets that come, go, count
    on and are reset, both budgets give the same series."""
    rng = random.Random(3)
    reused, fresh = Budget({"socket": 5}), Budget({"socket": 5})
    counts: dict[str, list[int]] = {}
    objects: dict[str, tuple] = {}
    for step in range(80):
        for _ in range(rng.randint(0, 8)):
            counts[str(rng.randint(1, 40))] = [rng.randint(0, 100), rng.randint(0, 100)]
        for inode in list(counts):
            roll = rng.random()
            if roll < 0.1:
                del counts[inode]
            elif roll < 0.15:
                counts[inode] = [rng.randint(0, 5), rng.randint(0, 5)]  # the inode reused: counts start over
            elif roll < 0.6:
                counts[inode] = [counts[inode][0] + rng.randint(0, 1000), counts[inode][1] + rng.randint(0, 50)]
        rows = []
        for inode, values in sorted(counts.items()):
            row = objects.get(inode)
            if row is None or list(row[1]) != values:
                row = objects[inode] = (("1", inode, "tcp"), tuple(values))
            rows.append(row)
        outs = []
        for budget, given in ((reused, rows), (fresh, [(labels, tuple(values)) for labels, values in rows])):
            snap = Snapshot()
            snap.group_rows((SOCKET_SENT, SOCKET_RECEIVED)).extend(given)
            outs.append({m.name: sorted(r) for m, r in budget.apply(snap).series.items()})
        assert outs[0] == outs[1], step


def test_a_budget_told_the_changes_gives_what_one_that_compares_every_row_gives():
    """Sockets come, go, count on, are reused and renamed; one budget is told each collect's
    changes (some collects are not told, or told against another collect than its last), the
    other compares every row: both give the same series."""
    rng = random.Random(7)
    told, compared = Budget({"socket": 5}), Budget({"socket": 5})
    rows: dict[tuple, tuple] = {}
    group = (SOCKET_SENT, SOCKET_RECEIVED)
    for step in range(150):
        before = dict(rows)
        for _ in range(rng.randint(0, 6)):
            rows[("1", str(rng.randint(1, 40)), "tcp")] = (rng.randint(0, 9), rng.randint(0, 9))
        for labels in list(rows):
            roll = rng.random()
            if roll < 0.08:
                del rows[labels]
            elif roll < 0.1:  # renamed: the same socket under other labels
                rows[(rng.choice("123"), labels[1], "tcp")] = rows.pop(labels)
            elif roll < 0.5:
                rows[labels] = (rows[labels][0] + rng.randint(0, 99), rows[labels][1] + rng.randint(0, 9))
        changed = [(labels, values) for labels, values in rows.items() if before.get(labels) != values]
        changed += rng.sample(list(rows.items()), min(2, len(rows)))  # a probe may tell of rows that did not change
        # and of a row as gone that it tells of again (a socket made anew under the same labels)
        gone = [labels for labels in before if labels not in rows] + [labels for labels, _ in changed[:1]]
        outs = []
        for budget, changes in ((told, Changes(step - rng.choice((1, 1, 1, 1, 2)), step, changed, gone)),
                                (compared, None)):
            snap = Snapshot()
            snap.group_rows(group).extend(rows.items())
            if changes is not None and rng.random() < 0.9:
                snap.changes[group] = changes
            outs.append({m.name: sorted(r) for m, r in budget.apply(snap).series.items()})
        assert outs[0] == outs[1], step


def test_a_budget_given_sockets_as_columns_gives_what_one_given_rows_gives():
    """Sockets of two protocols come, count on, get their own series, lose them and end; one
    budget is given them as Columns (in no order), the other as rows: both keep the same sockets,
    sum the same `other` and count the same folded. Every socket counts at every step, each by
    its own amount, so that which are kept does not hang on how ties are broken. No series ever
    goes back, and the last values of every series there was sum to what the sockets counted."""
    rng = random.Random(11)
    by_columns, by_rows = Budget({"socket": 5}), Budget({"socket": 5})
    counts: dict[int, list[int]] = {}  # inode -> [protocol, sent, received]
    ever: dict[int, list[int]] = {}  # every socket there was -> its last counts
    shown: dict[tuple, int] = {}  # every series there was -> its last value
    protocols = ("tcp", "udp")
    for step in range(150):
        for inode in [i for i in counts if rng.random() < 0.08]:
            del counts[inode]
        for _ in range(rng.randint(0, 4) if step else 30):
            counts[rng.randint(1, 10**9)] = [rng.randint(0, 1), 0, 0]
        for c in counts.values():  # now and then one socket outdoes the kept ones, and takes a slot
            c[1] += rng.randint(1, 10**6 if rng.random() < 0.97 else 10**9)
            c[2] += rng.randint(1, 10**4)
        inodes = list(counts)
        rng.shuffle(inodes)

        def labels(at: list[int]) -> list[tuple]:
            return [("1", str(inodes[i]), protocols[counts[inodes[i]][0]]) for i in at]
        columns, rows = Snapshot(), Snapshot()
        columns.groups[(SOCKET_SENT, SOCKET_RECEIVED)] = Columns(
            np.array(inodes, np.int64), np.array([counts[i][1:] for i in inodes], np.int64).reshape(-1, 2),
            np.array([counts[i][0] for i in inodes], np.intp), protocols, np.ones(len(inodes), np.int64), labels)
        rows.group_rows((SOCKET_SENT, SOCKET_RECEIVED)).extend(zip(labels(list(range(len(inodes)))),
                                                                   (tuple(counts[i][1:]) for i in inodes)))
        outs = [{m.name: sorted(r) for m, r in budget.apply(snap).series.items()}
                for budget, snap in ((by_columns, columns), (by_rows, rows))]
        assert outs[0] == outs[1], step
        assert by_columns.kept("socket") == by_rows.kept("socket"), step
        assert by_columns.folded() == by_rows.folded() and by_columns.folded_total() == by_rows.folded_total()
        ever.update((inode, c[1:]) for inode, c in counts.items())
        for name, rows in outs[0].items():
            for labels, v in rows:
                assert v >= shown.get((name, labels), 0), (step, name, labels)
                shown[(name, labels)] = v
    assert by_rows.folded_total()["socket"] > 100  # sockets were folded, promoted and demoted alike
    for i, metric in enumerate((SOCKET_SENT, SOCKET_RECEIVED)):
        assert sum(v for (name, _), v in shown.items() if name == metric.name) == sum(c[i] for c in ever.values())



def test_a_budget_told_which_columns_changed_gives_what_one_that_compares_and_ranks_every_row_gives(monkeypatch):
    """Sockets handed on as a probe does, in the same order while none come or go, a few counting at
    each collect; now and then some come or go, or one outdoes a kept one. One budget is told which
    rows changed since the probe's last collect (Columns.told; some collects it never sees, so that
    the next is told against another than its last; some not told; some told of rows that did not
    change) and keeps its kept rows in place while no entity
    comes, goes or changes slot; the other compares every row and ranks every entity at every
    collect. Both give the same series, keep the same sockets and fold the same."""
    class Compares(Budget):
        @classmethod
        def _keep_slots(cls, st, activity):  # never the steady path
            return False
    rng = random.Random(19)
    told, compared = Budget({"socket": 5}), Compares({"socket": 5})
    steady, compares = [], []  # what each _keep_slots of the told budget said; the rows each comparison took
    keep_slots = Budget._keep_slots.__func__
    monkeypatch.setattr(Budget, "_keep_slots", classmethod(
        lambda cls, st, activity: steady.append(keep_slots(cls, st, activity)) or steady[-1]))
    rows_differ = budget_module.rows_differ
    applying = [None]
    monkeypatch.setattr(budget_module, "rows_differ",
                        lambda a, b: (applying[0] is told and compares.append(len(a))) or rows_differ(a, b))
    counts: dict[int, list[int]] = {i: [i % 2, 10 * i, i] for i in range(1, 31)}  # inode -> protocol, sent, received
    order, busy = list(counts), {1, 2, 3}
    protocols = ("tcp", "udp")
    for step in range(1, 200):
        before = {i: list(c) for i, c in counts.items()}
        if rng.random() < 0.1:  # some go, some come: the order is another
            for inode in rng.sample(order, 2):
                del counts[inode]
                busy.discard(inode)
            for _ in range(rng.randint(0, 3)):
                counts[rng.randint(100, 10**6)] = [rng.randint(0, 1), 0, 0]
            order = list(counts)
            rng.shuffle(order)
        for inode in order:  # the busy few count at every collect, the others now and then; one by a lot
            if inode in busy or rng.random() < 0.02:
                counts[inode][1] += rng.randint(1, 10**3 if rng.random() < 0.99 else 10**8)
                counts[inode][2] += rng.randint(0, 9)
        changed = [at for at, i in enumerate(order) if before.get(i) != counts[i]] + rng.sample(range(len(order)), 1)
        if rng.random() < 0.05:  # a collect the budgets never see (the agent's failed after the probe's)
            continue
        outs = []
        for budget, hint in ((told, (step - 1, step, np.array(sorted(set(changed)), np.intp))), (compared, None)):
            def labels(at: list[int]) -> list[tuple]:
                return [("1", str(order[i]), protocols[counts[order[i]][0]]) for i in at]
            snap = Snapshot()
            snap.groups[(SOCKET_SENT, SOCKET_RECEIVED)] = Columns(
                np.array(order, np.int64), np.array([counts[i][1:] for i in order], np.int64).reshape(-1, 2),
                np.array([counts[i][0] for i in order], np.intp), protocols, np.ones(len(order), np.int64), labels,
                told=hint if rng.random() < 0.95 else None)
            applying[0] = budget
            outs.append({m.name: sorted(r) for m, r in budget.apply(snap).series.items()})
        assert outs[0] == outs[1], step
        assert told.kept("socket") == compared.kept("socket"), step
        assert told.folded() == compared.folded() and told.folded_total() == compared.folded_total(), step
    assert steady.count(True) > 60 and steady.count(False) > 5  # the steady path, and slots that changed
    assert len(compares) < 70  # the told budget compared rows only where it was not told, or they moved


def test_a_socket_that_loses_its_series_shows_what_it_counted_once_more_and_other_goes_on():
    """One slot: a busy socket holds it while another is folded; then the other outdoes it: its
    series begins at zero (what it counted goes to `other`), the idle one's shows what it counted
    one last time, and what it counts later goes to `other`; given as rows or as Columns alike."""
    steps = [{1: 100, 2: 1}, {1: 150, 2: 1}, {1: 150, 2: 1001}, {1: 160, 2: 1101}]
    shown = [{"1": 0, "other": 101}, {"1": 50, "other": 101}, {"1": 50, "2": 0, "other": 1101},
             {"2": 100, "other": 1111}]
    for as_columns in (False, True):
        budget = Budget({"socket": 1})
        for sent, series in zip(steps, shown):
            snap, ids = Snapshot(), list(sent)
            rows = [(("1", str(i), "tcp"), (sent[i], 0)) for i in ids]
            if as_columns:
                snap.groups[(SOCKET_SENT, SOCKET_RECEIVED)] = Columns(
                    np.array(ids, np.int64), np.array([v for _, v in rows], np.int64), np.zeros(len(ids), np.intp),
                    ("tcp",), np.ones(len(ids), np.int64), lambda at: [rows[i][0] for i in at])
            else:
                snap.group_rows((SOCKET_SENT, SOCKET_RECEIVED)).extend(rows)
            out = budget.apply(snap).values(SOCKET_SENT)
            assert {labels[1]: v for labels, v in out.items()} == series, (as_columns, sent)


def test_a_budget_given_connections_as_columns_with_their_rtt_beside_gives_what_one_given_rows_gives():
    """Connections come, count on, get their own series, lose them and end, half of them with an
    RTT: one budget is given their counters as Columns (in no order) and their RTT as rows, the
    other all as rows. Both keep the same connections, show the same RTT and sum the same
    `other`. Every connection counts at every step, each by its own amount."""
    rng = random.Random(13)
    by_columns, by_rows = Budget({"connection": 5}), Budget({"connection": 5})
    counts: dict[int, list[int]] = {}  # id -> its four counts
    for step in range(150):
        for id_ in [i for i in counts if rng.random() < 0.08]:
            del counts[id_]
        for _ in range(rng.randint(0, 4) if step else 30):
            counts[rng.randint(1, 10**9)] = [0, 0, 0, 0]
        for c in counts.values():
            c[0] += rng.randint(1, 10**6 if rng.random() < 0.97 else 10**9)
            c[1] += rng.randint(0, 3)
        ids = list(counts)
        rng.shuffle(ids)

        def labels(at: list[int]) -> list[tuple]:
            return [(f"10.0.0.1:{ids[i]}", "10.0.0.2:80", "1") for i in at]
        rtt = [((local, remote), rng.random()) for local, remote, _ in labels(list(range(len(ids))))
               if rng.random() < 0.5]
        columns, rows = Snapshot(), Snapshot()
        columns.groups[tcp.CONN_GROUP] = Columns(np.array(ids, np.int64), np.array([counts[i] for i in ids], np.int64),
                                                 np.zeros(len(ids), np.intp), ("",), None, labels)
        rows.group_rows(tcp.CONN_GROUP).extend(zip(labels(list(range(len(ids)))), (tuple(counts[i]) for i in ids)))
        for snap in (columns, rows):
            snap.rows(tcp.CONN_RTT).extend(rtt)
        outs = [{m.name: sorted(r) for m, r in budget.apply(snap).series.items()}
                for budget, snap in ((by_columns, columns), (by_rows, rows))]
        assert outs[0] == outs[1], step
        assert by_columns.kept("connection") == by_rows.kept("connection"), step
        assert by_columns.folded() == by_rows.folded() and by_columns.folded_total() == by_rows.folded_total()
    assert by_rows.folded_total()["connection"] > 100


def test_a_budget_given_threads_as_two_groups_of_columns_gives_what_one_given_rows_gives():
    """Threads come, count on, get their own series, lose them and end: one budget is given them as
    the sched probe gives them (their times in nanoseconds and their waits as one group of Columns,
    their switches as another, two rows a thread), the other as rows of seconds. Both keep the
    same threads and sum the same `other` (to the rounding of a float), of switches by kind."""
    rng = random.Random(17)
    by_columns, by_rows = Budget({"thread": 5}), Budget({"thread": 5})
    counts: dict[int, list[int]] = {}  # pid << 32 | tid -> cpu ns, run-queue ns, waits, voluntary, involuntary
    for step in range(150):
        for id_ in [i for i in counts if rng.random() < 0.08]:
            del counts[id_]
        for _ in range(rng.randint(0, 4) if step else 30):
            counts[rng.randint(1, 4000) << 32 | rng.randint(1, 4 * 10**6)] = [0] * 5
        for c in counts.values():
            c[0] += rng.randint(1, 10**6 if rng.random() < 0.97 else 10**9)
            for i in range(1, 5):
                c[i] += rng.randint(0, 10**4)
        ids = list(counts)
        rng.shuffle(ids)
        values = np.array([counts[i] for i in ids], np.int64).reshape(-1, 5)

        def labels(at: list[int]) -> list[tuple]:
            return [(str(ids[i] >> 32), str(ids[i] & 0xFFFFFFFF), "worker") for i in at]
        columns, rows = Snapshot(), Snapshot()
        every = labels(list(range(len(ids))))
        entities = np.array(ids, np.int64)
        columns.groups[sched.THREAD_GROUP] = Columns(entities, values[:, :3], np.zeros(len(ids), np.intp), ("",),
                                                     entities >> 32, labels, units=(10**9, 10**9, 1))
        columns.groups[(sched.THREAD_SWITCHES,)] = Columns(  # a row id each, stable while the thread lives
            (entities[:, None] * 2 + [0, 1]).ravel(), values[:, 3:].reshape(-1, 1), np.tile([0, 1], len(ids)),
            sched.SWITCH_KINDS, np.repeat(entities >> 32, 2),
            lambda at: [every[i // 2] + (sched.SWITCH_KINDS[i % 2],) for i in at], entities=np.repeat(entities, 2))
        for metric, at, unit in ((sched.THREAD_CPU, 0, 10**9), (sched.THREAD_RUNQ, 1, 10**9),
                                 (sched.THREAD_RUNQ_WAITS, 2, 1)):
            rows.rows(metric).extend((thread, counts[i][at] / unit if unit != 1 else counts[i][at])
                                     for thread, i in zip(every, ids))
        rows.rows(sched.THREAD_SWITCHES).extend((thread + (kind,), counts[i][3 + k]) for thread, i in zip(every, ids)
                                                for k, kind in enumerate(sched.SWITCH_KINDS))
        outs = [{(m.name, labels): v for m, r in budget.apply(snap).series.items() for labels, v in r}
                for budget, snap in ((by_columns, columns), (by_rows, rows))]
        assert outs[0] == pytest.approx(outs[1], rel=1e-12), step
        assert by_columns.kept("thread") == by_rows.kept("thread"), step
        assert by_columns.folded() == by_rows.folded() and by_columns.folded_total() == by_rows.folded_total()
    assert by_rows.folded_total()["thread"] > 100
    assert ("drums_thread_context_switches_total", ("other", "other", "other", "involuntary")) in outs[0]


def test_a_probe_that_fails_to_collect_leaves_the_budget_as_it_was():
    """Processes (rows: CPU and sent bytes from one probe, memory from another) and sockets (Columns)
    count on; at the second collect the probe of CPU and sockets fails, after it added some of its
    rows. That collect shows none of its series; the third shows what a budget that never saw the
    second shows: no entity lost or gained a slot, `other` counted nothing twice."""
    rng = random.Random(5)

    def collect(step: int) -> Snapshot:
        pids = range(1, 9)
        snap = _snap({str(p): 1.0 * p * step + rng.random() for p in pids},
                     sent={str(p): (9 - p) * step * 10 for p in pids}, mem={str(p): p * 100 for p in pids})
        inodes = np.arange(1, 41, dtype=np.int64)
        snap.groups[(SOCKET_SENT, SOCKET_RECEIVED)] = Columns(
            inodes, np.stack([inodes * step * rng.randint(1, 3), inodes]).T.copy(), np.zeros(40, np.intp), ("tcp",),
            np.ones(40, np.int64), lambda at: [("1", str(inodes[i]), "tcp") for i in at])
        return snap
    snaps = [collect(step) for step in (1, 2, 3)]
    snaps[1].leave_out((CPU, SENT, SOCKET_SENT, SOCKET_RECEIVED))
    failing, steady = Budget({"process": 2, "socket": 3}), Budget({"process": 2, "socket": 3})
    failing.apply(snaps[0])
    steady.apply(snaps[0])
    during = failing.apply(snaps[1]).series
    assert {m.name for m in during} == {MEM.name} and len(during[MEM]) == 3  # two kept and other
    after = [{m.name: sorted(rows) for m, rows in budget.apply(snaps[2]).series.items()}
             for budget in (failing, steady)]
    assert after[0] == after[1]
    assert after[0][CPU.name][-1][0] == ("other", "other") and len(after[0][SOCKET_SENT.name]) == 4
    assert failing.folded_total() == steady.folded_total()


def test_a_kept_row_whose_id_values_and_stamps_stay_is_given_again_without_its_labels():
    """Threads as the sched probe gives them (Columns with their names' words as stamps): a kept
    thread that did not run is given as the same row, its labels not asked for; one that ran, or
    was renamed, is made anew; a thread that gets a slot has its labels made."""
    names = {1: b"alpha", 2: b"beta", 3: b"gamma"}
    cpu = {1: 30, 2: 20, 3: 10}  # the two busiest get the slots
    asked = []

    def collect() -> list:
        snap = Snapshot()
        ids = np.array(sorted(names), np.int64)
        stamps = np.array([[int.from_bytes(names[i].ljust(16, b"\0")[:8], "little"),
                            int.from_bytes(names[i].ljust(16, b"\0")[8:], "little")] for i in ids], np.uint64)
        labels = {i: ("7", str(i), names[i].decode()) for i in names}
        snap.groups[sched.THREAD_GROUP] = Columns(
            ids, np.array([[cpu[i] * 10**9, 0, 0] for i in ids], np.int64), np.zeros(3, np.intp), ("",),
            np.full(3, 7, np.int64), lambda at: [asked.append(int(ids[i])) or labels[int(ids[i])] for i in at],
            units=(10**9, 10**9, 1), stamps=stamps.__getitem__)
        return budget.apply(snap).groups[sched.THREAD_GROUP]

    budget = Budget({"thread": 2})
    first = collect()
    assert sorted(asked) == [1, 2] and [row[0] for row in first[:2]] == [("7", "1", "alpha"), ("7", "2", "beta")]
    asked.clear()
    assert all(a is b for a, b in zip(collect()[:2], first[:2])) and asked == []  # neither ran
    cpu[1] += 1
    names[2] = b"renamed"
    third = collect()
    assert sorted(asked) == [1, 2] and third[:2] == [(("7", "1", "alpha"), (1.0, 0.0, 0)),
                                                      (("7", "2", "renamed"), (0.0, 0.0, 0))]
    asked.clear()
    assert all(a is b for a, b in zip(collect()[:2], third[:2])) and asked == []
    names[1] = b"idle"  # renamed while nothing ran: the rows as before, but for its name
    assert collect()[:2] == [(("7", "1", "idle"), (1.0, 0.0, 0)), third[1]] and asked == [1]


def test_the_rtt_of_a_connection_the_columns_lack_shows_while_a_slot_is_free():
    """A connection older than the agent has an RTT and no entry (it never moved under the
    probes): its RTT is shown in a slot the columns leave free, the first by its addresses."""
    budget = Budget({"connection": 2})
    rtt = {("a:1", "b:1"): 0.1, ("e:1", "f:1"): 0.3, ("c:1", "d:1"): 0.2}
    for connections, shown in (([("a:1", "b:1")], {("a:1", "b:1"), ("c:1", "d:1")}),
                               ([("a:1", "b:1"), ("x:1", "y:1")], {("a:1", "b:1")})):  # no slot free
        snap = Snapshot()
        snap.groups[tcp.CONN_GROUP] = Columns(
            np.arange(1, len(connections) + 1, dtype=np.int64), np.ones((len(connections), 4), np.int64),
            np.zeros(len(connections), np.intp), ("",), None, lambda at: [(*connections[i], "1") for i in at])
        snap.rows(tcp.CONN_RTT).extend(rtt.items())
        assert budget.apply(snap).values(tcp.CONN_RTT) == {k: rtt[k] for k in shown}
        assert budget.kept("connection") == {*connections} | shown


def test_the_edges_of_a_graph_ask_the_labels_of_the_sockets_on_their_ports_only():
    """A ROS 1 edge names its socket's endpoints: of a thousand connections given as Columns, the
    join makes the labels of those on the edge's ports only (both ends), and finds its own."""
    from drums.graph.join import EDGE_RETRANSMITS, _socket_edges
    from drums.graph.model import Connection
    n = 1000
    labels = [(f"10.0.0.1:{40000 + i}", f"10.0.0.2:{(5000 + i) % 6000}", "1") for i in range(n)]
    made = []
    snap = Snapshot()
    snap.groups[tcp.CONN_GROUP] = Columns(
        np.arange(n, dtype=np.int64), np.array([[i, 0, 0, 0] for i in range(n)], np.int64), np.zeros(n, np.intp),
        ("",), None, lambda at: made.extend(at) or [labels[i] for i in at],
        np.array([(40000 + i) << 16 | (5000 + i) % 6000 for i in range(n)], np.int64))
    out = Snapshot()
    _socket_edges([Connection("/t", "/a", "/b", "tcpros", labels[7][0], labels[7][1])], snap, out)
    assert out.values(EDGE_RETRANSMITS) == {("/t", "/a", "/b"): 7} and made == [7]


def test_the_budget_counts_its_entities_by_their_changes_as_a_count_of_all_would():
    """Processes come, go, are renamed (their rows change labels, the process stays) and hold rows
    in some metrics only: what the budget keeps, folds and has ever folded is what counting every
    process at every step gives."""
    rng = random.Random(5)
    b = Budget({"process": 3})
    procs: dict[str, dict] = {}
    folded_before, total = set(), 0
    for step in range(120):
        for _ in range(rng.randint(0, 3)):
            procs[str(rng.randint(1, 30))] = {"name": "a", "cpu": 0.0, "sent": None, "mem": None}
        for pid, p in list(procs.items()):
            roll = rng.random()
            if roll < 0.08:
                del procs[pid]
                continue
            if roll < 0.12:
                p["name"] = rng.choice("abc")
            p["cpu"] += rng.choice((0.0, 0.0, rng.random()))
            p["sent"] = rng.choice((None, (p["sent"] or 0) + rng.randint(0, 99)))
            p["mem"] = rng.choice((None, rng.randint(1, 9)))
        snap = Snapshot()
        for pid, p in procs.items():
            snap.add(CPU, (pid, p["name"]), p["cpu"])
            if p["sent"] is not None:
                snap.add(SENT, (pid, p["name"], "tcp"), p["sent"])
            if p["mem"] is not None:
                snap.add(MEM, (pid, p["name"]), p["mem"])
        b.apply(snap)
        kept = b.kept("process")
        assert kept <= procs.keys() and len(kept) == min(3, len(procs)), step
        folded = procs.keys() - kept
        total += len(folded - folded_before)
        folded_before = folded
        assert (b.folded()["process"], b.folded_total()["process"]) == (len(folded), total), step


def test_readme_metric_table_is_current():
    with open("README.md") as f:
        text = f.read()
    assert docs.rewrite(text) == text, "run `make readme`"


def test_readme_figures_are_those_of_the_last_bench_run():
    """Every figure in the README's "Measured" section comes from bench/results.json, which
    `make bench` writes: a figure no run printed cannot stand there."""
    sys.path.insert(0, "bench")
    try:
        import readme
    finally:
        sys.path.remove("bench")
    with open("README.md") as f:
        text = f.read()
    assert readme.rewrite(text, readme.load()) == text, "run `make readme` (or `make bench`)"


def test_non_additive_gauges_have_no_other_series():
    rtt = Metric("drums_tcp_connection_smoothed_rtt_seconds", GAUGE, "rtt", ("local", "remote"), additive=False)
    b = Budget({"connection": 1})
    snap = Snapshot()
    snap.add(rtt, ("a:1", "b:2"), 0.001)
    snap.add(rtt, ("c:3", "d:4"), 0.002)
    out = b.apply(snap).values(rtt)
    assert len(out) == 1 and ("other", "other") not in out


def test_readme_platform_table_is_that_of_the_last_kernel_runs():
    """The README's table of kernels comes from tests/kernels/results.json, which `make
    test-kernels` writes: a kernel no run proved cannot stand there."""
    from tests.kernels import readme as kernels
    with open("README.md") as f:
        text = f.read()
    assert kernels.rewrite(text, kernels.load()) == text, "run `make test-kernels` (or python -m tests.kernels.readme README.md)"

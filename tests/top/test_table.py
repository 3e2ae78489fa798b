"""The pure parts of `drums top`: reading /metrics back, rates and percentiles, messages lost, an
agent's state, and tables sorted, filtered and fitted to a width."""
from __future__ import annotations

import math

from drums.client import Sample
from drums.exporters import prometheus
from drums.metrics import COUNTER, HISTOGRAM, Histogram, Metric, Snapshot
from drums.exposition import rows as parse
from drums.top.losses import Losses
from drums.top.model import CONNECTING, DOWN, STALE, UP, Model
from drums.top.poll import Poll
from drums.top.rates import quantile, rate
from drums.top.table import ELLIPSIS, Column, Row, Table, arrange, cut, fit, line

BYTES = Metric("drums_socket_sent_bytes_total", COUNTER, "x", ("local", "process"))
WAITS = Metric("drums_process_runqueue_latency_seconds", HISTOGRAM, "x", ("pid",), (0.001, 0.01))


def test_metrics_are_read_back_as_our_exporter_wrote_them():
    snap = Snapshot()
    hostile = 'a "quoted" path\\with\nnewline {x="1"} 7'
    snap.add(BYTES, (hostile, "p q"), 12)
    snap.add(BYTES, ("", "plain"), 3.5)
    snap.add(WAITS, ("42",), Histogram([2, 5], 0.25, 9))
    text = prometheus.render(snap).decode()
    rows = parse(text, ["drums_socket_sent_bytes_total", "drums_process_runqueue_latency_seconds_bucket", "absent"])
    assert rows["drums_socket_sent_bytes_total"] == [({"local": hostile, "process": "p q"}, 12.0),
                                                     ({"local": "", "process": "plain"}, 3.5)]
    assert [(labels["le"], v) for labels, v in rows["drums_process_runqueue_latency_seconds_bucket"]] == \
        [("0.001", 2), ("0.01", 5), ("+Inf", 9)]
    assert rows["absent"] == []


def test_rates_take_a_counter_that_went_back_as_one_that_began_again():
    assert rate(30, 10, 2.0) == 10
    assert rate(4, 10, 2.0) == 2  # the process restarted: 4 since then
    assert rate(5, None, 1.0) is None and rate(5, 4, 0) is None


def test_quantiles_interpolate_within_the_bucket_like_histogram_quantile():
    before = {0.001: 10, 0.002: 10, 0.004: 10, math.inf: 10}
    now = {0.001: 10, 0.002: 60, 0.004: 110, math.inf: 110}  # 50 waits in (1, 2] ms, 50 in (2, 4] ms
    assert quantile(0.5, now, before) == 0.002
    assert math.isclose(quantile(0.99, now, before), 0.002 + 0.002 * 49 / 50)
    assert quantile(0.99, {0.001: 0, math.inf: 3}, {0.001: 0, math.inf: 0}) == 0.001  # in +Inf: the last bound
    assert quantile(0.99, now, now) is None  # nothing waited


def test_messages_lost_count_from_when_they_first_flowed_once_missing_at_three_reads():
    losses = Losses()
    reads = iter(range(100))

    def lost(links, published, taken):
        return losses.lost("/t", next(reads), links, published, taken)
    both = [("/pub", "/a"), ("/pub", "/b")]
    assert lost(both, {"/pub": 5}, {"/a": 0, "/b": 0}) is None  # not matched yet
    assert lost(both, {"/pub": 10}, {"/a": 3, "/b": 2}) == 0  # counted from here on
    assert lost(both, {"/pub": 20}, {"/a": 13, "/b": 11}) == 0  # 1 in flight to /b, or lost
    assert lost(both, {"/pub": 30}, {"/a": 23, "/b": 21}) == 0  # still missing: two reads
    assert lost(both, {"/pub": 40}, {"/a": 33, "/b": 31}) == 1  # three reads: lost
    assert losses.lost("/t", 4, both, {"/pub": 40}, {"/a": 33, "/b": 31}) == 1  # the same read again
    assert lost(both, {"/pub": 50}, {"/a": 43, "/b": 40}) == 1  # another one missing: not yet
    assert lost(both, {"/pub": 60}, {"/a": 52, "/b": 50}) == 1  # in flight to /a once: never counted
    assert lost(both, {"/pub": 70}, {"/a": 63, "/b": 60}) == 2  # /b's second one, three reads on
    assert lost(both[:1], {"/pub": 80}, {"/a": 73}) == 0  # /b left: counted again
    assert lost(both[:1], {"/pub": 2}, {"/a": 1}) == 0  # the publisher restarted
    assert lost(both[:1], {"/pub": 12}, {"/a": 12}) == 0  # one was in flight at the first read
    assert lost(both[:1], {"/pub": 22}, {"/a": 22}) == 0
    assert [lost(both[:1], {"/pub": 32 + i}, {"/a": 31 + i}) for i in range(3)] == [0, 0, 1]
    assert lost(both, {"/pub": 50}, {"/b": 30}) == 0  # /a is not measured: /b alone
    assert lost(both, {}, {"/a": 40, "/b": 40}) is None  # the publisher is not measured


NAME = Column("name", "NAME", name=True, least=6, keep=9)
HOST = Column("host", "HOST", name=True, least=4, keep=0)
CPU = Column("cpu", "CPU", lambda v: "-" if v is None else f"{v:.0f}%", keep=8)
PID = Column("pid", "PID", keep=3)


def test_rows_sort_by_any_column_with_unknown_values_last_and_groups_kept_together():
    rows = [Row("a", {"name": "/b", "cpu": 5}), Row("b", {"name": "/a", "cpu": None}),
            Row("c", {"name": "/C", "cpu": 50}), Row("c1", {"name": "eth0"}, group="c")]
    table = Table("nodes", [NAME, CPU], rows, sort="cpu", spark="cpu")
    assert [r.key for r in arrange(table, "cpu", False, "")] == ["c", "c1", "a", "b"]
    assert [r.key for r in arrange(table, "cpu", True, "")] == ["a", "c", "c1", "b"]
    assert [r.key for r in arrange(table, "name", False, "")] == ["b", "a", "c", "c1"]  # any case
    assert [r.key for r in arrange(table, "name", False, "/c")] == ["c", "c1"]  # its group comes along


def test_a_table_fits_its_width_by_cutting_names_then_dropping_the_least_kept_columns():
    long = "/a_namespace_of_its_own/and_a_long_node_name"
    texts = [[long, "vm", "12%", "4242"], ["/short", "vm", "1%", "7"]]
    titles = ["NAME", "HOST", "CPU", "PID"]
    columns = [NAME, HOST, CPU, PID]
    assert fit(columns, titles, texts, None) == [len(long), 4, 3, 4]
    assert fit(columns, titles, texts, 200) == [len(long), 4, 3, 4]  # all fits: the optional HOST too
    widths = fit(columns, titles, texts, 30)
    assert widths == [30 - 3 - 4 - 2, 0, 3, 4]  # HOST (optional) goes before a name is cut
    rendered = line(columns, texts[0], widths)
    assert len(rendered) == 30 and ELLIPSIS in rendered and rendered.endswith("12% 4242")
    assert fit(columns, titles, texts, 14) == [10, 0, 3, 0]  # PID (kept least) goes next
    assert all(len(line(columns, t, fit(columns, titles, texts, w))) <= w for t in texts for w in range(1, 60))


def test_a_cut_name_keeps_its_start_and_its_end():
    assert cut("/namespace/node_name", 20) == "/namespace/node_name"
    assert cut("/namespace/node_name", 10) == "/na…e_name"
    assert len(cut("x" * 40, 7)) == 7 and cut("abc", 1) == ELLIPSIS and cut("abc", 0) == ""


def test_an_agent_is_up_stale_or_down_by_its_last_answers():
    model = Model(["http://a:9969"], interval=1.0)
    agent = model.agents[0]
    assert agent.state(0, 1.0) == CONNECTING
    model.polled(0, "arm", Poll(100.0, 100.0))
    now = agent.last_ok
    assert agent.state(now + 2, 1.0) == UP
    assert agent.state(now + 4, 1.0) == STALE  # no fresh answer for three intervals: a slow agent
    model.polled(0, "arm", Poll(101.0, 101.0, stale="the ros2 reader did not answer"))
    assert agent.state(now, 1.0) == STALE and agent.before.graph_at == 100.0
    model.failed(0, "http://a:9969: Connection refused")
    assert agent.state(now, 1.0) == DOWN
    model.polled(0, "arm", Poll(105.0, 105.0))
    assert agent.state(now, 1.0) == UP and agent.before is None  # back: rates start again


def test_a_sample_right_after_another_does_not_make_a_rate():
    model = Model(["http://a:9969"], interval=1.0)

    def sample(at: float) -> Sample:
        model.sampled(Sample("arm:host:", 1, at, {}))
        before, latest = model.samples["arm:host:"]
        return before and before.time
    assert [sample(t) for t in (10.0, 11.0, 11.01, 12.0, 12.0)] == [None, 10.0, 10.0, 11.01, 11.01]

"""One topic on a robot: who publishes and takes it and how fast, its bandwidth, what each
subscriber lost, its publishers' Deadline QoS, and its edges (publisher -> subscriber)."""
from grafana_foundation_sdk.builders import dashboard

from deploy.mixin.config import Config
from deploy.mixin.dashboards.panels import (MESSAGES_PER_SECOND, ROW, Scope, base, legend, query, table_panel,
                                            timeseries_panel)

UID = "drums-topic"
EDGE = legend("publisher") + " -> " + legend("subscriber")


def build(cfg: Config) -> dashboard.Dashboard:
    s = Scope(cfg, "robot", "topic")
    host = cfg.host_label
    return (
        base("Topic", UID, "Rates, bandwidth, loss and Deadline QoS of a topic, and its edges.", cfg,
             "robot", "topic")
        .with_row(dashboard.Row("Rate"))
        .with_panel(timeseries_panel("Published", "Messages per second each node published (rcl_publish), and "
                                     "their sum on the robot.", MESSAGES_PER_SECOND,
                                     query(s("drums:topic_messages_published:rate1m"), legend("node", host)),
                                     query(s.without_job("drums_robot:topic_messages_published:rate1m"),
                                           legend(cfg.robot_label) + " all publishers")))
        .with_panel(timeseries_panel("Taken", "Messages per second each subscribing node took (rcl_take).",
                                     MESSAGES_PER_SECOND,
                                     query(s("drums:topic_messages_taken:rate1m"), legend("node", host))))
        .with_panel(timeseries_panel("Publish period and deadline", "Time between two messages of each "
                                     "publisher, p50 and p99 over a minute, beside the Deadline QoS it offers "
                                     "(DrumsTopicDeadlineMissed) and the longest period expected_rates.yaml "
                                     "allows the topic (DrumsTopicBelowExpectedRate).", "s",
                                     query(s("drums:topic_publish_period_seconds:p50_rate1m"), legend("node") + " p50"),
                                     query(s("drums:topic_publish_period_seconds:p99_rate1m"), legend("node") + " p99"),
                                     # every agent of the ROS domain reports every publisher's QoS
                                     query(f"max by ({cfg.robot_label}, topic, node) "
                                           f"({s('drums_topic_deadline_seconds')})", legend("node") + " deadline"),
                                     # the same on every robot: no robot label to select by
                                     query('drums:topic_longest_expected_period_seconds{topic="$topic"}',
                                           "expected at most")))
        .with_panel(timeseries_panel("Deadlines missed", "Deadlines each publisher let pass without a message, "
                                     "and each subscription without taking one, in the last minute, as the kernel "
                                     "saw its messages (DrumsTopicDeadlineMissed, DrumsSubscriptionDeadlineMissed).",
                                     "short",
                                     query(s("drums:topic_deadlines_missed:increase1m"), legend("node") + " publishing"),
                                     query(s("drums:topic_take_deadlines_missed:increase1m"),
                                           legend("node") + " taking")))
        .with_panel(timeseries_panel("Lost", "Share of the topic's messages on the robot each subscriber did not "
                                     "take (DrumsTopicMessagesLost).", "percentunit",
                                     query(s("drums:topic_messages_lost:ratio_rate1m"), legend("node", host))))
        .with_row(dashboard.Row("Bandwidth"))
        .with_panel(timeseries_panel("Sent over UDP", "Bytes per second of each publisher's samples over UDP: each "
                                     "sample once, and on the wire (a copy per reader, and repairs).", "Bps",
                                     query(s("drums:topic_sent_bytes:rate1m"), legend("node") + " samples"),
                                     query(s("drums:topic_sent_wire_bytes:rate1m"), legend("node") + " wire")))
        .with_panel(timeseries_panel("Edge bandwidth", "Bytes per second each subscriber received from each "
                                     "publisher.", "Bps", query(s("drums:edge_received_bytes:rate1m"), EDGE)))
        .with_row(dashboard.Row("Edges"))
        .with_panel(table_panel("Edges", "Each publisher -> subscriber edge of the topic: bytes and samples per "
                                "second, and the share of repairs or TCP retransmits.",
                                query(s("drums:edge_received_bytes:rate1m"), instant=True),
                                query(s("drums:edge_samples_received:rate1m"), instant=True),
                                query(s("drums:edge_retransmitted_bytes:ratio_rate1m"), instant=True), width=ROW))
        .with_panel(timeseries_panel("Edge bandwidth against its last hour", "The last minute's bytes per second over "
                                     "the last hour's (DrumsEdgeBandwidthCollapsed).", "percentunit",
                                     query(f"{s('drums:edge_received_bytes:rate1m')} / "
                                           f"{s('drums:edge_received_bytes:rate1h')}", EDGE)))
        .with_panel(timeseries_panel("Edge repairs and retransmits", "Share of an edge's bytes that were RTPS repairs "
                                     "or TCP retransmits (DrumsEdgeRetransmitsHigh).", "percentunit",
                                     query(s("drums:edge_retransmitted_bytes:ratio_rate1m"), EDGE)))
    )

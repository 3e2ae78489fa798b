"""One ROS node: its process's CPU, memory, context switches and run-queue waits, the topics it
publishes and takes, and its edges to other nodes."""
from grafana_foundation_sdk.builders import dashboard

from deploy.mixin.config import Config
from deploy.mixin.dashboards.panels import (MESSAGES_PER_SECOND, Scope, base, heatmap_panel, legend, query,
                                            table_panel, timeseries_panel)

UID = "drums-node"


def build(cfg: Config) -> dashboard.Dashboard:
    s = Scope(cfg, "robot", "host", "node")
    edges = Scope(cfg, "robot")  # an edge is counted on its subscriber's host
    shared = "Nodes of one process share these numbers (drums_node_info: nodes_in_process, same pid)."
    return (
        base("ROS node", UID, "CPU, memory and scheduling of a node's process, its topics and its edges.", cfg,
             "robot", "host", "node")
        .with_row(dashboard.Row("Process"))
        .with_panel(table_panel("Node", "The node's process, how it was mapped to it, and how many nodes that "
                                "process holds.", query(s("drums_node_info"), instant=True)))
        .with_panel(timeseries_panel("CPU", f"CPU cores the node's process keeps busy. {shared}", "none",
                                     query(s("drums:node_cpu_seconds:rate1m"), legend("node"))))
        .with_panel(timeseries_panel("Resident memory", f"Resident memory of the node's process. {shared}", "bytes",
                                     query(s("drums_node_resident_memory_bytes"), legend("node"))))
        .with_panel(timeseries_panel("Memory growth", "Growth of the resident memory over 30 minutes: a steady rise "
                                     "is a leak (DrumsNodeMemoryLeak).", "Bps",
                                     query(s("drums:node_resident_memory_bytes:deriv30m"), legend("node"))))
        .with_panel(timeseries_panel("Context switches", "Per second: voluntary (blocked) and involuntary "
                                     "(preempted).", "none",
                                     query(s("drums:node_context_switches:rate1m"), legend("node", "kind"))))
        .with_panel(timeseries_panel("Run-queue wait", "How long the node's threads waited for a CPU once runnable: "
                                     "median and 99th percentile over a minute.", "s",
                                     query(s("drums:node_runqueue_latency_seconds:histogram_quantile"),
                                           legend("node") + " p{{quantile}}")))
        .with_panel(heatmap_panel("Run-queue waits", "Waits per second in each histogram bucket.",
                                  f"sum by (le) (rate({s('drums_node_runqueue_latency_seconds_bucket')}"
                                  f"[$__rate_interval]))"))
        .with_row(dashboard.Row("Topics"))
        .with_panel(timeseries_panel("Published", "Messages per second the node published, per topic (rcl_publish).",
                                     MESSAGES_PER_SECOND,
                                     query(s("drums:topic_messages_published:rate1m"), legend("topic"))))
        .with_panel(timeseries_panel("Taken", "Messages per second the node took, per topic (rcl_take).",
                                     MESSAGES_PER_SECOND,
                                     query(s("drums:topic_messages_taken:rate1m"), legend("topic"))))
        .with_panel(timeseries_panel("Sent over UDP", "Bytes per second of the node's samples sent over UDP, each "
                                     "sample once, per topic.", "Bps",
                                     query(s("drums:topic_sent_bytes:rate1m"), legend("topic"))))
        .with_panel(timeseries_panel("Lost", "Share of each topic's messages on the robot that the node did not take.",
                                     "percentunit",
                                     query(s("drums:topic_messages_lost:ratio_rate1m"), legend("topic"))))
        .with_row(dashboard.Row("Edges"))
        .with_panel(table_panel("Edges", "Bytes per second on each edge the node publishes or subscribes on.",
                                query(edges("drums:edge_received_bytes:rate1m", 'publisher=~"$node"'), instant=True),
                                query(edges("drums:edge_received_bytes:rate1m", 'subscriber=~"$node"'), instant=True),
                                unit="Bps"))
    )

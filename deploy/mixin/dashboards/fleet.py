"""The fleet at a glance: robots, hosts and their agents, the alerts that fire, and the nodes and
topics that fare worst, across every robot or those picked."""
from grafana_foundation_sdk.builders import dashboard

from deploy.mixin.config import Config
from deploy.mixin.dashboards.panels import (ROW, Scope, base, legend, query, stat_panel, table_panel,
                                            timeseries_panel)

UID = "drums-fleet"
TOP = 10


def worst(title: str, description: str, expr: str, unit: str):
    return table_panel(f"{title} (top {TOP})", description, query(f"topk({TOP}, {expr})", instant=True), unit=unit)


def build(cfg: Config) -> dashboard.Dashboard:
    s = Scope(cfg, "robot")
    robot, host = cfg.robot_label, cfg.host_label
    up = s("up")
    local_nodes = s("drums_node_info", 'pid!=""')
    firing = s.without_job("ALERTS", 'alertstate="firing"')
    alerts = s.without_job("ALERTS", 'alertname=~"Drums.*"')
    p99 = s("drums:node_runqueue_latency_seconds:histogram_quantile", 'quantile="0.99"')
    return (
        base("Fleet", UID, "Robots, hosts and agents, firing alerts, and the worst nodes and topics.", cfg, "robot")
        .with_row(dashboard.Row("Fleet"))
        .with_panel(stat_panel("Robots", "Robots with at least one Drums target.", "none",
                               f"count(count by ({robot}) ({up}))"))
        .with_panel(stat_panel("Hosts", "Hosts with a Drums target.", "none",
                               f"count(count by ({robot}, {host}) ({up}))"))
        .with_panel(stat_panel("Agents up", "Drums agents Prometheus scrapes successfully.", "none", f"sum({up})"))
        .with_panel(stat_panel("Agents down", "Drums targets Prometheus cannot scrape.", "none", f"sum(1 - {up})"))
        .with_panel(stat_panel("ROS nodes", "Nodes with a process on a host of the robots.", "none",
                               f"count({local_nodes})"))
        .with_panel(stat_panel("Firing alerts", "Drums alerts firing now.", "none", f"count({firing}) or vector(0)"))
        .with_row(dashboard.Row("Alerts"))
        .with_panel(table_panel("Alerts", "Drums alerts firing or pending (about to fire), with what they name.",
                                query(alerts, instant=True), width=ROW))
        .with_row(dashboard.Row("Robots and hosts"))
        .with_panel(table_panel("Agents", "Every Drums target: 1 when scraped, 0 when down.", query(up, instant=True),
                                width=ROW))
        .with_panel(timeseries_panel("Host CPU busy", "Share of each host's CPU time not idle.", "percentunit",
                                     query(s("drums:host_cpu_busy:ratio_rate1m"), legend(robot, host))))
        .with_panel(timeseries_panel("Host memory used", "Share of each host's memory not available to processes.",
                                     "percentunit", query(s("drums:host_memory_used:ratio"), legend(robot, host))))
        .with_row(dashboard.Row("Anomalies"))
        .with_panel(timeseries_panel(
            "Anomalous series by category", "Series `drums detect` calls anomalous now, stacked by category "
            "(cpu, memory, io, network): a spike is something that changed at once; its incidents are on "
            "the detector's /anomalies.", "none",
            query(f"sum by (category) ({s.without_job('drums_anomalous_series')})", legend("category")),
            width=ROW, stacked=True))
        .with_row(dashboard.Row("Worst nodes and topics"))
        .with_panel(worst("Nodes by CPU", "CPU cores each node's process keeps busy.",
                          s("drums:node_cpu_seconds:rate1m"), "none"))
        .with_panel(worst("Nodes by memory growth", "Growth of each node's resident memory over 30 minutes.",
                          s("drums:node_resident_memory_bytes:deriv30m"), "Bps"))
        .with_panel(worst("Nodes by run-queue wait p99",
                          "How long a node's threads waited for a CPU: 99th percentile over a minute.", p99, "s"))
        .with_panel(worst("Subscribers by loss", "Share of a topic's messages on its robot a subscribing node "
                          "did not take.", s("drums:topic_messages_lost:ratio_rate1m"), "percentunit"))
    )

"""Recording rules: the rates, ratios and quantiles that alerts and dashboards share, per node,
topic and edge as the agent names them.

Names follow the Prometheus convention level:metric:operations. Level `drums` keeps every label of
the agent's series (target labels, node, topic, edge); level `drums_robot` sums a topic over all
publishers on all hosts of one robot. Rules that read other recorded series sit after them in the
same group, so both are evaluated at the same instant.
"""
from deploy.mixin.config import Config

# Grafana's and the alerts' windows: four scrapes at 15 s, and an hour as an edge's own baseline.
WINDOW = "1m"
BASELINE = "1h"
LEAK_WINDOW = "30m"  # long enough that a garbage collector's sawtooth averages out
QUANTILES = ("0.5", "0.99")


def record(name: str, expr: str, **labels: str) -> dict:
    rule = {"record": name, "expr": expr}
    if labels:
        rule["labels"] = labels
    return rule


def rate(cfg: Config, name: str, window: str = WINDOW, *extra: str) -> str:
    return f"rate({cfg.series(name, *extra)}[{window}])"


def node_rules(cfg: Config) -> list[dict]:
    quantiles = [record("drums:node_runqueue_latency_seconds:histogram_quantile",
                        f"histogram_quantile({q}, {rate(cfg, 'drums_node_runqueue_latency_seconds_bucket')})",
                        quantile=q) for q in QUANTILES]
    return [
        record("drums:node_cpu_seconds:rate1m", rate(cfg, "drums_node_cpu_seconds_total")),
        record("drums:node_context_switches:rate1m", rate(cfg, "drums_node_context_switches_total")),
        *quantiles,
        record("drums:node_resident_memory_bytes:deriv30m",
               f"deriv({cfg.series('drums_node_resident_memory_bytes')}[{LEAK_WINDOW}])"),
    ]


def host_rules(cfg: Config) -> list[dict]:
    cpu = "drums_host_cpu_seconds_total"
    idle = "sum without (mode) (%s)" % rate(cfg, cpu, WINDOW, 'mode=~"idle|iowait"')
    return [
        record("drums:host_cpu_busy:ratio_rate1m", f"1 - {idle} / sum without (mode) ({rate(cfg, cpu)})"),
        record("drums:host_memory_used:ratio", f"1 - {cfg.series('drums_host_memory_available_bytes')}\n"
                                               f"/ {cfg.series('drums_host_memory_total_bytes')}"),
    ]


def topic_rules(cfg: Config) -> list[dict]:
    robot = cfg.robot_label
    published = "drums:topic_messages_published:rate1m"
    robot_published = "drums_robot:topic_messages_published:rate1m"
    lost = "drums:topic_messages_lost:rate1m"
    return [
        record(published, rate(cfg, "drums_topic_messages_published_total")),
        record("drums:topic_messages_published:rate1h", rate(cfg, "drums_topic_messages_published_total", BASELINE)),
        record("drums:topic_messages_taken:rate1m", rate(cfg, "drums_topic_messages_taken_total")),
        record("drums:topic_sent_bytes:rate1m", rate(cfg, "drums_topic_sent_bytes_total")),
        record("drums:topic_sent_wire_bytes:rate1m", rate(cfg, "drums_topic_sent_wire_bytes_total")),
        # Each publisher's buckets are its own (the edges of the kernel's slots that counted any).
        *(record(f"drums:topic_publish_period_seconds:p{round(q * 100)}_rate1m",
                 f"histogram_quantile({q}, {rate(cfg, 'drums_topic_publish_period_seconds_bucket')})")
          for q in (0.5, 0.99)),
        record("drums:topic_deadlines_missed:increase1m",
               f"increase({cfg.series('drums_topic_deadlines_missed_total')}[{WINDOW}])"),
        record("drums:topic_take_deadlines_missed:increase1m",
               f"increase({cfg.series('drums_topic_take_deadlines_missed_total')}[{WINDOW}])"),
        # Publishers and subscribers of one topic may sit on different hosts of the robot.
        record(robot_published, f"sum by ({robot}, topic) ({published})"),
        # Per subscribing node: what the robot's publishers published that the node did not take.
        # Takes the agent could not name a node for (node "unknown") are no one subscriber's.
        record(lost, f"{robot_published}\n- on ({robot}, topic) group_right\n"
                     f'drums:topic_messages_taken:rate1m{{node!="unknown"}}'),
        record("drums:topic_messages_lost:ratio_rate1m",
               f"{lost}\n/ on ({robot}, topic) group_left\n{robot_published}"),
        # What expected_rates.yaml asks of each topic as a period, for the dashboard to draw beside
        # the measured one: the least rate on a robot is the longest period it allows.
        *(record("drums:topic_longest_expected_period_seconds", f"vector({1 / least:g})", topic=topic)
          for topic, least in sorted(cfg.expected_rates.items())),
    ]


def edge_rules(cfg: Config) -> list[dict]:
    received = "drums:edge_received_bytes:rate1m"
    # ROS 2 over UDP: the writer's repairs are the wire bytes beyond each sample once. ROS 1 over
    # TCP: retransmitted segments, each taken as one MSS, against the bytes sent (the agent counts
    # no segments sent, so this is an upper bound).
    repaired = f"(drums:edge_received_wire_bytes:rate1m - {received})\n/ {received}"
    retransmitted = (f"{rate(cfg, 'drums_edge_tcp_retransmits_total')} * {cfg.tcp_mss_bytes:g}\n"
                     f"/ {rate(cfg, 'drums_edge_sent_bytes_total')}")
    return [
        record(received, rate(cfg, "drums_edge_received_bytes_total")),
        record("drums:edge_received_bytes:rate1h", rate(cfg, "drums_edge_received_bytes_total", BASELINE)),
        record("drums:edge_received_wire_bytes:rate1m", rate(cfg, "drums_edge_received_wire_bytes_total")),
        record("drums:edge_samples_received:rate1m", rate(cfg, "drums_edge_samples_received_total")),
        record("drums:edge_retransmitted_bytes:ratio_rate1m", f"(\n{repaired}\n)\nor\n(\n{retransmitted}\n)"),
    ]


def recording_groups(cfg: Config) -> list[dict]:
    return [{"name": "drums-node.rules", "rules": node_rules(cfg)},
            {"name": "drums-host.rules", "rules": host_rules(cfg)},
            {"name": "drums-topic.rules", "rules": topic_rules(cfg)},
            {"name": "drums-edge.rules", "rules": edge_rules(cfg)}]

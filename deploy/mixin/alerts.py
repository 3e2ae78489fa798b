"""Alerting rules. Each names what it is about (host, node, topic or edge) in its summary and
description, carries a severity, and links to its section of docs/runbooks.md.

critical: the robot is blind or a part of it stopped (agent down, host unreachable, node gone,
topic stalled); warning: something degrades and needs a look; info: the monitoring itself is less
exact than it could be.
"""
from deploy.mixin.config import Config

INFO_LABELS = "pid, process, mapped_by, nodes_in_process"  # what drums_node_info adds to a node


def alert(cfg: Config, name: str, expr: str, for_: str, severity: str, summary: str, description: str,
          **labels: str) -> dict:
    """`labels`: set besides the severity, e.g. the topic of one of several rules of one alert
    (rules of one name need labels of their own, or promtool calls them duplicates)."""
    return {"alert": name, "expr": expr, "for": for_, "labels": {"severity": severity, **labels},
            "annotations": {"summary": summary, "description": description,
                            "runbook_url": f"{cfg.runbook_url}#{name.lower()}"}}


class Words:
    """The labels an alert's text names things by, as template references."""

    def __init__(self, cfg: Config):
        robot, host = cfg.label(cfg.robot_label), cfg.label(cfg.host_label)
        self.host = f"host {host} of robot {robot}"
        self.robot = f"robot {robot}"
        self.node = f"node {cfg.label('node')} on {self.host}"
        self.topic_node = f"{cfg.label('node')} on {cfg.label('topic')} ({self.host})"
        # an edge is measured on one of its ends: UDP and socket bytes at the subscriber, TCP
        # retransmits at the publisher
        self.edge = (f"edge {cfg.label('publisher')} -> {cfg.label('subscriber')} on {cfg.label('topic')} "
                     f"(seen on {self.host})")


def agent_alerts(cfg: Config) -> list[dict]:
    w, probe = Words(cfg), cfg.label("probe")
    fallbacks = "|".join(cfg.fallback_attach_types)
    return [
        alert(cfg, "DrumsAgentDown", f"{cfg.series('up')} == 0", cfg.agent_down_for, "critical",
              f"Drums agent down on {w.host}",
              f"Prometheus has not scraped the Drums agent at {cfg.label('instance')} ({w.host}) for "
              f"{cfg.agent_down_for}: the agent stopped or the host is down. Nothing of this host is measured."),
        alert(cfg, "DrumsHostUnreachable",
              f"min by ({cfg.robot_label}, target) ({cfg.series('drums_latency_loss_ratio')}) == 1",
              cfg.host_unreachable_for, "critical",
              f"Host {cfg.label('target')} of {w.robot} unreachable",
              f"Every Drums agent of {w.robot} that probes host {cfg.label('target')} lost all its probes "
              f"for {cfg.host_unreachable_for}: the host is down or cut off the network."),
        alert(cfg, "DrumsProbeDetached", cfg.series("drums_probe_attached") + " == 0", cfg.probe_detached_for,
              "warning", f"Drums probe {probe} not collecting on {w.host}",
              f"The {probe} probe of the Drums agent on {w.host} is attached neither with eBPF nor with its "
              f"fallback: what it measures is missing from this host's metrics."),
        alert(cfg, "DrumsProbeDegraded",
              cfg.series("drums_probe_attached", f'attach_type=~"{fallbacks}"') + " == 1",
              cfg.probe_degraded_for, "info", f"Drums probe {probe} on its fallback on {w.host}",
              f"The {probe} probe of the Drums agent on {w.host} runs without eBPF ({cfg.label('attach_type')}): "
              f"it counts less, and less exactly (README: Without eBPF)."),
        alert(cfg, "DrumsProbeCollectFailing", cfg.series("drums_probe_collect_success") + " == 0",
              cfg.probe_collect_failing_for, "warning", f"Drums probe {probe} failing to collect on {w.host}",
              f"Every collect of the {probe} probe of the Drums agent on {w.host} has failed for "
              f"{cfg.probe_collect_failing_for}: its series are missing or stale."),
        alert(cfg, "DrumsGraphStale", cfg.series("drums_graph_stale") + " == 1", cfg.graph_stale_for, "warning",
              f"Drums graph stale on {w.host}",
              f"The {cfg.label('adapter')} graph adapter of the Drums agent on {w.host} has failed for "
              f"{cfg.graph_stale_for}: node, topic and edge metrics are named after the last good graph, "
              f"and new nodes are not counted."),
        alert(cfg, "DrumsProbeMapNearFull", cfg.series("drums_probe_map_fill_ratio") + f" > {cfg.map_fill_ratio:g}",
              cfg.map_fill_for, "warning", f"Drums BPF map {probe}/{cfg.label('map')} nearly full on {w.host}",
              f"The {cfg.label('map')} map of the {probe} probe on {w.host} is {{{{ $value | humanizePercentage }}}} "
              f"full: once full, new entities are not counted (drums_probe_dropped_events_total)."),
        alert(cfg, "DrumsProbeEventsDropped",
              f"rate({cfg.series('drums_probe_dropped_events_total')}[5m]) > 0", cfg.dropped_events_for, "warning",
              f"Drums probe {probe} dropping events on {w.host}",
              f"The {probe} probe on {w.host} drops {{{{ $value | humanize }}}} events/s because a BPF map is "
              f"full: some sockets, threads or writers are not counted."),
        alert(cfg, "DrumsBudgetFolding", cfg.series("drums_budget_folded_entities") + " > 0", cfg.budget_folding_for,
              "info", f"Drums agent folding {cfg.label('kind')} series on {w.host}",
              f"{{{{ $value }}}} {cfg.label('kind')} entities on {w.host} are over the agent's cardinality budget "
              f"and summed into series labelled other: raise the agent's --max-* limit of that kind to see them."),
    ]


def node_alerts(cfg: Config) -> list[dict]:
    w = Words(cfg)
    on_target = ", ".join(cfg.target_labels)
    # A node that left this agent's graph while the agent still answers. Only nodes with a PID
    # here are this host's: every agent of a ROS 2 domain lists the other hosts' nodes too.
    local = cfg.series("drums_node_info", 'pid!=""')
    gone = (f"(\n  group without ({INFO_LABELS}) (max_over_time({local}[{cfg.node_gone_lookback}]))\n"
            f"  unless\n  group without ({INFO_LABELS}) ({cfg.series('drums_node_info')})\n)\n"
            f"and on ({on_target}) ({cfg.series('up')} == 1)")
    return [
        alert(cfg, "DrumsNodeGone", gone, cfg.node_gone_for, "critical",
              f"ROS node {cfg.label('node')} gone on {w.host}",
              f"The {w.node} was in the graph within the last {cfg.node_gone_lookback} and is not any more, "
              f"while the agent runs: the node exited, crashed or was renamed."),
        alert(cfg, "DrumsNodeMemoryLeak",
              f"drums:node_resident_memory_bytes:deriv30m > {cfg.memory_leak_bytes_per_second:g}",
              cfg.memory_leak_for, "warning", f"ROS node {cfg.label('node')} leaking memory on {w.host}",
              f"The resident memory of {w.node} has grown by {{{{ $value | humanize1024 }}}}B/s over 30 minutes, "
              f"for {cfg.memory_leak_for}."),
        alert(cfg, "DrumsNodeCpuSaturated", f"drums:node_cpu_seconds:rate1m > {cfg.node_cpu_saturated_cores:g}",
              cfg.node_cpu_saturated_for, "warning", f"ROS node {cfg.label('node')} CPU-bound on {w.host}",
              f"The process of {w.node} has kept {{{{ $value | humanize }}}} CPU cores busy for "
              f"{cfg.node_cpu_saturated_for}: a single-threaded executor cannot keep up."),
        alert(cfg, "DrumsHostCpuSaturated", f"drums:host_cpu_busy:ratio_rate1m > {cfg.host_cpu_busy_ratio:g}",
              cfg.host_cpu_saturated_for, "warning", f"CPU saturated on {w.host}",
              f"The CPUs of {w.host} have been {{{{ $value | humanizePercentage }}}} busy for "
              f"{cfg.host_cpu_saturated_for}: nodes wait for a CPU."),
        alert(cfg, "DrumsNodeRunqueueLatencyHigh",
              f'drums:node_runqueue_latency_seconds:histogram_quantile{{quantile="0.99"}} > '
              f"{cfg.runqueue_latency_p99_seconds:g}",
              cfg.runqueue_latency_for, "warning", f"ROS node {cfg.label('node')} waits for CPU on {w.host}",
              f"The threads of {w.node} waited {{{{ $value | humanizeDuration }}}} or more on a run queue "
              f"(p99 over a minute) for {cfg.runqueue_latency_for}: callbacks start late."),
    ]


def topic_alerts(cfg: Config) -> list[dict]:
    w = Words(cfg)
    published = "drums:topic_messages_published:rate1m"
    steady = ",".join(f'topic!="{t}"' for t in cfg.topic_stalled_ignore)
    rules = [
        alert(cfg, "DrumsTopicStalled",
              f"{published}{{{steady}}} == 0\nand\n"
              f"drums:topic_messages_published:rate1h >= {cfg.topic_stalled_min_rate:g}",
              cfg.topic_stalled_for, "critical", f"Topic {cfg.label('topic')} stalled: {w.topic_node}",
              f"{w.topic_node} published at least {cfg.topic_stalled_min_rate:g} messages/s over the last hour "
              f"and none for {cfg.topic_stalled_for} or more."),
    ]
    for topic, least in sorted(cfg.expected_rates.items()):
        rules.append(alert(
            cfg, "DrumsTopicBelowExpectedRate",
            f'drums_robot:topic_messages_published:rate1m{{topic="{topic}"}} < {least:g}',
            cfg.topic_below_expected_for, "warning", f"Topic {topic} below {least:g}/s on {w.robot}",
            f"{topic} is published at {{{{ $value | humanize }}}} messages/s on {w.robot}, summed over its "
            f"publishers, below the {least:g}/s expected of it (deploy/mixin/expected_rates.yaml).", topic=topic))
    rules += [
        alert(cfg, "DrumsTopicDeadlineMissed",
              f"drums:topic_deadlines_missed:increase1m >= {cfg.deadline_misses:g}",
              cfg.deadline_missed_for, "warning", f"Deadline QoS missed: {w.topic_node}",
              f"{w.topic_node} let {{{{ $value | humanize }}}} of the deadlines its Deadline QoS offers "
              f"(drums_topic_deadline_seconds) pass without a message in the last minute, for "
              f"{cfg.deadline_missed_for}: its subscribers see deadline-missed events."),
        alert(cfg, "DrumsSubscriptionDeadlineMissed",
              f"drums:topic_take_deadlines_missed:increase1m >= {cfg.deadline_misses:g}",
              cfg.deadline_missed_for, "warning", f"Deadline QoS missed in taking: {w.topic_node}",
              f"Subscriber {w.topic_node} let {{{{ $value | humanize }}}} of the deadlines its Deadline QoS "
              f"requests pass without taking a message in the last minute, for {cfg.deadline_missed_for}: it "
              f"sees deadline-missed events."),
        alert(cfg, "DrumsTopicMessagesLost",
              f"drums:topic_messages_lost:ratio_rate1m > {cfg.topic_loss_ratio:g}", cfg.topic_loss_for, "warning",
              f"Messages lost on {cfg.label('topic')}: {cfg.label('node')} ({w.host})",
              f"Subscriber {w.topic_node} took {{{{ $value | humanizePercentage }}}} fewer messages than the "
              f"publishers of {w.robot} published on the topic, for {cfg.topic_loss_for}."),
    ]
    def flooding(matchers: str, limit: float, **labels: str) -> dict:
        return alert(cfg, "DrumsTopicFlooding", f"{published}{{{matchers}}} > {limit:g}", cfg.topic_flood_for,
                     "warning", f"{cfg.label('node')} floods {cfg.label('topic')} on {w.host}",
                     f"{w.topic_node} publishes {{{{ $value | humanize }}}} messages/s, more than the {limit:g}/s "
                     f"allowed on this topic, for {cfg.topic_flood_for}.", **labels)
    for topic, limit in sorted(cfg.topic_flood_rates.items()):
        rules.append(flooding(f'topic="{topic}"', limit, topic=topic))
    rules.append(flooding(",".join(f'topic!="{t}"' for t in sorted(cfg.topic_flood_rates)), cfg.topic_flood_rate))
    return rules


def edge_alerts(cfg: Config) -> list[dict]:
    w = Words(cfg)
    received, baseline = "drums:edge_received_bytes:rate1m", "drums:edge_received_bytes:rate1h"
    return [
        alert(cfg, "DrumsEdgeBandwidthCollapsed",
              f"{received} < {cfg.edge_bandwidth_collapse_ratio:g} * {baseline}\nand\n"
              f"{baseline} > {cfg.edge_bandwidth_min_bytes_per_second:g}",
              cfg.edge_bandwidth_collapse_for, "warning", f"Bandwidth collapsed on {w.edge}",
              f"The {w.edge} carries {{{{ $value | humanize1024 }}}}B/s, less than "
              f"{cfg.edge_bandwidth_collapse_ratio:g} of its own mean over the last hour."),
        alert(cfg, "DrumsEdgeRetransmitsHigh",
              f"drums:edge_retransmitted_bytes:ratio_rate1m > {cfg.retransmit_ratio:g}", cfg.retransmit_for, "warning",
              f"Retransmits on {w.edge}",
              f"{{{{ $value | humanizePercentage }}}} of the bytes on the {w.edge} are repairs (RTPS) or "
              f"TCP retransmits, for {cfg.retransmit_for}: the link loses packets."),
        alert(cfg, "DrumsQoSIncompatible", cfg.series("drums_edge_qos_incompatible") + " == 1",
              cfg.qos_incompatible_for, "critical", f"QoS {cfg.label('policy')} keeps apart the {w.edge}",
              f"The subscriber gets no message from the publisher on the {w.edge}: their "
              f"{cfg.label('policy')} QoS policies cannot connect."),
    ]


def alert_groups(cfg: Config) -> list[dict]:
    return [{"name": "drums-agent.alerts", "rules": agent_alerts(cfg)},
            {"name": "drums-node.alerts", "rules": node_alerts(cfg)},
            {"name": "drums-topic.alerts", "rules": topic_alerts(cfg)},
            {"name": "drums-edge.alerts", "rules": edge_alerts(cfg)}]

"""One host (or several): its CPU, memory, network, storage and TCP, the round trips its agent
measures to other hosts, and the ROS nodes and processes that use it most."""
from grafana_foundation_sdk.builders import dashboard

from deploy.mixin.config import Config
from deploy.mixin.dashboards.panels import Scope, base, legend, query, table_panel, timeseries_panel

UID = "drums-host"
RATE = "[$__rate_interval]"  # Grafana's window: at least four scrapes


def build(cfg: Config) -> dashboard.Dashboard:
    s = Scope(cfg, "robot", "host")
    host = cfg.host_label

    def rate(metric: str, *extra: str) -> str:
        return f"rate({s(metric, *extra)}{RATE})"

    return (
        base("Host", UID, "CPU, memory, network, storage and TCP of a host, and its nodes and processes.", cfg,
             "robot", "host")
        .with_row(dashboard.Row("CPU and memory"))
        .with_panel(timeseries_panel("CPU busy", "Share of the host's CPU time not idle (all CPUs).", "percentunit",
                                     query(s("drums:host_cpu_busy:ratio_rate1m"), legend(host))))
        .with_panel(timeseries_panel("CPU by mode", "CPU cores busy in each mode, idle left out.", "none",
                                     query(rate("drums_host_cpu_seconds_total", 'mode!="idle"'), legend(host, "mode"))))
        .with_panel(timeseries_panel("Memory", "Memory in use (without buffers and cache), available, and swap used.",
                                     "bytes",
                                     query(s("drums_host_memory_used_bytes"), legend(host) + " used"),
                                     query(s("drums_host_memory_available_bytes"), legend(host) + " available"),
                                     query(s("drums_host_swap_used_bytes"), legend(host) + " swap used")))
        .with_panel(timeseries_panel("Load", "Run-queue load average.", "none",
                                     query(s("drums_host_load"), legend(host, "period"))))
        .with_row(dashboard.Row("Network and storage"))
        .with_panel(timeseries_panel("Network", "Bytes per second received and sent, per interface.", "Bps",
                                     query(rate("drums_host_network_received_bytes_total"),
                                           legend(host, "interface") + " received"),
                                     query(rate("drums_host_network_sent_bytes_total"),
                                           legend(host, "interface") + " sent")))
        .with_panel(timeseries_panel("Network errors and drops", "Packets per second in error or dropped.", "pps",
                                     *(query(rate(f"drums_host_network_{what}_total"),
                                             legend(host, "interface") + " " + what.replace("_", " "))
                                       for what in ("receive_errors", "transmit_errors", "receive_drops",
                                                    "transmit_drops"))))
        .with_panel(timeseries_panel("Disk I/O", "Bytes per second read and written, per block device.", "Bps",
                                     query(rate("drums_host_disk_read_bytes_total"), legend(host, "device") + " read"),
                                     query(rate("drums_host_disk_written_bytes_total"),
                                           legend(host, "device") + " written")))
        .with_panel(timeseries_panel("Filesystems used", "Share of each filesystem an unprivileged user cannot write.",
                                     "percentunit",
                                     query(f"1 - {s('drums_host_filesystem_free_bytes')} / "
                                           f"{s('drums_host_filesystem_size_bytes')}", legend(host, "mountpoint"))))
        .with_row(dashboard.Row("TCP and round trips"))
        .with_panel(timeseries_panel("TCP retransmits and resets", "Per second, all connections of the host.", "none",
                                     query(rate("drums_tcp_retransmits_total"), legend(host) + " retransmits"),
                                     query(rate("drums_tcp_resets_sent_total"), legend(host) + " resets sent"),
                                     query(rate("drums_tcp_resets_received_total"), legend(host) + " resets received")))
        .with_panel(timeseries_panel("Round trip to other hosts",
                                     "Mean and longest round trip of each round of probes (drums agent "
                                     "--latency-mesh or latency jobs).", "s",
                                     query(s("drums_latency_rtt_mean_seconds"), legend(host, "target") + " mean"),
                                     query(s("drums_latency_rtt_max_seconds"), legend(host, "target") + " max")))
        .with_panel(timeseries_panel("Probes lost", "Share of each round's probes left unanswered.", "percentunit",
                                     query(s("drums_latency_loss_ratio"), legend(host, "target"))))
        .with_row(dashboard.Row("Nodes and processes"))
        .with_panel(table_panel("ROS nodes", "The nodes with a process on the host, and how each was mapped to it.",
                                query(s("drums_node_info", 'pid!=""'), instant=True)))
        .with_panel(timeseries_panel("Node CPU", "CPU cores each node's process keeps busy.", "none",
                                     query(s("drums:node_cpu_seconds:rate1m"), legend(host, "node"))))
        .with_panel(table_panel("Processes by CPU (top 10)", "CPU cores each process keeps busy.",
                                query(f"topk(10, {rate('drums_process_cpu_seconds_total')})", instant=True)))
        .with_panel(table_panel("Processes by resident memory (top 10)", "Resident set size of each process.",
                                query(f"topk(10, {s('drums_process_resident_memory_bytes')})", instant=True),
                                unit="bytes"))
    )

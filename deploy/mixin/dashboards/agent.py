"""The Drums agent itself: whether each probe collects and how (eBPF or a fallback), how long
collecting takes, how full the BPF maps are, what the cardinality budget folds, the graph it
reads, and what the agent process and its scrapes cost."""
from grafana_foundation_sdk.builders import dashboard

from deploy.mixin.config import Config
from deploy.mixin.dashboards.panels import Scope, base, legend, query, table_panel, timeseries_panel

UID = "drums-agent"
RATE = "[$__rate_interval]"


def build(cfg: Config) -> dashboard.Dashboard:
    s = Scope(cfg, "robot", "host")
    host = cfg.host_label
    return (
        base("Agent", UID, "Probe state, collect time, BPF map fill, folded series and cost of the Drums agents.", cfg,
             "robot", "host")
        .with_row(dashboard.Row("Probes"))
        .with_panel(table_panel("Probe state", "Each probe's attach type (eBPF, or a fallback such as proc or "
                                "sock_diag; none when it is detached) and whether its last collect succeeded.",
                                query(s("drums_probe_attached"), instant=True),
                                query(s("drums_probe_collect_success"), instant=True)))
        .with_panel(timeseries_panel("Collect time", "How long each probe's last collect took, and the whole "
                                     "snapshot.", "s",
                                     query(s("drums_probe_collect_duration_seconds"), legend(host, "probe")),
                                     query(s("drums_agent_collect_duration_seconds"), legend(host) + " snapshot")))
        .with_panel(timeseries_panel("BPF map fill", "Used share of each BPF hash map (DrumsProbeMapNearFull).",
                                     "percentunit",
                                     query(s("drums_probe_map_fill_ratio"), legend(host, "probe", "map"))))
        .with_panel(timeseries_panel("Events dropped", "Events per second a probe could not count because a map was "
                                     "full (DrumsProbeEventsDropped).", "none",
                                     query(f"rate({s('drums_probe_dropped_events_total')}{RATE})",
                                           legend(host, "probe"))))
        .with_row(dashboard.Row("Budget and graph"))
        .with_panel(timeseries_panel("Folded entities", "Processes, threads, sockets and connections over the "
                                     "cardinality budget, summed into series labelled other (DrumsBudgetFolding).",
                                     "none", query(s("drums_budget_folded_entities"), legend(host, "kind"))))
        .with_panel(timeseries_panel("Graph", "Entities of the graph the agent names its series after, and whether "
                                     "its adapter fails (stale).", "none",
                                     query(s("drums_graph_entities"), legend(host, "kind")),
                                     query(s("drums_graph_stale"), legend(host, "adapter") + " stale")))
        .with_panel(timeseries_panel("Unattributed topic rows", "Per-process topic and edge counts no one node could "
                                     "be named for (node unknown).", "none",
                                     query(s("drums_topic_unattributed_rows"), legend(host, "kind"))))
        .with_row(dashboard.Row("Cost"))
        .with_panel(timeseries_panel("Agent CPU", "CPU cores the agent keeps busy: the agent process and each "
                                     "helper it started (role graph: the ROS 2 graph reader; diagnostics).", "none",
                                     query(f"rate({s('drums_agent_cpu_seconds_total')}{RATE})", legend(host, "role"))))
        .with_panel(timeseries_panel("Agent memory", "Resident memory of the agent's processes, and what only they "
                                     "use, by role; and the kernel memory its probes' BPF maps hold.", "bytes",
                                     query(s("drums_agent_resident_memory_bytes"), legend(host, "role") + " resident"),
                                     query(s("drums_agent_unique_memory_bytes"), legend(host, "role") + " unique"),
                                     query(f"sum by ({host}) ({s('drums_probe_map_memory_bytes')})",
                                           legend(host) + " BPF maps")))
        .with_panel(timeseries_panel("Scrapes", "How long Prometheus takes to scrape the agent, and the samples it "
                                     "gets.", "s",
                                     query(s("scrape_duration_seconds"), legend(host) + " duration"),
                                     query(s("scrape_samples_scraped"), legend(host) + " samples")))
    )

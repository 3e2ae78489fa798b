"""The graph views of `drums top`, each a Table computed from a Frame: Nodes (with the processes
that hold no node), Topics and Edges. Rates are over the last two polls of the agent that measured
them: a node's counters come from the agent of its own host.
"""
from __future__ import annotations

from collections import defaultdict

from drums import units
from drums.top.losses import Losses
from drums.top.model import AgentState, Frame
from drums.top.poll import Poll
from drums.top.rates import quantile, rate, total
from drums.top.table import Column, Row, Table


def host_column(frame: Frame) -> Column:
    """The host of a row matters once there are several: with one, it goes first when narrow."""
    several = len({a.host for a in frame.agents if a.host}) > 1
    return Column("host", "HOST", name=True, least=6, keep=6 if several else 0)


def count(value) -> str:
    return "-" if value is None else f"{value:.0f}"


def seconds(agent: AgentState, graph: bool = True) -> float:
    """Seconds between the agent's last two polls (of its graph, or of /metrics)."""
    if agent.before is None:
        return 0.0
    if graph:
        return agent.latest.graph_at - agent.before.graph_at
    return agent.latest.metrics_at - agent.before.metrics_at


def histograms(poll: Poll | None, name: str, label: str) -> dict[str, dict[float, float]]:
    """label value -> {upper bound: cumulative count} of a histogram on /metrics."""
    out: dict[str, dict[float, float]] = defaultdict(dict)
    for labels, value in poll.metrics.get(name, ()) if poll else ():
        out[labels[label]][float(labels["le"])] = value
    return out


def jitters(frame: Frame) -> dict[str, float]:
    """topic -> how much later than usual its late messages came over the last interval: p99 less
    p50 of the time between two messages of a publisher, the worst of the topic's publishers (each
    from the agent of its node's host)."""
    mine = owners(frame)
    out: dict[str, float] = {}
    for agent in frame.live():
        if agent.before is None:
            continue
        by_pair: list[dict[tuple[str, str], dict[float, float]]] = []
        for poll in (agent.latest, agent.before):
            pairs: dict[tuple[str, str], dict[float, float]] = defaultdict(dict)
            for labels, value in poll.metrics.get("drums_topic_publish_period_seconds_bucket", ()):
                if mine.get(labels["node"]) is agent:
                    pairs[labels["topic"], labels["node"]][float(labels["le"])] = value
            by_pair.append(pairs)
        for (topic, node), now in by_pair[0].items():
            before = by_pair[1].get((topic, node), {})
            p99, p50 = quantile(0.99, now, before), quantile(0.5, now, before)
            if p99 is not None and p50 is not None:
                out[topic] = max(out.get(topic, 0.0), p99 - p50)
    return out


def summed(poll: Poll | None, name: str, *by: str) -> dict[tuple[str, ...], float]:
    """A /metrics family summed over all labels but `by`."""
    out: dict[tuple[str, ...], float] = defaultdict(float)
    for labels, value in poll.metrics.get(name, ()) if poll else ():
        out[tuple(labels[k] for k in by)] += value
    return out


def owners(frame: Frame) -> dict[str, AgentState]:
    """node name -> the agent of its host, which measures its process and its counters."""
    return {name: a for a in frame.live() for name, v in a.latest.nodes.items()
            if v.get("host") == a.host and v.get("pid") is not None}


COUNTED_AS = {"messages_published_total": "publisher", "sent_bytes_total": "publisher",
              "messages_taken_total": "subscriber"}


def topic_counters(frame: Frame, counter: str) -> dict[str, dict[str, tuple[float, float | None, float]]]:
    """topic -> node -> (now, before, seconds) of a per-topic counter, each from its node's agent
    (where no agent owns the node, the first that counted it). Only the topic's own publishers
    (or subscribers) of the graph: not the counts the agent could not name (node "unknown", as
    from a process of another ROS domain). A count the agent's last poll did not have had not
    begun: it was 0 then (a new publisher's first messages are in its first rate)."""
    mine = owners(frame)
    ends = {(e["topic"], e["node"]) for a in frame.live() for e in a.latest.endpoints
            if e["kind"] == COUNTED_AS[counter]}
    out: dict[str, dict] = defaultdict(dict)
    for agent in frame.live():
        dt = seconds(agent)
        for topic, v in agent.latest.topics.items():
            before = agent.before.topics.get(topic, {}) if agent.before else {}
            for node, now in (v.get(counter) or {}).items():
                if (topic, node) in ends and mine.get(node, agent) is agent and node not in out[topic]:
                    out[topic][node] = (now, (before.get(counter) or {}).get(node, 0 if agent.before else None), dt)
    return out


def rates(counters: dict[str, tuple[float, float | None, float]]) -> dict[str, float | None]:
    return {key: rate(now, before, dt) for key, (now, before, dt) in counters.items()}


NODE_COLUMNS = [
    Column("name", "NAME", name=True, least=12, keep=9),
    Column("pid", "PID", keep=3),
    Column("cpu_percent", "CPU", units.percent, keep=8),
    Column("memory_bytes", "MEM", units.size, keep=7),
    Column("runqueue_p99_seconds", "RUNQ99", units.duration, keep=2),
    Column("published_hz", "PUB", units.rate, keep=5),
    Column("taken_hz", "TAKE", units.rate, keep=5),
    Column("sent_bytes_per_second", "TX", units.bandwidth, keep=4),
    Column("received_bytes_per_second", "RX", units.bandwidth, keep=4),
]


def nodes(frame: Frame, processes: bool = True) -> Table:
    """Every node of the agents' hosts (NAME starts with /), and with `processes` every process
    that holds none (NAME is the process's): CPU % of one core, resident memory, run-queue wait
    p99, messages published and taken per second on all its topics, and bytes per second: a
    node's messages over UDP, a process's sockets."""
    published = {t: rates(c) for t, c in topic_counters(frame, "messages_published_total").items()}
    taken = {t: rates(c) for t, c in topic_counters(frame, "messages_taken_total").items()}
    sent = {t: rates(c) for t, c in topic_counters(frame, "sent_bytes_total").items()}
    received = edge_rates(frame, "received_bytes_total")

    def per_node(by_topic: dict[str, dict[str, float | None]], node: str) -> float | None:
        return total(r.get(node) for r in by_topic.values() if node in r)
    rows, seen = [], set()
    for agent in frame.live():
        now, before = agent.latest, agent.before
        runq = histograms(now, "drums_node_runqueue_latency_seconds_bucket", "node")
        runq_before = histograms(before, "drums_node_runqueue_latency_seconds_bucket", "node") if before else None
        pids = set()
        for name, v in now.nodes.items():
            if v.get("host") != agent.host or v.get("pid") is None:
                continue
            pids.add(str(v["pid"]))
            seen.add(name)
            was = before.nodes.get(name) if before else None
            was = was if was is not None and was.get("pid") == v["pid"] else None  # a restart is another process
            cpu = rate(v.get("cpu_seconds_total"), was.get("cpu_seconds_total") if was else None, seconds(agent))
            rows.append(Row(f"node|{agent.host}|{name}", {
                "host": agent.host, "name": name, "pid": v["pid"],
                "process": now.processes.get(v["pid"], {}).get("name"),
                "cpu_percent": None if cpu is None else 100 * cpu,
                "memory_bytes": v.get("resident_memory_bytes"),
                "runqueue_p99_seconds": quantile(0.99, runq.get(name, {}), runq_before.get(name) if was else None),
                "published_hz": per_node(published, name), "taken_hz": per_node(taken, name),
                "sent_bytes_per_second": per_node(sent, name),
                "received_bytes_per_second": total(r for (_, _, sub), r in received.items() if sub == name)}))
        if processes:
            rows.extend(process_rows(agent, pids))
    for agent in frame.live():  # nodes seen through the middleware whose host no agent here watches
        for name, v in agent.latest.nodes.items():
            if name not in seen:
                seen.add(name)
                rows.append(Row(f"node||{name}", {"host": v.get("host") or None, "name": name}))
    return Table("nodes", [host_column(frame)] + NODE_COLUMNS, rows, sort="cpu_percent", spark="cpu_percent")


def process_rows(agent: AgentState, node_pids: set[str]) -> list[Row]:
    """The processes of an agent's /metrics that hold no node (the budget's `other` left out)."""
    now, before = agent.latest, agent.before
    dt = seconds(agent, graph=False)
    cpu, cpu_before = (summed(p, "drums_process_cpu_seconds_total", "pid", "process") for p in (now, before))
    tx, tx_before = (summed(p, "drums_process_socket_sent_bytes_total", "pid", "process") for p in (now, before))
    rx, rx_before = (summed(p, "drums_process_socket_received_bytes_total", "pid", "process") for p in (now, before))
    runq = histograms(now, "drums_process_runqueue_latency_seconds_bucket", "pid")
    runq_before = histograms(before, "drums_process_runqueue_latency_seconds_bucket", "pid")
    rows = []
    for (pid, name), memory in summed(now, "drums_process_resident_memory_bytes", "pid", "process").items():
        if pid in node_pids or pid == "other":
            continue
        key = (pid, name)  # with the name: a PID taken by another process is another row
        busy = rate(cpu.get(key), cpu_before.get(key), dt)
        rows.append(Row(f"process|{agent.host}|{pid}|{name}", {
            "host": agent.host, "name": name, "pid": int(pid), "process": name,
            "cpu_percent": None if busy is None else 100 * busy, "memory_bytes": memory,
            "runqueue_p99_seconds": quantile(0.99, runq.get(pid, {}), runq_before.get(pid) if key in cpu_before else None),
            "sent_bytes_per_second": rate(tx.get(key), tx_before.get(key), dt),
            "received_bytes_per_second": rate(rx.get(key), rx_before.get(key), dt)}))
    return rows


def edges_of(frame: Frame) -> dict[tuple[str, str, str], list[tuple[AgentState, dict]]]:
    """(topic, publisher, subscriber) -> the agents that list the connection, with its attributes;
    the subscriber's agent first (it counts what arrived), then the publisher's."""
    mine = owners(frame)
    out: dict[tuple, list] = defaultdict(list)
    for agent in frame.live():
        for key, e in agent.latest.edges.items():
            out[key].append((agent, e))
    for key, found in out.items():
        found.sort(key=lambda ae: (mine.get(key[2]) is not ae[0], mine.get(key[1]) is not ae[0]))
    return out


def edge_means(frame: Frame, histogram: str) -> dict[tuple[str, str, str], float | None]:
    """The mean over the last interval of an edge histogram (its count and sum in the graph), from
    the first agent (as edges_of orders them) that counted any."""
    out = {}
    for key, found in edges_of(frame).items():
        out[key] = None
        for agent, e in found:
            now = e.get(histogram)
            was = (agent.before.edges.get(key, {}) if agent.before else {}).get(histogram)
            if now and was and now["count"] > was["count"]:
                out[key] = (now["sum"] - was["sum"]) / (now["count"] - was["count"])
                break
    return out


def edge_rates(frame: Frame, counter: str) -> dict[tuple[str, str, str], float | None]:
    """The rate of an edge counter, from the first agent (as edges_of orders them) that has it (one
    its last poll did not have had not begun: 0 then)."""
    out = {}
    for key, found in edges_of(frame).items():
        out[key] = None
        for agent, e in found:
            if e.get(counter) is not None:
                was = agent.before.edges.get(key, {}) if agent.before else {}
                out[key] = rate(e[counter], was.get(counter, 0 if agent.before else None), seconds(agent))
                break
    return out


TOPIC_COLUMNS = [
    Column("name", "TOPIC", name=True, least=12, keep=9),
    Column("type", "TYPE", name=True, least=8, keep=1),
    Column("publishers", "PUBS", keep=4),
    Column("subscribers", "SUBS", keep=4),
    Column("rate_hz", "RATE", units.rate, keep=8),
    Column("jitter_seconds", "JITTER", units.duration, keep=2),
    Column("bytes_per_second", "BANDWIDTH", units.bandwidth, keep=7),
    Column("lost", "LOST", count, keep=6),
]


def topics(frame: Frame, losses: Losses) -> Table:
    """Each topic: its publishing and subscribing nodes, messages published per second (all its
    publishers), serialized bytes sent per second over UDP, and messages lost since top saw both
    ends (losses.py), and the jitter of its publishers' periods (jitters)."""
    published = topic_counters(frame, "messages_published_total")
    taken = topic_counters(frame, "messages_taken_total")
    sent = topic_counters(frame, "sent_bytes_total")
    jitter = jitters(frame)
    names: dict[str, dict] = {}
    ends: dict[str, dict[str, set]] = defaultdict(lambda: {"publisher": set(), "subscriber": set()})
    links: dict[str, set] = defaultdict(set)
    for agent in frame.live():
        for name, v in agent.latest.topics.items():
            names.setdefault(name, v)
        for e in agent.latest.endpoints:
            ends[e["topic"]][e["kind"]].add(e["node"])
        for topic, pub, sub in agent.latest.edges:
            links[topic].add((pub, sub))
    read = tuple(a.latest.graph_at for a in frame.live())  # a new poll of any agent: a new read
    rows = []
    for name, v in names.items():
        pubs = published.get(name, {})
        rows.append(Row(f"topic|{name}", {
            "name": name, "type": ", ".join(v.get("types") or ()) or None,
            "publishers": len(ends[name]["publisher"]), "subscribers": len(ends[name]["subscriber"]),
            "rate_hz": total(rates(pubs).values()), "jitter_seconds": jitter.get(name),
            "bytes_per_second": total(rates(sent.get(name, {})).values()),
            "lost": losses.lost(name, read, sorted(links[name]), {n: c[0] for n, c in pubs.items()},
                                {n: c[0] for n, c in taken.get(name, {}).items()})}))
    return Table("topics", TOPIC_COLUMNS, rows, sort="rate_hz", spark="rate_hz")


EDGE_COLUMNS = [
    Column("topic", "TOPIC", name=True, least=8, keep=7),
    Column("publisher", "FROM", name=True, least=8, keep=9),
    Column("subscriber", "TO", name=True, least=8, keep=9),
    Column("rate_hz", "RATE", units.rate, keep=8),
    Column("bytes_per_second", "BANDWIDTH", units.bandwidth, keep=7),
    Column("age_seconds", "AGE", units.duration, keep=5),
    Column("repairs_percent", "REPAIR", units.percent, keep=4),
    Column("retransmits_hz", "RETX", units.rate, keep=3),
    Column("rtt_seconds", "RTT", units.duration, keep=3),
    Column("qos", "QOS", name=True, least=4, keep=2),
]


def edges(frame: Frame) -> Table:
    """Publisher -> subscriber on a topic: samples per second the subscriber received over UDP
    (else, where it takes the topic from this publisher alone, the messages it took), bytes per
    second (UDP samples, or a ROS 1 connection's socket), the mean age of a message when taken,
    wire bytes beyond the samples' own (repairs, as a % of them), and a ROS 1 connection's TCP
    retransmits and RTT."""
    taken = {t: rates(c) for t, c in topic_counters(frame, "messages_taken_total").items()}
    found = edges_of(frame)
    senders = defaultdict(int)
    for topic, _, sub in found:
        senders[topic, sub] += 1
    samples, received = edge_rates(frame, "samples_received_total"), edge_rates(frame, "received_bytes_total")
    wire, sent = edge_rates(frame, "received_wire_bytes_total"), edge_rates(frame, "sent_bytes_total")
    retransmits = edge_rates(frame, "tcp_retransmits_total")
    age = edge_means(frame, "delivery_age_seconds")
    rows = []
    for key, ((_, e), *_) in found.items():
        topic, pub, sub = key
        speed = samples[key]
        if speed is None and senders[topic, sub] == 1:
            speed = taken.get(topic, {}).get(sub)
        data = received[key] if received[key] is not None else sent[key]
        rtt = next((ae[1]["tcp_rtt_seconds"] for ae in found[key] if ae[1].get("tcp_rtt_seconds") is not None), None)
        rows.append(Row(f"edge|{topic}|{pub}|{sub}", {
            "topic": topic, "publisher": pub, "subscriber": sub, "rate_hz": speed, "bytes_per_second": data,
            "age_seconds": age[key],
            "repairs_percent": 100 * (wire[key] - received[key]) / received[key]
            if wire[key] is not None and received[key] else None,
            "retransmits_hz": retransmits[key], "rtt_seconds": rtt, "qos": e.get("qos_check") or None}))
    return Table("edges", EDGE_COLUMNS, rows, sort="bytes_per_second", spark="rate_hz")

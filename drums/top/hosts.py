"""The machine views of `drums top`: Hosts (each agent's state, CPU, memory, load, network by
interface and latency to the other hosts, from the host and latency jobs top keeps on it) and
Connections (every socket that moved bytes, from the agents' /metrics, as tcptop shows them).
"""
from __future__ import annotations

from drums import units
from drums.client import Sample
from drums.top.model import DOWN, Frame
from drums.top.rates import rate, total
from drums.top.table import Column, Row, Table
from drums.top.views import host_column, seconds, summed

NO_AGENT = "no agent"  # a host of the graph that no agent given to top watches
LOOPBACK = "lo"


def load(value) -> str:
    return "-" if value is None else f"{value:.2f}"


def _series(sample: Sample | None, name: str, label: str) -> dict[str, float]:
    """label value -> value of one family in a job's sample."""
    if sample is None:
        return {}
    return {dict(labels).get(label, ""): v for (n, labels), v in sample.series.items() if n == name}


def _cpu_percent(now: Sample | None, before: Sample | None) -> float | None:
    """Busy share of all CPUs between two samples (idle and iowait are not busy)."""
    if now is None or before is None:
        return None
    a, b = (_series(s, "drums_host_cpu_seconds_total", "mode") for s in (before, now))
    spent = sum(b.values()) - sum(a.values())
    idle = sum(b.get(m, 0) - a.get(m, 0) for m in ("idle", "iowait"))
    return 100 * (spent - idle) / spent if spent > 0 else None


def _interfaces(now: Sample | None, before: Sample | None) -> dict[str, tuple[float | None, float | None]]:
    """interface -> (received, sent) bytes per second between two samples."""
    dt = now.time - before.time if now is not None and before is not None else 0
    rx, rx_before = (_series(s, "drums_host_network_received_bytes_total", "interface") for s in (now, before))
    tx, tx_before = (_series(s, "drums_host_network_sent_bytes_total", "interface") for s in (now, before))
    return {i: (rate(rx[i], rx_before.get(i), dt), rate(tx.get(i), tx_before.get(i), dt)) for i in rx}


HOST_COLUMNS = [
    Column("host", "HOST", name=True, least=8, keep=9),
    Column("interface", "IFACE", name=True, least=5, keep=5),
    Column("state", "STATE", name=True, keep=8),
    Column("cpu_percent", "CPU", units.percent, keep=7),
    Column("memory_percent", "MEM", units.percent, keep=7),
    Column("load", "LOAD", load, keep=3),
    Column("received_bytes_per_second", "RX", units.bandwidth, keep=6),
    Column("sent_bytes_per_second", "TX", units.bandwidth, keep=6),
    Column("latency_seconds", "LATENCY", units.duration, keep=4),
]


def hosts(frame: Frame) -> Table:
    """A row per agent (by its host, or its URL until it answered) with, under it, a row per
    network interface (loopback too) and per other host it measures the round trip to. The host
    row's RX and TX leave loopback out; its LATENCY is the longest round trip."""
    rows, named = [], set()
    for agent in frame.agents:
        name = agent.host or agent.url
        named.add(agent.host)
        state = agent.state(frame.at, frame.interval)
        before, now = frame.sample(f"{agent.host}:host:")
        up = state != DOWN and now is not None
        lead = f"host|{name}"
        nics = _interfaces(now, before) if up else {}
        latencies = {key.split(":", 2)[2]: latest.value("drums_latency_rtt_mean_seconds")
                     for key, (_, latest) in frame.samples.items() if up and key.startswith(f"{agent.host}:latency:")}
        used, size = (now.value(f"drums_host_memory_{k}_bytes") if up else None for k in ("used", "total"))
        rows.append(Row(lead, {
            "host": name, "interface": "all", "state": state, "error": agent.error or agent.jobs_error or None,
            "cpu_percent": _cpu_percent(now, before) if up else None,
            "memory_percent": 100 * used / size if used is not None and size else None,
            "load": now.value("drums_host_load", period="1m") if up else None,
            "received_bytes_per_second": total(rx for i, (rx, _) in nics.items() if i != LOOPBACK),
            "sent_bytes_per_second": total(tx for i, (_, tx) in nics.items() if i != LOOPBACK),
            "latency_seconds": max((v for v in latencies.values() if v is not None), default=None)}))
        for nic, (rx, tx) in sorted(nics.items()):
            rows.append(Row(f"{lead}|{nic}", {"host": name, "interface": nic, "received_bytes_per_second": rx,
                                              "sent_bytes_per_second": tx}, group=lead))
        for target, rtt in sorted(latencies.items()):
            rows.append(Row(f"{lead}|->{target}", {"host": name, "interface": f"->{target}",
                                                   "latency_seconds": rtt}, group=lead))
    for agent in frame.live():  # hosts the graph knows but no agent here watches
        for name in agent.latest.hosts.keys() - named:
            named.add(name)
            rows.append(Row(f"host|{name}", {"host": name, "state": NO_AGENT}))
    return Table("hosts", HOST_COLUMNS, rows, sort="host", spark="cpu_percent")


CONNECTION_COLUMNS = [
    Column("pid", "PID", keep=3),
    Column("process", "PROCESS", name=True, least=8, keep=8),
    Column("protocol", "PROTO", name=True, keep=5),
    Column("local", "LOCAL", name=True, least=10, keep=7),
    Column("remote", "REMOTE", name=True, least=10, keep=7),
    Column("received_bytes_per_second", "RX", units.bandwidth, keep=9),
    Column("sent_bytes_per_second", "TX", units.bandwidth, keep=9),
    Column("rtt_seconds", "RTT", units.duration, keep=2),
]
SOCKET = ("pid", "process", "protocol", "local", "remote", "inode")


def connections(frame: Frame) -> Table:
    """Every socket of the agents' hosts that moved bytes between their last two polls (the
    sockets the agent's budget folded are summed in one row of process `other`)."""
    rows = []
    for agent in frame.live():
        now, before, dt = agent.latest, agent.before, seconds(agent, graph=False)
        rx, rx_before = (summed(p, "drums_socket_received_bytes_total", *SOCKET) for p in (now, before))
        tx, tx_before = (summed(p, "drums_socket_sent_bytes_total", *SOCKET) for p in (now, before))
        rtts = summed(now, "drums_tcp_connection_smoothed_rtt_seconds", "local", "remote")
        for key in rx.keys() | tx.keys():
            received, sent = rate(rx.get(key), rx_before.get(key), dt), rate(tx.get(key), tx_before.get(key), dt)
            if not (received or sent):
                continue
            pid, process, protocol, local, remote, inode = key
            # With its protocol: the budget sums the sockets it folds into an `other` row per protocol
            rows.append(Row(f"socket|{agent.host}|{pid}|{protocol}|{inode}", {
                "host": agent.host, "pid": int(pid) if pid.isdigit() else None, "process": process,
                "protocol": protocol, "local": local or None, "remote": remote or None,
                "received_bytes_per_second": received, "sent_bytes_per_second": sent,
                "rtt_seconds": rtts.get((local, remote))}))
    return Table("connections", [host_column(frame)] + CONNECTION_COLUMNS, rows,
                 sort="received_bytes_per_second", spark="received_bytes_per_second",
                 note="sockets that moved bytes in the last interval")

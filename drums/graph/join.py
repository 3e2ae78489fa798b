"""The join: kernel data, keyed by PID, socket and DDS writer, renamed into the graph's terms.

Per node: CPU, memory, context switches and run-queue latency of its process. Several nodes in
one process share these numbers (ROS 2 runs nodes of a process on shared executor threads, so no
thread belongs to one node); `drums_node_info` says which nodes share a process.
Per topic: messages published and taken (rcl uprobes, whatever the transport) and samples and
bytes sent (RTPS over UDP). Per edge: samples and bytes the subscribing process received from the
publisher's writer; for connections with their own socket (ROS 1 TCPROS), the socket's bytes and
its TCP retransmits and RTT.

Labels are names (node, topic, publisher, subscriber), which stay bounded as the graph does; the
PID and the mapping live only in drums_node_info.
"""
from __future__ import annotations

from collections import defaultdict
from itertools import compress
from operator import itemgetter

from drums.graph.model import Connection, Endpoint, Node
from drums.metrics import COUNTER, GAUGE, HISTOGRAM, INFO, Histogram, Metric, Snapshot
from drums.probes import process, rcl, rtps, sched, sockets, tcp

NODE = ("node",)
TOPIC = ("topic", "node")
EDGE = ("topic", "publisher", "subscriber")

NODE_INFO = Metric("drums_node_info", INFO, "A middleware node: its process, how it was mapped to it "
                   "(gid, cmdline, librcl, getPid, ...), and how many nodes that process holds (the nodes "
                   "of one process share its pid label)", ("node", "pid", "process", "mapped_by", "nodes_in_process"))
NODE_CPU = Metric("drums_node_cpu_seconds_total", COUNTER, "CPU time of the node's process", NODE)
NODE_MEMORY = Metric("drums_node_resident_memory_bytes", GAUGE, "Resident memory of the node's process", NODE)
NODE_SWITCHES = Metric("drums_node_context_switches_total", COUNTER,
                       "Context switches of the node's process, voluntary or involuntary", NODE + ("kind",))
NODE_RUNQ = Metric("drums_node_runqueue_latency_seconds", HISTOGRAM,
                   "Run-queue waits of the node's process's threads", NODE, sched.RUNQ_BUCKETS)
NODE_REACTION = Metric("drums_node_reaction_seconds", HISTOGRAM,
                       "Time from the node's take of a message on the input topic to its publish on the output "
                       "topic, in the same thread before it takes another or runs a timer or service "
                       "(rcl_take to rcl_publish)",
                       NODE + ("input", "output"), additive=False)
TOPIC_PUBLISHED = Metric("drums_topic_messages_published_total", COUNTER,
                         "Messages the node published on the topic (rcl_publish)", TOPIC)
TOPIC_TAKEN = Metric("drums_topic_messages_taken_total", COUNTER,
                     "Messages the node took from the topic (rcl_take)", TOPIC)
TOPIC_PUBLISH_PERIOD = Metric("drums_topic_publish_period_seconds", HISTOGRAM,
                              "Time between two messages the node published on the topic (rcl_publish); "
                              "buckets as in drums_ros_publish_period_seconds", TOPIC, additive=False)
TOPIC_DEADLINES_MISSED = Metric("drums_topic_deadlines_missed_total", COUNTER,
                                "Deadlines the node's publisher on the topic offers (Deadline QoS) that passed "
                                "without a message from it, as the kernel saw its messages", TOPIC)
TOPIC_TAKE_DEADLINES_MISSED = Metric("drums_topic_take_deadlines_missed_total", COUNTER,
                                     "Deadlines the node's subscription on the topic requests (Deadline QoS) that "
                                     "passed without a message taken by it, as the kernel saw its takes", TOPIC)
TOPIC_SAMPLES_SENT = Metric("drums_topic_samples_sent_total", COUNTER,
                            "Samples of the node's writer on the topic sent over UDP", TOPIC)
TOPIC_SENT_BYTES = Metric("drums_topic_sent_bytes_total", COUNTER,
                          "Serialized size of those samples, each sample once", TOPIC)
TOPIC_SENT_WIRE_BYTES = Metric("drums_topic_sent_wire_bytes_total", COUNTER,
                               "Serialized payload the node's writer sent over UDP: a copy for each "
                               "reader, and repairs of lost fragments", TOPIC)
EDGE_SAMPLES = Metric("drums_edge_samples_received_total", COUNTER,
                      "Samples the subscriber's process received over UDP from the publisher's writer", EDGE)
EDGE_RECEIVED_BYTES = Metric("drums_edge_received_bytes_total", COUNTER,
                             "Bytes the subscriber received from the publisher on the topic: serialized "
                             "size of the samples over UDP (ROS 2), or the connection's socket (ROS 1)", EDGE)
EDGE_RECEIVED_WIRE_BYTES = Metric("drums_edge_received_wire_bytes_total", COUNTER,
                                  "Serialized payload the subscriber's process received over UDP from the "
                                  "publisher's writer, repairs included", EDGE)
EDGE_TRANSPORT = Metric("drums_edge_delivery_transport_seconds", HISTOGRAM,
                        "Time from the publisher's stamp of a message to its reception by the subscriber's RMW; "
                        "across hosts as close as their realtime clocks are (drums_latency_clock_offset_seconds "
                        "measures how close; see drums_ros_delivery_skewed_total)",
                        EDGE, additive=False)
EDGE_AGE = Metric("drums_edge_delivery_age_seconds", HISTOGRAM,
                  "Time from the publisher's stamp of a message to the subscriber's take of it (rcl_take): "
                  "transport and queueing in the subscriber's executor", EDGE, additive=False)
EDGE_SENT_BYTES = Metric("drums_edge_sent_bytes_total", COUNTER,
                         "Bytes the publisher sent on the connection's own socket (ROS 1)", EDGE)
EDGE_RETRANSMITS = Metric("drums_edge_tcp_retransmits_total", COUNTER,
                          "TCP segments retransmitted on the connection's socket", EDGE)
EDGE_RTT = Metric("drums_edge_tcp_rtt_seconds", GAUGE, "Smoothed RTT of the connection's TCP socket", EDGE,
                  additive=False)
EDGE_QOS_INCOMPATIBLE = Metric("drums_edge_qos_incompatible", GAUGE,
                               "1 for each QoS policy that keeps the publisher's and the subscriber's endpoints on "
                               "the topic from connecting (ROS 2: reliability, durability, deadline, liveliness, "
                               "liveliness_lease): the subscriber gets none of its messages; a compatible edge has "
                               "policy \"none\" at 0. Exported by the subscriber's host",
                               EDGE + ("policy",), additive=False)
TOPIC_DEADLINE = Metric("drums_topic_deadline_seconds", GAUGE,
                        "The Deadline QoS the node's publisher on the topic offers (ROS 2): the longest it "
                        "promises to go without publishing; only publishers with a deadline", TOPIC, additive=False)
UNATTRIBUTED = Metric("drums_topic_unattributed_rows", GAUGE,
                      "Per-process topic and edge counts of this scrape that no one node of the graph could be named for "
                      "(summed under node \"unknown\"): a process the graph does not know yet, or several of its "
                      "nodes on the topic and no endpoint GID", ("kind",))
UNKNOWN = "unknown"
METRICS = (NODE_INFO, NODE_CPU, NODE_MEMORY, NODE_SWITCHES, NODE_RUNQ, NODE_REACTION, TOPIC_PUBLISHED, TOPIC_TAKEN,
           TOPIC_PUBLISH_PERIOD, TOPIC_DEADLINES_MISSED, TOPIC_TAKE_DEADLINES_MISSED, TOPIC_SAMPLES_SENT,
           TOPIC_SENT_BYTES, TOPIC_SENT_WIRE_BYTES, EDGE_SAMPLES, EDGE_RECEIVED_BYTES, EDGE_RECEIVED_WIRE_BYTES, EDGE_TRANSPORT, EDGE_AGE, EDGE_SENT_BYTES,
           EDGE_RETRANSMITS, EDGE_RTT, EDGE_QOS_INCOMPATIBLE, TOPIC_DEADLINE, UNATTRIBUTED)

_FIRST = itemgetter(0)
INFINITE_NS = 1 << 62  # rmw's "no deadline" is the largest duration it can hold
GID_HEX = 32  # a DDS GUID: 12 bytes of prefix, 4 of entity id; rmw pads GIDs beyond that


def join(nodes: list[Node], endpoints: list[Endpoint], connections: list[Connection], raw: Snapshot,
         out: Snapshot) -> None:
    """Add the graph's metrics to `out`, computed from the probes' rows in `raw`."""
    by_pid: dict[str, list[str]] = defaultdict(list)
    for n in nodes:
        if n.pid is not None:
            by_pid[str(n.pid)].append(n.name)
    pid_of = {n.name: str(n.pid) for n in nodes if n.pid is not None}

    def per_node(metric: Metric, source: Metric, extra_labels: int = 0):
        # A host's thousand processes pass here, a few of which hold nodes: those are picked out
        # without a line of Python per process (rows are (labels, value), labels[0] the pid).
        every = raw.of(source)
        rows = [((name,) + tuple(labels[len(labels) - extra_labels:]), value)
                for labels, value in compress(every, map(by_pid.__contains__, map(_FIRST, map(_FIRST, every))))
                for name in by_pid[labels[0]]]
        if rows:
            out.rows(metric).extend(rows)

    names = {labels[0]: labels[1] for labels, _ in raw.of(process.RESIDENT_MEMORY) if labels[0] in by_pid}
    for n in nodes:
        pid = pid_of.get(n.name, "")
        out.add(NODE_INFO, (n.name, pid, names.get(pid, ""), n.mapped_by, str(len(by_pid.get(pid, ())))), 1)
    per_node(NODE_CPU, sched.PROCESS_CPU)
    per_node(NODE_MEMORY, process.RESIDENT_MEMORY)
    per_node(NODE_SWITCHES, sched.PROCESS_SWITCHES, 1)
    per_node(NODE_RUNQ, sched.PROCESS_RUNQ)

    # A count belongs to the node of its endpoint (the rcl probe reads the GID from the process),
    # else to the one node of its process with an endpoint of that kind on the topic. Where neither
    # names exactly one node, it is summed under node "unknown", and counted.
    members: dict[tuple[str, str, str], list[str]] = defaultdict(list)  # (pid, kind, topic) -> nodes
    by_gid: dict[str, Endpoint] = {}
    for e in endpoints:
        pid = pid_of.get(e.node)
        if pid is not None:
            members[(pid, e.kind, e.topic)].append(e.node)
        by_gid[e.id[:GID_HEX]] = e
        deadline = e.qos.get("deadline_ns", 0)
        if e.kind == "publisher" and 0 < deadline < INFINITE_NS:
            out.add(TOPIC_DEADLINE, (e.topic, e.node), deadline / 1e9)
    unknown: dict[str, int] = defaultdict(int)

    def owner(pid: str, kind: str, topic: str, gid: str = "", counted: bool = True) -> str:
        e = by_gid.get(gid) if gid else None
        if e is not None and e.kind == kind:
            return e.node
        nodes = members.get((pid, kind, topic), ())
        if len(nodes) == 1:
            return nodes[0]
        unknown[kind] += counted
        return UNKNOWN

    # Rows that name the same entity are summed: counts no node is known for, a node with two
    # writers on one topic.
    sums: dict[Metric, dict[tuple[str, ...], int]] = defaultdict(lambda: defaultdict(int))
    for metric, source, kind in ((TOPIC_PUBLISHED, rcl.PUBLISHED, "publisher"),
                                 (TOPIC_TAKEN, rcl.TAKEN, "subscriber")):
        for (pid, _, topic, gid), value in raw.of(source):
            sums[metric][topic, owner(pid, kind, topic, gid)] += value
    for metric, source, kind in ((TOPIC_DEADLINES_MISSED, rcl.MISSED, "publisher"),
                                 (TOPIC_TAKE_DEADLINES_MISSED, rcl.TAKE_MISSED, "subscriber")):
        for (pid, _, topic, gid), value in raw.of(source):  # counted with its messages
            sums[metric][topic, owner(pid, kind, topic, gid, counted=False)] += value
    for metric, source in ((TOPIC_SAMPLES_SENT, rtps.SAMPLES_SENT), (TOPIC_SENT_BYTES, rtps.SENT_BYTES),
                           (TOPIC_SENT_WIRE_BYTES, rtps.SENT_WIRE_BYTES)):
        for (_, _, writer), value in raw.of(source):
            e = by_gid.get(writer)
            if e is not None and e.kind == "publisher":
                sums[metric][e.topic, e.node] += value
    for metric, source in ((EDGE_SAMPLES, rtps.SAMPLES_RECEIVED), (EDGE_RECEIVED_BYTES, rtps.RECEIVED_BYTES),
                           (EDGE_RECEIVED_WIRE_BYTES, rtps.RECEIVED_WIRE_BYTES)):
        for (pid, _, writer), value in raw.of(source):
            e = by_gid.get(writer)
            if e is not None and e.kind == "publisher":
                sums[metric][e.topic, e.node, owner(pid, "subscriber", e.topic)] += value
    for metric, rows in sums.items():
        out.rows(metric).extend(rows.items())
    # A node's publishers on one topic (rarely more than one) share its histograms.
    timings: dict[Metric, dict[tuple[str, ...], Histogram]] = defaultdict(dict)

    def merge(metric: Metric, key: tuple[str, ...], h: Histogram) -> None:
        rows = timings[metric]
        rows[key] = rows[key] + h if key in rows else h
    # Named as their messages are, and counted with them if no node could be.
    for (pid, _, topic, gid), h in raw.of(rcl.PERIOD):
        merge(TOPIC_PUBLISH_PERIOD, (topic, owner(pid, "publisher", topic, gid, counted=False)), h)
    for (pid, _, taken, published, gid), h in raw.of(rcl.REACTION):
        merge(NODE_REACTION, (owner(pid, "publisher", published, gid, counted=False), taken, published), h)
    for metric, source in ((EDGE_TRANSPORT, rcl.TRANSPORT), (EDGE_AGE, rcl.AGE)):
        for (pid, _, topic, gid, publisher), h in raw.of(source):
            e = by_gid.get(publisher[:GID_HEX])
            sender = e.node if e is not None and e.kind == "publisher" else UNKNOWN
            merge(metric, (topic, sender, owner(pid, "subscriber", topic, gid, counted=False)), h)
    for metric, rows in timings.items():
        out.rows(metric).extend(rows.items())
    for kind in ("publisher", "subscriber"):
        out.add(UNATTRIBUTED, (kind,), unknown[kind])
    for c in connections:
        if c.qos_check and c.subscriber in pid_of:
            edge = (c.topic, c.publisher, c.subscriber)
            policies = c.incompatible()
            out.rows(EDGE_QOS_INCOMPATIBLE).extend([(edge + (p,), 1) for p in policies] or [(edge + ("none",), 0)])
    _socket_edges(connections, raw, out)


def _port(endpoint: str) -> int:
    """The port of an address:port, 0 if it has none."""
    port = endpoint.rpartition(":")[2]
    return int(port) if port.isdigit() else 0


def _socket_edges(connections: list[Connection], raw: Snapshot, out: Snapshot) -> None:
    """Edges with a socket of their own: `local` is the publisher's end, `remote` the subscriber's."""
    edges = {(c.local, c.remote): (c.topic, c.publisher, c.subscriber) for c in connections if c.local and c.remote}
    if not edges:
        return
    ports = {(_port(local), _port(remote)) for local, remote in edges}  # the sockets of the edges' ends are on
    ports |= {(remote, local) for local, remote in ports}  # these: the few rows whose labels are made
    for metric, source, reverse in ((EDGE_SENT_BYTES, sockets.SOCKET["sent_bytes"], False),
                                    (EDGE_RECEIVED_BYTES, sockets.SOCKET["received_bytes"], True)):
        for (_, _, _, local, remote, _, _), value in raw.of(source, ports):
            edge = edges.get((remote, local) if reverse else (local, remote))
            if edge is not None:
                out.add(metric, edge, value)
    for metric, source in ((EDGE_RETRANSMITS, tcp.CONN_RETRANSMITS), (EDGE_RTT, tcp.CONN_RTT)):
        for labels, value in raw.of(source, ports):
            edge = edges.get((labels[0], labels[1]))
            if edge is not None:
                out.add(metric, edge, value)

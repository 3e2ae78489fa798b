"""The ROS 2 graph, read with rclpy: nodes, topics, publishers and subscribers with their GIDs and
QoS, each node mapped to its process (drums.graph.nodepids).

rclpy and the DDS participant it creates live in a child process (`python -m drums.graph.ros2`)
that prints one JSON graph state per line: the agent stays lean, and a DDS stack that hangs or
crashes costs the graph its freshness, never the agent its kernel data.

ROS 2 has no list of hosts: each agent's reader announces its own on ANNOUNCE_TOPIC (a
std_msgs/String holding {"host", "address", "agent"} as JSON) and every reader lists the hosts
announced there, each for as long as its announcer is in the graph.
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import threading
import time
import uuid
from dataclasses import asdict
from itertools import chain
from typing import Callable
from urllib.parse import urlsplit

from drums.graph.adapter import ChildAdapter
from drums.graph.model import Connection, Endpoint, GraphState, Host, Node, Process, Topic
from drums.graph.nodepids import ProcScan, map_nodes
from drums.netfmt import is_address
from drums.rclchild import RCLPY_ARGS, start_helper

# Measured: a reader that is not root sees the topics of a root node but not the node, nor its
# endpoints (Fast DDS carries them over shared memory, whose segments are closed to other users).
NOT_ROOT = ("the agent is not root: nodes of other users' processes are missing (their DDS shared memory is "
            "closed to it) and nodes are not mapped to processes it may not read")
OWN_NODE = "_drums_graph"  # a leading underscore hides a node from `ros2 node list`; every agent's reader has it
ANNOUNCE_TOPIC = "/drums/agents"
# The name rmw gives an endpoint whose node is not discovered yet: skipped until it is.
UNKNOWN_NODE = "_NODE_NAME_UNKNOWN_"
INSTALL_HINT = "pip install ros-rclpy ros-std-msgs ros-rmw-fastrtps-cpp (ROS 2 from PyPI)"


def full_name(namespace: str, name: str) -> str:
    return f"{namespace.rstrip('/')}/{name}"


def _qos(profile) -> dict:
    """A QoS profile as plain values: policies by name, durations in nanoseconds."""
    out = {}
    for policy in ("reliability", "durability", "history", "liveliness"):
        out[policy] = getattr(profile, policy).name.lower()
    out["depth"] = profile.depth
    for duration in ("deadline", "lifespan", "liveliness_lease_duration"):
        out[f"{duration}_ns"] = getattr(profile, duration).nanoseconds
    return out


def announced(text: str) -> Host | None:
    """The host an announcement names, None for anything else (it comes from the network)."""
    try:
        data = json.loads(text)
    except ValueError:
        return None
    if not isinstance(data, dict) or not all(isinstance(data.get(k), str) for k in ("host", "address", "agent")):
        return None
    host, address, agent = data["host"], data["address"], data["agent"]
    try:
        url = urlsplit(agent)
        good_agent = not agent or (url.scheme == "http" and bool(url.hostname) and bool(url.port))
    except ValueError:
        good_agent = False
    if not host or (address and not is_address(address)) or not good_agent:
        return None
    return Host(host, address, agent)


class Agents:
    """The hosts of the agents on this ROS domain, as they announce them, each for as long as its
    announcer's publisher is in the graph; and this reader's own host, as it announces it or, when
    it does not (`drums graph`), as an agent of this host does or else by name."""

    def __init__(self, node, string_type, own: Host, announce: bool):
        """`string_type`: std_msgs/msg/String, imported where a missing package is reported."""
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        self.node, self.own, self.announce = node, own, announce
        self._by_writer: dict[str, Host] = {}  # announcer's GID (hex) -> the host it announced
        # Transient local: a reader that starts later still gets every live agent's announcement.
        qos = {"reliability": ReliabilityPolicy.RELIABLE, "durability": DurabilityPolicy.TRANSIENT_LOCAL}
        if announce:
            self._publisher = node.create_publisher(string_type, ANNOUNCE_TOPIC, QoSProfile(depth=1, **qos))
            self._publisher.publish(string_type(data=json.dumps(
                {"host": own.name, "address": own.address, "agent": own.agent})))
        # Keep all until taken: announcements of many agents arrive at once when a reader starts.
        node.create_subscription(string_type, ANNOUNCE_TOPIC, self._heard,
                                 QoSProfile(history=HistoryPolicy.KEEP_ALL, **qos))

    def _heard(self, message, info) -> None:
        host = announced(message.data)
        if host is not None:  # garbage from one announcer must not cost the graph its other hosts
            self._by_writer[bytes(info["publisher_gid"]["data"]).hex()] = host

    def hosts(self) -> list[Host]:
        live = {bytes(e.endpoint_gid).hex() for e in self.node.get_publishers_info_by_topic(ANNOUNCE_TOPIC)}
        self._by_writer = {gid: h for gid, h in self._by_writer.items() if gid in live}
        hosts: dict[str, Host] = {}
        for gid in sorted(self._by_writer):  # one host announced twice: every reader keeps the same one
            hosts.setdefault(self._by_writer[gid].name, self._by_writer[gid])
        if self.announce or self.own.name not in hosts:
            hosts[self.own.name] = self.own
        return list(hosts.values())


def discover(node, scan: ProcScan, agents: Agents) -> GraphState:
    """One look at the graph as this node's DDS participant knows it."""
    from rclpy.qos import QoSCompatibility, qos_check_compatible

    host = agents.own.name
    names = [full_name(ns, n) for n, ns in node.get_node_names_and_namespaces() if n != OWN_NODE]
    own = b""  # our participant's GUID prefix: its host id tells local nodes from remote ones
    state = GraphState(truncated=NOT_ROOT if os.geteuid() else "")
    listed = []  # (topic, publishers, subscribers) of the topics nodes use
    participants: dict[str, list[bytes]] = {name: [] for name in names}  # of each node, as listed
    for topic, types in node.get_topic_names_and_types():
        pubs = node.get_publishers_info_by_topic(topic)
        subs = node.get_subscriptions_info_by_topic(topic)
        readers = [e for e in pubs + subs if e.node_name == OWN_NODE]  # ours and other agents'
        ours = [e for e in readers if e.node_namespace == node.get_namespace()]
        if ours:
            own = bytes(ours[0].endpoint_gid)[:12]
        if readers and len(readers) == len(pubs) + len(subs):
            continue  # a topic only readers use (their /parameter_events publishers, ANNOUNCE_TOPIC)
        state.topics.append(Topic(topic, tuple(types)))
        pubs = [e for e in pubs if e.node_name not in (OWN_NODE, UNKNOWN_NODE)]
        subs = [e for e in subs if e.node_name not in (OWN_NODE, UNKNOWN_NODE)]
        listed.append((topic, pubs, subs))
        for info in pubs + subs:
            prefix, held = bytes(info.endpoint_gid)[:12], participants.setdefault(
                full_name(info.node_namespace, info.node_name), [])
            if prefix not in held:
                held.append(prefix)
    # A node started again under its name: DDS lists the killed participant's endpoints beside the
    # new one's until its lease runs out (20 s). Those of a participant whose process is known to
    # be gone are passed over while the node has another.
    stale = set()
    for name, held in participants.items():
        left = [prefix for prefix in held if scan.left_participant(name, prefix)] if len(held) > 1 else ()
        stale.update(left if len(left) < len(held) else ())
    prefixes = {name: next((p for p in held if p not in stale), None) for name, held in participants.items()}
    for topic, pubs, subs in listed:
        pubs = [e for e in pubs if bytes(e.endpoint_gid)[:12] not in stale]
        subs = [e for e in subs if bytes(e.endpoint_gid)[:12] not in stale]
        for info, kind in [(e, "publisher") for e in pubs] + [(e, "subscriber") for e in subs]:
            state.endpoints.append(Endpoint(bytes(info.endpoint_gid).hex(), kind,
                                            full_name(info.node_namespace, info.node_name), topic,
                                            _qos(info.qos_profile)))
        for pub in pubs:
            for sub in subs:
                verdict, reason = qos_check_compatible(pub.qos_profile, sub.qos_profile)
                state.connections.append(Connection(
                    topic, full_name(pub.node_namespace, pub.node_name),
                    full_name(sub.node_namespace, sub.node_name), "dds",
                    qos_check="ok" if verdict == QoSCompatibility.OK else reason))
    mapping = map_nodes(prefixes, scan, own, chain.from_iterable(participants.values()))
    gone = {name for name, (_, how) in mapping.items() if how == "gone"}
    if gone:
        state.endpoints = [e for e in state.endpoints if e.node not in gone]
        state.connections = [c for c in state.connections if not {c.publisher, c.subscriber} & gone]
        used = {e.topic for e in state.endpoints}
        state.topics = [t for t in state.topics if t.name in used]
    pids = set()
    for name in [n for n in prefixes if n not in gone]:
        pid, how = mapping[name]
        prefix = prefixes[name]
        extra = {"participant": prefix.hex()} if prefix else {}
        state.nodes.append(Node(name, host if pid is not None else "", pid, how, extra))
        if pid is not None:
            pids.add(pid)
    state.hosts = agents.hosts()
    state.processes.extend(Process(host, pid, scan.name(pid)) for pid in sorted(pids))
    return state


class Ros2Adapter(ChildAdapter):
    name = "ros2"
    module = "drums.graph.ros2"
    env = {"FASTDDS_DEFAULT_PROFILES_FILE": os.path.join(os.path.dirname(__file__), "fastdds_reader.xml")}
    # Every DDS participant announces itself every 3 s (Fast DDS's default), and a busy one may not
    # answer the reader's first announcements: it is seen at its next one, up to 3 s later and
    # then its endpoints (measured: 3.5-3.9 s after the reader started, with both cores busy).
    settle = 4.5

    def __init__(self, interval: float = 0.5, timeout: float = 5.0, announce: Host | None = None):
        """`announce`: the host this reader's agent runs on, to tell the other agents."""
        super().__init__(interval, timeout)
        self.child_args = ["--announce", json.dumps(asdict(announce))] if announce else []

    def carry(self, topic: str, answers) -> None:
        """The reader publishes the agent's DiagnosticArrays on `topic` too (one rclpy process and DDS
        participant for both: drums.exporters.diagnostics.Publisher.ride), handing each answer to
        `answers(child, error)`. Before start()."""
        self.child_args = [*self.child_args, "--diagnostics", topic]
        self._answers = answers


def child(interval: float, announce: Host | None, diagnostics: str | None) -> int:
    """The child process: print the graph every interval until we are killed (or, while it publishes
    the arrays read on stdin on the `diagnostics` topic, until stdin closes)."""
    try:
        import rclpy
        from rclpy.node import Node as RclNode
        from std_msgs.msg import String
    except ImportError as e:
        print(json.dumps({"error": f"ROS 2 cannot be imported ({e}): {INSTALL_HINT}"}), flush=True)
        return 2
    rclpy.init(args=RCLPY_ARGS)
    # A namespace of its own tells this reader's endpoints from other agents' readers' (same name).
    node = RclNode(OWN_NODE, namespace=f"/_drums_{uuid.uuid4().hex}", enable_rosout=False,
                   start_parameter_services=False)
    agents = Agents(node, String, announce or Host(socket.gethostname()), announce is not None)
    scan = ProcScan()
    said = threading.Lock()  # the graph and the answers go out on one stdout, a line at a time

    def say(line: str) -> None:
        with said:
            print(line, flush=True)

    done = threading.Event()
    arrays = None
    if diagnostics:
        from drums.rclchild import INSTALL_HINT as DIAGNOSTICS_HINT, Arrays, answer
        try:
            arrays = Arrays(diagnostics)
        except Exception as e:  # no diagnostic_msgs: each array is answered with why it goes nowhere
            reason = f"cannot publish {diagnostics}: {e} ({DIAGNOSTICS_HINT})"

        def publish(line: str) -> str:
            return answer(arrays.publish(line) if arrays is not None else reason)
        threading.Thread(target=_publish, args=(publish, say, done), daemon=True, name="arrays").start()
    try:
        while not done.is_set():
            until = time.monotonic() + interval
            while time.monotonic() < until:  # one spin runs one callback: take every announcement
                rclpy.spin_once(node, timeout_sec=max(0.0, until - time.monotonic()))
            try:
                state = discover(node, scan, agents)
            except Exception as e:  # the middleware answered something we cannot read: say so, go on
                say(json.dumps({"error": f"reading the ROS 2 graph: {e}"}))
                continue
            say(json.dumps({"state": state.to_dict()}))
    except (KeyboardInterrupt, BrokenPipeError):
        return 0
    finally:
        if arrays is not None:
            arrays.destroy()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def _publish(publish: Callable[[str], str], say: Callable[[str], None], done: threading.Event) -> None:
    """Each array read on stdin published, and its answer said; at the end of stdin, done."""
    try:
        for line in sys.stdin:
            say(publish(line))
    except (BrokenPipeError, ValueError):
        pass
    done.set()


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m drums.graph.ros2")
    parser.add_argument("--interval", type=float, default=0.5)
    parser.add_argument("--announce", type=lambda text: Host(**json.loads(text)), default=None,
                        help="the host to announce to other agents, as JSON: {name, address, agent}")
    parser.add_argument("--diagnostics", metavar="TOPIC", default=None,
                        help="publish the DiagnosticArrays read on stdin (JSON lines) on this topic too")
    args = parser.parse_args()
    start_helper("graph")
    return child(args.interval, args.announce, args.diagnostics)


if __name__ == "__main__":
    sys.exit(main())

"""The ROS 2 graph, read with rclpy: nodes, topics, publishers and subscribers with their GIDs and
QoS, each node mapped to its process (drums.graph.nodepids).

rclpy and the DDS participant it creates live in a child process (`python -m drums.graph.ros2`)
that prints one JSON graph state per line: the agent stays lean, and a DDS stack that hangs or
crashes costs the graph its freshness, never the agent its kernel data.
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import sys

from drums.graph.adapter import ChildAdapter
from drums.graph.model import Connection, Endpoint, GraphState, Host, Node, Process, Topic
from drums.graph.nodepids import ProcScan, map_nodes

OWN_NODE = "_drums_graph"  # a leading underscore hides a node from `ros2 node list`
# The name rmw gives an endpoint whose node is not discovered yet: skipped until it is.
UNKNOWN_NODE = "_NODE_NAME_UNKNOWN_"
INSTALL_HINT = "pip install ros-rclpy ros-rmw-fastrtps-cpp (ROS 2 from PyPI)"


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


def discover(node, scan: ProcScan, host: str) -> GraphState:
    """One look at the graph as this node's DDS participant knows it."""
    from rclpy.qos import QoSCompatibility, qos_check_compatible

    names = [full_name(ns, n) for n, ns in node.get_node_names_and_namespaces() if n != OWN_NODE]
    prefixes: dict[str, bytes | None] = dict.fromkeys(names)
    own = b""  # our participant's GUID prefix: its host id tells local nodes from remote ones
    state = GraphState()
    for topic, types in node.get_topic_names_and_types():
        pubs = node.get_publishers_info_by_topic(topic)
        subs = node.get_subscriptions_info_by_topic(topic)
        ours = [e for e in pubs + subs if e.node_name == OWN_NODE]
        if ours:
            own = bytes(ours[0].endpoint_gid)[:12]
            if len(ours) == len(pubs) + len(subs):
                continue  # a topic only we use (our /parameter_events publisher)
        state.topics.append(Topic(topic, tuple(types)))
        pubs = [e for e in pubs if e.node_name not in (OWN_NODE, UNKNOWN_NODE)]
        subs = [e for e in subs if e.node_name not in (OWN_NODE, UNKNOWN_NODE)]
        for info, kind in [(e, "publisher") for e in pubs] + [(e, "subscriber") for e in subs]:
            name = full_name(info.node_namespace, info.node_name)
            gid = bytes(info.endpoint_gid)
            prefixes[name] = prefixes.get(name) or gid[:12]
            state.endpoints.append(Endpoint(gid.hex(), kind, name, topic, _qos(info.qos_profile)))
        for pub in pubs:
            for sub in subs:
                verdict, reason = qos_check_compatible(pub.qos_profile, sub.qos_profile)
                state.connections.append(Connection(
                    topic, full_name(pub.node_namespace, pub.node_name),
                    full_name(sub.node_namespace, sub.node_name), "dds",
                    qos_check="ok" if verdict == QoSCompatibility.OK else reason))
    mapping = map_nodes(prefixes, scan, own)
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
    state.hosts.append(Host(host))
    state.processes.extend(Process(host, pid, scan.name(pid)) for pid in sorted(pids))
    return state


class Ros2Adapter(ChildAdapter):
    name = "ros2"
    module = "drums.graph.ros2"
    env = {"FASTDDS_DEFAULT_PROFILES_FILE": os.path.join(os.path.dirname(__file__), "fastdds_reader.xml")}
    settle = 3.0  # every DDS participant announces itself every 3 s (Fast DDS's default)


def child(interval: float) -> int:
    """The child process: print the graph every interval until stdin closes or we are killed."""
    try:
        import rclpy
        from rclpy.node import Node as RclNode
    except ImportError as e:
        print(json.dumps({"error": f"rclpy cannot be imported ({e}): {INSTALL_HINT}"}), flush=True)
        return 2
    rclpy.init(args=[])
    node = RclNode(OWN_NODE, enable_rosout=False, start_parameter_services=False)
    scan, host = ProcScan(), socket.gethostname()
    try:
        while True:
            rclpy.spin_once(node, timeout_sec=interval)
            try:
                state = discover(node, scan, host)
            except Exception as e:  # the middleware answered something we cannot read: say so, go on
                print(json.dumps({"error": f"reading the ROS 2 graph: {e}"}), flush=True)
                continue
            print(json.dumps({"state": state.to_dict()}), flush=True)
    except (KeyboardInterrupt, BrokenPipeError):
        return 0
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m drums.graph.ros2")
    parser.add_argument("--interval", type=float, default=0.5)
    return child(parser.parse_args().interval)


if __name__ == "__main__":
    sys.exit(main())

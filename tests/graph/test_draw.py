"""The graph as a picture: DOT that Debian's Graphviz draws for graphs of every adapter's shape,
hostile names included, with rates and bandwidth on the arrows."""
from __future__ import annotations

import re
import subprocess
import sys

import pytest

from drums.graph import draw, join
from drums.graph.model import Connection, Endpoint, Graph, GraphState, Host, Node, Process, Topic
from drums.metrics import Histogram, Snapshot

GID = "010f78fd4a21e7950000000000001403"


def ros2_state() -> GraphState:
    """Two hosts; a process of three nodes; the plumbing topics; Drums' own reader."""
    nodes = [Node("/camera", "robot1", 10, "gid"), Node("/detector", "robot2", 20, "gid"),
             Node("/planner", "robot2", 20, "gid"), Node("/logger", "robot2", 20, "gid"),
             Node("/_drums_graph", "robot2", 30, "gid")]
    endpoints = [Endpoint(GID[:-1] + "1", "publisher", "/camera", "/image"),
                 Endpoint(GID[:-1] + "2", "subscriber", "/detector", "/image"),
                 Endpoint(GID[:-1] + "3", "publisher", "/detector", "/objects"),
                 Endpoint(GID[:-1] + "4", "subscriber", "/planner", "/objects"),
                 Endpoint(GID[:-1] + "5", "publisher", "/logger", "/rosout"),
                 Endpoint(GID[:-1] + "6", "publisher", "/planner", "/parameter_events")]
    return GraphState(
        hosts=[Host("robot1", "10.0.0.1"), Host("robot2", "10.0.0.2")],
        processes=[Process("robot1", 10, "camera_node"), Process("robot2", 20, "python3"), Process("robot2", 30, "drums-graph")],
        nodes=nodes, endpoints=endpoints,
        topics=[Topic("/image", ("sensor_msgs/msg/Image",)), Topic("/objects", ("std_msgs/msg/String",)),
                Topic("/rosout", ("rcl_interfaces/msg/Log",)), Topic("/parameter_events", ())],
        connections=[Connection("/image", "/camera", "/detector", "dds"),
                     Connection("/objects", "/detector", "/planner", "dds")])


def ros1_state() -> GraphState:
    """Connections with sockets of their own, no endpoints (as the ros1 adapter makes them)."""
    return GraphState(
        hosts=[Host("pc")], processes=[Process("pc", 5, "talker"), Process("pc", 6, "listener")],
        nodes=[Node("/talker", "pc", 5, "getPid"), Node("/listener", "pc", 6, "getPid")],
        topics=[Topic("/chatter", ("std_msgs/String",))],
        connections=[Connection("/chatter", "/talker", "/listener", "TCPROS", "127.0.0.1:4000", "127.0.0.1:5000")])


def auto_state() -> GraphState:
    """Processes and their TCP connections, client to server, no topics (the auto adapter)."""
    return GraphState(hosts=[Host("pc")], processes=[Process("pc", 7, "curl"), Process("pc", 8, "nginx")],
                      nodes=[Node("curl/7", "pc", 7, "auto"), Node("nginx/8", "pc", 8, "auto")],
                      connections=[Connection("", "curl/7", "nginx/8", "tcp", "127.0.0.1:4321", "127.0.0.1:80")])


def hostile_state() -> GraphState:
    """Names DOT would choke on unquoted: its keywords, quotes, backslashes, braces, newlines."""
    names = ['/node', '/graph', '/a"b', '/back\\slash', '/{brace}', '/semi;colon', '/new\nline', '/ünï']
    return GraphState(hosts=[Host("edge")], nodes=[Node(n, "edge", None) for n in names],
                      topics=[Topic("/strict")],
                      endpoints=[Endpoint(f"e{i}", "publisher", n, "/strict") for i, n in enumerate(names)])


def drawn(state: GraphState, **kw) -> str:
    """The SVG Graphviz draws from the DOT of `state` (Graphviz must accept it)."""
    g = Graph()
    g.update(state)
    return drawn_graph(g, **kw)


def drawn_graph(graph: Graph, **kw) -> str:
    """The SVG Graphviz draws from the DOT of a live graph (Graphviz must accept it)."""
    text = draw.dot(graph.snapshot(), **kw)
    done = subprocess.run(["dot", "-Tsvg"], input=text, capture_output=True, text=True, timeout=30)
    assert done.returncode == 0 and done.stderr == "", (done.stderr, text)
    return done.stdout


def texts(svg: str) -> set[str]:
    """The text of every label in the SVG, entities decoded."""
    import html
    return {html.unescape(t) for t in re.findall(r"<text[^>]*>([^<]*)</text>", svg)}


@pytest.mark.parametrize("state", [ros2_state, ros1_state, auto_state, hostile_state])
def test_graphviz_draws_every_kind_of_graph(state):
    svg = drawn(state())
    shown = texts(svg)
    s = state()
    hidden = {"/_drums_graph", "/rosout", "/parameter_events"}
    for name in [n.name for n in s.nodes] + [t.name for t in s.topics]:
        if name not in hidden:
            assert name.split("\n")[0] in shown, (name, shown)


def test_plumbing_is_hidden_unless_everything_is_asked_for():
    default, everything = texts(drawn(ros2_state())), texts(drawn(ros2_state(), everything=True))
    for name in ("/_drums_graph", "/rosout", "/parameter_events"):
        assert name not in default and name in everything


def test_hosts_are_clusters_and_a_process_of_several_nodes_is_one_inside_its_host():
    shown = texts(drawn(ros2_state()))
    assert {"robot1", "robot2", "python3 20: 3 nodes"} <= shown
    assert not any(t.startswith("camera_node") for t in shown)  # a process of one node is just the node


def test_arrows_carry_rates_and_bandwidth_and_grow_with_it():
    g = Graph()
    g.update(ros2_state())
    before, after = Snapshot(), Snapshot()
    for snap, n in ((before, 0), (after, 30)):
        snap.add(join.TOPIC_PUBLISHED, ("/image", "/camera"), n)
        snap.add(join.TOPIC_SENT_BYTES, ("/image", "/camera"), n * 1 << 20)
        snap.add(join.TOPIC_TAKEN, ("/image", "/detector"), n)
        snap.add(join.EDGE_RECEIVED_BYTES, ("/image", "/camera", "/detector"), n * 1 << 20)
        snap.add(join.NODE_CPU, ("/detector",), n / 60)
        # Ages of 2 ms, and 4 ms from a second publisher: the arrow shows the older.
        snap.add(join.EDGE_AGE, ("/image", "/camera", "/detector"), Histogram([], n * 0.002, n, ()))
        snap.add(join.EDGE_AGE, ("/image", "/camera2", "/detector"), Histogram([], n * 0.004, n, ()))
        # Reactions of 15 ms, and of 5 ms on another pair: the node shows the slowest. Then none in
        # a third pair: it shows nothing.
        snap.add(join.NODE_REACTION, ("/detector", "/image", "/objects"), Histogram([], 1 + n * 0.015, 10 + n, ()))
        snap.add(join.NODE_REACTION, ("/detector", "/image", "/debug"), Histogram([], n * 0.005, n, ()))
        snap.add(join.NODE_REACTION, ("/detector", "/scan", "/debug"), Histogram([], 1.0, 10, ()))
    rates = draw.Rates()
    assert rates.update(before, now=100.0) == {}
    got = rates.update(after, now=103.0)  # 30 messages of 1 MiB in 3 s
    text = draw.dot(g.snapshot(), after, got)
    assert '"node:/camera" -> "topic:/image" [label="10.0 Hz  10.0 MiB/s", penwidth="5.01"]' in text
    assert '"topic:/image" -> "node:/detector" [label="10.0 Hz  10.0 MiB/s  age 4.0 ms", penwidth="5.01"]' in text
    assert '"topic:/objects" -> "node:/planner" [label="", penwidth="1.0"]' in text
    assert 'label="/detector\\nCPU 17%  reacts 15.0 ms"' in text  # 0.5 s of CPU in 3 s
    assert "10.0 Hz" in texts(drawn(ros2_state(), snap=after, rates=got))


def test_drums_graph_draws_svg_of_a_static_graph(tmp_path):
    (tmp_path / "g.yaml").write_text("nodes:\n  - name: /planner\n    process: nothing-matches-this\n"
                                     "topics:\n  - name: /cmd_vel\n    publishers: [/planner]\n")
    out = subprocess.run([sys.executable, "-m", "drums", "graph", "--graph", "static", "--graph-file",
                          str(tmp_path / "g.yaml"), "--format", "svg"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stderr == "", out.stderr
    assert {"/planner", "/cmd_vel"} <= texts(out.stdout)


def test_a_pair_whose_qos_cannot_connect_is_a_dashed_arrow_with_the_policies():
    state = ros2_state()
    state.connections.append(Connection("/image", "/camera", "/planner", "dds", qos_check=(
        "ERROR: Best effort publisher and reliable subscription;"
        "ERROR: Volatile publisher and transient local subscription;")))
    g = Graph()
    g.update(state)
    text = draw.dot(g.snapshot())
    assert ('"node:/camera" -> "node:/planner" [label="/image: QoS reliability, durability incompatible", '
            'style="dashed", color="#cc0000", fontcolor="#cc0000"]') in text
    assert '"topic:/image" -> "node:/detector"' in text  # the compatible subscriber as before
    assert "/image: QoS reliability, durability incompatible" in texts(drawn(state))

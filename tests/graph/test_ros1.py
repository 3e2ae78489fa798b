"""The ROS 1 adapter against a master and nodes that speak the wire protocols (ros1_wire.py), in
processes of their own on real sockets: nodes, PIDs, topics and each edge's socket exactly as the
processes report them; and what the graph keeps when the master answers garbage, nothing, or is gone."""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time

import psutil
import pytest

from drums.errors import GraphError
from drums.graph.adapter import Follower
from drums.graph.model import Connection, Endpoint, Graph, Host, Node, Process, Topic
from drums.graph.ros1 import Ros1Adapter, bus_info, connections, parse_info, system_state
from tests.conftest import wait_until
from tests.graph.ros1_wire import encode_header
from tests.graph.test_draw import drawn_graph, texts

WIRE = os.path.join(os.path.dirname(__file__), "ros1_wire.py")
IMAGE, OBJECTS, STATUS = "/image:sensor_msgs/Image", "/objects:vision_msgs/Detection2DArray", "/status:std_msgs/String"
HERE = socket.gethostname()


class Wire:
    """One ros1_wire.py process; a thread keeps what it prints."""

    def __init__(self, *args: str):
        self.proc = subprocess.Popen([sys.executable, WIRE, *args], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)
        ready = self.proc.stdout.readline().split()
        if ready[:1] != ["ready"]:
            self.kill()
            raise RuntimeError(f"ros1_wire.py {' '.join(args)} did not start")
        self.pid, self.uri = self.proc.pid, ready[-1]
        self.lines: list = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.append(json.loads(line) if line.startswith("{") else line.strip())

    def events(self, kind: str) -> list[dict]:
        return [e for e in list(self.lines) if isinstance(e, dict) and e["event"] == kind]

    def say(self, line: str) -> None:
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()
        wait_until(lambda: line in self.lines, f"the master to take {line!r}")

    def stop(self) -> None:
        """SIGTERM: a node unregisters from the master, as roscpp and rospy do on shutdown."""
        self.proc.terminate()
        self.proc.wait(5)

    def kill(self) -> None:
        """SIGKILL: nothing said to anyone, the master still lists the node."""
        self.proc.kill()
        self.proc.wait()


@pytest.fixture
def wire():
    started = []

    class Start:
        @staticmethod
        def master(*args: str) -> Wire:
            started.append(Wire("master", *args))
            return started[-1]

        @staticmethod
        def node(name: str, master: Wire, *args: str) -> Wire:
            started.append(Wire("node", "--name", name, "--master", master.uri, *args))
            return started[-1]
    yield Start
    for w in started:
        if w.proc.poll() is None:
            w.kill()
        w.proc.stdout.close()
        w.proc.stdin.close()


def flows(nodes: dict[str, Wire]) -> list[tuple[str, dict]]:
    """(publisher, what it printed) for every connection the publishers served."""
    return [(name, e) for name, w in nodes.items() for e in w.events("published")]


def wait_for_flows(nodes: dict[str, Wire], count: int) -> None:
    wait_until(lambda: len(flows(nodes)) == count and sum(len(w.events("received")) for w in nodes.values()) == count,
               f"{count} connections to carry their messages")


def edge(publisher: str, printed: dict) -> Connection:
    return Connection(printed["topic"], publisher, printed["subscriber"], "TCPROS", printed["local"], printed["remote"])


def comm(pid: int) -> str:
    with open(f"/proc/{pid}/comm") as f:
        return f.read().strip()


def poll_once(uri: str, timeout: float = 2.0) -> tuple[Graph, float]:
    adapter = Ros1Adapter(uri, timeout=timeout)
    adapter.start()
    try:
        started = time.monotonic()
        state = adapter.poll()
        took = time.monotonic() - started
    finally:
        adapter.stop()
    graph = Graph()
    graph.update(state)
    return graph, took


def test_the_graph_has_each_node_pid_topic_and_socket(wire):
    master = wire.master()
    nodes = {"/camera": wire.node("/camera", master, "--publish", IMAGE, "--size", "1000"),
             "/detector": wire.node("/detector", master, "--subscribe", IMAGE, "--publish", OBJECTS),
             "/planner": wire.node("/planner", master, "--subscribe", OBJECTS),
             "/logger": wire.node("/logger", master, "--subscribe", OBJECTS)}
    wait_for_flows(nodes, 3)
    graph, _ = poll_once(master.uri)

    assert {n.name: n for n in graph.entities("node")} == {
        name: Node(name, HERE, w.pid, "getPid", {"uri": w.uri}) for name, w in nodes.items()}
    assert set(graph.entities("process")) == {Process(HERE, w.pid, comm(w.pid)) for w in nodes.values()}
    assert graph.entities("host") == [Host(HERE, "127.0.0.1")]
    assert set(graph.entities("topic")) == {Topic("/image", ("sensor_msgs/Image",)),
                                            Topic("/objects", ("vision_msgs/Detection2DArray",))}
    assert sorted(graph.entities("endpoint"), key=str) == sorted(
        (Endpoint(f"{node}:{kind}:{topic}", kind, node, topic) for node, kind, topic in [
            ("/camera", "publisher", "/image"), ("/detector", "subscriber", "/image"),
            ("/detector", "publisher", "/objects"), ("/planner", "subscriber", "/objects"),
            ("/logger", "subscriber", "/objects")]), key=str)
    assert sorted(graph.connections(), key=str) == sorted((edge(pub, e) for pub, e in flows(nodes)), key=str)
    assert {(c.topic, c.publisher, c.subscriber) for c in graph.connections()} == {
        ("/image", "/camera", "/detector"), ("/objects", "/detector", "/planner"), ("/objects", "/detector", "/logger")}
    assert set(nodes) | {"/image", "/objects"} <= texts(drawn_graph(graph))  # Graphviz draws it

    # The ground truth holds: the publisher's socket is in the kernel's table of its process, and the
    # subscriber read exactly what the publisher wrote (connection header and 3 messages).
    sizes = {"/image": (3, 1000, "sensor_msgs/Image"), "/objects": (3, 100, "vision_msgs/Detection2DArray")}
    for pub, e in flows(nodes):
        proc = psutil.Process(nodes[pub].pid)
        sockets = {(f"{c.laddr.ip}:{c.laddr.port}", f"{c.raddr.ip}:{c.raddr.port}")
                   for c in getattr(proc, "net_connections", proc.connections)("tcp") if c.raddr}
        assert (e["local"], e["remote"]) in sockets
        count, size, kind = sizes[e["topic"]]
        header = encode_header({"callerid": pub, "topic": e["topic"], "type": kind, "md5sum": "*", "latching": "0"})
        assert e["bytes"] == len(header) + count * (4 + size)
        read = [r for r in nodes[e["subscriber"]].events("received") if r["topic"] == e["topic"]]
        assert [(r["local"], r["remote"], r["bytes"]) for r in read] == [(e["remote"], e["local"], e["bytes"])]


def test_each_edge_carries_the_bytes_of_its_socket(wire, proctable, sockets_probe, tcp_probe):
    from drums.agent import Agent
    from drums.graph import join
    from drums.graph.export import graph_metrics, render

    master = wire.master()
    nodes = {"/camera": wire.node("/camera", master, "--publish", IMAGE, "--size", "5000"),
             "/detector": wire.node("/detector", master, "--subscribe", IMAGE, "--publish", OBJECTS),
             "/planner": wire.node("/planner", master, "--subscribe", OBJECTS)}
    wait_for_flows(nodes, 2)
    graph, _ = poll_once(master.uri)
    snap = Agent([sockets_probe, tcp_probe], proctable, graph=graph, graph_adapter="ros1").collect()
    sent, received = snap.values(join.EDGE_SENT_BYTES), snap.values(join.EDGE_RECEIVED_BYTES)
    rtt = snap.values(join.EDGE_RTT)
    # What each publisher wrote on the connection's socket (header and messages), as it counted.
    truth = {(e["topic"], pub, e["subscriber"]): e["bytes"] for pub, e in flows(nodes)}
    assert sent == truth and received == truth
    assert set(rtt) == set(truth) and all(0 < v < 0.1 for v in rtt.values())
    assert snap.values(join.EDGE_RETRANSMITS) == dict.fromkeys(truth, 0)  # loopback loses nothing
    # `drums graph` exports carry the same numbers on the edges.
    exported = json.loads(render(graph.snapshot(), "json", graph_metrics(snap)))
    on_edges = {(e["topic"], e["publisher"], e["subscriber"]): (e["sent_bytes_total"], e["received_bytes_total"],
                                                                e["tcp_rtt_seconds"])
                for e in exported["edges"] if e["kind"] == "connection"}
    assert on_edges == {edge: (b, b, rtt[edge]) for edge, b in truth.items()}


class CountingAdapter(Ros1Adapter):
    polls = 0

    def poll(self):
        self.polls += 1
        return super().poll()


def test_a_node_that_exits_leaves_within_two_polls_and_a_killed_one_is_unmapped(wire):
    master = wire.master()
    nodes = {"/talker": wire.node("/talker", master, "--publish", STATUS),
             "/listener": wire.node("/listener", master, "--subscribe", STATUS),
             "/recorder": wire.node("/recorder", master, "--subscribe", STATUS)}
    wait_for_flows(nodes, 2)
    graph = Graph()
    adapter = CountingAdapter(master.uri, interval=0.1)
    follower = Follower(adapter, graph)
    follower.start(wait=True)
    try:
        wait_until(lambda: len(graph.connections()) == 2, "both edges")
        assert set(graph.connections()) == {edge(pub, e) for pub, e in flows(nodes)}

        nodes["/recorder"].stop()
        polls, exited = adapter.polls, time.monotonic()
        wait_until(lambda: "/recorder" not in {n.name for n in graph.entities("node")}, "the recorder to leave")
        assert adapter.polls - polls <= 2, f"{adapter.polls - polls} polls, {time.monotonic() - exited:.3f} s"
        assert [(c.publisher, c.subscriber) for c in graph.connections()] == [("/talker", "/listener")]

        # A killed node never unregisters: the master still lists it, so it stays, unmapped, without edges.
        nodes["/listener"].kill()
        wait_until(lambda: not graph.connections() and len(graph.entities("process")) == 1, "the listener to go silent")
        assert {n.name: n for n in graph.entities("node")} == {
            "/talker": Node("/talker", HERE, nodes["/talker"].pid, "getPid", {"uri": nodes["/talker"].uri}),
            "/listener": Node("/listener", HERE, None, "unmapped", {"uri": nodes["/listener"].uri})}
    finally:
        follower.stop()


def test_each_host_node_uris_name_is_a_host_at_the_address_they_give(wire):
    master = wire.master()
    wire.node("/loopback", master, "--publish", STATUS)
    wire.node("/named", master, "--publish", STATUS, "--hostname", HERE)  # roscpp's default: the host name
    # Another host (a documentation address): its slave never answers, its node stays unmapped.
    wire.node("/away", master, "--publish", STATUS, "--hostname", "203.0.113.9")
    graph, _ = poll_once(master.uri, timeout=3.0)
    # 127.0.0.1 and the host's name are one host, reached from elsewhere by its name.
    assert sorted(graph.entities("host"), key=str) == sorted([Host(HERE, HERE), Host("203.0.113.9", "203.0.113.9")],
                                                               key=str)
    assert {n.name: (n.host, n.mapped_by) for n in graph.entities("node")} == {
        "/loopback": (HERE, "getPid"), "/named": (HERE, "getPid"), "/away": ("203.0.113.9", "unmapped")}


def test_slaves_that_do_not_answer_leave_their_nodes_unmapped_and_the_poll_on_time(wire):
    master = wire.master()
    nodes = {"/camera": wire.node("/camera", master, "--publish", IMAGE, "--subscribe", STATUS),
             "/mute": wire.node("/mute", master, "--subscribe", IMAGE, "--hang", "getPid"),
             "/silent": wire.node("/silent", master, "--publish", STATUS, "--hang", "getPid", "--hang", "getBusInfo")}
    wait_for_flows(nodes, 2)
    # 3 s: on a loaded CI host a healthy slave once took more than 1 s to answer getPid.
    graph, took = poll_once(master.uri, timeout=3.0)
    assert {n.name: n for n in graph.entities("node")} == {
        "/camera": Node("/camera", HERE, nodes["/camera"].pid, "getPid", {"uri": nodes["/camera"].uri}),
        "/mute": Node("/mute", HERE, None, "unmapped", {"uri": nodes["/mute"].uri}),
        "/silent": Node("/silent", HERE, None, "unmapped", {"uri": nodes["/silent"].uri})}
    assert graph.entities("process") == [Process(HERE, nodes["/camera"].pid, comm(nodes["/camera"].pid))]
    # /mute's edge from /camera's bus info; /silent's, which says nothing, from its subscriber's.
    assert set(graph.connections()) == {edge(pub, e) for pub, e in flows(nodes)}
    assert 3.0 <= took < 4.0, f"a poll with a silent slave took {took:.3f} s"


def test_a_connection_string_that_does_not_parse_still_gives_an_edge(wire):
    master = wire.master()
    nodes = {"/talker": wire.node("/talker", master, "--publish", STATUS, "--bus-info", "opaque"),
             "/listener": wire.node("/listener", master, "--subscribe", STATUS)}
    wait_for_flows(nodes, 1)
    graph, _ = poll_once(master.uri)
    assert graph.connections() == [Connection("/status", "/talker", "/listener", "TCPROS", "", "")]


@pytest.mark.parametrize("mode, error", [
    ("garbage", "answered getSystemState with something that is not XML-RPC (not well-formed (invalid token): line 1, column 0)"),
    ("bomb", "answered getSystemState with something that is not XML-RPC "
             "(DTDForbidden(name='lolz', system_id=None, public_id=None))"),
    ("silent", "did not answer getSystemState within 1 s"),
])
def test_a_bad_master_fails_the_poll_in_one_line_on_time(wire, mode, error):
    master = wire.master("--mode", mode)
    adapter = Ros1Adapter(master.uri, timeout=1.0)
    adapter.start()
    started = time.monotonic()
    try:
        with pytest.raises(GraphError) as e:
            adapter.poll()
    finally:
        adapter.stop()
    assert str(e.value) == f"the ROS master at {master.uri} {error}"
    assert time.monotonic() - started < 2.0


def test_no_master_and_a_bad_uri_are_one_line(monkeypatch):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        uri = f"http://127.0.0.1:{s.getsockname()[1]}/"
    adapter = Ros1Adapter(uri)
    adapter.start()
    with pytest.raises(GraphError, match=None) as e:
        adapter.poll()
    adapter.stop()
    assert str(e.value) == f"the ROS master at {uri} refused the connection"
    with pytest.raises(GraphError) as e:
        Ros1Adapter("rosmaster:11311").start()
    assert str(e.value) == "the ROS master URI 'rosmaster:11311' is not an http:// URL"
    monkeypatch.setenv("ROS_MASTER_URI", "http://robot:11311")
    assert Ros1Adapter().master_uri == "http://robot:11311"
    monkeypatch.delenv("ROS_MASTER_URI")
    assert Ros1Adapter().master_uri == "http://localhost:11311/"


def test_a_master_that_turns_bad_leaves_the_last_good_graph_marked_stale(wire, caplog):
    master = wire.master()
    nodes = {"/talker": wire.node("/talker", master, "--publish", STATUS),
             "/listener": wire.node("/listener", master, "--subscribe", STATUS)}
    wait_for_flows(nodes, 1)
    graph = Graph()
    follower = Follower(Ros1Adapter(master.uri, interval=0.1, timeout=0.5), graph)
    follower.start(wait=True)
    good = ({"/listener", "/talker"}, {edge(pub, e) for pub, e in flows(nodes)})
    seen = lambda: ({n.name for n in graph.entities("node")}, set(graph.connections()))  # noqa: E731
    try:
        wait_until(lambda: seen() == good, "the good graph")
        for turn, reason in [(lambda: master.say("mode garbage"), "not XML-RPC"),
                             (lambda: master.say("mode silent"), "did not answer"),
                             (master.kill, "refused the connection")]:
            turn()
            wait_until(lambda: reason in graph.error, f"the master's {reason!r} to be noticed")
            assert graph.stale() and seen() == good
    finally:
        follower.stop()
    prefix, suffix = f"graph (ros1): the ROS master at {master.uri} ", "; keeping the last good graph, marked stale"
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == [prefix + reason + suffix for reason in (
        "answered getSystemState with something that is not XML-RPC (not well-formed (invalid token): line 1, column 0)",
        "did not answer getSystemState within 0.5 s", "refused the connection")]


# What the nodes say, decoded without a network: the formats of roscpp and rospy, and garbage.

def test_connection_strings_of_roscpp_and_rospy():
    assert parse_info("TCPROS connection on port 41437 to [127.0.0.1:52842 on socket 12]") == (41437, "127.0.0.1", 52842)
    assert parse_info("TCPROS connection on port 59746 to [robot-2:34318 on socket 11]") == (59746, "robot-2", 34318)
    assert parse_info("TCPROS connection on port 5 to [::1:6 on socket 7]") == (5, "::1", 6)
    assert parse_info("TCPROS connection on port None to [None:None on socket None]") is None  # rospy, not set up yet
    assert parse_info(None) is None and parse_info("INTRAPROCESS connection") is None


def test_bus_info_keeps_well_formed_live_entries():
    line = "TCPROS connection on port 1 to [10.0.0.2:2 on socket 3]"
    assert bus_info([[1, "/b", "o", "TCPROS", "/t", True, line], [2, "/c", "o", "TCPROS", "/t", False, line],
                     ["junk"], [3, 4, "o", "TCPROS", "/t", True], [4, "/d", "o", "TCPROS", "/t", 1]]) == [
        ("o", "/b", "TCPROS", "/t", (1, "10.0.0.2", 2)), ("o", "/d", "TCPROS", "/t", None)]
    with pytest.raises(GraphError):
        bus_info("connections")


def test_addresses_across_hosts_come_from_both_ends():
    # No local socket: the publisher's address is the one its subscriber was told to connect to.
    bus = {"/pub": [("o", "/sub", "TCPROS", "/t", (41000, "10.0.0.2", 52000))],
           "/sub": [("i", "/pub", "TCPROS", "/t", (52000, "10.0.0.1", 41000))]}
    assert connections(bus, {}) == [Connection("/t", "/pub", "/sub", "TCPROS", "10.0.0.1:41000", "10.0.0.2:52000")]
    # A publisher that does not answer: its subscriber tells the edge, and its own address if it can.
    assert connections({"/sub": bus["/sub"]}, {}) == [Connection("/t", "/pub", "/sub", "TCPROS", "10.0.0.1:41000", "")]
    sockets = {(52000, 41000): ("10.0.0.2:52000", "10.0.0.1:41000")}
    assert connections({"/sub": bus["/sub"]}, sockets) == [
        Connection("/t", "/pub", "/sub", "TCPROS", "10.0.0.1:41000", "10.0.0.2:52000")]


@pytest.mark.parametrize("value, error", [
    ("state", "answered getSystemState with str, not [pubs, subs, services]"),
    ([[], []], "answered getSystemState with list, not [pubs, subs, services]"),
    ([[["/t"]], [], []], ", getSystemState: not a list of [name, value] pairs"),
    ([[["/t", "/a"]], [], []], ", getSystemState: /t: not a list of node names"),
])
def test_a_malformed_system_state_is_one_line(value, error):
    with pytest.raises(GraphError) as e:
        system_state(value, "the ROS master at http://m:11311/")
    assert str(e.value) == "the ROS master at http://m:11311/" + ("" if error.startswith(",") else " ") + error

"""The ROS 2 adapter against real rclpy nodes in processes of their own (Fast DDS, from PyPI)."""
from __future__ import annotations

import json
import subprocess
import sys
import threading
import time

from drums.graph.model import Graph
from tests.conftest import eventually, wait_until
from tests.graph.test_draw import drawn_graph, texts

DEFAULT_TOPICS = {"/rosout", "/parameter_events"}  # every rclpy node publishes on these


def nodes(graph: Graph) -> dict[str, tuple]:
    return {n.name: (n.pid, n.mapped_by) for n in graph.entities("node")}


def edges(graph: Graph, topic: str) -> set[tuple[str, str]]:
    return {(c.publisher, c.subscriber) for c in graph.connections() if c.topic == topic}


def test_talker_listener(ros2_graph, ros_nodes):
    talker, listener = ros_nodes("talker"), ros_nodes("listener")

    def complete():
        assert nodes(ros2_graph) == {"/talker": (talker.pid, "gid"), "/listener": (listener.pid, "gid")}
        assert {t.name for t in ros2_graph.entities("topic")} == {"/chatter"} | DEFAULT_TOPICS
        assert edges(ros2_graph, "/chatter") == {("/talker", "/listener")}
    eventually(complete, timeout=5)
    (chatter,) = [t for t in ros2_graph.entities("topic") if t.name == "/chatter"]
    assert chatter.types == ("std_msgs/msg/String",)
    pub = [e for e in ros2_graph.entities("endpoint") if e.topic == "/chatter" and e.kind == "publisher"]
    assert [(e.node, e.qos["reliability"], e.qos["durability"]) for e in pub] == [("/talker", "reliable", "volatile")]
    assert {c.qos_check for c in ros2_graph.connections() if c.topic == "/chatter"} == {"ok"}
    assert {p.pid for p in ros2_graph.entities("process")} == {talker.pid, listener.pid}
    assert not ros2_graph.stale()


def test_pipeline_of_three_processes(ros2_graph, ros_nodes):
    producer, processor, sink = ros_nodes("producer"), ros_nodes("processor"), ros_nodes("sink")

    def complete():
        assert nodes(ros2_graph) == {"/producer": (producer.pid, "gid"), "/processor": (processor.pid, "gid"),
                                     "/sink": (sink.pid, "gid")}
        assert edges(ros2_graph, "/image") == {("/producer", "/processor")}
        assert edges(ros2_graph, "/processed") == {("/processor", "/sink")}
        assert {t.name for t in ros2_graph.entities("topic")} == {"/image", "/processed"} | DEFAULT_TOPICS
    eventually(complete, timeout=5)
    # The data really flows through the pipeline; the graph may be whole before the first 1 MB
    # image has gone through both hops.
    def flowing():
        assert sink.count() > 0
    eventually(flowing, timeout=5)
    shown = texts(drawn_graph(ros2_graph))  # Graphviz draws it; the plumbing is left out
    assert {"/producer", "/processor", "/sink", "/image", "/processed"} <= shown
    assert not DEFAULT_TOPICS & shown


def test_two_nodes_in_one_process_map_to_its_pid(ros2_graph, ros_nodes):
    both = ros_nodes("talker", "front", "back")
    wait_until(lambda: nodes(ros2_graph) == {"/front": (both.pid, "gid"), "/back": (both.pid, "gid")},
               "both nodes mapped to their process", timeout=5)


def test_node_without_gid_is_mapped_by_its_command_line(ros2_graph, ros_nodes):
    # Cyclone-like case: the GUID says nothing of the PID, here because the node is renamed by
    # a remapping argument and checked as the /proc fallback would check it.
    from drums.graph.nodepids import ProcScan, map_nodes
    p = ros_nodes("idle", "--ros-args", "-r", "__node:=quiet")
    assert map_nodes({"/quiet": None}, ProcScan()) == {"/quiet": (p.pid, "cmdline")}


def test_a_node_with_another_host_id_is_ours_while_its_pid_bits_are_one_of_our_processes(ros2_graph, ros_nodes):
    """Fast DDS hashes every interface address into the host id of a process, once: a node started
    after an interface came (a VPN, a veth, a new lease) carries another id than the agent's reader."""
    from drums.graph.nodepids import FASTDDS_VENDOR, ProcScan, map_nodes
    p = ros_nodes("idle", "--ros-args", "-r", "__node:=renumbered")
    ours, theirs = FASTDDS_VENDOR + b"\x01\x02" + bytes(8), FASTDDS_VENDOR + b"\x03\x04"
    scan = ProcScan()
    scan.refresh()
    unused = next(bits for bits in range(1, 1 << 16) if all(pid & 0xFFFF != bits for pid in scan.pids()))
    prefixes = {"/renumbered": theirs + (p.pid & 0xFFFF).to_bytes(2, "little") + bytes(6),
                "/elsewhere": theirs + unused.to_bytes(2, "little") + bytes(6)}
    assert map_nodes(prefixes, scan, ours) == {"/renumbered": (p.pid, "gid"), "/elsewhere": (None, "remote")}
    # Asked again with every node placed and its process running, the mapping stands without a
    # listing of /proc.
    listed = scan.table.refreshes
    assert map_nodes(prefixes, scan, ours) == {"/renumbered": (p.pid, "gid"), "/elsewhere": (None, "remote")}
    assert scan.table.refreshes == listed
    # Killed, it is gone at once, though its host id is not ours: it was mapped to a process of ours
    # (DDS would list it for its 20 s lease).
    p.kill()
    assert map_nodes(prefixes, scan, ours) == {"/renumbered": (None, "gone"), "/elsewhere": (None, "remote")}
    assert scan.table.refreshes == listed + 1


def test_a_node_placed_before_its_endpoints_were_read_is_gone_at_once_when_killed(ros2_graph, ros_nodes):
    """DDS tells a node's name before its endpoints: the node is placed by its command line with no
    participant known. Killed, DDS lists it for its 20 s lease, with or without the endpoints it
    read meanwhile; the graph says it is gone at once."""
    from drums.graph.nodepids import FASTDDS_VENDOR, ProcScan, map_nodes
    ours, theirs = FASTDDS_VENDOR + b"\x01\x02" + bytes(8), FASTDDS_VENDOR + b"\x03\x04"
    early = ros_nodes("idle", "--ros-args", "-r", "__node:=early")
    scan = ProcScan()
    assert map_nodes({"/early": None}, scan, ours) == {"/early": (early.pid, "cmdline")}
    early.kill()
    assert map_nodes({"/early": None}, scan, ours) == {"/early": (None, "gone")}
    # Its participant read since, with another host id than ours (an interface came or went).
    late = theirs + (early.pid & 0xFFFF).to_bytes(2, "little") + bytes(6)
    assert map_nodes({"/early": late}, scan, ours) == {"/early": (None, "gone")}
    # The name started again in a new process is placed there.
    again = ros_nodes("idle", "--ros-args", "-r", "__node:=early")
    assert map_nodes({"/early": None}, scan, ours) == {"/early": (again.pid, "cmdline")}


def test_a_process_seen_before_it_loaded_ros_is_mapped_once_its_node_appears(ros2_graph, ros_nodes):
    """A scan of every process (for a node the GIDs do not place) reads one that still imports
    rclpy: no librcl yet. Its node, when it comes, is placed by its GID all the same."""
    from drums.graph.nodepids import FASTDDS_VENDOR, ProcScan, map_nodes
    scan = ProcScan()
    late = {}
    slow = {"DRUMS_TEST_IMPORT_DELAY": "2"}
    starting = threading.Thread(target=lambda: late.update(p=ros_nodes("idle", "late", env=slow)))
    starting.start()
    importing = []

    def seen():
        scan.refresh()
        importing.extend(pid for pid in scan.pids() if "late" in scan.cmdline(pid))
        return importing
    wait_until(seen, "the late node's process", timeout=5)
    assert map_nodes({"/placed_by_nothing": None}, scan)["/placed_by_nothing"][1] in ("unmapped", "librcl")
    assert not scan.has_rcl(importing[0])  # asked while it imports, and remembered
    starting.join()
    prefix = FASTDDS_VENDOR + bytes(2) + (late["p"].pid & 0xFFFF).to_bytes(2, "little") + bytes(6)
    assert map_nodes({"/late": prefix}, scan) == {"/late": (late["p"].pid, "gid")}


def test_new_node_appears_and_killed_node_leaves_within_two_seconds(ros2_graph, ros_nodes):
    listener = ros_nodes("listener")

    def alone():  # the setting, not what is timed: the nodes of earlier tests gone, the listener seen
        assert set(nodes(ros2_graph)) == {"/listener"}
    eventually(alone, timeout=15)

    newcomer = ros_nodes("talker", "newcomer")  # returns once its node exists
    created_at = time.monotonic()
    # Two clocks run at once: when the graph shows the newcomer, and when DDS itself has
    # discovered it (the listener gets its first message). Fast DDS sometimes takes about 3 s
    # here (its announcement period) for the listener too; the graph must not lag DDS.
    appeared_after = heard_after = None
    while time.monotonic() - created_at < 10 and None in (appeared_after, heard_after):
        if appeared_after is None and nodes(ros2_graph).get("/newcomer") == (newcomer.pid, "gid"):
            appeared_after = time.monotonic() - created_at
        if heard_after is None and listener.count() > 0:
            heard_after = time.monotonic() - created_at
        time.sleep(0.01)
    assert None not in (appeared_after, heard_after), (appeared_after, heard_after)
    assert appeared_after <= max(2.0, heard_after + 0.5), (appeared_after, heard_after)
    wait_until(lambda: edges(ros2_graph, "/chatter") == {("/newcomer", "/listener")}, "the new edge", timeout=2)

    killed_at = time.monotonic()
    newcomer.kill()  # SIGKILL: DDS itself would keep it for its 20 s lease
    wait_until(lambda: set(nodes(ros2_graph)) == {"/listener"}, "the killed node to leave", timeout=5)
    left_after = time.monotonic() - killed_at
    assert edges(ros2_graph, "/chatter") == set()
    assert {p.pid for p in ros2_graph.entities("process")} == {listener.pid}
    assert left_after <= 2.0, left_after


def test_a_node_restarted_under_its_name_shows_in_its_new_process_while_dds_still_lists_the_killed_one(
        ros2_graph, ros_nodes):
    """The usual way to debug a crashed node: start it again. DDS lists the killed participant's
    endpoints under the same node name for its 20 s lease; the graph shows the new process's."""
    for round in range(3):  # which participant's endpoints DDS lists first varies
        first = ros_nodes("talker", "phoenix")
        wait_until(lambda: nodes(ros2_graph).get("/phoenix") == (first.pid, "gid"), "the first phoenix", timeout=10)
        first.kill()
        wait_until(lambda: "/phoenix" not in nodes(ros2_graph), "the killed phoenix to leave", timeout=5)
        again = ros_nodes("talker", "phoenix")
        wait_until(lambda: nodes(ros2_graph).get("/phoenix") == (again.pid, "gid"),
                   f"round {round}: the restarted phoenix, within DDS's lease of the killed one", timeout=8)
        # DDS may list the new participant before its endpoints (and the killed one's are gone).
        wait_until(lambda: {e.node for e in ros2_graph.entities("endpoint") if e.topic == "/chatter"} == {"/phoenix"},
                   f"round {round}: the restarted phoenix's /chatter publisher", timeout=8)
        again.kill()
        wait_until(lambda: "/phoenix" not in nodes(ros2_graph), "the restarted phoenix to leave", timeout=5)


def test_drums_graph_exports_json(ros_nodes, tmp_path):
    talker, listener = ros_nodes("talker"), ros_nodes("listener")
    out = tmp_path / "graph.json"
    # As the README shows it; the command waits for DDS discovery before it writes.
    done = subprocess.run([sys.executable, "-m", "drums", "graph", "--graph", "ros2", "--format", "json",
                           "--output", str(out)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    data = json.loads(out.read_text())
    by_id = {v["id"]: v for v in data["nodes"]}
    assert (by_id["node:/talker"]["pid"], by_id["node:/listener"]["pid"]) == (talker.pid, listener.pid)
    assert {(e["source"], e["target"]) for e in data["edges"] if e["kind"] == "connection"} == {
        ("node:/talker", "node:/listener")}
    assert data["stale"] == ""

"""Paths through the graph from joined timings (drums.graph.paths), on snapshots made by hand: which
chains are paths, and their times. The same against real nodes: tests/graph/test_topic_timing.py."""
from drums.graph import join
from drums.graph.paths import paths
from drums.metrics import Histogram, Snapshot


def timing(mean: float, count: int = 10) -> Histogram:
    return Histogram([], mean * count, count, ())


def test_chains_from_a_source_to_each_node_that_reacts_no_further():
    snap = Snapshot()
    snap.add(join.EDGE_AGE, ("/image", "/camera", "/detector"), timing(0.001))
    snap.add(join.NODE_REACTION, ("/detector", "/image", "/objects"), timing(0.015))
    snap.add(join.EDGE_AGE, ("/objects", "/detector", "/planner"), timing(0.002))
    snap.add(join.EDGE_AGE, ("/objects", "/detector", "/recorder"), timing(0.003))
    snap.add(join.NODE_REACTION, ("/planner", "/objects", "/path"), timing(0.030))  # /path: no one takes it
    # Plumbing is no path: the detector logs what it saw, and a node of Drums takes /objects.
    snap.add(join.NODE_REACTION, ("/detector", "/image", "/rosout"), timing(0.001))
    snap.add(join.EDGE_AGE, ("/rosout", "/detector", "/logger"), timing(0.001))
    snap.add(join.EDGE_AGE, ("/objects", "/detector", "/_drums_graph_1"), timing(0.001))
    # A loop (/a -> /b -> /a) has no start, and an edge with nothing counted is not taken.
    snap.add(join.EDGE_AGE, ("/ping", "/a", "/b"), timing(0.001))
    snap.add(join.NODE_REACTION, ("/b", "/ping", "/pong"), timing(0.001))
    snap.add(join.EDGE_AGE, ("/pong", "/b", "/a"), timing(0.001))
    snap.add(join.NODE_REACTION, ("/a", "/pong", "/ping"), timing(0.001))
    snap.add(join.EDGE_AGE, ("/image", "/camera", "/idle"), Histogram([], 0.0, 0, ()))
    found, truncated = paths(snap)
    assert not truncated
    assert [(p["nodes"], p["topics"], round(p["seconds"], 6)) for p in found] == [
        (["/camera", "/detector", "/recorder"], ["/image", "/objects"], 0.019),
        (["/camera", "/detector", "/planner"], ["/image", "/objects"], 0.018)]
    assert found[1]["parts"] == [
        {"edge": ["/image", "/camera", "/detector"], "count": 10, "sum": 0.01, "seconds": 0.001},
        {"reaction": ["/detector", "/image", "/objects"], "count": 10, "sum": 0.15, "seconds": 0.015},
        {"edge": ["/objects", "/detector", "/planner"], "count": 10, "sum": 0.02, "seconds": 0.002}]


def test_a_dense_graph_keeps_the_slowest_paths_and_says_it_left_some_out():
    snap = Snapshot()  # 3 layers of 6 nodes, each taking from every node of the layer before: 6^3 paths
    layers = [[f"/l{i}n{j}" for j in range(6)] for i in range(4)]
    layers[0] = ["/source"]
    for i in range(1, 4):
        for j, node in enumerate(layers[i]):
            for before in layers[i - 1]:
                snap.add(join.EDGE_AGE, (f"/t{i}", before, node), timing(0.001 * (j + 1)))
            if i < 3:
                snap.add(join.NODE_REACTION, (node, f"/t{i}", f"/t{i + 1}"), timing(0.001))
    found, truncated = paths(snap)
    assert truncated and len(found) == 100
    assert found[0]["nodes"] == ["/source", "/l1n5", "/l2n5", "/l3n5"] and round(found[0]["seconds"], 6) == 0.02
    assert [p["seconds"] for p in found] == sorted((p["seconds"] for p in found), reverse=True)

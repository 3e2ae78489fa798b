"""Per-topic and per-edge accounting, end to end: real ROS 2 nodes in processes of their own, the
rtps and rcl probes in the kernel, the ROS 2 graph, and the agent's join. Each publisher sends a
burst of exactly BURST messages; every count is checked against what the nodes themselves count."""
from __future__ import annotations

import glob
import json
import os

import pytest
from std_msgs.msg import String, UInt8MultiArray

from drums.agent import Agent
from drums.graph import join
from drums.graph.export import graph_metrics, render
from drums.kernel.features import Features
from tests.conftest import TEST_PIN_ROOT, wait_until
from tests.graph.rosnodes import IMAGE_BYTES, payload

BURST = 30
# Over UDP (FASTDDS_BUILTIN_TRANSPORTS=UDPv4; the LOCALHOST discovery range would put shared
# memory back) and over the default transports (shared memory between processes of one host).
UDP = {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}
PIPELINE = (("talker", "/chatter", "listener"), ("producer", "/image", "processor"),
            ("processor", "/processed", "sink"))


@pytest.fixture
def pipeline(ros_nodes, ros2_graph):
    def start(env):
        env = {**env, "DRUMS_TEST_BURST": str(BURST)}
        procs = {role: ros_nodes(role, env=env) for role in ("listener", "talker", "sink", "processor", "producer")}
        pids = {f"/{role}": p.pid for role, p in procs.items()}

        def mapped():
            nodes = {n.name: n.pid for n in ros2_graph.entities("node")}
            edges = {(c.topic, c.publisher, c.subscriber) for c in ros2_graph.connections()}
            return nodes == pids and edges == {(t, f"/{p}", f"/{s}") for p, t, s in PIPELINE}
        # DDS discovery of five processes, on a host the other lane of make test keeps busy
        wait_until(mapped, "the five nodes mapped to their PIDs and the three edges", timeout=40)
        return procs
    return start


def _run(procs, agent):
    agent.collect()  # the probes learn of the new processes: parse their datagrams from now on
    procs["talker"].go()
    procs["producer"].go()
    # 3 s at 10 Hz, once each publisher has matched its subscribers (pairwise DDS discovery, which
    # a host busy with three lanes of make test can hold up for tens of seconds)
    counts = {}

    def done() -> bool:
        counts.update((role, p.count()) for role, p in procs.items())
        return all(n == BURST for n in counts.values())
    wait_until(done, lambda: f"every node to publish or receive {BURST} messages (they did {counts})", timeout=60)
    return agent.collect()


def _before_linux_5_15(proctable):
    """The rtps and rcl probes as Linux 5.10 to 5.14 has them, on this kernel: each syscall's entry
    traced for its arguments (no bpf_task_pt_regs), a hash of threads for takes (no task-local
    storage in tracing programs before 5.12), and every tracepoint and uprobe held on its perf event
    by the agent (no BPF links on perf events); and with a head per thread to parse datagrams in, as
    on a PREEMPT_RT kernel (JetPack's 5.10 has one). Started and unloaded by the caller."""
    from drums.probes.rcl import RclProbe
    from drums.probes.rtps import RtpsProbe
    old = Features()
    old.__dict__.update(perf_links=False, task_pt_regs=False, task_storage=False, preempt_rt=True)
    rtps = RtpsProbe(old, proctable, pin_root=f"{TEST_PIN_ROOT}_before_5_15")
    rcl = RclProbe(old, proctable, pin_root=f"{TEST_PIN_ROOT}_before_5_15")
    return rtps, rcl


@pytest.mark.kernel
def test_udp_pipeline_counts_and_bytes_per_topic_and_edge(pipeline, ros2_graph, proctable, rtps_probe,
                                                          rcl_probe, sched_probe):
    _check_udp_pipeline(pipeline, ros2_graph, proctable, rtps_probe, rcl_probe, sched_probe)


def test_udp_pipeline_counts_alike_as_before_linux_5_15(pipeline, ros2_graph, proctable, sched_probe):
    rtps, rcl = _before_linux_5_15(proctable)
    rtps.start()
    try:
        rcl.start()
        try:
            # The entries' path, its programs pinned for the agent to hold on perf events, no link.
            assert os.path.exists(os.path.join(rtps.pin_dir, "prog_enter_sendto"))
            assert not glob.glob(os.path.join(rtps.pin_dir, "link*"))
            _check_udp_pipeline(pipeline, ros2_graph, proctable, rtps, rcl, sched_probe)
            assert not glob.glob(os.path.join(rcl.pin_dir, "lib-*"))  # its uprobes held likewise
        finally:
            rcl.unload()
    finally:
        rtps.unload()


def _check_udp_pipeline(pipeline, ros2_graph, proctable, rtps_probe, rcl_probe, sched_probe):
    procs = pipeline(UDP)
    agent = Agent([rtps_probe, rcl_probe, sched_probe], proctable, graph=ros2_graph, graph_adapter="ros2")
    snap = _run(procs, agent)
    published, taken = snap.values(join.TOPIC_PUBLISHED), snap.values(join.TOPIC_TAKEN)
    samples, sent = snap.values(join.TOPIC_SAMPLES_SENT), snap.values(join.TOPIC_SENT_BYTES)
    wire = snap.values(join.TOPIC_SENT_WIRE_BYTES)
    edge_samples, edge_bytes = snap.values(join.EDGE_SAMPLES), snap.values(join.EDGE_RECEIVED_BYTES)
    sizes = {"/chatter": payload(String(data="hello")), "/image": payload(UInt8MultiArray(data=bytes(IMAGE_BYTES)))}
    sizes["/processed"] = sizes["/image"]
    for pub, topic, sub in PIPELINE:
        pub, sub = f"/{pub}", f"/{sub}"
        assert published[topic, pub] == BURST
        assert taken[topic, sub] == BURST
        assert samples[topic, pub] == BURST
        assert edge_samples[topic, pub, sub] == BURST
        assert sent[topic, pub] == edge_bytes[topic, pub, sub] == BURST * sizes[topic]
        # On the wire, a fragment lost to a full socket buffer and sent again counts twice.
        assert wire[topic, pub] >= sent[topic, pub]
    assert wire["/chatter", "/talker"] == sent["/chatter", "/talker"]  # small samples, never lost here
    cpu = snap.values(join.NODE_CPU)
    assert set(cpu) == {(f"/{role}",) for role in procs} and all(v > 0 for v in cpu.values())

    # `drums graph` exports put the same numbers on the graph's vertices and edges.
    exported = json.loads(render(ros2_graph.snapshot(), "json", graph_metrics(snap)))
    vertices = {v["id"]: v for v in exported["nodes"]}
    edges = {(e["topic"], e["publisher"], e["subscriber"]): e for e in exported["edges"] if e["kind"] == "connection"}
    for pub, topic, sub in PIPELINE:
        pub, sub = f"/{pub}", f"/{sub}"
        assert vertices[f"topic:{topic}"]["messages_published_total"][pub] == BURST
        assert vertices[f"topic:{topic}"]["sent_bytes_total"] == {pub: BURST * sizes[topic]}
        edge = edges[topic, pub, sub]
        assert (edge["samples_received_total"], edge["received_bytes_total"]) == (BURST, BURST * sizes[topic])
    assert {v: vertices[f"node:{v[0]}"]["cpu_seconds_total"] for v in cpu} == cpu


def test_shared_memory_pipeline_counts_messages_per_topic(pipeline, ros2_graph, proctable, rtps_probe, rcl_probe):
    procs = pipeline({})
    agent = Agent([rtps_probe, rcl_probe], proctable, graph=ros2_graph, graph_adapter="ros2")
    snap = _run(procs, agent)
    published, taken = snap.values(join.TOPIC_PUBLISHED), snap.values(join.TOPIC_TAKEN)
    for pub, topic, sub in PIPELINE:
        assert published[topic, f"/{pub}"] == BURST
        assert taken[topic, f"/{sub}"] == BURST
    # No socket carried the samples: the RTPS probe saw none of them.
    assert not snap.values(join.EDGE_SAMPLES)

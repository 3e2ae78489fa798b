"""`drums foxglove` as a user runs it, beside `drums agent --graph ros2` and rclpy nodes in their own
processes, read by a WebSocket client written from the Foxglove WebSocket protocol's specification
(tests/foxglove_client.py, not the SDK): the server advertises a channel per node with its JSON schema, streams
its rows as the agent's /metrics has them, and tells the ROS graph; a client that never reads
costs the server bounded memory."""
from __future__ import annotations

import json
import socket
import subprocess
import sys
import time

import pytest

from tests.agentproc import running_agent, samples, scrape
from tests.conftest import TIME_SCALE, eventually
from tests.foxglove_client import Client

REMAP = ("--ros-args", "-r", "chatter:=fx_chatter")


def serving(url: str, *argv: str) -> tuple[subprocess.Popen, int]:
    proc = subprocess.Popen([sys.executable, "-m", "drums", "foxglove", "--port", "0", "--agent", url, *argv],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    line = proc.stdout.readline()
    assert line.startswith("drums foxglove: serving ws://"), line + proc.stdout.read()
    return proc, int(line.split("ws://", 1)[1].split()[0].rsplit(":", 1)[1])


def rss(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmRSS:"))


@pytest.mark.lane2
def test_a_client_from_the_spec_gets_channels_rows_as_metrics_has_them_and_the_graph(ros_nodes):
    host = socket.gethostname()
    with running_agent("--graph", "ros2") as url:
        base = url.rsplit("/", 1)[0]
        # On a topic of their own: the other lanes of make test count /chatter exactly
        ros_nodes("listener", "fx_listener", *REMAP)
        talker = ros_nodes("talker", "fx_talker", *REMAP)
        proc, port = serving(base)
        try:
            client = Client(port)
            info = client.message()
            assert info["op"] == "serverInfo" and "connectionGraph" in info["capabilities"], info
            channels, wanted = {}, f"/drums/nodes/{host}/fx_talker"
            deadline = time.monotonic() + 30
            while wanted not in channels and time.monotonic() < deadline:
                m = client.message()
                if m["op"] == "advertise":
                    channels.update({c["topic"]: c for c in m["channels"]})
            channel = channels[wanted]
            schema = json.loads(channel["schema"])
            assert channel["encoding"] == "json" and {"pid", "cpu_percent", "published_hz"} <= schema["properties"].keys()
            client.send({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": channel["id"]}]})
            client.send({"op": "subscribeConnectionGraph"})
            graph, rows = None, []
            deadline = time.monotonic() + 60 * TIME_SCALE  # an agent busy beside other lanes answers late
            while (graph is None or len(rows) < 3) and time.monotonic() < deadline:
                m = client.message()
                if m["op"] == "connectionGraphUpdate":
                    graph = m
                elif m["op"] == "messageData" and m["subscription"] == 7:
                    rows.append(m["data"])
            assert {"name": "/fx_chatter", "publisherIds": ["/fx_talker"]} in graph["publishedTopics"], graph
            assert {"name": "/fx_chatter", "subscriberIds": ["/fx_listener"]} in graph["subscribedTopics"], graph
            assert all(r["pid"] == talker.proc.pid for r in rows) and 5 < rows[-1]["published_hz"] < 15, rows

            def as_metrics_has_it():  # a gauge: the row of the moment is what a scrape says
                m = client.message()
                while m.get("subscription") != 7:
                    m = client.message()
                memory = samples(scrape(url), "drums_node_resident_memory_bytes")[(("node", "/fx_talker"),)]
                assert m["data"]["memory_bytes"] == memory, (m["data"], memory)
            eventually(as_metrics_has_it, timeout=20)
        finally:
            proc.terminate()
            assert proc.wait(timeout=20) == 0, proc.stdout.read()


@pytest.mark.lane2
def test_a_client_that_never_reads_costs_the_server_bounded_memory():
    with running_agent() as url:
        proc, port = serving(url.rsplit("/", 1)[0], "--interval", "0.2")
        try:
            reader = Client(port)  # reads, so that the channels are advertised to it and it can subscribe
            advertised = {}
            deadline = time.monotonic() + 20
            while len(advertised) < 20 and time.monotonic() < deadline:
                m = reader.message()
                if m["op"] == "advertise":
                    advertised.update({c["id"]: c for c in m["channels"]})
            stalled = Client(port)
            stalled.send({"op": "subscribe", "subscriptions": [{"id": i, "channelId": c}
                                                              for i, c in enumerate(advertised)]})
            time.sleep(10)  # what it does not read fills the sockets' buffers, then the server's backlog
            grown = rss(proc.pid)
            time.sleep(15)
            # Bounded: past the backlog the server drops the stalled client's oldest messages.
            assert rss(proc.pid) - grown < 4 << 20, (grown, rss(proc.pid))
            assert proc.poll() is None
        finally:
            proc.terminate()
            assert proc.wait(timeout=20) == 0, proc.stdout.read()

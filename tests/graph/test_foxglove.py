"""`drums foxglove` as a user runs it, beside `drums agent --graph ros2` and rclpy nodes in their own
processes, read by a WebSocket client written here from the Foxglove WebSocket protocol's
specification (not the SDK): the server advertises a channel per node with its JSON schema, streams
its rows as the agent's /metrics has them, and tells the ROS graph; a client that never reads
costs the server bounded memory."""
from __future__ import annotations

import base64
import hashlib
import json
import os
import socket
import struct
import subprocess
import sys
import time

import pytest

from tests.agentproc import running_agent, samples, scrape
from tests.conftest import eventually

GUID = "258EAFA5-E914-47DA-95CA-C5AB0DC85B11"  # RFC 6455's
# The protocol's subprotocol names: the specification's (v1), and the one the SDK's server speaks
# (the same messages, renamed); the server picks.
PROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")


class Client:
    """The protocol's client side, over a plain socket: the handshake, JSON text frames out (masked),
    text and binary frames in."""

    def __init__(self, port: int):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=20)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                           f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                           f"Sec-WebSocket-Protocol: {', '.join(PROTOCOLS)}\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            head += self.sock.recv(1)
        lines = head.decode().split("\r\n")
        assert lines[0].split()[1] == "101", lines
        headers = {k.lower(): v.strip() for k, v in (line.split(":", 1) for line in lines[1:] if ":" in line)}
        accept = base64.b64encode(hashlib.sha1((key + GUID).encode()).digest()).decode()
        assert headers["sec-websocket-accept"] == accept and headers["sec-websocket-protocol"] in PROTOCOLS, headers

    def _exactly(self, n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = self.sock.recv(n - len(data))
            if not chunk:
                raise ConnectionError("closed")
            data += chunk
        return data

    def frame(self) -> tuple[int, bytes]:
        """(opcode, payload) of the next whole message (the server's frames are not masked)."""
        payload, first = b"", None
        while True:
            b0, b1 = self._exactly(2)
            size = b1 & 0x7F
            if size == 126:
                size = struct.unpack(">H", self._exactly(2))[0]
            elif size == 127:
                size = struct.unpack(">Q", self._exactly(8))[0]
            payload += self._exactly(size)
            first = first if first is not None else b0 & 0x0F
            if b0 & 0x80:
                return first, payload

    def message(self):
        """The next text (JSON) or Message Data (binary: subscription id, timestamp, payload)."""
        while True:
            opcode, payload = self.frame()
            if opcode == 1:
                return json.loads(payload)
            if opcode == 2 and payload[0] == 0x01:
                sub, at = struct.unpack_from("<IQ", payload, 1)
                return {"op": "messageData", "subscription": sub, "at": at, "data": json.loads(payload[13:])}

    def send(self, message: dict) -> None:
        data, mask = json.dumps(message).encode(), os.urandom(4)
        head = bytes([0x81]) + (bytes([0x80 | len(data)]) if len(data) < 126 else bytes([0x80 | 126]) + struct.pack(">H", len(data)))
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))


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
        ros_nodes("listener", "fx_listener")
        talker = ros_nodes("talker", "fx_talker")
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
            deadline = time.monotonic() + 30
            while (graph is None or len(rows) < 3) and time.monotonic() < deadline:
                m = client.message()
                if m["op"] == "connectionGraphUpdate":
                    graph = m
                elif m["op"] == "messageData" and m["subscription"] == 7:
                    rows.append(m["data"])
            assert {"name": "/chatter", "publisherIds": ["/fx_talker"]} in graph["publishedTopics"], graph
            assert {"name": "/chatter", "subscriberIds": ["/fx_listener"]} in graph["subscribedTopics"], graph
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

"""A client of the Foxglove WebSocket protocol written from its specification (docs/spec.md of
foxglove/ws-protocol), not the SDK, over a plain socket: what the tests and the benchmark of
`drums foxglove` read it with."""
from __future__ import annotations

import base64
import hashlib
import json
import os
import socket
import struct

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

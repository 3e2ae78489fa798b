"""A ROS 1 master and ROS 1 nodes that speak the documented wire protocols (the Master and Slave
XML-RPC APIs, TCPROS), from the standard library alone: the ground truth of tests/graph/test_ros1.py.

    python ros1_wire.py master [--port P] [--mode good|garbage|silent|bomb|huge]
    python ros1_wire.py node --name /camera --master URI --publish /image:sensor_msgs/Image \\
        [--subscribe /objects:vision_msgs/Detection2DArray] [--messages 3] [--size 100] \\
        [--hang getPid] [--bus-info roscpp|opaque] [--hostname NAME]

A master prints "ready <uri>" and takes "mode <mode>" lines on stdin: "garbage" answers HTTP 200
with a body that is not XML, "bomb" an XML entity bomb, "silent" reads nothing and never answers,
"huge" lists HUGE topics, each published by a node of its own (about 17 MB), and knows no node.
A node prints "ready <pid> <uri>", then one JSON line per connection: a publisher, once it has
sent its messages, what it wrote on that socket (header included) and the socket's two addresses
as getsockname() and getpeername() give them; a subscriber, once it has read as many messages,
what it read. Its getBusInfo answers in roscpp's format. SIGTERM or SIGINT unregisters and exits.
"""
from __future__ import annotations

import argparse
import functools
import json
import os
import signal
import socket
import struct
import sys
import threading
import time
from socketserver import ThreadingMixIn
import xmlrpc.client
from xmlrpc.client import ServerProxy
from xmlrpc.server import SimpleXMLRPCRequestHandler, SimpleXMLRPCServer

HOST = "127.0.0.1"
GARBAGE = b"\x00\x01 this is not XML-RPC \xff"
BOMB = (b'<?xml version="1.0"?><!DOCTYPE lolz [<!ENTITY lol "lol">'
        b'<!ENTITY lol2 "&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;">]>'
        b"<methodResponse><params><param><value><string>&lol2;</string></value></param></params></methodResponse>")
_print_lock = threading.Lock()


def say(message) -> None:
    with _print_lock:
        print(message if isinstance(message, str) else json.dumps(message), flush=True)


def address(pair) -> str:
    return f"{pair[0]}:{pair[1]}"


class Server(ThreadingMixIn, SimpleXMLRPCServer):
    daemon_threads = True  # a handler that hangs on purpose must not keep the process alive


# -- the master ------------------------------------------------------------------------------

class Master:
    """The Master API's topic calls (http://wiki.ros.org/ROS/Master_API): every answer is
    [code, statusMessage, value]; publisherUpdate tells subscribers when publishers change."""

    def __init__(self):
        self.lock = threading.Lock()
        self.pubs: dict[str, set[str]] = {}
        self.subs: dict[str, set[str]] = {}
        self.types: dict[str, str] = {}
        self.uris: dict[str, str] = {}

    def _forget_idle(self, node: str) -> None:
        if not any(node in nodes for nodes in list(self.pubs.values()) + list(self.subs.values())):
            self.uris.pop(node, None)

    def _notify(self, topic: str) -> None:
        with self.lock:
            pubs = [self.uris[n] for n in sorted(self.pubs.get(topic, ()))]
            subs = [self.uris[n] for n in sorted(self.subs.get(topic, ()))]
        for uri in subs:
            threading.Thread(target=lambda u=uri: ServerProxy(u).publisherUpdate("/master", topic, pubs),
                             daemon=True).start()

    def registerPublisher(self, caller_id, topic, topic_type, caller_api):
        with self.lock:
            self.uris[caller_id] = caller_api
            self.pubs.setdefault(topic, set()).add(caller_id)
            self.types.setdefault(topic, topic_type)
            subs = [self.uris[n] for n in sorted(self.subs.get(topic, ()))]
        self._notify(topic)
        return [1, f"Registered [{caller_id}] as publisher of [{topic}]", subs]

    def registerSubscriber(self, caller_id, topic, topic_type, caller_api):
        with self.lock:
            self.uris[caller_id] = caller_api
            self.subs.setdefault(topic, set()).add(caller_id)
            self.types.setdefault(topic, topic_type)
            pubs = [self.uris[n] for n in sorted(self.pubs.get(topic, ()))]
        return [1, f"Subscribed to [{topic}]", pubs]

    def _unregister(self, table, caller_id, topic):
        with self.lock:
            members = table.get(topic, set())
            found = caller_id in members
            members.discard(caller_id)
            if not members:
                table.pop(topic, None)
            self._forget_idle(caller_id)
        return [1, f"Unregistered [{caller_id}] from [{topic}]", int(found)]

    def unregisterPublisher(self, caller_id, topic, caller_api):
        answer = self._unregister(self.pubs, caller_id, topic)
        self._notify(topic)
        return answer

    def unregisterSubscriber(self, caller_id, topic, caller_api):
        return self._unregister(self.subs, caller_id, topic)

    def getSystemState(self, caller_id):
        with self.lock:
            state = [[[t, sorted(nodes)] for t, nodes in sorted(table.items())] for table in (self.pubs, self.subs)]
        return [1, "current system state", state + [[]]]

    def getTopicTypes(self, caller_id):
        with self.lock:
            return [1, "current topics", [[t, kind] for t, kind in sorted(self.types.items())]]

    def lookupNode(self, caller_id, node):
        with self.lock:
            uri = self.uris.get(node)
        return [1, "node api", uri] if uri else [-1, f"unknown node [{node}]", ""]


HUGE = 100_000


def huge(handler) -> bytes:
    """The "huge" master's answer to the call the handler reads."""
    return huge_answer(xmlrpc.client.loads(handler.rfile.read(int(handler.headers["Content-Length"])))[1])


@functools.cache
def huge_answer(method: str) -> bytes:
    """Made once: a second of Python per answer would time the master, not the agent."""
    if method == "getSystemState":
        value = [[[f"/topic{i}", [f"/node{i}"]] for i in range(HUGE)], [], []]
    elif method == "getTopicTypes":
        value = [[f"/topic{i}", "std_msgs/String"] for i in range(HUGE)]
    else:
        return xmlrpc.client.dumps(([-1, "unknown node", ""],), methodresponse=True).encode()
    return xmlrpc.client.dumps(([1, "huge", value],), methodresponse=True).encode()


def run_master(port: int, mode: str) -> None:
    modes = {"now": mode}

    class Handler(SimpleXMLRPCRequestHandler):
        def do_POST(self):
            if modes["now"] == "good":
                return super().do_POST()
            while modes["now"] == "silent":
                time.sleep(0.05)  # holds the connection, never answers
            if modes["now"] in ("garbage", "bomb", "huge"):
                body = GARBAGE if modes["now"] == "garbage" else BOMB if modes["now"] == "bomb" else huge(self)
                self.send_response(200)
                self.send_header("Content-Type", "text/xml")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

        def log_message(self, *args):
            pass

    server = Server((HOST, port), requestHandler=Handler, allow_none=True, logRequests=False)
    server.register_instance(Master())
    threading.Thread(target=server.serve_forever, daemon=True).start()
    say(f"ready http://{HOST}:{server.server_address[1]}/")
    for line in sys.stdin:
        words = line.split()
        if words[:1] == ["mode"] and len(words) == 2:
            modes["now"] = words[1]
            say(f"mode {words[1]}")
    threading.Event().wait()


# -- TCPROS ----------------------------------------------------------------------------------

def recv_exact(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise EOFError
        data += chunk
    return data


def encode_header(fields: dict[str, str]) -> bytes:
    """A TCPROS connection header: 4-byte little-endian lengths before each key=value and the whole."""
    body = b"".join(struct.pack("<I", len(f)) + f for f in (f"{k}={v}".encode() for k, v in fields.items()))
    return struct.pack("<I", len(body)) + body


def read_header(sock: socket.socket) -> tuple[dict[str, str], int]:
    """The fields of a connection header, and its size in bytes."""
    (size,) = struct.unpack("<I", recv_exact(sock, 4))
    body, fields = recv_exact(sock, size), {}
    while body:
        (n,) = struct.unpack("<I", body[:4])
        key, _, value = body[4:4 + n].decode().partition("=")
        fields[key], body = value, body[4 + n:]
    return fields, 4 + size


# -- a node ----------------------------------------------------------------------------------

class RosNode:
    """A node with the Slave API (http://wiki.ros.org/ROS/Slave_API) and TCPROS connections."""

    def __init__(self, args):
        self.name, self.args = args.name, args
        self.publish = dict(t.split(":", 1) for t in args.publish)
        self.subscribe = dict(t.split(":", 1) for t in args.subscribe)
        self.master = ServerProxy(args.master)
        self.lock = threading.Lock()
        self.bus: dict[int, list] = {}  # connection id -> getBusInfo entry
        self.next_id = 0
        self.connected: set[tuple[str, str]] = set()  # (topic, publisher URI)
        self.tcpros = socket.create_server((HOST, 0))
        self.slave = Server((HOST, 0), allow_none=True, logRequests=False)
        self.slave.register_instance(self._api())
        self.uri = f"http://{args.hostname}:{self.slave.server_address[1]}/"

    def _api(self):
        node = self

        class SlaveApi:
            def getPid(self, caller_id):
                node._hang("getPid")
                return [1, "", os.getpid()]

            def getBusInfo(self, caller_id):
                node._hang("getBusInfo")
                with node.lock:
                    return [1, "bus info", [list(e) for _, e in sorted(node.bus.items())]]

            def requestTopic(self, caller_id, topic, protocols):
                if topic not in node.publish:
                    return [-1, f"not a publisher of [{topic}]", []]
                if not any(p[:1] == ["TCPROS"] for p in protocols):
                    return [0, "no supported protocol", []]
                return [1, "ready", ["TCPROS", HOST, node.tcpros.getsockname()[1]]]

            def publisherUpdate(self, caller_id, topic, publishers):
                for uri in publishers:
                    threading.Thread(target=node._connect, args=(topic, uri), daemon=True).start()
                return [1, "", 0]

        return SlaveApi()

    def _hang(self, method: str) -> None:
        if method in self.args.hang:
            threading.Event().wait()

    def _add(self, peer: str, direction: str, topic: str, sock: socket.socket, far: str) -> int:
        info = (f"TCPROS connection on port {sock.getsockname()[1]} to [{far} on socket {sock.fileno()}]"
                if self.args.bus_info == "roscpp" else "opaque transport")
        with self.lock:
            self.next_id += 1
            self.bus[self.next_id] = [self.next_id, peer, direction, "TCPROS", topic, True, info]
            return self.next_id

    def _drop(self, cid: int) -> None:
        with self.lock:
            self.bus.pop(cid, None)

    def _serve(self) -> None:
        while True:
            sock, _ = self.tcpros.accept()
            threading.Thread(target=self._publish_to, args=(sock,), daemon=True).start()

    def _publish_to(self, sock: socket.socket) -> None:
        with sock:
            fields, _ = read_header(sock)
            topic = fields["topic"]
            header = encode_header({"callerid": self.name, "topic": topic, "type": self.publish[topic],
                                    "md5sum": "*", "latching": "0"})
            sock.sendall(header)
            written = len(header)
            cid = self._add(fields["callerid"], "o", topic, sock, address(sock.getpeername()))
            for i in range(self.args.messages):
                message = struct.pack("<I", self.args.size) + bytes([i % 256]) * self.args.size
                sock.sendall(message)
                written += len(message)
            say({"event": "published", "topic": topic, "subscriber": fields["callerid"],
                 "local": address(sock.getsockname()), "remote": address(sock.getpeername()), "bytes": written})
            try:
                while sock.recv(4096):  # until the subscriber hangs up
                    pass
            except OSError:
                pass
            self._drop(cid)

    def _connect(self, topic: str, publisher: str) -> None:
        with self.lock:
            if (topic, publisher) in self.connected:
                return
            self.connected.add((topic, publisher))
        cid = None
        try:
            code, _, proto = ServerProxy(publisher).requestTopic(self.name, topic, [["TCPROS"]])
            if code != 1:
                return
            _, host, port = proto
            with socket.create_connection((host, port)) as sock:
                sock.sendall(encode_header({"callerid": self.name, "topic": topic, "type": self.subscribe[topic],
                                            "md5sum": "*", "tcp_nodelay": "0"}))
                _, read = read_header(sock)
                cid = self._add(publisher, "i", topic, sock, f"{host}:{port}")
                for _ in range(self.args.messages):
                    (size,) = struct.unpack("<I", recv_exact(sock, 4))
                    read += 4 + len(recv_exact(sock, size))
                say({"event": "received", "topic": topic, "publisher": publisher,
                     "local": address(sock.getsockname()), "remote": address(sock.getpeername()), "bytes": read})
                while sock.recv(4096):
                    pass
        except (OSError, EOFError):
            pass
        finally:
            if cid is not None:
                self._drop(cid)
            with self.lock:
                self.connected.discard((topic, publisher))

    def run(self) -> None:
        # The kernel hands a process signal to any thread that does not block it, and Python runs
        # handlers only in the main thread: so every thread blocks them and the main one waits.
        ending = {signal.SIGTERM, signal.SIGINT}
        signal.pthread_sigmask(signal.SIG_BLOCK, ending)
        threading.Thread(target=self.slave.serve_forever, daemon=True).start()
        threading.Thread(target=self._serve, daemon=True).start()
        for topic, kind in self.publish.items():
            self.master.registerPublisher(self.name, topic, kind, self.uri)
        found = [(topic, uri) for topic, kind in self.subscribe.items()
                 for uri in self.master.registerSubscriber(self.name, topic, kind, self.uri)[2]]
        # "ready" first: a connection's thread may have read its messages, and said so, before this
        # thread runs again.
        say(f"ready {os.getpid()} {self.uri}")
        for topic, uri in found:
            threading.Thread(target=self._connect, args=(topic, uri), daemon=True).start()
        signal.sigwait(ending)
        for topic in self.publish:
            self.master.unregisterPublisher(self.name, topic, self.uri)
        for topic in self.subscribe:
            self.master.unregisterSubscriber(self.name, topic, self.uri)
        os._exit(0)  # daemon threads blocked in accept() or recv(): their sockets close with us


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    roles = parser.add_subparsers(dest="role", required=True)
    master = roles.add_parser("master")
    master.add_argument("--port", type=int, default=0)
    master.add_argument("--mode", default="good", choices=("good", "garbage", "silent", "bomb", "huge"))
    node = roles.add_parser("node")
    node.add_argument("--name", required=True)
    node.add_argument("--master", required=True)
    node.add_argument("--publish", action="append", default=[], metavar="TOPIC:TYPE")
    node.add_argument("--subscribe", action="append", default=[], metavar="TOPIC:TYPE")
    node.add_argument("--messages", type=int, default=3)
    node.add_argument("--size", type=int, default=100)
    node.add_argument("--hang", action="append", default=[], choices=("getPid", "getBusInfo"))
    node.add_argument("--bus-info", default="roscpp", choices=("roscpp", "opaque"))
    node.add_argument("--hostname", default=HOST,
                      help="the host its URI names, as ROS_HOSTNAME sets it; it still listens on " + HOST)
    args = parser.parse_args()
    if args.role == "master":
        run_master(args.port, args.mode)
    else:
        RosNode(args).run()


if __name__ == "__main__":
    main()

"""The ROS 1 graph, read over XML-RPC: the master says which node publishes and subscribes to what
(getSystemState, getTopicTypes) and where each node's slave API listens (lookupNode); each slave
says its connections (getBusInfo) and its PID (getPid). A node runs on the host its slave URI
names, reached at the name or address the URI gives (this host's name for any of its addresses).

A Connection's `local` is the publisher's socket address and `remote` the subscriber's, both as
the publisher's socket sees them (a TCPROS publisher accepts: `local` carries its server port).
They come from the publisher's getBusInfo, completed by this host's sockets (sock_diag) or by the
address the subscriber was told to connect to; an address that cannot be known is left "".

Every answer comes from the network: XML is parsed by defusedxml, answers are capped in size, and
one poll, master and slaves together, takes at most `timeout` seconds. Slaves are asked in
parallel; one that does not answer leaves its node in the graph, unmapped.
"""
from __future__ import annotations

import concurrent.futures
import http.client
import os
import re
import socket
import time
import xmlrpc.client
from dataclasses import dataclass
from urllib.parse import urlsplit
from xml.parsers.expat import ExpatError

import psutil
from defusedxml import DefusedXmlException
from defusedxml.xmlrpc import DefusedExpatParser

from drums.errors import GraphError, KernelError
from drums.graph.adapter import Adapter
from drums.graph.model import Connection, Endpoint, GraphState, Host, Node, Process, Topic
from drums.netfmt import endpoint, is_loopback
from drums.probes.tcp import established
from drums.proctable import ProcessTable

CALLER_ID = "/drums_graph"  # who we say we are; we register nothing with the master
DEFAULT_MASTER = "http://localhost:11311/"
MAX_ANSWER = 64 << 20  # bytes: getSystemState of a large robot is a few MB, more is garbage or an attack
# What one poll keeps of what a master says, past which the graph is truncated: values in one answer
# (topic and node names: a large robot has a few thousand), and nodes asked for their connections
# and PID (three calls each). A master that lists a million topics costs no more than that.
MAX_VALUES = 10_000
MAX_NODES = 1_000
WORKERS = 16  # XML-RPC calls in flight at once
GRACE = 0.1  # seconds past the deadline for a call that timed out to say so
# roscpp's TransportTCP::getTransportInfo, which rospy's TCPROSTransport.get_transport_info copies:
# "TCPROS connection on port 41437 to [127.0.0.1:52842 on socket 12]". The port is the socket's own;
# the peer is the far end as accept() saw it on the publishing side, and the host and port that
# requestTopic named on the subscribing side (a host name where the publisher advertises one).
INFO = re.compile(r"(\w+) connection on port (\d+) to \[(.+):(\d+) on socket -?\d+\]")


def _line(text) -> str:
    return (str(text).strip().splitlines() or [""])[0][:200]


def _endpoint(host: str, port: int) -> str:
    """ip:port as drums.netfmt writes it, or "" when host is a name rather than an address."""
    for family in (socket.AF_INET, socket.AF_INET6):
        try:
            return endpoint(family, socket.inet_pton(family, host), port)
        except OSError:
            continue
    return ""


def _where(uri: str) -> tuple[str, int | None]:
    """(host, port) of an http URI, ("", None) for anything else: slaves name their peers by URI."""
    try:
        url = urlsplit(uri)
        return (url.hostname or "", url.port) if url.scheme == "http" else ("", None)
    except ValueError:
        return "", None


def parse_info(text) -> tuple[int, str, int] | None:
    """(own port, peer host, peer port) of a getBusInfo connection string; None if it has none
    (another client library, or rospy before its socket was set up: "[None:None on socket None]")."""
    match = INFO.fullmatch(text) if isinstance(text, str) else None
    return (int(match[2]), match[3], int(match[4])) if match else None


class _Transport(xmlrpc.client.Transport):
    """XML-RPC over HTTP that trusts nothing it reads: defusedxml parses, compression is refused
    (a gzip bomb), answers are capped at MAX_ANSWER, reading stops at the first value past
    MAX_VALUES, and each call ends by `deadline`."""

    accept_gzip_encoding = False

    def __init__(self, deadline: float):
        super().__init__()
        self.deadline = deadline
        self.cut = False  # the answer had more than MAX_VALUES values; the rest was not read

    def _left(self) -> float:
        left = self.deadline - time.monotonic()
        if left <= 0:
            raise socket.timeout("timed out")
        return left

    def request(self, host, handler, request_body, verbose=False):
        try:
            return super().request(host, handler, request_body, verbose)
        finally:
            self.close()  # one connection per call: the slaves are many and a master closes anyway

    def make_connection(self, host):
        self._connection = host, http.client.HTTPConnection(host, timeout=self._left())
        return self._connection[1]

    def send_request(self, host, handler, request_body, debug):
        connection = super().send_request(host, handler, request_body, debug)
        self._sock = connection.sock  # the response reads it even once the connection lets it go
        self._sock.settimeout(self._left())
        return connection

    def getparser(self):
        unmarshaller = _Capped()
        return DefusedExpatParser(unmarshaller, forbid_dtd=True), unmarshaller

    def parse_response(self, response):
        if response.getheader("Content-Encoding", "identity") != "identity":
            raise ValueError("a compressed answer, not asked for")
        parser, unmarshaller = self.getparser()
        size = 0
        while not unmarshaller.cut:
            if not response.isclosed():  # (it closes its socket once it read all it was told: Python 3.13)
                self._sock.settimeout(self._left())  # a peer that trickles still ends on time
            chunk = response.read1(1 << 16)
            if not chunk:
                parser.close()
                break
            size += len(chunk)
            if size > MAX_ANSWER:
                raise ValueError(f"an answer over {MAX_ANSWER >> 20} MiB")
            parser.feed(chunk)
        self.cut = unmarshaller.cut
        if self.cut:
            unmarshaller.close_open()  # what is open ends here, as if the answer did
        return unmarshaller.close()


class _Capped(xmlrpc.client.Unmarshaller):
    """An unmarshaller that keeps the first MAX_VALUES values of an answer and notes (`cut`) that
    there are more, whose reading then stops: a hostile master's 17 MB cost what 10,000 values do.
    Lists past the limit come out short or empty."""

    def __init__(self):
        super().__init__()
        self.kept = 0
        self.cut = False
        self._open: list[str] = []  # the elements open now, outermost first
        keep = self._stack.append

        def append(value) -> None:
            if self.kept < MAX_VALUES:
                self.kept += 1
                keep(value)
            else:
                self.cut = True
        self.append = append

    def start(self, tag, attrs):
        self._open.append(tag)
        super().start(tag, attrs)

    def end(self, tag):
        if self._open:
            self._open.pop()
        super().end(tag)

    def close_open(self) -> None:
        """End every element still open, innermost first."""
        while self._open:
            self.end(self._open[-1])


def _pairs(value, what: str, cut: bool = False) -> list[tuple[str, object]]:
    """[name, value] pairs; of an answer that was `cut`, the whole ones (the rest were cut short)."""
    whole = lambda p: isinstance(p, list) and len(p) == 2 and isinstance(p[0], str)  # noqa: E731
    if not isinstance(value, list) or not (cut or all(whole(p) for p in value)):
        raise GraphError(f"{what}: not a list of [name, value] pairs")
    return [(p[0], p[1]) for p in value if whole(p)]


def system_state(value, who: str, cut: bool = False) -> tuple[dict[str, list[str]], dict[str, list[str]], set[str]]:
    """(publishers by topic, subscribers by topic, every node) from getSystemState's value, which
    may have been `cut` short past MAX_VALUES."""
    if cut and isinstance(value, list):
        value = (value + [[], [], []])[:3]
    if not isinstance(value, list) or len(value) != 3:
        raise GraphError(f"{who} answered getSystemState with {type(value).__name__}, not [pubs, subs, services]")
    pubs, subs, services = (_pairs(part, f"{who}, getSystemState", cut) for part in value)
    nodes = set()
    for name, members in pubs + subs + services:
        if not isinstance(members, list) or not all(isinstance(m, str) for m in members):
            raise GraphError(f"{who}, getSystemState: {name}: not a list of node names")
        nodes.update(members)
    return dict(pubs), dict(subs), nodes


def bus_info(value) -> list[tuple[str, str, str, str, tuple | None]]:
    """(direction, peer, transport, topic, parsed info) of each live connection in getBusInfo's
    value: [connectionId, destinationId, direction, transport, topic, connected, info]. An entry of
    another shape is skipped; the info string is absent from old clients."""
    if not isinstance(value, list):
        raise GraphError(f"getBusInfo: {type(value).__name__}, not a list of connections")
    out = []
    for entry in value:
        if (isinstance(entry, list) and len(entry) >= 6 and entry[5]
                and all(isinstance(field, str) for field in entry[1:5])):
            out.append((entry[2], entry[1], entry[3], entry[4], parse_info(entry[6] if len(entry) > 6 else None)))
    return out


def connections(bus: dict[str, list], sockets: dict) -> list[Connection]:
    """The edges of the graph from each answering node's bus info (peers resolved to node names):
    a publisher's "o" entries, and for publishers that did not answer, their subscribers' "i"
    entries. `sockets` maps (local port, remote port) of this host's TCP sockets to their
    (local, remote) addresses."""
    told = {}  # (topic, publisher, subscriber, subscriber's port) -> the publisher's host as told
    for node, entries in bus.items():
        for direction, peer, _, topic, info in entries:
            if direction == "i" and info:
                told[topic, peer, node, info[0]] = info[1]
    out = []
    for node, entries in bus.items():
        for direction, peer, transport, topic, info in entries:
            local = remote = ""
            if direction == "o":
                if info:
                    port, host, peer_port = info
                    remote = _endpoint(host, peer_port)
                    here = sockets.get((port, peer_port))
                    if here and here[1] == remote:
                        local = here[0]
                    else:
                        local = _endpoint(told.get((topic, node, peer, peer_port), ""), port)
                out.append(Connection(topic, node, peer, transport, local, remote))
            elif direction == "i" and peer not in bus:
                if info:
                    port, host, pub_port = info
                    local = _endpoint(host, pub_port)
                    here = sockets.get((port, pub_port))
                    if here and local in ("", here[1]):
                        remote, local = here
                out.append(Connection(topic, peer, node, transport, local, remote))
    return out


def _socket_table() -> dict[tuple[int, int], tuple[str, str] | None]:
    """(local port, remote port) -> (local, remote) of this host's established TCP sockets; None
    where two sockets share the ports."""
    try:
        found = list(established())
    except KernelError:
        return {}  # addresses then come from what the nodes say alone
    table: dict = {}
    for c, local, remote in found:
        pair = (local, remote)
        key = (c.local_port, c.remote_port)
        table[key] = pair if table.get(key, pair) == pair else None
    return table


@dataclass
class _Slave:
    """What one node said in one poll, filled in call by call: the poll takes what is there."""
    uri: str = ""
    pid: int | None = None
    bus: list | None = None


class Ros1Adapter(Adapter):
    name = "ros1"

    def __init__(self, master_uri: str | None = None, interval: float = 1.0, timeout: float = 2.0,
                 proc: str = "/proc"):
        self.master_uri = master_uri or os.environ.get("ROS_MASTER_URI") or DEFAULT_MASTER
        self.interval = interval  # the paper polled every 15 s; a poll is a few ms of XML-RPC
        self.timeout = timeout  # seconds for one whole poll
        self.table = ProcessTable(proc)
        self._pool: concurrent.futures.ThreadPoolExecutor | None = None
        self._pids: dict[str, int] = {}  # slave URI -> PID: a node's PID stays while its URI does
        self._local: set[str] = set()
        self._here = ""
        self._cuts: list[str] = []  # what this poll kept only part of, said in the state's `truncated`

    def start(self) -> None:
        url = urlsplit(self.master_uri)
        if url.scheme != "http" or not url.hostname:
            raise GraphError(f"the ROS master URI {self.master_uri!r} is not an http:// URL")
        self._here = socket.gethostname()
        self._local = {"localhost", self._here.lower()} | {
            a.address.split("%")[0] for addrs in psutil.net_if_addrs().values() for a in addrs
            if a.family in (socket.AF_INET, socket.AF_INET6)}
        self._pool = concurrent.futures.ThreadPoolExecutor(WORKERS, thread_name_prefix="ros1")

    def stop(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)

    def _call(self, uri: str, who: str, deadline: float, method: str, *args):
        """The value of one ROS API call ([code, statusMessage, value]); a GraphError otherwise."""
        transport = _Transport(deadline)
        try:
            proxy = xmlrpc.client.ServerProxy(uri, transport=transport)
            answer = getattr(proxy, method)(CALLER_ID, *args)
        except (socket.timeout, TimeoutError):
            raise GraphError(f"{who} did not answer {method} within {self.timeout:g} s") from None
        except ConnectionRefusedError:
            raise GraphError(f"{who} refused the connection") from None
        except http.client.RemoteDisconnected:
            raise GraphError(f"{who} closed the connection without answering {method}") from None
        except xmlrpc.client.Fault as e:
            raise GraphError(f"{who} answered {method} with fault {e.faultCode}: {_line(e.faultString)}") from None
        except xmlrpc.client.ProtocolError as e:
            raise GraphError(f"{who} answered {method} with HTTP {e.errcode} {_line(e.errmsg)}") from None
        except (ExpatError, DefusedXmlException, xmlrpc.client.ResponseError, http.client.HTTPException,
                ValueError, TypeError) as e:
            raise GraphError(f"{who} answered {method} with something that is not XML-RPC ({_line(e) or type(e).__name__})") from None
        except OSError as e:
            raise GraphError(f"{who} is unreachable ({e.strerror or _line(e)})") from None
        if not (isinstance(answer, list) and len(answer) == 3 and isinstance(answer[0], int)):
            raise GraphError(f"{who} answered {method} with something that is not [code, message, value]")
        if answer[0] != 1:
            raise GraphError(f"{who} refused {method}: {_line(answer[1])}")
        if transport.cut:
            self._cuts.append(f"{who} answered {method} with more than {MAX_VALUES:,} values; "
                              f"the first {MAX_VALUES:,} were kept")
        return answer[2]

    def _ask(self, name: str, slave: _Slave, deadline: float) -> None:
        master = f"the ROS master at {self.master_uri}"
        try:
            uri = self._call(self.master_uri, master, deadline, "lookupNode", name)
        except GraphError:
            return
        if not isinstance(uri, str) or not _where(uri)[0]:
            return
        slave.uri = uri
        who = f"node {name} at {uri}"
        try:
            slave.bus = bus_info(self._call(uri, who, deadline, "getBusInfo"))
        except GraphError:
            pass
        pid = self._pids.get(uri) if slave.bus is not None else None  # no cache for a slave that is silent
        if pid is None:
            try:
                pid = self._call(uri, who, deadline, "getPid")
            except GraphError:
                return
            if not isinstance(pid, int) or isinstance(pid, bool) or pid <= 0:
                return
            self._pids[uri] = pid
        slave.pid = pid

    def _master(self, asked: concurrent.futures.Future, method: str, deadline: float):
        try:
            return asked.result(timeout=max(0.0, deadline + GRACE - time.monotonic()))
        except concurrent.futures.TimeoutError:
            raise GraphError(f"the ROS master at {self.master_uri} did not answer {method} within {self.timeout:g} s") from None

    def _host(self, uri: str) -> str:
        """The host a slave URI names; this host's name when it names one of this host's addresses."""
        host = _where(uri)[0]
        return self._here if is_loopback(host) or host in self._local else host

    def poll(self) -> GraphState:
        deadline = time.monotonic() + self.timeout
        master = f"the ROS master at {self.master_uri}"
        self._cuts = []
        asked = {m: self._pool.submit(self._call, self.master_uri, master, deadline, m)
                 for m in ("getSystemState", "getTopicTypes")}
        pubs, subs, names = system_state(self._master(asked["getSystemState"], "getSystemState", deadline), master,
                                         cut=bool(self._cuts))
        types = dict(_pairs(self._master(asked["getTopicTypes"], "getTopicTypes", deadline), f"{master}, getTopicTypes",
                            cut=bool(self._cuts)))
        if len(names) > MAX_NODES:
            self._cuts.append(f"{master} listed {len(names):,} nodes; the first {MAX_NODES:,} were asked")
        slaves = {name: _Slave() for name in sorted(names)[:MAX_NODES]}
        concurrent.futures.wait([self._pool.submit(self._ask, name, slave, deadline) for name, slave in slaves.items()],
                                timeout=max(0.0, deadline + GRACE - time.monotonic()))
        state = self._describe(pubs, subs, types, slaves)
        state.truncated = "; ".join(sorted(self._cuts))  # the calls ran side by side: in a stable order
        return state

    def _describe(self, pubs: dict, subs: dict, types: dict, slaves: dict[str, _Slave]) -> GraphState:
        state = GraphState()
        self.table.refresh()
        by_uri = {}
        named: dict[str, set[str]] = {}  # host -> the names or addresses its nodes' URIs give it
        for name, slave in slaves.items():
            host = self._host(slave.uri) if slave.uri else ""
            if slave.uri:
                by_uri[_where(slave.uri)] = name
                named.setdefault(host, set()).add(_where(slave.uri)[0])
            state.nodes.append(Node(name, host, slave.pid, "getPid" if slave.pid else "unmapped", {"uri": slave.uri}))
            if slave.pid:
                state.processes.append(Process(host, slave.pid, self.table.name(slave.pid) if host == self._here else ""))
        # This host may be named several ways (127.0.0.1, localhost, its name): the address is one
        # that other hosts can use too where a node gives one.
        state.hosts = [Host(h, min(names, key=lambda a: (is_loopback(a), a))) for h, names in sorted(named.items())]
        state.processes = sorted(set(state.processes), key=lambda p: (p.host, p.pid))
        self._pids = {slave.uri: self._pids[slave.uri] for slave in slaves.values() if slave.uri in self._pids}

        for topic in sorted(pubs.keys() | subs.keys()):
            kind = types.get(topic)
            state.topics.append(Topic(topic, (kind,) if isinstance(kind, str) and kind else ()))
            for role, members in (("publisher", pubs), ("subscriber", subs)):
                state.endpoints += [Endpoint(f"{node}:{role}:{topic}", role, node, topic)
                                    for node in members.get(topic, ()) if node in slaves]  # those kept

        def resolve(peer: str) -> str | None:  # a caller id ("o"), or the publisher's slave URI ("i")
            return peer if peer in slaves else by_uri.get(_where(peer))

        bus = {name: [(d, resolve(peer), transport, topic, info) for d, peer, transport, topic, info in slave.bus]
               for name, slave in slaves.items() if slave.bus is not None}
        bus = {name: [e for e in entries if e[1]] for name, entries in bus.items()}  # peers the master knows
        with_ports = any(e[4] for entries in bus.values() for e in entries)
        state.connections = connections(bus, _socket_table() if with_ports else {})
        return state

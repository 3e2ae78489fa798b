"""A graph described in a YAML file, for systems without ROS. Processes are found by a regular
expression over their command line at each poll, so restarts keep their names:

    host: arm-controller          # optional: the host of the nodes; default: this host's name
    hosts:                        # optional: where each host and its Drums agent are reached
      - name: arm-controller
        address: 10.0.0.2         # an IP address or a DNS name
        agent_port: 9969          # optional: the port its agent listens on
      - name: base
        address: base.local
    nodes:
      - name: /planner
        process: "python3 .*planner\\.py"
      - name: /driver
        process: "^/usr/bin/motor-driver"
    topics:
      - name: /cmd_vel
        type: geometry_msgs/msg/Twist     # optional
        publishers: [/planner]
        subscribers: [/driver]

The file is read again when it changes; a file that does not parse keeps the last good graph.
"""
from __future__ import annotations

import os
import socket

import yaml

from drums import linear_re, safeyaml
from drums.errors import GraphError
from drums.graph.adapter import Adapter
from drums.graph.model import Connection, Endpoint, GraphState, Host, Node, Process, Topic
from drums.graph.nodepids import ProcScan
from drums.netfmt import hostport, is_address

HOST_KEYS = ("name", "address", "agent_port")


def _list(doc: dict, key: str, where: str) -> list:
    value = doc.get(key, [])
    if not isinstance(value, list):
        raise GraphError(f"{where}{key}: a list, not {type(value).__name__}")
    return value


def _name(item, where: str) -> str:
    name = item.get("name") if isinstance(item, dict) else None
    if not isinstance(name, str) or not name.startswith("/"):
        raise GraphError(f"{where}: needs a name starting with / (got {name!r})")
    return name


def _hosts(doc: dict, path: str) -> list[Host]:
    hosts: dict[str, Host] = {}
    for i, item in enumerate(_list(doc, "hosts", f"{path}: ")):
        where = f"{path}: hosts[{i}]"
        if not isinstance(item, dict):
            raise GraphError(f"{where}: a mapping with {', '.join(HOST_KEYS)}, not {type(item).__name__}")
        unknown = set(item) - set(HOST_KEYS)
        if unknown:
            raise GraphError(f"{where}: unknown key {sorted(map(str, unknown))[0]!r} ({', '.join(HOST_KEYS)})")
        name, address, port = item.get("name"), item.get("address"), item.get("agent_port")
        if not isinstance(name, str) or not name:
            raise GraphError(f"{where}: needs a name (got {name!r})")
        if name in hosts:
            raise GraphError(f"{where}: host {name!r} is listed twice")
        if not isinstance(address, str) or not is_address(address):
            raise GraphError(f"{where}: needs an address, an IP address or a DNS name (got {address!r})")
        if port is not None and (type(port) is not int or not 0 < port < 65536):
            raise GraphError(f"{where}: agent_port is a port, 1-65535 (got {port!r})")
        hosts[name] = Host(name, address, f"http://{hostport(address, port)}" if port else "")
    return list(hosts.values())


def parse(text: str, path: str = "graph") -> tuple[str, list[Host], dict, list[dict]]:
    """(host of the nodes, hosts listed, node -> process pattern, topics) from the YAML text; every
    mistake is a GraphError that names the file and the entry."""
    try:
        doc = safeyaml.load(text) or {}
    except yaml.YAMLError as e:
        raise GraphError(f"{path}: not YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(doc, dict):
        raise GraphError(f"{path}: a mapping with nodes and topics, not {type(doc).__name__}")
    unknown = set(doc) - {"host", "hosts", "nodes", "topics"}
    if unknown:
        raise GraphError(f"{path}: unknown key {sorted(unknown)[0]!r} (host, hosts, nodes, topics)")
    host = doc.get("host") or socket.gethostname()
    hosts = _hosts(doc, path)
    nodes: dict = {}  # name -> the pattern of its process's command line, or None
    for i, item in enumerate(_list(doc, "nodes", f"{path}: ")):
        where = f"{path}: nodes[{i}]"
        name = _name(item, where)
        pattern = item.get("process")
        if pattern is not None and not isinstance(pattern, str):
            raise GraphError(f"{where}: process is a regular expression, not {type(pattern).__name__}")
        try:
            nodes[name] = linear_re.compile(pattern) if pattern else None
        except ValueError as e:
            raise GraphError(f"{where}: process is {e}") from None
    topics = []
    for i, item in enumerate(_list(doc, "topics", f"{path}: ")):
        where = f"{path}: topics[{i}]"
        topic = {"name": _name(item, where), "type": str(item.get("type", "")),
                 "publishers": _list(item, "publishers", f"{where}."),
                 "subscribers": _list(item, "subscribers", f"{where}.")}
        for node in topic["publishers"] + topic["subscribers"]:
            if not isinstance(node, str) or node not in nodes:
                raise GraphError(f"{where}: node {node!r} is not among the nodes")
        topics.append(topic)
    return str(host), hosts, nodes, topics


class StaticAdapter(Adapter):
    name = "static"

    def __init__(self, path: str, interval: float = 1.0, proc: str = "/proc"):
        """Reads the file at once: a bad file is an error at start, not a graph that never comes.
        Later, a file changed into a bad one leaves the last good graph (marked stale)."""
        self.path = path
        self.interval = interval
        self.scan = ProcScan(proc)
        self._parsed = None
        self._mtime = None
        self._read()

    def start(self) -> None:
        self._read()

    def _read(self) -> None:
        try:
            mtime = os.stat(self.path).st_mtime_ns
            if mtime != self._mtime:
                self._parsed, self._mtime = parse(safeyaml.read(self.path), self.path), mtime
        except OSError as e:
            raise GraphError(f"{self.path}: {e.strerror}") from None
        except yaml.YAMLError as e:  # too big to read
            raise GraphError(f"{self.path}: not YAML ({e})") from None

    def poll(self) -> GraphState:
        self._read()
        host, hosts, nodes, topics = self._parsed
        self.scan.refresh()
        listed = any(h.name == host for h in hosts)
        state = GraphState(hosts=hosts if listed else [Host(host), *hosts])
        pids = set()
        for name, pattern in nodes.items():
            found = [pid for pid in self.scan.pids()
                     if pattern and pattern.search(" ".join(self.scan.cmdline(pid)).strip())]
            pid = found[0] if len(found) == 1 else None
            how = "static" if pid else ("ambiguous" if found else "unmapped")
            state.nodes.append(Node(name, host if pid else "", pid, how))
            if pid:
                pids.add(pid)
        state.processes = [Process(host, pid, self.scan.name(pid)) for pid in sorted(pids)]
        for t in topics:
            state.topics.append(Topic(t["name"], (t["type"],) if t["type"] else ()))
            for kind in ("publishers", "subscribers"):
                state.endpoints.extend(Endpoint(f"{node}@{t['name']}/{kind[:-1]}", kind[:-1], node, t["name"])
                                       for node in t[kind])
            state.connections.extend(Connection(t["name"], pub, sub, "static")
                                     for pub in t["publishers"] for sub in t["subscribers"])
        return state

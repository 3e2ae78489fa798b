"""The graph without middleware: the processes of this host and their TCP connections, like a
service map. A process with a listening or connected TCP socket is a node (`/<name>/<pid>`);
each connection is an edge from the connecting process to the listening one, keyed by the
service port (`tcp:<port>`). A peer on another host is a node named by its address, with no
process. UDP and unix sockets carry no direction, so they are not edges here.
"""
from __future__ import annotations

import socket
import time
from typing import Callable

from drums.errors import GraphError, KernelError
from drums.graph.adapter import Adapter
from drums.graph.model import Connection, GraphState, Host, Node, Process
from drums.graph.nodepids import ProcScan
from drums.kernel import sockdiag
from drums.proctable import ProcessTable

ESTABLISHED, LISTEN = 1, 10
OWNERS_REREAD = 60.0


def _endpoint(address: str, port: int) -> str:
    return f"[{address}]:{port}" if ":" in address else f"{address}:{port}"


def _socket_owners(table: ProcessTable) -> dict[int, int]:
    """Socket inode -> PID, from every process's open files."""
    return {inode: pid for pid in table.pids() for inode in table.socket_inodes(pid)}


class AutoAdapter(Adapter):
    name = "auto"
    interval = 5.0  # reading every process's open files costs a readlink per file

    def __init__(self, proc: str = "/proc", tcp_changes: Callable[[], int | None] | None = None):
        """`tcp_changes`: a count that moves whenever a TCP socket of the host changes state (the
        tcp probe's; None when it cannot say). While it holds still, the connections and listeners
        are those of the last dump: a poll dumps them again (10,000 sockets: 30 ms) only when it
        moved, when a process of the graph ended, or at least every OWNERS_REREAD seconds."""
        self.scan = ProcScan(proc)
        self.tcp_changes = tcp_changes
        self._dumped: tuple[int | None, float, GraphState] | None = None  # (changes, when, state)
        self._owners: dict[int, int] = {}  # socket inode -> PID, from the last reading of open files
        self._unowned: set[int] = set()  # inodes no process held at that reading
        self._read_at = float("-inf")
        self._known: dict = {}  # socket cookie -> connection, of the last dump

    def _owners_of(self, conns: list) -> dict[int, int]:
        """Socket inode -> PID for these connections. Every process's open files are read when a
        connection's socket is new since the last reading, and at least every OWNERS_REREAD
        seconds (a socket handed to another process keeps its inode): on a host whose
        connections stay, rarely."""
        owners = {inode: pid for inode, pid in self._owners.items() if self.scan.table.alive(pid)}
        inodes = {c.inode for c in conns if c.inode}
        now = time.monotonic()
        if inodes - owners.keys() - self._unowned or now - self._read_at >= OWNERS_REREAD:
            owners = _socket_owners(self.scan.table)
            self._unowned = inodes - owners.keys()
            self._read_at = now
        else:
            self._unowned &= inodes
        self._owners = owners
        return owners

    def _changes(self) -> int | None:
        try:
            return self.tcp_changes() if self.tcp_changes else None
        except Exception:  # noqa: BLE001 - a probe stopped or failing: the poll dumps, as without one
            return None

    def poll(self) -> GraphState:
        changes = self._changes()
        self.scan.refresh()
        if self._dumped is not None and changes is not None:
            was, at, state = self._dumped
            alive = self.scan.table.alive
            if changes == was and time.monotonic() - at < OWNERS_REREAD and all(
                    p.pid is None or alive(p.pid) for p in state.processes):
                return state
        state = self._dump()
        self._dumped = (changes, time.monotonic(), state)
        return state

    def _dump(self) -> GraphState:
        try:
            conns = sockdiag.dump_tcp((1 << ESTABLISHED) | (1 << LISTEN), info=False, known=self._known)
        except KernelError as e:
            raise GraphError(str(e)) from None
        owners = self._owners_of(conns)
        host = socket.gethostname()
        listeners = {}  # port -> pid (any address)
        for c in conns:
            if c.state == LISTEN and c.inode in owners:
                listeners.setdefault(c.local_port, owners[c.inode])
        local = {c.local_address for c in conns} | {"127.0.0.1", "::1", "0.0.0.0", "::"}
        names: dict[int, str] = {}

        def node_of(pid: int) -> str:
            if pid not in names:
                names[pid] = f"/{self.scan.name(pid) or 'process'}/{pid}"
            return names[pid]

        state = GraphState(hosts=[Host(host)])
        edges, remote_nodes = set(), set()
        for c in conns:
            pid = owners.get(c.inode)
            if pid is None:
                continue
            node_of(pid)
            if c.state != ESTABLISHED:
                continue
            server = listeners.get(c.local_port)
            if server == pid:  # the accepting end: its client is on another host, or seen as it connects
                if c.remote_address not in local:
                    peer = f"/remote/{c.remote_address}"
                    remote_nodes.add(peer)
                    edges.add((peer, node_of(pid), f"tcp:{c.local_port}"))
                continue
            if c.remote_address in local and c.remote_port in listeners:
                target = node_of(listeners[c.remote_port])
            else:
                target = f"/remote/{_endpoint(c.remote_address, c.remote_port)}"
                remote_nodes.add(target)
            edges.add((node_of(pid), target, f"tcp:{c.remote_port}"))
        state.processes = [Process(host, pid, self.scan.name(pid)) for pid in sorted(names)]
        state.nodes = [Node(name, host, pid, "process") for pid, name in sorted(names.items())]
        state.nodes += [Node(name, "", None, "remote") for name in sorted(remote_nodes)]
        state.connections = [Connection(topic, u, v, "tcp") for (u, v, topic) in sorted(edges)]
        return state
